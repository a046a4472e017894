"""A hook for live views: the run loops report what they just did; by default nobody listens.

The SLAM, localization and stereo loops call :func:`emit` with an event name and
the finished objects of the step (no copies are made, nothing is computed for the
observer). A live view (``lampsam.evaluation.live``) installs a callback for the
duration of a run with :func:`observing`. With no observer installed, :func:`emit`
costs one context-variable lookup, so the loops keep their speed; the callback is
per context (thread / task), so parallel runs in one process do not mix.

Events and their fields (all optional to listen to):

- ``slam.step``: ``t`` (s), ``frame`` (the measurement frame or None),
  ``estimate`` (:class:`lampsam.backend.interface.StepEstimate`), ``backend``.
- ``slam.finish``: ``result`` (:class:`lampsam.backend.interface.SlamResult`).
- ``localize.start``: ``grid`` (the occupancy grid localized on).
- ``localize.candidates``: ``candidates`` (pose candidates after a turn).
- ``localize.particles``: ``particles`` (N, 3) world poses, ``log_weights`` (N,),
  ``update`` (count within the filter stage).
- ``localize.estimate``: ``pose`` (3,) the filter's estimate of an attempt, ``attempt``.
- ``stereo.step``: ``k`` (frame index), ``t`` (s), ``estimator``, ``step``
  (:class:`lampsam.backend.stereo.StereoStep`), ``time_s`` (wall time of the step).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Mapping
from contextvars import ContextVar
from typing import Any

Observer = Callable[[str, Mapping[str, Any]], None]
"""``observer(event, fields)``; it must not modify the objects it is given."""

_CURRENT: ContextVar[Observer | None] = ContextVar("lampsam_observer", default=None)


def emit(event: str, **fields: Any) -> None:
    """Report an event to the installed observer, if any (see the module docstring)."""
    observer = _CURRENT.get()
    if observer is not None:
        observer(event, fields)


def listening() -> bool:
    """True when an observer is installed (to skip work done only for it)."""
    return _CURRENT.get() is not None


@contextlib.contextmanager
def observing(observer: Observer | None) -> Iterator[None]:
    """Install ``observer`` for the block (None: keep whatever is installed)."""
    if observer is None:
        yield
        return
    token = _CURRENT.set(observer)
    try:
        yield
    finally:
        _CURRENT.reset(token)
