"""Cost-versus-map-size scaling: a power-law fit and its log-log figure.

The time of one backend update is modelled as ``t = c * n**a`` with ``n`` the number
of landmarks in the state. :func:`fit_power_law` fits ``(a, c)`` by least squares on
``log t = a log n + log c``; :func:`plot_scaling` draws finished measurements and
their fits on a given axis, :func:`save_scaling_figure` saves that figure as a PNG. The measurements themselves come from
``scripts/bench/bench_scaling.py`` (this module never estimates or times anything).

Expected exponents: the EKF's update (paper 1, eq. 23, ``P <- P - K (P H^T)^T``)
rewrites the whole ``n x n`` covariance, so ``a ~ 2``; iSAM2 on an exploration
without loop closures re-eliminates only the top of the Bayes tree, so ``a ~ 0``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from lampsam.arrays import FloatArray
from lampsam.errors import LampsamError
from lampsam.evaluation.outputs import save_figure

if TYPE_CHECKING:
    from matplotlib.axes import Axes

log = logging.getLogger(__name__)

#: Line colours per backend (same as the comparison figures).
COLORS = {"ekf": "tab:red", "ekf-dense": "tab:orange", "isam2": "tab:blue", "isam2-gtsam": "tab:cyan",
          "batch": "tab:green"}


class ScalingFitError(LampsamError):
    """A power law cannot be fitted (too few points, non-positive or NaN values)."""


@dataclass(frozen=True)
class ScalingSeries:
    """Measured update times of one backend over map sizes, and their power-law fit.

    Attributes:
        backend: backend name (``"ekf"``, ``"isam2"``).
        n_landmarks: (S,) landmarks in the state at the measured updates.
        median_s: (S,) median time per update, s.
        p95_s: (S,) 95th percentile of the time per update, s.
        exponent: fitted exponent ``a`` of ``t = c n**a`` (NaN when not fitted).
        coefficient: fitted ``c``, s (NaN when not fitted).
        fit_min_landmarks: the fit used the sizes with ``n >= fit_min_landmarks``.
    """

    backend: str
    n_landmarks: FloatArray
    median_s: FloatArray
    p95_s: FloatArray
    exponent: float = float("nan")
    coefficient: float = float("nan")
    fit_min_landmarks: float = 0.0


def fit_power_law(n: ArrayLike, t: ArrayLike) -> tuple[float, float]:
    """Least-squares fit of ``t = c * n**a`` on a log-log scale.

    Minimises ``sum_i (log t_i - a log n_i - log c)**2`` (ordinary least squares
    on the logarithms, i.e. relative errors weigh equally at every size).

    Args:
        n: (S,) sizes (e.g. number of landmarks), > 0.
        t: (S,) measured values (e.g. seconds per update), > 0.

    Returns:
        ``(exponent a, coefficient c)``; ``c`` is in the units of ``t``.

    Raises:
        ScalingFitError: different lengths, fewer than two distinct sizes, or a
            value that is not finite and positive.
    """
    n_arr = np.asarray(n, dtype=float).ravel()
    t_arr = np.asarray(t, dtype=float).ravel()
    if n_arr.shape != t_arr.shape:
        raise ScalingFitError(f"fit_power_law: {len(n_arr)} sizes but {len(t_arr)} times")
    bad = ~(np.isfinite(n_arr) & np.isfinite(t_arr) & (n_arr > 0) & (t_arr > 0))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ScalingFitError(
            f"fit_power_law: point {i} (n={n_arr[i]}, t={t_arr[i]}) is not finite and positive")
    if len(np.unique(n_arr)) < 2:
        raise ScalingFitError("fit_power_law: needs at least two distinct sizes")
    design = np.column_stack([np.log(n_arr), np.ones_like(n_arr)])
    (a, log_c), *_ = np.linalg.lstsq(design, np.log(t_arr), rcond=None)
    return float(a), float(np.exp(log_c))


def fit_series(backend: str, n: ArrayLike, median_s: ArrayLike, p95_s: ArrayLike,
               min_points: int = 3) -> ScalingSeries:
    """A :class:`ScalingSeries` with the exponent fitted over the larger sizes.

    The fit uses the ``max(min_points, ceil(S / 2))`` largest sizes: small maps are
    dominated by the per-update Python overhead, not by the asymptotic cost.

    Args:
        backend: backend name.
        n: (S,) landmarks in the state.
        median_s: (S,) median time per update, s.
        p95_s: (S,) p95 time per update, s.
        min_points: fewest sizes to fit over (default 3; all when fewer exist).

    Returns:
        The series with ``exponent``, ``coefficient`` and ``fit_min_landmarks``.

    Raises:
        ScalingFitError: see :func:`fit_power_law`.
    """
    n_arr = np.asarray(n, dtype=float)
    med = np.asarray(median_s, dtype=float)
    order = np.argsort(n_arr)
    n_arr, med, p95 = n_arr[order], med[order], np.asarray(p95_s, dtype=float)[order]
    k = min(len(n_arr), max(min_points, int(np.ceil(len(n_arr) / 2))))
    a, c = fit_power_law(n_arr[-k:], med[-k:])
    return ScalingSeries(backend, n_arr, med, p95, a, c, float(n_arr[-k]))


def plot_scaling(ax: Axes, series: list[ScalingSeries]) -> list[Any]:
    """Time per update against landmarks in the state, log-log, with the fitted lines.

    Medians are drawn as filled markers joined by a thin line, the p95 as open
    markers of the same colour, and each fit as a thick dashed line over the sizes it
    used, labelled with its exponent. Times are drawn in ms.

    Args:
        ax: target axis.
        series: finished results, one per backend.

    Returns:
        The artists drawn.
    """
    artists: list[Any] = []
    for s in series:
        color = COLORS.get(s.backend)
        artists += ax.plot(s.n_landmarks, s.median_s * 1e3, "o-", color=color, lw=1.0,
                           label=f"{s.backend} median")
        artists += ax.plot(s.n_landmarks, s.p95_s * 1e3, "^", color=color, mfc="none",
                           label=f"{s.backend} p95")
        if np.isfinite(s.exponent):
            used = s.n_landmarks[s.n_landmarks >= s.fit_min_landmarks]
            xs = np.geomspace(used.min(), used.max(), 20)
            artists += ax.plot(xs, s.coefficient * xs**s.exponent * 1e3, "--", color=color,
                               lw=2.5, alpha=0.6, label=f"{s.backend} fit: t ~ n^{s.exponent:.2f}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("landmarks in the state n [-]")
    ax.set_ylabel("time per update [ms]")
    ax.set_title("Update cost vs map size (last part of each run)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    return artists


def save_scaling_figure(path: str | Path, series: list[ScalingSeries], clock: str) -> Path:
    """The log-log figure of :func:`plot_scaling`, saved as a PNG.

    Args:
        path: output file.
        series: finished results, one per backend.
        clock: ``"cpu"`` (process CPU time) or ``"wall"``: which time the series hold,
            named on the y axis.

    Returns:
        The written path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 5.0))
    plot_scaling(ax, series)
    what = "CPU (process) time" if clock == "cpu" else "wall-clock time"
    ax.set_ylabel(f"{what} per update [ms]")
    fig.tight_layout()
    return save_figure(fig, path, dpi=120)
