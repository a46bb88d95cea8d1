"""MAVLink on the wire, once: typed values <-> MAVLink 2 messages, MAVLink 2 connections.

Every sender and reader of the project goes through this module (one encoder, so they cannot disagree): the daemon's
autopilot link (:mod:`onboard.io.mavlink_link`, decode side and its output), the camera component
(:mod:`onboard.io.gcs_link`, :mod:`onboard.io.camera_protocol`), FOLLOW_TARGET (:mod:`onboard.io.follow`),
the simulated vehicle (:mod:`groundsim.io.mavlink_vehicle`), the lockstep eval's telemetry feed, the
benchmarks and the test fakes.  Dialect: pymavlink's common, MAVLink 2 framing.

Messages, wire field (unit) -> typed field (unit, frame)
--------------------------------------------------------
=====================================  ==========================================================================
message                                mapping
=====================================  ==========================================================================
HEARTBEAT (#0) :class:`Heartbeat`      type, autopilot, base_mode, custom_mode, system_status as they are
SYSTEM_TIME (#2) :class:`SystemTime`   time_unix_usec (us) -> ``time_unix_us``; time_boot_ms -> ``time_boot_us``
ATTITUDE_QUATERNION (#31)              q1..q4 -> ``q_ned_from_body`` (w, x, y, z; FRD body in NED, Hamilton);
:class:`AttitudeQuaternion`            rollspeed, pitchspeed, yawspeed (rad/s, body FRD) -> ``omega_frd_rps``;
                                       repr_offset_q sent as zeros (not supported)
GLOBAL_POSITION_INT (#33)              lat, lon (degE7) -> ``lat_deg``, ``lon_deg``; alt (mm AMSL) ->
:class:`GlobalPositionInt`             ``alt_amsl_m``; relative_alt (mm) -> ``alt_rel_m``; vx, vy, vz (cm/s,
                                       north, east, down; int16) -> ``v_ned_mps``; hdg (cdeg 0..35999,
                                       UINT16_MAX unknown) -> ``heading_rad`` (NaN unknown)
GPS_RAW_INT (#24) :class:`GpsRawInt`   time_usec, fix_type (GPS_FIX_TYPE) as they are; satellites_visible (UINT8_MAX
                                       unknown -> None); eph, epv (DOP * 100, UINT16_MAX unknown) -> ``hdop``,
                                       ``vdop`` (NaN unknown); h_acc, v_acc (mm, 0 unknown) -> ``h_acc_m``,
                                       ``v_acc_m`` (NaN unknown); lat, lon, alt sent as zeros (#33 is the position)
TIMESYNC (#111) :class:`Timesync`      tc1, ts1 (ns) -> ``tc1_ns``, ``ts1_ns`` (tc1 = 0: a request)
COMMAND_LONG (#76)                     :func:`set_message_interval_message` (MAV_CMD_SET_MESSAGE_INTERVAL:
                                       param1 message id, param2 interval us)
COMMAND_ACK (#77)                      :func:`command_ack_message`
FOLLOW_TARGET (#144)                   timestamp (ms) <- ``time_boot_us``; lat, lon (degE7); alt (m AMSL);
:class:`FollowTarget`                  vel (m/s NED) <- ``v_ned_mps``; position_cov[0:2] <- ``h_acc_m``, ``v_acc_m``;
                                       acc, rates zeros, attitude_q (1, 0, 0, 0): unknown; est_capabilities POS, VEL only
SET_POSITION_TARGET_LOCAL_NED (#84)    time_boot_ms <- ``time_boot_us``; MAV_FRAME_LOCAL_NED; type_mask: velocity only
:class:`SetPositionTargetLocalNed`     (position, acceleration, yaw, yaw rate ignored); vx, vy, vz (m/s) <- ``v_ned_mps``
CAMERA_TRACKING_IMAGE_STATUS (#275)    normalised image coordinates (x 0 = left .. 1 = right, y 0 = top ..
:class:`CameraTrackingImageStatus`     1 = bottom; NaN = unknown) as they are
CAMERA_TRACKING_GEO_STATUS (#276)      lat, lon (degE7) <- ``lat_deg``, ``lon_deg``; alt (m AMSL) <- ``alt_m``;
:class:`CameraTrackingGeoStatus`       h_acc, v_acc (m), vel_n/e/d, vel_acc (m/s), dist (m), hdg, hdg_acc (rad)
GIMBAL_DEVICE_ATTITUDE_STATUS (#285)   q -> ``q_ref_from_gimbal`` (w, x, y, z) in the frame the flags name
:class:`GimbalDeviceAttitudeStatus`    (:attr:`~GimbalDeviceAttitudeStatus.reference`); angular_velocity_x/y/z
                                       (rad/s, same frame; NaN unknown) -> ``omega_ref_rps``; delta_yaw (rad)
=====================================  ==========================================================================

Every ``time_boot_ms`` is ``time_boot_us // 1000`` modulo 2^32 on the way out (uint32: it wraps after
49.7 days) and ``time_boot_ms * 1000`` on the way in.  Integer fields are rounded half to even
(Python's ``round``); floats travel as IEEE float32.  The frame conventions themselves are written
down once, in :mod:`onboard.core.frames`.

Encoding checks: ``to_message()`` raises :class:`~onboard.core.errors.InputError` naming the message and
the field for a value the field cannot carry (out of range, NaN where no NaN is allowed, wrong
length).  Decoding does not judge: ``from_message`` returns what the wire carried (NaN quaternions,
zero positions, dropout sentinels included); the pose buffer decides and counts.

The Track mapping onto #275 / #276 (:func:`image_status_fields`, :func:`geo_status_fields`) is here too:
the core's :class:`~onboard.core.track.Track` knows no message.

Connection strings, the one grammar :func:`connect` opens, are parsed by :mod:`onboard.io.mavlink_endpoint`.

MAVLink 2, one way (:func:`mavlink2_codec`, :func:`use_mavlink2`, :func:`connect`): pymavlink picks its
wire version from the process environment (``MAVLINK20``) and may switch a connection's dialect when
the first byte it reads looks like MAVLink 1, rewriting ``os.environ``.  Here a connection's codec is
replaced by a MAVLink 2 common one and the auto-switch is turned off; the environment is never touched.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from onboard.core.errors import InputError
from onboard.core.pose import GimbalReference
from onboard.io.mavlink_endpoint import MavlinkEndpoint

__all__ = [
    "mavlink2",
    "mavlink2_codec",
    "use_mavlink2",
    "connect",
    "pack",
    "parse_datagram",
    "wire_roundtrip",
    "time_boot_ms_from_us",
    "Heartbeat",
    "SystemTime",
    "AttitudeQuaternion",
    "GlobalPositionInt",
    "GpsRawInt",
    "GimbalDeviceAttitudeStatus",
    "Timesync",
    "TIMESYNC_HAS_TARGET",
    "set_message_interval_message",
    "requested_interval",
    "command_ack_message",
    "CameraTrackingImageStatus",
    "CameraTrackingGeoStatus",
    "FollowTarget",
    "SetPositionTargetLocalNed",
    "SETPOINT_VELOCITY_ONLY_MASK",
    "FOLLOW_TARGET_CAP_POS",
    "FOLLOW_TARGET_CAP_VEL",
    "CAMERA_TRACKING_STATUS_FLAGS_IDLE",
    "CAMERA_TRACKING_STATUS_FLAGS_ACTIVE",
    "CAMERA_TRACKING_STATUS_FLAGS_COASTING",
    "CAMERA_TRACKING_MODE_NONE",
    "CAMERA_TRACKING_MODE_POINT",
    "CAMERA_TRACKING_MODE_RECTANGLE",
    "CAMERA_TRACKING_TARGET_DATA_IN_STATUS",
    "CAMERA_TRACKING_TARGET_DATA_RENDERED",
    "image_status_fields",
    "geo_status_fields",
    "message_from_fields",
    "wire_fields",
    "INT16_MAX",
    "INT32_MAX",
    "UINT16_MAX",
    "UINT32_MAX",
]

INT16_MAX = 2**15 - 1
INT32_MAX = 2**31 - 1
UINT16_MAX = 2**16 - 1
UINT32_MAX = 2**32 - 1

CAMERA_TRACKING_STATUS_FLAGS_IDLE = mavlink2.CAMERA_TRACKING_STATUS_FLAGS_IDLE  # 0
CAMERA_TRACKING_STATUS_FLAGS_ACTIVE = mavlink2.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE  # 1
CAMERA_TRACKING_STATUS_FLAGS_COASTING = mavlink2.CAMERA_TRACKING_STATUS_FLAGS_COASTING  # 8
CAMERA_TRACKING_MODE_NONE = mavlink2.CAMERA_TRACKING_MODE_NONE  # 0
CAMERA_TRACKING_MODE_POINT = mavlink2.CAMERA_TRACKING_MODE_POINT  # 1
CAMERA_TRACKING_MODE_RECTANGLE = mavlink2.CAMERA_TRACKING_MODE_RECTANGLE  # 2
CAMERA_TRACKING_TARGET_DATA_IN_STATUS = mavlink2.CAMERA_TRACKING_TARGET_DATA_IN_STATUS  # 4
CAMERA_TRACKING_TARGET_DATA_RENDERED = mavlink2.CAMERA_TRACKING_TARGET_DATA_RENDERED  # 2
FOLLOW_TARGET_CAP_POS = 1 << 0  # FOLLOW_TARGET.est_capabilities bit positions (common.xml)
FOLLOW_TARGET_CAP_VEL = 1 << 1

#: TIMESYNC's target_system / target_component are extension fields of the current common.xml; the
#: dialect shipped with some pymavlink releases (2.4.50) predates them.
TIMESYNC_HAS_TARGET = "target_system" in mavlink2.MAVLink_timesync_message.fieldnames


# --------------------------------------------------------------------------- MAVLink 2, codecs, bytes


def mavlink2_codec(file=None, src_system: int = 0, src_component: int = 0) -> mavlink2.MAVLink:
    """A MAVLink 2 / common codec writing to ``file`` (None: pack and parse only), resynchronising on garbage."""
    codec = mavlink2.MAVLink(file, srcSystem=src_system, srcComponent=src_component)
    codec.robust_parsing = True
    return codec


def use_mavlink2(conn, src_system: int, src_component: int):
    """Make a pymavlink ``mavfile`` speak MAVLink 2 / common whatever the environment: its codec replaced,
    the dialect auto-switch off (it would rewrite ``os.environ``).  Returns ``conn``."""
    conn.mav = mavlink2_codec(conn, src_system, src_component)
    conn.WIRE_PROTOCOL_VERSION = "2.0"
    conn.first_byte = False
    return conn


def connect(endpoint: MavlinkEndpoint, src_system: int, src_component: int, **mavutil_kwargs):
    """Open ``endpoint`` with pymavlink's ``mavlink_connection``, MAVLink 2 (:func:`use_mavlink2`).

    ``mavutil_kwargs`` go to pymavlink (``autoreconnect``, ``retries`` ...); a serial endpoint's baud is
    passed for it.  Errors are pymavlink's / the OS's, for the caller to name."""
    from pymavlink import mavutil  # here: no pymavlink connection state at import time

    kwargs = dict(source_system=src_system, source_component=src_component, **mavutil_kwargs)
    if endpoint.kind == "serial":
        kwargs["baud"] = endpoint.baud
    return use_mavlink2(mavutil.mavlink_connection(endpoint.device, **kwargs), src_system, src_component)


def pack(msg, src_system: int = 1, src_component: int = 1, codec: mavlink2.MAVLink | None = None) -> bytes:
    """The MAVLink 2 bytes of ``msg`` (a fresh codec: sequence 0, unless ``codec`` is given)."""
    codec = codec if codec is not None else mavlink2_codec(None, src_system, src_component)
    return bytes(msg.pack(codec))


def parse_datagram(data: bytes) -> list:
    """Every message in ``data`` (a fresh parser; BAD_DATA for garbage, as pymavlink reports it)."""
    parser = mavlink2_codec()
    out = []
    msg = parser.parse_char(bytes(data))
    while msg is not None:
        out.append(msg)
        msg = parser.parse_char(b"")
    return out


def wire_roundtrip(msg):
    """``msg`` as the receiver decodes it: packed and parsed again (float32, integer fields as sent)."""
    (back,) = parse_datagram(pack(msg))
    return back


def message_from_fields(name: str, fields: Mapping[str, Any]):
    """The message pymavlink names ``name`` (``"command_ack"``), from its fields in wire units (keyword
    arguments of pymavlink's ``<name>_encode``); for messages whose fields a protocol module builds."""
    encode = getattr(_ENCODER, f"{name}_encode", None)
    if encode is None:
        raise InputError(f"{name}: not a message of the common dialect")
    return encode(**fields)  # pymavlink's encoder: the dialect's defaults for extension fields


#: ``<name>_encode`` only builds a message object: one stateless instance serves every caller
_ENCODER = mavlink2.MAVLink(None)


def wire_fields(msg) -> dict[str, Any]:
    """A message's fields in wire units by their dialect names (the inverse of :func:`message_from_fields`)."""
    return {name: getattr(msg, name) for name in msg.get_fieldnames()}


# --------------------------------------------------------------------------- field checks (encoding only)


def _int(msg: str, name: str, v, lo: int, hi: int) -> int:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
        raise InputError(f"{msg}.{name} must be an integer in {lo}..{hi}, got {v!r}")
    return int(v)


def _num(msg: str, name: str, v, lo: float = -math.inf, hi: float = math.inf, nan_ok: bool = False) -> float:
    """A finite number in [lo, hi] (or NaN = unknown when ``nan_ok``)."""
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise InputError(f"{msg}.{name} must be a number{' or NaN' if nan_ok else ''}, got {v!r}")
    v = float(v)
    if nan_ok and math.isnan(v):
        return v
    if not math.isfinite(v) or not lo <= v <= hi:
        what = "NaN or a finite number" if nan_ok else "a finite number"
        raise InputError(f"{msg}.{name} must be {what} in [{lo}, {hi}], got {v!r}")
    return v


def _vec(
    msg: str, name: str, v, n: int, nan_ok: bool = False, lo: float = -math.inf, hi: float = math.inf
) -> list[float]:
    try:
        items = list(v)
    except TypeError:
        raise InputError(f"{msg}.{name} must be {n} numbers, got {v!r}") from None
    if len(items) != n:
        raise InputError(f"{msg}.{name} must be {n} numbers, got {len(items)}")
    return [_num(msg, f"{name}[{i}]", x, lo, hi, nan_ok) for i, x in enumerate(items)]


def _degE7(msg: str, name: str, deg, limit: float) -> int:
    return int(round(_num(msg, name, deg, -limit, limit) * 1e7))


def time_boot_ms_from_us(time_boot_us: int) -> int:
    """MAVLink ``time_boot_ms`` (uint32 ms, wrapping after ~49.7 days) of a boot-clock time in us."""
    return (int(time_boot_us) // 1000) % 2**32


def _time_boot_ms(msg: str, time_boot_us) -> int:
    _int(msg, "time_boot_us", time_boot_us, 0, 2**63 - 1)
    return time_boot_ms_from_us(time_boot_us)


# --------------------------------------------------------------------------- pose in (and heartbeats, clocks)


@dataclass(frozen=True)
class Heartbeat:
    """HEARTBEAT (#0): MAV_TYPE, MAV_AUTOPILOT, MAV_MODE_FLAG bits, custom mode, MAV_STATE."""

    mav_type: int
    autopilot: int
    base_mode: int = 0
    custom_mode: int = 0
    system_status: int = mavlink2.MAV_STATE_ACTIVE

    def to_message(self):
        m = "HEARTBEAT"
        return mavlink2.MAVLink_heartbeat_message(
            _int(m, "mav_type", self.mav_type, 0, 255),
            _int(m, "autopilot", self.autopilot, 0, 255),
            _int(m, "base_mode", self.base_mode, 0, 255),
            _int(m, "custom_mode", self.custom_mode, 0, UINT32_MAX),
            _int(m, "system_status", self.system_status, 0, 255),
            3,
        )

    @classmethod
    def from_message(cls, msg) -> Heartbeat:
        return cls(msg.type, msg.autopilot, msg.base_mode, msg.custom_mode, msg.system_status)


@dataclass(frozen=True)
class SystemTime:
    """SYSTEM_TIME (#2): UNIX time (us) and the boot-clock time (us, ms on the wire) of the same instant."""

    time_unix_us: int
    time_boot_us: int

    def to_message(self):
        m = "SYSTEM_TIME"
        return mavlink2.MAVLink_system_time_message(
            _int(m, "time_unix_us", self.time_unix_us, 0, 2**64 - 1), _time_boot_ms(m, self.time_boot_us)
        )

    @classmethod
    def from_message(cls, msg) -> SystemTime:
        return cls(int(msg.time_unix_usec), int(msg.time_boot_ms) * 1000)


@dataclass(frozen=True)
class AttitudeQuaternion:
    """ATTITUDE_QUATERNION (#31): ``q_ned_from_body`` (w, x, y, z) and the body rates ``omega_frd_rps`` (rad/s, FRD)
    at ``time_boot_us`` (the autopilot's boot clock; whole ms on the wire)."""

    time_boot_us: int
    q_ned_from_body: tuple[float, float, float, float]
    omega_frd_rps: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def to_message(self):
        m = "ATTITUDE_QUATERNION"
        q = _vec(m, "q_ned_from_body", self.q_ned_from_body, 4)
        w = _vec(m, "omega_frd_rps", self.omega_frd_rps, 3, nan_ok=True)
        return mavlink2.MAVLink_attitude_quaternion_message(
            _time_boot_ms(m, self.time_boot_us), *q, *w, (0.0, 0.0, 0.0, 0.0)
        )

    @classmethod
    def from_message(cls, msg) -> AttitudeQuaternion:
        return cls(
            int(msg.time_boot_ms) * 1000,
            (msg.q1, msg.q2, msg.q3, msg.q4),
            (msg.rollspeed, msg.pitchspeed, msg.yawspeed),
        )


@dataclass(frozen=True)
class GlobalPositionInt:
    """GLOBAL_POSITION_INT (#33): WGS84 ``lat_deg`` / ``lon_deg``, ``alt_amsl_m``, ``alt_rel_m`` (above home),
    ``v_ned_mps`` (north, east, down), ``heading_rad`` (the vehicle's heading, its yaw angle, [0, 2 pi) on the wire; NaN unknown).

    On the wire: degE7, mm, cm/s as int16 (|v| <= 327.67 m/s: a sender saturates first), cdeg.  A
    decoded dropout position (0, 0 or INT32_MAX) is passed on as the numbers it is."""

    time_boot_us: int
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    alt_rel_m: float = 0.0
    v_ned_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    heading_rad: float = math.nan

    def to_message(self):
        m = "GLOBAL_POSITION_INT"
        alt_lim_m = INT32_MAX / 1000.0
        v_lim = INT16_MAX / 100.0
        v_cmps = [
            round(x * 100.0) for x in _vec(m, "v_ned_mps", self.v_ned_mps, 3, lo=-v_lim - 0.005, hi=v_lim + 0.005)
        ]
        hdg = _num(m, "heading_rad", self.heading_rad, nan_ok=True)
        hdg_cdeg = UINT16_MAX if math.isnan(hdg) else round(math.degrees(hdg) % 360.0 * 100.0) % 36000
        return mavlink2.MAVLink_global_position_int_message(
            _time_boot_ms(m, self.time_boot_us),
            _degE7(m, "lat_deg", self.lat_deg, 90.0),
            _degE7(m, "lon_deg", self.lon_deg, 180.0),
            round(_num(m, "alt_amsl_m", self.alt_amsl_m, -alt_lim_m, alt_lim_m) * 1000.0),
            round(_num(m, "alt_rel_m", self.alt_rel_m, -alt_lim_m, alt_lim_m) * 1000.0),
            *v_cmps,
            hdg_cdeg,
        )

    @classmethod
    def from_message(cls, msg) -> GlobalPositionInt:
        hdg = math.nan if msg.hdg == UINT16_MAX else math.radians(msg.hdg / 100.0)
        return cls(
            int(msg.time_boot_ms) * 1000,
            msg.lat * 1e-7,
            msg.lon * 1e-7,
            msg.alt * 1e-3,
            msg.relative_alt * 1e-3,
            (msg.vx * 0.01, msg.vy * 0.01, msg.vz * 0.01),
            hdg,
        )


@dataclass(frozen=True)
class GpsRawInt:
    """GPS_RAW_INT (#24): the GNSS receiver's own fix, not the autopilot's estimate (#33: the daemon's position,
    so position and velocity are not carried here and go out as zeros, speed and course as unknown).

    ``time_usec`` as it is (UNIX or boot us: common.xml lets the reader tell by its size); ``fix_type``: a
    GPS_FIX_TYPE (:data:`onboard.core.gnss.GPS_FIX_NAMES`; the link refuses others); ``satellites_visible``
    (None: UINT8_MAX, unknown); ``hdop`` / ``vdop``: eph / epv over 100, dilutions of precision (unitless in
    common.xml, not the centimetres of MAVLink 1's text; NaN: UINT16_MAX); ``h_acc_m`` / ``v_acc_m``: the
    extension's position and altitude uncertainty (mm; 0, what a sender without the extension leaves: NaN)."""

    time_usec: int
    fix_type: int
    satellites_visible: int | None = None
    hdop: float = math.nan
    vdop: float = math.nan
    h_acc_m: float = math.nan
    v_acc_m: float = math.nan

    def to_message(self):
        m, sats = "GPS_RAW_INT", self.satellites_visible
        dop = [_num(m, "dop", v, 0.0, 655.34, nan_ok=True) for v in (self.hdop, self.vdop)]
        acc = [_num(m, "acc_m", v, 0.0005, UINT32_MAX / 1000.0, nan_ok=True) for v in (self.h_acc_m, self.v_acc_m)]
        return mavlink2.MAVLink_gps_raw_int_message(
            _int(m, "time_usec", self.time_usec, 0, 2**64 - 1),
            _int(m, "fix_type", self.fix_type, 0, 255),
            *(0, 0, 0),
            *(UINT16_MAX if math.isnan(d) else round(d * 100.0) for d in dop),
            *(UINT16_MAX, UINT16_MAX),
            255 if sats is None else _int(m, "satellites_visible", sats, 0, 254),
            0,
            *(0 if math.isnan(a) else max(round(a * 1000.0), 1) for a in acc),  # at least 1 mm: 0 is unknown
            *(0, 0, 0),
        )

    @classmethod
    def from_message(cls, msg) -> GpsRawInt:
        dop = [math.nan if v == UINT16_MAX else v / 100.0 for v in (msg.eph, msg.epv)]
        acc = [math.nan if v == 0 else v / 1000.0 for v in (msg.h_acc, msg.v_acc)]
        sats = None if msg.satellites_visible == 255 else int(msg.satellites_visible)
        return cls(int(msg.time_usec), int(msg.fix_type), sats, *dop, *acc)


#: gimbal failures that make its reported attitude unusable (limits alone do not)
GIMBAL_BAD_ATTITUDE = (
    mavlink2.GIMBAL_DEVICE_ERROR_FLAGS_ENCODER_ERROR
    | mavlink2.GIMBAL_DEVICE_ERROR_FLAGS_SOFTWARE_ERROR
    | mavlink2.GIMBAL_DEVICE_ERROR_FLAGS_CALIBRATION_RUNNING
)


@dataclass(frozen=True)
class GimbalDeviceAttitudeStatus:
    """GIMBAL_DEVICE_ATTITUDE_STATUS (#285): ``q_ref_from_gimbal`` (w, x, y, z) in the frame ``flags`` name
    (:attr:`reference`), its angular velocity ``omega_ref_rps`` (rad/s, same frame; NaN unknown), the
    vehicle yaw ``delta_yaw_rad`` (NaN unknown), GIMBAL_DEVICE_ERROR_FLAGS ``failure_flags``.

    MAVLink gimbal protocol v2: "earth frame" is NED; "vehicle frame" is NED turned by the vehicle's yaw
    (roll and pitch still relative to the horizon).  Legacy senders set YAW_LOCK without either frame
    flag: earth frame; neither flag: vehicle frame."""

    time_boot_us: int
    q_ref_from_gimbal: tuple[float, float, float, float]
    flags: int
    omega_ref_rps: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    delta_yaw_rad: float = math.nan
    failure_flags: int = 0
    gimbal_device_id: int = 1
    target_system: int = 0
    target_component: int = 0

    @property
    def reference(self) -> GimbalReference:
        f = self.flags
        if f & mavlink2.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME:
            return GimbalReference.EARTH
        if f & mavlink2.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME:
            return GimbalReference.VEHICLE
        return GimbalReference.EARTH if f & mavlink2.GIMBAL_DEVICE_FLAGS_YAW_LOCK else GimbalReference.VEHICLE

    @property
    def attitude_usable(self) -> bool:
        """False when a failure flag makes the attitude unusable (encoder, software, calibration)."""
        return not self.failure_flags & GIMBAL_BAD_ATTITUDE

    def to_message(self):
        m = "GIMBAL_DEVICE_ATTITUDE_STATUS"
        nan = math.nan
        return mavlink2.MAVLink_gimbal_device_attitude_status_message(
            _int(m, "target_system", self.target_system, 0, 255),
            _int(m, "target_component", self.target_component, 0, 255),
            _time_boot_ms(m, self.time_boot_us),
            _int(m, "flags", self.flags, 0, UINT16_MAX),
            _vec(m, "q_ref_from_gimbal", self.q_ref_from_gimbal, 4),
            *_vec(m, "omega_ref_rps", self.omega_ref_rps, 3, nan_ok=True),
            _int(m, "failure_flags", self.failure_flags, 0, UINT32_MAX),
            _num(m, "delta_yaw_rad", self.delta_yaw_rad, nan_ok=True),
            nan,
            _int(m, "gimbal_device_id", self.gimbal_device_id, 0, 255),
        )

    @classmethod
    def from_message(cls, msg) -> GimbalDeviceAttitudeStatus:
        return cls(
            int(msg.time_boot_ms) * 1000,
            tuple(msg.q),
            msg.flags,
            (msg.angular_velocity_x, msg.angular_velocity_y, msg.angular_velocity_z),
            msg.delta_yaw,
            msg.failure_flags,
            msg.gimbal_device_id,
            msg.target_system,
            msg.target_component,
        )


@dataclass(frozen=True)
class Timesync:
    """TIMESYNC (#111): ``tc1_ns`` = 0 for a request (``ts1_ns`` the requester's clock), else the answerer's
    clock with ``ts1_ns`` echoed.  ``target_*`` go out only when the dialect has them
    (:data:`TIMESYNC_HAS_TARGET`)."""

    tc1_ns: int
    ts1_ns: int
    target_system: int = 0
    target_component: int = 0

    @property
    def is_request(self) -> bool:
        return self.tc1_ns == 0

    def to_message(self):
        m = "TIMESYNC"
        args = [
            _int(m, "tc1_ns", self.tc1_ns, -(2**63), 2**63 - 1),
            _int(m, "ts1_ns", self.ts1_ns, -(2**63), 2**63 - 1),
        ]
        if TIMESYNC_HAS_TARGET:
            args += [
                _int(m, "target_system", self.target_system, 0, 255),
                _int(m, "target_component", self.target_component, 0, 255),
            ]
        return mavlink2.MAVLink_timesync_message(*args)

    @classmethod
    def from_message(cls, msg) -> Timesync:
        return cls(int(msg.tc1), int(msg.ts1), getattr(msg, "target_system", 0), getattr(msg, "target_component", 0))


def set_message_interval_message(
    target_system: int, target_component: int, msg_id: int, interval_us: int, confirmation: int = 0
):
    """COMMAND_LONG(MAV_CMD_SET_MESSAGE_INTERVAL, param1 = message id, param2 = interval us (-1 off, 0 default);
    ``confirmation`` 0 first, +1 per retransmission (capped at 255); param7 0 = the flight stack's target."""
    m = "SET_MESSAGE_INTERVAL"
    return mavlink2.MAVLink_command_long_message(
        _int(m, "target_system", target_system, 0, 255),
        _int(m, "target_component", target_component, 0, 255),
        mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL,
        min(_int(m, "confirmation", confirmation, 0, 2**31), 255),
        float(_int(m, "msg_id", msg_id, 0, 2**24 - 1)),
        float(_int(m, "interval_us", interval_us, -1, 2**31 - 1)),
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
    )


def requested_interval(param2: float, default, from_us=lambda us: us) -> tuple[bool, Any]:
    """What a received MAV_CMD_SET_MESSAGE_INTERVAL asks with its ``param2`` (microseconds), as
    ``(accepted, interval)``: -1 stops the message (None), 0 restores ``default``, N > 0 is N us
    (``from_us(N)``, in the caller's unit); NaN, a fraction (a whole number of microseconds, whose -1 and 0 are
    sentinels: -0.6 must not stop a stream nor 0.4 reset it), below -1 or beyond an int32
    (MESSAGE_INTERVAL.interval_us, which must be able to report it: ~36 min) is refused (False, None)."""
    if not math.isfinite(param2) or param2 != int(param2) or param2 < -1 or param2 > INT32_MAX:
        return False, None
    us = round(param2)
    if us == -1:
        return True, None
    if us == 0:
        return True, default
    return True, from_us(us)


def command_ack_message(
    command: int, result: int, target_system: int, target_component: int, progress: int = 0, result_param2: int = 0
):
    """COMMAND_ACK (#77) of ``command`` with MAV_RESULT ``result`` to the requester."""
    m = "COMMAND_ACK"
    return mavlink2.MAVLink_command_ack_message(
        _int(m, "command", command, 0, UINT16_MAX),
        _int(m, "result", result, 0, 255),
        _int(m, "progress", progress, 0, 255),
        _int(m, "result_param2", result_param2, -(2**31), 2**31 - 1),
        _int(m, "target_system", target_system, 0, 255),
        _int(m, "target_component", target_component, 0, 255),
    )


# --------------------------------------------------------------------------- tracking out


@dataclass(frozen=True)
class CameraTrackingImageStatus:
    """CAMERA_TRACKING_IMAGE_STATUS (#275).  Coordinates in normalised image units: x 0 = left .. 1 = right,
    y 0 = top .. 1 = bottom (``u_px / width_px``), ``radius`` normalised to the width; NaN = unknown.
    ``tracking_status``: CAMERA_TRACKING_STATUS_FLAGS bits (IDLE 0, ACTIVE 1, ERROR 2, MTI 4, COASTING 8);
    ``tracking_mode``: CAMERA_TRACKING_MODE (NONE 0, POINT 1, RECTANGLE 2); ``target_data``:
    CAMERA_TRACKING_TARGET_DATA bits; ``camera_device_id`` 0 = the sender is the camera."""

    tracking_status: int
    tracking_mode: int
    target_data: int = CAMERA_TRACKING_TARGET_DATA_IN_STATUS
    point_x: float = math.nan
    point_y: float = math.nan
    radius: float = math.nan
    rec_top_x: float = math.nan
    rec_top_y: float = math.nan
    rec_bottom_x: float = math.nan
    rec_bottom_y: float = math.nan
    camera_device_id: int = 0

    _COORDS = ("point_x", "point_y", "radius", "rec_top_x", "rec_top_y", "rec_bottom_x", "rec_bottom_y")

    def to_message(self):
        m = "CAMERA_TRACKING_IMAGE_STATUS"
        _int(m, "tracking_status", self.tracking_status, 0, 255)
        if isinstance(self.tracking_mode, bool) or self.tracking_mode not in (0, 1, 2):
            raise InputError(f"{m}.tracking_mode must be CAMERA_TRACKING_MODE 0, 1 or 2, got {self.tracking_mode!r}")
        coords = [_num(m, n, getattr(self, n), 0.0, 1.0, nan_ok=True) for n in self._COORDS]
        return mavlink2.MAVLink_camera_tracking_image_status_message(
            int(self.tracking_status),
            int(self.tracking_mode),
            _int(m, "target_data", self.target_data, 0, 255),
            *coords,
            _int(m, "camera_device_id", self.camera_device_id, 0, 6),
        )

    @classmethod
    def from_message(cls, msg) -> CameraTrackingImageStatus:
        return cls(
            msg.tracking_status,
            msg.tracking_mode,
            msg.target_data,
            msg.point_x,
            msg.point_y,
            msg.radius,
            msg.rec_top_x,
            msg.rec_top_y,
            msg.rec_bottom_x,
            msg.rec_bottom_y,
            msg.camera_device_id,
        )


@dataclass(frozen=True)
class CameraTrackingGeoStatus:
    """CAMERA_TRACKING_GEO_STATUS (#276): the target's WGS84 ``lat_deg`` / ``lon_deg`` (degE7 on the wire),
    ``alt_m`` (AMSL), 1-sigma accuracies (m, m/s, rad; NaN unknown), NED velocity (m/s; NaN unknown),
    camera-target distance ``dist_m`` and heading ``hdg_rad`` (NED; NaN unknown)."""

    lat_deg: float
    lon_deg: float
    alt_m: float
    h_acc_m: float
    v_acc_m: float
    vel_n_mps: float
    vel_e_mps: float
    vel_d_mps: float
    vel_acc_mps: float
    dist_m: float = math.nan
    hdg_rad: float = math.nan
    hdg_acc_rad: float = math.nan
    tracking_status: int = CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
    camera_device_id: int = 0

    def to_message(self):
        m = "CAMERA_TRACKING_GEO_STATUS"
        lat = _degE7(m, "lat_deg", self.lat_deg, 90.0)
        lon = _degE7(m, "lon_deg", self.lon_deg, 180.0)
        alt = _num(m, "alt_m", self.alt_m, -1e6, 1e6)
        acc = {
            n: _num(m, n, getattr(self, n), 0.0, math.inf, nan_ok=True)
            for n in ("h_acc_m", "v_acc_m", "vel_acc_mps", "dist_m", "hdg_acc_rad")
        }
        vel = {n: _num(m, n, getattr(self, n), nan_ok=True) for n in ("vel_n_mps", "vel_e_mps", "vel_d_mps", "hdg_rad")}
        return mavlink2.MAVLink_camera_tracking_geo_status_message(
            _int(m, "tracking_status", self.tracking_status, 0, 255),
            lat,
            lon,
            alt,
            acc["h_acc_m"],
            acc["v_acc_m"],
            vel["vel_n_mps"],
            vel["vel_e_mps"],
            vel["vel_d_mps"],
            acc["vel_acc_mps"],
            acc["dist_m"],
            vel["hdg_rad"],
            acc["hdg_acc_rad"],
            _int(m, "camera_device_id", self.camera_device_id, 0, 6),
        )

    @classmethod
    def from_message(cls, msg) -> CameraTrackingGeoStatus:
        return cls(
            msg.lat * 1e-7,
            msg.lon * 1e-7,
            msg.alt,
            msg.h_acc,
            msg.v_acc,
            msg.vel_n,
            msg.vel_e,
            msg.vel_d,
            msg.vel_acc,
            msg.dist,
            msg.hdg,
            msg.hdg_acc,
            msg.tracking_status,
            msg.camera_device_id,
        )


#: SET_POSITION_TARGET type_mask of a velocity-only setpoint: position (bits 0-2), acceleration (6-8), yaw (10) and
#: yaw rate (11) ignored (common.xml POSITION_TARGET_TYPEMASK)
SETPOINT_VELOCITY_ONLY_MASK = 0b1101_1100_0111


@dataclass(frozen=True)
class SetPositionTargetLocalNed:
    """SET_POSITION_TARGET_LOCAL_NED (#84), velocity only: fly ``v_ned_mps`` (NED m/s) from ``time_boot_us`` on,
    to system ``target_system`` / component ``target_component`` (ArduPilot GUIDED, PX4 OFFBOARD)."""

    time_boot_us: int
    target_system: int
    target_component: int
    v_ned_mps: tuple[float, float, float]

    def to_message(self):
        m = "SET_POSITION_TARGET_LOCAL_NED"
        vx, vy, vz = _vec(m, "v_ned_mps", self.v_ned_mps, 3)
        return mavlink2.MAVLink_set_position_target_local_ned_message(
            _time_boot_ms(m, self.time_boot_us),
            _int(m, "target_system", self.target_system, 0, 255),
            _int(m, "target_component", self.target_component, 0, 255),
            mavlink2.MAV_FRAME_LOCAL_NED,
            SETPOINT_VELOCITY_ONLY_MASK,
            0.0,
            0.0,
            0.0,
            vx,
            vy,
            vz,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
        )

    @classmethod
    def from_message(cls, msg) -> SetPositionTargetLocalNed:
        """The setpoint of a message (raises InputError for a frame or mask this type does not carry)."""
        if msg.coordinate_frame != mavlink2.MAV_FRAME_LOCAL_NED or msg.type_mask != SETPOINT_VELOCITY_ONLY_MASK:
            raise InputError(
                f"SET_POSITION_TARGET_LOCAL_NED: only velocity in MAV_FRAME_LOCAL_NED is handled, got frame "
                f"{msg.coordinate_frame} type_mask 0x{msg.type_mask:x}"
            )
        return cls(int(msg.time_boot_ms) * 1000, msg.target_system, msg.target_component, (msg.vx, msg.vy, msg.vz))


@dataclass(frozen=True)
class FollowTarget:
    """FOLLOW_TARGET (#144): the target at ``time_boot_us`` (ms on the wire), WGS84 ``lat_deg`` / ``lon_deg``,
    ``alt_m`` (AMSL), ``v_ned_mps``, 1-sigma ``h_acc_m`` / ``v_acc_m`` (position_cov's "eph epv"; third
    element 0); acceleration, attitude and rates unknown: common.xml's "unknown" values (``acc`` (0, 0, 0),
    ``attitude_q`` (1, 0, 0, 0), ``rates`` (0, 0, 0)).  ``est_capabilities`` bits
    POS 0, VEL 1 (ACCEL 2 and ATT + RATES 3 never: we estimate neither); without VEL the velocity
    must be (0, 0, 0), common.xml's "unknown"."""

    time_boot_us: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    v_ned_mps: tuple[float, float, float]
    h_acc_m: float
    v_acc_m: float
    est_capabilities: int = FOLLOW_TARGET_CAP_POS | FOLLOW_TARGET_CAP_VEL

    def to_message(self):
        m = "FOLLOW_TARGET"
        _int(m, "time_boot_us", self.time_boot_us, 0, 2**63 - 1)
        caps = _int(m, "est_capabilities", self.est_capabilities, 0, 255)
        if caps & ~(FOLLOW_TARGET_CAP_POS | FOLLOW_TARGET_CAP_VEL):
            raise InputError(f"{m}.est_capabilities: only POS (1) and VEL (2) are estimated, got {caps}")
        vel = _vec(m, "v_ned_mps", self.v_ned_mps, 3)
        if not caps & FOLLOW_TARGET_CAP_VEL and any(vel):
            raise InputError(f"{m}.v_ned_mps must be (0, 0, 0) (unknown) without the VEL bit, got {vel}")
        return mavlink2.MAVLink_follow_target_message(
            int(self.time_boot_us // 1000),
            caps,
            _degE7(m, "lat_deg", self.lat_deg, 90.0),
            _degE7(m, "lon_deg", self.lon_deg, 180.0),
            _num(m, "alt_m", self.alt_m, -1e6, 1e6),
            vel,
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0, 0.0],  # common.xml: "(1 0 0 0 for unknown)"
            [0.0, 0.0, 0.0],
            [_num(m, "h_acc_m", self.h_acc_m, 0.0), _num(m, "v_acc_m", self.v_acc_m, 0.0), 0.0],
            0,
        )

    @classmethod
    def from_message(cls, msg) -> FollowTarget:
        return cls(
            int(msg.timestamp) * 1000,
            msg.lat * 1e-7,
            msg.lon * 1e-7,
            msg.alt,
            tuple(msg.vel),
            msg.position_cov[0],
            msg.position_cov[1],
            msg.est_capabilities,
        )


# --------------------------------------------------------------------------- Track -> #275 / #276


def _unit(x: float, size: float) -> float:
    return min(max(x / size, 0.0), 1.0)


def image_status_fields(
    track, width_px: int, height_px: int, mode: int | None = None, rendered: bool = False
) -> dict[str, Any]:
    """Fields of :class:`CameraTrackingImageStatus` (#275) for a :class:`~onboard.core.track.Track` (None = idle).

    Normalised image coordinates: ``x = u_px / width_px``, ``y = v_px / height_px``, clipped to
    [0, 1].  Status ACTIVE while tracking, ACTIVE | COASTING while coasting, IDLE otherwise.
    ``mode`` (CAMERA_TRACKING_MODE): POINT fills ``point_x/point_y`` and ``radius``, the tracked
    object's: half its box's larger side over the image width (common.xml: "normalized 0..1, 0 is image
    left, 1 is image right"; QGC draws a square of that half-side), NaN without a box; RECTANGLE fills
    ``rec_*`` from the box; the other mode's fields stay NaN (common.xml).  None: RECTANGLE with a box, POINT with only a
    centre.  A mode whose data the track lacks (RECTANGLE without a box) falls back to the other one;
    NONE without either.  ``target_data`` is IN_STATUS, plus RENDERED while a target is tracked when ``rendered``
    (the video stream draws it).
    """
    nan = math.nan
    out = dict(
        tracking_status=CAMERA_TRACKING_STATUS_FLAGS_IDLE,
        tracking_mode=CAMERA_TRACKING_MODE_NONE,
        target_data=CAMERA_TRACKING_TARGET_DATA_IN_STATUS,
        point_x=nan,
        point_y=nan,
        radius=nan,
        rec_top_x=nan,
        rec_top_y=nan,
        rec_bottom_x=nan,
        rec_bottom_y=nan,
    )
    if track is None or track.state in ("searching", "lost"):
        return out
    out["tracking_status"] = CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
    if rendered:
        out["target_data"] |= CAMERA_TRACKING_TARGET_DATA_RENDERED
    if track.state == "coasting":
        out["tracking_status"] |= CAMERA_TRACKING_STATUS_FLAGS_COASTING
    if mode is None or mode == CAMERA_TRACKING_MODE_NONE:
        mode = CAMERA_TRACKING_MODE_RECTANGLE if track.bbox is not None else CAMERA_TRACKING_MODE_POINT
    if mode == CAMERA_TRACKING_MODE_RECTANGLE and track.bbox is None:
        mode = CAMERA_TRACKING_MODE_POINT
    if mode == CAMERA_TRACKING_MODE_POINT and track.u_px is None:
        mode = CAMERA_TRACKING_MODE_RECTANGLE if track.bbox is not None else CAMERA_TRACKING_MODE_NONE
    if mode == CAMERA_TRACKING_MODE_POINT:
        out["tracking_mode"] = CAMERA_TRACKING_MODE_POINT
        out["point_x"] = _unit(track.u_px, width_px)
        out["point_y"] = _unit(track.v_px, height_px)
        if track.bbox is not None:
            out["radius"] = _unit(max(track.bbox[2], track.bbox[3]) / 2.0, width_px)
    elif mode == CAMERA_TRACKING_MODE_RECTANGLE:
        x, y, w, h = track.bbox
        out["tracking_mode"] = CAMERA_TRACKING_MODE_RECTANGLE
        out["rec_top_x"], out["rec_top_y"] = _unit(x, width_px), _unit(y, height_px)
        out["rec_bottom_x"], out["rec_bottom_y"] = _unit(x + w, width_px), _unit(y + h, height_px)
    return out


def geo_status_fields(track, observable_only: bool = True) -> dict[str, Any] | None:
    """Fields of :class:`CameraTrackingGeoStatus` (#276) for a :class:`~onboard.core.track.Track`, or None
    when nothing is to be sent.

    Nothing without a position, nor (``observable_only``, the default) for a position the estimator
    does not call observable: a ground station shows #276 as a fix and cannot read a quality flag.
    Accuracies are 1-sigma root-sum-squares over axes as PX4 reports ``eph``/``evh``:
    ``h_acc = sqrt(C_nn + C_ee)``, ``v_acc = sqrt(C_dd)``, ``vel_acc = sqrt(trace C_v)``; the heading
    ``hdg = atan2(v_e, v_n)`` with ``hdg_acc = sqrt(J C_v,ne J^T)``, ``J = (-v_e, v_n) / |v_h|^2``
    (first-order propagation), NaN when the horizontal speed is below twice its own sigma; ``dist_m``
    the estimate's camera-to-target range; unknown values are NaN.
    """
    if track is None or not track.has_position or (observable_only and not track.observable):
        return None
    C = track.cov_p_ned_m2
    v = np.asarray(track.v_ned_mps)
    nan = math.nan
    vel_acc = hdg = hdg_acc = nan
    speed_h = float(math.hypot(v[0], v[1]))
    if speed_h > 0:
        hdg = math.atan2(v[1], v[0])
    if track.cov_v_ned_m2ps2 is not None:
        Cv = track.cov_v_ned_m2ps2
        vel_acc = math.sqrt(max(float(np.trace(Cv)), 0.0))
        if speed_h > 0:
            J = np.array([-v[1], v[0]]) / speed_h**2
            hdg_acc = math.sqrt(max(float(J @ Cv[:2, :2] @ J), 0.0))
            u = v[:2] / speed_h
            sigma_speed = math.sqrt(max(float(u @ Cv[:2, :2] @ u), 0.0))
            if speed_h < 2.0 * sigma_speed or hdg_acc > math.pi:
                hdg = hdg_acc = nan
    tracking_status = CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
    if track.state == "coasting":
        tracking_status |= CAMERA_TRACKING_STATUS_FLAGS_COASTING
    return dict(
        lat_deg=track.lat_deg,
        lon_deg=track.lon_deg,
        alt_m=track.alt_m,
        h_acc_m=math.sqrt(max(float(C[0, 0] + C[1, 1]), 0.0)),
        v_acc_m=math.sqrt(max(float(C[2, 2]), 0.0)),
        vel_n_mps=float(v[0]),
        vel_e_mps=float(v[1]),
        vel_d_mps=float(v[2]),
        vel_acc_mps=vel_acc,
        dist_m=track.range_m,
        hdg_rad=hdg,
        hdg_acc_rad=hdg_acc,
        tracking_status=tracking_status,
    )
