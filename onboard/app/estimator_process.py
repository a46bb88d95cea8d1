"""The estimator's worker process (:class:`~onboard.app.estimator_worker.ProcessEstimator`'s child): it builds the
daemon's estimator and serves the parent's rows, resets and rebuilds over a pipe
(:mod:`onboard.app.estimator_wire`), answering each with its estimate and now and then a snapshot of its state."""

from __future__ import annotations

import logging
import math
import os
import signal
import time
from collections.abc import Iterable
from typing import Any

from onboard.app.config import OnboardConfig
from onboard.app.estimator_wire import pack_estimate, recv_msg, row_args, send_msg
from onboard.app.os_thread import name_os_thread
from onboard.core.errors import InputError
from onboard.pipeline.frame_pipeline import make_estimator

__all__ = ["SNAPSHOT_PERIOD_S", "estimator_process_main"]

# the worker's lines are the estimator worker's, as they were when this ran from that module
log = logging.getLogger("onboard.app.estimator_worker")

# observation time between two snapshots of the worker's state sent to the parent: a snapshot costs the
# worker a few milliseconds, so one a second would take a noticeable share of the daemon's CPU budget
SNAPSHOT_PERIOD_S = 5.0


def _add_rows(est, rows: Iterable[tuple]) -> Any:
    """``rows`` added to ``est`` in order, those it refuses skipped (they were counted when they first
    arrived); the estimate at the last one added (or None)."""
    out = None
    for args in rows:
        try:
            out = est.add(*args)
        except InputError:
            pass
    return out


def _unpack_rows(packed) -> list:
    t, uv, p, q, k_index, intrinsics = packed
    return [
        (float(t[i]), (float(uv[i, 0]), float(uv[i, 1])), intrinsics[int(k_index[i])], p[i], q[i])
        for i in range(len(t))
    ]


def estimator_process_main(conn, config: OnboardConfig) -> None:
    """Child process of :class:`~onboard.app.estimator_worker.ProcessEstimator`: builds the estimator, serves add/reset/rebuild until "stop".

    Every ``SNAPSHOT_PERIOD_S`` of observation time, an answer with an estimate also carries a
    snapshot of the estimator's state (:meth:`SlidingWindowEstimator.snapshot`), which the parent keeps for a
    replacement."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and stops us
    name_os_thread("irtrack-estim")
    from onboard.app.logs import setup_logging  # this process is an entry point of its own: same log lines

    setup_logging(config.logging.level, config.logging.format)
    est = make_estimator(config)
    last_snapshot_t = -math.inf
    intrinsics: dict[int, Any] = {}  # the rows' camera models, by the index the parent gave them
    while True:
        try:
            msg = recv_msg(conn)
        except (EOFError, OSError):
            return
        kind = msg[0]
        if kind == "stop":
            return
        if kind == "reset":
            est.reset()
            last_snapshot_t = -math.inf
            continue
        if kind == "intrinsics":
            intrinsics[msg[1]] = msg[2]
            continue
        out, err = None, None
        if kind == "rebuild":  # a replacement worker: the dead one's state, or its window from the parent's copy
            _, epoch, packed, snapshot = msg
            rows = _unpack_rows(packed)
            t = rows[-1][0] if rows else math.nan
            c0, w0 = time.process_time(), time.monotonic()
            how, n_rows = "rebuilt from", len(rows)
            try:
                if snapshot is not None:
                    snap_t, snap_bytes = snapshot
                    later = [r for r in rows if r[0] > snap_t]
                    try:
                        est.reset()
                        est.restore(snap_bytes)
                        out = _add_rows(est, later)
                        how, n_rows = f"restored from its state at {snap_t:.3f} s +", len(later)
                    except Exception as exc:  # noqa: BLE001 - an unusable snapshot: rebuild instead
                        log.warning(
                            "estimator worker %d: snapshot unusable (%s: %s); rebuilding the window",
                            os.getpid(),
                            type(exc).__name__,
                            exc,
                        )
                        snapshot = None
                if snapshot is None:
                    out = est.rebuild(rows)
                log.info(
                    "estimator worker %d: window %s %d observations in %.3f s (%.3f CPU s); %s",
                    os.getpid(),
                    how,
                    n_rows,
                    time.monotonic() - w0,
                    time.process_time() - c0,
                    "estimate ready" if out is not None else "no estimate yet" if n_rows else "nothing to add",
                )
            except InputError:
                pass  # the newest row was refused when it first arrived (and counted then)
            except Exception as exc:  # noqa: BLE001 - reported to the parent, never fatal here
                err = ("estimator_error", f"{type(est).__name__}.rebuild: {type(exc).__name__}: {exc}")
        else:
            epoch, t = msg[1], msg[2]
            try:
                out = est.add(*(row_args(msg, intrinsics) if kind == "row" else msg[3]))
            except InputError as exc:
                err = ("estimator_input", str(exc))
            except Exception as exc:  # noqa: BLE001 - reported to the parent, never fatal here
                err = ("estimator_error", f"{type(est).__name__}: {type(exc).__name__}: {exc}")
        snap = None
        if out is not None and t - last_snapshot_t >= SNAPSHOT_PERIOD_S:
            try:
                snap = (t, est.snapshot())
                last_snapshot_t = t
            except Exception as exc:  # noqa: BLE001 - no snapshot: a replacement rebuilds the window instead
                err = err or ("estimator_error", f"{type(est).__name__}.snapshot: {type(exc).__name__}: {exc}")
        try:
            send_msg(conn, (epoch, t, pack_estimate(out), err, time.process_time(), snap))
        except (OSError, ValueError):
            return
