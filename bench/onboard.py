"""Benchmark of the onboard daemon: loopback latency through it, and per-frame processing on one core.

``python -m bench.onboard [--frames N] [--latency-s S] [--no-latency] [--parts-s S] [--paced] [--chain objects|single]
[--scene C1 [--scene-s S]]``.
Prints (with ``--scene``, only the daemon's CPU on that scenario's flight: :mod:`bench.onboard_scene`):

* Loopback latency through the real daemon (``python -m onboard`` as a subprocess on 127.0.0.1,
  default configuration: estimator in a worker process): a fake autopilot (pymavlink, UDP) sends
  attitude (with the scene's body rates)/position at 100/25 Hz (``--attitude-rate-hz``: the daemon's default
  otherwise), a zenoh publisher sends 640 x 512
  frames at 30 Hz; the time from the ``put`` of a frame to the arrival of its track message,
  p50/p90/p99/max, over ``--latency-s`` seconds after a 2 s settling time; once per
  ``--capture-lags-ms`` (default 0, 10, 25, 50): frames stamped that long before they are sent (a
  camera's own latency; at 0 the telemetry after the frame has not arrived yet: the objects chain waits for
  the frame's attitude sample, ``imaging.pose_wait_ms`` at most, and the frame's pose ``pose.wait_ms`` at most,
  then extrapolates).  ``--chain``: the daemon's image chain (default: its configuration's, objects).  Also the daemon's own status numbers: frames
  dropped in the window, queue wait, processing and its imaging/estimator stages, pose wait,
  extrapolated poses and misses, CPU share; and the daemon's CPU over the timed window as CPU
  seconds per simulated second, summed over all its processes (the estimator worker process
  included) from /proc, beside the median per-frame processing.  A summary table ends the part.
* Per-frame processing on one core (the process pinned to one CPU, one BLAS and one OpenCV
  thread), synthetic frames (a Gaussian blob moving on a smooth background with 1 grey-level
  noise; observer circling at 8 m/s, target 150-180 m away), through
  ``FramePipeline.process_payload`` with the estimator inline = decode + filter + detect + track +
  pose lookup + sliding-window estimator: per-frame p10/p50/p90/p99, frames/s from the median and
  the mean, each stage's median (decode, imaging, estimator ``add``), the share of frames hit by
  the estimator's periodic model re-selection, the 3-D error of the last frame, and the same chain
  without the estimator as a baseline measured in the same run.

* With ``--paced``: the per-frame processing again over the same frames, one every 1/30 s (a sleep before
  each), its CPU per frame (thread clock, the last half: the estimator's window full) against back to back:
  the daemon's per-frame work as in flight, with none of its threads, processes, sockets or JSON.

* With ``--floor-s S``: the daemon's floor, its I/O with nothing done (:mod:`bench.onboard_floor`): zenoh frames
  in (and a track out), MAVLink in, the worker's round trips, a thread woken at 30 Hz, each in a child interpreter.

* With ``--parts-s S``: two parts of the daemon alone, each paced as in flight for ``S`` seconds, CPU
  s per s from the thread and process clocks (``--parts-repeats`` times, alternating): the main loop's
  telemetry input (a thread in ``select`` on a :class:`MavlinkLink` that polls it, the fake autopilot
  sending attitude / position at the daemon's default rates, 100 / 25 Hz) and the estimator hand-off (a :class:`ProcessEstimator`
  fed the scene at 30 Hz once its 20 s window is full: the caller thread's CPU, the worker process's,
  the frames answered late).  Smaller than the daemon's figures and steadier than them on a loaded
  machine: before/after figures of one part.

The autopilot of the latency benchmark is the tests' fake (``groundsim.io.scripted_autopilot.ScriptedAutopilot``, MAVLink
through :mod:`onboard.io.mavlink_wire`) flying :class:`SyntheticScene`'s observer.

Numbers only; nothing asserts on time.  The machine's load average is printed first: on a shared
2-core box the tails (p99, max) follow the other load.  So is its speed, before and after the latency runs
(:func:`bench.machine_speed_ms`: a fixed Python loop's CPU time; this VM's drifts by +-25 % between minutes,
and every CPU figure with it).  :class:`SyntheticScene` is also a fixture of
``tests/onboard/test_pipeline.py`` and ``test_service.py``.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field

from onboard.core.blas import single_thread_blas_env  # noqa: E402 - imports nothing but os

if __name__ == "__main__":  # one BLAS thread, as the daemon; must precede the numpy import
    single_thread_blas_env()

import numpy as np  # noqa: E402

from bench import frame_speed_ms, machine_speed_ms, pacing_factor, pin_to_one_cpu, run_benchmark  # noqa: E402
from bench.options import (  # noqa: E402
    BenchParser,
    known_scenario,
    nonnegative_number,
    positive_float,
    positive_int,
)
from groundsim.io.ports import free_tcp_port, free_udp_port  # noqa: E402
from onboard.core.frames import (  # noqa: E402
    CameraMount,
    GeodeticOrigin,
    PinholeIntrinsics,
    geodetic_from_ned,
    quat_conjugate,
    quat_from_rotmat,
    quat_multiply,
    quat_normalize,
    rotmat_from_quat,
    rotvec_from_quat,
)
from onboard.core.irframe import IrFrame, encode_irframe  # noqa: E402

__all__ = ["SyntheticScene", "bench_processing", "bench_latency", "main"]

ORIGIN = GeodeticOrigin(32.0, 118.8, 0.0)
BOOT_US0 = 20_000_000  # the scene starts 20 s after the autopilot booted


def _look_at(p_cam: np.ndarray, p_aim: np.ndarray) -> np.ndarray:
    """R_ned_from_cam looking from p_cam at p_aim, image x level (same as groundsim.evaluation.synth.look_at)."""
    z = p_aim - p_cam
    z = z / np.linalg.norm(z)
    x = np.cross(np.array([0.0, 0.0, 1.0]), z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


@dataclass
class SyntheticScene:
    """A deterministic scene: observer, target, camera pose, frames and telemetry on the boot clock.

    Observer: circle of radius 40 m at 8 m/s, 70 m up, about the origin.  Target: straight line at
    5 m/s (north), 150-170 m from the observer, 85 m up.  The camera (fixed pod, identity mount) is
    pointed at the target with a slowly varying error of a few percent of range, so the target moves
    over the image.  Frames: 640 x 512 mono8, background ``90 + 30 v/H + 8 sin(u/90)``, a Gaussian
    blob (``blob_sigma_px``, ``blob_amp_grey``), white noise ``noise_grey`` (a bank of precomputed
    noise frames).  Times: frame ``k`` is captured at ``BOOT_US0 + k / frame_rate_hz``.
    """

    frame_rate_hz: float = 30.0
    intrinsics: PinholeIntrinsics = field(default_factory=PinholeIntrinsics.vue_pro_640)
    origin: GeodeticOrigin = ORIGIN
    blob_sigma_px: float = 1.5
    blob_amp_grey: float = 60.0
    noise_grey: float = 1.0
    pointing_error_frac: tuple[float, float, float] = (0.03, 0.02, 0.015)
    seed: int = 0
    boot_us0: int = BOOT_US0

    def __post_init__(self) -> None:
        K = self.intrinsics
        h, w = K.height_px, K.width_px
        rng = np.random.default_rng(self.seed)
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float32)
        self._bg = 90.0 + 30.0 * vv / h + 8.0 * np.sin(uu / 90.0)
        self._noise = [rng.normal(0.0, self.noise_grey, (h, w)).astype(np.float32) for _ in range(8)]
        self.mount = CameraMount()
        self._q_body_from_cam = self.mount.q_body_from_cam()

    # ------------------------------------------------------------------ truth

    def t_us(self, k: int) -> int:
        return self.boot_us0 + int(round(k * 1e6 / self.frame_rate_hz))

    def observer(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Observer (= camera) position and velocity, NED."""
        w = 8.0 / 40.0
        a = w * t_s
        p = np.array([40.0 * math.cos(a), 40.0 * math.sin(a), -70.0])
        v = np.array([-40.0 * w * math.sin(a), 40.0 * w * math.cos(a), 0.0])
        return p, v

    def target(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        v = np.array([5.0, 0.0, 0.0])
        return np.array([150.0, 30.0, -85.0]) + v * t_s, v

    def camera(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(p_cam_ned_m, q_ned_from_cam) at ``t_s`` (seconds since the scene started)."""
        p_cam, _ = self.observer(t_s)
        p_tgt, _ = self.target(t_s)
        rng_m = float(np.linalg.norm(p_tgt - p_cam))
        frac = np.asarray(self.pointing_error_frac)
        err = rng_m * frac * np.sin(2 * np.pi * t_s / np.array([7.0, 5.0, 3.0]))
        R = _look_at(p_cam, p_tgt + err)
        return p_cam, quat_from_rotmat(R)

    def body(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(p_body_ned_m, v_ned_mps, q_ned_from_body) consistent with :meth:`camera` through the mount."""
        p_cam, q_nc = self.camera(t_s)
        _, v = self.observer(t_s)
        q_nb = quat_normalize(quat_multiply(q_nc, quat_conjugate(self._q_body_from_cam)))
        return p_cam, v, q_nb

    def body_rates_frd(self, t_s: float, dt_s: float = 1e-4) -> np.ndarray:
        """Body rates (FRD, rad/s) of :meth:`body`, as #31 reports them: ``Log(q(t-d)^-1 q(t+d)) / 2d``."""
        q0, q1 = self.body(t_s - dt_s)[2], self.body(t_s + dt_s)[2]
        return rotvec_from_quat(quat_multiply(quat_conjugate(q0), q1)) / (2.0 * dt_s)

    def uv(self, t_s: float) -> np.ndarray:
        """The target's true pixel."""
        p_cam, q_nc = self.camera(t_s)
        p_tgt, _ = self.target(t_s)
        return self.intrinsics.project(rotmat_from_quat(q_nc).T @ (p_tgt - p_cam))

    # ------------------------------------------------------------------ sensors

    def image(self, k: int, with_target: bool = True, content_us: int | None = None) -> np.ndarray:
        """Frame ``k``'s pixels: the scene at its capture time, or at ``content_us`` (boot clock) if given."""
        t_s = ((self.t_us(k) if content_us is None else content_us) - self.boot_us0) / 1e6
        img = self._bg + self._noise[k % len(self._noise)]
        if with_target:
            u, v = self.uv(t_s)
            r = int(math.ceil(4 * self.blob_sigma_px))
            j0, j1 = max(int(u) - r, 0), min(int(u) + r + 1, img.shape[1])
            i0, i1 = max(int(v) - r, 0), min(int(v) + r + 1, img.shape[0])
            if j1 > j0 and i1 > i0:
                jj, ii = np.meshgrid(np.arange(j0, j1) + 0.5, np.arange(i0, i1) + 0.5)
                img[i0:i1, j0:j1] += self.blob_amp_grey * np.exp(
                    -((jj - u) ** 2 + (ii - v) ** 2) / (2 * self.blob_sigma_px**2)
                )
        return np.clip(img + 0.5, 0, 255).astype(np.uint8)

    def frame(
        self,
        k: int,
        with_target: bool = True,
        seq: int | None = None,
        time_boot_us: int | None = None,
        content_us: int | None = None,
    ) -> IrFrame:
        """Frame ``k`` stamped ``time_boot_us`` (default: its capture time); the pixels show the scene at
        ``content_us`` (default: frame ``k``'s capture time, whatever the stamp says)."""
        return IrFrame(
            seq=k if seq is None else seq,
            time_boot_us=self.t_us(k) if time_boot_us is None else time_boot_us,
            pixels=self.image(k, with_target, content_us),
        )

    def payload(self, k: int, **kw) -> bytes:
        return encode_irframe(self.frame(k, **kw))

    def telemetry(self, t0_us: int, t1_us: int, rate_hz: float):
        """Samples ``(time_boot_us, p_body_ned_m, v_ned_mps, q_ned_from_body)`` every 1/rate_hz in [t0, t1]."""
        step = int(round(1e6 / rate_hz))
        t = t0_us + (-(t0_us - self.boot_us0)) % step  # the first sample time >= t0 on the grid
        while t <= t1_us:
            p, v, q = self.body((t - self.boot_us0) / 1e6)
            yield t, p, v, q
            t += step

    def feed(self, pose_buffer, t0_us: int, t1_us: int, att_rate_hz: float = 50.0, pos_rate_hz: float = 25.0) -> None:
        """Add attitude and NED position samples covering [t0, t1] to a PoseBuffer."""
        for t, _, _, q in self.telemetry(t0_us, t1_us, att_rate_hz):
            pose_buffer.add_attitude(t, q)
        for t, p, v, _ in self.telemetry(t0_us, t1_us, pos_rate_hz):
            pose_buffer.add_position_ned(t, p, v)

    def geodetic(self, p_ned_m) -> tuple[float, float, float]:
        lat, lon, alt = geodetic_from_ned(p_ned_m, self.origin)
        return float(lat), float(lon), float(alt)


# --------------------------------------------------------------------------- benchmark 1: per-frame processing


class _Timed:
    """Wraps one method of an object and records its wall time per call (ms)."""

    def __init__(self, obj, method: str) -> None:
        self._obj, self._fn = obj, getattr(obj, method)
        self.ms: list[float] = []
        setattr(self, method, self._call)

    def _call(self, *a, **kw):
        t0 = time.perf_counter()
        try:
            return self._fn(*a, **kw)
        finally:
            self.ms.append((time.perf_counter() - t0) * 1e3)

    def __getattr__(self, name):
        return getattr(self._obj, name)


def _pct(a, q) -> float:
    return float(np.percentile(np.asarray(a, dtype=float), q)) if len(a) else math.nan


def bench_processing(n_frames: int, paced: bool = False, chain: str | None = None) -> None:
    import cv2

    from onboard.app.config import OnboardConfig, build_config
    from onboard.core.counters import RejectCounter
    from onboard.core.irframe import decode_irframe
    from onboard.core.pose import PoseBuffer
    from onboard.pipeline.frame_pipeline import FramePipeline, make_estimator, make_tracker

    cv2.setNumThreads(1)
    try:
        from groundsim.evaluation.parallel import limit_blas_threads

        limit_blas_threads(1)
    except ImportError:  # the environment variables set at start are then all there is
        pass
    pinned = pin_to_one_cpu()
    scene = SyntheticScene()
    print(f"per-frame processing, 640 x 512 mono8, {n_frames} frames at 30 Hz scene time, one thread, {pinned}")
    payloads = [scene.payload(k) for k in range(n_frames)]

    def run(cfg: OnboardConfig, with_estimator: bool, pace_s: float = 0.0):
        """``pace_s`` > 0: one frame every ``pace_s`` (a sleep before each), as the daemon gets them."""
        counter = RejectCounter(log_interval_s=3600.0)
        pose = PoseBuffer(mount=scene.mount, config=cfg.pose, origin=scene.origin, counter=counter)
        tracker = _Timed(make_tracker(cfg), "update")
        est = _Timed(make_estimator(cfg), "add") if with_estimator else None
        pipe = FramePipeline(cfg, pose, tracker, est, counter=counter)
        total, cpu_ms, fed = [], [], scene.t_us(0) - 100_000
        n_pos = 0
        last_pos = None
        for k, payload in enumerate(payloads):
            t_hi = scene.t_us(k) + 45_000
            for t, p, v, q in scene.telemetry(fed + 1, t_hi, 50.0):
                pose.add_attitude(t, q)
                pose.add_position_ned(t, p, v)
            fed = t_hi
            if pace_s > 0:
                time.sleep(pace_s)
            c0, t0 = time.thread_time_ns(), time.perf_counter()
            tr = pipe.process_payload(payload, 0)
            total.append((time.perf_counter() - t0) * 1e3)
            cpu_ms.append((time.thread_time_ns() - c0) / 1e6)
            n_pos += tr.has_position
            last_pos = tr if tr.has_position else last_pos
        return total, tracker.ms, (est.ms if est else []), n_pos, counter.total, last_pos, cpu_ms

    decode_ms = []
    for p in payloads[:200]:
        t0 = time.perf_counter()
        decode_irframe(p)
        decode_ms.append((time.perf_counter() - t0) * 1e3)
    imaging = {"chain": chain} if chain else {}
    cfg = build_config({"imaging": imaging})
    print(f"   imaging.chain {cfg.imaging.chain}")
    base, base_img, _, _, _, _, _ = run(build_config({"imaging": imaging, "estimator": {"enabled": False}}), False)
    total, img, est, n_pos, rejects, last, cpu_ms = run(cfg, True)
    fps = 1000.0 / _pct(total, 50)
    print("   full chain (decode + filter + detect + track + pose + estimator):")
    print(
        f"     per frame ms  p10 {_pct(total, 10):6.2f}  p50 {_pct(total, 50):6.2f}  p90 {_pct(total, 90):6.2f}"
        f"  p99 {_pct(total, 99):7.1f}  max {max(total):7.1f}   mean {np.mean(total):6.2f}"
    )
    print(
        f"     frames/s from the median: {fps:6.0f}   from the mean: {1000.0 / np.mean(total):6.0f}   (target >= 300 median)"
    )
    print(
        f"     stages, median ms: decode {_pct(decode_ms, 50):.3f}  imaging {_pct(img, 50):.2f}"
        f"  estimator add {_pct(est, 50):.2f} (p90 {_pct(est, 90):.1f}, max {max(est) if est else math.nan:.0f})"
    )
    slow = sum(1 for x in est if x > 50.0)
    print(
        f"     estimator adds > 50 ms (model re-selection): {slow} of {len(est)} "
        f"({100.0 * slow / max(len(est), 1):.1f} %), {sum(x for x in est if x > 50.0) / max(sum(est), 1e-9) * 100:.0f} % of estimator time"
    )
    print(f"     frames with a 3-D position: {n_pos} of {n_frames}; refusals counted: {rejects}")
    if last is not None:
        ts = (last.time_boot_us - scene.boot_us0) / 1e6
        err = float(np.linalg.norm(np.asarray(last.p_ned_m) - scene.target(ts)[0]))
        print(
            f"     last frame with a position (seq {last.seq}): 3-D error {err:.2f} m,"
            f" 1-sigma (rss) {math.sqrt(np.trace(last.cov_p_ned_m2)):.2f} m, range {last.range_m:.0f} m"
        )
    print(
        f"   baseline without estimator: p50 {_pct(base, 50):.2f} ms -> {1000.0 / _pct(base, 50):.0f} frames/s;"
        f" ratio full / baseline (median) {_pct(total, 50) / _pct(base, 50):.2f}"
    )
    if paced:
        # the same frames and chain, one every 1/30 s: what the per-frame work costs when it runs as in flight,
        # with no thread, process, socket or JSON of the daemon's around it (the last half: the window full)
        *_, paced_ms = run(cfg, True, pace_s=1.0 / 30.0)
        half = slice(len(cpu_ms) // 2, None)
        b2b, inflight = float(np.mean(cpu_ms[half])), float(np.mean(paced_ms[half]))
        print(
            f"   paced as in flight (a sleep of 1/30 s before each frame; CPU, the last {len(cpu_ms[half])} frames):"
            f" mean {inflight:.2f} ms a frame against {b2b:.2f} back to back (x{inflight / b2b:.2f})"
            f" = {inflight * 30.0 / 1000.0:.3f} CPU s per s at 30 Hz, the daemon's per-frame work alone"
        )


# --------------------------------------------------------------------------- benchmark 2: loopback latency


#: the daemon's estimator window (config/onboard.yaml estimator.window_s): its CPU grows while the window
#: fills, then holds; the steady figure is timed from this long after the first track on
WINDOW_FILL_S = 20.0


def _stat_cpu_s(path: str) -> tuple[str, float]:
    """(comm, utime + stime in seconds) of a /proc ``stat`` file (the name may hold spaces and parentheses)."""
    with open(path) as f:
        text = f.read()
    rest = text.rsplit(")", 1)[1].split()
    return text[text.index("(") + 1 : text.rindex(")")], (int(rest[11]) + int(rest[12])) / os.sysconf("SC_CLK_TCK")


def _wakeups(path: str) -> int:
    """Voluntary context switches of a /proc ``status`` file: how often the thread slept and was woken."""
    with open(path) as f:
        for line in f:
            if line.startswith("voluntary_ctxt_switches:"):
                return int(line.split()[1])
    return 0


def _cpu_snapshot(pid: int) -> tuple[float, float, dict[str, float], dict[str, int]]:
    """(monotonic time, CPU seconds of process ``pid`` and its live descendants, the same by thread name,
    wake-ups by thread name) from /proc (Linux; NaN total elsewhere).  The daemon's estimator runs in a
    child of its fork server: counted.  Threads of one name are summed (``comm``: the daemon names its
    pipeline and estimator threads, zenoh its own); a process's main thread is ``main`` unless named.  A
    process's total also holds its exited threads, so it can exceed the sum of the live ones.  Wake-ups
    (voluntary context switches) are shown beside the CPU: on a loaded core each one costs a few tenths of
    a CPU millisecond (cold caches), which is most of what a thread that wakes often spends."""
    now = time.monotonic()
    total, by_thread, wakes = 0.0, {}, {}
    todo, seen = [pid], set()
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        try:
            total += _stat_cpu_s(f"/proc/{p}/stat")[1]
            tids = os.listdir(f"/proc/{p}/task")
        except OSError:
            if p == pid:
                return now, math.nan, {}, {}
            continue
        for tid in tids:
            try:
                comm, cpu_s = _stat_cpu_s(f"/proc/{p}/task/{tid}/stat")
                woken = _wakeups(f"/proc/{p}/task/{tid}/status")
                with open(f"/proc/{p}/task/{tid}/children") as f:
                    todo.extend(int(c) for c in f.read().split())
            except OSError:
                continue
            name = "main" if int(tid) == p and comm.startswith("python") else comm
            by_thread[name] = by_thread.get(name, 0.0) + cpu_s
            wakes[name] = wakes.get(name, 0) + woken
    return now, total, by_thread, wakes


#: the asks each figure is printed beside, by image chain: latency p99 (ms), the daemon's CPU (of a core); the
#: single chain's were set before perception (room for it), the objects chain's CPU ask is the C1 scene's
ASKS = {"single": (15.0, 0.10), "objects": (15.0, 0.25)}


def _default_chain() -> str:
    """The daemon's image chain when its configuration names none."""
    from onboard.app.config import OnboardConfig

    return OnboardConfig().imaging.chain


def _default_attitude_rate_hz() -> float:
    """The ATTITUDE_QUATERNION rate the daemon asks for when its configuration names none."""
    from onboard.app.config import OnboardConfig

    return OnboardConfig().mavlink.attitude_rate_hz


def bench_latency(
    duration_s: float,
    capture_lag_ms: float,
    rate_hz: float = 30.0,
    extra_args: tuple[str, ...] = (),
    chain: str = "objects",
    attitude_rate_hz: float = 100.0,
) -> dict:
    import queue

    import zenoh

    from groundsim.io.scripted_autopilot import ScriptedAutopilot as FakeAutopilot  # the tests' fake autopilot too
    from onboard.io.zenoh_session import ZenohConfig, frame_key, open_session, status_key, track_key

    scene = SyntheticScene()
    mport, zport = free_udp_port(), free_tcp_port()
    env = single_thread_blas_env({k: v for k, v in os.environ.items() if not k.startswith("IRTRACK_")})
    health = os.path.join(tempfile.gettempdir(), f"irtrack-bench-alive-{os.getpid()}")
    cmd = [
        sys.executable,
        "-m",
        "onboard",
        "--mavlink",
        f"udpin:127.0.0.1:{mport}",
        "--zenoh-listen",
        f"tcp/127.0.0.1:{zport}",
        "--set",
        f"output.health_file={health}",
        "--log-level",
        "WARNING",
        *extra_args,
    ]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    err_lines: list[str] = []
    threading.Thread(target=lambda: [err_lines.append(ln) for ln in proc.stderr], daemon=True).start()
    session = None
    try:
        session = open_session(ZenohConfig(connect=(f"tcp/127.0.0.1:{zport}",)))
        arrivals: queue.Queue = queue.Queue()
        statuses: list = []

        def on_track(sample):
            arrivals.put((time.monotonic_ns(), sample.payload.to_bytes()))

        subs = [
            session.declare_subscriber(track_key(), on_track),
            session.declare_subscriber(status_key(), lambda s: statuses.append(json.loads(s.payload.to_bytes()))),
        ]
        pub = session.declare_publisher(frame_key(), congestion_control=zenoh.CongestionControl.BLOCK)
        ap = FakeAutopilot(mport, scene=scene)
        put_ns: dict[int, int] = {}
        lat_ms: list[float] = []
        first_track = None
        t_start = time.monotonic()
        next_frame = next_tel = t_start
        next_hb = 0.0
        k = tel_n = 0
        measuring_from = None
        status_at_start = None
        cpu_at_start = cpu_at_full = None
        lag_us = int(capture_lag_ms * 1000)
        pos_every = max(round(attitude_rate_hz / 25.0), 1)
        while True:
            now = time.monotonic()
            ap.pump()
            if now >= next_hb:
                ap.heartbeat()
                next_hb = now + 1.0
            if now >= next_tel:
                t = ap.boot_us()
                ap.attitude(t)
                if tel_n % pos_every == 0:  # position at about 25 Hz (the attitude's rate over a whole number)
                    ap.position(t)
                tel_n += 1
                next_tel += 1.0 / attitude_rate_hz
            if now >= next_frame:
                # captured capture_lag_ms ago: stamped then, and showing the scene as it was then (the
                # telemetry the daemon pairs it with is the vehicle's at that stamp)
                t_capture_us = ap.boot_us() - lag_us
                payload = scene.payload(k, time_boot_us=t_capture_us, content_us=t_capture_us)
                put_ns[k] = time.monotonic_ns()
                pub.put(payload)
                k += 1
                next_frame += 1.0 / rate_hz
            while not arrivals.empty():
                t_ns, data = arrivals.get()
                j = json.loads(data)
                if first_track is None:
                    first_track = now
                    measuring_from = now + 2.0  # let the daemon settle (first track, rates, TIMESYNC)
                if measuring_from is not None and now >= measuring_from and status_at_start is None and statuses:
                    status_at_start = statuses[-1]
                if measuring_from is not None and now >= measuring_from and cpu_at_start is None:
                    cpu_at_start = _cpu_snapshot(proc.pid)
                if cpu_at_full is None and first_track is not None and now >= first_track + WINDOW_FILL_S:
                    cpu_at_full = _cpu_snapshot(proc.pid)
                if measuring_from is not None and now >= measuring_from and j["seq"] in put_ns:
                    lat_ms.append((t_ns - put_ns.pop(j["seq"])) / 1e6)
            if measuring_from is not None and now >= measuring_from + duration_s:
                break
            if now - t_start > duration_s + 60:
                print("   daemon produced no track within a minute; stderr:", *err_lines[-10:], sep="\n   ")
                return {}
            time.sleep(0.001)
        cpu_s_per_s = steady_cpu_s_per_s = math.nan
        by_thread: dict[str, float] = {}
        steady_by_thread: dict[str, float] = {}
        end = _cpu_snapshot(proc.pid)

        def rates(a, b):
            span_s = max(b[0] - a[0], 1e-9)
            return (b[1] - a[1]) / span_s, {k: (v - a[2].get(k, 0.0)) / span_s for k, v in b[2].items()}

        def wake_rates(a, b) -> dict[str, float]:
            span_s = max(b[0] - a[0], 1e-9)
            return {k: (v - a[3].get(k, 0)) / span_s for k, v in b[3].items()}

        if cpu_at_start is not None:
            cpu_s_per_s, by_thread = rates(cpu_at_start, end)
        if cpu_at_full is not None and end[0] - cpu_at_full[0] >= 10.0:
            steady_cpu_s_per_s, steady_by_thread = rates(cpu_at_full, end)
        woken = wake_rates(cpu_at_start, end) if cpu_at_start is not None else {}
        sent = k
        st = statuses[-1] if statuses else {}
        print(
            f"   capture lag {capture_lag_ms:.0f} ms (frame stamped that long before it is sent): "
            f"{len(lat_ms)} tracks timed over {duration_s:.0f} s of {sent} frames sent"
        )
        print(
            f"     put -> track received, ms: p50 {_pct(lat_ms, 50):.2f}  p90 {_pct(lat_ms, 90):.2f}"
            f"  p99 {_pct(lat_ms, 99):.2f}  max {max(lat_ms) if lat_ms else math.nan:.1f}   (target p99 <= {ASKS[chain][0]:g})"
        )
        if st:
            f = st["frames"]
            f0 = (status_at_start or {}).get("frames", {"in": 0, "processed": 0, "dropped": 0})
            print(
                f"     daemon during the timed window: in {f['in'] - f0['in']} processed {f['processed'] - f0['processed']}"
                f" dropped {f['dropped'] - f0['dropped']} (since start: dropped {f['dropped']}, rejected {f['rejected']})"
            )
            qw, pb = st.get("queue_wait_ms") or {}, st.get("publish_ms") or {}
            print(
                f"     daemon: queue wait p50 {qw.get('p50') or math.nan:.2f} p99 {qw.get('p99') or math.nan:.2f} max "
                f"{qw.get('max') or math.nan:.1f} ms; track put p99 {pb.get('p99') or math.nan:.2f} max {pb.get('max') or math.nan:.1f} ms"
            )
            sg = st.get("stages_ms") or {}
            for name, v in sg.items():
                print(
                    f"     daemon stage {name}: p50 {v['p50'] or math.nan:.2f} p99 {v['p99'] or math.nan:.2f} max {v['max'] or math.nan:.1f} ms"
                )
            print(
                f"     daemon status (last 1000 frames):"
                f" processing p50 {st['processing_ms']['p50']:.2f} p99 {st['processing_ms']['p99']:.2f}"
                f" max {st['processing_ms']['max']:.1f} ms;"
                f" pose wait p50 {st['pose_wait_ms']['p50']:.2f} p99 {st['pose_wait_ms']['p99']:.2f} ms;"
                f" receipt->published p99 {st['latency_ms']['p99']:.2f} ms"
            )
            rj = st.get("rejected") or {}
            n_proc = max(f["processed"] - f0["processed"], 1)
            print(
                f"     pose: extrapolated on {rj.get('pose_extrapolated', 0)} frames since start;"
                f" no pose on {sum(v for k2, v in rj.items() if k2.startswith('pose_') and k2 != 'pose_extrapolated')}"
                f" ({', '.join(f'{k2} {v}' for k2, v in rj.items() if k2.startswith('pose_') and k2 != 'pose_extrapolated') or 'none'})"
            )
            print(
                f"     daemon CPU (all its processes: daemon + estimator worker, /proc): {cpu_s_per_s:.3f} CPU s per"
                f" simulated s = {100 * cpu_s_per_s:.1f} % of one core (target <= {100 * ASKS[chain][1]:.0f} %),"
                f" {1000 * cpu_s_per_s / rate_hz:.2f} ms per frame at {rate_hz:.0f} Hz; median per-frame processing"
                f" {st['processing_ms']['p50']:.2f} ms ({n_proc} frames in the window)"
            )
            shown = sorted(((v, k) for k, v in by_thread.items() if v >= 0.002), reverse=True)
            print(
                "     daemon CPU by thread, CPU s per s (/proc; 'main': the MAVLink and status loop): "
                + ", ".join(f"{k} {v:.3f}" for v, k in shown)
            )
            shown_w = sorted(((v, k) for k, v in woken.items() if v >= 1.0), reverse=True)
            print(
                "     daemon wake-ups by thread, per s (voluntary context switches, /proc): "
                + ", ".join(f"{k} {v:.0f}" for v, k in shown_w)
            )
            if steady_by_thread:
                shown = sorted(((v, k) for k, v in steady_by_thread.items() if v >= 0.002), reverse=True)
                print(
                    f"     steady state, once the estimator's window is full ({WINDOW_FILL_S:.0f} s after the first"
                    f" track, {end[0] - cpu_at_full[0]:.0f} s): {steady_cpu_s_per_s:.3f} CPU s per s"
                    f" (target <= {ASKS[chain][1]:.2f}) = " + ", ".join(f"{k} {v:.3f}" for v, k in shown)
                )
            else:
                print(
                    f"     (steady state not measured: run --latency-s {WINDOW_FILL_S + 12:.0f} or more to time the"
                    " daemon after its estimator's window has filled)"
                )
            c2t = st.get("capture_to_track_ms") or {}
            print(
                f"     capture->track (TIMESYNC) p50 {c2t.get('p50') or math.nan:.1f} ms; cpu share {st['cpu']['share']:.2f}"
                f" (pipeline + estimator threads {st['cpu']['pipeline_share']:.2f}); link {st['link']['state']};"
                f" rejected {st['rejected']}"
            )
        for s in subs:
            s.undeclare()
        pub.undeclare()
        ap.close()
        return {
            "lag_ms": capture_lag_ms,
            "p50_ms": _pct(lat_ms, 50),
            "p99_ms": _pct(lat_ms, 99),
            "n": len(lat_ms),
            "cpu_s_per_s": cpu_s_per_s,
            "steady_cpu_s_per_s": steady_cpu_s_per_s,
            "processing_p50_ms": (st.get("processing_ms") or {}).get("p50", math.nan) if st else math.nan,
        }
    finally:
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        try:
            rc = proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            rc = proc.wait(5)
        print(f"     SIGTERM -> exit {rc} in {time.monotonic() - t0:.2f} s")
        if session is not None:
            session.close()


# --------------------------------------------------------------------------- benchmark 3: two parts, paced


def _paced_mavlink_cpu(duration_s: float, scene: SyntheticScene) -> tuple[float, int]:
    """CPU s per s of a thread that does what the daemon's main loop does with telemetry: sleeps in
    ``select`` on a :class:`MavlinkLink` and polls it, while the tests' fake autopilot sends the scene's
    attitude / position at 50 / 25 Hz; and the messages it handled."""
    import select

    from groundsim.io.scripted_autopilot import ScriptedAutopilot
    from onboard.app.config import OnboardConfig, build_config
    from onboard.app.locked_counter import LockedCounter
    from onboard.app.shared_pose import SharedPoseBuffer
    from onboard.core.pose import PoseBuffer
    from onboard.io.mavlink_link import MavlinkLink

    port = free_udp_port()
    cfg: OnboardConfig = build_config({"mavlink": {"connection": f"udpin:127.0.0.1:{port}"}})
    counter = LockedCounter(log_interval_s=3600.0)
    pose = SharedPoseBuffer(PoseBuffer(mount=cfg.camera.camera_mount(), config=cfg.pose, counter=counter))
    link = MavlinkLink(cfg.mavlink, pose, counter, gimballed=False)
    ap = ScriptedAutopilot(port, scene=scene)
    stop = threading.Event()
    cpu: list[float] = []

    def loop() -> None:
        c0 = time.thread_time()
        while not stop.is_set():
            fd = link.fileno()
            if fd is not None:
                select.select([fd], [], [], 0.05)
            link.poll()
            link.tick()
        cpu.append(time.thread_time() - c0)

    th = threading.Thread(target=loop, daemon=True)
    try:
        th.start()
        t0 = time.monotonic()
        ap.fly_paced(t0 + duration_s, answer=True)
        stop.set()
        th.join(1.0)
        return (cpu[0] if cpu else math.nan) / (time.monotonic() - t0), int(link.messages_rx)
    finally:
        stop.set()
        ap.close()
        link.close()


def _paced_estimator_cpu(duration_s: float, fill_s: float, scene: SyntheticScene) -> tuple[float, float, int]:
    """The estimator hand-off at 30 Hz: a thread adds the scene's observations to a
    :class:`ProcessEstimator` (the daemon's default worker) and sleeps to the next frame.  After ``fill_s``
    of scene time (the window filling), returns over ``duration_s``: the caller thread's CPU s per s, the
    worker process's CPU s per s, and the frames answered late (propagated instead)."""
    from onboard.app.config import OnboardConfig
    from onboard.app.estimator_worker import ProcessEstimator
    from onboard.app.locked_counter import LockedCounter

    cfg = OnboardConfig()
    wait_s = cfg.estimator.result_wait_ms / 1000.0
    pe = ProcessEstimator(cfg, LockedCounter(log_interval_s=3600.0), 30.0)  # the window filled answer by answer
    K = scene.intrinsics
    n_frames = int((fill_s + duration_s) * scene.frame_rate_hz) + 1
    rows = []  # made before any timing: the scene's own numpy is not the daemon's
    for k in range(n_frames):
        ts = k / scene.frame_rate_hz
        p_cam, q = scene.camera(ts)
        rows.append((ts, scene.t_us(k) / 1e6, scene.uv(ts), p_cam, q))
    try:
        marks = None
        for ts, t_s, uv, p_cam, q in rows:
            if marks is None and ts >= fill_s:
                pe.result_wait_s = wait_s  # the daemon's wait from here on
                marks = (time.monotonic(), time.thread_time(), pe.worker_cpu_s, pe.late_results)
            pe.add(t_s, uv, K, p_cam, q)
            if marks is not None:  # paced once the window is full
                time.sleep(max(marks[0] + (ts + 1 / scene.frame_rate_hz - fill_s) - time.monotonic(), 0.0))
        assert marks is not None
        span = time.monotonic() - marks[0]
        pe.predict(0.0)  # the worker's newest CPU figure
        return (time.thread_time() - marks[1]) / span, (pe.worker_cpu_s - marks[2]) / span, pe.late_results - marks[3]
    finally:
        pe.close()


def bench_parts(duration_s: float, repeats: int) -> None:
    """Two parts of the daemon alone, paced as in flight, CPU from the thread / process clocks."""
    scene = SyntheticScene()
    print(f"parts of the daemon, paced, {duration_s:.0f} s each, {repeats} times (CPU s per s; load varies):")
    for i in range(repeats):
        mav, n_msgs = _paced_mavlink_cpu(duration_s, scene)
        caller, worker, late = _paced_estimator_cpu(duration_s, 20.0, scene)
        print(
            f"   run {i + 1}: MAVLink telemetry in (50 + 25 Hz, select + poll): {mav:.4f} ({n_msgs} messages);"
            f"  estimator hand-off at 30 Hz, window full: caller {caller:.4f}, worker process {worker:.4f}"
            f" ({late} frames late)"
        )


def _scene_problem(scene: str, scene_s: float) -> str | None:
    """Why ``--scene`` cannot be flown for ``--scene-s`` by :func:`bench.onboard_scene.bench_scene` (which plans
    it as ``groundsim demo`` does: one observer, the scenario extended to the duration), or None.  Said with this
    command's option names: the planner's own errors name ``--scenario`` and ``--duration``."""
    from groundsim.world.scenario import load_scenario, resolve_scenario_path
    from groundsim.world.sim import check_duration_s, extend_scenario
    from onboard.core.errors import ConfigError

    sc = load_scenario(resolve_scenario_path(scene))  # known_scenario has read it: it loads
    if sc.is_fleet:
        return f"argument --scene: {sc.name} has several observers: expected a scenario of one (one daemon flies it)"
    try:
        extend_scenario(sc, check_duration_s(scene_s, sc))
    except ConfigError as exc:
        return f"argument --scene-s: {str(exc).removeprefix('--duration: ')}"
    return None


def main(argv=None) -> int:
    # every value is checked here, before the machine's speed is measured or a daemon started: an infinite or NaN
    # duration would never end, a count of 0 or a negative lag would time nothing and print NaN
    ap = BenchParser(prog="python -m bench.onboard", description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--frames", type=positive_int, default=600, help="frames for the processing benchmark (default 600 = 20 s)"
    )
    ap.add_argument(
        "--latency-s", type=positive_float, default=20.0, help="seconds of 30 Hz frames timed through the daemon"
    )
    ap.add_argument("--no-latency", action="store_true", help="skip the daemon loopback benchmark")
    ap.add_argument(
        "--capture-lags-ms",
        type=nonnegative_number,
        nargs="+",
        default=[0.0, 10.0, 25.0, 50.0],
        help="capture lags to time (frame stamped that long before it is sent), ms",
    )
    ap.add_argument(
        "--parts-s",
        type=nonnegative_number,
        default=0.0,
        help="also time two parts alone, paced (MAVLink in, estimator hand-off), this many seconds each",
    )
    ap.add_argument("--parts-repeats", type=positive_int, default=2, help="repeats of --parts-s")
    ap.add_argument(
        "--floor-s",
        type=nonnegative_number,
        default=0.0,
        help="also time the daemon's I/O with nothing done (bench.onboard_floor), this many seconds per case",
    )
    ap.add_argument(
        "--paced",
        action="store_true",
        help="also run the per-frame processing paced at 30 Hz (its CPU as in flight; use --frames 600 or more)",
    )
    ap.add_argument(
        "--chain",
        choices=("objects", "single"),
        help="imaging.chain of the daemon and of the per-frame processing (default: the daemon's, objects)",
    )
    ap.add_argument(
        "--attitude-rate-hz",
        type=positive_float,
        default=None,
        help="the fake autopilot's ATTITUDE_QUATERNION rate in the latency runs, which the daemon is then told to ask"
        " for (default: what the daemon asks, 100; a frame sent at its capture waits up to one attitude period for"
        " its bracketing sample)",
    )
    ap.add_argument(
        "--scene",
        type=known_scenario,
        help="instead: the daemon on this scenario (a shipped one's name or a file) flown by the simulator"
        " (bench.onboard_scene)",
    )
    ap.add_argument("--scene-s", type=positive_float, default=30.0, help="seconds flown with --scene (default 30)")
    args = ap.parse_args(argv)
    problem = _scene_problem(args.scene, args.scene_s) if args.scene else None
    if problem is not None:
        ap.error(problem)
    print(
        f"bench.onboard: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} (numbers vary with load);"
        f" machine speed: a fixed Python loop takes {machine_speed_ms():.1f} CPU ms, fixed whole-frame passes"
        f" {frame_speed_ms():.2f} CPU ms (lower is faster)"
    )
    tight_ms, paced_ratio = pacing_factor()
    print(
        f"   pacing: a fixed {tight_ms:.2f} ms workload costs x{paced_ratio:.2f} its CPU when run 30 times a second"
        " instead of back to back (the daemon's per-frame work pays this machine's factor)"
    )
    if args.scene:
        from bench.onboard_scene import bench_scene

        bench_scene(args.scene, args.scene_s, _cpu_snapshot, chain=args.chain or _default_chain())
        print(
            f"   machine speed after: the fixed Python loop takes {machine_speed_ms():.1f} CPU ms, the whole-frame"
            f" passes {frame_speed_ms():.2f}"
        )
        return 0
    if not args.no_latency:
        # first, before this process pins itself to one core
        chain = args.chain or _default_chain()
        extra = ("--set", f"imaging.chain={args.chain}") if args.chain else ()
        attitude_rate_hz = args.attitude_rate_hz or _default_attitude_rate_hz()
        if args.attitude_rate_hz is not None:  # the daemon asks for what it gets
            extra += ("--set", f"mavlink.attitude_rate_hz={args.attitude_rate_hz:g}")
        print(
            "loopback latency through `python -m onboard` (127.0.0.1, UDP MAVLink + zenoh TCP), 30 Hz,"
            f" imaging.chain {chain}{'' if args.chain else ' (the default)'}, attitude {attitude_rate_hz:g} Hz"
            f"{'' if args.attitude_rate_hz else ' (the default)'}"
        )
        rows = [
            bench_latency(args.latency_s, lag, extra_args=extra, chain=chain, attitude_rate_hz=attitude_rate_hz)
            for lag in args.capture_lags_ms
        ]
        lat_ask, cpu_ask = ASKS[chain]
        print(
            f"   summary, put -> track received (target p99 <= {lat_ask:g} ms at any capture lag;"
            f" daemon CPU <= {cpu_ask:.2f} s/s with the {chain} chain):"
        )
        for r in rows:
            if r:
                print(
                    f"     capture lag {r['lag_ms']:5.0f} ms: p50 {r['p50_ms']:6.2f} ms  p99 {r['p99_ms']:6.2f} ms"
                    f"  ({r['n']} tracks)   daemon CPU {r['cpu_s_per_s']:.3f} s per simulated s"
                    + (
                        f" (steady, window full: {r['steady_cpu_s_per_s']:.3f})"
                        if math.isfinite(r["steady_cpu_s_per_s"])
                        else ""
                    )
                    + ","
                    f" median per-frame processing {r['processing_p50_ms']:.2f} ms"
                )
        print(
            f"   machine speed after: the fixed Python loop takes {machine_speed_ms():.1f} CPU ms, the whole-frame"
            f" passes {frame_speed_ms():.2f}"
        )
    if args.parts_s > 0:
        bench_parts(args.parts_s, args.parts_repeats)  # before the pinning of bench_processing
    if args.floor_s > 0:
        from bench.onboard_floor import bench_floor

        bench_floor(args.floor_s, _cpu_snapshot, SyntheticScene())
    bench_processing(args.frames, args.paced, args.chain)
    return 0


if __name__ == "__main__":
    sys.exit(run_benchmark("onboard", main))
