"""Bad input to the stereo run reader (``read_stereo_run``, ``lampsam stereo RUN``).

Each corruption of a simulated run's files must give one DatasetError naming the file
(and the line or key where there is one), never a UnicodeDecodeError, a TypeError from
inside PyYAML's result or a multi-line YAML message. Before this file: a binary CSV
raised UnicodeDecodeError, an empty ``stereo_run.yaml`` gave "'NoneType' object is not
subscriptable", an unknown rig key gave Python's "unexpected keyword argument".
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from lampsam.cli import main
from lampsam.datasets.stereo_sim import read_stereo_run, simulate_stereo, write_stereo_run
from lampsam.errors import DatasetError


@pytest.fixture()
def stereo_run(tmp_path: Path) -> Path:
    """A simulated ``turn`` run (161 frames), seed 3."""
    run = simulate_stereo("turn", np.random.default_rng(3), seed=3)
    return write_stereo_run(run, tmp_path / "run")


def _binary(p: Path) -> None:
    p.write_bytes(np.random.default_rng(7).bytes(2000))


def _empty(p: Path) -> None:
    p.write_bytes(b"")


def _replace_line(k: int, text: str) -> Callable[[Path], None]:
    def edit(p: Path) -> None:
        lines = p.read_text().splitlines()
        lines[k] = text
        p.write_text("\n".join(lines) + "\n")
    return edit


def _directory(p: Path) -> None:
    p.unlink()
    p.mkdir()


def _yaml_sub(pattern: str, repl: str) -> Callable[[Path], None]:
    def edit(p: Path) -> None:
        p.write_text(re.sub(pattern, repl, p.read_text(), count=1))
    return edit


# (file, corruption, the message must match); the path of the file is always checked
CASES: list[tuple[str, Callable[[Path], None], str]] = [
    ("odometry.csv", _binary, r"odometry.csv:1: not UTF-8 text"),
    ("measurements.csv", _binary, r"measurements.csv:1: not UTF-8 text"),
    ("odometry.csv", _empty, r"odometry.csv: empty file"),
    ("odometry.csv", _directory, r"odometry.csv: is a directory"),
    ("odometry.csv", _replace_line(3, "0.3,nan,0.1"), r"odometry.csv:4: column 'v': non-finite"),
    ("odometry.csv", _replace_line(3, "0.1,0.2,0.1"), r"odometry.csv:4: time does not increase"),
    ("measurements.csv", _replace_line(5, "0.5,1,2,3"), r"measurements.csv:6: malformed line"),
    ("groundtruth.tum", _directory, r"groundtruth.tum: is a directory"),
    ("stereo_run.yaml", _empty, r"stereo_run.yaml: bad run description: expected a mapping"),
    ("stereo_run.yaml", _binary, r"stereo_run.yaml:\d+: not UTF-8 text"),
    ("stereo_run.yaml", _yaml_sub(r"rig:\n", "rig: [\n"), r"stereo_run.yaml:\d+: invalid YAML"),
    ("stereo_run.yaml", _yaml_sub(r"baseline:", "baselin:"),
     r"stereo_run.yaml: bad run description: rig.baselin: unknown key"),
    ("stereo_run.yaml", _yaml_sub(r"sigma_v: [^\n]+", "sigma_v: fast"),
     r"stereo_run.yaml: bad run description: noise.sigma_v: must be a number"),
    ("stereo_run.yaml", _yaml_sub(r"noise:", "noize:"),
     r"stereo_run.yaml: bad run description: noise is missing"),
    ("stereo_run.yaml", _yaml_sub(r"seed: \d+", "seed: three"),
     r"stereo_run.yaml: bad run description: seed: must be an integer"),
]


@pytest.mark.parametrize(("name", "corrupt", "match"), CASES,
                         ids=[f"{n}-{c.__qualname__.split('.')[0]}-{i}"
                              for i, (n, c, _) in enumerate(CASES)])
def test_corrupt_stereo_run_names_the_file(stereo_run: Path, name: str,
                                           corrupt: Callable[[Path], None], match: str) -> None:
    corrupt(stereo_run / name)
    with pytest.raises(DatasetError, match=match) as info:
        read_stereo_run(stereo_run)
    assert "\n" not in str(info.value)
    assert info.value.path is not None and info.value.path.name == name


def test_frame_count_mismatch_says_both_counts(stereo_run: Path) -> None:
    odo = stereo_run / "odometry.csv"
    lines = odo.read_text().splitlines()
    odo.write_text("\n".join(lines[:-10]) + "\n")
    with pytest.raises(DatasetError, match=r"odometry.csv: 151 rows, measurements.csv: 161"):
        read_stereo_run(stereo_run)


def test_cli_binary_measurements_is_a_clear_error(stereo_run: Path, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    _binary(stereo_run / "measurements.csv")
    out = tmp_path / "o"
    assert main(["stereo", str(stereo_run), "--estimator", "ekf", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "internal error" not in err and "Traceback" not in err
    assert "measurements.csv:1: not UTF-8 text" in err
    assert not out.exists()
