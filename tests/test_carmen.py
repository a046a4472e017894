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


def _robotlaser(ranges: list[float], pose: tuple[float, float, float], ts: float,
                start: float = -2.0, step: float = 0.5, max_range: float = 30.0,
                logger_ts: float | None = None) -> str:
    """A ROBOTLASER1 line: SICK type 0, fov = step * (n - 1), two remissions."""
    n = len(ranges)
    r = " ".join(str(v) for v in ranges)
    x, y, th = pose
    lt = ts if logger_ts is None else logger_ts
    return (f"ROBOTLASER1 0 {start} {step * (n - 1)} {step} {max_range} 0.01 0 {n} {r} "
            f"2 0.5 0.6 {x} {y} {th} {x + 0.1} {y} {th} 0.3 0.1 0.5 0.2 0.0 {ts} host {lt}\n")


@pytest.mark.parametrize(("n", "step_deg"), [(180, 1.0), (181, 1.0), (360, 0.5), (361, 0.5)])
def test_flaser_beam_spacing_from_the_count(tmp_path: Path, n: int, step_deg: float) -> None:
    text = _flaser([1.0] * n, (0, 0, 0), 1.0) + _flaser([2.0] * n, (0, 0, 0), 2.0)
    s = read_carmen(_write(tmp_path, text)).scans
    assert s.ranges.shape == (2, n)
    np.testing.assert_allclose(np.diff(np.degrees(s.angles)), step_deg, atol=1e-9)
    assert math.degrees(s.angles[0]) == pytest.approx(-90.0)
    # odd counts end at +90 deg, even counts one step short of it
    last = 90.0 if n % 2 else 90.0 - step_deg
    assert math.degrees(s.angles[-1]) == pytest.approx(last)


def test_robotlaser_reads_its_own_geometry(tmp_path: Path) -> None:
    text = ("PARAM robot_frontlaser_offset 0.0 nohost 0\n"
            + _flaser([9.0] * 4, (5, 5, 0), 0.5)  # ignored: the log has ROBOTLASER1
            + _robotlaser([1.0, 2.0, 3.0, 40.0, 5.0, 6.0, 7.0, 8.0, 9.0], (1, 2, 0.5), 1.0)
            + _robotlaser([1.5] * 9, (1.2, 2, 0.6), 1.2))
    log = read_carmen(_write(tmp_path, text))
    s = log.scans
    assert log.message == "ROBOTLASER1" and len(s) == 2 and s.ranges.shape == (2, 9)
    np.testing.assert_allclose(s.angles, -2.0 + 0.5 * np.arange(9))
    assert s.max_range == pytest.approx(30.0)  # the message's own maximum range
    np.testing.assert_allclose(s.poses, [[1, 2, 0.5], [1.2, 2, 0.6]])
    np.testing.assert_allclose(s.odom_poses[0], [1.1, 2, 0.5])  # the robot pose
    np.testing.assert_allclose(s.t, [1.0, 1.2])
    np.testing.assert_array_equal(s.line, [3, 4])
    # the 40 m beam is beyond max_range: no endpoint; beam 2 (3 m at -1 rad) is
    pts = scan_endpoints(s, 0)
    assert pts.shape == (8, 2)
    np.testing.assert_allclose(pts[2], [1 + 3 * math.cos(0.5 - 1.0), 2 + 3 * math.sin(0.5 - 1.0)])


@pytest.mark.parametrize(
    ("line", "match"),
    [
        ("ROBOTLASER1 0 -1.5 3.1 0.01 80 0.01 0 4 1 2 3\n", "without a remission count"),
        ("ROBOTLASER1 0 -1.5 3.1 0.01 80 0.01 0 4 1 2 3 4 0 1 2\n", "needs 26 fields"),
        ("ROBOTLASER1 0 -1.5 3.1 0.01 80 0.01 0 x\n", "without a beam count"),
        (_robotlaser([1.0] * 4, (0, 0, 0), 1.0).replace(" 0.3 0.1 ", " zz 0.1 "), "not a number"),
        (_robotlaser([1.0] * 4, (0, 0, 0), 1.0, step=0.25), "start angle/resolution"),
        (_robotlaser([1.0] * 4, (0, 0, 0), 1.0, step=0.0), "resolution 0.0 is not positive"),
    ],
)
def test_malformed_robotlaser_names_file_and_line(tmp_path: Path, line: str, match: str) -> None:
    path = _write(tmp_path, _robotlaser([1.0] * 4, (0, 0, 0), 0.5) + line)
    with pytest.raises(DatasetError, match=match) as info:
        read_carmen(path)
    assert f"{path}:2" in str(info.value)


def _warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.levelname == "WARNING" and r.name == "lampsam.datasets.carmen"]


def _stamped(stamps: list[str]) -> str:
    """FLASER lines with the given stamp strings, ranges 1, 2, 3, ... in file order."""
    return "".join(_flaser([1.0 + k] * N, (0.1 * k, 0, 0), 0.0)
                   .replace(" 0.0 host 0.0", f" {ts} host {ts}") for k, ts in enumerate(stamps))


def test_coarse_stamps_spread_between_distinct_values(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Stamps printed with 3 decimals of a second: runs of equal stamps between changes."""
    stamps = ["100.1"] * 2 + ["100.2"] * 4 + ["100.3"] * 2 + ["100.4"] * 3
    s = read_carmen(_write(tmp_path, _stamped(stamps))).scans
    assert len(s) == 11 and s.time_source == "spread"
    # interior runs spread over their 0.1 s (steps 0.025 and 0.05: median 0.0375);
    # the first run ends one such step before 100.2, the last continues at it
    expected = [100.125, 100.1625, 100.2, 100.225, 100.25, 100.275, 100.3, 100.35,
                100.4, 100.4375, 100.475]
    np.testing.assert_allclose(s.t, expected, atol=1e-9)
    np.testing.assert_allclose(s.ranges[:, 0], 1.0 + np.arange(11))  # file order kept
    msgs = _warnings(caplog)
    assert len(msgs) == 1 and "7 of 11 scans repeat" in msgs[0] and "spread" in msgs[0]


def test_six_digit_stamps_fall_back_to_the_nominal_rate(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """1.13486e+09 on every scan, then 1.13487e+09 (10,000 s later): nothing to interpolate."""
    stamps = ["1.13486e+09"] * 4 + ["1.13487e+09"] * 2
    s = read_carmen(_write(tmp_path, _stamped(stamps)), scan_rate_hz=10.0).scans
    assert len(s) == 6 and s.time_source == "rate"
    np.testing.assert_allclose(s.t - 1.13487e9, [-0.4, -0.3, -0.2, -0.1, 0.0, 0.1], atol=1e-6)
    msgs = _warnings(caplog)
    assert len(msgs) == 1 and "4 of 6 scans repeat" in msgs[0] and "nominal 10 Hz" in msgs[0]


@pytest.mark.parametrize(("logger", "source", "expected"),
                         [(True, "logger", [3.0, 3.1, 3.3]), (False, "rate", [0.0, 0.2, 0.4])])
def test_zero_stamps_use_logger_stamps_or_nominal_rate(
        tmp_path: Path, caplog: pytest.LogCaptureFixture, logger: bool, source: str,
        expected: list[float]) -> None:
    lines = [_flaser([1.0] * N, (0, 0, 0), 0.0) for _ in range(3)]
    if logger:
        lines = [ln.replace(" host 0.0", f" host {v}") for ln, v in zip(lines, expected, strict=True)]
    s = read_carmen(_write(tmp_path, "".join(lines)), scan_rate_hz=5.0).scans
    assert len(s) == 3 and s.time_source == source
    np.testing.assert_allclose(s.t, expected)
    msgs = _warnings(caplog)
    assert len(msgs) == 1 and "2 of 3 scans repeat" in msgs[0]
    assert ("logger" in msgs[0]) if logger else ("nominal 5 Hz" in msgs[0])


def test_increasing_stamps_give_no_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    text = _flaser([1.0] * N, (0, 0, 0), 1.0) + _flaser([1.0] * N, (0, 0, 0), 1.1)
    assert read_carmen(_write(tmp_path, text)).scans.time_source == "log"
    assert _warnings(caplog) == []
