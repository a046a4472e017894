"""Benchmark: building the environment map of a 5-minute office drive (target: under 2 min).

Simulates the office zig-zag mapping drive with the Kinect (``kinect_sim``; about
287 s of driving, 862 frames at 3 Hz, 320x240) unless ``--run`` names an existing
run, then times, median of ``--repeats`` runs:

* reference: reading every colour and depth frame (the I/O floor of any build);
* ``grid only``: the grid map from depth (``build_depth_layers`` without features);
* ``build_map``: the whole map directory (grid, SIFT spatial layer with merging,
  ceiling layer, manifest, truth checks).

Both wall-clock and process CPU time are printed: the machine is shared by several
engineers, so wall time is inflated by their load; ratios against the reference
measured in the same run are more stable. Also prints the grid's precision/recall
against the world's true geometry.

Usage: ``.venv/bin/python scripts/bench/bench_build_map.py [--run RUN] [--repeats 3]``
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from timing import median_wall_cpu  # scripts/bench/timing.py, a sibling module

from lampsam.datasets.kinect_sim import simulate_kinect_run
from lampsam.datasets.rgbd import read_tum_rgbd
from lampsam.evaluation.map_truth import floor_plan_of_run
from lampsam.localization.depth_grid import build_depth_layers
from lampsam.localization.map_build import build_map
from lampsam.localization.map_config import EnvMapConfig


def main() -> None:
    """Run the benchmark and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", default=None, help="existing run with kinect/ (default: simulate)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per case (default 3)")
    parser.add_argument("--duration", type=float, default=None, help="drive seconds (default all)")
    args = parser.parse_args()
    tmp = tempfile.TemporaryDirectory(prefix="bench_build_map_")
    if args.run is None:
        t0 = time.perf_counter()
        run = simulate_kinect_run("office", Path(tmp.name) / "run", seed=0, duration=args.duration)
        print(f"simulated the office drive in {time.perf_counter() - t0:.1f} s")
    else:
        run = Path(args.run)
    seq = read_tum_rgbd(run / "kinect")
    drive_s = float(seq.t[-1] - seq.t[0])
    print(f"run {run}: {len(seq)} frames, {drive_s:.0f} s of driving")

    def read_all() -> None:
        for i in range(len(seq)):
            seq.load_rgb(i)
            seq.load_depth(i)

    def grid_only() -> None:
        build_depth_layers(seq, seq.world_T_camera, EnvMapConfig(), with_features=False)

    truth = floor_plan_of_run(run, EnvMapConfig().depth.height_band)
    reports = []

    def full() -> None:
        reports.append(build_map(run, Path(tmp.name) / "map", truth=truth))

    read_all()  # warm the imports and the file cache
    ref_w, ref_c = median_wall_cpu(read_all, args.repeats)
    grid_w, grid_c = median_wall_cpu(grid_only, args.repeats)
    full_w, full_c = median_wall_cpu(full, args.repeats)
    print(f"{'case':<22}{'wall s':>9}{'cpu s':>9}{'x ref (wall)':>14}")
    for name, w, c in (
        ("reference: read", ref_w, ref_c),
        ("grid only", grid_w, grid_c),
        ("build_map (all)", full_w, full_c),
    ):
        print(f"{name:<22}{w:>9.1f}{c:>9.1f}{w / ref_w:>14.1f}")
    verdict = "under" if full_w < 120.0 else "OVER"
    print(f"build_map of a {drive_s / 60:.1f}-minute drive: {full_w:.1f} s wall ({verdict} 2 min)")
    print(f"per-stage seconds of the last build: {reports[-1].timings}")
    print(f"grid vs world: {reports[-1].checks.get('grid_vs_world')}")
    tmp.cleanup()


if __name__ == "__main__":
    main()
