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
# the child: its SIGTERM handler leaves a mark (argv[1]) before it exits, so the test tells the parent-death
# signal from any other end
CHILD = (
    "import signal, sys, time\n"
    "signal.signal(signal.SIGTERM, lambda *a: (open(sys.argv[1], 'w').write('SIGTERM'), sys.exit(7)))\n"
    "from onboard.app.parent_watch import end_with_parent\n"
    "print(end_with_parent(), flush=True)\n"
    "time.sleep(60)\n"
)
# the parent: starts the child with its own PID in the environment, says the child's PID, then waits to be killed
PARENT = (
    "import os, subprocess, sys, time\n"
    f"env = {{**os.environ, {PARENT_PID_ENV!r}: str(os.getpid())}}\n"
    "child = subprocess.Popen([sys.executable, '-c', sys.argv[1], sys.argv[2]], env=env, stdout=subprocess.PIPE,"
    " text=True)\n"
    "print(child.pid, child.stdout.readline().strip(), flush=True)\n"
    "time.sleep(60)\n"
)


def _gone(pid: int) -> bool:
    """Whether ``pid`` (not our child: watched in /proc) ends within ``EXIT_WAIT_S``."""
    t_end = time.monotonic() + EXIT_WAIT_S
    while time.monotonic() < t_end:
        try:
            with open(f"/proc/{pid}/stat") as f:
                if f.read().split()[2] == "Z":  # a zombie: ended, its parent gone before reaping
                    return True
        except FileNotFoundError:
            return True
        time.sleep(0.05)
    return False


@pytest.mark.subprocess
def test_a_child_ends_when_its_parent_is_killed_outright(tmp_path):
    mark = tmp_path / "sigterm"
    parent = subprocess.Popen([sys.executable, "-c", PARENT, CHILD, str(mark)], stdout=subprocess.PIPE, text=True)
    child_pid = None
    try:
        child_pid, arranged = parent.stdout.readline().split()
        child_pid = int(child_pid)
        assert arranged == "True"
        parent.kill()  # SIGKILL: none of the parent's clean-up runs
        parent.wait(EXIT_WAIT_S)
        assert _gone(child_pid), "the child outlived its killed parent"
        assert mark.read_text() == "SIGTERM"  # ended by the signal it asked for, through its handler
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


def test_the_variable_is_for_the_direct_child_alone(monkeypatch):
    """Removed from the child's own environment: a process the child starts (the daemon's, a simulator's) has
    another parent and must not take itself for an orphan."""
    import onboard.app.parent_watch as parent_watch

    monkeypatch.setattr(parent_watch, "_sigterm_on_parent_death", lambda: None)
    monkeypatch.setenv(PARENT_PID_ENV, str(os.getppid()))
    assert end_with_parent() is True
    assert PARENT_PID_ENV not in os.environ
