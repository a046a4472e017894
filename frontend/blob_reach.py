"""The pixels within reach of the labelled lamp blobs of a box, gathered in one pass.

The all-blob path of the lamp detector (:func:`lampsam.frontend.lamps.detect_lamps`)
measures every candidate blob of an image at once
(:func:`lampsam.frontend.blob_moments.measure_labels`). What it needs per pixel near
a blob: which blob's support (the blob dilated by ``support_px``) and which blob's
background ring (dilated by ``support_px + ring_px``, minus the support) the pixel
lies in, its grey level, and the thresholded pixels of other blobs within a blob's
reach (crowding). :func:`gather_reach` collects these in one pass over the box by
grey dilation of the label image (:mod:`lampsam.frontend.dilation`);
:func:`reaches_may_overlap` tells when the second, reversed-label dilation can be
skipped. Pixels are ``(col, row)``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from lampsam.arrays import FloatArray, ImageU8, IntArray
from lampsam.frontend.dilation import dilate_disk
from lampsam.frontend.lamp_config import LampDetectorConfig


class Reach(NamedTuple):
    """The pixels within reach of the labelled blobs of a box, gathered in one pass.

    One entry per pixel within ``support_px + ring_px`` of a blob, in
    row-major order of the box; labels are those of the label image given to
    :func:`gather_reach` (0: none).

    Attributes:
        xy: shape (2, P) float ``(col, row)`` in the box, px.
        grey: shape (P,) uint8 grey level.
        sup: shape (P,) label of the support the pixel lies in (the label
            image's 8- or 16-bit dtype).
        ring: shape (P,) int label of the background ring the pixel lies in.
        crowd: shape (C,) int labels, one per (pixel, blob) pair where a
            thresholded pixel of another blob (or of no measured blob) lies in
            that blob's reach: its bright neighbours (empty when
            ``max_crowding`` is None).
        flat: shape (P,) the pixel's flat index in the image (``row * W + col``).
    """

    xy: FloatArray
    grey: IntArray
    sup: IntArray
    ring: IntArray
    crowd: IntArray
    flat: IntArray


def gather_reach(
    comp: np.ndarray,
    sub: tuple[int, int, int, int],
    origin: tuple[int, int],
    binary: np.ndarray,
    image: ImageU8,
    config: LampDetectorConfig,
    reaches_overlap: bool = True,
) -> Reach:
    """Support and ring labels of every pixel near a blob (one pass over the box).

    Support: the blob dilated by ``support_px``; ring: dilated by
    ``support_px + ring_px`` minus the support (elliptic disks). Where the
    dilations of two blobs overlap the larger label wins (grey dilation of the
    label image); a blob's own pixels keep its label, and other thresholded
    pixels belong to no support and no ring.

    Args:
        comp: shape (h, w) C-contiguous uint8 or uint16 labels of the blobs to
            measure (0 elsewhere), a crop of the image.
        sub: ``(row0, row1, col0, col1)``, the box to work in, in ``comp``.
        origin: ``(col, row)`` of ``comp[0, 0]`` in the image.
        binary: shape (H, W) uint8, non-zero where thresholded (measured blobs or not).
        image: shape (H, W) uint8 grey levels.
        config: detector settings (``support_px``, ``ring_px``).
        reaches_overlap: False when no pixel lies within reach of two blobs
            (:func:`reaches_may_overlap`): the smallest label within reach is
            then the largest, and the second dilation for ``crowd`` is skipped.

    Returns:
        The gathered pixels, coordinates in the box.
    """
    r0, r1, c0, c1 = sub
    region = comp[r0:r1, c0:c1]
    outer = dilate_disk(region, config.support_px + config.ring_px).ravel()
    near = dilate_disk(region, config.support_px).ravel()
    # Flat nonzero of a flat boolean array: about 10x faster than the 2-D np.nonzero.
    idx = (outer > 0).nonzero()[0]
    rows, cols = np.divmod(idx, c1 - c0)
    # Flat indices in the crop and in the image (no copies of the box views).
    in_comp = idx + rows * (comp.shape[1] - (c1 - c0)) + (r0 * comp.shape[1] + c0)
    width = image.shape[1]
    in_image = idx + rows * (width - (c1 - c0)) + ((r0 + origin[1]) * width + c0 + origin[0])
    free = binary.reshape(-1).take(in_image) == 0
    near_v = near.take(idx)
    sup = np.where(free, near_v, comp.reshape(-1).take(in_comp))
    ring = np.where(free & (near_v == 0), outer.take(idx), 0).astype(np.intp)
    outer_v = outer.take(idx)
    crowd = np.zeros(0, dtype=np.intp)
    if config.max_crowding is not None:
        # Thresholded pixels of other blobs in a blob's reach. Where reaches overlap the
        # grey dilation keeps the larger label, so the smaller one is found by dilating
        # the reversed labels (top - label) too.
        bright = (~free).nonzero()[0]
        own = comp.reshape(-1).take(in_comp.take(bright))
        hi = outer_v.take(bright).astype(np.intp)
        crowd = hi[hi != own]
        if reaches_overlap:
            top = int(region.max()) + 1
            if top > np.iinfo(region.dtype).max:  # top - label must fit the dtype
                region = region.astype(np.uint16)
            rev = region.copy()  # top - label on the blobs, 0 elsewhere
            np.subtract(region.dtype.type(top), region, out=rev, where=region > 0)
            lo_raw = dilate_disk(rev, config.support_px + config.ring_px).ravel()
            lo_raw = lo_raw.take(idx.take(bright))
            lo = np.where(lo_raw > 0, top - lo_raw.astype(np.intp), 0)
            crowd = np.concatenate([crowd, lo[(lo != own) & (lo != hi)]])
    xy = np.array([cols, rows], dtype=np.float64)
    return Reach(xy, image.reshape(-1).take(in_image), sup, ring, crowd, in_image)


def reaches_may_overlap(lo: np.ndarray, hi: np.ndarray, reach: int) -> bool:
    """Whether two blobs' reaches may share a pixel (their boxes grown by ``reach`` intersect).

    Args:
        lo: shape (m, 2) int ``(left, top)`` of each blob's box, px.
        hi: shape (m, 2) int ``(right, bottom)``, exclusive, px.
        reach: ``support_px + ring_px``, px.

    Returns:
        False only when no two grown boxes intersect (then no pixel is within
        ``reach`` of two blobs; the converse need not hold).
    """
    if lo.shape[0] < 2:
        return False
    a, b = lo - reach, hi + reach
    apart = (a[:, None, :] >= b[None, :, :]) | (a[None, :, :] >= b[:, None, :])
    together = np.asarray(~apart.any(axis=2))
    np.fill_diagonal(together, False)
    return bool(together.any())
