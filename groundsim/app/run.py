"""``python -m groundsim run``: the ground simulator's main loop (wiring; the pieces live elsewhere).

It flies the observer and the target (JSBSim, :mod:`groundsim.world.flight`), renders what the
observer's thermal camera sees (:mod:`groundsim.world.render`) and emits what a real drone would:
MAVLink telemetry (:mod:`groundsim.io.mavlink_vehicle`), IR frames on zenoh
(:mod:`groundsim.io.zenoh_video`), plus one ground-truth CSV row per frame (:mod:`groundsim.world.truth`).

The simulated world -- ticks, frames, the pair flight, navigation errors, truth rows, determinism --
is :class:`groundsim.world.sim.SimCore`; this loop feeds its ticks to the MAVLink vehicle (its own
schedule picks #31 at 50 Hz, #33 at 25 Hz, #285 at 10 Hz, HEARTBEAT and SYSTEM_TIME at 1 Hz, and answers
TIMESYNC/commands) and publishes its frames as ``IrFrame(seq=k, time_boot_us)`` (stating zoom 1.0: ``CAMERA_ZOOM``), each with its truth row.
JSBSim flies a chunk of whole frames at a time (``PACED_CHUNK_S`` when paced, ``MAX_MODE_CHUNK_S`` at
``--rate max``); chunking does not change the flight.

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

Several observers (a fleet scenario, ``observers:``).  Each observer is a vehicle of its own: a
:class:`~groundsim.world.sim.SimCore` of its view of the scenario (one shared world and targets; its own
path, camera, navigation errors, boot clock), its own MAVLink endpoint (``--mavlink NAME=ENDPOINT``; an
observer not named gets ``udpout:127.0.0.1:<14540 + its index>``), its frames on ``irtrack/<NAME>/ir/frame``
and its own truth file (``--truth out/truth.csv`` -> ``out/truth.<NAME>.csv``).  They step through the same
ticks in lockstep, one after the other within a tick, so a fleet run is as deterministic as a single one.
Every vehicle's SYSTEM_TIME maps its boot clock to the one simulated UTC (``start_time_utc`` of the scenario,
or ``--start-time-utc``), which the truth's ``time_unix_us`` column also carries.

Stopping.  ``stop`` (a ``threading.Event``, set by SIGINT/SIGTERM in the CLI) is checked at every
tick and while sleeping (at most ``STOP_POLL_S``); the loop then returns at once, the truth file
holds whole lines for every frame published, and :func:`run` closes the sockets.
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from groundsim.world.guided import GUIDED_SETPOINT_TIMEOUT_S
from groundsim.world.nav_errors import InjectedErrors
from groundsim.world.scenario import Scenario
from groundsim.world.sim import (
    BOOT_START_US,
    CAMERA_ZOOM,
    SimCore,
    ThrottledErrorLog,
    check_duration_s,
    check_run_seed,
    extend_scenario,
)
from groundsim.world.spec import NAME_PATTERN
from groundsim.world.truth import TruthRow, TruthWriter, truth_json, truth_json_schema, truth_objects_json
from onboard.core.errors import ConfigError, IrtrackError

__all__ = [
    "RateSpec",
    "RunConfig",
    "RunReport",
    "VehicleLeg",
    "DEFAULT_FLEET_MAVLINK_PORT",
    "split_mavlink_option",
    "mavlink_endpoints",
    "fleet_truth_path",
    "parse_start_time",
    "JitterSummary",
    "JitterStats",
    "Pacer",
    "SystemClock",
    "run_loop",
    "run_fleet_loop",
    "run",
]

log = logging.getLogger(__name__)

MAX_MODE_CHUNK_S = 1.0  # at --rate max, JSBSim flies this much simulated time per call (fewer, cheaper calls)
PACED_CHUNK_S = 0.1  # when paced: short calls (~4 ms fixed + ~0.3 ms per tick, a burst well inside one frame)
STATUS_EVERY_S = 1.0  # wall seconds between status lines
JITTER_LOG_EVERY_S = 5.0  # wall seconds between jitter reports when paced
STOP_POLL_S = 0.05  # longest uninterrupted sleep: the stop flag is seen within this
MIN_FACTOR, MAX_FACTOR = 0.01, 1000.0
DEFAULT_FLEET_MAVLINK_PORT = 14540  # a fleet's observer i without --mavlink NAME=... sends to this port + i


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


def split_mavlink_option(text: str) -> tuple[str | None, str]:
    """``--mavlink NAME=ENDPOINT`` -> ``(NAME, ENDPOINT)``; a plain connection string -> ``(None, text)``
    (pymavlink's connection strings hold no ``=`` before their first ``:``)."""
    name, sep, conn = str(text).partition("=")
    if sep and NAME_PATTERN.match(name):
        return name, conn
    return None, str(text)


def utc_errors(scenario: Scenario, values, vehicle: str) -> tuple[tuple[str, int], ...]:
    """The ``--utc-error-ms NAME=MS`` options as ``((vehicle name, error us), ...)``: NAME one of the
    scenario's vehicles (the ``--vehicle`` of a single observer), each at most once, MS a finite number of
    milliseconds within a minute; ConfigError naming ``--utc-error-ms`` otherwise."""
    names = [o.name for o in scenario.observers] if scenario.is_fleet else [vehicle]
    out: dict[str, int] = {}
    for text in values or ():
        name, sep, ms_text = str(text).partition("=")
        name = name.strip()
        try:
            ms = float(ms_text)
        except ValueError:
            ms = math.nan
        if not sep or name not in names or name in out or not (math.isfinite(ms) and abs(ms) <= 60_000.0):
            raise ConfigError(
                f"--utc-error-ms: expected NAME=MS with NAME one of {', '.join(names)} (each once) and MS a number of"
                f" milliseconds within +-60000, got {text!r}"
            )
        out[name] = round(ms * 1000.0)
    return tuple(out.items())


def mavlink_endpoints(scenario: Scenario, values, vehicle: str) -> tuple[tuple[str, str], ...]:
    """The ``--mavlink`` options (a list of strings, possibly empty) as ``((vehicle name, connection), ...)``
    in observer order; ConfigError naming ``--mavlink`` for a mistake.

    One observer: at most one option, ``CONN`` or ``NAME=CONN`` with NAME the ``--vehicle`` (default: the
    simulator's default connection).  A fleet: every option ``NAME=CONN`` naming one of its observers, each at
    most once; an observer left out sends to ``udpout:127.0.0.1:<DEFAULT_FLEET_MAVLINK_PORT + index>``."""
    from groundsim.io.mavlink_vehicle import DEFAULT_CONNECTION

    values = list(values or ())
    if not scenario.is_fleet:
        if len(values) > 1:
            raise ConfigError(
                f"--mavlink: {scenario.name} has one observer: expected one connection, got {len(values)}"
            )
        if not values:
            return ((vehicle, DEFAULT_CONNECTION),)
        name, conn = split_mavlink_option(values[0])
        if name is not None and name != vehicle:
            raise ConfigError(
                f"--mavlink: {scenario.name} has one observer, vehicle {vehicle!r}: expected CONN or {vehicle}=CONN,"
                f" got {values[0]!r}"
            )
        return ((vehicle, conn),)
    names = [o.name for o in scenario.observers]
    given: dict[str, str] = {}
    for text in values:
        name, conn = split_mavlink_option(text)
        if name is None:
            raise ConfigError(
                f"--mavlink: {scenario.name} has several observers ({', '.join(names)}): expected NAME=ENDPOINT,"
                f" got {text!r}"
            )
        if name not in names:
            raise ConfigError(f"--mavlink: expected an observer of {scenario.name} ({', '.join(names)}), got {name!r}")
        if name in given:
            raise ConfigError(f"--mavlink: observer {name!r} given twice")
        given[name] = conn
    out = tuple((n, given.get(n, f"udpout:127.0.0.1:{DEFAULT_FLEET_MAVLINK_PORT + i}")) for i, n in enumerate(names))
    conns = [c for _, c in out]
    for i, c in enumerate(conns):
        if c in conns[:i]:
            raise ConfigError(f"--mavlink: observers {out[conns.index(c)][0]} and {out[i][0]} share endpoint {c!r}")
    return out


def fleet_truth_path(truth_path, name: str) -> Path:
    """A fleet's per-observer truth file: ``out/truth.csv`` -> ``out/truth.<name>.csv``."""
    p = Path(truth_path)
    return p.with_name(f"{p.stem}.{name}{p.suffix or '.csv'}")


def parse_start_time(text: str | None) -> int | None:
    """``--start-time-utc``: None (the scenario's ``start_time_utc``), ``now`` (the wall clock when the run
    starts) or an ISO 8601 UTC time -> us since the UNIX epoch (None for the scenario's); ConfigError otherwise."""
    from groundsim.world.scenario import parse_utc_us

    if text is None:
        return None
    if str(text).strip().lower() == "now":
        return time.time_ns() // 1000
    try:
        us = parse_utc_us(text)
    except ValueError:
        raise ConfigError(
            f"--start-time-utc: expected now or an ISO 8601 UTC time such as 2026-01-01T12:00:00Z, got {text!r}"
        ) from None
    if us < 0:  # SYSTEM_TIME's time_unix_usec is unsigned: no time before the UNIX epoch goes on the wire
        raise ConfigError(f"--start-time-utc: expected a time from 1970-01-01T00:00:00Z on, got {text!r}")
    return us


@dataclass(frozen=True)
class RunConfig:
    """Everything ``run`` needs, typed (built once by the CLI).

    ``duration_s`` None = the scenario's; a longer one extends the scenario's scripted motions
    (:func:`groundsim.world.sim.extend_scenario`).  ``run_seed``
    >= 0 selects the realisation (see the module docstring).  ``zenoh`` is an
    :class:`onboard.io.zenoh_session.ZenohConfig` (None: no endpoints, scouting off).
    ``truth_path`` None writes no truth.  ``flight_chunk_s`` None = automatic (``PACED_CHUNK_S`` or
    ``MAX_MODE_CHUNK_S``).  ``injected``: the navigation-error case (None = the scenario's ``nav_noise``,
    every observer's own in a fleet), GNSS dropout and camera clock error the run injects
    (:class:`groundsim.world.nav_errors.InjectedErrors`).
    ``mavlink_by_vehicle``: ``((name, connection), ...)`` of a fleet (:func:`mavlink_endpoints`; empty: each
    observer's default); a single observer uses ``mavlink`` and ``vehicle``.  ``start_time_unix_us``: the
    simulated UTC of t_s = 0 (None: the scenario's ``start_time_utc``).
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
    injected: InjectedErrors = field(default_factory=InjectedErrors)
    record_path: Path | None = None  # --record FILE.mcap: frames, MAVLink both ways and the truth (onboard.io.record)
    guided: bool = True  # the vehicle reports GUIDED and its observer follows velocity setpoints (--no-guided: not)
    mavlink_by_vehicle: tuple = ()
    start_time_unix_us: int | None = None
    utc_error_us: tuple = ()  # --utc-error-ms: ((vehicle name, us), ...), :func:`utc_errors`
    # --start-time-utc now: t = 0 is put on the wall clock again when the loop starts (start-up took ~0.5 s, which
    # every vehicle's UTC then trailed the machine's clock by, and the fusion node's clock check measured)
    start_time_now: bool = False
    #: --mavlink-signing-key: MAVLink 2 signing of every vehicle's link with this 32-byte key (None: unsigned)
    signing_key: bytes | None = None
    #: --gimbal-frame: the frame of a gimballed vehicle's #285, ``earth`` or ``vehicle`` (ArduPilot's, whatever the
    #: heartbeat says: groundsim.io.mavlink_vehicle)
    gimbal_frame: str = "earth"

    def __post_init__(self) -> None:
        sc = self.scenario
        if not isinstance(sc, Scenario):
            raise ConfigError(f"RunConfig.scenario must be a Scenario, got {type(sc).__name__}")
        if sc.is_fleet:
            given = [f"{n}={c}" for n, c in self.mavlink_by_vehicle]
            object.__setattr__(self, "mavlink_by_vehicle", mavlink_endpoints(sc, given, self.vehicle))
            if self.record_path is not None:
                raise ConfigError(f"--record: not supported for a scenario of several observers ({sc.name}) yet")
        elif self.mavlink_by_vehicle:
            raise ConfigError(f"RunConfig.mavlink_by_vehicle: {sc.name} has one observer: use mavlink and vehicle")
        u = self.start_time_unix_us
        if u is not None and (isinstance(u, bool) or not isinstance(u, int) or not 0 <= u < 2**62):
            raise ConfigError(f"RunConfig.start_time_unix_us must be a UNIX time in us or None, got {u!r}")
        object.__setattr__(self, "run_seed", check_run_seed(self.run_seed))
        from groundsim.io.vehicle_messages import check_gimbal_frame

        check_gimbal_frame(self.gimbal_frame)
        object.__setattr__(self, "duration_s", check_duration_s(self.duration_s, sc))
        object.__setattr__(self, "scenario", extend_scenario(sc, self.duration_s))
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
        if not isinstance(self.injected, InjectedErrors):
            raise ConfigError(f"RunConfig.injected must be an InjectedErrors, got {type(self.injected).__name__}")
        if self.injected.gnss_dropout is not None:
            self.injected.gnss_dropout.check_within(self.duration_s)
        if self.zenoh is not None:
            from onboard.io.zenoh_session import ZenohConfig

            if not isinstance(self.zenoh, ZenohConfig):
                raise ConfigError(f"RunConfig.zenoh must be a ZenohConfig or None, got {type(self.zenoh).__name__}")


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
    record_files: tuple[str, ...] = ()  # --record: the files the recording is in (empty without --record)

    def line(self) -> str:
        s = (
            f"{'stopped' if self.stopped else 'done'}: {self.frames}/{self.frames_total} frames, {self.sim_s:.2f} s simulated"
            f" in {self.wall_s:.2f} s (rt x{self.rt_factor:.2f}, rate {self.rate}; set-up {self.setup_s:.2f} s)"
        )
        if self.errors:
            s += "; errors " + ", ".join(f"{k} {v}" for k, v in sorted(self.errors.items()))
        return s


@dataclass
class VehicleLeg:
    """One simulated vehicle of a run: its :class:`SimCore` and its sinks (any may be None), see :func:`run_loop`.
    ``name``: the vehicle's name (a fleet's observer; it prefixes the fleet's MAVLink counters)."""

    core: SimCore
    mavlink: object | None = None
    publisher: object | None = None
    truth: object | None = None
    name: str = ""


def run_loop(
    core: SimCore,
    rate: RateSpec,
    *,
    mavlink=None,
    publisher=None,
    truth: TruthWriter | None = None,
    stop: threading.Event | None = None,
    clock=None,
    camera_clock=None,
    on_start=None,
) -> RunReport:
    """Drive ``core`` tick by tick into the sinks (any may be None); see the module docstring.
    ``camera_clock``: a :class:`groundsim.world.nav_errors.CameraClockError` that stamps the frames (None: exact).
    ``on_start``: called at the instant t = 0 is paced from (``--start-time-utc now`` puts UTC there).

    ``mavlink``: has ``update_state(**state, nav_error=sample)`` and ``poll(now_boot_us)`` (a MavlinkVehicle);
    ``publisher``: has ``publish(IrFrame)`` (a FramePublisher); ``truth``: a TruthWriter.
    Per-event errors (a sink's IrtrackError or zenoh error, a frame the renderer refuses) are
    counted in ``RunReport.errors`` and logged at most every 10 s, never raised; a flight failure
    (FlightError) or a truth file that cannot be written ends the run by raising.
    """
    leg = VehicleLeg(core, mavlink, publisher, truth)
    return run_fleet_loop([leg], rate, stop=stop, clock=clock, camera_clock=camera_clock, on_start=on_start)


def run_fleet_loop(
    legs,
    rate: RateSpec,
    *,
    stop: threading.Event | None = None,
    clock=None,
    camera_clock=None,
    on_start=None,
) -> RunReport:
    """:func:`run_loop` for one or several vehicles (:class:`VehicleLeg`), stepped in lockstep on one tick
    grid (their cores share the scenario's timing): within a tick each vehicle in turn gets its MAVLink poll,
    and at a frame's tick each publishes its frame and writes its truth row."""
    from onboard.core.irframe import IrFrame

    try:
        import zenoh

        sink_errors: tuple = (IrtrackError, zenoh.ZError)
    except ImportError:  # pragma: no cover - zenoh is a dependency
        sink_errors = (IrtrackError,)
    legs = list(legs)
    core = legs[0].core
    for leg in legs[1:]:
        if (leg.core.tick_count, leg.core.ticks_per_frame) != (core.tick_count, core.ticks_per_frame):
            raise ConfigError("run_fleet_loop: the vehicles' cores must share one tick grid")
    fleet = len(legs) > 1
    stop = stop if stop is not None else threading.Event()
    clock = clock if clock is not None else SystemClock()
    pacer = Pacer(rate.factor, clock)
    jitter = JitterStats(1.0 / core.frame_rate_hz / (rate.factor or 1.0)) if rate.paced else None

    t_setup = clock.now_s()
    pending = [leg.core.frame(0) if not stop.is_set() else None for leg in legs]
    setup_s = clock.now_s() - t_setup
    flight_setup_s = sum(leg.core.flight.flight_s for leg in legs)
    render_setup_s = sum(leg.core.render_s for leg in legs)
    log.info(
        "set-up %.2f s (flight %.2f s); %d frames at %g Hz, %d ticks at %g Hz, rate %s%s",
        setup_s,
        flight_setup_s,
        core.frame_count,
        core.frame_rate_hz,
        core.tick_count,
        core.tick_rate_hz,
        rate.text,
        f", {len(legs)} vehicles" if fleet else "",
    )

    if rate.paced:
        # the set-up left a large heap (SciPy, OpenCV, zenoh, JSBSim); a full collection of it stalls
        # the loop for tens of ms.  Freeze it so collections only scan new objects.
        gc.collect()
        gc.freeze()
    m = core.ticks_per_frame
    n_frames = core.frame_count
    mavlink_errors, publish_errors = ThrottledErrorLog("mavlink_error"), ThrottledErrorLog("publish_error")
    acc = {"publish": 0.0, "mavlink": 0.0, "truth": 0.0}
    published = 0
    frames = 0
    if on_start is not None:
        on_start()  # the instant t = 0 is paced from (--start-time-utc now puts UTC there)
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
            for leg in legs:
                if leg.mavlink is None:
                    continue
                c, vehicle = leg.core, leg.mavlink
                t0 = clock.now_s()
                try:
                    vehicle.update_state(**c.vehicle_state(i), nav_error=c.nav_error(i))
                    vehicle.poll(c.time_boot_us(i))
                    for v_ned_mps in getattr(vehicle, "take_setpoints", list)():  # guided: the observer follows them
                        t_s = c.tick_time_s(i)
                        c.flight.command_observer(t_s, v_ned_mps, t_s + GUIDED_SETPOINT_TIMEOUT_S)
                    if getattr(vehicle, "take_hold", bool)():  # a ground station switched to LOITER: hold there
                        t_s = c.tick_time_s(i)
                        c.flight.command_observer(t_s, (0.0, 0.0, 0.0), t_s)
                except sink_errors as exc:
                    mavlink_errors(f"tick {i}: mavlink{' ' + leg.name if fleet else ''}", exc)
                acc["mavlink"] += clock.now_s() - t0
            if r == 0:
                wall = clock.now_s()
                if jitter is not None:
                    jitter.add(wall, late)
                t_prev = wall  # one clock reading per step, as many as for one vehicle (fake clocks count them)
                for n, leg in enumerate(legs):
                    frame = pending[n]
                    if leg.publisher is not None and frame.pixels is not None:
                        try:
                            stamp: int | None = frame.time_boot_us
                            if camera_clock is not None:
                                stamp = camera_clock.stamp_us(frame.time_boot_us, frame.truth.t_s)
                            if stamp is not None:  # None: the camera clock puts it before boot, not sent
                                leg.publisher.publish(IrFrame(frame.seq, stamp, frame.pixels, zoom=CAMERA_ZOOM))
                                published += 1
                        except sink_errors as exc:
                            publish_errors(f"frame {frame.seq}: publish{' ' + leg.name if fleet else ''}", exc)
                    t1 = clock.now_s()
                    acc["publish"] += t1 - t_prev
                    if leg.truth is not None:
                        leg.truth.write(frame.truth, frame.labels)
                    t_prev = clock.now_s()
                    acc["truth"] += t_prev - t1
                frames += 1
                pending = [leg.core.frame(k + 1) if k + 1 < n_frames else None for leg in legs]
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
        "flight": 1e3 * (sum(leg.core.flight.flight_s for leg in legs) - flight_setup_s) / nf,
        "render": 1e3 * (sum(leg.core.render_s for leg in legs) - render_setup_s) / nf,
        "publish": 1e3 * acc["publish"] / nf,
        "mavlink": 1e3 * acc["mavlink"] / nf,
        "truth": 1e3 * acc["truth"] / nf,
    }
    errors = {e.kind: e.count for e in (mavlink_errors, publish_errors) if e.count}
    render_errors = sum(leg.core.render_errors.count for leg in legs)
    if render_errors:
        errors[core.render_errors.kind] = render_errors
    counters: dict = {}
    for leg in legs:
        for key, value in dict(getattr(leg.mavlink, "counters", {}) or {}).items():
            counters[f"{leg.name}.{key}" if fleet else key] = value
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
        errors=errors,
        mavlink_counters=counters,
        frames_published=published,
    )
    log.info("%s", report.line())
    if report.jitter is not None:
        log.info("pacing: %s", report.jitter.line())
    return report


def run(config: RunConfig, stop: threading.Event | None = None, clock=None) -> RunReport:
    """Open the adapters of ``config`` (zenoh, MAVLink, truth file), run, close them.

    A fleet scenario opens them per observer (see the module docstring).  Opening errors (port in use,
    unreachable zenoh peer, bad endpoint, unwritable truth path) raise
    :class:`~onboard.core.errors.IrtrackError` subclasses with one-line messages before any flying starts.
    """
    from groundsim.io.mavlink_vehicle import MavlinkVehicle
    from groundsim.io.zenoh_video import FramePublisher
    from onboard.io.zenoh_session import ZenohConfig, frame_key, open_session

    sc = config.scenario
    fleet = sc.is_fleet
    endpoints = config.mavlink_by_vehicle if fleet else ((config.vehicle, config.mavlink),)
    for name, _ in endpoints:
        frame_key(name)  # validates the vehicle names before opening anything
    chunk_s = config.flight_chunk_s
    if chunk_s is None:
        chunk_s = PACED_CHUNK_S if config.rate.paced else MAX_MODE_CHUNK_S
    boot = None if fleet else config.boot_start_us  # a fleet's vehicles: each view's own boot clock
    cores = [
        SimCore(
            view,
            config.run_seed,
            config.duration_s,
            config.render,
            boot,
            chunk_s,
            nav_noise=config.injected.nav_noise,
            start_time_unix_us=config.start_time_unix_us,
        )
        for view in sc.observer_views()
    ]

    utc_error_us = dict(config.utc_error_us)

    def reported_unix_at_boot_us(core: SimCore, name: str) -> int:
        """UTC at boot as the vehicle's SYSTEM_TIME says it: wrong by its ``--utc-error-ms`` (its frames and the
        truth keep the true UTC)."""
        return core.unix_time_at_boot_us + utc_error_us.get(name, 0)

    zs = config.zenoh if config.zenoh is not None else ZenohConfig()
    dropout = config.injected.gnss_dropout
    legs: list[VehicleLeg] = []
    session = recorder = None
    try:
        session = open_session(zs)
        for core, (name, conn) in zip(cores, endpoints):
            leg = VehicleLeg(core, name=name)
            legs.append(leg)
            if config.render:
                leg.publisher = FramePublisher(session, name)
            outage = None if dropout is None else dropout.boot_window_us(core.boot_start_us)
            leg.mavlink = MavlinkVehicle(
                conn,
                gimballed=core.gimballed,
                gimbal_yaw_frame=config.gimbal_frame,
                guided=config.guided,
                gnss_outage_us=outage,
                gnss_accuracy=core.nav_noise.gnss_accuracy_m(),
                signing_key=config.signing_key,
                unix_time_at_boot_us=reported_unix_at_boot_us(core, name),
            )
            if config.truth_path is not None:
                leg.truth = TruthWriter(fleet_truth_path(config.truth_path, name) if fleet else config.truth_path)
        if dropout is not None:
            log.info(
                "GNSS dropout from %.2f s for %.2f s: no GLOBAL_POSITION_INT, GPS_RAW_INT without a fix",
                dropout.start_s,
                dropout.duration_s,
            )
        if config.record_path is not None:  # one vehicle (RunConfig refuses --record for a fleet)
            leg = legs[0]
            recorder = _start_recorder(config, leg.core)
            leg.publisher, leg.truth = (
                _RecordingPublisher(leg.publisher, recorder),
                _RecordingTruth(leg.truth, recorder),
            )
            _tap_mavlink(leg.mavlink, recorder)
        for leg in legs:
            core = leg.core
            log.info(
                "scenario %s (seed %d), %.2f s, %s, navigation errors %s, mavlink %s, zenoh key %s%s%s",
                sc.name,
                config.run_seed,
                core.duration_s,
                f"gimballed (#285 in the {config.gimbal_frame} frame)"
                if core.gimballed
                else "fixed pod (observer yaws toward the target)",
                core.nav_noise.name,
                getattr(leg.mavlink, "connection", ""),
                frame_key(leg.name),
                "" if config.render else " (rendering off: no frames)",
                f", boot clock {core.boot_start_us / 1e6:.3f} s at t = 0" if fleet else "",
            )

        def utc_now() -> None:
            now_us = time.time_ns() // 1000
            for leg in legs:
                leg.core.start_time_unix_us = now_us
                leg.mavlink.set_unix_time_at_boot_us(reported_unix_at_boot_us(leg.core, leg.name))

        on_start = utc_now if config.start_time_now else None
        if not fleet:
            leg = legs[0]
            report = run_loop(
                leg.core,
                config.rate,
                mavlink=leg.mavlink,
                publisher=leg.publisher,
                truth=leg.truth,
                stop=stop,
                clock=clock,
                camera_clock=config.injected.camera_clock,
                on_start=on_start,
            )
        else:
            report = run_fleet_loop(
                legs, config.rate, stop=stop, clock=clock, camera_clock=config.injected.camera_clock, on_start=on_start
            )
    finally:
        closers = [c for leg in legs for c in (leg.truth, leg.publisher, leg.mavlink)] + [session, recorder]
        for closer in closers:
            if closer is not None:
                try:
                    closer.close()
                except Exception as exc:  # noqa: BLE001 - closing must not mask the run's outcome
                    log.debug("close %s: %s", type(closer).__name__, exc)
    if recorder is not None:  # where it went: another name when --record's held an earlier recording, or rotated
        report = dataclasses.replace(report, record_files=tuple(map(str, recorder.files)) or (str(recorder.path),))
    return report


# --------------------------------------------------------------------------- --record (onboard.io.record)


def _start_recorder(config: RunConfig, core: SimCore):
    import time as _time

    from onboard.io.foxglove_messages import TRUTH_SCHEMA
    from onboard.io.record import FlightRecorder, RecordConfig

    meta = {
        "scenario": config.scenario.name,
        "run_seed": str(config.run_seed),
        "duration_s": f"{core.duration_s:g}",
        "nav_noise": core.nav_noise.name,
        "rate": config.rate.text,
    }
    # the recorder opens its file here: an unwritable path is the operator's mistake, said in one line as --truth's
    try:
        rec = FlightRecorder(
            RecordConfig(path=str(config.record_path)),
            vehicle=config.vehicle,
            metadata=meta,
            recorder="groundsim",
            clock_ns=_time.monotonic_ns,
            json_schemas={TRUTH_SCHEMA: truth_json_schema(TRUTH_SCHEMA)},
        )
        rec.start()
    except OSError as exc:
        where = f" ({exc.filename})" if exc.filename and str(exc.filename) != str(config.record_path) else ""
        raise ConfigError(f"--record {config.record_path}: cannot write: {exc.strerror or exc}{where}") from None
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
    """The truth writer (or none), each frame's truth row also recorded (``irtrack.truth/1``), and with a scene its
    objects' labels (``irtrack.truth_objects/1`` and their boxes as foxglove.ImageAnnotations)."""

    def __init__(self, writer, recorder) -> None:
        self._writer, self._rec = writer, recorder

    def write(self, row: TruthRow, labels=()) -> None:
        from onboard.io.foxglove_messages import TRUTH_SCHEMA
        from onboard.io.record import TRUTH_TOPIC

        if self._writer is not None:
            self._writer.write(row, labels)
        self._rec.on_json(TRUTH_TOPIC, TRUTH_SCHEMA, truth_json(row), sequence=row.seq)
        if labels:  # a scene's objects (the rows of <truth>.objects.csv): /groundsim/truth/objects
            self._rec.on_truth_objects(truth_objects_json(row, labels))

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()


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
