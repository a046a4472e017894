"""Global scan matching over a whole grid map by branch and bound.

The search scores every pose ``(x, y, theta)`` of a grid over the map's free
space, so its cost grows with the area searched, not with a particle count
(Olson, *Real-time correlative scan matching*, ICRA 2009, sec. IV-B, the
multi-resolution lookup tables; Hess et al., *Real-time loop closure in 2D
LIDAR SLAM*, ICRA 2016, sec. V-C, the "fast correlative scan matcher" of
Cartographer, whose global localization runs it over a whole submap).

The score of a pose is the sum over scan points ``p_i`` (body frame) of a
per-cell score ``M`` at the point's cell in the world::

    S(x, y, theta) = sum_i M[cell(R(theta) p_i + (x, y))]          (Hess eq. 14)

``M`` here is the likelihood field's per-beam log-likelihood
(:func:`lampsam.localization.likelihood.beam_log_likelihood` of the distance to
the nearest occupied cell, Probabilistic Robotics sec. 6.4), max-pooled from
the map's cells to the search cells. For each heading, translations on the
search grid shift every point by whole cells, and a node of height ``h``
covers the ``2^h x 2^h`` translations starting at its corner. Its bound uses
the precomputed grid ``M_h[y, x] = max M[y : y + 2^h, x : x + 2^h]`` (Hess
eq. 15-16)::

    B_h(node) = sum_i M_h[cell of p_i at the node's corner] >= S(any leaf below)

so a node whose bound is below the K-th best leaf found so far can be dropped
(admissible: the best poses are never pruned; ``tests/test_correlative.py``
checks ``B_h >= S`` numerically). Nodes are expanded depth first in batches,
best bound first, so good leaves are met early and the threshold rises fast.

The answer is the top-``K`` *well-separated* leaves (greedy non-maximum
suppression with a position / heading separation): the candidates that seed the
particle filter, and the competing hypotheses of the acceptance test.

Frames: ``points`` are in the body (laser) frame, metres; poses ``world_T_body``
``(x, y, theta)`` in the map's world frame (m, m, rad); cells as in
:class:`~lampsam.localization.grid.OccupancyGrid` (row = y).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from lampsam.arrays import BoolArray, Float32Array, FloatArray, IntArray
from lampsam.errors import LocalizationError
from lampsam.factors.geometry import compose, wrap_angle
from lampsam.localization.grid import OccupancyGrid, free_mask


class CorrelativeError(LocalizationError):
    """Bad input to the branch-and-bound search (settings, empty map, no points)."""


@dataclass(frozen=True)
class SearchConfig:
    """The global branch-and-bound search.

    Attributes:
        resolution: search cell size (m); a whole multiple of the map's cell
            size (the map's field is max-pooled to it). Default 0.1.
        angle_step_deg: heading step (deg). Default 1.0.
        depth: levels above the leaves; root nodes cover ``2^depth`` search
            cells a side. Default 6.
        top_k: well-separated candidates returned. Default 8.
        separation: two leaves are the same mode when closer than both
            (m, rad). Default (1.0, 0.5).
        max_points: at most this many scan points are matched (a voxel
            filter at the search resolution, then an even subsample). Default 160.
        min_score: leaves below this mean score per point (nats) are never
            candidates: the search's starting threshold (Cartographer's
            ``min_score``). Default -1.0.
        window: leaves more than this below the best leaf (mean score per
            point, nats) are never candidates: the threshold rises with the best
            leaf found so far. Default 1.0.
        max_range: scan points farther than this are not matched (m); the
            levels are padded by it. Default 30.
        batch: nodes expanded per batch (memory: ``batch x max_points`` gathers).
            Default 4096.
    """

    resolution: float = 0.1
    angle_step_deg: float = 1.0
    depth: int = 6
    top_k: int = 8
    separation: tuple[float, float] = (1.0, 0.5)
    max_points: int = 160
    min_score: float = -1.0
    window: float = 1.0
    max_range: float = 30.0
    batch: int = 4096

    def __post_init__(self) -> None:
        if not (self.resolution > 0 and 0 < self.angle_step_deg <= 90 and 0 <= self.depth <= 12
                and self.top_k >= 1 and self.max_points >= 1 and self.batch >= 1):
            raise CorrelativeError(f"invalid search settings: {self}")


@dataclass(frozen=True)
class Candidate:
    """One leaf of the search.

    Attributes:
        pose: (3,) ``world_T_body`` (m, m, rad): the search cell's centre and heading.
        score: mean per-point score (nats per point, untempered).
    """

    pose: FloatArray
    score: float


@dataclass(frozen=True)
class SearchStats:
    """What a search did: nodes scored per level (root first) and leaves scored."""

    nodes_per_level: tuple[int, ...]
    leaves: int


class ScorePyramid:
    """The per-cell score at the search resolution and its max-pooled levels.

    Args:
        grid: the map (its origin yaw is honoured).
        cell_score: (H, W) per-cell score on the map's cells (nats per point),
            e.g. the likelihood field of the distance field.
        floor: the score of a point outside the map (at most ``cell_score.min()``).
        config: the search settings (resolution, depth).

    Attributes:
        levels: ``levels[h]`` float32, ``max`` of the search-resolution score
            over the ``2^h x 2^h`` cells from each index; index ``j`` is search
            cell ``j - pad`` (``floor`` in the padding, which holds every point
            within ``max_range`` of a cell of the map).
        pad: padding cells on each side.
        free: ``free[h]`` same shape, bool: some search cell of the window is free.
        shape: (Hs, Ws) search cells.
        res: search cell size (m).
    """

    def __init__(self, grid: OccupancyGrid, cell_score: FloatArray | Float32Array, floor: float,
                 config: SearchConfig) -> None:
        f = config.resolution / grid.resolution
        factor = int(round(f))
        if factor < 1 or abs(f - factor) > 1e-6:
            raise CorrelativeError(f"search resolution {config.resolution} m is not a whole multiple "
                                   f"of the map's {grid.resolution} m")
        score = np.asarray(cell_score, dtype=np.float32)
        if score.shape != (grid.height, grid.width):
            raise CorrelativeError(f"cell_score {score.shape} is not the grid's "
                                   f"{(grid.height, grid.width)}")
        self.grid = grid
        self.res = float(config.resolution)
        self.factor = factor
        self.floor = float(min(floor, float(score.min(initial=floor))))
        hs, ws = -(-grid.height // factor), -(-grid.width // factor)
        self.shape = (hs, ws)
        self.pad = int(math.ceil(config.max_range / self.res)) + 2
        base = pool_blocks(score, factor, self.floor)
        free = pool_blocks(free_mask(grid).astype(np.float32), factor, 0.0) > 0.5
        hi = self.pad + 2**config.depth
        lvl = np.full((hs + self.pad + hi, ws + self.pad + hi), self.floor, dtype=np.float32)
        lvl[self.pad : self.pad + hs, self.pad : self.pad + ws] = base
        fr = np.zeros(lvl.shape, dtype=bool)
        fr[self.pad : self.pad + hs, self.pad : self.pad + ws] = free
        self.levels = [lvl]
        self.free = [fr]
        for h in range(1, config.depth + 1):
            self.levels.append(window_max(self.levels[-1], 2 ** (h - 1), self.floor))
            self.free.append(window_max(self.free[-1].astype(np.uint8), 2 ** (h - 1), 0) > 0)
        self.flat = [np.ascontiguousarray(v).ravel() for v in self.levels]

    def cell_centre(self, ix: IntArray, iy: IntArray) -> FloatArray:
        """(N, 2) world positions of search cells' centres."""
        g = self.grid
        u = (np.asarray(ix, dtype=float) + 0.5) * self.res
        v = (np.asarray(iy, dtype=float) + 0.5) * self.res
        c, s = math.cos(g.origin[2]), math.sin(g.origin[2])
        return np.column_stack([g.origin[0] + c * u - s * v, g.origin[1] + s * u + c * v])

    def offsets(self, points: FloatArray, theta: float) -> tuple[IntArray, IntArray]:
        """Whole-cell offsets (N,) of the points' cells from the pose's cell, at heading ``theta``.

        A pose at the centre of search cell ``(ix, iy)`` puts point ``p`` in cell
        ``ix + floor(0.5 + p_u / res)`` (``p_u`` in map axes), so translations on
        the search grid move every point by whole cells.
        """
        a = theta - self.grid.origin[2]
        c, s = math.cos(a), math.sin(a)
        u = (c * points[:, 0] - s * points[:, 1]) / self.res
        v = (s * points[:, 0] + c * points[:, 1]) / self.res
        lim = self.pad - 1
        return (np.clip(np.floor(0.5 + u), -lim, lim).astype(np.int64),
                np.clip(np.floor(0.5 + v), -lim, lim).astype(np.int64))

    def flat_offsets(self, ox: IntArray, oy: IntArray) -> IntArray:
        """Offsets into the flattened levels of whole-cell offsets ``(ox, oy)``."""
        return np.asarray(oy * self.levels[0].shape[1] + ox, dtype=np.int64)

    def flat_index(self, ix: IntArray, iy: IntArray) -> IntArray:
        """Index into the flattened levels of search cells ``(ix, iy)``."""
        return np.asarray((iy + self.pad) * self.levels[0].shape[1] + ix + self.pad, dtype=np.int64)

    def score(self, h: int, ix: IntArray, iy: IntArray, off: IntArray) -> FloatArray:
        """(N,) sum over points of level ``h`` at the points' cells.

        ``ix, iy`` (N,) search cells (node corners); ``off`` (N, P) the points'
        flat offsets (:meth:`flat_offsets`). Offsets are clipped to the padding
        (``SearchConfig.max_range``), so every cell read is inside the array.
        """
        idx = self.flat_index(ix, iy)[:, None] + off
        return self.flat[h].take(idx).sum(axis=1, dtype=np.float64)


def pool_blocks(a: FloatArray | Float32Array, factor: int, fill: float) -> Float32Array:
    """Max over ``factor x factor`` blocks of ``a`` (H, W) -> (ceil(H/f), ceil(W/f)); edges padded with ``fill``."""
    if factor == 1:
        return np.asarray(a, dtype=np.float32).copy()
    h, w = a.shape
    hs, ws = -(-h // factor), -(-w // factor)
    padded = np.full((hs * factor, ws * factor), fill, dtype=np.float32)
    padded[:h, :w] = a
    return np.asarray(padded.reshape(hs, factor, ws, factor).max(axis=(1, 3)))


def window_max(a: np.ndarray, step: int, fill: float) -> np.ndarray:
    """``out[y, x] = max(a[y, x], a[y, x + step], a[y + step, x], a[y + step, x + step])`` (``fill`` beyond)."""
    out = a.copy()
    out[:, :-step] = np.maximum(out[:, :-step], a[:, step:])
    out[:, -step:] = np.maximum(out[:, -step:], np.asarray(fill, dtype=a.dtype))
    tmp = out.copy()
    out[:-step, :] = np.maximum(out[:-step, :], tmp[step:, :])
    out[-step:, :] = np.maximum(out[-step:, :], np.asarray(fill, dtype=a.dtype))
    return out


def scan_points(ranges: FloatArray, angles: FloatArray, odom: FloatArray, max_range: float,
                resolution: float, max_points: int) -> FloatArray:
    """The scans' endpoints in the frame of the first scan, thinned for the search.

    Args:
        ranges: (K, B) ranges (m; NaN or ``>= max_range`` = no return).
        angles: (B,) beam angles (rad, laser frame).
        odom: (K, 3) odometry poses at the scans (the scans are joined by it).
        max_range: metres.
        resolution: voxel filter cell (m): one point per cell.
        max_points: at most this many points (an even subsample after the filter).

    Returns:
        (N, 2) points (m), body frame of scan 0.

    Raises:
        CorrelativeError: no usable return.
    """
    ranges = np.asarray(ranges, dtype=float).reshape(len(odom), -1)
    pts = []
    for k in range(len(odom)):
        r = ranges[k]
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(r) & (r > 0) & (r < max_range)
        d = compose(np.zeros(3), _between(odom[0], odom[k]))
        c, s = math.cos(d[2]), math.sin(d[2])
        bx, by = r[ok] * np.cos(angles[ok]), r[ok] * np.sin(angles[ok])
        pts.append(np.column_stack([d[0] + c * bx - s * by, d[1] + s * bx + c * by]))
    p = np.concatenate(pts) if pts else np.zeros((0, 2))
    if len(p) == 0:
        raise CorrelativeError("the scans have no usable return to match")
    keys = np.floor(p / resolution).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    p = p[np.sort(first)]
    if len(p) > max_points:
        p = p[np.linspace(0, len(p) - 1, max_points).round().astype(int)]
    return p


def _between(a: FloatArray, b: FloatArray) -> FloatArray:
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, float(wrap_angle(float(b[2] - a[2])))])


class _TopK:
    """The best ``k`` pairwise well-separated leaves (greedy non-maximum suppression)."""

    def __init__(self, k: int, separation: tuple[float, float], floor: float,
                 window: float) -> None:
        self.k, self.sep, self.floor, self.window = k, separation, floor, window
        self.poses = np.zeros((0, 3))
        self.scores = np.zeros(0)

    def threshold(self) -> float:
        thr = self.floor
        if len(self.scores):
            thr = max(thr, float(self.scores[0]) - self.window)
        if len(self.scores) >= self.k:
            thr = max(thr, float(self.scores[-1]))
        return thr

    def offer(self, poses: FloatArray, scores: FloatArray) -> None:
        for i in np.argsort(-scores):
            s = float(scores[i])
            if s <= self.threshold():
                return
            p = poses[i]
            if len(self.poses):
                near = ((np.hypot(self.poses[:, 0] - p[0], self.poses[:, 1] - p[1]) < self.sep[0])
                        & (np.abs(wrap_angle(self.poses[:, 2] - p[2])) < self.sep[1]))
                if np.any(near & (self.scores >= s)):
                    continue
                keep = ~near
                self.poses, self.scores = self.poses[keep], self.scores[keep]
            j = int(np.searchsorted(-self.scores, -s))
            self.poses = np.insert(self.poses, j, p, axis=0)[: self.k]
            self.scores = np.insert(self.scores, j, s)[: self.k]
            low = self.scores < self.threshold()
            if low.any():
                self.poses, self.scores = self.poses[~low], self.scores[~low]


def branch_and_bound(pyramid: ScorePyramid, points: FloatArray, config: SearchConfig,
                     mask: BoolArray | None = None) -> tuple[list[Candidate], SearchStats]:
    """The top-K well-separated poses of ``points`` over the whole map.

    Args:
        pyramid: the map's score pyramid (built once per map and search resolution).
        points: (N, 2) scan points, body frame (m) (:func:`scan_points`).
        config: the search (angle step, top-K, separation, min_score, batch).
        mask: (Hs, Ws) search cells allowed as poses (default: the free ones).

    Returns:
        The candidates, best first, and the search's counts.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(pts) == 0:
        raise CorrelativeError("no scan points to match")
    n_pts = len(pts)
    depth = len(pyramid.levels) - 1
    n_ang = max(int(round(360.0 / config.angle_step_deg)), 1)
    thetas = np.arange(n_ang) * (2 * math.pi / n_ang) - math.pi
    off_all = np.stack([pyramid.flat_offsets(*pyramid.offsets(pts, float(t))) for t in thetas])
    hs, ws = pyramid.shape
    pd = pyramid.pad
    leaf_ok = (pyramid.free[0][pd : pd + hs, pd : pd + ws] if mask is None
               else np.asarray(mask, bool))
    if leaf_ok.shape != (hs, ws):
        raise CorrelativeError(f"mask {leaf_ok.shape} is not the search grid {(hs, ws)}")
    allowed = [np.zeros_like(pyramid.free[0])]
    allowed[0][pd : pd + hs, pd : pd + ws] = leaf_ok
    for h in range(1, depth + 1):
        allowed.append(window_max(allowed[-1].astype(np.uint8), 2 ** (h - 1), 0) > 0)
    top = _TopK(config.top_k, config.separation, config.min_score * n_pts, config.window * n_pts)
    counts = [0] * (depth + 1)
    leaves = 0

    step = 2**depth
    gy, gx = np.meshgrid(np.arange(0, hs, step), np.arange(0, ws, step), indexing="ij")
    rx, ry = gx.ravel(), gy.ravel()
    keep = allowed[depth][ry + pd, rx + pd]
    rx, ry = rx[keep], ry[keep]
    ra = np.repeat(np.arange(n_ang), len(rx))
    rx, ry = np.tile(rx, n_ang), np.tile(ry, n_ang)

    def bounds(h: int, ix: IntArray, iy: IntArray, ia: IntArray) -> FloatArray:
        out = np.empty(len(ix))
        for s in range(0, len(ix), config.batch):
            sl = slice(s, s + config.batch)
            out[sl] = pyramid.score(h, ix[sl], iy[sl], off_all[ia[sl]])
        return out

    def expand(h: int, ix: IntArray, iy: IntArray, ia: IntArray, b: FloatArray) -> None:
        nonlocal leaves
        order = np.argsort(-b)
        ix, iy, ia, b = ix[order], iy[order], ia[order], b[order]
        for s in range(0, len(ix), config.batch):
            thr = top.threshold()
            sl = slice(s, s + config.batch)
            live = b[sl] > thr
            if not live.any():
                return
            cx, cy, ca = ix[sl][live], iy[sl][live], ia[sl][live]
            if h == 0:
                leaves += len(cx)
                poses = np.column_stack([pyramid.cell_centre(cx, cy), thetas[ca]])
                top.offer(poses, b[sl][live])
                continue
            half = 2 ** (h - 1)
            kx = np.concatenate([cx, cx + half, cx, cx + half])
            ky = np.concatenate([cy, cy, cy + half, cy + half])
            ka = np.tile(ca, 4)
            ok = (kx < ws) & (ky < hs)
            ok[ok] = allowed[h - 1][ky[ok] + pd, kx[ok] + pd]
            kx, ky, ka = kx[ok], ky[ok], ka[ok]
            counts[h - 1] += len(kx)
            expand(h - 1, kx, ky, ka, bounds(h - 1, kx, ky, ka))

    counts[depth] = len(rx)
    expand(depth, rx, ry, ra, bounds(depth, rx, ry, ra))
    cands = [Candidate(top.poses[i].copy(), float(top.scores[i]) / n_pts)
             for i in range(len(top.scores))]
    return cands, SearchStats(tuple(counts[::-1]), leaves)


def field_score(dist_cells: FloatArray, resolution: float, sigma: float, z_hit: float,
                z_rand: float, max_range: float) -> tuple[Float32Array, float]:
    """Per-cell score (H, W) float32 and the off-map floor from a distance field (cells).

    The beam log-likelihood of the likelihood-field model, untempered:
    ``log(z_hit N(d; 0, sigma^2) + z_rand / max_range)`` of the distance ``d``
    (m) to the nearest occupied cell (Probabilistic Robotics, table 6.3).
    """
    d = np.asarray(dist_cells, dtype=np.float32) * np.float32(resolution)
    a = z_hit / (math.sqrt(2 * math.pi) * sigma)
    c = z_rand / max_range
    score = np.log(a * np.exp(-0.5 * (d / np.float32(sigma)) ** 2) + np.float32(c))
    return np.asarray(score, dtype=np.float32), float(math.log(c)) if c > 0 else -1e3


def dilate_free(mask: BoolArray, cells: int) -> BoolArray:
    """``mask`` grown by ``cells`` (a square structuring element)."""
    if cells <= 0:
        return mask
    k = np.ones((2 * cells + 1, 2 * cells + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), k) > 0
