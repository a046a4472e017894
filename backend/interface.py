"""One interface for the three SLAM backends (``ekf``, ``isam2``, ``batch``).

A backend is fed, in time order, the wheel travel since the previous step and
(optionally) one measurement frame (:class:`lampsam.frontend.measurements.CeilingFrame`
or :class:`~lampsam.frontend.measurements.RangeBearingFrame`). After every step it
gives the current pose estimate and its covariance (:class:`StepEstimate`); at the
end :meth:`SlamBackend.finish` gives a :class:`SlamResult`.

Poses are ``world_T_body = (x, y, theta)`` (docs/conventions.md); pose covariances
are over the plain coordinates ``(x, y, theta)`` in the world frame (the EKF's
state), for every backend: the smoothers convert GTSAM's tangent-space marginal
with ``coords_D_tangent = blockdiag(R(theta), 1)``.
"""

from __future__ import annotations

import abc
import enum
import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, TypeAlias

import numpy as np

from lampsam.arrays import BoolArray, FloatArray
from lampsam.errors import EstimationError
from lampsam.frontend.measurements import CeilingFrame, RangeBearingFrame

if TYPE_CHECKING:
    import gtsam

#: A measurement frame the backends accept.
Frame: TypeAlias = CeilingFrame | RangeBearingFrame



class LandmarkKind(enum.StrEnum):
    """Kinds of landmark the backends estimate (a ``str``: compares equal to its value).

    - ``POINT2``: planar range-bearing landmark, state ``(x, y)``, m;
    - ``LAMP``: ceiling lamp, state ``(x, y, z)`` or ``(x, y, z, phi)`` (paper 1, sec. III);
    - ``CORNER``: ceiling corner, state ``(x, y, z)``.
    """

    POINT2 = "point2"
    LAMP = "lamp"
    CORNER = "corner"


#: Landmark types written to ``landmarks.csv``.
LANDMARK_TYPES = (LandmarkKind.LAMP.value, LandmarkKind.CORNER.value, LandmarkKind.POINT2.value)


@dataclass(frozen=True)
class StepEstimate:
    """The estimate after one step.

    Attributes:
        t: time of the step, s (the run's clock).
        pose: (3,) ``world_T_body`` as (x, y, theta), m and rad.
        cov: (3, 3) covariance of ``pose`` over (x, y, theta), m^2 / rad^2.
        keyframe: True when the step's frame was used as a keyframe (smoothers) or
            any measurement was used (EKF).
        n_matched: observations associated with an existing landmark.
        n_new: landmarks created (or started, for smoothers' pending ones).
        time_s: wall-clock time of the step, s.
    """

    t: float
    pose: FloatArray
    cov: FloatArray
    keyframe: bool = False
    n_matched: int = 0
    n_new: int = 0
    time_s: float = 0.0


@dataclass(frozen=True)
class LandmarkEstimate:
    """One mapped landmark.

    Attributes:
        id: the backend's landmark id (equal to the known ``landmark_id`` when
            association is known).
        type: ``"lamp"``, ``"corner"`` or ``"point2"`` (planar range-bearing).
        position: (3,) world position (x, y, z), m; ``z`` is the height above the
            camera for ceiling landmarks and NaN for planar landmarks.
        orientation: lamp long axis ``phi`` in the world, rad mod pi, or None.
        cov: (k, k) covariance of the estimated coordinates, k = 2 (planar),
            3 (x, y, z) or 4 (x, y, z, phi).
        n_obs: number of observations used.
    """

    id: int
    type: LandmarkKind
    position: FloatArray
    orientation: float | None
    cov: FloatArray
    n_obs: int = 0


@dataclass(frozen=True)
class GraphSnapshot:
    """A smoother's final factor graph and the estimate it was solved to (for export).

    Attributes:
        factors: every factor the backend added (``gtsam.NonlinearFactorGraph``).
        values: the final estimate over the graph's keys.
        body_t_camera: (3,) the ceiling camera's offset in the body frame, m, the
            projection factors were made with; None without a camera.
    """

    factors: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    body_t_camera: FloatArray | None = None


@dataclass
class SlamResult:
    """The finished result of a SLAM run.

    Attributes:
        backend: ``"ekf"``, ``"isam2"`` or ``"batch"``.
        times: (N,) step times, s.
        poses: (N, 3) ``world_T_body`` (x, y, theta) at each step.
        pose_covs: (N, 3, 3) covariance of each pose over (x, y, theta). For the
            smoothers these are the final marginals at keyframes and the keyframe
            marginal propagated with odometry in between.
        landmarks: the final map.
        step_times_s: (N,) wall-clock time of each online step, s.
        keyframes: (N,) True where a keyframe was made (the start pose, a keyframe of
            the smoothers' graphs made before any step, is not counted).
        status: ``"ok"``, ``"interrupted"`` or ``"failed: <reason>"``.
        final_time_s: time of the final optimisation in :meth:`SlamBackend.finish`
            (batch LM), s.
        n_pruned: landmarks removed (uncertain, or seen only once).
        pruned: the same count by reason (``seen_too_few``, ``uncertain``,
            ``pending_stale``, ``failed_update``); its values sum to ``n_pruned``.
        provisional: landmarks seen fewer than ``association.min_observations``
            times: not in ``landmarks`` (nor in its metrics), written flagged
            ``seen_once``; empty with ``association.prune_once_seen``.
        graph: the smoothers' final factor graph (``lampsam slam --g2o``); None for
            the EKF. Not pickled (GTSAM's Python-callback factors cannot be): a
            result sent to another process arrives without it.
    """

    backend: str
    times: FloatArray
    poses: FloatArray
    pose_covs: FloatArray
    landmarks: list[LandmarkEstimate]
    step_times_s: FloatArray
    keyframes: BoolArray
    status: str = "ok"
    final_time_s: float = 0.0
    n_pruned: int = 0
    pruned: dict[str, int] = field(default_factory=dict)
    extra: dict[str, float] = field(default_factory=dict)
    provisional: list[LandmarkEstimate] = field(default_factory=list)
    graph: GraphSnapshot | None = field(default=None, repr=False, compare=False)

    def __getstate__(self) -> dict[str, object]:
        """Pickled state without :attr:`graph` (see its note)."""
        return {**self.__dict__, "graph": None}


@dataclass
class StepHistory:
    """What a filter keeps of each step for its :class:`SlamResult`: time (s), pose
    ``(x, y, theta)`` (3,), its covariance (3, 3), the step's wall time (s) and whether
    it updated (the result's ``keyframes``)."""

    times: list[float] = field(default_factory=list)
    poses: list[FloatArray] = field(default_factory=list)
    covs: list[FloatArray] = field(default_factory=list)
    step_times: list[float] = field(default_factory=list)
    updated: list[bool] = field(default_factory=list)

    def add(self, t: float, pose: FloatArray, cov: FloatArray, dt: float, updated: bool) -> None:
        """Record one step (the arrays are kept, not copied)."""
        self.times.append(t)
        self.poses.append(pose)
        self.covs.append(cov)
        self.step_times.append(dt)
        self.updated.append(updated)

    def result(self, backend: str, landmarks: list[LandmarkEstimate], status: str, *,
               provisional: list[LandmarkEstimate] | None = None, n_pruned: int = 0,
               pruned: dict[str, int] | None = None,
               extra: dict[str, float] | None = None) -> SlamResult:
        """The :class:`SlamResult` of the steps so far (the other fields as named there)."""
        return SlamResult(
            backend=backend,
            times=np.asarray(self.times, float),
            poses=np.asarray(self.poses, float).reshape(-1, 3),
            pose_covs=np.asarray(self.covs, float).reshape(-1, 3, 3),
            landmarks=landmarks,
            step_times_s=np.asarray(self.step_times, float),
            keyframes=np.asarray(self.updated, bool),
            status=status,
            n_pruned=n_pruned,
            pruned=pruned or {},
            extra=extra or {},
            provisional=provisional or [],
        )


class SlamBackend(abc.ABC):
    """Common interface of the EKF, iSAM2 and batch backends.

    Usage::

        backend = make_backend("isam2", ...)
        for t, wheel, frame in stream:
            est = backend.step(t, wheel, frame)
        result = backend.finish()
    """

    name: str = "?"

    @abc.abstractmethod
    def step(self, t: float, wheel: FloatArray, frame: Frame | None) -> StepEstimate:
        """Advance to time ``t``.

        Args:
            t: the step's time, s; must not decrease.
            wheel: (K, 2) wheel travels ``(d_left, d_right)``, m, of the odometry
                samples since the previous step, in time order (K may be 0).
            frame: the measurement frame taken at ``t``, or None.

        Returns:
            The estimate after the step.
        """

    @abc.abstractmethod
    def finish(self, status: str = "ok") -> SlamResult:
        """End the run and return the result (batch: runs the final optimisation).

        Args:
            status: status to record (``"interrupted"`` when the caller stopped early).
        """


def check_step_time(t: float, last_t: float) -> float:
    """``t`` (s) when it does not go back from the previous step's ``last_t``; returns it
    (the caller's new ``last_t``).

    Raises:
        EstimationError: time goes backwards (the same message for every backend).
    """
    if t < last_t:
        raise EstimationError(f"t={t:.3f} s: time goes backwards (previous {last_t:.3f})")
    return t


def empty_result(backend: str, status: str) -> SlamResult:
    """A result with no steps (used when nothing could be processed)."""
    return SlamResult(
        backend=backend,
        times=np.zeros(0),
        poses=np.zeros((0, 3)),
        pose_covs=np.zeros((0, 3, 3)),
        landmarks=[],
        step_times_s=np.zeros(0),
        keyframes=np.zeros(0, dtype=bool),
        status=status,
    )


PRUNE_REASONS = {
    "seen_too_few": "seen fewer than {min_obs} times",
    "uncertain": "still uncertain when no longer seen",
    "pending_stale": "corners never placed (too few sightings with parallax)",
    "failed_update": "dropped with a failed iSAM2 update",
}
"""What each key of :attr:`SlamResult.pruned` means (the finish log line uses these words)."""


def log_pruned(total: int, by_reason: dict[str, int], min_obs: int,
               once_seen_kept: bool = False) -> None:
    """One warning giving the pruned-landmark count of ``summary.json`` and its breakdown.

    ``once_seen_kept``: the landmarks seen too few times are not dropped but written
    apart, flagged ``seen_once`` (``association.prune_once_seen`` false), and the
    warning says so, so that it agrees with ``landmarks.csv``.
    """
    if total <= 0:
        return
    parts = []
    for k, n in sorted(by_reason.items()):
        if not n:
            continue
        text = PRUNE_REASONS.get(k, k).format(min_obs=min_obs)
        if k == "seen_too_few" and once_seen_kept:
            text += " (written apart to landmarks.csv, flagged seen_once)"
        parts.append(f"{n} {text}")
    logging.getLogger("lampsam.backend").warning(
        "%d landmarks pruned from the map: %s", total, "; ".join(parts))
