"""onboard.app.parent_watch: a child started with IRTRACK_PARENT_PID gets SIGTERM when that parent dies, even by
SIGKILL (a killed demo left its daemon and simulator running).  Real processes on this machine, bounded in time,
cleaned up by PID."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from onboard.app.parent_watch import PARENT_PID_ENV, end_with_parent

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl(PR_SET_PDEATHSIG) is Linux's")

EXIT_WAIT_S = 10.0  # a guard against a hang, not a measured property
# the child: SIGTERM ends it with code 7, so the test tells the parent-death signal from any other end
CHILD = (
    "import signal, sys, time\n"
    "signal.signal(signal.SIGTERM, lambda *a: sys.exit(7))\n"
    "from onboard.app.parent_watch import end_with_parent\n"
    "print(end_with_parent(), flush=True)\n"
    "time.sleep(60)\n"
)
# the parent: starts the child with its own PID in the environment, says the child's PID, then waits to be killed
PARENT = (
    "import os, subprocess, sys, time\n"
    f"env = {{**os.environ, {PARENT_PID_ENV!r}: str(os.getpid())}}\n"
    "child = subprocess.Popen([sys.executable, '-c', sys.argv[1]], env=env, stdout=subprocess.PIPE, text=True)\n"
    "print(child.pid, child.stdout.readline().strip(), flush=True)\n"
    "time.sleep(60)\n"
)


def _wait_gone(pid: int) -> int | None:
    """The exit status of ``pid`` (not our child: read from /proc until it is gone), None while it runs."""
    t_end = time.monotonic() + EXIT_WAIT_S
    while time.monotonic() < t_end:
        try:
            with open(f"/proc/{pid}/stat") as f:
                if f.read().split()[2] == "Z":  # a zombie: ended, its parent gone before reaping
                    return 0
        except FileNotFoundError:
            return 0
        time.sleep(0.05)
    return None


def test_a_child_ends_when_its_parent_is_killed_outright():
    parent = subprocess.Popen([sys.executable, "-c", PARENT, CHILD], stdout=subprocess.PIPE, text=True)
    child_pid = None
    try:
        child_pid, arranged = parent.stdout.readline().split()
        child_pid = int(child_pid)
        assert arranged == "True"
        parent.kill()  # SIGKILL: none of the parent's clean-up runs
        parent.wait(EXIT_WAIT_S)
        assert _wait_gone(child_pid) is not None, "the child outlived its killed parent"
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        if child_pid is not None:
            try:
                os.kill(child_pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_without_the_variable_nothing_is_arranged():
    assert end_with_parent({}) is False
    assert end_with_parent({PARENT_PID_ENV: "not-a-pid"}) is False


def test_a_parent_gone_before_the_request_stops_the_child_at_once(monkeypatch):
    """The request is made after exec: the parent may already be gone (the child then has another parent), and
    the signal it asked for would never come."""
    import onboard.app.parent_watch as parent_watch

    sent = []
    monkeypatch.setattr(os, "kill", lambda pid, sig: sent.append((pid, sig)))
    monkeypatch.setattr(parent_watch, "_sigterm_on_parent_death", lambda: None)  # not on the test's own process
    assert end_with_parent({PARENT_PID_ENV: str(os.getppid() + 10**6)}) is True
    assert sent == [(os.getpid(), signal.SIGTERM)]
