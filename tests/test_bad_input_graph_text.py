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
