"""The wait of a worker thread fed through a deque under a condition (the video encoder's, the threaded
estimator's): the oldest item, or None once its owner stops."""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import Any

__all__ = ["next_or_stop"]

POLL_S = 0.5  # a stop request is also seen after at most this long without a notify


def next_or_stop(cond: threading.Condition, items: deque, stopped: Callable[[], bool]) -> Any | None:
    """Wait under ``cond`` until ``items`` holds something or ``stopped()``; pop the oldest item, or
    return None once stopped (items still queued then are left)."""
    with cond:
        while not items and not stopped():
            cond.wait(POLL_S)
        return None if stopped() else items.popleft()
