"""Daemon life cycle: SIGHUP (a closed terminal) is a clean exit.  Loopback only, bounded, cleanup by PID."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from groundsim.io.ports import free_tcp_port
from tests.integration_helpers import loopback_daemon_command

pytestmark = [pytest.mark.integration, pytest.mark.timeout(90)]

REPO = Path(__file__).resolve().parents[2]
START_BUDGET_S = 45.0  # imports + zenoh session on a loaded 2-core box
STOP_BUDGET_S = 5.0


def test_sighup_is_a_clean_exit(tmp_path):
    alive = tmp_path / "alive"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        loopback_daemon_command(free_tcp_port(), alive),
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        deadline = time.monotonic() + START_BUDGET_S
        while not alive.exists():
            assert proc.poll() is None, f"daemon died at start: {proc.stdout.read()}"
            assert time.monotonic() < deadline, "daemon did not start in time"
            time.sleep(0.1)
        proc.send_signal(signal.SIGHUP)
        rc = proc.wait(STOP_BUDGET_S)
        out = proc.stdout.read()
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(5)
    assert rc == 0, out
    assert "signal SIGHUP" in out and "Traceback" not in out
    assert not alive.exists()  # the liveness file is removed on a clean exit
