"""Ctrl-C in the benchmarks (real processes on 127.0.0.1, SIGINT as a terminal sends it to its foreground
process group, or to the suite's PID alone): one line "interrupted: <what was kept>", exit code 130, no
traceback from the benchmark, its pool workers or the suite, and no process left behind."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

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


SUITE_CASES = {"terminal": True, "suite-pid": False}  # SIGINT to the suite's process group, or to its PID alone


def _interrupt_the_suite(group: bool) -> dict:
    """``bench flight imaging render``, SIGINT once bench.imaging is past its imports (bench.flight done): the
    processes it had then (``kids``), its exit code, stdout and stderr, and those of ``kids`` still alive
    ``GONE_TIMEOUT_S`` after its exit (``left``).  No ``rc`` when it had no child to interrupt.  Every process is
    killed by PID at the end, whatever happened."""
    bench = _bench("bench", "flight", "imaging", "render")
    kids: set[int] = set()
    try:
        bench.wait_for("onboard.imaging benchmark, ", READY_TIMEOUT_S)
        kids = descendants(bench.proc.pid)
        if not kids:
            return {"kids": kids}
        rc, out, err = bench.interrupt(group, EXIT_TIMEOUT_S)
        return {"kids": kids, "rc": rc, "out": out, "err": err, "left": wait_gone(kids, GONE_TIMEOUT_S)}
    finally:
        kill_all([bench.proc.pid, *kids])


@pytest.fixture(scope="module")
def interrupted_suites():
    """Both cases of the test below at once, each suite in a session of its own and interrupted as soon as it is
    ready (one after the other, each case's bench.flight made the other wait): per case a future of
    :func:`_interrupt_the_suite`'s result (its ``result()`` raises what the case raised)."""
    pool = ThreadPoolExecutor(len(SUITE_CASES))
    yield {case: pool.submit(_interrupt_the_suite, group) for case, group in SUITE_CASES.items()}
    pool.shutdown(wait=True)  # each case kills its processes by PID whatever happens


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize("case", list(SUITE_CASES))
def test_ctrl_c_in_the_suite_names_what_finished_stopped_and_did_not_run(case, interrupted_suites):
    r = interrupted_suites[case].result()
    assert r["kids"], "bench.imaging runs in a process of its own"
    rc, out, err = r["rc"], r["out"], r["err"]
    assert rc == EXIT_INTERRUPTED, err
    assert _interrupted_lines(err) == [
        "interrupted: finished: flight; stopped part-way: imaging; not run: render; the figures printed above are kept"
    ], err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert "----- bench.imaging: " in out and "===== bench.render" not in out, out[-3000:]
    assert not r["left"], "a benchmark outlived the interrupted suite"


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
