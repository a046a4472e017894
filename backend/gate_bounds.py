"""Exact gate decisions from cheap bounds on the eq.-19 innovation covariance.

The exact gate of a ceiling lamp (paper eq. 19) needs the innovation covariance

    Psi = Var(u + v) + R,   u = H_p dx,  v = H_l dl,

with the pose-landmark cross-covariance inside ``Var(u + v)``; iSAM2 gives it only
through the joint marginal of the pose and the landmark, which for a lamp last seen
long ago walks the Bayes tree from the lamp's old clique to the root (tens of ms at a
revisit, docs/speed.md). Without the cross term the covariance is bounded on both
sides: for every ``t > 0``

    (1 - t) A + (1 - 1/t) B  <=  Var(u + v)  <=  (1 + t) A + (1 + 1/t) B

(the differences are ``Var(sqrt(t) u -/+ v / sqrt(t))``), with ``A = Var(u)`` exact
(the current pose marginal) and ``B`` any upper bound of ``Var(v)`` (the landmark's
initialisation covariance: later factors only add information). That brackets the
squared Mahalanobis distance ``d2 = nu^T Psi^-1 nu`` in ``[lo, hi]``
(:func:`d2_interval`). :func:`resolve_screened` then settles every pair whose
association outcome is the same anywhere in its interval, so the joint marginal is
asked only for the pairs the bounds cannot decide; every gate decision is the one the
exact distances give.
"""

from __future__ import annotations

import math

import numpy as np

from lampsam.arrays import FloatArray

#: ``t`` values over which the bounds are tightened (each gives a valid bound).
T_GRID = np.geomspace(1.0 / 256.0, 256.0, 33)

#: Relative widening of every interval, against round-off in the two computations.
REL_MARGIN = 1e-6


def d2_interval(nu: FloatArray, a: FloatArray, b: FloatArray, r: FloatArray
                ) -> tuple[FloatArray, FloatArray]:
    """Bounds ``lo <= nu^T Psi^-1 nu <= hi`` without the cross-covariance.

    ``Psi = Var(u + v) + R`` with ``Var(u) = A`` and ``Var(v) <= B`` (module docstring):
    ``hi`` from the lower bounds ``R + (1 - t) A - (1/t - 1) B`` (``t <= 1``, where
    positive definite; ``t = 1`` is ``R`` alone), ``lo`` from the upper bounds
    ``R + (1 + t) A + (1 + 1/t) B``, each the best over :data:`T_GRID`.

    Args:
        nu: (P, m) innovations (measurement units, e.g. px and rad).
        a: (P, m, m) ``H_p Sigma_x H_p^T``, the pose part (exact).
        b: (P, m, m) ``H_l U_l H_l^T`` with ``U_l`` an upper bound of the landmark's
            marginal covariance.
        r: (P, m, m) measurement noise.

    Returns:
        ``(lo (P,), hi (P,))``, widened by :data:`REL_MARGIN`.
    """
    nu = np.asarray(nu, float)
    n = len(nu)
    if n == 0:
        return np.zeros(0), np.zeros(0)
    t = T_GRID[:, None, None, None]
    up = r[None] + (1.0 + t) * a[None] + (1.0 + 1.0 / t) * b[None]  # (T, P, m, m)
    sol = np.linalg.solve(up, np.broadcast_to(nu[None, :, :, None], (*up.shape[:2], nu.shape[1], 1)))
    lo = np.max(np.einsum("pi,tpi->tp", nu, sol[..., 0]), axis=0)
    tl = T_GRID[T_GRID <= 1.0][:, None, None, None]
    low = r[None] + (1.0 - tl) * a[None] - (1.0 / tl - 1.0) * b[None]
    hi = np.full(n, math.inf)
    for j in range(low.shape[0]):
        ev = np.linalg.eigvalsh(low[j])
        ok = ev[:, 0] > 1e-12 * np.maximum(ev[:, -1], 1e-300)
        if not ok.any():
            continue
        s = np.linalg.solve(low[j][ok], nu[ok][..., None])[..., 0]
        hi[ok] = np.minimum(hi[ok], np.einsum("pi,pi->p", nu[ok], s))
    return lo * (1.0 - REL_MARGIN), hi * (1.0 + REL_MARGIN)


Screened = dict[int, dict[int, tuple[float, bool]]]


def resolve_screened(screened: Screened, intervals: dict[tuple[int, int], tuple[float, float]],
                     gates: dict[int, tuple[float, float]]) -> int:
    """Mark the pairs whose association outcome the intervals settle as exact, in place.

    Only the observations in ``gates`` (lamps) are looked at. A pair that
    :func:`~lampsam.backend.association.associate` would send to the exact gate
    (inexact, screened below the gate) has the interval ``intervals[(i, lid)]`` if
    bounded, else ``[0, inf]``; exact pairs and screen-only pairs beyond the gate
    are points. With ``g`` the gate and ``n`` the new-landmark threshold of
    observation ``i``:

    - ``i`` has exactly one pair that can be inside (``lo < g``), it is surely inside
      (``hi < g``) and no other observation can be inside that landmark's gate: the
      greedy one-to-one assignment matches them whatever the exact distances, so
      every bounded pair of ``i`` becomes exact (the match with ``hi``, the others
      with ``lo``, all beyond the gate);
    - ``i`` has no pair that can be inside: it is unmatched, and new or dropped by
      its smallest distance against ``n``; a bounded pair is settled when
      ``lo > n`` or ``hi <= n`` (value ``lo``/``hi``, same side of ``n`` as the exact
      one), or whatever its value when another pair surely puts the smallest
      distance at or under ``n``;
    - otherwise (two or more possible matches, or a shared landmark) nothing of ``i``
      changes and the exact gate decides, as without the bounds.

    Args:
        screened: :func:`associate`'s pre-screen (obs index -> {landmark id: (d2, exact)}).
        intervals: ``(obs index, landmark id) -> (lo, hi)`` of the exact distance.
        gates: obs index -> ``(gate, new-landmark threshold)`` for the observations
            to resolve.

    Returns:
        The number of pairs marked exact.
    """
    spans: dict[int, dict[int, tuple[float, float, bool]]] = {}  # i -> lid -> (lo, hi, bounded)
    possible: dict[int, int] = {}  # landmark id -> observations that may be inside its gate
    for i, (gate, _) in gates.items():
        row: dict[int, tuple[float, float, bool]] = {}
        for lid, (d2, exact) in screened.get(i, {}).items():
            if exact or d2 >= gate:  # a final distance, or a screen-only one beyond the gate
                row[lid] = (d2, d2, False)
            elif (i, lid) in intervals:
                lo, hi = intervals[(i, lid)]
                row[lid] = (lo, hi, True)
            else:
                row[lid] = (0.0, math.inf, False)
            if row[lid][0] < gate:
                possible[lid] = possible.get(lid, 0) + 1
        spans[i] = row
    n_marked = 0
    for i, row in spans.items():
        gate, new_t = gates[i]
        inside = [lid for lid, (lo, _, _) in row.items() if lo < gate]
        values: dict[int, float] = {}
        if len(inside) == 1:
            lid = inside[0]
            hi = row[lid][1]
            if not hi < gate or possible[lid] != 1:
                continue
            values = {other: (h if other == lid else lo_o)
                      for other, (lo_o, h, b) in row.items() if b}
        elif not inside:
            surely_low = any(hi <= new_t for _, hi, _ in row.values())
            for lid, (lo, hi, bounded) in row.items():
                if bounded and (surely_low or lo > new_t):
                    values[lid] = lo
                elif bounded and hi <= new_t:
                    values[lid] = hi
        for lid, v in values.items():
            screened[i][lid] = (float(v), True)
            n_marked += 1
    return n_marked
