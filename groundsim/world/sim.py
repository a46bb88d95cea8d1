"""The simulated world on the simulator's tick grid: the pair flight, the frames, their truth (no sockets or files).

:class:`SimCore` is what ``python -m groundsim run`` (:mod:`groundsim.app.run`, which adds the sockets,
the files and the wall clock), the lockstep evaluation and the dataset export all step through.

Clock and events
----------------
The simulation clock *is* the vehicle's boot clock: ``time_boot_us = boot_start_us + round(t_s *
1e6)`` with ``t_s`` the scenario time (``boot_start_us`` = 1 s, so a receiver never sees boot time
0; an observer of a fleet has its own, ``Scenario.boot_start_us`` of its view).  Beside it runs one
simulated UTC shared by every vehicle: ``time_unix_us = start_time_unix_us + round(t_s * 1e6)``
(default: the scenario's ``start_time_utc``, so it never depends on the wall clock); the vehicle's
SYSTEM_TIME carries it (:attr:`SimCore.unix_time_at_boot_us`) and every truth row has it.  Time advances in *ticks* of ``1 / (frame_rate_hz * ticks_per_frame)`` seconds, with
``ticks_per_frame = ceil(MIN_POLL_RATE_HZ / frame_rate_hz)`` (4 at 30 Hz: a 120 Hz tick).  At
every tick the observer's true state is available as :meth:`SimCore.vehicle_state` (what the
MAVLink vehicle is handed) with its navigation error :meth:`SimCore.nav_error`; every
``ticks_per_frame``-th tick is a camera frame ``k`` (:meth:`SimCore.frame`): the pose at exactly that
capture time -> render -> pixels, and its truth row.  Frames cover ``k < duration_s * frame_rate_hz``.

Flight.  Both vehicles are flown by JSBSim on the tick grid, a chunk of whole frames at a time,
exactly as :func:`groundsim.world.flight.fly_pair` flies them (target first, heading along its
velocity; then the observer) -- chunking does not change the flight.  Without a gimbal the observer
yaws toward the target's flown position (the pod is fixed); with one it heads along its path and the
gimbal (:func:`groundsim.world.flight.guidance.gimbal_pointing`) aims at the target plus the scenario's
sinusoidal pointing error (phases drawn from ``scenario.rng("gimbal.pointing_phase", seed)``); its
attitude ``q_ned_from_gimbal`` is part of the vehicle state (earth frame).  A scenario's
``other_targets`` are flown the same way as the target, each after it, and drawn as scene objects 1..n.

Scene.  A scenario with a ``scene`` (clouds, terrain, distractors, crossover, the camera model) or other
targets renders through :class:`~groundsim.world.render.scene.SceneContent` (and
:class:`~groundsim.world.render.sensor.Sensor`): :meth:`SimCore.frame` then carries every object's label
and the camera's status; otherwise the renderer's own ``render`` makes the frame, byte for byte as before.

Duration.  ``duration_s`` None is the scenario's; a longer one extends the scenario
(:func:`extend_scenario`): the scripted motions continue as their models define them, the target's
disturbance is realised over the longer span (its first ``duration_s`` unchanged), and a model that is
defined only over the scenario's span is refused by name.  The flight of the first ``duration_s`` is the
scenario's own; the navigation errors' white noise is drawn for the whole tick grid at once
(:mod:`groundsim.world.nav_errors`), so a run of another duration has other draws.

Navigation errors.  The vehicle reports the truth with the run's navigation errors
(:mod:`groundsim.world.nav_errors`), case ``nav_noise`` (default: the scenario's ``nav_noise``, itself
RTK by default) drawn from ``scenario.rng("nav.errors", seed)``.  The truth rows keep the exact values
and record the injected errors of each frame's tick (``nav_*`` columns, :mod:`groundsim.world.truth`).

Determinism.  Truth rows and frames depend only on the scenario, the run seed (the target's
disturbance realisation, the render noise ``scenario.rng("render.noise", seed)``, the scene's and the
camera model's patterns ``"render.scene"`` and ``"render.sensor"``, the gimbal phases, the navigation
errors), ``nav_noise`` and the duration; never on the wall clock or chunking.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from groundsim.world.guided import GuidedReference
from groundsim.world.motion import Circular, Cubic, FigureEight, Perturbed, Waypoints
from groundsim.world.scenario import (
    MAX_DURATION_S,
    MIN_SEPARATION_M,
    SINGER_MARGIN_S,
    Scenario,
    VehicleSpec,
    too_close,
)
from groundsim.world.truth import TruthRow, truth_row
from onboard.core.errors import ConfigError, InputError
from onboard.core.frames import (
    camera_pose_ned,
    euler_from_quat,
    geodetic_from_ned,
    q_ned_from_level,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_rotate,
    rotmat_from_quat,
)

if TYPE_CHECKING:  # imported where first used: JSBSim and the renderer load only when a run flies and renders
    from groundsim.world.flight import FlownVehicle
    from groundsim.world.render import IrRenderer

__all__ = [
    "BOOT_START_US",
    "CAMERA_ZOOM",
    "MIN_POLL_RATE_HZ",
    "GROUND_D_M",
    "EXTENSIBLE_MOTIONS",
    "ThrottledErrorLog",
    "PairFlight",
    "SimFrame",
    "SimCore",
    "check_run_seed",
    "check_duration_s",
    "extend_scenario",
    "frame_count",
]

log = logging.getLogger(__name__)

BOOT_START_US = 1_000_000  # the boot clock reads 1 s at t_s = 0
#: the zoom the simulated camera's frames state (IRF1's zoom field): it has a fixed lens and renders with the
#: scenario's intrinsics, the ones the daemon is configured with (groundsim demo), so always the calibrated one
CAMERA_ZOOM = 1.0
MIN_POLL_RATE_HZ = 100.0  # MAVLink is polled at least this often in simulated time
GROUND_D_M = 0.0  # flat ground at the scenario origin's height (the scenarios' origin is on the ground)
DURATION_EPS_S = 1e-9  # a duration this close to the scenario's is the scenario's
#: a scripted path continued past duration_s must stay below this speed: an F450-class quadrotor's top speed
#: is about 20-25 m/s, and a cubic path's speed grows without bound (P3's observer, continued to 30 s, passes
#: 46 m/s at 19.7 s, where the JSBSim flight diverged after minutes of work instead of a clear refusal)
MAX_EXTENDED_SPEED_MPS = 25.0
_FRAME_COUNT_EPS = 1e-9  # k < duration * rate, robust to float products (as groundsim.world.scenario)
_ERROR_LOG_EVERY_S = 10.0

#: motion models defined in closed form for every t >= 0, so a run may outlast the scenario's duration_s
#: (Waypoints holds its last point once its legs are flown, as it does within the scenario)
EXTENSIBLE_MOTIONS = (Cubic, Circular, FigureEight, Waypoints)


# --------------------------------------------------------------------------- options


def check_run_seed(seed) -> int:
    """A run seed: an integer in [0, 2^63); ConfigError naming ``--seed`` otherwise."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2**63:
        raise ConfigError(f"--seed: expected an integer in [0, 2^63), got {seed!r}")
    return int(seed)


def check_duration_s(duration_s, scenario: Scenario) -> float:
    """``--duration``: None = the scenario's ``duration_s``; otherwise a positive number of seconds up to
    the longest scenario (``MAX_DURATION_S``).  A duration beyond the scenario's is allowed: the run extends
    it (:func:`extend_scenario`)."""
    d = scenario.duration_s if duration_s is None else duration_s
    if isinstance(d, bool) or not isinstance(d, (int, float)) or not math.isfinite(d) or d <= 0:
        raise ConfigError(f"--duration: expected a positive number of seconds, got {duration_s!r}")
    if d > MAX_DURATION_S:
        raise ConfigError(f"--duration: expected at most {MAX_DURATION_S:g} s, got {d:g}")
    return float(d)


def _motion_name(motion) -> str:
    return type(motion).__name__


def _check_extensible(role: str, spec: VehicleSpec, scenario: Scenario, duration_s: float) -> None:
    base = spec.base_motion
    if not isinstance(base, EXTENSIBLE_MOTIONS):
        raise ConfigError(
            f"--duration: {scenario.name}'s {role} motion model {_motion_name(base)} is defined only over the"
            f" scenario's duration_s ({scenario.duration_s:g} s), so it cannot fly {duration_s:g} s; expected"
            f" at most {scenario.duration_s:g} s or a scenario whose {role} flies one of "
            + ", ".join(m.__name__ for m in EXTENSIBLE_MOTIONS)
        )


def _check_speed(
    role: str, motion, v_ned_mps: np.ndarray, scenario: Scenario, t_s: np.ndarray, duration_s: float
) -> None:
    """Refuses a continued path (``motion``, its velocities ``v_ned_mps`` at ``t_s``) faster than
    :data:`MAX_EXTENDED_SPEED_MPS`, naming when it gets there and the longest ``--duration`` that stays below it."""
    if not t_s.size:
        return
    with np.errstate(all="ignore"):
        speed_mps = np.linalg.norm(v_ned_mps, axis=-1)
    fast = np.flatnonzero(~(speed_mps <= MAX_EXTENDED_SPEED_MPS))
    if fast.size:
        k = int(fast[0])
        raise ConfigError(
            f"--duration: {scenario.name}'s {role} path ({_motion_name(motion)}), continued to {duration_s:g} s,"
            f" reaches {speed_mps[k]:.3g} m/s at t = {t_s[k]:.3f} s (a multirotor flies at most"
            f" {MAX_EXTENDED_SPEED_MPS:g} m/s); expected --duration at most {max(t_s[k], scenario.duration_s):.3g} s"
        )


def extend_scenario(scenario: Scenario, duration_s: float) -> Scenario:
    """``scenario`` lasting ``duration_s`` (itself when not longer than its ``duration_s``).

    The observer's and the target's scripted motions continue as their models define them (models of
    :data:`EXTENSIBLE_MOTIONS`); the target's disturbance, if any, is realised again from the same stream
    over the longer span (the Singer process is drawn sequentially, so its first ``duration_s`` is the
    scenario's own).  Raises ConfigError naming a model that cannot be extended, or paths that stop being
    finite, fly faster than ``MAX_EXTENDED_SPEED_MPS`` or come within ``MIN_SEPARATION_M`` of each other in the
    added time.
    """
    d = check_duration_s(duration_s, scenario)
    if d <= scenario.duration_s + DURATION_EPS_S:
        return scenario
    _check_extensible("observer", scenario.observer, scenario, d)
    _check_extensible("target", scenario.target, scenario, d)
    target = scenario.target
    if target.disturbance is not None:
        realisation = target.disturbance.realise(d + SINGER_MARGIN_S, scenario.rng("target.disturbance", 0))
        target = VehicleSpec(Perturbed(target.base_motion, realisation), target.base_motion, target.disturbance)
    others = []
    for i, o in enumerate(scenario.other_targets):
        _check_extensible(f"other_targets[{i}]", o.vehicle, scenario, d)
        v = o.vehicle
        if v.disturbance is not None:
            realisation = v.disturbance.realise(d + SINGER_MARGIN_S, scenario.rng(f"other_targets[{i}].disturbance", 0))
            v = VehicleSpec(Perturbed(v.base_motion, realisation), v.base_motion, v.disturbance)
        others.append(dataclasses.replace(o, vehicle=v))
    t_s = np.arange(frame_count(d, scenario.frame_rate_hz)) / scenario.frame_rate_hz
    t_s = t_s[t_s >= scenario.duration_s - DURATION_EPS_S]
    with np.errstate(all="ignore"):
        s_obs = scenario.observer.base_motion.state(t_s)
        s_tgt = target.base_motion.state(t_s)
        p_obs, p_tgt = s_obs.p_ned_m, s_tgt.p_ned_m
    if not (np.all(np.isfinite(p_obs)) and np.all(np.isfinite(p_tgt))):
        raise ConfigError(f"--duration: {scenario.name}'s scripted paths overflow before {d:g} s")
    _check_speed("observer", scenario.observer.base_motion, s_obs.v_ned_mps, scenario, t_s, d)
    for o in scenario.observers[1:]:  # a fleet's other observers: the first is ``observer``
        _check_extensible(f"observer {o.name}", o.vehicle, scenario, d)
        with np.errstate(all="ignore"):
            v = o.vehicle.base_motion.state(t_s).v_ned_mps
        _check_speed(f"observer {o.name}", o.vehicle.base_motion, v, scenario, t_s, d)
    _check_speed("target", target.base_motion, s_tgt.v_ned_mps, scenario, t_s, d)
    for i, o in enumerate(others):
        m = o.vehicle.base_motion
        with np.errstate(all="ignore"):
            v = m.state(t_s).v_ned_mps
        _check_speed(f"other_targets[{i}]", m, v, scenario, t_s, d)
    close = too_close(p_obs, p_tgt)
    if close is not None:
        k, r_m = close
        raise ConfigError(
            f"--duration: {scenario.name}'s scripted paths, continued to {d:g} s, come within {r_m:.3g} m"
            f" of each other at t = {t_s[k]:.3f} s (at least {MIN_SEPARATION_M:g} m expected)"
        )
    log.info(
        "%s extended from %g s to %g s: the observer (%s) and the target (%s) continue their scripted motions",
        scenario.name,
        scenario.duration_s,
        d,
        _motion_name(scenario.observer.base_motion),
        _motion_name(target.base_motion),
    )
    return dataclasses.replace(scenario, duration_s=d, target=target, other_targets=tuple(others))


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
    # what the observer's autopilot measures, relative to the local level where it is (onboard.core.frames)
    obs_q_level_from_body: np.ndarray
    obs_v_level_mps: np.ndarray
    obs_heading_rad: np.ndarray
    tgt_p_ned_m: np.ndarray
    tgt_v_ned_mps: np.ndarray
    tgt_q_ned_from_body: np.ndarray
    tgt_lat_deg: np.ndarray
    tgt_lon_deg: np.ndarray
    tgt_alt_m: np.ndarray
    q_mount_from_gimbal: np.ndarray | None
    q_ned_from_gimbal: np.ndarray | None
    q_level_from_gimbal: np.ndarray | None
    cam_p_ned_m: np.ndarray
    cam_q_ned_from_cam: np.ndarray
    others: tuple = ()  # per other target: (p_ned_m, v_ned_mps, q_ned_from_body) arrays of the ticks

    @property
    def i1(self) -> int:
        return self.i0 + len(self.t_s)


#: flight kept behind the newest tick flown (s): a lockstep feed reads telemetry up to 0.3 s past a frame (a GNSS
#: dropout's bracket search, ``groundsim.evaluation.telemetry_feed.FEED_LEAD_MAX_US``) before it asks for the frame,
#: which guided flight's 0.1 s chunks had dropped
FLOWN_KEPT_S = 0.5


class PairFlight:
    """Flies a scenario's observer and target with JSBSim on a time grid, ``chunk_ticks`` at a time.

    The same flight as :func:`groundsim.world.flight.fly_pair` on that grid (same vehicles, same order,
    same look-at rows; ``FlownVehicle.step_through`` does not depend on how calls are split).
    :meth:`ensure` flies up to a tick; :meth:`chunk_of` returns the arrays holding a tick (the most recent
    chunks, at least two and :data:`FLOWN_KEPT_S` of flight, are kept, so memory does not grow with the duration).
    """

    def __init__(self, scenario: Scenario, run_seed: int, times_s: np.ndarray, chunk_ticks: int) -> None:
        self.scenario = scenario
        self.times_s = np.asarray(times_s, dtype=float)
        self.chunk_ticks = max(1, int(chunk_ticks))
        tick_s = float(self.times_s[1] - self.times_s[0]) if self.times_s.size > 1 else 1.0
        self._kept_chunks = max(2, math.ceil(FLOWN_KEPT_S / (self.chunk_ticks * tick_s)) + 1)
        self.gimballed = scenario.camera.gimbal is not None
        self.observer_yaw_mode = "velocity" if self.gimballed else "target"
        # the scripted motion until a guided setpoint arrives (command_observer), then the setpoints
        self._obs_ref = GuidedReference(scenario.observer_motion(run_seed))
        self._tgt_ref = scenario.target_motion(run_seed)
        self._other_refs = [scenario.other_target_motion(i, run_seed) for i in range(len(scenario.other_targets))]
        self._others: list[FlownVehicle] = []
        g = scenario.camera.gimbal
        self.gimbal_phase_rad: tuple[float, ...] | None = None
        if g is not None:
            rng = scenario.rng("gimbal.pointing_phase", run_seed)
            self.gimbal_phase_rad = tuple(float(x) for x in rng.uniform(0.0, 2.0 * math.pi, 3))
        self._target: FlownVehicle | None = None
        self._observer: FlownVehicle | None = None
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
        raise IndexError(f"tick {i} was flown and dropped (only the latest {self._kept_chunks} chunks are kept)")

    def command_observer(self, t_s: float, v_ned_mps, valid_until_s: float | None = None) -> float:
        """A velocity setpoint for the observer (the GUIDED-like mode of :mod:`groundsim.world.guided`), in effect
        from ``t_s`` or from where the flight has got to, whichever is later (the ticks already flown keep their
        path: up to one flight chunk of latency); returns the time it took effect."""
        t_from = float(t_s)
        if self.flown_ticks > 0:
            t_from = max(t_from, float(self.times_s[min(self.flown_ticks, len(self.times_s) - 1)]))
        if self._observer is not None:
            t_from = max(t_from, self._observer.t_s)
        self._obs_ref.command(t_from, v_ned_mps, valid_until_s)
        if self._observer is not None:
            self._observer.reference_changed()
        return t_from

    @property
    def observer_guided_since_s(self) -> float | None:
        """When the observer left its scripted motion for setpoints (None: it has not)."""
        return self._obs_ref.guided_since_s

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
        if not self._others:
            self._others = [
                FlownVehicle(ref, sc.origin, sc.wind_ned_mps, yaw_mode="velocity", name=f"target{i + 1}", seed=sc.seed)
                for i, ref in enumerate(self._other_refs)
            ]
        others = tuple((o.p_ned_m, o.v_ned_mps, o.q_ned_from_body) for o in (v.step_through(t) for v in self._others))
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
        kept = self._chunks[-(self._kept_chunks - 1) :]
        self._chunks = kept + [dataclasses.replace(self._derive(a, t, obs, tgt), others=others)]
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
        q_level_from_ned = quat_conjugate(q_ned_from_level(lat[:n], lon[:n], sc.origin))
        q_level_from_body = quat_normalize(quat_multiply(q_level_from_ned, obs.q_ned_from_body))
        _, _, heading = euler_from_quat(q_level_from_body)
        q_mg = q_ng = q_lg = None
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
            q_lg = quat_normalize(quat_multiply(q_level_from_ned, q_ng))
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
            obs_q_level_from_body=q_level_from_body,
            obs_v_level_mps=quat_rotate(q_level_from_ned, obs.v_ned_mps),
            obs_heading_rad=np.asarray(heading),
            tgt_p_ned_m=tgt.p_ned_m,
            tgt_v_ned_mps=tgt.v_ned_mps,
            tgt_q_ned_from_body=tgt.q_ned_from_body,
            q_mount_from_gimbal=q_mg,
            q_ned_from_gimbal=q_ng,
            q_level_from_gimbal=q_lg,
            cam_p_ned_m=np.asarray(p_cam),
            cam_q_ned_from_cam=np.asarray(q_cam),
        )


class ThrottledErrorLog:
    """Counts one kind of error and logs it at most every ``_ERROR_LOG_EVERY_S`` (never raises)."""

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
    None when rendering is off or the camera dropped the frame) and its
    :class:`~groundsim.world.truth.TruthRow`.  With a scene (``scenario.scene``): ``labels``, one
    :class:`~groundsim.world.render.scene.ObjectLabel` per object (the target, id 0, first), and
    ``sensor_status`` (``ok`` / ``frozen`` / ``dropped``: the camera model's flat-field events; ``ok``
    without one).  The labels describe the image delivered: a frozen frame's are those of the image it
    repeats, a dropped frame's objects are ``occluded``; the truth row stays the frame's own time's.  Without
    a scene ``labels`` is empty: the truth row holds the one target.  ``target_box_px``: the target as drawn,
    ``(x0, y0, x1, y1)`` of the pixels holding at least ``BOX_FRACTION`` of its peak signal (ends exclusive;
    with a scene its label's box), None when it was not drawn."""

    seq: int
    time_boot_us: int
    pixels: np.ndarray | None
    truth: TruthRow
    labels: tuple = ()
    sensor_status: str = "ok"
    target_box_px: tuple[int, int, int, int] | None = None


def frame_count(duration_s: float, frame_rate_hz: float) -> int:
    """Frames ``k`` with ``k < duration_s * frame_rate_hz`` (at least one), as the scenario counts."""
    return max(1, math.ceil(duration_s * frame_rate_hz - _FRAME_COUNT_EPS))


class SimCore:
    """The simulated world on the tick grid, with step methods and no sockets or files.

    ``vehicle_state(i)``: keyword arguments of ``MavlinkVehicle.update_state`` at tick ``i`` (the
    truth); ``nav_error(i)``: the navigation error the vehicle reports it with
    (:class:`groundsim.world.nav_errors.NavErrorSample`); ``frame(k)``: fly (if needed), render and compute
    the truth of frame ``k``.  Ticks and frames must be asked for in non-decreasing order (older
    flight chunks are dropped).  ``duration_s``: None = the scenario's; a longer one extends the scenario
    (:func:`extend_scenario`; ``self.scenario`` is then the extended one).  ``nav_noise``: a
    :class:`~groundsim.world.scenario.NoiseCase`, a case name, or None (the scenario's ``nav_noise``).
    ``boot_start_us``: the boot clock at t_s = 0 (None: the scenario view's, else ``BOOT_START_US``);
    ``start_time_unix_us``: the simulated UTC at t_s = 0 (None: the scenario's ``start_time_utc``).
    A fleet scenario is simulated as its first observer's view (``scenario.observer_views()[0]``).
    """

    def __init__(
        self,
        scenario: Scenario,
        run_seed: int = 0,
        duration_s: float | None = None,
        render: bool = True,
        boot_start_us: int | None = None,
        flight_chunk_s: float | None = None,
        nav_noise=None,
        start_time_unix_us: int | None = None,
    ) -> None:
        from groundsim.world.nav_errors import NAV_ERROR_STREAM, NavErrorModel, run_nav_case

        if not isinstance(scenario, Scenario):
            raise ConfigError(f"SimCore: expected a Scenario, got {type(scenario).__name__}")
        if scenario.is_fleet:  # the fleet's first observer, exactly as a fleet run flies it
            scenario = scenario.observer_views()[0]
        if boot_start_us is None:
            boot_start_us = BOOT_START_US if scenario.boot_start_us is None else scenario.boot_start_us
        if isinstance(boot_start_us, bool) or not isinstance(boot_start_us, int) or not 0 <= boot_start_us < 2**40:
            raise ConfigError(f"SimCore: boot_start_us must be a non-negative integer, got {boot_start_us!r}")
        if start_time_unix_us is None:
            start_time_unix_us = scenario.start_time_utc_us
        u = start_time_unix_us
        if isinstance(u, bool) or not isinstance(u, int) or not boot_start_us <= u < 2**62:
            raise ConfigError(
                f"SimCore: start_time_unix_us must be an integer UNIX time in us not before boot, got {u!r}"
            )
        self.start_time_unix_us = u
        self.run_seed = check_run_seed(run_seed)
        self.duration_s = check_duration_s(duration_s, scenario)
        scenario = extend_scenario(scenario, self.duration_s)
        self.scenario = scenario
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
        case = run_nav_case(scenario, nav_noise)
        self.nav_noise = case
        self.nav_errors = NavErrorModel(case, scenario.rng(NAV_ERROR_STREAM, self.run_seed), self.times_s)
        self._renderer: IrRenderer | None = None
        self._scene = None  # SceneContent and Sensor, built on first use when the scenario has a scene
        self._imaged_labels: tuple | None = None  # the labels of the camera model's last image (a frozen frame's)
        self._sensor = None
        self.scene_enabled = scenario.scene.has_content or scenario.scene.sensor.enabled or bool(scenario.other_targets)
        self._other_rasters: tuple = ()
        self.render_s = 0.0  # wall seconds spent rendering
        self.render_errors = ThrottledErrorLog("render_error")

    def time_boot_us(self, i: int) -> int:
        return self.boot_start_us + round(float(self.times_s[i]) * 1e6)

    def time_unix_us(self, i: int) -> int:
        """Tick ``i``'s simulated UTC, us since the UNIX epoch (the same for every vehicle of a run)."""
        return self.start_time_unix_us + round(float(self.times_s[i]) * 1e6)

    @property
    def unix_time_at_boot_us(self) -> int:
        """UTC when the boot clock read 0: SYSTEM_TIME's ``time_unix_usec - time_boot`` for this vehicle."""
        return self.start_time_unix_us - self.boot_start_us

    def tick_time_s(self, i: int) -> float:
        return float(self.times_s[i])

    def vehicle_state(self, i: int) -> dict:
        """Tick ``i``'s observer as :meth:`groundsim.io.mavlink_vehicle.MavlinkVehicle.update_state` takes it.

        ``alt_rel_m`` (GLOBAL_POSITION_INT's "altitude above home") is above the scenario origin's altitude, the
        ground the observer took off from: the vehicle's HOME_POSITION is at that altitude (below the first
        sample), so the two agree on every tick and under navigation errors, which move both altitudes alike.

        The attitude, the velocity, the heading and the gimbal's earth-frame attitude are relative to the local level
        where the observer is, as an autopilot measures them (:mod:`onboard.core.frames`, "Local level"); the world
        simulated is in the origin's NED.
        """
        c = self.flight.chunk_of(i)
        j = i - c.i0
        return dict(
            time_boot_us=self.time_boot_us(i),
            lat_deg=float(c.obs_lat_deg[j]),
            lon_deg=float(c.obs_lon_deg[j]),
            alt_amsl_m=float(c.obs_alt_m[j]),
            alt_rel_m=float(c.obs_alt_m[j]) - self.scenario.origin.alt_m,
            v_ned_mps=c.obs_v_level_mps[j],
            q_ned_from_body=c.obs_q_level_from_body[j],
            body_rates_radps=c.obs_omega_frd_radps[j],
            heading_rad=float(c.obs_heading_rad[j]),
            q_gimbal=None if c.q_level_from_gimbal is None else c.q_level_from_gimbal[j],
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

    def scene(self):
        """``(SceneContent, Sensor or None)`` of a scenario with a scene (built on first use: textures take
        a second or two), seeded by ``scenario.rng("render.scene", seed)`` and ``("render.sensor", seed)``."""
        if self._scene is None:
            from groundsim.world.render.scene import SceneContent
            from groundsim.world.render.sensor import Sensor

            sc = self.scenario
            renderer = self.renderer()
            scene_seed = int(sc.rng("render.scene", self.run_seed).integers(0, 2**63 - 1))
            self._scene = SceneContent.from_config(sc.scene, renderer, scene_seed)
            self._other_rasters = tuple(self._scene.target_raster(o.parts) for o in sc.other_targets)
            if sc.scene.sensor.enabled:
                sensor_seed = int(sc.rng("render.sensor", self.run_seed).integers(0, 2**63 - 1))
                self._sensor = Sensor(sc.scene.sensor, sc.camera.intrinsics, sc.ir, sensor_seed, self.frame_rate_hz)
        return self._scene, self._sensor

    def other_targets_at(self, i: int) -> list:
        """The scenario's other targets at tick ``i`` as scene objects 1..n (SceneObject, class ``target``,
        their flown poses and their own parts) for ``SceneContent.render``."""
        from groundsim.world.render.scene import SceneObject

        self.scene()
        c = self.flight.chunk_of(i)
        j = i - c.i0
        return [
            SceneObject(n + 1, "target", np.asarray(p[j], float), rotmat_from_quat(q[j]), raster)
            for n, ((p, _, q), raster) in enumerate(zip(c.others, self._other_rasters))
        ]

    def _render_scene(self, k: int, t_s: float, p_cam, R_nc, p_t, R_nt, others=()):
        """Pixels, labels and the camera's status of frame ``k`` through the scene and the camera model.

        ``others``: :meth:`other_targets_at` the frame's tick.  Without the camera model: the renderer's
        grey map and NETD noise (``ir.encoding``).  With it: mono16 is the raw counts; mono8 the AGC output,
        or the counts' top 8 bits when the AGC is off."""
        scene, sensor = self.scene()
        fr = scene.render(t_s, p_cam, R_nc, p_t, R_nt, GROUND_D_M, others)
        if sensor is None:
            return self.renderer().quantise(fr.radiance), fr.labels, "ok"
        out = sensor.apply(fr.radiance, t_s, k)
        labels = fr.labels
        if out.status == "ok":
            self._imaged_labels = labels
        elif out.status == "frozen" and self._imaged_labels is not None:
            # the camera repeats its last image: the objects are where that image shows them, not where they
            # have flown since (a tracker on the frozen image is right, one following the truth is not)
            labels = self._imaged_labels
        else:  # the shutter is closed and nothing is imaged: every object is hidden behind it
            labels = tuple(
                dataclasses.replace(lab, visibility="occluded") if lab.visibility == "visible" else lab
                for lab in labels
            )
        if out.counts is None:
            return None, labels, out.status
        if self.scenario.ir.encoding == "mono16":
            return out.counts, labels, out.status
        if out.mono8 is not None:
            return out.mono8, labels, out.status
        return (out.counts >> (sensor.config.raw_bits - 8)).astype(np.uint8), labels, out.status

    def frame(self, k: int) -> SimFrame:
        if not 0 <= k < self.frame_count:
            raise IndexError(f"frame {k} outside [0, {self.frame_count})")
        i = k * self.ticks_per_frame
        c = self.flight.chunk_of(i)
        j = i - c.i0
        t_us = self.time_boot_us(i)
        pixels = None
        labels: tuple = ()
        status = "ok"
        target_box = None
        if self.render_enabled:
            renderer = self.renderer()
            t0 = time.perf_counter()
            p_cam, R_nc = c.cam_p_ned_m[j], rotmat_from_quat(c.cam_q_ned_from_cam[j])
            p_t, R_nt = c.tgt_p_ned_m[j], rotmat_from_quat(c.tgt_q_ned_from_body[j])
            try:
                if self.scene_enabled:
                    others = self.other_targets_at(i)
                    pixels, labels, status = self._render_scene(k, float(c.t_s[j]), p_cam, R_nc, p_t, R_nt, others)
                    target_box = next((lab.box_px for lab in labels if lab.object_id == 0), None)
                else:
                    pixels = renderer.render(p_cam, R_nc, p_t, R_nt, GROUND_D_M)
                    target_box = renderer.last_target_box_px
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
            time_unix_us=self.time_unix_us(i),
        )
        return SimFrame(k, t_us, pixels, row, labels, status, target_box)
