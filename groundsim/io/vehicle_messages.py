"""What the simulated autopilot says, without the link: its state (:class:`VehicleState`, validated), the ids of the
messages it streams, its identity and modes (HEARTBEAT), its gimbal's GIMBAL_DEVICE_ATTITUDE_STATUS in either frame,
and the other messages it builds from the state (LOCAL_POSITION_NED and what a ground station reads of a whole vehicle:
SYS_STATUS ... AUTOPILOT_VERSION), each a pymavlink message of the common dialect.

No socket, no clock, no log: :class:`groundsim.io.mavlink_vehicle.MavlinkVehicle` schedules, sends and answers (the
link and its loop), and its module docstring tabulates what every message carries.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from onboard.core.errors import ConfigError, InputError
from onboard.core.frames import (
    FrameError,
    GeodeticOrigin,
    check_unit_quat,
    euler_from_quat,
    ned_from_geodetic,
    quat_conjugate,
    quat_from_euler,
    quat_multiply,
    quat_normalize,
)
from onboard.io.mavlink_wire import (
    INT16_MAX,
    INT32_MAX,
    UINT16_MAX,
    GimbalDeviceAttitudeStatus,
    Heartbeat,
    mavlink2,
    time_boot_ms_from_us,
)

__all__ = [
    "ARDUCOPTER_BASE_MODE",
    "ARDUCOPTER_GUIDED_MODE",
    "ARDUCOPTER_LOITER_MODE",
    "BATTERY_CELLS",
    "DATA_STREAMS",
    "DEFAULT_PARAMS",
    "GCS_STREAM_INTERVAL_US",
    "GEOID_UNDULATION_M",
    "GIMBAL_FRAMES",
    "MavlinkConfigError",
    "NEEDS_STATE",
    "POSITION_STREAMS",
    "VehicleState",
    "attitude",
    "autopilot_version",
    "battery_remaining_pct",
    "battery_status",
    "check_gimbal_frame",
    "extended_sys_state",
    "gimbal_device_attitude_status",
    "gps_raw_int",
    "heartbeat",
    "home_position",
    "local_position_ned",
    "sys_status",
]

MSG_HEARTBEAT = mavlink2.MAVLINK_MSG_ID_HEARTBEAT  # 0
MSG_SYSTEM_TIME = mavlink2.MAVLINK_MSG_ID_SYSTEM_TIME  # 2
MSG_ATTITUDE_QUATERNION = mavlink2.MAVLINK_MSG_ID_ATTITUDE_QUATERNION  # 31
MSG_GLOBAL_POSITION_INT = mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT  # 33
MSG_LOCAL_POSITION_NED = mavlink2.MAVLINK_MSG_ID_LOCAL_POSITION_NED  # 32
MSG_GIMBAL_DEVICE_ATTITUDE_STATUS = mavlink2.MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS  # 285
DATA_STREAMS = (
    MSG_ATTITUDE_QUATERNION,
    MSG_GLOBAL_POSITION_INT,
    MSG_LOCAL_POSITION_NED,
    MSG_GIMBAL_DEVICE_ATTITUDE_STATUS,
)
#: the position streams, withheld without a GNSS fix (the simulated vehicle then has no position estimate)
POSITION_STREAMS = (MSG_GLOBAL_POSITION_INT, MSG_LOCAL_POSITION_NED)
# what a ground station reads of a whole vehicle: streams at the usual rates, or on request
MSG_SYS_STATUS = mavlink2.MAVLINK_MSG_ID_SYS_STATUS  # 1
MSG_GPS_RAW_INT = mavlink2.MAVLINK_MSG_ID_GPS_RAW_INT  # 24
MSG_ATTITUDE = mavlink2.MAVLINK_MSG_ID_ATTITUDE  # 30
MSG_BATTERY_STATUS = mavlink2.MAVLINK_MSG_ID_BATTERY_STATUS  # 147
MSG_AUTOPILOT_VERSION = mavlink2.MAVLINK_MSG_ID_AUTOPILOT_VERSION  # 148
MSG_HOME_POSITION = mavlink2.MAVLINK_MSG_ID_HOME_POSITION  # 242
MSG_EXTENDED_SYS_STATE = mavlink2.MAVLINK_MSG_ID_EXTENDED_SYS_STATE  # 245
NEEDS_STATE = (MSG_GPS_RAW_INT, MSG_ATTITUDE, MSG_HOME_POSITION)
#: default intervals of the ground-station streams, us (None: only on request)
GCS_STREAM_INTERVAL_US = {
    MSG_SYS_STATUS: 1_000_000,
    MSG_EXTENDED_SYS_STATE: 1_000_000,
    MSG_GPS_RAW_INT: 200_000,
    MSG_ATTITUDE: 100_000,
    MSG_BATTERY_STATUS: 1_000_000,
    MSG_HOME_POSITION: 5_000_000,
    MSG_AUTOPILOT_VERSION: None,
}
_SENSORS = (
    mavlink2.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink2.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink2.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink2.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink2.MAV_SYS_STATUS_SENSOR_GPS
    | mavlink2.MAV_SYS_STATUS_AHRS
    | mavlink2.MAV_SYS_STATUS_SENSOR_BATTERY
)
# PARAM_ENCODE_C_CAST, not the deprecated PARAM_FLOAT it replaces (every parameter is a REAL32: the same bytes
# either way); SET_POSITION_TARGET_LOCAL_NED: a guided vehicle takes velocity setpoints
_CAPABILITIES = (
    mavlink2.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink2.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mavlink2.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink2.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
    | mavlink2.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
)
#: geoid height above the WGS84 ellipsoid (m) in the simulated world: its positions are ellipsoidal heights
#: (the NED frames of :mod:`onboard.core.frames`), reported as AMSL, so its geoid is the ellipsoid and GPS_RAW_INT's
#: alt_ellipsoid equals its alt; common.xml gives alt_ellipsoid no "unknown" value, so 0 would claim sea level
GEOID_UNDULATION_M = 0.0
BATTERY_CELLS = 4
BATTERY_FULL_V, BATTERY_EMPTY_V = 4.2, 3.5  # per cell
BATTERY_DRAIN_PCT_PER_S = 0.05  # 100 % -> 0 % in 2000 s: a long simulated flight never runs flat
BATTERY_CURRENT_A = 12.0
#: the small parameter set PARAM_REQUEST_LIST returns (name -> value; all MAV_PARAM_TYPE_REAL32)
DEFAULT_PARAMS = (
    ("MAV_SYS_ID", 1.0),
    ("MAV_COMP_ID", 1.0),
    ("MAV_TYPE", float(mavlink2.MAV_TYPE_QUADROTOR)),
    ("BAT_N_CELLS", float(BATTERY_CELLS)),
    ("BAT_CAPACITY", 5000.0),
    ("SIM_FRAME_RATE", 30.0),
)

# armed, stabilised, guided, pilot's sticks live: common.xml's MAV_MODE_GUIDED_ARMED (216), the whole mode of the
# generic autopilot, which has no custom mode; ArduCopter sets MANUAL_INPUT_ENABLED in every mode (stick mixing) and
# GUIDED_ENABLED in its position-controlled ones (LOITER, GUIDED), then CUSTOM_MODE_ENABLED beside its custom_mode
_BASE_MODE = mavlink2.MAV_MODE_GUIDED_ARMED
ARDUCOPTER_BASE_MODE = _BASE_MODE | mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


#: ArduCopter's GUIDED custom_mode: the mode the simulated vehicle reports with ``guided`` (what the daemon's
#: ``guidance.accept_custom_mode`` expects by default)
ARDUCOPTER_GUIDED_MODE = 4
#: ArduCopter's LOITER custom_mode: the guided vehicle's mode until its pilot hands it over to the companion
ARDUCOPTER_LOITER_MODE = 5


#: GIMBAL_DEVICE_ATTITUDE_STATUS's frames (:func:`gimbal_device_attitude_status`)
GIMBAL_FRAMES = ("earth", "vehicle")
#: what the simulated gimbal holds: it aims at a point of the world (the target), so its pitch and yaw are the
#: earth's (common.xml: "relative to horizon", "relative to North"); a pan/tilt on the mount, its roll about the
#: optical axis follows the mount, so no ROLL_LOCK.  YAW_LOCK also makes the
#: earth-frame q read as the earth's by a receiver of the older rule (no YAW_IN_* flag understood: YAW_LOCK set
#: means earth frame), as PX4's own gimbal status still reads it
EARTH_GIMBAL_FLAGS = (
    mavlink2.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME
    | mavlink2.GIMBAL_DEVICE_FLAGS_PITCH_LOCK
    | mavlink2.GIMBAL_DEVICE_FLAGS_YAW_LOCK
)
#: ArduPilot's #285 flags for a mount pointing at a location, sent as they are (get_gimbal_device_flags: roll and
#: pitch always earth-locked, yaw in the vehicle frame, locked on the scenery; to a receiver of the older rule its
#: YAW_LOCK says earth frame for this vehicle-frame q, as a real ArduPilot's does)
ARDUPILOT_GIMBAL_FLAGS = (
    mavlink2.GIMBAL_DEVICE_FLAGS_ROLL_LOCK
    | mavlink2.GIMBAL_DEVICE_FLAGS_PITCH_LOCK
    | mavlink2.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME
    | mavlink2.GIMBAL_DEVICE_FLAGS_YAW_LOCK
)


def check_gimbal_frame(frame: str, option: str = "--gimbal-frame") -> str:
    """``frame`` if it is one of :data:`GIMBAL_FRAMES`, else a ConfigError naming ``option``."""
    if frame not in GIMBAL_FRAMES:
        raise ConfigError(f"{option}: expected {' or '.join(GIMBAL_FRAMES)}, got {frame!r}")
    return frame


def gimbal_device_attitude_status(
    state_time_boot_us: int, send_time_boot_us: int, q_ned_from_gimbal, q_ned_from_body, frame: str
) -> GimbalDeviceAttitudeStatus:
    """GIMBAL_DEVICE_ATTITUDE_STATUS of a gimbal attitude ``q_ned_from_gimbal`` (w, x, y, z, the local level's) on a
    vehicle at ``q_ned_from_body``, in ``frame`` (module docstring, "Gimbal"): ``earth`` stamped with the state's
    time, q as is, :data:`EARTH_GIMBAL_FLAGS`, delta_yaw = the vehicle yaw; ``vehicle`` as ArduPilot sends it, stamped when sent
    (``send_time_boot_us``: ArduPilot's AP_HAL::millis() at the send), q with the vehicle's yaw taken out,
    :data:`ARDUPILOT_GIMBAL_FLAGS`, delta_yaw NaN.  Rates NaN, gimbal_device_id 1 in both."""
    if frame not in GIMBAL_FRAMES:
        raise MavlinkConfigError(f"gimbal frame must be one of {', '.join(GIMBAL_FRAMES)}, got {frame!r}")
    _, _, yaw_rad = euler_from_quat(np.asarray(q_ned_from_body, dtype=float))
    yaw_rad = float(yaw_rad)
    if frame == "earth":
        return GimbalDeviceAttitudeStatus(
            int(state_time_boot_us),
            tuple(float(c) for c in q_ned_from_gimbal),
            EARTH_GIMBAL_FLAGS,
            delta_yaw_rad=yaw_rad,
            gimbal_device_id=1,
        )
    q_yaw = quat_from_euler(0.0, 0.0, yaw_rad)
    q = quat_normalize(quat_multiply(quat_conjugate(q_yaw), np.asarray(q_ned_from_gimbal, dtype=float)))
    return GimbalDeviceAttitudeStatus(
        int(send_time_boot_us), tuple(float(c) for c in q), ARDUPILOT_GIMBAL_FLAGS, gimbal_device_id=1
    )


class MavlinkConfigError(ConfigError):
    """The MAVLink connection string or a vehicle option is invalid."""


# --------------------------------------------------------------------------- state


def _finite(name: str, value, lo: float = -math.inf, hi: float = math.inf) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"vehicle state {name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or not lo <= v <= hi:
        raise InputError(f"vehicle state {name} must be finite in [{lo}, {hi}], got {value!r}")
    return v


def _vec(name: str, value, n: int) -> tuple[float, ...]:
    try:
        v = tuple(float(x) for x in value)
    except (TypeError, ValueError):
        v = ()
    if len(v) != n or not all(math.isfinite(x) for x in v):
        raise InputError(f"vehicle state {name} must be {n} finite numbers, got {value!r}")
    return v


def _quat(name: str, value) -> tuple[float, float, float, float]:
    try:
        q = check_unit_quat(np.asarray(value, dtype=float), f"vehicle state {name}")
    except (FrameError, TypeError, ValueError) as exc:
        raise InputError(f"vehicle state {name}: {exc}") from None
    if q.shape != (4,):
        raise InputError(f"vehicle state {name} must be one quaternion (w, x, y, z), got shape {q.shape}")
    return tuple(float(x) for x in q)


@dataclass(frozen=True)
class VehicleState:
    """One truth sample of the observer, as the simulator knows it.

    time_boot_us: int, boot clock; lat_deg, lon_deg: WGS84; alt_amsl_m, alt_rel_m: metres;
    v_ned_mps: (3,) NED and q_ned_from_body: (4,) w, x, y, z, both in the local level where the vehicle is (as an
    autopilot reports them); body_rates_radps: (3,) FRD p, q, r; heading_rad: the heading (yaw), or NaN if unknown;
    q_ned_from_gimbal: (4,) (the same local level) or None.
    """

    time_boot_us: int
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    alt_rel_m: float
    v_ned_mps: tuple[float, float, float]
    q_ned_from_body: tuple[float, float, float, float]
    body_rates_radps: tuple[float, float, float]
    heading_rad: float
    q_ned_from_gimbal: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        t = self.time_boot_us
        if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or not 0 <= int(t) < 2**63:
            raise InputError(f"vehicle state time_boot_us must be a non-negative integer, got {t!r}")
        object.__setattr__(self, "time_boot_us", int(t))
        object.__setattr__(self, "lat_deg", _finite("lat_deg", self.lat_deg, -90.0, 90.0))
        object.__setattr__(self, "lon_deg", _finite("lon_deg", self.lon_deg, -180.0, 180.0))
        alt_lim = INT32_MAX / 1000.0
        object.__setattr__(self, "alt_amsl_m", _finite("alt_amsl_m", self.alt_amsl_m, -alt_lim, alt_lim))
        object.__setattr__(self, "alt_rel_m", _finite("alt_rel_m", self.alt_rel_m, -alt_lim, alt_lim))
        object.__setattr__(self, "v_ned_mps", _vec("v_ned_mps", self.v_ned_mps, 3))
        object.__setattr__(self, "q_ned_from_body", _quat("q_ned_from_body", self.q_ned_from_body))
        object.__setattr__(self, "body_rates_radps", _vec("body_rates_radps", self.body_rates_radps, 3))
        h = self.heading_rad
        h = math.nan if h is None else h
        try:
            h = float(h)
        except (TypeError, ValueError):
            raise InputError(f"vehicle state heading_rad must be a number or NaN, got {self.heading_rad!r}") from None
        if math.isinf(h):
            raise InputError(f"vehicle state heading_rad must be finite or NaN (unknown), got {h}")
        object.__setattr__(self, "heading_rad", h)
        if self.q_ned_from_gimbal is not None:
            object.__setattr__(self, "q_ned_from_gimbal", _quat("q_gimbal", self.q_ned_from_gimbal))


# --------------------------------------------------------------------------- messages built from the state


def heartbeat(custom_mode: int | None) -> Heartbeat:
    """HEARTBEAT of the generic autopilot (``custom_mode`` None: base_mode is its whole mode) or of ArduCopter in
    ``custom_mode`` (:data:`ARDUCOPTER_GUIDED_MODE`, :data:`ARDUCOPTER_LOITER_MODE`)."""
    if custom_mode is None:
        return Heartbeat(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_GENERIC, _BASE_MODE)
    return Heartbeat(
        mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, ARDUCOPTER_BASE_MODE, custom_mode
    )


def local_position_ned(s: VehicleState, home: VehicleState):
    """LOCAL_POSITION_NED of the state about ``home`` (the first state): north and east on the plane tangent at home,
    down = home's altitude - the state's, i.e. -relative_alt (as the autopilots' EKF origin height, no curvature
    drop: 8 cm at 1 km from home, 2 m at 5 km, would set z apart from #33's relative_alt); the state's velocity."""
    home_alt_m = home.alt_amsl_m - home.alt_rel_m
    n_m, e_m, _ = ned_from_geodetic(
        s.lat_deg, s.lon_deg, home_alt_m, GeodeticOrigin(home.lat_deg, home.lon_deg, home_alt_m)
    )
    return mavlink2.MAVLink_local_position_ned_message(
        time_boot_ms_from_us(s.time_boot_us), float(n_m), float(e_m), home_alt_m - s.alt_amsl_m, *s.v_ned_mps
    )


def battery_remaining_pct(now_us: int) -> float:
    """The simulated battery's charge, %: linear drain from 100 % at boot."""
    return max(100.0 - BATTERY_DRAIN_PCT_PER_S * now_us / 1e6, 0.0)


def _cell_v(pct: float) -> float:
    return BATTERY_EMPTY_V + (BATTERY_FULL_V - BATTERY_EMPTY_V) * pct / 100.0


def sys_status(now_us: int):
    """SYS_STATUS at boot time ``now_us``: every sensor present, enabled and healthy; the battery's volts, current
    and charge."""
    pct = battery_remaining_pct(now_us)
    return mavlink2.MAVLink_sys_status_message(
        _SENSORS,
        _SENSORS,
        _SENSORS,
        250,
        round(_cell_v(pct) * BATTERY_CELLS * 1000),
        round(BATTERY_CURRENT_A * 100),
        round(pct),
        0,
        0,
        0,
        0,
        0,
        0,
    )


def extended_sys_state():
    """EXTENDED_SYS_STATE: in the air."""
    return mavlink2.MAVLink_extended_sys_state_message(
        mavlink2.MAV_VTOL_STATE_UNDEFINED, mavlink2.MAV_LANDED_STATE_IN_AIR
    )


def battery_status(now_us: int):
    """BATTERY_STATUS at boot time ``now_us``: :data:`BATTERY_CELLS` cells (the others UINT16_MAX), current, mAh
    used, charge and time left."""
    pct = battery_remaining_pct(now_us)
    cells = [round(_cell_v(pct) * 1000)] * BATTERY_CELLS + [UINT16_MAX] * (10 - BATTERY_CELLS)
    used_mah = round(BATTERY_CURRENT_A * 1000 * now_us / 1e6 / 3600)
    return mavlink2.MAVLink_battery_status_message(
        0,
        mavlink2.MAV_BATTERY_FUNCTION_ALL,
        mavlink2.MAV_BATTERY_TYPE_LIPO,
        INT16_MAX,
        cells,
        round(BATTERY_CURRENT_A * 100),
        used_mah,
        -1,
        round(pct),
        round(pct / BATTERY_DRAIN_PCT_PER_S),
        mavlink2.MAV_BATTERY_CHARGE_STATE_OK,
        [0, 0, 0, 0],
        0,
        0,
    )


def gps_raw_int(time_unix_us: int, gpi, fix_type: int | None, h_acc_m: float, v_acc_m: float):
    """GPS_RAW_INT at UTC ``time_unix_us`` of the position of ``gpi`` (the state's GLOBAL_POSITION_INT message,
    quantised alike) with ``fix_type`` and 1-sigma accuracies, or without a fix (``fix_type`` None)."""
    lat, lon, alt_mm, vx, vy = gpi.lat, gpi.lon, gpi.alt, gpi.vx, gpi.vy
    vel = min(round(math.hypot(vx, vy)), UINT16_MAX - 1)
    cog = round(math.degrees(math.atan2(vy, vx)) % 360.0 * 100.0) % 36000 if vel > 0 else UINT16_MAX
    no_fix = fix_type is None
    # without a fix the uncertainty is unknown (0, as onboard.io.mavlink_wire.GpsRawInt reads it); the
    # position is then not to be used, whatever it says
    h_acc_mm, v_acc_mm = (0, 0) if no_fix else (round(h_acc_m * 1000.0), round(v_acc_m * 1000.0))
    return mavlink2.MAVLink_gps_raw_int_message(
        time_unix_us,
        mavlink2.GPS_FIX_TYPE_NO_FIX if fix_type is None else fix_type,
        lat,
        lon,
        alt_mm,
        UINT16_MAX if no_fix else 80,
        UINT16_MAX if no_fix else 120,
        # without a fix the speed and course are unknown as well (UINT16_MAX), their accuracy too (0)
        UINT16_MAX if no_fix else vel,
        UINT16_MAX if no_fix else cog,
        0 if no_fix else 14,
        alt_mm + round(GEOID_UNDULATION_M * 1000.0),
        h_acc_mm,
        v_acc_mm,
        0 if no_fix else 200,
        0,
        0,
    )


def attitude(s: VehicleState):
    """ATTITUDE: roll, pitch, yaw of the state's ``q_ned_from_body`` and its body rates."""
    roll, pitch, yaw = (float(a) for a in euler_from_quat(np.asarray(s.q_ned_from_body)))
    p, q, r = s.body_rates_radps
    return mavlink2.MAVLink_attitude_message(time_boot_ms_from_us(s.time_boot_us), roll, pitch, yaw, p, q, r)


def home_position(home: VehicleState, time_unix_us: int):
    """HOME_POSITION: the first state's lat/lon at the altitude every relative_alt is measured from."""
    return mavlink2.MAVLink_home_position_message(
        round(home.lat_deg * 1e7),
        round(home.lon_deg * 1e7),
        round((home.alt_amsl_m - home.alt_rel_m) * 1000.0),  # what every relative_alt is measured from
        0.0,
        0.0,
        0.0,
        [1.0, 0.0, 0.0, 0.0],
        0.0,
        0.0,
        0.0,
        time_unix_us,
    )


def autopilot_version():
    """AUTOPILOT_VERSION: :data:`_CAPABILITIES`, version 1.0.0, a fixed uid."""
    return mavlink2.MAVLink_autopilot_version_message(
        _CAPABILITIES, 0x01000000, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x1A2B3C4D, [0] * 18
    )
