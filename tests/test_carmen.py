"""CARMEN log reader and the Intel lab grid map built from its scans."""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from lampsam.datasets.carmen import LaserScans, carmen_beam_angles, read_carmen, scan_endpoints
from lampsam.errors import DatasetError
from lampsam.localization.grid import grid_from_scans, occupied_mask
from tests.conftest import require_shared

N = 4  # beams in the hand-made logs


def _flaser(ranges: list[float], pose: tuple[float, float, float], ts: float) -> str:
    r = " ".join(str(v) for v in ranges)
    x, y, th = pose
    return f"FLASER {len(ranges)} {r} {x} {y} {th} {x} {y} {th} {ts} host {ts}\n"


def _write(tmp_path: Path, text: str, gz: bool = False) -> Path:
    path = tmp_path / ("log.gz" if gz else "log.txt")
    if gz:
        with gzip.open(path, "wt") as fh:
            fh.write(text)
    else:
        path.write_text(text)
    return path


def test_read_hand_made_log(tmp_path: Path) -> None:
    text = ("# comment\nPARAM robot_frontlaser_offset 0.0 nohost 0\n"
            "ODOM 1 2 0.5 0 0 0 0.1 host 0.1\n"
            + _flaser([1.0, 2.0, 3.0, 90.0], (1.0, 2.0, 0.5), 1.0)
            + _flaser([1.5, 2.5, 3.5, 4.5], (1.1, 2.0, 0.6), 2.0))
    log = read_carmen(_write(tmp_path, text, gz=True))
    s = log.scans
    assert len(s) == 2 and s.ranges.shape == (2, N)
    np.testing.assert_allclose(s.t, [1.0, 2.0])
    np.testing.assert_allclose(s.poses[1], [1.1, 2.0, 0.6])
    np.testing.assert_array_equal(s.line, [4, 5])
    np.testing.assert_allclose(s.angles, [-math.pi / 2, -math.pi / 4, 0.0, math.pi / 4])
    np.testing.assert_allclose(log.odom_poses, [[1.0, 2.0, 0.5]])
    # Endpoint of scan 0, beam 2 (straight ahead at heading 0.5), 90 m beam dropped.
    pts = scan_endpoints(s, 0)
    assert pts.shape == (3, 2)
    np.testing.assert_allclose(pts[2], [1.0 + 3 * math.cos(0.5), 2.0 + 3 * math.sin(0.5)])


@pytest.mark.parametrize(
    ("line", "match"),
    [
        (_flaser([1.0, 2.0, 3.0, 4.0], (0, 0, 0), 1.0).replace(" 3.0 ", " abc "), "not a number"),
        (_flaser([1.0, 2.0, 3.0, 4.0], (0, 0, 0), 1.0).replace(" 3.0 ", " nan "), "non-finite"),
        ("FLASER 4 1.0 2.0\n", "needs 13 fields"),
        ("FLASER x\n", "beam count"),
        ("ODOM 1 2\n", "ODOM needs"),
        (_flaser([1.0, 2.0, 3.0], (0, 0, 0), 1.0), "beam count 3 differs"),
    ],
)
def test_malformed_line_names_file_and_line(tmp_path: Path, line: str, match: str) -> None:
    text = _flaser([1.0, 2.0, 3.0, 4.0], (0, 0, 0), 0.5) + line
    path = _write(tmp_path, text)
    with pytest.raises(DatasetError, match=match) as info:
        read_carmen(path)
    assert f"{path}:2" in str(info.value)


def test_time_backwards_skipped_or_strict(tmp_path: Path) -> None:
    text = (_flaser([1.0] * N, (0, 0, 0), 2.0) + _flaser([2.0] * N, (0, 0, 0), 1.5)
            + _flaser([3.0] * N, (0, 0, 0), 3.0))
    path = _write(tmp_path, text)
    s = read_carmen(path).scans
    np.testing.assert_allclose(s.t, [2.0, 3.0])
    with pytest.raises(DatasetError, match=r"log.txt:2: time goes backwards"):
        read_carmen(path, strict_time=True)


def test_missing_or_empty_log(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="not found"):
        read_carmen(tmp_path / "nope.log")
    with pytest.raises(DatasetError, match="no FLASER"):
        read_carmen(_write(tmp_path, "ODOM 0 0 0 0 0 0 1 h 1\n"))


@pytest.fixture(scope="module")
def intel() -> LaserScans:
    path = require_shared("carmen") / "intel-corrected.log.gz"
    return read_carmen(path).scans


def _endpoint_hit_fraction(scans: LaserScans, angles: np.ndarray, map_idx: np.ndarray,
                           test_idx: np.ndarray) -> float:
    r = np.where(scans.ranges >= scans.max_range, np.nan, scans.ranges)
    grid = grid_from_scans(scans.poses[map_idx], r[map_idx], angles, 0.1, 30.0)
    occ = ndimage.binary_dilation(occupied_mask(grid))  # one cell of slack (0.1 m)
    phi = scans.poses[test_idx, 2:3] + angles
    rt = r[test_idx]
    ok = ~np.isnan(rt)
    pts = np.stack([(scans.poses[test_idx, 0:1] + rt * np.cos(phi))[ok],
                    (scans.poses[test_idx, 1:2] + rt * np.sin(phi))[ok]], axis=1)
    cells = grid.world_to_cell(pts)
    inside = grid.in_bounds(cells)
    return float(occ[cells[inside, 1], cells[inside, 0]].mean())


@pytest.mark.shared_data
def test_intel_log_contents(intel: LaserScans) -> None:
    assert len(intel) == 906  # 910 FLASER lines, 4 with time going backwards dropped
    assert intel.ranges.shape == (906, 180)
    assert np.all(np.diff(intel.t) > 0)
    np.testing.assert_allclose(intel.angles[[0, 90, 179]], np.radians([-90.0, 0.0, 89.0]))


@pytest.mark.shared_data
def test_intel_grid_reproduces_walls_on_held_out_scans(intel: LaserScans) -> None:
    # Map from every 4th scan, check the endpoints of other scans (not in the map).
    idx = np.arange(len(intel))
    map_idx, test_idx = idx[::4], idx[2::16]
    frac = _endpoint_hit_fraction(intel, intel.angles, map_idx, test_idx)
    assert frac > 0.85, frac
    # The beam-order convention matters: reversed beams do not reproduce the walls.
    frac_rev = _endpoint_hit_fraction(intel, intel.angles[::-1].copy(), map_idx, test_idx)
    assert frac_rev < 0.3, frac_rev


def test_beam_angles() -> None:
    a = carmen_beam_angles(360, 2 * math.pi)
    assert a[0] == pytest.approx(-math.pi) and a[-1] == pytest.approx(math.pi - math.radians(1))
