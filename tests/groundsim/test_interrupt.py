"""Ctrl-C in the long commands (real processes, SIGINT as a terminal sends it; SIGTERM as a service manager or
``kill`` sends it): one line "interrupted: <what was kept>", exit code 130, no traceback from the pool's workers,
no worker left behind, even when the command alone was killed outright."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.process_helpers import WatchedCommand, descendants, kill_all, wait_gone

EXIT_INTERRUPTED = 130
READY_TIMEOUT_S = 60.0  # the command's first log line (imports on a busy machine)
EXIT_TIMEOUT_S = 60.0  # from SIGINT to exit
GONE_TIMEOUT_S = 10.0  # the workers' exit after the parent's
ORPHAN_GONE_S = 2.0  # a pool's processes after their command was signalled alone and exited (or was killed)
EVAL_ARGS = ("eval", "--scenario", "P1", "P2", "--seeds", "3", "--workers", "2", "--no-batch", "--no-progress")


def _groundsim(*args: str) -> WatchedCommand:
    """``python -m groundsim ARGS``, its stderr read line by line."""
    return WatchedCommand("groundsim", *args, watch="stderr")


def _wait_for_pool(cmd: WatchedCommand, workers: set[int], at_least: int, poll_s: float) -> None:
    """Once eval has said what it runs: adds its descendants to ``workers`` until there are ``at_least`` (or
    READY_TIMEOUT_S has passed); ``workers`` is the caller's, for its clean-up whatever happens here."""
    cmd.wait_for("eval: 2 scenario(s) x 3 seed(s)", READY_TIMEOUT_S)
    t_end = time.monotonic() + READY_TIMEOUT_S
    while len(workers) < at_least and time.monotonic() < t_end:
        workers |= descendants(cmd.proc.pid)
        time.sleep(poll_s)


def _interrupt(cmd: WatchedCommand, signum: int = signal.SIGINT) -> tuple[int, str, str]:
    """SIGINT to the command alone (as the terminal sends it to the foreground group, whose pool workers
    ignore it), or ``signum``; returns (exit code, stdout, stderr)."""
    return cmd.interrupt(group=False, exit_timeout_s=EXIT_TIMEOUT_S, signum=signum)


@pytest.mark.integration
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["sigint", "sigterm"])
def test_ctrl_c_or_sigterm_in_eval_keeps_the_finished_runs_and_exits_130(tmp_path, signum):
    """SIGTERM had ended eval at once (exit -15, no line, the finished runs' report not written)."""
    out = tmp_path / "eval"
    cmd = _groundsim(*EVAL_ARGS, "--out", str(out))
    workers: set[int] = set()
    try:
        _wait_for_pool(cmd, workers, 2, poll_s=0.1)  # the fork server and its two workers
        time.sleep(2.0)  # the workers are flying and rendering
        workers |= descendants(cmd.proc.pid)
        rc, stdout, stderr = _interrupt(cmd, signum)
        assert rc == EXIT_INTERRUPTED, stderr[-3000:]
        lines = [line for line in stderr.splitlines() if line.startswith("interrupted:")]
        assert len(lines) == 1 and " of 6 runs done; " in lines[0], stderr[-3000:]
        assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr[-3000:]
        if lines[0].startswith("interrupted: 0 of"):
            assert lines[0].endswith("nothing written")
        else:
            assert (out / "report.md").is_file() and str(out / "report.md") in lines[0]
        assert not wait_gone(workers, GONE_TIMEOUT_S), "pool workers outlived the interrupted eval"
    finally:
        kill_all([cmd.proc.pid, *workers])


@pytest.mark.integration
def test_ctrl_c_while_the_eval_pool_starts_is_one_line_without_a_traceback(tmp_path):
    """SIGINT once eval's fork server exists, while it starts the workers: one line, 130, no traceback from a
    worker the fork server was starting."""
    out = tmp_path / "eval"
    cmd = _groundsim(*EVAL_ARGS, "--out", str(out))
    workers: set[int] = set()
    try:
        _wait_for_pool(cmd, workers, 1, poll_s=0.01)  # the fork server: it is starting the workers
        rc, _, stderr = _interrupt(cmd)
        assert rc == EXIT_INTERRUPTED, stderr[-3000:]
        lines = [line for line in stderr.splitlines() if line.startswith("interrupted:")]
        # "0 of 6 runs done; nothing written" (or "nothing written" had it come before the pool)
        assert len(lines) == 1 and lines[0].endswith("nothing written"), stderr[-3000:]
        assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr[-3000:]
        assert not out.exists() or not (out / "report.md").exists()
    finally:
        kill_all([cmd.proc.pid, *workers])


@pytest.mark.integration
def test_ctrl_c_in_run_says_how_many_frames_were_sent_and_exits_130(tmp_path):
    truth = tmp_path / "truth.csv"
    cmd = _groundsim(
        "run", "--scenario", "p1", "--duration", "30", "--rate", "realtime", "--no-render", "--truth", str(truth),
        "--mavlink", "udpout:127.0.0.1:9",
    )  # fmt: skip
    try:
        cmd.wait_for("/900, sim ", READY_TIMEOUT_S)  # the first status line: frames are going out
        rc, _, stderr = _interrupt(cmd)
        assert rc == EXIT_INTERRUPTED, stderr[-3000:]
        lines = [line for line in stderr.splitlines() if line.startswith("interrupted:")]
        assert len(lines) == 1 and " of 900 frames sent; truth of those frames in " in lines[0], stderr[-3000:]
        assert "Traceback" not in stderr
        sent = int(lines[0].split()[1])
        assert len(truth.read_text().splitlines()) == sent + 1  # the header and one row per frame sent
    finally:
        kill_all([cmd.proc.pid])


def test_the_interrupted_line_names_the_recording_where_it_went(capsys):
    """--record onto an earlier recording goes to another name (r-2.mcap): the line says that one, not the name
    asked for, which holds the earlier recording."""
    import signal as signal_module
    from pathlib import Path
    from types import SimpleNamespace

    from groundsim.app.cli import _run_interrupted

    config = SimpleNamespace(truth_path=None, record_path=Path("r.mcap"), scenario=SimpleNamespace(is_fleet=False))
    report = SimpleNamespace(frames=10, frames_total=30, record_files=("r-2.mcap",))
    assert _run_interrupted([signal_module.SIGINT], config, report) == 130
    assert capsys.readouterr().err == "interrupted: 10 of 30 frames sent; recording in r-2.mcap\n"


@pytest.mark.integration
@pytest.mark.multicore
def test_sigterm_stops_a_dataset_as_ctrl_c_does_its_workers_too(tmp_path):
    """SIGTERM to the dataset command alone (not its group) while its two workers render: it stops as on Ctrl-C
    (one line, 130, its pool ended); it had ended at once, its workers rendering on into --out, then printing
    BrokenPipeError tracebacks."""
    out = tmp_path / "ds"
    err_path = tmp_path / "stderr.txt"
    args = ["dataset", "--seeds", "2", "--duration", "20", "--workers", "2", "--no-progress", "--out", str(out)]
    with open(err_path, "w") as err:  # a file, not a pipe: no wait on what the workers hold open
        proc = subprocess.Popen(
            [sys.executable, "-m", "groundsim", *args], cwd=Path(__file__).resolve().parents[2], stderr=err
        )
    pool: set[int] = set()
    try:
        t_end = time.monotonic() + READY_TIMEOUT_S
        while len({p.parents[1] for p in out.glob("*/img1/*.png")}) < 2 and time.monotonic() < t_end:
            pool |= descendants(proc.pid)  # both workers are rendering once both sequences have frames
            time.sleep(0.1)
        pool |= descendants(proc.pid)
        assert proc.poll() is None and len(pool) >= 3, err_path.read_text()[-3000:]  # fork server, 2 workers
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(EXIT_TIMEOUT_S)
        left = wait_gone(pool, ORPHAN_GONE_S)
        assert not left, f"alive {ORPHAN_GONE_S} s after the command exited: {left}"
        stderr = err_path.read_text()
        assert rc == EXIT_INTERRUPTED, stderr[-3000:]
        lines = [line for line in stderr.splitlines() if line.startswith("interrupted:")]
        assert len(lines) == 1 and " of 2 sequences written in " in lines[0], stderr[-3000:]
        assert "Traceback" not in stderr, stderr[-3000:]
    finally:
        kill_all([proc.pid, *pool])


def test_a_second_sigterm_while_the_finished_runs_are_scored_does_not_lose_them(tmp_path, monkeypatch, capsys):
    """The first SIGTERM stops the runs; a second while the finished ones are scored had escaped as a bare
    KeyboardInterrupt, and the command said 'interrupted: nothing written' (measured: two SIGTERMs back to back
    10 s into a P1 eval, '0 of 6 runs done; nothing written' where one signal kept 2 of 6)."""
    import groundsim.evaluation.eval as ev
    from groundsim.app.cli import main as cli_main
    from groundsim.evaluation.parallel import JobsInterrupted

    def first_run_then_sigterm(job, jobs, *args, **kwargs):
        done = [job(jobs[0])]
        try:
            signal.raise_signal(signal.SIGTERM)  # a service manager's stop as the second run starts
        except KeyboardInterrupt:
            raise JobsInterrupted(done + [None] * (len(jobs) - 1)) from None
        raise AssertionError("SIGTERM did not stop the eval")

    score_run = ev.score_run

    def second_sigterm_then_score(run):
        signal.raise_signal(signal.SIGTERM)  # the stop sent again, impatient
        return score_run(run)

    monkeypatch.setattr(ev, "run_jobs", first_run_then_sigterm)
    monkeypatch.setattr(ev, "score_run", second_sigterm_then_score)
    out = tmp_path / "eval"
    argv = ["eval", "--scenario", "P1", "--seeds", "2", "--duration", "2", "--workers", "1", "--no-progress"]
    assert cli_main([*argv, "--no-batch", "--out", str(out)]) == 130
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("interrupted:")]
    assert lines == [
        f"interrupted: 1 of 2 runs done; partial report in {out / 'report.md'}; MOT files in {out / 'mot'}"
    ]
    assert (out / "report.md").is_file()
