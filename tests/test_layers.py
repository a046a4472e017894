"""The package's one-way data flow, checked on the source with :mod:`ast`.

``datasets -> frontend -> factors -> backend -> localization -> evaluation -> commands/cli``:
a module may import its own stage or an earlier one, never a later one; the shared
top-level modules (``errors``, ``angles``, ``safe_io``, ...) import no stage; nothing but
``cli``/``__main__`` imports ``cli`` or ``commands``. Every import counts: module level,
inside functions, and under ``TYPE_CHECKING``; so do the absolute module names of the
subpackages' lazy-export tables (``lazy_exports``). The checker itself is tested on a
planted reverse import in a temporary tree.

Only ``evaluation`` plots: no other module of the package, and no script, imports
matplotlib (a script computes its results and hands them to a plot function of
``lampsam.evaluation``); tests may.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parents[1]
STAGES = ("datasets", "frontend", "factors", "backend", "localization", "evaluation", "commands")
CLI_LAYER = len(STAGES) - 1
SKIP_DIRS = {"tests", "scripts", "docs", "out", ".venv", "__pycache__"}


def _module_name(root: Path, path: Path) -> str:
    """``lampsam.backend.ekf`` for ``root/backend/ekf.py``; the package for an ``__init__``."""
    parts = ["lampsam", *path.relative_to(root).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _layer(module: str) -> int | None:
    """The stage index of a ``lampsam`` module (``cli``/``__main__``: the CLI's), -1 for a
    shared top-level module, None for the package itself or a module outside lampsam."""
    parts = module.split(".")
    if parts[0] != "lampsam" or len(parts) == 1:
        return None
    if parts[1] in STAGES:
        return STAGES.index(parts[1])
    if parts[1] in ("cli", "__main__"):
        return CLI_LAYER
    return -1


def _imports(tree: ast.Module, module: str, is_package: bool) -> Iterator[tuple[str, int]]:
    """Every ``lampsam`` module a parsed source imports, with its line."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against this module's package
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[: len(base) - node.level + 1]
                target = ".".join([*base, *([node.module] if node.module else [])])
            else:
                target = node.module or ""
            yield target, node.lineno
            for alias in node.names:  # ``from lampsam import cli`` / ``from lampsam.x import y``
                yield f"{target}.{alias.name}", node.lineno
        elif (is_package and isinstance(node, ast.Constant) and isinstance(node.value, str)
              and node.value.startswith("lampsam.") and " " not in node.value):
            yield node.value, node.lineno  # a lazy-export table's target module


def layer_violations(root: Path) -> list[str]:
    """``file:line: importer -> imported (why)``, one per import against the data flow."""
    found: dict[tuple[str, int], str] = {}
    for path in sorted(root.rglob("*.py")):
        if SKIP_DIRS & set(path.relative_to(root).parts):
            continue
        me = _module_name(root, path)
        mine = _layer(me)
        if mine is None:  # lampsam/__init__.py: lazy public names of every stage
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for target, line in _imports(tree, me, path.name == "__init__.py"):
            theirs = _layer(target)
            if theirs is None or theirs == -1 or target == me:
                continue
            why = None
            if mine == -1:
                why = "a shared top-level module imports a stage"
            elif theirs > mine:
                why = f"{STAGES[mine]} imports the later stage {STAGES[theirs]}"
            elif theirs == CLI_LAYER and not me.startswith(("lampsam.cli", "lampsam.__main__",
                                                            "lampsam.commands")):
                why = "only the CLI imports cli/commands"
            rel = str(path.relative_to(root))
            if why and (rel, line) not in found:
                found[rel, line] = f"{rel}:{line}: {me} -> {target} ({why})"
    return [found[key] for key in sorted(found)]


def plotting_outside_evaluation(root: Path) -> list[str]:
    """``file:line`` of every matplotlib import outside ``evaluation/`` (scripts included,
    tests not)."""
    found = []
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root).parts
        if {"tests", ".venv", "__pycache__", "out"} & set(parts) or parts[0] == "evaluation":
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            if any(n.split(".")[0] == "matplotlib" for n in names):
                found.append(f"{path.relative_to(root)}:{node.lineno}")
    return found


def test_only_evaluation_plots(tmp_path: Path) -> None:
    assert plotting_outside_evaluation(PACKAGE_ROOT) == []
    root = _plant(tmp_path, {
        "evaluation/plots.py": "import matplotlib.pyplot as plt\n",
        "tests/test_plots.py": "import matplotlib\n",
        "scripts/bench/b.py": "def f():\n    from matplotlib import pyplot\n",
        "backend/x.py": "import numpy, matplotlib\n",
    })
    assert plotting_outside_evaluation(root) == ["backend/x.py:1", "scripts/bench/b.py:2"]


def test_package_respects_the_data_flow() -> None:
    assert layer_violations(PACKAGE_ROOT) == []


def test_every_stage_is_checked() -> None:
    """The checker sees the real tree: each stage has modules, and imports are found."""
    for stage in STAGES:
        assert list((PACKAGE_ROOT / stage).glob("*.py")), stage
    tree = ast.parse((PACKAGE_ROOT / "cli.py").read_text(encoding="utf-8"))
    targets = {t for t, _ in _imports(tree, "lampsam.cli", False)}
    assert "lampsam.commands.slam" in targets


def _plant(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    return root


def test_planted_reverse_imports_are_caught(tmp_path: Path) -> None:
    root = _plant(tmp_path, {
        "__init__.py": "",
        "errors.py": "import lampsam.backend.ekf\n",  # shared module -> stage
        "datasets/__init__.py": "",
        "datasets/simulator.py": ("def f():\n"
                                  "    from lampsam.backend.slam import run_slam\n"),  # lazy
        "frontend/__init__.py": "",
        "frontend/lamps.py": ("from typing import TYPE_CHECKING\n"
                              "if TYPE_CHECKING:\n"
                              "    from lampsam.localization import grid\n"),
        "backend/__init__.py": "TABLE = {'x': 'lampsam.evaluation.metrics'}\n",
        "backend/ekf.py": "from ..evaluation import metrics\nfrom lampsam import cli\n",
        "backend/ok.py": "from lampsam.datasets import world\nfrom . import ekf\n",
        "evaluation/__init__.py": "",
        "evaluation/report.py": "from lampsam.commands._args import positive\n",
        "commands/__init__.py": "",
        "commands/run.py": "from lampsam.evaluation import report\nimport lampsam.errors\n",
        "cli.py": "from lampsam.commands import run\n",
    })
    found = layer_violations(root)
    assert [f.split(":")[0] for f in found] == [
        "backend/__init__.py", "backend/ekf.py", "backend/ekf.py",
        "datasets/simulator.py", "errors.py", "evaluation/report.py", "frontend/lamps.py",
    ], found
    assert "backend/ekf.py:1: lampsam.backend.ekf -> lampsam.evaluation" in found[1]
    assert "datasets imports the later stage backend" in found[3]
    assert "evaluation imports the later stage commands" in found[5]


def test_a_clean_tree_passes(tmp_path: Path) -> None:
    root = _plant(tmp_path, {
        "datasets/world.py": "import numpy\nfrom lampsam.errors import LampsamError\n",
        "backend/slam.py": "from lampsam.datasets import world\nfrom lampsam.frontend import x\n",
        "commands/slam.py": "from lampsam.backend import slam\n",
        "cli.py": "from lampsam.commands import slam\n",
    })
    assert layer_violations(root) == []
