"""The evaluation's worker set-up (:mod:`groundsim.evaluation.parallel`): quieting the run loggers is
undone afterwards, so an evaluation run inside a longer-lived process (a test session, a notebook, the
demo) does not silence that process's ``onboard`` INFO records for good."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from groundsim.app.cli import build_parser
from groundsim.app.eval_command import cmd_eval
from groundsim.evaluation.campaign import cmd_campaign
from groundsim.evaluation.dataset import cmd_dataset
from groundsim.evaluation.parallel import RUN_LOGGERS, pool_workers, quiet_run_logs
from onboard.core.errors import ConfigError, IrtrackError

EXTRA = "groundsim.world.truth"
NAMES = ("", *RUN_LOGGERS, EXTRA, "groundsim.evaluation.eval")  # "" is the root logger
EXAMPLE_SPEC = Path(__file__).resolve().parents[2] / "config" / "campaigns" / "example.yaml"


@pytest.fixture
def levels():
    """Every logger these tests touch at the level it had before them, afterwards; the root at INFO (the
    programs' default) and ``onboard`` at DEBUG meanwhile, so that a level left at WARNING shows."""
    saved = {n: logging.getLogger(n).level for n in NAMES}
    logging.getLogger().setLevel(logging.INFO)
    logging.getLogger("onboard").setLevel(logging.DEBUG)
    yield
    for n, level in saved.items():
        logging.getLogger(n).setLevel(level)


def _snapshot() -> dict[str, int]:
    return {n: logging.getLogger(n).level for n in NAMES}


def test_run_loggers_keep_warnings_only_inside_the_block_and_get_their_levels_back(levels):
    before = _snapshot()
    with quiet_run_logs(EXTRA, EXTRA):  # a name given twice still gets its own level back
        for n in (*RUN_LOGGERS, EXTRA):
            assert logging.getLogger(n).level == logging.WARNING, n
        assert not logging.getLogger("onboard.pipeline").isEnabledFor(logging.INFO)
    assert _snapshot() == before
    assert logging.getLogger("onboard").level == logging.DEBUG


def test_levels_come_back_when_the_block_raises(levels):
    before = _snapshot()
    with pytest.raises(KeyboardInterrupt), quiet_run_logs(EXTRA):
        raise KeyboardInterrupt
    assert _snapshot() == before


def test_at_debug_nothing_is_quieted(levels):
    logging.getLogger().setLevel(logging.DEBUG)
    before = _snapshot()
    with quiet_run_logs(EXTRA):
        assert _snapshot() == before
    assert _snapshot() == before


@pytest.mark.parametrize(
    "command, argv",
    [
        (cmd_eval, ["eval", "--seeds", "0"]),
        (cmd_dataset, ["dataset", "--seeds", "0"]),
        (cmd_campaign, ["campaign", "no-such-campaign.yaml"]),
    ],
    ids=["eval", "dataset", "campaign"],
)
def test_a_command_run_in_process_leaves_the_logger_levels_as_it_found_them(levels, tmp_path, command, argv):
    """The command handlers quiet the run loggers for their whole run; one that stops on a bad argument
    (after the loggers were quieted, before anything ran) shows that they are restored on every way out."""
    args = build_parser().parse_args([*argv, "--out", str(tmp_path / "out")])
    before = _snapshot()
    with pytest.raises(IrtrackError):
        command(args)
    assert _snapshot() == before
    assert logging.getLogger("onboard").isEnabledFor(logging.INFO)


def test_pool_workers_is_the_option_else_two_at_most(monkeypatch):
    assert pool_workers(3) == 3
    for cpus, expected in ((None, 1), (1, 1), (2, 2), (16, 2)):
        monkeypatch.setattr("os.cpu_count", lambda cpus=cpus: cpus)
        assert pool_workers(None) == expected
    with pytest.raises(ConfigError, match=r"^--workers: expected an integer >= 1, got 0$"):
        pool_workers(0)


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf"])
@pytest.mark.parametrize("argv", [["eval"], ["campaign", str(EXAMPLE_SPEC)]], ids=["eval", "campaign"])
def test_run_timeout_is_a_positive_finite_number_of_seconds(tmp_path, argv, value):
    args = build_parser().parse_args([*argv, "--out", str(tmp_path / "out"), f"--run-timeout={value}"])
    command = cmd_eval if argv[0] == "eval" else cmd_campaign
    with pytest.raises(ConfigError, match=r"^--run-timeout: expected a positive number of seconds, got "):
        command(args)
    assert not (tmp_path / "out").exists()


# a process that starts a pool of two workers on an hour's job each, says so, and waits
_POOL_OWNER = """
import time
from groundsim.evaluation.parallel import start_pool

pool, _ = start_pool(2, preload=(), progress=False)
for _ in range(2):
    pool.apply_async(time.sleep, (3600,))
print("started", flush=True)
time.sleep(3600)
"""
POOL_GONE_S = 2.0  # a pool's workers after their command was killed outright


@pytest.mark.integration
@pytest.mark.multicore
def test_pool_workers_end_with_a_command_killed_outright():
    """SIGKILL (an out-of-memory kill, a CI job's hard limit) runs none of the command's clean-up: its workers had
    gone on with their jobs, orphans, until those ended (a closed-loop campaign's case: minutes)."""
    import signal
    import subprocess
    import sys

    from tests.process_helpers import descendants, kill_all, repo_env, wait_gone

    proc = subprocess.Popen([sys.executable, "-c", _POOL_OWNER], env=repo_env(), stdout=subprocess.PIPE, text=True)
    pool: set[int] = set()
    try:
        assert proc.stdout is not None and proc.stdout.readline() == "started\n"
        pool = descendants(proc.pid)
        assert len(pool) >= 3, pool  # the fork server and its two workers
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        left = wait_gone(pool, POOL_GONE_S)
        assert not left, f"alive {POOL_GONE_S} s after their command was killed: {left}"
    finally:
        kill_all([proc.pid, *pool])


LOST_BOUND_S = 60.0  # hang guard: a pool that lost a worker had waited for ever


@pytest.mark.integration
@pytest.mark.multicore
def test_a_job_that_ends_its_worker_fails_alone_and_the_pool_ends():
    """A pool worker gone under its job (sys.exit or os._exit in foreign code) left that job pending for ever: the
    command never ended, and its terminate hung too.  Now the job is ``on_lost``'s result, the others are kept."""
    import time

    from groundsim.evaluation.parallel import run_jobs
    from tests.groundsim.plugin_faults import pool_job

    t0 = time.monotonic()
    out = run_jobs(pool_job, [1, "exit", "os_exit", 2], 2, preload=(), on_lost=lambda j, why: ("lost", j, why))
    assert time.monotonic() - t0 < LOST_BOUND_S
    assert out[0] == 10 and out[3] == 20
    for k, j in ((1, "exit"), (2, "os_exit")):
        assert out[k][:2] == ("lost", j) and "worker process" in out[k][2] and "ended" in out[k][2], out[k]


DEADLINE_BOUND_S = 10.0  # the hanging job sleeps 30 s: a deadline not enforced waits for all of it


@pytest.mark.integration
@pytest.mark.multicore
def test_a_job_past_its_deadline_is_lost_alone_and_its_worker_killed():
    """A plug-in that hung (a 60 s sleep in every add) made a 5 s eval run for hours: nothing set a deadline.
    Now a job running past ``deadline_s`` has its worker killed and is ``on_lost``'s result naming the deadline;
    the quick job's result is kept and no worker of the pool (the killed one's replacement included) is left."""
    import time

    from groundsim.evaluation.parallel import finish_pool, pool_results, start_pool
    from tests.groundsim.plugin_faults import pool_job
    from tests.process_helpers import kill_all, wait_gone

    t0 = time.monotonic()
    pool, _ = start_pool(2, preload=(), progress=False)
    pids = {p.pid for p in pool._pool}
    try:
        out = dict(pool_results(pool, pool_job, ["hang", 1], on_lost=lambda j, why: ("lost", j, why), deadline_s=1.0))
        pids |= {p.pid for p in pool._pool}
        finish_pool(pool)
    finally:
        pids |= {p.pid for p in pool._pool}
        left = wait_gone(pids, 5.0)
        kill_all(pids)
    assert time.monotonic() - t0 < DEADLINE_BOUND_S
    assert out[1] == 10
    assert out[0][:2] == ("lost", "hang") and "ran past the run deadline of 1 s" in out[0][2], out[0]
    assert not left, f"pool workers still alive: {left}"
