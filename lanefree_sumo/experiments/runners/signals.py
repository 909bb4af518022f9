"""SIGTERM handled like Ctrl-C: ``lanefree`` runs every verb inside :func:`sigterm_as_interrupt` (so ``kill PID``
stops any verb as Ctrl-C does: its message, exit code 130, its ``--json`` summary); verbs that stop at a step
boundary of their choosing (train, evaluate, rollout, mixed-autonomy) take both signals over with
:func:`stop_requested` (train with its own handler) while they run."""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator
from typing import Any


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block SIGTERM raises KeyboardInterrupt, so ``kill PID`` stops as Ctrl-C does."""

    def interrupt(_signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, interrupt)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class StopRequest:
    """Set by Ctrl-C or SIGTERM inside :func:`stop_requested`; the work checks it between steps."""

    def __init__(self) -> None:
        self.requested = False


@contextlib.contextmanager
def stop_requested() -> Iterator[StopRequest]:
    """Within the block Ctrl-C and SIGTERM only set ``.requested`` (no exception at an arbitrary
    line), so a loop stops at a step boundary it chooses and its files stay consistent."""
    stop = StopRequest()

    def request(_signum: int, _frame: Any) -> None:
        stop.requested = True

    try:
        previous = {s: signal.signal(s, request) for s in (signal.SIGINT, signal.SIGTERM)}
    except ValueError:  # not the main thread: leave signals alone
        yield stop
        return
    try:
        yield stop
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
