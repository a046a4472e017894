"""Do a laser log's poses agree with each other? A cross-check of its scans.

A grid map drawn at poses that drift (a raw log's odometry instead of corrected
poses) shows every wall twice; nothing in the log says so, and the map would be
used as if it were right. The check: the keyframes are split into ``K`` chunks
in time; each chunk's hit cells are compared with the grid of the OTHER chunks
(the sum of their log-odds, clamped). Of the hit cells that grid has seen (free
or occupied), the consistent ones lie within one cell of an occupied cell. With
agreeing poses a revisited wall is hit where the other chunks saw it; with
drifting poses the hits fall into free space the other chunks saw.

Two rules, either flags the poses: the whole log's fraction below
``min_consistency`` (0.75), or its worst chunk's below ``min_chunk_consistency``
(0.70): drift over a long drive spoils one stretch of it while the others still
agree, and the mean hides it. Measured in docs/envmap.md (Intel tuned on, the
simulated campus held out).

World frame: ``x, y`` metres; cells as in :mod:`lampsam.localization.grid`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from lampsam.arrays import FloatArray, IntArray
from lampsam.localization.grid import LogOddsConfig, free_cells, occupied_cells


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
        chunk_threshold: the worst chunk's fraction below which they are called
            inconsistent too (NaN: no such rule).
    """

    score: float
    per_chunk: tuple[float, ...]
    checked: int
    hits: int
    threshold: float
    chunk_threshold: float = math.nan

    @property
    def worst_chunk(self) -> float:
        """The lowest per-chunk fraction (NaN when no chunk was checked)."""
        finite = [v for v in self.per_chunk if math.isfinite(v)]
        return min(finite) if finite else math.nan

    @property
    def poor(self) -> bool:
        """Whether the score, or the worst chunk, is below its threshold (NaN is not poor)."""
        return bool(self.score < self.threshold or self.worst_chunk < self.chunk_threshold)

    def reason(self) -> str:
        """Why the poses are called inconsistent, in a sentence (the warnings use it)."""
        if self.score < self.threshold:
            return (f"{100 * self.score:.0f} % of the hits checked lie on walls the rest of the "
                    f"log saw (below {100 * self.threshold:.0f} %)")
        if self.worst_chunk < self.chunk_threshold:
            return (f"in the worst of its {len(self.per_chunk)} time chunks "
                    f"{100 * self.worst_chunk:.0f} % of the hits checked lie on walls the rest "
                    f"of the log saw (below {100 * self.chunk_threshold:.0f} %; "
                    f"{100 * self.score:.0f} % over the whole log)")
        return (f"{100 * self.score:.0f} % of the hits checked lie on walls the rest of the log "
                f"saw, {100 * self.worst_chunk:.0f} % in the worst time chunk")

    def as_dict(self) -> dict[str, object]:
        """Plain values for a manifest (strict JSON: NaN as None)."""
        def num(v: float) -> float | None:
            return round(v, 4) if math.isfinite(v) else None
        return {"score": num(self.score), "per_chunk": [num(v) for v in self.per_chunk],
                "worst_chunk": num(self.worst_chunk),
                "hit_cells_checked": self.checked, "hit_cells": self.hits,
                "threshold": self.threshold, "chunk_threshold": num(self.chunk_threshold),
                "poor": self.poor, "reason": self.reason()}


def chunk_of(n_keyframes: int, chunks: int) -> IntArray:
    """(n_keyframes,) chunk index of each keyframe in time order (``chunks`` near-equal parts)."""
    return (np.arange(n_keyframes) * chunks) // max(n_keyframes, 1)


def cross_chunk_consistency(chunk_log_odds: list[FloatArray], chunk_hits: list[IntArray],
                            log_odds: LogOddsConfig, threshold: float,
                            chunk_threshold: float = math.nan) -> ScanConsistency:
    """Each chunk's hit cells against the grid of the other chunks (module docstring).

    Args:
        chunk_log_odds: K (H, W) log-odds grids, one per chunk, same geometry.
        chunk_hits: K arrays of flat cell indices ``iy * W + ix`` where a beam of a
            keyframe of that chunk ended (repeated across scans).
        log_odds: thresholds and clamps of the inverse sensor model.
        threshold: a score below it is ``poor``.
        chunk_threshold: a worst chunk below it is ``poor`` too (NaN: no such rule).

    Returns:
        The :class:`ScanConsistency`.
    """
    total = np.sum(chunk_log_odds, axis=0)
    kernel = np.ones((3, 3), np.uint8)
    per: list[float] = []
    checked = consistent = n_hits = 0
    for lo_k, hits in zip(chunk_log_odds, chunk_hits, strict=True):
        other = np.clip(total - lo_k, log_odds.l_min, log_odds.l_max)
        near_occ = cv2.dilate(occupied_cells(other, log_odds).astype(np.uint8), kernel).astype(bool).ravel()
        seen = near_occ | free_cells(other, log_odds).ravel()
        k_seen = seen[hits]
        k_ok = near_occ[hits] & k_seen
        n_seen, n_ok = int(k_seen.sum()), int(k_ok.sum())
        per.append(n_ok / n_seen if n_seen else math.nan)
        checked += n_seen
        consistent += n_ok
        n_hits += len(hits)
    score = consistent / checked if checked else math.nan
    return ScanConsistency(score, tuple(per), checked, n_hits, threshold, chunk_threshold)
