"""``python -m groundsim run``: the ground simulator's main loop (wiring; the pieces live elsewhere).

It flies the observer and the target (JSBSim, :mod:`groundsim.world.flight`), renders what the
observer's thermal camera sees (:mod:`groundsim.world.render`) and emits what a real drone would:
MAVLink telemetry (:mod:`groundsim.io.mavlink_vehicle`), IR frames on zenoh
(:mod:`groundsim.io.zenoh_video`), plus one ground-truth CSV row per frame (:mod:`groundsim.world.truth`).

Clock and events
----------------
The simulation clock *is* the vehicle's boot clock: ``time_boot_us = boot_start_us + round(t_s *
1e6)`` with ``t_s`` the scenario time (``boot_start_us`` = 1 s, so a receiver never sees boot time
0).  Time advances in *ticks* of ``1 / (frame_rate_hz * ticks_per_frame)`` seconds, with
``ticks_per_frame = ceil(MIN_POLL_RATE_HZ / frame_rate_hz)`` (4 at 30 Hz: a 120 Hz tick).  At
every tick the observer's true state at that tick is handed to the MAVLink vehicle and the
vehicle is polled (its own schedule picks #31 at 50 Hz, #33 at 25 Hz, #285 at 10 Hz, HEARTBEAT
and SYSTEM_TIME at 1 Hz, and answers TIMESYNC/commands).  Every ``ticks_per_frame``-th tick is a
camera frame ``k``: the pose at exactly that capture time -> render -> ``IrFrame(seq=k,
time_boot_us)`` -> publish, and its truth row.  Frames cover ``k < duration_s * frame_rate_hz``.

Flight.  Both vehicles are flown by JSBSim on the tick grid, a chunk of whole frames at a time
(``PACED_CHUNK_S`` when paced, ``MAX_MODE_CHUNK_S`` at ``--rate max``), exactly as
:func:`groundsim.world.flight.fly_pair` flies them (target first, heading along its velocity; then the
observer) -- chunking does not change the flight.  Without a gimbal the observer yaws toward the
target's flown position (the pod is fixed); with one it heads along its path and the gimbal
(:func:`groundsim.world.flight.guidance.gimbal_pointing`) aims at the target plus the scenario's
sinusoidal pointing error (phases drawn from ``scenario.rng("gimbal.pointing_phase", seed)``); its
attitude ``q_ned_from_gimbal`` goes out as GIMBAL_DEVICE_ATTITUDE_STATUS (earth frame).

Pacing.  ``--rate realtime`` (factor 1), a factor ``F`` (F x real time), or ``max`` (no sleeping).
When paced, each tick waits for its wall deadline ``wall_start + t_s / F``; the next frame is
flown and rendered right after the current one is published (its pose is known in advance), so
the publication instant does not depend on the render time.  Frame-period jitter (``|interval
between publications - period / F|``) and lateness behind the deadline are reported every
``JITTER_LOG_EVERY_S`` and at exit.  A status line (frames, sim time, real-time factor) is logged
once per ``STATUS_EVERY_S`` of wall time.  While paced, the heap left by the set-up is frozen
(``gc.freeze``): a full collection of it stalled the loop by tens of ms.  On a busy machine the
wake-ups themselves come late; ``groundsim run --rt-priority N`` (opt-in SCHED_FIFO) fixes that
(``python -m bench.simrate`` measures both).

Navigation errors.  The state handed to the MAVLink vehicle is the truth; the vehicle reports it
with the run's navigation errors (:mod:`groundsim.world.nav_errors`: attitude bias + white noise on #31
and #285, position offset + drift + white noise on #33, velocity + drift rate), case
``--nav-noise`` (default: the scenario's ``nav_noise``, itself RTK by default) drawn from
``scenario.rng("nav.errors", seed)``.  The truth CSV keeps the exact values and records the
injected errors of each frame's tick (``nav_*`` columns, :mod:`groundsim.world.truth`).

Determinism.  Truth rows and frames depend only on the scenario, ``--seed`` (the run seed: the
target's disturbance realisation, the render noise ``scenario.rng("render.noise", seed)``, the
gimbal phases, the navigation errors), ``--nav-noise`` and ``--duration``; never on the rate, the
wall clock or chunking.

Stopping.  ``stop`` (a ``threading.Event``, set by SIGINT/SIGTERM in the CLI) is checked at every
tick and while sleeping (at most ``STOP_POLL_S``); the loop then returns at once, the truth file
holds whole lines for every frame published, and :func:`run` closes the sockets.
"""

from __future__ import annotations

import gc
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from groundsim.world.scenario import Scenario
from groundsim.world.truth import TruthRow, TruthWriter, truth_row
from onboard.core.errors import ConfigError, InputError, IrtrackError
from onboard.core.frames import (
    camera_pose_ned,
    euler_from_quat,
    geodetic_from_ned,
    quat_multiply,
    quat_normalize,
    rotmat_from_quat,
)

__all__ = [
    "BOOT_START_US",
    "MIN_POLL_RATE_HZ",
    "RateSpec",
    "RunConfig",
    "RunReport",
    "JitterSummary",
    "JitterStats",
    "Pacer",
    "SystemClock",
    "PairFlight",
    "SimFrame",
    "SimCore",
    "run_loop",
    "run",
]

log = logging.getLogger(__name__)

BOOT_START_US = 1_000_000  # the boot clock reads 1 s at t_s = 0
MIN_POLL_RATE_HZ = 100.0  # MAVLink is polled at least this often in simulated time
MAX_MODE_CHUNK_S = 1.0  # at --rate max, JSBSim flies this much simulated time per call (fewer, cheaper calls)
PACED_CHUNK_S = 0.1  # when paced: short calls (~4 ms fixed + ~0.3 ms per tick, a burst well inside one frame)
STATUS_EVERY_S = 1.0  # wall seconds between status lines
JITTER_LOG_EVERY_S = 5.0  # wall seconds between jitter reports when paced
STOP_POLL_S = 0.05  # longest uninterrupted sleep: the stop flag is seen within this
MIN_FACTOR, MAX_FACTOR = 0.01, 1000.0
GROUND_D_M = 0.0  # flat ground at the scenario origin's height (the scenarios' origin is on the ground)
_FRAME_COUNT_EPS = 1e-9  # k < duration * rate, robust to float products (as groundsim.world.scenario)
_ERROR_LOG_EVERY_S = 10.0


# --------------------------------------------------------------------------- options


@dataclass(frozen=True)
class RateSpec:
    """How fast to run: ``factor`` x real time, or as fast as possible when ``factor is None``."""

    factor: float | None
    text: str = ""

    def __post_init__(self) -> None:
        f = self.factor
        if f is not None and (
            isinstance(f, bool)
            or not isinstance(f, (int, float))
            or not math.isfinite(f)
            or not MIN_FACTOR <= f <= MAX_FACTOR
        ):
            raise ConfigError(
                f"--rate: expected realtime, max or a factor in [{MIN_FACTOR:g}, {MAX_FACTOR:g}], got {f!r}"
            )
        if not self.text:
            object.__setattr__(self, "text", "max" if f is None else ("realtime" if f == 1.0 else f"{f:g}"))

    @property
    def paced(self) -> bool:
        return self.factor is not None

    @classmethod
    def parse(cls, text: str) -> RateSpec:
        """``realtime`` | ``max`` | a factor such as ``2`` or ``0.5``; ConfigError naming ``--rate``."""
        t = str(text).strip().lower()
        if t in ("realtime", "real-time", "rt"):
            return cls(1.0, "realtime")
        if t == "max":
            return cls(None, "max")
        try:
            f = float(t.rstrip("x"))
        except ValueError:
            raise ConfigError(f"--rate: expected realtime, max or a factor (e.g. 2), got {text!r}") from None
        return cls(f, t)


REALTIME = RateSpec(1.0, "realtime")
MAX_RATE = RateSpec(None, "max")


@dataclass(frozen=True)
class RunConfig:
    """Everything ``run`` needs, typed (built once by the CLI).

    ``duration_s`` None = the scenario's; otherwise in (0, scenario.duration_s].  ``run_seed``
    >= 0 selects the realisation (see the module docstring).  ``zenoh`` is an
    :class:`onboard.io.zenoh_session.ZenohSettings` (None: no endpoints, scouting off).
    ``truth_path`` None writes no truth.  ``flight_chunk_s`` None = automatic (``PACED_CHUNK_S`` or
    ``MAX_MODE_CHUNK_S``).  ``nav_noise``: a case name of ``config/noise_cases.yaml`` for the
    telemetry's navigation errors; None = the scenario's ``nav_noise``.
    """

    scenario: Scenario
    run_seed: int = 0
    duration_s: float | None = None
    rate: RateSpec = REALTIME
    mavlink: str = "udpout:127.0.0.1:14540"
    vehicle: str = "uav1"
    zenoh: object | None = None
    truth_path: Path | None = None
    render: bool = True
    boot_start_us: int = BOOT_START_US
    flight_chunk_s: float | None = None
    nav_noise: str | None = None
    record_path: Path | None = None  # --record FILE.mcap: frames, MAVLink both ways and the truth (onboard.io.record)

    def __post_init__(self) -> None:
        sc = self.scenario
        if not isinstance(sc, Scenario):
            raise ConfigError(f"RunConfig.scenario must be a Scenario, got {type(sc).__name__}")
        s = self.run_seed
        if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or not 0 <= int(s) < 2**63:
            raise ConfigError(f"--seed: expected an integer in [0, 2^63), got {s!r}")
        object.__setattr__(self, "run_seed", int(s))
        d = sc.duration_s if self.duration_s is None else self.duration_s
        if isinstance(d, bool) or not isinstance(d, (int, float)) or not math.isfinite(d) or d <= 0:
            raise ConfigError(f"--duration: expected a positive number of seconds, got {self.duration_s!r}")
        if d > sc.duration_s + 1e-9:
            raise ConfigError(
                f"--duration: expected at most the scenario's duration_s ({sc.duration_s:g} s) of {sc.name}, got {d:g};"
                " lengthen duration_s in the scenario file instead"
            )
        object.__setattr__(self, "duration_s", float(d))
        if not isinstance(self.rate, RateSpec):
            raise ConfigError(f"RunConfig.rate must be a RateSpec, got {type(self.rate).__name__}")
        b = self.boot_start_us
        if isinstance(b, bool) or not isinstance(b, int) or not 0 <= b < 2**40:
            raise ConfigError(f"RunConfig.boot_start_us must be a non-negative integer, got {b!r}")
        c = self.flight_chunk_s
        if c is not None and (not isinstance(c, (int, float)) or not math.isfinite(c) or c <= 0):
            raise ConfigError(f"RunConfig.flight_chunk_s must be > 0 s or None, got {c!r}")
        if self.truth_path is not None:
            object.__setattr__(self, "truth_path", Path(self.truth_path))
        if self.record_path is not None:
            if not str(self.record_path).endswith(".mcap"):
                raise ConfigError(f"--record: expected a file name ending in .mcap, got {str(self.record_path)!r}")
            object.__setattr__(self, "record_path", Path(self.record_path))
        if self.nav_noise is not None:
            from groundsim.world.nav_errors import resolve_nav_noise

            resolve_nav_noise(self.nav_noise)  # an unknown name fails here, naming the file and the choices
        if self.zenoh is not None:
            from onboard.io.zenoh_session import ZenohSettings

            if not isinstance(self.zenoh, ZenohSettings):
                raise ConfigError(f"RunConfig.zenoh must be a ZenohSettings or None, got {type(self.zenoh).__name__}")


# --------------------------------------------------------------------------- clock, pacing, jitter


class SystemClock:
    """Monotonic wall clock (``time.perf_counter``) and ``time.sleep``; tests inject a fake."""

    @staticmethod
    def now_s() -> float:
        return time.perf_counter()

    @staticmethod
    def sleep(seconds: float) -> None:
        time.sleep(seconds)


class Pacer:
    """Holds each event until its wall deadline ``wall_start + (t_s - t0_s) / factor``.

    ``factor`` None: never waits (``--rate max``).  A late event is not delayed further and
    nothing is skipped: the schedule is absolute, so a slow stretch is caught up by not sleeping.
    """

    def __init__(self, factor: float | None, clock=None) -> None:
        self.factor = factor
        self.clock = clock if clock is not None else SystemClock()
        self._wall0: float | None = None
        self._t0 = 0.0

    def start(self, t0_s: float = 0.0) -> None:
        self._wall0 = self.clock.now_s()
        self._t0 = float(t0_s)

    def deadline_s(self, t_s: float) -> float:
        if self._wall0 is None:
            raise RuntimeError("Pacer.start() first")
        if self.factor is None:
            return -math.inf
        return self._wall0 + (t_s - self._t0) / self.factor

    def wait_until(self, t_s: float, stop: threading.Event | None = None) -> float:
        """Sleep until ``t_s``'s deadline (in slices of at most STOP_POLL_S while ``stop`` is
        clear); returns the lateness in seconds (>= 0; 0 when not paced or stopped)."""
        if self.factor is None:
            return 0.0
        deadline = self.deadline_s(t_s)
        while True:
            now = self.clock.now_s()
            remaining = deadline - now
            if remaining <= 0.0:
                return -remaining
            if stop is not None and stop.is_set():
                return 0.0
            self.clock.sleep(min(remaining, STOP_POLL_S))


@dataclass(frozen=True)
class JitterSummary:
    """Frame-period jitter ``|dt_wall - period|`` and lateness behind the deadline, milliseconds."""

    frames: int
    period_ms: float
    jitter_p50_ms: float
    jitter_p99_ms: float
    jitter_max_ms: float
    late_p50_ms: float
    late_p99_ms: float
    late_max_ms: float

    def line(self) -> str:
        return (
            f"frame period {self.period_ms:.2f} ms: jitter p50 {self.jitter_p50_ms:.3f} ms, p99 {self.jitter_p99_ms:.3f} ms,"
            f" max {self.jitter_max_ms:.3f} ms; lateness p50 {self.late_p50_ms:.3f} ms, p99 {self.late_p99_ms:.3f} ms,"
            f" max {self.late_max_ms:.3f} ms ({self.frames} frames)"
        )


class JitterStats:
    """Wall times of frame publications (pure bookkeeping; the clock is read by the caller)."""

    def __init__(self, period_s: float) -> None:
        self.period_s = float(period_s)
        self._wall: list[float] = []
        self._late: list[float] = []

    def add(self, wall_s: float, late_s: float) -> None:
        self._wall.append(float(wall_s))
        self._late.append(float(late_s))

    def __len__(self) -> int:
        return len(self._wall)

    def summary(self) -> JitterSummary | None:
        """None before two frames (no interval yet)."""
        if len(self._wall) < 2:
            return None
        jit = np.abs(np.diff(np.asarray(self._wall)) - self.period_s) * 1e3
        late = np.asarray(self._late) * 1e3
        return JitterSummary(
            frames=len(self._wall),
            period_ms=self.period_s * 1e3,
            jitter_p50_ms=float(np.percentile(jit, 50)),
            jitter_p99_ms=float(np.percentile(jit, 99)),
            jitter_max_ms=float(jit.max()),
            late_p50_ms=float(np.percentile(late, 50)),
            late_p99_ms=float(np.percentile(late, 99)),
            late_max_ms=float(late.max()),
        )


# --------------------------------------------------------------------------- flight


@dataclass(frozen=True)
class _Chunk:
    """Truth of ticks ``[i0, i0 + n)``: flown states and everything derived from them (arrays)."""

    i0: int
    t_s: np.ndarray
    obs_p_ned_m: np.ndarray
    obs_v_ned_mps: np.ndarray
    obs_q_ned_from_body: np.ndarray
    obs_omega_frd_radps: np.ndarray
    obs_lat_deg: np.ndarray
    obs_lon_deg: np.ndarray
    obs_alt_m: np.ndarray
    obs_yaw_rad: np.ndarray
    tgt_p_ned_m: np.ndarray
    tgt_v_ned_mps: np.ndarray
    tgt_q_ned_from_body: np.ndarray
    tgt_lat_deg: np.ndarray
    tgt_lon_deg: np.ndarray
    tgt_alt_m: np.ndarray
    q_mount_from_gimbal: np.ndarray | None
    q_ned_from_gimbal: np.ndarray | None
    cam_p_ned_m: np.ndarray
    cam_q_ned_from_cam: np.ndarray

    @property
    def i1(self) -> int:
        return self.i0 + len(self.t_s)


class PairFlight:
    """Flies a scenario's observer and target with JSBSim on a time grid, ``chunk_ticks`` at a time.

    The same flight as :func:`groundsim.world.flight.fly_pair` on that grid (same vehicles, same order,
    same look-at rows; ``FlownVehicle.step_through`` does not depend on how calls are split).
    :meth:`ensure` flies up to a tick; :meth:`chunk_of` returns the arrays holding a tick (the
    two most recent chunks are kept, so memory does not grow with the duration).
    """

    def __init__(self, scenario: Scenario, run_seed: int, times_s: np.ndarray, chunk_ticks: int) -> None:
        self.scenario = scenario
        self.times_s = np.asarray(times_s, dtype=float)
        self.chunk_ticks = max(1, int(chunk_ticks))
        self.gimballed = scenario.camera.gimbal is not None
        self.observer_yaw_mode = "velocity" if self.gimballed else "target"
        self._obs_ref = scenario.observer_motion(run_seed)
        self._tgt_ref = scenario.target_motion(run_seed)
        g = scenario.camera.gimbal
        if g is not None:
            rng = scenario.rng("gimbal.pointing_phase", run_seed)
            self.gimbal_phase_rad = tuple(float(x) for x in rng.uniform(0.0, 2.0 * math.pi, 3))
        else:
            self.gimbal_phase_rad = None
        self._target = None
        self._observer = None
        self._chunks: list[_Chunk] = []
        self.flown_ticks = 0
        self.flight_s = 0.0  # wall seconds spent flying and deriving

    def ensure(self, i: int) -> None:
        """Fly until tick ``i`` is available (ticks past the grid are an error)."""
        if not 0 <= i < len(self.times_s):
            raise IndexError(f"tick {i} outside the grid of {len(self.times_s)}")
        while self.flown_ticks <= i:
            self._fly_chunk()

    def chunk_of(self, i: int) -> _Chunk:
        self.ensure(i)
        for c in reversed(self._chunks):
            if c.i0 <= i < c.i1:
                return c
        raise IndexError(f"tick {i} was flown and dropped (only the two latest chunks are kept)")

    def _fly_chunk(self) -> None:
        from groundsim.world.flight import FlownVehicle  # JSBSim is imported on first flight only

        t0 = time.perf_counter()
        sc = self.scenario
        a = self.flown_ticks
        b = min(a + self.chunk_ticks, len(self.times_s))
        t = self.times_s[a:b]
        if self._target is None:
            self._target = FlownVehicle(
                self._tgt_ref, sc.origin, sc.wind_ned_mps, yaw_mode="velocity", name="target", seed=sc.seed
            )
        tgt = self._target.step_through(t)
        if self._observer is None:
            kw = {"look_at_ned_m": tgt.p_ned_m[0]} if self.observer_yaw_mode == "target" else {}
            self._observer = FlownVehicle(
                self._obs_ref,
                sc.origin,
                sc.wind_ned_mps,
                yaw_mode=self.observer_yaw_mode,
                name="observer",
                seed=sc.seed,
                **kw,
            )
        if self.observer_yaw_mode == "target":
            obs = self._observer.step_through(t, tgt.p_ned_m, tgt.v_ned_mps)
        else:
            obs = self._observer.step_through(t)
        self._chunks = self._chunks[-1:] + [self._derive(a, t, obs, tgt)]
        self.flown_ticks = b
        self.flight_s += time.perf_counter() - t0

    def _derive(self, i0: int, t: np.ndarray, obs, tgt) -> _Chunk:
        from groundsim.world.flight.guidance import gimbal_pointing, sinusoidal_pointing_error_ned_m

        sc = self.scenario
        mount = sc.camera.mount
        n = len(t)
        lat, lon, alt = geodetic_from_ned(
            np.concatenate([obs.p_ned_m, tgt.p_ned_m]), sc.origin
        )  # one call: ~0.5 ms each
        _, _, yaw = euler_from_quat(obs.q_ned_from_body)
        q_mg = q_ng = None
        if self.gimballed:
            g = sc.camera.gimbal
            p_cam0, _ = camera_pose_ned(obs.p_ned_m, obs.q_ned_from_body, mount)
            range_m = np.linalg.norm(tgt.p_ned_m - p_cam0, axis=-1)
            aim = tgt.p_ned_m + sinusoidal_pointing_error_ned_m(
                t, range_m, g.pointing_error_frac_of_range, g.pointing_error_period_s, self.gimbal_phase_rad
            )
            q_mg = gimbal_pointing(obs.p_ned_m, obs.q_ned_from_body, mount, aim)
            q_ng = quat_normalize(
                quat_multiply(quat_multiply(obs.q_ned_from_body, np.asarray(mount.q_body_from_mount)), q_mg)
            )
        p_cam, q_cam = camera_pose_ned(obs.p_ned_m, obs.q_ned_from_body, mount, q_mg)
        return _Chunk(
            i0=i0,
            t_s=t,
            obs_p_ned_m=obs.p_ned_m,
            obs_v_ned_mps=obs.v_ned_mps,
            obs_q_ned_from_body=obs.q_ned_from_body,
            obs_omega_frd_radps=obs.omega_frd_radps,
            obs_lat_deg=lat[:n],
            obs_lon_deg=lon[:n],
            obs_alt_m=alt[:n],
            tgt_lat_deg=lat[n:],
            tgt_lon_deg=lon[n:],
            tgt_alt_m=alt[n:],
            obs_yaw_rad=np.asarray(yaw),
            tgt_p_ned_m=tgt.p_ned_m,
            tgt_v_ned_mps=tgt.v_ned_mps,
            tgt_q_ned_from_body=tgt.q_ned_from_body,
            q_mount_from_gimbal=q_mg,
            q_ned_from_gimbal=q_ng,
            cam_p_ned_m=np.asarray(p_cam),
            cam_q_ned_from_cam=np.asarray(q_cam),
        )


class _Limited:
    """Counts one kind of error and logs it at most every _ERROR_LOG_EVERY_S (never raises)."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self.count = 0
        self._last = -math.inf

    def __call__(self, what: str, exc: BaseException) -> None:
        self.count += 1
        now = time.monotonic()
        if now - self._last >= _ERROR_LOG_EVERY_S:
            self._last = now
            log.warning("%s: %s (%d %s so far)", what, exc, self.count, self.kind)


# --------------------------------------------------------------------------- the simulation core


@dataclass(frozen=True)
class SimFrame:
    """One camera frame: ``seq``, capture ``time_boot_us``, ``pixels`` ((H, W) uint8/uint16, or
    None when rendering is off) and its :class:`~groundsim.world.truth.TruthRow`."""

    seq: int
    time_boot_us: int
    pixels: np.ndarray | None
    truth: TruthRow


def frame_count(duration_s: float, frame_rate_hz: float) -> int:
    """Frames ``k`` with ``k < duration_s * frame_rate_hz`` (at least one), as the scenario counts."""
    return max(1, math.ceil(duration_s * frame_rate_hz - _FRAME_COUNT_EPS))


class SimCore:
    """The simulated world on the tick grid, with step methods and no sockets or files.

    ``vehicle_state(i)``: keyword arguments of ``MavlinkVehicle.update_state`` at tick ``i`` (the
    truth); ``nav_error(i)``: the navigation error the vehicle reports it with
    (:class:`groundsim.world.nav_errors.NavErrorSample`); ``frame(k)``: fly (if needed), render and compute
    the truth of frame ``k``.  Ticks and frames must be asked for in non-decreasing order (older
    flight chunks are dropped).  ``nav_noise``: a :class:`~groundsim.world.scenario.NoiseCase`, a case name,
    or None (the scenario's ``nav_noise``).
    """

    def __init__(
        self,
        scenario: Scenario,
        run_seed: int = 0,
        duration_s: float | None = None,
        render: bool = True,
        boot_start_us: int = BOOT_START_US,
        flight_chunk_s: float | None = None,
        nav_noise=None,
    ) -> None:
        from groundsim.world.nav_errors import NAV_ERROR_STREAM, NavErrorModel, resolve_nav_noise

        cfg = RunConfig(scenario, run_seed=run_seed, duration_s=duration_s, render=render, boot_start_us=boot_start_us)
        self.scenario = scenario
        self.run_seed = cfg.run_seed
        self.duration_s = cfg.duration_s
        self.render_enabled = bool(render)
        self.boot_start_us = boot_start_us
        self.frame_rate_hz = float(scenario.frame_rate_hz)
        self.ticks_per_frame = max(1, math.ceil(MIN_POLL_RATE_HZ / self.frame_rate_hz - 1e-9))
        self.tick_rate_hz = self.frame_rate_hz * self.ticks_per_frame
        self.frame_count = frame_count(self.duration_s, self.frame_rate_hz)
        self.tick_count = self.frame_count * self.ticks_per_frame
        self.times_s = np.arange(self.tick_count) / self.tick_rate_hz
        # JSBSim flies a whole number of frames' ticks per call: flight_chunk_s of them, at least one frame
        chunk_frames = 1 if flight_chunk_s is None else max(1, round(flight_chunk_s * self.frame_rate_hz))
        chunk_ticks = chunk_frames * self.ticks_per_frame
        self.flight = PairFlight(scenario, self.run_seed, self.times_s, chunk_ticks)
        self.gimballed = self.flight.gimballed
        nav_noise = scenario.nav_noise if nav_noise is None else nav_noise
        case = resolve_nav_noise(nav_noise) if isinstance(nav_noise, str) else nav_noise
        self.nav_noise = case
        self.nav_errors = NavErrorModel(case, scenario.rng(NAV_ERROR_STREAM, self.run_seed), self.times_s)
        self._renderer = None
        self.render_s = 0.0  # wall seconds spent rendering
        self.render_errors = _Limited("render_error")

    def time_boot_us(self, i: int) -> int:
        return self.boot_start_us + round(float(self.times_s[i]) * 1e6)

    def tick_time_s(self, i: int) -> float:
        return float(self.times_s[i])

    def vehicle_state(self, i: int) -> dict:
        c = self.flight.chunk_of(i)
        j = i - c.i0
        return dict(
            time_boot_us=self.time_boot_us(i),
            lat_deg=float(c.obs_lat_deg[j]),
            lon_deg=float(c.obs_lon_deg[j]),
            alt_amsl_m=float(c.obs_alt_m[j]),
            alt_rel_m=float(c.obs_alt_m[j]) - self.scenario.origin.alt_m,
            v_ned_mps=c.obs_v_ned_mps[j],
            q_ned_from_body=c.obs_q_ned_from_body[j],
            body_rates_radps=c.obs_omega_frd_radps[j],
            heading_rad=float(c.obs_yaw_rad[j]),
            q_gimbal=None if c.q_ned_from_gimbal is None else c.q_ned_from_gimbal[j],
        )

    def nav_error(self, i: int):
        """The navigation error the vehicle reports tick ``i``'s state with (a NavErrorSample)."""
        return self.nav_errors.sample(i)

    def renderer(self):
        """The IR renderer (built on first use; seeded by ``scenario.rng("render.noise", seed)``)."""
        if self._renderer is None:
            from groundsim.world.render import IrRenderer

            seed = int(self.scenario.rng("render.noise", self.run_seed).integers(0, 2**63 - 1))
            self._renderer = IrRenderer(self.scenario.camera.intrinsics, self.scenario.ir, seed)
        return self._renderer

    def frame(self, k: int) -> SimFrame:
        if not 0 <= k < self.frame_count:
            raise IndexError(f"frame {k} outside [0, {self.frame_count})")
        i = k * self.ticks_per_frame
        c = self.flight.chunk_of(i)
        j = i - c.i0
        t_us = self.time_boot_us(i)
        pixels = None
        if self.render_enabled:
            renderer = self.renderer()
            t0 = time.perf_counter()
            try:
                pixels = renderer.render(
                    c.cam_p_ned_m[j],
                    rotmat_from_quat(c.cam_q_ned_from_cam[j]),
                    c.tgt_p_ned_m[j],
                    rotmat_from_quat(c.tgt_q_ned_from_body[j]),
                    GROUND_D_M,
                )
            except InputError as exc:  # a frame that cannot be rendered is skipped, its truth row is kept
                self.render_errors(f"frame {k}: render failed", exc)
            self.render_s += time.perf_counter() - t0
        row = truth_row(
            k,
            t_us,
            float(c.t_s[j]),
            self.scenario.origin,
            self.scenario.camera.intrinsics,
            c.tgt_p_ned_m[j],
            c.tgt_v_ned_mps[j],
            c.obs_p_ned_m[j],
            c.cam_p_ned_m[j],
            c.cam_q_ned_from_cam[j],
            target_lla=(c.tgt_lat_deg[j], c.tgt_lon_deg[j], c.tgt_alt_m[j]),
            observer_lla=(c.obs_lat_deg[j], c.obs_lon_deg[j], c.obs_alt_m[j]),
            nav_error=self.nav_error(i),
        )
        return SimFrame(k, t_us, pixels, row)


# --------------------------------------------------------------------------- the loop


@dataclass(frozen=True)
class RunReport:
    """What a run did.  ``wall_s``: the loop from the first event to the last; ``setup_s``: flight
    set-up, renderer set-up and the first frame before it; ``rt_factor``: ``sim_s / wall_s``.
    ``per_frame_ms``: mean wall ms per frame of ``flight``, ``render``, ``publish``, ``mavlink``
    (all ticks' polls), ``truth``."""

    frames: int
    frames_total: int
    sim_s: float
    wall_s: float
    setup_s: float
    rt_factor: float
    stopped: bool
    rate: str
    jitter: JitterSummary | None
    per_frame_ms: dict = field(default_factory=dict)
    errors: dict = field(default_factory=dict)
    mavlink_counters: dict = field(default_factory=dict)
    frames_published: int = 0

    def line(self) -> str:
        s = (
            f"{'stopped' if self.stopped else 'done'}: {self.frames}/{self.frames_total} frames, {self.sim_s:.2f} s simulated"
            f" in {self.wall_s:.2f} s (rt x{self.rt_factor:.2f}, rate {self.rate}; set-up {self.setup_s:.2f} s)"
        )
        if self.errors:
            s += "; errors " + ", ".join(f"{k} {v}" for k, v in sorted(self.errors.items()))
        return s


def run_loop(
    core: SimCore,
    rate: RateSpec,
    *,
    mavlink=None,
    publisher=None,
    truth: TruthWriter | None = None,
    stop: threading.Event | None = None,
    clock=None,
) -> RunReport:
    """Drive ``core`` tick by tick into the sinks (any may be None); see the module docstring.

    ``mavlink``: has ``update_state(**state, nav_error=sample)`` and ``poll(now_boot_us)`` (a MavlinkVehicle);
    ``publisher``: has ``publish(IrFrame)`` (a FramePublisher); ``truth``: a TruthWriter.
    Per-event errors (a sink's IrtrackError or zenoh error, a frame the renderer refuses) are
    counted in ``RunReport.errors`` and logged at most every 10 s, never raised; a flight failure
    (FlightError) or a truth file that cannot be written ends the run by raising.
    """
    from onboard.core.irframe import IrFrame

    try:
        import zenoh

        sink_errors: tuple = (IrtrackError, zenoh.ZError)
    except ImportError:  # pragma: no cover - zenoh is a dependency
        sink_errors = (IrtrackError,)
    stop = stop if stop is not None else threading.Event()
    clock = clock if clock is not None else SystemClock()
    pacer = Pacer(rate.factor, clock)
    jitter = JitterStats(1.0 / core.frame_rate_hz / (rate.factor or 1.0)) if rate.paced else None

    t_setup = clock.now_s()
    pending = core.frame(0) if not stop.is_set() else None
    setup_s = clock.now_s() - t_setup
    flight_setup_s, render_setup_s = core.flight.flight_s, core.render_s
    log.info(
        "set-up %.2f s (flight %.2f s); %d frames at %g Hz, %d ticks at %g Hz, rate %s",
        setup_s,
        flight_setup_s,
        core.frame_count,
        core.frame_rate_hz,
        core.tick_count,
        core.tick_rate_hz,
        rate.text,
    )

    if rate.paced:
        # the set-up left a large heap (SciPy, OpenCV, zenoh, JSBSim); a full collection of it stalls
        # the loop for tens of ms (measured: 37 ms).  Freeze it so collections only scan new objects.
        gc.collect()
        gc.freeze()
    m = core.ticks_per_frame
    n_frames = core.frame_count
    mavlink_errors, publish_errors = _Limited("mavlink_error"), _Limited("publish_error")
    acc = {"publish": 0.0, "mavlink": 0.0, "truth": 0.0}
    published = 0
    frames = 0
    pacer.start(0.0)
    wall0 = clock.now_s()
    next_status = wall0 + STATUS_EVERY_S
    next_jitter_log = wall0 + JITTER_LOG_EVERY_S
    try:
        for i in range(core.tick_count):
            if stop.is_set():
                break
            k, r = divmod(i, m)
            late = pacer.wait_until(core.tick_time_s(i), stop)
            if stop.is_set():
                break
            if mavlink is not None:
                t0 = clock.now_s()
                try:
                    mavlink.update_state(**core.vehicle_state(i), nav_error=core.nav_error(i))
                    mavlink.poll(core.time_boot_us(i))
                except sink_errors as exc:
                    mavlink_errors(f"tick {i}: mavlink", exc)
                acc["mavlink"] += clock.now_s() - t0
            if r == 0:
                frame = pending
                wall = clock.now_s()
                if jitter is not None:
                    jitter.add(wall, late)
                if publisher is not None and frame.pixels is not None:
                    try:
                        publisher.publish(IrFrame(frame.seq, frame.time_boot_us, frame.pixels))
                        published += 1
                    except sink_errors as exc:
                        publish_errors(f"frame {frame.seq}: publish", exc)
                t1 = clock.now_s()
                acc["publish"] += t1 - wall
                if truth is not None:
                    truth.write(frame.truth)
                acc["truth"] += clock.now_s() - t1
                frames += 1
                pending = core.frame(k + 1) if k + 1 < n_frames else None
            now = clock.now_s()
            if now >= next_status:
                next_status = now + STATUS_EVERY_S
                sim_s = frames / core.frame_rate_hz
                log.info(
                    "frames %d/%d, sim %.2f/%.2f s, rt x%.2f",
                    frames,
                    n_frames,
                    sim_s,
                    core.duration_s,
                    sim_s / max(now - wall0, 1e-9),
                )
            if jitter is not None and now >= next_jitter_log:
                next_jitter_log = now + JITTER_LOG_EVERY_S
                summary = jitter.summary()
                if summary is not None:
                    log.info("pacing: %s", summary.line())
    finally:
        if rate.paced:
            gc.unfreeze()
    wall_s = max(clock.now_s() - wall0, 1e-9)
    sim_s = frames / core.frame_rate_hz
    nf = max(frames, 1)
    per_frame = {
        "flight": 1e3 * (core.flight.flight_s - flight_setup_s) / nf,
        "render": 1e3 * (core.render_s - render_setup_s) / nf,
        "publish": 1e3 * acc["publish"] / nf,
        "mavlink": 1e3 * acc["mavlink"] / nf,
        "truth": 1e3 * acc["truth"] / nf,
    }
    report = RunReport(
        frames=frames,
        frames_total=n_frames,
        sim_s=sim_s,
        wall_s=wall_s,
        setup_s=setup_s,
        rt_factor=sim_s / wall_s,
        stopped=frames < n_frames,
        rate=rate.text,
        jitter=jitter.summary() if jitter is not None else None,
        per_frame_ms=per_frame,
        errors={e.kind: e.count for e in (mavlink_errors, publish_errors, core.render_errors) if e.count},
        mavlink_counters=dict(getattr(mavlink, "counters", {}) or {}),
        frames_published=published,
    )
    log.info("%s", report.line())
    if report.jitter is not None:
        log.info("pacing: %s", report.jitter.line())
    return report


def run(config: RunConfig, stop: threading.Event | None = None, clock=None) -> RunReport:
    """Open the adapters of ``config`` (zenoh, MAVLink, truth file), run, close them.

    Opening errors (port in use, unreachable zenoh peer, bad endpoint, unwritable truth path)
    raise :class:`~onboard.core.errors.IrtrackError` subclasses with one-line messages before any
    flying starts.
    """
    from groundsim.io.mavlink_vehicle import MavlinkVehicle
    from groundsim.io.zenoh_video import FramePublisher
    from onboard.io.zenoh_session import ZenohSettings, frame_key, open_session

    frame_key(config.vehicle)  # validates the vehicle name before opening anything
    chunk_s = config.flight_chunk_s
    if chunk_s is None:
        chunk_s = PACED_CHUNK_S if config.rate.paced else MAX_MODE_CHUNK_S
    sc = config.scenario
    core = SimCore(
        sc, config.run_seed, config.duration_s, config.render, config.boot_start_us, chunk_s, nav_noise=config.nav_noise
    )

    zs = config.zenoh if config.zenoh is not None else ZenohSettings()
    session = publisher = vehicle = writer = recorder = None
    try:
        session = open_session(zs)
        if config.render:
            publisher = FramePublisher(session, config.vehicle)
        vehicle = MavlinkVehicle(config.mavlink, gimballed=core.gimballed)
        if config.truth_path is not None:
            writer = TruthWriter(config.truth_path)
        if config.record_path is not None:
            recorder = _start_recorder(config, core)
            publisher, writer = _RecordingPublisher(publisher, recorder), _RecordingTruth(writer, recorder)
            _tap_mavlink(vehicle, recorder)
        log.info(
            "scenario %s (seed %d), %.2f s, %s, navigation errors %s, mavlink %s, zenoh key %s%s",
            sc.name,
            config.run_seed,
            core.duration_s,
            "gimballed" if core.gimballed else "fixed pod (observer yaws toward the target)",
            core.nav_noise.name,
            config.mavlink,
            frame_key(config.vehicle),
            "" if config.render else " (rendering off: no frames)",
        )
        return run_loop(core, config.rate, mavlink=vehicle, publisher=publisher, truth=writer, stop=stop, clock=clock)
    finally:
        for closer in (writer, publisher, vehicle, session, recorder):
            if closer is not None:
                try:
                    closer.close()
                except Exception as exc:  # noqa: BLE001 - closing must not mask the run's outcome
                    log.debug("close %s: %s", type(closer).__name__, exc)


# --------------------------------------------------------------------------- --record (onboard.io.record)


def _start_recorder(config: RunConfig, core: SimCore):
    import time as _time

    from onboard.io.record import FlightRecorder, RecordSettings

    meta = {
        "scenario": config.scenario.name,
        "run_seed": str(config.run_seed),
        "duration_s": f"{core.duration_s:g}",
        "nav_noise": core.nav_noise.name,
        "rate": config.rate.text,
    }
    rec = FlightRecorder(
        RecordSettings(str(config.record_path)),
        vehicle=config.vehicle,
        metadata=meta,
        recorder="groundsim",
        clock_ns=_time.monotonic_ns,
    )
    rec.start()
    return rec


class _RecordingPublisher:
    """The frame publisher, each published frame also recorded (foxglove.RawImage)."""

    def __init__(self, publisher, recorder) -> None:
        self._pub, self._rec = publisher, recorder

    def publish(self, frame) -> None:
        import time as _time

        if self._pub is not None:
            self._pub.publish(frame)
        self._rec.on_frame(frame, _time.monotonic_ns())

    def close(self) -> None:
        if self._pub is not None:
            self._pub.close()


class _RecordingTruth:
    """The truth writer (or none), each frame's truth row also recorded (``irtrack.truth/1``)."""

    def __init__(self, writer, recorder) -> None:
        self._writer, self._rec = writer, recorder

    def write(self, row: TruthRow) -> None:
        from onboard.io.foxglove_messages import TRUTH_SCHEMA
        from onboard.io.record import TRUTH_TOPIC

        if self._writer is not None:
            self._writer.write(row)
        self._rec.on_json(TRUTH_TOPIC, TRUTH_SCHEMA, truth_json(row))

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()


def truth_json(row: TruthRow) -> dict:
    """A truth row as ``irtrack.truth/1``: every CSV column (NaN as null) plus vectors for viewers."""
    import dataclasses as _dc

    out = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in _dc.asdict(row).items()}
    out["target_ned_m"] = [row.target_n_m, row.target_e_m, row.target_d_m]
    out["target_vel_ned_mps"] = [row.target_vn_mps, row.target_ve_mps, row.target_vd_mps]
    out["camera_ned_m"] = [row.cam_n_m, row.cam_e_m, row.cam_d_m]
    return out


def _tap_mavlink(vehicle, recorder) -> None:
    """Record every datagram the vehicle's pymavlink connection writes (tx) and reads (rx)."""
    conn = getattr(vehicle, "_conn", None)
    if conn is None:
        return
    write, recv = conn.write, conn.recv

    def tapped_write(buf):
        recorder.on_mavlink(bytes(buf), "vehicle", None, "tx")
        return write(buf)

    def tapped_recv(n=None):
        data = recv(n)
        if data:
            recorder.on_mavlink(bytes(data), "vehicle", None, "rx")
        return data

    conn.write, conn.recv = tapped_write, tapped_recv
