"""Every option of every configuration dataclass (``*Config`` in the package, and the
dataclasses they nest) is documented in its ``Attributes:`` section with its default, and
that default is the code's.

Forms read (one entry may document several fields: ``a, b: ...``):

- ``(default X)``, ``default X``, ``Default X.``, ``defaults X, Y, Z`` (one value per name of
  the entry, in order), ``default X-Y`` (two names), ``X (default)`` / ``X (default, ...)``;
- ``X`` is a number (``1e-4``, ``10**9``, ``inf``), ``None``, ``True`` / ``False``
  (``on`` / ``off``), a string (``"x"``, ``'x'``, ````"x"````), a tuple ``(1.0, 0.5)``
  or an enum member's name; a number followed by ``deg`` documents a field in radians.

A nested configuration (a field whose default is a dataclass) needs no default in the text.
"""

from __future__ import annotations

import ast
import dataclasses
import enum
import importlib
import inspect
import math
import pkgutil
import re
from pathlib import Path

import pytest

import lampsam
from lampsam.config_loader import _default_of  # the loader's own reading of a default

ROOT = Path(lampsam.__file__).resolve().parent

_NUM = (r"[-+]?(?:\d+/\d+|\d{1,3}(?:,\d{3})+(?!\d)|\d[\d_]*\.?\d*(?:e[-+]?\d+)?|\.\d+|inf)"
        r"(?:\s*\*\*\s*\d+)?")
_VALUE = (rf"``[^`]+``|\"[^\"]*\"|'[^']*'|\([^()]*\)|{_NUM}(?:\s*deg\b)?|None|True|False"
          r"|\boff\b|\bon\b|\b[A-Z][A-Z_]+\b")
_DEFAULT = re.compile(rf"\b[Dd]efault\b[:=]?\s*(?:is\s+|=\s*)?({_VALUE})")
_DEFAULTS = re.compile(rf"\b[Dd]efaults\b:?\s*((?:{_VALUE})(?:\s*(?:,|and)\s*(?:{_VALUE}))+)")
_RANGE = re.compile(rf"\b[Dd]efault\s+({_NUM})\s*-\s*({_NUM})\b")
_LIST = re.compile(rf"\b[Dd]efaults?\b:?\s*((?:{_VALUE})(?:\s*,\s*(?:{_VALUE}))+)")
_AFTER = re.compile(rf"({_VALUE})\s*\((?:[^()]*,\s*)?default\b")


def config_classes() -> list[type]:
    """The package's ``*Config`` dataclasses and the dataclasses their fields hold."""
    out = []
    for info in pkgutil.walk_packages([str(ROOT)], "lampsam."):
        if info.name.startswith(("lampsam.tests", "lampsam.scripts")) or info.name.endswith(
                "__main__"):
            continue
        m = importlib.import_module(info.name)
        out += [v for v in vars(m).values() if inspect.isclass(v) and dataclasses.is_dataclass(v)
                and v.__module__ == m.__name__ and v.__name__.endswith("Config")]
    stack, seen = list(out), set(out)  # and the dataclasses they nest (MotionNoise, ...)
    while stack:
        for f in dataclasses.fields(stack.pop()):
            nested = type(_default_of(f))
            if dataclasses.is_dataclass(nested) and nested not in seen:
                seen.add(nested)
                out.append(nested)
                stack.append(nested)
    return sorted(out, key=lambda c: (c.__module__, c.__name__))


def attribute_entries(doc: str) -> list[tuple[list[str], str]]:
    """``([names], text)`` of each entry of the ``Attributes:`` section."""
    lines = inspect.cleandoc(doc).splitlines()
    start = next((k for k, line in enumerate(lines) if line.strip() == "Attributes:"), None)
    if start is None:
        return []
    entries: list[tuple[list[str], str]] = []
    base = None
    for line in lines[start + 1:]:
        if not line.strip():
            continue
        indent = len(line) - len(line.lstrip())
        base = indent if base is None else base
        if indent < base:
            break
        head = re.match(r"^([\w, ]+?)(?: \([^)]*\))?:\s(.*)$", line.strip())
        if indent == base and head:
            entries.append(([n.strip() for n in head.group(1).split(",")], head.group(2)))
        elif entries:
            entries[-1] = (entries[-1][0], entries[-1][1] + " " + line.strip())
    return entries


def stated_defaults(names: list[str], text: str) -> dict[str, str]:
    """name -> the default its entry states (the token as written), for the names it can pair."""
    if len(names) > 1:
        m = _DEFAULTS.search(text)
        if m:
            vals = re.findall(_VALUE, m.group(1))
            if len(vals) == len(names):
                return dict(zip(names, vals, strict=True))
        m = _RANGE.search(text)
        if m and len(names) == 2:
            return dict(zip(names, (m.group(1), m.group(2)), strict=True))
    found = [m.group(1) for m in _DEFAULT.finditer(text)] or [
        m.group(1) for m in _AFTER.finditer(text)]
    if len(found) == len(names):
        return dict(zip(names, found, strict=True))
    if found and len(names) > 1 and len(set(found)) == 1:
        return dict.fromkeys(names, found[0])  # one default for all
    if len(names) == 1 and found:
        return {names[0]: found[0]}
    return {}


def parse(token: str) -> object:
    """The value a default token states (``(0.3 m, 10 deg)``: a tuple in SI units)."""
    t = token.strip()
    if t.startswith("``"):
        t = t[2:-2]
    if t.startswith("(") and t.endswith(")") and re.search(r"\d\s*(m|deg|s|px)\b", t):
        return tuple(parse(x) for x in t[1:-1].split(","))
    t = re.sub(r"^(.*\d)\s*(m|s|px)$", r"\1", t)
    if t.endswith("deg"):
        return math.radians(float(t.removesuffix("deg")))
    if re.fullmatch(r"\d{1,3}(,\d{3})+", t):
        return int(t.replace(",", ""))
    if re.fullmatch(r"\d+/\d+", t):
        num, den = t.split("/")
        return int(num) / int(den)
    if t in ("on", "off"):
        return t == "on"
    try:
        return ast.literal_eval(t) if "**" not in t else eval(t, {})  # noqa: S307
    except (ValueError, SyntaxError):
        return math.inf if t == "inf" else t


def same(stated: object, code: object) -> bool:
    if isinstance(code, enum.Enum):
        return stated in (code.name, code.value)
    if isinstance(code, bool) or code is None or isinstance(stated, bool) or stated is None:
        return stated is code or (stated is None and code in ((), ""))
    if isinstance(code, int | float) and isinstance(stated, int | float):
        return math.isclose(stated, code, rel_tol=1e-6, abs_tol=1e-12)
    if isinstance(code, tuple | list) and isinstance(stated, tuple | list):
        return len(code) == len(stated) and all(same(s, c) for s, c in zip(stated, code, strict=True))
    return stated == code


CLASSES = config_classes()


def test_the_scan_sees_the_configs() -> None:
    names = {c.__name__ for c in CLASSES}
    assert len(CLASSES) > 35 and {"AssociationConfig", "Isam2Config", "LogOddsConfig"} <= names


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
def test_every_option_documents_its_default(cls: type) -> None:
    """Each field has an ``Attributes:`` entry stating a default equal to the code's."""
    entries = attribute_entries(cls.__doc__ or "")
    stated: dict[str, str] = {}
    documented: set[str] = set()
    text_of: dict[str, str] = {}
    for names, text in entries:
        documented.update(names)
        text_of.update(dict.fromkeys(names, text))
        stated.update(stated_defaults(names, text))
    bad = []
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        code = _default_of(f)
        if f.name not in documented:
            bad.append(f"{f.name}: not in the docstring's Attributes (default {code!r})")
        elif dataclasses.is_dataclass(code) or code is dataclasses.MISSING:
            continue
        elif isinstance(code, tuple) and len(code) > 1 and (m := _LIST.search(text_of[f.name])):
            values = tuple(parse(v) for v in re.findall(_VALUE, m.group(1)))  # one entry: a tuple
            if not same(values, code):
                bad.append(f"{f.name}: docstring says default {m.group(1)}, code {code!r}")
        elif f.name not in stated:
            bad.append(f"{f.name}: no '(default X)' (code: {code!r})")
        elif not same(parse(stated[f.name]), code):
            bad.append(f"{f.name}: docstring says default {stated[f.name]}, code {code!r}")
    assert not bad, f"{cls.__module__}.{cls.__name__}:\n" + "\n".join(bad)


@pytest.mark.parametrize(("names", "text", "expected"), [
    (["a"], "gate, m (default 0.75).", {"a": "0.75"}),
    (["a", "b"], "clamp and window (defaults 0.05, 200).", {"a": "0.05", "b": "200"}),
    (["a", "b"], "range (default 0.5-5.0, see x).", {"a": "0.5", "b": "5.0"}),
    (["a", "b"], "distance (default 0.75) and count (default 4).", {"a": "0.75", "b": "4"}),
    (["a"], '``"isam2"`` (start from iSAM2, default) or ``"odometry"``.', {"a": '``"isam2"``'}),
    (["a"], "a bin, rad (default 10 deg).", {"a": "10 deg"}),
])
def test_parser_reads_the_forms(names: list[str], text: str, expected: dict[str, str]) -> None:
    assert stated_defaults(names, text) == expected
    assert parse("10 deg") == pytest.approx(math.radians(10))
    assert same(parse("(1.0, 0.5)"), (1.0, 0.5)) and not same(parse("-2.0"), -1.0)
