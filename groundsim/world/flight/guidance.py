"""Guidance and control law for a multirotor following a reference path (pure; no JSBSim here).

Frames and angles follow :mod:`onboard.core.frames`: positions and velocities in local NED, body FRD,
aerospace Z-Y-X Euler angles ``(roll, pitch, yaw)`` of ``R_ned_from_body``.  The adapter
(:mod:`groundsim.world.flight.vehicle`) converts JSBSim's units before anything here sees them.

Control law (one tick every ``dt_s``, plain floats: it runs 100-250 times per simulated second)
------------------------------------------------------------------------------------------------
Outer loop, position + velocity feedback, integral action and reference feed-forward::

    a_cmd = a_ref + kp (p_ref - p) + kd (v_ref - v) + ki * integral(p_ref - p) dt

The thrust must supply what gravity and drag do not::

    f_thrust = a_cmd - g_ned - a_drag(v - wind),    a_drag(v_air) = -k_drag |v_air| v_air

The feedback part is bounded (``max_accel_mps2``) and the horizontal part of ``f_thrust`` is cut
to ``max_tilt_rad``.  Thrust acts along body -z, so with heading ``psi`` the tilt that points it
along ``f_thrust`` is (``f'`` = ``f_thrust`` rotated by ``-psi`` about down; Beard & McLain,
*Small Unmanned Aircraft*, 2012, sec. 3.2 and 14.2; Mellinger & Kumar, ICRA 2011, eq. 6-8)::

    roll  = asin(f'_y / |f|),    pitch = atan2(-f'_x, -f'_d),    specific thrust c = |f|

``psi`` is the *current* heading, not the desired one: while the heading turns, tilting for the
desired heading would point the thrust the wrong way.  The heading has its own loop::

    yaw_dot = k_yaw wrap(psi_des - psi) + psi_des_dot

Inner loop: Euler-angle errors -> Euler-angle rates (proportional, plus the rates the reference
itself needs, from differencing the feed-forward tilt along the reference), then the Euler
kinematics (Beard & McLain eq. 3.3) give FRD body-rate commands::

    p = roll_dot - yaw_dot sin(pitch)
    q = pitch_dot cos(roll) + yaw_dot sin(roll) cos(pitch)
    r = -pitch_dot sin(roll) + yaw_dot cos(roll) cos(pitch)

The body rates go to the airframe's own rate loops (the F450 SCAS), the specific thrust to the
collective throttle.  A drag model that is isotropic in the relative wind is all the feed-forward
assumes; the integral absorbs what it misses (thrust map, inflow).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from onboard.core.checks import is_positive_number, require_each
from onboard.core.errors import IrtrackError
from onboard.core.frames import (
    CameraMount,
    camera_pose_ned,
    quat_conjugate,
    quat_from_euler,
    quat_multiply,
    quat_rotate,
)

__all__ = [
    "GRAVITY_MPS2",
    "GuidanceError",
    "GuidanceGains",
    "ReferencePoint",
    "ControlCommand",
    "TrackingStats",
    "tilt_from_specific_thrust",
    "body_rates_from_euler_rates",
    "drag_accel_ned",
    "wrap_pi",
    "yaw_toward",
    "yaw_rate_toward",
    "yaw_along",
    "yaw_rate_along",
    "MulticopterController",
    "gimbal_pointing",
    "sinusoidal_pointing_error_ned_m",
]

#: standard gravity; the controller's model of it (JSBSim's own J2 gravity differs by < 0.3 %,
#: which the integral absorbs)
GRAVITY_MPS2 = 9.80665
_MIN_SPECIFIC_THRUST_MPS2 = 0.5  # never command (near) free fall: the tilt would be undefined
_MIN_YAW_DISTANCE_M = 1.0  # closer than this horizontally, a bearing is meaningless
_MIN_YAW_SPEED_MPS = 0.5


class GuidanceError(IrtrackError, ValueError):
    """Invalid guidance configuration or input; the message names the field."""


@dataclass(frozen=True)
class GuidanceGains:
    """Gains and limits of :class:`MulticopterController` (SI units, radians).

    The position loop is a critically damped second-order system of natural frequency
    ``pos_bandwidth_radps`` (``kp = w^2``, ``kd = 2 zeta w``) plus an integral whose corner is
    ``pos_integral_radps`` (``ki = kp * w_i``); it must stay well below the attitude loop
    (``att_gain_radps``), which must stay below the airframe's rate loop (~20 rad/s for F450).
    """

    pos_bandwidth_radps: float = 1.6
    pos_damping: float = 1.0
    pos_integral_radps: float = 0.25
    integral_limit_mps2: float = 2.0
    att_gain_radps: float = 7.0
    yaw_gain_radps: float = 2.5
    max_tilt_rad: float = math.radians(35.0)
    max_accel_mps2: float = 6.0
    max_rate_radps: float = 0.75
    max_yaw_rate_radps: float = 0.75

    def __post_init__(self) -> None:
        require_each(
            self,
            (
                "pos_bandwidth_radps",
                "pos_damping",
                "integral_limit_mps2",
                "att_gain_radps",
                "yaw_gain_radps",
                "max_tilt_rad",
                "max_accel_mps2",
                "max_rate_radps",
                "max_yaw_rate_radps",
            ),
            is_positive_number,
            GuidanceError,
            "GuidanceGains.{name} must be a finite number > 0, got {value!r}",
        )
        if not (math.isfinite(self.pos_integral_radps) and self.pos_integral_radps >= 0):
            raise GuidanceError(f"GuidanceGains.pos_integral_radps must be >= 0, got {self.pos_integral_radps!r}")
        if self.max_tilt_rad >= math.radians(80.0):
            raise GuidanceError(
                f"GuidanceGains.max_tilt_rad must be < 80 deg, got {math.degrees(self.max_tilt_rad):.1f} deg"
            )

    @property
    def kp(self) -> float:
        return self.pos_bandwidth_radps**2

    @property
    def kd(self) -> float:
        return 2.0 * self.pos_damping * self.pos_bandwidth_radps

    @property
    def ki(self) -> float:
        return self.kp * self.pos_integral_radps


class ReferencePoint(tuple):
    """``(p_ned_m, v_ned_mps, a_ned_mps2)``, each a 3-tuple of floats: one sample of a reference path."""

    __slots__ = ()

    def __new__(cls, p_ned_m, v_ned_mps, a_ned_mps2):
        return tuple.__new__(cls, (tuple(p_ned_m), tuple(v_ned_mps), tuple(a_ned_mps2)))

    @property
    def p_ned_m(self):
        return self[0]

    @property
    def v_ned_mps(self):
        return self[1]

    @property
    def a_ned_mps2(self):
        return self[2]


class ControlCommand(NamedTuple):
    """One controller output (a NamedTuple: built 100-250 times per simulated second).

    ``rates_frd_radps``: (p, q, r) body-rate command; ``specific_thrust_mps2``: thrust / mass;
    ``roll_rad``, ``pitch_rad``: the tilt the loop is steering to (in the current heading's
    frame), ``yaw_rad``: the heading it is turning to; ``accel_cmd_ned_mps2``: the acceleration
    the outer loop asked for.
    """

    rates_frd_radps: tuple
    specific_thrust_mps2: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    accel_cmd_ned_mps2: tuple


@dataclass(frozen=True)
class TrackingStats:
    """Distance between flown and reference positions over the control ticks so far."""

    rms_m: float
    max_m: float
    n: int


# --------------------------------------------------------------------------- pure helpers


def wrap_pi(angle_rad: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def drag_accel_ned(v_air_ned_mps, k_drag_per_m: float) -> tuple:
    """Quadratic drag acceleration ``-k |v_air| v_air`` (m/s^2), isotropic in the relative wind."""
    vn, ve, vd = v_air_ned_mps
    s = k_drag_per_m * math.sqrt(vn * vn + ve * ve + vd * vd)
    return (-s * vn, -s * ve, -s * vd)


def tilt_from_specific_thrust(f_ned_mps2, yaw_rad: float) -> tuple:
    """(roll_rad, pitch_rad, c_mps2) that point body -z along the thrust specific force ``f``.

    ``f`` is what the rotors must provide per unit mass (NED), e.g. ``(0, 0, -g)`` in hover.
    ``c = |f|``.  Raises :class:`GuidanceError` when ``f`` does not point up (|f| ~ 0 or
    downward thrust), which a multirotor cannot fly.
    """
    fn, fe, fd = f_ned_mps2
    c = math.sqrt(fn * fn + fe * fe + fd * fd)
    if not c >= _MIN_SPECIFIC_THRUST_MPS2 or fd >= 0.0:
        f = tuple(float(x) for x in f_ned_mps2)  # plain floats: a numpy scalar's repr buries the numbers
        raise GuidanceError(
            f"thrust specific force f_ned_mps2 {f!r} m/s^2 does not point up: expected a negative down component and "
            f"a magnitude of at least {_MIN_SPECIFIC_THRUST_MPS2} m/s^2"
        )
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    fx = cy * fn + sy * fe
    fy = -sy * fn + cy * fe
    roll = math.asin(max(-1.0, min(1.0, fy / c)))
    pitch = math.atan2(-fx, -fd)
    return roll, pitch, c


def body_rates_from_euler_rates(roll_rad, pitch_rad, roll_dot, pitch_dot, yaw_dot) -> tuple:
    """FRD body rates (p, q, r) from Z-Y-X Euler-angle rates (Beard & McLain 2012, eq. 3.3)."""
    sr, cr = math.sin(roll_rad), math.cos(roll_rad)
    sp, cp = math.sin(pitch_rad), math.cos(pitch_rad)
    return (
        roll_dot - yaw_dot * sp,
        pitch_dot * cr + yaw_dot * sr * cp,
        -pitch_dot * sr + yaw_dot * cr * cp,
    )


def yaw_toward(p_from_ned_m, p_to_ned_m, default_rad: float) -> float:
    """Heading (rad, from north towards east) of the horizontal line from ``p_from`` to ``p_to``.

    ``default_rad`` when the two are closer than 1 m horizontally.
    """
    dn = p_to_ned_m[0] - p_from_ned_m[0]
    de = p_to_ned_m[1] - p_from_ned_m[1]
    if dn * dn + de * de < _MIN_YAW_DISTANCE_M**2:
        return default_rad
    return math.atan2(de, dn)


def yaw_rate_toward(p_from_ned_m, v_from_ned_mps, p_to_ned_m, v_to_ned_mps) -> float:
    """Rate (rad/s) of :func:`yaw_toward`'s bearing, from the relative velocity; 0 when too close."""
    dn = p_to_ned_m[0] - p_from_ned_m[0]
    de = p_to_ned_m[1] - p_from_ned_m[1]
    r2 = dn * dn + de * de
    if r2 < _MIN_YAW_DISTANCE_M**2:
        return 0.0
    vn = v_to_ned_mps[0] - v_from_ned_mps[0]
    ve = v_to_ned_mps[1] - v_from_ned_mps[1]
    return (dn * ve - de * vn) / r2


def yaw_along(v_ned_mps, default_rad: float) -> float:
    """Heading of the horizontal velocity; ``default_rad`` below 0.5 m/s."""
    vn, ve = v_ned_mps[0], v_ned_mps[1]
    if vn * vn + ve * ve < _MIN_YAW_SPEED_MPS**2:
        return default_rad
    return math.atan2(ve, vn)


def yaw_rate_along(v_ned_mps, a_ned_mps2) -> float:
    """Rate of :func:`yaw_along`'s heading, ``(vn ae - ve an) / (vn^2 + ve^2)``; 0 below 0.5 m/s."""
    vn, ve = v_ned_mps[0], v_ned_mps[1]
    s2 = vn * vn + ve * ve
    if s2 < _MIN_YAW_SPEED_MPS**2:
        return 0.0
    return (vn * a_ned_mps2[1] - ve * a_ned_mps2[0]) / s2


# --------------------------------------------------------------------------- controller


class MulticopterController:
    """Position/attitude controller of the module docstring; one :meth:`update` per tick.

    ``k_drag_per_m``: the airframe's drag per unit mass (``a_drag = -k |v_air| v_air``);
    ``wind_ned_mps``: the constant wind the controller is told about (a crew knows it).
    State: the position-error integral only.
    """

    def __init__(self, gains: GuidanceGains, dt_s: float, k_drag_per_m: float = 0.0, wind_ned_mps=(0.0, 0.0, 0.0)):
        if not isinstance(gains, GuidanceGains):
            raise GuidanceError(f"gains must be a GuidanceGains, got {type(gains).__name__}")
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise GuidanceError(f"dt_s must be > 0, got {dt_s!r}")
        if not (math.isfinite(k_drag_per_m) and k_drag_per_m >= 0):
            raise GuidanceError(f"k_drag_per_m must be >= 0, got {k_drag_per_m!r}")
        w = tuple(float(x) for x in wind_ned_mps)
        if len(w) != 3 or not all(math.isfinite(x) for x in w):
            raise GuidanceError(f"wind_ned_mps must be 3 finite numbers, got {wind_ned_mps!r}")
        self.gains = gains
        self.dt_s = float(dt_s)
        self.k_drag_per_m = float(k_drag_per_m)
        self.wind_ned_mps = w
        self._integral = [0.0, 0.0, 0.0]
        self._kp, self._kd, self._ki = gains.kp, gains.kd, gains.ki
        self._integral_lim = gains.integral_limit_mps2 / gains.ki if gains.ki > 0 else 0.0
        self._tan_max_tilt = math.tan(gains.max_tilt_rad)
        self._ff_ref = None
        self._ff_force = (0.0, 0.0, -GRAVITY_MPS2)

    # -- feed-forward along the reference alone (no feedback): used for trim and rate feed-forward
    def feedforward_force(self, ref: ReferencePoint) -> tuple:
        """Thrust specific force (NED, m/s^2) that flies ``ref`` exactly if the vehicle were on it.

        Cached for the last reference point asked (the next tick asks for it again)."""
        if ref is self._ff_ref:
            return self._ff_force
        v, a = ref[1], ref[2]
        w = self.wind_ned_mps
        d = drag_accel_ned((v[0] - w[0], v[1] - w[1], v[2] - w[2]), self.k_drag_per_m)
        f = (a[0] - d[0], a[1] - d[1], a[2] - GRAVITY_MPS2 - d[2])
        self._ff_ref, self._ff_force = ref, f
        return f

    def feedforward_tilt(self, ref: ReferencePoint, yaw_rad: float) -> tuple:
        """(roll_rad, pitch_rad, c_mps2) that fly ``ref`` exactly if the vehicle were on it."""
        return tilt_from_specific_thrust(self.feedforward_force(ref), yaw_rad)

    def update(
        self,
        p_ned_m,
        v_ned_mps,
        roll_rad: float,
        pitch_rad: float,
        yaw_rad: float,
        ref: ReferencePoint,
        ref_next: ReferencePoint,
        yaw_des_rad: float,
        yaw_rate_ff_radps: float,
    ) -> ControlCommand:
        """One tick: state now, reference now and one tick ahead, desired yaw and its rate."""
        g = self.gains
        dt = self.dt_s
        pr, vr, ar = ref
        kp, kd, ki = self._kp, self._kd, self._ki
        integ = self._integral
        lim = self._integral_lim
        a_fb = [0.0, 0.0, 0.0]
        for i in range(3):
            ep = pr[i] - p_ned_m[i]
            if ki > 0.0:
                x = integ[i] + ep * dt
                integ[i] = lim if x > lim else (-lim if x < -lim else x)
            a_fb[i] = kp * ep + kd * (vr[i] - v_ned_mps[i]) + ki * integ[i]
        # bound the feedback, never the feed-forward
        n_fb = math.sqrt(a_fb[0] * a_fb[0] + a_fb[1] * a_fb[1] + a_fb[2] * a_fb[2])
        if n_fb > g.max_accel_mps2:
            s = g.max_accel_mps2 / n_fb
            a_fb = [x * s for x in a_fb]
        a_cmd = (ar[0] + a_fb[0], ar[1] + a_fb[1], ar[2] + a_fb[2])

        w = self.wind_ned_mps
        d = drag_accel_ned((v_ned_mps[0] - w[0], v_ned_mps[1] - w[1], v_ned_mps[2] - w[2]), self.k_drag_per_m)
        fn, fe = a_cmd[0] - d[0], a_cmd[1] - d[1]
        # tilt limit: keep the vertical component, shrink the horizontal one
        up = GRAVITY_MPS2 + d[2] - a_cmd[2]
        if up < _MIN_SPECIFIC_THRUST_MPS2:
            up = _MIN_SPECIFIC_THRUST_MPS2
        f_h = math.sqrt(fn * fn + fe * fe)
        max_h = up * self._tan_max_tilt
        if f_h > max_h:
            fn *= max_h / f_h
            fe *= max_h / f_h

        yaw_dot = g.yaw_gain_radps * wrap_pi(yaw_des_rad - yaw_rad) + yaw_rate_ff_radps
        m = g.max_yaw_rate_radps
        yaw_dot = m if yaw_dot > m else (-m if yaw_dot < -m else yaw_dot)
        # roll and pitch are taken in the *current* heading's frame: while the heading is still
        # turning toward yaw_des, tilting for yaw_des would point the thrust the wrong way
        roll_d, pitch_d, c = tilt_from_specific_thrust((fn, fe, -up), yaw_rad)

        # rates the reference itself needs (tilt along the reference, one tick ahead, as the
        # heading turns at the commanded rate)
        roll_0, pitch_0, _ = tilt_from_specific_thrust(self.feedforward_force(ref), yaw_rad)
        roll_1, pitch_1, _ = tilt_from_specific_thrust(self.feedforward_force(ref_next), yaw_rad + yaw_dot * dt)
        k_att = g.att_gain_radps
        roll_dot = k_att * (roll_d - roll_rad) + (roll_1 - roll_0) / dt
        pitch_dot = k_att * (pitch_d - pitch_rad) + (pitch_1 - pitch_0) / dt
        p, q, r = body_rates_from_euler_rates(roll_rad, pitch_rad, roll_dot, pitch_dot, yaw_dot)
        m = g.max_rate_radps
        rates = (
            m if p > m else (-m if p < -m else p),
            m if q > m else (-m if q < -m else q),
            m if r > m else (-m if r < -m else r),
        )
        return ControlCommand(rates, c, roll_d, pitch_d, yaw_des_rad, a_cmd)


# --------------------------------------------------------------------------- optional gimbal


def gimbal_pointing(p_body_ned_m, q_ned_from_body, mount: CameraMount, aim_ned_m) -> np.ndarray:
    """``q_mount_from_gimbal`` (..., 4) that puts the optical axis on ``aim_ned_m``.

    A two-axis pan/tilt gimbal: pan about the mount's z (down) axis, then tilt about the panned
    y axis, ``q_mount_from_gimbal = quat_from_euler(0, tilt, pan)`` (tilt > 0 looks up).  The
    camera centre is the mount's lever arm (see :func:`onboard.core.frames.camera_pose_ned`); with
    the result, ``camera_pose_ned(p, q, mount, q_mount_from_gimbal)`` looks exactly at the aim
    point.  Vectorised over a leading axis.
    """
    q_nb = np.asarray(q_ned_from_body, dtype=float)
    p_cam, _ = camera_pose_ned(p_body_ned_m, q_nb, mount)
    q_nm = np.asarray(mount.q_body_from_mount, dtype=float)
    q_ned_from_mount = quat_multiply(q_nb, q_nm)
    d_mount = quat_rotate(quat_conjugate(q_ned_from_mount), np.asarray(aim_ned_m, dtype=float) - p_cam)
    pan = np.arctan2(d_mount[..., 1], d_mount[..., 0])
    tilt = np.arctan2(-d_mount[..., 2], np.hypot(d_mount[..., 0], d_mount[..., 1]))
    return quat_from_euler(np.zeros_like(pan), tilt, pan)


def sinusoidal_pointing_error_ned_m(t_s, range_m, frac_of_range, period_s, phase_rad) -> np.ndarray:
    """The reference study's slowly varying gimbal error (``groundsim.world.scenario.GimbalSpec``).

    Per NED axis ``i``: ``frac_of_range[i] * range_m * sin(2 pi t / period_s[i] + phase_rad[i])``
    metres, added to the target position to get the aim point.  Shape ``t_s.shape + (3,)``.
    """
    t = np.asarray(t_s, dtype=float)[..., None]
    rng = np.asarray(range_m, dtype=float)[..., None]
    frac, period, phase = (np.asarray(x, dtype=float).reshape(3) for x in (frac_of_range, period_s, phase_rad))
    if np.any(period <= 0) or not np.all(np.isfinite(period)):
        raise GuidanceError(f"period_s must be 3 finite numbers > 0, got {period_s!r}")
    return frac * rng * np.sin(2.0 * np.pi * t / period + phase)
