"""A SLAM result as a g2o graph file (``lampsam slam ... --g2o OUT.g2o``).

The smoothers (``isam2``, ``batch``) hand over their whole final factor graph
(:class:`~lampsam.backend.interface.GraphSnapshot`); every factor is written, in g2o's
planar types where one exists and as a documented ``LAMPSAM_*`` line otherwise
(g2o and GTSAM's ``readG2o`` skip lines whose tag they do not know). Ids: pose
``X(k)`` is vertex ``k``; the other variables follow in key order; each vertex line
ends with a ``# <gtsam key>`` comment (``l17`` = landmark 17).

Standard lines (read by g2o and, except ``EDGE_SE2_XY``, by ``gtsam.readG2o``)::

    VERTEX_SE2 id x y theta                   every pose X(k)
    VERTEX_XY id x y                          every Point2 / Point3 landmark (x, y)
    EDGE_SE2 i j dx dy dtheta I(6)            BetweenFactorPose2 between two poses
    EDGE_SE2_XY i j dx dy I(3)                range-bearing: the point in pose i's frame,
                                              information J^-T C^-1 J^-1 propagated
                                              from the (bearing, range) covariance C
    BR i j bearing range sigma_b sigma_r      the same observation for GTSAM's readG2o
                                              (which ignores EDGE_SE2_XY, and g2o BR)
    FIX id                                    the gauge: the pose with a prior (last,
                                              as readG2o stops reading edges at FIX)

Custom lines (lampsam's ceiling model; ``I(n)`` = upper triangle of the information
matrix, row by row, of the base Gaussian: a Huber kernel is dropped)::

    LAMPSAM_VERTEX_XYZ id x y z               a Point3 landmark's height (lamp, corner)
    LAMPSAM_VERTEX_SE2 id x y theta           a Pose2 that is not a robot pose (a lamp
                                              axis A(j): only theta is meaningful)
    LAMPSAM_VERTEX_VECTOR id n v1..vn         an inverse-depth corner (alpha_x, alpha_y, rho)
    LAMPSAM_EDGE_SE2 i j dx dy dtheta I(6)    BetweenFactorPose2 to a non-pose (lamp axis,
                                              :func:`~lampsam.factors.axis_factors.lamp_axis_between_factor`)
    LAMPSAM_EDGE_PROJ i j u v I(3)            upward-camera projection of Point3 j from
                                              pose i (normalised ceiling coordinates,
                                              :func:`~lampsam.factors.ceiling.project_point`),
                                              camera offset in LAMPSAM_CAMERA
    LAMPSAM_CAMERA tx ty tz                   body_t_camera of the projection lines, m
    LAMPSAM_PRIOR_SE2 id x y theta I(6)       PriorFactorPose2 (start pose, axis anchors)
    LAMPSAM_PRIOR_XYZ id x y z I(6)           PriorFactorPoint3 (corner height prior)
    LAMPSAM_PRIOR_VECTOR id n v1..vn I(...)   PriorFactorVector (inverse-depth first sight)

Omitted, and counted in the returned summary: ``CustomFactor`` s (a range-bearing
sensor offset, inverse-depth and per-frame axis forms: their model lives in Python
callbacks) and factors on variables no longer in the estimate (removed landmarks).

The EKF has no graph: for it the poses are the keyframe poses, ``EDGE_SE2`` the
odometry re-derived from the run between them (wheel travel through paper 1,
eqs. 13-15, or Pose2 increments composed with their covariances), and the landmarks
``VERTEX_XY`` vertices with no observation edges (its map is a joint Gaussian, not
factors).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import gtsam
import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.interface import GraphSnapshot, SlamResult
from lampsam.backend.odometry import Pose2Motion
from lampsam.datasets.g2o_writer import write_g2o
from lampsam.datasets.logrun import LoggedRun
from lampsam.datasets.odometry import Pose2OdometryLog, Pose2OdometryModel
from lampsam.errors import InputError
from lampsam.factors.gtsam_factors import projection_factor
from lampsam.factors.motion import DEFAULT_FLOOR_VAR, accumulate_odometry
from lampsam.safe_io import write_text_atomic

POSE_CHR = "x"  #: the robot poses' symbol character (``gtsam.symbol_shorthand.X``)


@dataclass
class G2oSummary:
    """What a g2o file holds.

    Attributes:
        poses: ``VERTEX_SE2`` robot poses.
        landmarks: other vertices (landmarks, lamp axes, corners).
        lines: written lines by tag.
        omitted: factors not written, by reason (``CustomFactor``, ``removed variable``).
    """

    poses: int = 0
    landmarks: int = 0
    lines: dict[str, int] = field(default_factory=dict)
    omitted: dict[str, int] = field(default_factory=dict)

    def text(self) -> str:
        """One line for the console."""
        parts = [f"{n} {tag}" for tag, n in sorted(self.lines.items())]
        out = f"{self.poses} poses, {self.landmarks} other vertices; " + ", ".join(parts)
        if self.omitted:
            out += "; omitted: " + ", ".join(f"{n} {k}" for k, n in sorted(self.omitted.items()))
        return out


def upper(info: FloatArray) -> str:
    """The upper triangle of a square matrix, row by row (g2o's information layout)."""
    m = np.atleast_2d(np.asarray(info, dtype=float))
    n = m.shape[0]
    return " ".join(f"{m[r, c]:.9g}" for r in range(n) for c in range(r, n))


def information(noise: gtsam.noiseModel.Base) -> FloatArray:
    """Information matrix of a Gaussian noise model (of the base model under a robust kernel)."""
    if isinstance(noise, gtsam.noiseModel.Robust):
        noise = noise.noise()
    if not isinstance(noise, gtsam.noiseModel.Gaussian):
        raise TypeError(f"g2o: no information matrix for a {type(noise).__name__} noise model")
    r: FloatArray = np.asarray(noise.R(), dtype=np.float64)
    return r.T @ r


def range_bearing_xy(bearing: float, range_: float, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
    """A (bearing, range) observation as a body-frame point and that point's information.

    ``p = r (cos b, sin b)``; ``J = dp/d(b, r) = [[-r sin b, cos b], [r cos b, sin b]]``;
    the point's covariance is ``J C J^T`` (first order), its information the inverse.
    """
    c, s = math.cos(bearing), math.sin(bearing)
    p = np.array([range_ * c, range_ * s])
    jac = np.array([[-range_ * s, c], [range_ * c, s]])
    return p, np.linalg.inv(jac @ np.asarray(cov, dtype=float) @ jac.T)


def _vertex_lines(values: gtsam.Values, ids: dict[int, int]) -> tuple[list[str], int, int]:
    """Vertex lines for every key of ``values``; fills ``ids`` (key -> g2o id)."""
    keys = sorted(values.keys())
    pose_keys = [k for k in keys if chr(gtsam.Symbol(k).chr()) == POSE_CHR]
    for k in pose_keys:
        ids[k] = int(gtsam.Symbol(k).index())
    next_id = max(ids.values(), default=-1) + 1
    lines: list[str] = []
    for k in pose_keys:
        p = values.atPose2(k)
        lines.append(f"VERTEX_SE2 {ids[k]} {p.x():.9f} {p.y():.9f} {p.theta():.9f}")
    n_other = 0
    for k in keys:
        if k in ids:
            continue
        ids[k] = i = next_id
        next_id += 1
        n_other += 1
        name = gtsam.DefaultKeyFormatter(k)
        line = _other_vertex(values, k, i)
        lines += [f"{x}  # {name}" for x in line]
    return lines, len(pose_keys), n_other


def _try(get: Callable[[int], object], key: int) -> object | None:
    try:
        return get(key)
    except RuntimeError:
        return None


def _other_vertex(values: gtsam.Values, key: int, i: int) -> list[str]:
    """Lines of a non-pose variable (see the module docstring)."""
    p2 = _try(values.atPoint2, key)
    if p2 is not None:
        x, y = np.asarray(p2, dtype=float)
        return [f"VERTEX_XY {i} {x:.9f} {y:.9f}"]
    p3 = _try(values.atPoint3, key)
    if p3 is not None:
        x, y, z = np.asarray(p3, dtype=float)
        return [f"VERTEX_XY {i} {x:.9f} {y:.9f}", f"LAMPSAM_VERTEX_XYZ {i} {x:.9f} {y:.9f} {z:.9f}"]
    pose = _try(values.atPose2, key)
    if isinstance(pose, gtsam.Pose2):
        return [f"LAMPSAM_VERTEX_SE2 {i} {pose.x():.9f} {pose.y():.9f} {pose.theta():.9f}"]
    rot = _try(values.atRot2, key)
    if isinstance(rot, gtsam.Rot2):
        return [f"LAMPSAM_VERTEX_SE2 {i} 0 0 {rot.theta():.9f}"]
    vec = np.asarray(values.atVector(key), dtype=float).ravel()
    return [f"LAMPSAM_VERTEX_VECTOR {i} {len(vec)} " + " ".join(f"{v:.9g}" for v in vec)]


def _count(d: dict[str, int], k: str) -> None:
    d[k] = d.get(k, 0) + 1


def graph_lines(snap: GraphSnapshot) -> tuple[list[str], G2oSummary]:
    """The g2o lines of a factor graph and its estimate (module docstring), and what they hold."""
    ids: dict[int, int] = {}
    vertices, n_pose, n_other = _vertex_lines(snap.values, ids)
    summary = G2oSummary(poses=n_pose, landmarks=n_other)
    std: list[str] = []
    custom: list[str] = []
    fixed: list[int] = []
    if snap.body_t_camera is not None:
        tx, ty, tz = np.asarray(snap.body_t_camera, dtype=float)
        custom.append(f"LAMPSAM_CAMERA {tx:.9g} {ty:.9g} {tz:.9g}")
    factors = snap.factors
    for n in range(factors.size()):
        f = factors.at(n)
        if f is None:
            continue
        keys = list(f.keys())
        if not all(k in ids for k in keys):
            _count(summary.omitted, "on a removed variable")
            continue
        is_pose = [chr(gtsam.Symbol(k).chr()) == POSE_CHR for k in keys]
        g = [ids[k] for k in keys]
        if isinstance(f, gtsam.BetweenFactorPose2):
            d = f.measured()
            tag = "EDGE_SE2" if all(is_pose) else "LAMPSAM_EDGE_SE2"
            (std if all(is_pose) else custom).append(
                f"{tag} {g[0]} {g[1]} {d.x():.9f} {d.y():.9f} {d.theta():.9f} "
                f"{upper(information(f.noiseModel()))}")
        elif isinstance(f, gtsam.BearingRangeFactor2D):
            br = f.measured()
            b, r = float(br.bearing().theta()), float(br.range())
            info = information(f.noiseModel())
            cov: FloatArray = np.linalg.inv(info).astype(np.float64)
            xy, info_xy = range_bearing_xy(b, r, cov)
            std.append(f"EDGE_SE2_XY {g[0]} {g[1]} {xy[0]:.9f} {xy[1]:.9f} {upper(info_xy)}")
            std.append(f"BR {g[0]} {g[1]} {b:.9f} {r:.9f} "
                       f"{math.sqrt(cov[0, 0]):.9g} {math.sqrt(cov[1, 1]):.9g}")
        elif isinstance(f, gtsam.PlanarProjectionFactor2) and snap.body_t_camera is not None:
            # the factor keeps its measurement in C++ only: predicted - error = measured
            twin = projection_factor(keys[0], keys[1], np.zeros(2), np.eye(2), snap.body_t_camera)
            u, v = (np.asarray(twin.unwhitenedError(snap.values), dtype=float)
                    - np.asarray(f.unwhitenedError(snap.values), dtype=float))
            custom.append(f"LAMPSAM_EDGE_PROJ {g[0]} {g[1]} {u:.9f} {v:.9f} "
                          f"{upper(information(f.noiseModel()))}")
        elif isinstance(f, gtsam.PriorFactorPose2):
            p = f.prior()
            custom.append(f"LAMPSAM_PRIOR_SE2 {g[0]} {p.x():.9f} {p.y():.9f} {p.theta():.9f} "
                          f"{upper(information(f.noiseModel()))}")
            if is_pose[0]:
                fixed.append(g[0])
        elif isinstance(f, gtsam.PriorFactorPoint3):
            x, y, z = np.asarray(f.prior(), dtype=float)
            custom.append(f"LAMPSAM_PRIOR_XYZ {g[0]} {x:.9f} {y:.9f} {z:.9f} "
                          f"{upper(information(f.noiseModel()))}")
        elif isinstance(f, gtsam.PriorFactorVector):
            vec = np.asarray(f.prior(), dtype=float).ravel()
            custom.append(f"LAMPSAM_PRIOR_VECTOR {g[0]} {len(vec)} "
                          + " ".join(f"{x:.9g}" for x in vec)
                          + f" {upper(information(f.noiseModel()))}")
        else:
            _count(summary.omitted, type(f).__name__)
    lines = vertices + std + custom + [f"FIX {i}" for i in sorted(set(fixed))]
    for line in lines:
        _count(summary.lines, line.split(" ", 1)[0])
    return lines, summary


def _ekf_g2o(path: Path, result: SlamResult, run: LoggedRun) -> G2oSummary:
    """The EKF's result: keyframe poses, re-derived odometry edges, landmark vertices."""
    kf = np.flatnonzero(result.keyframes) if np.any(result.keyframes) else np.arange(len(result.times))
    odo, wheel = run.odometry, run.rig.odometry
    edges = []
    for i in range(len(kf) - 1):
        ta, tb = result.times[kf[i]], result.times[kf[i + 1]]
        sel = (odo.t > ta) & (odo.t <= tb)
        if isinstance(odo, Pose2OdometryLog):
            delta, cov = Pose2Motion(Pose2OdometryModel()).relative(odo.samples()[sel],
                                                                    DEFAULT_FLOOR_VAR)
        else:
            delta, cov = accumulate_odometry(odo.d_left[sel], odo.d_right[sel],
                                             wheel.wheel_base, wheel.k_r, wheel.k_l)
        edges.append((i, i + 1, delta, np.linalg.inv(cov)))
    lms = result.landmarks
    notes = [f"{lm.type} id {lm.id} z {lm.position[2]:.4f} m"
             + (f" phi {lm.orientation:.6f} rad" if lm.orientation is not None else "") for lm in lms]
    write_g2o(path, np.arange(len(kf)), result.poses[kf], edges,
              landmark_ids=len(kf) + np.arange(len(lms)),
              landmarks=np.array([lm.position[:2] for lm in lms]).reshape(-1, 2),
              fixed=(0,) if len(kf) else (), landmark_notes=notes)
    lines = {"VERTEX_SE2": len(kf), "EDGE_SE2": len(edges), "VERTEX_XY": len(lms)}
    if len(kf):
        lines["FIX"] = 1
    return G2oSummary(poses=len(kf), landmarks=len(lms), lines=lines)


def write_result_g2o(path: str | Path, result: SlamResult, run: LoggedRun | None) -> G2oSummary:
    """Write ``result`` as g2o to ``path`` (atomically).

    Args:
        path: the ``.g2o`` file to write.
        result: the finished SLAM result; a smoother's carries its graph.
        run: the run it came from (needed only for the EKF: its odometry and wheel
            model give the factors).

    Returns:
        What was written.

    Raises:
        InputError: an EKF result without its run.
    """
    path = Path(path)
    if result.graph is not None:
        lines, summary = graph_lines(result.graph)
        write_text_atomic(path, "\n".join(lines) + "\n")
        return summary
    if run is None:
        raise InputError("g2o: an EKF result needs its run to derive the odometry factors")
    return _ekf_g2o(path, result, run)
