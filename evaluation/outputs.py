"""Outputs of the evaluation jobs: directories created up front, figures written atomically.

Every job that writes files (``stereo``, ``frontend-eval``, ``gallery``,
``compare``) creates its output directory with :func:`ensure_dir` before the
work, so that an impossible output path (below a file, no permission) is a
:class:`~lampsam.errors.LampsamError` naming the path, not an ``OSError``
traceback after minutes of computing. :func:`save_figure` writes a finished
matplotlib figure through :func:`lampsam.safe_io.atomic_path` and closes it.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from lampsam.errors import LampsamError
from lampsam.safe_io import atomic_path

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def ensure_dir(path: str | Path, error: type[LampsamError] = LampsamError) -> Path:
    """Create a directory and its parents if needed.

    Args:
        path: the directory.
        error: the error class to raise (the calling module's own subclass).

    Returns:
        ``path`` as a ``Path``.

    Raises:
        LampsamError: (``error``) the directory cannot be created; the message
            names ``path`` and the operating system's reason.
    """
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise error(f"{path}: cannot create the output directory ({exc.strerror})") from exc
    return path


def save_figure(fig: Figure, path: str | Path, dpi: int) -> Path:
    """Write a figure atomically (the format from ``path``'s suffix) and close it.

    Args:
        fig: the finished figure.
        path: output file (its folder must exist).
        dpi: resolution, dots per inch.

    Returns:
        ``path`` as a ``Path``.
    """
    import matplotlib.pyplot as plt

    out = Path(path)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    return out
