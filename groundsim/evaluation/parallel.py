"""Worker processes for the evaluation's pools (eval, report, dataset)."""

from __future__ import annotations

__all__ = ["mp_context"]


def mp_context():
    """Worker processes come from a fork server (a fresh process that imported our modules once),
    never from a plain fork of this one: a process that already ran OpenCV, JSBSim or OpenBLAS has
    threads and locks a forked child would inherit half-held (a pool forked after a lockstep run in
    the same process hung)."""
    import multiprocessing as mp

    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["groundsim.evaluation.eval", "groundsim.evaluation.report"])
    return ctx
