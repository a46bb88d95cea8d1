"""The processes a test started, found and ended by PID (Linux /proc): for the Ctrl-C tests, which check
that a command leaves no child or pool worker behind; and :class:`WatchedCommand`, such a command run with
one of its output streams read line by line."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

__all__ = ["WatchedCommand", "alive", "descendants", "kill_all", "repo_env", "run_module", "terminate", "wait_gone"]

REPO = Path(__file__).resolve().parents[1]


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


def wait_gone(pids: set[int], timeout_s: float) -> list[int]:
    """Those of ``pids`` still alive after up to ``timeout_s`` (polled every 0.1 s)."""
    t_end = time.monotonic() + timeout_s
    while any(alive(p) for p in pids) and time.monotonic() < t_end:
        time.sleep(0.1)
    return [p for p in pids if alive(p)]


def kill_all(pids) -> None:
    """SIGKILL each of ``pids`` still alive (a test's clean-up, whatever happened)."""
    for pid in pids:
        if alive(pid):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def repo_env() -> dict:
    """This process's environment for a child started from the repository's root: the repository on PYTHONPATH,
    one BLAS/OpenMP thread unless set (the pipeline is single-threaded by design)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("OMP_NUM_THREADS", "1")
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    return env


def run_module(module: str, *args: str, timeout_s: float, env: dict | None = None) -> subprocess.CompletedProcess:
    """``python -m MODULE ARGS`` to its end from the repository's root, output captured as text; in ``env``, by
    default :func:`repo_env`."""
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=REPO,
        env=repo_env() if env is None else env,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


def terminate(proc: subprocess.Popen, timeout_s: float) -> int:
    """SIGTERM to ``proc``, SIGKILL if it has not exited within ``timeout_s``; its exit code (negative: the
    signal that ended it, so a test that wants 0 sees a hang as a failure and leaves no process behind)."""
    proc.terminate()
    try:
        return proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
    return proc.wait()


class WatchedCommand:
    """``python -m MODULE ARGS`` from the repository's root, with one stream (``watch``: ``"stdout"`` or
    ``"stderr"``) read line by line into :attr:`lines` (so that a test can wait for a line) and the other read
    whole once it has exited; ``new_session``: in a session of its own, so that a signal to its process group
    is a terminal's Ctrl-C."""

    def __init__(self, module: str, *args: str, watch: str = "stderr", new_session: bool = False) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", module, *args],
            cwd=REPO,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},  # its lines as they are printed, through the pipe
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=new_session,
        )
        self._watched, self._other = (
            (self.proc.stdout, self.proc.stderr) if watch == "stdout" else (self.proc.stderr, self.proc.stdout)
        )
        self._watch = watch
        self.lines: list[str] = []
        self.seen = threading.Event()
        self._needle = ""
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self._watched:
            self.lines.append(line)
            if self._needle and self._needle in line:
                self.seen.set()

    def wait_for(self, needle: str, timeout_s: float) -> None:
        """Until a line of the watched stream contains ``needle``; fails the test after ``timeout_s``."""
        self._needle = needle
        if any(needle in line for line in self.lines):
            self.seen.set()
        assert self.seen.wait(timeout_s), f"no {needle!r} within {timeout_s} s:\n{''.join(self.lines)[-3000:]}"

    def kill(self) -> None:
        """SIGKILL the command if it still runs, and reap it (a test's clean-up, whatever happened)."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)

    def interrupt(self, group: bool, exit_timeout_s: float, signum: int = signal.SIGINT) -> tuple[int, str, str]:
        """SIGINT (or ``signum``) to the process group (a terminal's Ctrl-C; ``new_session`` needed) or to the
        command's PID alone; waits up to ``exit_timeout_s`` for its exit; returns (exit code, stdout, stderr)."""
        if group:
            os.killpg(self.proc.pid, signum)
        else:
            self.proc.send_signal(signum)
        other = self._other.read() if self.proc.wait(exit_timeout_s) is not None else ""
        self._reader.join(5.0)
        watched = "".join(self.lines)
        out, err = (watched, other) if self._watch == "stdout" else (other, watched)
        return self.proc.returncode, out, err
