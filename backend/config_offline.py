"""Configuration of the offline passes: batch Levenberg-Marquardt (``[batch]``) and the
batch re-association without ids (``[reassociation]``).

Frozen dataclasses with documented defaults, checked on construction like the rest of
:mod:`lampsam.backend.config` (which composes them into ``SlamConfig`` and re-exports them).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import gtsam

from lampsam.config_loader import FieldValueError, check_limits, limits


@dataclass(frozen=True)
class BatchConfig:
    """Offline Levenberg-Marquardt over the whole run.

    Attributes:
        init: ``"isam2"`` (start LM from the online iSAM2 estimate, default) or
            ``"odometry"`` (start from odometry and first-sight landmark estimates;
            association then uses that running estimate).
        huber_k: Huber threshold in sigmas for measurement factors, or None for
            plain Gaussian noise (default None).
        max_iterations: LM iterations (default 100).
        relative_error_tol: LM relative error decrease to stop (default 1e-4).
            From the iSAM2 start the whole lab graph's error settles within 1e-4
            after three iterations (1e-6 took six, with no change in the
            estimate's accuracy: each iteration is about a second on the lab run).
        ordering: GTSAM's elimination ordering for LM, ``"METIS"`` (default) or
            ``"COLAMD"``; METIS was about 10 % faster on the lab graph.
    """

    init: str = "isam2"
    huber_k: float | None = field(default=None, metadata=limits(gt=0.0))
    max_iterations: int = field(default=100, metadata=limits(ge=1))
    relative_error_tol: float = field(default=1e-4, metadata=limits(ge=0.0))
    ordering: str = "METIS"

    def __post_init__(self) -> None:
        """Check the declared ranges (:class:`FieldValueError` naming the key)."""
        check_limits(self)
        if self.init not in ("isam2", "odometry"):
            raise FieldValueError("init", f"must be 'isam2' or 'odometry', got {self.init!r}")
        if self.ordering not in ("METIS", "COLAMD", "NATURAL"):
            raise FieldValueError("ordering", f"must be 'METIS', 'COLAMD' or 'NATURAL', got {self.ordering!r}")

    def to_gtsam(self) -> gtsam.LevenbergMarquardtParams:
        """The ``gtsam.LevenbergMarquardtParams`` for this config."""
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.max_iterations)
        params.setRelativeErrorTol(self.relative_error_tol)
        params.setOrderingType(self.ordering)
        return params


@dataclass(frozen=True)
class ReassociationConfig:
    """Batch re-association without ids (:mod:`lampsam.backend.reassociate`; TOML
    ``[reassociation]``): the batch backend without ids revises the online pass's
    association against the optimised map.

    Attributes:
        passes: passes at most (default 0: off, the online association is final).
        window: new landmarks per revisit constellation (default 12).
        revisit_keyframes: an old landmark is a revisit candidate when idle this many
            keyframes before the constellation's first landmark was made (default 300).
        radius: old landmarks within this distance of the constellation's centre, m (default 100).
        tol: inlier distance and pair-length tolerance, m (the optimised map's
            non-rigidity across a revisit; default 0.75).
        min_inliers: inliers a revisit alignment needs (default 4).
        margin: inliers by which it must beat any differently-paired hypothesis (default 2).
        max_rotation: largest rotation believed, rad (default 0.5).
        merge_radius: duplicate pairs closer than this are tested, m (default 10; 0: no pair test).
        switch: a sighting inside the gate of its landmark moves to another landmark
            closer by more than this in squared Mahalanobis distance (default inf: never).
        fit_noise: the re-association's gate uses the sightings' noise shrunk to their
            own spread at each pass's optimum (its variance-component factor, never above 1:
            :func:`lampsam.backend.reassociate.noise_factor`), and a sighting beyond the
            new-landmark threshold of its landmark and outside every gate splits off
            (default False).
        cost_moves: after the passes, merge and split single landmarks by description
            length (:mod:`lampsam.backend.landmark_moves`; the offline pipeline of
            :mod:`lampsam.backend.noids_offline` only; default True).
        final_pass: on the chosen candidate only, single sightings move to another
            landmark inside their gate (or a new one), and landmark pairs merge with the
            poses free, where that lowers the description length
            (:func:`lampsam.backend.final_moves.refine_final`; default True).
        final_rounds: LM re-solves of the final pass at most (default 30).
        readmit_dropped: the final pass first takes back the sightings the online pass
            dropped where a landmark explains one at ``d2 < c_new``
            (:func:`lampsam.backend.final_moves.readmit`), kept if ``C`` falls. Default False: on
            Victoria Park it took back 134 of 138 and lowered ``C``, but the RMS from
            the known-id batch rose 0.372 -> 0.431 m and 14 went to a neighbour's
            landmark (docs/noids-offline.md).
        scales: candidate odometry variance factors of the online no-ids pass that
            precedes the offline re-association of a graph log
            (:mod:`lampsam.backend.noids_offline`): each is run, and the association with
            the least description length is kept (default 1/16, 1/4, 1, 4, 16, 64: sigma
            x1/4-x8; the factors below 1 for logs that overstate their odometry noise,
            as GTSAM's victoriaPark_reduced_1k and cityTrees_reduced_1k do ~20x in
            sigma: docs/noids-offline.md).
        online_final: a graph text log run online without ids (``lampsam slam LOG
            --no-ids --backend isam2``, or ``ekf`` / ``batch`` with ``passes = 0``) ends
            with a final solve: the online run's association re-solved in batch at the
            log's stated noise (:mod:`lampsam.backend.online_final`: the re-association
            passes, the cost moves and the final pass as above); ``trajectory.tum`` /
            ``landmarks.csv`` are then its answer and ``online.tum`` the online poses
            (default True: docs/noids-offline.md, "online runs: the final solve").
        online_final_cov_scale: the final solve's odometry covariance factor on the
            log's stated covariance (default 1: as stated; the online pass's
            ``[pose2_odometry] cov_scale`` does not apply to it).
        online_final_passes: re-association passes of the final solve at most (default
            20, as the offline bench; they stop when the association stops changing).
        online_final_singletons: the final solve starts with every sighting the online
            run held and never used, or dropped, as a landmark of its own, for the
            description-length merges to place (default False).
        online_candidates: with ``online_final``, settings of the online pass to
            try, each run online and final-solved, the final solve with the least
            description length ``C`` kept (:func:`lampsam.backend.online_final.run_online_picker`); a candidate
            whose online run fails, or is stopped, loses. Each is a string of
            ``+``-joined changes to the config as given (:func:`online_candidate_changes`):
            ``defaults`` (none), ``planar_unique``, ``revisit_check``, ``both`` (the
            two), ``cov_scale=X`` (the online pass's ``[pose2_odometry] cov_scale``; X
            a number or a fraction such as ``1/16``), ``alias_odds=X`` (the online
            pass's ``[association] alias_odds``, for aliased sparse logs). Only the
            online pass sees them: every final solve runs with the config as given, so
            ``C`` compares like with like. Empty: the online pass runs once with the
            config as given. Default ``defaults``, ``both+cov_scale=16``,
            ``cov_scale=1/16``, ``alias_odds=1`` (the stated setting; the one that holds
            Victoria Park online; the one that holds victoriaPark_reduced_1k, whose
            stated odometry noise is ~4x too large in sigma; the alias test, the one
            that holds cityTrees_reduced_1k, a grid of trees sighted a few at a time,
            chosen there with ``online_label_entropy``: docs/noids-aliasing.md, last
            section): no divergence added on the logs measured, for the sum of the
            candidates' CPU (docs/noids-offline.md, "The online picker").
        online_candidate_cpu_factor: a candidate's online run is stopped (and loses)
            once its process CPU exceeds this factor times the least CPU (online run and
            final solve) of the candidates finished before it, or
            ``online_candidate_cpu_floor_s`` if that is more (default 5; inf: never
            stopped). A candidate that starves (holds most sightings as ambiguous) runs
            far longer than one that holds: on MRCLAM 68 s against 1.8 s.
        online_candidate_cpu_floor_s: the least budget of a candidate's online run, s of
            process CPU (default 30).
        online_final_held_mixture: after the final solve, the sightings the online run
            held and never used, or dropped, enter it as max-mixture factors
            (:mod:`lampsam.backend.held_placement`): each is explained by the best of its
            candidate landmarks (those within the new-landmark threshold at the final
            map) or by none (cost ``c_new``), chosen again at every linearisation; the
            placement is kept if the description length ``C`` fell. With the online
            picker it runs on the chosen candidate only, after the pick (in every
            candidate it swayed the pick: MRCLAM chose ``cov_scale=1/16``, 0.342 m).
            Default True: nearer GTSAM's LM on every log measured but Victoria Park
            (MRCLAM 0.005 -> 0.000 m, cityTrees 0.025 -> 0.014, held-out loop 0.203 ->
            0.073, corridor 0.065 -> 0.017, carpark 0.001 -> 0.000); Victoria Park
            0.180 -> 0.300 m from LM, where the final map merges four twin id pairs that
            LM keeps apart (from the known-id optimum with them merged 0.199 -> 0.109 m),
            108 landmarks seen 2+ for 119 trees (was 107: the count within 10 %);
            docs/noids-offline.md, "Placing the held sightings".
        online_final_held_new_landmarks: with ``online_final_held_mixture``, clusters of
            left-out sightings that pay as landmarks of their own (two sightings or more,
            joined inside the association gate) are candidates too (default False: Victoria
            Park 117 landmarks for 119 trees against 108 without, but on the held-out loop
            and corridor logs they map trees twice, 62 landmarks for 50 and 137 for 120).
        online_label_entropy: the online picker compares candidates by ``C`` plus twice
            the entropy of each recorded sighting's label among its rival landmarks
            (:mod:`lampsam.backend.label_entropy`, the ICL of mixture models): a map that
            splits one landmark into copies closer than the noise pays for its guessed
            labels; a candidate whose sightings fit worse than stated is scored at its
            own noise scale (default True: with it ``C`` no longer takes the alias
            test's split map on MRCLAM; False: ``C`` alone, docs/noids-aliasing.md).
        online_first_cpu_per_sighting: the CPU budget of the first online candidate's
            online run (the later ones have ``online_candidate_cpu_factor``'s), s of
            process CPU per range-bearing sighting of the log, at least
            ``online_candidate_cpu_floor_s`` (default 0.05: 467 s on the 9,342
            sightings of the held-out pillars log; the slowest first candidate measured
            used 0.012 s per sighting, Victoria Park's 44 s; inf: no budget). Past it
            the run stops and loses, as a later candidate past its own budget.
        final_solve_cpu_per_sighting: the CPU budget of each final solve (the
            re-association passes with their duplicate merges, the description-length
            moves, the final pass, the placement of the left-out sightings), s of
            process CPU per range-bearing sighting, at least
            ``online_candidate_cpu_floor_s`` (default 0.05; inf: no budget). Past it
            the solve stops at the next pass, round or stage and keeps the last one it
            accepted (a warning names the stage; ``summary.json`` has
            ``noids_stopped_by_budget`` and the candidate's ``stopped_by_budget``).
            docs/noids-aliasing.md, last section.
        online_final_held_new_unexplained: with ``online_final_held_new_landmarks``, only
            the left-out sightings that no mapped landmark explains (none within ``c_new``
            at the final map) are clustered into new landmarks (default True; False: all
            of them, session 17's rule, which mapped trees twice on the held-out loop).
        online_final_held_new_merge: with ``online_final_held_new_landmarks``, the final
            pass's merges and single moves (:mod:`lampsam.backend.final_moves`) run again
            after the placement, each kept only if ``C`` falls, so a tree mapped twice is
            merged back (default True). docs/noids-offline.md, "Victoria Park: the
            reference and the trees never mapped".
        online_final_held_residual_scale: with ``online_final_held_mixture``, each
            left-out sighting's choice among its candidate landmarks and "none" is made at
            the noise the final solve's residuals show: the threshold and the "none" cost
            are ``c_new`` times the sightings' chi-square per dof, at most 1 (default
            False; Victoria Park's sightings fit at 0.09 of their stated variance, and its
            wrong placements are of trees 3-10 m from the landmark they were put on).
    """

    passes: int = field(default=0, metadata=limits(ge=0))
    window: int = field(default=12, metadata=limits(ge=3))
    revisit_keyframes: int = field(default=300, metadata=limits(ge=1))
    radius: float = field(default=100.0, metadata=limits(gt=0.0))
    tol: float = field(default=0.75, metadata=limits(gt=0.0))
    min_inliers: int = field(default=4, metadata=limits(ge=3))
    margin: int = field(default=2, metadata=limits(ge=1))
    max_rotation: float = field(default=0.5, metadata=limits(gt=0.0))
    merge_radius: float = field(default=10.0, metadata=limits(ge=0.0))
    switch: float = field(default=float("inf"), metadata=limits(gt=0.0, finite=False))
    fit_noise: bool = False
    cost_moves: bool = True
    final_pass: bool = True
    final_rounds: int = field(default=30, metadata=limits(ge=1))
    readmit_dropped: bool = False
    scales: tuple[float, ...] = (0.0625, 0.25, 1.0, 4.0, 16.0, 64.0)
    online_final: bool = True
    online_final_cov_scale: float = field(default=1.0, metadata=limits(gt=0.0))
    online_final_passes: int = field(default=20, metadata=limits(ge=1))
    online_final_singletons: bool = False
    online_candidates: tuple[str, ...] = ("defaults", "both+cov_scale=16", "cov_scale=1/16",
                                          "alias_odds=1")
    online_candidate_cpu_factor: float = field(default=5.0,
                                               metadata=limits(ge=1.0, finite=False))
    online_candidate_cpu_floor_s: float = field(default=30.0, metadata=limits(ge=0.0))
    online_final_held_mixture: bool = True
    online_final_held_new_landmarks: bool = False
    online_label_entropy: bool = True
    online_first_cpu_per_sighting: float = field(default=0.05,
                                                 metadata=limits(gt=0.0, finite=False))
    final_solve_cpu_per_sighting: float = field(default=0.05,
                                                metadata=limits(gt=0.0, finite=False))
    # vpgap
    online_final_held_new_unexplained: bool = True
    online_final_held_new_merge: bool = True
    online_final_held_residual_scale: bool = False

    def __post_init__(self) -> None:
        """Check the declared ranges (:class:`FieldValueError` naming the key)."""
        check_limits(self)
        if not self.scales or any(not q > 0 for q in self.scales):
            raise FieldValueError("scales", f"needs one or more factors > 0, got {self.scales}")
        for i, spec in enumerate(self.online_candidates):
            try:
                online_candidate_changes(spec)
            except ValueError as exc:
                raise FieldValueError(f"online_candidates[{i}]", str(exc)) from None
        if len(set(self.online_candidates)) != len(self.online_candidates):
            raise FieldValueError("online_candidates",
                                  f"names a candidate twice: {list(self.online_candidates)}")


#: ``online_candidates`` tokens that switch an ``[association]`` option on
_ASSOCIATION_TOKENS = {"planar_unique": ("planar_unique",),
                       "revisit_check": ("revisit_check",),
                       "both": ("planar_unique", "revisit_check")}


def online_candidate_changes(spec: str) -> tuple[dict[str, Any], float | None]:
    """The changes one ``[reassociation] online_candidates`` entry makes to the online pass.

    Args:
        spec: ``+``-joined tokens: ``defaults``, ``planar_unique``, ``revisit_check``,
            ``both``, ``cov_scale=X``, ``alias_odds=X`` (X > 0: a number or ``a/b``);
            e.g. ``"both+cov_scale=16"``.

    Returns:
        ``(association options and their values, the online pass's cov_scale or None)``.

    Raises:
        ValueError: an unknown token (the message names it and the known ones), an
            empty entry, a bad or non-positive ``cov_scale`` / ``alias_odds``, or ``defaults`` with others.
    """
    tokens = [t.strip() for t in spec.split("+")]
    if not spec.strip() or any(not t for t in tokens):
        raise ValueError(f"empty candidate or token in {spec!r}")
    if "defaults" in tokens and len(tokens) > 1:
        raise ValueError(f"'defaults' stands alone, got {spec!r}")
    assoc: dict[str, Any] = {}
    cov: float | None = None
    for t in tokens:
        if t == "defaults":
            continue
        if t in _ASSOCIATION_TOKENS:
            assoc.update(dict.fromkeys(_ASSOCIATION_TOKENS[t], True))
            continue
        name, sep, text = t.partition("=")
        if name.strip() == "alias_odds" and sep:
            assoc["alias_odds"] = _positive_number(text, spec, "alias_odds")
            continue
        if name.strip() != "cov_scale" or not sep:
            raise ValueError(f"unknown token {t!r} in {spec!r} (known: defaults, "
                             f"{', '.join(_ASSOCIATION_TOKENS)}, cov_scale=X, alias_odds=X)")
        cov = _positive_number(text, spec, "cov_scale")
    return assoc, cov


def _positive_number(text: str, spec: str, key: str) -> float:
    """``text`` (a number or ``a/b``) as a finite float > 0; ValueError naming ``key``."""
    num, slash, den = text.partition("/")
    try:
        value = float(num) / (float(den) if slash else 1.0)
    except (ValueError, ZeroDivisionError):
        raise ValueError(f"{key} in {spec!r}: not a number or fraction: {text!r}") from None
    if not (value > 0 and value < float("inf")):
        raise ValueError(f"{key} in {spec!r} must be > 0 and finite, got {text!r}")
    return value
