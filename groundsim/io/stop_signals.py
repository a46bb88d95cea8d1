"""SIGINT/SIGTERM as a clean stop, and the one line a command prints when Ctrl-C ended it.

A long command installs :func:`install_stop_signals` so that Ctrl-C (or SIGTERM) sets a stop event its loop
checks, instead of raising wherever the loop happens to be; when SIGINT ended it, the command prints
:func:`print_interrupted`'s line, ``interrupted: <what was kept>``, and exits :data:`EXIT_INTERRUPTED`.

The evaluation's commands (eval, dataset, campaign) stop by KeyboardInterrupt instead: their work is in pools
and generators that Ctrl-C unwinds.  :func:`first_signal_stops` makes SIGTERM (a service manager's stop, ``kill``,
a CI job's time limit) take that path too, its first signal raising and every later one only noted, so a second
one cannot land between the first's KeyboardInterrupt and the command's finishing; :func:`finish_despite_signals`
holds both signals while the work that is done is written.

SIGINT ignored when the process started (what a non-interactive shell does to a command run with ``&``, so that
Ctrl-C at the terminal is not its business) stays ignored: :func:`finish_despite_signals`, :func:`signals_held`
and :func:`first_signal_stops` leave it so, SIGTERM is taken whatever its inherited handler.  A command ended by
a signal settles its exit code with :func:`settle_exit`.
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
    "first_signal_stops",
    "redeliver",
    "settle_exit",
]

log = logging.getLogger(__name__)

EXIT_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports for a command Ctrl-C ended


def _ignored(sig: int) -> bool:
    """Whether ``sig`` is ignored (SIGINT: as a non-interactive shell starts a background command)."""
    try:
        return signal.getsignal(sig) is signal.SIG_IGN
    except ValueError:
        return False


def install_stop_signals(
    stop: threading.Event,
    received: list[int] | None = None,
    on_first: Callable[[str], object] | None = None,
    keep_ignored: bool = False,
):
    """SIGINT/SIGTERM set ``stop`` and append their number to ``received``; the first one is announced by
    ``on_first(signal name)`` (default: an INFO log line).  ``keep_ignored``: a signal ignored now stays ignored.
    Returns a function restoring the old handlers."""
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
        if keep_ignored and _ignored(sig):
            continue
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
        threading.Event(),
        received,
        on_first=lambda name: log.warning("%s: writing %s first", name, what),
        keep_ignored=True,
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
    holds.  The signal is handed to the handler in place after the block when that is a Python one (a command's
    :func:`first_signal_stops` then knows it has been asked to stop), else raised as KeyboardInterrupt."""
    received: list[int] = []
    restore = install_stop_signals(threading.Event(), received, on_first=lambda _name: None, keep_ignored=True)
    try:
        yield
    finally:
        restore()
    if received:
        redeliver(received[0])


def redeliver(sig: int) -> None:
    """Hand ``sig``, held while another handler was in place, to the handler in place now when that is a Python
    one (it raises, or only notes it: :func:`first_signal_stops` after its first); otherwise (the default, which
    would end the process, or not the main thread) raise KeyboardInterrupt, as a held signal always did."""
    try:
        handler = signal.getsignal(sig)
    except ValueError:
        handler = None
    if callable(handler):
        signal.raise_signal(sig)
        return
    raise KeyboardInterrupt


@contextlib.contextmanager
def first_signal_stops(what: str) -> Iterator[list[int]]:
    """While the block runs, the first SIGTERM, or SIGINT unless it was ignored on entry, raises KeyboardInterrupt
    (Ctrl-C's clean stop: SIGTERM takes it too, where Python's default would end the process at once, its pool's
    workers left running and the files of the work done so far not written); every later one is appended to the list it
    yields, the first of them announced as a warning, ``<SIGNAL>: stopping already; writing <what> first``, and not
    raised.  Two quick signals had the second land while the first was being caught, before the command's
    :func:`finish_despite_signals` took over, and end the command without writing ``what``.  Outside the main thread
    nothing changes: the caller owns stopping."""
    received: list[int] = []

    def on_signal(signum, _frame):
        received.append(signum)
        if len(received) == 1:
            raise KeyboardInterrupt
        if len(received) == 2:
            log.warning("%s: stopping already; writing %s first", signal.Signals(signum).name, what)

    old = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        if sig == signal.SIGINT and _ignored(sig):
            continue
        try:
            old[sig] = signal.signal(sig, on_signal)
        except ValueError:
            break
    try:
        yield received
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def settle_exit(code: int) -> int:
    """``code``, the process's exit code; when it is :data:`EXIT_INTERRUPTED` (the command stopped on a signal and
    said so) SIGINT and SIGTERM are ignored from here to the process's end: a repeated one while Python exits (the
    pool's and the fork server's finalizers take a moment) had ended the process as killed by it (exit 143), its
    files written and its interrupted line printed.  For entry points only (``__main__``)."""
    if code == EXIT_INTERRUPTED:
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                signal.signal(sig, signal.SIG_IGN)
            except ValueError:
                pass
    return code
