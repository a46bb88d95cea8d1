"""The project-wide count of rejected inputs and notable events, by reason.

Pure core: no threads (a thread-safe variant wraps it where threads share one), no I/O besides logging.
Every component that refuses an input (the pose buffer, the clock sync, the MAVLink adapter, the frame
pipeline, the estimator) counts it here under a reason of its own (e.g. ``attitude_zero``,
``timesync_rtt``, ``frame_short``) instead of raising; the daemon's status JSON shows the counts
(``rejected``).  Each module documents the reasons it counts.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

from onboard.core.errors import ConfigError

__all__ = ["RejectCounter"]

log = logging.getLogger(__name__)

#: (reason, subject) pairs remembered before those whose interval has passed are forgotten
MAX_LOG_KEYS = 1024


class RejectCounter:
    """Counts by reason; logs each reason (and subject, when the caller names one) at most once per
    ``log_interval_s`` (with the count since).

    ``count(reason, detail)`` never raises.  ``counts`` is a copy of the reason -> count dict.
    """

    def __init__(
        self,
        log_interval_s: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
        logger: logging.Logger | None = None,
    ) -> None:
        if not (math.isfinite(log_interval_s) and log_interval_s >= 0):
            raise ConfigError(f"RejectCounter.log_interval_s must be >= 0 seconds, got {log_interval_s!r}")
        self.log_interval_s = float(log_interval_s)
        self._clock = clock
        self._log = logger or log
        self._counts: dict[str, int] = {}
        # the log interval is kept per (reason, subject): subject "" unless the caller names one
        self._last_log_s: dict[tuple[str, str], float] = {}
        self._unlogged: dict[tuple[str, str], int] = {}

    def count(self, reason: str, detail: str = "", n: int = 1, level: int = logging.WARNING, subject: str = "") -> None:
        """Count ``n`` of ``reason``; log it at ``level`` (WARNING: a rejection; DEBUG: a normal event).

        ``subject`` (a vehicle's name): the log interval is kept per reason and subject, so that one vehicle's
        event does not hide another's within the interval (the fusion's ``vehicle_silent`` of a second vehicle, or
        its ``clock_inconsistent`` naming the right vehicle after a wrong one, were never logged); the count is the
        reason's either way."""
        self._counts[reason] = self._counts.get(reason, 0) + n
        try:
            now = float(self._clock())
        except Exception:  # a broken clock must not break the caller
            now = math.nan
        key = (reason, subject)
        last = self._last_log_s.get(key)
        if last is None or not now - last < self.log_interval_s:
            since = self._unlogged.get(key, 0) + n
            self._log.log(
                level, "%s: %s (total %d, %d since last report)", reason, detail or "-", self._counts[reason], since
            )
            if subject and len(self._last_log_s) >= MAX_LOG_KEYS:
                self._prune(now)
            self._last_log_s[key] = now
            self._unlogged[key] = 0
        else:
            self._unlogged[key] = self._unlogged.get(key, 0) + n

    def _prune(self, now: float) -> None:
        """Forget the subjects whose interval has passed with nothing left unlogged: their next event is logged
        whether remembered or not, and names that come and go (vehicles forgotten, new ones) must not grow the
        dicts for the life of the process."""
        for key in [k for k, t in self._last_log_s.items() if not now - t < self.log_interval_s]:
            if not self._unlogged.get(key):
                del self._last_log_s[key]
                self._unlogged.pop(key, None)

    def __getitem__(self, reason: str) -> int:
        return self._counts.get(reason, 0)

    @property
    def counts(self) -> dict[str, int]:
        return dict(self._counts)

    @property
    def total(self) -> int:
        return sum(self._counts.values())
