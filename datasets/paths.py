"""Where the shared real-data folder is.

The data recorded by others (MRCLAM, Intel lab, slambook2 RGB-D, KITTI, ceiling
photos) is never copied into the repository. It is found through one setting:
the environment variable ``LAMPSAM_DATA``, defaulting to ``../shared/data``
next to the repository root.
"""

from __future__ import annotations

import os
from pathlib import Path

ENV_VAR = "LAMPSAM_DATA"


def shared_data_dir() -> Path | None:
    """The shared data folder, or None when it is absent.

    Returns:
        ``$LAMPSAM_DATA`` if set, else ``<repo>/../shared/data``; None if that
        directory does not exist.
    """
    env = os.environ.get(ENV_VAR)
    candidate = Path(env) if env else Path(__file__).resolve().parent.parent.parent / "shared" / "data"
    return candidate if candidate.is_dir() else None


def shared_dataset(name: str) -> Path | None:
    """One dataset folder inside the shared data folder (e.g. ``"mrclam_ds0"``), or None."""
    root = shared_data_dir()
    if root is None:
        return None
    path = root / name
    return path if path.exists() else None
