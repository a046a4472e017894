"""Shared fixtures: seeded generators and the shared real-data folder."""

from __future__ import annotations

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
