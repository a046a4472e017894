"""Benchmark: one particle-filter measurement update, 10,000 particles x 360 beams.

Compares the three ways to score a scan (target < 50 ms):
the likelihood field (nearest cell and bilinear), the precomputed range table,
and ray marching (sphere tracing) every update. The map is a synthetic
10 m x 10 m office at 5 cm cells (the paper's room size), built with a fixed
seed; ``--intel`` uses the Intel lab map instead (from the shared data).
Prints the median of several runs per method and its ratio to the likelihood
field measured in the same run; also the one-off build times and memory.

``--env-map DIR`` uses the grid layer of an environment map directory (e.g. the
Table-1 office map cached by ``scripts/table1_experiment.py``).
Also prints how closely the range table's expected ranges agree with marching
(per beam, over the same particles).

Usage: ``python scripts/bench/bench_particle_filter.py [--runs 7] [--intel | --env-map DIR]``
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable

import numpy as np
from timing import median_wall_cpu  # scripts/bench/timing.py, a sibling module

from lampsam.localization.grid import OccupancyGrid, free_mask
from lampsam.localization.likelihood import BeamModelConfig, LikelihoodFieldModel, RayCastModel
from lampsam.localization.particle_filter import sample_free_space
from lampsam.localization.raycast import cast_rays


def office_grid(rng: np.random.Generator, size: float = 10.0, res: float = 0.05) -> OccupancyGrid:
    """A walled square room with interior walls and furniture boxes."""
    n = int(round(size / res))
    lo = np.full((n, n), -4.0)
    lo[:2, :] = lo[-2:, :] = lo[:, :2] = lo[:, -2:] = 4.0
    lo[: n // 2, n // 3: n // 3 + 2] = 4.0          # partition
    lo[n // 2 + 20:, 2 * n // 3: 2 * n // 3 + 2] = 4.0
    for _ in range(12):                              # furniture
        w, h = rng.integers(6, 25, 2)
        x, y = rng.integers(5, n - 30, 2)
        lo[y:y + h, x:x + w] = 4.0
    return OccupancyGrid(lo, res, np.zeros(3))


def intel_grid() -> OccupancyGrid:
    """The Intel lab map at 5 cm from every scan at the corrected poses."""
    from lampsam.datasets.carmen import read_carmen
    from lampsam.datasets.paths import shared_dataset
    from lampsam.localization.grid import grid_from_scans

    root = shared_dataset("carmen")
    if root is None:
        raise SystemExit("shared dataset 'carmen' not found")
    s = read_carmen(root / "intel-corrected.log.gz").scans
    r = np.where(s.ranges >= s.max_range, np.nan, s.ranges)
    return grid_from_scans(s.poses, r, s.angles, 0.05, 30.0)


def median_ms(fn: Callable[[], object], runs: int) -> tuple[float, float]:
    """Median wall time and median process CPU time of ``runs`` calls (after a warm-up), ms.

    The CPU time (all threads of this process) is less inflated than the wall
    time when other jobs share the cores.
    """
    fn()
    wall, cpu = median_wall_cpu(fn, runs)
    return 1000.0 * wall, 1000.0 * cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7, help="timed runs per method (default 7)")
    ap.add_argument("--particles", type=int, default=10_000)
    ap.add_argument("--march-runs", type=int, default=1, help="runs for ray marching (slow)")
    ap.add_argument("--intel", action="store_true", help="use the Intel lab map")
    ap.add_argument("--env-map", default=None, help="use the grid of this environment map dir")
    args = ap.parse_args()

    rng = np.random.default_rng(7)
    if args.env_map is not None:
        from lampsam.localization.map_store import load_env_map

        grid = load_env_map(args.env_map).grid
    else:
        grid = intel_grid() if args.intel else office_grid(rng)
    cfg = BeamModelConfig(sigma_hit=0.1, max_range=10.0)
    angles = np.radians(np.arange(360.0))
    particles = sample_free_space(grid, args.particles, rng)
    true_pose = sample_free_space(grid, 1, rng)[0]
    ranges = cast_rays(grid, true_pose[None], angles, cfg.max_range)[0]
    ranges = ranges + rng.normal(0.0, 0.02, ranges.shape)
    ranges[ranges >= cfg.max_range - 0.05] = np.nan
    print(f"map {grid.width} x {grid.height} cells at {grid.resolution} m, "
          f"{int(free_mask(grid).sum())} free; {args.particles} particles x {angles.size} beams "
          f"({int(np.isfinite(ranges).sum())} with a return)")

    t0 = time.perf_counter()
    lf = LikelihoodFieldModel(grid, cfg)
    t_lf = time.perf_counter() - t0
    lf_lin = LikelihoodFieldModel(grid, cfg, interpolate=True)
    t0 = time.perf_counter()
    table = RayCastModel(grid, cfg, "table", n_angles=360)
    t_table = time.perf_counter() - t0
    march = RayCastModel(grid, cfg, "march")
    assert table.table is not None
    print(f"build: likelihood field {1000 * t_lf:.0f} ms; range table {t_table:.1f} s, "
          f"{table.table.nbytes / 1e6:.0f} MB")

    results = {
        "likelihood field (nearest)": median_ms(
            lambda: lf.log_likelihood(particles, ranges, angles), args.runs),
        "likelihood field (bilinear)": median_ms(
            lambda: lf_lin.log_likelihood(particles, ranges, angles), args.runs),
        "range table": median_ms(
            lambda: table.log_likelihood(particles, ranges, angles), args.runs),
        "ray marching": median_ms(lambda: march.log_likelihood(particles, ranges, angles),
                                  args.march_runs),
    }
    ref_wall, ref_cpu = results["likelihood field (nearest)"]
    print(f"{'method':<30}{'wall ms':>10}{'cpu ms':>10}{'x field (wall)':>16}{'x field (cpu)':>15}")
    for name, (wall, cpu) in results.items():
        flag = "" if wall < 50 else "  (wall over 50 ms)"
        print(f"{name:<30}{wall:>10.1f}{cpu:>10.1f}{wall / ref_wall:>16.2f}{cpu / ref_cpu:>15.2f}"
              f"{flag}")
    # Agreement of the expected ranges themselves (nearest cell and 1-deg bin vs exact).
    diff = np.abs(table.expected_ranges(particles, angles) - march.expected_ranges(particles, angles))
    p50, p95, p99 = np.percentile(diff, [50, 95, 99])
    print(f"table vs marching expected ranges: {100 * np.mean(diff <= grid.resolution):.1f} % of "
          f"beams within one cell; |difference| median {100 * p50:.1f} cm, 95 % {100 * p95:.1f} cm, "
          f"99 % {100 * p99:.1f} cm")
    # Agreement: the table and marching rank the particles alike (Spearman-free check).
    best_lf = int(np.argmax(lf.log_likelihood(particles, ranges, angles)))
    best_tab = int(np.argmax(table.log_likelihood(particles, ranges, angles)))
    d = math.hypot(*(particles[best_lf, :2] - particles[best_tab, :2]))
    print(f"best particle: field vs table {d:.2f} m apart; "
          f"field best is {math.hypot(*(particles[best_lf, :2] - true_pose[:2])):.2f} m from truth")


if __name__ == "__main__":
    main()
