"""Lazy public names for a package's ``__init__`` (PEP 562).

Importing ``lampsam`` or a subpackage must stay cheap: the entry points live in
modules that load GTSAM, Open3D or OpenCV, so each public name is resolved from its
module on first use only.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable


def lazy_exports(package: str, table: dict[str, str], eager: tuple[str, ...] = ()
                 ) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` for a package whose names live in submodules.

    Args:
        package: the package's ``__name__`` (for error messages).
        table: public name -> module that defines it (absolute, ``lampsam.x.y``).
        eager: names the package defines itself (listed by ``dir`` too).

    Returns:
        ``(__getattr__, __dir__)`` to assign at the package's top level.
    """

    def __getattr__(name: str) -> object:  # noqa: N807
        module = table.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(module), name)

    def __dir__() -> list[str]:  # noqa: N807
        return sorted([*table, *eager])

    return __getattr__, __dir__
