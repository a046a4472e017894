"""Stop requests (SIGINT and SIGTERM, handled alike) that never lose finished work.

Ctrl-C sends SIGINT; ``timeout``, batch schedulers, systemd and ``docker stop``
send SIGTERM. Inside :func:`stop_on_signals` the first of either only *requests*
a stop: the run loops check it between steps (:func:`interruptible`, or
:func:`raise_if_stopped`), so the current step finishes, everything finished is
written with status ``"interrupted"`` and the command exits with
:data:`EXIT_INTERRUPTED`. A second signal raises :class:`KeyboardInterrupt` at
once (the caller still writes what it has).

Exit codes of the ``lampsam`` command (also in ``docs/failures.md``):
:data:`EXIT_OK` 0, :data:`EXIT_FAILED` 1 (the job ran but failed, e.g. the final
optimisation failed and the online estimate was written), :data:`EXIT_USAGE` 2
(bad input or usage, nothing computed), :data:`EXIT_INTERRUPTED` 3 (stopped by a
signal; finished work written with status ``"interrupted"``).
"""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 3

_SIGNALS = (signal.SIGINT, signal.SIGTERM)
_received: list[str] = []  # names of the signals received since the handlers went in


def stop_requested() -> str | None:
    """The name of the first stop signal received (``"SIGTERM"``...), or None."""
    return _received[0] if _received else None


def request_stop(name: str = "stop request") -> None:
    """Request a stop as a signal would (for callers that run without signals, and tests)."""
    _received.append(name)


def clear_stop() -> None:
    """Forget received stop requests."""
    _received.clear()


def raise_if_stopped() -> None:
    """Raise :class:`KeyboardInterrupt` when a stop was requested (call between steps)."""
    name = stop_requested()
    if name is not None:
        raise KeyboardInterrupt(f"stopped by {name}")


def interruptible(items: Iterable[T]) -> Iterator[T]:
    """Yield ``items``, checking for a stop request before each one.

    The consumer's loop (e.g. a SLAM run's steps) then stops between two items
    with a :class:`KeyboardInterrupt` raised by the iterator itself, never in the
    middle of processing one.
    """
    it = iter(items)
    while True:
        raise_if_stopped()
        try:
            item = next(it)
        except StopIteration:
            return
        yield item


def _graceful_handler(signum: int, frame: FrameType | None) -> None:
    name = signal.Signals(signum).name
    first = not _received
    _received.append(name)
    if first:
        log.warning("%s received: finishing the current step, then writing what is finished "
                    "(send it again to stop at once)", name)
        return
    raise KeyboardInterrupt(f"stopped by {name} (second signal)")


def _immediate_handler(signum: int, frame: FrameType | None) -> None:
    name = signal.Signals(signum).name
    _received.append(name)
    raise KeyboardInterrupt(f"stopped by {name}")


@contextmanager
def stop_on_signals(graceful: bool = True) -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM are handled alike.

    Args:
        graceful: True for code that checks :func:`stop_requested` between steps:
            the first signal only requests a stop, a second raises
            :class:`KeyboardInterrupt`. False: the first signal raises
            :class:`KeyboardInterrupt` at once (SIGTERM then behaves as Ctrl-C, for
            commands that write their results only at the end, atomically).

    The previous handlers are restored on exit. Outside the main thread (where
    Python cannot install handlers) the block runs with the default handlers.
    """
    clear_stop()
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.getsignal(s) for s in _SIGNALS}
    for s in _SIGNALS:
        signal.signal(s, _graceful_handler if graceful else _immediate_handler)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
