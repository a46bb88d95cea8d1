"""Worker processes for the evaluation's pools (eval, report, dataset, campaign): one set-up for all of them.

A pool's workers come from a fork server (:func:`mp_context`) and run :func:`init_worker` first: one BLAS
thread (:func:`limit_blas_threads`), one OpenCV thread, SIGINT ignored (Ctrl-C is the parent's: it
terminates the pool, so no worker prints a KeyboardInterrupt traceback), an end when the command that made the
pool ends, however it ends (:func:`end_with_owner`), and the progress queue.  A job
reports the frames it has done with :func:`report_progress`, in a worker or in the parent alike.
:func:`run_jobs` runs jobs in this process (one worker) or on a pool; interrupted, it raises
:class:`JobsInterrupted` carrying the results of the jobs that finished.  On a pool a job may have a wall-clock
deadline (:func:`pool_results`): its worker is killed and the job lost, so a plug-in that hangs ends its run
alone instead of the command.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

__all__ = [
    "DEFAULT_PRELOAD",
    "JobsInterrupted",
    "WorkerLost",
    "pool_workers",
    "mp_context",
    "init_worker",
    "end_with_owner",
    "limit_blas_threads",
    "report_progress",
    "run_jobs",
    "run_pool",
    "start_pool",
    "pool_results",
    "auto_deadline_s",
    "check_run_timeout",
    "stop_pool",
    "finish_pool",
    "quiet_run_logs",
    "progress_bar",
    "bar_pacing",
]

#: the modules the fork server imports once, so that each worker starts with them loaded
DEFAULT_PRELOAD = ("groundsim.evaluation.eval", "groundsim.evaluation.report")

_progress: Callable[[int], object] | None = None  # where report_progress goes in this process
_starts = None  # in a pool worker: where a job says it started on this process (start_pool's SimpleQueue)
POOL_START_TIMEOUT_S = 120.0  # the longest a pool's start holds Ctrl-C (the fork server imports on a busy machine)


class JobsInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`run_jobs`: ``results`` in job order, None for the jobs that did not finish."""

    def __init__(self, results: list) -> None:
        super().__init__(f"{sum(r is not None for r in results)} of {len(results)} jobs done")
        self.results = results

    @property
    def done(self) -> int:
        return sum(r is not None for r in self.results)


class WorkerLost(RuntimeError):
    """A pool worker process ended while it ran a job (``os._exit``, a crash, a kill): that job has no result."""


def pool_workers(workers: int | None) -> int:
    """The worker processes a command's ``--workers`` asks for; None: ``min(2, CPUs)``, as every command's help
    says (the lockstep runs are CPU-bound, and two leave a small machine usable).  ConfigError below 1."""
    import os

    from onboard.core.errors import ConfigError

    n = workers if workers is not None else max(1, min(2, os.cpu_count() or 1))
    if n < 1:
        raise ConfigError(f"--workers: expected an integer >= 1, got {n}")
    return n


def limit_blas_threads(n: int = 1) -> int:
    """One BLAS thread per process, now and in child processes; returns the number of BLAS libraries limited.

    The estimator's matrices are small: BLAS worker threads buy nothing there, and on a loaded 2-core
    machine their spinning made a whole-flight solve 20x slower.  Sets the environment variables
    (:func:`onboard.core.blas.single_thread_blas_env`, for children started later) and limits every BLAS
    already loaded here with threadpoolctl (numpy and scipy each bundle an OpenBLAS; scipy.linalg is
    imported first so that its copy is loaded and limited too).
    """
    from threadpoolctl import ThreadpoolController

    from onboard.core.blas import single_thread_blas_env

    single_thread_blas_env(n=n)
    import scipy.linalg  # noqa: F401 - loads scipy's own OpenBLAS so that it is limited too

    blas = ThreadpoolController().select(user_api="blas")
    blas.limit(limits=int(n))
    return len(blas.lib_controllers)


def mp_context(preload: tuple[str, ...] = DEFAULT_PRELOAD):
    """Worker processes come from a fork server (a fresh process that imported ``preload`` once),
    never from a plain fork of this one: a process that already ran OpenCV, JSBSim or OpenBLAS has
    threads and locks a forked child would inherit half-held (a pool forked after a lockstep run in
    the same process hung)."""
    import multiprocessing as mp

    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(list(preload))
    return ctx


def init_worker(queue=None, ready=None, owner_pid: int | None = None, starts=None) -> None:
    """A pool worker's set-up: SIGINT ignored, ended with the process that made the pool (``owner_pid``:
    :func:`end_with_owner`), one BLAS and one OpenCV thread, progress to ``queue``; a 0 to ``ready`` (or
    ``queue``) once started; ``starts``: where :func:`pool_results`' jobs say which process runs them."""
    import signal

    global _progress, _starts
    _starts = starts
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it terminates the pool
    if owner_pid is not None:
        end_with_owner(owner_pid)
    limit_blas_threads(1)
    try:
        import cv2

        cv2.setNumThreads(1)
    except Exception:  # noqa: BLE001 - OpenCV threading is an optimisation only
        pass
    _progress = None if queue is None else queue.put
    started = queue if ready is None else ready
    if started is not None:
        started.put(0)  # started: no frames done yet (start_pool waits for this from every worker)


def end_with_owner(owner_pid: int) -> bool:
    """SIGTERM to this process when process ``owner_pid`` (the command that made the pool) exits, however it
    ends; True when that is arranged (Linux 5.3 and later: a pidfd, waited on by a daemon thread).

    A command killed outright (SIGKILL, an out-of-memory kill) terminates no pool, and its workers went on with
    their jobs, orphans, for as long as the jobs ran.  A worker's parent is the fork server, not the command,
    and the fork server ends only once every worker has (each holds its liveness pipe), so a signal on the
    parent's death (``prctl(PR_SET_PDEATHSIG)``, :mod:`onboard.app.parent_watch`) would never come."""
    import os
    import select
    import signal
    import threading

    try:
        fd = os.pidfd_open(owner_pid)
    except ProcessLookupError:  # gone already
        os.kill(os.getpid(), signal.SIGTERM)
        return True
    except (AttributeError, OSError):  # no pidfd here: the pool's own terminate is the only end
        return False

    def wait_for_owner() -> None:
        select.select([fd], [], [])  # a pidfd turns readable when its process exits
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=wait_for_owner, name="end-with-owner", daemon=True).start()
    return True


def report_progress(n: int) -> None:
    """A job's ``n`` frames just done: to the parent's progress bar (through the pool's queue in a worker,
    directly in the parent); nothing when no one listens."""
    if _progress is not None:
        _progress(n)


def run_jobs(
    job,
    jobs: list,
    workers: int,
    on_progress=None,
    preload: tuple[str, ...] = DEFAULT_PRELOAD,
    on_lost=None,
    deadline_s=None,
) -> list:
    """``job(j)`` for every ``j`` of ``jobs``, in this process (``workers`` 1) or on a fork-server pool; their
    results in the order of ``jobs``.  ``on_progress(n)`` gets what the jobs pass to :func:`report_progress`;
    ``on_lost(j, why)`` is the result of a job whose pool worker ended under it or that ran past ``deadline_s``
    (:func:`pool_results`; in this process a job cannot be stopped, and the deadline is not enforced).
    Ctrl-C raises :class:`JobsInterrupted` with the results so far (the pool terminated first)."""
    global _progress
    if workers <= 1:
        results: list = [None] * len(jobs)
        saved, _progress = _progress, on_progress
        try:
            for n, j in enumerate(jobs):
                results[n] = job(j)
        except KeyboardInterrupt:
            raise JobsInterrupted(results) from None
        finally:
            _progress = saved
        return results
    return run_pool(job, jobs, workers, on_progress, preload, on_lost, deadline_s)


def start_pool(workers: int, preload: tuple[str, ...] = DEFAULT_PRELOAD, progress: bool = True):
    """``(pool, queue)``: ``workers`` fork-server processes, every one started (:func:`init_worker`) before this
    returns; ``queue`` carries what the jobs report with :func:`report_progress` (None without ``progress``:
    nothing is reported, so a caller that never drains a queue leaves none filling).  Ctrl-C during the start
    is held until the workers have started, then raised as KeyboardInterrupt, the pool terminated."""
    import os
    import queue as queue_mod
    import signal
    import threading
    import time

    from groundsim.io.stop_signals import redeliver

    ctx = mp_context(preload)
    pool = None
    # Ctrl-C while the pool starts is held until every worker has started (init_worker's 0 on the queue), then
    # raised: raised inside ctx.Pool it left workers half started, and a worker still unpickling its queue when
    # this process had exited printed a traceback (the queue's semaphore was gone).  It is held by a Python
    # handler that only notes it, not by blocking the signal in this thread: a signal blocked here is still
    # taken by any other thread that had it unblocked (BLAS, OpenCV, a progress bar's), and Python then raises
    # it in the main thread all the same.  signal.signal works in the main thread only; elsewhere the caller
    # owns Ctrl-C.
    # SIGTERM is held the same way while a Python handler takes it (a command that stops on SIGTERM as on
    # Ctrl-C, groundsim.io.stop_signals.first_signal_stops), then handed to that handler.
    held: list[int] = []
    main = threading.current_thread() is threading.main_thread()
    # SIGINT ignored (a command started in the background by a non-interactive shell) stays ignored
    take_int = main and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN
    previous = signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum)) if take_int else None
    term = signal.getsignal(signal.SIGTERM) if main else None
    if not callable(term):  # the default (the process ends) or ignored: left as it is
        term = None
    if term is not None:
        signal.signal(signal.SIGTERM, lambda signum, frame: held.append(signum))
    try:
        try:
            ready = ctx.Queue()
            q = ready if progress else None
            starts = ctx.SimpleQueue()
            pool = ctx.Pool(workers, initializer=init_worker, initargs=(q, ready, os.getpid(), starts))
            pool.job_starts = starts  # read by pool_results
            t_end = time.monotonic() + POOL_START_TIMEOUT_S
            started = 0
            while started < workers and time.monotonic() < t_end:
                try:
                    started += ready.get(timeout=0.2) == 0
                except queue_mod.Empty:
                    pass
        finally:
            if take_int:  # None: a handler installed outside Python; Python's own is the nearest honest one
                signal.signal(signal.SIGINT, previous if previous is not None else signal.default_int_handler)
            if term is not None:
                signal.signal(signal.SIGTERM, term)
        if held:  # to its handler, now back (a command's first_signal_stops then knows it was asked to stop)
            redeliver(held[0])
    except BaseException:
        if pool is not None:
            stop_pool(pool)
        raise
    return pool, q


def _watched(job, i: int, j):
    """In a pool worker: say that job ``i`` runs on this process (before it can end the process), run it, then say
    that it returned."""
    import os

    if _starts is not None:
        _starts.put((i, os.getpid()))  # a SimpleQueue's put is written before it returns: no feeder thread to lose
    try:
        return job(j)
    finally:
        if _starts is not None:
            _starts.put((i, None))  # returned: past its deadline now, it is no longer killed (pool_results)


def _worker_gone(pid: int, procs: dict) -> str | None:
    """How worker ``pid`` ended (`` (exit code 3)``, `` (killed by signal 9)``, ``""`` when not known), or None
    while it runs."""
    import os

    p = procs.get(pid)
    if p is not None:
        code = p.exitcode
        if code is None:
            return None
        return f" (killed by signal {-code})" if code < 0 else f" (exit code {code})"
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return ""
    except PermissionError:
        return None
    return None


#: how long a job whose worker has ended may still deliver its result (sent just before the end) before it is lost
LOST_GRACE_S = 1.0
#: the automatic run deadline (``--run-timeout`` not given): this many times the flight's simulated seconds, plus
#: :data:`AUTO_DEADLINE_BASE_S` for start-up and scoring; generous, as a loaded machine runs a flight many times
#: slower than real time, and it is there only to end a run that hangs
AUTO_DEADLINE_FACTOR = 20.0
AUTO_DEADLINE_BASE_S = 120.0


def auto_deadline_s(duration_s: float, runs: int = 1) -> float:
    """The automatic deadline of a job of ``runs`` runs of ``duration_s`` simulated seconds each."""
    return runs * (AUTO_DEADLINE_FACTOR * float(duration_s) + AUTO_DEADLINE_BASE_S)


def check_run_timeout(value) -> float | None:
    """``--run-timeout``: None (the automatic deadline) or a positive finite number of seconds; ConfigError else."""
    import math

    from onboard.core.errors import ConfigError

    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ConfigError(f"--run-timeout: expected a positive number of seconds, got {value!r}")
    return float(value)


def _kill_worker(pid: int) -> None:
    import os
    import signal

    try:
        os.kill(pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):  # ended already: the pool replaces it all the same
        pass


def pool_results(pool, job, jobs: list, on_lost=None, drain=None, deadline_s=None) -> Iterator[tuple[int, object]]:
    """``(i, job(jobs[i]))`` as each job finishes on ``pool`` (from :func:`start_pool`), in the order they finish.

    A job whose worker process ends under it (``os._exit``, a crash, a kill) yields ``on_lost(jobs[i], why)``
    (raises :class:`WorkerLost` without ``on_lost``): a multiprocessing pool replaces such a worker but never
    finishes its job, so a command waiting for every result had waited for ever.  ``deadline_s`` (seconds, or a
    function of the job giving them; None: none) is each job's wall-clock limit from when its worker started it:
    a job still running then has its worker killed (SIGKILL; the pool replaces it) and is lost the same way, its
    ``why`` naming the deadline.  ``drain(timeout_s)`` is called while waiting (the progress queue's reader), else
    the wait is a 0.2 s poll."""
    import time

    starts = getattr(pool, "job_starts", None)
    pending = [pool.apply_async(_watched, (job, i, j)) for i, j in enumerate(jobs)]
    left = set(range(len(jobs)))
    running: dict[int, int] = {}  # job -> the worker pid it started on
    started_at: dict[int, float] = {}  # job -> when its start was read here
    finished: set[int] = set()  # jobs whose worker said they returned (their result may still be on its way)
    procs: dict = {}  # every worker process seen, by pid: a replaced one leaves the pool's list
    gone_since: dict[int, float] = {}

    def read_starts() -> None:
        while starts is not None and not starts.empty():
            i, pid = starts.get()
            if pid is None:
                finished.add(i)
            else:
                running[i] = pid
                started_at[i] = time.monotonic()

    def limit(i: int) -> float | None:
        return deadline_s(jobs[i]) if callable(deadline_s) else deadline_s

    def lost(i: int, reason: str):
        left.discard(i)
        if on_lost is None:
            raise WorkerLost(reason)
        return on_lost(jobs[i], reason)

    while left:
        if drain is not None:
            drain(0.2)
        else:
            pending[min(left)].wait(0.2)
        procs.update((p.pid, p) for p in list(getattr(pool, "_pool", [])))
        read_starts()
        for i in sorted(left):
            if pending[i].ready():
                left.discard(i)
                yield i, pending[i].get()  # re-raises the job's exception here
                continue
            pid = running.get(i)
            t_limit = None if pid is None or starts is None else limit(i)
            if t_limit is not None and time.monotonic() - started_at[i] > t_limit:
                # read again just before the kill: a worker whose job has returned goes on to wait for its next
                # task holding the task queue's lock, and killed then it would leave every other worker unfed
                read_starts()
                if i not in finished and not pending[i].ready():
                    _kill_worker(pid)
                    yield i, lost(i, f"ran past the run deadline of {t_limit:g} s; its worker (pid {pid}) was stopped")
                    continue
            why = None if pid is None else _worker_gone(pid, procs)
            if why is None:
                continue
            t_gone = gone_since.setdefault(i, time.monotonic())
            if time.monotonic() - t_gone < LOST_GRACE_S:
                continue
            yield i, lost(i, f"its worker process (pid {pid}) ended{why} before the job finished")


def stop_pool(pool, timeout_s: float = 10.0) -> None:
    """Terminate ``pool`` and wait for it, bounded: a pool whose worker died holding the task queue's lock (killed
    while it waited for a task) hangs ``Pool.terminate`` for ever; after ``timeout_s`` its workers are killed
    and the lock freed so that the terminate can finish."""
    import threading

    workers = list(getattr(pool, "_pool", []))
    t = threading.Thread(target=lambda: (pool.terminate(), pool.join()), name="stop-pool", daemon=True)
    t.start()
    t.join(timeout_s)
    if not t.is_alive():
        return
    for p in workers + list(getattr(pool, "_pool", [])):
        try:
            p.kill()
        except (OSError, ValueError, AttributeError):
            pass
    lock = getattr(getattr(pool, "_inqueue", None), "_rlock", None)
    try:
        if lock is not None:
            lock.release()  # held by a dead worker: no one else will ever release it
    except ValueError:
        pass
    t.join(timeout_s)


def finish_pool(pool) -> None:
    """Close ``pool`` and wait for its workers once its jobs are done; terminated instead when a job was lost with
    its worker (:func:`pool_results`): the pool still counts that job as pending and its join would wait for ever."""
    if getattr(pool, "_cache", None):
        stop_pool(pool)
    else:
        pool.close()
        pool.join()


def run_pool(
    job,
    jobs: list,
    workers: int,
    on_progress=None,
    preload: tuple[str, ...] = DEFAULT_PRELOAD,
    on_lost=None,
    deadline_s=None,
) -> list:
    """``job(j)`` for every ``j`` of ``jobs`` on ``workers`` fork-server processes (:func:`start_pool`); their
    results in the order of ``jobs``.  What the jobs report with :func:`report_progress` is handed to
    ``on_progress`` as it arrives.  A worker's exception is re-raised here after the pool is terminated; a job
    whose worker ends under it, or that runs past ``deadline_s``, is ``on_lost(j, why)`` (:func:`pool_results`);
    Ctrl-C terminates the pool and raises :class:`JobsInterrupted` (one during the pool's start waits until its
    workers have started)."""
    import queue as queue_mod

    results: list = [None] * len(jobs)
    pool = None

    def drain(timeout_s: float | None) -> bool:
        try:
            n = q.get(timeout=timeout_s) if timeout_s else q.get_nowait()
        except queue_mod.Empty:
            return False
        if on_progress is not None:
            on_progress(n)
        return True

    try:
        pool, q = start_pool(workers, preload)
        for i, r in pool_results(pool, job, jobs, on_lost, drain, deadline_s):
            results[i] = r
        while drain(None):  # the last progress messages
            pass
        finish_pool(pool)
        return results
    except KeyboardInterrupt:
        if pool is not None:
            stop_pool(pool)
        raise JobsInterrupted(results) from None
    except BaseException:
        if pool is not None:
            stop_pool(pool)
        raise


#: the loggers whose per-run chatter (tracks started, flights trimmed, frames rendered) would drown a progress bar
RUN_LOGGERS = (
    "onboard",
    "groundsim.app.run",
    "groundsim.world.sim",
    "groundsim.world.flight",
    "groundsim.world.render",
)


@contextmanager
def quiet_run_logs(*extra: str) -> Iterator[None]:
    """While the block runs, at the default log level (INFO or quieter), keep only warnings from
    :data:`RUN_LOGGERS` and ``extra``; at ``--log-level DEBUG`` leave everything on.

    On the way out (an exception or Ctrl-C included) each logger gets back the level it had: the evaluation
    can run inside a longer-lived process (a test session, a notebook, the demo), whose later ``onboard``
    INFO records must not vanish because an eval once ran there."""
    import logging

    saved: dict[str, int] = {}
    if logging.getLogger().getEffectiveLevel() >= logging.INFO:
        for name in RUN_LOGGERS + extra:
            logger = logging.getLogger(name)
            saved.setdefault(name, logger.level)
            logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)


def bar_pacing() -> dict:
    """tqdm pacing: live on a terminal; one update every 10 s into a log file or pipe (a redrawn bar
    there is thousands of carriage-return segments)."""
    import sys

    return {} if sys.stderr.isatty() else {"mininterval": 10.0, "maxinterval": 30.0}


def progress_bar(total: int, unit: str, desc: str):
    """The evaluation's progress bar on stderr (tqdm, paced by :func:`bar_pacing`); close it when done."""
    from tqdm import tqdm

    return tqdm(total=total, unit=unit, desc=desc, leave=True, dynamic_ncols=True, **bar_pacing())
