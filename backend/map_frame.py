"""The map's frame uncertainty: the common part of a batch map's landmark errors.

A batch smoother anchored at the mapping run's first pose places every landmark
relative to that pose, so the landmarks' joint covariance ``Sigma`` (over all of
them) is dominated by one shared error: the whole map shifted and rotated in the
world. Storing each landmark's marginal alone throws that correlation away, and a
localizer then treats a common offset as many independent ones.

This module summarises ``Sigma`` by a rank-3 factor model, the textbook treatment
of a map's gauge:

    e_l = C_l g + r_l,   g ~ N(0, S),   r_l ~ N(0, D_l) independent of g and of
    each other,   D_l = Sigma_ll - C_l S C_l^T

with ``e_l`` the error of landmark ``l``'s state ``(x, y, z, phi)``, ``g = (dx, dy,
dtheta)`` the map frame's planar offset (m, m, rad: a rotation ``dtheta`` about the
frame's reference point ``c``, then a translation ``(dx, dy)``), ``S`` (3 x 3) its
covariance and ``C_l`` (4 x 3) the landmark's regression on ``g``. ``g`` is defined
as the generalised-least-squares rigid fit of the landmark errors,

    g = M e,  M = (J^T W J)^-1 J^T W

with ``J_l`` the rigid-motion Jacobian of the landmark (:func:`rigid_jacobian`)
and ``W`` the landmarks' marginal information (``x, y`` and ``phi`` rows), so that
``S = M Sigma M^T`` and ``C_l = (Sigma M^T)_l S^-1`` (the exact conditional of the
Gaussian ``(e_l, g)``). The diagonal blocks of ``Sigma`` are kept exactly
(``C_l S C_l^T + D_l = Sigma_ll``); the cross-covariances between landmarks become
``C_l S C_m^T`` (the part through the frame; the rest is dropped).

``Sigma M^T`` needs three solves with the batch's information matrix
``H = A^T A`` (``A`` the whitened Jacobian of the final factor graph, GTSAM's
``sparseJacobian_``), not ``Sigma`` itself: one sparse LU of ``H`` (a few thousand
variables, well under a second).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from gtsam.symbol_shorthand import A

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling_graph import find_point_key
from lampsam.errors import EstimationError


@dataclass(frozen=True)
class MapFrame:
    """The map frame's uncertainty and each landmark's regression on it.

    Attributes:
        center: (2,) reference point ``c`` of the frame's rotation, m (world frame).
        cov: (3, 3) ``S``, covariance of ``g = (dx, dy, dtheta)``, m^2, m rad, rad^2.
        gains: landmark id -> (4, 3) ``C_l`` (rows ``x, y, z, phi``; the ``phi`` row
            is zero without an axis).
    """

    center: FloatArray
    cov: FloatArray
    gains: dict[int, FloatArray]

    def conditional(self, lid: int, marginal: FloatArray) -> FloatArray:
        """``D_l = Sigma_ll - C_l S C_l^T`` (4 x 4), its eigenvalues clipped at 0."""
        c = self.gains[lid]
        d = np.asarray(marginal, float) - c @ self.cov @ c.T
        d = 0.5 * (d + d.T)
        w, v = np.linalg.eigh(d)
        if w.min() >= 0.0:
            return d
        return (v * np.clip(w, 0.0, None)) @ v.T


def rigid_jacobian(position: FloatArray, center: FloatArray, has_axis: bool) -> FloatArray:
    """(4, 3) ``d (x, y, z, phi) / d (dx, dy, dtheta)`` of a planar rigid motion.

    A point ``p`` moved by a rotation ``dtheta`` about ``c`` and a translation
    ``(dx, dy)``: ``x' = x + dx - dtheta (y - c_y)``, ``y' = y + dy + dtheta (x - c_x)``,
    ``z' = z``, and a lamp axis ``phi' = phi + dtheta`` (zero row without an axis).
    """
    j = np.zeros((4, 3))
    j[0, 0] = j[1, 1] = 1.0
    j[0, 2] = -(float(position[1]) - float(center[1]))
    j[1, 2] = float(position[0]) - float(center[0])
    if has_axis:
        j[3, 2] = 1.0
    return j


def information_matrix(factors: gtsam.NonlinearFactorGraph, values: gtsam.Values
                       ) -> tuple[sp.csc_matrix, dict[int, int]]:
    """The whitened information matrix ``H = A^T A`` at ``values`` and each key's column.

    Every variable of the ceiling graphs (``Pose2`` poses and axes, ``Point3``
    landmarks) has three tangent dimensions; another graph raises.

    Raises:
        EstimationError: a variable that is not 3-dimensional.
    """
    lin = factors.linearize(values)
    keys = sorted(int(k) for k in values.keys())  # a KeySet does not iterate in Python
    if lin.keys().size() != len(keys) or values.dim() != 3 * len(keys):
        raise EstimationError(f"map frame: expected 3-dof variables only ({len(keys)} keys, "
                              f"{values.dim()} dims)")
    ijs = lin.sparseJacobian_()
    n = 3 * len(keys)
    rows = ijs[0].astype(int) - 1
    cols = ijs[1].astype(int) - 1
    inside = cols < n  # the last column is the right-hand side b
    a = sp.csr_matrix((ijs[2][inside], (rows[inside], cols[inside])),
                      shape=(int(rows.max()) + 1, n))
    return (a.T @ a).tocsc(), {k: 3 * i for i, k in enumerate(keys)}


def map_frame(factors: gtsam.NonlinearFactorGraph, values: gtsam.Values,
              landmarks: list[tuple[int, FloatArray, FloatArray, bool]]) -> MapFrame:
    """The factor model of the module docstring from a batch's final graph.

    Args:
        factors: the final factor graph (:class:`lampsam.backend.interface.GraphSnapshot`).
        values: its solution.
        landmarks: ``(id, (3,) position, (4, 4) marginal covariance, has_axis)`` of
            the landmarks to describe (``L(id)``, and ``A(id)`` when ``has_axis``).

    Raises:
        EstimationError: a landmark not in the graph, or a singular information matrix.
    """
    h, col = information_matrix(factors, values)
    if not landmarks:
        raise EstimationError("map frame: no landmarks")
    pos = np.array([p[:2] for _, p, _, _ in landmarks], float)
    center = pos.mean(axis=0)
    n = h.shape[0]
    # M^T, padded to the graph's columns: rows x, y of L(id) / C(id) and the angle of A(id)
    mt = np.zeros((n, 3))
    jtwj = np.zeros((3, 3))
    point_col: dict[int, int] = {}
    for lid, p, cov, has_axis in landmarks:
        key = find_point_key(lid, col)
        if key is None or (has_axis and int(A(lid)) not in col):
            raise EstimationError(f"map frame: landmark {lid} is not in the graph")
        j = rigid_jacobian(p, center, has_axis)
        rows = [0, 1, 3] if has_axis else [0, 1]
        w = np.linalg.inv(np.asarray(cov, float)[np.ix_(rows, rows)])
        jw = j[rows].T @ w  # (3, k)
        jtwj += jw @ j[rows]
        c0 = point_col[lid] = col[key]
        mt[c0:c0 + 2] += jw[:, :2].T
        if has_axis:
            mt[col[int(A(lid))] + 2] += jw[:, 2]
    mt = mt @ np.linalg.inv(jtwj).T  # (J^T W J)^-1 J^T W, transposed
    try:
        y = spla.splu(h).solve(mt)  # Sigma M^T, (n, 3)
    except RuntimeError as exc:
        raise EstimationError(f"map frame: information matrix not invertible ({exc})") from None
    s = mt.T @ y
    s = 0.5 * (s + s.T)
    s_inv = np.linalg.inv(s)
    gains: dict[int, FloatArray] = {}
    for lid, _, _, has_axis in landmarks:
        c0 = point_col[lid]
        cross = np.zeros((4, 3))
        cross[:3] = y[c0:c0 + 3]
        if has_axis:
            cross[3] = y[col[int(A(lid))] + 2]
        gains[lid] = cross @ s_inv
    return MapFrame(center, s, gains)


#: variance added to the diagonal of a landmark's residual covariance ``D`` (m^2, rad^2):
#: ``D`` is a difference of covariances, clipped at 0, and may be singular
D_FLOOR = 1e-12


def shift_only(frame: MapFrame) -> MapFrame:
    """The frame model regressed on the shift ``(dx, dy)`` alone.

    From the joint Gaussian of ``(e_l, g)`` (``Cov(e_l, g) = C_l S``): ``C'_l = (C_l S)_{:, xy}
    S_xy^-1`` and ``S' = S_xy``; returned as a 3-dof frame whose turn has variance
    :data:`D_FLOOR` and zero gain, so that :meth:`MapFrame.conditional` gives
    ``D'_l = Sigma_ll - C'_l S_xy C'_l^T`` (the turn's share stays in ``D'_l``, independent
    between landmarks).
    """
    s = np.asarray(frame.cov, float)
    s_xy_inv = np.linalg.inv(s[:2, :2])
    cov = np.zeros((3, 3))
    cov[:2, :2] = s[:2, :2]
    cov[2, 2] = D_FLOOR
    gains = {}
    for lid, c in frame.gains.items():
        g = np.zeros((4, 3))
        g[:, :2] = (np.asarray(c, float) @ s)[:, :2] @ s_xy_inv
        gains[lid] = g
    return MapFrame(np.asarray(frame.center, float), cov, gains)
