"""The verification stage: drive on and test the pose on the ceiling (paper 2, sec. 4.2).

While the robot drives on, each ceiling frame's lamps and corners are matched
against the ceiling feature map predicted at the dead-reckoned estimate
(:class:`~lampsam.localization.verification.CeilingChecker`), and the
verifier (the paper's ``R_loc``, eq. 10, or the sequential test) accepts or
rejects the pose.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from lampsam.arrays import BoolArray, FloatArray
from lampsam.datasets.steerable_robot import PixelCamera
from lampsam.factors.geometry import between, compose
from lampsam.localization.filter_config import GlobalLocalizerConfig
from lampsam.localization.map_layers import EnvironmentMaps
from lampsam.localization.robot import Robot
from lampsam.localization.verification import (
    CeilingChecker,
    RlocVerifier,
    SequentialVerifier,
    Verdict,
    refine_pose,
)

log = logging.getLogger(__name__)


def image_interior(
    camera: PixelCamera, margin_px: float = 15.0
) -> Callable[[FloatArray], BoolArray]:
    """``m (N, 2) -> (N,) bool``: inside the camera's image by ``margin_px`` pixels."""

    def in_view(m: FloatArray) -> BoolArray:
        px = np.asarray(camera.pixels_from_normalized(np.asarray(m, dtype=float).reshape(-1, 2)))
        w, h = float(camera.width), float(camera.height)
        return (
            (px[:, 0] >= margin_px) & (px[:, 0] <= w - 1 - margin_px)
            & (px[:, 1] >= margin_px) & (px[:, 1] <= h - 1 - margin_px)
        )  # fmt: skip

    return in_view


def verify_stage(
    robot: Robot,
    pose_end: FloatArray,
    odom_end: FloatArray,
    maps: EnvironmentMaps,
    config: GlobalLocalizerConfig,
    monitoring: bool = False,
) -> tuple[Verdict, float, float, FloatArray, FloatArray, float, float]:
    """Drive on and verify the pose with the ceiling features.

    Args:
        robot: the robot, driven ``config.drive_step`` at a time.
        pose_end: (3,) the estimate at the start of the drive (world, m, m, rad).
        odom_end: (3,) the odometry reading that goes with it.
        maps: the map layers (ceiling layer and camera).
        config: the (resolved) configuration.
        monitoring: start the sequential verifier as already accepted (CUSUM),
            for re-checking a pose localized earlier (kidnapping).

    Returns:
        verdict, R_loc (NaN for the sequential test), distance driven, the pose
        at the end of the drive (3,), the odometry there (3,), robot seconds,
        compute seconds.
    """
    vc = config.verification
    checker = CeilingChecker(
        maps.ceiling_xyz,
        maps.ceiling_body_t_camera,
        vc,
        is_lamp=maps.ceiling_is_lamp,
        phi=maps.ceiling_phi,
        in_view=None if maps.ceiling_camera is None else image_interior(maps.ceiling_camera),
    )
    verifier: RlocVerifier | SequentialVerifier
    verifier = RlocVerifier(vc) if config.verifier == "r_loc" else SequentialVerifier(vc)
    if monitoring and isinstance(verifier, SequentialVerifier):
        verifier.verdict = Verdict.ACCEPTED
    prev = np.asarray(odom_end, dtype=float)
    pose = np.asarray(pose_end, dtype=float)
    refine = bool(config.refine_with_ceiling) and not monitoring
    refine &= maps.ceiling_is_lamp is not None
    d = 0.0
    robot_s = 0.0
    compute = 0.0
    verdict = Verdict.PENDING
    evidence = False
    target = (
        vc.verify_distance if isinstance(verifier, RlocVerifier) else config.max_verify_distance
    )
    while d < target - 1e-9:
        frames = robot.drive(min(config.drive_step, target - d))
        if not frames:
            break
        t0 = time.perf_counter()
        robot_s += float(frames[-1].t - frames[0].t) + (
            frames[1].t - frames[0].t if len(frames) > 1 else 0.0
        )
        for f in frames:
            delta = between(prev, np.asarray(f.odom, dtype=float))
            prev = np.asarray(f.odom, dtype=float)
            pose = compose(pose, delta)
            ds = float(np.hypot(delta[0], delta[1]))
            d += ds
            if refine and f.ceiling_is_lamp is not None and np.sum(f.ceiling_is_lamp) >= 2:
                assert maps.ceiling_is_lamp is not None
                fixed, n_l = refine_pose(
                    pose, f.ceiling_m, f.ceiling_is_lamp, maps.ceiling_xyz,
                    maps.ceiling_is_lamp, maps.ceiling_body_t_camera,
                )  # fmt: skip
                if n_l >= 2:
                    refine = False
                    step = between(pose, fixed)
                    if (
                        np.hypot(step[0], step[1]) <= config.max_refine[0]
                        and abs(step[2]) <= config.max_refine[1]
                    ):
                        log.info("ceiling refinement: %.2f m, %.1f deg", np.hypot(*step[:2]),
                                 np.rad2deg(step[2]))  # fmt: skip
                        pose = fixed
            outcome = checker.outcome(pose, f.ceiling_m, f.ceiling_is_lamp, f.ceiling_axis)
            evidence |= outcome is not None
            verdict = verifier.update(ds, outcome)
        compute += time.perf_counter() - t0
        if verdict is Verdict.FAILED:
            break
        if verdict is Verdict.ACCEPTED and not monitoring:
            # the sequential test, and the paper's R_loc with early_decision,
            # accept before the full distance; without it R_loc drives it all
            if isinstance(verifier, SequentialVerifier) or vc.early_decision or d >= target - 1e-9:
                break
    if verdict is Verdict.PENDING:
        if not evidence and vc.accept_without_evidence:
            log.warning("no discriminating ceiling feature while verifying: accepted unverified")
            verdict = Verdict.ACCEPTED
        else:
            if not evidence:
                log.warning("no discriminating ceiling feature while verifying: starting over")
            verdict = Verdict.FAILED
    r_loc = verifier.r_loc if isinstance(verifier, RlocVerifier) else float("nan")
    return verdict, r_loc, d, pose, prev, robot_s, compute
