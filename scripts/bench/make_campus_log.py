"""A campus-scale simulated laser log (CARMEN format) for the global-localization trials.

A 140 m x 140 m site of irregular buildings (random sizes and offsets, so no
two places look alike by construction, but many look similar) crossed by
streets; a robot drives a serpentine over the streets, scanning 180 beams over
180 degrees (30 m range, 1 cm noise) every 0.5 m. Written as
``FLASER`` lines with the true poses as the corrected poses, so that
``lampsam build-map LOG`` and ``lampsam localize LOG --map MAP --trials N``
run on it like on the Intel log.

Usage: ``python scripts/bench/make_campus_log.py OUT.log [--seed 0]``
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from lampsam.datasets.carmen import carmen_beam_angles
from lampsam.localization.grid import OccupancyGrid, free_mask
from lampsam.localization.raycast import cast_rays
from lampsam.safe_io import atomic_path

SIZE, RES, BLOCK, STREET = 140.0, 0.1, 20.0, 6.0


def campus_grid(rng: np.random.Generator) -> OccupancyGrid:
    """Buildings in 20 m blocks (each a random rectangle, sometimes two), 6 m streets."""
    g = OccupancyGrid.empty(0.0, 0.0, SIZE, SIZE, RES)
    lo = np.full((g.height, g.width), -4.0)
    lo[:3, :] = lo[-3:, :] = lo[:, :3] = lo[:, -3:] = 4.0
    for bx in np.arange(STREET, SIZE - BLOCK + 1e-9, BLOCK):
        for by in np.arange(STREET, SIZE - BLOCK + 1e-9, BLOCK):
            for _ in range(int(rng.integers(1, 3))):
                w, h = rng.uniform(4.0, BLOCK - STREET, 2)
                x0 = bx + rng.uniform(0.0, BLOCK - STREET - w)
                y0 = by + rng.uniform(0.0, BLOCK - STREET - h)
                lo[int(y0 / RES) : int((y0 + h) / RES), int(x0 / RES) : int((x0 + w) / RES)] = 4.0
    g.log_odds = lo
    return g


def serpentine(step: float) -> np.ndarray:
    """(N, 3) poses along the streets at y = k * BLOCK + STREET / 2, back and forth."""
    pts = []
    ys = np.arange(STREET / 2, SIZE - STREET / 2 + 1e-9, BLOCK)
    for i, y in enumerate(ys):
        xs = np.arange(STREET / 2, SIZE - STREET / 2, step)
        xs = xs if i % 2 == 0 else xs[::-1]
        th = 0.0 if i % 2 == 0 else math.pi
        pts += [(x, y, th) for x in xs]
        if i + 1 < len(ys):  # up the street at the end
            x_end = xs[-1]
            pts += [(x_end, yy, math.pi / 2) for yy in np.arange(y + step, ys[i + 1], step)]
    return np.array(pts)


def main() -> None:
    """Write the log."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    grid = campus_grid(rng)
    poses = serpentine(0.5)
    angles = carmen_beam_angles(180)
    ranges = cast_rays(grid, poses, angles, 30.0)
    ranges = np.where(ranges >= 30.0 - 1e-6, 81.83, ranges + rng.normal(0, 0.01, ranges.shape))
    with atomic_path(args.out) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        for k, (p, r) in enumerate(zip(poses, ranges, strict=True)):
            ts = 1000.0 + 0.5 * k
            fh.write(f"FLASER 180 {' '.join(f'{v:.3f}' for v in r)} {p[0]:.4f} {p[1]:.4f} {p[2]:.4f} "
                     f"{p[0]:.4f} {p[1]:.4f} {p[2]:.4f} {ts:.3f} host {ts:.3f}\n")  # fmt: skip
    free = int(free_mask(grid).sum()) * RES**2
    print(f"{args.out}: {len(poses)} scans, {free:.0f} m^2 free")


if __name__ == "__main__":
    main()
