"""Ctrl-C in the long commands (real processes, SIGINT as a terminal sends it): one line "interrupted: <what
was kept>", exit code 130, no traceback from the pool's workers, no worker left behind."""

from __future__ import annotations

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
READY_TIMEOUT_S = 60.0  # the command's first log line (imports on a busy machine)
EXIT_TIMEOUT_S = 60.0  # from SIGINT to exit
GONE_TIMEOUT_S = 10.0  # the workers' exit after the parent's


class _Command:
    """``python -m groundsim ARGS`` with stderr read line by line (so a test can wait for a line)."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "groundsim", *args],
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.err: list[str] = []
        self.seen = threading.Event()
        self._needle = ""
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.err.append(line)
            if self._needle and self._needle in line:
                self.seen.set()

    def wait_for(self, needle: str, timeout_s: float) -> None:
        self._needle = needle
        if any(needle in line for line in self.err):
            self.seen.set()
        assert self.seen.wait(timeout_s), f"no {needle!r} within {timeout_s} s:\n{''.join(self.err)[-3000:]}"

    def interrupt(self, workers: set[int]) -> tuple[int, str, str]:
        """SIGINT to the command alone (as the terminal sends it to the foreground group, whose pool workers
        ignore it); returns (exit code, stdout, stderr)."""
        self.proc.send_signal(signal.SIGINT)
        out = self.proc.stdout.read() if self.proc.wait(EXIT_TIMEOUT_S) is not None else ""
        self._reader.join(5.0)
        return self.proc.returncode, out, "".join(self.err)

    def kill(self, pids: set[int]) -> None:
        kill_all([self.proc.pid, *pids])


@pytest.mark.integration
def test_ctrl_c_in_eval_keeps_the_finished_runs_and_exits_130(tmp_path):
    out = tmp_path / "eval"
    cmd = _Command(
        "eval", "--scenario", "P1", "P2", "--seeds", "3", "--workers", "2", "--no-batch", "--no-progress",
        "--out", str(out),
    )  # fmt: skip
    workers: set[int] = set()
    try:
        cmd.wait_for("eval: 2 scenario(s) x 3 seed(s)", READY_TIMEOUT_S)
        t_end = time.monotonic() + READY_TIMEOUT_S
        while len(workers) < 2 and time.monotonic() < t_end:  # the fork server and its two workers
            workers |= descendants(cmd.proc.pid)
            time.sleep(0.1)
        time.sleep(2.0)  # the workers are flying and rendering
        workers |= descendants(cmd.proc.pid)
        rc, stdout, stderr = cmd.interrupt(workers)
        assert rc == EXIT_INTERRUPTED, stderr[-3000:]
        lines = [line for line in stderr.splitlines() if line.startswith("interrupted:")]
        assert len(lines) == 1 and " of 6 runs done; " in lines[0], stderr[-3000:]
        assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr[-3000:]
        if lines[0].startswith("interrupted: 0 of"):
            assert lines[0].endswith("nothing written")
        else:
            assert (out / "report.md").is_file() and str(out / "report.md") in lines[0]
        t_end = time.monotonic() + GONE_TIMEOUT_S
        while any(alive(p) for p in workers) and time.monotonic() < t_end:
            time.sleep(0.1)
        assert not [p for p in workers if alive(p)], "pool workers outlived the interrupted eval"
    finally:
        cmd.kill(workers)


@pytest.mark.integration
def test_ctrl_c_while_the_eval_pool_starts_is_one_line_without_a_traceback(tmp_path):
    """SIGINT once eval's fork server exists, while it starts the workers: one line, 130, no traceback from a
    worker the fork server was starting."""
    out = tmp_path / "eval"
    cmd = _Command(
        "eval", "--scenario", "P1", "P2", "--seeds", "3", "--workers", "2", "--no-batch", "--no-progress",
        "--out", str(out),
    )  # fmt: skip
    workers: set[int] = set()
    try:
        cmd.wait_for("eval: 2 scenario(s) x 3 seed(s)", READY_TIMEOUT_S)
        t_end = time.monotonic() + READY_TIMEOUT_S
        while not workers and time.monotonic() < t_end:  # the fork server: it is starting the workers
            workers |= descendants(cmd.proc.pid)
            time.sleep(0.01)
        rc, _, stderr = cmd.interrupt(workers)
        assert rc == EXIT_INTERRUPTED, stderr[-3000:]
        lines = [line for line in stderr.splitlines() if line.startswith("interrupted:")]
        # "0 of 6 runs done; nothing written" (or "nothing written" had it come before the pool)
        assert len(lines) == 1 and lines[0].endswith("nothing written"), stderr[-3000:]
        assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr[-3000:]
        assert not out.exists() or not (out / "report.md").exists()
    finally:
        cmd.kill(workers)


@pytest.mark.integration
def test_ctrl_c_in_run_says_how_many_frames_were_sent_and_exits_130(tmp_path):
    truth = tmp_path / "truth.csv"
    cmd = _Command(
        "run", "--scenario", "p1", "--duration", "30", "--rate", "realtime", "--no-render", "--truth", str(truth),
        "--mavlink", "udpout:127.0.0.1:9",
    )  # fmt: skip
    try:
        cmd.wait_for("/900, sim ", READY_TIMEOUT_S)  # the first status line: frames are going out
        rc, _, stderr = cmd.interrupt(set())
        assert rc == EXIT_INTERRUPTED, stderr[-3000:]
        lines = [line for line in stderr.splitlines() if line.startswith("interrupted:")]
        assert len(lines) == 1 and " of 900 frames sent; truth of those frames in " in lines[0], stderr[-3000:]
        assert "Traceback" not in stderr
        sent = int(lines[0].split()[1])
        assert len(truth.read_text().splitlines()) == sent + 1  # the header and one row per frame sent
    finally:
        cmd.kill(set())
