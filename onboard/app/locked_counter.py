"""The daemon's event counter: a :class:`~onboard.core.counters.RejectCounter` that several threads count into
(the zenoh callback, the pipeline thread, the main loop, the estimator worker's reader)."""

from __future__ import annotations

import logging
import threading
from typing import Any

from onboard.core.counters import RejectCounter

__all__ = ["LockedCounter"]


class LockedCounter(RejectCounter):
    """A :class:`RejectCounter` that several threads may count into."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._lock = threading.Lock()

    def count(self, reason: str, detail: str = "", n: int = 1, level: int = logging.WARNING, subject: str = "") -> None:
        with self._lock:
            super().count(reason, detail, n, level=level, subject=subject)

    @property
    def counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)
