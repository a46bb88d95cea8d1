"""Test doubles shared by several test files: the fake clock, and the fake autopilot (groundsim's scripted one)."""

from __future__ import annotations

from groundsim.io.scripted_autopilot import ScriptedAutopilot


class FakeClock:
    """The tests' one fake clock: monotonic seconds that move only when the test sets or adds to ``t_s``,
    or when the code under test calls :meth:`sleep` (which advances it and records the request in ``sleeps``).

    Every clock interface the code takes: callable (seconds; ``OnboardService``, ``PoseBuffer``,
    ``MavlinkLink``), ``ns()`` (``OnboardService``), ``now_s()`` and ``sleep(s)`` (the simulator's paced loop,
    the interface of ``groundsim.app.run.SystemClock``)."""

    def __init__(self, t_s: float = 1000.0) -> None:
        self.t_s = t_s
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.t_s

    def ns(self) -> int:
        return int(self.t_s * 1e9)

    def now_s(self) -> float:
        return self.t_s

    def sleep(self, s: float) -> None:
        """Advance by ``s`` seconds at once; a sleep of zero or less is a bug of the caller (it raises)."""
        if not s > 0:
            raise AssertionError(f"FakeClock.sleep({s!r}): the caller must not sleep for zero or less")
        self.sleeps.append(s)
        self.t_s += s


# the one fake autopilot of the tests (and of bench.onboard, which cannot import tests/): scripted, call by call
FakeAutopilot = ScriptedAutopilot
