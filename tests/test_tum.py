"""The one TUM parser: planar and 3-D views agree, the writer round-trips, errors name the line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lampsam.datasets.tables import Trajectory
from lampsam.datasets.tum import read_tum, read_tum_3d, read_tum_rows, write_tum
from lampsam.errors import DatasetError


def test_planar_round_trip_and_3d_view(tmp_path: Path) -> None:
    """write_tum -> read_tum gives the poses back; read_tum_3d gives the same yaw, z = 0."""
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.05, 0.2, 40))
    poses = np.column_stack([rng.normal(0, 5, 40), rng.normal(0, 5, 40), rng.uniform(-3.1, 3.1, 40)])
    path = tmp_path / "traj.tum"
    write_tum(path, Trajectory(t=t, poses=poses))
    back = read_tum(path)
    np.testing.assert_allclose(back.t, t, atol=1e-6)
    np.testing.assert_allclose(back.poses[:, :2], poses[:, :2], atol=1e-9)
    np.testing.assert_allclose(back.poses[:, 2], poses[:, 2], atol=1e-11)
    t3, T = read_tum_3d(path)
    assert T.shape == (40, 4, 4)
    np.testing.assert_array_equal(t3, back.t)
    np.testing.assert_allclose(T[:, 2, 3], 0.0)
    np.testing.assert_allclose(np.arctan2(T[:, 1, 0], T[:, 0, 0]), poses[:, 2], atol=1e-11)


def test_planar_view_of_a_3d_trajectory_is_its_zyx_yaw(tmp_path: Path) -> None:
    """Roll and pitch are dropped: the planar theta is the ZYX Euler yaw; 3-D keeps all."""
    rng = np.random.default_rng(4)
    rot = Rotation.from_euler("ZYX", np.column_stack([
        rng.uniform(-3, 3, 10), rng.uniform(-0.3, 0.3, 10), rng.uniform(-0.3, 0.3, 10)
    ]))  # fmt: skip
    q = rot.as_quat() * rng.uniform(0.5, 2.0, (10, 1))  # not normalised on purpose
    xyz = rng.normal(0, 1, (10, 3))
    lines = ["# t x y z qx qy qz qw"] + [
        " ".join(f"{v:.12f}" for v in (k, *xyz[k], *q[k])) for k in range(10)
    ]
    path = tmp_path / "t.tum"
    path.write_text("\n".join(lines) + "\n")
    planar = read_tum(path)
    np.testing.assert_allclose(planar.poses[:, 2], rot.as_euler("ZYX")[:, 0], atol=1e-9)
    _, T = read_tum_3d(path)
    np.testing.assert_allclose(T[:, :3, :3], rot.as_matrix(), atol=1e-9)
    np.testing.assert_allclose(T[:, :3, 3], xyz, atol=1e-11)


@pytest.mark.parametrize(
    ("text", "pattern", "line"),
    [
        ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n", "8 fields", 2),
        ("# c\n0 0 0 0 0 0 0 1\n0 1 0 0 0 0 0 1\n", "does not increase", 3),
        ("0 0 0 0 0 0 0 0\n", "zero quaternion", 1),
        ("0 0 x 0 0 0 0 1\n", "not a number", 1),
        ("0 0 0 nan 0 0 0 1\n", "non-finite", 1),
    ],
)
def test_errors_name_file_and_line(tmp_path: Path, text: str, pattern: str, line: int) -> None:
    """Each malformed file is a DatasetError naming the file and the 1-based line."""
    path = tmp_path / "bad.tum"
    path.write_text(text)
    with pytest.raises(DatasetError, match=pattern) as exc:
        read_tum_rows(path)
    assert exc.value.path == path
    assert exc.value.line == line
