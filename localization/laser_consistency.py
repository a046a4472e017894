"""Do a laser log's poses agree with each other? A cross-check of its scans.

A grid map drawn at poses that drift (a raw log's odometry instead of corrected
poses) shows every wall twice; nothing in the log says so, and the map would be
used as if it were right. The check: the keyframes are split into ``K`` chunks
in time; each chunk's hit cells are compared with the grid of the OTHER chunks
(the sum of their log-odds, clamped). Of the hit cells that grid has seen (free
or occupied), the consistent ones lie within one cell of an occupied cell. With
agreeing poses a revisited wall is hit where the other chunks saw it; with
drifting poses the hits fall into free space the other chunks saw.

Measured (docs/failures.md, "A new user's first day"): the real Intel log at its
corrected poses 0.865; the same log with simulated odometry drift of 0.5 m over the
run 0.653 (1.8 m: 0.396); the threshold 0.75 was set on these. Held out, the
simulated campus log: 0.990 at its true poses, 0.613 with 10 m of drift over its
~1 km drive, but 0.848 with 3.4 m: mild drift over a long run is not caught.

World frame: ``x, y`` metres; cells as in :mod:`lampsam.localization.grid`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from lampsam.arrays import FloatArray, IntArray
from lampsam.localization.grid import LogOddsConfig


@dataclass(frozen=True)
class ScanConsistency:
    """How well a log's scans agree with each other at its poses.

    Attributes:
        score: fraction of the checked hit cells that lie within one cell of an
            occupied cell of the other chunks' grid, in [0, 1] (NaN: none checked).
        per_chunk: (K,) the same fraction per chunk (NaN where none checked).
        checked: hit cells that fell on cells the other chunks' grid has seen.
        hits: all hit cells of the keyframes (one per cell per scan).
        threshold: the score below which the poses are called inconsistent.
    """

    score: float
    per_chunk: tuple[float, ...]
    checked: int
    hits: int
    threshold: float

    @property
    def poor(self) -> bool:
        """Whether the score is below the threshold (NaN is not poor: nothing to say)."""
        return bool(self.score < self.threshold)

    def as_dict(self) -> dict[str, object]:
        """Plain values for a manifest (strict JSON: NaN as None)."""
        def num(v: float) -> float | None:
            return round(v, 4) if math.isfinite(v) else None
        return {"score": num(self.score), "per_chunk": [num(v) for v in self.per_chunk],
                "hit_cells_checked": self.checked, "hit_cells": self.hits,
                "threshold": self.threshold, "poor": self.poor}


def chunk_of(n_keyframes: int, chunks: int) -> IntArray:
    """(n_keyframes,) chunk index of each keyframe in time order (``chunks`` near-equal parts)."""
    return (np.arange(n_keyframes) * chunks) // max(n_keyframes, 1)


def cross_chunk_consistency(chunk_log_odds: list[FloatArray], chunk_hits: list[IntArray],
                            log_odds: LogOddsConfig, threshold: float) -> ScanConsistency:
    """Each chunk's hit cells against the grid of the other chunks (module docstring).

    Args:
        chunk_log_odds: K (H, W) log-odds grids, one per chunk, same geometry.
        chunk_hits: K arrays of flat cell indices ``iy * W + ix`` where a beam of a
            keyframe of that chunk ended (repeated across scans).
        log_odds: thresholds and clamps of the inverse sensor model.
        threshold: a score below it is ``poor``.

    Returns:
        The :class:`ScanConsistency`.
    """
    total = np.sum(chunk_log_odds, axis=0)
    occ_l = math.log(log_odds.occupied_thresh / (1.0 - log_odds.occupied_thresh))
    free_l = math.log(log_odds.free_thresh / (1.0 - log_odds.free_thresh))
    kernel = np.ones((3, 3), np.uint8)
    per: list[float] = []
    checked = consistent = n_hits = 0
    for lo_k, hits in zip(chunk_log_odds, chunk_hits, strict=True):
        other = np.clip(total - lo_k, log_odds.l_min, log_odds.l_max)
        near_occ = cv2.dilate((other > occ_l).astype(np.uint8), kernel).astype(bool).ravel()
        seen = near_occ | (other < free_l).ravel()
        k_seen = seen[hits]
        k_ok = near_occ[hits] & k_seen
        n_seen, n_ok = int(k_seen.sum()), int(k_ok.sum())
        per.append(n_ok / n_seen if n_seen else math.nan)
        checked += n_seen
        consistent += n_ok
        n_hits += len(hits)
    score = consistent / checked if checked else math.nan
    return ScanConsistency(score, tuple(per), checked, n_hits, threshold)
