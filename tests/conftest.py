"""Shared fixtures: seeded generators, the shared real-data folder, and the environment
for running this checkout's ``lampsam`` in a subprocess."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lampsam.datasets.paths import shared_dataset


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
