"""Hostile bytes in every text reader: each reads the file as it was meant, or raises one
DatasetError naming the file (and line); never a UnicodeDecodeError or a silent loss.

The variants are the ones of docs/failures.md ("Every reader, hostile bytes"): a UTF-8
byte-order mark, Windows line ends and tabs read exactly like the clean file; bytes that
are not UTF-8 (a binary file, a Latin-1 comment), a gzip-compressed file and a directory
are each refused with their own message.
"""

from __future__ import annotations

import gzip
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lampsam.datasets import calibration, carmen, graph_text, kitti, mrclam, odometry, tables, tum
from lampsam.datasets.camera import CameraModel
from lampsam.errors import DatasetError


def _carmen_text() -> str:
    """Five FLASER lines of 180 beams, 0.5 s apart (the Intel log's layout)."""
    lines = []
    for k in range(5):
        ranges = " ".join(f"{2.0 + 0.01 * ((b + k) % 7):.3f}" for b in range(180))
        t = 10.0 + 0.5 * k
        lines.append(f"FLASER 180 {ranges} {0.1 * k} 0.0 0.0 {0.1 * k} 0.0 0.0 {t} host {t}")
    return "\n".join(lines) + "\n"


def _camera_info_text(tmp: Path) -> str:
    cam = CameraModel(width=320, height=240, fx=92.4, fy=92.4, cx=159.5, cy=119.5)
    p = tmp / "cam_base.yaml"
    calibration.write_camera_info(p, calibration.intrinsics_of(cam))
    return p.read_text(encoding="utf-8")


# name: (reader, clean text or a builder of it, whitespace-separated)
READERS: dict[str, tuple[Callable[[Path], Any], Callable[[Path], str], bool]] = {
    "graph_text": (graph_text.read_graph_text, lambda _: (
        "ODOMETRY 0 1 1.0 0.0 0.1 0.0001 0 0 4e-06 0 4e-06\nBR 1 7 0.1 2.5 0.05 0.2\n"
        "ODOMETRY 1 2 1.0 0.0 0.1 0.0001 0 0 4e-06 0 4e-06\n"), True),
    "tum": (tum.read_tum, lambda _: "# t x y z qx qy qz qw\n" + "".join(
        f"{0.1 * k:.1f} {k}.5 0 0 0 0 0 1\n" for k in range(5)), True),
    "odometry.csv": (tables.read_odometry, lambda _: "t,d_left,d_right\n" + "".join(
        f"{0.1 * k:.1f},0.01,0.02\n" for k in range(5)), False),
    "odometry_pose2.csv": (odometry.read_pose2_odometry, lambda _: (
        "t,dx,dy,dtheta,var_x,cov_xy,cov_xtheta,var_y,cov_ytheta,var_theta\n" + "".join(
            f"{0.1 * k:.1f},0.1,0.0,0.01,1e-4,0,0,1e-4,0,1e-5\n" for k in range(5))), False),
    "carmen": (carmen.read_carmen, lambda _: _carmen_text(), True),
    "kitti matrices": (kitti._read_matrices, lambda _: "".join(
        " ".join(str(float(v)) for v in np.eye(3, 4).ravel() + k) + "\n" for k in range(3)), True),
    "mrclam table": (lambda p: mrclam._read_table(p, 4), lambda _: "".join(
        f"{11.1 + 0.02 * k:.3f} 27.000 1.192 0.485\n" for k in range(5)), True),
    "camera_info": (calibration.read_calibration, _camera_info_text, True),
}


def _numbers(result: Any) -> list[np.ndarray]:
    """The arrays a reader returned, for comparing two reads."""
    if isinstance(result, np.ndarray):
        return [result]
    if isinstance(result, carmen.CarmenLog):
        return [result.scans.t, result.scans.ranges, result.scans.poses]
    if isinstance(result, graph_text.GraphLog):
        return [np.asarray(result.pose_ids, float), result.odometry.delta, result.odometry.cov,
                np.array([[s.bearing, s.range] for ss in result.sightings for s in ss])]
    if isinstance(result, calibration.Intrinsics):
        return [np.array([result.fx, result.fy, result.cx, result.cy]), np.asarray(result.dist, float)]
    return [np.asarray(v, float) for k, v in vars(result).items()
            if isinstance(v, np.ndarray) and v.dtype.kind in "fi"]


SAME = {
    "UTF-8 BOM": lambda s: "\ufeff" + s,
    "CRLF": lambda s: s.replace("\n", "\r\n"),
    "CR only (old Mac)": lambda s: s.replace("\n", "\r"),
}


@pytest.mark.parametrize("variant", list(SAME))
@pytest.mark.parametrize("name", list(READERS))
def test_bom_and_line_ends_read_like_the_clean_file(name: str, variant: str, tmp_path: Path) -> None:
    reader, text_of, _ = READERS[name]
    text = text_of(tmp_path)
    clean, hostile = tmp_path / "clean.txt", tmp_path / "hostile.txt"
    clean.write_text(text, encoding="utf-8", newline="")
    hostile.write_text(SAME[variant](text), encoding="utf-8", newline="")
    a, b = _numbers(reader(clean)), _numbers(reader(hostile))
    assert len(a) == len(b) and len(a) > 0
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("name", [n for n, (_, _, ws) in READERS.items() if ws and n != "camera_info"])
def test_tabs_read_like_spaces(name: str, tmp_path: Path) -> None:
    reader, text_of, _ = READERS[name]
    text = text_of(tmp_path)
    clean, tabs = tmp_path / "clean.txt", tmp_path / "tabs.txt"
    clean.write_text(text, encoding="utf-8")
    tabs.write_text(text.replace(" ", "\t"), encoding="utf-8")
    for x, y in zip(_numbers(reader(clean)), _numbers(reader(tabs)), strict=True):
        np.testing.assert_array_equal(x, y)


REFUSED = {
    "binary": (lambda s: bytes(np.random.default_rng(0).integers(128, 256, 64, dtype=np.uint8)),
               r"hostile.txt:1: not UTF-8 text \(byte 0x"),
    "Latin-1 line 2": (lambda s: s.split("\n")[0].encode() + b"\n# caf\xe9\n",
                       r"hostile.txt:2: not UTF-8 text \(byte 0xe9"),
    "gzip without .gz": (lambda s: gzip.compress(s.encode()), r"hostile.txt: gzip-compressed"),
}


@pytest.mark.parametrize("variant", list(REFUSED))
@pytest.mark.parametrize("name", [n for n in READERS if n != "carmen"])
def test_non_text_is_refused_naming_file_and_line(name: str, variant: str, tmp_path: Path) -> None:
    reader, text_of, _ = READERS[name]
    make, match = REFUSED[variant]
    p = tmp_path / "hostile.txt"
    p.write_bytes(make(text_of(tmp_path)))
    with pytest.raises(DatasetError, match=match):
        reader(p)


@pytest.mark.parametrize("name", list(READERS))
def test_a_directory_is_named_as_such(name: str, tmp_path: Path) -> None:
    reader, _, _ = READERS[name]
    d = tmp_path / "hostile.txt"
    d.mkdir()
    with pytest.raises(DatasetError, match=r"hostile.txt: (is a directory|cannot read)"):
        reader(d)


def test_carmen_reads_a_gzip_log_whatever_its_suffix(tmp_path: Path) -> None:
    """CARMEN logs are often shipped gzipped; the magic bytes decide, not the name."""
    text = _carmen_text()
    (tmp_path / "a.log").write_text(text)
    (tmp_path / "b.log").write_bytes(gzip.compress(text.encode()))
    a, b = carmen.read_carmen(tmp_path / "a.log"), carmen.read_carmen(tmp_path / "b.log")
    assert len(a.scans) == 5
    np.testing.assert_array_equal(a.scans.ranges, b.scans.ranges)


def test_carmen_bom_keeps_the_first_scan(tmp_path: Path) -> None:
    """A BOM glued to the first ``FLASER`` used to drop that scan without a word."""
    p = tmp_path / "bom.log"
    p.write_text("\ufeff" + _carmen_text(), encoding="utf-8")
    assert len(carmen.read_carmen(p).scans) == 5


def test_time_messages_print_plain_numbers(tmp_path: Path) -> None:
    p = tmp_path / "t.tum"
    p.write_text("0.5 0 0 0 0 0 0 1\n0.25 0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"t.tum:2: time stamp 0.25 does not increase "
                                           r"\(previous 0.5\)") as info:
        tum.read_tum(p)
    assert "np.float64" not in str(info.value)


def test_yaml_error_is_one_line(tmp_path: Path) -> None:
    p = tmp_path / "cam.yaml"
    p.write_text("image_width: 320\n\tbad: 1\n")
    with pytest.raises(DatasetError, match=r"cam.yaml:2: invalid YAML: .*\(column 1\)") as info:
        calibration.read_calibration(p)
    assert "\n" not in str(info.value)


def test_yaml_key_given_twice_names_both_lines(tmp_path: Path) -> None:
    """A calibration with ``image_width`` twice was read with the last value; now an error
    naming the file, the second line and the first."""
    p = tmp_path / "cam.yaml"
    p.write_text("image_width: 320\nimage_height: 240\nimage_width: 640\n")
    with pytest.raises(DatasetError) as info:
        calibration.read_calibration(p)
    assert str(info.value) == (f"{p}:3: invalid YAML: key 'image_width' given twice "
                               "(first on line 1) (column 1)")


def test_slambook2_empty_pose_file(tmp_path: Path) -> None:
    from lampsam.datasets.rgbd import read_slambook2

    (tmp_path / "pose.txt").write_text("# no poses\n\n")
    with pytest.raises(DatasetError, match=r"pose.txt: no poses"):
        read_slambook2(tmp_path)


def test_config_with_bom_reads(tmp_path: Path) -> None:
    from lampsam.backend.config import SlamConfig
    from lampsam.config_loader import load_config

    p = tmp_path / "c.toml"
    p.write_text("\ufeff[isam2]\nrelinearize_threshold = 0.05\n", encoding="utf-8")
    assert math.isclose(load_config(SlamConfig, p).isam2.relinearize_threshold, 0.05)


@pytest.mark.parametrize(("name", "row", "match"), [
    ("odometry.csv", "0.2,1e300,0.02", r"hostile.txt:4: d_left/d_right: 1e\+300 m in 0.1 s is faster"),
    ("odometry.csv", "0.2,-20.0,0.02", r"hostile.txt:4: d_left/d_right: 20.0 m in 0.1 s is faster"),
    ("odometry_pose2.csv", "0.2,1e6,0.0,0.01,1e-4,0,0,1e-4,0,1e-5", r"hostile.txt:4: dx/dy: 1000000.0 m"),
    ("tum", "0.2 1e300 0 0 0 0 0 1", r"hostile.txt:4: x/y/z: 1e\+300 m is beyond 1e\+08 m"),
    ("graph_text", "ODOMETRY 1 2 1e300 0.0 0.1 0.0001 0 0 4e-06 0 4e-06",
     r"hostile.txt:3: ODOMETRY: x/y beyond 1e\+08 m"),
])
def test_huge_values_are_refused_naming_the_line(name: str, row: str, match: str, tmp_path: Path) -> None:
    """A value no robot log holds (1e300 m, 200 m/s wheels) was read and sent the EKF
    kilometres away with exit 0, or iSAM2 into 'covariance not positive definite'."""
    reader, text_of, _ = READERS[name]
    lines = text_of(tmp_path).splitlines()
    where = 3 if name != "graph_text" else 2  # the third data line (after a header/comment)
    lines[where] = row
    p = tmp_path / "hostile.txt"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=match):
        reader(p)


def test_plausible_speeds_still_read(tmp_path: Path) -> None:
    """99 m/s and a first sample alone are within the limit."""
    p = tmp_path / "odometry.csv"
    p.write_text("t,d_left,d_right\n0.0,0.0,0.0\n1.0,99.0,99.0\n1.5,0.0,0.0\n")
    assert len(tables.read_odometry(p).t) == 3


@pytest.mark.parametrize("name", list(READERS))
def test_no_read_permission_is_named(name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """chmod 000 (emulated: the suite may run as root, which reads anything)."""
    reader, text_of, _ = READERS[name]
    p = tmp_path / "hostile.txt"
    p.write_text(text_of(tmp_path))
    real_open = open

    def refuse(path: Any, *args: Any, **kwargs: Any) -> Any:
        if Path(str(path)) == p:
            raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr("builtins.open", refuse)
    monkeypatch.setattr(Path, "read_bytes", lambda self: refuse(self, "rb").read())
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: refuse(self).read())
    with pytest.raises(DatasetError, match=r"hostile.txt: cannot read: [Pp]ermission denied"):
        reader(p)
