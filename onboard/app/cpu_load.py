"""The status JSON's CPU figures: what the daemon got and what its cgroup's quota refused it.

The service calls :meth:`CpuLoad.sample` once per status interval with the worker process's CPU seconds
(a live child is not in ``/proc/self/stat``'s ``cutime`` until it is reaped); the reader is
:class:`onboard.io.cpu_usage.CpuUsageReader`.
"""

from __future__ import annotations

from typing import Any

from onboard.core.cpu_accounting import share_per_s
from onboard.io.cpu_usage import CpuReading, CpuUsageReader

__all__ = ["CpuLoad"]


class CpuLoad:
    """``sample(now_s, worker_cpu_s)`` -> the ``cpu`` keys added to the status:

    ``gets_share``: the daemon's CPU (process, reaped children and the live estimator worker) per wall
    second over the last interval; ``throttled_share``: wall seconds per second the cgroup had work and
    its CFS quota had run out (null without a CPU controller); ``needs_share``: their sum, a lower bound
    of what it needed; ``throttled_periods``: CFS periods throttled in the interval; ``quota_cores``: the
    cgroup's quota (null: none)."""

    def __init__(self, reader: CpuUsageReader | None = None) -> None:
        self.reader = reader or CpuUsageReader()
        self._last: tuple[float, CpuReading, float] | None = None
        self.last_section: dict[str, Any] = {}

    def sample(self, now_s: float, worker_cpu_s: float) -> dict[str, Any]:
        r = self.reader.read()
        last, self._last = self._last, (now_s, r, worker_cpu_s)
        if last is None:
            section: dict[str, Any] = {
                "gets_share": None,
                "throttled_share": None,
                "needs_share": None,
                "throttled_periods": None,
                "quota_cores": r.quota_cores,
            }
        else:
            t0, r0, w0 = last
            wall = now_s - t0
            p0 = None if r0.process_cpu_s is None else r0.process_cpu_s + w0
            p1 = None if r.process_cpu_s is None else r.process_cpu_s + worker_cpu_s
            gets = share_per_s(p0, p1, wall)
            throttled = share_per_s(r0.throttled_s, r.throttled_s, wall)
            periods = None if r.nr_throttled is None or r0.nr_throttled is None else r.nr_throttled - r0.nr_throttled
            section = {
                "gets_share": gets,
                "throttled_share": throttled,
                "needs_share": None if gets is None else gets + (throttled or 0.0),
                "throttled_periods": periods,
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
        if s.get("throttled_share"):
            out += f", throttled {s['throttled_share']:.2f} s per s"
        if s.get("quota_cores") is not None:
            out += f" under a quota of {s['quota_cores']:.2f} cores"
        return out + ")"
