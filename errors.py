"""One exception base for the whole package, subclassed per stage.

Every error that reaches a user names what was wrong and where (file and line
for input files). Catch :class:`LampsamError` to handle all of them.
"""

from __future__ import annotations

from pathlib import Path


class LampsamError(Exception):
    """Base class of every error lampsam raises on purpose."""


class InputError(LampsamError):
    """Bad input: a missing file, a malformed line, NaN, time going backwards.

    Args:
        message: what is wrong.
        path: the offending file, if any.
        line: 1-based line number in ``path``, if any.
    """

    def __init__(self, message: str, path: str | Path | None = None, line: int | None = None):
        self.path = Path(path) if path is not None else None
        self.line = line
        where = ""
        if path is not None:
            where = f"{path}"
            if line is not None:
                where += f":{line}"
            where += ": "
        super().__init__(where + message)


class DatasetError(InputError):
    """A logged run or public dataset could not be read."""


class FrontendError(LampsamError):
    """An image or depth frame cannot be processed (wrong size, type, ...)."""


class EstimationError(LampsamError):
    """An estimator failed (indeterminate system, divergence, no usable data)."""


class LocalizationError(LampsamError):
    """Map building or global localization failed."""
