"""Benchmark the ceiling simulator: per-frame rendering, truth projection, whole runs.

Prints medians of several repetitions and, as the reference measured in the same
process, one full-grid bilinear ``cv2.remap`` of the supersampled ray grid (the
lower bound of a frame: the renderer does that for the ceiling plus small windows
for lamps and low surfaces). The target is a 3-minute lab run at
15 images/s (2,700 frames) in under a minute on a 2-core machine.

    .venv/bin/python scripts/bench/bench_simulator.py [--full] [--repeats N]

``--full`` also simulates the whole lab path (about 3 minutes, 2,600 frames) with
2 worker processes. Timings on a shared machine are inflated by other load; the
CPU time per frame is the steadier figure.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from lampsam.datasets.ceiling_truth import occluders, project_landmarks
from lampsam.datasets.render_ceiling import CeilingRenderer
from lampsam.datasets.simulator import simulate_trajectory, simulate_world
from lampsam.datasets.world import load_world
from lampsam.datasets.world_landmarks import world_landmarks


def _median_ms(fn, poses: np.ndarray, repeats: int) -> tuple[float, float]:
    """Median wall and CPU ms per call over ``repeats`` passes through ``poses``."""
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        for p in poses:
            fn(p)
        wall.append(1000 * (time.perf_counter() - t0) / len(poses))
        cpu.append(1000 * (time.process_time() - c0) / len(poses))
    return statistics.median(wall), statistics.median(cpu)


def main() -> None:
    """Run the benchmark and print the figures."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--frames", type=int, default=40, help="poses per repetition")
    ap.add_argument("--full", action="store_true", help="also simulate the whole lab path")
    args = ap.parse_args()

    cv2.setNumThreads(1)
    world = load_world("lab")
    t0 = time.perf_counter()
    renderer = CeilingRenderer(world)
    build_s = time.perf_counter() - t0
    _, poses, _, _ = simulate_trajectory(world, seed=0)
    sel = poses[np.linspace(0, len(poses) - 1, args.frames).astype(int)]
    rng = np.random.default_rng(0)
    lms = world_landmarks(world)
    occ = occluders(world)

    # Reference: one bilinear remap of the whole supersampled grid from the ceiling texture.
    layer = renderer.layers[-1]
    mx = renderer.u * np.float32(200) + np.float32(layer.flat.shape[1] / 2)
    my = renderer.v * np.float32(200) + np.float32(layer.flat.shape[0] / 2)

    def ref(_: np.ndarray) -> None:
        """The reference: one full-grid remap."""
        cv2.remap(layer.flat, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    ref_ms, ref_cpu = _median_ms(ref, sel, args.repeats)
    ren_ms, ren_cpu = _median_ms(lambda p: renderer.render(p, rng), sel, args.repeats)
    tru_ms, tru_cpu = _median_ms(
        lambda p: project_landmarks(renderer.camera, p, lms, occ, renderer.m_max), sel, args.repeats
    )
    s = world.render.supersample
    print(f"lab world: {len(renderer.layers)} layers built in {build_s:.2f} s; "
          f"{s}x{s} rays/pixel, 320x240, 1 OpenCV thread")  # fmt: skip
    print(f"reference (one {renderer.u.shape[1]}x{renderer.u.shape[0]} remap): "
          f"{ref_ms:.2f} ms wall, {ref_cpu:.2f} ms CPU")  # fmt: skip
    print(f"render frame:      {ren_ms:6.2f} ms wall, {ren_cpu:6.2f} ms CPU "
          f"(= {ren_ms / ref_ms:.1f} x reference)")  # fmt: skip
    print(f"truth projections: {tru_ms:6.2f} ms wall, {tru_cpu:6.2f} ms CPU")
    per_frame = ren_cpu + tru_cpu
    print(f"3-min lab run (2,700 frames) on 2 idle cores, CPU-bound estimate: "
          f"{2700 * per_frame / 2 / 1000:.1f} s")  # fmt: skip

    with tempfile.TemporaryDirectory() as tmp:
        durations = [None] if args.full else [20.0]
        for dur in durations:
            t0, c0 = time.perf_counter(), time.process_time()
            out = simulate_world(world, Path(tmp) / "run", seed=0, duration=dur, workers=2)
            wall = time.perf_counter() - t0
            n = sum(1 for _ in open(out / "images.csv")) - 1
            label = "whole lab path" if dur is None else f"{dur:.0f} s of the lab path"
            print(f"simulate_world ({label}, 2 workers): {n} frames in {wall:.1f} s wall "
                  f"= {1000 * wall / n:.1f} ms/frame -> 2,700 frames in {2.7 * wall / n * 1000:.0f} s")  # fmt: skip
            print(f"  (parent-process CPU {time.process_time() - c0:.1f} s; workers not counted)")


if __name__ == "__main__":
    main()
