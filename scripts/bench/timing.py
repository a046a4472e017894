"""Helpers shared by the benchmark scripts (imported as a sibling module): timing, and
loading another bench script."""

from __future__ import annotations

import importlib
import statistics
import time
from collections.abc import Callable
from types import ModuleType


def median_wall_cpu(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """Median wall and process-CPU seconds of ``fn`` over ``repeats`` calls (no warm-up)."""
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def sibling(name: str) -> ModuleType:
    """Another script of ``scripts/bench`` as a module (e.g. ``bench_noids_scale`` for its log
    loaders and scoring); the folder is on ``sys.path`` when a script in it is run."""
    return importlib.import_module(name)
