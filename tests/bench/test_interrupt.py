"""Ctrl-C in the benchmarks (real processes on 127.0.0.1, SIGINT as a terminal sends it to its foreground
process group, or to the suite's PID alone): one line "interrupted: <what was kept>", exit code 130, no
traceback from the benchmark, its pool workers or the suite, and no process left behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.process_helpers import alive, descendants, kill_all

REPO = Path(__file__).resolve().parents[2]
EXIT_INTERRUPTED = 130
READY_TIMEOUT_S = 120.0  # a benchmark's first figures (imports, and bench.flight first, on a busy machine)
EXIT_TIMEOUT_S = 60.0  # from SIGINT to exit
GONE_TIMEOUT_S = 10.0  # the pool workers' exit after the benchmark's


class _Bench:
    """``python -m MODULE ARGS`` in a session of its own (so that a signal to its process group is a
    terminal's Ctrl-C), its stdout read line by line (so a test can wait for a line)."""

    def __init__(self, module: str, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", module, *args],
            cwd=REPO,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},  # its lines as they are printed, through the pipe
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        self.out: list[str] = []
        self.seen = threading.Event()
        self._needle = ""
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.out.append(line)
            if self._needle and self._needle in line:
                self.seen.set()

    def wait_for(self, needle: str) -> None:
        self._needle = needle
        if any(needle in line for line in self.out):
            self.seen.set()
        assert self.seen.wait(READY_TIMEOUT_S), (
            f"no {needle!r} within {READY_TIMEOUT_S} s:\n{''.join(self.out)[-3000:]}"
        )

    def interrupt(self, group: bool) -> tuple[int, str, str]:
        """SIGINT to the process group (a terminal's Ctrl-C) or to the command's PID alone; returns (exit
        code, stdout, stderr)."""
        if group:
            os.killpg(self.proc.pid, signal.SIGINT)
        else:
            self.proc.send_signal(signal.SIGINT)
        err = self.proc.stderr.read() if self.proc.wait(EXIT_TIMEOUT_S) is not None else ""
        self._reader.join(5.0)
        return self.proc.returncode, "".join(self.out), err


def _interrupted_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("interrupted:")]


def _wait_gone(pids: set[int]) -> list[int]:
    t_end = time.monotonic() + GONE_TIMEOUT_S
    while any(alive(p) for p in pids) and time.monotonic() < t_end:
        time.sleep(0.1)
    return [p for p in pids if alive(p)]


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize("group", [True, False], ids=["terminal", "suite-pid"])
def test_ctrl_c_in_the_suite_names_what_finished_stopped_and_did_not_run(group):
    bench = _Bench("bench", "flight", "imaging", "render")
    kids: set[int] = set()
    try:
        bench.wait_for("onboard.imaging benchmark: ")  # bench.flight done, bench.imaging past its imports
        kids = descendants(bench.proc.pid)
        assert kids, "bench.imaging runs in a process of its own"
        rc, out, err = bench.interrupt(group)
        assert rc == EXIT_INTERRUPTED, err
        assert _interrupted_lines(err) == [
            "interrupted: finished: flight; stopped part-way: imaging; not run: render;"
            " the figures printed above are kept"
        ], err
        assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
        assert "----- bench.imaging: " in out and "===== bench.render" not in out, out[-3000:]
        assert not _wait_gone(kids), "a benchmark outlived the interrupted suite"
    finally:
        kill_all([bench.proc.pid, *kids])


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_ctrl_c_in_a_benchmark_with_a_pool_stops_its_workers_without_a_traceback():
    bench = _Bench(
        "bench.estimator", "--verdict", "--seeds", "20", "--scenarios", "P1,P2", "--noises", "px0.3", "--workers", "2"
    )
    workers: set[int] = set()
    try:
        t_end = time.monotonic() + READY_TIMEOUT_S
        while len(workers) < 2 and time.monotonic() < t_end:  # its pool's two workers are forked
            workers |= descendants(bench.proc.pid)
            time.sleep(0.1)
        assert len(workers) >= 2, f"no pool within {READY_TIMEOUT_S} s"
        rc, out, err = bench.interrupt(group=True)
        assert rc == EXIT_INTERRUPTED, err
        assert _interrupted_lines(err) == [
            "interrupted: bench.estimator stopped part-way; the figures printed above are kept; no --json file written"
        ], err
        assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
        assert "verdict over" not in out  # stopped before its table
        assert not _wait_gone(workers), "pool workers outlived the interrupted benchmark"
    finally:
        kill_all([bench.proc.pid, *workers])
