"""A bracket of the exact gate distance from the pose and landmark marginals alone (issue 19).

The exact gate of the smoothers (:meth:`~lampsam.backend.gate_exact.ExactGate._innovation`,
paper eqs. 19-20) needs iSAM2's joint marginal of the last keyframe pose and the
landmark, because the pose-landmark cross-covariance matters. That query is cheap
for a landmark near the Bayes tree's root and costs 10-40 ms for one that was not
observed at the last keyframes (docs/speed.md). This module brackets the exact
distance without the cross term, from blocks that are cheap to have:

- ``A = H_p Sigma_x H_p^T`` with ``Sigma_x`` the current pose marginal (exact: the
  last keyframe's marginal composed with the odometry since, computed once per
  keyframe);
- ``B = H_l Sigma_l H_l^T`` with ``Sigma_l`` an **upper bound** of the landmark's
  marginal: its block of the last exact joint marginal, while iSAM2 has not
  relinearised since (at one linearisation a marginal only shrinks as factors are
  added; new Jacobians can widen it, so the record is dropped then);
- ``R`` the measurement noise.

**The bounds.** Let ``u = H_p dx``, ``v = H_l dl`` (jointly Gaussian, zero mean) and
``K = E[u v^T]`` the unknown cross term, so ``Var(u + v) = A + B_true + K + K^T``.
For any ``t > 0``, since ``Var(sqrt(t) u -/+ v / sqrt(t)) = t A + B_true / t -/+ (K + K^T)``
is positive semi-definite:

- upper: ``Var(u + v) = (1 + t) A + (1 + 1/t) B_true - Var(sqrt(t) u - v / sqrt(t))
  <= (1 + t) A + (1 + 1/t) B`` (``B_true <= B``); ``t = 1`` is ``2 (A + B)``;
- lower, ``0 < t < 1``: ``Var(u + v) = (1 - t) A + (1 - 1/t) B_true
  + Var(sqrt(t) u + v / sqrt(t)) >= (1 - t) A + (1 - 1/t) B`` (``1 - 1/t < 0``, so the
  upper bound ``B`` keeps it a lower bound); and always ``Var(u + v) >= 0``.

With ``S = Var(u + v) + R`` the exact innovation covariance and
``S_lo <= S <= S_hi`` in the Loewner order (``S_lo`` positive definite), inversion
reverses the order, so ``d2 = nu^T S^-1 nu`` satisfies
``nu^T S_hi^-1 nu <= d2 <= nu^T S_lo^-1 nu`` (the Cauchy-Schwarz bound of the cross
term, e.g. Bar-Shalom, Li & Kirubarajan 2001, sec. 1.4; here in matrix form).
Every ``t`` gives a valid bracket; the best of a few per pair is taken, around
``t* = sqrt(nu^T B nu / nu^T A nu)`` (the scalar optimum of both bounds) and ``t = 1``.

A pair whose association outcome is the same anywhere in its bracket is settled
without the joint marginal (:func:`settle_bracketed`): surely inside the gate and
nothing to compete with, or beyond the new-landmark threshold.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from lampsam.arrays import FloatArray

#: Multiples of ``t*`` tried for each bound (any ``t > 0`` is valid).
T_FACTORS = np.array([0.5, 0.71, 1.0, 1.41, 2.0])
#: The lower bound's ``t`` is kept below this (at ``t = 1`` it is ``R`` alone).
T_LOWER_MAX = 0.999
#: Relative margin for rounding: a bracket end is trusted to this fraction.
ROUNDING = 1e-9


def _quad(s: FloatArray, nu: FloatArray) -> FloatArray:
    """``nu^T S^-1 nu`` for stacked ``S`` (n, T, m, m) and ``nu`` (n, m) -> (n, T)."""
    nus = np.broadcast_to(nu[:, None, :, None], (*s.shape[:-1], 1))
    return np.einsum("ntm,ntm->nt", nus[..., 0], np.linalg.solve(s, nus)[..., 0])


def bracket_d2(nu: FloatArray, a: FloatArray, b: FloatArray | None, r: FloatArray,
               r_only: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
    """Lower and upper bounds of the exact eq.-20 distance of n pairs (module docstring).

    Args:
        nu: (n, m) innovations.
        a: (n, m, m) pose parts ``H_p Sigma_x H_p^T`` (exact).
        b: (n, m, m) landmark parts ``H_l Sigma_l H_l^T`` from an upper bound of the
            landmark marginal, or None when there is none (the bracket is then
            ``[0, nu^T R^-1 nu]``).
        r: (n, m, m) measurement noise.
        r_only: optional (n,) bool: rows for which ``[0, nu^T R^-1 nu]`` is enough (the
            bounds over ``t`` are not computed for them).

    Returns:
        ``(lo, hi)``, each (n,): ``lo <= nu^T S^-1 nu <= hi`` for every joint
        covariance whose marginal blocks give ``a`` and at most ``b``.
    """
    nu = np.asarray(nu, float)
    hi_r = _quad(np.asarray(r, float)[:, None], nu)[:, 0]
    lo_out = np.zeros(len(nu))
    if b is None or not len(nu):
        return lo_out, hi_r
    if r_only is not None:
        rows = np.flatnonzero(~np.asarray(r_only, bool))
        if len(rows) < len(nu):
            if len(rows):
                lo_out[rows], hi_r[rows] = bracket_d2(nu[rows], a[rows], b[rows], r[rows])
            return lo_out, hi_r
    na = np.einsum("ni,nij,nj->n", nu, a, nu)
    nb = np.einsum("ni,nij,nj->n", nu, b, nu)
    t_star = np.sqrt(np.maximum(nb, 1e-300) / np.maximum(na, 1e-300))
    # around t*, and t = 1 (the plain ``2 (A + B)``, so never looser than it)
    t = np.concatenate([t_star[:, None] * T_FACTORS[None, :], np.ones((len(nu), 1))],
                       axis=1)[..., None, None]  # (n, T, 1, 1)
    a4, b4, r4 = a[:, None], b[:, None], r[:, None]
    lo = np.max(_quad((1.0 + t) * a4 + (1.0 + 1.0 / t) * b4 + r4, nu), axis=1)
    t_lo = np.minimum(t, T_LOWER_MAX)
    s_lo = (1.0 - t_lo) * a4 + (1.0 - 1.0 / t_lo) * b4 + r4
    pd = np.all(np.linalg.eigvalsh(s_lo) > 0.0, axis=-1)  # (n, T)
    s_safe = np.where(pd[..., None, None], s_lo, r4)  # R where the bound is not PD
    hi = np.minimum(hi_r, np.min(_quad(s_safe, nu), axis=1))
    return lo, hi


def sole_candidates(pairs: Mapping[int, Mapping[int, float]], gate: Mapping[int, float]
                    ) -> set[tuple[int, int]]:
    """Pairs that are their observation's only candidate, of a landmark no other observation wants.

    A candidate is a pair whose screen distance is below the observation's gate (the
    pairs :func:`~lampsam.backend.association.associate` may match). For such a pair
    the greedy one-to-one assignment matches it exactly when it is inside the gate,
    whatever its distance.

    Args:
        pairs: observation index -> {landmark id: screen distance} of every pair of the kind.
        gate: the gate per observation index.
    """
    cand = {i: [lid for lid, d2 in row.items() if d2 < gate[i]] for i, row in pairs.items()}
    wanted: dict[int, int] = {}
    for lids in cand.values():
        for lid in lids:
            wanted[lid] = wanted.get(lid, 0) + 1
    return {(i, lids[0]) for i, lids in cand.items() if len(lids) == 1 and wanted[lids[0]] == 1}


def settle_bracketed(sole: set[tuple[int, int]],
                     bracket: Mapping[tuple[int, int], tuple[float, float]],
                     gate: Mapping[int, float], new_threshold: Mapping[int, float],
                     far: Mapping[int, float] | None) -> dict[tuple[int, int], tuple[float, str]]:
    """Which pairs the bracket decides alone, as :func:`~lampsam.backend.association.associate` would.

    ``associate`` matches greedily by exact distance among the pairs inside the gate
    (one landmark per observation and vice versa); an observation with no match
    becomes new when its smallest distance is above the new-landmark threshold, else
    it is dropped. So a pair is settled when:

    - ``hi < gate`` and it is in ``sole`` (:func:`sole_candidates`): matched whatever
      the exact distance (``"inside"``, reported as ``hi``);
    - ``lo > new_threshold`` (and ``lo > far`` when given: the exact gate would have
      recorded a distance that far, :meth:`~lampsam.backend.gate_shortcuts.LampGateShortcuts._reuse_far`
      reuses it): neither a match nor keeping the observation from being new
      (``"outside"``, reported as ``lo``).

    Args:
        sole: :func:`sole_candidates` of the kind's pairs.
        bracket: (observation index, landmark id) -> ``(lo, hi)`` for the pairs that
            would be asked for the exact distance.
        gate, new_threshold: per observation index.
        far: per observation index, the far-lamp reuse threshold, or None (no reuse).

    Returns:
        (observation index, landmark id) -> (distance to report, "inside" | "outside").
    """
    out: dict[tuple[int, int], tuple[float, str]] = {}
    for (i, lid), (lo, hi) in bracket.items():
        if not (math.isfinite(lo) and math.isfinite(hi)):
            continue
        if hi * (1.0 + ROUNDING) < gate[i] and (i, lid) in sole:
            out[(i, lid)] = (hi, "inside")
        elif lo * (1.0 - ROUNDING) > max(new_threshold[i], far[i] if far is not None else 0.0):
            out[(i, lid)] = (lo, "outside")
    return out
