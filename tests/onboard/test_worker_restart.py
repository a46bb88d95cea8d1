"""A dead estimator worker is replaced with its window rebuilt (a crash costs a gap, not the track).

The estimator interface (:class:`onboard.app.estimator_worker.ProcessEstimator`) is driven directly with
synthetic observations of a reference scenario (:func:`groundsim.evaluation.synth.synthesize_scenario`); the
worker is killed with SIGKILL.  Waits are bounded (``RESULT_WAIT_S``); how long the replacement
takes in wall time is printed (``pytest -s``), not asserted.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time

import numpy as np
import pytest

from onboard.app import estimator_worker
from onboard.app.config import OnboardConfig
from onboard.app.estimator_worker import SNAPSHOT_PERIOD_S, ProcessEstimator
from onboard.app.locked_counter import LockedCounter
from onboard.app.status_sections import estimator_label
from onboard.pipeline.frame_pipeline import make_estimator
from tests.process_helpers import alive, wait_gone

RESULT_WAIT_S = 30.0  # upper bound of one wait for the worker's own estimate (spawn + one model selection)
JOIN_S = 10.0  # upper bound for a SIGKILLed child to be reaped
FRAMES_BEFORE_KILL = 240  # 8 s at 30 Hz: the window holds estimates before the kill
HUNG_FRAMES_BEFORE_STOP = 30  # a worker that has rows, answered: no estimate needed to judge a hang
HONEST_SIGMAS = 4.0  # the rebuilt estimate is within this many reported sigma (sqrt trace P) of the truth


pytestmark = pytest.mark.usefixtures("one_blas_thread")


@pytest.fixture(scope="module")
def scene(p3_px03_flight):
    return p3_px03_flight


def _add(pe, obs, K, i):
    return pe.add(obs.t_s[i], obs.uv_px[i], K, obs.p_cam_ned_m[i], obs.q_ned_from_cam[i])


def _kill(pe: ProcessEstimator) -> None:
    pid = pe.pid
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    pe._proc.join(JOIN_S)  # reap it, bounded: the next add must find it dead
    assert pe._proc.exitcode == -signal.SIGKILL


def _started(pe: ProcessEstimator) -> None:
    """Wait (bounded) until the replacement being spawned is there for the next add to take (a spawn that was
    done when the frame looked was taken by it already)."""
    starting = pe._starting
    if starting is not None:
        starting.thread.join(JOIN_S)
        assert not starting.thread.is_alive()


def _first_worker(pe: ProcessEstimator) -> None:
    """Wait (bounded) for the first worker, which the constructor spawns on a thread, and take it as the next frame
    would."""
    _started(pe)
    assert pe._adopt_started(0.0) and pe.pid is not None


def _fill_window(pe, obs, K) -> None:
    """The first FRAMES_BEFORE_KILL observations added, the last one answered with an estimate."""
    for i in range(FRAMES_BEFORE_KILL):
        last = _add(pe, obs, K, i)
    assert last is not None


def _own_estimate(pe, obs, K, i):
    """add() observation i; returns (estimate, whether it was the worker's own result, not a propagation)."""
    late = pe.late_results
    est = _add(pe, obs, K, i)
    return est, pe.late_results == late


@pytest.fixture(scope="module")
def never_killed(scene, one_blas_thread) -> list:
    """The estimates of the same estimator in this process, never interrupted, for the observations up to
    ``FRAMES_BEFORE_KILL + 9``: what the test below compares each case's worker with (computed once for both
    cases: it is deterministic, and each case had run its own, as much CPU as its worker's)."""
    K, _truth, obs = scene
    reference = make_estimator(OnboardConfig())
    return [_add(reference, obs, K, i) for i in range(FRAMES_BEFORE_KILL + 10)]


@pytest.mark.integration
@pytest.mark.parametrize("with_snapshot", [True, False], ids=["restored-state", "rebuilt-window"])
def test_killed_worker_is_replaced_and_the_next_observation_gets_a_3d_estimate(
    scene, never_killed, caplog, with_snapshot
):
    """After SIGKILL the very next observation is answered by the new worker (0 observations of refill;
    the old behaviour needed min_frames / min_span_s of new ones), over the same window rows as a
    worker that was never killed.  From the dead worker's last state (snapshot + the rows after it),
    the answer is exactly the never-killed worker's; without a snapshot the window is rebuilt cold."""
    K, truth, obs = scene
    counter = LockedCounter(logger=logging.getLogger("onboard.rejects"))
    pe = ProcessEstimator(OnboardConfig(), counter, result_wait_s=RESULT_WAIT_S)
    try:
        for i in range(FRAMES_BEFORE_KILL):
            est = _add(pe, obs, K, i)
        assert est is not None, "no estimate before the kill: the scene is too short"
        if with_snapshot:
            assert pe._snapshot is not None and obs.t_s[FRAMES_BEFORE_KILL] - pe._snapshot[0] <= SNAPSHOT_PERIOD_S + 0.1
        else:
            pe._snapshot = None  # as before the first snapshot: the cold rebuild
        old_pid = pe.pid
        _kill(pe)
        t0 = time.monotonic()
        with caplog.at_level(logging.WARNING, logger="onboard.rejects"):
            est, own = _own_estimate(pe, obs, K, FRAMES_BEFORE_KILL)
        restart_s = time.monotonic() - t0
        print(
            f"\nworker replaced ({'restored state' if with_snapshot else 'cold rebuild'}): first own estimate "
            f"{restart_s:.3f} s after the kill was noticed"
        )
        ref = never_killed[FRAMES_BEFORE_KILL]
        assert own and est is not None
        assert est.t_s == obs.t_s[FRAMES_BEFORE_KILL]
        assert est.window_frames == ref.window_frames  # the whole window, not a fresh one
        if with_snapshot:
            assert np.array_equal(est.p_ned_m, ref.p_ned_m) and np.array_equal(est.cov_p_ned_m2, ref.cov_p_ned_m2)
        err_m = float(np.linalg.norm(est.p_ned_m - truth.p_target_ned_m[FRAMES_BEFORE_KILL]))
        assert err_m <= HONEST_SIGMAS * float(np.sqrt(np.trace(est.cov_p_ned_m2)))
        assert pe.pid != old_pid and pe.restarts == 1
        assert counter["estimator_restart"] == 1 and counter["estimator_error"] == 0
        lines = [r.getMessage() for r in caplog.records if "estimator_restart" in r.getMessage()]
        assert len(lines) == 1 and "exit code -9" in lines[0], lines
        # and it keeps going: the next observations get their own estimates as before
        for i in range(FRAMES_BEFORE_KILL + 1, FRAMES_BEFORE_KILL + 10):
            est, own = _own_estimate(pe, obs, K, i)
            ref = never_killed[i]
            assert own and est is not None and est.window_frames == ref.window_frames
            if with_snapshot:
                assert np.array_equal(est.p_ned_m, ref.p_ned_m)
        assert counter["estimator_restart"] == 1
    finally:
        pe.close()


@pytest.mark.integration
def test_while_the_worker_restarts_the_newest_estimate_is_propagated(scene):
    """With the daemon's short result wait, the frames right after the kill are not left without 3-D:
    the last estimate before the kill is propagated (as when the worker is busy) until the new
    worker answers.  Prints how many 30 Hz frames that took; asserts only that the worker's own
    estimates come back within a bounded number of frames."""
    K, truth, obs = scene
    counter = LockedCounter()
    pe = ProcessEstimator(OnboardConfig(), counter, result_wait_s=RESULT_WAIT_S)
    try:
        _fill_window(pe, obs, K)
        pe.result_wait_s = 1.0 / 30.0  # now at most one frame period per observation, like a 30 Hz feed
        _kill(pe)
        first_own, propagated, none = None, 0, 0
        t0 = time.monotonic()
        deadline = t0 + RESULT_WAIT_S
        i = FRAMES_BEFORE_KILL
        while first_own is None and time.monotonic() < deadline and i < len(obs.t_s):
            est, own = _own_estimate(pe, obs, K, i)
            if own and est is not None:
                first_own = i
            elif est is not None:
                assert est.t_s == obs.t_s[i]
                propagated += 1
            else:
                none += 1
            i += 1
        assert first_own is not None, f"no own estimate within {RESULT_WAIT_S} s after the kill"
        frames = first_own - FRAMES_BEFORE_KILL
        print(
            f"\nafter the kill: {frames} frames ({frames / 30.0:.2f} s at 30 Hz, {time.monotonic() - t0:.2f} s wall) "
            f"until the new worker's own estimate; {propagated} propagated, {none} without 3-D"
        )
        assert counter["estimator_restart"] == 1
    finally:
        pe.close()


@pytest.mark.integration
def test_a_crash_loop_backs_off_instead_of_spawning_a_process_per_frame(scene):
    """A worker that dies before answering anything makes the next replacement wait (fake clock),
    1 s then doubling; observations are still kept for it; each death is counted once.  A worker
    that had answered is replaced at once."""
    K, truth, obs = scene
    now = [100.0]
    counter = LockedCounter(clock=lambda: now[0])
    pe = ProcessEstimator(OnboardConfig(), counter, result_wait_s=0.0, clock=lambda: now[0])
    try:
        _first_worker(pe)
        _kill(pe)  # died before answering: replaced after the first back-off
        assert _add(pe, obs, K, 0) is None
        assert pe.restarts == 1 and pe.pid is None and pe._backoff_s == ProcessEstimator.RESTART_BACKOFF_MIN_S
        for i in range(1, 5):
            assert _add(pe, obs, K, i) is None
        assert pe.pid is None and counter["estimator_restart"] == 1  # counted once per death, not per frame
        now[0] += ProcessEstimator.RESTART_BACKOFF_MIN_S
        _add(pe, obs, K, 5)  # the replacement is spawned; returns at once (result_wait_s = 0)
        _started(pe)
        _add(pe, obs, K, 6)  # taken by the next frame; nothing answered yet
        assert pe.pid is not None and pe.restarts == 1
        _kill(pe)  # dead before answering again: the back-off doubles
        _add(pe, obs, K, 7)
        assert pe.pid is None and pe.restarts == 2 and pe._backoff_s == 2 * ProcessEstimator.RESTART_BACKOFF_MIN_S
        now[0] += 2 * ProcessEstimator.RESTART_BACKOFF_MIN_S
        pe.result_wait_s = RESULT_WAIT_S
        est, own = _own_estimate(pe, obs, K, 8)
        assert pe.pid is not None and own and est is None  # the new worker answered (9 rows: no estimate yet)
        _kill(pe)  # this one had answered: replaced on the next observation, no back-off
        est, own = _own_estimate(pe, obs, K, 9)
        assert pe.pid is not None and own and pe.restarts == 3 and pe._backoff_s == 0.0
        assert counter["estimator_restart"] == 3 and counter["estimator_error"] == 0
    finally:
        pe.close()


def _children_named(name: str) -> list[int]:
    """Live (not zombie) child processes of this process whose command line is multiprocessing's ``name``."""
    import multiprocessing

    return [p.pid for p in multiprocessing.active_children() if p.name == name and p.is_alive()]


def _fork_server_pid() -> int | None:
    """The estimator workers' fork server (None: none started yet in this process)."""
    from multiprocessing import forkserver

    return forkserver._forkserver._forkserver_pid


def _kill_fork_server() -> None:
    """SIGKILL the estimator workers' fork server and wait (bounded) until it is dead, unreaped: multiprocessing
    reaps it itself when it finds it gone and starts another."""
    pid = _fork_server_pid()
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + JOIN_S
    while time.monotonic() < deadline:
        with open(f"/proc/{pid}/stat") as f:
            if f.read().rsplit(")", 1)[1].split()[0] == "Z":
                return
        time.sleep(0.01)
    raise AssertionError(f"fork server {pid} still running {JOIN_S} s after SIGKILL")


@pytest.mark.integration
def test_a_fork_server_gone_with_the_worker_is_started_again_without_holding_the_frames(scene):
    """When the fork server is gone too, the replacement waits for a new one, which imports the estimator's
    modules first (a second or more of CPU).  That start runs on a thread: the frame that found the worker dead
    returns at once with the newest estimate carried to it, and a later frame takes the new worker, which
    restores the window and answers with its own estimate."""
    K, truth, obs = scene
    counter = LockedCounter()
    pe = ProcessEstimator(OnboardConfig(), counter, result_wait_s=RESULT_WAIT_S)
    try:
        _fill_window(pe, obs, K)
        _kill(pe)
        _kill_fork_server()
        pe.result_wait_s = 0.0
        late = pe.late_results
        est = _add(pe, obs, K, FRAMES_BEFORE_KILL)
        assert pe.pid is None and pe._starting is not None and pe._starting.thread.is_alive()
        assert est is not None and pe.late_results == late + 1  # carried from the newest estimate
        _started(pe)
        pe.result_wait_s = RESULT_WAIT_S
        est, own = _own_estimate(pe, obs, K, FRAMES_BEFORE_KILL + 1)
        assert pe.pid is not None and own and est is not None
        assert pe.restarts == 1 and counter["estimator_restart"] == 1 and counter["estimator_error"] == 0
    finally:
        pe.close()


@pytest.mark.integration
def test_close_while_a_replacement_is_being_started_leaves_no_worker_running(scene):
    """close() during the replacement's start waits for it briefly and stops the fork server still importing its
    preload (it would outlive the daemon): no worker is made, none is left running, nor the fork server."""
    K, truth, obs = scene
    now = [100.0]
    pe = ProcessEstimator(OnboardConfig(), LockedCounter(), result_wait_s=0.0, clock=lambda: now[0])
    _first_worker(pe)
    _kill(pe)
    _kill_fork_server()
    _add(pe, obs, K, 0)  # it had not answered: the crash back-off first
    now[0] += ProcessEstimator.RESTART_BACKOFF_MIN_S
    _add(pe, obs, K, 1)
    starting = pe._starting
    assert starting is not None and starting.thread.is_alive()
    fork_server = _fork_server_pid()
    pe.close()  # the daemon's timeout: it does not wait for the fork server
    starting.thread.join(JOIN_S)
    assert not starting.thread.is_alive() and starting.worker is None and starting.error is not None
    assert fork_server is not None and wait_gone({fork_server}, JOIN_S) == []
    pids = _children_named("irtrack-estimator")
    assert pids == [], f"estimator workers left running after close(): {pids}"


def _without_fork_server() -> None:
    """The next worker needs a new fork server, which imports its preload first (a second or more)."""
    if _fork_server_pid() is not None and alive(_fork_server_pid()):
        _kill_fork_server()


@pytest.mark.integration
def test_the_first_worker_is_started_beside_the_frames_and_gets_the_rows_that_came_first(scene, never_killed):
    """The constructor does not wait for the first worker (its fork server imports for a second or more): it
    returns with none, the rows meanwhile are carried and kept, and the frame that takes the worker hands it the
    window, so that its first answer is over the same rows as a worker that was there from the start."""
    K, truth, obs = scene
    _without_fork_server()
    counter = LockedCounter()
    pe = ProcessEstimator(OnboardConfig(), counter, result_wait_s=0.0)
    try:
        assert pe.pid is None and pe._starting is not None  # the daemon's start goes on meanwhile
        # the status says so: until the worker is there a first position comes later than it will
        assert pe.starting and estimator_label("sliding window (process)", pe).endswith(", worker starting")
        for i in range(FRAMES_BEFORE_KILL):
            _add(pe, obs, K, i)
        _started(pe)
        assert not pe.starting and estimator_label("sliding window (process)", pe) == "sliding window (process)"
        pe.result_wait_s = RESULT_WAIT_S
        est, own = _own_estimate(pe, obs, K, FRAMES_BEFORE_KILL)
        assert own and est is not None and pe.pid is not None
        assert est.window_frames == never_killed[FRAMES_BEFORE_KILL].window_frames
        assert pe.start_error is None and pe.restarts == 0 and counter.total == 0
    finally:
        pe.close()


@pytest.mark.integration
def test_close_while_the_first_worker_is_started_leaves_no_process_running():
    """A daemon stopped during its start (SIGTERM right after it began serving) closes its estimator while the
    fork server still imports: that fork server is stopped, not left to outlive the daemon, and no worker is made."""
    _without_fork_server()
    pe = ProcessEstimator(OnboardConfig(), LockedCounter(), result_wait_s=0.0)
    starting, fork_server = pe._starting, _fork_server_pid()
    assert starting is not None and fork_server is not None
    pe.close()
    starting.thread.join(JOIN_S)
    assert not starting.thread.is_alive() and starting.worker is None
    assert wait_gone({fork_server}, JOIN_S) == []  # killed (this process holds its pipe: it would run on)
    assert _children_named("irtrack-estimator") == []


@pytest.mark.integration
def test_close_before_the_start_thread_reaches_the_fork_server_leaves_no_fork_server_running(monkeypatch):
    """close() kills the fork server while the start thread is still on its way to it (pickling the worker's config
    on a loaded core, before proc.start() connects): multiprocessing finds it dead there and starts another, which
    the thread's worker is forked from.  Before, close() had returned and that new fork server ran on (the very
    thing close() kills the first one for); now the thread that finds the estimator closed stops it too."""
    _without_fork_server()
    reached = threading.Event()
    go = threading.Event()
    start_fork_server = estimator_worker._start_fork_server

    def held_in_the_thread() -> None:
        if threading.current_thread().name == "irtrack-estimator-start":
            reached.set()
            assert go.wait(JOIN_S)
        start_fork_server()

    monkeypatch.setattr(estimator_worker, "_start_fork_server", held_in_the_thread)
    pe = ProcessEstimator(OnboardConfig(), LockedCounter(), result_wait_s=0.0)
    starting, first = pe._starting, _fork_server_pid()
    assert starting is not None and first is not None and reached.wait(JOIN_S)
    pe.close()
    assert wait_gone({first}, JOIN_S) == []
    go.set()
    starting.thread.join(RESULT_WAIT_S)
    assert not starting.thread.is_alive() and starting.worker is None
    later = _fork_server_pid()
    assert later is None or wait_gone({later}, JOIN_S) == [], f"fork server {later} left running after close()"
    assert _children_named("irtrack-estimator") == []


def test_a_first_worker_that_cannot_be_started_is_counted_and_named(monkeypatch, scene):
    """A first worker that cannot be started (its fork server failed) raised from the constructor, which the daemon
    waited on before serving; spawned beside the start now, it is counted on the next frame, as a replacement that
    cannot be started is, and start_error says why (the daemon ends on it: OnboardService.run)."""
    K, truth, obs = scene

    def no_fork(self):
        raise OSError("fork server: no such interpreter")

    monkeypatch.setattr(ProcessEstimator, "_spawn", no_fork)
    monkeypatch.setattr(estimator_worker, "_start_fork_server", lambda: None)  # no process at all
    counter = LockedCounter()
    pe = ProcessEstimator(OnboardConfig(), counter, result_wait_s=0.0)
    try:
        _started(pe)
        assert isinstance(pe.start_error, OSError) and "no such interpreter" in str(pe.start_error)
        assert _add(pe, obs, K, 0) is None and pe.pid is None
        assert counter["estimator_error"] == 1 and pe.restarts == 0
    finally:
        pe.close()


@pytest.mark.integration
def test_frames_the_worker_would_not_keep_are_answered_here_with_its_numbers(scene):
    """Half the frames of a 30 Hz camera are not kept by the window (min_spacing_s): the worker would only
    carry its newest estimate to them.  The parent does that itself once the worker's answer to the newest
    kept frame is in: every answer equals the in-process estimator's, bit for bit, without the round trip."""
    K, truth, obs = scene
    cfg = OnboardConfig()
    inline = make_estimator(cfg)
    pe = ProcessEstimator(cfg, LockedCounter(), result_wait_s=RESULT_WAIT_S)
    try:
        n, skipped_before_first = 150, None
        for i in range(n):
            want = _add(inline, obs, K, i)
            got = _add(pe, obs, K, i)
            assert (got is None) == (want is None), i
            if want is not None:
                if skipped_before_first is None:
                    skipped_before_first = inline.stats["skipped"]
                np.testing.assert_array_equal(got.p_ned_m, want.p_ned_m)
                np.testing.assert_array_equal(got.cov_p_ned_m2, want.cov_p_ned_m2)
                assert (got.t_s, got.observable, got.range_sigma_ratio) == (
                    want.t_s,
                    want.observable,
                    want.range_sigma_ratio,
                )
        assert pe.late_results == 0 and skipped_before_first is not None
        # every frame the window skipped once estimates flowed was answered here (the rest by the worker)
        assert pe.carried == inline.stats["skipped"] - skipped_before_first > n // 4
    finally:
        pe.close()


@pytest.mark.integration
def test_a_hung_worker_is_killed_and_replaced_before_its_pipe_can_block_the_frames(scene):
    """A worker that is alive but answers nothing (SIGSTOP here) would let the pipe to it fill, after ~10 s of rows,
    and the next write block the frame loop for as long as it hangs; answered nothing for HUNG_S, it is killed and
    replaced, and the next rows are the new worker's.  close() ends a stopped worker too."""
    K, truth, obs = scene
    counter = LockedCounter(logger=logging.getLogger("onboard.rejects"))
    now = [0.0]
    pe = ProcessEstimator(
        OnboardConfig(), counter, result_wait_s=0.05, clock=lambda: now[0]
    )  # a stopped worker answers nothing
    try:
        _first_worker(pe)
        for i in range(HUNG_FRAMES_BEFORE_STOP):
            _add(pe, obs, K, i)
        hung_pid = pe.pid
        assert hung_pid is not None
        os.kill(hung_pid, signal.SIGSTOP)
        # the daemon's own wait from here: a stopped worker answers no row, so each waited its whole 0.05 s for
        # nothing (1.36 s of the test over the 26 rows until HUNG_S)
        pe.result_wait_s = OnboardConfig().estimator.result_wait_ms / 1000.0
        i = HUNG_FRAMES_BEFORE_STOP
        t0 = time.monotonic()
        silent = []
        while counter.counts.get("estimator_hung", 0) == 0 and i < len(obs.t_s) - 1:
            now[0] += 0.2  # the daemon's clock, not the rows': a few rows reach HUNG_S
            silent.append(pe.silent_s)  # what the watchdog names as overload's cause meanwhile
            _add(pe, obs, K, i)
            i += 1
        pe.result_wait_s = 0.05  # long enough for the replacement below to be taken by a row
        # up to date when stopped; from the first row it did not answer, the clock runs
        assert silent[0] == 0.0 and silent[1] == pytest.approx(0.2) and max(silent) >= pe.HUNG_S - 0.2
        assert counter["estimator_hung"] == 1 and time.monotonic() - t0 < 15.0  # ~HUNG_S of fake clock, not a block
        assert now[0] >= pe.HUNG_S
        deadline = time.monotonic() + 10.0
        while pe.pid in (None, hung_pid) and time.monotonic() < deadline and i < len(obs.t_s) - 1:
            now[0] += 1.0 / 30.0
            _add(pe, obs, K, i)
            i += 1
        assert pe.pid not in (None, hung_pid) and counter["estimator_restart"] == 1
        os.kill(pe.pid, signal.SIGSTOP)  # close() must not wait on a stopped worker's pipe
        t1 = time.monotonic()
        pe.close()
        assert time.monotonic() - t1 < 3.0
    finally:
        pe.close()
        try:
            os.kill(hung_pid, signal.SIGKILL)
        except (ProcessLookupError, UnboundLocalError):
            pass


def test_the_frame_loop_never_waits_on_the_workers_pipe(scene):
    """A message longer than the pipe takes (a replacement's snapshot, 0.6-0.9 MB) was written whole before the frame
    went on: the frame loop waited for the new worker to start and read it (0.4-1.3 s).  What the pipe cannot take
    now waits behind, written as the worker reads; the rows after it keep their order."""
    import threading

    K, _truth, obs = scene
    pe = ProcessEstimator(OnboardConfig(), LockedCounter(logger=logging.getLogger("onboard.rejects")))
    _first_worker(pe)
    pid = pe.pid
    assert pid is not None
    os.kill(pid, signal.SIGSTOP)  # reads nothing
    try:
        sent = threading.Thread(target=pe._send, args=(("intrinsics", 99, b"x" * 2_000_000),), daemon=True)
        sent.start()
        sent.join(10.0)
        assert not sent.is_alive()  # it returned, the worker stopped
        assert len(pe._out) > 0  # what the pipe did not take waits
        os.kill(pid, signal.SIGCONT)
        _add(pe, obs, K, 0)  # the worker reads it all, then the row, in order
        deadline = time.monotonic() + 10.0
        while pe._out and time.monotonic() < deadline:
            pe.predict(float(obs.t_s[0]))
        assert not pe._out and pe._alive()
    finally:
        os.kill(pid, signal.SIGCONT)
        pe.close()


@pytest.mark.integration
def test_positions_withheld_after_a_gap_in_the_frames_are_not_counted_as_the_daemon_behind(scene):
    """A camera or network outage longer than estimator.max_extrapolation_s: the first frames after it find only an
    estimate from before it, too old to carry, and their positions are withheld. Counted estimate_stale, they raised
    `overload` ("the daemon does not get the CPU it needs") after an outage of the frames; now estimate_after_gap,
    and frames late without a gap are still estimate_stale."""
    K, truth, obs = scene
    counter = LockedCounter()
    pe = ProcessEstimator(OnboardConfig(), counter, result_wait_s=RESULT_WAIT_S)
    try:
        _fill_window(pe, obs, K)
        pe.result_wait_s = 0.0  # never wait: what a frame gets is the newest estimate carried to it, or nothing
        end = FRAMES_BEFORE_KILL - 1
        gap = next(i for i in range(end, len(obs.t_s)) if obs.t_s[i] - obs.t_s[end] > pe.max_extrapolation_s + 0.5)
        # the worker held still while the frame after the gap is added: on a loaded machine this thread could be
        # descheduled between the row's send and its read for as long as the worker takes to answer it, and the
        # frame then got its own estimate (a fresh one: nothing withheld, nothing counted) -- the case under test is
        # the frame that finds only the estimate from before the gap
        pid = pe.pid
        assert pid is not None
        os.kill(pid, signal.SIGSTOP)
        try:
            assert _add(pe, obs, K, gap) is None
        finally:
            os.kill(pid, signal.SIGCONT)
        assert counter["estimate_after_gap"] == 1 and counter["estimate_stale"] == 0
    finally:
        pe.close()


def test_the_threaded_worker_counts_a_gap_in_the_frames_as_the_process_one_does():
    """estimator.worker: thread: the first frame after an outage of the frames, its estimate still being made,
    found only the estimate from before the outage: counted estimate_stale (overload) there too."""
    import types

    from onboard.app.estimator_worker import ThreadedEstimator
    from onboard.core.counters import RejectCounter

    class Slow:  # an estimator whose solve takes 30 ms (a model re-selection after the gap)
        def add(self, t, *a):
            time.sleep(0.03)
            return types.SimpleNamespace(t_s=t, p_ned_m=np.zeros(3), v_ned_mps=np.zeros(3), cov_p_ned_m2=np.eye(3))

        def reset(self):
            pass

    counter = RejectCounter()
    te = ThreadedEstimator(Slow(), counter, result_wait_s=1.0, max_extrapolation_s=1.0)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    try:
        for i in range(5):
            assert te.add(i * 0.04, (1.0, 1.0), None, np.zeros(3), q) is not None
        te.result_wait_s = 0.002
        assert te.add(8.0, (1.0, 1.0), None, np.zeros(3), q) is None  # 8 s after the last frame
        assert counter["estimate_after_gap"] == 1 and counter["estimate_stale"] == 0
    finally:
        te.close()


def test_an_estimator_that_raises_in_the_worker_thread_is_counted_naming_its_class(caplog):
    """estimator.worker: thread: the error line names the estimator, as the inline pipeline's does."""
    from onboard.app.estimator_worker import ThreadedEstimator
    from onboard.core.counters import RejectCounter

    class Broken:
        def add(self, t, *a):
            raise RuntimeError("singular window")

        def reset(self):
            pass

    counter = RejectCounter()
    te = ThreadedEstimator(Broken(), counter, result_wait_s=1.0)
    try:
        with caplog.at_level(logging.WARNING):
            assert te.add(0.0, (1.0, 1.0), None, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])) is None
        assert counter["estimator_error"] == 1
        lines = [r.getMessage() for r in caplog.records if "estimator_error" in r.getMessage()]
        assert len(lines) == 1 and "Broken: RuntimeError: singular window" in lines[0], lines
    finally:
        te.close()
