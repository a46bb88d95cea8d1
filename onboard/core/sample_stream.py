"""A bounded, time-ordered stream of samples and the bracket of a query time (pure core).

The pose buffer (:mod:`onboard.core.pose`) keeps one per telemetry source (attitude, position, gimbal):
samples arrive in time order at their own rate, and a frame's capture time is answered by the two
samples around it, never by the latest one.
"""

from __future__ import annotations

import bisect

import numpy as np

__all__ = ["SampleStream"]


class SampleStream:
    """Time-ordered samples of one source (``t_us`` ascending, ``values`` rows of equal length).

    ``name`` prefixes the miss reasons of :meth:`bracket`; ``max_gap_us`` is the widest bracket it
    accepts.  ``pending_t_us`` is the owner's: a run of far-off stamps that may yet confirm a clock step.
    """

    def __init__(self, name: str, max_gap_us: int) -> None:
        self.name = name
        self.max_gap_us = max_gap_us
        self.t_us: list[int] = []
        self.values: list[np.ndarray] = []
        self.pending_t_us: list[int] = []

    @property
    def last_t(self) -> int | None:
        return self.t_us[-1] if self.t_us else None

    def clear(self) -> None:
        self.t_us.clear()
        self.values.clear()
        self.pending_t_us.clear()

    def append(self, t_us: int, value: np.ndarray, window_us: int, max_samples: int) -> None:
        """Add a sample newer than the newest; drop those older than ``window_us`` before it and all but
        the newest ``max_samples``."""
        self.t_us.append(t_us)
        self.values.append(value)
        cut = bisect.bisect_left(self.t_us, t_us - window_us)
        cut = max(cut, len(self.t_us) - max_samples)
        if cut > 0:
            del self.t_us[:cut]
            del self.values[:cut]

    def bracket(self, t_us: int) -> tuple[int, int, float] | tuple[None, str, bool]:
        """``(i0, i1, alpha)`` with ``t_us[i0] <= t_us <= t_us[i1]`` and ``alpha`` the fraction of the way
        from the first to the second (``i0 == i1``, 0.0 on a sample), or ``(None, reason, retry)``:
        ``<name>_empty``, ``<name>_before_buffer``, ``<name>_gap`` (the bracket, or the time past the
        newest sample, is wider than ``max_gap_us``) or ``<name>_not_yet`` (past the newest sample by less:
        ``retry`` True, the next sample may bracket it)."""
        if not self.t_us:
            return None, f"{self.name}_empty", False
        if t_us < self.t_us[0]:
            return None, f"{self.name}_before_buffer", False
        if t_us > self.t_us[-1]:
            if t_us - self.t_us[-1] > self.max_gap_us:
                return None, f"{self.name}_gap", False
            return None, f"{self.name}_not_yet", True
        i = bisect.bisect_left(self.t_us, t_us)
        if self.t_us[i] == t_us:
            return i, i, 0.0
        t0, t1 = self.t_us[i - 1], self.t_us[i]
        if t1 - t0 > self.max_gap_us:
            return None, f"{self.name}_gap", False
        return i - 1, i, (t_us - t0) / (t1 - t0)
