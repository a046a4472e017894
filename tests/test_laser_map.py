"""build-map on CARMEN logs (scan selection, too few scans) and the stored lookup tables."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lampsam.cli import main
from lampsam.datasets.carmen import flaser_beam_angles
from lampsam.localization.grid import occupied_mask
from lampsam.localization.map_build import build_map, detect_source
from lampsam.localization.map_config import EnvMapConfig, LaserGridConfig
from lampsam.localization.map_store import EnvMapError, load_env_map
from lampsam.localization.map_tables import (
    TableConfig,
    build_range_table,
    grid_fingerprint,
    load_distance_field,
    load_range_table,
    range_table_for_map,
)
from lampsam.localization.raycast import distance_field

ROOM = (6.0, 4.0)  # walls at x = 0, 6 and y = 0, 4, metres


def _room_ranges(pose: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Exact ranges from ``pose`` to the walls of the empty ROOM, metres."""
    x, y, th = pose
    phi = th + angles
    c, s = np.cos(phi), np.sin(phi)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (ROOM[0] - x) / c, np.where(c < 0, -x / c, np.inf))
        ty = np.where(s > 0, (ROOM[1] - y) / s, np.where(s < 0, -y / s, np.inf))
    return np.minimum(tx, ty)


def _room_log(path: Path, n_scans: int, beams: int = 361) -> Path:
    """A FLASER log of a robot turning and driving inside ROOM, 0.5 s apart."""
    angles = flaser_beam_angles(beams)
    lines = []
    for k in range(n_scans):
        u = k / max(n_scans - 1, 1)
        pose = np.array([1.0 + 4.0 * u, 2.0 + 0.5 * math.sin(6 * u), 2 * math.pi * 3 * u])
        r = " ".join(f"{v:.4f}" for v in _room_ranges(pose, angles))
        p = " ".join(f"{v:.5f}" for v in pose)
        lines.append(f"FLASER {beams} {r} {p} {p} {0.5 * k:.3f} host {0.5 * k:.3f}\n")
    path.write_text("".join(lines))
    return path


def test_build_map_from_even_scans_of_a_log(tmp_path: Path) -> None:
    log = _room_log(tmp_path / "room.log", 60)
    report = build_map(log, tmp_path / "map", scans="even")
    env = load_env_map(tmp_path / "map")
    grid_layer = env.manifest["layers"]["grid"]
    assert report.source == "laser" and grid_layer["scans_selected"] == 30
    assert grid_layer["scans_total"] == 60 and grid_layer["beams"] == 361
    assert grid_layer["beam_angles_deg"] == [-90.0, 90.0]
    occ = occupied_mask(env.grid)
    centres = env.grid.cell_centres()[occ]
    wall_dist = np.minimum.reduce([np.abs(centres[:, 0]), np.abs(centres[:, 0] - ROOM[0]),
                                   np.abs(centres[:, 1]), np.abs(centres[:, 1] - ROOM[1])])
    assert occ.sum() > 150 and np.all(wall_dist < 0.11)  # walls within a cell
    # laser maps store the distance field, not the range table (TableConfig default)
    assert "distance_field" in env.manifest["layers"] and "range_table" not in env.manifest["layers"]
    stored = load_distance_field(tmp_path / "map", env.grid)
    assert stored is not None
    np.testing.assert_array_equal(stored, distance_field(occupied_mask(env.grid)))


def test_too_few_scans_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = _room_log(tmp_path / "short.log", 8)
    with pytest.raises(EnvMapError, match=r"a map from 4 scans .* at least 10 are needed"):
        build_map(log, tmp_path / "m1", scans="odd")
    code = main(["build-map", str(log), "--out", str(tmp_path / "m2"), "--scans", "odd"])
    assert code == 2 and not (tmp_path / "m2" / "manifest.yaml").exists()
    assert "at least 10 are needed" in capsys.readouterr().err
    with pytest.raises(EnvMapError, match="scans must be one of all, even, odd, got 'bad'"):
        build_map(log, tmp_path / "m3", scans="bad")
    rgbd = tmp_path / "rgbd"
    rgbd.mkdir()
    (rgbd / "rgb.txt").write_text("")
    (rgbd / "depth.txt").write_text("")
    with pytest.raises(EnvMapError, match="laser logs only"):
        build_map(rgbd, tmp_path / "m4", scans="even")


def test_a_renamed_log_is_known_by_its_content(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """``build-map`` took a file for a CARMEN log only when its name held ``.log``: a
    ``.clf`` (or gzip'd and renamed) log was refused. Now the records decide: the same
    grid from ``room.log``, ``room.clf`` and a gzip'd ``room.dat`` (comments and a
    ``PARAM`` line first)."""
    import gzip

    log = _room_log(tmp_path / "room.log", 24)
    text = "# message formats defined: PARAM ODOM FLASER\nPARAM robot_frontlaser_offset 0.0\n"
    clf = tmp_path / "room.clf"
    clf.write_text(text + log.read_text())
    dat = tmp_path / "room.dat"
    dat.write_bytes(gzip.compress(clf.read_bytes()))
    assert detect_source(clf) == ("laser", clf) and detect_source(dat) == ("laser", dat)
    assert main(["build-map", str(log), "--out", str(tmp_path / "m0")]) == 0
    assert main(["build-map", str(dat), "--out", str(tmp_path / "m1")]) == 0
    assert "(laser, 24 frames" in capsys.readouterr().out
    np.testing.assert_array_equal(load_env_map(tmp_path / "m1").grid.log_odds,
                                  load_env_map(tmp_path / "m0").grid.log_odds)


@pytest.mark.parametrize(
    ("name", "content", "found"),
    [
        ("graph.log", b"VERTEX_SE2 0 0.0 0.0 0.0\nEDGE_SE2 0 1 1.0 0 0 1 0 0 1 0 1\n",
         "its first record is 'VERTEX_SE2 0 0.0 0.0 0.0'"),
        ("poses.txt", b"# tum\n0.0 1 2 0 0 0 0 1\n", "its first record is '0.0 1 2 0 0 0 0 1'"),
        ("empty.log", b"# nothing\n\n", "no records (empty, or comments only)"),
    ],
)
def test_a_file_that_is_no_log_says_what_it_holds(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, content: bytes, found: str
) -> None:
    """A file that is no CARMEN log (even named ``.log``) is refused naming the file and
    what its first record is, exit 2 and no map written."""
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(EnvMapError) as info:
        detect_source(path)
    assert str(info.value) == (f"{path}: not a run directory or a CARMEN log: {found} (a CARMEN "
                               "log's lines start with PARAM, ODOM, FLASER, ROBOTLASER1, ...)")
    assert main(["build-map", str(path), "--out", str(tmp_path / "m")]) == 2
    err = capsys.readouterr().err
    assert found in err and "Traceback" not in err
    assert not (tmp_path / "m" / "manifest.yaml").exists()


def test_stored_range_table_is_loaded_only_for_its_grid(tmp_path: Path) -> None:
    log = _room_log(tmp_path / "room.log", 40, beams=180)
    cfg = EnvMapConfig(laser=LaserGridConfig(resolution=0.2),
                       tables=TableConfig(laser_range_table=True, range_max_range=3.0))
    assert main(["build-map", str(log), "--out", str(tmp_path / "nt"), "--no-tables"]) == 0
    assert not list((tmp_path / "nt").glob("range_table*"))
    build_map(log, tmp_path / "map", config=cfg)
    env = load_env_map(tmp_path / "map")
    assert env.path == tmp_path / "map"
    assert env.manifest["layers"]["range_table"]["grid_sha256"] == grid_fingerprint(env.grid)
    table = load_range_table(tmp_path / "map", env.grid, 3.0)
    assert table is not None
    fresh = build_range_table(env.grid, 3.0)
    np.testing.assert_array_equal(table.ranges_mm, fresh.ranges_mm)
    np.testing.assert_array_equal(table.row_of_cell, fresh.row_of_cell)
    rng = np.random.default_rng(3)
    poses = np.column_stack([rng.uniform(1, 5, 50), rng.uniform(1, 3, 50), rng.uniform(-3, 3, 50)])
    beams = flaser_beam_angles(180)
    np.testing.assert_array_equal(table.lookup(poses, beams), fresh.lookup(poses, beams))
    # another max_range or bin count, or a changed grid: not loaded
    assert load_range_table(tmp_path / "map", env.grid, 4.5) is None
    assert load_range_table(tmp_path / "map", env.grid, 3.0, n_angles=180) is None
    edited = env.grid.copy()
    edited.log_odds[10, 10] = 10.0  # one more occupied cell
    assert load_range_table(tmp_path / "map", edited, 3.0) is None
    assert load_distance_field(tmp_path / "map", edited) is None
    # range_table_for_map rebuilds for the edited grid and stores the new table
    rebuilt = range_table_for_map(tmp_path / "map", edited, 3.0)
    assert rebuilt.ranges_mm.shape[0] == fresh.ranges_mm.shape[0] - 1
    assert load_range_table(tmp_path / "map", edited, 3.0) is not None
    assert load_range_table(tmp_path / "map", env.grid, 3.0) is None
