r"""Observer guidance: the manoeuvre over the next seconds that makes the target's range observable.

One camera measures bearings; range comes only from the observer's own motion across the line of sight
(a straight, constant-velocity observer never ranges a constant-velocity target).  Bearing-only
observer trajectory optimisation (Le Cadre & Jauffret, IEEE TAES 33(4), 1997; Passerieux & Van Cappel,
IEEE TAES 34(1), 1998) chooses the observer's path that minimises a scalar of the predicted posterior
covariance.  Here that scalar is the predicted range variance at the end of the horizon:

    sigma_r^2(c) = u^T P_c(t_0 + T) u,     P_c = (I_0 + sum_k H_k(c)^T W H_k(c))^{-1}  (position block)

where ``I_0`` is the information already held (the posterior of ``(p, v)`` at ``t_0``, inverted), ``H_k(c)``
the Jacobian of the bearing taken at ``t_k`` from candidate path ``c`` towards the predicted target
(constant velocity from the posterior mean), ``W`` the estimator's own bearing weights and ``u`` the
predicted line of sight.  The sum is the Bayesian Cramer-Rao machinery of the reconstruction
(:func:`onboard.estimation.crb.predicted_point_covariance`: the same spline, motion prior, noise model
and navigation nuisances as the estimator), so the prediction charges a manoeuvre for the attitude bias
it cannot separate from range.

Candidates (a small set, evaluated exhaustively): hold the current velocity (the reference, "without"),
turn the horizontal velocity by each of ``heading_changes_deg`` left and right, fly across the line of
sight left and right, and climb or descend at the current heading.  Each candidate is a velocity
setpoint ``v_sp`` reached at the configured acceleration: ``v(t) = v_0 + a (v_sp - v_0)/|v_sp - v_0| t``
until ``v_sp``, then constant (the path a velocity-controlled multirotor flies).  A candidate is
feasible when ``v_sp`` is within the speed and climb-rate limits and its predicted path keeps the
altitude band and the target inside the camera's view (line-of-sight elevation band, angle off the
heading).  Nothing is recommended while the posterior range sigma is already below
``quiet_below_sigma_range_ratio`` of the range (observable with margin), when the observer is outside
its own limits, or when the best candidate does not beat holding by ``min_gain_ratio``.

Frames and units follow :mod:`onboard.core.frames`: local NED metres, velocities m/s; the planner's positions
have their origin at the altitude band's reference (home or sea level, ``altitude_reference``) below the local
NED origin, so altitude = -down is metres above that reference.  Pure: no I/O, no clock; the caller passes the
times.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np

from onboard.core.errors import InputError, IrtrackError
from onboard.core.frames import quat_from_euler, quat_from_rotmat, quat_multiply, rotmat_from_quat
from onboard.core.json_schema import object_schema
from onboard.core.schema import Bool, Integer, Invalid, Number, Numbers, Text, config_dataclass

if TYPE_CHECKING:  # the planner imports the estimator when built: the config section stays light to import
    from onboard.core.gnss import GnssState
    from onboard.estimation.map_estimator import MapEstimator, NoiseModel

__all__ = [
    "GuidanceConfig",
    "ObserverState",
    "TargetPosterior",
    "Candidate",
    "Advice",
    "GuidancePlanner",
    "candidate_path",
    "GuidanceAdvisor",
    "SetpointGate",
    "SetpointDecision",
    "advice_to_json",
    "GUIDANCE_SCHEMA",
    "GUIDANCE_JSON_KEYS",
    "guidance_json_schema",
]

#: 1 mm/s: a velocity below this has no heading
_V_EPS_MPS = 1e-3


#: MAV_AUTOPILOT_PX4 (common.xml): its OFFBOARD mode needs a setpoint stream faster than PX4_MIN_SETPOINT_RATE_HZ, before
#: it accepts the mode and for as long as it is in it (else it falls back to COM_OBL_RC_ACT)
MAV_AUTOPILOT_PX4 = 12
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
PX4_MIN_SETPOINT_RATE_HZ = 2.0
#: the slowest ``setpoint_rate_hz`` taken for PX4: at PX4's own minimum, a setpoint late by one turn of the daemon's
#: main loop (or a busy CPU) makes a gap PX4 counts as the stream lost; a third of a second between setpoints leaves
#: a sixth of one to be late by
PX4_SETPOINT_RATE_FLOOR_HZ = 3.0


@config_dataclass
class GuidanceConfig:
    """The ``guidance`` section of the daemon's configuration (``config/onboard.yaml`` documents each field):
    whether the advice is published and sent, how it is planned, and the limits it must keep.

    Units are in the names.  Altitudes (the band) are metres above ``altitude_reference``: ``home`` (default:
    the autopilot's home, as GLOBAL_POSITION_INT's ``relative_alt`` counts it, so a band holds at any site
    elevation) or ``amsl``; the callers shift positions by the reference's height over the local NED origin
    (:meth:`GuidanceAdvisor.update`).
    """

    advise: Bool = True
    enabled: Bool = False
    update_interval_s: Annotated[float, Number(0.1, 60.0)] = 1.0
    horizon_s: Annotated[float, Number(2.0, 60.0)] = 6.0
    sample_interval_s: Annotated[float, Number(0.05, 2.0)] = 0.25
    bearing_rate_hz: Annotated[float, Number(0.1, 1000.0)] = 15.0
    valid_for_s: Annotated[float, Number(0.1, 60.0)] = 3.0
    quiet_below_sigma_range_ratio: Annotated[float, Number(0.0, 1.0)] = 0.03
    min_gain_ratio: Annotated[float, Number(0.0, 1.0, lo_open=True)] = 0.8
    target_accel_psd_m2ps3: Annotated[float, Number(0.0, 100.0, lo_open=True)] = 0.05
    heading_changes_deg: Annotated[tuple[float, ...], Numbers(lo=0.0, lo_open=True, min_length=1)] = (
        45.0,
        90.0,
    )
    cruise_speed_mps: Annotated[float, Number(0.0, 100.0, lo_open=True)] = 6.0
    min_speed_mps: Annotated[float, Number(0.0, 100.0)] = 0.0
    max_speed_mps: Annotated[float, Number(0.0, 100.0, lo_open=True)] = 12.0
    max_accel_mps2: Annotated[float, Number(0.0, 50.0, lo_open=True)] = 2.0
    max_climb_rate_mps: Annotated[float, Number(0.0, 50.0)] = 2.0
    altitude_reference: Annotated[Literal["home", "amsl"], Text()] = "home"
    min_altitude_m: Annotated[float, Number(-1000.0, 100000.0)] = 20.0
    max_altitude_m: Annotated[float, Number(-1000.0, 100000.0)] = 150.0
    los_elevation_min_deg: Annotated[float, Number(-90.0, 90.0)] = -80.0
    los_elevation_max_deg: Annotated[float, Number(-90.0, 90.0)] = 45.0
    max_los_off_heading_deg: Annotated[float, Number(0.0, 180.0)] = 180.0
    # in the loop (enabled): what the autopilot must report, the box it must stay in, how often setpoints go out
    setpoint_rate_hz: Annotated[float, Number(0.5, 50.0)] = 4.0
    accept_autopilot: Annotated[int, Integer(0, 255)] = 3
    accept_custom_mode: Annotated[int, Integer(0, 2**32 - 1)] = 4
    require_armed: Bool = True
    geofence_north_m: Annotated[tuple[float, float], Numbers(2)] = (-300.0, 300.0)
    geofence_east_m: Annotated[tuple[float, float], Numbers(2)] = (-300.0, 300.0)
    # the planner's manoeuvres stay this far inside the box: the airframe lags the turn it plans, and a vehicle past
    # the box is a latched stop (a planned path grazing the edge was flown 0.2 m past it in the loop)
    geofence_margin_m: Annotated[float, Number(0.0, 10_000.0)] = 10.0
    speed_margin_mps: Annotated[float, Number(0.0, 50.0)] = 2.0
    pose_timeout_s: Annotated[float, Number(0.1, 60.0)] = 1.0
    heartbeat_timeout_s: Annotated[float, Number(1.5, 60.0)] = 2.5

    def __post_init__(self) -> None:
        if self.min_speed_mps > self.max_speed_mps:
            raise Invalid("min_speed_mps", f"<= max_speed_mps ({self.max_speed_mps:g})", self.min_speed_mps)
        if not self.min_speed_mps <= self.cruise_speed_mps <= self.max_speed_mps:
            raise Invalid(
                "cruise_speed_mps",
                f"within [min_speed_mps, max_speed_mps] = [{self.min_speed_mps:g}, {self.max_speed_mps:g}]",
                self.cruise_speed_mps,
            )
        if self.min_altitude_m >= self.max_altitude_m:
            raise Invalid("min_altitude_m", f"< max_altitude_m ({self.max_altitude_m:g})", self.min_altitude_m)
        if self.los_elevation_min_deg >= self.los_elevation_max_deg:
            raise Invalid(
                "los_elevation_min_deg",
                f"< los_elevation_max_deg ({self.los_elevation_max_deg:g})",
                self.los_elevation_min_deg,
            )
        for i, d in enumerate(self.heading_changes_deg):
            if d > 180.0:
                raise Invalid(f"heading_changes_deg[{i}]", "a number of degrees in (0, 180]", d)
        for name in ("geofence_north_m", "geofence_east_m"):
            lo, hi = getattr(self, name)
            if not lo < hi:
                raise Invalid(name, "[min, max] with min < max, metres from the NED origin", [lo, hi])
            if not 2.0 * self.geofence_margin_m < hi - lo:  # the planner would find no place to fly
                raise Invalid(
                    "geofence_margin_m", f"< half of {name}'s span ({(hi - lo) / 2:g} m)", self.geofence_margin_m
                )
        if self.sample_interval_s * 10 > self.horizon_s:
            raise Invalid("sample_interval_s", f"<= horizon_s / 10 ({self.horizon_s / 10:g})", self.sample_interval_s)
        if self.valid_for_s > self.horizon_s:  # flown beyond what the planner looked at
            raise Invalid(
                "valid_for_s", f"<= horizon_s ({self.horizon_s:g}), the span the planner checked", self.valid_for_s
            )
        if self.enabled and not self.advise:  # the loop sends the advice: without it nothing would ever go out
            raise Invalid("enabled", "false while guidance.advise is false (the loop sends the advice)", True)
        # each autopilot's custom_mode encoding: a value the other's would never report (the gate would wait in
        # not_accepting for good, saying nothing about why)
        if self.accept_autopilot == MAV_AUTOPILOT_PX4 and (
            self.accept_custom_mode & 0xFFFF or not (self.accept_custom_mode >> 16) & 0xFF
        ):
            raise Invalid(
                "accept_custom_mode",
                "PX4's encoding for accept_autopilot 12: the main mode << 16 (+ the sub mode << 24), e.g. OFFBOARD = "
                "393216 (6 << 16)",
                self.accept_custom_mode,
            )
        if self.accept_autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA and self.accept_custom_mode > 0xFFFF:
            raise Invalid(
                "accept_custom_mode",
                "ArduPilot's mode number for accept_autopilot 3 (e.g. 4 = ArduCopter GUIDED), not PX4's encoding",
                self.accept_custom_mode,
            )
        if self.accept_autopilot == MAV_AUTOPILOT_PX4 and self.setpoint_rate_hz < PX4_SETPOINT_RATE_FLOOR_HZ:
            raise Invalid(
                "setpoint_rate_hz",
                f">= {PX4_SETPOINT_RATE_FLOOR_HZ:g} Hz for PX4 (accept_autopilot {MAV_AUTOPILOT_PX4}): OFFBOARD leaves "
                f"the mode unless the stream is faster than {PX4_MIN_SETPOINT_RATE_HZ:g} Hz, and setpoints can be late",
                self.setpoint_rate_hz,
            )

    def speed_ok(self, v_ned_mps: np.ndarray, slack_mps: float = 1e-9) -> bool:
        """Whether a velocity keeps the speed (horizontal) and climb-rate limits."""
        s = math.hypot(float(v_ned_mps[0]), float(v_ned_mps[1]))
        return (
            self.min_speed_mps - slack_mps <= s <= self.max_speed_mps + slack_mps
            and abs(float(v_ned_mps[2])) <= self.max_climb_rate_mps + slack_mps
        )

    def _beyond_box_m(self, p_ned_m: np.ndarray, margin_m: float) -> np.ndarray:
        """How far each position (..., 3) lies beyond the geofence box shrunk by ``margin_m`` (north, east about the
        NED origin), metres: negative inside, 0 on its edge, NaN for a position that is not a number."""
        p = np.asarray(p_ned_m, dtype=float)
        (n0, n1), (e0, e1) = self.geofence_north_m, self.geofence_east_m
        return np.maximum(
            np.maximum(n0 + margin_m - p[..., 0], p[..., 0] - (n1 - margin_m)),
            np.maximum(e0 + margin_m - p[..., 1], p[..., 1] - (e1 - margin_m)),
        )

    def inside_geofence(self, p_ned_m: np.ndarray) -> bool:
        """Whether every position (..., 3) is inside the geofence box, its edge included."""
        return bool(np.all(self._beyond_box_m(p_ned_m, 0.0) <= 0.0))

    def fence_excess_m(self, p_ned_m: np.ndarray) -> np.ndarray:
        """How far each position (..., 3) lies outside the geofence box shrunk by ``geofence_margin_m`` (0 within),
        metres: the planner's distance from the fence."""
        return np.maximum(self._beyond_box_m(p_ned_m, self.geofence_margin_m), 0.0)

    def altitude_ok(self, p_ned_m: np.ndarray, slack_m: float = 1e-9) -> bool:
        """Whether every position (..., 3) is within the altitude band."""
        alt = -np.asarray(p_ned_m, dtype=float)[..., 2]
        return bool(np.all(alt >= self.min_altitude_m - slack_m) and np.all(alt <= self.max_altitude_m + slack_m))


def _vec3(x, what: str) -> np.ndarray:
    a = np.asarray(x, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InputError(f"{what}: expected 3 finite numbers, got {x!r}")
    return a


def _check_t_p_v(state: ObserverState | TargetPosterior) -> None:
    """A frozen state's ``t_s`` finite, its ``p_ned_m`` and ``v_ned_mps`` made (3,) float arrays (errors name
    the class and the field)."""
    what = type(state).__name__
    if not math.isfinite(state.t_s):
        raise InputError(f"{what}.t_s: expected a finite time, got {state.t_s!r}")
    object.__setattr__(state, "p_ned_m", _vec3(state.p_ned_m, f"{what}.p_ned_m"))
    object.__setattr__(state, "v_ned_mps", _vec3(state.v_ned_mps, f"{what}.v_ned_mps"))


@dataclass(frozen=True)
class ObserverState:
    """The observer (camera) at ``t_s``: position ``p_ned_m`` (3,) and velocity ``v_ned_mps`` (3,)."""

    t_s: float
    p_ned_m: np.ndarray
    v_ned_mps: np.ndarray

    def __post_init__(self) -> None:
        _check_t_p_v(self)


@dataclass(frozen=True)
class TargetPosterior:
    """The target's posterior at ``t_s``: mean position ``p_ned_m`` (3,), velocity ``v_ned_mps`` (3,) and the
    joint covariance ``cov_pv`` (6, 6) of ``(p, v)`` (m^2, m^2/s, m^2/s^2 blocks), symmetric positive definite."""

    t_s: float
    p_ned_m: np.ndarray
    v_ned_mps: np.ndarray
    cov_pv: np.ndarray

    def __post_init__(self) -> None:
        _check_t_p_v(self)
        c = np.asarray(self.cov_pv, dtype=float)
        if c.shape != (6, 6) or not np.all(np.isfinite(c)):
            raise InputError(f"TargetPosterior.cov_pv: expected a finite (6, 6) matrix, got shape {c.shape}")
        c = 0.5 * (c + c.T)
        if np.linalg.eigvalsh(c)[0] <= 0.0:
            raise InputError("TargetPosterior.cov_pv: not positive definite")
        object.__setattr__(self, "cov_pv", c)

    @classmethod
    def from_track(
        cls, t_s: float, p_ned_m, v_ned_mps, cov_p_ned_m2, sigma_v_ned_mps, p_cam_ned_m, v_cam_ned_mps
    ) -> TargetPosterior:
        """From what a track carries (position covariance (3, 3), per-axis velocity sigmas) and the camera's
        position and velocity then.

        The track has no position-velocity cross term, and the part it misses is the one guidance is about:
        along the unobservable direction of bearing-only tracking the relative trajectory scales freely
        (``p = C + s (p_hat - C)``, ``v = v_C + s (v_hat - v_C)``; Nardone & Aidala, IEEE TAES 17(2), 1981),
        so position and velocity errors along range are one mode.  The covariance is built as that mode with
        the track's range sigma, ``sigma_s^2 d d^T`` with ``d = (p_hat - C, v_hat - v_C)`` and ``sigma_s =
        sigma_r / r``, plus the track's position covariance off the line of sight and its velocity variances.
        """
        p = _vec3(p_ned_m, "TargetPosterior.p_ned_m")
        v = _vec3(v_ned_mps, "TargetPosterior.v_ned_mps")
        C = _vec3(p_cam_ned_m, "TargetPosterior.p_cam_ned_m")
        vC = _vec3(v_cam_ned_mps, "TargetPosterior.v_cam_ned_mps")
        cov_p = np.asarray(cov_p_ned_m2, dtype=float).reshape(3, 3)
        d_p, d_v = p - C, v - vC
        r = float(np.linalg.norm(d_p))
        if not r > 0.0:
            raise InputError("TargetPosterior.from_track: the target is at the camera")
        u = d_p / r
        sigma_s = math.sqrt(max(float(u @ cov_p @ u), 0.0)) / r
        Pu = np.eye(3) - np.outer(u, u)
        cov = np.zeros((6, 6))
        cov[:3, :3] = Pu @ cov_p @ Pu + 1e-4 * np.eye(3)
        sv = np.maximum(np.asarray(sigma_v_ned_mps, dtype=float).reshape(3), 1e-2)
        cov[3:, 3:] = np.diag(sv**2)
        d = np.concatenate([d_p, d_v])
        cov += sigma_s**2 * np.outer(d, d)
        return cls(float(t_s), p, v, cov)

    def sigma_along(self, u: np.ndarray) -> float:
        """1-sigma of the position along the unit vector ``u`` (m)."""
        return float(math.sqrt(max(float(u @ self.cov_pv[:3, :3] @ u), 0.0)))


@dataclass(frozen=True)
class Candidate:
    """One manoeuvre evaluated: its ``name``, velocity setpoint ``v_ned_mps`` (3,), whether it keeps the limits
    (``feasible``, ``why`` not) and its predicted range sigma at the horizon's end (m; inf: not evaluated)."""

    name: str
    v_ned_mps: np.ndarray
    feasible: bool
    why: str
    sigma_range_m: float


@dataclass(frozen=True)
class Advice:
    """What :meth:`GuidancePlanner.advise` decided at ``t_s`` (the observer's time).

    ``status``: ``advise`` (``v_ned_mps`` recommended until ``valid_until_s``), ``observable`` (the range
    sigma is already below the quiet threshold), ``no_gain`` (no candidate beats holding by
    ``min_gain_ratio``), ``outside_limits`` (the observer itself is faster than its speed or climb-rate
    limits or outside its altitude band: nothing is advised that would have to leave them; slower than
    ``min_speed_mps`` is not outside: every manoeuvre's setpoint is at least that fast), ``no_feasible`` (every candidate breaks a limit), ``unavailable``
    (the prediction failed: see ``why``).  ``sigma_range_now_m`` is the posterior's range sigma now;
    ``sigma_range_without_m`` / ``sigma_range_with_m`` the predicted ones at ``t_s + horizon_s`` holding
    the current velocity / flying the advice (equal when nothing is advised); ``range_m`` the predicted
    range at ``t_s``; ``candidates`` every manoeuvre considered.
    """

    t_s: float
    status: str
    manoeuvre: str | None
    v_ned_mps: np.ndarray | None
    valid_until_s: float
    range_m: float
    sigma_range_now_m: float
    sigma_range_without_m: float
    sigma_range_with_m: float
    why: str = ""
    candidates: tuple[Candidate, ...] = field(default=(), repr=False)

    @property
    def recommended(self) -> bool:
        return self.status == "advise" and self.v_ned_mps is not None


def candidate_path(
    p0_ned_m: np.ndarray, v0_ned_mps: np.ndarray, v_sp_ned_mps: np.ndarray, accel_mps2: float, dt_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Positions and velocities (N, 3) at ``dt_s`` (N,) after now of an observer that slews its velocity from
    ``v0`` to ``v_sp`` at constant acceleration ``accel_mps2`` along ``v_sp - v0``, then holds it.

    ``v(t) = v0 + a e t`` for ``t < T = |v_sp - v0| / a`` (``e`` the unit direction), ``v_sp`` after;
    ``p`` its exact integral.  The speed along the slew never exceeds ``max(|v0|, |v_sp|)`` (convexity).
    """
    p0, v0, vs = (np.asarray(x, dtype=float) for x in (p0_ned_m, v0_ned_mps, v_sp_ned_mps))
    t = np.asarray(dt_s, dtype=float)[:, None]
    dv = vs - v0
    n = float(np.linalg.norm(dv))
    if n < _V_EPS_MPS:
        return p0 + v0 * t, np.broadcast_to(v0, (t.shape[0], 3)).copy()
    T = n / accel_mps2
    a = dv / T
    ts = np.minimum(t, T)
    p = p0 + v0 * ts + 0.5 * a * ts * ts + vs * (t - ts)
    v = v0 + a * ts
    return p, v


#: camera axes (x right, y down, z forward) in body FRD axes: forward = z, right = x, down = y
_Q_BODY_FROM_CAM = quat_from_rotmat(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))


def _camera_looking(u_ned: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(q_ned_from_cam, R_ned_from_cam)`` (N, 4), (N, 3, 3) of cameras whose optical axis is ``u_ned`` (N, 3,
    unit) with no roll: a body yawed to the azimuth and pitched to the elevation, the camera looking along its x."""
    yaw = np.arctan2(u_ned[:, 1], u_ned[:, 0])
    pitch = np.arctan2(-u_ned[:, 2], np.hypot(u_ned[:, 0], u_ned[:, 1]))
    q = quat_multiply(quat_from_euler(np.zeros_like(yaw), pitch, yaw), _Q_BODY_FROM_CAM)
    return q, rotmat_from_quat(q)


class GuidancePlanner:
    """Chooses the manoeuvre (module docstring).  ``estimator``: the reconstruction whose prior, noise model and
    nuisances the prediction uses (its ``knot_spacing_s`` is the prediction's); ``f_px``: the camera's focal
    lengths (fx, fy) in pixels, which turn the pixel noise into bearing noise.

    Step method: :meth:`advise` (pure; one call costs a few candidate predictions, each a small QR).
    """

    def __init__(self, config: GuidanceConfig, estimator: MapEstimator, f_px: tuple[float, float]):
        self.config = config
        self.estimator = estimator
        self.f_px = (float(f_px[0]), float(f_px[1]))
        c = config
        from onboard.estimation.map_estimator import MotionPrior

        self.prior = MotionPrior(c.target_accel_psd_m2ps3, c.target_accel_psd_m2ps3 * 0.25, turn_rate_sigma_radps=0.0)
        n = int(round(c.horizon_s / c.sample_interval_s))
        self.dt_s = np.linspace(0.0, c.horizon_s, n + 1)
        # predicted bearings are sampled sparsely; each stands for this many of the estimator's
        self.information_scale = max(1.0, c.sample_interval_s * c.bearing_rate_hz)

    @classmethod
    def for_noise(
        cls, config: GuidanceConfig, noise: NoiseModel, f_px: tuple[float, float], knot_spacing_s: float = 1.0
    ) -> GuidancePlanner:
        """A planner over the online estimator's spline (``knot_spacing_s``) and ``noise`` model."""
        from onboard.estimation.map_estimator import MapConfig, MapEstimator

        return cls(config, MapEstimator(MapConfig(knot_spacing_s=knot_spacing_s, min_frames=10), noise), f_px)

    # ------------------------------------------------------------------ candidates
    def candidates(self, observer: ObserverState, target: TargetPosterior) -> list[tuple[str, np.ndarray]]:
        """(name, velocity setpoint) of every manoeuvre considered; the first is ``hold``."""
        c = self.config
        v0 = observer.v_ned_mps
        out: list[tuple[str, np.ndarray]] = [("hold", v0.copy())]
        vh = v0[:2]
        speed = float(np.hypot(*vh))
        s = min(max(speed, c.cruise_speed_mps), c.max_speed_mps)
        s = max(s, c.min_speed_mps)
        if speed > _V_EPS_MPS:
            psi = math.atan2(vh[1], vh[0])
            for d in c.heading_changes_deg:
                for sign, side in ((1.0, "right"), (-1.0, "left")):
                    a = psi + sign * math.radians(d)
                    out.append((f"turn_{side}_{d:g}deg", np.array([s * math.cos(a), s * math.sin(a), 0.0])))
        los = target.p_ned_m - observer.p_ned_m
        az = math.atan2(los[1], los[0])
        for sign, side in ((1.0, "right"), (-1.0, "left")):
            a = az + sign * 0.5 * math.pi
            out.append((f"cross_{side}", np.array([s * math.cos(a), s * math.sin(a), 0.0])))
        if c.max_climb_rate_mps > 0:
            if speed >= c.min_speed_mps:
                base = np.array([vh[0], vh[1], 0.0])
            elif speed > _V_EPS_MPS:  # slower than the limit: on its heading at the manoeuvres' speed
                base = np.array([vh[0] * s / speed, vh[1] * s / speed, 0.0])
            else:
                base = np.array([s, 0.0, 0.0])
            out.append(("climb", base + np.array([0.0, 0.0, -c.max_climb_rate_mps])))
            out.append(("descend", base + np.array([0.0, 0.0, c.max_climb_rate_mps])))
        return out

    def feasibility(
        self, name: str, v_sp: np.ndarray, p_obs: np.ndarray, p_tgt: np.ndarray, v_path: np.ndarray
    ) -> tuple[bool, str]:
        """Whether a candidate keeps the limits: its setpoint, and along its predicted path (N, 3) the altitude band,
        the geofence box and the target in view; ``why`` names the first limit broken."""
        c = self.config
        if name != "hold" and not c.speed_ok(v_sp):
            return False, "speed"
        if not c.altitude_ok(p_obs):
            return False, "altitude"
        if not c.inside_geofence(p_obs):  # the gate stops a vehicle outside it; never plan it out there
            return False, "geofence"
        # nor into the margin inside it (the airframe lags the planned turn): a path that starts within the margin
        # (p_obs[0] is the observer now) may only keep or gain its distance from the fence
        excess = c.fence_excess_m(p_obs)
        if np.any(excess > excess[0] + 1e-9):
            return False, "geofence"
        los = p_tgt - p_obs
        el = np.degrees(np.arctan2(-los[:, 2], np.hypot(los[:, 0], los[:, 1])))
        if np.any(el < c.los_elevation_min_deg) or np.any(el > c.los_elevation_max_deg):
            return False, "field_of_view"
        if c.max_los_off_heading_deg < 180.0:
            vh = v_path[:, :2]
            moving = np.hypot(vh[:, 0], vh[:, 1]) > 0.5
            off = np.degrees(
                np.abs(np.angle(np.exp(1j * (np.arctan2(los[:, 1], los[:, 0]) - np.arctan2(vh[:, 1], vh[:, 0])))))
            )
            if np.any(off[moving] > c.max_los_off_heading_deg):
                return False, "field_of_view"
        return True, ""

    # ------------------------------------------------------------------ prediction
    def predicted_sigma_range_m(
        self, observer: ObserverState, info_pv: np.ndarray, p_obs: np.ndarray, p_tgt: np.ndarray
    ) -> float:
        """Predicted 1-sigma range at the horizon's end after flying ``p_obs`` (N, 3) while the target flies
        ``p_tgt`` (N, 3), both at ``observer.t_s + dt_s``, knowing ``info_pv`` (6, 6) about the target's ``(p, v)`` at
        ``observer.t_s`` (:func:`~onboard.estimation.crb.predicted_point_covariance`)."""
        from onboard.estimation.crb import predicted_point_covariance
        from onboard.estimation.observations import Observations

        t = observer.t_s + self.dt_s
        u = p_tgt - p_obs
        r = np.linalg.norm(u, axis=1, keepdims=True)
        u = u / np.maximum(r, 1e-9)
        q, R = _camera_looking(u)
        fx, fy = self.f_px
        n = t.shape[0]
        obs = Observations.from_checked_rows(
            t, np.zeros((n, 2)), np.full(n, fx), np.full(n, fy), np.zeros(n), np.zeros(n), p_obs, q, R
        )
        P = predicted_point_covariance(
            self.estimator,
            obs,
            p_tgt,
            self.prior,
            float(t[-1]),
            state_prior=(float(t[0]), info_pv),
            information_scale=self.information_scale,
        )
        ue = u[-1]
        return float(math.sqrt(max(float(ue @ P @ ue), 0.0)))

    # ------------------------------------------------------------------ the step
    def advise(self, observer: ObserverState, target: TargetPosterior) -> Advice:
        """The advice at ``observer.t_s`` for the target posterior ``target`` (propagated to that time at constant
        velocity when older; its covariance is not inflated for the gap, which is a fraction of the horizon)."""
        c = self.config
        t0 = observer.t_s
        p_t0 = target.p_ned_m + target.v_ned_mps * (t0 - target.t_s)
        los0 = p_t0 - observer.p_ned_m
        range_m = float(np.linalg.norm(los0))
        u0 = los0 / max(range_m, 1e-9)
        sigma_now = target.sigma_along(u0)

        def nothing(status: str, without_m: float, with_m: float, why: str = "", evaluated=()) -> Advice:
            return Advice(
                t_s=t0,
                status=status,
                manoeuvre=None,
                v_ned_mps=None,
                valid_until_s=t0,
                range_m=range_m,
                sigma_range_now_m=sigma_now,
                sigma_range_without_m=without_m,
                sigma_range_with_m=with_m,
                why=why,
                candidates=tuple(evaluated),
            )

        if range_m <= 1.0:
            return nothing("unavailable", math.nan, math.nan, "target at the camera")
        if sigma_now < c.quiet_below_sigma_range_ratio * range_m:
            return nothing("observable", sigma_now, sigma_now)
        # faster than the limits, not slower: every manoeuvre's setpoint is at least min_speed_mps, so a slow observer
        # (hovering after the gate's zero-velocity brake, or a multirotor starting) is brought up to it; refusing it
        # left a vehicle with min_speed_mps over 0.5 m/s unadvised for good after its first brake
        v0 = observer.v_ned_mps
        too_fast = not (
            math.hypot(float(v0[0]), float(v0[1])) <= c.max_speed_mps + 0.5
            and abs(float(v0[2])) <= c.max_climb_rate_mps + 0.5
        )
        if too_fast or not c.altitude_ok(observer.p_ned_m):
            return nothing("outside_limits", math.nan, math.nan, "the observer is outside its speed or altitude limits")
        target_at_t0 = TargetPosterior(t0, p_t0, target.v_ned_mps, target.cov_pv)
        info_pv = np.linalg.inv(target.cov_pv)
        p_tgt = p_t0 + target.v_ned_mps * self.dt_s[:, None]
        evaluated: list[Candidate] = []
        try:
            for name, v_sp in self.candidates(observer, target_at_t0):
                p_obs, v_path = candidate_path(observer.p_ned_m, observer.v_ned_mps, v_sp, c.max_accel_mps2, self.dt_s)
                ok, why = self.feasibility(name, v_sp, p_obs, p_tgt, v_path)
                sig = math.inf
                if ok or name == "hold":
                    sig = self.predicted_sigma_range_m(observer, info_pv, p_obs, p_tgt)
                evaluated.append(Candidate(name, v_sp, ok, why, sig))
        except (IrtrackError, np.linalg.LinAlgError, ValueError) as exc:  # EstimationError, InputError included
            return nothing("unavailable", math.nan, math.nan, str(exc))
        hold = evaluated[0]
        options = [k for k in evaluated[1:] if k.feasible and math.isfinite(k.sigma_range_m)]
        if not options:
            return nothing(
                "no_feasible", hold.sigma_range_m, hold.sigma_range_m, "every manoeuvre breaks a limit", evaluated
            )
        best = min(options, key=lambda k: k.sigma_range_m)
        if not best.sigma_range_m < c.min_gain_ratio * hold.sigma_range_m:
            return nothing("no_gain", hold.sigma_range_m, hold.sigma_range_m, "", evaluated)
        return Advice(
            t_s=t0,
            status="advise",
            manoeuvre=best.name,
            v_ned_mps=best.v_ned_mps.copy(),
            valid_until_s=t0 + c.valid_for_s,
            range_m=range_m,
            sigma_range_now_m=sigma_now,
            sigma_range_without_m=hold.sigma_range_m,
            sigma_range_with_m=best.sigma_range_m,
            candidates=tuple(evaluated),
        )


#: the guidance payload's schema name (``irtrack/<vehicle>/guidance``; README "On the wire")
GUIDANCE_SCHEMA = "irtrack.guidance/1"
_US_PER_S = 1_000_000


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


_NUM_OR_NULL = {"type": ["number", "null"]}

#: Every key :func:`advice_to_json` writes, in its order, with its JSON Schema: the recording's
#: ``irtrack.guidance/1`` schema is made of it (:func:`guidance_json_schema`), and a test holds the payload to it
GUIDANCE_JSON_KEYS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("schema", {"type": "string", "const": GUIDANCE_SCHEMA}),
    ("vehicle", {"type": "string"}),
    ("time_boot_us", {"type": "integer", "description": "capture time of the track it was planned from, us boot"}),
    ("valid_until_boot_us", {"type": "integer", "description": "follow the advice until then, us boot"}),
    ("status", {"type": "string", "description": "advise"}),
    ("manoeuvre", {"type": ["string", "null"], "description": "the candidate chosen"}),
    (
        "v_ned_mps",
        {"type": ["array", "null"], "items": {"type": "number"}, "minItems": 3, "maxItems": 3, "description": "m/s"},
    ),
    ("range_m", {**_NUM_OR_NULL, "description": "the target's range now, m"}),
    ("sigma_range_now_m", {**_NUM_OR_NULL, "description": "range 1-sigma now, m"}),
    ("sigma_range_without_m", {**_NUM_OR_NULL, "description": "predicted at the horizon holding course, m"}),
    ("sigma_range_with_m", {**_NUM_OR_NULL, "description": "predicted at the horizon with the manoeuvre, m"}),
    ("in_loop", {"type": "boolean", "description": "the daemon also flies it (guidance.enabled)"}),
)


def guidance_json_schema() -> dict[str, Any]:
    """The JSON Schema of an ``irtrack.guidance/1`` message as :func:`advice_to_json` writes it (every key)."""
    return object_schema(
        GUIDANCE_SCHEMA,
        "An advised observer manoeuvre (onboard/estimation/guidance.py), as published.",
        GUIDANCE_JSON_KEYS,
    )


def advice_to_json(advice: Advice, vehicle: str, time_boot_us: int, in_loop: bool = False) -> dict:
    """The ``irtrack.guidance/1`` payload of one advice (README, "On the wire"): times on the autopilot's boot
    clock in microseconds, velocities in NED m/s, sigmas in metres (null when not finite)."""
    valid_us = time_boot_us + int(round((advice.valid_until_s - advice.t_s) * _US_PER_S))
    return {
        "schema": GUIDANCE_SCHEMA,
        "vehicle": vehicle,
        "time_boot_us": int(time_boot_us),
        "valid_until_boot_us": int(valid_us),
        "status": advice.status,
        "manoeuvre": advice.manoeuvre,
        "v_ned_mps": None if advice.v_ned_mps is None else [float(x) for x in advice.v_ned_mps],
        "range_m": _num(advice.range_m),
        "sigma_range_now_m": _num(advice.sigma_range_now_m),
        "sigma_range_without_m": _num(advice.sigma_range_without_m),
        "sigma_range_with_m": _num(advice.sigma_range_with_m),
        "in_loop": bool(in_loop),
    }


class GuidanceAdvisor:
    """Runs the planner on the tracks' own clock (every ``config.update_interval_s`` of capture time), from what a
    track and the frame's pose carry.  Step method :meth:`update`; no threads, no clock of its own (a replay or the
    lockstep evaluation gets the same advice as the daemon).

    ``skipped``: updates due but not planned, by reason (``no_position``: the track has no 3-D position yet;
    ``no_velocity``: the autopilot sent no velocity with the pose; ``bad_input``: a track or pose the posterior
    cannot be built from, ``last_error`` says why).
    """

    def __init__(self, planner: GuidancePlanner) -> None:
        self.planner = planner
        self.interval_us = int(round(planner.config.update_interval_s * _US_PER_S))
        self._next_us: int | None = None
        self.last: Advice | None = None
        self.updates = 0
        self.advised = 0
        self.skipped: dict[str, int] = {}
        self.last_error = ""

    def due(self, time_boot_us: int) -> bool:
        """Whether a track captured at ``time_boot_us`` is due an update (a clock that steps back restarts the pacing)."""
        nxt = self._next_us
        return nxt is None or time_boot_us >= nxt or time_boot_us < nxt - 2 * self.interval_us

    def update(self, track: Any, p_cam_ned_m, v_cam_ned_mps, origin_alt_m: float = 0.0) -> Advice | None:
        """The advice for ``track`` (an :class:`onboard.core.track.Track`) seen from the camera at ``p_cam_ned_m``
        moving at ``v_cam_ned_mps`` (the vehicle's velocity; NaN = unknown), or None when not due or not possible.

        ``origin_alt_m``: the local NED origin's altitude above the band's reference (``altitude_reference``: m
        above home, or AMSL); both positions are moved down by it (``d - origin_alt_m``), which changes no
        relative geometry."""
        t_us = int(track.time_boot_us)
        if not self.due(t_us):
            return None
        self._next_us = t_us + self.interval_us
        if not track.has_position or track.v_ned_mps is None or track.cov_p_ned_m2 is None:
            self.skipped["no_position"] = self.skipped.get("no_position", 0) + 1
            return None
        v_cam = np.asarray(v_cam_ned_mps, dtype=float)
        if v_cam.shape != (3,) or not np.all(np.isfinite(v_cam)):
            self.skipped["no_velocity"] = self.skipped.get("no_velocity", 0) + 1
            return None
        t_s = t_us / _US_PER_S
        sig_v = track.sigma_vel_ned_mps or (2.0, 2.0, 1.0)
        down = np.array([0.0, 0.0, -float(origin_alt_m)])
        try:
            p_cam = np.asarray(p_cam_ned_m, dtype=float) + down
            p_tgt = np.asarray(track.p_ned_m, dtype=float) + down
            target = TargetPosterior.from_track(t_s, p_tgt, track.v_ned_mps, track.cov_p_ned_m2, sig_v, p_cam, v_cam)
            observer = ObserverState(t_s, p_cam, v_cam)
        except InputError as exc:  # a track or pose the posterior cannot be built from: counted, the caller logs it
            self.skipped["bad_input"] = self.skipped.get("bad_input", 0) + 1
            self.last_error = str(exc)
            return None
        advice = self.planner.advise(observer, target)
        self.updates += 1
        self.advised += advice.recommended
        self.last = advice
        return advice


#: MAV_MODE_FLAG_SAFETY_ARMED (common.xml): the autopilot's motors are armed
_MODE_FLAG_ARMED = 128
#: after sending ends (a stop, the advice over, the daemon stopping), zero-velocity setpoints for this long (then
#: silence: the autopilot's own timeout)
BRAKE_S = 1.0
#: GPS_RAW_INT older than this after one was heard stops the setpoints too: PX4 stops the message when its receiver
#: is gone (ArduPilot sends NO_GPS), and a fix nobody reports is no fix known (autopilots send it at 1-5 Hz)
GNSS_STALE_S = 5.0
#: an autopilot heartbeat (1 Hz) older than this is late: the link, not the camera, is named when the poses stop
HEARTBEAT_LATE_S = 1.5
#: why the gate has no pose to judge: its pose is the one each camera frame got
_NO_FRAME_POSE = "no camera frame with a measured vehicle position (no frames, none with a pose, or dead reckoning)"


@dataclass(frozen=True)
class SetpointDecision:
    """What :meth:`SetpointGate.step` decided: ``send`` ``v_ned_mps`` (3,) now, or not; ``state`` (``off``,
    ``waiting``: no valid advice (zero velocity for :data:`BRAKE_S` after one ended), ``not_accepting``: the autopilot
    is not in the accepting mode, ``sending``, ``holding``: zero velocity between advices for PX4's OFFBOARD,
    ``stopped``: a limit was reached, the link lost or the daemon stopping while commanding, latched) and ``why`` in
    words."""

    send: bool
    v_ned_mps: np.ndarray | None
    state: str
    why: str


class SetpointGate:
    """The safety gate between the advice and the autopilot (``guidance.enabled``).  Pure: the caller passes the
    time, the link state, the autopilot's heartbeat mode, the vehicle's newest position and velocity and the
    advice in force; :meth:`step` says whether to send it.

    Sends only while the link is connected and its newest heartbeat is not older than ``heartbeat_timeout_s`` (a few
    of the autopilot's heartbeat periods, sooner than the link's own ``mavlink.heartbeat_timeout_s``), the heartbeat
    reports ``accept_autopilot`` / ``accept_custom_mode`` (armed when ``require_armed``), the vehicle is inside the
    geofence box and the altitude band, not faster than ``max_speed_mps + speed_margin_mps``, its pose (the newest
    camera frame's) newer than ``pose_timeout_s``, its GNSS not below a 3-D fix after one nor its GPS_RAW_INT stopped for :data:`GNSS_STALE_S` (the autopilot
    then dead-reckons the positions it goes on reporting, and the box and band are checked on a drifting position;
    a vehicle that never had a 3-D fix is positioned otherwise and not judged by it) and the advice still valid.  A
    limit reached or the link lost while sending stops it (``stopped``, latched, ``why`` says which): for
    :data:`BRAKE_S` the setpoint is zero velocity (the vehicle holds where it is instead of flying the last setpoint
    on until the autopilot's timeout: 3 s, 36 m at 12 m/s on ArduCopter), then nothing; after a link loss, again for
    :data:`BRAKE_S` when the link comes back with the autopilot still in the accepting mode (the first brake went
    into the dead link); setpoints resume only after
    the autopilot has left the accepting mode (the pilot took over) and re-entered it.  The advice ending (expired, none in force, a target lost) brakes
    the same way, unlatched: the next advice is sent.  Where the accepting autopilot is PX4, whose OFFBOARD mode
    needs the stream to go on, the setpoint between advices is zero velocity at the setpoint rate (``holding``)
    instead.  :meth:`halt` brakes for a daemon that stops.  A gate that first sees the autopilot already in the
    accepting mode (a daemon restarted in flight) starts stopped too: the hand-over is the pilot's entering the mode
    while this daemon watches (with ``require_armed``, arming in the mode is entering it).  A link that comes back after a loss is such a start (the pilot may have left and
    re-entered the mode unheard): the first heartbeat after it decides the same way, and a gate that was commanding
    when the link was lost is stopped already (``link_lost``) and stays so.  The autopilot's own failsafe handles a
    setpoint stream that stops (ArduPilot GUIDED holds after its velocity timeout, PX4 leaves OFFBOARD):
    deploy/README.md.
    """

    def __init__(self, config: GuidanceConfig) -> None:
        self.config = config
        self.state = "off" if not config.enabled else "waiting"
        self.why = "" if config.enabled else "guidance.enabled is false"
        self.stops: dict[str, int] = {}
        # a heartbeat's mode seen since start or since the link came back (the first decides the hand-over)
        self._mode_seen = False
        self._link_was_up = False  # a mode seen before (the hand-over's why: a restart, or the link back)
        self._brake_until_s = -math.inf

    def _accepting(self, mode: tuple[int, int, int] | None) -> bool:
        c = self.config
        if mode is None:
            return False
        autopilot, base_mode, custom_mode = mode
        return (
            autopilot == c.accept_autopilot
            and custom_mode == c.accept_custom_mode
            and (not c.require_armed or bool(base_mode & _MODE_FLAG_ARMED))
        )

    def _limit(self, p_ned_m: np.ndarray, v_ned_mps: np.ndarray) -> str:
        c = self.config
        n0, n1 = c.geofence_north_m
        e0, e1 = c.geofence_east_m
        if not (n0 <= p_ned_m[0] <= n1 and e0 <= p_ned_m[1] <= e1):
            return f"geofence: vehicle at north {p_ned_m[0]:.1f} east {p_ned_m[1]:.1f} m, box north {n0:g}..{n1:g} east {e0:g}..{e1:g} m"
        alt = -float(p_ned_m[2])
        if not c.min_altitude_m <= alt <= c.max_altitude_m:
            return f"altitude: vehicle at {alt:.1f} m, band {c.min_altitude_m:g}..{c.max_altitude_m:g} m"
        speed = float(np.linalg.norm(v_ned_mps[:2]))
        if not (  # written so that a NaN (an unknown velocity) stops too
            speed <= c.max_speed_mps + c.speed_margin_mps
            and abs(float(v_ned_mps[2])) <= c.max_climb_rate_mps + c.speed_margin_mps
        ):
            return f"speed: vehicle at {speed:.1f} m/s horizontal, {float(v_ned_mps[2]):.1f} m/s down"
        return ""

    def _stop(self, why: str, now_s: float | None = None) -> SetpointDecision:
        """Latch ``stopped``; ``now_s`` given (a stop while commanding the vehicle): brake from now."""
        self.state, self.why = "stopped", why
        kind = why.split(":", 1)[0]
        self.stops[kind] = self.stops.get(kind, 0) + 1
        if now_s is not None:
            self._brake_until_s = now_s + BRAKE_S
            return SetpointDecision(True, np.zeros(3), self.state, why)
        return SetpointDecision(False, None, self.state, why)

    def step(
        self,
        now_s: float,
        *,
        link_connected: bool,
        mode: tuple[int, int, int] | None,
        pose: tuple[float, np.ndarray, np.ndarray] | None,
        advice: tuple[float, np.ndarray] | None,
        heartbeat_age_s: float = 0.0,
        ended: str = "",
        gnss: GnssState | None = None,
    ) -> SetpointDecision:
        """``pose``: (when it came, s on ``now_s``'s clock; position (3,) NED m; velocity (3,) NED m/s) or None;
        ``advice``: (valid until, s on the same clock; velocity (3,) NED m/s) or None; ``heartbeat_age_s``: how
        long ago the autopilot's newest heartbeat came (a NaN: never); ``ended``: why the last advice was ended
        early when none is in force (the target lost, ...), said in ``why``; ``gnss``: the autopilot's newest
        GPS_RAW_INT (None: none heard)."""
        if not self.config.enabled:
            return SetpointDecision(False, None, "off", self.why)
        # the link's own timeout (mavlink.heartbeat_timeout_s) is for the telemetry; a vehicle being commanded may
        # not wait that long for an autopilot it no longer hears
        unheard = link_connected and not heartbeat_age_s <= self.config.heartbeat_timeout_s
        link_up = link_connected and not unheard
        accepting = link_up and self._accepting(mode)
        if not link_up:  # the pilot may switch modes while nothing is heard: the link's return decides afresh
            self._mode_seen = False
        elif mode is not None and not self._mode_seen:
            self._mode_seen = True
            if accepting and self.state == "stopped" and self.why.startswith("link_lost"):
                # the brake went into the dead link and may not have arrived: the vehicle, still in the mode, may be
                # flying the last setpoint until its own timeout (ArduCopter: 3 s); zero velocity again now it hears
                self._brake_until_s = now_s + BRAKE_S
            # in the mode before this daemon saw it enter it: not handed over to this daemon (a gate already stopped,
            # e.g. by the loss while commanding, stays latched under its own reason)
            if accepting and self.state != "stopped":
                self._stop(
                    "handover: the autopilot was in the accepting mode when its link came back"
                    if self._link_was_up
                    else "handover: the autopilot was in the accepting mode when guidance started (a restart?)"
                )
            self._link_was_up = True
        if self.state == "stopped":
            late = not heartbeat_age_s <= HEARTBEAT_LATE_S
            if (not link_up or late) and self.why.startswith("pose_lost") and "heartbeat" not in self.why:
                # the poses stopped first, then the heartbeat too (late, if not yet timed out: a cut of 1.5-2.5 s ends
                # before the link's timeout): the link it was, said where the status shows it
                self.why += " (then no autopilot heartbeat either: the MAVLink link)"
            if link_up and not accepting:  # the pilot took the vehicle back: re-arm the gate
                self._brake_until_s = -math.inf
                self.state, self.why = "not_accepting", "the autopilot left the accepting mode after a stop"
            elif (accepting or not link_up) and now_s < self._brake_until_s:
                # without heartbeats the mode is unknown: zero velocity is harmless in any other mode
                return SetpointDecision(True, np.zeros(3), self.state, self.why)
            return SetpointDecision(False, None, self.state, self.why)
        was_sending = self._commanding(now_s)
        if not link_up:
            if was_sending:
                since = " for guidance.heartbeat_timeout_s" if unheard else ""
                return self._stop(f"link_lost: no autopilot heartbeat{since}", now_s)
            self.state = "waiting"
            self.why = "no autopilot heartbeat for guidance.heartbeat_timeout_s" if unheard else "no autopilot link"
            return SetpointDecision(False, None, self.state, self.why)
        if not accepting:
            if was_sending:
                self.why = "the autopilot left the accepting mode"
            elif self.state != "not_accepting":
                self.why = "the autopilot is not in the accepting mode"
            # else: still out of the mode; why keeps what it said when the vehicle left it (the pilot took it back, or
            # the re-arm after a stop), which the 1 Hz status would otherwise show for one setpoint step in four
            self.state = "not_accepting"
            self._brake_until_s = -math.inf  # the pilot's: nothing more is sent
            return SetpointDecision(False, None, self.state, self.why)
        brake = now_s if was_sending else None
        # the pose comes with the camera's frames, so a camera that stops stops the setpoints too, telemetry or not
        # (the advice in force is about a target no longer seen); a stamp that is not a number is not a recent one
        if pose is None or not now_s - pose[0] <= self.config.pose_timeout_s:
            if was_sending:
                # a link gone quiet loses the frames' poses before its heartbeat times out: said, so that the link is
                # looked at rather than the camera (the stop stays latched under this reason)
                quiet = (
                    f" (and no autopilot heartbeat for {heartbeat_age_s:.1f} s: the MAVLink link)"
                    if heartbeat_age_s > HEARTBEAT_LATE_S
                    else ""
                )
                return self._stop(f"pose_lost: {_NO_FRAME_POSE} within guidance.pose_timeout_s{quiet}", brake)
            self.state, self.why = "waiting", _NO_FRAME_POSE
            return SetpointDecision(False, None, self.state, self.why)
        limit = self._limit(np.asarray(pose[1], float), np.asarray(pose[2], float))
        # (a vehicle that never reported a 3-D fix is positioned otherwise: its GNSS going quiet says nothing)
        had_3d_fix = gnss is not None and (gnss.has_3d_fix or gnss.fix_losses > 0)
        if not limit and gnss is not None and had_3d_fix and not now_s - gnss.received_s <= GNSS_STALE_S:
            limit = f"gnss: no GPS_RAW_INT for {now_s - gnss.received_s:.1f} s after one: its receiver may be gone"
        if not limit and gnss is not None and not gnss.has_3d_fix and gnss.fix_losses:
            # GLOBAL_POSITION_INT goes on through the outage, dead-reckoned by the autopilot: fresh, but drifting
            limit = (
                f"gnss: {gnss.fix} (fix_type {gnss.fix_type}) after a 3-D fix: the vehicle's position is dead-reckoned"
            )
        if limit:
            return self._stop(limit, brake)
        if advice is None or not now_s <= advice[0]:  # (an expiry that is not a number is no advice)
            none = f"no advice in force ({ended})" if advice is None and ended else "no advice in force"
            if self.config.accept_autopilot == MAV_AUTOPILOT_PX4:
                self.state, self.why = "holding", f"{none}: zero velocity, the stream PX4's OFFBOARD needs"
                return SetpointDecision(True, np.zeros(3), self.state, self.why)
            if self.state == "sending":
                self._brake_until_s = now_s + BRAKE_S
            self.state, self.why = "waiting", none
            if now_s < self._brake_until_s:
                self.why = f"{none}: braking"
                return SetpointDecision(True, np.zeros(3), self.state, self.why)
            return SetpointDecision(False, None, self.state, self.why)
        v = np.asarray(advice[1], dtype=float)
        if not self.config.speed_ok(v):  # the planner keeps the limits; the gate checks again, never trusts
            return self._stop("speed: the advice is outside the speed limits", brake)
        self.state, self.why = "sending", ""
        self._brake_until_s = -math.inf
        return SetpointDecision(True, v.copy(), self.state, "")

    def halt(self, now_s: float) -> SetpointDecision:
        """The daemon is stopping: zero velocity once when it was commanding the vehicle (sending, holding or
        braking), so that the vehicle does not fly the last setpoint on until the autopilot's timeout; the gate
        then latches ``stopped`` (counted once).  Not commanding: nothing sent, nothing changed."""
        if not self.config.enabled or self.state == "off":
            return SetpointDecision(False, None, "off", self.why)
        if not self._commanding(now_s):
            return SetpointDecision(False, None, self.state, self.why)
        decision = self._stop("shutdown: the daemon stopped", now_s)
        self._brake_until_s = -math.inf  # one setpoint: nothing follows a daemon that stops
        return decision

    def _commanding(self, now_s: float) -> bool:
        """Whether the vehicle is being commanded: an advice sent, or zero velocity braking or holding after one."""
        return self.state in ("sending", "holding") or now_s < self._brake_until_s
