"""Output paths checked before any computing, and files written atomically.

Two rules keep finished work from being lost or mistaken:

- :func:`check_output_dir` / :func:`check_output_file` run before a command
  computes anything: an output that exists as the wrong kind (a file where a
  directory is wanted, or the reverse), that cannot be created or written, or that
  already holds results (unless ``force``) is an :class:`~lampsam.errors.InputError`
  naming the path, not an ``OSError`` traceback after minutes of work.
- :func:`append_json_line` / :func:`read_json_lines` keep a progress log of
  finished jobs: a kill cuts at most the last line, which the reader skips.
- :func:`atomic_path` (and :func:`write_text_atomic`, :func:`write_json_atomic`
  built on it) writes to a temporary name in the same directory and renames it
  over the target only when the writer returned: a kill mid-write leaves the old
  file or none, never a half-written file that looks complete. ``os.replace`` is
  atomic on POSIX within one file system.
"""

from __future__ import annotations

import json
import logging
import os
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from lampsam.errors import InputError

log = logging.getLogger(__name__)

TMP_PREFIX = ".tmp-"  #: temporary files are ``.tmp-<hex>-<name>`` beside the target


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path to write ``path`` through; renamed over ``path`` on success.

    The temporary name keeps ``path``'s suffix (writers that choose the format by
    extension, such as ``cv2.imwrite`` and ``savefig``, still work). On an
    exception (including :class:`KeyboardInterrupt`) the temporary file is removed
    and ``path`` is left as it was.

    Usage::

        with atomic_path(out / "trajectory.tum") as tmp:
            write_tum(tmp, trajectory)
    """
    path = Path(path)
    tmp = path.with_name(f"{TMP_PREFIX}{uuid.uuid4().hex[:8]}-{path.name}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write a text file atomically (UTF-8)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def json_default(x: object) -> object:
    """``json.dumps`` fallback for numpy scalars (as Python numbers) and arrays (as lists)."""
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def write_json_atomic(path: str | Path, obj: object,
                      default: Callable[[object], object] = json_default) -> None:
    """Write a JSON document atomically (indented; numpy values through :func:`json_default`)."""
    write_text_atomic(path, json.dumps(obj, indent=2, default=default) + "\n")


def _creatable_dir(path: Path, what: str) -> None:
    """Create ``path`` (and parents) and check a file can be written in it."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError) as exc:
        raise InputError(f"{what}: cannot create the output directory: a file is in the way "
                         f"({exc.filename})", path) from exc
    except OSError as exc:
        raise InputError(f"{what}: cannot create the output directory ({exc.strerror})",
                         path) from exc
    probe = path / f"{TMP_PREFIX}probe-{uuid.uuid4().hex[:8]}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise InputError(f"{what}: the output directory is not writable ({exc.strerror})",
                         path) from exc


def check_output_dir(path: str | Path, force: bool = False, what: str = "--out",
                     allow: Callable[[Path], bool] | None = None) -> Path:
    """Check (and create) an output directory before any computing.

    Args:
        path: the directory.
        force: allow a directory that already holds files (they are overwritten).
        what: how to name it in messages (``"--out"``...).
        allow: when given, a non-empty directory is accepted if ``allow(path)``
            is True (e.g. ``compare --resume`` on its own earlier output).

    Returns:
        ``path`` as a ``Path`` (created, empty unless ``force`` or ``allow``).

    Raises:
        InputError: exists as a file, cannot be created or written, or is not
            empty without ``force``.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{what}: is a file, not an output directory", path)
    if path.is_dir() and not force and any(path.iterdir()):
        if allow is None or not allow(path):
            raise InputError(f"{what}: the output directory is not empty (use --force to "
                             "overwrite its files)", path)
    _creatable_dir(path, what)
    return path


def check_output_file(path: str | Path, force: bool = False, what: str = "--out") -> Path:
    """Check an output file's place before any computing (its directory is created).

    Raises:
        InputError: ``path`` is a directory, exists without ``force``, or its
            directory cannot be created or written.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{what}: is a directory, not an output file", path)
    if path.exists() and not force:
        raise InputError(f"{what}: the output file exists (use --force to overwrite it)", path)
    _creatable_dir(path.parent, what)
    return path


def append_json_line(path: str | Path, row: object) -> None:
    """Append one JSON document as a line to a JSON-lines file, in one ``write`` call.

    A progress log of finished jobs: each line is complete once written and flushed;
    a kill can cut at most the line being written, which :func:`read_json_lines` skips.
    """
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(json.dumps(row, default=json_default) + "\n")
        fh.flush()


def read_json_lines(path: str | Path) -> list[dict[str, object]]:
    """The objects of a JSON-lines file (blank lines skipped).

    A last line without its newline that does not parse is the line a kill cut
    short (:func:`append_json_line`): it is skipped with a warning, as unfinished
    work. Any other line that does not parse, or that is not an object, is an
    :class:`~lampsam.errors.InputError` naming the file and line.
    """
    path = Path(path)
    text = path.read_text(encoding="utf-8")
    lines = text.split("\n")
    rows: list[dict[str, object]] = []
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
        except json.JSONDecodeError as exc:
            if i == len(lines) - 1:  # no newline after it: cut short by a kill
                log.warning("%s:%d: skipping a line cut short (unfinished write)", path, i + 1)
                continue
            raise InputError(f"not JSON ({exc.msg})", path, i + 1) from exc
        if not isinstance(obj, dict):
            raise InputError("not a JSON object", path, i + 1)
        rows.append(obj)
    return rows
