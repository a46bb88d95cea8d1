"""The simulator's observer as a MAVLink 2 autopilot (pymavlink, common dialect; thin adapter).

HEARTBEAT, SYSTEM_TIME, #31, #33, #285, TIMESYNC and COMMAND_ACK are encoded by
:mod:`onboard.io.mavlink_wire` (the daemon decodes them with the same module); the connection string
follows the one grammar (:func:`onboard.io.mavlink_endpoint.parse_endpoint`).  This module is the link and its
loop (streams' schedule, requests, services); the state and what each message says are
:mod:`groundsim.io.vehicle_messages` (no socket, no clock).

The observer is system 1, component 1 (``MAV_COMP_ID_AUTOPILOT1``) and emits, on the
simulation's boot clock (the caller passes ``time_boot_us``; nothing here reads a wall clock
for stamps, so lockstep and faster-than-real-time runs stay consistent):

===========================================  ========  =============================================
message                                      default   content
===========================================  ========  =============================================
HEARTBEAT (#0)                               1 Hz      MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_GENERIC, base_mode
                                                       MAV_MODE_GUIDED_ARMED (armed, guided, stabilised, manual
                                                       input), MAV_STATE_ACTIVE; ``guided``: ARDUPILOTMEGA,
                                                       ArduCopter's LOITER/GUIDED custom_mode, base_mode as
                                                       ArduCopter's (the same | CUSTOM_MODE_ENABLED)
SYSTEM_TIME (#2)                             1 Hz      time_unix_usec = unix time at boot + boot time
                                                       (``unix_time_at_boot_us``: ``groundsim run`` passes
                                                       the simulated UTC's; None: the wall clock's), of an
                                                       instant up to 1 ms after poll time, time_boot_ms its
                                                       boot time truncated as an autopilot's
ATTITUDE_QUATERNION (#31)                    50 Hz     q1..q4 = w, x, y, z of ``q_ned_from_body``
                                                       (body FRD -> NED, Hamilton); rollspeed,
                                                       pitchspeed, yawspeed = body rates p, q, r rad/s;
                                                       repr_offset_q = 0 (not supported, per spec)
GLOBAL_POSITION_INT (#33)                    25 Hz     lat, lon degE7; alt mm AMSL; relative_alt mm
                                                       (the state's ``alt_rel_m``: above HOME_POSITION);
                                                       vx, vy, vz cm/s NED (int16, saturated);
                                                       hdg cdeg 0..35999 (UINT16_MAX if unknown)
LOCAL_POSITION_NED (#32)                     25 Hz     #33's position in the local frame whose origin is
                                                       HOME_POSITION (as an autopilot's EKF origin where it
                                                       booted and armed): x, y m north and east on the plane
                                                       tangent at home, z m = -relative_alt (the autopilots'
                                                       height above their origin, no curvature drop); vx, vy,
                                                       vz m/s = #33's velocity unrounded; #33's rate (ArduPilot's
                                                       POSITION group) and set alike (``pos_rate_hz``)
GIMBAL_DEVICE_ATTITUDE_STATUS (#285)         10 Hz     only when ``gimballed``: q = gimbal attitude
                                                       (w, x, y, z) in the earth frame (``earth``:
                                                       YAW_IN_EARTH_FRAME | PITCH_LOCK | YAW_LOCK,
                                                       delta_yaw = vehicle yaw) or, as ArduPilot
                                                       sends it, the vehicle
                                                       frame (``vehicle``: ROLL_LOCK | PITCH_LOCK |
                                                       YAW_IN_VEHICLE_FRAME | YAW_LOCK, delta_yaw
                                                       NaN); rates NaN; gimbal_device_id 1
SYS_STATUS (#1)                              1 Hz      gyro, accel, mag, baro, GPS, AHRS, battery
                                                       present/enabled/healthy; 4S battery volts,
                                                       current, remaining (linear drain from 100 %)
EXTENDED_SYS_STATE (#245)                    1 Hz      landed_state IN_AIR
GPS_RAW_INT (#24)                            5 Hz      3D fix (RTK fixed for an RTK navigation case), 14
                                                       satellites, the #33 position, h_acc / v_acc of the
                                                       case (``gnss_accuracy``); inside ``gnss_outage_us``
                                                       no fix, 0 satellites, accuracies 0 = unknown (no #33, #32);
                                                       alt_ellipsoid = alt + GEOID_UNDULATION_M (see
                                                       :mod:`groundsim.io.vehicle_messages`)
ATTITUDE (#30)                               10 Hz     roll, pitch, yaw of ``q_ned_from_body``, rates
BATTERY_STATUS (#147)                        1 Hz      4 cells (others UINT16_MAX), current, mAh used
HOME_POSITION (#242)                         0.2 Hz    the first state's lat/lon at the altitude its
                                                       relative altitude is measured from
                                                       (``alt_amsl_m - alt_rel_m``; and on request)
AUTOPILOT_VERSION (#148)                     request   MAVLINK2 | MISSION_INT | COMMAND_INT | PARAM_ENCODE_C_CAST
                                                       | SET_POSITION_TARGET_LOCAL_NED
===========================================  ========  =============================================

A ground station's other requests: PARAM_REQUEST_LIST -> PARAM_VALUE for each of
:data:`~groundsim.io.vehicle_messages.DEFAULT_PARAMS` (REAL32), PARAM_REQUEST_READ (name or index) and PARAM_SET (stored, echoed);
MISSION_REQUEST_LIST -> MISSION_COUNT 0 of the asked mission type (no mission, fence or rally);
MISSION_CLEAR_ALL -> MISSION_ACK ACCEPTED; MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES -> AUTOPILOT_VERSION;
MAV_CMD_GET_HOME_POSITION -> HOME_POSITION; MAV_CMD_GET_MESSAGE_INTERVAL and REQUEST_MESSAGE(244, param2 = id)
-> MESSAGE_INTERVAL (-1: off, 0: not streamed); SET_MESSAGE_INTERVAL of HEARTBEAT is FAILED (as PX4).  MAVSDK reads
health, home, GPS and battery with no request DENIED (tested).

Navigation errors: ``update_state(..., nav_error=sample)`` reports the state with a
:class:`groundsim.world.nav_errors.NavErrorSample` applied (attitude error on #31 and on #285's gimbal
attitude, position offset/drift/white noise on #33's lat/lon/alt and #32's x/y/z, drift rate on their velocity);
``groundsim.app.run`` passes the run's :class:`~groundsim.world.nav_errors.NavErrorModel` sample of each tick.

Rates: SET_MESSAGE_INTERVAL of any interval > 0 is ACCEPTED and stored (MESSAGE_INTERVAL reports it back), but a
stream goes out at most once per :meth:`~MavlinkVehicle.poll`, so what is sent is capped at the poll rate without a
word: ``groundsim.app.run`` polls and updates the state on its tick, 120 Hz at 30 fps, so 1 ms is ACCEPTED and
delivered at 120 Hz, and 100 Hz comes on that tick grid (8.3 and 16.7 ms steps, 100 a second on average).
ArduPilot does the same (it caps a stream at its scheduler's rate and still ACCEPTS), hence no DENIED here; the
daemon measures what it gets (status ``link.streams``, warning ``stream_rate_low``).

Data messages (#31, #33, #32, #285) carry the *state's* ``time_boot_ms`` (when the sample is true)
and are not repeated for an unchanged state: a stream is due by its interval but waits for a
new :meth:`MavlinkVehicle.update_state` sample.  HEARTBEAT and SYSTEM_TIME carry poll time.
At most one message per stream per :meth:`~MavlinkVehicle.poll`: poll at least as fast as the
fastest stream.  A stream that fell behind restarts its schedule instead of bursting.

Services (read on every poll):

* TIMESYNC (#111) request (``tc1 == 0``): answered with ``tc1`` = our boot time in ns,
  ``ts1`` echoed, target = the requester's system/component (when the installed dialect has
  those extension fields; pymavlink 2.4.50's does not).
* COMMAND_LONG / COMMAND_INT addressed to us (target system 1 or 0, component 1 or 0):
  ``MAV_CMD_SET_MESSAGE_INTERVAL`` (param1 message id, param2 interval us: -1 disables, 0
  restores the default, > 0 sets) -> COMMAND_ACK ACCEPTED for a message id we emit, DENIED for
  any other id or a bad interval; ``MAV_CMD_REQUEST_MESSAGE`` (param1 message id) -> ACCEPTED
  and one message now when we can produce it, DENIED otherwise; REQUEST_AUTOPILOT_CAPABILITIES and
  GET_HOME_POSITION as above; ``MAV_CMD_DO_SET_MODE`` (and the SET_MODE message, acked as ArduPilot acks it, with
  its message id 11 as the command) of a guided vehicle: LOITER or GUIDED as a custom mode (param1 with
  MAV_MODE_FLAG_CUSTOM_MODE_ENABLED) ACCEPTED, any other DENIED, UNSUPPORTED without ``guided``; from then on the
  vehicle reports that mode instead of the automatic hand-over, takes setpoints in GUIDED only, and holds where it
  is when GUIDED is left (:meth:`MavlinkVehicle.take_hold`); any other command -> UNSUPPORTED.

Gimbal: ``update_state(..., q_gimbal=q_ned_from_gimbal)`` takes the gimbal's attitude in the local level where
the vehicle is, as the body's (``SimCore.vehicle_state``; :mod:`onboard.core.frames`, "Local level") (gimbal axes as the mount's in :mod:`onboard.core.frames`: x optical axis, y right, z down), i.e.
``q_ned_from_body (x) q_body_from_mount (x) q_mount_from_gimbal``.  MAVLink gimbal protocol v2
frames: "earth frame" is that local level, so q is sent as is; "vehicle frame" is it turned by the vehicle's
yaw (roll and pitch still relative to the horizon), so q is sent as
``conj(q_yaw) (x) q_ned_from_gimbal`` with ``q_yaw = quat_from_euler(0, 0, yaw)``
(:func:`gimbal_device_attitude_status`, which the lockstep eval's telemetry encodes with too).  ``earth`` sends
``delta_yaw`` = the vehicle yaw (the spec's ``q_earth = q_delta_yaw (x) q_vehicle``); ``vehicle`` is what
ArduPilot's mount sends (AP_Mount_Backend::send_gimbal_device_attitude_status and get_gimbal_device_flags): roll and
pitch always earth-locked, yaw in the vehicle frame, YAW_LOCK while it points at a location (the simulated gimbal
aims at the target), no delta_yaw (NaN), ``time_boot_ms`` when it is sent, ``gimbal_device_id`` = mount instance +
1 = 1; the receiver turns it into the earth frame with the vehicle's own attitude stream.

Garbage on the link is counted (``counters['rx_bad_data']``, ``['rx_unknown']``) and skipped by
pymavlink's resynchronising parser; a partial frame left by garbage can swallow the next two
or three real messages before it resyncs (measured), which periodic requesters ride out.

Errors: a malformed connection string is a :class:`MavlinkConfigError` (a ConfigError); a
host name that does not resolve, a port in use or a device that cannot be opened is a :class:`MavlinkLinkError`; both
:class:`~onboard.core.errors.IrtrackError`, one line, for the CLI to map to exit code 2.  Invalid
state is an :class:`~onboard.core.errors.InputError` naming the field.  Nothing received from the
network raises out of :meth:`~MavlinkVehicle.poll`.
"""

from __future__ import annotations

import errno
import logging
import math
import random
import socket
import time
from collections import Counter

import numpy as np

from groundsim.io.vehicle_messages import (
    ARDUCOPTER_GUIDED_MODE,
    ARDUCOPTER_LOITER_MODE,
    BATTERY_CELLS,
    DATA_STREAMS,
    DEFAULT_PARAMS,
    GCS_STREAM_INTERVAL_US,
    GEOID_UNDULATION_M,
    GIMBAL_FRAMES,
    MSG_ATTITUDE,
    MSG_ATTITUDE_QUATERNION,
    MSG_AUTOPILOT_VERSION,
    MSG_BATTERY_STATUS,
    MSG_EXTENDED_SYS_STATE,
    MSG_GIMBAL_DEVICE_ATTITUDE_STATUS,
    MSG_GLOBAL_POSITION_INT,
    MSG_GPS_RAW_INT,
    MSG_HEARTBEAT,
    MSG_HOME_POSITION,
    MSG_LOCAL_POSITION_NED,
    MSG_SYS_STATUS,
    MSG_SYSTEM_TIME,
    NEEDS_STATE,
    POSITION_STREAMS,
    MavlinkConfigError,
    VehicleState,
    attitude,
    autopilot_version,
    battery_remaining_pct,
    battery_status,
    check_gimbal_frame,
    extended_sys_state,
    gimbal_device_attitude_status,
    gps_raw_int,
    heartbeat,
    home_position,
    local_position_ned,
    sys_status,
)
from onboard.core.errors import ConfigError, InputError, IrtrackError
from onboard.io.mavlink_endpoint import parse_endpoint
from onboard.io.mavlink_transport import new_parser, new_signing, signature_refusal
from onboard.io.mavlink_wire import (
    INT16_MAX,
    AttitudeQuaternion,
    GimbalDeviceAttitudeStatus,
    GlobalPositionInt,
    SetPositionTargetLocalNed,
    SystemTime,
    Timesync,
    command_ack_message,
    connect,
    mavlink2,
    requested_interval,
)

__all__ = [
    "ARDUCOPTER_GUIDED_MODE",
    "ARDUCOPTER_LOITER_MODE",
    "BATTERY_CELLS",
    "DEFAULT_CONNECTION",
    "DEFAULT_PARAMS",
    "GEOID_UNDULATION_M",
    "MavlinkConfigError",
    "MavlinkLinkError",
    "VehicleState",
    "MavlinkVehicle",
    "open_mavlink2",
    "GIMBAL_FRAMES",
    "check_gimbal_frame",
    "gimbal_device_attitude_status",
]

log = logging.getLogger(__name__)

DEFAULT_CONNECTION = "udpout:127.0.0.1:14540"

_ACK_COUNTER = {
    mavlink2.MAV_RESULT_ACCEPTED: "ack_accepted",
    mavlink2.MAV_RESULT_DENIED: "ack_denied",
    mavlink2.MAV_RESULT_UNSUPPORTED: "ack_unsupported",
}

_LOG_EVERY_S = 10.0  # a repeated network complaint is logged at most this often per reason


class MavlinkLinkError(IrtrackError):
    """The MAVLink connection could not be opened (port in use, no such device, ...)."""


# --------------------------------------------------------------------------- connection


def _resolve(kind: str, host: str, port: int, connection: str) -> tuple:
    """``(family, socket type, address)`` of ``host:port``; a name that does not resolve is a MavlinkLinkError.
    Every kind is looked up before pymavlink opens it: its udpout takes any name and fails each send to one that
    does not resolve without a word, so a mistyped host had the whole run's MAVLink lost and the run exit 0."""
    stype = socket.SOCK_DGRAM if kind.startswith("udp") else socket.SOCK_STREAM
    try:
        infos = socket.getaddrinfo(host, port, 0, stype)
    except socket.gaierror as exc:
        raise MavlinkLinkError(
            f"mavlink: cannot open {connection!r}: cannot resolve {host!r} ({exc.strerror})"
        ) from None
    family, _, _, _, addr = infos[0]
    return family, stype, addr


def _probe_bind(kind: str, host: str, port: int, connection: str) -> None:
    """pymavlink binds with SO_REUSEADDR, which lets a second UDP socket share a busy port on
    Linux and hides the clash; probe with a plain bind first so "port in use" is an error."""
    family, stype, addr = _resolve(kind, host, port, connection)
    with socket.socket(family, stype) as s:
        try:
            s.bind(addr)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise MavlinkLinkError(f"mavlink: cannot open {connection!r}: port {port} already in use") from None
            raise MavlinkLinkError(f"mavlink: cannot open {connection!r}: {exc.strerror or exc}") from None


def open_mavlink2(connection: str, sysid: int, compid: int):
    """Open ``connection`` with pymavlink, speaking MAVLink 2 / common whatever the environment.

    pymavlink picks its dialect and wire version from process-wide environment variables
    (``MAVLINK20``, ``MAVLINK_DIALECT``); instead of setting them for everybody, the connection
    speaks MAVLink 2 common by :func:`onboard.io.mavlink_wire.connect`.  Returns the pymavlink
    ``mavfile``.  A malformed string is a :class:`MavlinkConfigError` naming ``--mavlink``.
    """
    try:
        ep = parse_endpoint(connection, "--mavlink")
    except ConfigError as exc:
        raise MavlinkConfigError(str(exc)) from None
    if ep.listens:
        _probe_bind(ep.kind, ep.host, ep.port, connection)
    elif ep.host is not None and ep.port is not None:
        _resolve(ep.kind, ep.host, ep.port, connection)
    try:
        conn = connect(ep, sysid, compid, autoreconnect=False, retries=0)
    except (OSError, ValueError) as exc:
        raise MavlinkLinkError(
            f"mavlink: cannot open {connection!r}: {getattr(exc, 'strerror', None) or exc}"
        ) from None
    except Exception as exc:  # noqa: BLE001 - pyserial and friends raise their own types
        raise MavlinkLinkError(f"mavlink: cannot open {connection!r}: {exc}") from None
    return conn


# --------------------------------------------------------------------------- vehicle


class MavlinkVehicle:
    """The observer's autopilot: feed it truth with :meth:`update_state`, pump it with :meth:`poll`.

    ``update_state`` may be called from another thread than ``poll`` (it swaps one immutable
    reference); ``poll`` itself is single-threaded.
    """

    def __init__(
        self,
        connection: str = DEFAULT_CONNECTION,
        sysid: int = 1,
        compid: int = 1,
        att_rate_hz: float = 50.0,
        pos_rate_hz: float = 25.0,
        gimballed: bool = False,
        gimbal_rate_hz: float = 10.0,
        gimbal_yaw_frame: str = "earth",
        unix_time_at_boot_us: int | None = None,
        guided: bool = False,
        gnss_outage_us: tuple[int, int] | None = None,
        gnss_accuracy: tuple[bool, float, float] = (False, 0.5, 0.8),
        signing_key: bytes | None = None,
    ) -> None:
        # gnss_accuracy: (RTK fix, horizontal and vertical 1-sigma, m) GPS_RAW_INT reports with a fix: the
        # navigation case's (NoiseCase.gnss_accuracy_m); the default a plain GNSS fix's
        self.gnss_rtk, self.gnss_h_acc_m, self.gnss_v_acc_m = bool(gnss_accuracy[0]), *map(float, gnss_accuracy[1:])
        # guided: heartbeat as ArduPilot and take velocity setpoints (SET_POSITION_TARGET_LOCAL_NED) in GUIDED for
        # the flight (take_setpoints); otherwise they are counted and ignored.  It reports LOITER until it has heard
        # the companion's heartbeat and sent it one more LOITER heartbeat, then GUIDED: the pilot's hand-over, which
        # the daemon's gate waits to see (a daemon that first sees GUIDED was not handed the vehicle)
        self.guided = bool(guided)
        # the mode a ground station set (MAV_CMD_DO_SET_MODE or SET_MODE: LOITER or GUIDED), which then rules over the
        # automatic hand-over: the pilot takes the vehicle back, or hands it over, as on a real autopilot
        self._pilot_mode: int | None = None
        self._hold = False  # GUIDED left for LOITER since the last take_hold: the flight holds where it is
        self._companion_heard = False
        self._loiter_after_companion = 0
        self._setpoints: list[tuple[float, float, float]] = []
        # the hand-over and the first setpoint flown are said once each: from the simulator's side nothing else shows
        # that the vehicle flew the companion's setpoints
        self._said: set[str] = set()
        for name, v in (("sysid", sysid), ("compid", compid)):
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 255:
                raise MavlinkConfigError(f"MavlinkVehicle.{name} must be an integer in [1, 255], got {v!r}")
        rates = {"att_rate_hz": att_rate_hz, "pos_rate_hz": pos_rate_hz, "gimbal_rate_hz": gimbal_rate_hz}
        for name, v in rates.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not 0 < v <= 1000:
                raise MavlinkConfigError(f"MavlinkVehicle.{name} must be in (0, 1000] Hz, got {v!r}")
        if gimbal_yaw_frame not in GIMBAL_FRAMES:
            raise MavlinkConfigError(
                f"MavlinkVehicle.gimbal_yaw_frame must be 'earth' or 'vehicle', got {gimbal_yaw_frame!r}"
            )
        self.gimbal_yaw_frame = gimbal_yaw_frame
        #: [start, end) on the boot clock without GNSS: no #33 nor #32, GPS_RAW_INT without a fix
        self.gnss_outage_us = None if gnss_outage_us is None else (int(gnss_outage_us[0]), int(gnss_outage_us[1]))
        self.connection = connection
        self.sysid = sysid
        self.compid = compid
        self.gimballed = bool(gimballed)
        self._default_interval_us: dict[int, int] = {
            MSG_HEARTBEAT: 1_000_000,
            MSG_SYSTEM_TIME: 1_000_000,
            MSG_ATTITUDE_QUATERNION: round(1e6 / att_rate_hz),
            MSG_GLOBAL_POSITION_INT: round(1e6 / pos_rate_hz),
            # ArduPilot streams both in its POSITION group (SRn_POSITION): one rate
            MSG_LOCAL_POSITION_NED: round(1e6 / pos_rate_hz),
        }
        if self.gimballed:
            self._default_interval_us[MSG_GIMBAL_DEVICE_ATTITUDE_STATUS] = round(1e6 / gimbal_rate_hz)
        self._default_interval_us.update(GCS_STREAM_INTERVAL_US)
        self._params: dict[str, float] = dict(DEFAULT_PARAMS)
        self._params["MAV_SYS_ID"], self._params["MAV_COMP_ID"] = float(sysid), float(compid)
        self._home: VehicleState | None = None
        #: current interval per stream, microseconds; None = disabled by SET_MESSAGE_INTERVAL -1
        self._interval_us: dict[int, int | None] = dict(self._default_interval_us)
        self._next_due_us: dict[int, int] = {m: 0 for m in self._interval_us}
        self._last_state_us_sent: dict[int, int] = {}
        self._oneshot: set[int] = set()
        self._state: VehicleState | None = None
        self._now_us: int | None = None
        self._unix_at_boot_us = unix_time_at_boot_us
        self._system_time_phase = random.Random(sysid)  # the same instants every run of a vehicle
        self._last_log: dict[str, float] = {}
        self.counters: Counter[str] = Counter()
        self._conn = open_mavlink2(connection, sysid, compid)
        # the daemon's parser, signed or not: with a key (signing on, as PX4 or ArduPilot with a key) everything sent
        # is signed and only verified packets are taken, a refused one counted (rx_unsigned ...), its replay rule
        self._conn.mav = new_parser(new_signing(signing_key), self._conn, sysid, compid)
        log.info("mavlink vehicle %d/%d on %s%s", sysid, compid, connection, " (signed)" if signing_key else "")

    def set_unix_time_at_boot_us(self, unix_time_at_boot_us: int) -> None:
        """UTC when the boot clock read 0 (SYSTEM_TIME, GPS_RAW_INT and HOME_POSITION's times), set again before
        the first message (a paced run puts its t = 0 on the wall clock when its loop starts)."""
        self._unix_at_boot_us = int(unix_time_at_boot_us)

    # -- inputs ---------------------------------------------------------------

    def update_state(
        self,
        time_boot_us: int,
        lat_deg: float,
        lon_deg: float,
        alt_amsl_m: float,
        alt_rel_m: float,
        v_ned_mps,
        q_ned_from_body,
        body_rates_radps,
        heading_rad: float,
        q_gimbal=None,
        nav_error=None,
    ) -> VehicleState:
        """Store the latest truth, as the autopilot reports it (validated; raises InputError naming a bad field).

        Units and frames as :class:`VehicleState`; ``q_gimbal`` is ``q_ned_from_gimbal`` (the
        gimbal's attitude in NED, see the module docstring), needed only when ``gimballed``.
        ``alt_rel_m``: the altitude above home (#33's relative_alt); home is the first sample's lat/lon at
        its ``alt_amsl_m - alt_rel_m``, so every sample's ``alt_amsl_m - alt_rel_m`` should be that same
        altitude (the simulator's is the scenario origin's: the ground the observer took off from).
        ``nav_error``: a :class:`groundsim.world.nav_errors.NavErrorSample` (or None: exact) applied by
        :func:`groundsim.world.nav_errors.reported_state` before anything is stored: #31, #33, #32 and #285 carry
        the reported attitude, position, velocity and gimbal attitude; the returned state is the reported one.
        """
        reported = dict(
            lat_deg=lat_deg,
            lon_deg=lon_deg,
            alt_amsl_m=alt_amsl_m,
            alt_rel_m=alt_rel_m,
            v_ned_mps=v_ned_mps,
            q_ned_from_body=q_ned_from_body,
            heading_rad=heading_rad,
            q_gimbal=q_gimbal,
        )
        if nav_error is not None:
            from groundsim.world.nav_errors import reported_state

            reported = reported_state(reported, nav_error)
        q_ned_from_gimbal = reported.pop("q_gimbal")
        state = VehicleState(
            time_boot_us=time_boot_us,
            body_rates_radps=body_rates_radps,
            q_ned_from_gimbal=q_ned_from_gimbal,
            **reported,
        )
        self._state = state
        if self._home is None:
            self._home = state  # home: under (or over) the first sample, at the altitude relative_alt starts from
        return state

    def message_interval_us(self, msg_id: int) -> int | None:
        """Current interval of a stream we emit (None: disabled); KeyError for others."""
        return self._interval_us[msg_id]

    # -- pump -----------------------------------------------------------------

    def poll(self, now_boot_us: int, max_messages: int = 100) -> int:
        """Service up to ``max_messages`` incoming messages, then send what is due at ``now_boot_us``.

        Returns the number of messages sent.  Never raises for anything received.
        """
        if isinstance(now_boot_us, bool) or not isinstance(now_boot_us, (int, np.integer)) or now_boot_us < 0:
            raise InputError(f"poll now_boot_us must be a non-negative integer, got {now_boot_us!r}")
        now = int(now_boot_us)
        if self._now_us is not None and now < self._now_us:
            log.info("boot clock went back from %d to %d us: schedules restart", self._now_us, now)
            self._next_due_us = {m: now for m in self._next_due_us}
            self._last_state_us_sent.clear()
        self._now_us = now
        if self._unix_at_boot_us is None:
            self._unix_at_boot_us = time.time_ns() // 1000 - now
        sent = self._service_incoming(max_messages)
        for msg_id in list(self._oneshot):
            self._oneshot.discard(msg_id)
            sent += self._send(msg_id, forced=True)
        for msg_id, interval in self._interval_us.items():
            if interval is None or now < self._next_due_us[msg_id]:
                continue
            if self._send(msg_id, forced=False):
                sent += 1
                nxt = self._next_due_us[msg_id] + interval
                self._next_due_us[msg_id] = nxt if nxt > now else now + interval
        return sent

    def close(self) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            try:
                conn.close()
            except OSError:
                pass

    def __enter__(self) -> MavlinkVehicle:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- sending --------------------------------------------------------------

    def _send(self, msg_id: int, forced: bool) -> int:
        """Send one message of stream ``msg_id``; 1 if sent, 0 if there is nothing to send."""
        mav = self._conn.mav
        now = self._now_us
        state = self._state
        if msg_id in DATA_STREAMS:
            if state is None:
                return 0
            if msg_id == MSG_GIMBAL_DEVICE_ATTITUDE_STATUS and state.q_ned_from_gimbal is None:
                return 0
            if msg_id in POSITION_STREAMS and self._no_gnss(state.time_boot_us):
                return 0
            if not forced and self._last_state_us_sent.get(msg_id) == state.time_boot_us:
                return 0
            self._last_state_us_sent[msg_id] = state.time_boot_us
        if msg_id in NEEDS_STATE and state is None:
            return 0
        try:
            if msg_id == MSG_HEARTBEAT:
                mav.send(heartbeat(self._custom_mode()).to_message())
            elif msg_id == MSG_SYSTEM_TIME:
                # an autopilot samples both clocks at an instant of its own microsecond clock and truncates the boot
                # time to ms; poll times lie on the simulation's step grid, whole ms, where the truncation would lose
                # nothing and a receiver's half-ms correction (onboard.core.utc_clock) would read 0.5 ms late
                at = now + self._system_time_phase.randrange(1000)
                mav.send(SystemTime(self._unix_at_boot_us + at, at).to_message())
            elif msg_id == MSG_ATTITUDE_QUATERNION:
                mav.send(
                    AttitudeQuaternion(state.time_boot_us, state.q_ned_from_body, state.body_rates_radps).to_message()
                )
            elif msg_id == MSG_GLOBAL_POSITION_INT:
                mav.send(self._global_position_int(state).to_message())
            elif msg_id == MSG_LOCAL_POSITION_NED:
                mav.send(local_position_ned(state, self._home or state))  # home: the first state, stored before
            elif msg_id == MSG_GIMBAL_DEVICE_ATTITUDE_STATUS:
                mav.send(self._gimbal_status(state).to_message())
            else:
                msg = self._gcs_message(msg_id, now, state)
                if msg is None:  # pragma: no cover - streams fixed at construction
                    return 0
                mav.send(msg)
        except OSError as exc:
            self._log_limited("tx_error", "mavlink send failed: %s", exc)
            self.counters["tx_error"] += 1
            return 0
        self.counters[f"tx_{msg_id}"] += 1
        return 1

    def _no_gnss(self, time_boot_us: int) -> bool:
        w = self.gnss_outage_us
        return w is not None and w[0] <= time_boot_us < w[1]

    def battery_remaining_pct(self, now_us: int) -> float:
        """The simulated battery's charge, %: linear drain from 100 % at boot."""
        return battery_remaining_pct(now_us)

    def _custom_mode(self) -> int | None:
        """The heartbeat's ArduCopter mode with ``guided`` (None: the generic autopilot): LOITER until the companion
        is heard and has been sent one more LOITER heartbeat, then GUIDED."""
        if not self.guided:
            return None
        if self._pilot_mode is not None:
            return self._pilot_mode
        if self._companion_heard and self._loiter_after_companion < 1:
            self._loiter_after_companion += 1  # this LOITER one reaches the companion listening
            return ARDUCOPTER_LOITER_MODE
        if self.in_guided and "guided" not in self._said:
            self._said.add("guided")
            log.info(
                "guided: the companion heard; mode LOITER -> GUIDED (the pilot's hand-over): its setpoints are flown"
            )
        return ARDUCOPTER_GUIDED_MODE if self.in_guided else ARDUCOPTER_LOITER_MODE

    def _gcs_message(self, msg_id: int, now: int, state: VehicleState | None):
        """The message of a ground station's stream (module docstring), or None: not ours."""
        if msg_id == MSG_SYS_STATUS:
            return sys_status(now)
        if msg_id == MSG_EXTENDED_SYS_STATE:
            return extended_sys_state()
        if msg_id == MSG_BATTERY_STATUS:
            return battery_status(now)
        if msg_id == MSG_AUTOPILOT_VERSION:
            return autopilot_version()
        if state is None:  # pragma: no cover - _send sends none of NEEDS_STATE without a state
            return None
        if msg_id == MSG_GPS_RAW_INT:
            no_fix = self._no_gnss(state.time_boot_us)
            fix = mavlink2.GPS_FIX_TYPE_RTK_FIXED if self.gnss_rtk else mavlink2.GPS_FIX_TYPE_3D_FIX
            gpi = self._global_position_int(state).to_message()  # the #33 position, quantised alike
            return gps_raw_int(
                self._unix_at_boot_us + state.time_boot_us,
                gpi,
                None if no_fix else fix,
                self.gnss_h_acc_m,
                self.gnss_v_acc_m,
            )
        if msg_id == MSG_ATTITUDE:
            return attitude(state)
        if msg_id == MSG_HOME_POSITION:
            return home_position(self._home or state, self._unix_at_boot_us + now)
        return None  # pragma: no cover - streams fixed at construction

    def _gimbal_status(self, s: VehicleState) -> GimbalDeviceAttitudeStatus:
        """GIMBAL_DEVICE_ATTITUDE_STATUS of the state in the configured frame (module docstring)."""
        return gimbal_device_attitude_status(
            s.time_boot_us, self._now_us, s.q_ned_from_gimbal, s.q_ned_from_body, self.gimbal_yaw_frame
        )

    def _global_position_int(self, s: VehicleState) -> GlobalPositionInt:
        """GLOBAL_POSITION_INT of the state, each velocity component saturated to the wire's int16 cm/s (logged)."""
        v_lim = INT16_MAX / 100.0
        v_sat = []
        for name, v in zip(("vx", "vy", "vz"), s.v_ned_mps):
            if abs(round(v * 100.0)) > INT16_MAX:
                self._log_limited(
                    "velocity_saturated", "GLOBAL_POSITION_INT %s %.1f m/s saturated to int16 cm/s", name, v
                )
                v = v_lim if v > 0 else -v_lim
            v_sat.append(v)
        return GlobalPositionInt(
            s.time_boot_us, s.lat_deg, s.lon_deg, s.alt_amsl_m, s.alt_rel_m, tuple(v_sat), s.heading_rad
        )

    # -- receiving ------------------------------------------------------------

    def _service_incoming(self, max_messages: int) -> int:
        sent = 0
        for _ in range(max_messages):
            try:
                msg = self._conn.recv_match(blocking=False)
            except Exception as exc:  # noqa: BLE001 - nothing from the wire may stop the pump
                self.counters["rx_error"] += 1
                self._log_limited("rx_error", "mavlink receive failed: %s", exc)
                break
            if msg is None:
                break
            mtype = msg.get_type()
            if mtype == "BAD_DATA":
                refused = signature_refusal(msg, self._conn.mav.sig_reject, "rx")
                self._conn.mav.sig_reject = ""
                if refused is not None:  # signing on: rx_unsigned, rx_v1_refused, rx_signature_bad|replay|stale
                    self.counters[refused] += 1
                    self._log_limited(refused, "mavlink: packet refused (%s): MAVLink 2 signing is on", refused)
                    continue
                self.counters["rx_bad_data"] += 1
                self._log_limited("rx_bad_data", "mavlink: undecodable bytes received")
                continue
            # garbage decodes as UNKNOWN_<id>: one counter for all, so noise cannot grow the dict
            self.counters["rx_unknown" if mtype.startswith("UNKNOWN") else f"rx_{mtype}"] += 1
            try:
                if mtype == "TIMESYNC":
                    sent += self._on_timesync(msg)
                elif mtype in ("COMMAND_LONG", "COMMAND_INT"):
                    sent += self._on_command(msg)
                elif mtype in ("PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET"):
                    sent += self._on_param(msg, mtype)
                elif mtype in ("MISSION_REQUEST_LIST", "MISSION_CLEAR_ALL"):
                    sent += self._on_mission(msg, mtype)
                elif mtype == "SET_POSITION_TARGET_LOCAL_NED" and self.in_guided and self._for_us(msg):
                    self._setpoints.append(SetPositionTargetLocalNed.from_message(msg).v_ned_mps)
                elif mtype == "SET_MODE" and msg.target_system == self.sysid:
                    # (deprecated, still what many ground stations send); ArduPilot acks it with the message's id
                    self._ack(mavlink2.MAVLINK_MSG_ID_SET_MODE, self._set_mode(msg.base_mode, msg.custom_mode), msg)
                    sent += 1
                elif (
                    mtype == "HEARTBEAT"
                    and msg.type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
                    and msg.get_srcSystem() == self.sysid
                    and msg.get_srcComponent() != self.compid
                ):
                    # the companion: an onboard controller of this vehicle; a ground station's heartbeat (another
                    # system, MAV_TYPE_GCS) reaching the vehicle first must not hand it over
                    self._companion_heard = True
            except Exception as exc:  # noqa: BLE001 - a malformed request must not stop the pump
                self.counters["rx_handler_error"] += 1
                self._log_limited("rx_handler_error", "mavlink: cannot handle %s: %s", mtype, exc)
        return sent

    @property
    def in_guided(self) -> bool:
        """Reporting GUIDED (``guided``, handed over to the companion, or put there by a ground station): the
        setpoints are taken."""
        if self._pilot_mode is not None:
            return self.guided and self._pilot_mode == ARDUCOPTER_GUIDED_MODE
        return self.guided and self._companion_heard and self._loiter_after_companion >= 1

    def take_hold(self) -> bool:
        """True once after a ground station switched GUIDED to LOITER: the flight is to hold where it is (LOITER)
        instead of flying the last setpoint on."""
        hold, self._hold = self._hold, False
        return hold

    def _set_mode(self, base_mode: float, custom_mode: float) -> int:
        """A ground station's mode change (``guided`` only): ArduCopter's LOITER or GUIDED as a custom mode;
        MAV_RESULT of it."""
        if not self.guided:
            return mavlink2.MAV_RESULT_UNSUPPORTED
        # (a COMMAND_LONG's param1 is a float: NaN or infinite is denied, as the other commands' params, not raised)
        if not math.isfinite(base_mode) or not int(base_mode) & mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return mavlink2.MAV_RESULT_DENIED
        if custom_mode not in (ARDUCOPTER_LOITER_MODE, ARDUCOPTER_GUIDED_MODE):
            return mavlink2.MAV_RESULT_DENIED
        was_guided, mode = self.in_guided, int(custom_mode)
        self._pilot_mode = mode
        if was_guided and mode != ARDUCOPTER_GUIDED_MODE:
            self._hold, self._setpoints = True, []
        name = "GUIDED" if mode == ARDUCOPTER_GUIDED_MODE else "LOITER"
        log.info("guided: a ground station set the mode %s%s", name, ": the companion's setpoints are flown"
                 if mode == ARDUCOPTER_GUIDED_MODE else ": the vehicle holds, setpoints are ignored")  # fmt: skip
        return mavlink2.MAV_RESULT_ACCEPTED

    def take_setpoints(self) -> list[tuple[float, float, float]]:
        """The velocity setpoints (NED m/s) received since the last call, oldest first (``guided`` only)."""
        out, self._setpoints = self._setpoints, []
        if out and "setpoint" not in self._said:
            self._said.add("setpoint")
            n, e, d = out[0]
            log.info("guided: first velocity setpoint flown: north %.2f east %.2f down %.2f m/s", n, e, d)
        return out

    def _on_timesync(self, msg) -> int:
        if msg.tc1 != 0:  # a response to somebody's request, not a request
            return 0
        if getattr(msg, "target_system", 0) not in (0, self.sysid):
            return 0
        self._conn.mav.send(
            Timesync(self._now_us * 1000, msg.ts1, msg.get_srcSystem(), msg.get_srcComponent()).to_message()
        )
        self.counters["tx_111"] += 1
        return 1

    def _for_us(self, msg) -> bool:
        return msg.target_system in (0, self.sysid) and msg.target_component in (0, self.compid)

    def _param_value(self, index: int) -> None:
        name, value = list(self._params.items())[index]
        self._conn.mav.param_value_send(name.encode(), value, mavlink2.MAV_PARAM_TYPE_REAL32, len(self._params), index)
        self.counters["tx_22"] += 1

    def _on_param(self, msg, mtype: str) -> int:
        """PARAM_REQUEST_LIST -> every PARAM_VALUE; _READ -> one (by name, or index when -1 ... ); _SET -> stored
        (REAL32) and echoed; an unknown name is ignored, as the parameter protocol says."""
        if not self._for_us(msg):
            return 0
        names = list(self._params)
        if mtype == "PARAM_REQUEST_LIST":
            for i in range(len(names)):
                self._param_value(i)
            return len(names)
        name = (
            msg.param_id.rstrip("\0") if isinstance(msg.param_id, str) else bytes(msg.param_id).rstrip(b"\0").decode()
        )
        if mtype == "PARAM_REQUEST_READ":
            index = msg.param_index if msg.param_index >= 0 else (names.index(name) if name in names else -1)
            if not 0 <= index < len(names):
                return 0
            self._param_value(index)
            return 1
        if name not in names or not math.isfinite(msg.param_value):
            return 0
        self._params[name] = float(msg.param_value)
        self._param_value(names.index(name))
        return 1

    def _on_mission(self, msg, mtype: str) -> int:
        """No mission: MISSION_REQUEST_LIST -> MISSION_COUNT 0; MISSION_CLEAR_ALL -> MISSION_ACK accepted."""
        if not self._for_us(msg):
            return 0
        mission_type = getattr(msg, "mission_type", 0)
        if mtype == "MISSION_REQUEST_LIST":
            self._conn.mav.mission_count_send(msg.get_srcSystem(), msg.get_srcComponent(), 0, mission_type)
        else:
            self._conn.mav.mission_ack_send(
                msg.get_srcSystem(), msg.get_srcComponent(), mavlink2.MAV_MISSION_ACCEPTED, mission_type
            )
        return 1

    def _on_command(self, msg) -> int:
        if msg.target_system not in (0, self.sysid) or msg.target_component not in (0, self.compid):
            return 0
        cmd = msg.command
        interval_of = None  # a MESSAGE_INTERVAL to send after the ACK: (message id, interval us)
        if cmd == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_message_interval(msg.param1, msg.param2)
        elif cmd == mavlink2.MAV_CMD_GET_MESSAGE_INTERVAL or (
            cmd == mavlink2.MAV_CMD_REQUEST_MESSAGE and msg.param1 == mavlink2.MAVLINK_MSG_ID_MESSAGE_INTERVAL
        ):
            # the interval of param1 (GET) or param2 (REQUEST_MESSAGE 244), as PX4 answers both
            asked = msg.param1 if cmd == mavlink2.MAV_CMD_GET_MESSAGE_INTERVAL else msg.param2
            interval_of = self._interval_report(asked)
            result = mavlink2.MAV_RESULT_DENIED if interval_of is None else mavlink2.MAV_RESULT_ACCEPTED
        elif cmd == mavlink2.MAV_CMD_REQUEST_MESSAGE:
            result = self._request_message(msg.param1)
        elif cmd == mavlink2.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            result = self._request_message(float(MSG_AUTOPILOT_VERSION))
        elif cmd == mavlink2.MAV_CMD_GET_HOME_POSITION:
            result = self._request_message(float(MSG_HOME_POSITION))
        elif cmd == mavlink2.MAV_CMD_DO_SET_MODE:
            result = self._set_mode(msg.param1, msg.param2)
        else:
            result = mavlink2.MAV_RESULT_UNSUPPORTED
        self._ack(cmd, result, msg)
        if interval_of is None:
            return 1
        self._conn.mav.message_interval_send(*interval_of)
        return 2

    def _ack(self, command: int, result: int, msg) -> None:
        """COMMAND_ACK of ``command`` with ``result`` to ``msg``'s sender, counted by result."""
        self._conn.mav.send(command_ack_message(command, result, msg.get_srcSystem(), msg.get_srcComponent()))
        self.counters[_ACK_COUNTER.get(result, "ack_other")] += 1

    def _interval_report(self, param: float) -> tuple[int, int] | None:
        """MESSAGE_INTERVAL's (message_id, interval_us) for a message id: -1 for a stream switched off, 0 for a
        message not streamed (common.xml: "not available"); None for an id that is not a uint16."""
        if not math.isfinite(param) or param != int(param) or not 0 <= param <= 0xFFFF:
            return None
        msg_id = int(param)
        if msg_id not in self._interval_us:
            return msg_id, 0
        interval = self._interval_us[msg_id]
        return msg_id, -1 if interval is None else int(interval)

    def _message_id(self, param: float) -> int | None:
        if not math.isfinite(param) or param != int(param):
            return None
        msg_id = int(param)
        return msg_id if msg_id in self._interval_us else None

    def _set_message_interval(self, param1: float, param2: float) -> int:
        msg_id = self._message_id(param1)
        if msg_id == MSG_HEARTBEAT:  # as PX4: every component heartbeats; switched off, the link would look lost
            return mavlink2.MAV_RESULT_FAILED
        accepted, interval_us = requested_interval(param2, self._default_interval_us.get(msg_id))
        if msg_id is None or not accepted:
            return mavlink2.MAV_RESULT_DENIED
        self._interval_us[msg_id] = interval_us
        self._next_due_us[msg_id] = self._now_us
        log.info("message %d interval set to %s us", msg_id, self._interval_us[msg_id])
        return mavlink2.MAV_RESULT_ACCEPTED

    def _request_message(self, param1: float) -> int:
        msg_id = self._message_id(param1)
        state = self._state
        if msg_id is None:
            return mavlink2.MAV_RESULT_DENIED
        if (msg_id in DATA_STREAMS or msg_id in NEEDS_STATE) and (
            state is None or (msg_id == MSG_GIMBAL_DEVICE_ATTITUDE_STATUS and state.q_ned_from_gimbal is None)
        ):
            return mavlink2.MAV_RESULT_DENIED
        self._oneshot.add(msg_id)
        return mavlink2.MAV_RESULT_ACCEPTED

    def _log_limited(self, reason: str, fmt: str, *args) -> None:
        t = time.monotonic()
        if t - self._last_log.get(reason, -math.inf) >= _LOG_EVERY_S:
            self._last_log[reason] = t
            log.warning(fmt, *args)
