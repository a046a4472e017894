"""How honest a batch map's landmark covariances are, measured on the mapping run itself.

The batch smoother treats every sighting as an independent measurement with the
frontend's stated noise, so a landmark's covariance shrinks as ``1 / n`` with its
sightings. A part of the frontend's error is the same at every sighting from one pass
under a landmark (the lamp's saturated-edge phase, a corner's detector offset, both
depending on where the landmark is seen from), and that part does not average out with
``n``: the map then states its landmarks more precisely than they are, and a localizer
that takes the map as a prior is pulled by it instead of correcting it.

**The test: split each landmark's sightings by pass.** A landmark seen in two or more
separate passes (runs of sightings with no gap longer than
:attr:`MapCalibrationConfig.pass_gap` keyframes) has its passes dealt alternately into
two groups ``a`` and ``b``. With the final graph linearised at its solution (whitened
Jacobian ``J``, residual ``r``; ``H = J^T J``), each group's own estimate of the
landmark, the poses held at the solution, is ``x_g = x* + K_g r_g`` with
``K_g = -(J_gl^T J_gl)^-1 J_gl^T`` over the group's rows (its sightings and the
landmark's priors). Under the batch's model the residual at the solution is
``r = (I - J H^-1 J^T) w``, ``w ~ N(0, I)``, so the difference ``d = x_a - x_b = K r``
(``K`` the two groups' gains, the second negated, scattered over the landmark's rows)
has the exact covariance

    Cov(d) = K K^T - (K J) H^-1 (K J)^T

(the landmark's own column of ``K J`` is ``-I + I = 0``: only the poses' columns are
left, one sparse solve with ``H`` for all landmarks). ``nees = d_xy^T Cov(d)_xy^-1 d_xy
/ 2`` is 1 on average when the sightings are independent at their stated noise; its
mean over a kind's landmarks is the factor by which that kind's independent map error
is larger than the batch states (the pass-to-pass part of the frontend's error, and any
error of the stated pixel sigma). It is measured on the map's own data: no truth, no
constant tuned on a localization run. An error that is the same on every pass (the same
detector seeing the same ceiling place the same way) is not seen by it, and need not be:
the next day's detector repeats it too (docs/ceiling-map.md).

**The fix.** A landmark whose pass-split NEES is above the chi-square test's
:attr:`MapCalibrationConfig.quantile` (2 dof; 3.0 per dof at 0.95) is inconsistent with
its stated noise: the part of its covariance that its own sightings determine, ``Sigma_l|x
= (J_l^T J_l)^-1`` (the poses held: what more sighting noise would add to), is scaled by
its NEES, ``Sigma' = Sigma + (nees - 1) Sigma_l|x`` (position block; the frame gains
``C_l = Cov(e_l, g) S^-1`` are unchanged, so the extra variance goes to ``D_l``). A
landmark seen in one pass, or consistent, keeps its covariance. Measured on lab
(docs/ceiling-map.md): a lamp's ``Sigma_l|x`` is 0.05-0.09 mm against a ``D_l`` of about
1 mm (its error is the poses', not its sightings'), so lamps barely change; a corner
on a lamp or item edge that slides with the viewpoint has a NEES of 10-80 and gets the
5-7 mm sigma its error against the truth has. Per kind, the figures (landmarks tested
and inflated, mean and median NEES, the projection residuals' chi-square per row) are
written to ``map.yaml`` under ``calibration`` (:mod:`lampsam.backend.ceiling_map_io`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import gtsam
import numpy as np
import scipy.sparse.linalg as spla

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling_graph import point_key
from lampsam.backend.ceiling_map_io import CeilingMap, MapLandmark
from lampsam.backend.map_frame import information_matrix
from lampsam.config_loader import check_limits, limits
from lampsam.errors import EstimationError

#: the position characters of the ceiling graph and the landmark kind each holds
_KINDS = {"l": "lamp", "c": "corner"}


@dataclass(frozen=True)
class MapCalibrationConfig:
    """The pass-split test (module docstring).

    Attributes:
        pass_gap: a gap of more than this many keyframes between two sightings of a
            landmark starts a new pass (default 30: about 4 s of a lab drive, longer than
            the time a ceiling landmark stays in the upward camera's view).
        quantile: a landmark whose split NEES per dof is above this quantile of
            chi-square(2) / 2 is inflated (default 0.95: 3.0; a consistent landmark is
            inflated 5 % of the time).
    """

    pass_gap: int = field(default=30, metadata=limits(ge=1))
    quantile: float = field(default=0.95, metadata=limits(gt=0.0, lt=1.0))

    def __post_init__(self) -> None:
        """Check the declared ranges (:class:`FieldValueError` naming the key)."""
        check_limits(self)

    @property
    def threshold(self) -> float:
        """The NEES per dof above which a landmark is inflated: ``-ln(1 - q)`` (the
        chi-square(2) quantile, halved)."""
        return -math.log(1.0 - self.quantile)


@dataclass(frozen=True)
class LandmarkTest:
    """One landmark's pass-split test.

    Attributes:
        kind: ``"lamp"`` or ``"corner"``.
        nees: NEES per dof of the split difference ``d_xy``, or NaN (one pass).
        cov_sightings: (3, 3) ``Sigma_l|x = (J_l^T J_l)^-1``, m^2: the position's
            covariance from its own sightings and priors, the poses held.
    """

    kind: str
    nees: float
    cov_sightings: FloatArray


@dataclass(frozen=True)
class KindCalibration:
    """The pass-split test's figures for one landmark kind (written to ``map.yaml``).

    Attributes:
        kind: ``"lamp"`` or ``"corner"``.
        landmarks_split: landmarks of the kind seen in two or more passes (tested).
        failed: of them, those above the test's threshold.
        inflated: those whose covariance was inflated (``failed``, or 0 when the test
            only reported: :func:`calibrate_map`'s ``inflate``).
        nees_mean: mean of the split NEES per dof over the tested landmarks.
        nees_median: its median.
        chi2_per_row: the kind's projection residuals, whitened (robust weights applied),
            squared and summed over their rows (all landmarks of the kind).
    """

    kind: str
    landmarks_split: int
    failed: int
    inflated: int
    nees_mean: float
    nees_median: float
    chi2_per_row: float

    def to_dict(self) -> dict[str, float | int]:
        """Plain numbers for ``map.yaml``."""
        return {k: v for k, v in dataclasses.asdict(self).items() if k != "kind"}


def split_passes(keyframes: FloatArray, gap: int) -> np.ndarray | None:
    """Group labels (0 / 1) of a landmark's sightings, passes dealt alternately.

    Args:
        keyframes: (n,) keyframe index of each sighting (any order).
        gap: more than ``gap`` keyframes between consecutive sightings starts a pass.

    Returns:
        (n,) int labels, or None when the sightings form a single pass.
    """
    k = np.asarray(keyframes, float)
    order = np.argsort(k, kind="stable")
    passes = np.zeros(len(k), int)
    passes[order[1:]] = np.cumsum(np.diff(k[order]) > gap)
    if passes.max(initial=0) == 0:
        return None
    return passes % 2


@dataclass
class _Rows:
    """One landmark's whitened rows: per factor, its Jacobian blocks and residual."""

    blocks: list[dict[int, FloatArray]] = field(default_factory=list)  # key -> (m, 3)
    b: list[FloatArray] = field(default_factory=list)  # (m,)
    pose_k: list[float] = field(default_factory=list)  # keyframe index, NaN for priors


def _landmark_rows(factors: gtsam.NonlinearFactorGraph, values: gtsam.Values
                   ) -> tuple[dict[int, _Rows], dict[str, list[float]]]:
    """Every ceiling landmark position key's linearised factors, and per kind the
    squared whitened residuals of its projection factors (for ``chi2_per_row``)."""
    rows: dict[int, _Rows] = {}
    chi2: dict[str, list[float]] = {kind: [] for kind in _KINDS.values()}
    for i in range(factors.size()):
        f = factors.at(i)
        if f is None:
            continue
        keys = [int(k) for k in f.keys()]
        chars = [chr(gtsam.Symbol(k).chr()) for k in keys]
        point = [k for k, c in zip(keys, chars, strict=True) if c in _KINDS]
        if len(point) != 1 or any(c not in _KINDS and c != "x" for c in chars):
            continue  # axis factors, odometry, priors on poses
        lin = f.linearize(values)
        a, b = lin.jacobian()
        blocks = {k: a[:, 3 * j:3 * j + 3] for j, k in enumerate(int(k) for k in lin.keys())}
        rec = rows.setdefault(point[0], _Rows())
        rec.blocks.append(blocks)
        rec.b.append(np.asarray(b, float))
        pose = [gtsam.Symbol(k).index() for k, c in zip(keys, chars, strict=True) if c == "x"]
        rec.pose_k.append(float(pose[0]) if pose else float("nan"))
        if pose:
            chi2[_KINDS[chars[keys.index(point[0])]]].append(float(np.dot(b, b)))
    return rows, chi2


def _information(rec: _Rows, key: int, members: list[int]) -> FloatArray | None:
    """``(J^T J)^-1`` of the landmark's block over factors ``members``; None if singular."""
    j_l = np.vstack([rec.blocks[i][key] for i in members])
    try:
        cov: FloatArray = np.asarray(np.linalg.inv(j_l.T @ j_l), np.float64)
    except np.linalg.LinAlgError:
        return None
    return cov if np.all(np.isfinite(cov)) else None


def _split_gain(rec: _Rows, key: int, labels: np.ndarray
                ) -> tuple[list[FloatArray], FloatArray] | None:
    """``K`` (3 x m_i per factor) of ``d = x_a - x_b``, and ``d``; None if a group's
    information is singular. Prior rows (no pose) belong to both groups."""
    sight = [i for i, k in enumerate(rec.pose_k) if not np.isnan(k)]
    priors = [i for i, k in enumerate(rec.pose_k) if np.isnan(k)]
    gains = [np.zeros((3, len(bb))) for bb in rec.b]
    d = np.zeros(3)
    for grp, sign in ((0, 1.0), (1, -1.0)):
        members = [i for j, i in enumerate(sight) if labels[j] == grp] + priors
        cov = _information(rec, key, members)
        if cov is None:
            return None
        for i in members:
            k_i = -cov @ rec.blocks[i][key].T
            gains[i] += sign * k_i
            d += sign * (k_i @ rec.b[i])
    return gains, d


def pass_split_tests(factors: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                     config: MapCalibrationConfig | None = None
                     ) -> tuple[dict[int, LandmarkTest], dict[str, list[float]]]:
    """The pass-split test of every ceiling landmark of a batch graph (module docstring).

    Args:
        factors: the batch's final factor graph (ceiling graph: 3-dof variables).
        values: its solution.
        config: the pass rule.

    Returns:
        ``(tests, chi2)``: landmark position key (``L(id)`` or ``C(id)``) -> its test
        (NaN NEES for a landmark seen in one pass), and per kind the squared whitened
        residual of each projection factor.

    Raises:
        EstimationError: the information matrix is singular.
    """
    config = config or MapCalibrationConfig()
    rows, chi2 = _landmark_rows(factors, values)
    h, col = information_matrix(factors, values)
    n = h.shape[0]
    tests: dict[int, LandmarkTest] = {}
    split: list[tuple[int, FloatArray, FloatArray, FloatArray]] = []  # key, d, KK^T, (KJ)^T
    for key, rec in rows.items():
        cov_l = _information(rec, key, list(range(len(rec.b))))
        if cov_l is None:
            continue
        tests[key] = LandmarkTest(_KINDS[chr(gtsam.Symbol(key).chr())], math.nan, cov_l)
        labels = split_passes(np.array([k for k in rec.pose_k if not np.isnan(k)]),
                              config.pass_gap)
        out = None if labels is None else _split_gain(rec, key, labels)
        if out is None:
            continue
        gains, d = out
        kk = sum((g @ g.T for g in gains), np.zeros((3, 3)))
        kj = np.zeros((n, 3))  # (K J)^T over the graph's columns; the landmark's cancels
        for g, blocks in zip(gains, rec.blocks, strict=True):
            for k, blk in blocks.items():
                if k != key:
                    kj[col[k]:col[k] + 3] += (g @ blk).T
        split.append((key, d, kk, kj))
    if not split:
        return tests, chi2
    try:
        lu = spla.splu(h)
    except RuntimeError as exc:
        raise EstimationError(f"map calibration: information matrix not invertible ({exc})") from None
    sol = lu.solve(np.hstack([kj for _, _, _, kj in split]))
    for i, (key, d, kk, kj) in enumerate(split):
        cov = kk - kj.T @ sol[:, 3 * i:3 * i + 3]
        cxy = 0.5 * (cov[:2, :2] + cov[:2, :2].T)
        if np.min(np.linalg.eigvalsh(cxy)) <= 0.0:
            continue
        nees = float(d[:2] @ np.linalg.solve(cxy, d[:2])) / 2.0
        tests[key] = dataclasses.replace(tests[key], nees=nees)
    return tests, chi2


def kind_figures(tests: dict[int, LandmarkTest], chi2: dict[str, list[float]],
                 config: MapCalibrationConfig | None = None, inflate: bool = True
                 ) -> dict[str, KindCalibration]:
    """Per kind: the pass-split figures (:class:`KindCalibration`); projection factors
    have 2 rows."""
    config = config or MapCalibrationConfig()
    out = {}
    for kind in _KINDS.values():
        vals = np.array([t.nees for t in tests.values()
                         if t.kind == kind and math.isfinite(t.nees)], float)
        res = chi2.get(kind, [])
        failed = int(np.sum(vals > config.threshold))
        out[kind] = KindCalibration(
            kind, len(vals), failed, failed if inflate else 0,
            float(np.mean(vals)) if len(vals) else math.nan,
            float(np.median(vals)) if len(vals) else math.nan,
            float(np.sum(res)) / (2 * len(res)) if res else math.nan)
    return out


def inflated_landmark(lm: MapLandmark, test: LandmarkTest | None, threshold: float) -> MapLandmark:
    """``lm`` with ``(nees - 1) Sigma_l|x`` added to its position covariance when its
    pass-split NEES is above ``threshold`` (unchanged otherwise, or with NaN marginals)."""
    if test is None or not math.isfinite(test.nees) or test.nees <= threshold:
        return lm
    if not np.all(np.isfinite(lm.cov)):
        return lm
    cov = np.array(lm.cov, float)
    cov[:3, :3] += (test.nees - 1.0) * test.cov_sightings
    return dataclasses.replace(lm, cov=0.5 * (cov + cov.T))


def calibrate_map(cmap: CeilingMap, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                  config: MapCalibrationConfig | None = None, inflate: bool = True
                  ) -> tuple[CeilingMap, dict[str, KindCalibration]]:
    """The map with every inconsistent landmark's covariance inflated (module docstring).

    Args:
        cmap: the map as the batch made it (marginals and, when present, frame model).
        factors: the batch's final factor graph.
        values: its solution.
        config: the pass rule and the test's quantile.
        inflate: inflate the landmarks that fail the test (default True); False: the
            covariances unchanged, the figures recorded.

    Returns:
        ``(calibrated map, per-kind figures)``; the map's ``calibration`` holds the
        figures for ``map.yaml``.
    """
    config = config or MapCalibrationConfig()
    tests, chi2 = pass_split_tests(factors, values, config)
    lms = [inflated_landmark(lm, tests.get(point_key(lm.kind, lm.id)), config.threshold)
           for lm in cmap.landmarks] if inflate else list(cmap.landmarks)
    figs = kind_figures(tests, chi2, config, inflate)
    out = dataclasses.replace(cmap, landmarks=lms,
                              calibration={k: v.to_dict() for k, v in figs.items()})
    return out, figs
