"""Configuration of localize-only tracking on a saved ceiling map (:class:`LocalizeConfig`).

Used by :class:`lampsam.backend.localize_only.MapLocalizer` (the filter),
:mod:`lampsam.backend.map_smoother` (the smoother after it) and
:mod:`lampsam.backend.map_release` (releasing contradicted map landmarks); every option is
documented with its default below and measured in docs/ceiling-map.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from lampsam.config_loader import check_limits, limits

MapMode = Literal["fixed", "priors", "consider"]
MAP_MODES: tuple[str, ...] = ("fixed", "priors", "consider")


@dataclass(frozen=True)
class LocalizeConfig:
    """Localize-only tracking.

    Attributes:
        sigma_start_xy: standard deviation of the start position, m (default 1e-3, as
            the SLAM backends hold a known start: :class:`lampsam.backend.config.EkfConfig`),
            used when the start has no covariance of its own (the run's known start pose;
            a typed ``--start`` carries its own, looser one, and ``--start-from`` the
            global localizer's). The known start is the run's only tie to the world: with
            :attr:`frame_offset` it is what fixes the map frame's offset ``g``.
        sigma_start_theta: of the start heading, rad (default 1e-3).
        var_floor: additive floor on the pose process covariance per step, m^2 and
            rad^2 (default 1e-10).
        map_cov_scale: factor on the map's landmark covariances (default 1).
        corner_cov_scale: a further factor on the corners' (default 1).
        corner_bias_px: a per-corner error floor, px: ``(b d / f_x)^2`` is added to the
            ``x`` and ``y`` variances of every map corner (``d`` its height above the
            mapping camera, ``f_x`` that camera's focal length). The frontend's corner
            position has a part that is the same at every sighting (measured on lab:
            0.17-0.21 px RMS per corner against 0.27-0.33 px that varies between
            sightings, 0.5 px in all; docs/ceiling-map.md), which the batch, whose
            sightings are independent, averages away: its corner marginals are 4-5x too
            small (NEES). Default 0 (the map's covariance as saved).
        unique: use an observation only when exactly one map landmark is inside its
            gate (default True).
        corner_ncc: also require ``association.ncc_min`` NCC between a corner's patch
            and the map's (default False: patches are not rotation invariant).
        max_corners: at most this many corner observations per frame, the smallest
            Mahalanobis distances first (default None: all).
        min_corner_obs: map corners observed fewer times are not used (default 10).
        max_corner_sigma: nor those whose larger horizontal sigma in the map exceeds
            this, m (default 0.005). Measured (docs/ceiling-map.md): with a 2.5 mm map of
            lab, every corner gave 3.6 mm RMS on lab_day2, the 28 corners passing both
            2.5 mm (lamps only 2.6 mm); the rejected corners are mostly frontend corners
            on lamp and item edges whose map position is off by centimetres.
        map_mode: how the map's landmark positions enter (default ``"priors"``: with
            the map frame state, over four lab maps x three lab_day2 runs its mean
            position RMS is 2.47 mm against the fixed map's 2.50 mm; docs/ceiling-map.md):
            ``"fixed"``: fixed values, their covariance added to each innovation
            (module docstring); ``"priors"``: the used map landmarks join the state
            (``x = (pose, p_1 .. p_L)``, prior ``N(map position, map marginal)``) and
            every update is the joint EKF update (eqs. 19-23 with the pose-landmark
            cross terms), so repeated sightings of one landmark are correlated through
            it and the run's own known start can pull part of the map's error out;
            ``"consider"``: the same state, but a Schmidt (consider) update: the
            landmarks keep their map values and covariance, only the pose and the
            pose-landmark cross-covariance are updated (the correlation of repeated
            sightings without moving the map). No landmark is ever added and the
            saved map is not changed.
        frame_offset: when the map has a frame model (a version-2 map,
            :mod:`lampsam.backend.map_frame`), add the map frame's offset ``g = (dx,
            dy, dtheta)`` to the state with the map's ``S`` as its prior, and use each
            landmark's conditional covariance ``D_l`` instead of its marginal: a
            landmark's world position is ``p_l + C_l g``. The pose is
            then in the world frame of the start pose, and the map's common error is
            one 3-dof state the run can correct, not many independent ones. Default
            True (maps without a frame model, version 1 or merged, run without it): with
            lamp sightings read through the saturated-edge model
            (:mod:`lampsam.frontend.saturated_edges`) and the 1 mm start, its mean
            position RMS over four lab maps x three lab_day2 runs is 2.47 mm against
            3.94 mm without it (and the 2 cm start): the start ties the map's frame to the
            world. Before that model the biased lamp sightings pulled ``g`` off and it was
            worse (docs/ceiling-map.md).
        frame_turn: with :attr:`frame_offset`, estimate the frame's turn too (default
            False: the frame model reduced to its shift,
            :func:`lampsam.backend.map_frame.shift_only`, as the localize-only smoother
            does; the turn's share of each landmark's error stays in its own covariance).
            A known start pose does not observe the map's turn (its posterior sigma stays
            at its prior's), and the run's own sightings pull it: estimated, it came out
            13 mdeg from the truth on map 1 and 17 on map 3 of lab (docs/ceiling-map.md).
        release: release map landmarks that the run's sightings contradict
            (:mod:`lampsam.backend.map_release`: a chi-square test of each used landmark's
            correction against its map prior, the failing one's prior widened by
            :attr:`release_sigma`, reported in ``summary.json``); ``map_mode`` ``"priors"``
            only (the landmarks must be states; no effect in ``"fixed"`` / ``"consider"``).
            Default True: on four lab maps x three lab_day2 runs, none with a changed
            lamp, it releases nothing; on map 2 with one lamp moved 2 cm it releases that
            lamp after 5 sightings (docs/ceiling-map.md).
        release_prob: the test's level: a landmark is released when its statistic (2
            dof, horizontal) exceeds this chi-square quantile (default 0.999: 13.8).
        release_min_sightings: a landmark is tested only after this many of the run's
            sightings (default 5: a moved lamp pulls the filter from its first sighting;
            20 let a 2 cm move on lab drag the filter and another lamp be released first).
        release_max_fraction: a release is allowed only while the failing and released
            landmarks of its kind are at most this fraction of the tested and released ones
            (and 3 or more): when most of the map disagrees, the pose is what is wrong
            (default 0.34: a run releases at most a third of the lamps it uses).
        release_sigma: standard deviation added to a released landmark's ``x, y, z``, m
            (default 0.05: a released landmark is placed by the run's sightings alone).
        release_evidence_scale: ``k``, the factor by which the run's own evidence on a
            landmark is taken to be over-confident in the test
            (:func:`lampsam.backend.map_release.release_statistic`): a lamp's sightings
            within one pass share an error that their count does not average (the map's
            pass-split test: NEES 6-8 for lab's lamps). Default 8 (1: the run's evidence taken
            as stated released lamp 1 of lab on every map and day: docs/ceiling-map.md).
        release_kinds: the kinds tested (default ``("lamp",)``: lamps are what is moved or
            replaced; lab's map corners carry a detector offset of a few millimetres that
            the next day's views see partly differently, and releasing the 3-5 corners per
            run that fail made the smoother worse, 1.53 -> 1.78 mm on the tuning runs).
    """

    sigma_start_xy: float = field(default=1e-3, metadata=limits(gt=0.0))
    sigma_start_theta: float = field(default=1e-3, metadata=limits(gt=0.0))
    var_floor: float = field(default=1e-10, metadata=limits(ge=0.0))
    map_cov_scale: float = field(default=1.0, metadata=limits(ge=0.0))
    corner_cov_scale: float = field(default=1.0, metadata=limits(ge=0.0))
    corner_bias_px: float = field(default=0.0, metadata=limits(ge=0.0))
    unique: bool = True
    corner_ncc: bool = False
    max_corners: int | None = field(default=None, metadata=limits(ge=0))
    min_corner_obs: int = field(default=10, metadata=limits(ge=0))
    max_corner_sigma: float = field(default=0.005, metadata=limits(gt=0.0))
    map_mode: MapMode = "priors"
    frame_offset: bool = True
    frame_turn: bool = False
    release: bool = True
    release_prob: float = field(default=0.999, metadata=limits(gt=0.0, lt=1.0))
    release_min_sightings: int = field(default=5, metadata=limits(ge=1))
    release_max_fraction: float = field(default=0.34, metadata=limits(ge=0.0, le=1.0))
    release_sigma: float = field(default=0.05, metadata=limits(gt=0.0))
    release_kinds: tuple[str, ...] = ("lamp",)
    release_evidence_scale: float = field(default=8.0, metadata=limits(ge=1.0))

    def __post_init__(self) -> None:
        """Check the declared ranges (:class:`FieldValueError` naming the key)."""
        check_limits(self)
        if self.map_mode not in MAP_MODES:
            raise ValueError(f"map_mode {self.map_mode!r}: expected one of {', '.join(MAP_MODES)}")
        bad = [k for k in self.release_kinds if k not in ("lamp", "corner")]
        if bad:
            raise ValueError(f"release_kinds {bad!r}: expected 'lamp' and/or 'corner'")
