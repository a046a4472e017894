"""Readers for the planar SLAM text formats that ``gtsam.load2D`` reads (iSAM and g2o).

One file gives a robot's poses (integer ids, in the order the odometry visits them),
the odometry between consecutive poses and landmark sightings from poses:

- iSAM (``.txt``, e.g. GTSAM's ``victoria_park.txt``):
  ``ODOMETRY i j dx dy dtheta c11 c12 c13 c22 c23 c33`` (also ``EDGE2``): the increment
  ``i_T_j`` and its covariance, as ``gtsam.load2D`` reads it: the upper triangle, or
  the ``.graph`` order ``c11 c12 c22 c33 c13 c23`` told by its zeros (``_covariance_2d``);
  ``LANDMARK i l dx dy v11 v12 v22``: landmark ``l`` at ``(dx, dy)`` in pose ``i``'s
  body frame, turned into ``[bearing, range]`` with GTSAM's rule (``sigma_bearing =
  sqrt(v11 / 10)``, ``sigma_range = sqrt(v11)`` when ``v11 == v22``, else 1 and 1, so
  that both build the same graph); ``BR i l bearing range sigma_bearing sigma_range``;
  ``VERTEX2 i x y theta`` (an initial or true pose).
- g2o: ``VERTEX_SE2 i x y theta``, ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33``
  (the upper triangle of the **information** matrix, g2o's convention),
  ``VERTEX_XY l x y``, ``EDGE_SE2_XY i l dx dy I11 I12 I22`` (also ``LANDMARK2``): a
  Cartesian sighting with information, turned into ``[bearing, range]`` with its
  covariance propagated to first order.

Text after ``#`` is a comment. ``EQUIV i j`` (TORO's pose equivalence, in GTSAM's
``w100.graph``) is counted and left out, as ``gtsam.load2D`` leaves it out (warned).
``FIX id`` (g2o's gauge) is read and left out: lampsam holds
the first pose with its prior (a warning names any other fixed id). A file written by
``lampsam slam ... --g2o`` reads back: its ``LAMPSAM_*`` lines (the ceiling model) are
counted and left out, and as it writes each sighting twice (``EDGE_SE2_XY`` for g2o, ``BR``
for GTSAM), a file holding both reads the ``BR`` lines only (warned).

Each pose becomes one step, at time ``t = k`` s for the ``k``-th pose (the formats
carry no times). The odometry chain is built in file order: an edge from the chain's
last pose to a new one extends it, and so does an edge from a new pose to the last one
(a chain written backwards, ``EDGE2 1 0`` as in GTSAM's ``w100.graph``: the edge
``j_T_i`` is inverted, :func:`invert_edge`; a file whose first edge runs to a lower id
starts its chain at that id). Every other pose-pose edge is a loop closure
(:class:`PoseEdge`, kept as written, ``i_T_j``, between two poses of the chain,
wherever the file lists it). Bad input gives a :class:`~lampsam.errors.DatasetError`
naming the file and line (a closure to a pose that no odometry reaches: that edge's line).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.datasets.odometry import Pose2OdometryLog
from lampsam.datasets.textio import MAX_COORDINATE, open_text
from lampsam.errors import DatasetError

log = logging.getLogger(__name__)

#: Suffixes taken as a graph text file by ``lampsam slam``.
GRAPH_TEXT_SUFFIXES = (".txt", ".g2o", ".graph")


@dataclass(frozen=True)
class Sighting:
    """One landmark sighting from a pose.

    Attributes:
        landmark: the file's landmark id.
        bearing: rad, from body ``x``, counter-clockwise; range: m.
        cov: (2, 2) covariance of ``[bearing, range]``, rad^2 and m^2.
    """

    landmark: int
    bearing: float
    range: float
    cov: FloatArray


@dataclass(frozen=True)
class PoseEdge:
    """A pose-pose edge that is not the odometry chain (a loop closure).

    Attributes:
        i, j: the step indices (positions in :attr:`GraphLog.pose_ids`) of its poses.
        delta: (3,) the measured ``i_T_j`` (m, m, rad), as the file writes it.
        cov: (3, 3) its covariance in GTSAM's ``Pose2`` tangent order ``(x, y, theta)``
            (m^2, rad^2; a g2o information matrix inverted).
        line: the file's line of the record (for messages).
    """

    i: int
    j: int
    delta: FloatArray
    cov: FloatArray
    line: int


@dataclass
class GraphLog:
    """A planar landmark-SLAM log read from a text file.

    Attributes:
        path: the file.
        pose_ids: (N,) the file's pose ids in odometry order.
        odometry: N samples; sample ``k`` is the increment from pose ``k-1`` to ``k``
            (sample 0: zero, the start), ``t = k`` s.
        sightings: per pose, its landmark sightings.
        vertices: the file's ``VERTEX`` poses by id (initial values or truth).
        closures: the loop closures (:class:`PoseEdge`), in file order.
        n_reversed: odometry edges written backwards (``j -> j-1``) and inverted.
    """

    path: Path
    pose_ids: list[int]
    odometry: Pose2OdometryLog
    sightings: list[list[Sighting]]
    vertices: dict[int, FloatArray] = field(default_factory=dict)
    closures: list[PoseEdge] = field(default_factory=list)
    n_reversed: int = 0

    @property
    def n_landmarks(self) -> int:
        """Distinct landmark ids sighted."""
        return len({s.landmark for ss in self.sightings for s in ss})

    def start_pose(self) -> FloatArray:
        """(3,) the first pose's vertex if the file has one, else the origin."""
        return np.asarray(self.vertices.get(self.pose_ids[0], np.zeros(3)), float)


def _sym(u: list[float]) -> FloatArray:
    """(3, 3) symmetric matrix from its upper triangle ``(a11, a12, a13, a22, a23, a33)``."""
    a = np.array([[u[0], u[1], u[2]], [u[1], u[3], u[4]], [u[2], u[4], u[5]]])
    return a


def _covariance_2d(v: list[float]) -> FloatArray:
    """(3, 3) covariance of an iSAM ``ODOMETRY`` / ``EDGE2`` record's six numbers.

    GTSAM's ``load2D`` (``NoiseFormatAUTO``) tells two layouts apart by their zeros,
    and so does this: ``v1 0 v3 v4 0 0`` is the ``.graph`` (TORO-style) order
    ``[[v1, v2, v5], [v2, v3, v6], [v5, v6, v4]]`` (e.g. GTSAM's ``example.graph``,
    ``w100.graph``: ``1 0 1 1 0 0`` = identity); anything else is the upper triangle
    ``c11 c12 c13 c22 c23 c33`` (``victoria_park.txt``, ``w20000.txt``). Both are
    covariances (x, y, theta; m^2, rad^2).
    """
    if v[0] != 0 and v[1] == 0 and v[2] != 0 and v[3] != 0 and v[4] == 0 and v[5] == 0:
        return np.array([[v[0], v[1], v[4]], [v[1], v[2], v[5]], [v[4], v[5], v[3]]])
    return _sym(v)


def invert_edge(delta: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The edge ``j_T_i`` of a measured ``i_T_j`` with its covariance.

    With GTSAM's right perturbation (``T exp(xi)``, ``xi = (x, y, theta)``),
    ``(T exp(xi))^-1 = T^-1 exp(-Ad_T xi)``: the inverse's covariance is
    ``Ad_T cov Ad_T^T``, ``Ad_T = [[c, -s, y], [s, c, -x], [0, 0, 1]]`` (``Pose2``'s
    adjoint), exactly, not to first order only; a ``BetweenFactorPose2`` on the
    inverted edge has the same error at every pair of poses as the original.

    Args:
        delta: (3,) ``i_T_j`` as ``(x, y, theta)``, m and rad.
        cov: (3, 3) its covariance.

    Returns:
        ``(delta (3,), cov (3, 3))`` of ``j_T_i`` (theta wrapped to (-pi, pi]).
    """
    x, y, th = (float(v) for v in delta)
    c, s = math.cos(th), math.sin(th)
    inv = np.array([-(c * x + s * y), s * x - c * y, -th])
    inv[2] = math.atan2(math.sin(inv[2]), math.cos(inv[2]))
    ad = np.array([[c, -s, y], [s, c, -x], [0.0, 0.0, 1.0]])
    out = ad @ np.asarray(cov, float) @ ad.T
    return inv, 0.5 * (out + out.T)


#: Records of 3-D files (GTSAM's ``pose3example.txt``, g2o SE3 graphs), refused by name.
_TAGS_3D = ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT", "VERTEX3", "EDGE3", "VERTEX_TRACKXYZ",
            "EDGE_SE3_TRACKXYZ", "VERTEX_SE3", "EDGE_SE3")


def _cartesian_to_br(dx: float, dy: float, cov_xy: FloatArray) -> tuple[float, float, FloatArray]:
    """``(bearing, range, cov)`` of a body-frame point with (2, 2) covariance (first order)."""
    r = math.hypot(dx, dy)
    b = math.atan2(dy, dx)
    j = np.array([[-dy / r**2, dx / r**2], [dx / r, dy / r]])
    return b, r, j @ cov_xy @ j.T


#: The fields after each record's tag, for messages.
_LAYOUTS = {
    "ODOMETRY": "i j dx dy dtheta c11 c12 c13 c22 c23 c33",
    "EDGE2": "i j dx dy dtheta c11 c12 c13 c22 c23 c33",
    "EDGE_SE2": "i j dx dy dtheta I11 I12 I13 I22 I23 I33",
    "LANDMARK": "i l dx dy v11 v12 v22",
    "LANDMARK2": "i l dx dy I11 I12 I22",
    "EDGE_SE2_XY": "i l dx dy I11 I12 I22",
    "BR": "i l bearing range sigma_bearing sigma_range",
    "VERTEX2": "i x y theta",
    "VERTEX_SE2": "i x y theta",
    "VERTEX": "i x y theta",
    "VERTEX_XY": "l x y",
}


def _unknown_record(tag: str, known: list[str]) -> str:
    """The message for a line whose first word is no record tag (long words cut to 40 chars)."""
    try:
        float(tag)
        return (f"the line starts with a number ({tag!r}), not a record tag: not an iSAM / g2o "
                "graph file (a plain table of numbers?)")
    except ValueError:
        pass
    shown = repr(tag if len(tag) <= 40 else tag[:40] + "...")
    if "," in tag:
        return (f"the line {shown} holds commas: a CSV table, not an iSAM / g2o graph file "
                "(space-separated records: ODOMETRY, EDGE_SE2, LANDMARK, ...)")
    if tag.startswith("<"):
        return f"the file starts like XML ({shown}), not an iSAM / g2o graph file"
    return f"unknown record {shown} (known: {', '.join(known)})"


def _ids(tag: str, words: list[str], path: Path, line_no: int) -> list[int]:
    """The integer ids of a record, or DatasetError naming the first that is not one."""
    ids = []
    for x in words:
        try:
            ids.append(int(x))
        except ValueError:
            raise DatasetError(f"{tag}: ids must be integers, got {x!r} (symbol ids such "
                               "as PyFG's 'L0' / 'A1' are not read)", path, line_no) from None
    return ids


def read_graph_text(path: str | Path) -> GraphLog:
    """Read an iSAM or g2o planar SLAM file (formats: module docstring).

    Raises:
        DatasetError: missing file, unknown record, wrong field count, a non-number,
            a covariance that is not positive definite, or odometry that does not
            form one chain; the message names the file and line.
    """
    path = Path(path)
    pose_ids: list[int] = []
    index: dict[int, int] = {}
    deltas: list[FloatArray] = [np.zeros(3)]
    covs: list[FloatArray] = [np.zeros((3, 3))]
    pending: list[tuple[int, Sighting, int, str]] = []  # (pose id, sighting, line, tag)
    tags_seen: set[str] = set()
    fixed: list[str] = []
    n_lampsam = 0
    vertices: dict[int, FloatArray] = {}
    edges: list[tuple[int, int, FloatArray, FloatArray, int, str]] = []  # not the chain
    n_reversed = 0
    n_equiv = 0
    counts = {"ODOMETRY": 11, "EDGE2": 11, "EDGE_SE2": 11, "LANDMARK": 7, "LANDMARK2": 7,
              "EDGE_SE2_XY": 7, "BR": 6, "VERTEX2": 4, "VERTEX_SE2": 4, "VERTEX_XY": 3,
              "VERTEX": 4}
    with open_text(path) as fh:
        for line_no, raw in enumerate(fh, start=1):
            parts = raw.split("#", 1)[0].split()  # a trailing "# l6" (lampsam's --g2o) too
            if not parts:
                continue
            tag = parts[0]
            if tag == "FIX":  # g2o's gauge; lampsam holds the first pose (one id per field)
                fixed.extend(parts[1:])
                continue
            if tag == "EQUIV":  # TORO's pose equivalence (w100.graph); GTSAM's load2D skips it
                n_equiv += 1
                continue
            if tag.startswith("LAMPSAM_"):  # lampsam's ceiling-model lines (its --g2o)
                n_lampsam += 1
                continue
            if tag in _TAGS_3D:
                raise DatasetError(f"3-D record {tag!r}: lampsam reads planar (2-D) graphs only "
                                   "(VERTEX_SE2 / EDGE_SE2 / ODOMETRY / LANDMARK ...)", path, line_no)
            if tag not in counts:
                raise DatasetError(_unknown_record(tag, sorted(counts)), path, line_no)
            if len(parts) - 1 != counts[tag]:
                raise DatasetError(f"{tag} needs {counts[tag]} fields, got {len(parts) - 1} "
                                   f"(layout: {tag} {_LAYOUTS[tag]})", path, line_no)
            n_ids = 2 if counts[tag] >= 6 else 1
            ids = _ids(tag, parts[1 : 1 + n_ids], path, line_no)
            try:
                nums = [float(x) for x in parts[1 + len(ids):]]
            except ValueError as exc:
                raise DatasetError(f"{tag}: not a number ({exc})", path, line_no) from None
            if not all(math.isfinite(v) for v in nums):
                raise DatasetError(f"{tag}: a value is not finite", path, line_no)
            if any(abs(v) > MAX_COORDINATE for v in nums[:2]):
                raise DatasetError(f"{tag}: x/y beyond {MAX_COORDINATE:g} m (a corrupt value, or "
                                   "not metres)", path, line_no)
            if tag in ("VERTEX2", "VERTEX_SE2", "VERTEX"):
                vertices[ids[0]] = np.array(nums)
                continue
            if tag == "VERTEX_XY":
                continue
            if tag in ("ODOMETRY", "EDGE2", "EDGE_SE2"):
                i, j = ids
                m = _sym(nums[3:])
                try:
                    cov = np.linalg.inv(m) if tag == "EDGE_SE2" else _covariance_2d(nums[3:])
                    np.linalg.cholesky(cov)
                except np.linalg.LinAlgError:
                    raise DatasetError(f"{tag} {i} {j}: the {'information' if tag == 'EDGE_SE2' else 'covariance'}"
                                       " matrix is not positive definite", path, line_no) from None
                delta = np.array(nums[:3])
                cov = np.asarray(cov, dtype=np.float64)
                if not pose_ids:  # the first edge starts the chain at its lower id
                    if j < i:
                        i, j = j, i
                        delta, cov = invert_edge(delta, cov)
                        n_reversed += 1
                    pose_ids.append(i)
                    index[i] = 0
                if i == pose_ids[-1] and j not in index:
                    extend = (j, delta, cov)
                elif j == pose_ids[-1] and i not in index:  # written backwards: j -> j-1
                    extend = (i, *invert_edge(delta, cov))
                    n_reversed += 1
                else:  # a loop closure: checked when the chain is complete
                    edges.append((i, j, delta, cov, line_no, tag))
                    continue
                index[extend[0]] = len(pose_ids)
                pose_ids.append(extend[0])
                deltas.append(extend[1])
                covs.append(extend[2])
                continue
            i, lid = ids
            if tag == "BR":
                b, r, sb, sr = nums
                s = Sighting(lid, b, r, np.diag([sb**2, sr**2]))
            elif tag == "LANDMARK":
                dx, dy, v1, _, v3 = nums
                if abs(v1 - v3) < 1e-4:
                    sb, sr = math.sqrt(v1 / 10.0), math.sqrt(v1)
                else:  # GTSAM's load2D does the same for a non-isotropic covariance
                    sb, sr = 1.0, 1.0
                s = Sighting(lid, math.atan2(dy, dx), math.hypot(dx, dy), np.diag([sb**2, sr**2]))
            else:  # g2o Cartesian sighting with information
                dx, dy, i11, i12, i22 = nums
                info = np.array([[i11, i12], [i12, i22]])
                try:
                    cov_xy = np.linalg.inv(info)
                    np.linalg.cholesky(cov_xy)
                except np.linalg.LinAlgError:
                    raise DatasetError(f"{tag}: information matrix not positive definite",
                                       path, line_no) from None
                if math.hypot(dx, dy) <= 0:
                    raise DatasetError(f"{tag}: landmark at the robot (zero range)", path, line_no)
                b, r, cov = _cartesian_to_br(dx, dy, cov_xy)
                s = Sighting(lid, b, r, cov)
            if s.range <= 0 or not np.all(np.linalg.eigvalsh(s.cov) > 0):
                raise DatasetError(f"{tag}: range must be > 0 and sigmas > 0", path, line_no)
            pending.append((i, s, line_no, tag))
            tags_seen.add(tag)
    if not pose_ids:
        raise DatasetError("no odometry records (ODOMETRY / EDGE2 / EDGE_SE2)", path)
    if "BR" in tags_seen and "EDGE_SE2_XY" in tags_seen:
        # lampsam's --g2o writes each sighting twice: EDGE_SE2_XY for g2o, BR for GTSAM
        n_xy = sum(1 for _, _, _, t in pending if t == "EDGE_SE2_XY")
        pending = [q for q in pending if q[3] != "EDGE_SE2_XY"]
        log.warning("%s: both BR and EDGE_SE2_XY sightings (as lampsam's --g2o writes each "
                    "sighting): the %d EDGE_SE2_XY lines are left out, the BR lines read", path, n_xy)
    if n_equiv:
        log.warning("%s: %d EQUIV lines (TORO's pose equivalences) left out, as GTSAM's load2D "
                    "leaves them out", path, n_equiv)
    if n_lampsam:
        log.warning("%s: %d LAMPSAM_* lines (lampsam's ceiling-model factors) left out: a planar "
                    "log reads the standard records", path, n_lampsam)
    if any(f != str(pose_ids[0]) for f in fixed):
        log.warning("%s: FIX %s left out: lampsam holds the first pose (%d) with its prior",
                    path, " ".join(fixed), pose_ids[0])
    sightings: list[list[Sighting]] = [[] for _ in pose_ids]
    for i, s, line_no, _ in pending:
        if i not in index:
            raise DatasetError(f"sighting from pose {i}, which no odometry reaches", path, line_no)
        sightings[index[i]].append(s)
    closures: list[PoseEdge] = []
    for i, j, delta, cov, line_no, tag in edges:
        lost = next((x for x in (i, j) if x not in index), None)
        if lost is not None:
            raise DatasetError(f"{tag} {i} {j}: pose {lost} is not on the odometry chain "
                               f"({pose_ids[0]} ... {pose_ids[-1]}, {len(pose_ids)} poses): a loop "
                               "closure must join two poses that the odometry reaches (each "
                               "odometry edge runs from the chain's last pose to a new one, "
                               "or back)", path, line_no)
        if i == j:
            raise DatasetError(f"{tag} {i} {j}: an edge from a pose to itself", path, line_no)
        closures.append(PoseEdge(index[i], index[j], delta, cov, line_no))
    if closures:
        log.info("%s: %d loop closures (pose-pose edges off the odometry chain)", path,
                 len(closures))
    n = len(pose_ids)
    odo = Pose2OdometryLog(t=np.arange(n, dtype=float), delta=np.array(deltas),
                           cov=np.array(covs))
    return GraphLog(path, pose_ids, odo, sightings, vertices, closures, n_reversed)


def read_vertices(path: str | Path) -> dict[int, FloatArray]:
    """``{id: (x, y, theta)}`` from a file's ``VERTEX2`` / ``VERTEX_SE2`` records (e.g. truth).

    Raises:
        DatasetError: missing file, or a malformed vertex line (file and line named).
    """
    path = Path(path)
    out: dict[int, FloatArray] = {}
    with open_text(path) as fh:
        for line_no, raw in enumerate(fh, start=1):
            parts = raw.split("#", 1)[0].split()
            if not parts or parts[0] not in ("VERTEX2", "VERTEX_SE2", "VERTEX"):
                continue
            if len(parts) != 5:
                raise DatasetError(f"{parts[0]} needs 4 fields, got {len(parts) - 1}", path, line_no)
            try:
                out[int(parts[1])] = np.array([float(x) for x in parts[2:]])
            except ValueError as exc:
                raise DatasetError(f"{parts[0]}: not a number ({exc})", path, line_no) from None
    return out
