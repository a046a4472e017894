"""The label entropy of an association: what the online picker's ``C`` adds so that a
landmark split in overlapping copies does not win (no ids).

The description length of :mod:`lampsam.backend.noids_offline`,
``C = chi2 + c_new (n_landmarks + n_dropped)``, charges a landmark ``c_new`` and its
sightings their chi-square. A map that splits one landmark into two copies a few
centimetres apart pays one more ``c_new`` and fits better wherever the sightings of one
landmark do not fit one point at the stated noise: on MRCLAM (landmarks are tubes,
ranges to their surface; sighted from different sides) the alias test's map of 29
landmarks for 15 has ``C`` 1,237 against the 15-landmark map's 1,661. The split's
labels are then a guess: each sighting is explained by either copy almost equally well.

Mixture models have the same problem (BIC over-counts the components of a cluster that
is not Gaussian); the integrated completed likelihood (ICL; Biernacki, Celeux and
Govaert, IEEE TPAMI 22(7), 2000) adds the entropy of the labels:
``ICL = BIC + 2 sum_i E_i``, ``E_i = -sum_j t_ij log t_ij`` with ``t_ij`` the
responsibility of component ``j`` for point ``i``. Here, for each recorded sighting
``i`` of landmark ``j0`` at pose ``x_k`` (the association's optimum):

- the rivals are the ``n_near`` landmarks nearest the point the sighting puts its
  landmark at, less the landmarks another sighting of the same pose is given to (one
  pose sees a landmark once, as the merge test's mutual exclusion);
- ``t_ij`` is proportional to ``exp(-d_ij / 2)``, ``d_ij = nu^T R_i^-1 nu`` of the
  sighting against landmark ``j`` (equal weights; the same ``R_i`` for all, so the
  Gaussian normalisations cancel);
- the added cost is ``2 sum_i E_i`` (chi-square units, as ``chi2 = 2 x`` nats).

Landmarks a few sigma apart for the stated noise (trees on a grid, a real pair of
neighbours) give ``t`` near 0 or 1 and cost nothing; copies of one landmark closer than
the noise cost up to ``2 log 2`` per sighting. A split whose copies are told apart by
the data (its chi-square gain over ``2 sum E``) still wins.

Where the stated sighting noise is too small (the sightings fit worse than stated:
chi-square per dof above 1), the chi-square gain of any split grows with the
understatement while its label entropy falls (its copies look farther apart than they
are). Each candidate is then scored at its own maximum-likelihood scale ``s2`` of the
range-bearing covariance, never below 1 (:func:`sighting_scale`; the profile likelihood
of the noise scale): its sightings cost ``chi2 / s2 + dof log s2`` (the Gaussian's
normalisation at that scale, relative to the stated one) and its label entropy is taken
with ``R s2`` (:func:`profiled_cost`). Where the stated noise is right or too large
(``s2 = 1``) that is ``C`` plus the label term. Hand-made check (tests): one landmark
sighted 60 times from all sides with noise 2x the stated sigma (20 seeds): its best
two-point split has the lesser ``C`` in all 20, and with the label term at the stated
noise too; each at its own scale, one landmark has the lesser cost in 16 (both at the
split's scale: 6). A split that the data supports (copies 10 sigma apart) keeps its win.

Frames: world, m and rad; sightings ``[bearing, range]`` in the body frame.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from lampsam.arrays import FloatArray, IntArray
from lampsam.backend.landmark_moves import point_chi2, sighted_points
from lampsam.backend.noids_offline import association_cost

#: Rival landmarks per sighting (the nearest to where it puts its landmark).
N_NEAR = 8


def label_entropy(poses: FloatArray, k: IntArray, z: FloatArray, r: FloatArray, lid: IntArray,
                  landmarks: dict[int, FloatArray], n_near: int = N_NEAR) -> FloatArray:
    """Entropy of each sighting's label among its rival landmarks (module doc), nats.

    Args:
        poses: (N, 3) poses ``(x, y, theta)`` indexed by ``k``, world.
        k: (S,) pose index of each sighting; z: (S, 2) ``[bearing, range]`` (rad, m);
            r: (S, 2, 2) their noise covariance; lid: (S,) landmark of each sighting.
        landmarks: landmark id -> (2,) position, world, m (every id of ``lid``).
        n_near: rivals considered per sighting (the nearest landmarks).

    Returns:
        (S,) ``E_i = -sum_j t_ij log t_ij`` (0 where the label is certain; at most
        ``log(n_near + 1)``).
    """
    s = len(k)
    if s == 0:
        return np.zeros(0)
    ids = np.array(sorted(landmarks), int)
    xy = np.array([landmarks[int(i)] for i in ids], float).reshape(-1, 2)
    pk = np.asarray(poses, float)[k]
    w: FloatArray = np.asarray(np.linalg.inv(r), float)
    d_own = point_chi2(pk, z, w, np.array([landmarks[int(i)] for i in lid], float))
    m = min(n_near, len(ids))
    _, nb = cKDTree(xy).query(sighted_points(pk, z), k=m)
    nb = np.asarray(nb, int).reshape(s, m)
    rival = ids[nb]  # (S, m)
    # a landmark another sighting of the same pose is given to is no rival
    big = int(ids.max()) + 1 if len(ids) else 1
    used = np.unique(k.astype(np.int64) * big + lid)
    taken = np.isin(k[:, None].astype(np.int64) * big + rival, used)
    skip = (rival == lid[:, None]) | taken
    d = np.full((s, m + 1), np.inf)
    d[:, 0] = d_own
    for c in range(m):
        dc = point_chi2(pk, z, w, xy[nb[:, c]])
        d[:, c + 1] = np.where(skip[:, c], np.inf, dc)
    a = -0.5 * (d - d.min(axis=1, keepdims=True))
    t = np.exp(a)
    t /= t.sum(axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        e = -np.sum(np.where(t > 0.0, t * np.log(np.where(t > 0.0, t, 1.0)), 0.0), axis=1)
    out: FloatArray = e
    return out


def label_cost(poses: FloatArray, k: IntArray, z: FloatArray, r: FloatArray, lid: IntArray,
               landmarks: dict[int, FloatArray], n_near: int = N_NEAR) -> float:
    """``2 sum_i E_i`` (:func:`label_entropy`), in chi-square units: the ICL term the
    online picker adds to an association's ``C``."""
    return float(2.0 * label_entropy(poses, k, z, r, lid, landmarks, n_near).sum())


def sighting_scale(chi2: float, dof: int) -> float:
    """A candidate's range-bearing noise scale (module doc): ``chi2 / dof`` of its
    sightings, at least 1 (the stated noise is never shrunk); 1 without a sighting."""
    if dof <= 0 or not np.isfinite(chi2):
        return 1.0
    return max(1.0, float(chi2) / dof)


def profiled_cost(chi2_odometry: float, chi2_sightings: float, dof_sightings: int,
                  n_landmarks: int, n_dropped: int, new_cost: float, s2: float,
                  labels: float) -> float:
    """A candidate's cost at the sighting noise scale ``s2`` (module doc):
    :func:`~lampsam.backend.noids_offline.association_cost` of
    ``chi2_odometry + chi2_sightings / s2 + dof_sightings log s2``, plus ``labels``
    (:func:`label_cost` with the noise ``R s2``); at ``s2 = 1`` the stated ``C`` plus
    ``labels``."""
    chi2 = chi2_odometry + chi2_sightings / s2 + dof_sightings * float(np.log(s2))
    return association_cost(chi2, n_landmarks, n_dropped, new_cost) + labels
