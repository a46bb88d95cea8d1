"""The CPU the daemon gets and the CPU it was refused: parsers of the kernel's accounting files.

Pure: each function takes a file's text and returns numbers; :mod:`onboard.io.cpu_usage` reads the
files.  The sources:

``/proc/<pid>/stat`` (proc(5))
    Fields 14-17 after the parenthesised command: ``utime``, ``stime`` (this process), ``cutime``,
    ``cstime`` (its waited-for children), in clock ticks (``SC_CLK_TCK``, 100 on Linux).
``/proc/self/cgroup`` (cgroups(7))
    Lines ``hierarchy-ID:controllers:path``; cgroup v2 is the line ``0::/path``, v1 names the ``cpu``
    controller among its comma-separated controllers.
``cpu.stat`` of the cgroup
    v2: ``usage_usec``, ``nr_periods``, ``nr_throttled``, ``throttled_usec``; v1 (``cpu`` controller):
    ``nr_periods``, ``nr_throttled``, ``throttled_time`` in nanoseconds.
``cpu.max`` (v2: ``<quota_us|max> <period_us>``) and ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us`` (v1,
    quota ``-1`` for none): the CFS quota, as a number of cores.

Throttled time is not the CPU the daemon needed and did not get: the kernel adds, for every CPU whose run queue of
the cgroup ran out of quota, the time to the end of that period, however little it had left to run (so it can
exceed one second per second on a machine of several cores).  ``nr_throttled`` over ``nr_periods`` says how often
the quota bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from onboard.core.errors import InputError

__all__ = [
    "ProcCpuTicks",
    "CgroupThrottle",
    "parse_proc_stat",
    "parse_proc_cgroup",
    "parse_cgroup_cpu_stat",
    "parse_cpu_max",
    "parse_cfs_quota",
    "share_per_s",
]


@dataclass(frozen=True)
class ProcCpuTicks:
    """CPU of a process in clock ticks: its own ``utime``/``stime``, its reaped children's ``cutime``/``cstime``."""

    utime_ticks: int
    stime_ticks: int
    cutime_ticks: int
    cstime_ticks: int

    def total_s(self, ticks_per_s: float) -> float:
        """Process plus reaped children, in CPU seconds."""
        return (self.utime_ticks + self.stime_ticks + self.cutime_ticks + self.cstime_ticks) / float(ticks_per_s)


@dataclass(frozen=True)
class CgroupThrottle:
    """A cgroup's CFS counters: periods elapsed, periods throttled, and the time throttled (s)."""

    nr_periods: int
    nr_throttled: int
    throttled_s: float


def parse_proc_stat(text: str) -> ProcCpuTicks:
    """``/proc/<pid>/stat`` -> the four CPU time fields.  The command name (field 2) may hold spaces and
    parentheses, so the fields are counted after its *last* ``)``.  Raises :class:`InputError` otherwise."""
    end = text.rfind(")")
    if end < 0:
        raise InputError(f"/proc stat: no ')' closing the command name in {text[:80]!r}")
    fields = text[end + 1 :].split()
    # fields[0] is the state (field 3), so utime (field 14) is fields[11]
    if len(fields) < 15:
        raise InputError(f"/proc stat: {len(fields) + 2} fields, expected at least 17")
    try:
        vals = [int(fields[i]) for i in range(11, 15)]
    except ValueError as exc:
        raise InputError(f"/proc stat: CPU time fields are not integers: {fields[11:15]!r}") from exc
    if any(v < 0 for v in vals):
        raise InputError(f"/proc stat: negative CPU time {vals!r}")
    return ProcCpuTicks(*vals)


def parse_proc_cgroup(text: str) -> tuple[int, str] | None:
    """``/proc/self/cgroup`` -> ``(version, path)`` of the cgroup that holds the CPU controller: the v1
    line naming ``cpu`` when there is one (a v1 ``cpu`` hierarchy is where a quota lives), else the v2
    line ``0::path``; None when neither is there."""
    v2: str | None = None
    for line in text.splitlines():
        parts = line.strip().split(":", 2)
        if len(parts) != 3:
            continue
        hid, controllers, path = parts
        if hid == "0" and controllers == "":
            v2 = path
        elif "cpu" in controllers.split(","):
            return 1, path
    return None if v2 is None else (2, v2)


def parse_cgroup_cpu_stat(text: str) -> CgroupThrottle | None:
    """A cgroup's ``cpu.stat`` (v2 ``throttled_usec`` or v1 ``throttled_time`` in ns) -> its counters;
    None when it has no throttling counters (v2 without the cpu controller enabled has only usage)."""
    kv: dict[str, int] = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) != 2:
            continue
        try:
            kv[parts[0]] = int(parts[1])
        except ValueError:
            continue
    if "throttled_usec" in kv:
        throttled_s = kv["throttled_usec"] / 1e6
    elif "throttled_time" in kv:
        throttled_s = kv["throttled_time"] / 1e9
    else:
        return None
    if throttled_s < 0 or kv.get("nr_periods", 0) < 0 or kv.get("nr_throttled", 0) < 0:
        raise InputError(f"cpu.stat: negative counter in {kv!r}")
    return CgroupThrottle(kv.get("nr_periods", 0), kv.get("nr_throttled", 0), throttled_s)


def parse_cpu_max(text: str) -> float | None:
    """cgroup v2 ``cpu.max`` (``"<quota_us> <period_us>"`` or ``"max <period_us>"``) -> quota in cores, None
    for no quota.  Raises :class:`InputError` on anything else."""
    parts = text.split()
    if len(parts) != 2:
        raise InputError(f"cpu.max: expected '<quota> <period>', got {text!r}")
    if parts[0] == "max":
        return None
    try:
        quota_us, period_us = int(parts[0]), int(parts[1])
    except ValueError as exc:
        raise InputError(f"cpu.max: not integers: {text!r}") from exc
    return _cores(quota_us, period_us, "cpu.max")  # its own words for a value out of range (InputError is a ValueError)


def parse_cfs_quota(quota_text: str, period_text: str) -> float | None:
    """cgroup v1 ``cpu.cfs_quota_us`` and ``cpu.cfs_period_us`` -> quota in cores, None for ``-1`` (none)."""
    try:
        quota_us, period_us = int(quota_text.strip()), int(period_text.strip())
    except ValueError as exc:
        raise InputError(
            f"cpu.cfs_quota_us / cpu.cfs_period_us: not integers: {quota_text!r}, {period_text!r}"
        ) from exc
    if quota_us == -1:
        return None
    return _cores(quota_us, period_us, "cpu.cfs_quota_us")


def _cores(quota_us: int, period_us: int, what: str) -> float:
    if quota_us <= 0 or period_us <= 0:
        raise InputError(f"{what}: quota and period must be positive, got {quota_us}, {period_us}")
    return quota_us / period_us


def share_per_s(before: float | None, after: float | None, wall_s: float) -> float | None:
    """The increase of a seconds counter over ``wall_s`` of wall time (1.0 = one core busy); None when
    either reading is missing, the wall time is not positive, or the counter went back (a new cgroup)."""
    if before is None or after is None or not (wall_s > 0 and math.isfinite(wall_s)) or after < before:
        return None
    return (after - before) / wall_s
