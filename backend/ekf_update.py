"""The EKF's stacked measurement update and gathered innovation covariances (eqs. 19-23).

Also the right-invariant EKF's correction (Barrau & Bonnabel, "An EKF-SLAM algorithm
with consistency properties", 2015): :func:`invariant_retract`, :func:`invariant_remap`.

Pure functions over :class:`lampsam.backend.covariance.LowerCovariance`: ``H`` of a
frame has nonzero blocks only in the robot columns and each observed landmark's
columns, so ``P H^T`` is assembled from column blocks of ``P`` and
``Psi = H P H^T + R`` from its rows; nothing ``n x n`` is formed.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.linalg import solve_triangular

from lampsam.arrays import FloatArray, IntArray
from lampsam.backend.covariance import LowerCovariance
from lampsam.factors.geometry import wrap_angle

log = logging.getLogger(__name__)

#: One measurement row block: ``(landmark offset, landmark dim, innovation (k,),
#: H_robot (k, 3) coordinates, H_landmark (k, d), R (k, k))``.
Row = tuple[int, int, FloatArray, FloatArray, FloatArray, FloatArray]


def stacked_gain(cov: LowerCovariance, rows: list[Row]) -> tuple[FloatArray, FloatArray] | None:
    """``W`` and the state step of one stacked update (eqs. 19-22).

    With the Cholesky factor ``C C^T = Psi`` and ``W = (P H^T) C^-T``:
    ``K nu = W (C^-1 nu)`` (eq. 22) and ``K (P H^T)^T = W W^T`` (eq. 23, applied by the
    caller as ``cov.downdate(W)``).

    Args:
        cov: the covariance ``P`` (n x n).
        rows: the row blocks (:data:`Row`).

    Returns:
        ``(W (n, K), step (n,))``, or None when ``Psi`` is not positive definite.
    """
    n = cov.n
    k_tot = sum(len(r[2]) for r in rows)
    pht = np.empty((n, k_tot))
    nu = np.empty(k_tot)
    r_blk = np.zeros((k_tot, k_tot))
    p_r = cov.columns(0, 3)  # (n, 3) P[:, R]
    i = 0
    for o, d, res, h_r, h_l, r in rows:
        k = len(res)
        pht[:, i : i + k] = p_r @ h_r.T + cov.columns(o, d) @ h_l.T
        nu[i : i + k] = res
        r_blk[i : i + k, i : i + k] = r
        i += k
    psi = np.empty((k_tot, k_tot))  # eq. 19: H (P H^T) + R
    i = 0
    for o, d, res, h_r, h_l, _r in rows:
        k = len(res)
        psi[i : i + k] = h_r @ pht[:3] + h_l @ pht[o : o + d]
        i += k
    psi += r_blk
    psi = 0.5 * (psi + psi.T)
    try:
        chol = np.linalg.cholesky(psi)
    except np.linalg.LinAlgError:
        log.warning("innovation covariance not positive definite: update skipped")
        return None
    c_inv = solve_triangular(chol, np.eye(k_tot), lower=True, check_finite=False)
    w = pht @ c_inv.T  # (n, K); a small inverse + one BLAS product beats n RHS solves
    return w, w @ (c_inv @ nu)


def gathered_s(cov: LowerCovariance, idx: IntArray, h_r: FloatArray, h_l: FloatArray
               ) -> FloatArray:
    """``S = H P H^T`` (eq. 19 without ``R``, with the robot-landmark cross term) of M landmarks.

    Args:
        cov: the covariance.
        idx: (M, d) state indices of each landmark's columns.
        h_r: (M, k, 3) robot Jacobians (coordinates); h_l: (M, k, d).

    Returns:
        (M, k, k).
    """
    p_rr = cov.block(0, 3, 0, 3)
    p_rl = cov.take(np.arange(3)[None, :, None], idx[:, None, :])  # (M, 3, d)
    p_ll = cov.take(idx[:, :, None], idx[:, None, :])  # (M, d, d)
    hl_t = np.transpose(h_l, (0, 2, 1))
    cross = h_r @ p_rl @ hl_t
    return (h_r @ p_rr @ np.transpose(h_r, (0, 2, 1)) + cross
            + np.transpose(cross, (0, 2, 1)) + h_l @ p_ll @ hl_t)


def invariant_retract(p0: FloatArray, p: FloatArray, dth: float) -> FloatArray:
    """Positions after a linear update applied as ``exp(xi) x`` on ``SE_{1+K}(2)``.

    The update moved every position (robot and planar landmarks, world frame) from
    ``p0`` to ``p`` and the heading by ``dth``. In the right-invariant error
    (``x = exp(xi) x_hat``) that step is ``xi_p = (p - p0) - J p0 dth`` (``J``: +90 deg
    rotation; first order, exact at ``p0``); the invariant EKF's new state is
    ``R(dth) p0 + V(dth) xi_p`` with ``V`` the SE(2) left Jacobian
    ``[[sin w, -(1 - cos w)], [1 - cos w, sin w]] / w``.

    Args:
        p0: (m, 2) positions before the update, m.
        p: (m, 2) positions after the additive update, m.
        dth: heading step, rad.

    Returns:
        (m, 2) positions, m.
    """
    xi = p - p0 - dth * np.column_stack([-p0[:, 1], p0[:, 0]])
    c, s = np.cos(dth), np.sin(dth)
    if abs(dth) > 1e-9:
        v = np.array([[s, -(1.0 - c)], [1.0 - c, s]]) / dth
    else:
        v = np.array([[1.0, -0.5 * dth], [0.5 * dth, 1.0]])
    rot = np.array([[c, -s], [s, c]])
    out: FloatArray = p0 @ rot.T + xi @ v.T
    return out


def invariant_remap(cov: LowerCovariance, idx: IntArray, moved: FloatArray) -> None:
    """Carry ``P`` (plain coordinates, heading at index 2) to the updated state's.

    The invariant error ``xi_p = delta_p - J p delta_theta`` depends on where it is
    taken: ``P`` in plain coordinates at the old state becomes ``A P A^T`` at the new
    one, with ``A = I + a e_theta^T`` and ``a_p = J (p_new - p_old)`` on each position
    (zero elsewhere). ``A P A^T - P = [a, P e_theta] M [a, P e_theta]^T`` with
    ``M = [[P_theta_theta, 1], [1, 0]]``: two symmetric rank-1 updates, in place.

    Args:
        cov: the covariance (n x n), updated in place.
        idx: (m, 2) state indices of the positions.
        moved: (m, 2) ``p_new - p_old``, m.
    """
    a = np.zeros(cov.n)
    a[idx[:, 0]] = -moved[:, 1]
    a[idx[:, 1]] = moved[:, 0]
    p_th = cov.columns(2, 1)[:, 0]
    lam, vec = np.linalg.eigh(np.array([[p_th[2], 1.0], [1.0, 0.0]]))
    b = np.column_stack([a, p_th]) @ vec
    for j in range(2):
        cov.rank_update(b[:, j : j + 1], float(lam[j]))


def invariant_update(x: FloatArray, x0: FloatArray, cov: LowerCovariance,
                     offsets: list[int]) -> None:
    """Apply an additive update ``x0 -> x`` as the right-invariant EKF does, in place.

    :func:`invariant_retract` on the robot (offset 0) and every planar landmark
    position, then ``P`` carried to the new state's coordinates (:func:`invariant_remap`).

    Args:
        x: (n,) the state after the additive update (heading at index 2), changed in place.
        x0: (n,) the state before it.
        cov: ``P``, changed in place.
        offsets: first state index of the robot and of each planar landmark.
    """
    idx = np.asarray(offsets)[:, None] + np.arange(2)[None, :]
    dth = wrap_angle(float(x[2] - x0[2]))
    new = invariant_retract(x0[idx], x[idx], dth)
    invariant_remap(cov, idx, new - x0[idx])
    x[idx] = new


def observability_project(h_r: FloatArray, h_l: FloatArray, pose_xy: FloatArray,
                          first_xy: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Range-bearing Jacobians projected so that the global pose stays unobservable (OC-EKF).

    The observability-constrained EKF (Huang, Mourikis & Roumeliotis, "Observability-based
    rules for designing consistent EKF SLAM estimators", IJRR 29(5) 2010, sec. 5) takes
    the ``H`` closest in the Frobenius norm to the Jacobian at the latest estimate,
    ``H = [H_R, H_L]``, among those with ``H* N = 0``:
    ``H* = H (I - N (N^T N)^-1 N^T)``. ``N`` spans the directions that no measurement
    can observe, a global translation and rotation of robot and landmark,
    ``N = [[I_2, J p_R], [0, 1], [I_2, J p_L]]`` (rows: robot x, y, theta, landmark x, y;
    ``J`` the +90 deg rotation), with ``p_R`` the robot's predicted position
    ``p_{k|k-1}`` (what the first-estimates prediction's heading column propagates) and
    ``p_L`` the landmark's first estimate. The first-estimates ``H`` satisfies the same
    constraint but may be far from the latest ``H`` once the landmark has moved; ``H*``
    is the nearest one that keeps the rotation unobservable.

    Args:
        h_r: (..., k, 3) robot Jacobians (plain coordinates) at the latest estimate;
            h_l: (..., k, 2) landmark Jacobians.
        pose_xy: (2,) ``p_R``, m; first_xy: (..., 2) ``p_L``, m.

    Returns:
        ``(H*_R (..., k, 3), H*_L (..., k, 2))``.
    """
    h = np.concatenate([h_r, h_l], axis=-1)  # (..., k, 5)
    pl = np.asarray(first_xy, float)
    n = np.zeros((*pl.shape[:-1], 5, 3))
    n[..., 0, 0] = n[..., 1, 1] = n[..., 3, 0] = n[..., 4, 1] = n[..., 2, 2] = 1.0
    n[..., 0, 2], n[..., 1, 2] = -float(pose_xy[1]), float(pose_xy[0])
    n[..., 3, 2], n[..., 4, 2] = -pl[..., 1], pl[..., 0]
    nt = np.swapaxes(n, -1, -2)
    proj = n @ np.linalg.solve(nt @ n, nt)  # (..., 5, 5)
    out = h - h @ proj
    return out[..., :3], out[..., 3:]
