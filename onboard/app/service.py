"""The onboard daemon's wiring and event loop (``python -m onboard``).

Threads (nothing else runs concurrently):

* **zenoh subscriber callback** (zenoh's thread) on ``irtrack/<vehicle>/ir/frame``: counts the
  payload, refuses it on its length alone (:func:`onboard.core.irframe.check_payload_size`: a frame
  100x too large is never copied), copies it out once and checks its header and size
  (:func:`onboard.core.irframe.decode_irframe`: microseconds, the pixels stay a view), counting each
  refusal as ``frame_<reason>``, and pushes ``(IrFrame, received_mono_ns)`` into a bounded
  :class:`FrameQueue`; when full the *oldest* frame is dropped and counted (``dropped_queue``).
  It never blocks.
* **pipeline thread**: pops frames, runs :meth:`FramePipeline.process` (admission,
  imaging, pose at capture time -- waiting up to ``pose.wait_ms`` (a few ms) for telemetry that
  brackets it, on a condition signalled by every new pose sample, then extrapolating the newest
  samples over a bounded horizon (:mod:`onboard.core.pose`) -- and the estimator), publishes the track JSON on
  ``irtrack/<vehicle>/track`` and hands the newest :class:`Track` to the main thread.  It touches
  the liveness file (:func:`onboard.app.health.mark_alive`) at least every ``output.health_interval_s``,
  busy or idle.
* **estimator worker** (``estimator.worker``): ``process`` (default, :class:`ProcessEstimator`) runs
  the sliding-window estimator in a child process, ``thread`` (:class:`ThreadedEstimator`) in a
  thread, ``inline`` in the pipeline thread.  With a worker, the estimator's periodic model
  re-selection (tenths of a second) never stalls the frame loop: a frame waits up to
  ``estimator.result_wait_ms`` for its own estimate, past that it gets the newest estimate
  propagated to its time at constant velocity (``P + dt^2 V``); the observation is used by the
  worker either way, no measurement is lost.  A process also keeps the estimator's Python work off
  the pipeline's GIL (measured: loopback p99 latency several times lower than with a thread).  A
  worker process that dies is replaced on the next frame from a fork server, restored from its last
  state (a snapshot every 5 s) and the parent's copy of the observations (``estimator_restart``;
  bridged by the propagated last estimate meanwhile).
* **main thread**: woken by MAVLink input and by its own timers (at most ``mavlink.poll_rate_hz`` turns a
  second, :meth:`OnboardService._idle`): :meth:`MavlinkLink.poll` /
  :meth:`MavlinkLink.tick` (the autopilot link, component 191: heartbeat, rate requests, TIMESYNC);
  the camera component (:meth:`OnboardService.camera_step`, with ``gcs.endpoints``): commands from
  ground stations through :class:`~onboard.io.gcs_link.GcsLink` into
  :class:`~onboard.io.camera_protocol.CameraProtocol`, tracking requests queued to the pipeline
  (:meth:`FramePipeline.request_selection`, decided on its next frame and ACKed here), heartbeat,
  CAMERA_TRACKING_IMAGE_STATUS / GEO_STATUS of the newest track while tracking at the rates asked
  (defaults ``output.tracking_*_status_hz``; #276 only for observable positions unless
  ``output.geo_status_unobservable``), the status JSON on ``irtrack/<vehicle>/status`` every
  ``output.status_interval_s``, and the :class:`~onboard.app.watchdog.Watchdog`'s input checks (no frames
  / no MAVLink for 5 s; frame size and residual checks are fed by the pipeline thread): each
  condition is logged once at WARNING and listed in the status JSON's ``warnings`` while it holds.  It owns the pymavlink connection alone; pose samples go into the
  shared :class:`SharedPoseBuffer` under a lock held for one ``add`` or one lookup (microseconds),
  so a pose lookup never blocks MAVLink.

Shutdown: :meth:`OnboardService.request_stop` (the SIGTERM/SIGINT handler of ``__main__``) ends the
main loop; :meth:`OnboardService.close` stops the threads, undeclares the zenoh entities, closes
the session and the MAVLink connection, and removes the liveness file.
"""

from __future__ import annotations

import collections
import json
import logging
import math
import os
import select
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from onboard.app.config import OnboardConfig
from onboard.app.os_thread import name_os_thread
from onboard.app.watchdog import Watchdog
from onboard.core.counters import RejectCounter
from onboard.core.errors import InputError
from onboard.core.irframe import IrFrameError, check_payload_size, decode_irframe
from onboard.core.pose import PoseBuffer
from onboard.core.status import RollingStats, build_status
from onboard.core.track import Track, track_to_bytes
from onboard.estimation.sliding import bearing_sigma_rad, line_of_sight_unit_ned
from onboard.io.worker_queue import next_or_stop
from onboard.pipeline.frame_pipeline import FramePipeline, FrameRejected, make_estimator, make_tracker

__all__ = ["LockedCounter", "SharedPoseBuffer", "FrameQueue", "ThreadedEstimator", "ProcessEstimator", "OnboardService"]

log = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000
ESTIMATE_QUEUE_MAX = 1000  # observations waiting for the estimator worker (about 30 s at 30 Hz)
# imported once by the estimator workers' fork server, so a replacement worker neither imports them nor
# pays their first use inside its first model selection (measured: first window rebuild 0.6-0.75 s with
# a cold scipy.stats, 0.16-0.18 s preloaded); onboard.app.main first: it sets one BLAS thread
FORKSERVER_PRELOAD = ["onboard.app.main", "onboard.app.service", "onboard.estimation.sliding", "scipy.stats"]


# --------------------------------------------------------------------------- thread-safe pieces


class LockedCounter(RejectCounter):
    """A :class:`RejectCounter` that several threads may count into."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._lock = threading.Lock()

    def count(self, reason: str, detail: str = "", n: int = 1, **kw) -> None:
        with self._lock:
            super().count(reason, detail, n, **kw)

    @property
    def counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)


class SharedPoseBuffer:
    """A :class:`PoseBuffer` shared by the MAVLink thread (writer) and the pipeline (reader).

    Each ``add_*``, ``lookup`` and ``pose_at`` runs under one lock; every stored sample notifies
    :meth:`wait_for`.  Other attributes (``mount``, ``reboots``, ``origin``, ``counter`` ...) are
    read through.
    """

    _WRAPPED = ("add_attitude", "add_position", "add_position_ned", "add_gimbal", "add_gimbal_status", "clear")

    def __init__(self, buffer: PoseBuffer) -> None:
        self._buffer = buffer
        self._cond = threading.Condition(threading.Lock())
        # the last look-up and the buffer's version it was made at: a frame's wait and its pose_at ask the
        # same question, and a full look-up (brackets, SLERP, Hermite, gimbal, camera pose) was a third of
        # the pipeline thread's CPU when made three times per frame
        self._version = 0
        self._memo: tuple | None = None  # (time_boot_us, extrapolate, version, PoseLookup)
        for name in self._WRAPPED:
            setattr(self, name, self._writer(getattr(buffer, name)))

    def _writer(self, fn: Callable) -> Callable:
        def locked(*args, **kwargs):
            with self._cond:
                out = fn(*args, **kwargs)
                self._version += 1
                self._cond.notify_all()
            return out

        locked.__name__ = fn.__name__
        locked.__doc__ = fn.__doc__
        return locked

    def _lookup(self, time_boot_us: int, extrapolate: bool):
        """PoseBuffer.lookup, memoised for the buffer's current version (call under the lock)."""
        m = self._memo
        if m is not None and m[0] == time_boot_us and m[1] == extrapolate and m[2] == self._version:
            return m[3]
        res = self._buffer.lookup(time_boot_us, extrapolate)
        self._memo = (time_boot_us, extrapolate, self._version, res)
        return res

    def lookup(self, time_boot_us: int, extrapolate: bool = False):
        with self._cond:
            return self._lookup(time_boot_us, extrapolate)

    def pose_at(self, time_boot_us: int, extrapolate: bool = True):
        with self._cond:
            return self._buffer.pose_at(time_boot_us, extrapolate, result=self._lookup(time_boot_us, extrapolate))

    def wait_for(self, time_boot_us: int, timeout_s: float, clock: Callable[[], float] = time.monotonic) -> bool:
        """Wait until a lookup at ``time_boot_us`` is decided by the data (the telemetry reaches that
        time, or a miss that waiting cannot fix) or ``timeout_s`` passed.  True when the telemetry
        covers the time (``pose_at`` then answers; it may still be a gap), False otherwise (then
        ``pose_at`` extrapolates within its horizon).  Never longer than ``timeout_s``, and not at
        all once the newest samples can be extrapolated to the time: waiting would buy a bracket
        whose gain (a few thousandths of a degree, :mod:`onboard.core.pose`) is not worth the latency;
        it waits only for streams that cannot be extrapolated (no rates, no velocity, beyond the
        horizon)."""
        deadline = clock() + max(timeout_s, 0.0)
        buf = self._buffer
        cheap = not buf.mount.gimballed  # newest_time_boot_us covers attitude and position only
        with self._cond:
            while True:
                if cheap:
                    newest = buf.newest_time_boot_us()
                    if newest is not None and newest >= time_boot_us:
                        return True  # bracketed (or decided): the caller's pose_at tells which
                res = self._lookup(time_boot_us, True)  # memoised: the caller's pose_at asks the same
                if res.pose is not None:
                    return not res.pose.extrapolated  # bracketed, or decided: pose_at extrapolates
                plain = buf.lookup(time_boot_us)  # no pose even extrapolating: can waiting bring a bracket?
                if plain.pose is not None:
                    return True
                left = deadline - clock()
                if not plain.retry or left <= 0:
                    return False
                self._cond.wait(left)

    def __getattr__(self, name: str):
        return getattr(self._buffer, name)


class FrameQueue:
    """Bounded FIFO (of ``(IrFrame, received_mono_ns)`` in the service); pushing onto a full queue drops the oldest."""

    def __init__(self, maxlen: int) -> None:
        if isinstance(maxlen, bool) or not isinstance(maxlen, int) or maxlen < 1:
            raise InputError(f"FrameQueue maxlen must be a positive integer, got {maxlen!r}")
        self._d: collections.deque = collections.deque()
        self._maxlen = maxlen
        self._cond = threading.Condition(threading.Lock())
        self._closed = False

    def push(self, item) -> int:
        """Append; returns how many old items were dropped to make room (0 or 1)."""
        with self._cond:
            dropped = 0
            while len(self._d) >= self._maxlen:
                self._d.popleft()
                dropped += 1
            self._d.append(item)
            self._cond.notify()
            return dropped

    def pop(self, timeout_s: float):
        """The oldest item, or None after ``timeout_s`` or once closed."""
        with self._cond:
            if not self._d and not self._closed:
                self._cond.wait(timeout_s)
            if self._d:
                return self._d.popleft()
            return None

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def __len__(self) -> int:
        return len(self._d)


# --------------------------------------------------------------------------- estimator worker


class ThreadedEstimator:
    """The estimator interface (``add`` / ``predict`` / ``reset``) with the work in a worker thread.

    ``add`` queues the observation and waits up to ``result_wait_s`` for its estimate; if the
    worker is busy (model re-selection) it returns the newest estimate propagated to ``t_s``
    instead (None when that is older than ``max_extrapolation_s``).  ``predict`` never waits.
    Estimator exceptions are counted (``estimator_input`` / ``estimator_error``), never raised.
    """

    def __init__(
        self,
        estimator,
        counter: RejectCounter,
        result_wait_s: float = 0.005,
        max_extrapolation_s: float = 1.0,
        max_pending: int = ESTIMATE_QUEUE_MAX,
    ) -> None:
        self._est = estimator
        self._noise = getattr(getattr(estimator, "map", None), "noise", None)  # for the bearing update (_propagate)
        self._counter = counter
        self.result_wait_s = float(result_wait_s)
        self.max_extrapolation_s = float(max_extrapolation_s)
        self._max_pending = max_pending
        self._q: collections.deque = collections.deque()
        self._cond = threading.Condition(threading.Lock())
        self._epoch = 0
        self._latest = None  # (epoch, estimate): the newest non-None estimate
        self._result = None  # (epoch, t_s, estimate or None): the last processed observation
        self._stop = False
        self.worker_cpu_s = 0.0
        self.late_results = 0
        self._thread = threading.Thread(target=self._run, name="irtrack-estimator", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ caller side

    def add(self, t_s: float, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam):
        args = _observation(t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam)
        t = args[0]
        deadline = time.monotonic() + self.result_wait_s
        with self._cond:
            if len(self._q) >= self._max_pending:
                self._q.popleft()
                self._counter.count(
                    "estimator_backlog", f"more than {self._max_pending} observations pending; oldest dropped"
                )
            epoch = self._epoch
            self._q.append(("add", epoch, t, args))
            self._cond.notify_all()
            while True:
                r = self._result
                if r is not None and r[0] == epoch and r[1] == t:
                    return r[2]
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(left)
            self.late_results += 1
            return self._extrapolate(t, p_cam_ned_m, args[1:])

    def predict(self, t_s: float, p_cam_ned_m=None):
        with self._cond:
            return self._extrapolate(float(t_s), p_cam_ned_m)

    def reset(self) -> None:
        with self._cond:
            self._epoch += 1
            self._q.clear()
            self._q.append(("reset", self._epoch, None, None))
            self._latest = None
            self._result = None
            self._cond.notify_all()

    def close(self, timeout_s: float = 1.0) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout_s)

    def _extrapolate(self, t: float, p_cam_ned_m, obs=None):
        latest = self._latest
        if latest is None or latest[0] != self._epoch:
            return None
        return _propagate(latest[1], t, p_cam_ned_m, self.max_extrapolation_s, self._counter, obs, self._noise)

    # ------------------------------------------------------------------ worker

    def _run(self) -> None:
        name_os_thread("irtrack-estim")
        while True:
            item = next_or_stop(self._cond, self._q, lambda: self._stop)
            if item is None:
                return
            kind, epoch, t, args = item
            c0 = time.thread_time()
            est = None
            try:
                if kind == "reset":
                    self._est.reset()
                    continue
                est = self._est.add(*args)
            except InputError as exc:
                self._counter.count("estimator_input", str(exc))
            except Exception as exc:  # noqa: BLE001 - the worker must never die
                self._counter.count("estimator_error", f"{type(exc).__name__}: {exc}")
            finally:
                self.worker_cpu_s += time.thread_time() - c0
            if kind != "add":
                continue
            with self._cond:
                if epoch == self._epoch:
                    self._result = (epoch, t, est)
                    if est is not None:
                        self._latest = (epoch, est)
                    self._cond.notify_all()

    @property
    def pending(self) -> int:
        return len(self._q)


def _rebuild_window(est, rows) -> Any:
    """Replay ``rows`` (the parent's copy of the window, oldest first) into a fresh estimator ``est``
    with one model selection, on the newest row, instead of one per second of replayed data.

    The earlier rows go in with ``config.min_frames`` raised out of reach, so ``add`` only stores them
    (the window trims itself as in normal running); the last row, with the real config, solves the
    whole window cold.  Rows the estimator refuses were counted when they first arrived: skipped
    silently here.  Returns the estimate at the newest row (or None)."""
    import dataclasses as _dc

    cfg = est.config
    est.config = _dc.replace(cfg, min_frames=1 << 30)
    try:
        for args in rows[:-1]:
            try:
                est.add(*args)
            except InputError:
                pass
    finally:
        est.config = cfg
    return est.add(*rows[-1]) if rows else None


def _unpack_rows(packed) -> list:
    t, uv, p, q, k_index, intrinsics = packed
    return [
        (float(t[i]), (float(uv[i, 0]), float(uv[i, 1])), intrinsics[int(k_index[i])], p[i], q[i])
        for i in range(len(t))
    ]


WATCH_PERIOD_S = 0.5  # the watchdog's input checks in the main loop
MAIN_LOOP_MAX_IDLE_S = 0.05  # the main loop's longest sleep without input (stop requests, timers it cannot see)
SNAPSHOT_PERIOD_S = 5.0  # observation time between two snapshots of the worker's state sent to the parent (4-5 ms of the worker each: 1 s cost 3 % of the CPU budget)
_NOT_SNAPSHOTTED = ("map",)  # the MAP solver (config + caches, ~11 MB pickled): the new worker builds its own


def _snapshot(est) -> bytes:
    """The sliding-window estimator's state (its attributes but the solver) as bytes (~0.9 MB for a
    full window: the rows, the spline solution, the model, the last linearisation)."""
    import pickle

    return pickle.dumps(
        {k: v for k, v in vars(est).items() if k not in _NOT_SNAPSHOTTED}, protocol=pickle.HIGHEST_PROTOCOL
    )


def _restore(est, snapshot: bytes, rows) -> Any:
    """``est`` (fresh) put back in the snapshotted state, then the ``rows`` that came after it added
    as usual.  Returns the estimate at the newest row (or None)."""
    import pickle

    state = pickle.loads(snapshot)
    if not isinstance(state, dict) or set(state) & set(_NOT_SNAPSHOTTED):
        raise ValueError("not an estimator snapshot")
    vars(est).update(state)
    out = None
    for args in rows:
        try:
            out = est.add(*args)
        except InputError:
            pass
    return out


def _estimator_process_main(conn, config: OnboardConfig) -> None:
    """Child process of :class:`ProcessEstimator`: builds the estimator, serves add/reset/rebuild until "stop".

    Every ``SNAPSHOT_PERIOD_S`` of observation time, an answer with an estimate also carries a
    snapshot of the estimator's state (:func:`_snapshot`), which the parent keeps for a replacement."""
    import signal as _signal

    _signal.signal(_signal.SIGINT, _signal.SIG_IGN)  # the parent handles Ctrl-C and stops us
    name_os_thread("irtrack-estim")
    from onboard.app.logs import setup_logging  # this process is an entry point of its own: same log lines

    setup_logging(config.logging.level, config.logging.format)
    est = make_estimator(config)
    last_snapshot_t = -math.inf
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        kind = msg[0]
        if kind == "stop":
            return
        if kind == "reset":
            est.reset()
            last_snapshot_t = -math.inf
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
                        out = _restore(est, snap_bytes, later)
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
                    est.reset()
                    out = _rebuild_window(est, rows)
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
                err = ("estimator_error", f"rebuild: {type(exc).__name__}: {exc}")
        else:
            _, epoch, t, args = msg
            try:
                out = est.add(*args)
            except InputError as exc:
                err = ("estimator_input", str(exc))
            except Exception as exc:  # noqa: BLE001 - reported to the parent, never fatal here
                err = ("estimator_error", f"{type(exc).__name__}: {exc}")
        snap = None
        if out is not None and t - last_snapshot_t >= SNAPSHOT_PERIOD_S:
            try:
                snap = (t, _snapshot(est))
                last_snapshot_t = t
            except Exception as exc:  # noqa: BLE001 - no snapshot: a replacement rebuilds the window instead
                err = err or ("estimator_error", f"snapshot: {type(exc).__name__}: {exc}")
        try:
            conn.send((epoch, t, out, err, time.process_time(), snap))
        except (OSError, ValueError):
            return


class ProcessEstimator:
    """The estimator interface with the estimator in a child process (no GIL shared with the frames).

    Same contract as :class:`ThreadedEstimator`: ``add`` sends the observation and waits up to
    ``result_wait_s`` for its estimate, else returns the newest estimate propagated to ``t_s``;
    ``predict`` never waits.  Results are read by the caller's thread (no extra thread here).

    **A worker that dies** (killed, OOM, crashed) is noticed on the next ``add``, counted
    (``estimator_restart``, logged with its exit code) and replaced at once.  The parent keeps its
    own copy of the window (the rows the estimator keeps: the last ``window_s``, one per
    ``min_spacing_s``, at most ``max_frames``; about 25 kB) and the worker's newest state (a snapshot
    the worker sends every ``SNAPSHOT_PERIOD_S`` of observation time, ~0.9 MB, 4-5 ms to make; :func:`_snapshot`).  The
    new worker is handed both: it restores the state and adds the rows that came after it
    (milliseconds; :func:`_restore`), or, without a usable snapshot, rebuilds the window with a single
    cold model selection (:func:`_rebuild_window`: 0.2-1 CPU s for a full 20 s window).  Either way 3-D
    output resumes without waiting for a new window to fill.  In between, the newest estimate keeps being propagated (up to
    ``max_extrapolation_s``), as when the worker is busy.  A worker that dies before it answered
    anything (a crash at start, or on an observation the rebuild replays) is replaced after a delay
    that starts at ``RESTART_BACKOFF_MIN_S`` and doubles each time (up to ``RESTART_BACKOFF_MAX_S``),
    so a crash loop cannot spawn a process per frame.
    """

    RESTART_BACKOFF_MIN_S = 1.0
    RESTART_BACKOFF_MAX_S = 30.0

    def __init__(
        self,
        config: OnboardConfig,
        counter: RejectCounter,
        result_wait_s: float = 0.002,
        max_extrapolation_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        import multiprocessing as mp

        # results are unpickled here: import their module now, not on the first result (~0.4 s stall)
        import onboard.estimation.sliding  # noqa: F401

        self._config = config
        self._noise = config.estimator.noise_model()  # the worker's noise model, for the bearing update (_propagate)
        self._counter = counter
        self._clock = clock
        self.result_wait_s = float(result_wait_s)
        self.max_extrapolation_s = float(max_extrapolation_s)
        # never fork this process (it runs zenoh's threads): the workers fork from a fork server, a
        # fresh single-threaded interpreter that has imported the estimator once, so a replacement
        # starts in milliseconds instead of re-importing numpy/scipy (~0.5-1 s on a loaded core)
        self._ctx = mp.get_context("forkserver")
        self._ctx.set_forkserver_preload(FORKSERVER_PRELOAD)
        self._epoch = 0
        self._latest = None  # (epoch, estimate)
        self.worker_cpu_s = 0.0
        self.late_results = 0
        self.carried = 0  # frames answered here, not by the worker (add)
        self.restarts = 0
        # the child's own window rules, mirrored so that the copy holds the rows its window holds: the
        # last window_s, at most max_frames, a row kept only min_spacing_s after the previous kept one
        self._local = make_estimator(config)  # for carry(): frames the worker would not keep (add)
        limits = self._local.config
        self._window_s = float(limits.window_s)
        self._min_spacing_s = float(getattr(limits, "min_spacing_s", 0.0))
        self._window: collections.deque = collections.deque(maxlen=int(limits.max_frames))  # observation args
        self._snapshot = None  # (t_s, bytes): the worker's state, every SNAPSHOT_PERIOD_S
        self._backoff_s = 0.0
        self._next_start_s = -math.inf
        self._started_s = -math.inf
        self._proc = None
        self._conn = None
        self._start()

    @property
    def pid(self) -> int | None:
        """The worker's process id (None while there is none)."""
        return None if self._proc is None else self._proc.pid

    def _start(self) -> None:
        parent, child = self._ctx.Pipe()
        self._proc = self._ctx.Process(
            target=_estimator_process_main, args=(child, self._config), name="irtrack-estimator", daemon=True
        )
        self._proc.start()
        child.close()
        self._conn = parent
        self._cpu_base = self.worker_cpu_s
        self._started_s = self._clock()
        self._answered = False  # no result from this worker yet

    def _alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def _replace_dead_worker(self) -> bool:
        """Start a new worker with the window rebuilt; False while a crash loop's back-off lasts."""
        now = self._clock()
        if self._proc is not None:  # just found dead: count it once, choose the back-off
            code = self._proc.exitcode
            lived_s = now - self._started_s
            self._backoff_s = (
                0.0
                if self._answered
                else min(max(2 * self._backoff_s, self.RESTART_BACKOFF_MIN_S), self.RESTART_BACKOFF_MAX_S)
            )
            self._next_start_s = now + self._backoff_s
            self.restarts += 1
            self._counter.count(
                "estimator_restart",
                f"estimator process died (exit code {code}, after {lived_s:.1f} s); replaced"
                + (f" in {self._backoff_s:.0f} s" if self._backoff_s else "")
                + f", window rebuilt from the last {len(self._window)} observations",
            )
            try:
                self._conn.close()
            except OSError:
                pass
            self._proc.join(0)
            self._proc, self._conn = None, None
        if now < self._next_start_s:
            return False
        self._start()
        if self._window:
            snap = self._snapshot
            if snap is not None and snap[0] < self._window[0][0]:
                snap = None  # older than the window: rebuild instead (a reset clears both)
            try:
                self._conn.send(("rebuild", self._epoch, self._packed_window(), snap))
            except (OSError, ValueError) as exc:
                self._counter.count("estimator_error", f"send to the estimator process: {exc}")
        return True

    def _packed_window(self):
        """The window as arrays (about 80 B per row; the intrinsics, nearly always one object, once)."""
        rows = list(self._window)
        intrinsics: list = []
        index = np.empty(len(rows), dtype=np.int32)
        for i, r in enumerate(rows):
            k = r[2]
            for j, known in enumerate(intrinsics):
                if known is k or known == k:
                    index[i] = j
                    break
            else:
                intrinsics.append(k)
                index[i] = len(intrinsics) - 1
        return (
            np.array([r[0] for r in rows]),
            np.array([r[1] for r in rows]).reshape(-1, 2),
            np.array([r[3] for r in rows]).reshape(-1, 3),
            np.array([r[4] for r in rows]).reshape(-1, 4),
            index,
            intrinsics,
        )

    def _remember(self, args) -> None:
        w = self._window
        if w and not args[0] - w[-1][0] >= max(self._min_spacing_s, 1e-12):
            return  # the estimator does not keep it either (too soon after its previous row, or not after it)
        w.append(args)
        while w and w[0][0] < args[0] - self._window_s:
            w.popleft()

    def _drain(self, until_t: float | None = None, wait_s: float = 0.0):
        """Read every available result; with ``until_t`` wait up to ``wait_s`` for that one.
        Returns (found, estimate) for ``until_t``."""
        if self._conn is None:
            return False, None
        deadline = time.monotonic() + wait_s
        found, value = False, None
        while True:
            left = deadline - time.monotonic() if until_t is not None and not found else 0.0
            try:
                ready = self._conn.poll(max(left, 0.0))
            except (OSError, EOFError):
                return found, value
            if not ready:
                return found, value
            try:
                epoch, t, est, err, cpu_s, snapshot = self._conn.recv()
            except (OSError, EOFError):
                return found, value
            self.worker_cpu_s = self._cpu_base + cpu_s
            self._answered = True
            if err is not None:
                self._counter.count(*err)
            if epoch != self._epoch:
                continue
            if snapshot is not None:
                self._snapshot = snapshot  # (t_s of its newest row, bytes)
            if est is not None:
                self._latest = (epoch, est)
            if until_t is not None and t == until_t:
                found, value = True, est

    def add(self, t_s: float, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam):
        args = _observation(t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam)
        t = args[0]
        if not self._alive() and not self._replace_dead_worker():
            self._remember(args)  # kept for the replacement
            self.late_results += 1
            return self._extrapolate(t, p_cam_ned_m, args[1:])
        w = self._window
        if w and 0.0 < t - w[-1][0] < self._min_spacing_s:
            # the worker would not keep this row and would answer with its estimate at the newest kept row
            # carried to t: when that answer is here, carry it here (same numbers, no round trip: half the
            # frames at 30 Hz; issue 9 item 7)
            self._drain()
            latest = self._latest
            if latest is not None and latest[0] == self._epoch and latest[1].t_s == w[-1][0]:
                self.carried += 1
                return self._local.carry(latest[1], t, p_cam_ned_m)
        self._remember(args)
        try:
            self._conn.send(("add", self._epoch, t, args))
        except (OSError, ValueError) as exc:
            self._counter.count("estimator_error", f"send to the estimator process: {exc}")
            return self._extrapolate(t, p_cam_ned_m, args[1:])
        found, est = self._drain(t, self.result_wait_s)
        if found:
            return est
        self.late_results += 1
        return self._extrapolate(t, p_cam_ned_m, args[1:])

    def predict(self, t_s: float, p_cam_ned_m=None):
        self._drain()
        return self._extrapolate(float(t_s), p_cam_ned_m)

    def reset(self) -> None:
        self._epoch += 1
        self._latest = None
        self._window.clear()
        self._snapshot = None
        if self._conn is None:
            return
        try:
            self._conn.send(("reset",))
        except (OSError, ValueError):
            pass

    def _extrapolate(self, t: float, p_cam_ned_m, obs=None):
        latest = self._latest
        if latest is None or latest[0] != self._epoch:
            return None
        return _propagate(latest[1], t, p_cam_ned_m, self.max_extrapolation_s, self._counter, obs, self._noise)

    def close(self, timeout_s: float = 1.0) -> None:
        if self._proc is None:
            return
        try:
            self._conn.send(("stop",))
        except (OSError, ValueError):
            pass
        self._proc.join(timeout_s / 2)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(timeout_s / 2)
        self._conn.close()
        self._proc = None


def _observation(t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam) -> tuple:
    """One estimator observation as the workers take it (and as the process worker pickles it)."""
    return (
        float(t_s),
        tuple(float(x) for x in uv_px),
        intrinsics,
        np.array(p_cam_ned_m, dtype=float),
        np.array(q_ned_from_cam, dtype=float),
    )


def _propagate(est, t: float, p_cam_ned_m, max_extrapolation_s: float, counter: RejectCounter, obs=None, noise=None):
    """``est`` at ``t`` at constant velocity, None beyond ``max_extrapolation_s``.

    ``obs`` (the frame's ``(uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam)``, which ``est`` was solved
    without) with the estimator's ``noise`` model: the propagated position is corrected by the frame's own
    line of sight (:meth:`~onboard.estimation.sliding.TrackEstimate.with_bearing`), so an estimate carried
    over a busy worker's re-selection keeps the target on its current bearing; a bearing outside the
    estimate's gate is counted (``bearing_gate``) and not fused."""
    dt = t - float(est.t_s)
    if abs(dt) > max_extrapolation_s:
        return None
    if dt == 0.0 and p_cam_ned_m is None:
        return est
    try:
        out = est.propagated(t, p_cam_ned_m)
        if obs is not None and noise is not None and dt > 0:
            uv, intrinsics, p_cam, q = obs
            fused = out.with_bearing(
                p_cam,
                line_of_sight_unit_ned(uv, intrinsics, q),
                bearing_sigma_rad(noise, intrinsics),
                noise.camera_position_white_sigma_m,
            )
            if fused is None:
                counter.count(
                    "bearing_gate",
                    f"the frame's line of sight is outside the propagated estimate's gate at t={t:.3f} s",
                )
            else:
                out = fused
        return out
    except (TypeError, ValueError, AttributeError, np.linalg.LinAlgError) as exc:
        counter.count("estimator_error", f"extrapolation: {exc}")
        return None


# --------------------------------------------------------------------------- the service


class OnboardService:
    """The daemon: build with a validated :class:`OnboardConfig`, then :meth:`start`, :meth:`run`, :meth:`close`.

    ``clock`` (s) and ``clock_ns`` are monotonic clocks (fakeable); ``clock_ns`` stamps frame
    receipt and TIMESYNC, so the two are on one clock.
    """

    def __init__(
        self,
        config: OnboardConfig,
        *,
        clock: Callable[[], float] = time.monotonic,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if not isinstance(config, OnboardConfig):
            raise InputError(f"OnboardService needs an OnboardConfig, got {type(config).__name__}")
        self.config = config
        self._clock = clock
        self._clock_ns = clock_ns
        self.counter = LockedCounter(
            log_interval_s=config.logging.reject_log_interval_s,
            clock=clock,
            logger=logging.getLogger("onboard.rejects"),
        )
        self.mount = config.camera.camera_mount()
        self._first_telemetry_s: float | None = None  # when the first attitude/position arrived (watchdog)
        self._next_follow_s = -math.inf  # FOLLOW_TARGET pacing (follow_step)
        buffer = PoseBuffer(
            mount=self.mount,
            config=config.pose_buffer_config(),
            origin=config.pose.geodetic_origin(),
            counter=self.counter,
        )
        self.pose = SharedPoseBuffer(buffer)
        self.queue = FrameQueue(config.input.queue_length)
        ec = config.estimator
        est = None
        if ec.enabled and ec.worker == "process":
            est = ProcessEstimator(config, self.counter, ec.result_wait_ms / 1000.0, ec.max_extrapolation_s)
        elif ec.enabled:
            est = make_estimator(config)
            if ec.worker == "thread":
                est = ThreadedEstimator(est, self.counter, ec.result_wait_ms / 1000.0, ec.max_extrapolation_s)
        self.estimator_kind = "disabled" if est is None else f"sliding window ({ec.worker})"
        self.estimator = est
        wait_s = config.pose.wait_ms / 1000.0
        from onboard.io.zenoh_session import FRAME_SCHEMA

        self._frame_schema = FRAME_SCHEMA  # frames typed with another schema are refused (frame_schema)
        self.recorder = None  # onboard.io.record.FlightRecorder (record.path / --record)
        pose_source = self.pose
        if config.record.path:
            from onboard.io.record import FlightRecorder, RecordingPoseSource, RecordSettings

            self.recorder = FlightRecorder(
                RecordSettings.from_config(config.record),
                vehicle=config.vehicle,
                metadata=_record_metadata(config),
                clock_ns=clock_ns,
            )
            pose_source = RecordingPoseSource(self.pose)  # remembers each frame's pose for the recording
        self.live_view = None  # onboard.io.live_view.LiveView (live_view.port / --live-view)
        if config.live_view.port is not None:
            from onboard.io.live_view import LiveView, LiveViewSettings
            from onboard.io.record import RecordingPoseSource

            if not isinstance(pose_source, RecordingPoseSource):
                pose_source = RecordingPoseSource(self.pose)  # the frame's pose for the 3-D scene
        self.pipeline = FramePipeline(
            config,
            pose_source,
            make_tracker(config),
            est,
            config.pose.geodetic_origin(),
            counter=self.counter,
            pose_wait=(lambda t_us: self.pose.wait_for(t_us, wait_s, self._clock)) if wait_s > 0 else None,
            clock_ns=clock_ns,
        )
        if config.live_view.port is not None:
            self.live_view = LiveView(
                LiveViewSettings.from_config(config.live_view),
                vehicle=config.vehicle,
                intrinsics=self.pipeline.intrinsics,
            )
        self.link = None
        self.gcs = None  # onboard.io.gcs_link.GcsLink: the camera component's sockets (gcs.endpoints)
        self.camera = make_camera_protocol(config, self.pipeline.intrinsics) if config.gcs.endpoints else None
        self._selection_results: collections.deque = collections.deque()  # TrackResults from the pipeline thread
        self.video = None  # onboard.io.video.VideoStreamer (video.destination)
        self.session = None
        self._sub = None
        self._track_pub = None
        self._status_pub = None
        self._stop = threading.Event()
        self._pipe_thread: threading.Thread | None = None
        self._pipe_stop = threading.Event()
        self._stats_lock = threading.Lock()
        self.frames_in = 0
        self.frames_dropped = 0
        self.tracks_published = 0
        self.latency_ms = RollingStats(1000)
        self.queue_wait_ms = RollingStats(1000)
        self.publish_ms = RollingStats(1000)
        self.capture_to_track_ms = RollingStats(1000)
        self._done = collections.deque(maxlen=1000)  # (time_boot_us, published_mono_ns) for capture-to-track
        self._latest: tuple[Track, float] | None = None
        self._pipeline_cpu_s = 0.0
        self._health_path = config.output.health_file
        self._health_failed = False
        self._started_s = clock()
        self.status_count = 0
        self.watchdog = Watchdog(
            started_s=self._started_s,
            frame_key=frame_key_of(config.vehicle),
            zenoh_where=_zenoh_where(config),
            mavlink_connection=config.mavlink.connection,
            camera_size_px=(self.pipeline.intrinsics.width_px, self.pipeline.intrinsics.height_px),
        )

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        """Open MAVLink and zenoh, declare the subscriber/publishers, start the pipeline thread.

        Raises the zenoh adapter's typed errors (port in use ...); a missing peer is not an error.
        """
        import zenoh

        from onboard.io.mavlink_link import MavlinkLink
        from onboard.io.zenoh_session import (
            STATUS_ENCODING,
            TRACK_ENCODING,
            frame_key,
            open_session,
            status_key,
            track_key,
        )

        cfg = self.config
        if self.recorder is not None:
            try:
                self.recorder.start()  # a file that cannot be opened fails the start, in one line
            except OSError as exc:
                raise InputError(
                    f"record.path: cannot write {exc.filename or cfg.record.path}: {exc.strerror or exc}"
                ) from None
        if self.live_view is not None:
            self.live_view.start()  # a port in use fails the start, in one line (InputError)
        self.link = MavlinkLink(
            cfg.mavlink.connection,
            self.pose,
            self.counter,
            gimballed=self.mount.gimballed,
            att_rate_hz=cfg.mavlink.attitude_rate_hz,
            pos_rate_hz=cfg.mavlink.position_rate_hz,
            clock=self._clock,
            clock_ns=self._clock_ns,
            config=cfg.mavlink.link_config(),
        )
        if self.recorder is not None:
            self.link.raw_tap = self.recorder.on_mavlink
        if cfg.video.destination:
            from onboard.io.video import VideoStreamer

            v, K = cfg.video, self.pipeline.intrinsics
            self.video = VideoStreamer(
                v.destination,
                K.width_px,
                K.height_px,
                v.fps,
                v.bitrate_bps,
                v.gop_s,
                v.overlay,
                v.queue_length,
                v.transport,
            )
        if self.camera is not None:
            from onboard.io.gcs_link import GcsLink

            self.gcs = GcsLink(cfg.gcs.endpoints, cfg.gcs.component_id, counter=self.counter)
        self.session = open_session(cfg.zenoh.settings(max_payload_bytes=cfg.input.max_frame_bytes))
        self._track_pub = self.session.declare_publisher(
            track_key(cfg.vehicle),
            encoding=zenoh.Encoding(TRACK_ENCODING),
            congestion_control=zenoh.CongestionControl.DROP,
        )
        self._status_pub = self.session.declare_publisher(
            status_key(cfg.vehicle), encoding=zenoh.Encoding(STATUS_ENCODING)
        )
        self._sub = self.session.declare_subscriber(frame_key(cfg.vehicle), self._on_frame)
        self._pipe_thread = threading.Thread(target=self._pipeline_loop, name="irtrack-pipeline", daemon=True)
        self._pipe_thread.start()
        self._started_s = self._clock()
        self.watchdog.restart(self._started_s)  # the 5 s of the input checks run from here
        log.info(
            "onboard service started: vehicle=%s mavlink=%s frames=%s estimator=%s",
            cfg.vehicle,
            cfg.mavlink.connection,
            frame_key(cfg.vehicle),
            self.estimator_kind,
        )

    def request_stop(self) -> None:
        """Ask :meth:`run` to return (signal-handler safe)."""
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def close(self, timeout_s: float = 1.0) -> None:
        """Stop threads and close everything; bounded by about ``timeout_s`` plus zenoh's close."""
        self._stop.set()
        self._pipe_stop.set()
        self.queue.close()
        if self._pipe_thread is not None:
            self._pipe_thread.join(timeout_s)
            if self._pipe_thread.is_alive():
                log.warning("pipeline thread did not stop within %.1f s", timeout_s)
        if isinstance(self.estimator, (ThreadedEstimator, ProcessEstimator)):
            self.estimator.close(timeout_s / 2)
        for ent in (self._sub, self._track_pub, self._status_pub):
            if ent is not None:
                try:
                    ent.undeclare()
                except Exception as exc:  # noqa: BLE001 - already gone with the session
                    log.debug("zenoh undeclare failed: %s", exc)
        self._sub = self._track_pub = self._status_pub = None
        if self.session is not None:
            try:
                self.session.close()
            except Exception as exc:  # noqa: BLE001
                log.warning("zenoh session close failed: %s", exc)
            self.session = None
        if self.link is not None:
            self.link.close()
        if self.gcs is not None:
            self.gcs.close()
            self.gcs = None
        if self.video is not None:
            self.video.close(timeout_s / 2)
        if self.recorder is not None:
            self.recorder.close(max(timeout_s, 2.0))  # after the pipeline: its last frames are in the file
        if self.live_view is not None:
            self.live_view.close()
        if self._health_path:
            try:
                os.unlink(self._health_path)
            except OSError:
                pass
        if self._pipe_thread is not None:
            log.info(
                "onboard service stopped: %d frames in, %d tracks published", self.frames_in, self.tracks_published
            )

    # ------------------------------------------------------------------ frames in (zenoh thread)

    def _on_frame(self, sample) -> None:
        received = self._clock_ns()
        with self._stats_lock:
            self.frames_in += 1
        try:
            enc = getattr(sample, "encoding", None)
            if enc is not None:  # typed: it must name the IRF1 schema; untyped (octet-stream) is accepted too
                schema = str(enc).partition(";")[2]
                if schema and schema != self._frame_schema:
                    self.counter.count(
                        "frame_schema", f"frame encoding {enc} names another schema than {self._frame_schema}"
                    )
                    return
            payload = sample.payload
            max_bytes = self.config.input.max_frame_bytes
            check_payload_size(len(payload), max_bytes)  # before any copy: a 100x frame costs nothing
            frame = decode_irframe(payload.to_bytes(), max_bytes)  # header checks; pixels stay a view
            if self.recorder is not None:
                self.recorder.on_frame(frame, received)  # never blocks: queued for the writer thread
            if self.live_view is not None:
                self.live_view.on_frame(frame)  # never blocks: dropped and counted when the publisher is behind
        except IrFrameError as exc:
            self.counter.count(f"frame_{exc.reason}", str(exc))
            return
        except Exception as exc:  # noqa: BLE001 - a callback must never raise into zenoh
            self.counter.count("frame_receive_error", f"{type(exc).__name__}: {exc}")
            return
        dropped = self.queue.push((frame, received))
        if dropped:
            with self._stats_lock:
                self.frames_dropped += dropped
            self.counter.count(
                "dropped_queue",
                f"pipeline behind: oldest frame dropped (queue of {self.config.input.queue_length})",
                dropped,
            )

    # ------------------------------------------------------------------ pipeline thread

    def _pipeline_loop(self) -> None:
        name_os_thread("irtrack-pipe")
        health_every_s = self.config.output.health_interval_s
        next_health = -math.inf
        publish = self.config.output.publish_track
        while not self._pipe_stop.is_set():
            now = self._clock()
            if now >= next_health:
                self._touch_health()
                next_health = now + health_every_s
            item = self.queue.pop(min(health_every_s, 0.5))
            if item is None:
                continue
            frame, received_ns = item
            self.queue_wait_ms.add((self._clock_ns() - received_ns) / 1e6)
            c0 = time.thread_time()
            try:
                track = self.pipeline.process(frame, received_ns)
                now_s = self._clock()
                self.watchdog.frame_size(now_s, frame.width_px, frame.height_px)
                self.watchdog.residual(now_s, track.residual_rms_norm)
            except FrameRejected as exc:
                if exc.reason == "dims_mismatch":
                    self.watchdog.frame_size(self._clock(), frame.width_px, frame.height_px)
                continue
            except Exception as exc:  # noqa: BLE001 - never let one frame kill the loop
                self.counter.count("pipeline_error", f"{type(exc).__name__}: {exc}")
                if self.counter["pipeline_error"] == 1:  # the first one with its traceback, on one line
                    log.exception("pipeline error (frame skipped)")
                continue
            finally:
                self._pipeline_cpu_s += time.thread_time() - c0
                if self.recorder is not None or self.live_view is not None:
                    looked_up, pose = self.pipeline.pose_source.take()
                    if self.recorder is not None:
                        self.recorder.on_frame_input(frame, received_ns, looked_up, pose)
                    if self.live_view is not None:
                        self.live_view.on_pose(frame, pose)
            if self.video is not None:
                self.video.submit(frame.pixels, track, frame.time_boot_us)  # never blocks: drops its oldest frame
            payload = None
            if publish and self._track_pub is not None:
                try:
                    p0 = self._clock_ns()
                    payload = track_to_bytes(track)
                    self._track_pub.put(payload)
                    self.publish_ms.add((self._clock_ns() - p0) / 1e6)
                    with self._stats_lock:
                        self.tracks_published += 1
                except Exception as exc:  # noqa: BLE001
                    self.counter.count("track_publish_error", f"{type(exc).__name__}: {exc}")
            if self.recorder is not None:
                self.recorder.on_track(track, payload)
            if self.live_view is not None:
                self.live_view.on_track(track, payload)
            done = self._clock_ns()
            self.latency_ms.add((done - received_ns) / 1e6)
            self._done.append((track.time_boot_us, done))
            self._latest = (track, self._clock())

    def _touch_health(self) -> None:
        if not self._health_path:
            return
        try:
            from onboard.app.health import mark_alive

            mark_alive(self._health_path)
            self._health_failed = False
        except OSError as exc:
            if not self._health_failed:
                log.warning("cannot touch liveness file %s: %s", self._health_path, exc)
            self._health_failed = True

    # ------------------------------------------------------------------ main thread

    def run(self, max_duration_s: float | None = None) -> None:
        """The main loop: MAVLink poll/tick, tracking status out, status JSON; returns when stopped."""
        cfg = self.config
        period = 1.0 / cfg.mavlink.poll_rate_hz
        now = self._clock()
        end = math.inf if max_duration_s is None else now + max_duration_s
        next_status = now + cfg.output.status_interval_s
        last_cpu = (now, time.process_time(), self._pipeline_cpu_s + self._worker_cpu())
        next_watch = now
        turn_s = now
        while not self._stop.is_set() and now < end:
            try:
                self.link.poll()
                self.link.tick()
            except Exception as exc:  # noqa: BLE001 - the link adapter should not raise; be sure
                self.counter.count("mavlink_loop_error", f"{type(exc).__name__}: {exc}")
            now = self._clock()
            try:
                self.camera_step(now)
            except Exception as exc:  # noqa: BLE001 - the camera component must not stop the loop
                self.counter.count("camera_loop_error", f"{type(exc).__name__}: {exc}")
            if now >= next_watch:  # 5 s timeouts: 2 Hz is plenty, the loop itself turns at poll_rate_hz
                self._watch(now)
                next_watch = now + WATCH_PERIOD_S
            try:
                self.follow_step(now)
            except Exception as exc:  # noqa: BLE001 - the follow output must not stop the loop
                self.counter.count("follow_loop_error", f"{type(exc).__name__}: {exc}")
            if now >= next_status:
                last_cpu = self._publish_status(now, last_cpu)
                next_status = max(next_status + cfg.output.status_interval_s, now)
            self._idle(turn_s, period, min(next_watch, next_status))
            turn_s = now = self._clock()

    def _idle(self, turn_s: float, period_s: float, next_own_s: float) -> None:
        """Sleep until MAVLink input arrives (the autopilot link, the camera component's endpoints) or
        the next timer is due (the link's heartbeats and TIMESYNC, the camera's messages, FOLLOW_TARGET,
        the watchdog, the status), at most ``MAIN_LOOP_MAX_IDLE_S``; and never turn more often than
        ``mavlink.poll_rate_hz`` (a flood of datagrams costs at most that many turns).  A fixed-rate
        loop woke 200 times a second whether or not anything had come: ~0.02 CPU s per s on a
        companion-class core for nothing (issue 9 item 7).  Without a file descriptor to wait on (a
        link being reopened, a test double), the loop turns at ``poll_rate_hz`` as it used to."""
        fds: list[int] = []
        link_fd = getattr(self.link, "fileno", lambda: None)()
        if link_fd is not None:
            fds.append(link_fd)
        if self.gcs is not None:
            fds += self.gcs.filenos()
        now = self._clock()
        if not fds:
            self._stop.wait(max(turn_s + period_s - now, 0.0))
            return
        due = [next_own_s, now + getattr(self.link, "seconds_to_next_due", lambda: 0.0)()]
        if self.camera is not None:
            due.append(self.camera.next_due_s())
        if self.config.follow.enabled:
            due.append(self._next_follow_s)
        timeout = min(max(min(due) - now, 0.0), MAIN_LOOP_MAX_IDLE_S)
        try:
            ready, _, _ = select.select(fds, [], [], timeout)
        except (OSError, ValueError):  # a descriptor closed under us: the next turn reopens or counts it
            ready = []
            timeout = 0.0
        if ready or timeout == 0.0:  # the rate cap, for input that was waiting (a flood) or a busy timer
            rest = turn_s + period_s - self._clock()
            if rest > 0:
                time.sleep(rest)

    def _watch(self, now: float) -> None:
        with self._stats_lock:
            frames_in = self.frames_in
        rx = None
        if self.link is not None:
            try:
                rx = int(self.link.status().messages_rx)
            except Exception as exc:  # noqa: BLE001 - a status snapshot must not stop the loop
                self.counter.count("mavlink_loop_error", f"status: {type(exc).__name__}: {exc}")
        self.watchdog.step(now, frames_in=frames_in, mavlink_rx=rx)
        if self.link is not None:
            if self._first_telemetry_s is None and self.pose.newest_time_boot_us() is not None:
                self._first_telemetry_s = now
            self.watchdog.gimbal(
                now,
                gimballed=self.mount.gimballed,
                gimbal_reports=int(getattr(self.link, "gimbal_reports", 0)),
                telemetry_since_s=self._first_telemetry_s,
            )

    def _worker_cpu(self) -> float:
        return getattr(self.estimator, "worker_cpu_s", 0.0)

    def _current_track(self, now: float) -> Track | None:
        latest = self._latest
        if latest is None or now - latest[1] > self.config.output.track_stale_s:
            return None
        return latest[0]

    def follow_step(self, now: float) -> bool:
        """FOLLOW_TARGET (#144) to the autopilot when ``follow.enabled``: the newest track's position at
        most every 1 / ``follow.rate_hz`` s, only when it is observable and not stale (an autopilot
        chasing an unobservable range would chase a guess).  Returns True when one was sent."""
        fc = self.config.follow
        if not fc.enabled or self.link is None or now < self._next_follow_s:
            return False
        from onboard.io.follow import follow_target

        target = follow_target(self._current_track(now))
        if target is None:
            return False
        self._next_follow_s = now + 1.0 / fc.rate_hz
        return bool(self.link.send_follow_target(target))

    def camera_step(self, now: float) -> int:
        """The camera component's turn in the main loop: commands in (tracking requests queued to the
        pipeline), the pipeline's decisions ACKed, heartbeat and #275/#276 out, with the autopilot's
        system id (the link's, else ``mavlink.autopilot_sysid``; a ground station ties the camera to
        that vehicle); silent while neither is known.  Returns
        the number of messages sent."""
        cam, gcs = self.camera, self.gcs
        if cam is None or gcs is None:
            return 0
        sysid = getattr(self.link, "autopilot_sysid", None) or self.config.mavlink.autopilot_sysid
        if sysid is None:
            return 0
        gcs.set_system_id(sysid)
        boot_ms = int((now - self._started_s) * 1000)
        track = self._current_track(now)
        sent = 0
        for cmd in gcs.poll():
            out, request = cam.handle(cmd, now, boot_ms, track)
            for msg in out:
                sent += gcs.send(msg) > 0
            if request is not None:
                self.pipeline.request_selection(request, self._selection_results.append)
        while self._selection_results:
            for msg in cam.complete(self._selection_results.popleft()):
                sent += gcs.send(msg) > 0
        for msg in cam.tick(now, track):
            sent += gcs.send(msg) > 0
        return sent

    def status(
        self, now: float | None = None, cpu_share: float | None = None, pipeline_share: float | None = None
    ) -> dict[str, Any]:
        """The ``irtrack.status/1`` dict now (see :func:`onboard.core.track.build_status`)."""
        now = self._clock() if now is None else now
        self._drain_capture_latency()
        counts = self.counter.counts
        link = None
        if self.link is not None:
            st = self.link.status()
            link = {k: getattr(st, k) for k in st.__dataclass_fields__}
        latest = self._latest
        with self._stats_lock:
            frames_in, dropped, published = self.frames_in, self.frames_dropped, self.tracks_published
        return (
            build_status(
                vehicle=self.config.vehicle,
                uptime_s=now - self._started_s,
                frames_in=frames_in,
                frames_processed=self.pipeline.frames_processed,
                frames_dropped=dropped,
                frames_rejected=sum(
                    v for k, v in counts.items() if k.startswith("frame_") and k not in _ACCEPTED_EVENTS
                ),
                tracks_published=published,
                processing_ms=self.pipeline.processing_ms.summary(),
                latency_ms=self.latency_ms.summary(),
                pose_wait_ms=self.pipeline.pose_wait_ms.summary(),
                capture_to_track_ms=self.capture_to_track_ms.summary() if len(self.capture_to_track_ms) else None,
                rejected=counts,
                link=link,
                cpu_share=cpu_share,
                pipeline_cpu_share=pipeline_share,
                last_track=None if latest is None else latest[0],
                estimator=self.estimator_kind,
                queue_length=len(self.queue),
                queue_wait_ms=self.queue_wait_ms.summary(),
                publish_ms=self.publish_ms.summary(),
                stages_ms={
                    "imaging": self.pipeline.imaging_ms.summary(),
                    "estimator": self.pipeline.estimator_ms.summary(),
                },
                warnings=self.watchdog.active_dicts(),
            )
            | ({"camera": self._camera_status()} if self.camera is not None else {})
            | ({"video": self.video.status()} if self.video is not None else {})
            | ({"record": self.recorder.stats()} if self.recorder is not None else {})
            | ({"live_view": self.live_view.stats()} if self.live_view is not None else {})
        )

    def _camera_status(self) -> dict[str, Any]:
        st = self.camera.status()
        st["endpoints"] = list(self.config.gcs.endpoints)
        st["tracker_mode"] = self.config.gcs.tracker_mode
        st["tracker_holding"] = bool(getattr(self.pipeline.tracker, "holding", False))
        st["last_selection"] = self.pipeline.last_selection
        return st

    def _drain_capture_latency(self) -> None:
        sync = getattr(self.link, "clock_sync", None)
        while self._done:
            t_boot_us, done_ns = self._done.popleft()
            if sync is None or not sync.synced:
                continue
            boot_us = sync.to_boot_us(done_ns)
            if boot_us is not None:
                self.capture_to_track_ms.add((boot_us - t_boot_us) / 1000.0)

    def _publish_status(self, now: float, last_cpu: tuple[float, float, float]) -> tuple[float, float, float]:
        t0, p0, w0 = last_cpu
        p1, w1 = time.process_time(), self._pipeline_cpu_s + self._worker_cpu()
        wall = max(now - t0, 1e-9)
        status = self.status(now, (p1 - p0) / wall, (w1 - w0) / wall)
        try:
            data = json.dumps(status, separators=(",", ":"), allow_nan=False).encode()
        except (TypeError, ValueError) as exc:
            self.counter.count("status_publish_error", f"{type(exc).__name__}: {exc}")
            return now, p1, w1
        if self.recorder is not None:
            self.recorder.on_status(data)
        if self.live_view is not None:
            self.live_view.on_status(data)
        if self._status_pub is not None:
            try:
                self._status_pub.put(data)
                self.status_count += 1
            except Exception as exc:  # noqa: BLE001
                self.counter.count("status_publish_error", f"{type(exc).__name__}: {exc}")
        return now, p1, w1


#: ``frame_*`` counter keys that are accepted events, not refusals
_ACCEPTED_EVENTS = frozenset({"frame_time_reset", "frame_sequence_reset", "frame_stream_restart"})


def make_camera_protocol(config: OnboardConfig, intrinsics):
    """The :class:`~onboard.io.camera_protocol.CameraProtocol` of ``config`` (gcs, output rates, camera)."""
    from onboard.io.camera_protocol import CameraIdentity, CameraProtocol, VideoStream, video_stream_type

    g, o, v = config.gcs, config.output, config.video
    identity = CameraIdentity.from_intrinsics(
        intrinsics.fx_px, intrinsics.width_px, intrinsics.height_px, g.pixel_pitch_um, g.vendor_name, g.model_name
    )
    stream = None
    if v.destination:  # the ground station listens on the destination's port (QGC: udp://0.0.0.0:PORT)
        hfov_deg = math.degrees(2.0 * math.atan(intrinsics.width_px / (2.0 * intrinsics.fx_px)))
        stream = VideoStream(
            video_stream_type(v.transport),
            v.destination.rpartition(":")[2],
            v.fps,
            v.bitrate_bps,
            intrinsics.width_px,
            intrinsics.height_px,
            hfov_deg,
        )
    return CameraProtocol(
        identity,
        intrinsics.width_px,
        intrinsics.height_px,
        component_id=g.component_id,
        stream=stream,
        image_status_hz=o.tracking_image_status_hz,
        geo_status_hz=o.tracking_geo_status_hz,
        observable_only=not o.geo_status_unobservable,
        heartbeat_interval_s=g.heartbeat_interval_s,
        track_request_timeout_s=g.track_request_timeout_s,
    )


def _record_metadata(config: OnboardConfig) -> dict[str, str]:
    """The recording's ``irtrack`` metadata: the effective configuration (replay's default), as YAML."""
    import yaml

    from onboard.app.config import config_to_dict

    return {"config_yaml": yaml.safe_dump(config_to_dict(config), sort_keys=False), "vehicle": config.vehicle}


def frame_key_of(vehicle: str) -> str:
    """The frames' zenoh key (:func:`onboard.io.zenoh_session.frame_key`, without importing zenoh here)."""
    return f"irtrack/{vehicle}/ir/frame"


def _zenoh_where(config: OnboardConfig) -> str:
    """The zenoh session's endpoints and mode in words, for the no-frames warning."""
    z = config.zenoh
    parts = [f"zenoh mode as {z.config_file} sets it (peer by default)" if z.config_file else "zenoh mode peer"]
    parts.append("connect " + (", ".join(z.connect) if z.connect else "none (--zenoh-connect)"))
    parts.append("listen " + (", ".join(z.listen) if z.listen else "none (--zenoh-listen)"))
    scout = {True: "on", False: "off", None: "as the config file says"}[z.multicast_scouting]
    parts.append(f"multicast scouting {scout}")
    return "; ".join(parts)
