"""JSBSim adapter: a multirotor flown by JSBSim under :mod:`groundsim.world.flight.guidance`.

The ground truth of a scenario is what JSBSim flew, not the commanded path.  This module is the
only place that touches JSBSim: it converts JSBSim's units (ft, ft/s) once, reads positions from
geodetic latitude/longitude/altitude through :func:`onboard.core.frames.ned_from_geodetic` about the
scenario origin and attitudes from (phi, theta, psi) through :func:`onboard.core.frames.quat_from_euler`.

Airframe: ``groundsim/models/aircraft/irquad`` -- the F450 quad-rotor of the jsbsim wheel
(1.4 kg, four DJI E305 motors with 9.4" propellers, body-rate SCAS), repackaged so it loads
silently.  The SCAS takes ``fcs/{aileron,elevator,rudder}-cmd-norm`` as roll/pitch/yaw-rate
commands, 0.75 rad/s per unit; ``fcs/throttle-cmd-norm`` is the collective.

Timing.  JSBSim integrates at ``dt_s``; the controller runs every ``control_every`` JSBSim steps
on a fixed grid from t = 0, so the flight does not depend on when :meth:`FlownVehicle.step_to`
is called.  The controller's own position estimate integrates JSBSim's NED velocity between
ticks and is re-anchored on ``ned_from_geodetic`` every ``anchor_every`` ticks (it stays within
micrometres of the truth, at a fraction of the cost).  States returned between JSBSim steps are
interpolated linearly in (lat, lon, alt, v, Euler angles, body rates) over one step
(<= 1/240 s: the interpolation error is micrometres); the acceleration is the velocity
difference over the last JSBSim step.

Console: JSBSim's process-wide debug level is set to 0 when the first vehicle is built, and the
``irquad`` model is written so that JSBSim prints nothing while loading or flying it.

Start: the vehicle is initialised on the reference at t = 0, at its velocity and with the trim
attitude and body rates the reference needs; the rotors are spun up and the collective is
calibrated (secant on the measured thrust) before t = 0, so the first seconds show no transient.
JSBSim's terrain is put 2 km below the ellipsoid: the vehicles never touch its ground model.

Use: :meth:`FlownVehicle.step_to` once per frame (simple; each call converts one state), or
:meth:`FlownVehicle.step_through` / :func:`fly` / :func:`fly_pair` for a whole scenario at once
(the same flight, with the geodetic and Euler conversions vectorised: about half the cost).
Truth never depends on rendering, so a simulator can fly both vehicles first and render after.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from groundsim.world.flight.guidance import (
    GRAVITY_MPS2,
    GuidanceError,
    GuidanceGains,
    MulticopterController,
    ReferencePoint,
    TrackingStats,
    body_rates_from_euler_rates,
    wrap_pi,
    yaw_along,
    yaw_rate_along,
    yaw_rate_toward,
    yaw_toward,
)
from onboard.core.errors import IrtrackError
from onboard.core.frames import (
    GeodeticOrigin,
    geodetic_from_ned,
    ned_from_geodetic,
    q_ned_from_level,
    quat_from_euler,
    quat_multiply,
    quat_rotate,
)

__all__ = [
    "FlightError",
    "FlownState",
    "FlownTrajectory",
    "FlownVehicle",
    "fly",
    "fly_pair",
    "YAW_MODES",
    "DEFAULT_MODEL",
]

log = logging.getLogger(__name__)

FT_M = 0.3048  # exact, by definition of the international foot
LBF_N = 4.4482216152605  # exact
SLUG_KG = 14.593902937206364
YAW_MODES = ("velocity", "target", "fixed")
DEFAULT_MODEL = "irquad"
#: thrust ~ throttle**THRUST_EXPONENT for the DJI E305 + 9450 pair (measured: 1.8 near 0.3, 1.95 near 0.5)
THRUST_EXPONENT = 1.9
_SPINUP_S = 0.6
_CALIBRATION_ITERATIONS = 3
_DIVERGED_M = 50.0  # farther than this from the reference: the flight has failed
_T_EPS_S = 1e-9
#: JSBSim's terrain is put this far below the ellipsoid: the vehicles never meet the ground model
#: (the scenario decides altitudes; the renderer draws its own ground)
_TERRAIN_BELOW_M = -2000.0


class FlightError(IrtrackError, RuntimeError):
    """The flight cannot be set up or has diverged; the message names the vehicle and field."""


@dataclass(frozen=True)
class FlownState:
    """One truth sample of a flown vehicle.

    ``t_s`` scenario seconds; ``p_ned_m``, ``v_ned_mps``, ``a_ned_mps2`` (3,) in local NED about
    the scenario origin; ``q_ned_from_body`` (4,) w-first Hamilton; ``omega_frd_radps`` (3,) body
    rates (p, q, r).
    """

    t_s: float
    p_ned_m: np.ndarray
    v_ned_mps: np.ndarray
    a_ned_mps2: np.ndarray
    q_ned_from_body: np.ndarray
    omega_frd_radps: np.ndarray

    def __post_init__(self) -> None:
        if not math.isfinite(self.t_s):
            raise FlightError(f"FlownState.t_s must be finite, got {self.t_s!r}")
        for name, n in _STATE_FIELDS:
            arr = np.array(getattr(self, name), dtype=float)  # a private copy: inputs are never aliased
            if arr.shape != (n,) or not np.isfinite(arr).all():
                raise FlightError(f"FlownState.{name} must be {n} finite numbers, got {getattr(self, name)!r}")
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)


_STATE_FIELDS = (("p_ned_m", 3), ("v_ned_mps", 3), ("a_ned_mps2", 3), ("q_ned_from_body", 4), ("omega_frd_radps", 3))


@dataclass(frozen=True)
class FlownTrajectory:
    """Truth samples of one flight as arrays: ``t_s`` (N,), ``p_ned_m`` (N, 3), ``v_ned_mps``
    (N, 3), ``a_ned_mps2`` (N, 3), ``q_ned_from_body`` (N, 4), ``omega_frd_radps`` (N, 3), plus the
    guidance's :class:`TrackingStats` against the reference over the whole flight."""

    t_s: np.ndarray
    p_ned_m: np.ndarray
    v_ned_mps: np.ndarray
    a_ned_mps2: np.ndarray
    q_ned_from_body: np.ndarray
    omega_frd_radps: np.ndarray
    tracking: TrackingStats

    def __post_init__(self) -> None:
        t = np.array(self.t_s, dtype=float).reshape(-1)
        t.flags.writeable = False
        object.__setattr__(self, "t_s", t)
        n = t.shape[0]
        for name, w in _STATE_FIELDS:
            arr = np.array(getattr(self, name), dtype=float)
            if arr.shape != (n, w):
                raise FlightError(f"FlownTrajectory.{name} must have shape ({n}, {w}), got {arr.shape}")
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)
        if not isinstance(self.tracking, TrackingStats):
            raise FlightError(f"FlownTrajectory.tracking must be a TrackingStats, got {type(self.tracking).__name__}")

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def state(self, i: int) -> FlownState:
        return FlownState(
            float(self.t_s[i]),
            self.p_ned_m[i],
            self.v_ned_mps[i],
            self.a_ned_mps2[i],
            self.q_ned_from_body[i],
            self.omega_frd_radps[i],
        )

    @classmethod
    def from_states(cls, states: Sequence[FlownState], tracking: TrackingStats) -> FlownTrajectory:
        if not states:
            raise FlightError("FlownTrajectory.from_states: no states")
        return cls(
            np.array([s.t_s for s in states]),
            np.array([s.p_ned_m for s in states]),
            np.array([s.v_ned_mps for s in states]),
            np.array([s.a_ned_mps2 for s in states]),
            np.array([s.q_ned_from_body for s in states]),
            np.array([s.omega_frd_radps for s in states]),
            tracking,
        )


def _level_to_ned(origin: GeodeticOrigin, lat_deg, lon_deg, q_level_from_body, v_level_mps, a_level_mps2):
    """JSBSim's attitude, velocity and acceleration are relative to the local level where the vehicle is (its
    Euler angles to the local horizon and north): into the origin's NED, as the simulated world is
    (:mod:`onboard.core.frames`, "Local level"); an autopilot reports them in the local level again
    (``SimCore.vehicle_state``).  Rows (..., k)."""
    q_lv = q_ned_from_level(lat_deg, lon_deg, origin)
    return (
        quat_multiply(q_lv, q_level_from_body),
        quat_rotate(q_lv, v_level_mps),
        quat_rotate(q_lv, a_level_mps2),
    )


def models_dir() -> Path:
    """The directory holding irtrack's JSBSim aircraft (``<dir>/aircraft/<model>/<model>.xml``)."""
    return Path(__file__).resolve().parents[2] / "models"  # groundsim/models: JSBSim needs a real directory


def _vec3(value, what: str) -> tuple:
    try:
        v = tuple(float(x) for x in np.asarray(value, dtype=float).reshape(3))
    except (TypeError, ValueError) as exc:
        raise FlightError(f"{what} must be 3 finite numbers, got {value!r}") from exc
    if not all(math.isfinite(x) for x in v):
        raise FlightError(f"{what} must be 3 finite numbers, got {value!r}")
    return v


# raw JSBSim state, converted to SI: lat_deg, lon_deg, alt_m, vn, ve, vd (m/s), phi, theta, psi, p, q, r (rad, rad/s)
_RAW_PROPS = (
    ("position/lat-geod-deg", 1.0),
    ("position/long-gc-deg", 1.0),
    ("position/geod-alt-ft", FT_M),
    ("velocities/v-north-fps", FT_M),
    ("velocities/v-east-fps", FT_M),
    ("velocities/v-down-fps", FT_M),
    ("attitude/phi-rad", 1.0),
    ("attitude/theta-rad", 1.0),
    ("attitude/psi-rad", 1.0),
    ("velocities/p-rad_sec", 1.0),
    ("velocities/q-rad_sec", 1.0),
    ("velocities/r-rad_sec", 1.0),
)


class FlownVehicle:
    """One multirotor flown by JSBSim along ``reference`` (a :class:`groundsim.world.motion.Motion`).

    ``yaw_mode``: ``"velocity"`` heads along the reference velocity, ``"target"`` yaws the
    airframe toward ``look_at_ned_m`` (a fixed camera pod then keeps the target in azimuth),
    ``"fixed"`` holds ``yaw_rad`` (default: the initial heading).  ``wind_ned_mps``: constant
    wind.  ``dt_s``: JSBSim step; the controller runs at ``control_rate_hz`` (an integer divisor
    of ``1/dt_s``).  ``seed`` seeds JSBSim's random generator (the flight itself is
    deterministic: the same inputs give the same truth, bit for bit).
    """

    def __init__(
        self,
        reference,
        origin: GeodeticOrigin,
        wind_ned_mps=(0.0, 0.0, 0.0),
        yaw_mode: str = "velocity",
        dt_s: float = 1.0 / 240.0,
        name: str = "observer",
        seed: int = 0,
        *,
        control_rate_hz: float = 120.0,
        gains: GuidanceGains | None = None,
        yaw_rad: float | None = None,
        look_at_ned_m=None,
        anchor_every: int = 12,
        model: str = DEFAULT_MODEL,
    ):
        self.name = str(name)
        if not hasattr(reference, "state"):
            raise FlightError(f"{self.name}: reference must have .state(t_s), got {type(reference).__name__}")
        if not isinstance(origin, GeodeticOrigin):
            raise FlightError(f"{self.name}: origin must be a GeodeticOrigin, got {type(origin).__name__}")
        if yaw_mode not in YAW_MODES:
            raise FlightError(f"{self.name}: yaw_mode must be one of {YAW_MODES}, got {yaw_mode!r}")
        if not (isinstance(dt_s, (int, float)) and math.isfinite(dt_s) and 1e-4 <= dt_s <= 0.02):
            raise FlightError(f"{self.name}: dt_s must be in [1e-4, 0.02] s, got {dt_s!r}")
        if not (isinstance(control_rate_hz, (int, float)) and math.isfinite(control_rate_hz) and control_rate_hz > 0):
            raise FlightError(f"{self.name}: control_rate_hz must be > 0, got {control_rate_hz!r}")
        every = round(1.0 / (dt_s * control_rate_hz))
        if every < 1 or abs(every * dt_s * control_rate_hz - 1.0) > 1e-6:
            raise FlightError(
                f"{self.name}: control_rate_hz ({control_rate_hz}) must divide the JSBSim rate 1/dt_s ({1.0 / dt_s:g} Hz)"
            )
        if not (isinstance(anchor_every, int) and anchor_every >= 1):
            raise FlightError(f"{self.name}: anchor_every must be an int >= 1, got {anchor_every!r}")
        if yaw_rad is not None and not math.isfinite(yaw_rad):
            raise FlightError(f"{self.name}: yaw_rad must be finite, got {yaw_rad!r}")
        self.reference = reference
        self.origin = origin
        self.yaw_mode = yaw_mode
        self.dt_s = float(dt_s)
        self.control_every = int(every)
        self.dt_control_s = self.dt_s * self.control_every
        self.anchor_every = anchor_every
        self.seed = int(seed)
        self.wind_ned_mps = _vec3(wind_ned_mps, f"{self.name}: wind_ned_mps")
        self.gains = gains if gains is not None else GuidanceGains()
        self._look_at = _vec3(look_at_ned_m, f"{self.name}: look_at_ned_m") if look_at_ned_m is not None else None
        self._look_at_v = (0.0, 0.0, 0.0)
        self._look_at_t = None

        self._fdm = self._load(model)
        self._nodes = [self._pm.get_node(p) for p, _ in _RAW_PROPS]
        self._scales = [s for _, s in _RAW_PROPS]
        node = self._pm.get_node
        self._n_vel = [node("velocities/v-north-fps"), node("velocities/v-east-fps"), node("velocities/v-down-fps")]
        self._n_att = [node("attitude/phi-rad"), node("attitude/theta-rad"), node("attitude/psi-rad")]
        self._n_cmd = [node("fcs/aileron-cmd-norm"), node("fcs/elevator-cmd-norm"), node("fcs/rudder-cmd-norm")]
        self._n_thr = [node(f"fcs/throttle-cmd-norm[{i}]") for i in range(4)]
        self._rate_per_cmd = 0.75  # rad/s per unit command, the SCAS's pilot gain

        # flight state
        self._k = 0  # JSBSim steps since t = 0
        self._tick = 0
        self._ref_cache_start = 0
        self._ref_cache: list = []
        self._p_nav = None
        self._v_nav = None
        self._err_sq_sum = 0.0
        self._err_max = 0.0
        self._err_n = 0
        self._raw_prev = None
        self._raw_now = None
        self._last_state: FlownState | None = None
        self._yaw_hold = 0.0
        self._initialise(yaw_rad)

    # ------------------------------------------------------------------ JSBSim set-up
    def _load(self, model: str):
        import jsbsim  # imported here: no JSBSim work at import time of groundsim

        jsbsim.FGJSBBase().debug_lvl = 0
        fdm = jsbsim.FGFDMExec(jsbsim.get_default_root_dir())
        fdm.set_debug_level(0)
        fdm.set_aircraft_path(str(models_dir() / "aircraft"))
        t0 = time.perf_counter()
        if not fdm.load_model(model):
            raise FlightError(f"{self.name}: JSBSim could not load model {model!r} from {models_dir() / 'aircraft'}")
        fdm.set_dt(self.dt_s)
        self._pm = fdm.get_property_manager()
        fdm["simulation/randomseed"] = float(self.seed)
        log.debug("%s: loaded JSBSim model %s in %.1f ms", self.name, model, 1e3 * (time.perf_counter() - t0))
        return fdm

    def _ref_at_tick(self, j: int) -> ReferencePoint:
        """Reference at control tick ``j`` (evaluated in vectorised chunks, cached)."""
        idx = j - self._ref_cache_start
        if not 0 <= idx < len(self._ref_cache):
            n = 256
            t = (j + np.arange(n + 1)) * self.dt_control_s
            st = self.reference.state(t)
            p, v, a = (np.asarray(x, dtype=float).reshape(n + 1, 3) for x in st)
            if not (np.all(np.isfinite(p)) and np.all(np.isfinite(v)) and np.all(np.isfinite(a))):
                raise FlightError(f"{self.name}: reference is not finite near t = {t[0]:.3f} s")
            self._ref_cache = [ReferencePoint(pi, vi, ai) for pi, vi, ai in zip(p.tolist(), v.tolist(), a.tolist())]
            self._ref_cache_start = j
            idx = 0
        return self._ref_cache[idx]

    def reference_changed(self) -> None:
        """The reference's future changed (a guided setpoint, :mod:`groundsim.world.guided`): forget the
        reference ticks evaluated ahead, so the next control tick reads the new path."""
        self._ref_cache = []

    def _set_ic(self, p_ned, v_ned, roll, pitch, yaw, rates_frd_radps=(0.0, 0.0, 0.0)) -> None:
        fdm = self._fdm
        lat, lon, alt = (float(x) for x in geodetic_from_ned(np.asarray(p_ned, dtype=float), self.origin))
        fdm["ic/terrain-elevation-ft"] = _TERRAIN_BELOW_M / FT_M  # no ground to touch anywhere
        fdm["ic/lat-geod-deg"] = lat
        fdm["ic/long-gc-deg"] = lon
        fdm["ic/h-sl-ft"] = alt / FT_M
        fdm["ic/vn-fps"] = v_ned[0] / FT_M
        fdm["ic/ve-fps"] = v_ned[1] / FT_M
        fdm["ic/vd-fps"] = v_ned[2] / FT_M
        fdm["ic/phi-rad"] = roll
        fdm["ic/theta-rad"] = pitch
        fdm["ic/psi-true-rad"] = yaw % (2.0 * math.pi)
        fdm["ic/p-rad_sec"] = rates_frd_radps[0]
        fdm["ic/q-rad_sec"] = rates_frd_radps[1]
        fdm["ic/r-rad_sec"] = rates_frd_radps[2]
        self._run_ic()
        # JSBSim's sea-level height differs from the geodetic height by millimetres: correct once
        dh_ft = alt / FT_M - fdm["position/geod-alt-ft"]
        if abs(dh_ft) > 1e-7:
            fdm["ic/h-sl-ft"] = alt / FT_M + dh_ft
            fdm["ic/lat-geod-deg"] = lat
            self._run_ic()

    def _run_ic(self, wind_ned_mps=None) -> None:
        fdm = self._fdm
        if not fdm.run_ic():
            raise FlightError(f"{self.name}: JSBSim rejected the initial conditions")
        # run_ic resets the wind to the IC's (horizontal-only) wind: set ours after it
        w = self.wind_ned_mps if wind_ned_mps is None else wind_ned_mps
        fdm["atmosphere/wind-north-fps"] = w[0] / FT_M
        fdm["atmosphere/wind-east-fps"] = w[1] / FT_M
        fdm["atmosphere/wind-down-fps"] = w[2] / FT_M

    def _set_throttle(self, thr: float) -> None:
        thr = max(0.0, min(1.0, thr))
        for n in self._n_thr:
            n.set_double_value(thr)

    def _total_thrust_n(self) -> float:
        return sum(self._fdm[f"propulsion/engine[{i}]/thrust-lbs"] for i in range(4)) * LBF_N

    def _initialise(self, yaw_rad: float | None) -> None:
        fdm = self._fdm
        ref0 = self._ref_at_tick(0)
        p0, v0 = ref0.p_ned_m, ref0.v_ned_mps
        self._mass_kg = fdm["inertia/mass-slugs"] * SLUG_KG
        # drag per unit mass, measured: |F_aero| = k m |v_air|^2 (the airframe's drag is isotropic)
        s_probe = 5.0
        self._set_ic(p0, (s_probe, 0.0, 0.0), 0.0, 0.0, 0.0)
        self._run_ic(wind_ned_mps=(0.0, 0.0, 0.0))  # aero forces of run_ic, in still air
        f_aero_n = math.sqrt(sum(fdm[f"forces/fb{a}-aero-lbs"] ** 2 for a in "xyz")) * LBF_N
        k_drag = f_aero_n / (self._mass_kg * s_probe**2)
        self.controller = MulticopterController(self.gains, self.dt_control_s, k_drag, self.wind_ned_mps)

        if yaw_rad is None:
            if self.yaw_mode == "target" and self._look_at is not None:
                yaw_rad = yaw_toward(p0, self._look_at, 0.0)
            else:
                yaw_rad = yaw_along(v0, 0.0)
        self._yaw_hold = float(yaw_rad)
        try:
            roll0, pitch0, c0 = self.controller.feedforward_tilt(ref0, self._yaw_hold)
        except GuidanceError as exc:
            raise FlightError(f"{self.name}: reference at t = 0 cannot be flown: {exc}") from exc
        # body rates the reference needs at t = 0 (tilt and heading along the reference)
        ref1 = self._ref_at_tick(1)
        yaw_rate0 = yaw_rate_along(v0, ref0.a_ned_mps2) if self.yaw_mode == "velocity" else 0.0
        roll1, pitch1, _ = self.controller.feedforward_tilt(ref1, self._yaw_hold + yaw_rate0 * self.dt_control_s)
        rates0 = body_rates_from_euler_rates(
            roll0, pitch0, (roll1 - roll0) / self.dt_control_s, (pitch1 - pitch0) / self.dt_control_s, yaw_rate0
        )
        self._trim = (p0, v0, roll0, pitch0, self._yaw_hold, rates0)

        # spin the rotors up and calibrate the collective for c0 (secant on thrust ~ thr^n)
        thrust_goal_n = c0 * self._mass_kg
        fdm["fcs/ScasEngage"] = 0.0
        fdm["propulsion/set-running"] = -1
        thr = 0.41 * math.sqrt(c0 / GRAVITY_MPS2)
        n_spin = max(1, round(_SPINUP_S / self.dt_s))
        for _ in range(_CALIBRATION_ITERATIONS):
            self._set_throttle(thr)
            self._set_ic(*self._trim)
            for _ in range(n_spin):
                fdm.run()
            self._set_ic(*self._trim)  # back to t = 0 conditions; rotor speeds carry over
            fdm.run()
            thrust_n = self._total_thrust_n()
            if not thrust_n > 0:
                raise FlightError(f"{self.name}: rotors produced no thrust during spin-up")
            thr *= (thrust_goal_n / thrust_n) ** (1.0 / THRUST_EXPONENT)
        self._thr0 = thr
        self._c0 = c0
        self._set_throttle(thr)
        for _ in range(n_spin // 2):
            fdm.run()
        self._set_ic(*self._trim)
        for n in self._n_cmd:
            n.set_double_value(0.0)
        fdm["fcs/ScasEngage"] = 1.0
        self._k = 0
        self._tick = 0
        self._raw_now = self._read_raw()
        self._raw_prev = self._raw_now
        self._raw_k = 0
        self._p_nav = list(p0)
        self._v_nav = list(self._raw_now[3:6])
        self._last_state = None
        self._err_sq_sum, self._err_max, self._err_n = 0.0, 0.0, 0
        log.debug(
            "%s: trimmed at roll %.2f deg pitch %.2f deg yaw %.1f deg, collective %.4f for %.2f m/s^2, drag k %.4f 1/m",
            self.name,
            math.degrees(roll0),
            math.degrees(pitch0),
            math.degrees(self._yaw_hold),
            thr,
            c0,
            k_drag,
        )

    def _read_raw(self) -> tuple:
        return tuple(n.get_double_value() * s for n, s in zip(self._nodes, self._scales))

    # ------------------------------------------------------------------ flying
    @property
    def t_s(self) -> float:
        """Time JSBSim has been flown to (scenario seconds)."""
        return self._k * self.dt_s

    @property
    def tracking_error_m(self) -> TrackingStats:
        """RMS and max distance between flown and reference positions over all control ticks so far."""
        n = self._err_n
        return TrackingStats(math.sqrt(self._err_sq_sum / n) if n else 0.0, self._err_max, n)

    def _desired_yaw(self, ref: ReferencePoint, p, v) -> tuple:
        mode = self.yaw_mode
        if mode == "velocity":
            yaw = yaw_along(ref[1], self._yaw_hold)
            rate = yaw_rate_along(ref[1], ref[2])
        elif mode == "target" and self._look_at is not None:
            yaw = yaw_toward(p, self._look_at, self._yaw_hold)
            rate = yaw_rate_toward(p, v, self._look_at, self._look_at_v)
        else:
            return self._yaw_hold, 0.0
        self._yaw_hold = yaw
        return yaw, rate

    def _control_tick(self) -> None:
        """Navigation update, tracking statistics and one controller step at tick ``self._tick``."""
        j = self._tick
        v = [n.get_double_value() * FT_M for n in self._n_vel]
        if j % self.anchor_every == 0:
            raw = self._read_raw()
            self._p_nav = [float(x) for x in ned_from_geodetic(raw[0], raw[1], raw[2], self.origin)]
        else:
            h = 0.5 * self.dt_control_s
            pv = self._v_nav
            self._p_nav = [self._p_nav[i] + h * (pv[i] + v[i]) for i in range(3)]
        self._v_nav = v
        p = self._p_nav
        roll, pitch, yaw = (n.get_double_value() for n in self._n_att)

        ref = self._ref_at_tick(j)
        ref_next = self._ref_at_tick(j + 1)
        pr = ref[0]
        err = math.sqrt((p[0] - pr[0]) ** 2 + (p[1] - pr[1]) ** 2 + (p[2] - pr[2]) ** 2)
        self._err_sq_sum += err * err
        self._err_n += 1
        if err > self._err_max:
            self._err_max = err
        if not err < _DIVERGED_M:
            raise FlightError(
                f"{self.name}: flight diverged at t = {j * self.dt_control_s:.2f} s: {err:.1f} m from the reference"
            )
        yaw_des, yaw_rate_ff = self._desired_yaw(ref, p, v)
        cmd = self.controller.update(p, v, roll, pitch, yaw, ref, ref_next, yaw_des, yaw_rate_ff)
        k = 1.0 / self._rate_per_cmd
        for n, rate in zip(self._n_cmd, cmd.rates_frd_radps):
            n.set_double_value(rate * k)
        self._set_throttle(self._thr0 * (cmd.specific_thrust_mps2 / self._c0) ** (1.0 / THRUST_EXPONENT))
        self._tick += 1

    def step_to(self, t_s: float, look_at_ned_m=None, look_at_v_ned_mps=None) -> FlownState:
        """Fly JSBSim forward to ``t_s`` and return the truth state there.

        ``look_at_ned_m`` (with ``yaw_mode="target"``): the point to yaw toward from now on;
        its velocity ``look_at_v_ned_mps`` feeds the yaw-rate feed-forward (estimated from
        successive points when not given).  ``t_s`` must not go backwards.
        """
        raw, acc = self._advance(t_s, look_at_ned_m, look_at_v_ned_mps)
        p = ned_from_geodetic(raw[0], raw[1], raw[2], self.origin)
        q, v, a = _level_to_ned(self.origin, raw[0], raw[1], quat_from_euler(raw[6], raw[7], raw[8]), raw[3:6], acc)
        state = FlownState(float(t_s), p, v, a, q, raw[9:12])
        self._last_state = state
        return state

    def step_through(self, times_s, look_at_ned_m=None, look_at_v_ned_mps=None) -> FlownTrajectory:
        """:meth:`step_to` each of ``times_s`` (increasing) and return all states as arrays.

        Same flight and same states as calling :meth:`step_to` in a loop, but the geodetic and
        Euler conversions run once, vectorised (several times cheaper for a whole scenario).
        ``look_at_ned_m`` / ``look_at_v_ned_mps``: None or arrays (N, 3), one row per time.
        """
        times = np.asarray(times_s, dtype=float).reshape(-1)
        if times.size == 0 or not np.all(np.isfinite(times)) or np.any(np.diff(times) < 0):
            raise FlightError(f"{self.name}: step_through times_s must be finite, non-decreasing and not empty")
        la_p = self._rows(look_at_ned_m, times.size, "look_at_ned_m")
        la_v = self._rows(look_at_v_ned_mps, times.size, "look_at_v_ned_mps")
        raws, accs = [], []
        for i, t in enumerate(times.tolist()):
            raw, acc = self._advance(t, None if la_p is None else la_p[i], None if la_v is None else la_v[i])
            raws.append(raw)
            accs.append(acc)
        r = np.array(raws)
        p = ned_from_geodetic(r[:, 0], r[:, 1], r[:, 2], self.origin)
        q, v, a = _level_to_ned(
            self.origin, r[:, 0], r[:, 1], quat_from_euler(r[:, 6], r[:, 7], r[:, 8]), r[:, 3:6], np.array(accs)
        )
        traj = FlownTrajectory(times, p, v, a, q, r[:, 9:12].copy(), self.tracking_error_m)
        if not (np.isfinite(p).all() and np.isfinite(r).all()):
            raise FlightError(f"{self.name}: JSBSim state is not finite")
        self._last_state = traj.state(len(traj) - 1)
        return traj

    def _rows(self, value, n: int, what: str):
        if value is None:
            return None
        arr = np.asarray(value, dtype=float)
        if arr.shape != (n, 3):
            raise FlightError(f"{self.name}: {what} must have shape ({n}, 3), one row per time, got {arr.shape}")
        return arr

    def _advance(self, t_s, look_at_ned_m, look_at_v_ned_mps) -> tuple:
        """Fly to ``t_s``; the raw SI state there (interpolated within one JSBSim step) and the
        acceleration (velocity difference over the last step), as tuples."""
        if not (isinstance(t_s, (int, float)) and math.isfinite(t_s)):
            raise FlightError(f"{self.name}: step_to t_s must be a finite number, got {t_s!r}")
        if t_s < -_T_EPS_S:
            raise FlightError(f"{self.name}: step_to t_s must be >= 0, got {t_s}")
        if t_s < self.t_s - self.dt_s - _T_EPS_S or (
            self._last_state is not None and t_s < self._last_state.t_s - _T_EPS_S
        ):
            raise FlightError(f"{self.name}: step_to t_s = {t_s} goes back in time (now {self.t_s} s)")
        if look_at_ned_m is not None:
            self._update_look_at(t_s, look_at_ned_m, look_at_v_ned_mps)
        k_target = max(0, math.ceil(t_s / self.dt_s - 1e-6))
        run = self._fdm.run
        every = self.control_every
        while self._k < k_target:
            if self._k % every == 0:
                self._control_tick()
            if self._k == k_target - 1:
                self._raw_prev = self._read_raw()
            if not run():
                raise FlightError(f"{self.name}: JSBSim stopped at t = {self.t_s:.3f} s")
            self._k += 1
        if self._raw_k != self._k:
            self._raw_now = self._read_raw()
            self._raw_k = self._k
        a, b = self._raw_prev, self._raw_now
        if self._k == 0:
            return b, tuple(self._ref_at_tick(0).a_ned_mps2)  # trimmed on the reference at t = 0
        acc = tuple((y - x) / self.dt_s for x, y in zip(a[3:6], b[3:6]))
        alpha = 1.0 - (self._k * self.dt_s - t_s) / self.dt_s
        if alpha >= 1.0 - 1e-9:
            return b, acc
        alpha = max(0.0, alpha)
        r = [x + alpha * (y - x) for x, y in zip(a, b)]
        r[8] = wrap_pi(a[8] + alpha * wrap_pi(b[8] - a[8]))
        return tuple(r), acc

    def _update_look_at(self, t_s, look_at_ned_m, look_at_v_ned_mps) -> None:
        new = _vec3(look_at_ned_m, f"{self.name}: look_at_ned_m")
        if look_at_v_ned_mps is not None:
            self._look_at_v = _vec3(look_at_v_ned_mps, f"{self.name}: look_at_v_ned_mps")
        elif self._look_at is not None and self._look_at_t is not None and t_s - self._look_at_t > 1e-6:
            dt = t_s - self._look_at_t
            self._look_at_v = tuple((a - b) / dt for a, b in zip(new, self._look_at))
        if self._k == 0 and self.yaw_mode == "target" and new != self._look_at:
            # first target before any flight: start already facing it
            self._look_at = new
            self._initialise(yaw_toward(self._trim[0], new, self._yaw_hold))
        self._look_at = new
        self._look_at_t = t_s


def fly(
    reference,
    duration_s: float,
    sample_rate_hz: float,
    origin: GeodeticOrigin | None = None,
    look_at=None,
    **vehicle_kwargs,
) -> FlownTrajectory:
    """Fly ``reference`` for ``duration_s`` and sample the truth at ``sample_rate_hz`` from t = 0.

    ``look_at``: a motion (``.state(t_s)``) whose position the vehicle yaws toward (sets
    ``yaw_mode="target"``).  ``origin`` defaults to 47 N, 8 E, 400 m.  Other keywords go to
    :class:`FlownVehicle`.
    """
    if not (math.isfinite(duration_s) and duration_s >= 0):
        raise FlightError(f"fly: duration_s must be >= 0, got {duration_s!r}")
    if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
        raise FlightError(f"fly: sample_rate_hz must be > 0, got {sample_rate_hz!r}")
    origin = origin if origin is not None else GeodeticOrigin(47.0, 8.0, 400.0)
    t = np.arange(int(math.floor(duration_s * sample_rate_hz + 1e-9)) + 1) / sample_rate_hz
    if look_at is not None:
        vehicle_kwargs.setdefault("yaw_mode", "target")
        la = look_at.state(t)
        la_p, la_v = np.asarray(la[0], dtype=float).reshape(-1, 3), np.asarray(la[1], dtype=float).reshape(-1, 3)
        vehicle_kwargs.setdefault("look_at_ned_m", la_p[0])
    vehicle = FlownVehicle(reference, origin, **vehicle_kwargs)
    if look_at is None:
        return vehicle.step_through(t)
    return vehicle.step_through(t, la_p, la_v)


def fly_pair(
    observer_reference,
    target_reference,
    duration_s: float,
    sample_rate_hz: float,
    origin: GeodeticOrigin,
    wind_ned_mps=(0.0, 0.0, 0.0),
    observer_yaw_mode: str = "target",
    seed: int = 0,
    **vehicle_kwargs,
) -> tuple[FlownTrajectory, FlownTrajectory]:
    """Fly a scenario's two vehicles; returns ``(observer, target)`` truth sampled from t = 0.

    The target flies first (heading along its velocity); the observer then flies with
    ``observer_yaw_mode`` (default ``"target"``: it yaws toward the target's *flown* position
    and velocity at every sample, exactly as a frame-by-frame loop calling ``step_to`` would).
    Both use the batch path, so this is the cheapest way to get a scenario's truth.
    """
    if not (math.isfinite(duration_s) and duration_s >= 0):
        raise FlightError(f"fly_pair: duration_s must be >= 0, got {duration_s!r}")
    if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
        raise FlightError(f"fly_pair: sample_rate_hz must be > 0, got {sample_rate_hz!r}")
    t = np.arange(int(math.floor(duration_s * sample_rate_hz + 1e-9)) + 1) / sample_rate_hz
    target = FlownVehicle(
        target_reference, origin, wind_ned_mps, yaw_mode="velocity", name="target", seed=seed, **vehicle_kwargs
    ).step_through(t)
    if observer_yaw_mode == "target":
        vehicle_kwargs.setdefault("look_at_ned_m", target.p_ned_m[0])
    observer_vehicle = FlownVehicle(
        observer_reference,
        origin,
        wind_ned_mps,
        yaw_mode=observer_yaw_mode,
        name="observer",
        seed=seed,
        **vehicle_kwargs,
    )
    if observer_yaw_mode == "target":
        observer = observer_vehicle.step_through(t, target.p_ned_m, target.v_ned_mps)
    else:
        observer = observer_vehicle.step_through(t)
    return observer, target
