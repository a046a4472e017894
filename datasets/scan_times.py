"""Strictly increasing scan times from the time stamps a laser log gives (CARMEN reader).

Real CARMEN logs of other buildings print the time with 6 significant digits
(``1.13486e+09`` on every scan) or write 0, so their stamps cannot order the scans.
:func:`derive_scan_times` takes the message stamps when they increase, else the logger's,
else spreads runs of equal stamps evenly between distinct values, else counts scans at a
nominal rate, and says which (:mod:`lampsam.datasets.carmen` logs it once).

Times in seconds; arrays (N,) in file order.
"""

from __future__ import annotations

import numpy as np

from lampsam.arrays import FloatArray

#: Scan rate assumed when a log has no usable time stamps at all, Hz.
NOMINAL_SCAN_RATE_HZ = 5.0


def _increasing(t: FloatArray) -> bool:
    """Whether ``t`` is finite and strictly increasing."""
    return bool(np.all(np.isfinite(t)) and np.all(np.diff(t) > 0))


def _spread_equal_stamps(stamps: FloatArray) -> tuple[FloatArray, float] | None:
    """Spread runs of equal stamps evenly between distinct stamps (coarse stamps).

    A run of ``c`` scans stamped ``v`` and followed by the stamp ``w`` is spread as
    ``v + (w - v) * k / c``, ``k = 0..c-1`` when it is bounded on both sides (an
    interior run: the stamps only say that its scans lie in ``[v, w)``). The first run
    (its start unknown) ends at the median interior step before ``w`` (a single scan
    keeps its stamp), the last run continues at that step.

    Args:
        stamps: (N,) non-decreasing stamps, s.

    Returns:
        ``(t, step)``: (N,) strictly increasing times and the median interior step, s;
        None when there is no interior run (fewer than three distinct stamps), as the
        step is then unknown.
    """
    n = len(stamps)
    change = np.r_[True, stamps[1:] != stamps[:-1]]
    starts = np.flatnonzero(change)
    if len(starts) < 3:
        return None
    counts = np.diff(np.r_[starts, n])
    values = stamps[starts]
    steps = np.empty(len(values))
    steps[:-1] = np.diff(values) / counts[:-1]
    step = float(np.median(steps[1:-1]))
    steps[-1] = step
    run = np.cumsum(change) - 1
    t = values[run] + steps[run] * (np.arange(n) - starts[run])
    c0 = int(counts[0])
    if c0 > 1:
        step0 = min(step, float(values[1] - values[0]) / c0)
        t[:c0] = values[1] - step0 * (c0 - np.arange(c0))
    return t, step


def derive_scan_times(stamps: FloatArray, logger_stamps: FloatArray,
                      rate_hz: float = NOMINAL_SCAN_RATE_HZ) -> tuple[FloatArray, str, str]:
    """Strictly increasing scan times from the stamps a log gives, in file order.

    In order of preference: the message stamps when they increase; the logger's
    stamps when they increase; the message (else logger) stamps with runs of equal
    values spread evenly between distinct values (:func:`_spread_equal_stamps`, needs
    three distinct values); else a count at ``rate_hz``, placed so that the first
    change of stamp (if any) falls on its new value (coarse stamps that change once,
    or all equal, e.g. all 0).

    Args:
        stamps: (N,) message time stamps, s, non-decreasing.
        logger_stamps: (N,) the logger's stamps, s (NaN where absent).
        rate_hz: the nominal scan rate for the last resort, Hz.

    Returns:
        ``(t, source, note)``: (N,) times, s; ``log``, ``logger``, ``spread`` or
        ``rate``; and a sentence saying what was done ("" for ``log``).
    """
    n = len(stamps)
    if n < 2 or _increasing(stamps):
        return stamps.astype(float), "log", ""
    n_ties = int(np.sum(stamps[1:] == stamps[:-1]))
    n_distinct = len(np.unique(stamps))
    what = (f"{n_ties} of {n} scans repeat the previous time stamp ({n_distinct} distinct "
            f"values, e.g. {stamps[0]:.6g})")
    if _increasing(logger_stamps):
        return logger_stamps.astype(float), "logger", f"{what}: used the logger's time stamps"
    for name, s in (("message", stamps), ("logger", logger_stamps)):
        if np.all(np.isfinite(s)) and np.all(np.diff(s) >= 0):
            spread = _spread_equal_stamps(s.astype(float))
            if spread is not None:
                return spread[0], "spread", (
                    f"{what}: spread the scans evenly between the distinct {name} stamps "
                    f"(median step {spread[1]:.3g} s)")
    changes = np.flatnonzero(stamps[1:] != stamps[:-1]) + 1
    k = int(changes[0]) if len(changes) else 0
    t = float(stamps[k]) + (np.arange(n) - k) / rate_hz
    return t, "rate", (f"{what}: too few distinct stamps to interpolate, times counted at "
                       f"the nominal {rate_hz:g} Hz in file order (scan {k} at {stamps[k]:.6g} s)")
