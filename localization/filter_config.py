"""Settings of the global localizer: the Table-1 configuration and each stage's options.

:class:`Mode` names the configurations of paper 2's Table 1 plus ours; every
other option is a plain setting of the pipeline (:class:`FilterConfig` for the
particle filter, :class:`GlobalLocalizerConfig` for the whole). A few options
default to ``None``, meaning "what the mode does": :meth:`GlobalLocalizerConfig.resolved`
fills them in (what :attr:`Mode.OURS` adds to the paper's pipeline). Why each default was chosen, with the trials that decided
it, is in docs/table1.md.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from lampsam.localization.candidates import CandidateConfig
from lampsam.localization.likelihood import BeamModelConfig
from lampsam.localization.particle_filter import ParticleFilterConfig
from lampsam.localization.verification import VerificationConfig
from lampsam.localization.virtual_scan import VirtualScanConfig


class Mode(enum.Enum):
    """The configurations of the paper's Table 1, plus ours.

    GRID_ONLY: particles everywhere in free space, no candidates, no verification.
    NO_CEILING: candidates + particle filter, no ceiling verification.
    PROPOSED: candidates + particle filter + ``R_loc`` verification (paper 2,
        sec. 4.2, eq. 10).
    OURS: the proposed pipeline plus, by default (:meth:`GlobalLocalizerConfig.resolved`), an
        adaptive (KLD) sample size, the half-turn twin check after a turn
        without candidates, the pose refined by the first ceiling frame with
        two lamps, and driving on to 1.5 m after a failed attempt without
        candidates.
    """

    GRID_ONLY = "grid_only"
    NO_CEILING = "no_ceiling"
    PROPOSED = "proposed"
    OURS = "ours"


@dataclass(frozen=True)
class FilterConfig:
    """Particle filter settings of the localizer (paper 2, sec. 4.1).

    Attributes:
        particles_per_candidate: particles in each candidate disc (paper: the
            same number in every candidate). Default 300.
        n_uniform: particles spread over the free space when there is no
            candidate (GRID_ONLY, or a turn without any). Default 20000.
        max_updates: measurement updates on the virtual scan before giving up.
            Default 15.
        beam: per-beam measurement model (eqs. 8-9). Default sigma 0.15 m,
            20 % random returns, 4.5 m (the Kinect's range), beams tempered by
            0.2 (the 360 beams of a virtual scan are far from independent).
        beam_step: use every ``beam_step``-th beam of the 360. Default 2.
        pf: the filter's own settings: convergence bounds 0.05 m and 0.03 rad,
            roughening between updates on the same scan 5 cm and 0.03 rad
            (strong enough for the particles to reach the likelihood's peak).
        adaptive_sample_size: KLD-adaptive sample size (Fox 2003) when
            ``pf.kld`` is not set. Default None: on in :attr:`Mode.OURS` only.
        likelihood_field: weigh particles with the likelihood field
            (:class:`~lampsam.localization.likelihood.LikelihoodFieldModel`,
            no occlusion) instead of the ray-casting model. Default False.
        uniform_beside_candidates: particles spread over the free space in
            addition to the candidates' discs (recovers when a changed
            environment leaves only wrong candidates). Default 0 (off).
        uniform_share: prior probability mass of those uniform particles (the
            candidates share the rest). Default 0.05.
        recheck_modes: the converged estimate and the best distinct modes of
            the first update (up to this many in all) are re-scored by a short
            ray-casting filter; useful with the likelihood field. Default 0 (off).
        mode_separation: two modes are distinct when more than this apart in
            position (m) or heading (rad). Default (0.5, 0.5).
        recheck_radius: disc radius (m) of the re-scoring particles around each
            mode. Default 0.25.
        recheck_particles: particles per mode in the re-scoring. Default 200.
        expected_ranges: how the ray-casting model gets each particle's
            expected ranges: ``"table"`` (default) looks them up in the maps'
            :class:`~lampsam.localization.raycast.RangeTable` (cell centre,
            1-degree heading bin); ``"march"`` sphere-traces every particle's
            rays at every update (exact, about 35x slower on the office map).
        twin_margin: after a turn without SIFT candidates, when the ceiling map
            is symmetric under a half turn
            (:func:`~lampsam.localization.symmetry.half_turn_centre`), the
            estimate and its half-turn twin are each refined and scored on the
            scan; the better one is kept if it wins by this log-likelihood
            margin (nats, after tempering), else the attempt ends unverified
            (no ceiling test can tell the two apart). 0 = off. Default None: 3.0 in
            :attr:`Mode.OURS`, off otherwise.
        keep_scans_on_restart: after a failed verification, the virtual scans
            of the earlier turns stay in the next attempt's filter, scored
            through the odometry (:class:`~lampsam.localization.stages.JointScanModel`).
            Default False (start from scratch, as the paper).
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
    adaptive_sample_size: bool | None = None
    likelihood_field: bool = False
    uniform_beside_candidates: int = 0
    uniform_share: float = 0.05
    recheck_modes: int = 0
    mode_separation: tuple[float, float] = (0.5, 0.5)
    recheck_radius: float = 0.25
    recheck_particles: int = 200
    expected_ranges: Literal["table", "march"] = "table"
    twin_margin: float | None = None
    keep_scans_on_restart: bool = False


@dataclass(frozen=True)
class GlobalLocalizerConfig:
    """The whole pipeline (paper 2, Fig. 11: turn, filter, verify, restart).

    Attributes:
        mode: which Table-1 configuration. Default PROPOSED.
        turn_rate: in-place turning rate (rad/s). Default 30 deg/s (paper).
        turn_angle: how far to turn (rad). Default 360 deg (one full turn).
        drive_step: distance driven between verifier decisions (m). Default 0.25.
        max_verify_distance: give up verifying (count as failure) after this
            distance (m), sequential verifier. Default 3.0.
        max_restarts: start over at most this many times. Default 3.
        refine_with_ceiling: the first ceiling frame of the verification drive
            that matches at least two lamps corrects the pose
            (:func:`~lampsam.localization.verification.refine_pose`) before the
            frames are tested. Default None: on in :attr:`Mode.OURS` only.
        verifier: ``"r_loc"`` (the paper's ``R_loc`` over a fixed distance,
            eq. 10) or ``"sequential"``
            (:class:`~lampsam.localization.verification.SequentialVerifier`,
            decides earlier). Default ``"r_loc"``.
        relocate_distance: after a failed attempt whose turn found no
            candidate, drive on until this distance (m) since the turn before
            turning again (a turn 0.3 m away sees the same ambiguity). Default None:
            1.5 m in :attr:`Mode.OURS`, 0 (off) otherwise.
        head_for_open_space: in the verifying modes, before the verification
            drive, turn (the shorter way, at ``turn_rate``) to face open space
            when the robot's own virtual scan shows less than
            ``open_space_need`` metres free ahead
            (:func:`~lampsam.localization.open_space.open_heading`; no map is
            used). Default True (the paper only says the robot drives on).
        open_space_need: free distance (m) wanted ahead of the verification
            drive: the 2 m verification distance plus 0.7 m to stop short of
            an obstacle. Default 2.7.
        accept_margin: in the modes without ceiling verification, the answer is
            ``localized`` only when the estimate's scan log-likelihood exceeds
            the best well-separated competing mode's by this many nats
            (:func:`~lampsam.localization.acceptance.mode_margin`), else
            ``ambiguous``; the paper's ``success`` is not affected. Default 8.0.
        max_refine: the ceiling correction is applied only when within this
            ``(metres, radians)``; a larger one is a different pose, left to
            verification. Default (0.3 m, 10 deg): the success bound.
        candidates: candidate generation (eqs. 1-7).
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
    refine_with_ceiling: bool | None = None
    verifier: Literal["r_loc", "sequential"] = "r_loc"
    relocate_distance: float | None = None
    head_for_open_space: bool = True
    open_space_need: float = 2.7
    accept_margin: float = 8.0
    max_refine: tuple[float, float] = (0.3, float(np.deg2rad(10.0)))
    candidates: CandidateConfig = field(default_factory=CandidateConfig)
    scan: VirtualScanConfig = field(default_factory=VirtualScanConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    verification: VerificationConfig = field(default_factory=VerificationConfig)

    @property
    def verifies(self) -> bool:
        """The mode drives on and verifies with the ceiling (PROPOSED, OURS)."""
        return self.mode in (Mode.PROPOSED, Mode.OURS)

    def resolved(self) -> GlobalLocalizerConfig:
        """A copy with every ``None`` option replaced by the mode's value.

        :attr:`Mode.OURS` turns on the adaptive sample size and the ceiling
        refinement and uses :data:`OURS_TWIN_MARGIN` and
        :data:`OURS_RELOCATE_DISTANCE`; the other modes leave them off.
        """
        ours = self.mode is Mode.OURS
        fc = self.filter

        def pick(value: float | None, ours_value: float, off: float) -> float:
            return (ours_value if ours else off) if value is None else value

        filt = replace(
            fc,
            adaptive_sample_size=ours if fc.adaptive_sample_size is None else fc.adaptive_sample_size,
            twin_margin=pick(fc.twin_margin, OURS_TWIN_MARGIN, 0.0),
        )
        return replace(
            self,
            filter=filt,
            refine_with_ceiling=(
                ours if self.refine_with_ceiling is None else self.refine_with_ceiling
            ),
            relocate_distance=pick(self.relocate_distance, OURS_RELOCATE_DISTANCE, 0.0),
        )


#: :attr:`Mode.OURS`'s half-turn twin margin (nats): ``FilterConfig.twin_margin``.
OURS_TWIN_MARGIN = 3.0
#: :attr:`Mode.OURS`'s drive after a failed attempt without candidates (m).
OURS_RELOCATE_DISTANCE = 1.5
