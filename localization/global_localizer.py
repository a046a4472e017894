"""Global localization on the environment map (paper 2, secs. 3-4, Fig. 11).

The pipeline, for a robot at an unknown pose:

1. **Turn in place** (30 deg/s, one full turn): every Kinect frame's SIFT
   features give a pose candidate (:mod:`.candidates`, eqs. 1-7), earlier
   candidates are carried along with the turn, and the depth is accumulated in
   the 360-beam virtual scan (:mod:`.virtual_scan`).
2. **Particle filter** on the grid map (:mod:`.particle_filter`): the same
   number of particles in each candidate (or particles everywhere when there
   are no candidates / the configuration says so), updated with the virtual
   scan until the particles' spread falls below a bound.
3. **Verification** while driving on (:mod:`.verification`): the ceiling
   features seen must match the ceiling feature map at the estimated pose
   (``R_loc``, eq. 10, or our sequential test); on failure, start over.

The robot is reached through the :class:`Robot` protocol (turn, drive, each
returning the frames recorded meanwhile), so the same pipeline runs on a
simulator (``scripts/table1_experiment.py``, the tests) and on a logged run
replayed in order (the ``localize`` subcommand).

Configurations (paper Table 1, plus ours): :class:`Mode`.
"""

from __future__ import annotations

import enum
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Protocol

import numpy as np

from lampsam.arrays import BoolArray, FloatArray
from lampsam.errors import LocalizationError
from lampsam.factors.geometry import between, compose, wrap_angle
from lampsam.localization.candidates import (
    CandidateCollector,
    CandidateConfig,
    PoseCandidate,
    pf_candidates,
)
from lampsam.localization.grid import OccupancyGrid, occupied_mask
from lampsam.localization.likelihood import BeamModelConfig, LikelihoodFieldModel, RayCastModel
from lampsam.localization.particle_filter import (
    KldConfig,
    ParticleFilter,
    ParticleFilterConfig,
    normalise_log_weights,
    sample_candidate_discs,
    sample_free_space,
)
from lampsam.localization.raycast import RangeTable
from lampsam.localization.verification import (
    CeilingChecker,
    RlocVerifier,
    SequentialVerifier,
    Verdict,
    VerificationConfig,
    refine_pose,
)
from lampsam.localization.virtual_scan import VirtualScan, VirtualScanConfig, beam_angles
from lampsam.observe import emit

if TYPE_CHECKING:
    from lampsam.localization.envmap import EnvironmentMap

log = logging.getLogger(__name__)


class GlobalLocalizationError(LocalizationError):
    """The pipeline cannot run (no usable data, bad configuration)."""


class Mode(enum.Enum):
    """The configurations of the paper's Table 1, plus ours.

    GRID_ONLY: particles everywhere in free space, no candidates, no verification.
    NO_CEILING: candidates + particle filter, no ceiling verification.
    PROPOSED: candidates + particle filter + ``R_loc`` verification (the paper).
    OURS: the proposed pipeline (ray casting by table, ``R_loc``), plus: an
        adaptive (KLD) sample size; after a turn without candidates, the
        estimate checked against its half-turn twin by the scan; the pose
        refined by the first ceiling frame with two lamps (2-D alignment to
        the ceiling map) before the frames are tested; after a failed attempt
        without candidates, driving on to 1.5 m before turning again.
        Earlier parts of ours (likelihood field, uniform particles beside the
        candidates, re-scoring distinct modes, the sequential verifier) are
        still available through :class:`FilterConfig` and
        :class:`GlobalLocalizerConfig`, off by default (docs/table1.md).
    """

    GRID_ONLY = "grid_only"
    NO_CEILING = "no_ceiling"
    PROPOSED = "proposed"
    OURS = "ours"


# ----------------------------------------------------------------------------- data
@dataclass(frozen=True)
class TurnFrame:
    """One Kinect frame recorded while turning in place.

    Attributes:
        t: time (s, the robot's clock).
        odom: (3,) ``odom_T_body`` from wheel odometry (m, m, rad).
        sift_points: (N, 3) SIFT keypoints with valid depth, body frame (m).
        sift_descriptors: (N, 128) float32 descriptors.
        depth_points: (P, 3) depth points, body frame (m), for the virtual scan.
    """

    t: float
    odom: FloatArray
    sift_points: FloatArray
    sift_descriptors: FloatArray
    depth_points: FloatArray


@dataclass(frozen=True)
class DriveFrame:
    """One ceiling-camera frame recorded while driving on.

    Attributes:
        t: time (s).
        odom: (3,) ``odom_T_body`` (m, m, rad).
        ceiling_m: (K, 2) observed ceiling features (lamps and corners) in
            normalised ceiling coordinates (conventions.md).
        ceiling_is_lamp: (K,) bool, which of them are lamps (None: unknown).
        ceiling_axis: (K,) lamps' long axes in the image (rad, mod pi, the
            frontend's ``LampObservation.axis``), NaN for none (None: unknown).
    """

    t: float
    odom: FloatArray
    ceiling_m: FloatArray
    ceiling_is_lamp: BoolArray | None = None
    ceiling_axis: FloatArray | None = None


class Robot(Protocol):
    """What the localizer asks of the robot (or of a simulator, or a log replay)."""

    def turn(self, angle: float, rate: float) -> Sequence[TurnFrame]:
        """Turn in place by ``angle`` (rad) at ``rate`` (rad/s); the frames recorded."""
        ...

    def drive(self, distance: float) -> Sequence[DriveFrame]:
        """Drive on for ``distance`` (m, along a collision-free path); the frames recorded."""
        ...


@dataclass(frozen=True)
class EnvironmentMaps:
    """The three layers of the environment map the localizer uses.

    Attributes:
        grid: the grid map (Kinect depth projected to the floor).
        spatial_xyz: (M, 3) spatial feature map points, world frame (m).
        spatial_descriptors: (M, 128) their SIFT descriptors.
        ceiling_xyz: (L, 3) ceiling feature map (lamps, corners), world (m).
        ceiling_body_t_camera: (3,) ceiling camera offset and height (m).
        ceiling_is_lamp: (L,) bool, which ceiling features are lamps (None: unknown).
        ceiling_phi: (L,) lamps' long axes in the world (rad, mod pi), NaN for
            none (None: axes not checked).
        ceiling_camera: the upward camera (``lampsam.datasets.logrun.CameraModel``):
            with it, map lamps predicted inside the image must be seen too.
    """

    grid: OccupancyGrid
    spatial_xyz: FloatArray
    spatial_descriptors: FloatArray
    ceiling_xyz: FloatArray
    ceiling_body_t_camera: FloatArray
    ceiling_is_lamp: BoolArray | None = None
    ceiling_phi: FloatArray | None = None
    ceiling_camera: Any = None

    @classmethod
    def from_env_map(
        cls, env: EnvironmentMap, body_t_camera: FloatArray, camera: Any = None
    ) -> EnvironmentMaps:
        """Adapt a loaded map directory (:func:`lampsam.localization.envmap.load_env_map`).

        Args:
            env: the map; a missing spatial or ceiling layer gives empty arrays
                (no candidates / no verification evidence).
            body_t_camera: (3,) the ceiling camera's mounting (from the run's rig).
            camera: the run's ``CameraModel`` (optional, see ``ceiling_camera``).
        """
        sp, ce = env.spatial, env.ceiling
        return cls(
            env.grid,
            np.zeros((0, 3)) if sp is None else np.asarray(sp.xyz, dtype=float),
            np.zeros((0, 128), np.float32) if sp is None else np.asarray(sp.descriptors),
            np.zeros((0, 3)) if ce is None else np.asarray(ce.xyz, dtype=float),
            np.asarray(body_t_camera, dtype=float).reshape(3),
            None if ce is None else np.asarray(ce.is_lamp(), dtype=bool),
            None if ce is None else np.asarray(ce.phi, dtype=float),
            camera,
        )


# ----------------------------------------------------------------------------- config
@dataclass(frozen=True)
class FilterConfig:
    """Particle filter settings of the localizer.

    Attributes:
        particles_per_candidate: particles in each candidate disc (paper: the
            same number in every candidate). Default 300.
        n_uniform: particles spread over the free space when there is no
            candidate (GRID_ONLY, or a turn without any). Default 20000.
        max_updates: measurement updates on the virtual scan before giving up.
            Default 15.
        beam: per-beam measurement model. Default sigma 0.15 m, 20 % random
            returns, 4.5 m (the Kinect's range), beams tempered by 0.2 (the 360
            beams of a virtual scan are far from independent).
        beam_step: use every ``beam_step``-th beam of the 360. Default 2.
        pf: the filter's own settings (convergence bounds: 0.05 m and 0.03 rad
            here; roughening between updates on the same scan: 5 cm, 0.03 rad).
            Before (0.10 m / 0.08 rad, 2 cm / 0.01 rad), a filter started over
            the whole free space converged onto the few particles nearest the
            truth and stopped with their bias (office trial 30: 10 cm, 6 deg
            off, then rejected by the ceiling verification); the stronger
            roughening lets the particles move towards the likelihood's peak and
            the tighter bounds wait for it (no-candidate turns of 16 office
            starts: estimates within 8 cm / 2.5 deg from 3 to 10 of 32).
        kld_in_ours: use the KLD-adaptive sample size in :attr:`Mode.OURS`.
            Default True.
        likelihood_field_in_ours: :attr:`Mode.OURS` weighs particles with the
            likelihood field (:class:`LikelihoodFieldModel`) instead of the
            ray-casting model. Default False: the field ignores occlusion and,
            in the changed office, ranked twins of the true pose higher; the
            range table made ray casting fast enough (docs/table1.md).
        uniform_in_ours: in :attr:`Mode.OURS`, particles spread over the free
            space in addition to the candidates' (when a changed environment
            leaves only wrong candidates, the paper's filter cannot recover
            until verification fails). Default 0 (off): they were the source
            of ours' wrong poses (office trial 42: the half-turn twin won).
        uniform_share_in_ours: prior probability mass of those uniform
            particles (the candidates share the rest): the SIFT candidates are
            evidence, a uniform particle must out-score them by a large
            likelihood ratio to win. Default 0.05.
        recheck_modes_in_ours: in :attr:`Mode.OURS`, the converged estimate and
            the best distinct modes of the first update (up to this many in
            all) are re-scored by a short particle filter with the ray-casting
            model (0 = off). Default 0: needed only with the likelihood
            field. The likelihood field ignores occlusion
            and is fast, but in the changed office it preferred a pose's
            half-turn twin (the ceiling is symmetric under a half turn, so
            verification cannot tell them apart either); ray casting preferred
            the truth (office trial 12).
        mode_separation: two modes are distinct when more than this apart in
            position (m) or heading (rad). Default (0.5, 0.5).
        recheck_radius: disc radius (m) of the re-scoring particles around each
            mode. Default 0.25.
        recheck_particles: particles per mode in the re-scoring. Default 200.
        expected_ranges: how the ray-casting model gets each particle's
            expected ranges: ``"table"`` (default) looks them up in a
            :class:`~lampsam.localization.raycast.RangeTable` built once per
            grid (the same sphere-traced ranges, tabulated per cell centre and
            1-degree heading; nearest cell and bin at lookup); ``"march"``
            sphere-traces every particle's rays at every update. On the office
            map the two agree to within one cell (5 cm) on 95 % of the beams
            and to 0.25 m on 99 %, and a 20,000-particle x 180-beam update takes
            0.08 s instead of 2.8 s (docs/table1.md).
        twin_margin_in_ours: in :attr:`Mode.OURS`, after a turn without SIFT
            candidates, when the ceiling map is symmetric under a half turn
            (:func:`half_turn_centre`; the office's is), the estimate ``x`` and
            its half-turn twin (``x`` rotated by pi about the centre) are each
            refined by a short ray-casting filter and their scan
            log-likelihoods compared: the better one is kept if it wins by
            this margin (nats, after the beams' tempering), else the attempt
            fails without a verification drive (no ceiling test can tell the
            two apart) and the robot drives on and turns again. 0 = off.
            Default 3.0.
        keep_scans_on_restart: after a failed verification, the virtual scans
            of the earlier turns stay in the filter of the next attempt (in
            :attr:`Mode.PROPOSED` and :attr:`Mode.OURS`): a particle at pose
            ``x`` now is scored on an earlier scan at ``x`` composed with the
            odometry from now back to the end of that turn (the filter's motion
            model, without noise: the robot turned once and drove about 2 m in
            between). The paper only says the process is repeated, so the
            default is False (start from scratch, as the paper). Tried on
            office trial 7 (three turns without SIFT candidates in a row, each
            scan fitting a 90-degree twin of the near-square room best): the
            second estimate moved from 3.7 m to 0.5 m off, not enough to pass
            verification, so it did not save the trial; off in docs/table1.md.
    """

    particles_per_candidate: int = 300
    n_uniform: int = 20000
    max_updates: int = 15
    beam: BeamModelConfig = field(
        default_factory=lambda: BeamModelConfig(
            sigma_hit=0.15, z_hit=0.8, z_rand=0.2, max_range=4.5, beam_weight=0.2
        )
    )
    beam_step: int = 2
    pf: ParticleFilterConfig = field(
        default_factory=lambda: ParticleFilterConfig(
            converged_sigma_xy=0.05, converged_sigma_theta=0.03, jitter_xy=0.05, jitter_theta=0.03
        )
    )
    kld_in_ours: bool = True
    likelihood_field_in_ours: bool = False
    uniform_in_ours: int = 0
    uniform_share_in_ours: float = 0.05
    recheck_modes_in_ours: int = 0
    mode_separation: tuple[float, float] = (0.5, 0.5)
    recheck_radius: float = 0.25
    recheck_particles: int = 200
    expected_ranges: Literal["table", "march"] = "table"
    twin_margin_in_ours: float = 3.0
    keep_scans_on_restart: bool = False


@dataclass(frozen=True)
class GlobalLocalizerConfig:
    """The whole pipeline.

    Attributes:
        mode: which Table-1 configuration. Default PROPOSED.
        turn_rate: in-place turning rate (rad/s). Default 30 deg/s (paper).
        turn_angle: how far to turn (rad). Default one full turn.
        drive_step: distance driven between verifier decisions (m). Default 0.25.
        max_verify_distance: give up verifying (count as failure) after this
            distance (m). Default 3.0.
        max_restarts: start over at most this many times. Default 3.
        refine_in_ours: in :attr:`Mode.OURS`, the first ceiling frame of the
            verification drive that matches at least two lamps corrects the
            pose (:func:`lampsam.localization.verification.refine_pose`)
            before the frames are tested. Default True. In the changed office
            the scan alone left a bias of 0.2 m / 5 deg (moved furniture) that
            the ceiling test then rejected, restart after restart.
        sequential_in_ours: :attr:`Mode.OURS` verifies with the sequential test
            (:class:`SequentialVerifier`) instead of the paper's ``R_loc``.
            Default False: it decides after about 0.3 m instead of 0.5 m, but
            three short runs of missed frames fail a pose 15 cm off (office
            trial 42), and a restart costs a 12 s turn.
        relocate_in_ours: in :attr:`Mode.OURS`, after a failed attempt whose
            turn found no candidate, drive on until this distance (m) since the
            turn before turning again. Default 1.5 m. Without SIFT matches the
            scan alone is ambiguous in a near-symmetric room; turning again
            0.3 m away sees the same ambiguity, while the paper's verifier
            (2 m) reaches new, mapped features (office: the proposed
            configuration found candidates after its restarts, ours did not).
        head_for_open_space: in :attr:`Mode.PROPOSED` and :attr:`Mode.OURS`,
            before the verification drive, turn (the shorter way, at
            ``turn_rate``) to face open space when the robot's own virtual scan
            shows less than ``open_space_need`` metres free ahead
            (:func:`open_heading`; no map is used). The paper only says the
            robot drives on. Default True. Before, the drive went straight
            ahead from the start heading and, blocked by a wall, followed it:
            in office trials 7 and 48 the robot hugged a wall (0.3-0.6 m off)
            through three turns that saw no remaining picture (SIFT
            candidates need one within 4.5 m at a moderate angle), so it
            timed out; from the open side the pictures are in view.
        open_space_need: free distance (m) wanted ahead of the verification
            drive: the 2 m verification distance plus 0.7 m to stop short of
            an obstacle. Default 2.7.
        max_refine: the correction is applied only when within this
            ``(metres, radians)``; a larger one is a different pose, left to
            verification. Default (0.3 m, 10 deg): the success bound.
        candidates: candidate generation.
        scan: the virtual scan's point band.
        filter: the particle filter.
        verification: ceiling verification.
    """

    mode: Mode = Mode.PROPOSED
    turn_rate: float = float(np.deg2rad(30.0))
    turn_angle: float = float(2 * np.pi)
    drive_step: float = 0.25
    max_verify_distance: float = 3.0
    max_restarts: int = 3
    refine_in_ours: bool = True
    sequential_in_ours: bool = False
    relocate_in_ours: float = 1.5
    head_for_open_space: bool = True
    open_space_need: float = 2.7
    max_refine: tuple[float, float] = (0.3, float(np.deg2rad(10.0)))
    candidates: CandidateConfig = field(default_factory=CandidateConfig)
    scan: VirtualScanConfig = field(default_factory=VirtualScanConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    verification: VerificationConfig = field(default_factory=VerificationConfig)


# ----------------------------------------------------------------------------- result
@dataclass(frozen=True)
class AttemptRecord:
    """One try (turn, filter, verification).

    Attributes:
        n_candidates: candidates found during the turn.
        filter_updates: measurement updates until convergence (or the limit).
        converged: the particle spread fell below the bound.
        verdict: the verifier's final verdict (``accepted`` without verification).
        r_loc: ``R_loc`` at the end (NaN for the sequential verifier / none).
        verify_distance: distance driven while verifying (m).
        pose: (3,) the estimate at the end of the attempt.
    """

    n_candidates: int
    filter_updates: int
    converged: bool
    verdict: str
    r_loc: float
    verify_distance: float
    pose: list[float]


@dataclass(frozen=True)
class LocalizationResult:
    """What ``OUT/result.json`` holds.

    Attributes:
        success: the last attempt was accepted.
        pose: (3,) ``world_T_body`` at the end (m, m, rad), in the world frame.
        covariance: (3, 3) particle covariance of the pose (heading wrapped).
        mode: the configuration's name.
        restarts: attempts minus one.
        robot_time: seconds of robot time (turning + driving), by stage.
        compute_time: seconds of computation, by stage.
        attempts: one record per attempt.
        odom: (3,) the odometry reading that goes with ``pose`` (to re-check
            or track it later).
    """

    success: bool
    pose: FloatArray
    covariance: FloatArray
    mode: str
    restarts: int
    robot_time: dict[str, float]
    compute_time: dict[str, float]
    attempts: list[AttemptRecord]
    odom: FloatArray = field(default_factory=lambda: np.zeros(3))

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict (lists instead of arrays)."""
        return {
            "success": self.success,
            "pose": [float(v) for v in self.pose],
            "covariance": np.asarray(self.covariance).tolist(),
            "mode": self.mode,
            "restarts": self.restarts,
            "robot_time_s": self.robot_time,
            "compute_time_s": self.compute_time,
            "attempts": [asdict(a) for a in self.attempts],
        }


def write_result(result: LocalizationResult, out_dir: str | Path) -> Path:
    """Write ``out_dir/result.json``; returns its path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "result.json"
    path.write_text(json.dumps(result.to_json(), indent=2))
    return path


# ----------------------------------------------------------------------------- filter
def mode_estimate(
    particles: FloatArray, log_weights: FloatArray, radius: float = 0.5
) -> FloatArray:
    """Weighted mean of the particles near the heaviest one.

    Unlike the global weighted mean, it stays on one mode when the filter has
    not (yet) collapsed to a single hypothesis.

    Args:
        particles: (N, 3) poses ``(x, y, theta)``.
        log_weights: (N,) log-weights.
        radius: neighbourhood of the heaviest particle (m in x, y; rad in theta).

    Returns:
        (3,) pose, circular mean heading.
    """
    w = np.exp(log_weights - log_weights.max())
    best = particles[int(np.argmax(w))]
    near = (np.hypot(particles[:, 0] - best[0], particles[:, 1] - best[1]) < radius) & (
        np.abs(np.asarray(wrap_angle(particles[:, 2] - best[2]))) < radius
    )
    ws = w[near] / w[near].sum()
    p = particles[near]
    th = float(np.arctan2(ws @ np.sin(p[:, 2]), ws @ np.cos(p[:, 2])))
    xy = ws @ p[:, :2]
    return np.array([xy[0], xy[1], th])


# ----------------------------------------------------------------------------- pipeline
#: Range tables already built, keyed by ``(id(grid), max_range)``; the grid is
#: kept with its table so that its id cannot be reused while cached.
_TABLES: dict[tuple[int, float], tuple[OccupancyGrid, RangeTable]] = {}
_MAX_TABLES = 2


def range_table_for(grid: OccupancyGrid, max_range: float) -> RangeTable:
    """The :class:`RangeTable` of ``grid`` (360 heading bins, every non-occupied cell), cached.

    A table takes seconds to build (office map: 110,000 cells x 360 bins, about
    20 s on a loaded machine, 77 MB), so it is built once per grid and reused
    by every localization on that grid (the Table-1 experiment runs 200 on one
    map). The grid must not be modified while cached.

    Args:
        grid: the map.
        max_range: metres (the beam model's).

    Returns:
        The table.
    """
    key = (id(grid), float(max_range))
    hit = _TABLES.get(key)
    if hit is not None and hit[0] is grid:
        return hit[1]
    occupied = occupied_mask(grid)
    table = RangeTable.build(grid, 360, max_range, cells=~occupied)
    while len(_TABLES) >= _MAX_TABLES:
        _TABLES.pop(next(iter(_TABLES)))
    _TABLES[key] = (grid, table)
    return table


def _ray_model(maps: EnvironmentMaps, config: GlobalLocalizerConfig) -> RayCastModel:
    """The ray-casting beam model of the configuration (table lookup or marching)."""
    beam = config.filter.beam
    if config.filter.expected_ranges == "table":
        return RayCastModel(
            maps.grid, beam, method="table", table=range_table_for(maps.grid, beam.max_range)
        )
    return RayCastModel(maps.grid, beam, method="march")


def _make_model(maps: EnvironmentMaps, config: GlobalLocalizerConfig) -> Any:
    beam = config.filter.beam
    if config.mode is Mode.OURS and config.filter.likelihood_field_in_ours:
        return LikelihoodFieldModel(maps.grid, beam)
    return _ray_model(maps, config)


def _turn_stage(
    robot: Robot, maps: EnvironmentMaps, config: GlobalLocalizerConfig, rng: np.random.Generator
) -> tuple[list[PoseCandidate], FloatArray, FloatArray, float, float]:
    """Turn in place: candidates and the virtual scan.

    Returns:
        candidates (in the body frame at the end of the turn), the 360-beam scan
        (360,), the odometry pose at the end (3,), robot seconds, compute seconds.
    """
    frames = robot.turn(config.turn_angle, config.turn_rate)
    if not frames:
        raise GlobalLocalizationError("the robot returned no frame while turning")
    t0 = time.perf_counter()
    collector = CandidateCollector(
        maps.spatial_xyz, maps.spatial_descriptors, config.candidates, rng
    )
    vscan = VirtualScan(config.scan)
    use_candidates = config.mode is not Mode.GRID_ONLY
    for f in frames:
        vscan.add(f.odom, f.depth_points)
        if use_candidates:
            collector.add_frame(f.t, f.odom, f.sift_points, f.sift_descriptors)
        else:
            collector.move_to(f.odom)
    odom_end = np.asarray(frames[-1].odom, dtype=float)
    scan = vscan.scan(odom_end)
    compute = time.perf_counter() - t0
    robot_s = float(frames[-1].t - frames[0].t)
    log.info(
        "turn: %d frames, %d candidates, %d/360 beams",
        len(frames),
        len(collector.candidates),
        int(np.count_nonzero(np.isfinite(scan))),
    )
    emit("localize.candidates", candidates=list(collector.candidates))
    return collector.candidates, scan, odom_end, robot_s, compute


@dataclass(frozen=True)
class KeptScan:
    """A virtual scan of an earlier turn, kept for the next attempt.

    Attributes:
        ranges: (B,) ranges of the scan's used beams (m, NaN = no return).
        angles: (B,) their bearings (rad, body frame).
        odom: (3,) the odometry pose at the end of that turn.
    """

    ranges: FloatArray
    angles: FloatArray
    odom: FloatArray


class JointScanModel:
    """A measurement model that also scores earlier scans through the odometry.

    ``log p(z, z_1..z_K | x) = log p(z | x) + sum_k log p(z_k | x (+) delta_k)``
    with ``delta_k = between(odom_now, odom_k)``: the pose at the end of turn
    ``k`` seen from the current one (odometry frame), so ``x (+) delta_k`` is
    where a particle now was then.

    Args:
        model: the per-scan model (ray casting or likelihood field).
        kept: the earlier scans.
        odom_now: (3,) the odometry pose the particles refer to.
    """

    def __init__(self, model: Any, kept: Sequence[KeptScan], odom_now: FloatArray) -> None:
        self.model = model
        self.config = model.config
        self.kept = list(kept)
        self.deltas = [between(np.asarray(odom_now, dtype=float), k.odom) for k in self.kept]

    def log_likelihood(
        self, poses: FloatArray, ranges: FloatArray, angles: FloatArray
    ) -> FloatArray:
        """(P,) joint log-likelihood of the current scan and the kept ones (see class)."""
        ll = np.asarray(self.model.log_likelihood(poses, ranges, angles), dtype=np.float64)
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        for k, delta in zip(self.kept, self.deltas, strict=True):
            c, sn = np.cos(poses[:, 2]), np.sin(poses[:, 2])
            then = np.column_stack([
                poses[:, 0] + c * delta[0] - sn * delta[1],
                poses[:, 1] + sn * delta[0] + c * delta[1],
                wrap_angle(poses[:, 2] + delta[2]),
            ])  # fmt: skip
            ll = ll + self.model.log_likelihood(then, k.ranges, k.angles)
        return ll


def _filter_stage(
    cands: Sequence[PoseCandidate],
    scan: FloatArray,
    model: Any,
    maps: EnvironmentMaps,
    config: GlobalLocalizerConfig,
    rng: np.random.Generator,
    kept: Sequence[KeptScan] = (),
    odom_now: FloatArray | None = None,
) -> tuple[ParticleFilter, int, bool]:
    """Particle filter on the virtual scan until the spread is below the bound.

    The robot stands still after the turn, so the same scan is applied
    repeatedly, resampling (with roughening) in between, as the paper's
    "repeated process" (sec. 4.1) does. ``kept`` scans of earlier turns
    (``odom_now``: the odometry at the end of this turn) are scored along
    with it (:class:`JointScanModel`).
    """
    fc = config.filter
    if kept:
        assert odom_now is not None
        model = JointScanModel(model, kept, odom_now)
    pf_config = fc.pf
    if config.mode is Mode.OURS and fc.kld_in_ours and pf_config.kld is None:
        pf_config = replace(pf_config, kld=KldConfig())
    pf = ParticleFilter(model, pf_config, rng)
    if cands and config.mode is Mode.OURS and fc.uniform_in_ours > 0:
        disc = sample_candidate_discs(
            pf_candidates(cands), fc.particles_per_candidate, config.candidates.sigma_theta, rng
        )
        pf.init_particles(np.vstack([disc, sample_free_space(maps.grid, fc.uniform_in_ours, rng)]))
        share = min(max(fc.uniform_share_in_ours, 1e-6), 1.0 - 1e-6)
        prior = np.concatenate([
            np.full(len(disc), np.log((1.0 - share) / len(disc))),
            np.full(fc.uniform_in_ours, np.log(share / fc.uniform_in_ours)),
        ])  # fmt: skip
        pf.log_weights = normalise_log_weights(prior)
    elif cands and config.mode is not Mode.GRID_ONLY:
        pf.init_candidates(
            pf_candidates(cands), fc.particles_per_candidate, config.candidates.sigma_theta
        )
    else:
        pf.init_uniform(maps.grid, fc.n_uniform)
    angles = beam_angles()[:: fc.beam_step]
    ranges = scan[:: fc.beam_step]
    recheck = config.mode is Mode.OURS and fc.recheck_modes_in_ours > 0
    first_modes = np.zeros((0, 3))
    converged = False
    n_updates = 0
    while n_updates < fc.max_updates:
        n_updates += 1
        pf.update(ranges, angles)
        emit("localize.particles", particles=pf.particles, log_weights=pf.log_weights,
             update=n_updates)
        if recheck and n_updates == 1:
            first_modes = distinct_modes(
                pf.particles, pf.log_weights, fc.recheck_modes_in_ours, fc.mode_separation
            )
        if pf.converged():
            converged = True
            break
        pf.resample()
    log.info("filter: %d updates, %d particles, converged %s", n_updates, pf.n, converged)
    if recheck:
        best = mode_estimate(pf.particles, pf.log_weights)
        modes = distinct_modes(
            np.vstack([best[None], first_modes]),
            np.concatenate([[0.0], np.full(len(first_modes), -1.0)]),
            fc.recheck_modes_in_ours,
            fc.mode_separation,
        )
        pf, n_more, converged = _recheck_modes(
            modes, ranges, angles, maps, config, rng, kept, odom_now
        )
        n_updates += n_more
    return pf, n_updates, converged


def distinct_modes(
    particles: FloatArray, log_weights: FloatArray, k: int, separation: tuple[float, float]
) -> FloatArray:
    """The heaviest particles that are pairwise distinct (greedy non-maximum suppression).

    Args:
        particles: (N, 3) poses (m, m, rad).
        log_weights: (N,) log-weights (only their order matters).
        k: at most this many modes.
        separation: ``(metres, radians)``: a particle closer than both to a
            chosen mode is suppressed.

    Returns:
        (M, 3) modes, M <= k, heaviest first.
    """
    order = np.argsort(-np.asarray(log_weights, dtype=float))[: max(50 * k, 1000)]
    chosen: list[FloatArray] = []
    for i in order:
        p = particles[i]
        if chosen:
            c = np.asarray(chosen)
            near = (np.hypot(c[:, 0] - p[0], c[:, 1] - p[1]) < separation[0]) & (
                np.abs(np.asarray(wrap_angle(c[:, 2] - p[2]))) < separation[1]
            )
            if near.any():
                continue
        chosen.append(np.asarray(p, dtype=float))
        if len(chosen) >= k:
            break
    return np.asarray(chosen, dtype=float).reshape(-1, 3)


def _recheck_modes(
    modes: FloatArray,
    ranges: FloatArray,
    angles: FloatArray,
    maps: EnvironmentMaps,
    config: GlobalLocalizerConfig,
    rng: np.random.Generator,
    kept: Sequence[KeptScan] = (),
    odom_now: FloatArray | None = None,
) -> tuple[ParticleFilter, int, bool]:
    """Ours: a short ray-casting particle filter over discs around the given modes.

    The same number of particles in each disc (as the paper does with its
    candidates), updated on the virtual scan until converged.
    """
    fc = config.filter
    model: Any = _ray_model(maps, config)
    if kept:
        assert odom_now is not None
        model = JointScanModel(model, kept, odom_now)
    pf = ParticleFilter(model, fc.pf, rng)
    pf.init_candidates(
        [(m, fc.recheck_radius) for m in modes], fc.recheck_particles, config.candidates.sigma_theta
    )
    converged = False
    n_updates = 0
    while n_updates < fc.max_updates:
        n_updates += 1
        pf.update(ranges, angles)
        emit("localize.particles", particles=pf.particles, log_weights=pf.log_weights,
             update=n_updates)
        if pf.converged():
            converged = True
            break
        pf.resample()
    log.info(
        "re-check of %d modes by ray casting: %d updates, converged %s",
        len(modes),
        n_updates,
        converged,
    )
    return pf, n_updates, converged


def half_turn_centre(
    xy: FloatArray, phi: FloatArray | None = None, tol: float = 0.15
) -> FloatArray | None:
    """Centre of a half-turn symmetry of a ceiling map, if it has one.

    The map is half-turn symmetric about its centroid ``c`` when every feature
    ``p`` has a feature within ``tol`` of ``2 c - p`` (and, with axes, with
    the same axis mod pi: a half turn keeps a line's direction). A pose and
    its half-turn twin then see the same ceiling.

    Args:
        xy: (L, 2) feature positions, world frame (m).
        phi: (L,) long axes (rad, mod pi), NaN for none; None: not checked.
        tol: position tolerance (m).

    Returns:
        (2,) the centre (m), or None (no symmetry, or fewer than 2 features).
    """
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if len(xy) < 2:
        return None
    c = xy.mean(axis=0)
    mirrored = 2.0 * c - xy
    d = np.hypot(*(mirrored[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    j = np.argmin(d, axis=1)
    if not np.all(d[np.arange(len(xy)), j] <= tol):
        return None
    if phi is not None:
        a = np.asarray(phi, dtype=float).reshape(-1)
        both = np.isfinite(a) & np.isfinite(a[j])
        if np.any(np.isfinite(a) != np.isfinite(a[j])):
            return None
        diff = np.abs(np.asarray(wrap_angle(2.0 * (a[both] - a[j][both])))) / 2.0
        if np.any(diff > np.deg2rad(10.0)):
            return None
    return c


def half_turn_twin(pose: FloatArray, centre: FloatArray) -> FloatArray:
    """(3,) the pose rotated by pi about ``centre`` (m): ``(2c - xy, theta + pi)``."""
    p = np.asarray(pose, dtype=float)
    return np.array(
        [2.0 * centre[0] - p[0], 2.0 * centre[1] - p[1], float(wrap_angle(p[2] + np.pi))]
    )


def open_heading(
    scan: FloatArray,
    need: float,
    half_width: float = float(np.deg2rad(15.0)),
    near_border: float = 1.5,
    far: float = 4.5,
) -> float:
    """Where to turn to drive into open space, from the robot's own virtual scan.

    A beam without a return (NaN) is either beyond the sensor's range or
    nearer than its minimum depth; it counts as ``far`` metres free when the
    returns on both sides of its run of NaN beams are at least ``near_border``
    away, else as blocked (0 m). The free distance of a heading is the
    smallest filled range within ``half_width`` of it (the robot's width at a
    few metres). When straight ahead has ``need`` metres free the robot goes
    on (0 is returned); otherwise it turns to the heading whose sector is
    freest on average among those with ``need`` metres free (the most open
    one when none has).

    Args:
        scan: (360,) ranges at :func:`beam_angles` (m, NaN = no return), body
            frame at the end of the turn.
        need: free distance wanted ahead (m).
        half_width: half the angular width of a drive corridor (rad).
        near_border: NaN runs bordered by returns nearer than this are blocked (m).
        far: free distance credited to a NaN beam of an open run (m): the
            sensor's range.

    Returns:
        The turn (rad, in ``(-pi, pi]``, counter-clockwise positive), 0 when
        ahead is free or the scan has no return at all.
    """
    r = np.asarray(scan, dtype=float).reshape(-1)
    n = len(r)
    finite = np.isfinite(r)
    if not finite.any():
        return 0.0
    filled = np.where(finite, np.minimum(r, far), 0.0)
    # each NaN beam's nearest returns clockwise and counter-clockwise
    idx = np.arange(n)
    fin_idx = np.nonzero(finite)[0]
    ext = np.concatenate([fin_idx - n, fin_idx, fin_idx + n])
    nxt = ext[np.searchsorted(ext, idx, side="left")] % n
    prv = ext[np.searchsorted(ext, idx, side="right") - 1] % n
    open_nan = ~finite & (np.minimum(r[nxt], r[prv]) >= near_border)
    filled[open_nan] = far
    k = max(int(round(np.rad2deg(half_width))), 0)
    window = np.stack([np.roll(filled, -j) for j in range(-k, k + 1)])
    free = window.min(axis=0)
    if free[0] >= need:
        return 0.0
    mean = window.mean(axis=0)
    ok = free >= need
    score = np.where(ok, mean, -np.inf) if ok.any() else free
    best = int(np.argmax(score))
    return float(wrap_angle(np.deg2rad(float(best))))


def _image_interior(camera: Any, margin_px: float = 15.0) -> Any:
    """``m (N, 2) -> (N,) bool``: inside the camera's image by ``margin_px`` pixels."""

    def in_view(m: FloatArray) -> BoolArray:
        px = np.asarray(camera.pixels_from_normalized(np.asarray(m, dtype=float).reshape(-1, 2)))
        w, h = float(camera.width), float(camera.height)
        return (
            (px[:, 0] >= margin_px) & (px[:, 0] <= w - 1 - margin_px)
            & (px[:, 1] >= margin_px) & (px[:, 1] <= h - 1 - margin_px)
        )  # fmt: skip

    return in_view


def _verify_stage(
    robot: Robot,
    pose_end: FloatArray,
    odom_end: FloatArray,
    maps: EnvironmentMaps,
    config: GlobalLocalizerConfig,
    monitoring: bool = False,
) -> tuple[Verdict, float, float, FloatArray, FloatArray, float, float]:
    """Drive on and verify the pose with the ceiling features.

    Args:
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
        in_view=None if maps.ceiling_camera is None else _image_interior(maps.ceiling_camera),
    )
    verifier: RlocVerifier | SequentialVerifier
    rloc = config.mode is Mode.PROPOSED or (
        config.mode is Mode.OURS and not config.sequential_in_ours
    )
    verifier = RlocVerifier(vc) if rloc else SequentialVerifier(vc)
    if monitoring and isinstance(verifier, SequentialVerifier):
        verifier.verdict = Verdict.ACCEPTED
    prev = np.asarray(odom_end, dtype=float)
    pose = np.asarray(pose_end, dtype=float)
    refine = config.mode is Mode.OURS and config.refine_in_ours and not monitoring
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


def resolve_half_turn(
    pose: FloatArray,
    scan: FloatArray,
    centre: FloatArray,
    maps: EnvironmentMaps,
    config: GlobalLocalizerConfig,
    rng: np.random.Generator,
) -> tuple[FloatArray, float]:
    """Ours: the estimate or its half-turn twin, whichever the scan prefers, and by how much.

    Each of the two poses is refined by a short ray-casting particle filter
    (:func:`_recheck_modes`, one disc) and scored by the ray-casting model
    (eqs. 8-9, tempered); the ceiling cannot tell them apart when the map is
    half-turn symmetric about ``centre``.

    Args:
        pose: (3,) the filter's estimate (m, m, rad).
        scan: (360,) the virtual scan (m, NaN = no return).
        centre: (2,) the symmetry centre (m), :func:`half_turn_centre`.
        maps: the map layers.
        config: the configuration.
        rng: generator of the refinement.

    Returns:
        The preferred pose (3,) and its log-likelihood margin over the other (nats, >= 0).
    """
    fc = config.filter
    angles = beam_angles()[:: fc.beam_step]
    ranges = scan[:: fc.beam_step]
    model = _ray_model(maps, config)
    refined, scores = [], []
    for h in (np.asarray(pose, dtype=float), half_turn_twin(pose, centre)):
        pf, _, _ = _recheck_modes(h[None], ranges, angles, maps, config, rng)
        est = mode_estimate(pf.particles, pf.log_weights)
        refined.append(est)
        scores.append(float(model.log_likelihood(est[None], ranges, angles)[0]))
    best = int(np.argmax(scores))
    margin = abs(scores[0] - scores[1])
    log.info(
        "half-turn twin check: estimate %.1f, twin %.1f (log-likelihood): %s",
        scores[0],
        scores[1],
        "twin" if best == 1 else "estimate",
    )
    return refined[best], margin


def _face_open_space(
    robot: Robot,
    scan: FloatArray,
    pose: FloatArray,
    odom: FloatArray,
    config: GlobalLocalizerConfig,
    robot_time: dict[str, float],
) -> tuple[FloatArray, FloatArray]:
    """Turn in place towards open space (:func:`open_heading`) before driving on.

    The estimate follows the turn by odometry; the turn's robot seconds are
    added to ``robot_time["turn"]``.

    Returns:
        The pose estimate (3,) and the odometry (3,) after the turn.
    """
    angle = open_heading(scan, config.open_space_need)
    if abs(angle) < 1e-9:
        return pose, odom
    frames = robot.turn(angle, config.turn_rate)
    if not frames:
        return pose, odom
    robot_time["turn"] += float(frames[-1].t - frames[0].t)
    new_odom = np.asarray(frames[-1].odom, dtype=float)
    log.info("turned %.0f deg towards open space before driving on", np.rad2deg(angle))
    return compose(pose, between(np.asarray(odom, dtype=float), new_odom)), new_odom


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
    model = _make_model(maps, config)
    emit("localize.start", grid=maps.grid)
    robot_time = {"turn": 0.0, "verification": 0.0}
    compute_time = {"candidates": 0.0, "filter": 0.0, "verification": 0.0}
    attempts: list[AttemptRecord] = []
    pose, odom = np.zeros(3), np.zeros(3)
    cov = np.full((3, 3), np.nan)
    success = False
    verifies = config.mode in (Mode.PROPOSED, Mode.OURS)
    fc = config.filter
    keep = verifies and fc.keep_scans_on_restart
    twin_centre = None
    if config.mode is Mode.OURS and fc.twin_margin_in_ours > 0 and len(maps.ceiling_xyz) >= 2:
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
    if initial is not None and verifies:
        verdict, r_loc, d, pose, odom, rs, cs = _verify_stage(
            robot, initial.pose, initial.odom, maps, config, monitoring=True
        )
        robot_time["verification"] += rs
        compute_time["verification"] += cs
        cov = np.asarray(initial.covariance)
        attempts.append(
            AttemptRecord(0, 0, True, verdict.value, r_loc, d, [float(v) for v in pose])
        )
        success = verdict is Verdict.ACCEPTED
        if not success:
            log.info("re-check of the earlier pose failed (kidnapped?): starting over")
    for attempt in range(config.max_restarts + 1):
        if success:
            break
        cands, scan, odom, rs, cs = _turn_stage(robot, maps, config, rng)
        odom_turn = odom
        robot_time["turn"] += rs
        compute_time["candidates"] += cs
        t0 = time.perf_counter()
        pf, n_upd, converged = _filter_stage(
            cands, scan, model, maps, config, rng, kept if keep else (), odom
        )
        pose = mode_estimate(pf.particles, pf.log_weights)
        _, cov = pf.estimate()
        ambiguous = False
        if twin_centre is not None and not cands:
            pose, margin = resolve_half_turn(pose, scan, twin_centre, maps, config, rng)
            ambiguous = margin < fc.twin_margin_in_ours
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
            pose, odom = _face_open_space(robot, scan, pose, odom, config, robot_time)
        if ambiguous:
            verdict, r_loc, d = Verdict.FAILED, float("nan"), 0.0
            log.info("the scan cannot tell the estimate from its half-turn twin: not verified")
        else:
            verdict, r_loc, d, pose, odom, rs, cs = _verify_stage(robot, pose, odom, maps, config)
            robot_time["verification"] += rs
            compute_time["verification"] += cs
        attempts.append(
            AttemptRecord(
                len(cands), n_upd, converged, verdict.value, r_loc, d, [float(v) for v in pose]
            )
        )
        success = verdict is Verdict.ACCEPTED
        if not success:
            log.info("attempt %d failed verification (R_loc %.2f): starting over", attempt, r_loc)
            kept.append(KeptScan(scan[:: fc.beam_step].copy(), beam_angles()[:: fc.beam_step],
                                 np.asarray(odom_turn, dtype=float).copy()))  # fmt: skip
            more = config.relocate_in_ours - d
            if (
                config.mode is Mode.OURS
                and not cands
                and more > 0
                and attempt < config.max_restarts
            ):
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
    )


# ----------------------------------------------------------------------------- log replay
class ReplayRobot:
    """A logged run replayed in time order as a :class:`Robot`.

    The run (``docs/log-format.md``) must hold wheel odometry and the Kinect
    frames under ``kinect/`` (TUM RGB-D layout with ``kinect.yaml``, whose
    ``body_T_camera`` places the Kinect on the robot); ceiling features come
    from the run's ceiling images through the frontend when it has images.
    ``turn`` returns the Kinect frames from the current time until the odometry
    heading has turned by ``angle``; ``drive`` the ceiling frames until the
    odometry has covered ``distance``. The recorded motion decides what the
    robot did: the requested rate is not enforced. An exhausted log returns no
    frame.

    Args:
        run_dir: the run directory.
    """

    def __init__(self, run_dir: str | Path) -> None:
        from lampsam.datasets.logrun import read_run
        from lampsam.datasets.motion import dead_reckoning
        from lampsam.datasets.rgbd import read_tum_rgbd
        from lampsam.localization.spatial_map import make_sift

        self.run = read_run(run_dir)
        odo = self.run.odometry
        if len(odo.t) == 0:
            raise GlobalLocalizationError(f"{run_dir}: the run has no odometry")
        wheel = np.column_stack([odo.d_left, odo.d_right])
        self.t_odom = np.asarray(odo.t, dtype=float)
        self.odom = dead_reckoning(wheel, self.run.rig.odometry.wheel_base, np.zeros(3))
        self.heading = np.unwrap(self.odom[:, 2])
        self.path = np.cumsum(np.abs(0.5 * (wheel[:, 0] + wheel[:, 1])))
        kdir = Path(run_dir) / "kinect"
        if not kdir.is_dir():
            raise GlobalLocalizationError(f"{kdir}: the run has no Kinect frames")
        self.kinect = read_tum_rgbd(kdir)
        self.sift = make_sift()
        self.cursor = float(min(self.t_odom[0], self.kinect.t[0]))
        self._ceiling: list[DriveFrame] | None = None

    def _odom_at(self, t: float) -> FloatArray:
        i = int(np.clip(np.searchsorted(self.t_odom, t, side="right") - 1, 0, len(self.t_odom) - 1))
        return self.odom[i].copy()

    def _index_at(self, t: float) -> int:
        return int(
            np.clip(np.searchsorted(self.t_odom, t, side="right") - 1, 0, len(self.t_odom) - 1)
        )

    def turn(self, angle: float, rate: float) -> list[TurnFrame]:
        """Kinect frames until the recorded heading has changed by ``|angle|``."""
        from lampsam.localization.pointcloud import depth_to_points
        from lampsam.localization.spatial_map import frame_features

        cam = self.kinect.camera
        R, t = cam.body_T_camera[:3, :3], cam.body_T_camera[:3, 3]
        h0 = self.heading[self._index_at(self.cursor)]
        frames: list[TurnFrame] = []
        for i in np.nonzero(self.kinect.t >= self.cursor)[0]:
            ti = float(self.kinect.t[i])
            rgb, depth = self.kinect.load_rgb(int(i)), self.kinect.load_depth(int(i))
            ff = frame_features(rgb, depth, cam, self.sift)
            pts = depth_to_points(depth, cam, stride=4)
            frames.append(
                TurnFrame(ti, self._odom_at(ti), ff.camera_xyz @ R.T + t, ff.descriptors,
                          pts @ R.T + t)
            )  # fmt: skip
            self.cursor = ti + 1e-6
            if abs(self.heading[self._index_at(ti)] - h0) >= abs(angle) - 1e-3:
                break
        return frames

    def _ceiling_frames(self) -> list[DriveFrame]:
        if self._ceiling is None:
            from lampsam.frontend.pipeline import iter_run

            out: list[DriveFrame] = []
            if self.run.images is not None:
                for f in iter_run(self.run):
                    m = [o.m for o in f.lamps] + [o.m for o in f.corners]
                    kinds = [True] * len(f.lamps) + [False] * len(f.corners)
                    axis = [np.nan if o.axis is None else o.axis for o in f.lamps]
                    axis += [np.nan] * len(f.corners)
                    out.append(DriveFrame(
                        f.t, self._odom_at(f.t), np.array(m, dtype=float).reshape(-1, 2),
                        np.array(kinds, bool), np.array(axis, dtype=float),
                    ))  # fmt: skip
            self._ceiling = out
        return self._ceiling

    def drive(self, distance: float) -> list[DriveFrame]:
        """Ceiling frames until the recorded path has grown by ``distance``."""
        s0 = self.path[self._index_at(self.cursor)]
        frames: list[DriveFrame] = []
        for f in self._ceiling_frames():
            if f.t < self.cursor:
                continue
            frames.append(f)
            self.cursor = f.t + 1e-6
            if self.path[self._index_at(f.t)] - s0 >= distance - 1e-9:
                break
        return frames


def localize_run(
    run_dir: str | Path,
    map_dir: str | Path,
    out_dir: str | Path,
    config: GlobalLocalizerConfig,
    seed: int = 0,
) -> LocalizationResult:
    """Global localization of a logged run against a map directory; writes ``result.json``.

    Args:
        run_dir: the run (see :class:`ReplayRobot`).
        map_dir: the environment map (``lampsam.localization.envmap``).
        out_dir: where ``result.json`` goes.
        config: the pipeline configuration.
        seed: seed of RANSAC and the particle filter.
            ``config.head_for_open_space`` is switched off: a replayed log
            cannot turn where the localizer asks.

    Returns:
        The result (also written).

    Raises:
        LampsamError subclasses: unreadable run or map, no usable data.
    """
    from lampsam.localization.envmap import load_env_map

    env = load_env_map(map_dir)
    # a log cannot be steered: the recorded drive decides where the robot went
    config = replace(config, head_for_open_space=False)
    robot = ReplayRobot(run_dir)
    cam = robot.run.rig.camera
    maps = EnvironmentMaps.from_env_map(env, cam.body_t_camera, cam)
    result = localize(robot, maps, config, np.random.default_rng(seed))
    path = write_result(result, out_dir)
    log.info("localization %s: result in %s", "succeeded" if result.success else "failed", path)
    return result
