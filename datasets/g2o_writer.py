"""Write a planar pose graph as a g2o text file (readable by g2o, GTSAM's ``readG2o``, ...).

Plain arrays in, so any backend can hand over its final graph. Lines written
(g2o's 2-D types; ids are shared by poses and landmarks)::

    VERTEX_SE2 id x y theta
    VERTEX_XY id x y
    EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33
    EDGE_SE2_XY i j dx dy I11 I12 I22
    FIX id

``EDGE_SE2`` holds the relative pose ``i_T_j`` and its information matrix (upper
triangle, row by row) in g2o's error coordinates (translation in ``i``'s frame,
then angle), which are GTSAM's ``Pose2`` right-tangent coordinates.
``EDGE_SE2_XY`` holds a landmark's position in pose ``i``'s body frame, m.
Ceiling landmarks are 3-D: their height above the camera (and a lamp's axis) go
into a ``#`` comment after the vertex, which g2o readers skip.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lampsam.arrays import FloatArray, IntArray
from lampsam.errors import InputError
from lampsam.safe_io import write_text_atomic


def _upper(info: FloatArray, n: int) -> str:
    """The upper triangle of an (n, n) matrix, row by row."""
    m = np.asarray(info, dtype=float).reshape(n, n)
    return " ".join(f"{m[r, c]:.9g}" for r in range(n) for c in range(r, n))


def write_g2o(
    path: str | Path,
    pose_ids: IntArray,
    poses: FloatArray,
    edges: list[tuple[int, int, FloatArray, np.ndarray]],
    landmark_ids: IntArray | None = None,
    landmarks: FloatArray | None = None,
    landmark_edges: list[tuple[int, int, FloatArray, np.ndarray]] | None = None,
    fixed: tuple[int, ...] = (),
    landmark_notes: list[str] | None = None,
) -> Path:
    """Write the graph.

    Args:
        path: the ``.g2o`` file (overwritten).
        pose_ids: (N,) vertex ids of the poses.
        poses: (N, 3) ``world_T_body`` ``(x, y, theta)``, m and rad.
        edges: ``(i, j, i_T_j (3,), information (3, 3))`` per pose-pose factor.
        landmark_ids: (L,) vertex ids of the landmarks (disjoint from ``pose_ids``).
        landmarks: (L, 2) world ``(x, y)``, m.
        landmark_edges: ``(pose id, landmark id, (2,) position in the body frame,
            information (2, 2))`` per observation.
        fixed: vertex ids to ``FIX`` (the gauge, usually the first pose).
        landmark_notes: (L,) text for the ``#`` comment after each landmark vertex.

    Raises:
        InputError: shapes that do not match, repeated ids, non-finite values, or an
            edge naming an unknown vertex.
    """
    pose_ids = np.asarray(pose_ids, dtype=np.int64).ravel()
    poses = np.asarray(poses, dtype=float).reshape(-1, 3)
    lm_ids = np.zeros(0, dtype=np.int64) if landmark_ids is None else np.asarray(landmark_ids, np.int64).ravel()
    lms = np.zeros((0, 2)) if landmarks is None else np.asarray(landmarks, dtype=float).reshape(-1, 2)
    if len(pose_ids) != len(poses) or len(lm_ids) != len(lms):
        raise InputError("g2o: ids and values differ in length")
    ids = np.concatenate([pose_ids, lm_ids])
    if len(np.unique(ids)) != len(ids):
        raise InputError("g2o: vertex ids repeat")
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(lms))):
        raise InputError("g2o: non-finite vertex values")
    known_poses, known = set(pose_ids.tolist()), set(ids.tolist())
    lines = [f"VERTEX_SE2 {pid} {x:.9f} {y:.9f} {th:.9f}"
             for pid, (x, y, th) in zip(pose_ids.tolist(), poses, strict=True)]  # fmt: skip
    notes = landmark_notes or [""] * len(lm_ids)
    for lid, (x, y), note in zip(lm_ids.tolist(), lms, notes, strict=True):
        lines.append(f"VERTEX_XY {lid} {x:.9f} {y:.9f}" + (f"  # {note}" if note else ""))
    for i, j, z, info in edges:
        if i not in known_poses or j not in known_poses:
            raise InputError(f"g2o: EDGE_SE2 {i} {j} names an unknown pose")
        dx, dy, dth = np.asarray(z, dtype=float).ravel()
        lines.append(f"EDGE_SE2 {i} {j} {dx:.9f} {dy:.9f} {dth:.9f} {_upper(info, 3)}")
    for i, j, z, info in landmark_edges or []:
        if i not in known_poses or j not in known:
            raise InputError(f"g2o: EDGE_SE2_XY {i} {j} names an unknown vertex")
        dx, dy = np.asarray(z, dtype=float).ravel()
        lines.append(f"EDGE_SE2_XY {i} {j} {dx:.9f} {dy:.9f} {_upper(info, 2)}")
    lines += [f"FIX {i}" for i in fixed]  # last: GTSAM's readG2o stops at a line it does not know
    path = Path(path)
    write_text_atomic(path, "\n".join(lines) + "\n")
    return path
