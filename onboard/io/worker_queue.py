"""The loop of a worker thread fed through a deque under a condition (the video encoder's, the threaded
estimator's): the oldest item each turn, until its owner stops."""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Iterator
from typing import Any

__all__ = ["items_until_stopped"]

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
