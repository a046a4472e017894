"""Shared fixtures: seeded generators, the shared real-data folder, simulated runs made
once per session, and the environment for running this checkout's ``lampsam`` in a
subprocess."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lampsam.datasets.paths import shared_dataset
from lampsam.interrupt import EXIT_INTERRUPTED
from lampsam.localization.grid import OccupancyGrid


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh generator with a fixed seed for each test."""
    return np.random.default_rng(20261122)


def require_shared(name: str) -> Path:
    """Path of a shared dataset, or skip the test with the reason."""
    path = shared_dataset(name)
    if path is None:
        pytest.skip(f"shared dataset {name!r} not found (set LAMPSAM_DATA or place ../shared/data)")
    return path


SimRun = Callable[..., Path]
"""``sim_run(world="lab", *, seed, duration)``: the folder of a simulated run (see
:func:`sim_run`)."""


def _fingerprint(folder: Path) -> dict[str, tuple[int, int]]:
    """Every file and folder below ``folder``: relative path -> (size, mtime in ns)."""
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in folder.rglob("*")}


@pytest.fixture(scope="session")
def sim_run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimRun]:
    """Factory of simulated runs (``lampsam.simulate_world``, in-process), each made once
    per test session (once per xdist worker) and shared by every test that asks for the
    same ``(world, seed, duration)``.

    The runs are read-only: a test that writes into one (an output file, a corrupted
    copy) must copy it first. Checked when the session ends: any file added, removed or
    rewritten below a shared run fails the last test's teardown, naming the run.

    Returns:
        ``make(world="lab", *, seed, duration) -> Path`` (``duration`` in seconds of
        the world's path; the run's folder, holding ``rig.yaml``, ``images/`` ...).
    """
    from lampsam.datasets.simulator import simulate_world

    made: dict[tuple[str, int, float], tuple[Path, dict[str, tuple[int, int]]]] = {}

    def make(world: str = "lab", *, seed: int, duration: float) -> Path:
        key = (world, seed, float(duration))
        if key not in made:
            name = f"sim_{world}_seed{seed}_{duration:g}s".replace(".", "_")
            out = simulate_world(world, tmp_path_factory.mktemp(name) / "run", seed=seed,
                                 duration=duration, workers=1)
            made[key] = (out, _fingerprint(out))
        return made[key][0]

    yield make
    changed = [str(out) for out, before in made.values() if _fingerprint(out) != before]
    assert not changed, f"a test wrote into a shared simulated run (read-only): {changed}"


#: the folder that holds this checkout's ``lampsam/`` (a development checkout is importable
#: from it; an installed package is found without it)
PACKAGE_PARENT = Path(__file__).resolve().parents[2]


@pytest.fixture
def cli_env() -> dict[str, str]:
    """Environment for a subprocess running ``python -m lampsam`` (or a script importing
    it) from this checkout, with one BLAS/OpenMP thread."""
    path = os.pathsep.join(p for p in (str(PACKAGE_PARENT), os.environ.get("PYTHONPATH")) if p)
    return dict(os.environ, PYTHONPATH=path, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")


def start_lampsam(env: dict[str, str], *args: str) -> subprocess.Popen[str]:
    """``python -m lampsam -v ARGS`` in a subprocess with ``env`` (:func:`cli_env`),
    stdout and stderr piped as text."""
    return subprocess.Popen([sys.executable, "-m", "lampsam", "-v", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for_line(proc: subprocess.Popen[str], text: str, timeout: float = 120.0) -> list[str]:
    """Read ``proc``'s stderr lines until one contains ``text``; returns the lines read.
    Kills the process and fails the test when the stream ends or ``timeout`` (s) passes
    first."""
    assert proc.stderr is not None
    lines = []
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        line = proc.stderr.readline()
        if not line:
            break
        lines.append(line)
        if text in line:
            return lines
    proc.kill()
    raise AssertionError(f"{text!r} never printed: {''.join(lines)}")


def interrupted_summary(proc: subprocess.Popen[str], out: Path, total_steps: int,
                        lines: Sequence[str] = (), signal_name: str | None = None) -> dict[str, Any]:
    """Wait (120 s at most: a hang at exit fails) for a ``lampsam slam`` stopped by a
    signal and check what it left: exit 3 with no traceback (and ``SIGxxx received``
    with ``signal_name``), ``summary.json`` status interrupted with some but not all of
    the run's ``total_steps``, ``trajectory.tum`` one finite row per finished step,
    ``landmarks.csv`` written, no temporary file left in ``out``.

    Args:
        lines: stderr lines already read from ``proc`` (:func:`wait_for_line`).

    Returns:
        The summary.
    """
    try:
        _, rest = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError("the process hung at exit after the signal") from None
    rest = "".join(lines) + rest
    assert proc.returncode == EXIT_INTERRUPTED, rest
    assert "Traceback" not in rest
    if signal_name is not None:
        assert f"{signal_name} received" in rest, rest
    summary: dict[str, Any] = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "interrupted"
    assert 0 < summary["steps"] < total_steps
    traj = np.loadtxt(out / "trajectory.tum", ndmin=2)
    assert len(traj) == summary["steps"] and np.all(np.isfinite(traj))
    assert (out / "landmarks.csv").read_text().startswith("id,type")
    assert not [p for p in out.iterdir() if p.name.startswith(".tmp-")]
    return summary


def cast_grid_ranges(grid: OccupancyGrid, poses: np.ndarray, angles: np.ndarray,
                     max_range: float, step: float) -> np.ndarray:
    """(N, B) ranges from each pose ``(x, y, theta)`` to the first occupied cell
    (``log_odds > 0``) along body-frame beam ``angles`` (rad), marched in ``step`` m;
    ``max_range`` where none is hit. The laser-log tests' independent truth (no
    lampsam ray caster)."""
    occ = grid.log_odds > 0
    steps = np.arange(step, max_range, step)
    out = np.full((len(poses), len(angles)), max_range)
    for k, p in enumerate(poses):
        phi = p[2] + angles
        xy = p[:2] + steps[None, :, None] * np.stack([np.cos(phi), np.sin(phi)], -1)[:, None, :]
        cells = grid.world_to_cell(xy.reshape(-1, 2)).reshape(len(angles), len(steps), 2)
        inside = grid.in_bounds(cells)
        hit = np.zeros(inside.shape, bool)
        hit[inside] = occ[cells[inside][:, 1], cells[inside][:, 0]]
        first = np.argmax(hit, axis=1)
        out[k] = np.where(hit.any(axis=1), steps[first], max_range)
    return out


def boxed_room(width: float, height: float,
               boxes: Sequence[tuple[float, float, float, float]]) -> OccupancyGrid:
    """A ``width`` x ``height`` m room at the origin, 0.1 m cells: 0.2 m walls and the
    ``(x0, y0, x1, y1)`` boxes occupied (log-odds 4), the rest free (-4)."""
    g = OccupancyGrid.empty(0.0, 0.0, width, height, 0.1)
    lo = np.full((g.height, g.width), -4.0)
    lo[:2, :] = lo[-2:, :] = lo[:, :2] = lo[:, -2:] = 4.0
    for x0, y0, x1, y1 in boxes:
        lo[int(y0 * 10):int(y1 * 10), int(x0 * 10):int(x1 * 10)] = 4.0
    g.log_odds = lo
    return g


def rectangle_laps(lo: tuple[float, float], hi: tuple[float, float], laps: int,
                   step: float) -> np.ndarray:
    """(N, 3) poses driven ``laps`` times around the rectangle from corner ``lo`` to
    ``hi`` (counter-clockwise from ``lo``), every ``step`` m, heading along each side."""
    corners = [lo, (hi[0], lo[1]), hi, (lo[0], hi[1]), lo]
    lap = []
    for (xa, ya), (xb, yb) in zip(corners[:-1], corners[1:], strict=True):
        n = int(round(math.hypot(xb - xa, yb - ya) / step))
        th = math.atan2(yb - ya, xb - xa)
        lap += [(xa + (xb - xa) * k / n, ya + (yb - ya) * k / n, th) for k in range(n)]
    return np.array(lap * laps)


def write_flaser_log(path: Path, poses: np.ndarray, ranges: np.ndarray) -> Path:
    """A CARMEN log of one ``FLASER 180`` line per scan: ``ranges`` (N, 180) m at ``poses``
    (N, 3) (as laser and odometry pose), 5 Hz from t = 100 s; returns ``path``."""
    with open(path, "w", encoding="utf-8") as fh:
        for k, (p, r) in enumerate(zip(poses, ranges, strict=True)):
            ts = 100.0 + 0.2 * k
            fh.write(f"FLASER 180 {' '.join(f'{v:.3f}' for v in r)} {p[0]:.4f} {p[1]:.4f} "
                     f"{p[2]:.4f} {p[0]:.4f} {p[1]:.4f} {p[2]:.4f} {ts:.3f} host {ts:.3f}\n")
    return path
