"""The command chain of a simulated global localization: kinect-sim -> build-map -> localize."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from lampsam.cli import main
from lampsam.localization.map_tables import range_table_file

START = (3.0, 5.5, 0.5)  # free floor of the office, 0.6 m from the nearest obstacle


def _strict(path: Path) -> dict[str, object]:
    """Parse JSON that must not contain NaN or Infinity."""

    def bad(name: str) -> None:
        raise ValueError(f"{path}: {name} in JSON")

    return json.loads(path.read_text(), parse_constant=bad)  # type: ignore[no-any-return]


@pytest.fixture(scope="module")
def office_search(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A one-round search run from START (small Kinect images) and a map made from it."""
    root = tmp_path_factory.mktemp("search")
    run, map_dir = root / "run", root / "map"
    args = ["kinect-sim", "office", "--localize-from", ",".join(map(str, START)), "--rounds", "1",
            "--width", "160", "--height", "120", "--rate", "1.5", "--seed", "3", "--out", str(run)]
    assert main(args) == 0
    assert main(["build-map", str(run), "--out", str(map_dir)]) == 0
    return run, map_dir


def test_search_run_turns_in_place_then_drives(office_search: tuple[Path, Path]) -> None:
    run, _ = office_search
    meta = __import__("yaml").safe_load((run / "meta.yaml").read_text())
    assert meta["localization_start"] == list(START)
    kinds = [p[0] for p in meta["phases"]]
    assert kinds[0] == "turn" and kinds[-1] == "drive"
    turn = meta["phases"][0]
    assert turn[2] - turn[1] == pytest.approx((2 * math.pi + math.radians(10)) / math.radians(30), abs=0.1)
    gt = np.loadtxt(run / "groundtruth.tum")
    assert np.allclose(gt[0, 1:3], START[:2])  # the truth starts at the start pose
    assert len(list((run / "kinect" / "rgb").glob("*.png"))) == pytest.approx(12.3 * 1.5, abs=2)


@pytest.mark.parametrize("mode", ["grid_only", "proposed"])
def test_localize_finds_the_start_area_and_writes_strict_json(
    office_search: tuple[Path, Path], tmp_path: Path, mode: str
) -> None:
    run, map_dir = office_search
    rc = main(["localize", str(run), "--map", str(map_dir), "--out", str(tmp_path), "--mode", mode])
    doc = _strict(tmp_path / "result.json")
    assert rc == 0 and doc["status"] == "localized"
    summary = doc["summary"]
    assert isinstance(summary, dict)
    assert summary["trials"] == 1 and summary["correct"] == 1 and summary["wrong_accepted"] == 0
    assert summary["success_rate"] == 1.0
    for key in ("localized", "ambiguous", "failed", "compute_s_mean", "robot_s_mean"):
        assert key in summary
    trial = doc["trial"]
    assert isinstance(trial, dict) and float(trial["error_m"]) <= 0.30
    assert (map_dir / range_table_file(4.5)).is_file()  # stored with the map for the next run (map_tables)


def test_replay_runs_the_frontend_lazily_with_the_same_frames(office_search: tuple[Path, Path]) -> None:
    from lampsam.datasets.logrun import read_run
    from lampsam.frontend.pipeline import process_run
    from lampsam.localization.replay import ReplayRobot

    run, _ = office_search
    full = process_run(read_run(run))
    robot = ReplayRobot(run)
    robot.turn(2 * math.pi, math.radians(30))
    first = robot.drive(0.5)
    assert 0 < len(first) < len(full)
    assert len(robot._ceiling) == len(first)  # nothing processed beyond the frames asked for
    rest = robot.drive(100.0)  # the rest of the run
    got = first + rest
    assert len(got) == len(full)
    for a, b in zip(got, full, strict=True):
        assert a.t == b.t
        np.testing.assert_array_equal(a.ceiling_m, np.array([o.m for o in b.lamps] + [o.m for o in b.corners],
                                                    dtype=float).reshape(-1, 2))
