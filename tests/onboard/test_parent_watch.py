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


# the launcher of the real commands below: starts argv[2:] with its own PID in the environment and the child's
# output in the file argv[1] (a pipe would die with the launcher), says the child's PID, then waits to be killed
LAUNCHER = (
    "import os, subprocess, sys, time\n"
    f"env = {{**os.environ, {PARENT_PID_ENV!r}: str(os.getpid())}}\n"
    "log = open(sys.argv[1], 'w')\n"
    "child = subprocess.Popen(sys.argv[2:], env=env, stdout=log, stderr=subprocess.STDOUT)\n"
    "print(child.pid, flush=True)\n"
    "time.sleep(120)\n"
)
START_TIMEOUT_S = 60.0  # imports and the first frames on a busy 2-core machine


def _ends_with_its_killed_launcher(tmp_path, argv: list[str], ready: str) -> str:
    """Start ``argv`` from a launcher that asks for it to end with it, wait for ``ready`` in its output, SIGKILL the
    launcher and assert the command ends by itself; returns its output."""
    out = tmp_path / "child.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("IRTRACK_")}
    env.update(OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    launcher = subprocess.Popen(
        [sys.executable, "-c", LAUNCHER, str(out), *argv], stdout=subprocess.PIPE, text=True, env=env
    )
    child_pid = None
    gone = False
    try:
        child_pid = int(launcher.stdout.readline())
        t_end = time.monotonic() + START_TIMEOUT_S
        while ready not in out.read_text(errors="replace"):
            assert time.monotonic() < t_end, f"never ready ({ready!r}):\n{out.read_text(errors='replace')[-3000:]}"
            assert not _gone_now(child_pid), f"ended before the launcher:\n{out.read_text(errors='replace')[-3000:]}"
            time.sleep(0.1)
        launcher.kill()
        launcher.wait(EXIT_WAIT_S)
        assert _gone(child_pid), "outlived its killed launcher:\n" + out.read_text(errors="replace")[-3000:]
        gone = True
        return out.read_text(errors="replace")
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()
        if child_pid is not None and not gone:  # once gone, its PID may be another process's
            try:
                os.kill(child_pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def _gone_now(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] == "Z"
    except FileNotFoundError:
        return True


@pytest.mark.integration
def test_the_daemon_ends_cleanly_when_its_launcher_is_killed(tmp_path):
    """The daemon asks for it (a demo killed outright left it running, holding its ports): a clean stop by SIGTERM."""
    from groundsim.io.ports import free_tcp_port, free_udp_port

    argv = [sys.executable, "-m", "onboard", "--mavlink", f"udpin:127.0.0.1:{free_udp_port()}"]
    argv += ["--zenoh-connect", f"tcp/127.0.0.1:{free_tcp_port()}"]
    log = _ends_with_its_killed_launcher(tmp_path, argv, "onboard service started")
    assert "signal SIGTERM: shutting down" in log, log[-3000:]
    assert "Traceback" not in log, log[-3000:]


@pytest.mark.integration
def test_the_simulator_ends_cleanly_when_its_launcher_is_killed(tmp_path):
    from groundsim.io.ports import free_tcp_port

    argv = [sys.executable, "-m", "groundsim", "run", "--scenario", "p1", "--duration", "30", "--rate", "realtime"]
    argv += ["--no-render", "--mavlink", "udpout:127.0.0.1:9", "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}"]
    log = _ends_with_its_killed_launcher(tmp_path, argv, "/900, sim ")
    assert "Traceback" not in log, log[-3000:]
