"""CPU share of a process tree from ``/proc`` (Linux): the demo's per-second CPU figures of its two
children, each with its own child processes (the daemon runs its estimator in a worker process)."""

from __future__ import annotations

import os
import time

__all__ = ["ProcCpu", "children_by_parent"]


def _proc_stat(pid: int) -> list[str] | None:
    """Fields of ``/proc/<pid>/stat`` after the command name (field 3 onwards), or None."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as f:
            return f.read().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def children_by_parent() -> dict[int, list[int]]:
    """Every live process's children by parent pid, from ``/proc/<pid>/stat`` (Linux; empty elsewhere): the
    daemon's process tree, whose estimator worker is a child of its fork server.  A process that ends while
    it is read is left out."""
    kids: dict[int, list[int]] = {}
    try:
        names = os.listdir("/proc")
    except OSError:
        return kids
    for name in names:
        if name.isdigit():
            # the command name may hold spaces and parentheses: the parent pid is the 2nd field after its ")"
            st = _proc_stat(int(name))
            if st is not None and len(st) > 1 and st[1].isdigit():
                kids.setdefault(int(st[1]), []).append(int(name))
    return kids


class ProcCpu:
    """CPU seconds of a process and all its descendants (the daemon runs its estimator in a child
    process): utime + stime of every living process of the tree (``/proc/<pid>/stat``, parents found
    by scanning ``/proc``) plus the root's cutime + cstime (children already reaped).  None off Linux
    or once the root is gone."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self._tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
        self.t0 = time.monotonic()
        self.cpu0 = self.cpu_s() or 0.0
        self.last = (self.t0, self.cpu0)
        self.final: float | None = None

    def _descendants(self) -> list[int]:
        kids = children_by_parent()
        out, frontier = [], [self.pid]
        while frontier:
            found = kids.get(frontier.pop(), [])
            out += found
            frontier += found
        return out

    def cpu_s(self) -> float | None:
        root = _proc_stat(self.pid)
        try:
            if root is None:
                return None
            total = sum(int(x) for x in root[11:15])  # utime, stime, cutime, cstime
            for pid in self._descendants():
                st = _proc_stat(pid)
                if st is not None:
                    total += int(st[11]) + int(st[12])
        except (IndexError, ValueError):
            return None
        return total / self._tick

    def share_since_last(self) -> float | None:
        now, c = time.monotonic(), self.cpu_s()
        if c is None:
            return None
        t_last, c_last = self.last
        self.last = (now, c)
        self.final = c
        return (c - c_last) / max(now - t_last, 1e-9)

    def share_overall(self) -> float | None:
        c = self.final if self.final is not None else self.cpu_s()
        if c is None:
            return None
        return (c - self.cpu0) / max(self.last[0] - self.t0, 1e-9)
