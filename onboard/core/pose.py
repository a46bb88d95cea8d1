"""Vehicle and camera pose on the autopilot's boot clock: the pose buffer and its settings.

Pure core: no pymavlink, no sockets, no threads.  The MAVLink adapter (:mod:`onboard.io.mavlink_link`)
translates wire messages once and calls the ``add_*`` methods; the lockstep evaluation calls them
directly from truth.  Frame conventions are those of :mod:`onboard.core.frames` (local NED, body FRD,
``q_a_from_b`` Hamilton, w first); every time here is ``time_boot_us``, integer microseconds on the
autopilot's boot clock (MAVLink ``time_boot_ms * 1000``).  The nouns it makes and answers with
(:class:`~onboard.core.pose_types.PoseSample`, :class:`~onboard.core.pose_types.PoseAt`,
:class:`~onboard.core.pose_types.PoseLookup`) are in :mod:`onboard.core.pose_types`; the clock mapping
that puts camera frames on the boot clock is :mod:`onboard.core.clock_sync`.

:class:`PoseBuffer`
    Two (three with a gimbal) bounded streams, because attitude (MAVLink #31) and position (#33)
    arrive at different rates and times.  A query at a frame's capture time interpolates between
    the two samples that bracket it -- position by cubic Hermite on (p, v) (linear when a velocity
    is unknown), attitude by SLERP -- and never falls back to "latest sample".  A query outside a
    stream, or whose bracket is wider than the stream's ``max_gap``, gets ``None`` and a reason.

Interpolation
-------------
With ``s = (t - t0) / (t1 - t0)`` and ``dt = t1 - t0`` (s), the cubic Hermite position is
``p(s) = h00 p0 + h10 dt v0 + h01 p1 + h11 dt v1`` with ``h00 = 2s^3 - 3s^2 + 1``,
``h10 = s^3 - 2s^2 + s``, ``h01 = -2s^3 + 3s^2``, ``h11 = s^3 - s^2`` (exact for any cubic
trajectory).  Its departure from the chord is ``dt * (h10 (v0 - m) + h11 (v1 - m))`` with
``m = (p1 - p0) / dt``, bounded by ``4/27 * dt * (|v0 - m| + |v1 - m|)``; so a wrong velocity can
move the answer by at most that much.  Velocity: the reported velocities interpolated linearly
(the chord slope when one is unknown).  Attitude: ``quat_slerp(q0, q1, s)`` (Shoemake 1985).

Extrapolation (a frame newer than the telemetry)
------------------------------------------------
A frame's pose must not wait for the sample after it: the wait adds latency, and a wait short enough to
keep the latency low still leaves many gimballed frames without a bracket.  (The objects image chain waits for
the attitude sample after its frame before it registers the frame, ``imaging.pose_wait_ms``: its registration
error is the rotation's, and an extrapolated attitude's noise dominates it; the 3-D's pose does not wait.)  :meth:`PoseBuffer.pose_at` (not :meth:`~PoseBuffer.lookup`,
which stays interpolation-only so that a caller can wait for a bracket) extrapolates from the
newest sample ``h = t - t_last`` ahead, within a bounded horizon per stream:

* attitude with the reported body rates (ATTITUDE_QUATERNION #31 ``rollspeed, pitchspeed,
  yawspeed`` = ``omega_frd_rps``, body FRD): ``q(t) = q_last (x) Exp(omega_frd h)`` (a body-frame
  rate multiplies on the right; exact for a constant body rate);
* position with the reported velocity (#33 ``vx, vy, vz``): ``p(t) = p_last + v_last h``;
* gimbal (#285) with its reported angular velocity (a vector in the quaternion's reference frame,
  so ``q(t) = Exp(omega_ref h) (x) q_last``) or, when the gimbal reports NaN, the rate of a
  least-squares fit through the samples of the last ``gimbal_rate_window_us``, anchored at the
  newest one.

No rate (or velocity) known: no extrapolation, the miss stays ``<stream>_not_yet``.  Beyond the
horizon: no pose, reason ``<stream>_extrapolation_limit``.  Every extrapolated pose is counted as
``pose_extrapolated`` (logged at DEBUG only: it is a normal event) and says so in
:attr:`PoseAt.mode` and the ``*_extrapolated_us`` horizons.

Dead reckoning.  Position alone goes on past that horizon, through a gap in the position stream (a
GNSS dropout: no #33 while attitude continues), for up to ``pose.dead_reckoning_max_s``, with the
same formula and the same growing sigma: seconds of it add metres, which the pose says
(:attr:`PoseAt.sigma_extrapolation_m`) and the frame pipeline carries into the 3-D estimate as
camera-position noise instead of adding such a pose to the estimator's window.  The line of sight
needs attitude only and stays exact.

Added uncertainty (1 sigma, per axis).  Attitude: ``sigma_rad(h) = sqrt((sigma_w h)^2 +
(sigma_alpha h^2 / 2)^2)`` -- the rate's error over the horizon and an unmodelled angular
acceleration; position: ``sigma_m(h) = sqrt((sigma_v h)^2 + (sigma_a h^2 / 2)^2)``.  The
estimator's noise model is not widened per observation (the estimator is not this module's);
instead the horizon is *bounded* so that the added attitude sigma stays below a stated fraction of
the bearing white noise the estimator is configured with, ``sqrt(attitude_white^2 +
(pixel_sigma / f)^2)`` (:func:`~onboard.core.pose_config.attitude_horizon_us`; ``pose.extrapolation_noise_fraction``, 0.25:
the total sigma grows by at most ``sqrt(1 + 0.25^2) - 1 = 3 %``).  With the shipped
``config/onboard.yaml`` (0.05 deg white attitude, 0.3 px at f = 764.7 px: bearing white noise
0.0548 deg; limit 0.0137 deg) and the assumed rate errors -- body rates 0.1 deg/s (a MEMS gyro after
the autopilot's filter), gimbal rates 0.5 deg/s (reported, or the 100 ms least-squares fit of
0.05 deg-noisy samples at 50 Hz: 0.46 deg/s), unmodelled angular acceleration 20 deg/s^2 -- the
horizons come out at 36 ms (attitude) and 25 ms (gimbal); at the ~15 ms a frame actually needs
with 50 Hz telemetry and a 5 ms wait, the attitude adds 0.0027 deg (5 % of the white noise).
Position: ``pose.max_extrapolation_ms`` (50 ms) bounds it; with 0.1 m/s velocity error and
2 m/s^2 unmodelled acceleration it adds 5.6 mm at 50 ms, i.e. 0.0032 deg of bearing at 100 m
(6 % of the white noise; 25 Hz #33 needs up to ~40 ms).  :attr:`PoseAt.sigma_extrapolation_rad` and
:attr:`PoseAt.sigma_extrapolation_m` carry the figures of each pose, should the estimator want
to weight by them.

Rejection reasons (keys of :attr:`~onboard.core.counters.RejectCounter.counts`)
------------------------------------------------------------------------------
Per stream, prefixed ``attitude_``, ``position_`` or ``gimbal_``: ``time_invalid``, ``duplicate``
(same time again), ``out_of_order`` (earlier by less than the reboot threshold), ``not_finite``,
``shape``; quaternions also ``zero``, ``not_unit``.  Position also ``zero`` (lat = lon = 0: GPS
dropout), ``out_of_range`` (e.g. INT32_MAX sentinels), ``alt_out_of_range``, ``jump`` (implied speed
above ``max_speed_mps``, or a step the reported velocity does not explain: ``max_position_step_m``), ``reset``
(a jump persisted: the stream restarts), ``velocity_invalid``
(not three finite numbers, or a speed above ``max_speed_mps``: sample kept, velocity dropped), ``no_origin``.
Gimbal also ``time_reset``, ``reference_changed``, ``reference_invalid``.  ``reboot``: time went back by more than the threshold on the attitude or
position stream (all buffers cleared).  :meth:`PoseBuffer.pose_at` counts a miss as ``pose_<reason>``
with reason ``time_invalid``, ``no_origin`` or
``<stream>_empty|before_buffer|not_yet|gap|extrapolation_limit``; an extrapolated pose is counted as
``pose_extrapolated``; a time looked up again at once with the same outcome (a frame's image chain, then the frame)
is counted once.

Discontinuities
---------------
A reboot breaks the boot clock; a position ``reset`` (a GNSS jump or a reset of the
autopilot's position estimate, persisting for ``jump_reset_count`` samples) breaks the camera's position
track: the positions after it are tens of metres to kilometres off the ones before, on the same clock.  An
``attitude_reset`` or ``gimbal_reset`` (a sample turned :data:`ATTITUDE_STEP_RAD` beyond what the reported rates
allow: the autopilot's attitude estimate reset, e.g. an EKF yaw reset, which an earth-frame gimbal report follows)
breaks its pointing alike; that stream starts again from the new sample.
Either raises :attr:`PoseBuffer.discontinuities`, which every :class:`PoseAt` carries.  Rows of a 3-D
estimate made on both sides of a break would place the target by a camera track that never was, with the
confidence of a consistent one: the frame pipeline starts its estimate again when the count changes.

Limits: ``time_boot_ms`` is uint32 and wraps after 49.7 days; a wrap looks like a reboot.
"""

from __future__ import annotations

import bisect
import enum
import logging
import math
from collections.abc import Callable

import numpy as np

from onboard.core.counters import RejectCounter
from onboard.core.errors import InputError
from onboard.core.frames import (
    Q_MOUNT_FROM_CAM,
    QUAT_NORM_TOL,
    CameraMount,
    FrameError,
    GeodeticOrigin,
    Quat,
    check_unit_quat,
    euler_from_quat,
    ned_from_geodetic,
    q_ned_from_level1,
    quat_conjugate1,
    quat_from_euler,
    quat_from_rotvec1,
    quat_multiply1,
    quat_normalize1,
    quat_rotate,
    quat_slerp1,
    rotvec_from_quat1,
)
from onboard.core.pose_config import PoseConfig, extrapolation_sigma, position_step_check
from onboard.core.pose_types import PoseAt, PoseLookup, PoseSample, check_time_us
from onboard.core.sample_stream import SampleStream

__all__ = [
    "GimbalReference",
    "PoseBuffer",
]

log = logging.getLogger(__name__)

US_PER_S = 1_000_000
ZERO_QUAT_NORM = 1e-6  # a quaternion shorter than this is "zero", not merely "not unit"


# --------------------------------------------------------------------------- float paths
# The buffer handles one message (4 or 3 numbers) or one frame at a time, where numpy's per-call
# overhead cost more than the arithmetic (an ATTITUDE_QUATERNION took longer to validate than pymavlink
# took to parse it).  The common case runs on Python floats; anything unusual goes to the numpy code,
# which alone decides rejections (same counters, same messages).  The quaternions go through the float
# kernels of onboard.core.frames' single-quaternion paths (``quat_*1``): the same bits
# (tests/onboard/test_pose_fast_paths.py checks the look-up against the numpy formulation).

_F64 = np.dtype(float)
_NAN3 = (math.nan, math.nan, math.nan)
_IDENTITY = (1.0, 0.0, 0.0, 0.0)

Vec3 = tuple[float, float, float]
_Q_MOUNT_FROM_CAM = tuple(Q_MOUNT_FROM_CAM.tolist())


def _plain_floats(v, n: int):
    """``v`` when it is a tuple or list of ``n`` Python floats, its items when it is a float64 array of
    shape (n,); else None (the numpy path then judges it)."""
    tv = type(v)
    if tv is tuple or tv is list:
        if len(v) != n:
            return None
        for c in v:
            if type(c) is not float:
                return None
        return v
    if tv is np.ndarray and v.shape == (n,) and v.dtype == _F64:
        return v.tolist()
    return None


def _rotate1(q, v) -> Vec3:
    """``R(q) v`` of one unit quaternion and one vector, in floats: ``v + 2 w (u x v) + 2 u x (u x v)``."""
    w, x, y, z = q
    a, b, c = v
    tx, ty, tz = 2.0 * (y * c - z * b), 2.0 * (z * a - x * c), 2.0 * (x * b - y * a)
    return (a + w * tx + (y * tz - z * ty), b + w * ty + (z * tx - x * tz), c + w * tz + (x * ty - y * tx))


def _finite_from(row: np.ndarray, k: int) -> bool:
    """All of ``row[k:]`` finite."""
    for c in row[k:].tolist():
        if not math.isfinite(c):
            return False
    return True


class GimbalReference(str, enum.Enum):
    """What a gimbal quaternion is relative to.

    ``MOUNT``: the pod mount frame (``q_mount_from_gimbal``).  ``VEHICLE``: MAVLink gimbal v2
    "vehicle frame" -- the local level turned by the vehicle's heading (roll and pitch relative to the
    horizon, yaw relative to the nose).  ``EARTH``: the local level ("yaw in earth frame"), as the
    autopilot's attitude (:mod:`onboard.core.frames`).
    """

    MOUNT = "mount"
    VEHICLE = "vehicle"
    EARTH = "earth"


#: samples kept per stream at most (besides the window)
MAX_SAMPLES = 4096
#: an attitude sample turned this much beyond what its reported rates allow is a reset of the attitude estimate,
#: far above the rates' own error over a telemetry interval
ATTITUDE_STEP_RAD = math.radians(10.0)
#: the turn rate allowed a gimbal sample whose rates are unknown (#285 may send NaN): a fast slew (rad/s)
MAX_TURN_RPS = 2.0 * math.pi
#: consecutive far-off stamps that agree with each other: a clock step, not an outlier
TIME_CONFIRM_COUNT = 3
#: misses of pose before the first one served are the start-up's (INFO) for this long of frame time (from the earliest
#: stamp looked up), then faults
STARTUP_S = 5.0
#: a position outside these altitudes (AMSL, m) is refused (``position_alt_out_of_range``)
MIN_ALT_M, MAX_ALT_M = -1_000.0, 50_000.0
#: gimbal samples that feed the rate fit when the gimbal reports no rate (us)
GIMBAL_RATE_WINDOW_US = 100_000


# --------------------------------------------------------------------------- pose buffer

_AFTER = "after"  # bracket marker: the time is past the newest sample (extrapolate from it)


class PoseBuffer:
    """Attitude, position and gimbal streams on the boot clock; interpolated pose at any covered time.

    ``mount``: the pod mount from the config (a gimballed mount makes the gimbal stream mandatory).
    ``origin``: the local NED origin; None fixes it at the first valid position.  ``counter``: where
    rejections are counted (shared with the adapter).  ``add_*`` return True when the sample was
    stored; rejected samples are counted, never raised.
    """

    def __init__(
        self,
        mount: CameraMount | None = None,
        config: PoseConfig | None = None,
        origin: GeodeticOrigin | None = None,
        counter: RejectCounter | None = None,
        *,
        bearing_white_sigma_rad: float | None = None,
    ) -> None:
        self.mount = mount if mount is not None else CameraMount()
        self.config = config if config is not None else PoseConfig()
        #: how far past its newest sample each stream is extrapolated (``bearing_white_sigma_rad``: see
        #: :meth:`PoseConfig.extrapolation_horizons`)
        self.horizons = self.config.extrapolation_horizons(bearing_white_sigma_rad)
        self.counter = counter if counter is not None else RejectCounter()
        self._configured_origin = origin
        self._origin = origin
        c = self.config
        self._att = SampleStream("attitude", c.att_max_gap_us)
        self._pos = SampleStream("position", c.pos_max_gap_us)
        self._gim = SampleStream("gimbal", c.gimbal_max_gap_us)
        self._gim_ref: GimbalReference | None = None
        self._mount_cache: tuple[CameraMount, Vec3, Quat, Quat] | None = None
        self._jumps = 0
        self._refused: tuple[int, np.ndarray] | None = None  # the newest refused position (t, p and v)
        self.reboots = 0
        self.position_resets = 0  # position streams restarted after a persisting jump (``position_reset``)
        self.attitude_resets = 0  # attitude or gimbal steps the reported rates cannot explain (``<stream>_reset``)
        self.last_miss_reason: str | None = None
        self._counted_at: tuple[int, str | None] | None = None  # the latest (time, outcome) pose_at counted
        # The streams arrive one after the other when the link comes up (the gimbal's first report, with
        # no rate to extrapolate by, can trail the first frames): a miss before the first pose served is the
        # start-up's, not a fault, and is logged at INFO; the status counts it all the same.  Only for its first
        # STARTUP_S of frame time: a camera whose stamps never get a pose (stamped ahead of the telemetry) is a fault,
        # not a start-up that lasts the whole flight.
        self.served_pose = False
        self._first_lookup_us: int | None = None

    # ------------------------------------------------------------------ state

    @property
    def origin(self) -> GeodeticOrigin | None:
        return self._origin

    @property
    def epoch(self) -> int:
        return self.reboots

    @property
    def discontinuities(self) -> int:
        """Breaks in the camera's pose track so far: reboots, position and attitude resets (module docstring)."""
        return self.reboots + self.position_resets + self.attitude_resets

    def newest_time_boot_us(self) -> int | None:
        """Latest time covered by both attitude and position, or None."""
        if not self._att.t_us or not self._pos.t_us:
            return None
        return min(self._att.t_us[-1], self._pos.t_us[-1])

    def newest_rotation_time_boot_us(self) -> int | None:
        """Latest time covered by the streams the camera's rotation is made of (attitude, and the gimbal's on a
        gimballed mount), or None: a rotation looked up at or before it is interpolated, whatever the position."""
        if not self._att.t_us or (self.mount.gimballed and not self._gim.t_us):
            return None
        return min(self._att.t_us[-1], self._gim.t_us[-1]) if self.mount.gimballed else self._att.t_us[-1]

    def sizes(self) -> dict[str, int]:
        return {"attitude": len(self._att.t_us), "position": len(self._pos.t_us), "gimbal": len(self._gim.t_us)}

    def clear(self) -> None:
        """Drop all samples (the origin stays)."""
        for s in (self._att, self._pos, self._gim):
            s.clear()
        self._jumps = 0
        self._refused = None

    # ------------------------------------------------------------------ time checks

    def _time(self, stream: str, t) -> int | None:
        if type(t) is int and t >= 0:  # the common case, without the checker's isinstance tests
            return t
        try:
            return check_time_us(t, f"{stream}.time_boot_us")
        except InputError as exc:
            self.counter.count(f"{stream}_time_invalid", str(exc))
            return None

    def _admit(self, s: SampleStream, t: int) -> bool:
        """Ordering and outlier check (see :class:`PoseConfig` ``reboot_threshold_s``); detects
        reboots and clock steps.  Mutates only the pending run, and on a confirmed reboot / step."""
        last = s.last_t
        thr = self.config.reboot_threshold_us
        if last is None or last < t <= last + thr:
            s.pending_t_us.clear()
            return True
        if t == last:
            self.counter.count(f"{s.name}_duplicate", f"time_boot_us={t} repeated")
            return False
        if last - thr <= t < last:
            self.counter.count(f"{s.name}_out_of_order", f"time_boot_us={t} is {last - t} us before {last}")
            return False
        if t > last and self._agrees_with_other_streams(s, t):
            # a stream that was silent (a GNSS dropout) resumes on the clock the others run on: not an outlier
            s.pending_t_us.clear()
            self.counter.count(
                f"{s.name}_resumed", f"after {(t - last) / US_PER_S:.3f} s without samples", level=logging.INFO
            )
            return True
        run = s.pending_t_us
        if run and run[-1] < t <= run[-1] + thr:
            run.append(t)
        else:
            run[:] = [t]
        if len(run) < TIME_CONFIRM_COUNT:
            self.counter.count(
                f"{s.name}_time_outlier",
                f"time_boot_us={t} is {(t - last) / US_PER_S:+.3f} s from the stream's newest {last}",
            )
            return False
        run.clear()
        if t > last:
            self.counter.count(
                f"{s.name}_time_step",
                f"time_boot_us stepped {(t - last) / US_PER_S:+.3f} s ({last} -> {t})",
                level=logging.INFO,
            )
            return True
        if s is self._gim:
            s.clear()
            self.counter.count("gimbal_time_reset", f"gimbal time went back {last - t} us; gimbal stream restarted")
            return True
        self._reboot(
            f"{s.name} time_boot_us went back {last - t} us ({last} -> {t}), confirmed by {TIME_CONFIRM_COUNT} samples"
        )
        return True

    def _agrees_with_other_streams(self, s: SampleStream, t: int) -> bool:
        """``t`` is within the reboot threshold of the newest sample of another attitude/position stream."""
        thr = self.config.reboot_threshold_us
        for other in (self._att, self._pos):
            if other is not s and other.last_t is not None and abs(t - other.last_t) <= thr:
                return True
        return False

    def _reboot(self, detail: str) -> None:
        self.clear()
        self.reboots += 1
        if not self.config.keep_origin_on_reboot:
            self._origin = self._configured_origin
        self.counter.count("reboot", detail + "; pose buffers cleared")

    # ------------------------------------------------------------------ inputs

    def _quat(self, stream: str, q) -> Quat | None:
        """The unit quaternion (normalised, w >= 0) or None (counted).  Fast path: 4 floats whose norm is
        within ``QUAT_NORM_TOL`` of 1 (so finite and not zero), normalised as :func:`check_unit_quat` does."""
        f = _plain_floats(q, 4)
        if f is not None:
            w, x, y, z = f
            n1 = math.sqrt(w * w + x * x + y * y + z * z)
            if abs(n1 - 1.0) <= QUAT_NORM_TOL:  # False for NaN
                return quat_normalize1(f)
        try:
            a = np.asarray(q, dtype=float)
        except (TypeError, ValueError):
            self.counter.count(f"{stream}_shape", f"quaternion {q!r} is not 4 numbers")
            return None
        if a.shape != (4,):
            self.counter.count(f"{stream}_shape", f"quaternion shape {a.shape}, expected (4,)")
            return None
        if not np.all(np.isfinite(a)):
            self.counter.count(f"{stream}_not_finite", f"quaternion {a.tolist()}")
            return None
        if np.linalg.norm(a) < ZERO_QUAT_NORM:
            self.counter.count(f"{stream}_zero", "zero quaternion")
            return None
        try:
            qw, qx, qy, qz = check_unit_quat(a, f"{stream} quaternion").tolist()
            return (qw, qx, qy, qz)
        except FrameError as exc:
            self.counter.count(f"{stream}_not_unit", str(exc))
            return None

    def _rates(self, stream: str, omega_rps) -> list[float]:
        """3 angular velocity components, NaN when unknown or invalid (counted as ``<stream>_rate_invalid``)."""
        if omega_rps is None:
            return list(_NAN3)
        f = _plain_floats(omega_rps, 3)
        if f is not None and (
            (math.isfinite(f[0]) and math.isfinite(f[1]) and math.isfinite(f[2]))
            or (math.isnan(f[0]) and math.isnan(f[1]) and math.isnan(f[2]))  # unknown (the gimbal's NaN)
        ):
            return list(f)
        try:
            w = np.array(omega_rps, dtype=float).reshape(3)
        except (TypeError, ValueError):
            self.counter.count(f"{stream}_rate_invalid", f"angular velocity {omega_rps!r} is not 3 numbers; dropped")
            return list(_NAN3)
        if np.any(np.isinf(w)) or (np.any(np.isnan(w)) and not np.all(np.isnan(w))):
            self.counter.count(f"{stream}_rate_invalid", f"angular velocity {w.tolist()}; dropped")
            return list(_NAN3)
        return w.tolist()

    def add_attitude(self, time_boot_us: int, q_ned_from_body, omega_frd_rps=None) -> bool:
        """Store ``q_ned_from_body`` (w, x, y, z) at ``time_boot_us`` and the body rates
        ``omega_frd_rps`` (3,; body FRD, rad/s; None or NaN = unknown: no extrapolation).

        The attitude is relative to the local level where the vehicle is, as an autopilot's
        (:mod:`onboard.core.frames`); a look-up turns it into the origin's NED with the rotation of the position
        sample it is paired with (the identity for :meth:`add_position_ned`'s flat world)."""
        t = self._time("attitude", time_boot_us)
        if t is None:
            return False
        q = self._quat("attitude", q_ned_from_body)
        if q is None:
            return False
        w = self._rates("attitude", omega_frd_rps)
        if not self._admit(self._att, t):
            return False
        self._attitude_step(self._att, t, q, w, None)  # the autopilot reports its rates with its attitude
        self._att.append(t, np.array((*q, *w)), self.config.window_us, MAX_SAMPLES)
        return True

    def add_position(self, time_boot_us: int, lat_deg: float, lon_deg: float, alt_m: float, v_ned_mps=None) -> bool:
        """Store a WGS84 position (alt treated as ellipsoidal, see frames) and its velocity (None = unknown) in
        the local level there, as GLOBAL_POSITION_INT's: both kept in the origin's NED, with the rotation from the
        local level (:func:`~onboard.core.frames.q_ned_from_level1`) that the attitudes paired with it take."""
        t = self._time("position", time_boot_us)
        if t is None:
            return False
        try:
            lat, lon, alt = float(lat_deg), float(lon_deg), float(alt_m)
        except (TypeError, ValueError):
            self.counter.count("position_not_finite", f"lat/lon/alt not numbers: {lat_deg!r}, {lon_deg!r}, {alt_m!r}")
            return False
        if not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(alt)):
            self.counter.count("position_not_finite", f"lat={lat} lon={lon} alt={alt}")
            return False
        if lat == 0.0 and lon == 0.0:
            self.counter.count("position_zero", "lat = lon = 0 (GPS dropout)")
            return False
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            self.counter.count("position_out_of_range", f"lat={lat} lon={lon} deg")
            return False
        if not (MIN_ALT_M <= alt <= MAX_ALT_M):
            self.counter.count("position_alt_out_of_range", f"alt={alt} m")
            return False
        v = self._velocity(v_ned_mps)
        if not self._admit(self._pos, t):  # first: a reboot may reset the origin
            return False
        if self._origin is None:  # the position stream is empty whenever the origin is unset
            self._origin = GeodeticOrigin(lat, lon, alt)
            log.info("local NED origin fixed at the first valid position: %s", self._origin)
        q_lv = q_ned_from_level1(lat, lon, self._origin)
        if math.isfinite(v[0]):  # _velocity gives three finite numbers or three NaN
            v = list(_rotate1(q_lv, v))
        # numpy's one-point conversion, kept: its 3 x 3 product may fuse multiply-adds, which floats
        # cannot repeat bit for bit, and at 25 Hz it costs ~2 us more than floats would
        return self._store_position(t, ned_from_geodetic(lat, lon, alt, self._origin).tolist(), v, q_lv)

    def add_position_ned(self, time_boot_us: int, p_ned_m, v_ned_mps=None) -> bool:
        """Store a local NED position and velocity (needs an origin: configured or fixed by an earlier geodetic
        sample).  A flat world: the attitudes paired with it are taken in the origin's NED as they are."""
        t = self._time("position", time_boot_us)
        if t is None:
            return False
        if self._origin is None:
            self.counter.count("position_no_origin", "add_position_ned needs a configured origin")
            return False
        p = _plain_floats(p_ned_m, 3)
        if p is None or not (math.isfinite(p[0]) and math.isfinite(p[1]) and math.isfinite(p[2])):
            try:
                a = np.asarray(p_ned_m, dtype=float).reshape(3)
            except (TypeError, ValueError):
                self.counter.count("position_shape", f"p_ned_m {p_ned_m!r} is not 3 numbers")
                return False
            if not np.all(np.isfinite(a)):
                self.counter.count("position_not_finite", f"p_ned_m={a.tolist()}")
                return False
            p = a.tolist()
        v = self._velocity(v_ned_mps)
        if not self._admit(self._pos, t):
            return False
        return self._store_position(t, p, v, _IDENTITY)

    def _velocity(self, v_ned_mps) -> list[float]:
        """3 velocity components, NaN when unknown or invalid (counted; the position is still used).  A speed the
        positions themselves may not have (``max_speed_mps``) is invalid too: interpolation and extrapolation would
        move the camera by it."""
        if v_ned_mps is None:
            return list(_NAN3)
        f = _plain_floats(v_ned_mps, 3)
        if f is not None and math.isfinite(f[0]) and math.isfinite(f[1]) and math.isfinite(f[2]):
            return self._plausible(list(f))
        try:
            v = np.array(v_ned_mps, dtype=float).reshape(3)
        except (TypeError, ValueError):
            self.counter.count("position_velocity_invalid", f"v_ned_mps={v_ned_mps!r}; velocity dropped")
            return list(_NAN3)
        if not np.all(np.isfinite(v)):
            self.counter.count("position_velocity_invalid", f"v_ned_mps={v.tolist()}; velocity dropped")
            return list(_NAN3)
        return self._plausible(v.tolist())

    def _plausible(self, v: list[float]) -> list[float]:
        speed = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
        if speed <= self.config.max_speed_mps:
            return v
        self.counter.count(
            "position_velocity_invalid",
            f"speed {speed:.1f} m/s above pose.max_speed_mps {self.config.max_speed_mps:g}; velocity dropped",
        )
        return list(_NAN3)

    def _store_position(self, t: int, p, v, q_lv) -> bool:
        """Store ``p`` (3 floats, NED m), ``v`` (3 floats) and ``q_lv`` (``q_ned_from_level`` there, 4 floats) unless
        ``p`` is a jump from the newest position: faster than ``max_speed_mps``, or :meth:`_velocity_miss`."""
        if self._pos.t_us:
            t_last = self._pos.t_us[-1]
            dt_s = (t - t_last) / US_PER_S
            last = self._pos.values[-1]
            n0, e0, d0 = last[:3].tolist()
            dn, de, dd = p[0] - n0, p[1] - e0, p[2] - d0
            step_m = math.sqrt(dn * dn + de * de + dd * dd)
            limit_m = self.config.max_speed_mps * dt_s
            if step_m > limit_m * (1.0 - 1e-9):  # a jump, or near enough that numpy's norm must decide
                step_m = float(np.linalg.norm(np.array(p) - last[:3]))
            jump = (
                f"{step_m:.1f} m in {dt_s * 1e3:.0f} ms"
                if step_m > limit_m
                else self._velocity_miss(last, t_last, p, v, t)
            )
            refused = self._refused
            if jump is None and self._jumps and refused is not None and refused[0] < t:
                # each refusal widens the interval to the newest kept sample, and the tolerances with it: a sample
                # going on from the refused ones is the displaced track persisting, not the old one coming back
                check = self._velocity_check(refused[1], refused[0], p, v, t)
                if check is not None and check[0] <= check[1]:
                    jump = "on from the refused positions"
            if jump is not None:
                self._refused = (t, np.array((*p, *v)))
                self._jumps += 1
                if self._jumps < self.config.jump_reset_count:
                    self.counter.count("position_jump", jump)
                    return False
                self.position_resets += 1
                self.counter.count(
                    "position_reset",
                    f"{self._jumps} consecutive jumps ({jump}); position stream restarted "
                    f"(pose discontinuity {self.discontinuities}: 3-D estimates start again)",
                )
                self._pos.clear()
        self._jumps = 0
        self._refused = None
        self._pos.append(t, np.array((*p, *v, *q_lv)), self.config.window_us, MAX_SAMPLES)
        return True

    def _velocity_miss(self, last: np.ndarray, t_last: int, p, v, t: int) -> str | None:
        """Why ``p`` (at ``t``) is a jump from ``last`` (a sample's row, at ``t_last``) though no faster than
        ``max_speed_mps`` (farther than :meth:`_velocity_check` allows), or None.  An autopilot reports its estimate's position
        and velocity together, so a reset of that estimate (a GNSS jump, a switch of receiver) is a position step its
        velocity does not share, which the speed test alone takes for motion.  Not judged past a position bracket (a
        gap: the speed test alone)."""
        if t - t_last > self.config.pos_max_gap_us:
            return None
        check = self._velocity_check(last, t_last, p, v, t)
        if check is None or check[0] <= check[1]:
            return None
        return f"{check[0]:.1f} m off where the reported velocity puts it after {(t - t_last) / 1e3:.0f} ms"

    def _velocity_check(self, last: np.ndarray, t_last: int, p, v, t: int) -> tuple[float, float] | None:
        """:func:`~onboard.core.pose_config.position_step_check` of ``p``, ``v`` at ``t``: ``last``'s row at ``t_last``."""
        last_p, last_v = last[:3].tolist(), last[3:6].tolist()
        return position_step_check(self.config, (t - t_last) / US_PER_S, last_p, last_v, p, v)

    def add_gimbal(self, time_boot_us: int, q_mount_from_gimbal) -> bool:
        """Store the gimbal attitude relative to the pod mount."""
        return self.add_gimbal_status(time_boot_us, q_mount_from_gimbal, GimbalReference.MOUNT)

    def add_gimbal_status(
        self, time_boot_us: int, q_ref_from_gimbal, reference: GimbalReference, omega_ref_rps=None
    ) -> bool:
        """Store a gimbal attitude relative to ``reference`` (see :class:`GimbalReference`) and its
        angular velocity ``omega_ref_rps`` (3,; rad/s, a vector in the reference frame as #285
        defines it; None or NaN = unknown: extrapolation fits a rate to recent samples).

        The stream holds one reference at a time; a change of reference restarts it.
        """
        t = self._time("gimbal", time_boot_us)
        if t is None:
            return False
        try:
            ref = reference if type(reference) is GimbalReference else GimbalReference(reference)
        except ValueError:
            self.counter.count("gimbal_reference_invalid", f"reference {reference!r}")
            return False
        q = self._quat("gimbal", q_ref_from_gimbal)
        if q is None:
            return False
        w = self._rates("gimbal", omega_ref_rps)
        if ref != self._gim_ref:
            if self._gim.t_us:
                self.counter.count("gimbal_reference_changed", f"{self._gim_ref} -> {ref}; gimbal stream restarted")
            self._gim.clear()
            self._gim_ref = ref
        if not self._admit(self._gim, t):
            return False
        self._attitude_step(self._gim, t, q, w, MAX_TURN_RPS)  # a gimbal may send no rates (NaN)
        self._gim.append(t, np.array((*q, *w)), self.config.window_us, MAX_SAMPLES)
        return True

    def _attitude_step(self, stream: SampleStream, t: int, q, w, unknown_rate_rps: float | None) -> None:
        """An attitude sample ``q`` (with its rates ``w``, NaN when unknown) turned from the stream's newest by more
        than the rates allow over the interval, by :data:`ATTITUDE_STEP_RAD` at least: a reset of the autopilot's
        attitude estimate (an EKF yaw reset, which a gimbal reporting in the earth frame follows), a break of the
        camera's pose track like a position reset.  Counted ``<stream>_reset``, the stream restarted (no frame is
        given an attitude half-way between the two), :attr:`discontinuities` raised.  Without both samples' rates
        the turn allowed is ``unknown_rate_rps`` over the interval (None: not judged)."""
        if not stream.t_us:
            return
        dt_us = t - stream.t_us[-1]
        if not 0 < dt_us <= stream.max_gap_us:
            return
        last = stream.values[-1].tolist()
        dot = abs(last[0] * q[0] + last[1] * q[1] + last[2] * q[2] + last[3] * q[3])
        turned = 2.0 * math.acos(min(dot, 1.0))
        if all(math.isfinite(x) for x in (*last[4:7], *w)):  # the larger of the two samples' rates
            rate = math.sqrt(max(sum(x * x for x in last[4:7]), sum(x * x for x in w)))
        elif unknown_rate_rps is None:
            return
        else:
            rate = unknown_rate_rps
        dt_s = dt_us / US_PER_S
        if turned <= rate * dt_s + ATTITUDE_STEP_RAD:
            return
        self.attitude_resets += 1
        self.counter.count(
            f"{stream.name}_reset",
            f"turned {math.degrees(turned):.1f} deg in {dt_s * 1e3:.0f} ms against {math.degrees(rate):.0f} deg/s; "
            f"{stream.name} stream restarted (pose discontinuity {self.discontinuities}: 3-D estimates start again)",
        )
        stream.clear()

    # ------------------------------------------------------------------ queries

    def lookup(self, time_boot_us: int, extrapolate: bool = False) -> PoseLookup:
        """Pose at ``time_boot_us`` or the reason there is none.  No side effects.

        Interpolation only by default (a miss newer than the telemetry says ``retry``: a caller may
        wait for the bracket); ``extrapolate=True`` extrapolates a stream whose newest sample is
        older than the time by at most its horizon (module docstring), else names the miss
        ``<stream>_extrapolation_limit``.

        Computed on floats (the stored rows' ``tolist()``) with the operations, in the order, of the
        numpy formulation (frames' single-quaternion paths): the same bits.
        """
        if isinstance(time_boot_us, bool) or not isinstance(time_boot_us, (int, np.integer)) or time_boot_us < 0:
            return PoseLookup(None, "time_invalid")
        t = int(time_boot_us)
        if self._origin is None:
            return PoseLookup(None, "no_origin")
        c = self.config
        att, pos, gim = self._att, self._pos, self._gim
        ba = self._bracket_or_extrapolate(
            att, t, extrapolate, self.horizons.attitude_us, lambda: _finite_from(att.values[-1], 4)
        )
        if ba[0] is None:
            return PoseLookup(None, ba[1], ba[2])
        # past the bounded horizon, dead reckoning through a position gap (module docstring)
        pos_horizon_us = max(self.horizons.position_us, c.dead_reckoning_us)
        bp = self._bracket_or_extrapolate(pos, t, extrapolate, pos_horizon_us, lambda: _finite_from(pos.values[-1], 3))
        if bp[0] is None and extrapolate and bp[1] == "position_gap" and pos.t_us[0] < t:
            # a silent stream (past its newest sample by more than the max gap), or a gap it has since closed (a
            # frame older than the first sample after a dropout): dead-reckoned from the sample before the time
            j = bisect.bisect_right(pos.t_us, t) - 1
            if not _finite_from(pos.values[j], 3):
                pass  # no velocity: no dead reckoning, the gap stands
            elif t - pos.t_us[j] <= pos_horizon_us:
                bp = (j, _AFTER, 0.0)
            elif j == len(pos.t_us) - 1:
                bp = (None, "position_extrapolation_limit", True)
        if bp[0] is None:
            return PoseLookup(None, bp[1], bp[2])
        bg = None
        gim_rate: list[Vec3 | None] = []  # _gimbal_rate(), once per look-up

        def can_gimbal() -> bool:
            gim_rate.append(self._gimbal_rate())
            return gim_rate[-1] is not None

        if self.mount.gimballed:
            bg = self._bracket_or_extrapolate(gim, t, extrapolate, self.horizons.gimbal_us, can_gimbal)
            if bg[0] is None:
                return PoseLookup(None, bg[1], bg[2])

        att_x_us = pos_x_us = 0
        i0, i1, a = ba
        if i1 is _AFTER:
            att_x_us = t - att.t_us[i0]
            r = att.values[i0].tolist()
            h_s = att_x_us / US_PER_S
            q_nb = quat_normalize1(quat_multiply1(r[:4], quat_from_rotvec1(r[4] * h_s, r[5] * h_s, r[6] * h_s)))
            att_span = 0
        else:
            q0 = att.values[i0].tolist()[:4]
            q_nb = q0 if i0 == i1 else quat_slerp1(q0, att.values[i1].tolist()[:4], a)
            att_span = att.t_us[i1] - att.t_us[i0]

        j0, j1, s = bp
        if j1 is _AFTER:
            pos_x_us = t - pos.t_us[j0]
            n, e, d, vn, ve, vd = pos.values[j0].tolist()[:6]
            h_s = pos_x_us / US_PER_S
            p_ned, v_ned = (n + vn * h_s, e + ve * h_s, d + vd * h_s), (vn, ve, vd)
            pos_span = 0
        else:
            pos_span = pos.t_us[j1] - pos.t_us[j0]
            p_ned, v_ned = self._interp_position(j0, j1, s, pos_span / US_PER_S)

        q_mg = None
        gim_span = None
        gim_x_us = None
        sigma_rad = extrapolation_sigma(att_x_us / US_PER_S, c.body_rate_sigma_rps, c.angular_accel_sigma_rps2)
        if bg is not None:
            k0, k1, g = bg
            if k1 is _AFTER:
                gim_x_us = t - gim.t_us[k0]
                w_ref = gim_rate[-1]  # not None: can_gimbal() said so
                assert w_ref is not None
                h_s = gim_x_us / US_PER_S
                dq = quat_from_rotvec1(w_ref[0] * h_s, w_ref[1] * h_s, w_ref[2] * h_s)
                q_ref = quat_normalize1(quat_multiply1(dq, gim.values[k0].tolist()[:4]))
                gim_span = 0
                sigma_rad = math.hypot(
                    sigma_rad,
                    extrapolation_sigma(gim_x_us / US_PER_S, c.gimbal_rate_sigma_rps, c.angular_accel_sigma_rps2),
                )
            else:
                gim_x_us = 0
                gim_span = gim.t_us[k1] - gim.t_us[k0]
                g0 = gim.values[k0].tolist()[:4]
                q_ref = g0 if k0 == k1 else quat_slerp1(g0, gim.values[k1].tolist()[:4], g)
            q_mg = self._q_mount_from_gimbal(q_ref, q_nb)  # both relative to the local level: q_mg is the mount's

        q_lv = pos.values[j0].tolist()[6:]
        if q_lv != [1.0, 0.0, 0.0, 0.0]:  # the attitude from the local level to the origin's NED (add_attitude)
            q_nb = quat_normalize1(quat_multiply1(q_lv, q_nb))
        p_cam, q_nc = self._camera_pose(p_ned, q_nb, q_mg)
        body = PoseSample.from_floats(t, p_ned, v_ned, q_nb)
        sigma_m = extrapolation_sigma(pos_x_us / US_PER_S, c.velocity_sigma_mps, c.accel_sigma_mps2)
        pose = PoseAt.from_floats(
            body,
            p_cam,
            q_nc,
            q_mg,
            self._origin,
            att_span,
            pos_span,
            gim_span,
            self.reboots,
            att_x_us,
            pos_x_us,
            gim_x_us,
            sigma_rad,
            sigma_m,
            self.discontinuities,
        )
        return PoseLookup(pose)

    def _camera_pose(self, p_ned, q_nb: Quat, q_mg: Quat | None) -> tuple[Vec3, Quat]:
        """:func:`~onboard.core.frames.camera_pose_ned` on floats: ``p_ned + R(q_nb) lever_arm`` and
        ``q_nb (x) q_body_from_mount [(x) q_mg] (x) q_mount_from_cam``.  The lever-arm rotation stays
        numpy's (its sum order is the SIMD kernel's); a zero arm adds a signed zero, which changes
        no coordinate that is not itself zero."""
        arm, q_bm, q_bc = self._mount_floats()
        if q_mg is not None:
            q_bc = quat_multiply1(quat_multiply1(q_bm, q_mg), _Q_MOUNT_FROM_CAM)
        q_nc = quat_normalize1(quat_multiply1(q_nb, q_bc))
        if arm == (0.0, 0.0, 0.0) and p_ned[0] != 0.0 and p_ned[1] != 0.0 and p_ned[2] != 0.0:
            return (p_ned[0], p_ned[1], p_ned[2]), q_nc
        rn, re, rd = quat_rotate(q_nb, arm).tolist()
        return (p_ned[0] + rn, p_ned[1] + re, p_ned[2] + rd), q_nc

    def _mount_floats(self) -> tuple[Vec3, Quat, Quat]:
        """The mount's lever arm, ``q_body_from_mount`` and ``q_body_from_cam()`` (no gimbal) as floats,
        computed once per mount object."""
        m = self.mount
        if self._mount_cache is None or self._mount_cache[0] is not m:
            ax, ay, az = np.asarray(m.lever_arm_frd_m, dtype=float).tolist()
            bw, bx, by, bz = np.asarray(m.q_body_from_mount, dtype=float).tolist()
            cw, cx, cy, cz = m.q_body_from_cam().tolist()
            self._mount_cache = (m, (ax, ay, az), (bw, bx, by, bz), (cw, cx, cy, cz))
        return self._mount_cache[1:]

    def _bracket_or_extrapolate(
        self, stream: SampleStream, t: int, extrapolate: bool, horizon_us: int, can: Callable[[], bool]
    ):
        """``stream.bracket(t)``; past the newest sample with ``extrapolate``: ``(i_last, _AFTER, 0.0)``
        within ``horizon_us`` when ``can()``, else the miss (``<name>_extrapolation_limit`` beyond it)."""
        b = stream.bracket(t)
        if b[0] is not None or not extrapolate or b[1] != f"{stream.name}_not_yet":
            return b
        if not can():
            return b
        if t - stream.t_us[-1] > horizon_us:
            return None, f"{stream.name}_extrapolation_limit", True
        return len(stream.t_us) - 1, _AFTER, 0.0

    def _gimbal_rate(self) -> Vec3 | None:
        """The gimbal's angular velocity (rad/s, reference frame) for extrapolation: the newest
        sample's reported one, else the least-squares rate through the samples of the last
        ``gimbal_rate_window_us`` anchored at the newest (``phi_i = Log(q_i (x) q_last^-1) = w tau_i``,
        ``w = sum tau_i phi_i / sum tau_i^2``); None with fewer than two samples there."""
        g = self._gim
        if not g.t_us:
            return None
        last = g.values[-1]
        wx, wy, wz = last[4:].tolist()
        if math.isfinite(wx) and math.isfinite(wy) and math.isfinite(wz):
            return wx, wy, wz
        t_last = g.t_us[-1]
        k = bisect.bisect_left(g.t_us, t_last - GIMBAL_RATE_WINDOW_US)
        if len(g.t_us) - k < 2:
            return None
        q_inv = quat_conjugate1(last[:4].tolist())
        nx = ny = nz = den = 0.0
        for i in range(k, len(g.t_us) - 1):
            tau = (g.t_us[i] - t_last) / US_PER_S
            dq = quat_multiply1(g.values[i][:4].tolist(), q_inv)
            rx, ry, rz = rotvec_from_quat1(dq if dq[0] >= 0 else (-dq[0], -dq[1], -dq[2], -dq[3]))
            nx, ny, nz = nx + tau * rx, ny + tau * ry, nz + tau * rz
            den += tau * tau
        if not den > 0:
            return None
        return nx / den, ny / den, nz / den

    def pose_at(self, time_boot_us: int, extrapolate: bool = True, result: PoseLookup | None = None) -> PoseAt | None:
        """:meth:`lookup` (extrapolating by default), counting a miss as ``pose_<reason>`` (kept in
        ``last_miss_reason``) and an extrapolated pose as ``pose_extrapolated``.  ``result``: that
        look-up already made (same time, same data), not repeated.

        A service that waits for late telemetry should call :meth:`lookup` while ``retry`` is True
        and this only once it gives up, so that each frame is counted once.
        """
        res = self.lookup(time_boot_us, extrapolate=extrapolate) if result is None else result
        self.last_miss_reason = res.reason
        # one frame looks its time up more than once (its image chain's rotation, then its own pose): counted once,
        # or a telemetry gap read as twice its missing poses
        outcome = (time_boot_us, "extrapolated" if res.pose is not None and res.pose.extrapolated else res.reason)
        repeated, self._counted_at = outcome == self._counted_at, outcome
        if res.pose is None:
            if repeated:
                return None
            t_us = time_boot_us if isinstance(time_boot_us, (int, np.integer)) else None  # else refused by lookup
            if t_us is not None and (self._first_lookup_us is None or t_us < self._first_lookup_us):
                # the earliest stamp: a first frame stamped far ahead (its camera not yet synced) left every later
                # one behind it, under STARTUP_S for good
                self._first_lookup_us = int(t_us)
            start_up = not self.served_pose and (
                t_us is None or self._first_lookup_us is None or t_us - self._first_lookup_us < STARTUP_S * US_PER_S
            )
            self.counter.count(
                f"pose_{res.reason}",
                f"no pose at time_boot_us={time_boot_us!r}" + (" (start-up)" if start_up else ""),
                level=logging.INFO if start_up else logging.WARNING,
            )
            return None
        self.served_pose = True
        if res.pose.extrapolated and not repeated:
            p = res.pose
            self.counter.count(
                "pose_extrapolated",
                f"attitude {p.att_extrapolated_us} us, position {p.pos_extrapolated_us} us, "
                f"gimbal {p.gimbal_extrapolated_us} us past the newest sample",
                level=logging.DEBUG,
            )
        return res.pose

    def _interp_position(self, j0: int, j1: int, s: float, dt_s: float) -> tuple[Vec3, Vec3]:
        """(p, v) between position rows ``j0`` and ``j1``, on floats: numpy's element-wise operations, in
        its order (the same bits)."""
        n0, e0, d0, vn0, ve0, vd0 = self._pos.values[j0].tolist()[:6]
        if j0 == j1:
            return (n0, e0, d0), (vn0, ve0, vd0)
        n1, e1, d1, vn1, ve1, vd1 = self._pos.values[j1].tolist()[:6]
        have_v = (
            math.isfinite(vn0)
            and math.isfinite(ve0)
            and math.isfinite(vd0)
            and math.isfinite(vn1)
            and math.isfinite(ve1)
            and math.isfinite(vd1)
        )
        # velocity: the autopilot's own estimate, interpolated linearly, when both ends have it
        # (differentiating the Hermite would amplify the 1e-7 deg quantisation of #33 over a short dt)
        if have_v:
            r = 1.0 - s
            v = (r * vn0 + s * vn1, r * ve0 + s * ve1, r * vd0 + s * vd1)
        else:
            v = ((n1 - n0) / dt_s, (e1 - e0) / dt_s, (d1 - d0) / dt_s)
        if have_v and self.config.position_interp == "hermite":
            s2, s3 = s * s, s * s * s
            h00, h10, h01, h11 = 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2
            a, b = h10 * dt_s, h11 * dt_s
            return (
                h00 * n0 + a * vn0 + h01 * n1 + b * vn1,
                h00 * e0 + a * ve0 + h01 * e1 + b * ve1,
                h00 * d0 + a * vd0 + h01 * d1 + b * vd1,
            ), v
        r = 1.0 - s
        return (r * n0 + s * n1, r * e0 + s * e1, r * d0 + s * d1), v

    def _q_mount_from_gimbal(self, q_ref_from_gimbal: Quat, q_ned_from_body: Quat) -> Quat:
        if self._gim_ref == GimbalReference.MOUNT:
            return q_ref_from_gimbal
        if self._gim_ref == GimbalReference.VEHICLE:
            yaw_rad = float(euler_from_quat(q_ned_from_body)[2])
            q_ned_from_gimbal = quat_multiply1(quat_from_euler(0.0, 0.0, yaw_rad).tolist(), q_ref_from_gimbal)
        else:
            q_ned_from_gimbal = q_ref_from_gimbal
        q_mount_from_ned = quat_conjugate1(quat_multiply1(q_ned_from_body, self._mount_floats()[1]))
        return quat_normalize1(quat_multiply1(q_mount_from_ned, q_ned_from_gimbal))
