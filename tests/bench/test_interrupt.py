"""Ctrl-C in the benchmarks (real processes on 127.0.0.1, SIGINT as a terminal sends it to its foreground
process group, or to the suite's PID alone): one line "interrupted: <what was kept>", exit code 130, no
traceback from the benchmark, its pool workers or the suite, and no process left behind."""

from __future__ import annotations

import time

import pytest

from tests.process_helpers import WatchedCommand, descendants, kill_all, wait_gone

EXIT_INTERRUPTED = 130
READY_TIMEOUT_S = 120.0  # a benchmark's first figures (imports, and bench.flight first, on a busy machine)
EXIT_TIMEOUT_S = 60.0  # from SIGINT to exit
GONE_TIMEOUT_S = 10.0  # the pool workers' exit after the benchmark's


def _bench(module: str, *args: str) -> WatchedCommand:
    """``python -m MODULE ARGS`` in a session of its own (so that a signal to its process group is a
    terminal's Ctrl-C), its stdout read line by line (so a test can wait for a line)."""
    return WatchedCommand(module, *args, watch="stdout", new_session=True)


def _interrupted_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("interrupted:")]


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize("group", [True, False], ids=["terminal", "suite-pid"])
def test_ctrl_c_in_the_suite_names_what_finished_stopped_and_did_not_run(group):
    bench = _bench("bench", "flight", "imaging", "render")
    kids: set[int] = set()
    try:
        # bench.flight done, bench.imaging past its imports
        bench.wait_for("onboard.imaging benchmark: ", READY_TIMEOUT_S)
        kids = descendants(bench.proc.pid)
        assert kids, "bench.imaging runs in a process of its own"
        rc, out, err = bench.interrupt(group, EXIT_TIMEOUT_S)
        assert rc == EXIT_INTERRUPTED, err
        assert _interrupted_lines(err) == [
            "interrupted: finished: flight; stopped part-way: imaging; not run: render;"
            " the figures printed above are kept"
        ], err
        assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
        assert "----- bench.imaging: " in out and "===== bench.render" not in out, out[-3000:]
        assert not wait_gone(kids, GONE_TIMEOUT_S), "a benchmark outlived the interrupted suite"
    finally:
        kill_all([bench.proc.pid, *kids])


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_ctrl_c_in_a_benchmark_with_a_pool_stops_its_workers_without_a_traceback():
    bench = _bench(
        "bench.estimator", "--verdict", "--seeds", "20", "--scenarios", "P1,P2", "--noises", "px0.3", "--workers", "2"
    )
    workers: set[int] = set()
    try:
        t_end = time.monotonic() + READY_TIMEOUT_S
        while len(workers) < 2 and time.monotonic() < t_end:  # its pool's two workers are forked
            workers |= descendants(bench.proc.pid)
            time.sleep(0.1)
        assert len(workers) >= 2, f"no pool within {READY_TIMEOUT_S} s"
        rc, out, err = bench.interrupt(group=True, exit_timeout_s=EXIT_TIMEOUT_S)
        assert rc == EXIT_INTERRUPTED, err
        assert _interrupted_lines(err) == [
            "interrupted: bench.estimator stopped part-way; the figures printed above are kept; no --json file written"
        ], err
        assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
        assert "verdict over" not in out  # stopped before its table
        assert not wait_gone(workers, GONE_TIMEOUT_S), "pool workers outlived the interrupted benchmark"
    finally:
        kill_all([bench.proc.pid, *workers])
