"""SIGINT/SIGTERM as a clean stop, and the one line a command prints when Ctrl-C ended it.

A long command installs :func:`install_stop_signals` so that Ctrl-C (or SIGTERM) sets a stop event its loop
checks, instead of raising wherever the loop happens to be; when SIGINT ended it, the command prints
:func:`print_interrupted`'s line, ``interrupted: <what was kept>``, and exits :data:`EXIT_INTERRUPTED`.

The evaluation's commands (eval, dataset, campaign) stop by KeyboardInterrupt instead: their work is in pools
and generators that Ctrl-C unwinds.  :func:`sigterm_as_ctrl_c` makes SIGTERM (a service manager's stop, ``kill``,
a CI job's time limit) take that path too, and :func:`finish_despite_signals` holds both signals while the work
that is done is written.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import sys
import threading
from collections.abc import Callable, Iterator

__all__ = [
    "EXIT_INTERRUPTED",
    "install_stop_signals",
    "print_interrupted",
    "finish_despite_signals",
    "signals_held",
    "sigterm_as_ctrl_c",
]

log = logging.getLogger(__name__)

EXIT_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports for a command Ctrl-C ended


def install_stop_signals(
    stop: threading.Event, received: list[int] | None = None, on_first: Callable[[str], object] | None = None
):
    """SIGINT/SIGTERM set ``stop`` and append their number to ``received``; the first one is announced by
    ``on_first(signal name)`` (default: an INFO log line).  Returns a function restoring the old handlers."""
    old = {}

    def on_signal(signum, _frame):
        if not stop.is_set():
            name = signal.Signals(signum).name
            if on_first is not None:
                on_first(name)
            else:
                log.info("%s: stopping", name)
        if received is not None:
            received.append(signum)
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            old[sig] = signal.signal(sig, on_signal)
        except ValueError:  # not the main thread (embedded use): the caller owns stopping
            pass

    def restore() -> None:
        for sig, handler in old.items():
            signal.signal(sig, handler)

    return restore


def print_interrupted(kept: str) -> int:
    """Print ``interrupted: <kept>`` on stderr; returns :data:`EXIT_INTERRUPTED`."""
    print(f"interrupted: {kept}", file=sys.stderr, flush=True)
    return EXIT_INTERRUPTED


@contextlib.contextmanager
def finish_despite_signals(what: str = "the report") -> Iterator[list[int]]:
    """While the block runs, SIGINT and SIGTERM are recorded (into the list it yields), not raised: the runs
    are done and what is left is writing their results, which a Ctrl-C would otherwise throw away half-written.
    The first is announced as a warning, ``<SIGNAL>: writing <what> first``."""
    received: list[int] = []
    restore = install_stop_signals(
        threading.Event(), received, on_first=lambda name: log.warning("%s: writing %s first", name, what)
    )
    try:
        yield received
    finally:
        restore()


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """While the block runs, SIGINT and SIGTERM wait: one received in it raises KeyboardInterrupt as the block
    ends (unless the block raised).  For a short step that must happen whole or not at all, such as a result
    written to a log and counted: a Ctrl-C between the two had the command report fewer runs done than its log
    holds."""
    received: list[int] = []
    restore = install_stop_signals(threading.Event(), received, on_first=lambda _name: None)
    try:
        yield
    finally:
        restore()
    if received:
        raise KeyboardInterrupt


@contextlib.contextmanager
def sigterm_as_ctrl_c() -> Iterator[None]:
    """While the block runs, SIGTERM raises KeyboardInterrupt, as Ctrl-C does: a command that stops cleanly on
    Ctrl-C (its pool ended, the finished work kept, the interrupted line) stops so on SIGTERM too, where Python's
    default would end the process at once (its pool's workers left running, the files of the work done so far not
    written).  Outside the main thread (embedded use) nothing changes: the caller owns stopping."""
    try:
        old = signal.signal(signal.SIGTERM, signal.default_int_handler)
    except ValueError:
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)
