"""Worker processes for the evaluation's pools (eval, report, dataset)."""

from __future__ import annotations

__all__ = ["mp_context", "run_pool", "quiet_run_logs", "progress_bar", "bar_pacing"]


def mp_context():
    """Worker processes come from a fork server (a fresh process that imported our modules once),
    never from a plain fork of this one: a process that already ran OpenCV, JSBSim or OpenBLAS has
    threads and locks a forked child would inherit half-held (a pool forked after a lockstep run in
    the same process hung)."""
    import multiprocessing as mp

    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["groundsim.evaluation.eval", "groundsim.evaluation.report"])
    return ctx


def run_pool(job, jobs: list, workers: int, init_worker, on_progress=None) -> list:
    """``job(j)`` for every ``j`` of ``jobs`` on ``workers`` fork-server processes; their results in the order
    of ``jobs``.  Each worker runs ``init_worker(queue)`` first; what the jobs put on that queue (frame counts)
    is handed to ``on_progress`` as it arrives.  A worker's exception is re-raised here, after the pool is
    terminated (so is a KeyboardInterrupt)."""
    import queue as queue_mod

    ctx = mp_context()
    q = ctx.Queue()
    pool = ctx.Pool(workers, initializer=init_worker, initargs=(q,))

    def drain(timeout_s: float | None) -> bool:
        try:
            n = q.get(timeout=timeout_s) if timeout_s else q.get_nowait()
        except queue_mod.Empty:
            return False
        if on_progress is not None:
            on_progress(n)
        return True

    try:
        pending = [pool.apply_async(job, (j,)) for j in jobs]
        results: list = [None] * len(jobs)
        left = set(range(len(jobs)))
        while left:
            drain(0.2)
            for i in [i for i in left if pending[i].ready()]:
                results[i] = pending[i].get()  # re-raises a worker's exception here
                left.discard(i)
        while drain(None):  # the last progress messages
            pass
        pool.close()
        pool.join()
        return results
    except BaseException:
        pool.terminate()
        pool.join()
        raise


#: the loggers whose per-run chatter (tracks started, flights trimmed, frames rendered) would drown a progress bar
RUN_LOGGERS = (
    "onboard",
    "groundsim.app.run",
    "groundsim.world.sim",
    "groundsim.world.flight",
    "groundsim.world.render",
)


def quiet_run_logs(*extra: str) -> None:
    """At the default log level (INFO or quieter) keep only warnings from :data:`RUN_LOGGERS` and ``extra``;
    at ``--log-level DEBUG`` leave everything on."""
    import logging

    if logging.getLogger().getEffectiveLevel() >= logging.INFO:
        for name in RUN_LOGGERS + extra:
            logging.getLogger(name).setLevel(logging.WARNING)


def bar_pacing() -> dict:
    """tqdm pacing: live on a terminal; one update every 10 s into a log file or pipe (a redrawn bar
    there is thousands of carriage-return segments)."""
    import sys

    return {} if sys.stderr.isatty() else {"mininterval": 10.0, "maxinterval": 30.0}


def progress_bar(total: int, unit: str, desc: str):
    """The evaluation's progress bar on stderr (tqdm, paced by :func:`bar_pacing`); close it when done."""
    from tqdm import tqdm

    return tqdm(total=total, unit=unit, desc=desc, leave=True, dynamic_ncols=True, **bar_pacing())
