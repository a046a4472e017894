"""Helpers shared by the benchmark scripts (imported as a sibling module): timing,
loading another bench script, and printing a table of result rows."""

from __future__ import annotations

import importlib
import os
import statistics
import sys
import time
from collections.abc import Callable
from types import ModuleType
from typing import Any


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


def print_rows(rows: list[dict[str, Any]]) -> None:
    """The load average, then ``rows`` as a Markdown table (columns of the first row;
    floats to 4 significant digits), flushed so that a long bench shows each table as it
    grows."""
    cols = list(rows[0])
    print("load average (1, 5, 15 min): " + ", ".join(f"{v:.1f}" for v in os.getloadavg()))
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(f"{r[c]:.4g}" if isinstance(r[c], float) else str(r[c])
                                for c in cols) + " |")
    print(flush=True)
    sys.stdout.flush()
