"""Messages of the iSAM / g2o graph reader for files found beside real graphs (GTSAM's
``Data/`` folder: docs/log-format.md, "GTSAM's data files").

Before: a CSV file was reported as ``unknown record 't,q_w,q_x,...'`` with its whole
header line (EqFdata.csv: 39 column names), GTSAM's multi-hypothesis ``T1_city10000_04.txt``
as ``EDGE2 needs 11 fields, got 8`` without the layout, and PyFG's symbol ids (``L0``) as
``not a number (invalid literal for int() ...)``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from lampsam.datasets.graph_text import read_graph_text
from lampsam.errors import DatasetError


@pytest.mark.parametrize(("text", "match"), [
    ("t,q_w,q_x,q_y,q_z,b_x,b_y,b_z,cq_w_0,cq_x_0,cq_y_0,cq_z_0,w_x,w_y,w_z\n1,2,3\n",
     r"g.txt:1: the line 't,q_w,q_x,q_y,q_z,b_x,b_y,b_z,cq_w_0,cq_\.\.\.' holds commas: "
     r"a CSV table, not an iSAM / g2o graph file"),
    ('<?xml version="1.0"?>\n<boost_serialization>\n',
     r"g.txt:1: the file starts like XML \('<\?xml'\)"),
    ("EDGE2 0 1 1 0 1 0.974351 -0.014717 0.024917\n",
     r"g.txt:1: EDGE2 needs 11 fields, got 8 \(layout: EDGE2 i j dx dy dtheta c11 c12 c13 c22 "
     r"c23 c33\)"),
    ("VERTEX_XY L0 730.1 429.9\n",
     r"g.txt:1: VERTEX_XY: ids must be integers, got 'L0' \(symbol ids such as PyFG's"),
    ("EDGE_SE2 A0 A1 1 0 0 1 0 0 1 0 1\n", r"g.txt:1: EDGE_SE2: ids must be integers, got 'A0'"),
    ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nBR 1 2.5 0.1 2.0 0.05 0.1\n",
     r"g.txt:2: BR: ids must be integers, got '2.5'"),
], ids=["csv", "xml", "edge2_8_fields", "pyfg_symbol", "symbol_pose", "float_landmark_id"])
def test_foreign_lines_are_named(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "g.txt"
    path.write_text(text)
    with pytest.raises(DatasetError, match=match) as info:
        read_graph_text(path)
    assert len(str(info.value)) < 300


def test_integer_ids_still_read(tmp_path: Path) -> None:
    path = tmp_path / "g.txt"
    path.write_text("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nBR 1 7 0.1 2.0 0.05 0.1\n")
    log = read_graph_text(path)
    assert log.pose_ids == [0, 1] and log.sightings[1][0].landmark == 7


def test_own_g2o_export_reads_back(tmp_path: Path) -> None:
    """``lampsam slam RUN --g2o G`` then ``lampsam slam G``: was an error at the first vertex
    (its trailing ``# l6`` comment), then at ``FIX`` / ``LAMPSAM_*``; now it reads back, each
    sighting once (BR; the EDGE_SE2_XY twin left out), and batch on it returns the exported
    batch estimate."""
    import numpy as np

    from lampsam.cli import main
    from lampsam.datasets.graph_text import read_vertices
    from lampsam.datasets.logrun import write_run
    from lampsam.datasets.rig import Rig
    from lampsam.datasets.tables import OdometryLog, RangeBearingLog

    rng = np.random.default_rng(21)
    n, step, wheel_base = 60, 0.05, Rig().odometry.wheel_base
    t = np.arange(n) * 0.2
    d_left = np.full(n, step)
    d_right = np.full(n, step + 0.002)
    d_left[0] = d_right[0] = 0.0
    theta = np.cumsum((d_right - d_left) / wheel_base)
    ds = (d_left + d_right) / 2
    xy = np.cumsum(np.column_stack([ds * np.cos(theta), ds * np.sin(theta)]), axis=0)
    marks = np.array([[1.0, 1.5], [2.0, -1.0], [3.0, 1.0]])
    rows = []
    for k in range(n):
        for j, m in enumerate(marks):
            d = m - xy[k]
            rows.append((t[k], j, np.hypot(*d) + rng.normal(0, 0.01),
                         np.arctan2(d[1], d[0]) - theta[k] + rng.normal(0, 0.005)))
    a = np.array(rows)
    rb = RangeBearingLog(t=a[:, 0], landmark_id=a[:, 1].astype(int), range=a[:, 2], bearing=a[:, 3])
    odo = OdometryLog(t=t, d_left=d_left + rng.normal(0, 1e-4, n), d_right=d_right)
    run = tmp_path / "run"
    write_run(run, Rig(), odo, range_bearing=rb)
    g2o = tmp_path / "g.g2o"
    assert main(["slam", str(run), "--backend", "batch", "--out", str(tmp_path / "a"),
                 "--g2o", str(g2o)]) == 0
    text = g2o.read_text()
    assert "# l" in text and "\nFIX " in text and "LAMPSAM_" in text

    log = read_graph_text(g2o)
    n_br = sum(line.startswith("BR ") for line in text.splitlines())
    assert sum(len(s) for s in log.sightings) == n_br > 0
    assert log.n_landmarks == 3

    assert main(["slam", str(g2o), "--backend", "batch", "--out", str(tmp_path / "b")]) == 0
    est = np.loadtxt(tmp_path / "b" / "trajectory.tum", comments="#")
    exported = read_vertices(g2o)
    ref = np.array([exported[k] for k in log.pose_ids])
    yaw = 2 * np.arctan2(est[:, 6], est[:, 7])
    assert np.abs(est[:, 1:3] - ref[:, :2]).max() < 1e-4  # m (measured 4.9e-6: LM tolerance)
    assert np.abs(np.angle(np.exp(1j * (yaw - ref[:, 2])))).max() < 1e-4  # rad (5e-7)


@pytest.mark.parametrize(("text", "match"), [
    ("EDGE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE2 1 2 1 0 0 1 0 0 1 0 1\nEDGE2 0 9 0 0 0 1 0 0 1 0 1\n",
     r"g.txt:3: EDGE2 0 9: pose 9 is not on the odometry chain \(0 ... 2, 3 poses\): a loop "
     r"closure must join two poses that the odometry reaches"),
    ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 7 0 0 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n",
     r"g.txt:2: EDGE_SE2 7 0: pose 7 is not on the odometry chain"),
    ("EDGE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE2 1 1 0 0 0 1 0 0 1 0 1\n",
     r"g.txt:2: EDGE2 1 1: an edge from a pose to itself"),
], ids=["closure_to_missing_pose", "closure_from_missing_pose", "self_edge"])
def test_bad_loop_closures_are_named(tmp_path: Path, text: str, match: str) -> None:
    """A loop closure to a pose that no odometry reaches names the closure's own line (was:
    every pose-pose edge off the chain left out with one warning)."""
    path = tmp_path / "g.txt"
    path.write_text(text)
    with pytest.raises(DatasetError, match=match):
        read_graph_text(path)


def test_closure_listed_before_its_pose_is_read(tmp_path: Path) -> None:
    """w100.graph lists ``EDGE2 99 40`` before ``EDGE2 99 98`` brings pose 99 onto the
    chain: the closure is resolved once the whole file is read."""
    path = tmp_path / "g.graph"
    path.write_text("EDGE2 1 0 -1 0 0 1 0 1 1 0 0\nEDGE2 2 0 -2 0 0 1 0 1 1 0 0\n"
                    "EDGE2 2 1 -1 0 0 1 0 1 1 0 0\nEQUIV 2 0\n")
    log = read_graph_text(path)
    assert log.pose_ids == [0, 1, 2] and log.n_reversed == 2
    assert [(e.i, e.j, e.line) for e in log.closures] == [(2, 0, 2)]
