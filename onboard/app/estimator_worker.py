"""The estimator off the frame loop: :class:`ThreadedEstimator` (a thread) and :class:`ProcessEstimator`
(a child process, the daemon's default), both with the estimator's interface (``add`` / ``predict`` /
``reset``) plus ``close``.

With a worker, the estimator's periodic model re-selection (tenths of a second) never stalls the frame
loop: a frame waits up to ``estimator.result_wait_ms`` for its own estimate, past that it gets the newest
estimate propagated to its time at constant velocity (``P + dt^2 V``) and corrected by the frame's own
line of sight; the observation is used by the worker either way, no measurement is lost.  A process also
keeps the estimator's Python work off the pipeline's GIL (the frames' latency tail is several times
shorter than with a thread).  A worker process that dies is replaced on the next frame from a fork
server, restored from its last state (:meth:`SlidingWindowEstimator.snapshot`, every
``SNAPSHOT_PERIOD_S``) and the parent's copy of the observations (``estimator_restart``; bridged by the
propagated last estimate meanwhile).

Because a late answer is replaced by a propagated one, the estimates a worker gives depend on timing:
only the inline estimator (``estimator.worker: inline``) gives the same tracks on every run.

The worker talks to the estimator through its public interface only: ``add``, ``reset``, ``carry``,
``snapshot``, ``restore``, ``rebuild``, ``noise`` and ``config`` (read).
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import os
import select
import signal
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any

import numpy as np

from onboard.app.config import OnboardConfig
from onboard.app.estimator_process import SNAPSHOT_PERIOD_S, estimator_process_main
from onboard.app.estimator_wire import (
    MAX_INTRINSICS_SENT,
    framed,
    recv_msg,
    row_message,
    unpack_estimate,
)
from onboard.app.os_thread import name_os_thread
from onboard.core.counters import RejectCounter
from onboard.core.errors import InputError, IrtrackError
from onboard.estimation.map_estimator import MapConfig
from onboard.estimation.sliding import (
    SlidingWindowEstimator,
    bearing_sigma_rad,
    line_of_sight_unit_ned,
    range_floored,
)
from onboard.io.worker_queue import items_until_stopped, stop_and_join
from onboard.pipeline.frame_pipeline import make_estimator

__all__ = [
    "ESTIMATE_QUEUE_MAX",
    "EstimatorStartError",
    "as_observation",
    "SNAPSHOT_PERIOD_S",
    "FORKSERVER_PRELOAD",
    "ThreadedEstimator",
    "ProcessEstimator",
    "make_estimator_worker",
]

log = logging.getLogger(__name__)

ESTIMATE_QUEUE_MAX = 1000  # observations waiting for the estimator worker (about 30 s at 30 Hz)
# imported once by the estimator workers' fork server, so that a replacement worker neither imports them
# nor pays their first use inside its first model selection (a cold scipy.stats makes the first window
# rebuild several times slower); onboard.app.main first: it sets one BLAS thread
FORKSERVER_PRELOAD = [
    "onboard.app.main",
    "onboard.app.estimator_worker",
    "onboard.app.estimator_process",
    "onboard.estimation.sliding",
    "scipy.stats",
]


class EstimatorStartError(IrtrackError):
    """The estimator's first worker process could not be started (its fork server failed): the daemon ends on it,
    with exit code 1, as when it waited for that worker before serving."""


class _Carried:
    """What both workers' callers share: the newest estimate of the current epoch carried to a frame's time
    (:func:`_propagate`) when the worker's own answer is late, and the gap in the frames that makes an old one no
    sign of overload (``_gap_end_t``)."""

    _latest: Any
    _epoch: int
    max_extrapolation_s: float
    _counter: Any
    _noise: Any
    _map_config: Any
    #: the first frame after the latest gap in the frames longer than ``max_extrapolation_s`` (:meth:`_note_frame`)
    _gap_end_t: float = -math.inf

    def _note_frame(self, t: float, previous_t: float | None) -> None:
        """A frame at ``t``, the one before it at ``previous_t`` (None: none): frames that stopped coming for longer
        than an estimate is carried (a camera or network outage) make the newest estimate old because nothing came,
        not because the daemon is behind, until an estimate made after them comes."""
        if previous_t is not None and t - previous_t > self.max_extrapolation_s:
            self._gap_end_t = t

    def _extrapolate(self, t: float, p_cam_ned_m, obs=None):
        latest = self._latest
        if latest is None or latest[0] != self._epoch:
            return None
        return _propagate(
            latest[1],
            t,
            p_cam_ned_m,
            self.max_extrapolation_s,
            self._counter,
            obs,
            self._noise,
            self._map_config,
            after_gap=obs is not None and float(latest[1].t_s) < self._gap_end_t,
        )


class ThreadedEstimator(_Carried):
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
        self._noise = getattr(estimator, "noise", None)  # for the bearing update (_propagate)
        estimator_map = getattr(estimator, "map", None)  # and its range floor (an estimator of a test may have none)
        self._map_config = getattr(estimator_map, "config", None)
        self._counter = counter
        self.result_wait_s = float(result_wait_s)
        self.max_extrapolation_s = float(max_extrapolation_s)
        self._max_pending = max_pending
        self._q: collections.deque = collections.deque()
        self._cond = threading.Condition(threading.Lock())
        self._epoch = 0
        self._latest: tuple[int, Any] | None = None  # (epoch, estimate): the newest non-None estimate
        self._result: tuple[int, float, Any] | None = None  # (epoch, t_s, estimate or None): the last processed
        self._stop = threading.Event()
        self.worker_cpu_s = 0.0
        self.late_results = 0
        self._last_add_t: float | None = None
        self._thread = threading.Thread(target=self._run, name="irtrack-estimator", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ caller side

    def add(self, t_s: float, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam):
        args = as_observation(t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam)
        t = args[0]
        self._note_frame(t, self._last_add_t)
        self._last_add_t = t
        deadline = time.monotonic() + self.result_wait_s
        with self._cond:
            if len(self._q) >= self._max_pending:
                # the oldest observation, never a queued reset or rebuild (it heads the queue it cleared): dropping
                # one would add the new track's rows to the old window under the new epoch, unseen
                oldest = next((i for i, item in enumerate(self._q) if item[0] == "add"), None)
                if oldest is not None:
                    del self._q[oldest]
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

    def rebuild(self, rows) -> None:
        """Replace the window with ``rows`` (``add``'s arguments, oldest first: the same frames at a new camera
        clock compensation), made by the worker with one model selection (:meth:`SlidingWindowEstimator.rebuild`).
        Returns None: the estimate comes with the next frames."""
        packed = [as_observation(*r) for r in rows]
        with self._cond:
            self._epoch += 1
            self._q.clear()
            self._q.append(("rebuild", self._epoch, packed[-1][0] if packed else None, packed))
            self._latest = None
            self._result = None
            self._cond.notify_all()

    def reset(self) -> None:
        with self._cond:
            self._epoch += 1
            self._q.clear()
            self._q.append(("reset", self._epoch, None, None))
            self._latest = None
            self._result = None
            self._cond.notify_all()

    def close(self, timeout_s: float = 1.0) -> None:
        stop_and_join(self._cond, self._stop, self._thread, timeout_s)

    # ------------------------------------------------------------------ worker

    def _run(self) -> None:
        name_os_thread("irtrack-estim")
        for kind, epoch, t, args in items_until_stopped(self._cond, self._q, self._stop.is_set):
            c0 = time.thread_time()
            est = None
            try:
                if kind == "reset":
                    self._est.reset()
                    continue
                est = self._est.rebuild(args) if kind == "rebuild" else self._est.add(*args)
            except InputError as exc:
                self._counter.count("estimator_input", str(exc))
            except Exception as exc:  # noqa: BLE001 - the worker must never die
                self._counter.count("estimator_error", f"{type(self._est).__name__}: {type(exc).__name__}: {exc}")
            finally:
                self.worker_cpu_s += time.thread_time() - c0
            with self._cond:
                if epoch == self._epoch:
                    if kind == "rebuild":
                        self._latest = (epoch, est) if est is not None else self._latest
                        continue
                    self._result = (epoch, t, est)
                    if est is not None:
                        self._latest = (epoch, est)
                    self._cond.notify_all()

    @property
    def pending(self) -> int:
        return len(self._q)


def _start_fork_server() -> None:
    """Start the fork server (if not running) with SIGINT blocked: it inherits the mask, so a Ctrl-C in the
    terminal, which reaches the whole process group, never prints a traceback from a fork server still
    importing its preload (it ignores SIGINT once it serves); the parent stops it.  A Ctrl-C that comes
    meanwhile reaches this process when the mask is restored.  The resource tracker first: its own start
    unblocks SIGINT (it protects itself the same way)."""
    from multiprocessing import forkserver, resource_tracker

    resource_tracker.ensure_running()
    if not hasattr(signal, "pthread_sigmask"):
        forkserver.ensure_running()
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        forkserver.ensure_running()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


class ProcessEstimator(_Carried):
    """The estimator interface with the estimator in a child process (no GIL shared with the frames).

    Same contract as :class:`ThreadedEstimator`: ``add`` sends the observation and waits up to
    ``result_wait_s`` for its estimate, else returns the newest estimate propagated to ``t_s``;
    ``predict`` never waits.  Results are read by the caller's thread (no extra thread here).

    **A worker that dies** (killed, OOM, crashed) is noticed on the next ``add``, counted
    (``estimator_restart``, logged with its exit code) and replaced at once.  The parent keeps its
    own copy of the window (the rows the estimator keeps: the last ``window_s``, one per
    ``min_spacing_s``, at most ``max_frames``; about 25 kB) and the worker's newest state (a snapshot
    the worker sends every ``SNAPSHOT_PERIOD_S`` of observation time, ~0.9 MB, a few ms to make; :meth:`SlidingWindowEstimator.snapshot`).  The
    new worker is handed both: it restores the state and adds the rows that came after it
    (milliseconds; :meth:`SlidingWindowEstimator.restore`), or, without a usable snapshot, rebuilds the window with a single
    cold model selection (:meth:`SlidingWindowEstimator.rebuild`: tenths of a CPU second for a full window).  Either way 3-D
    output resumes without waiting for a new window to fill.  In between, the newest estimate keeps being propagated (up to
    ``max_extrapolation_s``), as when the worker is busy.  A worker that dies before it answered
    anything (a crash at start, or on an observation the rebuild replays) is replaced after a delay
    that starts at ``RESTART_BACKOFF_MIN_S`` and doubles each time (up to ``RESTART_BACKOFF_MAX_S``),
    so a crash loop cannot spawn a process per frame.  The replacement is spawned on a thread, so that a fork
    server gone with the worker (it then imports the estimator's modules again: a second or more) never holds the
    frames; a frame waits for it no longer than for its estimate (``result_wait_s``).

    **The first worker** is spawned on a thread too, from the constructor: its fork server imports the estimator's
    modules (a second or more) while the daemon opens its links, instead of before it serves.  The frames that come
    first are kept for it and carried, as for a replacement, and the first frame after it is there takes it.  A first
    worker that cannot be started is counted (``estimator_error``) on the next frame and :attr:`start_error` says
    why: the daemon ends on it (:class:`EstimatorStartError`), as it did when the constructor raised it.
    :meth:`close` during that start stops the fork server, which would otherwise outlive the daemon.

    **A worker that hangs** (alive, answering nothing: stopped, deadlocked, spinning) would let the pipe to it fill
    and the next row's write block the frame loop: a worker sent rows it has not answered for ``HUNG_S`` is killed
    (counted ``estimator_hung``) and replaced as a dead one.  No selection or rebuild comes near it; a CPU quota
    that starves it that long loses its state to a restore, no more.
    """

    RESTART_BACKOFF_MIN_S = 1.0
    RESTART_BACKOFF_MAX_S = 30.0
    HUNG_S = 5.0

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
        # and its range floor: the config the worker's estimator solves with (make_estimator builds it so)
        self._map_config = SlidingWindowEstimator.default_map_config(config.estimator.sliding_config())
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
        self._latest: tuple[int, Any] | None = None  # (epoch, estimate)
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
        self._proc: BaseProcess | None = None
        self._conn: Connection | None = None
        # what _adopt sets for each worker, as it stands before the first one (silent_s, the hang check)
        self._out = bytearray()
        self._intrinsics_sent: list = []
        self._answered = False
        self._unanswered_since_s: float | None = None
        self._starting: _WorkerStart | None = None  # a worker being spawned: the first, or a replacement
        self._first_start = self._begin_start()  # for start_error

    @property
    def pid(self) -> int | None:
        """The worker's process id (None while there is none: before the first frame takes the first worker too)."""
        return None if self._proc is None else self._proc.pid

    @property
    def starting(self) -> bool:
        """A worker (the first, or a replacement) is being spawned and is not there yet."""
        start = self._starting
        return start is not None and start.thread.is_alive()

    @property
    def start_error(self) -> Exception | None:
        """Why the first worker could not be started (None: it started, or is still starting).  Read by another thread
        than the frames' (the daemon's main loop): the start's outcome, set once by its own thread."""
        return self._first_start.error

    def _spawn(self) -> tuple[BaseProcess, Connection]:
        """A new worker process and the parent's end of its pipe.  Blocks until the fork server has forked it:
        milliseconds, unless the fork server has to be started again first (it imports the preload: a second or
        more), which is why a replacement is spawned on a thread (:meth:`_begin_start`)."""
        parent, child = self._ctx.Pipe()
        proc = self._ctx.Process(
            target=estimator_process_main, args=(child, self._config), name="irtrack-estimator", daemon=True
        )
        try:
            _start_fork_server()
            proc.start()
        except BaseException:
            parent.close()
            raise
        finally:
            child.close()
        return proc, parent

    def _begin_start(self) -> _WorkerStart:
        """Spawn a worker on a thread (the first one, or a replacement): the frame loop goes on (carried estimates)
        while its fork server starts (the first one, or one that died with the worker), and adopts the worker when it
        is there (:meth:`_adopt_started`).  The fork server is launched here (milliseconds: it then imports its
        preload for a second or more, by itself), not by the thread: a :meth:`close` right after finds it and stops it,
        whatever the thread has reached."""
        try:
            _start_fork_server()
        except Exception:  # noqa: BLE001 - the thread's spawn tries it again, and what fails there is counted
            pass
        self._starting = start = _WorkerStart(self._spawn, self._clock())
        return start

    def _adopt_started(self, wait_s: float) -> bool:
        """Take the worker :meth:`_begin_start` spawned, waiting up to ``wait_s`` for it; False while it is not
        there yet, or when it could not be started (counted; tried again after the crash back-off)."""
        start = self._starting
        assert start is not None
        start.thread.join(wait_s)
        if start.thread.is_alive():
            if not start.slow_counted and self._clock() - start.since_s >= self.HUNG_S:
                start.slow_counted = True
                self._counter.count(
                    "estimator_hung", f"estimator process not started after {self.HUNG_S:.0f} s (its fork server)"
                )
            return False
        self._starting = None
        if start.worker is None:
            self._counter.count("estimator_error", f"estimator process could not be started: {start.error}")
            self._backoff_s = min(max(2 * self._backoff_s, self.RESTART_BACKOFF_MIN_S), self.RESTART_BACKOFF_MAX_S)
            self._next_start_s = self._clock() + self._backoff_s
            return False
        self._adopt(*start.worker)
        return True

    def _adopt(self, proc: BaseProcess, parent: Connection) -> None:
        self._proc = proc
        self._conn = parent
        # the parent never waits on the pipe: what it cannot take now waits in _out, written as it drains (a
        # replacement's snapshot, near a megabyte, would otherwise hold the frame loop for the new worker's start)
        os.set_blocking(parent.fileno(), False)
        self._out = bytearray()  # bytes for this worker the pipe has not taken yet (_send)
        self._intrinsics_sent = []  # the camera models this worker has, by index (_intrinsics_index)
        # Connection.poll and Process.is_alive build a selector on every call (~7 and ~16 us, the pipeline
        # thread's two checks per frame): one poll object each, made once per worker
        self._answers = select.poll()
        self._answers.register(parent.fileno(), select.POLLIN)
        self._exit = select.poll()
        self._exit.register(self._proc.sentinel, select.POLLIN)
        self._cpu_base = self.worker_cpu_s
        self._started_s = self._clock()
        self._answered = False  # no result from this worker yet
        self._unanswered_since_s = None  # the first row sent since the worker last answered

    def _alive(self) -> bool:
        proc = self._proc
        if proc is None:
            return False
        pid = proc.pid
        if pid is not None and not self._exit.poll(0):  # the fork server writes the exit code on the sentinel
            try:
                os.kill(pid, 0)  # and if something else read that code (a join), the pid is gone
                return True
            except (ProcessLookupError, PermissionError):  # gone, or another user's process by now
                pass
        return proc.is_alive()  # reads the exit code

    def _replace_dead_worker(self) -> bool:
        """Start a new worker with the window rebuilt; False while a crash loop's back-off lasts or the new worker
        is still being spawned."""
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
                if self._conn is not None:
                    self._conn.close()
            except OSError:
                pass
            self._proc.join(0)
            self._proc, self._conn = None, None
        if self._starting is None:
            if now < self._next_start_s:
                return False
            self._begin_start()
        # the frame's own wait for its estimate is also what it may wait for the new worker (the fork server
        # alive, a start takes milliseconds)
        if not self._adopt_started(self.result_wait_s):
            return False
        if self._window:
            snap = self._snapshot
            if snap is not None and snap[0] < self._window[0][0]:
                snap = None  # older than the window: rebuild instead (a reset clears both)
            self._send(("rebuild", self._epoch, self._packed_window(), snap))
        return True

    def _send(self, msg: tuple) -> bool:
        """``msg`` to the worker, behind what is still waiting to go, never blocking; False (counted) when the pipe
        is gone."""
        try:
            self._queue(msg)
        except (OSError, ValueError) as exc:
            self._counter.count("estimator_error", f"send to the estimator process: {exc}")
            return False
        return True

    def _queue(self, msg: tuple) -> None:
        """``msg`` behind what waits for the worker, and as much written as the pipe takes (OSError, ValueError:
        the pipe is gone)."""
        if self._conn is None:
            raise OSError("no estimator process")
        self._out += framed(msg)
        self._flush_out()

    def _flush_out(self) -> None:
        """Write what the pipe takes now of the bytes waiting for the worker (OSError when it is gone)."""
        out = self._out
        if not out or self._conn is None:
            return
        try:
            n = os.write(self._conn.fileno(), out)
        except BlockingIOError:
            return
        del out[:n]

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

    def _intrinsics_index(self, intrinsics) -> int:
        """The index the worker knows ``intrinsics`` by, sent to it first when new (``-1``: could not be sent,
        the row then fails in the worker and is counted there as an estimator error)."""
        known = self._intrinsics_sent
        for i, k in enumerate(known):
            if k is intrinsics:
                return i
        for i, k in enumerate(known):
            if k == intrinsics:
                return i
        if len(known) >= MAX_INTRINSICS_SENT:
            known.clear()  # indices start again; the worker's entries are overwritten in order
        known.append(intrinsics)
        index = len(known) - 1
        return index if self._send(("intrinsics", index, intrinsics)) else -1

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
        with contextlib.suppress(OSError):
            self._flush_out()
        deadline = time.monotonic() + wait_s
        found, value = False, None
        fd = self._conn.fileno()
        while True:
            left = deadline - time.monotonic() if until_t is not None and not found else 0.0
            sending = bool(self._out)  # bytes still for the worker: written as it reads them, while waiting here
            try:  # milliseconds rounded up, as Connection.poll does
                if sending:
                    self._answers.modify(fd, select.POLLIN | select.POLLOUT)
                events = self._answers.poll(math.ceil(left * 1e3) if left > 0 else 0)
                if sending:
                    self._answers.modify(fd, select.POLLIN)
            except (OSError, ValueError):
                return found, value
            if not events:
                return found, value
            if events[0][1] & select.POLLOUT:
                with contextlib.suppress(OSError):
                    self._flush_out()
                if not events[0][1] & ~select.POLLOUT:  # writable only: no answer yet
                    continue
            try:
                epoch, t, packed, err, cpu_s, snapshot = recv_msg(self._conn)
            except (OSError, EOFError):
                return found, value
            est = unpack_estimate(packed)
            self.worker_cpu_s = self._cpu_base + cpu_s
            self._answered = True
            self._unanswered_since_s = None
            if err is not None:
                self._counter.count(*err)
            if epoch != self._epoch:
                continue
            if snapshot is not None:
                self._snapshot = snapshot  # (t_s of its newest row, bytes)
            if est is not None:
                self._latest = (epoch, est)
            if until_t is not None and t == until_t:
                return True, est  # the rest, if any, on the next call: no poll that finds nothing, per frame

    def add(self, t_s: float, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam):
        args = as_observation(t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam)
        t = args[0]
        w = self._window
        self._note_frame(t, w[-1][0] if w else None)
        self._kill_if_hung()
        if not self._alive() and not self._replace_dead_worker():
            self._remember(args)  # kept for the replacement
            self.late_results += 1
            return self._extrapolate(t, p_cam_ned_m, args[1:])
        if w and 0.0 < t - w[-1][0] < self._min_spacing_s:
            # the worker would not keep this row and would answer with its estimate at the newest kept row
            # carried to t: when that answer is here, carry it here (same numbers, no round trip: half the
            # frames at 30 Hz)
            self._drain()
            latest = self._latest
            if latest is not None and latest[0] == self._epoch and latest[1].t_s == w[-1][0]:
                self.carried += 1
                return self._local.carry(latest[1], t, p_cam_ned_m)
        self._remember(args)
        msg = row_message(self._epoch, args, self._intrinsics_index(args[2]))
        if not self._send(("add", self._epoch, t, args) if msg is None else msg):
            return self._extrapolate(t, p_cam_ned_m, args[1:])
        if self._unanswered_since_s is None:
            self._unanswered_since_s = self._clock()
        found, est = self._drain(t, self.result_wait_s)
        if found:
            return est
        self.late_results += 1
        return self._extrapolate(t, p_cam_ned_m, args[1:])

    @property
    def silent_s(self) -> float:
        """How long the worker has answered none of the rows sent to it (s; 0 when it is up to date): a stopped or
        stalled process, killed and replaced at ``HUNG_S``."""
        since = self._unanswered_since_s
        return 0.0 if since is None else max(self._clock() - since, 0.0)

    def _kill_if_hung(self) -> None:
        """Kill a worker that answered none of the rows sent to it for ``HUNG_S`` (class docstring); the caller's
        liveness check then replaces it."""
        since = self._unanswered_since_s
        if since is None or self._proc is None or self._clock() - since < self.HUNG_S:
            return
        self._drain()  # its answers may be waiting unread
        if self._unanswered_since_s is None:
            return
        self._counter.count(
            "estimator_hung",
            f"estimator process answered nothing for {self._clock() - since:.1f} s; killed and replaced",
        )
        self._unanswered_since_s = None
        self._proc.kill()  # SIGKILL: a stopped or spinning process ignores a polite request
        self._proc.join(1.0)

    def predict(self, t_s: float, p_cam_ned_m=None):
        self._drain()
        return self._extrapolate(float(t_s), p_cam_ned_m)

    def rebuild(self, rows) -> None:
        """Replace the window with ``rows`` (``add``'s arguments, oldest first: the same frames at a new camera
        clock compensation), made by the worker with one model selection, as for a replacement worker.  Returns
        None: the estimate comes with the next frames."""
        self.reset()
        for r in rows:
            self._remember(as_observation(*r))
        if self._window and self._alive():
            self._send(("rebuild", self._epoch, self._packed_window(), None))

    def reset(self) -> None:
        self._epoch += 1
        self._latest = None
        self._window.clear()
        self._snapshot = None
        if self._conn is None:
            return
        with contextlib.suppress(OSError, ValueError):  # a dead worker is found and replaced by the next add
            self._queue(("reset",))

    def close(self, timeout_s: float = 1.0) -> None:
        starting, self._starting = self._starting, None
        if starting is not None:  # a worker being spawned: stopped with the rest, never left running
            starting.thread.join(min(timeout_s / 2, 0.05))  # a start with the fork server up is milliseconds
            if starting.thread.is_alive():
                _stop_fork_server()  # still importing its preload: it would outlive this process
            worker = starting.close()
            if worker is not None:
                if self._proc is None:
                    self._adopt(*worker)
                else:
                    _stop_unadopted(*worker)
        proc, conn = self._proc, self._conn
        if proc is None or conn is None:
            return
        with contextlib.suppress(OSError, ValueError):  # a hung worker's full pipe: it is killed below instead
            self._queue(("stop",))
        proc.join(timeout_s / 2)
        if proc.is_alive():
            proc.terminate()
            proc.join(timeout_s / 4)
        if proc.is_alive():
            proc.kill()  # a stopped process does not act on SIGTERM
            proc.join(timeout_s / 4)
        conn.close()
        self._proc = None


class _WorkerStart:
    """A worker (the first, or a replacement) being spawned on a thread (:meth:`ProcessEstimator._begin_start`):
    ``worker`` once it is there, ``error`` when it could not be started.  :meth:`close` and the thread hand over under a
    lock, so that a worker made after the estimator closed is stopped by the thread itself, not left running, and so is
    the fork server its spawn started again after close() had stopped the first."""

    def __init__(self, spawn: Callable[[], tuple[BaseProcess, Connection]], since_s: float) -> None:
        self.since_s = since_s
        self.slow_counted = False  # estimator_hung counted for it
        self.worker: tuple[BaseProcess, Connection] | None = None
        self.error: Exception | None = None
        self._lock = threading.Lock()
        self._closed = False
        self.thread = threading.Thread(target=self._run, args=(spawn,), name="irtrack-estimator-start", daemon=True)
        self.thread.start()

    def _run(self, spawn: Callable[[], tuple[BaseProcess, Connection]]) -> None:
        name_os_thread("irtrack-est-start")
        if self._closed:  # close() came before the thread ran: nothing to start
            return
        try:
            worker = spawn()
        except Exception as exc:  # noqa: BLE001 - any failure to start is counted by the frame loop
            self.error = exc
            return
        with self._lock:
            if not self._closed:
                self.worker = worker
                return
        _stop_unadopted(*worker)  # close() came first and did not wait for it
        # ... and stopped the fork server, which this spawn, not yet connected to it (pickling the worker's config),
        # found dead and started again: the worker came from that one, which would otherwise outlive the estimator
        _stop_fork_server()

    def close(self) -> tuple[BaseProcess, Connection] | None:
        """No taker after this: the worker made by now (the caller takes or stops it), or None (the thread stops
        the one it makes)."""
        with self._lock:
            self._closed = True
            return self.worker


def _stop_fork_server() -> None:
    """SIGKILL the workers' fork server (if any).  One that is still importing its preload reads neither its pipe
    from this process nor SIGINT (blocked: :func:`_start_fork_server`) until that is done, a second or more: a daemon
    stopped meanwhile left it running past its own exit, holding the daemon's stderr open, and it then forked a worker
    for the gone daemon.  multiprocessing reaps it, and starts another, when a worker is next spawned.

    Every :class:`ProcessEstimator` of this process shares it (the daemon has one; only tests make several): one
    closed during its start makes another's spawn fail (counted, tried again after the back-off) and makes its running
    worker, whose liveness pipe the fork server holds, look dead: replaced, the old process left until its own pipe
    closes."""
    from multiprocessing import forkserver

    pid = getattr(forkserver._forkserver, "_forkserver_pid", None)  # private: the stdlib has no public stop
    if pid is not None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGKILL)


def _stop_unadopted(proc: BaseProcess, conn: Connection) -> None:
    """Stop a worker no estimator took (spawned after, or beside, the one it has): its pipe closed, killed, reaped."""
    conn.close()
    proc.kill()
    proc.join(1.0)


def as_observation(t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam) -> tuple:
    """One estimator observation as the workers take it (and as the process worker pickles it)."""
    return (
        float(t_s),
        tuple(float(x) for x in uv_px),
        intrinsics,
        np.array(p_cam_ned_m, dtype=float),
        np.array(q_ned_from_cam, dtype=float),
    )


def _propagate(
    est,
    t: float,
    p_cam_ned_m,
    max_extrapolation_s: float,
    counter: RejectCounter,
    obs=None,
    noise=None,
    map_config: MapConfig | None = None,
    after_gap: bool = False,
):
    """``est`` at ``t`` at constant velocity, None beyond ``max_extrapolation_s`` (a frame's position withheld then:
    counted ``estimate_stale``, the daemon behind, or ``estimate_after_gap`` when the frames themselves had stopped
    for longer, ``after_gap``: nothing to keep up with, so no sign of overload).

    ``obs`` (the frame's ``(uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam)``, which ``est`` was solved
    without) with the estimator's ``noise`` model: the propagated position is corrected by the frame's own
    line of sight (:meth:`~onboard.estimation.sliding.TrackEstimate.with_bearing`), so an estimate carried
    over a busy worker's re-selection keeps the target on its current bearing; a bearing outside the
    estimate's gate is counted (``bearing_gate``) and not fused.  An unobservable estimate then gets the
    estimator's range floor (``map_config``'s) again along its new line of sight
    (:func:`~onboard.estimation.sliding.range_floored`), as the estimator's own carried estimates do."""
    dt = t - float(est.t_s)
    if abs(dt) > max_extrapolation_s:
        if obs is not None and after_gap:  # the first frames after an outage of the frames: not the daemon's lag
            counter.count(
                "estimate_after_gap",
                f"newest estimate {dt:.2f} s older than the frame, the first after a gap in the frames: position "
                "withheld until the estimator answers",
                level=logging.INFO,
            )
        elif obs is not None:  # a frame's own position withheld (not a query between frames): the daemon is behind
            counter.count(
                "estimate_stale",
                f"newest estimate {dt:.2f} s older than the frame (estimator.max_extrapolation_s "
                f"{max_extrapolation_s:g}): position withheld",
            )
        return None
    if dt == 0.0 and p_cam_ned_m is None:
        return est
    try:
        out = est.propagated(t, p_cam_ned_m)
        camera = p_cam_ned_m
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
                out, camera = fused, p_cam
        if map_config is not None and camera is not None:
            out = range_floored(out, camera, map_config)
        return out
    except (TypeError, ValueError, AttributeError, np.linalg.LinAlgError) as exc:
        counter.count("estimator_error", f"extrapolation: {exc}")
        return None


def make_estimator_worker(config: OnboardConfig, counter: RejectCounter) -> Any:
    """The estimator the frame pipeline calls, where ``estimator.worker`` puts it: a
    :class:`ProcessEstimator` (``process``), a :class:`ThreadedEstimator` (``thread``), the estimator
    itself (``inline``); None when ``estimator.enabled`` is false."""
    ec = config.estimator
    if not ec.enabled:
        return None
    if ec.worker == "process":
        return ProcessEstimator(config, counter, ec.result_wait_ms / 1000.0, ec.max_extrapolation_s)
    est = make_estimator(config)
    if ec.worker == "thread":
        return ThreadedEstimator(est, counter, ec.result_wait_ms / 1000.0, ec.max_extrapolation_s)
    return est
