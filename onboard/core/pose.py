"""Vehicle and camera pose on the autopilot's boot clock, and the clock mapping that feeds it.

Pure core: no pymavlink, no sockets, no threads.  The MAVLink adapter (:mod:`onboard.io.mavlink_link`)
translates wire messages once and calls the ``add_*`` methods; the lockstep evaluation calls them
directly from truth.  Frame conventions are those of :mod:`onboard.core.frames` (local NED, body FRD,
``q_a_from_b`` Hamilton, w first); every time here is ``time_boot_us``, integer microseconds on the
autopilot's boot clock (MAVLink ``time_boot_ms * 1000``).

Nouns
-----
:class:`PoseSample`
    One vehicle pose: ``time_boot_us`` (int), ``p_ned_m`` (3,), ``v_ned_mps`` (3,; NaN = unknown),
    ``q_ned_from_body`` (4,).
:class:`PoseAt`
    The answer of :meth:`PoseBuffer.pose_at`: the interpolated body pose, the camera centre
    ``p_cam_ned_m`` (3,) and attitude ``q_ned_from_cam`` (4,) through the pod mount (and gimbal),
    and how far apart the bracketing samples were.

Verbs
-----
:class:`PoseBuffer`
    Two (three with a gimbal) bounded streams, because attitude (MAVLink #31) and position (#33)
    arrive at different rates and times.  A query at a frame's capture time interpolates between
    the two samples that bracket it -- position by cubic Hermite on (p, v) (linear when a velocity
    is unknown), attitude by SLERP -- and never falls back to "latest sample".  A query outside a
    stream, or whose bracket is wider than the stream's ``max_gap``, gets ``None`` and a reason.
:class:`ClockSync`
    Offset (and skew) between a local clock (ns; e.g. the clock that stamps camera frames) and the
    autopilot's boot clock, from TIMESYNC (#111) exchanges.
:class:`RejectCounter`
    Counts rejected inputs and notable events by reason; logs each reason at most once per interval.

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
A frame must not wait for the sample after it (issue 9: a 60 ms wait cost 19-33 % of gimballed
frames their pose and ~50 ms of latency).  :meth:`PoseBuffer.pose_at` (not :meth:`~PoseBuffer.lookup`,
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

Added uncertainty (1 sigma, per axis).  Attitude: ``sigma_rad(h) = sqrt((sigma_w h)^2 +
(sigma_alpha h^2 / 2)^2)`` -- the rate's error over the horizon and an unmodelled angular
acceleration; position: ``sigma_m(h) = sqrt((sigma_v h)^2 + (sigma_a h^2 / 2)^2)``.  The
estimator's noise model is not widened per observation (the estimator is not this module's);
instead the horizon is *bounded* so that the added attitude sigma stays below a stated fraction of
the bearing white noise the estimator is configured with, ``sqrt(attitude_white^2 +
(pixel_sigma / f)^2)`` (:func:`attitude_horizon_us`; ``pose.extrapolation_noise_fraction``, 0.25:
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

Rejection reasons (keys of :attr:`RejectCounter.counts`)
-------------------------------------------------------
Per stream, prefixed ``attitude_``, ``position_`` or ``gimbal_``: ``time_invalid``, ``duplicate``
(same time again), ``out_of_order`` (earlier by less than the reboot threshold), ``not_finite``,
``shape``; quaternions also ``zero``, ``not_unit``.  Position also ``zero`` (lat = lon = 0: GPS
dropout), ``out_of_range`` (e.g. INT32_MAX sentinels), ``alt_out_of_range``, ``jump`` (implied speed
above ``max_speed_mps``), ``reset`` (a jump persisted: the stream restarts), ``velocity_invalid``
(sample kept, velocity dropped), ``no_origin``.  Gimbal also ``time_reset``, ``reference_changed``,
``reference_invalid``.  ``reboot``: time went back by more than the threshold on the attitude or
position stream (all buffers cleared).  :meth:`PoseBuffer.pose_at` counts a miss as ``pose_<reason>``
with reason ``time_invalid``, ``no_origin`` or
``<stream>_empty|before_buffer|not_yet|gap|extrapolation_limit``; an extrapolated pose is counted as
``pose_extrapolated``.
:class:`ClockSync` counts ``timesync_invalid``, ``timesync_rtt``, ``timesync_outlier``,
``timesync_reset``.

Limits: ``time_boot_ms`` is uint32 and wraps after 49.7 days; a wrap looks like a reboot.
"""

from __future__ import annotations

import bisect
import enum
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, fields

import numpy as np

from onboard.core.errors import ConfigError, InputError
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
    quat_conjugate1,
    quat_from_euler,
    quat_from_rotvec1,
    quat_multiply1,
    quat_normalize1,
    quat_rotate,
    quat_slerp1,
    rotvec_from_quat1,
)
from onboard.core.schema import Flag, Integer, Invalid, Number, Text, config_dataclass

__all__ = [
    "RejectCounter",
    "PoseSample",
    "PoseAt",
    "PoseLookup",
    "GimbalReference",
    "PoseBufferConfig",
    "PoseConfig",
    "OriginConfig",
    "PoseBuffer",
    "ClockSyncConfig",
    "ClockSync",
    "extrapolation_sigma",
    "attitude_horizon_us",
]

log = logging.getLogger(__name__)

US_PER_S = 1_000_000
NS_PER_US = 1_000
NS_PER_S = 1_000_000_000
ZERO_QUAT_NORM = 1e-6  # a quaternion shorter than this is "zero", not merely "not unit"


# --------------------------------------------------------------------------- reject counter


class RejectCounter:
    """Counts by reason; logs each reason at most once per ``log_interval_s`` (with the count since).

    ``count(reason, detail)`` never raises.  ``counts`` is a copy of the reason -> count dict.
    """

    def __init__(
        self,
        log_interval_s: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
        logger: logging.Logger | None = None,
    ) -> None:
        if not (math.isfinite(log_interval_s) and log_interval_s >= 0):
            raise ConfigError(f"RejectCounter.log_interval_s must be >= 0 seconds, got {log_interval_s!r}")
        self.log_interval_s = float(log_interval_s)
        self._clock = clock
        self._log = logger or log
        self._counts: dict[str, int] = {}
        self._last_log_s: dict[str, float] = {}
        self._unlogged: dict[str, int] = {}

    def count(self, reason: str, detail: str = "", n: int = 1, level: int = logging.WARNING) -> None:
        """Count ``n`` of ``reason``; log it at ``level`` (WARNING: a rejection; DEBUG: a normal event)."""
        self._counts[reason] = self._counts.get(reason, 0) + n
        try:
            now = float(self._clock())
        except Exception:  # a broken clock must not break the caller
            now = math.nan
        last = self._last_log_s.get(reason)
        if last is None or not now - last < self.log_interval_s:
            since = self._unlogged.get(reason, 0) + n
            self._log.log(
                level, "%s: %s (total %d, %d since last report)", reason, detail or "-", self._counts[reason], since
            )
            self._last_log_s[reason] = now
            self._unlogged[reason] = 0
        else:
            self._unlogged[reason] = self._unlogged.get(reason, 0) + n

    def __getitem__(self, reason: str) -> int:
        return self._counts.get(reason, 0)

    @property
    def counts(self) -> dict[str, int]:
        return dict(self._counts)

    @property
    def total(self) -> int:
        return sum(self._counts.values())


# --------------------------------------------------------------------------- nouns


def _frozen_vec(value, shape: tuple[int, ...], what: str, allow_nan: bool = False) -> np.ndarray:
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what} must be numbers of shape {shape}, got {value!r}") from exc
    if a.shape != shape:
        raise InputError(f"{what} must have shape {shape}, got {a.shape}")
    bad = ~np.isfinite(a)
    if allow_nan:
        bad &= ~np.isnan(a)
    if bad.any():
        raise InputError(f"{what} must be finite{' (NaN = unknown allowed)' if allow_nan else ''}, got {a.tolist()}")
    a.setflags(write=False)
    return a


def _check_time_us(value, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{what} must be an integer number of microseconds, got {value!r}")
    if value < 0:
        raise InputError(f"{what} must be >= 0, got {value}")
    return int(value)


# --------------------------------------------------------------------------- float paths
# The buffer handles one message (4 or 3 numbers) or one frame at a time, where numpy's per-call
# overhead cost more than the arithmetic (an ATTITUDE_QUATERNION took longer to validate than pymavlink
# took to parse it).  The common case runs on Python floats; anything unusual goes to the numpy code,
# which alone decides rejections (same counters, same messages).  The quaternions go through the float
# kernels of onboard.core.frames' single-quaternion paths (``quat_*1``): the same bits
# (tests/onboard/test_pose_fast_paths.py checks the look-up against the numpy formulation).

_F64 = np.dtype(float)
_NAN3 = (math.nan, math.nan, math.nan)

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


def _finite_from(row: np.ndarray, k: int) -> bool:
    """All of ``row[k:]`` finite."""
    for c in row[k:].tolist():
        if not math.isfinite(c):
            return False
    return True


def _frozen_floats(values) -> np.ndarray:
    """A read-only float64 array of computed, already checked values (what :func:`_frozen_vec` makes)."""
    a = np.array(values, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class PoseSample:
    """Vehicle pose at ``time_boot_us``: ``p_ned_m`` (3,), ``v_ned_mps`` (3,; NaN = unknown), ``q_ned_from_body`` (4,)."""

    time_boot_us: int
    p_ned_m: np.ndarray
    v_ned_mps: np.ndarray
    q_ned_from_body: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "time_boot_us", _check_time_us(self.time_boot_us, "PoseSample.time_boot_us"))
        object.__setattr__(self, "p_ned_m", _frozen_vec(self.p_ned_m, (3,), "PoseSample.p_ned_m"))
        object.__setattr__(self, "v_ned_mps", _frozen_vec(self.v_ned_mps, (3,), "PoseSample.v_ned_mps", allow_nan=True))
        try:
            q = check_unit_quat(self.q_ned_from_body, "PoseSample.q_ned_from_body")
        except FrameError as exc:
            raise InputError(str(exc)) from exc
        object.__setattr__(self, "q_ned_from_body", _frozen_vec(q, (4,), "PoseSample.q_ned_from_body"))


@dataclass(frozen=True, eq=False)
class PoseAt:
    """Pose interpolated at ``body.time_boot_us``.

    ``p_cam_ned_m`` (3,) and ``q_ned_from_cam`` (4,) from :func:`onboard.core.frames.camera_pose_ned`;
    ``q_mount_from_gimbal`` (4,) or None without a gimbal; ``att_span_us`` / ``pos_span_us`` /
    ``gimbal_span_us``: spacing of the bracketing samples (0 when the query hit a sample);
    ``epoch``: number of autopilot reboots seen so far (poses of different epochs share the origin
    only when ``keep_origin_on_reboot``).  ``att_extrapolated_us`` / ``pos_extrapolated_us`` /
    ``gimbal_extrapolated_us``: how far past its newest sample each stream was extrapolated (0 =
    interpolated; the span is then 0 too); ``sigma_extrapolation_rad`` / ``sigma_extrapolation_m``:
    the 1-sigma attitude / position error that extrapolation adds (module docstring; 0 when
    interpolated).
    """

    body: PoseSample
    p_cam_ned_m: np.ndarray
    q_ned_from_cam: np.ndarray
    q_mount_from_gimbal: np.ndarray | None
    origin: GeodeticOrigin
    att_span_us: int
    pos_span_us: int
    gimbal_span_us: int | None
    epoch: int
    att_extrapolated_us: int = 0
    pos_extrapolated_us: int = 0
    gimbal_extrapolated_us: int | None = None
    sigma_extrapolation_rad: float = 0.0
    sigma_extrapolation_m: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "p_cam_ned_m", _frozen_vec(self.p_cam_ned_m, (3,), "PoseAt.p_cam_ned_m"))
        object.__setattr__(self, "q_ned_from_cam", _frozen_vec(self.q_ned_from_cam, (4,), "PoseAt.q_ned_from_cam"))
        if self.q_mount_from_gimbal is not None:
            object.__setattr__(
                self, "q_mount_from_gimbal", _frozen_vec(self.q_mount_from_gimbal, (4,), "PoseAt.q_mount_from_gimbal")
            )

    @property
    def time_boot_us(self) -> int:
        return self.body.time_boot_us

    @property
    def extrapolated(self) -> bool:
        return bool(self.att_extrapolated_us or self.pos_extrapolated_us or self.gimbal_extrapolated_us)

    @property
    def mode(self) -> str:
        """``"interpolated"`` (every stream bracketed the time) or ``"extrapolated"``."""
        return "extrapolated" if self.extrapolated else "interpolated"


_POSE_AT_FIELDS = tuple(f.name for f in fields(PoseAt))


def _pose_sample_computed(t: int, p, v, q) -> PoseSample:
    """``PoseSample(t, p, v, q)`` for floats the buffer computed (``t`` an int >= 0): the same sample,
    without repeating :meth:`PoseSample.__post_init__`'s array checks when they pass; when they would not,
    the constructor itself (which raises as it always did)."""
    w, x, y, z = q
    n1 = math.sqrt(w * w + x * x + y * y + z * z)  # check_unit_quat's norm
    if not (
        math.isfinite(p[0] + p[1] + p[2])
        and not (math.isinf(v[0]) or math.isinf(v[1]) or math.isinf(v[2]))
        and abs(n1 - 1.0) <= QUAT_NORM_TOL
    ):
        return PoseSample(t, p, v, q)
    sample = object.__new__(PoseSample)
    object.__setattr__(sample, "time_boot_us", t)
    object.__setattr__(sample, "p_ned_m", _frozen_floats(p))
    object.__setattr__(sample, "v_ned_mps", _frozen_floats(v))
    object.__setattr__(sample, "q_ned_from_body", _frozen_floats(quat_normalize1(q)))  # as check_unit_quat
    return sample


def _pose_at_computed(body: PoseSample, p_cam, q_nc, q_mg, *rest) -> PoseAt:
    """``PoseAt(body, p_cam, q_nc, q_mg, *rest)`` for floats the buffer computed, as
    :func:`_pose_sample_computed`."""
    if not (
        math.isfinite(p_cam[0] + p_cam[1] + p_cam[2])
        and math.isfinite(q_nc[0] + q_nc[1] + q_nc[2] + q_nc[3])
        and (q_mg is None or math.isfinite(q_mg[0] + q_mg[1] + q_mg[2] + q_mg[3]))
    ):
        return PoseAt(body, p_cam, q_nc, q_mg, *rest)
    pose = object.__new__(PoseAt)
    values = (body, _frozen_floats(p_cam), _frozen_floats(q_nc), None if q_mg is None else _frozen_floats(q_mg))
    for name, value in zip(_POSE_AT_FIELDS, values + rest, strict=True):
        object.__setattr__(pose, name, value)
    return pose


def extrapolation_sigma(horizon_s: float, rate_sigma: float, accel_sigma: float) -> float:
    """1-sigma error of a constant-rate extrapolation over ``horizon_s``:
    ``sqrt((rate_sigma h)^2 + (accel_sigma h^2 / 2)^2)`` (rate error over the horizon plus an
    unmodelled second derivative; units of the rate times s: rad from rad/s and rad/s^2, m from
    m/s and m/s^2)."""
    h = max(float(horizon_s), 0.0)
    return math.hypot(rate_sigma * h, 0.5 * accel_sigma * h * h)


def attitude_horizon_us(limit: float, rate_sigma: float, accel_sigma: float, cap_us: int) -> int:
    """The longest horizon (us, at most ``cap_us``) whose :func:`extrapolation_sigma` stays <= ``limit``.

    Solves ``rate^2 h^2 + accel^2 h^4 / 4 = limit^2`` for ``h^2`` (a quadratic; monotone in h), in
    the cancellation-free form ``h^2 = 2 limit^2 / (rate^2 + sqrt(rate^4 + accel^2 limit^2))``.
    """
    if limit <= 0.0:
        return 0
    a, b = 0.25 * accel_sigma**2, rate_sigma**2
    den = b + math.sqrt(b * b + 4.0 * a * limit**2)
    h2 = math.inf if den == 0.0 else 2.0 * limit**2 / den
    return int(min(cap_us, math.floor(math.sqrt(h2) * US_PER_S))) if math.isfinite(h2) else int(cap_us)


@dataclass(frozen=True)
class PoseLookup:
    """Side-effect-free answer of :meth:`PoseBuffer.lookup`.

    ``pose`` or ``reason``; ``retry`` is True when the query is newer than a stream's last sample
    by less than its ``max_gap`` (the next sample may still bracket it: ask again later).
    """

    pose: PoseAt | None
    reason: str | None = None
    retry: bool = False


class GimbalReference(str, enum.Enum):
    """What a gimbal quaternion is relative to.

    ``MOUNT``: the pod mount frame (``q_mount_from_gimbal``).  ``VEHICLE``: MAVLink gimbal v2
    "vehicle frame" -- the NED frame turned by the vehicle's heading (roll and pitch relative to the
    horizon, yaw relative to the nose).  ``EARTH``: NED ("yaw in earth frame").
    """

    MOUNT = "mount"
    VEHICLE = "vehicle"
    EARTH = "earth"


@config_dataclass
class PoseBufferConfig:
    """Bounds and tolerances.  All times in microseconds on the boot clock.

    ``window_us``: history kept per stream.  ``*_max_gap_us``: the widest bracket a lookup accepts
    (the "pose tolerance": a frame whose bracket is wider has no pose and is not used for 3-D).
    ``reboot_threshold_us``: a sample more than this before or after its stream's newest one is far
    from the running clock: an outlier, refused (``<stream>_time_outlier``), unless
    ``time_confirm_count`` consecutive such samples agree with each other (each after the previous,
    by at most the threshold): then it is a clock step, backwards an autopilot reboot (buffers
    cleared, ``reboot``), forwards a gap (``<stream>_time_step``).  One bad stamp costs one sample.
    ``max_speed_mps``: a position implying a faster move from the previous one is a jump;
    ``jump_reset_count`` consecutive jumps restart the position stream.
    ``position_interp``: ``"hermite"`` (uses velocity) or ``"linear"``.

    Extrapolation past the newest sample (module docstring; 0 disables it for that stream):
    ``att_max_extrapolation_us`` (with the reported body rates), ``pos_max_extrapolation_us`` (with
    the reported velocity), ``gimbal_max_extrapolation_us`` (with the reported or fitted gimbal
    rate; ``gimbal_rate_window_us`` of samples feed the fit).  The error model of
    :attr:`PoseAt.sigma_extrapolation_rad` / ``_m``: ``body_rate_sigma_rps``,
    ``gimbal_rate_sigma_rps``, ``angular_accel_sigma_rps2``, ``velocity_sigma_mps``,
    ``accel_sigma_mps2``.

    The daemon builds it from the ``pose`` section (:class:`PoseConfig`, milliseconds and degrees) with
    :meth:`PoseConfig.buffer_config`; a :func:`~onboard.core.schema.config_dataclass`: a bad value raises
    :class:`~onboard.core.schema.SchemaError` naming the field.
    """

    window_us: Integer(lo=1) = 5 * US_PER_S
    max_samples: Integer(lo=1) = 4096
    att_max_gap_us: Integer(lo=1) = 100_000
    pos_max_gap_us: Integer(lo=1) = 300_000
    gimbal_max_gap_us: Integer(lo=1) = 300_000
    reboot_threshold_us: Integer(lo=1) = 1 * US_PER_S
    time_confirm_count: Integer(lo=1) = 3
    max_speed_mps: Number(lo=0.0, lo_open=True) = 200.0
    jump_reset_count: Integer(lo=1) = 5
    keep_origin_on_reboot: Flag() = True
    position_interp: Text(choices=("hermite", "linear")) = "hermite"
    min_alt_m: Number() = -1_000.0
    max_alt_m: Number() = 50_000.0
    att_max_extrapolation_us: Integer(lo=0) = 36_000
    pos_max_extrapolation_us: Integer(lo=0) = 50_000
    gimbal_max_extrapolation_us: Integer(lo=0) = 25_000
    gimbal_rate_window_us: Integer(lo=0) = 100_000
    body_rate_sigma_rps: Number(lo=0.0) = math.radians(0.1)
    gimbal_rate_sigma_rps: Number(lo=0.0) = math.radians(0.5)
    angular_accel_sigma_rps2: Number(lo=0.0) = math.radians(20.0)
    velocity_sigma_mps: Number(lo=0.0) = 0.1
    accel_sigma_mps2: Number(lo=0.0) = 2.0

    def __post_init__(self) -> None:
        if not self.min_alt_m < self.max_alt_m:
            raise Invalid("max_alt_m", f"a number > min_alt_m ({self.min_alt_m:g})", self.max_alt_m)
        for name in ("att_max_gap_us", "pos_max_gap_us", "gimbal_max_gap_us"):
            if getattr(self, name) > self.window_us:
                raise Invalid(name, f"an integer <= window_us ({self.window_us})", getattr(self, name))
        for name, gap in (
            ("att_max_extrapolation_us", "att_max_gap_us"),
            ("pos_max_extrapolation_us", "pos_max_gap_us"),
            ("gimbal_max_extrapolation_us", "gimbal_max_gap_us"),
            ("gimbal_rate_window_us", "window_us"),
        ):
            if getattr(self, name) > getattr(self, gap):
                raise Invalid(name, f"an integer <= {gap} ({getattr(self, gap)})", getattr(self, name))


@config_dataclass
class OriginConfig:
    """``pose.origin`` of the daemon's configuration: a fixed local NED origin (degrees, metres)."""

    lat_deg: Number(-90.0, 90.0) = 0.0
    lon_deg: Number(-180.0, 180.0) = 0.0
    alt_m: Number(-1000.0, 100000.0) = 0.0

    def geodetic(self) -> GeodeticOrigin:
        return GeodeticOrigin(self.lat_deg, self.lon_deg, self.alt_m)


@config_dataclass
class PoseConfig:
    """The ``pose`` section of the daemon's configuration (``config/onboard.yaml``; composed by
    :class:`onboard.app.config.OnboardConfig`): the pose buffer's tolerances in the file's units
    (milliseconds, seconds, degrees), declared here, beside the :class:`PoseBufferConfig` they become
    (:meth:`buffer_config`: ms/s -> us, deg -> rad)."""

    window_s: Number(0.1, 600.0) = 5.0
    attitude_max_gap_ms: Number(0.0, 10000.0, lo_open=True) = 100.0
    position_max_gap_ms: Number(0.0, 10000.0, lo_open=True) = 300.0
    gimbal_max_gap_ms: Number(0.0, 10000.0, lo_open=True) = 300.0
    reboot_threshold_s: Number(0.0, 3600.0, lo_open=True) = 1.0
    max_speed_mps: Number(0.0, 10000.0, lo_open=True) = 200.0
    jump_reset_count: Integer(1, 1000) = 5
    keep_origin_on_reboot: Flag() = True
    position_interp: Text(choices=("hermite", "linear")) = "hermite"
    wait_ms: Number(0.0, 1000.0) = 5.0
    max_extrapolation_ms: Number(0.0, 10000.0) = 50.0
    extrapolation_noise_fraction: Number(0.0, 10.0) = 0.25
    body_rate_sigma_dps: Number(0.0, 1000.0) = 0.1
    gimbal_rate_sigma_dps: Number(0.0, 1000.0) = 0.5
    angular_accel_sigma_dps2: Number(0.0, 100000.0) = 20.0
    velocity_sigma_mps: Number(0.0, 1000.0) = 0.1
    accel_sigma_mps2: Number(0.0, 1000.0) = 2.0
    origin: OriginConfig | None = None

    def __post_init__(self) -> None:
        for name in ("attitude_max_gap_ms", "position_max_gap_ms", "gimbal_max_gap_ms"):
            if getattr(self, name) > self.window_s * 1000.0:
                raise Invalid(name, f"a gap <= pose.window_s ({self.window_s:g} s)", getattr(self, name))

    def buffer_config(self, bearing_white_sigma_rad: float | None = None) -> PoseBufferConfig:
        """The :class:`PoseBufferConfig` (ms/s -> us, deg -> rad).

        Extrapolation horizons (each capped by its stream's max gap): position
        ``max_extrapolation_ms``; attitude and gimbal the same, shortened so that their added 1-sigma stays <= ``extrapolation_noise_fraction`` x
        ``bearing_white_sigma_rad`` (:func:`attitude_horizon_us`; the service passes
        ``OnboardConfig.bearing_white_sigma_rad()``; None: not shortened).
        """
        us = lambda ms: max(1, int(round(ms * 1000.0)))  # noqa: E731
        cap_us = int(round(self.max_extrapolation_ms * 1000.0))
        body_rps, gim_rps = math.radians(self.body_rate_sigma_dps), math.radians(self.gimbal_rate_sigma_dps)
        acc_rps2 = math.radians(self.angular_accel_sigma_dps2)
        if bearing_white_sigma_rad is None:
            att_us = gim_us = cap_us
        else:
            limit = self.extrapolation_noise_fraction * bearing_white_sigma_rad
            att_us = attitude_horizon_us(limit, body_rps, acc_rps2, cap_us)
            gim_us = attitude_horizon_us(limit, gim_rps, acc_rps2, cap_us)
        return PoseBufferConfig(
            att_max_extrapolation_us=min(att_us, us(self.attitude_max_gap_ms)),
            pos_max_extrapolation_us=min(cap_us, us(self.position_max_gap_ms)),
            gimbal_max_extrapolation_us=min(gim_us, us(self.gimbal_max_gap_ms)),
            body_rate_sigma_rps=body_rps,
            gimbal_rate_sigma_rps=gim_rps,
            angular_accel_sigma_rps2=acc_rps2,
            velocity_sigma_mps=self.velocity_sigma_mps,
            accel_sigma_mps2=self.accel_sigma_mps2,
            window_us=us(self.window_s * 1000.0),
            att_max_gap_us=us(self.attitude_max_gap_ms),
            pos_max_gap_us=us(self.position_max_gap_ms),
            gimbal_max_gap_us=us(self.gimbal_max_gap_ms),
            reboot_threshold_us=us(self.reboot_threshold_s * 1000.0),
            max_speed_mps=self.max_speed_mps,
            jump_reset_count=self.jump_reset_count,
            keep_origin_on_reboot=self.keep_origin_on_reboot,
            position_interp=self.position_interp,
        )

    def geodetic_origin(self) -> GeodeticOrigin | None:
        return None if self.origin is None else self.origin.geodetic()


# --------------------------------------------------------------------------- streams


class _Stream:
    """Time-ordered samples of one source; values are rows of equal length."""

    def __init__(self, name: str, max_gap_us: int) -> None:
        self.name = name
        self.max_gap_us = max_gap_us
        self.t_us: list[int] = []
        self.values: list[np.ndarray] = []
        self.pending_t_us: list[int] = []  # a run of far-off stamps that may confirm a clock step

    @property
    def last_t(self) -> int | None:
        return self.t_us[-1] if self.t_us else None

    def clear(self) -> None:
        self.t_us.clear()
        self.values.clear()
        self.pending_t_us.clear()

    def append(self, t_us: int, value: np.ndarray, window_us: int, max_samples: int) -> None:
        self.t_us.append(t_us)
        self.values.append(value)
        cut = bisect.bisect_left(self.t_us, t_us - window_us)
        cut = max(cut, len(self.t_us) - max_samples)
        if cut > 0:
            del self.t_us[:cut]
            del self.values[:cut]

    def bracket(self, t_us: int) -> tuple[int, int, float] | tuple[None, str, bool]:
        """(i0, i1, alpha) with t0 <= t <= t1, or (None, reason, retry)."""
        if not self.t_us:
            return None, f"{self.name}_empty", False
        if t_us < self.t_us[0]:
            return None, f"{self.name}_before_buffer", False
        if t_us > self.t_us[-1]:
            if t_us - self.t_us[-1] > self.max_gap_us:
                return None, f"{self.name}_gap", False
            return None, f"{self.name}_not_yet", True
        i = bisect.bisect_left(self.t_us, t_us)
        if self.t_us[i] == t_us:
            return i, i, 0.0
        t0, t1 = self.t_us[i - 1], self.t_us[i]
        if t1 - t0 > self.max_gap_us:
            return None, f"{self.name}_gap", False
        return i - 1, i, (t_us - t0) / (t1 - t0)


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
        config: PoseBufferConfig | None = None,
        origin: GeodeticOrigin | None = None,
        counter: RejectCounter | None = None,
    ) -> None:
        self.mount = mount if mount is not None else CameraMount()
        self.config = config if config is not None else PoseBufferConfig()
        self.counter = counter if counter is not None else RejectCounter()
        self._configured_origin = origin
        self._origin = origin
        c = self.config
        self._att = _Stream("attitude", c.att_max_gap_us)
        self._pos = _Stream("position", c.pos_max_gap_us)
        self._gim = _Stream("gimbal", c.gimbal_max_gap_us)
        self._gim_ref: GimbalReference | None = None
        self._mount_cache: tuple[CameraMount, Vec3, Quat, Quat] | None = None
        self._jumps = 0
        self.reboots = 0
        self.last_miss_reason: str | None = None

    # ------------------------------------------------------------------ state

    @property
    def origin(self) -> GeodeticOrigin | None:
        return self._origin

    @property
    def epoch(self) -> int:
        return self.reboots

    def newest_time_boot_us(self) -> int | None:
        """Latest time covered by both attitude and position, or None."""
        if not self._att.t_us or not self._pos.t_us:
            return None
        return min(self._att.t_us[-1], self._pos.t_us[-1])

    def sizes(self) -> dict[str, int]:
        return {"attitude": len(self._att.t_us), "position": len(self._pos.t_us), "gimbal": len(self._gim.t_us)}

    def clear(self) -> None:
        """Drop all samples (the origin stays)."""
        for s in (self._att, self._pos, self._gim):
            s.clear()
        self._jumps = 0

    # ------------------------------------------------------------------ time checks

    def _time(self, stream: str, t) -> int | None:
        if type(t) is int and t >= 0:  # the common case, without the checker's isinstance tests
            return t
        try:
            return _check_time_us(t, f"{stream}.time_boot_us")
        except InputError as exc:
            self.counter.count(f"{stream}_time_invalid", str(exc))
            return None

    def _admit(self, s: _Stream, t: int) -> bool:
        """Ordering and outlier check (see :class:`PoseBufferConfig` ``reboot_threshold_us``); detects
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
        run = s.pending_t_us
        if run and run[-1] < t <= run[-1] + thr:
            run.append(t)
        else:
            run[:] = [t]
        if len(run) < self.config.time_confirm_count:
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
            f"{s.name} time_boot_us went back {last - t} us ({last} -> {t}), "
            f"confirmed by {self.config.time_confirm_count} samples"
        )
        return True

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
        ``omega_frd_rps`` (3,; body FRD, rad/s; None or NaN = unknown: no extrapolation)."""
        t = self._time("attitude", time_boot_us)
        if t is None:
            return False
        q = self._quat("attitude", q_ned_from_body)
        if q is None:
            return False
        w = self._rates("attitude", omega_frd_rps)
        if not self._admit(self._att, t):
            return False
        self._att.append(t, np.array((*q, *w)), self.config.window_us, self.config.max_samples)
        return True

    def add_position(self, time_boot_us: int, lat_deg: float, lon_deg: float, alt_m: float, v_ned_mps=None) -> bool:
        """Store a WGS84 position (alt treated as ellipsoidal, see frames) and NED velocity (None = unknown)."""
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
        if not (self.config.min_alt_m <= alt <= self.config.max_alt_m):
            self.counter.count("position_alt_out_of_range", f"alt={alt} m")
            return False
        v = self._velocity(v_ned_mps)
        if not self._admit(self._pos, t):  # first: a reboot may reset the origin
            return False
        if self._origin is None:  # the position stream is empty whenever the origin is unset
            self._origin = GeodeticOrigin(lat, lon, alt)
            log.info("local NED origin fixed at the first valid position: %s", self._origin)
        # numpy's one-point conversion, kept: its 3 x 3 product may fuse multiply-adds, which floats
        # cannot repeat bit for bit, and at 25 Hz it costs ~2 us more than floats would
        return self._store_position(t, ned_from_geodetic(lat, lon, alt, self._origin).tolist(), v)

    def add_position_ned(self, time_boot_us: int, p_ned_m, v_ned_mps=None) -> bool:
        """Store a local NED position (needs an origin: configured or fixed by an earlier geodetic sample)."""
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
        return self._store_position(t, p, v)

    def _velocity(self, v_ned_mps) -> list[float]:
        """3 velocity components, NaN when unknown or invalid (counted; the position is still used)."""
        if v_ned_mps is None:
            return list(_NAN3)
        f = _plain_floats(v_ned_mps, 3)
        if f is not None and math.isfinite(f[0]) and math.isfinite(f[1]) and math.isfinite(f[2]):
            return list(f)
        try:
            v = np.array(v_ned_mps, dtype=float).reshape(3)
        except (TypeError, ValueError):
            self.counter.count("position_velocity_invalid", f"v_ned_mps={v_ned_mps!r}; velocity dropped")
            return list(_NAN3)
        if not np.all(np.isfinite(v)):
            self.counter.count("position_velocity_invalid", f"v_ned_mps={v.tolist()}; velocity dropped")
            return list(_NAN3)
        return v.tolist()

    def _store_position(self, t: int, p, v) -> bool:
        """Store ``p`` (3 floats, NED m) and ``v`` (3 floats) unless ``p`` is a jump from the newest position."""
        if self._pos.t_us:
            dt_s = (t - self._pos.t_us[-1]) / US_PER_S
            last = self._pos.values[-1]
            n0, e0, d0 = last[:3].tolist()
            dn, de, dd = p[0] - n0, p[1] - e0, p[2] - d0
            step_m = math.sqrt(dn * dn + de * de + dd * dd)
            limit_m = self.config.max_speed_mps * dt_s
            if step_m > limit_m * (1.0 - 1e-9):  # a jump, or near enough that numpy's norm must decide
                step_m = float(np.linalg.norm(np.array(p) - last[:3]))
            if step_m > limit_m:
                self._jumps += 1
                if self._jumps < self.config.jump_reset_count:
                    self.counter.count("position_jump", f"{step_m:.1f} m in {dt_s * 1e3:.0f} ms")
                    return False
                self.counter.count("position_reset", f"{self._jumps} consecutive jumps; position stream restarted")
                self._pos.clear()
        self._jumps = 0
        self._pos.append(t, np.array((*p, *v)), self.config.window_us, self.config.max_samples)
        return True

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
        self._gim.append(t, np.array((*q, *w)), self.config.window_us, self.config.max_samples)
        return True

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
            att, t, extrapolate, c.att_max_extrapolation_us, lambda: _finite_from(att.values[-1], 4)
        )
        if ba[0] is None:
            return PoseLookup(None, ba[1], ba[2])
        bp = self._bracket_or_extrapolate(
            pos, t, extrapolate, c.pos_max_extrapolation_us, lambda: _finite_from(pos.values[-1], 3)
        )
        if bp[0] is None:
            return PoseLookup(None, bp[1], bp[2])
        bg = None
        gim_rate: list[Vec3 | None] = []  # _gimbal_rate(), once per look-up

        def can_gimbal() -> bool:
            gim_rate.append(self._gimbal_rate())
            return gim_rate[-1] is not None

        if self.mount.gimballed:
            bg = self._bracket_or_extrapolate(gim, t, extrapolate, c.gimbal_max_extrapolation_us, can_gimbal)
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
            n, e, d, vn, ve, vd = pos.values[j0].tolist()
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
            q_mg = self._q_mount_from_gimbal(q_ref, q_nb)

        p_cam, q_nc = self._camera_pose(p_ned, q_nb, q_mg)
        body = _pose_sample_computed(t, p_ned, v_ned, q_nb)
        sigma_m = extrapolation_sigma(pos_x_us / US_PER_S, c.velocity_sigma_mps, c.accel_sigma_mps2)
        pose = _pose_at_computed(
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
        self, stream: _Stream, t: int, extrapolate: bool, horizon_us: int, can: Callable[[], bool]
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
        k = bisect.bisect_left(g.t_us, t_last - self.config.gimbal_rate_window_us)
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
        if res.pose is None:
            self.counter.count(f"pose_{res.reason}", f"no pose at time_boot_us={time_boot_us!r}")
        elif res.pose.extrapolated:
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
        n0, e0, d0, vn0, ve0, vd0 = self._pos.values[j0].tolist()
        if j0 == j1:
            return (n0, e0, d0), (vn0, ve0, vd0)
        n1, e1, d1, vn1, ve1, vd1 = self._pos.values[j1].tolist()
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


# --------------------------------------------------------------------------- clock sync


@dataclass(frozen=True)
class ClockSyncConfig:
    """TIMESYNC filter settings (ns).

    ``max_rtt_ns``: exchanges with a longer round trip are discarded.  ``window``: exchanges kept.
    ``min_samples``: exchanges before :attr:`ClockSync.synced`.  ``rtt_floor_ns``: weights are
    ``1 / (rtt + rtt_floor)^2``.  ``min_skew_span_ns``: history span before a drift (skew) is fitted.
    ``jump_ns``/``jump_count``: that many consecutive exchanges off the estimate by more than
    ``jump_ns`` (plus half their RTT) mean the remote clock restarted: the filter re-seeds from them.
    """

    max_rtt_ns: int = 50_000_000
    window: int = 64
    min_samples: int = 3
    rtt_floor_ns: int = 200_000
    min_skew_span_ns: int = 20 * NS_PER_S
    max_skew_ppm: float = 1000.0
    jump_ns: int = 50_000_000
    jump_count: int = 3

    def __post_init__(self) -> None:
        for name in (
            "max_rtt_ns",
            "window",
            "min_samples",
            "rtt_floor_ns",
            "min_skew_span_ns",
            "jump_ns",
            "jump_count",
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise ConfigError(f"ClockSyncConfig.{name} must be a positive integer, got {v!r}")
        if self.min_samples > self.window:
            raise ConfigError(f"ClockSyncConfig.min_samples ({self.min_samples}) must be <= window ({self.window})")
        if not (math.isfinite(self.max_skew_ppm) and self.max_skew_ppm >= 0):
            raise ConfigError(f"ClockSyncConfig.max_skew_ppm must be >= 0, got {self.max_skew_ppm!r}")


@dataclass
class _Exchange:
    mid_local_ns: int
    offset_ns: int
    rtt_ns: int


class ClockSync:
    """Maps a local clock (ns) to the autopilot boot clock from TIMESYNC exchanges.

    One exchange: we send ``ts1 = local send time`` (tc1 = 0); the autopilot answers with its boot
    time ``tc1`` and our ``ts1`` mirrored; we note the local receive time ``t3``.  Assuming a
    symmetric path, ``offset = tc1 - (ts1 + t3) / 2`` (autopilot minus local, at the midpoint), with
    an error of at most ``rtt / 2`` where ``rtt = t3 - ts1`` (Cristian 1989; MAVLink timesync
    service).  The estimate is a weighted least-squares line ``offset(t) = a + b (t - t_ref)`` over the
    last ``window`` exchanges, weights ``1 / (rtt + floor)^2`` so short round trips dominate; the
    slope ``b`` (clock skew) is fitted only once the history spans ``min_skew_span_ns``.
    PX4 and ArduPilot answer with their boot time in ns, the same clock as ``time_boot_ms``.
    """

    def __init__(self, config: ClockSyncConfig | None = None, counter: RejectCounter | None = None) -> None:
        self.config = config if config is not None else ClockSyncConfig()
        self.counter = counter if counter is not None else RejectCounter()
        self._ex: list[_Exchange] = []
        self._outliers: list[_Exchange] = []
        self._ref_local_ns = 0
        self._ref_offset_ns = 0
        self._a_ns = 0.0
        self._b = 0.0  # ns of offset per ns of local time
        self.resets = 0
        self._long_rtt_run = 0  # consecutive exchanges discarded for their round trip

    # ------------------------------------------------------------------ state

    @property
    def synced(self) -> bool:
        return len(self._ex) >= self.config.min_samples

    @property
    def n_samples(self) -> int:
        return len(self._ex)

    @property
    def skew_ppm(self) -> float:
        return self._b * 1e6

    @property
    def min_rtt_ns(self) -> int | None:
        return min(e.rtt_ns for e in self._ex) if self._ex else None

    def reset(self) -> None:
        """Forget every exchange (call on an autopilot reboot)."""
        self._ex.clear()
        self._outliers.clear()
        self._a_ns, self._b = 0.0, 0.0
        self._long_rtt_run = 0

    # ------------------------------------------------------------------ input

    def add_exchange(self, ts1_local_ns: int, tc1_remote_ns: int, recv_local_ns: int) -> bool:
        """Feed one TIMESYNC round trip; True when it was used."""
        vals = (ts1_local_ns, tc1_remote_ns, recv_local_ns)
        if any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) for v in vals) or tc1_remote_ns <= 0:
            self.counter.count("timesync_invalid", f"ts1={ts1_local_ns!r} tc1={tc1_remote_ns!r} t3={recv_local_ns!r}")
            return False
        ts1, tc1, t3 = (int(v) for v in vals)
        rtt = t3 - ts1
        if rtt < 0 or rtt > self.config.max_rtt_ns:
            # discarded either way; one alone is a moment when either end was busy (typically the first
            # exchange, sent while the autopilot side is still starting): INFO.  Two in a row mean the
            # link itself is slow and the clock may not sync: one WARNING per run of them.
            self._long_rtt_run += 1
            detail = f"round trip {rtt / 1e6:.3f} ms outside [0, {self.config.max_rtt_ns / 1e6:g}] ms"
            self.counter.count("timesync_rtt", detail, level=logging.INFO)
            if self._long_rtt_run == 2:
                log.warning(
                    "timesync_rtt: TIMESYNC round trips too long twice in a row (the last: %s): a slow link or a "
                    "busy CPU; exchanges are discarded while it lasts",
                    detail,
                )
            return False
        self._long_rtt_run = 0
        mid = ts1 + rtt // 2
        ex = _Exchange(mid, tc1 - mid, rtt)
        if self.synced:
            err = abs(ex.offset_ns - self.offset_ns_at(mid))
            if err > self.config.jump_ns + rtt / 2:
                self._outliers.append(ex)
                if len(self._outliers) < self.config.jump_count:
                    self.counter.count("timesync_outlier", f"offset off the estimate by {err / 1e6:.1f} ms")
                    return False
                self.counter.count(
                    "timesync_reset",
                    f"{len(self._outliers)} consecutive exchanges off by > "
                    f"{self.config.jump_ns / 1e6:g} ms: remote clock restarted",
                )
                self._ex = list(self._outliers)
                self._outliers.clear()
                self.resets += 1
                self._fit()
                return True
        self._outliers.clear()
        self._ex.append(ex)
        if len(self._ex) > self.config.window:
            del self._ex[: len(self._ex) - self.config.window]
        self._fit()
        return True

    def _fit(self) -> None:
        if not self._ex:
            return
        self._ref_local_ns = self._ex[0].mid_local_ns
        self._ref_offset_ns = self._ex[0].offset_ns
        x = np.array([e.mid_local_ns - self._ref_local_ns for e in self._ex], dtype=float)
        y = np.array([e.offset_ns - self._ref_offset_ns for e in self._ex], dtype=float)
        w = 1.0 / (np.array([e.rtt_ns for e in self._ex], dtype=float) + self.config.rtt_floor_ns) ** 2
        w /= w.sum()
        xm, ym = float(w @ x), float(w @ y)
        b = 0.0
        if x.max() - x.min() >= self.config.min_skew_span_ns:
            sxx = float(w @ (x - xm) ** 2)
            if sxx > 0:
                b = float(w @ ((x - xm) * (y - ym))) / sxx
                lim = self.config.max_skew_ppm * 1e-6
                b = min(max(b, -lim), lim)
        self._b = b
        self._a_ns = ym - b * xm

    # ------------------------------------------------------------------ output

    def offset_ns_at(self, local_ns: int) -> int:
        """Estimated ``boot_ns - local_ns`` at local time ``local_ns`` (0 before any exchange)."""
        dx = int(local_ns) - self._ref_local_ns
        return self._ref_offset_ns + int(round(self._a_ns + self._b * dx))

    def to_boot_us(self, local_ns: int) -> int | None:
        """Local clock (ns) -> autopilot ``time_boot_us``; None until synced or when before boot."""
        if not self.synced:
            return None
        boot_ns = int(local_ns) + self.offset_ns_at(local_ns)
        if boot_ns < 0:
            return None
        return (boot_ns + NS_PER_US // 2) // NS_PER_US

    def to_local_ns(self, time_boot_us: int) -> int | None:
        """Inverse of :meth:`to_boot_us` (one fixed-point step; skew is tiny); None until synced."""
        if not self.synced:
            return None
        boot_ns = int(time_boot_us) * NS_PER_US
        guess = boot_ns - self.offset_ns_at(boot_ns - self._ref_offset_ns)
        return boot_ns - self.offset_ns_at(guess)
