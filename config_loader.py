"""The one strict loader from TOML/YAML tables to the configuration dataclasses.

Every command that reads a settings file, and every reader of a YAML section
that maps onto a dataclass (the rig, ...), goes through :func:`from_mapping`:

- an unknown key is an error naming it (with a close match when there is one), an
  unknown table likewise; a key or table given twice in one file is an error (TOML
  says so; PyYAML would keep the last silently, :func:`parse_yaml` refuses it);
- a value of the wrong type is an error naming the key and the expected type:
  an ``int`` is accepted where a ``float`` is expected (and stored as a float),
  a ``bool`` is never accepted as a number, NaN never as a float, and ``inf``
  (``1e400`` in TOML) only where the field's :func:`limits` say ``finite=False``
  (a threshold where infinite means "never");
- nested tables build nested dataclasses; a partial table changes only the keys
  it gives (the rest keep the default, or the ``base`` object's values);
- ``X | None`` fields take ``None`` from YAML, or the string ``"none"`` (TOML
  has no null);
- ranges declared on a field with ``field(metadata=limits(gt=0.0))`` are
  checked, and a dataclass's own ``__post_init__`` checks report the key when
  they raise :class:`FieldValueError`.

Every message names the file and the dotted key, e.g.
``run.toml: isam2.keyframe_distance: must be >= 0, got -1.0``.

The key and number checks and their messages are :mod:`lampsam.strict_keys`'s,
shared with the readers that check a YAML mapping by hand (world files, RGB-D camera
files). This module sits beside :mod:`lampsam.errors` at the package root so that
every stage (datasets to cli) may import it.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import re
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import tomllib
import yaml

from lampsam.errors import InputError
from lampsam.strict_keys import MISSING as MISSING_KEY
from lampsam.strict_keys import check_keys, check_number, finite_array, join_key, kind

T = TypeVar("T")

LIMITS_KEY = "lampsam_limits"  #: field-metadata key holding a :class:`Limits`


class ConfigError(InputError):
    """A settings file or section is malformed; names the file and the dotted key.

    Args:
        key: dotted path of the offending key (``""`` for the whole table).
        problem: what is wrong with it.
        source: the file (or a description of where the mapping came from).
    """

    def __init__(self, key: str, problem: str, source: str | Path | None = None):
        self.key = key
        self.problem = problem
        super().__init__(f"{key}: {problem}" if key else problem, source)


class FieldValueError(ValueError):
    """Raised by a config dataclass's own check; the loader prefixes the table path.

    Args:
        key: the field's name (or a dotted path below it).
        problem: what is wrong.
    """

    def __init__(self, key: str, problem: str):
        self.key = key
        self.problem = problem
        super().__init__(f"{key}: {problem}")


@dataclass(frozen=True)
class Limits:
    """Closed (``ge``, ``le``) and open (``gt``, ``lt``) bounds of a numeric field.

    A tuple field is checked element by element; ``None`` values are not checked.
    ``finite``: infinite values are refused (the default; the loader applies it to
    every number field, with or without declared limits).
    """

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    finite: bool = True

    def problem(self, value: object) -> str | None:
        """Why ``value`` is out of range, or None when it is inside (or not a number)."""
        if isinstance(value, tuple | list):
            for i, v in enumerate(value):
                bad = self.problem(v)
                if bad is not None:
                    return f"element {i}: {bad}"
            return None
        if isinstance(value, bool) or not isinstance(value, int | float):
            return None
        v = float(value)
        if math.isnan(v):
            return "must be a number, got nan"
        if self.finite and math.isinf(v):
            return f"must be finite, got {plain(value)}"
        for bound, ok, word in (
            (self.ge, lambda b: v >= b, ">="),
            (self.gt, lambda b: v > b, ">"),
            (self.le, lambda b: v <= b, "<="),
            (self.lt, lambda b: v < b, "<"),
        ):
            if bound is not None and not ok(bound):
                return f"must be {word} {plain(bound)}, got {plain(value)}"
        return None


def limits(
    *, ge: float | None = None, gt: float | None = None, le: float | None = None,
    lt: float | None = None, finite: bool = True,
) -> dict[str, Limits]:
    """Field metadata declaring a range: ``x: float = field(default=1.0, metadata=limits(gt=0))``;
    ``finite=False`` lets the field take ``inf``."""
    return {LIMITS_KEY: Limits(ge=ge, gt=gt, le=le, lt=lt, finite=finite)}


#: What a number field without declared limits is held to: finite, any sign.
FINITE = Limits()


def check_limits(obj: object) -> None:
    """Check every field of a dataclass instance against its declared :func:`limits`.

    Call it from ``__post_init__`` so that objects built in Python are checked too.

    Raises:
        FieldValueError: the first field out of range (named).
    """
    for f in dataclasses.fields(obj):  # type: ignore[arg-type]
        lim = f.metadata.get(LIMITS_KEY)
        if lim is not None:
            bad = lim.problem(getattr(obj, f.name))
            if bad is not None:
                raise FieldValueError(f.name, bad)


def plain(value: object) -> str:
    """A number as a user reads it (``5.0``, not ``np.float64(5.0)``); other values by repr."""
    if isinstance(value, bool | np.bool_):
        return str(bool(value))
    if isinstance(value, np.integer):
        return str(int(value))
    if isinstance(value, np.floating):
        return repr(float(value))
    if isinstance(value, int | float):
        return repr(value)
    return repr(value)


# --------------------------------------------------------------------------- files
class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping."""


def _unique_mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode,
                    deep: bool = False) -> dict[object, object]:
    """Build a mapping like the safe loader, but a repeated key is a ConstructorError
    at the second key's line (YAML 1.2 says keys are unique; PyYAML keeps the last)."""
    first: dict[object, int] = {}
    for key_node, _ in node.value:
        if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
            continue  # complex keys and merges (``<<``): the safe loader's own rules
        key = loader.construct_object(key_node, deep=deep)
        if key in first:
            raise yaml.constructor.ConstructorError(
                None, None, f"key {key!r} given twice (first on line {first[key]})",
                key_node.start_mark)
        first.setdefault(key, key_node.start_mark.line + 1)
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _unique_mapping)


def parse_yaml(text: str) -> Any:
    """``yaml.safe_load`` with one more rule: a key given twice in a mapping is an error.

    Raises:
        yaml.YAMLError: as ``yaml.safe_load`` (a ``ConstructorError`` naming the
            repeated key, with the line in ``problem_mark``).
    """
    return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader subclass)


def _toml_problem(exc: tomllib.TOMLDecodeError, text: str) -> str:
    """tomllib's message with the offending line's text (tomllib names only its number),
    and the likely cause when a key or table is given twice."""
    msg = str(exc)
    found = re.search(r" ?\(at line (\d+), column (\d+)\)", msg)
    if found is None:
        return f"invalid TOML: {msg}"
    lineno = int(found.group(1))
    lines = text.splitlines()
    shown = lines[lineno - 1].strip() if 0 < lineno <= len(lines) else ""
    problem = msg[: found.start()] + msg[found.end():]
    hint = (": a key or table given twice"
            if "overwrite" in msg.lower() or "twice" in msg.lower() else "")
    return (f"invalid TOML, line {lineno} ({shown!r}, column {found.group(2)}): "
            f"{problem}{hint}")


def read_table_file(path: str | Path) -> dict[str, Any]:
    """Parse a settings file: TOML (``.toml``) or YAML (``.yaml``/``.yml``).

    Returns:
        The top-level table (empty for an empty YAML file).

    Raises:
        ConfigError: missing or unreadable file, a parse error (with the parser's
            line), or a top level that is not a table.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError as exc:
        raise ConfigError("", "config file not found", path) from exc
    except IsADirectoryError as exc:
        raise ConfigError("", "is a directory, not a config file", path) from exc
    except OSError as exc:
        raise ConfigError("", f"cannot read: {exc.strerror or exc}", path) from exc
    try:
        text = raw.decode("utf-8-sig")  # a byte-order mark (Windows editors) is dropped
    except UnicodeDecodeError as exc:
        raise ConfigError("", f"not UTF-8 text (byte {exc.start})", path) from exc
    doc: object
    if path.suffix.lower() in (".yaml", ".yml"):
        try:
            doc = parse_yaml(text)
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" (line {mark.line + 1})" if mark is not None else ""
            problem = getattr(exc, "problem", None) or str(exc)
            raise ConfigError("", f"invalid YAML{where}: {problem}", path) from exc
        if doc is None:
            doc = {}
    else:
        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError("", _toml_problem(exc, text), path) from exc
    if not isinstance(doc, dict):
        raise ConfigError("", f"the top level must be a table, got {kind(doc)}", path)
    return doc


def load_config(
    cls: type[T], path: str | Path | None, table: str | None = None, base: T | None = None,
) -> T:
    """Build ``cls`` from a settings file (or its defaults when ``path`` is None).

    Args:
        cls: the configuration dataclass.
        path: the TOML/YAML file, or None.
        table: the top-level table that holds ``cls``'s keys (e.g. ``"envmap"``),
            or None when the whole file is ``cls`` (e.g. :class:`SlamConfig`). Any
            other top-level key is an error: a misspelt table is never ignored.
        base: start from this object instead of ``cls()``'s defaults.

    Raises:
        ConfigError: naming the file and the dotted key.
    """
    if path is None:
        return base if base is not None else cls()
    doc = read_table_file(path)
    if table is not None:
        extra = [k for k in doc if k != table]
        if extra:
            raise ConfigError(str(extra[0]), f"unknown table (this command reads [{table}])", path)
        doc = doc.get(table, {})
    return from_mapping(cls, doc, source=path, key=table or "", base=base)


# --------------------------------------------------------------------------- conversion
def from_mapping(
    cls: type[T], data: object, *, source: str | Path | None = None, key: str = "",
    base: T | None = None,
) -> T:
    """Build the dataclass ``cls`` from a parsed table, strictly (rules in the module doc).

    Args:
        cls: a dataclass type.
        data: the table (a mapping of ``str`` keys).
        source: the file it came from, for messages.
        key: the dotted path of ``data`` inside that file (``""`` at the top).
        base: values for the keys ``data`` does not give (default: ``cls``'s defaults).

    Raises:
        ConfigError: unknown key, wrong type, missing required key, out of range.
    """
    return _Converter(source).build(cls, data, key, base)


def _type_name(tp: object) -> str:
    """A type annotation as a user reads it."""
    if tp is float:
        return "a number"
    if tp is int:
        return "an integer"
    if tp is bool:
        return "true or false"
    if tp is str:
        return "a string"
    if isinstance(tp, type):
        if dataclasses.is_dataclass(tp):
            return "a table"
        if issubclass(tp, enum.Enum):
            return "one of " + ", ".join(repr(m.value) for m in tp)
        return tp.__name__
    return str(tp).replace("typing.", "")


_HINTS: dict[type, dict[str, Any]] = {}


def _hints(cls: type) -> dict[str, Any]:
    """Resolved field annotations of a dataclass (its module's names), cached per class."""
    hints = _HINTS.get(cls)
    if hints is None:
        hints = _HINTS[cls] = typing.get_type_hints(cls)
    return hints


def _default_of(f: dataclasses.Field[Any]) -> object:
    """A field's default value (calling its factory), or MISSING."""
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


class _Converter:
    """Conversion of one file's tables; carries the source for messages."""

    def __init__(self, source: str | Path | None):
        self.source = source

    def fail(self, key: str, problem: str) -> ConfigError:
        return ConfigError(key, problem, self.source)

    # ----------------------------------------------------------------- dataclasses
    def build(self, cls: type[T], data: object, path: str, base: T | None) -> T:
        fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
        data = check_keys(data, path, fields, fail=self.fail)
        hints = _hints(cls)
        kwargs: dict[str, object] = {}
        for name, value in data.items():
            f = fields[name]
            key = join_key(path, name)
            current = getattr(base, name) if base is not None else _default_of(f)
            converted = self.convert(hints[name], value, key, current)
            bad = f.metadata.get(LIMITS_KEY, FINITE).problem(converted)
            if bad is not None:
                raise self.fail(key, bad)
            kwargs[name] = converted
        if base is None:
            missing = [n for n, f in fields.items() if n not in kwargs
                       and _default_of(f) is dataclasses.MISSING]
            if missing:
                raise self.fail(join_key(path, missing[0]), MISSING_KEY)
        try:
            if base is not None:
                return dataclasses.replace(base, **kwargs)  # type: ignore[type-var]
            return cls(**kwargs)
        except FieldValueError as exc:
            raise self.fail(join_key(path, exc.key), exc.problem) from exc
        except (ValueError, TypeError) as exc:
            raise self.fail(path, str(exc)) from exc

    # ----------------------------------------------------------------- one value
    def convert(self, tp: Any, value: object, key: str, current: object) -> Any:
        """Check and convert one value to the annotation ``tp``."""
        if tp is Any or tp is object:
            return value
        origin = typing.get_origin(tp)
        args = typing.get_args(tp)
        if origin is typing.Union or origin is types.UnionType:
            return self._union(args, value, key, current)
        if origin is typing.Literal:
            for option in args:
                if type(option) is type(value) and option == value:
                    return value
            raise self.fail(key, f"must be one of {', '.join(repr(a) for a in args)}, got {value!r}")
        if isinstance(tp, type) and dataclasses.is_dataclass(tp):
            base = current if isinstance(current, tp) else None
            return self.build(tp, value, key, base)
        if isinstance(tp, type) and issubclass(tp, enum.Enum):
            if isinstance(value, tp):
                return value
            for member in tp:
                if type(member.value) is type(value) and member.value == value:
                    return member
            raise self.fail(key, f"must be {_type_name(tp)}, got {value!r}")
        if tp is bool:
            if isinstance(value, bool):
                return value
            raise self.fail(key, f"must be true or false, got {kind(value)} ({value!r})")
        if tp is int:
            return check_number(value, key, fail=self.fail, integer=True)
        if tp is float:  # infinite where the field's limits allow it
            return float(check_number(value, key, fail=self.fail, finite=False))
        if tp is str:
            if isinstance(value, str):
                return value
            raise self.fail(key, f"must be a string, got {kind(value)} ({value!r})")
        if tp is Path or (isinstance(tp, type) and issubclass(tp, Path)):
            if isinstance(value, str | Path):
                return Path(value)
            raise self.fail(key, f"must be a path string, got {kind(value)}")
        if origin in (tuple, list) or tp in (tuple, list):
            return self._sequence(tp, origin or tp, args, value, key)
        if origin in (dict, Mapping) or tp is dict:
            return self._mapping(args, value, key)
        if origin is np.ndarray or tp is np.ndarray:
            return finite_array(value, None, key, fail=self.fail)
        if isinstance(tp, type) and isinstance(value, tp):
            return value
        raise self.fail(key, f"must be {_type_name(tp)}, got {kind(value)}")

    def _union(self, args: tuple[Any, ...], value: object, key: str, current: object) -> Any:
        options = [a for a in args if a is not type(None)]
        if len(options) < len(args):  # optional
            if value is None:
                return None
            if isinstance(value, str) and value.lower() == "none" and str not in options:
                return None
        if len(options) == 1:
            return self.convert(options[0], value, key, current)
        problems = []
        for option in options:
            try:
                return self.convert(option, value, key, current)
            except ConfigError as exc:
                problems.append(exc.problem)
        raise self.fail(key, " or ".join(problems))

    def _sequence(self, tp: Any, origin: Any, args: tuple[Any, ...], value: object,
                  key: str) -> Any:
        if isinstance(value, str | bytes) or not isinstance(value, list | tuple):
            raise self.fail(key, f"must be an array, got {kind(value)} ({value!r})")
        if origin is tuple and args and not (len(args) == 2 and args[1] is Ellipsis):
            if len(value) != len(args):
                raise self.fail(key, f"must have {len(args)} elements, got {len(value)}")
            return tuple(self.convert(a, v, join_key(key, i), None)
                         for i, (a, v) in enumerate(zip(args, value, strict=True)))
        item = args[0] if args else Any
        items = [self.convert(item, v, join_key(key, i), None) for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items

    def _mapping(self, args: tuple[Any, ...], value: object, key: str) -> dict[str, Any]:
        if not isinstance(value, Mapping):
            raise self.fail(key, f"must be a table, got {kind(value)}")
        vt = args[1] if len(args) == 2 else Any
        return {str(k): self.convert(vt, v, join_key(key, str(k)), None) for k, v in value.items()}
