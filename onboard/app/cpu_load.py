"""The status JSON's CPU figures: what the daemon got and what its cgroup's quota refused it.

The service calls :meth:`CpuLoad.sample` with each status (an interval shorter than :data:`MIN_WINDOW_S` keeps
the last figures) with the worker process's CPU seconds
(a live child is not in ``/proc/self/stat``'s ``cutime`` until it is reaped); the reader is
:class:`onboard.io.cpu_usage.CpuUsageReader`.
"""

from __future__ import annotations

from typing import Any

from onboard.core.cpu_accounting import share_per_s
from onboard.io.cpu_usage import CpuReading, CpuUsageReader

__all__ = ["CpuLoad", "MIN_WINDOW_S"]

#: the shortest interval sampled: /proc's CPU times tick at 10 ms, so a window of tens of ms is mostly rounding
MIN_WINDOW_S = 0.5


class CpuLoad:
    """``sample(now_s, worker_cpu_s)`` -> the ``cpu`` keys added to the status:

    ``gets_share``: the daemon's CPU (process, reaped children and the live estimator worker) per wall
    second over the last interval; ``throttled_periods``: CFS periods in which the quota ran out, and
    ``throttled_periods_share`` their share of the periods the cgroup ran in (null without a CPU controller, or
    when the counters went back); ``needs_share``: what it needed, ``gets_share`` while the quota did not bind in
    the interval, null when it did (more than it got; the kernel does not say how much more);
    ``throttled_share``: the kernel's ``throttled_time`` per wall second (null without a controller), which is not
    CPU needed: it is summed over every CPU whose run queue of the cgroup waited, each to the end of its period
    however little it had to run (1.07 s a second at a 0.15 quota where the free-running daemon used 0.26);
    ``quota_cores``: the cgroup's quota (null: none)."""

    def __init__(self, reader: CpuUsageReader | None = None) -> None:
        self.reader = reader or CpuUsageReader()
        self._last: tuple[float, CpuReading, float] | None = None
        self.last_section: dict[str, Any] = {}

    def sample(self, now_s: float, worker_cpu_s: float) -> dict[str, Any]:
        if self._last is not None and now_s - self._last[0] < MIN_WINDOW_S:
            # an extra status (a warning raised or cleared) tens of ms after the last: a window of a few clock ticks
            # read 0.02 and 0.41 of a core between seconds at 0.2-0.26; the last figures stand until a full one
            return self.last_section
        r = self.reader.read()
        last, self._last = self._last, (now_s, r, worker_cpu_s)
        if last is None:
            section: dict[str, Any] = {
                "gets_share": None,
                "throttled_share": None,
                "needs_share": None,
                "throttled_periods": None,
                "throttled_periods_share": None,
                "quota_cores": r.quota_cores,
            }
        else:
            t0, r0, w0 = last
            wall = now_s - t0
            p0 = None if r0.process_cpu_s is None else r0.process_cpu_s + w0
            p1 = None if r.process_cpu_s is None else r.process_cpu_s + worker_cpu_s
            gets = share_per_s(p0, p1, wall)
            throttled = share_per_s(r0.throttled_s, r.throttled_s, wall)
            periods = _delta(r0.nr_throttled, r.nr_throttled)
            ran = _delta(r0.nr_periods, r.nr_periods)
            bound = periods is not None and periods > 0
            section = {
                "gets_share": gets,
                "throttled_share": throttled,
                "needs_share": None if gets is None or bound else gets,
                "throttled_periods": periods,
                "throttled_periods_share": None if periods is None or not ran else min(periods / ran, 1.0),
                "quota_cores": r.quota_cores,
            }
        self.last_section = section
        return section

    def words(self) -> str:
        """The last sample in words, for the ``overload`` warning (empty before two samples)."""
        s = self.last_section
        if s.get("gets_share") is None:
            return ""
        out = f" (it got {s['gets_share']:.2f} of a core"
        if s.get("throttled_periods_share"):
            out += f", its CPU quota ran out in {100 * s['throttled_periods_share']:.0f} % of its periods"
        if s.get("quota_cores") is not None:
            out += f" under a quota of {s['quota_cores']:.2f} cores"
        return out + ")"

    def quota_bound(self) -> bool | None:
        """Whether the CPU quota ran out in the last interval (None: no controller or no sample yet)."""
        periods = self.last_section.get("throttled_periods")
        return None if periods is None else periods > 0


def _delta(before: int | None, after: int | None) -> int | None:
    """A counter's growth; None when either is unknown or it went back (a cgroup recreated, or nonsense)."""
    if before is None or after is None or after < before:
        return None
    return after - before
