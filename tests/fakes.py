"""Test doubles shared by several test files (no sockets, no threads)."""

from __future__ import annotations


class FakeClock:
    """A monotonic clock that moves only when the test sets ``t_s``; callable (seconds) and ``ns()``,
    the two clocks :class:`onboard.app.service.OnboardService` takes."""

    def __init__(self, t_s: float = 1000.0) -> None:
        self.t_s = t_s

    def __call__(self) -> float:
        return self.t_s

    def ns(self) -> int:
        return int(self.t_s * 1e9)
