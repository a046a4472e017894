"""Output directories of the evaluation jobs: created up front, failures named.

Every job that writes files (``stereo``, ``frontend-eval``, ``gallery``,
``compare``) creates its output directory with :func:`ensure_dir` before the
work, so that an impossible output path (below a file, no permission) is a
:class:`~lampsam.errors.LampsamError` naming the path, not an ``OSError``
traceback after minutes of computing.
"""

from __future__ import annotations

from pathlib import Path

from lampsam.errors import LampsamError


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
