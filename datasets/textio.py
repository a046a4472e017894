"""Reading text files with errors that name the file and the 1-based line.

The logged-run tables (``docs/log-format.md``) are comma-separated with an exact
header line; blank lines and ``#`` comments are skipped. :func:`columns` parses
a well-formed table with ``np.loadtxt`` (C speed) and falls back to a
line-by-line parser that names the offending line, column and value when
anything is off. Every failure is a :class:`lampsam.errors.DatasetError`.
"""

from __future__ import annotations

import io
import math
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import yaml

from lampsam.arrays import FloatArray
from lampsam.config_loader import parse_yaml
from lampsam.errors import DatasetError

FieldParser = Callable[[str, Path, int, str], Any]
"""Parses one field: ``(text, path, line, column) -> value`` or DatasetError."""


def read_yaml(path: Path) -> Any:
    """Parse a YAML file, or DatasetError naming it (one line: problem, line and column).

    A key given twice in one mapping is an error (:func:`lampsam.config_loader.parse_yaml`;
    PyYAML alone keeps the last value silently).
    """
    text = read_text(path)
    try:
        return parse_yaml(text)
    except yaml.YAMLError as exc:
        line = None
        mark = getattr(exc, "problem_mark", None)
        if mark is not None:
            line = int(mark.line) + 1
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        where = f" (column {int(mark.column) + 1})" if mark is not None else ""
        raise DatasetError(f"invalid YAML: {problem}{where}", path, line) from exc


#: The first bytes of a gzip stream (RFC 1952).
GZIP_MAGIC = b"\x1f\x8b"


def read_text(path: Path) -> str:
    """The whole text of a UTF-8 file, or DatasetError naming it.

    A UTF-8 byte-order mark is dropped (``utf-8-sig``: editors on Windows write one,
    and it would otherwise stick to the first field). A directory, an unreadable
    file, a gzip-compressed file and bytes that are not UTF-8 (a binary file, a
    Latin-1 export) each get their own message; the last names the line of the
    first bad byte.
    """
    path = Path(path)
    if path.is_dir():
        raise DatasetError("is a directory, expected a file", path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError as exc:
        raise DatasetError("file not found", path) from exc
    except PermissionError as exc:
        raise DatasetError("cannot read: permission denied", path) from exc
    except OSError as exc:
        raise DatasetError(f"cannot read: {exc.strerror or exc}", path) from exc
    if raw.startswith(GZIP_MAGIC):
        raise DatasetError("gzip-compressed: decompress it first (gunzip)", path)
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise DatasetError(f"not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start}: "
                           "a binary file, or text in another encoding?)", path, line) from exc


def open_text(path: Path) -> TextIO:
    """A UTF-8 text file as a stream with universal newlines, or DatasetError naming it.

    The file is decoded whole by :func:`read_text`, so a bad byte is reported before
    any line is parsed.
    """
    return io.StringIO(read_text(path), newline=None)


def data_lines(path: Path) -> Iterator[tuple[int, str]]:
    """``(line number, text)`` of each line of a text file (:func:`open_text`) that is
    not blank or a ``#`` comment; the text stripped of surrounding white space, the
    number 1-based."""
    with open_text(path) as fh:
        for lineno, raw in enumerate(fh, start=1):
            text = raw.strip()
            if text and not text.startswith("#"):
                yield lineno, text


def parse_float(text: str, path: Path, line: int, column: str) -> float:
    """A finite float, or DatasetError naming file, line and column."""
    try:
        value = float(text)
    except ValueError as exc:
        raise DatasetError(f"column {column!r}: not a number: {text!r}", path, line) from exc
    if not math.isfinite(value):
        raise DatasetError(f"column {column!r}: non-finite value {text!r}", path, line)
    return value


def parse_int(text: str, path: Path, line: int, column: str) -> int:
    """An integer, or DatasetError naming file, line and column."""
    try:
        return int(text)
    except ValueError as exc:
        raise DatasetError(f"column {column!r}: not an integer: {text!r}", path, line) from exc


def read_csv(
    path: Path,
    header: Sequence[str],
    parsers: Sequence[FieldParser],
    allow_empty: bool = False,
) -> tuple[list[list[Any]], list[int]]:
    """Read a comma-separated table with an exact header line.

    Blank lines and lines starting with ``#`` are skipped.

    Returns:
        The parsed rows and their 1-based line numbers.

    Raises:
        DatasetError: missing file, wrong header, wrong column count, bad value,
            or no data rows (unless ``allow_empty``).
    """
    rows: list[list[Any]] = []
    lines: list[int] = []
    header_seen = False
    for lineno, text in data_lines(path):
        fields = [f.strip() for f in text.split(",")]
        if not header_seen:
            if tuple(fields) != tuple(header):
                raise DatasetError(
                    f"expected header {','.join(header)!r}, got {text!r}", path, lineno
                )
            header_seen = True
            continue
        if len(fields) != len(header):
            raise DatasetError(
                f"malformed line: expected {len(header)} fields, got {len(fields)}",
                path,
                lineno,
            )
        rows.append(
            [p(f, path, lineno, c) for p, f, c in zip(parsers, fields, header, strict=True)]
        )
        lines.append(lineno)
    if not header_seen:
        raise DatasetError(f"empty file (expected header {','.join(header)!r})", path)
    if not rows and not allow_empty:
        raise DatasetError("no data lines (empty log)", path)
    return rows, lines


def check_time(
    t: FloatArray, lines: Sequence[int] | None, path: Path, strict: bool = True
) -> None:
    """DatasetError at the first time stamp that does not increase (or decreases if not strict).

    ``lines`` are the data lines' numbers; None re-scans ``path`` for them on error.
    """
    if len(t) < 2:
        return
    dt = np.diff(t)
    bad = np.flatnonzero(dt <= 0 if strict else dt < 0)
    if len(bad):
        k = int(bad[0]) + 1
        what = "does not increase" if strict else "goes backwards"
        line_nos = lines if lines is not None else data_line_numbers(path)
        raise DatasetError(f"time stamp {float(t[k])!r} {what} (previous {float(t[k - 1])!r})",
                           path, line_nos[k])


#: Fastest wheel or body speed a logged increment may imply, m/s (360 km/h). A faster
#: one is a corrupt field (an exponent typo, a unit in mm or ns), not motion: taken
#: as read it sends the EKF metres to kilometres away with exit code 0.
MAX_SPEED = 100.0

#: Largest coordinate a position may have, m (100,000 km: beyond any map frame,
#: including UTM's 10,000 km northing). Larger values overflow the covariance products.
MAX_COORDINATE = 1e8


def check_speed(t: FloatArray, travel: FloatArray, lines: Sequence[int] | None, path: Path,
                what: str) -> None:
    """DatasetError at the first sample whose travel implies more than :data:`MAX_SPEED`.

    Args:
        t: (K,) sample times, s, increasing. travel: (K,) or (K, n) distance of each
            sample since the previous one, m (per column: the largest counts). The first
            sample is measured against the second's interval (1 s when alone).
        lines: the data lines' numbers (None: re-scanned from ``path`` on error).
        what: the column(s) named in the message.
    """
    d = np.abs(np.asarray(travel, dtype=np.float64).reshape(len(t), -1)).max(axis=1)
    dt = np.diff(t, prepend=t[0] - (t[1] - t[0] if len(t) > 1 else 1.0))
    bad = np.flatnonzero(d > MAX_SPEED * np.maximum(dt, 1e-9))
    if len(bad):
        k = int(bad[0])
        line_nos = lines if lines is not None else data_line_numbers(path)
        raise DatasetError(f"{what}: {float(d[k])!r} m in {float(dt[k]):.6g} s is faster than "
                           f"{MAX_SPEED:g} m/s: a corrupt value, or not metres and seconds",
                           path, line_nos[k])


def check_coordinates(values: FloatArray, lines: Sequence[int] | None, path: Path,
                      what: str) -> None:
    """DatasetError at the first row with a coordinate beyond :data:`MAX_COORDINATE`."""
    v = np.abs(np.asarray(values, dtype=np.float64).reshape(len(values), -1)).max(axis=1)
    bad = np.flatnonzero(v > MAX_COORDINATE)
    if len(bad):
        k = int(bad[0])
        line_nos = lines if lines is not None else data_line_numbers(path)
        raise DatasetError(f"{what}: {float(v[k])!r} m is beyond {MAX_COORDINATE:g} m: a corrupt "
                           "value, or not metres", path, line_nos[k])


def str_field(text: str, path: Path, line: int, column: str) -> str:
    """A non-empty string field."""
    if not text:
        raise DatasetError(f"column {column!r}: empty", path, line)
    return text


def fast_columns(path: Path, header: Sequence[str], kinds: str) -> tuple[list[Any], None] | None:
    """Parse a well-formed table with ``np.loadtxt`` (C speed); None when anything is off.

    ``kinds`` has one letter per column: ``f`` finite float, ``n`` float allowing NaN,
    ``i`` integer, ``s`` non-empty string, ``b`` 0/1. On None the caller re-reads the
    file line by line with :func:`read_csv`, which names the offending line. Line
    numbers are not returned (see :func:`data_line_numbers`).
    """
    skip = 0
    try:
        with open(path, encoding="utf-8-sig") as fh:
            for raw in fh:
                skip += 1
                line = raw.strip()
                if line and not line.startswith("#"):
                    if line != ",".join(header):
                        return None
                    break
            else:
                return None
    except (OSError, UnicodeDecodeError):
        return None
    num_idx = [j for j, k in enumerate(kinds) if k != "s"]
    str_idx = [j for j, k in enumerate(kinds) if k == "s"]
    cols: list[Any] = [None] * len(kinds)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # "empty input file" and friends -> slow path
            if num_idx:
                a = np.loadtxt(path, delimiter=",", skiprows=skip, usecols=num_idx, ndmin=2,
                               dtype=np.float64, comments="#", encoding="utf-8")  # fmt: skip
            if str_idx:
                st = np.loadtxt(path, delimiter=",", skiprows=skip, usecols=str_idx, ndmin=2,
                                dtype=str, comments="#", encoding="utf-8")  # fmt: skip
    except (ValueError, UserWarning):
        return None
    rows = len(a) if num_idx else len(st)
    if rows == 0:
        return None
    for c, j in enumerate(num_idx):
        col = a[:, c]
        kind = kinds[j]
        if kind == "n":
            if np.any(np.isinf(col)):
                return None
            cols[j] = col.copy()
            continue
        if not np.all(np.isfinite(col)):
            return None
        if kind == "f":
            cols[j] = col.copy()
        elif kind == "i":
            if not np.all(col == np.round(col)) or np.any(np.abs(col) > 2**53):
                return None
            cols[j] = col.astype(np.int64)
        else:  # "b"
            if not np.all((col == 0) | (col == 1)):
                return None
            cols[j] = col == 1
    for c, j in enumerate(str_idx):
        strs = [x.strip() for x in st[:, c].tolist()]
        if not all(strs):
            return None
        cols[j] = strs
    if num_idx and str_idx and len(st) != len(a):
        return None
    return cols, None


def data_line_numbers(path: Path) -> list[int]:
    """1-based line numbers of a table's data lines (after the header; no blanks/comments)."""
    return [n for n, _ in data_lines(path)][1:]


def columns(
    path: Path,
    header: Sequence[str],
    kinds: str,
    parsers: Sequence[FieldParser],
    allow_empty: bool = False,
) -> tuple[list[Any], list[int] | None]:
    """Columns of a table: the fast path, else the line-by-line parser (precise errors)."""
    fast = fast_columns(path, header, kinds)
    if fast is not None:
        return fast
    rows, lines = read_csv(path, header, parsers, allow_empty)
    cols: list[Any] = []
    for j, kind in enumerate(kinds):
        col = [r[j] for r in rows]
        if kind in "fn":
            cols.append(np.array(col, dtype=np.float64))
        elif kind == "i":
            cols.append(np.array(col, dtype=np.int64))
        elif kind == "b":
            cols.append(np.array(col, dtype=bool))
        else:
            cols.append(col)
    return cols, lines

