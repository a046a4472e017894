"""Shared fixtures: seeded generators, the shared real-data folder, and the environment
for running this checkout's ``lampsam`` in a subprocess."""

from __future__ import annotations

import os
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
