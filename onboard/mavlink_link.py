"""Thin pymavlink adapter: autopilot telemetry in, heartbeats / rate requests / tracking status out.

Wire -> core translation happens here and only here (MAVLink common, v2 framing):

* ``ATTITUDE_QUATERNION`` (#31): ``time_boot_ms * 1000`` -> ``time_boot_us``; ``(q1, q2, q3, q4)`` is
  already ``q_ned_from_body`` (w, x, y, z; FRD body in NED); ``rollspeed, pitchspeed, yawspeed``
  (rad/s, body FRD: common.xml) -> ``omega_frd_rps`` (the pose buffer extrapolates with them) ->
  :meth:`PoseBuffer.add_attitude`.
* ``GLOBAL_POSITION_INT`` (#33): ``lat``/``lon`` degE7 -> deg, ``alt`` mm AMSL -> m,
  ``vx, vy, vz`` cm/s (north, east, down) -> ``v_ned_mps`` -> :meth:`PoseBuffer.add_position`.
  Dropout sentinels (0, INT32_MAX) are passed through and rejected (counted) by the core.
* ``GIMBAL_DEVICE_ATTITUDE_STATUS`` (#285), only when the pod is gimballed: ``q`` relative to the
  earth frame when ``GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME`` (or, legacy, ``YAW_LOCK`` without
  either frame flag) is set, else to the heading-turned "vehicle frame" ->
  :meth:`PoseBuffer.add_gimbal_status`.  Stamped with ``time_boot_ms`` when the autopilot itself
  sends it; a separate gimbal component has its own clock, so its samples are stamped on receipt
  through :class:`ClockSync` instead.  ``angular_velocity_x/y/z`` (rad/s, same frame as ``q``; NaN =
  unknown) -> ``omega_ref_rps``.  Requested at ``gimbal_rate_hz`` (50 Hz: a sample at most 20 ms
  before any frame, so a frame's gimbal extrapolation stays within its horizon).
* ``TIMESYNC`` (#111): our requests carry ``ts1 = clock_ns()``; answers feed :class:`ClockSync`;
  the autopilot's requests are answered with ``tc1 = clock_ns()``.

Out: ``HEARTBEAT`` at 1 Hz as ``MAV_TYPE_ONBOARD_CONTROLLER`` / ``MAV_AUTOPILOT_INVALID`` from
component 191 (``MAV_COMP_ID_ONBOARD_COMPUTER``) with the autopilot's system id;
``COMMAND_LONG(MAV_CMD_SET_MESSAGE_INTERVAL, param1 = message id, param2 = interval us)``, one at a
time (an ACK does not say which message it is for), retried every ``command_retry_s`` until
``COMMAND_ACK`` ACCEPTED, and re-sent after a link loss or an autopilot reboot;
``CAMERA_TRACKING_IMAGE_STATUS`` (#275) and ``CAMERA_TRACKING_GEO_STATUS`` (#276).

Link state: ``waiting`` (no autopilot heartbeat yet) -> ``connected`` -> ``lost`` (no heartbeat for
``heartbeat_timeout_s``) -> ``connected`` ...  :meth:`MavlinkLink.poll` never blocks and never
raises on bad input: random bytes and bad CRCs come back from pymavlink as ``BAD_DATA`` and are
counted as ``mavlink_bad_data``; anything else that throws is counted as ``mavlink_recv_error``.

pymavlink note: MAVLink 2 is selected by ``MAVLINK20=1`` in the environment before the connection
is made (pymavlink reads it there); this module sets it, which affects other pymavlink users in the
same process (they get MAVLink 2 as well, which every current autopilot speaks).
"""

from __future__ import annotations

import logging
import math
import os
import re
import select
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable

from pymavlink.dialects.v20 import common as mavlink2

from onboard.errors import ConfigError, InputError
from onboard.pose import ClockSync, GimbalReference, PoseBuffer, RejectCounter

__all__ = [
    "LINK_WAITING",
    "LINK_CONNECTED",
    "LINK_LOST",
    "MavlinkEndpoint",
    "parse_connection",
    "MavlinkLinkConfig",
    "LinkStatus",
    "MavlinkLink",
]

log = logging.getLogger(__name__)

LINK_WAITING = "waiting"
LINK_CONNECTED = "connected"
LINK_LOST = "lost"

DEFAULT_CONNECTION = "udpin:0.0.0.0:14540"
DEFAULT_SERIAL_BAUD = 115200

MSG_ID_ATTITUDE_QUATERNION = mavlink2.MAVLINK_MSG_ID_ATTITUDE_QUATERNION  # 31
MSG_ID_GLOBAL_POSITION_INT = mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT  # 33
MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS = mavlink2.MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS  # 285

_NOT_AUTOPILOT_TYPES = frozenset(
    {
        mavlink2.MAV_TYPE_GCS,
        mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
        mavlink2.MAV_TYPE_GIMBAL,
        mavlink2.MAV_TYPE_CAMERA,
        mavlink2.MAV_TYPE_ADSB,
    }
)
#: gimbal failures that make its reported attitude unusable (limits alone do not)
_GIMBAL_BAD_ATTITUDE = (
    mavlink2.GIMBAL_DEVICE_ERROR_FLAGS_ENCODER_ERROR
    | mavlink2.GIMBAL_DEVICE_ERROR_FLAGS_SOFTWARE_ERROR
    | mavlink2.GIMBAL_DEVICE_ERROR_FLAGS_CALIBRATION_RUNNING
)
_RESULT_NAMES = {
    v: k[len("MAV_RESULT_"):] for k, v in vars(mavlink2).items() if k.startswith("MAV_RESULT_") and k != "MAV_RESULT_ENUM_END"
}


# --------------------------------------------------------------------------- connection strings


@dataclass(frozen=True)
class MavlinkEndpoint:
    """A parsed ``--mavlink`` value: ``kind`` (udpin, udpout, tcp, tcpin, serial), pymavlink ``device``, ``baud``."""

    kind: str
    device: str
    baud: int = DEFAULT_SERIAL_BAUD


_HOSTPORT = re.compile(r"^(?P<host>[^:\s]+):(?P<port>\d+)$")


def parse_connection(connection: str, field: str = "--mavlink") -> MavlinkEndpoint:
    """Validate a connection string.

    Accepted: ``udpin:HOST:PORT`` (listen; the default ``udpin:0.0.0.0:14540``), ``udpout:HOST:PORT``,
    ``udp:HOST:PORT`` (= udpin), ``tcp:HOST:PORT`` (connect), ``tcpin:HOST:PORT`` (listen),
    ``serial:/dev/ttyX[:BAUD]`` (also ``serial:///dev/ttyX:BAUD``), ``/dev/ttyX[:BAUD]`` and
    ``/dev/ttyX,BAUD``.  Raises :class:`ConfigError` naming ``field``.
    """
    if not isinstance(connection, str) or not connection.strip():
        raise ConfigError(f"{field}: expected a MAVLink connection like {DEFAULT_CONNECTION!r}, got {connection!r}")
    text = connection.strip()
    for prefix in ("udpin", "udpout", "udp", "tcpin", "tcp"):
        if text.startswith(prefix + ":"):
            rest = text[len(prefix) + 1:]
            m = _HOSTPORT.match(rest)
            if not m or not 1 <= int(m["port"]) <= 65535:
                raise ConfigError(f"{field}: {prefix} needs HOST:PORT with PORT in 1..65535, got {connection!r}")
            kind = "udpin" if prefix == "udp" else prefix
            return MavlinkEndpoint(kind, f"{kind}:{m['host']}:{int(m['port'])}")
    if text.startswith("serial:"):
        rest = text[len("serial:"):]
        if rest.startswith("//"):
            rest = rest[2:]
        return _parse_serial(rest, connection, field)
    if text.startswith("/dev/") or text.upper().startswith("COM"):
        return _parse_serial(text, connection, field)
    raise ConfigError(
        f"{field}: unknown MAVLink connection {connection!r}; expected udpin:HOST:PORT, udpout:HOST:PORT, "
        "tcp:HOST:PORT, tcpin:HOST:PORT or serial:/dev/ttyX[:BAUD]"
    )


def _parse_serial(rest: str, original: str, field: str) -> MavlinkEndpoint:
    baud = DEFAULT_SERIAL_BAUD
    m = re.match(r"^(?P<dev>[^,:]+)(?:[,:](?P<baud>[^,:]*))?$", rest)
    if not m or not m["dev"]:
        raise ConfigError(f"{field}: serial needs a device path like /dev/ttyS0[:BAUD], got {original!r}")
    if m["baud"] is not None:
        if not m["baud"].isdigit() or int(m["baud"]) <= 0:
            raise ConfigError(f"{field}: serial baud must be a positive integer, got {m['baud']!r} in {original!r}")
        baud = int(m["baud"])
    return MavlinkEndpoint("serial", m["dev"], baud)


# --------------------------------------------------------------------------- config and status


@dataclass(frozen=True)
class MavlinkLinkConfig:
    """Timing and identity.  Seconds on the injected ``clock``; ids are MAVLink system/component ids.

    ``autopilot_sysid``: None locks onto the first autopilot heartbeat from ``autopilot_compid``.
    """

    component_id: int = mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER
    autopilot_sysid: int | None = None
    autopilot_compid: int = mavlink2.MAV_COMP_ID_AUTOPILOT1
    heartbeat_interval_s: float = 1.0
    heartbeat_timeout_s: float = 5.0
    command_retry_s: float = 1.0
    timesync_interval_s: float = 1.0
    reopen_interval_s: float = 2.0
    gimbal_rate_hz: float = 50.0
    max_outstanding_timesync: int = 16

    def __post_init__(self) -> None:
        for name in ("component_id", "autopilot_compid"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 255:
                raise ConfigError(f"MavlinkLinkConfig.{name} must be an integer in 1..255, got {v!r}")
        if self.autopilot_sysid is not None and (
            isinstance(self.autopilot_sysid, bool) or not isinstance(self.autopilot_sysid, int) or not 1 <= self.autopilot_sysid <= 255
        ):
            raise ConfigError(f"MavlinkLinkConfig.autopilot_sysid must be None or 1..255, got {self.autopilot_sysid!r}")
        for name in ("heartbeat_interval_s", "heartbeat_timeout_s", "command_retry_s", "timesync_interval_s",
                     "reopen_interval_s", "gimbal_rate_hz"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ConfigError(f"MavlinkLinkConfig.{name} must be a positive number, got {v!r}")
        if not isinstance(self.max_outstanding_timesync, int) or self.max_outstanding_timesync <= 0:
            raise ConfigError(f"MavlinkLinkConfig.max_outstanding_timesync must be a positive integer, got {self.max_outstanding_timesync!r}")


@dataclass(frozen=True)
class LinkStatus:
    """Snapshot for the status topic.  ``rates_*`` are MAVLink message ids."""

    state: str
    autopilot_sysid: int | None
    heartbeat_age_s: float | None
    rates_confirmed: tuple[int, ...]
    rates_pending: tuple[int, ...]
    rates_refused: tuple[int, ...]
    clock_synced: bool
    messages_rx: int
    link_losses: int
    reboots: int


@dataclass
class _Inflight:
    msg_id: int
    interval_us: int
    sent_s: float
    attempts: int


def _check_rate(name: str, v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise ConfigError(f"MavlinkLink.{name} must be a positive rate in Hz, got {v!r}")
    return float(v)


# --------------------------------------------------------------------------- the adapter


class MavlinkLink:
    """The autopilot link.  Drive it with :meth:`poll` (drain input) and :meth:`tick` (timers).

    ``pose_buffer`` receives the telemetry; ``counters`` counts rejected input (share it with the
    buffer).  ``clock`` (s, monotonic) drives heartbeats, timeouts and retries and can be faked in
    tests; ``clock_ns`` stamps TIMESYNC and must be the clock that stamps camera frames, so that
    :meth:`to_boot_us` maps them onto the boot clock.
    """

    def __init__(
        self,
        connection: str,
        pose_buffer: PoseBuffer,
        counters: RejectCounter,
        gimballed: bool = False,
        att_rate_hz: float = 50.0,
        pos_rate_hz: float = 25.0,
        clock: Callable[[], float] = time.monotonic,
        *,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        clock_sync: ClockSync | None = None,
        config: MavlinkLinkConfig | None = None,
    ) -> None:
        self.endpoint = parse_connection(connection)
        if bool(gimballed) != pose_buffer.mount.gimballed:
            raise ConfigError(
                f"MavlinkLink.gimballed={bool(gimballed)} disagrees with the pose buffer's mount "
                f"(CameraMount.gimballed={pose_buffer.mount.gimballed}); take both from the same config"
            )
        self.config = config if config is not None else MavlinkLinkConfig()
        self._pose = pose_buffer
        self._counters = counters
        self.gimballed = bool(gimballed)
        self._clock = clock
        self._clock_ns = clock_ns
        self.clock_sync = clock_sync if clock_sync is not None else ClockSync(counter=counters)
        rates = [
            (MSG_ID_ATTITUDE_QUATERNION, _check_rate("att_rate_hz", att_rate_hz)),
            (MSG_ID_GLOBAL_POSITION_INT, _check_rate("pos_rate_hz", pos_rate_hz)),
        ]
        if self.gimballed:
            rates.append((MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS, float(self.config.gimbal_rate_hz)))
        self.rate_plan: dict[int, int] = {mid: int(round(1e6 / hz)) for mid, hz in rates}

        self._conn = None
        self._next_open_s = -math.inf
        self.state = LINK_WAITING
        self.autopilot_sysid: int | None = self.config.autopilot_sysid
        self._last_hb_rx_s: float | None = None
        self._last_hb_tx_s = -math.inf
        self._last_ts_tx_s = -math.inf
        self._rate_queue: list[int] = []
        self._inflight: _Inflight | None = None
        self.rates_confirmed: set[int] = set()
        self.rates_refused: dict[int, int] = {}
        self._ts_outstanding: OrderedDict[int, None] = OrderedDict()
        self._seen_reboots = pose_buffer.reboots
        self.messages_rx = 0
        self.link_losses = 0
        self._open(self._now())

    # ------------------------------------------------------------------ plumbing

    def _now(self) -> float:
        return float(self._clock())

    def _open(self, now: float) -> None:
        from pymavlink import mavutil  # imported here: no pymavlink state is touched at import time

        os.environ["MAVLINK20"] = "1"
        ep = self.endpoint
        kwargs = dict(
            source_system=self.autopilot_sysid or 1,
            source_component=self.config.component_id,
            dialect="common",
        )
        if ep.kind == "tcp":
            kwargs.update(autoreconnect=True, retries=0, reconnect_delay=0.1)
        if ep.kind == "serial":
            kwargs.update(baud=ep.baud)
        try:
            self._conn = mavutil.mavlink_connection(ep.device, **kwargs)
            self._conn.robust_parsing = True
            self._conn.mav.robust_parsing = True
            log.info("MAVLink %s open on %s", ep.kind, ep.device)
        except Exception as exc:  # noqa: BLE001 - any failure to open is retried, never fatal
            self._conn = None
            self._next_open_s = now + self.config.reopen_interval_s
            self._counters.count("mavlink_open_failed", f"{ep.device}: {exc}")

    def close(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except Exception:  # noqa: BLE001
                pass
            self._conn = None

    def __enter__(self) -> "MavlinkLink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _readable(self) -> bool:
        fd = getattr(self._conn, "fd", None)
        if fd is None:
            return False
        try:
            r, _, _ = select.select([fd], [], [], 0)
        except (OSError, ValueError):
            return False
        return bool(r)

    def _send(self, what: str, fn, *args) -> bool:
        if self._conn is None:
            return False
        try:
            fn(*args)
            return True
        except Exception as exc:  # noqa: BLE001 - a send failure is counted, the loop goes on
            self._counters.count("mavlink_send_error", f"{what}: {exc}")
            return False

    def _set_autopilot(self, sysid: int) -> None:
        self.autopilot_sysid = sysid
        # pymavlink rebuilds conn.mav from conn.source_* when it switches protocol: set both
        self._conn.source_system = sysid
        self._conn.source_component = self.config.component_id
        self._conn.mav.srcSystem = sysid
        self._conn.mav.srcComponent = self.config.component_id
        log.info("autopilot is system %d; heartbeating as %d/%d", sysid, sysid, self.config.component_id)

    # ------------------------------------------------------------------ input

    def poll(self, max_messages: int = 200) -> int:
        """Handle up to ``max_messages`` waiting messages without blocking; returns how many."""
        if self._conn is None:
            return 0
        now = self._now()
        handled = 0
        spins = 0
        while handled < max_messages and spins < 2 * max_messages:
            spins += 1
            try:
                msg = self._conn.recv_msg()
            except Exception as exc:  # noqa: BLE001 - pymavlink raises on some garbage and on I/O errors
                self._counters.count("mavlink_recv_error", f"{type(exc).__name__}: {exc}")
                handled += 1
                if isinstance(exc, OSError):
                    break
                continue
            if msg is None:
                if self._readable():
                    continue
                break
            handled += 1
            self.messages_rx += 1
            try:
                self._handle(msg, now)
            except Exception as exc:  # noqa: BLE001 - a message we cannot translate is counted and dropped
                self._counters.count("mavlink_handler_error", f"{msg.get_type()}: {type(exc).__name__}: {exc}")
            self._check_reboot(now)
        if self.state == LINK_CONNECTED:
            self._service_commands(now)
        return handled

    def _handle(self, msg, now: float) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            self._counters.count("mavlink_bad_data", str(getattr(msg, "reason", "")))
            return
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        if mtype == "HEARTBEAT":
            self._on_heartbeat(msg, src_sys, src_comp, now)
            return
        if self.autopilot_sysid is None or src_sys != self.autopilot_sysid:
            return
        from_autopilot = src_comp == self.config.autopilot_compid
        if mtype == "ATTITUDE_QUATERNION" and from_autopilot:
            self._pose.add_attitude(int(msg.time_boot_ms) * 1000, (msg.q1, msg.q2, msg.q3, msg.q4),
                                    (msg.rollspeed, msg.pitchspeed, msg.yawspeed))
        elif mtype == "GLOBAL_POSITION_INT" and from_autopilot:
            self._pose.add_position(
                int(msg.time_boot_ms) * 1000,
                msg.lat * 1e-7,
                msg.lon * 1e-7,
                msg.alt * 1e-3,
                (msg.vx * 0.01, msg.vy * 0.01, msg.vz * 0.01),
            )
        elif mtype == "GIMBAL_DEVICE_ATTITUDE_STATUS" and self.gimballed:
            self._on_gimbal(msg, from_autopilot)
        elif mtype == "TIMESYNC":
            self._on_timesync(msg)
        elif mtype == "COMMAND_ACK" and from_autopilot:
            self._on_ack(msg, now)

    def _on_heartbeat(self, msg, src_sys: int, src_comp: int, now: float) -> None:
        if msg.autopilot == mavlink2.MAV_AUTOPILOT_INVALID or msg.type in _NOT_AUTOPILOT_TYPES:
            return
        if src_comp != self.config.autopilot_compid:
            return
        if self.autopilot_sysid is None:
            self._set_autopilot(src_sys)
        elif src_sys != self.autopilot_sysid:
            return
        elif self._conn.mav.srcSystem != src_sys:
            self._set_autopilot(src_sys)
        self._last_hb_rx_s = now
        if self.state != LINK_CONNECTED:
            previous = self.state
            self.state = LINK_CONNECTED
            if previous == LINK_LOST:
                log.warning("autopilot %d back; re-requesting message rates", src_sys)
            else:
                log.info("autopilot %d connected", src_sys)
            self._request_rates()
            self._last_ts_tx_s = -math.inf

    def _on_gimbal(self, msg, from_autopilot: bool) -> None:
        if msg.failure_flags & _GIMBAL_BAD_ATTITUDE:
            self._counters.count("gimbal_failure", f"failure_flags=0x{msg.failure_flags:x}")
            return
        flags = msg.flags
        if flags & mavlink2.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME:
            ref = GimbalReference.EARTH
        elif flags & mavlink2.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME:
            ref = GimbalReference.VEHICLE
        elif flags & mavlink2.GIMBAL_DEVICE_FLAGS_YAW_LOCK:
            ref = GimbalReference.EARTH
        else:
            ref = GimbalReference.VEHICLE
        if from_autopilot:
            t_us = int(msg.time_boot_ms) * 1000
        else:
            t_us = self.clock_sync.to_boot_us(self._clock_ns())
            if t_us is None:
                self._counters.count("gimbal_clock_unsynced", "gimbal sample from a separate component before TIMESYNC")
                return
        self._pose.add_gimbal_status(t_us, tuple(msg.q), ref,
                                     (msg.angular_velocity_x, msg.angular_velocity_y, msg.angular_velocity_z))

    def _on_timesync(self, msg) -> None:
        now_ns = int(self._clock_ns())
        if msg.tc1 == 0:
            self._send("TIMESYNC reply", self._conn.mav.timesync_send, now_ns, msg.ts1)
            return
        if msg.ts1 in self._ts_outstanding:
            del self._ts_outstanding[msg.ts1]
            self.clock_sync.add_exchange(int(msg.ts1), int(msg.tc1), now_ns)

    def _on_ack(self, msg, now: float) -> None:
        if msg.command != mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL or self._inflight is None:
            return
        tgt_sys = getattr(msg, "target_system", 0)
        tgt_comp = getattr(msg, "target_component", 0)
        if tgt_sys not in (0, self.autopilot_sysid) or tgt_comp not in (0, self.config.component_id):
            return  # an answer to somebody else's command
        inf = self._inflight
        result = msg.result
        if result == mavlink2.MAV_RESULT_ACCEPTED:
            self.rates_confirmed.add(inf.msg_id)
            self._inflight = None
            log.info("rate of message %d set to %d us", inf.msg_id, inf.interval_us)
        elif result == mavlink2.MAV_RESULT_IN_PROGRESS:
            inf.sent_s = now
        elif result == mavlink2.MAV_RESULT_TEMPORARILY_REJECTED:
            pass  # retried on the next timeout
        else:
            self.rates_refused[inf.msg_id] = result
            self._inflight = None
            self._counters.count(
                "rate_request_refused", f"message {inf.msg_id}: {_RESULT_NAMES.get(result, result)}"
            )

    def _check_reboot(self, now: float) -> None:
        if self._pose.reboots != self._seen_reboots:
            self._seen_reboots = self._pose.reboots
            log.warning("autopilot reboot detected; clock sync reset, message rates re-requested")
            self.clock_sync.reset()
            self._ts_outstanding.clear()
            if self.state == LINK_CONNECTED:
                self._request_rates()

    # ------------------------------------------------------------------ timers and output

    def tick(self, now: float | None = None) -> None:
        """Timers: heartbeat out, heartbeat timeout, rate-request retries, TIMESYNC requests, reopen."""
        now = self._now() if now is None else float(now)
        if self._conn is None:
            if now >= self._next_open_s:
                self._open(now)
            return
        if self.state == LINK_CONNECTED and now - self._last_hb_rx_s > self.config.heartbeat_timeout_s:
            self.state = LINK_LOST
            self.link_losses += 1
            self._inflight = None
            self._rate_queue.clear()
            self.rates_confirmed.clear()
            self._ts_outstanding.clear()
            self._counters.count("autopilot_lost", f"no heartbeat for {now - self._last_hb_rx_s:.1f} s")
        if self.autopilot_sysid is not None and now - self._last_hb_tx_s >= self.config.heartbeat_interval_s:
            self._last_hb_tx_s = now
            self._send(
                "HEARTBEAT",
                self._conn.mav.heartbeat_send,
                mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
                mavlink2.MAV_AUTOPILOT_INVALID,
                0,
                0,
                mavlink2.MAV_STATE_ACTIVE,
            )
        if self.state != LINK_CONNECTED:
            return
        self._service_commands(now)
        if now - self._last_ts_tx_s >= self.config.timesync_interval_s:
            self._last_ts_tx_s = now
            ts1 = int(self._clock_ns())
            self._ts_outstanding[ts1] = None
            while len(self._ts_outstanding) > self.config.max_outstanding_timesync:
                self._ts_outstanding.popitem(last=False)
            self._send("TIMESYNC", self._conn.mav.timesync_send, 0, ts1)

    def _request_rates(self) -> None:
        self.rates_confirmed.clear()
        self.rates_refused.clear()
        self._inflight = None
        self._rate_queue = list(self.rate_plan)

    def _service_commands(self, now: float) -> None:
        inf = self._inflight
        if inf is not None:
            if now - inf.sent_s < self.config.command_retry_s:
                return
            inf.attempts += 1
            inf.sent_s = now
            self._send_interval(inf)
            return
        if not self._rate_queue:
            return
        mid = self._rate_queue.pop(0)
        self._inflight = _Inflight(mid, self.rate_plan[mid], now, 0)
        self._send_interval(self._inflight)

    def _send_interval(self, inf: _Inflight) -> None:
        self._send(
            "SET_MESSAGE_INTERVAL",
            self._conn.mav.command_long_send,
            self.autopilot_sysid,
            self.config.autopilot_compid,
            mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL,
            min(inf.attempts, 255),  # confirmation: 0 first, +1 per retransmission
            float(inf.msg_id),
            float(inf.interval_us),
            0.0, 0.0, 0.0, 0.0,
            0.0,  # param7 response target: flight-stack default
        )

    # ------------------------------------------------------------------ tracking status out

    def send_tracking_image_status(
        self,
        tracking_status: int,
        tracking_mode: int,
        target_data: int = mavlink2.CAMERA_TRACKING_TARGET_DATA_IN_STATUS,
        point_x: float = math.nan,
        point_y: float = math.nan,
        radius: float = math.nan,
        rec_top_x: float = math.nan,
        rec_top_y: float = math.nan,
        rec_bottom_x: float = math.nan,
        rec_bottom_y: float = math.nan,
        camera_device_id: int = 0,
    ) -> bool:
        """CAMERA_TRACKING_IMAGE_STATUS (#275).  Coordinates are normalised image units: x 0 = left ..
        1 = right, y 0 = top .. 1 = bottom (``u_px / width_px``); NaN = unknown.  ``tracking_status``:
        CAMERA_TRACKING_STATUS_FLAGS bits (IDLE 0, ACTIVE 1, ERROR 2, MTI 4, COASTING 8);
        ``tracking_mode``: CAMERA_TRACKING_MODE (NONE 0, POINT 1, RECTANGLE 2); ``target_data``:
        CAMERA_TRACKING_TARGET_DATA bits.  Returns True when written.  Bad values raise InputError.
        """
        _check_uint("tracking_status", tracking_status, 255)
        if tracking_mode not in (0, 1, 2) or isinstance(tracking_mode, bool):
            raise InputError(f"tracking_mode must be CAMERA_TRACKING_MODE 0, 1 or 2, got {tracking_mode!r}")
        _check_uint("target_data", target_data, 255)
        _check_uint("camera_device_id", camera_device_id, 6)
        values = dict(point_x=point_x, point_y=point_y, radius=radius, rec_top_x=rec_top_x, rec_top_y=rec_top_y,
                      rec_bottom_x=rec_bottom_x, rec_bottom_y=rec_bottom_y)
        for name, v in values.items():
            _check_optional(name, v, 0.0, 1.0)
        if self._conn is None:
            return False
        return self._send(
            "CAMERA_TRACKING_IMAGE_STATUS",
            self._conn.mav.camera_tracking_image_status_send,
            int(tracking_status), int(tracking_mode), int(target_data),
            *(float(v) for v in values.values()),
            int(camera_device_id),
        )

    def send_tracking_geo_status(
        self,
        lat_deg: float,
        lon_deg: float,
        alt_m: float,
        h_acc_m: float,
        v_acc_m: float,
        vel_n_mps: float,
        vel_e_mps: float,
        vel_d_mps: float,
        vel_acc_mps: float,
        dist_m: float = math.nan,
        hdg_rad: float = math.nan,
        hdg_acc_rad: float = math.nan,
        tracking_status: int = mavlink2.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE,
        camera_device_id: int = 0,
    ) -> bool:
        """CAMERA_TRACKING_GEO_STATUS (#276): target WGS84 lat/lon (deg, sent as degE7), altitude AMSL
        (m), accuracies (m, m/s, rad; NaN = unknown), NED velocity (m/s; NaN = unknown), camera-target
        distance (m) and heading (rad, NED).  Returns True when written.  Bad values raise InputError.
        """
        for name, v, lo, hi in (("lat_deg", lat_deg, -90.0, 90.0), ("lon_deg", lon_deg, -180.0, 180.0),
                                ("alt_m", alt_m, -1e6, 1e6)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
                raise InputError(f"{name} must be a finite number in [{lo}, {hi}], got {v!r}")
        for name, v in (("h_acc_m", h_acc_m), ("v_acc_m", v_acc_m), ("vel_acc_mps", vel_acc_mps),
                        ("dist_m", dist_m), ("hdg_acc_rad", hdg_acc_rad)):
            _check_optional(name, v, 0.0, math.inf)
        for name, v in (("vel_n_mps", vel_n_mps), ("vel_e_mps", vel_e_mps), ("vel_d_mps", vel_d_mps),
                        ("hdg_rad", hdg_rad)):
            _check_optional(name, v, -math.inf, math.inf)
        _check_uint("tracking_status", tracking_status, 255)
        _check_uint("camera_device_id", camera_device_id, 6)
        if self._conn is None:
            return False
        return self._send(
            "CAMERA_TRACKING_GEO_STATUS",
            self._conn.mav.camera_tracking_geo_status_send,
            int(tracking_status),
            int(round(lat_deg * 1e7)),
            int(round(lon_deg * 1e7)),
            float(alt_m), float(h_acc_m), float(v_acc_m),
            float(vel_n_mps), float(vel_e_mps), float(vel_d_mps), float(vel_acc_mps),
            float(dist_m), float(hdg_rad), float(hdg_acc_rad),
            int(camera_device_id),
        )

    # ------------------------------------------------------------------ queries

    def to_boot_us(self, local_ns: int) -> int | None:
        """A ``clock_ns`` time (e.g. a frame stamp) on the autopilot boot clock; None until TIMESYNC converged."""
        return self.clock_sync.to_boot_us(local_ns)

    def status(self) -> LinkStatus:
        now = self._now()
        return LinkStatus(
            state=self.state,
            autopilot_sysid=self.autopilot_sysid,
            heartbeat_age_s=None if self._last_hb_rx_s is None else now - self._last_hb_rx_s,
            rates_confirmed=tuple(sorted(self.rates_confirmed)),
            rates_pending=tuple(([self._inflight.msg_id] if self._inflight else []) + self._rate_queue),
            rates_refused=tuple(sorted(self.rates_refused)),
            clock_synced=self.clock_sync.synced,
            messages_rx=self.messages_rx,
            link_losses=self.link_losses,
            reboots=self._pose.reboots,
        )


def _check_uint(name: str, v, hi: int) -> None:
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= hi:
        raise InputError(f"{name} must be an integer in 0..{hi}, got {v!r}")


def _check_optional(name: str, v, lo: float, hi: float) -> None:
    """NaN (unknown) or a number in [lo, hi]."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InputError(f"{name} must be a number or NaN, got {v!r}")
    if math.isnan(v):
        return
    if not (lo <= v <= hi) or math.isinf(v):
        raise InputError(f"{name} must be NaN or a finite number in [{lo}, {hi}], got {v!r}")
