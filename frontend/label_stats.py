"""Connected-component labelling and per-label statistics over pixel lists.

The lamp detector measures every blob of an image at once: its pixels are
gathered into flat arrays with one label each, and sums (moments, eqs. 2-4 of
paper 1) and order statistics (median levels) are taken per label with a few
vectorised calls instead of one loop per blob. Labels are ``0..n-1`` (0: no
blob), grey levels the integers ``0..255`` of a uint8 image.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from lampsam.arrays import FloatArray, IntArray


def label_blobs(binary: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """8-connected labelling with statistics (the paper's grassfire labelling).

    Uses 16-bit labels whenever the image cannot hold 65535 components (at most
    one per 2x2 block): OpenCV computes the statistics about 3x faster then.

    Args:
        binary: shape (H, W) uint8, non-zero = foreground.

    Returns:
        ``(n, labels (H, W), stats (n, 5))`` as ``cv2.connectedComponentsWithStats``.
    """
    h, w = binary.shape
    ltype = cv2.CV_16U if ((h + 1) // 2) * ((w + 1) // 2) < 65535 else cv2.CV_32S
    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, None, None, None, 8, ltype)
    return int(n), labels, stats


class Groups(NamedTuple):
    """Pixels grouped by label (a stable permutation) for segment sums.

    Attributes:
        order: shape (P,) permutation listing the pixels label by label (row-major within).
        starts: shape (G,) start of each non-empty group in that order.
        present: shape (G,) the label of each non-empty group.
    """

    order: IntArray
    starts: IntArray
    present: IntArray


def group_by_label(lab: IntArray, n: int, count: IntArray | None = None) -> Groups:
    """Group pixels by label ``0..n-1`` (stable argsort).

    Per-label sums are then ``np.add.reduceat`` over contiguous segments:
    ``np.bincount`` with weights adds each pixel into the bin the previous one
    went to (a blob's pixels come in long runs) and waits on that addition,
    several times slower here. The sort runs on 8- or 16-bit labels (numpy's
    radix sort); the group starts come from the label counts.

    Args:
        lab: shape (P,) labels ``0..n-1`` (any integer dtype).
        n: number of labels.
        count: shape (n,) pixels per label when the caller has them.
    """
    small = lab.astype(np.uint8 if n <= 256 else np.uint16 if n <= 65536 else np.intp, copy=False)
    order = np.argsort(small, kind="stable")
    if count is None:
        count = np.bincount(lab, minlength=n)
    present = count.nonzero()[0]
    return Groups(order, (count.cumsum() - count).take(present), present)


def label_sums(groups: Groups, values: FloatArray, n: int) -> FloatArray:
    """Per-label sums of the rows of ``values``.

    Args:
        groups: the pixels' grouping (:func:`group_by_label`).
        values: shape (k, P), per-pixel values already in ``groups.order``.
        n: number of labels.

    Returns:
        shape (k, n): the sums, 0 for absent labels (integer-valued inputs sum
        exactly; others differ from a sequential sum by rounding only).
    """
    out = np.zeros((values.shape[0], n))
    if groups.present.size:
        out[:, groups.present] = np.add.reduceat(values, groups.starts, axis=1)
    return out


HIST_MAX_LABELS = 1024  # per-label level histograms up to this many labels, a sort above


class Levels(NamedTuple):
    """Per-label grey-level distributions, for order statistics (:func:`levels_at`).

    Up to ``HIST_MAX_LABELS`` labels: cumulative 256-bin histograms per label
    (one ``bincount``, cheaper than a sort); above, the sorted keys
    ``256 label + level`` (memory linear in the pixels, not the labels).

    Attributes:
        cum: shape (n, 256) cumulative counts per label, or None (sort path).
        key: shape (P,) sorted keys, or None (histogram path).
        start: shape (n,) first position of each label in ``key`` (histogram path: unused).
        counts: shape (n,) pixels per label.
    """

    cum: IntArray | None
    key: IntArray | None
    start: IntArray
    counts: IntArray


def label_levels(lab: IntArray, grey: IntArray, n: int) -> Levels:
    """The grey levels of the pixels grouped per label (see :class:`Levels`).

    Args:
        lab: shape (P,) int labels ``0..n-1``.
        grey: shape (P,) int grey levels ``0..255``.
        n: number of labels.
    """
    key = lab * 256 + grey
    if n <= HIST_MAX_LABELS:
        cum = np.bincount(key, minlength=256 * n).reshape(n, 256).cumsum(axis=1)
        count = cum[:, -1]
        return Levels(cum, None, count, count)
    key.sort()
    edges = np.searchsorted(key, 256 * np.arange(n + 1))
    start = edges[:-1]
    return Levels(None, key, start, edges[1:] - start)


def levels_at(levels: Levels, rank: IntArray) -> IntArray:
    """Per-label order statistics.

    Args:
        levels: from :func:`label_levels`.
        rank: shape (n,) or (k, n), 0-based ranks (ascending) wanted in each
            label's group; labels without pixels (or ranks past the end) get
            an arbitrary level.

    Returns:
        int grey levels, the shape of ``rank``. On the histogram path the level
        of rank ``r`` is the first whose cumulative count exceeds ``r``.
    """
    if levels.cum is not None:  # (integer counts: cum < rank + 1 is cum <= rank)
        return (levels.cum <= rank[..., None]).sum(axis=-1)
    assert levels.key is not None
    pos = np.minimum(levels.start + rank, levels.key.size - 1)
    return levels.key.take(pos) - 256 * np.arange(levels.start.size)


def lower_median_rank(count: IntArray) -> IntArray:
    """0-based rank of the lower median of ``count`` values (0 for empty groups).

    The first level at which the cumulative count reaches half the total, as
    for a histogram.
    """
    return np.maximum((count + 1) // 2 - 1, 0)
