"""A worker thread fed through a deque under a condition: :func:`items_until_stopped`, its loop taking the oldest
item each turn until its owner stops it (the video encoder's, the threaded estimator's), and
:func:`stop_and_join`, the owner's stop (those and the recorder's and the live view's, whose loops wait on their
own terms)."""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Iterator
from typing import Any

__all__ = ["items_until_stopped", "stop_and_join"]

POLL_S = 0.5  # a stop request is also seen after at most this long without a notify


def items_until_stopped(cond: threading.Condition, items: deque, stopped: Callable[[], bool]) -> Iterator[Any]:
    """Each turn, wait under ``cond`` until ``items`` holds something or ``stopped()``, and yield the oldest item
    (popped, the lock released while the caller works on it); end once stopped (items still queued then are
    left)."""
    while True:
        with cond:
            while not items and not stopped():
                cond.wait(POLL_S)
            if stopped():
                return
            item = items.popleft()
        yield item


def stop_and_join(
    cond: threading.Condition, stop: threading.Event, thread: threading.Thread | None, timeout_s: float
) -> bool:
    """Set ``stop`` under ``cond`` and wake every waiter on it (a worker between its check of ``stop`` and its wait
    would otherwise sleep through the request), then wait up to ``timeout_s`` for ``thread`` (None: never
    started) to end.  True once it has ended; False while it still runs (its owner says what that leaves undone)."""
    with cond:
        stop.set()
        cond.notify_all()
    if thread is None:
        return True
    thread.join(timeout_s)
    return not thread.is_alive()
