"""The processes a test started, found and ended by PID (Linux /proc): for the Ctrl-C tests, which check
that a command leaves no child or pool worker behind."""

from __future__ import annotations

import os
import signal
from pathlib import Path

__all__ = ["alive", "descendants", "kill_all"]


def descendants(pid: int) -> set[int]:
    """Every descendant of ``pid`` now (its children, theirs, ...)."""
    out: set[int] = set()
    todo = [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                kids = {int(x) for x in (task / "children").read_text().split()}
            except OSError:
                continue
            todo += list(kids - out)
            out |= kids
    return out


def alive(pid: int) -> bool:
    """``pid`` exists and is not a zombie (an exited child its parent has not reaped yet)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rpartition(")")[2].split()[0] != "Z"


def kill_all(pids) -> None:
    """SIGKILL each of ``pids`` still alive (a test's clean-up, whatever happened)."""
    for pid in pids:
        if alive(pid):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
