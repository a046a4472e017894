"""The g2o writer: GTSAM's readG2o reads back the poses, landmarks and odometry factors."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest

from lampsam.datasets.g2o_writer import write_g2o
from lampsam.errors import InputError


def test_gtsam_reads_what_we_write(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    poses = np.column_stack([rng.normal(0, 3, 5), rng.normal(0, 3, 5), rng.uniform(-3, 3, 5)])
    info = np.array([[400.0, 5.0, 1.0], [5.0, 300.0, 2.0], [1.0, 2.0, 900.0]])
    edges = []
    for i in range(4):
        d = gtsam.Pose2(*poses[i]).between(gtsam.Pose2(*poses[i + 1]))
        edges.append((i, i + 1, np.array([d.x(), d.y(), d.theta()]), info))
    lms = rng.normal(0, 2, (3, 2))
    path = write_g2o(tmp_path / "g.g2o", np.arange(5), poses, edges, np.arange(5, 8), lms,
                     fixed=(0,), landmark_notes=["lamp z 2.5 m", "", "corner"])  # fmt: skip
    graph, values = gtsam.readG2o(str(path), False)
    assert graph.size() == 4 and values.size() == 8
    for i in range(5):
        p = values.atPose2(i)
        np.testing.assert_allclose([p.x(), p.y(), p.theta()], poses[i], atol=1e-8)
    for k in range(3):  # GTSAM keys landmarks as symbol 'l'
        np.testing.assert_allclose(values.atPoint2(gtsam.symbol("l", 5 + k)), lms[k], atol=1e-8)
    assert graph.error(values) < 1e-12  # measurements are the exact relative poses
    moved = gtsam.Values(values)
    moved.update(1, gtsam.Pose2(poses[1, 0] + 0.01, poses[1, 1], poses[1, 2]))
    # 0.5 e^T I e with the written information, e in edge 0's frame (first) and edge 1's
    d0 = gtsam.Pose2(*poses[0]).between(moved.atPose2(1))
    e0 = gtsam.Pose2(*edges[0][2]).between(d0)
    e0v = np.array([e0.x(), e0.y(), e0.theta()])
    d1 = moved.atPose2(1).between(gtsam.Pose2(*poses[2]))
    e1 = gtsam.Pose2(*edges[1][2]).between(d1)
    e1v = np.array([e1.x(), e1.y(), e1.theta()])
    assert graph.error(moved) == pytest.approx(0.5 * (e0v @ info @ e0v + e1v @ info @ e1v), rel=1e-6)
    assert path.read_text().splitlines()[-1] == "FIX 0"


def test_bad_input_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="unknown pose"):
        write_g2o(tmp_path / "g.g2o", np.arange(2), np.zeros((2, 3)), [(0, 5, np.zeros(3), np.eye(3))])
    with pytest.raises(InputError, match="repeat"):
        write_g2o(tmp_path / "g.g2o", np.arange(2), np.zeros((2, 3)), [], np.array([1]), np.zeros((1, 2)))
