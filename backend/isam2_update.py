"""iSAM2 updates of a factor-graph backend, and recovery from a failed one.

One ``ISAM2.update`` per keyframe (Kaess et al. 2012, "iSAM2: Incremental smoothing
and mapping using the Bayes tree") with the keyframe's new factors and values. A
failed update is not fatal (:meth:`Isam2Updates._recover`, logged):

- an *ill-conditioned* clique (GTSAM's ``IndeterminantLinearSystemException`` on a
  graph whose every variable is constrained) is a numerical failure, not a bad
  measurement: iSAM2 is rebuilt from the whole graph with QR factorisation, nothing
  dropped (:func:`ill_conditioned`);
- any other failure (e.g. GTSAM's CheiralityException: a relinearised landmark below
  the camera) drops the offending measurements and rebuilds iSAM2 from the rest.

- a *diverging* Gauss-Newton step (iSAM2 takes undamped steps: on a graph made
  inconsistent by wrong associations or stiff ties the steps can grow without
  bound, the estimates swing by hundreds of metres at each relinearisation and
  a landmark seen once, which follows its pose's swings, runs off to infinity
  until the solve fails on it): after an update that relinearised, when the
  graph's error at the new estimate exceeds :data:`DIVERGENCE_RATIO` times its
  error at the linearisation point (plus :data:`DIVERGENCE_MARGIN`), the whole
  graph is solved by Levenberg-Marquardt (never raises the error) from the
  better of the two and iSAM2 is rebuilt there with Powell's dogleg steps (a
  trust region) for the rest of the run, nothing dropped
  (:meth:`Isam2Updates._damp_divergence`).

Why QR: GTSAM (4.3) factors each clique's frontal block ``A`` (the joint information
of its frontal variables) by Cholesky and refuses it when the reciprocal condition
number of the diagonally equilibrated block is under ``sqrt(eps)`` (1.5e-8).
Two consecutive keyframes in one clique have a joint information whose condition is
about (odometry information) / (absolute pose information): on Victoria Park without
ids (no loop closed for a while, the pose 10-16 m uncertain, odometry sigmas of
mm and mrad) it is 1.9e8 at keyframe 2,081 (docs/failures.md). QR works on the
square-root information (condition the square root: 1.4e4) and has no such test.
"""

from __future__ import annotations

import logging
import math
import re
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from lampsam.backend.ceiling import MIN_USABLE_HEIGHT
from lampsam.backend.ceiling_graph import point_key
from lampsam.backend.fixed_lag import keyframe_stamps, left_window, without_keys
from lampsam.backend.graph_state import GraphState
from lampsam.backend.handlers import value_at
from lampsam.backend.pose_cov import pose_array
from lampsam.errors import EstimationError

log = logging.getLogger(__name__)

#: A relinearising update whose estimate has more than this times the graph's error
#: at iSAM2's linearisation point (plus :data:`DIVERGENCE_MARGIN`) is a diverging
#: Gauss-Newton step. A converging step lowers the error (ratio under 1).
DIVERGENCE_RATIO = 2.0
#: ... plus this much error (half a chi-square sum): small graphs' noise.
DIVERGENCE_MARGIN = 100.0
#: The check evaluates the graph's error only when some variable's Gauss-Newton step
#: (iSAM2's delta from its linearisation point) is at least this large, in the
#: variables' own units (m, rad, 1/m for inverse depth): the diverging steps seen were
#: tens to hundreds of metres (docs/failures.md, "The loop's numerical failure"), while
#: a converging ceiling run's largest step is 0.1-0.55 (lab, seed 3). Two full error
#: evaluations per relinearisation cost 1.33x the 173 s lab run's CPU (tidy7,
#: docs/architecture.md); the step is read from iSAM2 at no extra cost.
DIVERGENCE_MIN_STEP = 1.0


class Isam2Updates(GraphState):
    """Sending a keyframe's factors to iSAM2 (mixin of :class:`~lampsam.backend.graph.GraphSlam`)."""

    def _flush(self) -> None:
        """Send the new factors and values to iSAM2 (one update)."""
        if self.isam is None:
            self._new_graph = gtsam.NonlinearFactorGraph()
            self._new_values = gtsam.Values()
            return
        t0 = time.perf_counter()
        self._pose_cache = {}
        try:
            relin = False
            if self.smoother is not None:
                self._fixed_lag_update()
                self._joint_at = {}  # (marginalisation relinearises: no bound across it)
            else:
                relin = self._relinearized(self.isam.update(self._new_graph, self._new_values))
            for _ in range(self.config.isam2.extra_updates):
                relin |= self._relinearized(self.isam.update())
            if relin and self.divergence_check and self.smoother is None:
                self._damp_divergence()
        except RuntimeError as exc:
            if not (ill_conditioned(exc) and self._refactor_qr(exc)):
                self._recover(exc)
        t1 = time.perf_counter()
        self._new_graph = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._update_factor_lids = []
        self._kf_pose = pose_array(self.isam.calculateEstimatePose2(X(self._k)))
        self._kf_cov_key = X(self._k)  # its marginal, when first read (GraphState._kf_cov)
        self.update_times.append(t1 - t0)
        self.estimate_times.append(time.perf_counter() - t1)

    def _relinearized(self, result: gtsam.ISAM2Result) -> bool:
        """Forget the gate's joint-marginal records when an update relinearised variables;
        whether it did.

        :meth:`~lampsam.backend.gate_shortcuts.LampGateShortcuts._bound_far` bounds an exact distance by
        an earlier joint marginal; that holds for one linearisation only (new
        Jacobians can widen a marginal).
        """
        if result.getVariablesRelinearized():
            self._joint_at = {}
            return True
        return False

    #: Check each relinearising update for a diverging Gauss-Newton step (module doc).
    divergence_check = True

    def _damp_divergence(self) -> bool:
        """After a relinearising update: when iSAM2's estimate has more error than its
        linearisation point (:data:`DIVERGENCE_RATIO`, :data:`DIVERGENCE_MARGIN`), or a
        non-finite one, solve the whole graph by Levenberg-Marquardt (``[batch]``'s
        parameters) from the lower-error of the two and rebuild iSAM2 from that
        solution with Powell's dogleg steps (``ISAM2DoglegParams``) for the rest of
        the run: on an inconsistent graph a Gauss-Newton step from near a minimum
        (LM stops at a small, not zero, gradient) can be huge again where the
        information is near singular. Nothing dropped; counted in ``n_damped``.
        Returns whether it did.

        Costs two error evaluations and one full estimate per relinearisation
        (every ``relinearize_skip`` updates) whose largest step is at least
        :data:`DIVERGENCE_MIN_STEP`; read only when the step converges.
        """
        assert self.isam is not None
        step = np.abs(self.isam.getDelta().vector())
        if step.size and float(step.max()) < DIVERGENCE_MIN_STEP:
            return False
        est, lin = self.isam.calculateEstimate(), self.isam.getLinearizationPoint()
        e_est, e_lin = self.graph.error(est), self.graph.error(lin)
        if math.isfinite(e_est) and e_est <= DIVERGENCE_RATIO * e_lin + DIVERGENCE_MARGIN:
            return False
        start = lin if not (math.isfinite(e_est) and e_est < e_lin) else est
        opt = gtsam.LevenbergMarquardtOptimizer(self.graph, start, self.config.batch.to_gtsam())
        values = opt.optimize()
        self.n_damped += 1
        isam = gtsam.ISAM2(self._isam2_params())
        isam.update(self.graph, values)  # (raises like any update: the caller recovers)
        log.warning("iSAM2 update at keyframe %d: the Gauss-Newton step raised the graph's "
                    "error %.4g -> %.4g; solved by Levenberg-Marquardt (%.4g, %d iterations) "
                    "and rebuilt there with dogleg steps for the rest of the run, no "
                    "measurement dropped", self._k, e_lin, e_est, opt.error(), opt.iterations())
        self.isam = isam
        self._forget_linearisation()
        return True

    def _fixed_lag_update(self) -> None:
        """One fixed-lag update (:mod:`lampsam.backend.fixed_lag`): keys stamped with the
        keyframe, lamps kept, factors on keys that already left dropped (a corner's
        pending sights from keyframes gone); then what left the window is dropped from
        the backend (a keyframe keeps its last estimate, a corner is forgotten)."""
        assert self.smoother is not None
        lamps = [key for lm in self._landmarks.values() if lm.kind == "lamp" and lm.in_graph
                 for key in self.handlers[lm.kind].keys(lm)]
        graph = without_keys(self._new_graph, self._fl_gone)
        stamps = keyframe_stamps(self._k, self._new_values, graph, lamps)
        self.smoother.update(graph, self._new_values, stamps)
        self._fl_alive.update(int(key) for key in stamps)
        gone = left_window(self.smoother, self._fl_alive)
        if gone:
            self._fl_alive -= gone
            self._fl_gone |= gone
            lids = set()
            for key in gone:
                sym = gtsam.Symbol(key)
                if sym.chr() == ord("x"):
                    k = int(sym.index())
                    if self._fl_last.exists(key):
                        self._kf_poses[k] = pose_array(self._fl_last.atPose2(key))
                    self._left_poses.add(k)
                else:
                    lids.add(int(sym.index()))
            for lid in lids & set(self._landmarks):
                if self._landmarks[lid].kind != "lamp":
                    del self._landmarks[lid]
                    self.pruned["left_window"] = self.pruned.get("left_window", 0) + 1
        self._fl_last = self.smoother.calculateEstimate()

    def _isam2_params(self) -> gtsam.ISAM2Params:
        """iSAM2 parameters for a rebuild: the backend's (``isam2_params``, with its
        per-symbol thresholds), switched to QR for good once a rebuild needed it, and
        to Powell's dogleg for good once a Gauss-Newton step diverged."""
        params = self.isam2_params
        if self.qr_factorization:
            params.setFactorization("QR")
        if self.n_damped:  # (Powell's dogleg: a trust region bounds each step)
            params.setOptimizationParams(gtsam.ISAM2DoglegParams())
        return params

    def _last_estimate(self) -> gtsam.Values:
        """iSAM2's estimate before a failed update; empty when it cannot give one."""
        try:
            return self.isam.calculateEstimate() if self.isam is not None else gtsam.Values()
        except RuntimeError:
            return gtsam.Values()

    def _rebuild_values(self, old: gtsam.Values, removed_keys: set[int]) -> gtsam.Values:
        """Start values for a rebuilt iSAM2: ``old`` (the last estimate) where it has
        the variable, else the initial value; ``removed_keys`` left out."""
        values = gtsam.Values()
        for key in self.initial.keys():
            if key in removed_keys:
                continue
            src = old if old.exists(key) else self.initial
            values.insert(key, value_at(src, key))
        return values

    def _refactor_qr(self, exc: RuntimeError) -> bool:
        """Rebuild iSAM2 from the whole graph (this update's factors included) with QR
        factorisation, for the rest of the run; nothing is dropped.

        Returns:
            True when the rebuild succeeded; False when it was already QR, a
            variable has no factor (a structural failure: :meth:`_recover` handles
            it), or the rebuild threw too.
        """
        if self.qr_factorization or self.smoother is not None:
            return False
        orphans = unconstrained_keys(self.graph, self.initial)
        if orphans:
            log.warning("iSAM2 update failed at keyframe %d with variables without factors "
                        "(%s)", self._k, ", ".join(gtsam.DefaultKeyFormatter(k) for k in orphans[:5]))
            return False
        values = self._rebuild_values(self._last_estimate(), set())
        self.qr_factorization = True
        isam = gtsam.ISAM2(self._isam2_params())
        try:
            isam.update(self.graph, values)
        except RuntimeError as exc2:
            log.warning("iSAM2 rebuild with QR failed at keyframe %d (%s)", self._k,
                        str(exc2).strip()[:120])
            return False
        log.warning("iSAM2 update at keyframe %d: ill-conditioned clique (%s); rebuilt with QR "
                    "factorisation for the rest of the run, no measurement dropped",
                    self._k, str(exc).strip().splitlines()[0][:100])
        self.isam = isam
        self._forget_linearisation()
        self.n_refactorized += 1
        return True

    def _forget_linearisation(self) -> None:
        """After a rebuild (new linearisation points): the cached joint and pose
        marginals, and the gate's bound records (:meth:`_relinearized`), no longer hold."""
        self._joint_cache = {}
        self._joint_at = {}
        self._pose_cache = {}

    def _recover(self, exc: RuntimeError) -> None:
        """Rebuild iSAM2 after a failed update, without the offending measurements.

        A failed ``update()`` (e.g. GTSAM's CheiralityException: a relinearised
        landmark below the camera) leaves iSAM2 in an unknown state. The landmark
        named in the message (else every landmark measured in this update) loses
        the factors added in this update; one that entered the graph in this update
        is removed altogether, and so is any ceiling landmark whose estimate is
        now below the camera (no usable linearisation point). A fresh iSAM2 is then
        built from the whole remaining graph, started from the last estimate (each
        removed landmark's factors go too). Logged as a warning.

        Raises:
            EstimationError: the rebuilt graph fails too.
        """
        if self.smoother is not None:  # rebuilt from the whole graph: full iSAM2 from here
            log.warning("fixed-lag smoother failed: continuing with full iSAM2")
            self.smoother = None
        # GTSAM names a landmark by its key: l<id> (lamps, planar points) or c<id> (corners)
        named = {int(m.group(1)) for m in re.finditer(r"\b[lc](\d+)\b", str(exc))}
        new_lids = {lid for _, lid in self._update_factor_lids}
        bad = (named & set(self._landmarks)) or new_lids
        drop_idx = {i for i, lid in self._update_factor_lids if lid in bad}
        entered = {lid for lid in bad if lid in self._landmarks and self._new_values.exists(
            self.handlers[self._landmarks[lid].kind].keys(self._landmarks[lid])[0])}
        old = self._last_estimate()
        if self.ceiling is not None:  # landmarks the failed step put under the lens
            z_min = float(self.ceiling.body_t_camera[2]) + MIN_USABLE_HEIGHT
            for lid, lm in self._landmarks.items():
                key = point_key(lm.kind, lid)
                if lm.in_graph and lm.kind in ("lamp", "corner") and old.exists(key):
                    if float(old.atPoint3(key)[2]) < z_min:
                        entered.add(lid)
        log.warning("iSAM2 update failed at keyframe %d (%s: %s): dropping this update's "
                    "factors of %d landmarks (%d removed) and rebuilding iSAM2",
                    self._k, type(exc).__name__, str(exc).strip()[:120], len(bad), len(entered))
        removed_keys: set[int] = set()
        for lid in entered:
            self._drop_failed(lid, removed_keys)
        graph = gtsam.NonlinearFactorGraph()
        for i in range(self.graph.size()):
            f = self.graph.at(i)
            if f is None or i in drop_idx or any(key in removed_keys for key in f.keys()):
                continue
            graph.add(f)
        # A rebuild never leaves a variable without a factor (an indeterminate system):
        # a landmark whose every factor went is removed with it.
        for key in unconstrained_keys(graph, self.initial):
            sym = gtsam.Symbol(key)
            lid = int(sym.index())
            if chr(sym.chr()) != "x" and lid in self._landmarks:
                self._drop_failed(lid, removed_keys)
            removed_keys.add(key)
        values = self._rebuild_values(old, removed_keys)
        initial = gtsam.Values()
        for key in self.initial.keys():
            if key not in removed_keys:
                initial.insert(key, value_at(self.initial, key))
        self.graph = graph
        self.initial = initial
        self.isam = gtsam.ISAM2(self._isam2_params())
        try:
            self.isam.update(graph, values)
        except RuntimeError as exc2:
            raise EstimationError(f"iSAM2 rebuild failed at keyframe {self._k}: "
                                  f"{type(exc2).__name__} {exc2}") from exc2
        self._forget_linearisation()
        self.n_recoveries += 1

    def _drop_failed(self, lid: int, removed_keys: set[int]) -> None:
        """Remove landmark ``lid`` for a rebuild (:meth:`_recover`): its keys join
        ``removed_keys``, and it counts as pruned (reason ``failed_update``)."""
        lm = self._landmarks.pop(lid)
        removed_keys.update(self.handlers[lm.kind].keys(lm))
        self.n_pruned += 1
        self.pruned["failed_update"] = self.pruned.get("failed_update", 0) + 1


def ill_conditioned(exc: RuntimeError) -> bool:
    """Whether a failed update is GTSAM's ``IndeterminantLinearSystemException``
    ("Indeterminate linear system detected while working near variable ..."): a
    clique that is singular or too poorly conditioned for Cholesky."""
    return "indeterminate linear system" in str(exc).lower() or (
        "indeterminant" in type(exc).__name__.lower())


def unconstrained_keys(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> list[int]:
    """Keys of ``values`` that no factor of ``graph`` involves (each makes the system
    indeterminate), in ``values``' order."""
    used = set(graph.keys())
    return [key for key in values.keys() if key not in used]
