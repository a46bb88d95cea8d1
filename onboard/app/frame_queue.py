"""The bounded frame queue between the zenoh callback (which must never block) and the pipeline thread."""

from __future__ import annotations

import collections
import threading
from typing import Any

from onboard.core.checks import is_positive_int
from onboard.core.errors import InputError

__all__ = ["FrameQueue", "BUNCHED_FRACTION", "arrived_bunched"]

#: frames that reached the queue in less than this fraction of the time between their capture stamps arrived bunched
BUNCHED_FRACTION = 0.5


def arrived_bunched(
    oldest_received_ns: int, oldest_time_boot_us: int, newest_received_ns: int, newest_time_boot_us: int
) -> bool:
    """Whether the queued frames, from the oldest to the newest, arrived much faster than they were captured.

    A pipeline that falls behind overflows the queue with frames arriving at the camera's pace (arrival span about
    the capture span); a link or sender that holds frames and releases them together (network jitter) overflows it
    with frames arriving within milliseconds of each other though captured a camera period apart.  The two call for
    different remedies (CPU, or the link and ``input.queue_length``), so the drops are told apart."""
    capture_span_ns = (newest_time_boot_us - oldest_time_boot_us) * 1000
    if capture_span_ns <= 0:
        return False
    return newest_received_ns - oldest_received_ns < BUNCHED_FRACTION * capture_span_ns


class FrameQueue:
    """Bounded FIFO (of ``(IrFrame, received_mono_ns)`` in the service); pushing onto a full queue drops the oldest."""

    def __init__(self, maxlen: int) -> None:
        if not is_positive_int(maxlen):
            raise InputError(f"FrameQueue maxlen must be a positive integer, got {maxlen!r}")
        self._d: collections.deque = collections.deque()
        self._maxlen = maxlen
        self._cond = threading.Condition(threading.Lock())
        self._closed = False

    def push(self, item: Any) -> int:
        """Append; returns how many old items were dropped to make room (0 or 1)."""
        with self._cond:
            dropped = 0
            while len(self._d) >= self._maxlen:
                self._d.popleft()
                dropped += 1
            self._d.append(item)
            self._cond.notify()
            return dropped

    def pop(self, timeout_s: float) -> Any:
        """The oldest item, or None after ``timeout_s`` or once closed."""
        with self._cond:
            if not self._d and not self._closed:
                self._cond.wait(timeout_s)
            if self._d:
                return self._d.popleft()
            return None

    def oldest(self) -> Any:
        """The oldest item, left in the queue; None when it is empty."""
        with self._cond:
            return self._d[0] if self._d else None

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def __len__(self) -> int:
        return len(self._d)
