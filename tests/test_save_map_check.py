"""``lampsam slam --save-map --no-map-check``: the map without the pass-split test.

On 4 s of the simulated lab (batch, true frames) the map saved with and without the
test has the same landmarks, covariances and patches bit for bit; ``map.yaml`` differs
only in the ``calibration`` figures (absent) and ``source.map_check`` (present), and the
format-version-3 reader reads both. Bad combinations are clear errors.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import pytest
import yaml

from lampsam.backend.ceiling_map_io import MAP_VERSION, read_map
from lampsam.backend.localize_run import MAP_CHECK_NOT_RUN, save_map
from lampsam.cli import main
from tests.conftest import SimRun


@pytest.fixture(scope="module")
def lab4(sim_run: SimRun) -> Path:
    """4 s of the simulated lab (61 images)."""
    return sim_run(seed=5, duration=4.0)


def test_no_map_check_same_map_without_figures(lab4: Path, tmp_path: Path) -> None:
    """Same landmarks.csv and patches.npz; map.yaml: no 'calibration', 'map_check' said."""
    maps = {}
    for name, extra in (("with", []), ("without", ["--no-map-check"])):
        mp = tmp_path / name
        assert main(["slam", str(lab4), "--backend", "batch", "--frames", "truth", "--out",
                     str(tmp_path / f"slam_{name}"), "--save-map", str(mp), *extra]) == 0
        maps[name] = mp
    a, b = maps["with"], maps["without"]
    for f in ("landmarks.csv", "patches.npz"):
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    da = yaml.safe_load((a / "map.yaml").read_text())
    db = yaml.safe_load((b / "map.yaml").read_text())
    assert "calibration" in da and "calibration" not in db
    assert "map_check" not in da["source"] and db["source"]["map_check"] == MAP_CHECK_NOT_RUN
    assert db["format_version"] == MAP_VERSION == 3
    da.pop("calibration")
    db["source"].pop("map_check")
    assert da == db  # everything else: same rig, source, counts, frame uncertainty
    ma, mb = read_map(a), read_map(b)
    assert ma.calibration is not None and mb.calibration is None
    assert mb.source["map_check"] == MAP_CHECK_NOT_RUN
    assert [lm.id for lm in ma.landmarks] == [lm.id for lm in mb.landmarks]


def test_no_map_check_needs_save_map(lab4: Path, tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    """--no-map-check alone is exit 2 naming both flags."""
    assert main(["slam", str(lab4), "--no-map-check", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "--no-map-check" in err and "--save-map" in err and "Traceback" not in err


def test_calibrate_needs_the_check(tmp_path: Path) -> None:
    """Inflating the covariances uses the test: calibrate without check is refused."""
    dummy = cast(Any, SimpleNamespace())
    with pytest.raises(ValueError, match="calibrate=True needs check=True"):
        save_map(tmp_path / "m", dummy, dummy, calibrate=True, check=False)
