"""Reads the daemon's CPU accounting from ``/proc`` and its cgroup (parsers: :mod:`onboard.core.cpu_accounting`).

Thin: each read opens a file and hands its text to a parser; a file that is missing or unreadable
(no cgroup CPU controller, another OS) gives None for what it would have said, never an error.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

from onboard.core.cpu_accounting import (
    parse_cfs_quota,
    parse_cgroup_cpu_stat,
    parse_cpu_max,
    parse_proc_cgroup,
    parse_proc_stat,
)
from onboard.core.errors import InputError

__all__ = ["CpuReading", "CpuUsageReader"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CpuReading:
    """One reading: CPU seconds of the process and its reaped children, seconds the cgroup was throttled
    (None without a CFS controller), the quota in cores (None: none or unknown)."""

    process_cpu_s: float | None
    throttled_s: float | None
    nr_throttled: int | None
    quota_cores: float | None
    nr_periods: int | None = None  # CFS periods in which the cgroup ran (None without a CFS controller)


class CpuUsageReader:
    """``read()`` -> :class:`CpuReading` of this process (``proc_root``/self) and the cgroup holding it
    under ``cgroup_root``.  The cgroup's directory is found once, at construction."""

    def __init__(self, proc_root: str | Path = "/proc", cgroup_root: str | Path = "/sys/fs/cgroup") -> None:
        self._proc = Path(proc_root)
        self._ticks_per_s = float(os.sysconf("SC_CLK_TCK")) if hasattr(os, "sysconf") else 100.0
        self._dir: Path | None = None
        self._version = 0
        self._warned: set[str] = set()
        where = parse_proc_cgroup(_read(self._proc / "self" / "cgroup") or "")
        if where is not None:
            self._version, path = where
            root = Path(cgroup_root)
            rel = path.lstrip("/")
            mounts = [root / "cpu", root / "cpu,cpuacct", root / "cpuacct,cpu"] if self._version == 1 else [root]
            candidates = [m / rel for m in mounts] + ([] if self._version == 1 else [root / "unified" / rel])
            # cgroup v1 has no cgroup namespace in a container (Docker, Podman on a v1 host such as a Jetson's
            # L4T): /proc/self/cgroup names the host's /docker/<id> while the container sees its own cgroup at the
            # controller's mount root; a path that is not there falls back to that root
            if self._version == 1 and rel:
                candidates += mounts
            self._dir = next((d for d in candidates if (d / "cpu.stat").is_file()), None)
            if self._dir is None:
                log.warning(
                    "CPU accounting: %s names cgroup %s (v%d), but no cpu.stat under %s: the quota and its "
                    "throttling are reported as null",
                    self._proc / "self" / "cgroup",
                    path,
                    self._version,
                    root,
                )

    @property
    def cgroup_dir(self) -> Path | None:
        return self._dir

    def read(self) -> CpuReading:
        process_s = None
        text = _read(self._proc / "self" / "stat")
        if text is not None:
            try:
                process_s = parse_proc_stat(text).total_s(self._ticks_per_s)
            except InputError as exc:
                self._warn_once("stat", f"{self._proc}/self/stat: {exc}")
        throttled_s = quota = None
        nr = periods = None
        if self._dir is not None:
            try:
                th = parse_cgroup_cpu_stat(_read(self._dir / "cpu.stat") or "")
                if th is not None:
                    throttled_s, nr, periods = th.throttled_s, th.nr_throttled, th.nr_periods
                if self._version == 2:
                    mx = _read(self._dir / "cpu.max")
                    quota = None if mx is None else parse_cpu_max(mx)
                else:
                    q, p = _read(self._dir / "cpu.cfs_quota_us"), _read(self._dir / "cpu.cfs_period_us")
                    quota = None if q is None or p is None else parse_cfs_quota(q, p)
            except InputError as exc:
                self._warn_once("cgroup", f"{self._dir}: {exc}")
        return CpuReading(process_s, throttled_s, nr, quota, periods)

    def _warn_once(self, key: str, message: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            log.warning("CPU accounting unreadable, reported as null: %s", message)


def _read(path: Path) -> str | None:
    try:
        return path.read_text()
    except OSError:
        return None
