"""Strict checks of one YAML/TOML mapping's keys and values, with one set of messages.

The dataclass loader (:func:`lampsam.config_loader.from_mapping`) and the readers that
check a mapping by hand (a world file's sections, :mod:`lampsam.datasets.world`, and
its ``scene3d``, :mod:`lampsam.datasets.scene3d`; an RGB-D camera's ``kinect.yaml``,
:mod:`lampsam.datasets.rgbd`) use these checks, so the same mistake reads the same
everywhere::

    world.yaml: ceiling.lamps[0].brightnes: unknown key (did you mean 'brightness'?)
    world.yaml: ceiling.lamps[0].height: missing (required)
    kinect.yaml: fx: must be a number, got a string ('fifty')
    kinect.yaml: fy: must be a number, got nan
    world.yaml: render.texel: must be finite, got inf
    kinect.yaml: body_R_camera: must be 3x3 finite numbers, got [1, 0, 0]

Each check names the dotted key and raises what the caller's ``fail(key, problem)``
returns: the caller adds its file and picks its stage's exception
(:class:`lampsam.config_loader.ConfigError`, :class:`lampsam.errors.DatasetError`).

A number is an ``int`` or a ``float`` (a ``bool`` never is; nor is a string, even one
that reads as a number: PyYAML reads ``5e-3``, without a dot, as a string); NaN is never
one. Like :mod:`lampsam.errors`, this module sits at the package root and imports no
stage, so every stage may use it.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Collection, Mapping
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray

Fail = Callable[[str, str], Exception]
"""``fail(key, problem)``: the exception to raise for ``key`` (dotted path) and the
problem (the caller adds the file)."""

MISSING = "missing (required)"
"""The problem of a required key that is absent."""


def join_key(path: str, name: str | int) -> str:
    """``path.name`` (``name`` at the top, ``path[name]`` for a list index)."""
    if isinstance(name, int):
        return f"{path}[{name}]"
    return f"{path}.{name}" if path else name


def kind(value: object) -> str:
    """A value's type as a TOML/YAML user says it (``a string``, ``a table``, ...)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int):
        return "an integer"
    if isinstance(value, float):
        return "a float"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, Mapping):
        return "a table"
    if isinstance(value, list | tuple):
        return "an array"
    return type(value).__name__


def unknown_key_problem(name: str, known: Collection[str], value: object) -> str:
    """``unknown key (did you mean 'x'?)`` (the closest known key), or the known keys
    when none is close; ``unknown table`` when ``value`` is a mapping."""
    close = difflib.get_close_matches(name, list(known), n=1)
    hint = f"did you mean {close[0]!r}?" if close else f"known keys: {', '.join(sorted(known))}"
    what = "table" if isinstance(value, Mapping) else "key"
    return f"unknown {what} ({hint})"


def check_keys(data: object, where: str, allowed: Collection[str],
               required: Collection[str] = (), *, fail: Fail) -> Mapping[str, Any]:
    """``data`` itself when it is a mapping of string keys, each of them ``allowed``, with
    every ``required`` key.

    Raises:
        what ``fail`` returns: not a mapping (``where``), a key that is not a string or
            not allowed (the key, with the closest allowed one), a required key absent.
    """
    if not isinstance(data, Mapping):
        raise fail(where, f"must be a table, got {kind(data)}")
    for name in data:
        if not isinstance(name, str):
            raise fail(join_key(where, str(name)), "keys must be strings")
        if name not in allowed:
            raise fail(join_key(where, name), unknown_key_problem(name, allowed, data[name]))
    for name in sorted(required):
        if name not in data:
            raise fail(join_key(where, name), MISSING)
    return data


def check_number(value: object, key: str, *, fail: Fail, integer: bool = False,
                 finite: bool = True) -> int | float:
    """``value`` when it is a number (an ``int`` with ``integer``), never NaN, and finite
    unless ``finite=False`` (a threshold where infinite means "never").

    Raises:
        what ``fail`` returns, for ``key``: the wrong type (with the value), NaN, or an
            infinity where ``finite``.
    """
    if isinstance(value, bool) or not isinstance(value, int if integer else int | float):
        raise fail(key, f"must be {'an integer' if integer else 'a number'}, "
                        f"got {kind(value)} ({value!r})")
    if math.isnan(value):
        raise fail(key, "must be a number, got nan")
    if finite and math.isinf(value):
        raise fail(key, f"must be finite, got {value!r}")
    return value


def number(data: Mapping[str, Any], key: str, where: str, *, fail: Fail,
           default: float | None = None, integer: bool = False, positive: bool = False,
           nonneg: bool = False) -> float:
    """``data[key]`` as a finite float (its integer value with ``integer``), ``default``
    when the key is absent; optionally ``> 0`` (``positive``) or ``>= 0`` (``nonneg``).

    Raises:
        what ``fail`` returns, for ``where.key``: absent without a default
            (:data:`MISSING`), not a number, NaN, infinite, or out of range.
    """
    name = join_key(where, key)
    if key not in data:
        if default is None:
            raise fail(name, MISSING)
        return float(default)
    value = check_number(data[key], name, fail=fail, integer=integer)
    if positive and value <= 0:
        raise fail(name, f"must be > 0, got {value!r}")
    if nonneg and value < 0:
        raise fail(name, f"must be >= 0, got {value!r}")
    return float(value)


def array(data: Mapping[str, Any], key: str, shape: tuple[int, ...], where: str, *,
          fail: Fail) -> FloatArray:
    """``data[key]`` as a finite float array of ``shape`` (:func:`finite_array`).

    Raises:
        what ``fail`` returns, for ``where.key``: absent (:data:`MISSING`), or not
            ``shape`` finite numbers.
    """
    name = join_key(where, key)
    if key not in data:
        raise fail(name, MISSING)
    return finite_array(data[key], shape, name, fail=fail)


def finite_array(value: object, shape: tuple[int, ...] | None, key: str, *,
                 fail: Fail) -> FloatArray:
    """``value`` (nested lists of numbers, NumPy scalars among them, or a numeric array)
    as a float array of ``shape``, or of any shape with at least one axis when ``shape``
    is None (a config field annotated ``np.ndarray``, whose shape its owner checks).

    Raises:
        what ``fail`` returns, for ``key``: ``must be 3x3 finite numbers, got ...``
            (``must be an array of finite numbers, got ...`` without a shape) for a
            value of another shape, a ragged one, one that is not all numbers (a
            ``bool`` never is; nor a string, nor an array of them), or one not all
            finite.
    """

    def numbers(v: object) -> bool:
        if isinstance(v, np.ndarray):
            return v.dtype.kind in "iuf"
        if isinstance(v, list | tuple):
            return all(numbers(x) for x in v)
        return isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool)

    arr: FloatArray | None = None
    if numbers(value):
        try:
            arr = np.array(value, dtype=np.float64)  # a copy: the caller's array stays its own
        except ValueError:  # ragged
            pass
    if (arr is None or not (arr.shape == shape if shape is not None else arr.ndim >= 1)
            or not np.all(np.isfinite(arr))):
        want = "an array of" if shape is None else "x".join(map(str, shape))
        raise fail(key, f"must be {want} finite numbers, got {value!r}")
    return arr
