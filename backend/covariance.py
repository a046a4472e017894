"""A growable symmetric covariance kept as its lower triangle, updated in place by BLAS.

The EKF's covariance ``P`` (n x n, n up to several thousand) is the only O(n^2)
object of the filter; every full copy of it costs as much as the update itself.
:class:`LowerCovariance` keeps ``P`` in a preallocated ``capacity x capacity``
C-order buffer of which only the lower triangle (row >= column) of the leading
``n x n`` block is meaningful; the upper triangle is never read. Operations:

- :meth:`LowerCovariance.downdate`: ``P <- P - W W^T`` (the EKF update, paper 1 eq.
  23, written as a symmetric rank-K product) by BLAS ``dsyrk`` on the lower triangle
  in place: half the flops of the general product, no n x n temporary, symmetric by
  construction (no periodic re-symmetrisation).
- :meth:`LowerCovariance.transform_leading`: ``P_RR <- F P_RR F^T + Q`` and
  ``P_MR <- P_MR F^T`` for a transition that moves only the leading ``r`` states
  (the robot, eqs. 13-15); the ``P_MM`` block is not touched.
- :meth:`LowerCovariance.append` / :meth:`LowerCovariance.delete`: augmentation
  (eqs. 24-25) writes one new row block; removal compacts the triangle in place.
- reads (:class:`LowerCovariance`'s): :meth:`~LowerCovariance.columns` (``P[:, o:o+d]``),
  :meth:`~LowerCovariance.block` (``P[r0:r1, c0:c1]``), :meth:`~LowerCovariance.take`
  (gathered entries), :meth:`~LowerCovariance.dense` (a full copy, for checks).

Why ``scipy.linalg.cython_blas`` and not ``scipy.linalg.blas``: the f2py wrappers of
``scipy.linalg.blas`` copy any argument that is not contiguous, and the leading
``n x n`` block of the capacity buffer has a leading dimension ``capacity > n``, so
``overwrite_c`` would update a copy. ``scipy.linalg.cython_blas`` exports the same
BLAS routines (the ones scipy links) as C function pointers taking the leading
dimension; :func:`_cython_blas` binds ``dsyrk`` through ctypes once per process.
"""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Callable

import numpy as np

from lampsam.arrays import FloatArray, IntArray

_PD = ctypes.POINTER(ctypes.c_double)
_PI = ctypes.POINTER(ctypes.c_int)
_PC = ctypes.POINTER(ctypes.c_char)

#: ``dsyrk(uplo, trans, n, k, alpha, a, lda, beta, c, ldc)``, Fortran (all by reference).
_DSYRK = ctypes.CFUNCTYPE(None, _PC, _PC, _PI, _PI, _PD, _PD, _PI, _PD, _PD, _PI)


@functools.cache
def _cython_blas(name: str) -> Callable[..., None]:
    """The C function pointer of ``scipy.linalg.cython_blas.<name>`` as a ctypes callable."""
    from scipy.linalg import cython_blas

    capsule = cython_blas.__pyx_capi__[name]  # type: ignore[attr-defined]
    get_name = ctypes.pythonapi.PyCapsule_GetName
    get_name.restype = ctypes.c_char_p
    get_name.argtypes = [ctypes.py_object]
    get_pointer = ctypes.pythonapi.PyCapsule_GetPointer
    get_pointer.restype = ctypes.c_void_p
    get_pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    address = get_pointer(capsule, get_name(capsule))
    return _DSYRK(address)  # type: ignore[no-any-return]


def syrk_lower_inplace(c: FloatArray, n: int, w: FloatArray, alpha: float = -1.0) -> None:
    """``C[:n, :n] += alpha W W^T`` on the lower triangle (row >= column) of C, in place.

    Args:
        c: (cap, cap) C-contiguous float64 buffer, ``cap >= n``; only the lower
            triangle of its leading ``n x n`` block is written.
        n: size of the active block.
        w: (n, K) factor (copied to C order if it is not).
        alpha: scale of the rank-K term.
    """
    if not (c.flags.c_contiguous and c.dtype == np.float64 and c.ndim == 2
            and c.shape[0] == c.shape[1] and c.shape[0] >= n):
        raise ValueError("syrk_lower_inplace: c must be a square C-contiguous float64 buffer")
    w = np.ascontiguousarray(w, dtype=np.float64)
    if w.ndim != 2 or w.shape[0] != n:
        raise ValueError(f"syrk_lower_inplace: w has shape {w.shape}, expected ({n}, K)")
    k = w.shape[1]
    if n == 0 or k == 0:
        return
    # BLAS sees the C-order buffer as its transpose (column-major, ld = cap): the lower
    # triangle of C is BLAS's upper ('U'); the C-order (n, K) w is BLAS's (K, n)
    # matrix A with lda = K, so C_blas += alpha A^T A is trans = 'T'.
    fn = _cython_blas("dsyrk")
    ref = ctypes.byref
    fn(ref(ctypes.c_char(b"U")), ref(ctypes.c_char(b"T")), ref(ctypes.c_int(n)),
       ref(ctypes.c_int(k)), ref(ctypes.c_double(alpha)), w.ctypes.data_as(_PD),
       ref(ctypes.c_int(k)), ref(ctypes.c_double(1.0)), c.ctypes.data_as(_PD),
       ref(ctypes.c_int(c.shape[1])))


@functools.cache
def _strict_upper(d: int) -> tuple[IntArray, IntArray]:
    """Row and column indices of the strict upper triangle of a d x d matrix (cached)."""
    return np.triu_indices(d, 1)


def _sym_from_lower(block: FloatArray) -> FloatArray:
    """Full symmetric matrix from the lower triangle of a square block (a new array)."""
    d = block.shape[0]
    if d > 32:  # large (dense() for checks): no cached index arrays of n^2 entries
        return np.tril(block) + np.tril(block, -1).T
    out = block.copy()
    iu = _strict_upper(d)
    out[iu] = block.T[iu]
    return out


class LowerCovariance:
    """A symmetric n x n matrix stored as the lower triangle of a growable buffer.

    Args:
        initial: (n0, n0) the starting covariance (its lower triangle is used).
        capacity: initial buffer size (grows by half as needed).
    """

    def __init__(self, initial: FloatArray, capacity: int = 64) -> None:
        p0 = np.asarray(initial, float)
        n0 = p0.shape[0]
        self._buf = np.zeros((max(capacity, n0), max(capacity, n0)))
        self._buf[:n0, :n0] = p0
        self._n = n0

    @property
    def n(self) -> int:
        """Current size of the matrix."""
        return self._n

    @property
    def capacity(self) -> int:
        """Rows of the buffer."""
        return self._buf.shape[0]

    def reserve(self, need: int) -> None:
        """Make room for ``need`` states (one O(n^2) copy of the triangle when it grows)."""
        cap = self._buf.shape[0]
        if need <= cap:
            return
        new_cap = max(need, cap + cap // 2)
        buf = np.zeros((new_cap, new_cap))
        n = self._n
        buf[:n, :n] = self._buf[:n, :n]
        self._buf = buf

    # ------------------------------------------------------------------ reads
    def dense(self) -> FloatArray:
        """(n, n) the full symmetric matrix (a copy: O(n^2), for checks and small n)."""
        return _sym_from_lower(self._buf[: self._n, : self._n])

    def block(self, r0: int, r1: int, c0: int, c1: int) -> FloatArray:
        """``P[r0:r1, c0:c1]`` (a copy), from whichever triangle holds each entry."""
        n = self._n
        if not (0 <= r0 <= r1 <= n and 0 <= c0 <= c1 <= n):
            raise IndexError(f"block [{r0}:{r1}, {c0}:{c1}] outside a {n} x {n} matrix")
        if r0 >= c1 - 1:  # every row >= every column: stored as is
            return self._buf[r0:r1, c0:c1].copy()
        if c0 >= r1 - 1:  # every column >= every row: the transposed stored block
            return self._buf[c0:c1, r0:r1].T.copy()
        rows = np.arange(r0, r1)[:, None]
        cols = np.arange(c0, c1)[None, :]
        return self._buf[np.maximum(rows, cols), np.minimum(rows, cols)]

    def columns(self, o: int, d: int) -> FloatArray:
        """(n, d) ``P[:, o:o+d]``: rows above from row block ``o`` (contiguous), rows below as stored."""
        n = self._n
        if not 0 <= o <= o + d <= n:
            raise IndexError(f"columns {o}:{o + d} outside a {n} x {n} matrix")
        out = np.empty((n, d))
        out[:o] = self._buf[o : o + d, :o].T
        out[o : o + d] = _sym_from_lower(self._buf[o : o + d, o : o + d])
        out[o + d :] = self._buf[o + d : n, o : o + d]
        return out

    def take(self, rows: IntArray, cols: IntArray) -> FloatArray:
        """``P[rows, cols]`` for broadcastable integer index arrays (numpy fancy indexing)."""
        r = np.asarray(rows)
        c = np.asarray(cols)
        return self._buf[np.maximum(r, c), np.minimum(r, c)]

    # ------------------------------------------------------------------ updates
    def downdate(self, w: FloatArray) -> None:
        """``P <- P - W W^T`` in place (BLAS ``dsyrk`` on the lower triangle).

        Args:
            w: (n, K).
        """
        syrk_lower_inplace(self._buf, self._n, w, -1.0)

    def rank_update(self, w: FloatArray, alpha: float) -> None:
        """``P <- P + alpha W W^T`` in place (BLAS ``dsyrk`` on the lower triangle).

        Args:
            w: (n, K).
            alpha: scale (negative for a downdate).
        """
        syrk_lower_inplace(self._buf, self._n, w, alpha)

    def transform_leading(self, f: FloatArray, q: FloatArray) -> None:
        """``P <- T P T^T + diag(Q, 0)`` with ``T = diag(F, I)``: only the leading r states move.

        Touches the r x r block and the (n - r) x r column block (O(n r^2)); the rest
        of ``P`` is unchanged.

        Args:
            f: (r, r) transition of the leading states.
            q: (r, r) noise added to them.
        """
        r = f.shape[0]
        n = self._n
        buf = self._buf
        p_rr = _sym_from_lower(buf[:r, :r])
        buf[:r, :r] = f @ p_rr @ f.T + q
        if n > r:
            buf[r:n, :r] = buf[r:n, :r] @ f.T

    def append(self, cross: FloatArray, new: FloatArray) -> None:
        """Add d states: ``P <- [[P, C^T], [C, N]]``.

        Args:
            cross: (d, n) covariance of the new states with the existing ones.
            new: (d, d) covariance of the new states.
        """
        d = new.shape[0]
        n = self._n
        if cross.shape != (d, n):
            raise ValueError(f"append: cross has shape {cross.shape}, expected ({d}, {n})")
        self.reserve(n + d)
        self._buf[n : n + d, :n] = cross
        self._buf[n : n + d, n : n + d] = new
        self._n = n + d

    def delete(self, keep: np.ndarray) -> None:
        """Remove the states where ``keep`` is False, compacting the triangle in place.

        Row ``r`` of the result is row ``idx[r] >= r`` of the old matrix restricted to
        the kept columns ``idx[:r+1]``; rows are rewritten in increasing order, so every
        source row is read before it is overwritten. O(n^2) reads, no n x n temporary.

        Args:
            keep: (n,) bool mask.
        """
        keep = np.asarray(keep, bool)
        if keep.shape != (self._n,):
            raise ValueError(f"delete: mask of shape {keep.shape} for {self._n} states")
        idx = np.flatnonzero(keep)
        dropped = np.flatnonzero(~keep)
        if len(dropped) == 0:
            return
        r0 = int(dropped[0])  # rows and columns before the first removal stay in place
        buf = self._buf
        tail_idx = idx[r0:]
        for r in range(r0, len(idx)):
            i = idx[r]
            buf[r, r0 : r + 1] = buf[i, tail_idx[: r - r0 + 1]]
            if r0:
                buf[r, :r0] = buf[i, :r0]
        self._n = len(idx)
