"""The EKF covariance stored as a full matrix: the reference of ``bench_scaling``'s ``vs dense``.

:class:`DenseCovariance` is the storage the EKF had before
:class:`lampsam.backend.covariance.LowerCovariance` (general numpy products on the whole
``n x n`` matrix); :func:`covariance_storage` makes the EKFs built inside it use it.
Imported as a sibling module by ``scripts/bench/bench_scaling.py``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from unittest import mock

import numpy as np

import lampsam.backend.ekf_state as ekf_state
from lampsam.arrays import FloatArray, IntArray


class DenseCovariance:
    """The reference storage: the full ``n x n`` matrix in a capacity buffer, numpy products.

    Same interface as :class:`lampsam.backend.covariance.LowerCovariance`; the update
    is ``P -= W @ W.T`` (an n x n temporary, both triangles), the prediction writes
    the robot rows and columns, augmentation writes both the new rows and columns,
    and removal copies ``P[ix_(keep, keep)]``. Only for timing against the in-place
    storage (the EKF's results agree to round-off: tests/test_covariance.py).
    """

    def __init__(self, initial: FloatArray, capacity: int = 64) -> None:
        p0 = np.asarray(initial, float)
        n0 = p0.shape[0]
        self._buf = np.zeros((max(capacity, n0), max(capacity, n0)))
        self._buf[:n0, :n0] = p0
        self._n = n0

    @property
    def n(self) -> int:
        return self._n

    def _p(self) -> FloatArray:
        return self._buf[: self._n, : self._n]

    def dense(self) -> FloatArray:
        return self._p().copy()

    def block(self, r0: int, r1: int, c0: int, c1: int) -> FloatArray:
        return self._p()[r0:r1, c0:c1].copy()

    def columns(self, o: int, d: int) -> FloatArray:
        return self._p()[:, o : o + d]

    def take(self, rows: IntArray, cols: IntArray) -> FloatArray:
        return self._p()[rows, cols]

    def downdate(self, w: FloatArray) -> None:
        p = self._p()
        p -= w @ w.T

    def rank_update(self, w: FloatArray, alpha: float) -> None:
        p = self._p()
        p += alpha * (w @ w.T)

    def transform_leading(self, f: FloatArray, q: FloatArray) -> None:
        r = f.shape[0]
        p = self._p()
        p[:r, :r] = f @ p[:r, :r] @ f.T + q
        p[:r, r:] = f @ p[:r, r:]
        p[r:, :r] = p[:r, r:].T

    def append(self, cross: FloatArray, new: FloatArray) -> None:
        d, n = new.shape[0], self._n
        if n + d > self._buf.shape[0]:
            buf = np.zeros((2 * (n + d), 2 * (n + d)))
            buf[:n, :n] = self._p()
            self._buf = buf
        self._buf[n : n + d, :n] = cross
        self._buf[:n, n : n + d] = cross.T
        self._buf[n : n + d, n : n + d] = new
        self._n = n + d

    def delete(self, keep: np.ndarray) -> None:
        idx = np.flatnonzero(keep)
        p = self._p()[np.ix_(idx, idx)].copy()
        self._n = len(idx)
        self._p()[:] = p


@contextlib.contextmanager
def covariance_storage(dense: bool) -> Iterator[None]:
    """EKFs constructed inside the block store P as :class:`DenseCovariance` when ``dense``."""
    if not dense:
        yield
        return
    with mock.patch.object(ekf_state, "LowerCovariance", DenseCovariance):
        yield
