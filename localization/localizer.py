"""Global localization on the environment map (paper 2, secs. 3-4, Fig. 11).

For a robot at an unknown pose, :func:`localize` repeats, up to
``max_restarts`` times:

1. **turn in place** (30 deg/s, one full turn): SIFT pose candidates and the
   360-beam virtual scan (:func:`~lampsam.localization.stages.turn_stage`);
2. **particle filter** on the grid map until the particles' spread falls below
   a bound (:func:`~lampsam.localization.stages.filter_stage`);
3. **verification** while driving on: the ceiling features seen must match the
   ceiling feature map at the estimate (``R_loc``, eq. 10;
   :func:`~lampsam.localization.verify_drive.verify_stage`); on failure, start
   over.

The robot is reached through the :class:`~lampsam.localization.robot.Robot`
protocol, so the same pipeline runs on a simulator
(:class:`lampsam.datasets.steerable_robot.SimulatedRobot`, the tests) and on a
logged run replayed in order (:mod:`lampsam.localization.replay`).
Configurations (paper Table 1, plus ours):
:class:`~lampsam.localization.filter_config.Mode`.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.localization.acceptance import mode_margin
from lampsam.localization.filter_config import GlobalLocalizerConfig
from lampsam.localization.map_layers import EnvironmentMaps
from lampsam.localization.open_space import face_open_space
from lampsam.localization.result import AttemptRecord, LocalizationResult, Status
from lampsam.localization.robot import Robot
from lampsam.localization.stages import (
    KeptScan,
    filter_stage,
    mode_estimate,
    scan_model,
    turn_stage,
)
from lampsam.localization.symmetry import half_turn_centre, half_turn_twin, resolve_half_turn
from lampsam.localization.verification import Verdict
from lampsam.localization.verify_drive import verify_stage
from lampsam.localization.virtual_scan import beam_angles
from lampsam.observe import emit

log = logging.getLogger(__name__)


def localize(
    robot: Robot,
    maps: EnvironmentMaps,
    config: GlobalLocalizerConfig,
    rng: np.random.Generator,
    initial: LocalizationResult | None = None,
) -> LocalizationResult:
    """Run global localization (Fig. 11 of paper 2): turn, filter, verify, restart.

    Args:
        robot: the robot (or simulator / replay), see :class:`Robot`.
        maps: the environment map layers.
        config: the configuration (``config.mode`` picks the Table-1 row).
        rng: generator for RANSAC, particles and resampling.
        initial: a previous result to re-check first, by driving on from its
            pose and odometry (monitoring after convergence: after a kidnapping
            this check fails and the pipeline starts over). Ignored by the
            configurations without verification.

    Returns:
        The :class:`LocalizationResult` (pose in the world frame at the end of
        the last drive). ``restarts`` counts the attempts after the first,
        including the re-check of ``initial``.
    """
    config = config.resolved()
    model = scan_model(maps, config)
    emit("localize.start", grid=maps.grid)
    robot_time = {"turn": 0.0, "verification": 0.0}
    compute_time = {"candidates": 0.0, "filter": 0.0, "verification": 0.0}
    attempts: list[AttemptRecord] = []
    pose, odom = np.zeros(3), np.zeros(3)
    cov = np.full((3, 3), np.nan)
    success = False
    verifies = config.verifies
    fc = config.filter
    keep = verifies and fc.keep_scans_on_restart
    twin_centre = None
    if fc.twin_margin and len(maps.ceiling_xyz) >= 2:
        lamps = (
            np.ones(len(maps.ceiling_xyz), bool)
            if maps.ceiling_is_lamp is None
            else np.asarray(maps.ceiling_is_lamp, bool)
        )
        twin_centre = half_turn_centre(
            maps.ceiling_xyz[lamps, :2],
            None if maps.ceiling_phi is None else np.asarray(maps.ceiling_phi)[lamps],
        )
        if twin_centre is not None:
            log.info("the ceiling map is half-turn symmetric about (%.2f, %.2f)", *twin_centre)
    kept: list[KeptScan] = []
    status: Status = "failed"
    modes: list[FloatArray] = []
    evidence: dict[str, float | str | bool] = {"mode": config.mode.value}
    if initial is not None and verifies:
        verdict, r_loc, d, pose, odom, rs, cs = verify_stage(
            robot, initial.pose, initial.odom, maps, config, monitoring=True
        )
        robot_time["verification"] += rs
        compute_time["verification"] += cs
        cov = np.asarray(initial.covariance)
        attempts.append(
            AttemptRecord(0, 0, True, verdict.value, r_loc, d, [float(v) for v in pose])
        )
        success = verdict is Verdict.ACCEPTED
        status = "localized" if success else "failed"
        if not success:
            log.info("re-check of the earlier pose failed (kidnapped?): starting over")
    for attempt in range(config.max_restarts + 1):
        if success:
            break
        turned = turn_stage(robot, maps, config, rng, required=attempt == 0 and not attempts)
        if turned is None:
            log.info("the robot returned no frame while turning: stopping after %d attempts",
                     len(attempts))  # fmt: skip
            break
        cands, scan, odom, rs, cs = turned
        odom_turn = odom
        robot_time["turn"] += rs
        compute_time["candidates"] += cs
        t0 = time.perf_counter()
        pf, n_upd, converged, first_modes = filter_stage(
            cands, scan, model, maps, config, rng, kept if keep else (), odom
        )
        pose = mode_estimate(pf.particles, pf.log_weights)
        _, cov = pf.estimate()
        ambiguous = False
        modes = []
        if twin_centre is not None and not cands:
            pose, margin = resolve_half_turn(pose, scan, twin_centre, maps, config, rng)
            ambiguous = margin < (fc.twin_margin or 0.0)
            modes = [pose, half_turn_twin(pose, twin_centre)]
            evidence["twin_margin"] = margin
        if not verifies:
            mm = mode_margin(pose, first_modes, scan, maps, config, rng)
            evidence.update(mode_margin=mm.margin, scan_score=mm.score, converged=converged)
            if not converged:
                status = "failed"
            elif mm.margin >= config.accept_margin:
                status = "localized"
            else:
                status = "ambiguous"
                modes = [pose] + ([] if mm.competitor is None else [mm.competitor])
        compute_time["filter"] += time.perf_counter() - t0
        emit("localize.estimate", pose=pose, attempt=attempt)
        if not verifies:
            attempts.append(
                AttemptRecord(
                    len(cands),
                    n_upd,
                    converged,
                    Verdict.ACCEPTED.value,
                    float("nan"),
                    0.0,
                    [float(v) for v in pose],
                )
            )
            success = True
            break
        if config.head_for_open_space:
            pose, odom = face_open_space(robot, scan, pose, odom, config, robot_time)
        if ambiguous:
            verdict, r_loc, d = Verdict.FAILED, float("nan"), 0.0
            log.info("the scan cannot tell the estimate from its half-turn twin: not verified")
        else:
            verdict, r_loc, d, pose, odom, rs, cs = verify_stage(robot, pose, odom, maps, config)
            robot_time["verification"] += rs
            compute_time["verification"] += cs
        attempts.append(
            AttemptRecord(
                len(cands), n_upd, converged, verdict.value, r_loc, d, [float(v) for v in pose]
            )
        )
        success = verdict is Verdict.ACCEPTED
        evidence.update(verdict=verdict.value, r_loc=r_loc, verify_distance=d)
        status = "localized" if success else "ambiguous" if ambiguous else "failed"
        if not success:
            log.info("attempt %d failed verification (R_loc %.2f): starting over", attempt, r_loc)
            kept.append(KeptScan(scan[:: fc.beam_step].copy(), beam_angles()[:: fc.beam_step],
                                 np.asarray(odom_turn, dtype=float).copy()))  # fmt: skip
            more = float(config.relocate_distance or 0.0) - d
            if not cands and more > 0 and attempt < config.max_restarts:
                frames = robot.drive(more)
                if frames:
                    robot_time["verification"] += float(frames[-1].t - frames[0].t)
                log.info("no candidate in this turn: drove %.2f m on before turning again", more)
    return LocalizationResult(
        success,
        pose,
        cov,
        config.mode.value,
        max(len(attempts) - 1, 0),
        robot_time,
        compute_time,
        attempts,
        odom,
        status,
        [[float(v) for v in m] for m in modes] if status == "ambiguous" else [],
        evidence,
    )
