"""Verification of a global-localization result with the ceiling feature map.

Paper 2, sec. 4.2, eq. 10: after the particle filter has converged the robot
drives on; ``R_loc = 1 - d_fail / d``, where ``d`` is the distance driven and
``d_fail`` the part of it driven while the ceiling features (lamps, corners)
seen by the upward camera fail to match the ceiling feature map at the
estimated pose. ``R_loc < 0.25`` means failure: start over.

Per-frame test (:func:`frame_match`): every landmark of the ceiling feature map
is projected into normalised ceiling coordinates at the estimated pose with
:func:`lampsam.factors.ceiling.project_point` (``docs/conventions.md``); an
observed feature matches when a predicted landmark lies within a gate of it
(Euclidean in ``m``, which is metres per metre of height: a gate of 0.1 at a
2.5 m ceiling is 25 cm on the ceiling). A frame *matches* when at least
``min_match_fraction`` of its observed features match. Frames without any
observed feature carry no evidence and their distance counts neither in ``d``
nor in ``d_fail`` (documented choice: the paper does not say; a stretch of
blank ceiling should not decide).

Two deciders share that per-frame test:

* :class:`RlocVerifier` (the paper): decides once ``d`` reaches
  ``verify_distance``; afterwards it keeps ``R_loc`` over a sliding window of the
  same length, so a kidnapped robot is detected too.
* :class:`SequentialVerifier` (ours): Wald's sequential probability ratio test
  on the frames' match/no-match outcomes, with the evidence of a frame weighted
  by the distance driven since the previous one (``ds / step_length``; frames a
  few cm apart are not independent). It accepts or rejects as soon as the
  log-likelihood ratio crosses a bound -- typically after 0.2-0.5 m, about 1-2 s
  of driving, instead of a fixed distance. After acceptance it keeps running as
  a CUSUM (the ratio is clipped at 0 from below), which detects a kidnapping
  within a similar distance.
"""

from __future__ import annotations

import enum
import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lampsam.arrays import BoolArray, FloatArray
from lampsam.errors import LocalizationError
from lampsam.factors.ceiling import project_point
from lampsam.factors.geometry import rigid_fit_2d, wrap_axis
from lampsam.frontend.measurements import CeilingFrame

log = logging.getLogger(__name__)

MIN_HEIGHT = 0.1  # m, conventions.md: a landmark is usable only when h > 0.1 m


class VerificationError(LocalizationError):
    """Malformed ceiling map or observations for verification."""


class Verdict(enum.Enum):
    """State of a verifier."""

    PENDING = "pending"
    ACCEPTED = "accepted"
    FAILED = "failed"


@dataclass(frozen=True)
class VerificationConfig:
    """Ceiling-feature verification (paper 2, sec. 4.2, plus the sequential test).

    Attributes:
        gate: match gate in normalised ceiling coordinates (m per m of height).
            Default 0.10 (25 cm on a ceiling 2.5 m above the camera).
        min_match_fraction: a frame matches when at least this fraction of its
            observed features match. Default 0.5.
        verify_distance: distance (m) the paper's verifier drives before
            deciding; also its sliding-window length. Default 2.0 m.
        r_loc_threshold: failure when ``R_loc`` is below this (eq. 10). Default
            0.25 (the paper's, chosen by experiment).
        p_match_correct: probability that a frame matches when the pose is right
            (sequential test, H0). Default 0.85.
        p_match_wrong: probability that a frame matches by chance when the pose
            is wrong (H1). Default 0.15.
        alpha: accepted rate of false alarms (rejecting a right pose). Default 0.01.
        beta: accepted rate of missed failures (accepting a wrong pose). Default 0.01.
        step_length: driving distance (m) over which frames count as one
            independent outcome. Default 0.10 m.
        axis_gate: a lamp with a long axis matches only a map lamp whose
            predicted image axis ``wrap_axis(phi - theta)`` (conventions.md) is
            within this (rad) of the observed one. Default 15 deg. Without it a
            ceiling of strip lamps on a square lattice accepts a pose turned by
            90 deg.
        lamp_match_fraction: a frame that sees lamps matches only when at least
            this fraction of them match (separately from the corners). Default
            0.75. Lamps are large and bright: at the right pose the detector
            finds and places them reliably, whereas at a twin pose of a
            symmetric lamp layout half of them can still match (office trial
            12: a pose turned by 90 deg about the room centre matched 2 of 4
            lamps and passed the 0.5 fraction).
        twin_radius: shifts of the ceiling map up to this length (m, on the
            ceiling) are the "twin" hypotheses of :func:`self_similarity`.
            Default 1.0 m.
        twin_min_shift: shifts shorter than this (m) are not twins (they are
            within the 30 cm failure bound). Default 0.3 m.
        max_self_similarity: a kind of feature whose map matches itself under a
            twin shift for more than this fraction of its features (a periodic
            tile-corner lattice: about 1.0) cannot tell a pose from its twins
            and does not vote in a frame's outcome. Default 0.5.
        early_decision: the paper's verifier decides as soon as its verdict at
            ``verify_distance`` is certain (default True): ``R_loc`` at
            ``d = verify_distance`` is the matched distance over
            ``verify_distance``, so it will be at least ``r_loc_threshold`` once
            ``r_loc_threshold * verify_distance`` metres have matched (0.5 m
            with the defaults), and below it once more than ``(1 -
            r_loc_threshold) * verify_distance`` metres have failed (1.5 m).
            The verdict is the one the full drive would give; only the robot
            stops driving sooner. False: always drive ``verify_distance``.
        accept_without_evidence: when the whole verification drive produced no
            discriminating evidence, accept the pose unverified (True) or start
            over (False). Default False: verification must not accept on
            evidence that cannot discriminate.
    """

    gate: float = 0.10
    min_match_fraction: float = 0.5
    verify_distance: float = 2.0
    r_loc_threshold: float = 0.25
    p_match_correct: float = 0.85
    p_match_wrong: float = 0.15
    alpha: float = 0.01
    beta: float = 0.01
    step_length: float = 0.10
    axis_gate: float = float(np.deg2rad(15.0))
    lamp_match_fraction: float = 0.75
    twin_radius: float = 1.0
    twin_min_shift: float = 0.3
    max_self_similarity: float = 0.5
    early_decision: bool = True
    accept_without_evidence: bool = False


def predict_landmarks(
    pose: FloatArray, landmarks: FloatArray, body_t_camera: FloatArray, max_norm: float = 3.0
) -> FloatArray:
    """Normalised ceiling coordinates of the map's landmarks seen from ``pose``.

    Args:
        pose: (3,) estimated ``world_T_body`` (m, m, rad).
        landmarks: (L, 3) ceiling feature map points, world frame (m).
        body_t_camera: (3,) the ceiling camera's ``(x_off, y_off, z_cam)`` (m).
        max_norm: landmarks predicted farther than this from the image centre (in
            ``m`` units, i.e. outside any plausible field of view) are dropped.

    Returns:
        (L, 2) predicted ``m``; NaN rows for landmarks not higher than 0.1 m
        above the camera or beyond ``max_norm``.
    """
    out = np.full((len(landmarks), 2), np.nan)
    for i, p in enumerate(landmarks):
        if p[2] - body_t_camera[2] <= MIN_HEIGHT:
            continue
        m, _, _ = project_point(pose, p, body_t_camera)
        if np.hypot(m[0], m[1]) <= max_norm:
            out[i] = m
    return out


def self_similarity(xy: FloatArray, gate: float, radius: float, min_shift: float) -> float:
    """Worst-case fraction of map features that a shifted copy of the map matches.

    The twins of a pose are the poses shifted by a vector ``t`` with
    ``min_shift <= |t| <= radius``; a feature of a kind discriminates between a
    pose and its twins only when the kind's map does not match itself after
    such a shift. The candidate shifts are the differences between pairs of
    features (only they can bring a feature onto another), rounded to
    ``gate / 2``; for each, the fraction of features with a feature of the same
    kind within ``gate`` after the shift. A tile lattice of pitch ``a <= radius``
    gives about 1 (interior corners), lamps spaced by more than ``radius`` give 0.

    Args:
        xy: (N, 2) the kind's feature positions on the ceiling, world frame (m).
        gate: match radius on the ceiling (m).
        radius: longest twin shift (m).
        min_shift: shortest twin shift (m).

    Returns:
        The largest matched fraction over the twin shifts, in [0, 1]; 0 for
        fewer than two features.
    """
    from scipy.spatial import cKDTree

    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if len(xy) < 2:
        return 0.0
    tree = cKDTree(xy)
    pairs = tree.query_pairs(radius + gate, output_type="ndarray")
    if len(pairs) == 0:
        return 0.0
    d = xy[pairs[:, 1]] - xy[pairs[:, 0]]
    d = np.vstack([d, -d])
    q = max(gate / 2.0, 1e-6)
    shifts = np.unique(np.round(d / q), axis=0) * q
    n = np.hypot(shifts[:, 0], shifts[:, 1])
    shifts = shifts[(n >= min_shift) & (n <= radius)]
    best = 0.0
    for t in shifts:
        dist, _ = tree.query(xy + t, distance_upper_bound=gate)
        best = max(best, float(np.mean(np.isfinite(dist))))
    return best


def observed_points(frame: CeilingFrame) -> FloatArray:
    """All feature positions of a ceiling frame (lamps, then corners).

    Args:
        frame: the frontend's frame.

    Returns:
        (K, 2) normalised ceiling coordinates.
    """
    ms = [o.m for o in frame.lamps] + [o.m for o in frame.corners]
    return np.array(ms, dtype=float).reshape(-1, 2)


def frame_match(
    observed: FloatArray,
    predicted: FloatArray,
    gate: float,
    observed_axis: FloatArray | None = None,
    predicted_axis: FloatArray | None = None,
    axis_gate: float = np.pi,
) -> tuple[int, int]:
    """Count the observed features with a predicted landmark within ``gate``.

    Args:
        observed: (K, 2) observed ``m``; non-finite rows are ignored.
        predicted: (P, 2) predicted ``m`` at the estimated pose; NaN rows never match.
        gate: Euclidean gate in ``m`` units.
        observed_axis: (K,) observed lamp axes (rad, mod pi), NaN = none.
        predicted_axis: (P,) predicted image axes ``wrap_axis(phi - theta)``, NaN = none.
        axis_gate: when both axes are known they must agree within this (rad, mod pi).

    Returns:
        (n_matched, n_observed).
    """
    observed = np.asarray(observed, dtype=float).reshape(-1, 2)
    keep = np.all(np.isfinite(observed), axis=1)
    observed = observed[keep]
    if len(observed) == 0:
        return 0, 0
    predicted = np.asarray(predicted, dtype=float).reshape(-1, 2)
    if len(predicted) == 0:
        return 0, len(observed)
    d = np.linalg.norm(observed[:, None, :] - predicted[None, :, :], axis=2)
    ok = np.nan_to_num(d, nan=np.inf) <= gate
    if observed_axis is not None and predicted_axis is not None:
        oa = np.asarray(observed_axis, dtype=float).reshape(-1)[keep]
        pa = np.asarray(predicted_axis, dtype=float).reshape(-1)
        da = np.abs(np.asarray(wrap_axis(oa[:, None] - pa[None, :])))
        ok &= ~(np.isfinite(da) & (da > axis_gate))
    return int(np.count_nonzero(ok.any(axis=1))), len(observed)


def frame_outcome(n_matched: int, n_observed: int, config: VerificationConfig) -> bool | None:
    """Match (True), no match (False) or no evidence (None) for one frame."""
    if n_observed == 0:
        return None
    return n_matched >= config.min_match_fraction * n_observed


class RlocVerifier:
    """The paper's verifier: ``R_loc = 1 - d_fail / d`` (eq. 10).

    Feed it each frame's outcome with the distance driven since the previous
    frame. The distance is attributed to the frame's outcome.

    Args:
        config: thresholds.
    """

    def __init__(self, config: VerificationConfig) -> None:
        self.config = config
        self.d = 0.0
        self.d_fail = 0.0
        self.verdict = Verdict.PENDING
        self._window: deque[tuple[float, bool]] = deque()

    @property
    def r_loc(self) -> float:
        """``1 - d_fail / d`` over the last ``verify_distance`` metres (1.0 before any)."""
        return 1.0 - self.d_fail / self.d if self.d > 0 else 1.0

    def update(self, ds: float, outcome: bool | None) -> Verdict:
        """Add one frame.

        Args:
            ds: distance driven since the previous frame (m, >= 0).
            outcome: :func:`frame_outcome` of this frame.

        Returns:
            The verdict after this frame.
        """
        if not (ds >= 0.0 and np.isfinite(ds)):
            raise VerificationError(f"distance increment must be finite and >= 0, got {ds}")
        if outcome is None or ds == 0.0:
            return self.verdict
        self._window.append((ds, not outcome))
        self.d += ds
        self.d_fail += ds if not outcome else 0.0
        # keep a sliding window of verify_distance
        while self._window and self.d - self._window[0][0] >= self.config.verify_distance:
            old_ds, old_fail = self._window.popleft()
            self.d -= old_ds
            self.d_fail -= old_ds if old_fail else 0.0
        c = self.config
        if c.early_decision and self.verdict is Verdict.PENDING:
            # The verdict at d = verify_distance is already certain (see VerificationConfig).
            if self.d_fail > (1.0 - c.r_loc_threshold) * c.verify_distance + 1e-9:
                self.verdict = Verdict.FAILED
                return self.verdict
            if self.d - self.d_fail >= c.r_loc_threshold * c.verify_distance - 1e-9:
                self.verdict = Verdict.ACCEPTED
                return self.verdict
        if self.d >= self.config.verify_distance - 1e-9 or self.verdict is Verdict.ACCEPTED:
            if self.r_loc < self.config.r_loc_threshold:
                self.verdict = Verdict.FAILED
            elif self.d >= self.config.verify_distance - 1e-9 and self.verdict is Verdict.PENDING:
                self.verdict = Verdict.ACCEPTED
        return self.verdict


class SequentialVerifier:
    """Ours: Wald's SPRT on the per-frame outcomes, then CUSUM monitoring.

    The statistic ``S`` is the log-likelihood ratio of "pose wrong" (H1) over
    "pose right" (H0), each frame contributing ``w * log(P(o | H1) / P(o | H0))``
    with ``w = ds / step_length``. Wald's bounds: failure when
    ``S >= log((1 - beta) / alpha)``, acceptance when ``S <= log(beta / (1 - alpha))``.
    After acceptance ``S`` is clipped at 0 from below (CUSUM), so a later run of
    mismatches (kidnapping) raises the alarm after about the same distance.

    Args:
        config: thresholds.
    """

    def __init__(self, config: VerificationConfig) -> None:
        self.config = config
        c = config
        self.upper = float(np.log((1.0 - c.beta) / c.alpha))
        self.lower = float(np.log(c.beta / (1.0 - c.alpha)))
        self.llr_match = float(np.log(c.p_match_wrong / c.p_match_correct))
        self.llr_fail = float(np.log((1.0 - c.p_match_wrong) / (1.0 - c.p_match_correct)))
        self.S = 0.0
        self.d = 0.0
        self.verdict = Verdict.PENDING
        self.d_decided: float | None = None

    def update(self, ds: float, outcome: bool | None) -> Verdict:
        """Add one frame (same arguments as :meth:`RlocVerifier.update`).

        Returns:
            The verdict after this frame; FAILED is final until :meth:`reset`.
        """
        if not (ds >= 0.0 and np.isfinite(ds)):
            raise VerificationError(f"distance increment must be finite and >= 0, got {ds}")
        if outcome is None or self.verdict is Verdict.FAILED:
            return self.verdict
        self.d += ds
        w = ds / self.config.step_length
        self.S += w * (self.llr_match if outcome else self.llr_fail)
        if self.verdict is Verdict.ACCEPTED:
            self.S = max(self.S, 0.0)
        if self.S >= self.upper:
            self.verdict = Verdict.FAILED
            self.d_decided = self.d
            log.info("sequential verification: failure after %.2f m", self.d)
        elif self.S <= self.lower and self.verdict is Verdict.PENDING:
            self.verdict = Verdict.ACCEPTED
            self.d_decided = self.d
            self.S = 0.0
            log.info("sequential verification: accepted after %.2f m", self.d)
        return self.verdict

    def reset(self) -> None:
        """Start over (after a restart of the localization)."""
        self.S = 0.0
        self.d = 0.0
        self.verdict = Verdict.PENDING
        self.d_decided = None


class CeilingChecker:
    """Per-frame ceiling test at an estimated pose against a ceiling feature map.

    Lamps and corners are matched within their own kind when the kinds are
    known: a frame that sees lamps must match at least ``lamp_match_fraction``
    of them and, separately, ``min_match_fraction`` of its corners. A kind
    votes only when it can tell a pose from its twins: a tiled ceiling's
    corners form a periodic lattice that a pose off by one tile matches as
    well (:func:`self_similarity` above ``max_self_similarity``), so they carry
    no evidence and a frame that sees only them is no evidence (None).

    Args:
        landmarks: (L, 3) ceiling feature map points, world frame (m).
        body_t_camera: (3,) ceiling camera offset and height (m).
        config: gate and fraction.
        is_lamp: (L,) bool, which landmarks are lamps; None = kinds unknown
            (all features are matched against all landmarks).
        phi: (L,) lamps' long axes in the world (rad, mod pi), NaN = no axis;
            None = axes not checked.
        in_view: maps predicted ``m`` (N, 2) to (N,) bool "well inside the
            image"; when given (and kinds are known), every map lamp predicted
            in view must also be observed (a lamp is too large to miss): a frame
            whose observations all match but which misses the map's lamps fails
            too. Without it only the observed features are checked, and a tiled
            ceiling's corner lattice alone can accept a pose turned by 90 deg.
    """

    def __init__(
        self,
        landmarks: FloatArray,
        body_t_camera: FloatArray,
        config: VerificationConfig,
        is_lamp: BoolArray | None = None,
        phi: FloatArray | None = None,
        in_view: Callable[[FloatArray], BoolArray] | None = None,
    ) -> None:
        self.landmarks = np.asarray(landmarks, dtype=float).reshape(-1, 3)
        if not np.all(np.isfinite(self.landmarks)):
            raise VerificationError("ceiling feature map contains NaN or inf")
        self.body_t_camera = np.asarray(body_t_camera, dtype=float).reshape(3)
        self.config = config
        self.is_lamp = None if is_lamp is None else np.asarray(is_lamp, dtype=bool).reshape(-1)
        if self.is_lamp is not None and len(self.is_lamp) != len(self.landmarks):
            raise VerificationError("is_lamp and the ceiling landmarks differ in length")
        self.phi = None if phi is None else np.asarray(phi, dtype=float).reshape(-1)
        self.in_view = in_view
        if self.phi is not None and len(self.phi) != len(self.landmarks):
            raise VerificationError("phi and the ceiling landmarks differ in length")
        self.votes = {True: True, False: True}
        if self.is_lamp is not None and len(self.landmarks):
            h = float(np.median(self.landmarks[:, 2])) - float(self.body_t_camera[2])
            gate_m = config.gate * max(h, MIN_HEIGHT)
            for kind in (True, False):
                xy = self.landmarks[self.is_lamp == kind, :2]
                sim = self_similarity(xy, gate_m, config.twin_radius, config.twin_min_shift)
                self.votes[kind] = sim <= config.max_self_similarity
                log.info(
                    "ceiling %s: self-similarity under twin shifts %.2f -> %s",
                    "lamps" if kind else "corners",
                    sim,
                    "vote" if self.votes[kind] else "do not vote (periodic)",
                )

    def outcome(
        self,
        pose: FloatArray,
        observed: FloatArray,
        observed_is_lamp: BoolArray | None = None,
        observed_axis: FloatArray | None = None,
    ) -> bool | None:
        """Match / no match / no evidence for one frame.

        Args:
            pose: (3,) estimated ``world_T_body``.
            observed: (K, 2) observed ``m`` (lamps and corners).
            observed_is_lamp: (K,) bool kinds of the observations, or None.
            observed_axis: (K,) observed lamp axes in the image (rad, mod pi),
                NaN for none, or None.

        Returns:
            True (match), False (no match) or None (nothing observed).
        """
        observed = np.asarray(observed, dtype=float).reshape(-1, 2)
        pose = np.asarray(pose, dtype=float)
        if len(observed) == 0:
            if self.in_view is None or self.is_lamp is None:
                return None
            pred = predict_landmarks(pose, self.landmarks, self.body_t_camera)
            return None if self._lamps_seen(pred, observed) else False
        k = len(observed)
        oa = None if observed_axis is None else np.asarray(observed_axis, float).reshape(k)
        pa = None if self.phi is None else np.asarray(wrap_axis(self.phi - pose[2]))
        pred = predict_landmarks(pose, self.landmarks, self.body_t_camera)
        gate, agate = self.config.gate, self.config.axis_gate
        if self.is_lamp is None or observed_is_lamp is None:
            return frame_outcome(*frame_match(observed, pred, gate, oa, pa, agate), self.config)
        kinds = np.asarray(observed_is_lamp, dtype=bool).reshape(-1)
        if self.in_view is not None and not self._lamps_seen(pred, observed[kinds]):
            return False
        result: bool | None = None
        for kind in (True, False):
            sel, lm = kinds == kind, self.is_lamp == kind
            if not sel.any() or not self.votes[kind]:
                continue
            n_ok, n = frame_match(
                observed[sel], pred[lm], gate,
                None if oa is None else oa[sel], None if pa is None else pa[lm], agate,
            )  # fmt: skip
            need = self.config.lamp_match_fraction if kind else self.config.min_match_fraction
            if n_ok < need * n:
                return False
            result = True
        return result

    def _lamps_seen(self, pred: FloatArray, observed_lamps: FloatArray) -> bool:
        """Whether enough of the map lamps predicted well inside the image were observed."""
        assert self.in_view is not None and self.is_lamp is not None
        lamps = pred[self.is_lamp]
        lamps = lamps[np.all(np.isfinite(lamps), axis=1)]
        if len(lamps) == 0:
            return True
        lamps = lamps[np.asarray(self.in_view(lamps), dtype=bool)]
        if len(lamps) == 0:
            return True
        n_seen, n = frame_match(lamps, observed_lamps, self.config.gate)
        return n_seen >= self.config.lamp_match_fraction * n


def refine_pose(
    pose: FloatArray,
    observed: FloatArray,
    observed_is_lamp: BoolArray,
    landmarks: FloatArray,
    is_lamp: BoolArray,
    body_t_camera: FloatArray,
    gates: tuple[float, float] = (0.25, 0.08),
    iterations: int = 3,
) -> tuple[FloatArray, int]:
    """Correct a pose with one ceiling frame: match, align in 2-D, repeat (ours).

    Each observed feature ``m`` of a landmark at height ``h`` above the camera
    lies at ``q = h m + o_xy`` in the body frame (the inverse of
    :func:`lampsam.factors.ceiling.project_point`); the pose that maps the
    matched ``q`` onto the landmarks' ``(x, y)`` is the 2-D rigid alignment
    (:func:`lampsam.factors.geometry.rigid_fit_2d`). Matches are nearest predicted landmarks of the same
    kind within ``gates`` (lamps, corners; normalised units): the lamp gate is
    wide (lamps are sparse), the corner gate below half a tile (a corner
    lattice matches the wrong corner beyond that).

    Args:
        pose: (3,) initial ``world_T_body``.
        observed: (K, 2) observed ``m``.
        observed_is_lamp: (K,) kinds.
        landmarks: (L, 3) ceiling map, world (m).
        is_lamp: (L,) kinds.
        body_t_camera: (3,) camera offset and height (m).
        gates: match gates for lamps and corners.
        iterations: match-align rounds.

    Returns:
        The refined pose (3,) and the number of lamps matched in the last
        round (the pose is returned unchanged when fewer than 2 lamps match).
    """
    pose = np.asarray(pose, dtype=float).copy()
    observed = np.asarray(observed, dtype=float).reshape(-1, 2)
    kinds = np.asarray(observed_is_lamp, dtype=bool).reshape(-1)
    n_lamps = 0
    for _ in range(iterations):
        pred = predict_landmarks(pose, landmarks, body_t_camera)
        src, dst = [], []
        n_lamps = 0
        for kind, gate in ((True, gates[0]), (False, gates[1])):
            obs_k = observed[kinds == kind]
            idx = np.nonzero((is_lamp == kind) & np.all(np.isfinite(pred), axis=1))[0]
            if len(obs_k) == 0 or len(idx) == 0:
                continue
            dist = np.linalg.norm(obs_k[:, None, :] - pred[idx][None, :, :], axis=2)
            j = np.argmin(dist, axis=1)
            ok = dist[np.arange(len(obs_k)), j] <= gate
            lm = landmarks[idx[j[ok]]]
            h = lm[:, 2] - body_t_camera[2]
            src.append(obs_k[ok] * h[:, None] + body_t_camera[:2])
            dst.append(lm[:, :2])
            if kind:
                n_lamps = int(ok.sum())
        if n_lamps < 2:
            return pose, n_lamps
        pose = rigid_fit_2d(np.vstack(src), np.vstack(dst))
    return pose, n_lamps
