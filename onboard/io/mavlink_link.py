"""Thin pymavlink adapter: autopilot telemetry in, heartbeats / rate requests / tracking status out.

Messages are encoded and decoded by :mod:`onboard.io.mavlink_wire` (units and frames there); this
module decides what to do with them (MAVLink common, v2 framing):

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
  before any frame, so a frame's gimbal extrapolation stays within its horizon).  The first report
  with a finite unit quaternion picks the gimbal followed (unless ``gimbal_device_id`` is set); such
  reports are counted (:attr:`MavlinkLink.gimbal_reports`) whatever the mount, for the watchdog.
* ``TIMESYNC`` (#111): our requests carry ``ts1 = clock_ns()``; the autopilot component's answers feed
  :class:`ClockSync` (another component's, on its own clock, are counted ``timesync_foreign``; one
  addressed to another requester is not ours; one whose clock puts the newest attitude's ``time_boot_ms``
  more than :data:`TIMESYNC_BOOT_SLACK_NS` from where it says, a UNIX epoch or microseconds, is counted
  ``timesync_implausible`` and not used); requests of the autopilot's system are answered with
  ``tc1 = clock_ns()``.  Requests and replies name their target where the dialect has the fields.
* ``GPS_RAW_INT`` (#24) of the autopilot (its default stream; not requested): fix type, satellites, DOPs and
  accuracies -> :class:`~onboard.core.gnss.GnssState` (``gnss``, the status's ``link.gnss``; the watchdog's
  ``gnss_degraded``).  A fix type outside GPS_FIX_TYPE is counted (``gps_raw_fix_type``) and dropped.
* ``SYSTEM_TIME`` (#2) of the autopilot (its default stream, about 1 Hz; not requested): ``time_boot_ms * 1000``
  and ``time_unix_usec`` feed :class:`~onboard.core.utc_clock.UtcClock` (boot clock -> UTC), reset with
  :class:`ClockSync` on a reboot; not seeded while a fresh GPS_RAW_INT reports no 3-D fix (``utc_without_fix``:
  the autopilot's UTC is then an RTC's or a ground station's, seconds off without a word).

Out: ``HEARTBEAT`` at 1 Hz as ``MAV_TYPE_ONBOARD_CONTROLLER`` / ``MAV_AUTOPILOT_INVALID`` from
component 191 (``MAV_COMP_ID_ONBOARD_COMPUTER``) with the autopilot's system id;
``COMMAND_LONG(MAV_CMD_SET_MESSAGE_INTERVAL)`` for the telemetry rates, one at a time until ACCEPTED
(:mod:`onboard.io.mavlink_rates`), and re-sent after a link loss or an autopilot reboot; the velocity setpoints and
FOLLOW_TARGET of guidance when asked.  The tracking statuses (#275, #276) go to ground stations
(:mod:`onboard.io.gcs_link`); the ``send_tracking_*`` methods here serve a deployment whose ground station shares
the autopilot's link.

Input (hostile links): UDP links use a socket of our own and parse **each datagram
alone** with a fresh parser, so a truncated or garbage datagram costs only itself
(``mavlink_truncated``, ``mavlink_bad_data``) and never swallows the next one; serial/TCP keep one
parser per stream.  A ``tcp:`` autopilot is dialled without blocking (:class:`~onboard.io.mavlink_transport.TcpDial`:
no answer within 5 s is ``mavlink_open_failed``), and its close or reset is counted ``mavlink_connection_lost`` and
dialled again after ``reopen_interval_s`` (SITL restarts; pymavlink's own reconnection blocked in every read).
Nothing is stored per message type (pymavlink's ``mavutil`` ``messages`` dict is not used): ids the common dialect lacks are dropped and counted (``mavlink_unknown_id``).
Every message of the kinds the link uses that it drops is counted, by why (message types it has no use for, the
autopilot's SYS_STATUS or VFR_HUD among them, are not); the ones that are normal traffic on a shared link (a
ground station, a companion computer, a camera) at DEBUG, so that they show in the status's ``rejected`` without a
log line at the default level:

* ``mavlink_foreign_system`` (DEBUG): any message of a system other than the followed autopilot's, but for an
  autopilot's HEARTBEAT (``autopilot_compid``, an autopilot MAV_TYPE and MAV_AUTOPILOT: a lock candidate, or
  ``second_autopilot`` once one is followed); before the lock, a HEARTBEAT that is not an autopilot's (MAV_TYPE
  GCS, onboard controller, gimbal, camera, ADS-B, or MAV_AUTOPILOT_INVALID) too;
* ``mavlink_foreign_component`` (DEBUG): ATTITUDE_QUATERNION, GLOBAL_POSITION_INT, GPS_RAW_INT, SYSTEM_TIME and
  COMMAND_ACK from a component of the autopilot's system other than ``autopilot_compid``, and a HEARTBEAT of
  that system that is not the autopilot's (another component, or typed as a GCS, a camera ...);
* ``mavlink_before_lock`` (DEBUG): a message other than HEARTBEAT while no autopilot is followed yet
  (``autopilot_sysid`` unpinned and not settled);
* ``mavlink_empty_datagram`` (DEBUG): a UDP datagram of no bytes;
* ``mavlink_signed_without_key`` (INFO, once per link): a signed packet while no signing key is configured; it is
  used as an unsigned one would be (nothing to verify it with), the log names its sender and the key to set;
* ``gimbal_attitude_invalid``: a GIMBAL_DEVICE_ATTITUDE_STATUS whose quaternion is not a finite unit one; it
  neither picks the gimbal followed nor counts as a report for the watchdog's ``gimbal_mismatch``.

Output goes only to the locked autopilot's address (``udpin``: the address its heartbeats come from, below)
or the fixed ``udpout`` address, plus ``extra_destinations``: a sender of garbage or of another
system id never becomes a recipient.  Identity and MAVLink 2 signing: see :class:`MavlinkConfig`.

One autopilot, one address (``udpin``): a second sender of its system/component is refused, a moved autopilot
followed (:mod:`onboard.io.mavlink_peer`).

Link state: ``waiting`` (no autopilot heartbeat yet) -> ``connected`` -> ``lost`` (no heartbeat for
``heartbeat_timeout_s``) -> ``connected`` ...  :meth:`MavlinkLink.poll` never blocks and never
raises on bad input: random bytes and bad CRCs come back from pymavlink as ``BAD_DATA`` and are
counted as ``mavlink_bad_data``; anything else that throws is counted as ``mavlink_recv_error``.

MAVLink 2 without the environment: UDP links parse with our own MAVLink 2 codec; serial/TCP links open
through :func:`onboard.io.mavlink_wire.connect` (``MAVLINK20`` is neither read nor set).
"""

from __future__ import annotations

import logging
import math
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from onboard.core.clock_sync import ClockSync
from onboard.core.counters import RejectCounter
from onboard.core.errors import ConfigError
from onboard.core.frames import QUAT_NORM_TOL
from onboard.core.gnss import GPS_FIX_NAMES, GnssState
from onboard.core.pose_sink import PoseSink
from onboard.core.schema import show
from onboard.core.stream_rate import StreamRate, StreamRates
from onboard.core.utc_clock import UtcClock
from onboard.io.mavlink_config import MavlinkConfig, parse_connection
from onboard.io.mavlink_fast import decode_telemetry
from onboard.io.mavlink_peer import AutopilotAddress, DuplicateSender
from onboard.io.mavlink_rates import RateRequests
from onboard.io.mavlink_transport import (
    MAX_DATAGRAM_PARSE_BYTES,
    DialFailed,
    StreamTransport,
    TcpDial,
    UdpTransport,
    new_parser,
    new_signing,
    signature_refusal,
)
from onboard.io.mavlink_wire import (
    AttitudeQuaternion,
    CameraTrackingGeoStatus,
    CameraTrackingImageStatus,
    FollowTarget,
    GimbalDeviceAttitudeStatus,
    GlobalPositionInt,
    GpsRawInt,
    Heartbeat,
    SetPositionTargetLocalNed,
    SystemTime,
    Timesync,
    connect,
)

__all__ = [
    "LINK_WAITING",
    "LINK_CONNECTED",
    "LINK_LOST",
    "parse_connection",
    "MavlinkConfig",
    "MAX_OUTSTANDING_TIMESYNC",
    "LinkStatus",
    "MavlinkLink",
    "UdpTransport",
    "new_parser",
    "MAX_DATAGRAM_PARSE_BYTES",
]

log = logging.getLogger(__name__)

LINK_WAITING = "waiting"
LINK_CONNECTED = "connected"
LINK_LOST = "lost"

MSG_ID_ATTITUDE_QUATERNION = mavlink2.MAVLINK_MSG_ID_ATTITUDE_QUATERNION  # 31
MSG_ID_GLOBAL_POSITION_INT = mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT  # 33
MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS = mavlink2.MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS  # 285
_STREAM_NAMES = {
    MSG_ID_ATTITUDE_QUATERNION: "ATTITUDE_QUATERNION",
    MSG_ID_GLOBAL_POSITION_INT: "GLOBAL_POSITION_INT",
    MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS: "GIMBAL_DEVICE_ATTITUDE_STATUS",
}

_NOT_AUTOPILOT_TYPES = frozenset(
    {
        mavlink2.MAV_TYPE_GCS,
        mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
        mavlink2.MAV_TYPE_GIMBAL,
        mavlink2.MAV_TYPE_CAMERA,
        mavlink2.MAV_TYPE_ADSB,
    }
)
#: used only from the autopilot component; another component's is counted (``mavlink_foreign_component``).
#: GIMBAL_DEVICE_ATTITUDE_STATUS and TIMESYNC are judged by their own rules (module docstring)
_AUTOPILOT_ONLY = frozenset({"ATTITUDE_QUATERNION", "GLOBAL_POSITION_INT", "GPS_RAW_INT", "SYSTEM_TIME", "COMMAND_ACK"})

# --------------------------------------------------------------------------- constants and status


#: TIMESYNC requests remembered for matching their answers (older ones are forgotten)
MAX_OUTSTANDING_TIMESYNC = 16
#: how often (s) a ``tcp:`` connection under way is looked at: a main loop that sleeps on the link's descriptor has
#: none to sleep on until the autopilot answers
DIAL_POLL_S = 0.02
#: a GPS_RAW_INT newer than this (s) says whether the receiver has a fix when SYSTEM_TIME would seed UTC
UTC_FIX_FRESH_S = 5.0
#: a TIMESYNC answer whose clock puts the autopilot's newest time_boot_ms further than this from where that
#: message says it was is on another clock (common.xml allows a UNIX-epoch one) or in other units
TIMESYNC_BOOT_SLACK_NS = 1_000_000_000


def _is_destination(dest: Any) -> bool:
    return (
        isinstance(dest, tuple)
        and len(dest) == 2
        and isinstance(dest[0], str)
        and not isinstance(dest[1], bool)
        and isinstance(dest[1], int)
        and 1 <= dest[1] <= 65535
    )


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
    gnss: dict[str, Any] | None = None  # GnssState.summary of the latest GPS_RAW_INT; None until one
    #: of messages_rx, those refused by MAVLink 2 signing (a bad signature, a replay, a stale timestamp)
    messages_refused: int = 0
    #: per requested stream (by message name): msg_id, requested_hz, measured_hz over the last seconds (None at first)
    streams: dict[str, dict[str, Any]] = field(default_factory=dict)


# --------------------------------------------------------------------------- wire: parser and transports


class _Writer:
    """The ``file`` of the sending parser: whatever it packs goes to the transport (if open)."""

    def __init__(self, link: MavlinkLink) -> None:
        self._link = link

    def write(self, buf) -> None:
        t = self._link._transport
        if t is None:
            raise OSError("link not open")
        data = bytes(buf)
        t.write(data)
        tap = self._link.raw_tap
        if tap is not None:  # the flight recorder: what we told the autopilot (setpoints, rates, FOLLOW_TARGET)
            tap(data, "autopilot", None, "tx")


# --------------------------------------------------------------------------- the adapter


class MavlinkLink:
    """The autopilot link.  Drive it with :meth:`poll` (drain input) and :meth:`tick` (timers).

    ``config``: the ``mavlink`` section (:class:`MavlinkConfig`).  ``signing_key`` (32 bytes; default: the
    section's :meth:`MavlinkConfig.signing_key`) signs everything we send with ``signing_link_id``.
    ``extra_destinations``: (host, port) pairs that receive everything we send besides the autopilot
    (UDP links only; e.g. a ground-station endpoint of mavlink-router).
    ``pose_buffer`` receives the telemetry (a :class:`~onboard.core.pose.PoseBuffer`, or the daemon's
    locked :class:`~onboard.app.shared_pose.SharedPoseBuffer`); ``counters`` counts rejected input (share it with the
    buffer).  ``clock`` (s, monotonic) drives heartbeats, timeouts and retries and can be faked in
    tests; ``clock_ns`` stamps TIMESYNC and must be the clock that stamps camera frames, so that
    :meth:`to_boot_us` maps them onto the boot clock.
    """

    def __init__(
        self,
        config: MavlinkConfig,
        pose_buffer: PoseSink,
        counters: RejectCounter,
        *,
        gimballed: bool = False,
        clock: Callable[[], float] = time.monotonic,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        clock_sync: ClockSync | None = None,
        utc_clock: UtcClock | None = None,
        signing_key: bytes | None = None,
        signing_link_id: int = 0,
        extra_destinations: tuple[tuple[str, int], ...] = (),
    ) -> None:
        if not isinstance(config, MavlinkConfig):
            raise ConfigError(f"MavlinkLink needs a MavlinkConfig, got {type(config).__name__}")
        if signing_key is None:
            signing_key = config.signing_key()
        elif not isinstance(signing_key, bytes) or len(signing_key) != 32:
            raise ConfigError(f"MavlinkLink.signing_key: expected 32 bytes, got {show(signing_key)}")
        if isinstance(signing_link_id, bool) or not isinstance(signing_link_id, int) or not 0 <= signing_link_id <= 255:
            raise ConfigError(f"MavlinkLink.signing_link_id: expected an integer in [0, 255], got {signing_link_id!r}")
        if not isinstance(extra_destinations, tuple) or not all(map(_is_destination, extra_destinations)):
            raise ConfigError(
                "MavlinkLink.extra_destinations: expected a tuple of (host, port 1..65535) pairs, "
                f"got {show(extra_destinations)}"
            )
        #: called with (bytes, link name, peer address or None, "rx" | "tx") for every read, before parsing, and
        #: every message written (the flight recorder)
        self.raw_tap: Callable[[bytes, str, Any, str], Any] | None = None
        self.config = config
        self.endpoint = parse_connection(config.connection)
        if bool(gimballed) != pose_buffer.mount.gimballed:
            raise ConfigError(
                f"MavlinkLink.gimballed={bool(gimballed)} disagrees with the pose buffer's mount "
                f"(CameraMount.gimballed={pose_buffer.mount.gimballed}); take both from the same config"
            )
        self._pose = pose_buffer
        self._counters = counters
        self.gimballed = bool(gimballed)
        self._extra_destinations = extra_destinations
        #: GIMBAL_DEVICE_ATTITUDE_STATUS messages of the autopilot's system with an attitude (a finite unit
        #: quaternion), used or not (the watchdog's gimbal check): of any gimbal, or of ``gimbal_device_id``'s alone
        #: when it is configured
        self.gimbal_reports = 0
        #: the gimbal followed (MavlinkConfig.gimbal_device_id's numbering); None until one is heard
        self.gimbal_device_id: int | None = config.gimbal_device_id
        self._clock = clock
        self._clock_ns = clock_ns
        self.clock_sync = clock_sync if clock_sync is not None else ClockSync(counter=counters)
        self.utc_clock = utc_clock if utc_clock is not None else UtcClock(counter=counters)
        rates = [
            (MSG_ID_ATTITUDE_QUATERNION, config.attitude_rate_hz),
            (MSG_ID_GLOBAL_POSITION_INT, config.position_rate_hz),
        ]
        if self.gimballed:
            rates.append((MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS, config.gimbal_rate_hz))
        rate_plan = {mid: int(round(1e6 / hz)) for mid, hz in rates}
        #: what each requested stream delivers (status ``link.streams``; the watchdog's ``stream_rate_low``)
        self.stream_rates = StreamRates({mid: (_STREAM_NAMES[mid], float(hz)) for mid, hz in rates})
        self._rates = RateRequests(config, rate_plan, self.stream_rates, counters, self._send)

        self._signing = new_signing(signing_key, signing_link_id)
        self._signed_without_key_seen = False  # mavlink_signed_without_key: counted once per link
        self._transport: UdpTransport | StreamTransport | None = None
        self._dial: TcpDial | None = None  # a tcp: connection under way
        self._stream_parser = new_parser(self._signing)  # serial/TCP: one parser per stream (new on each open)
        self._mav = new_parser(self._signing, _Writer(self), self.config.autopilot_sysid or 1, self.config.component_id)
        self._candidates: dict[int, list] = {}  # unpinned lock: sysid -> [first_s, last_s, heartbeats]
        self._address = AutopilotAddress(config, counters)  # udpin: the autopilot's address, second senders
        self._next_open_s = -math.inf
        #: why the connection could not be opened the last time it was tried (None: open, or not tried yet)
        self.open_error: str | None = None
        self.state = LINK_WAITING
        self.autopilot_sysid: int | None = self.config.autopilot_sysid
        self.autopilot_mode: tuple[int, int, int] | None = (
            None  # (MAV_AUTOPILOT, base_mode, custom_mode) of its heartbeat
        )
        #: the autopilot's home altitude (m AMSL): GLOBAL_POSITION_INT's alt minus its relative_alt (None until one)
        self.home_alt_amsl_m: float | None = None
        self.gnss: GnssState | None = None  # the latest GPS_RAW_INT (None until one)
        self._last_hb_rx_s: float | None = None
        self._last_hb_tx_s = -math.inf
        self._last_ts_tx_s = -math.inf
        self._ts_outstanding: OrderedDict[int, None] = OrderedDict()
        self._boot_seen: tuple[int, int] | None = None  # (our clock_ns, time_boot_us) of the newest attitude
        self._seen_reboots = pose_buffer.reboots
        self.messages_rx = 0
        self.messages_refused = 0  # of them, refused by signing: they say nothing of the autopilot
        self.link_losses = 0
        self._open(self._now())

    # ------------------------------------------------------------------ plumbing

    def _now(self) -> float:
        return float(self._clock())

    def _open(self, now: float) -> None:
        """Open the connection; a ``tcp:`` one is begun without blocking and finished by :meth:`_settle_dial`."""
        ep = self.endpoint
        try:
            if ep.kind in ("udpin", "udpout"):
                _, host, port = ep.device.split(":")
                self._transport = UdpTransport(ep.kind, host, int(port), self._extra_destinations)
            elif ep.kind == "tcp":
                self._dial = TcpDial(ep, now)
                self._settle_dial(now)  # on loopback the answer (accepted or refused) is already in
                return
            else:
                self._transport = StreamTransport(connect(ep, self.autopilot_sysid or 1, self.config.component_id))
                self._stream_parser = new_parser(self._signing)
            self._opened()
        except Exception as exc:  # noqa: BLE001 - any failure to open is retried, never fatal
            self._open_failed(now, str(exc))

    def _opened(self) -> None:
        ep = self.endpoint
        log.info("MAVLink %s open on %s%s", ep.kind, ep.device, " (signed)" if self._signing.secret_key else "")
        self.open_error = None

    def _open_failed(self, now: float, why: str) -> None:
        self._transport = None
        self._next_open_s = now + self.config.reopen_interval_s
        self.open_error = why
        self._counters.count("mavlink_open_failed", f"{self.endpoint.device}: {why}")

    def _settle_dial(self, now: float) -> None:
        """Finish a ``tcp:`` connection under way once the autopilot has answered, or count it failed (refused, or no
        answer within :data:`~onboard.io.mavlink_transport.TCP_CONNECT_TIMEOUT_S`) and dial again after
        ``reopen_interval_s``."""
        dial = self._dial
        if dial is None:
            return
        try:
            conn = dial.settle(now, self.autopilot_sysid or 1, self.config.component_id)
        except DialFailed as exc:
            self._dial = None
            self._open_failed(now, str(exc))
            return
        if conn is not None:
            self._dial = None
            self._transport = StreamTransport(conn)
            self._stream_parser = new_parser(self._signing)
            self._opened()

    def _mark_lost(self) -> None:
        """The link is lost (no heartbeat for ``heartbeat_timeout_s``, or its connection gone): what the autopilot
        said of itself (its mode, the rates it confirmed, the TIMESYNC requests) no longer holds; its next heartbeat
        connects it again."""
        self.state = LINK_LOST
        self.link_losses += 1
        self.autopilot_mode = None
        self._rates.forget()
        self._ts_outstanding.clear()

    def _lost(self, now: float) -> None:
        """The autopilot closed or reset the ``tcp:`` connection: the link is lost at once (nothing more can come
        on it: a setpoint gate must not wait for the heartbeat timeout), closed here and dialled again after
        ``reopen_interval_s`` (pymavlink would dial again at once, on every read, blocking)."""
        if self.state == LINK_CONNECTED:
            self._mark_lost()
        self.close()
        self._next_open_s = now + self.config.reopen_interval_s
        self.open_error = "closed by the autopilot"
        self._counters.count(
            "mavlink_connection_lost",
            f"{self.endpoint.device}: closed by the autopilot; dialled again every {self.config.reopen_interval_s:g} s",
        )

    def close(self) -> None:
        if self._dial is not None:
            self._dial.close()
            self._dial = None
        if self._transport is not None:
            try:
                self._transport.close()
            except Exception:  # noqa: BLE001
                pass
            self._transport = None

    def __enter__(self) -> MavlinkLink:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def fileno(self) -> int | None:
        """The input file descriptor (for select), None while closed."""
        return None if self._transport is None else self._transport.fileno()

    def seconds_to_next_due(self) -> float:
        """How long until :meth:`tick` has something to do (0 when overdue, inf when nothing is
        scheduled): the next heartbeat out, heartbeat-timeout check, TIMESYNC request, rate-request
        retry or reopen.  For a caller that sleeps until input arrives (:meth:`fileno`) or this."""
        now = self._now()
        if self._dial is not None:  # its answer is looked for by tick, not waited for on a descriptor
            return DIAL_POLL_S
        if self._transport is None:
            return max(self._next_open_s - now, 0.0)
        cfg = self.config
        due = [self._last_hb_tx_s + cfg.heartbeat_interval_s] if self.autopilot_sysid is not None else []
        if self.state == LINK_CONNECTED and self._last_hb_rx_s is not None:  # connected: a heartbeat came
            due += [self._last_hb_rx_s + cfg.heartbeat_timeout_s, self._last_ts_tx_s + cfg.timesync_interval_s]
            due += self._rates.due_s(now)
        return max(min(due, default=math.inf) - now, 0.0)

    @property
    def peer_address(self):
        """Where UDP output goes besides ``extra_destinations``: the locked autopilot's address (udpin)."""
        t = self._transport
        if isinstance(t, UdpTransport) and t.fixed:
            return t.fixed
        return None if t is None else getattr(t, "peer", None)

    def _send(self, what: str, msg) -> bool:
        """Write one message (a pymavlink message from :mod:`onboard.io.mavlink_wire`); False when closed or failed."""
        if self._transport is None:
            return False
        try:
            self._mav.send(msg)
            return True
        except Exception as exc:  # noqa: BLE001 - a send failure is counted, the loop goes on
            self._counters.count("mavlink_send_error", f"{what}: {exc}")
            return False

    def _set_autopilot(self, sysid: int) -> None:
        self.autopilot_sysid = sysid
        self._mav.srcSystem = sysid
        self._mav.srcComponent = self.config.component_id
        log.info("autopilot is system %d; heartbeating as %d/%d", sysid, sysid, self.config.component_id)

    # ------------------------------------------------------------------ input

    def poll(self, max_messages: int = 200) -> int:
        """Handle up to ``max_messages`` waiting messages (and at most as many reads) without blocking.

        UDP: each datagram is parsed alone by a fresh parser, so a truncated or garbage datagram
        costs only itself (``mavlink_truncated``, ``mavlink_bad_data``); datagrams over
        ``MAX_DATAGRAM_PARSE_BYTES`` are dropped unparsed (``mavlink_datagram_too_large``).
        Serial/TCP: one parser per stream.  Returns how many messages were handled."""
        if self._transport is None:
            return 0
        now = self._now()
        handled = 0
        reads = 0
        while handled < max_messages and reads < max_messages:
            reads += 1
            try:
                got = self._transport.read()
            except Exception as exc:  # noqa: BLE001 - I/O errors are counted, never fatal
                if not getattr(self._transport, "lost", False):  # a reset tcp: connection is counted once, below
                    self._counters.count("mavlink_recv_error", f"{type(exc).__name__}: {exc}")
                break
            if got is None:
                break
            data, addr = got
            if data:
                if self.raw_tap is not None:  # the flight recorder: the bytes as read, before any parsing
                    self.raw_tap(data, "autopilot", addr, "rx")
                handled += self._feed(data, addr, now)
            elif addr is not None:  # a datagram with no bytes (None: the ICMP error of an earlier send, not input)
                self._counters.count("mavlink_empty_datagram", f"from {addr}", level=logging.DEBUG)
        transport = self._transport
        if isinstance(transport, StreamTransport) and transport.lost:
            self._lost(now)
            return handled
        if self.state == LINK_CONNECTED:
            self._rates.service(now, self.autopilot_sysid)
        return handled

    def _feed(self, data: bytes, addr, now: float) -> int:
        datagram = self._transport is not None and self._transport.datagrams
        if datagram:
            if len(data) > MAX_DATAGRAM_PARSE_BYTES:
                self._counters.count("mavlink_datagram_too_large", f"{len(data)} bytes from {addr}")
                return 0
            fast = None if self._signing.secret_key else decode_telemetry(data)  # 100 + 25 Hz: see mavlink_fast
            if fast is not None:
                self._dispatch(fast, "", addr, now)
                return 1
            parser = new_parser(self._signing)
        else:
            parser = self._stream_parser
        n = 0
        parser.sig_reject = ""
        try:
            msg = parser.parse_char(data)
            while msg is not None:
                n += 1
                self._dispatch(msg, parser.sig_reject, addr, now)
                parser.sig_reject = ""
                msg = parser.parse_char(b"")
        except Exception as exc:  # noqa: BLE001 - pymavlink raises on some garbage
            self._counters.count("mavlink_recv_error", f"{type(exc).__name__}: {exc}")
            if not datagram:
                self._stream_parser = new_parser(self._signing)
        if datagram and parser.buf_len() > 0:
            self._counters.count("mavlink_truncated", f"{parser.buf_len()} bytes left over in a datagram from {addr}")
        return n

    def _dispatch(self, msg, sig_reject: str, addr, now: float) -> None:
        self.messages_rx += 1
        try:
            self._handle(msg, now, sig_reject, addr)
        except Exception as exc:  # noqa: BLE001 - a message we cannot translate is counted and dropped
            self._counters.count("mavlink_handler_error", f"{msg.get_type()}: {type(exc).__name__}: {exc}")
        self._check_reboot(now)

    def _handle(self, msg, now: float, sig_reject: str = "", addr=None) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            reason = str(getattr(msg, "reason", ""))
            refused = signature_refusal(msg, sig_reject, "mavlink")
            if refused is not None:
                self.messages_refused += 1
                self._counters.count(refused, "packet refused: MAVLink 2 signing is on")
            else:
                self._counters.count("mavlink_bad_data", reason)
            return
        if mtype.startswith("UNKNOWN_"):
            self._counters.count(
                "mavlink_unknown_id", f"message id {mtype[len('UNKNOWN_') :]} not in the common dialect"
            )
            return
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        if not self._signed_without_key_seen and not self._signing.secret_key:
            header = getattr(msg, "_header", None)  # the unsigned fast path's messages carry none
            if header is not None and header.incompat_flags & mavlink2.MAVLINK_IFLAG_SIGNED:
                # without a key the signature cannot be checked, so the frame is taken as an unsigned one would be;
                # said once: a signing vehicle means a key is missing here, not that anything is wrong with it
                self._signed_without_key_seen = True
                self._counters.count(
                    "mavlink_signed_without_key",
                    f"{mtype} from {src_sys}/{src_comp} is signed but no key is configured: its signature is not "
                    "checked; set mavlink.signing_key_file (mavlink signing keys) to verify it",
                    level=logging.INFO,
                )
        if mtype == "HEARTBEAT":
            self._on_heartbeat(msg, src_sys, src_comp, now, addr)
            return
        if self.autopilot_sysid is None:
            self._counters.count(
                "mavlink_before_lock",
                f"{mtype} from {src_sys}/{src_comp}: no autopilot followed yet",
                level=logging.DEBUG,
            )
            return
        if src_sys != self.autopilot_sysid:
            self._foreign(mtype, src_sys, src_comp)
            return
        if addr is not None and self._address.refuses(self._transport, mtype, src_comp, addr, self.autopilot_sysid):
            return
        from_autopilot = src_comp == self.config.autopilot_compid
        if not from_autopilot and mtype in _AUTOPILOT_ONLY:
            self._foreign(mtype, src_sys, src_comp)
            return
        if mtype == "ATTITUDE_QUATERNION" and from_autopilot:
            att = AttitudeQuaternion.from_message(msg)
            self.stream_rates.count(MSG_ID_ATTITUDE_QUATERNION)
            self._pose.add_attitude(att.time_boot_us, att.q_ned_from_body, att.omega_frd_rps)
            self._boot_seen = (int(self._clock_ns()), att.time_boot_us)
        elif mtype == "GLOBAL_POSITION_INT" and from_autopilot:
            pos = GlobalPositionInt.from_message(msg)
            self.stream_rates.count(MSG_ID_GLOBAL_POSITION_INT)
            stored = self._pose.add_position(pos.time_boot_us, pos.lat_deg, pos.lon_deg, pos.alt_amsl_m, pos.v_ned_mps)
            home = pos.alt_amsl_m - pos.alt_rel_m
            if stored and math.isfinite(home):  # a dropout's zeros or sentinels are no home
                self.home_alt_amsl_m = home
        elif mtype == "GPS_RAW_INT" and from_autopilot:
            g = GpsRawInt.from_message(msg)
            if g.fix_type not in GPS_FIX_NAMES:
                self._counters.count("gps_raw_fix_type", f"GPS_RAW_INT fix_type {g.fix_type} is not a GPS_FIX_TYPE")
                return
            fields = (g.satellites_visible, g.hdop, g.vdop, g.h_acc_m, g.v_acc_m)
            self.gnss = GnssState.updated(self.gnss, now, g.fix_type, *fields)
        elif mtype == "GIMBAL_DEVICE_ATTITUDE_STATUS":
            self._on_gimbal(GimbalDeviceAttitudeStatus.from_message(msg), src_comp, from_autopilot)
        elif mtype == "TIMESYNC":
            self._on_timesync(Timesync.from_message(msg), src_comp, from_autopilot)
        elif mtype == "SYSTEM_TIME" and from_autopilot:
            st = SystemTime.from_message(msg)
            gnss = self.gnss
            if (
                self.utc_clock.mapping is None
                and gnss is not None
                and now - gnss.received_s <= UTC_FIX_FRESH_S
                and not gnss.has_3d_fix
            ):
                # before any GNSS fix an autopilot's UTC is an RTC's or a ground station's, seconds off without a
                # word; the mapping is seeded from a fixed receiver's time only (once seeded, a step re-seeds it)
                self._counters.count(
                    "utc_without_fix",
                    f"SYSTEM_TIME while GPS_RAW_INT reports {gnss.fix}: its UTC may be an unset or RTC clock; not used",
                    level=logging.INFO,
                )
                return
            self.utc_clock.add_system_time(st.time_boot_us, st.time_unix_us)
        elif mtype == "COMMAND_ACK" and from_autopilot:
            self._rates.on_ack(msg, now, self.autopilot_sysid)

    def _settled(self, sysid: int, now: float) -> bool:
        """Unpinned identity rule (see :class:`MavlinkConfig`): True when ``sysid`` may be locked."""
        timeout = self.config.heartbeat_timeout_s
        c = self._candidates.get(sysid)
        if c is None or now - c[1] > timeout:
            c = self._candidates[sysid] = [now, now, 0]
        c[1] = now
        c[2] += 1
        for s in [s for s, v in self._candidates.items() if now - v[1] > timeout]:
            del self._candidates[s]
        rivals = sorted(s for s, v in self._candidates.items() if s != sysid and v[2] >= 2)
        if rivals and c[2] >= 2:
            self._counters.count(
                "autopilot_ambiguous",
                f"systems {sorted([sysid, *rivals])} all heartbeat as autopilots; none followed: set mavlink.autopilot_sysid",
            )
            return False
        return not rivals and now - c[0] >= self.config.lock_settle_s

    def _foreign(self, what: str, src_sys: int, src_comp: int) -> None:
        """Count a message of another system, or of another component of the autopilot's system, that is not
        used (module docstring): at DEBUG, a ground station or a companion on the link is normal traffic."""
        ap_sys, ap_comp = self.autopilot_sysid, self.config.autopilot_compid
        if src_sys == ap_sys:
            reason, whose = "mavlink_foreign_component", f"component {src_comp} of the autopilot's system {src_sys}"
        else:
            reason, whose = "mavlink_foreign_system", f"system {src_sys} (component {src_comp})"
        used = "no autopilot followed yet" if ap_sys is None else f"only {ap_sys}/{ap_comp}'s is used"
        self._counters.count(reason, f"{what} from {whose}: {used}", level=logging.DEBUG)

    def _peer_alive(self, now: float) -> bool:
        """Whether the followed autopilot is alive: its newest heartbeat within ``heartbeat_timeout_s``, the window
        the link calls it connected by (:meth:`tick` marks it lost past it; the unpinned lock tells a gap by it)."""
        last = self._last_hb_rx_s
        return last is not None and now - last <= self.config.heartbeat_timeout_s

    def duplicate_senders(self) -> list[DuplicateSender]:
        """The second senders of the autopilot's identity heard within ``heartbeat_timeout_s`` (the watchdog's
        ``autopilot_duplicate``); empty when none."""
        return self._address.senders(self._now())

    def _on_heartbeat(self, msg, src_sys: int, src_comp: int, now: float, addr=None) -> None:
        if msg.autopilot == mavlink2.MAV_AUTOPILOT_INVALID or msg.type in _NOT_AUTOPILOT_TYPES:
            self._foreign(f"HEARTBEAT (MAV_TYPE {msg.type}, MAV_AUTOPILOT {msg.autopilot})", src_sys, src_comp)
            return
        if src_comp != self.config.autopilot_compid:
            self._foreign(f"HEARTBEAT (MAV_TYPE {msg.type})", src_sys, src_comp)
            return
        if self.autopilot_sysid is None:
            if not self._settled(src_sys, now):
                return
            self._candidates.clear()
            self._set_autopilot(src_sys)
        elif src_sys != self.autopilot_sysid:
            self._counters.count(
                "second_autopilot",
                f"system {src_sys} heartbeats as an autopilot; following system {self.autopilot_sysid} only",
            )
            return
        elif self._mav.srcSystem != src_sys:
            self._set_autopilot(src_sys)
        t = self._transport
        if addr is not None and isinstance(t, UdpTransport) and t.kind == "udpin" and t.peer != addr:
            age_s = 0.0 if self._last_hb_rx_s is None else now - self._last_hb_rx_s
            if not self._address.heartbeat(t, src_sys, src_comp, addr, now, self._peer_alive(now), age_s):
                return
        self._last_hb_rx_s = now
        # the autopilot's mode as its heartbeat says (guidance in the loop sends setpoints only in the accepting mode)
        self.autopilot_mode = (int(msg.autopilot), int(msg.base_mode), int(msg.custom_mode))
        if self.state != LINK_CONNECTED:
            previous = self.state
            self.state = LINK_CONNECTED
            if previous == LINK_LOST:
                log.warning("autopilot %d back; re-requesting message rates", src_sys)
            else:
                log.info("autopilot %d connected", src_sys)
            self._rates.request()
            self._last_ts_tx_s = -math.inf

    def _on_gimbal(self, gim: GimbalDeviceAttitudeStatus, src_comp: int, from_autopilot: bool) -> None:
        # common.xml: gimbal_device_id is 1-6 when the manager speaks for its device, else 0 and the sender's
        # component id names the device; a vehicle may carry several (e.g. ArduPilot's MNT1 and MNT2)
        device = gim.gimbal_device_id or src_comp
        # only a report with an attitude is one: a garbage report must neither pick the gimbal that is followed
        # nor tell the watchdog that the vehicle has (or lacks) the gimbal the configured mount says
        q = gim.q_ref_from_gimbal
        norm = math.sqrt(sum(c * c for c in q)) if len(q) == 4 else math.nan
        if not abs(norm - 1.0) <= QUAT_NORM_TOL:  # False for NaN
            self._counters.count(
                "gimbal_attitude_invalid",
                f"gimbal {device} (component {src_comp}): quaternion {q} is not a unit quaternion; report dropped",
            )
            return
        configured = self.config.gimbal_device_id
        if configured is None or device == configured:
            # the watchdog checks it against the configured mount; with the camera's gimbal named, another gimbal of
            # the vehicle (a daylight camera's) says nothing about it
            self.gimbal_reports += 1
        if not self.gimballed:
            return
        if self.gimbal_device_id is None:
            self.gimbal_device_id = device
            log.info("following gimbal %d (component %d)", device, src_comp)
        elif device != self.gimbal_device_id:
            self._counters.count(
                "second_gimbal",
                f"gimbal {device} (component {src_comp}) reports too; following gimbal {self.gimbal_device_id} "
                "only: set mavlink.gimbal_device_id to the camera's",
            )
            return
        self.stream_rates.count(MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS)  # the followed gimbal's, usable or not
        if not gim.attitude_usable:
            self._counters.count("gimbal_failure", f"failure_flags=0x{gim.failure_flags:x}")
            return
        t_us: int | None
        if from_autopilot:
            t_us = gim.time_boot_us
        else:
            t_us = self.clock_sync.to_boot_us(self._clock_ns())
            if t_us is None:
                self._counters.count("gimbal_clock_unsynced", "gimbal sample from a separate component before TIMESYNC")
                return
        self._pose.add_gimbal_status(t_us, gim.q_ref_from_gimbal, gim.reference, gim.omega_ref_rps)

    def _on_timesync(self, ts: Timesync, src_comp: int, from_autopilot: bool) -> None:
        now_ns = int(self._clock_ns())
        sysid = self.autopilot_sysid or 0
        if ts.is_request:
            self._send("TIMESYNC reply", Timesync(now_ns, ts.ts1_ns, sysid, src_comp).to_message())
            return
        if (ts.target_system, ts.target_component) not in ((0, 0), (sysid, self.config.component_id)):
            return  # an answer to another component's request
        if not from_autopilot:
            # Another component of the vehicle (a companion's MAVLink router, a gimbal) answers broadcast
            # requests too, with its own clock: only the autopilot's is the boot clock the pose is stamped on.
            if ts.ts1_ns in self._ts_outstanding:
                self._counters.count(
                    "timesync_foreign",
                    f"TIMESYNC answer from component {src_comp} of system {sysid}: only the autopilot's "
                    f"(component {self.config.autopilot_compid}) sets the boot clock",
                )
            return
        if ts.ts1_ns in self._ts_outstanding:
            del self._ts_outstanding[ts.ts1_ns]
            off_ns = self._timesync_off_boot_ns(ts.ts1_ns, ts.tc1_ns, now_ns)
            if off_ns is not None:
                self._counters.count(
                    "timesync_implausible",
                    f"TIMESYNC answers on a clock {off_ns / 1e9:+.3f} s from the autopilot's time_boot_ms: another "
                    "epoch or other units (tc1 must be its boot time in ns); not used",
                )
                return
            self.clock_sync.add_exchange(ts.ts1_ns, ts.tc1_ns, now_ns)

    def _timesync_off_boot_ns(self, ts1_ns: int, tc1_ns: int, now_ns: int) -> int | None:
        """How far an exchange's remote clock is from the boot clock of the autopilot's newest attitude (received
        within the last seconds), when that is beyond :data:`TIMESYNC_BOOT_SLACK_NS`; else None."""
        seen = self._boot_seen
        if seen is None or not 0 <= now_ns - seen[0] <= 5 * TIMESYNC_BOOT_SLACK_NS:
            return None
        mid_ns = ts1_ns + (now_ns - ts1_ns) // 2
        off_ns = (seen[0] + tc1_ns - mid_ns) - seen[1] * 1000  # the exchange's boot time there minus the message's
        return off_ns if abs(off_ns) > TIMESYNC_BOOT_SLACK_NS else None

    def _check_reboot(self, now: float) -> None:
        if self._pose.reboots != self._seen_reboots:
            self._seen_reboots = self._pose.reboots
            log.warning("autopilot reboot detected; clock sync reset, message rates re-requested")
            self.clock_sync.reset()
            self.utc_clock.reset()
            self._ts_outstanding.clear()
            if self.state == LINK_CONNECTED:
                self._rates.request()

    # ------------------------------------------------------------------ timers and output

    def tick(self, now: float | None = None) -> None:
        """Timers: heartbeat out, heartbeat timeout, rate-request retries, TIMESYNC requests, reopen."""
        now = self._now() if now is None else float(now)
        if (  # before the closed transport's return: a link whose connection is gone times out as well
            self.state == LINK_CONNECTED
            and self._last_hb_rx_s is not None  # connected: a heartbeat came
            and not self._peer_alive(now)
        ):
            self._mark_lost()
            self._counters.count("autopilot_lost", f"no heartbeat for {now - self._last_hb_rx_s:.1f} s")
        if self._transport is None:
            if self._dial is not None:
                self._settle_dial(now)
            elif now >= self._next_open_s:
                self._open(now)
            return
        if self.autopilot_sysid is not None and now - self._last_hb_tx_s >= self.config.heartbeat_interval_s:
            self._last_hb_tx_s = now
            self._send(
                "HEARTBEAT",
                Heartbeat(mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID).to_message(),
            )
        if self.state != LINK_CONNECTED:
            return
        self._rates.service(now, self.autopilot_sysid)
        if now - self._last_ts_tx_s >= self.config.timesync_interval_s:
            self._last_ts_tx_s = now
            ts1 = int(self._clock_ns())
            self._ts_outstanding[ts1] = None
            while len(self._ts_outstanding) > MAX_OUTSTANDING_TIMESYNC:
                self._ts_outstanding.popitem(last=False)
            self._send(
                "TIMESYNC", Timesync(0, ts1, self.autopilot_sysid or 0, self.config.autopilot_compid).to_message()
            )

    # ------------------------------------------------------------------ tracking status out

    def send_tracking_image_status(self, status: CameraTrackingImageStatus) -> bool:
        """CAMERA_TRACKING_IMAGE_STATUS (#275) (normalised image units, NaN = unknown).  Returns True when written.
        Bad values raise InputError."""
        return self._send("CAMERA_TRACKING_IMAGE_STATUS", status.to_message())

    def send_setpoint(self, v_ned_mps) -> bool:
        """SET_POSITION_TARGET_LOCAL_NED (#84), velocity only, to the locked autopilot (its system, component
        ``autopilot_compid``), stamped with the autopilot's boot clock when TIMESYNC converged (else 0, as
        common.xml allows); True when written, False without a locked autopilot."""
        if self.autopilot_sysid is None:
            return False
        t_us = self.to_boot_us(self._clock_ns()) or 0
        sp = SetPositionTargetLocalNed(int(t_us), self.autopilot_sysid, self.config.autopilot_compid, tuple(v_ned_mps))
        return self._send("SET_POSITION_TARGET_LOCAL_NED", sp.to_message())

    def send_follow_target(self, target: FollowTarget) -> bool:
        """FOLLOW_TARGET (#144) of :func:`onboard.io.follow.follow_target`; True when written."""
        return self._send("FOLLOW_TARGET", target.to_message())

    def send_tracking_geo_status(self, status: CameraTrackingGeoStatus) -> bool:
        """CAMERA_TRACKING_GEO_STATUS (#276) (deg, m AMSL, m/s NED, rad; NaN = unknown).  Returns True when
        written.  Bad values raise InputError."""
        return self._send("CAMERA_TRACKING_GEO_STATUS", status.to_message())

    # ------------------------------------------------------------------ queries

    @property
    def rate_plan(self) -> dict[int, int]:
        """The message rates asked of the autopilot: message id -> interval us."""
        return self._rates.rate_plan

    @property
    def rates_confirmed(self) -> set[int]:
        """The message ids whose rate the autopilot ACCEPTED since the link connected (or it rebooted)."""
        return self._rates.rates_confirmed

    @property
    def rates_refused(self) -> dict[int, int]:
        """Message id -> the MAV_RESULT that refused its rate."""
        return self._rates.rates_refused

    def heartbeat_age_s(self) -> float:
        """How long ago the autopilot's newest heartbeat came, s on the link's clock (inf before the first)."""
        return math.inf if self._last_hb_rx_s is None else self._now() - self._last_hb_rx_s

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
            rates_pending=self._rates.pending(),
            rates_refused=tuple(sorted(self.rates_refused)),
            clock_synced=self.clock_sync.synced,
            messages_rx=self.messages_rx,
            messages_refused=self.messages_refused,
            link_losses=self.link_losses,
            reboots=self._pose.reboots,
            gnss=None if self.gnss is None else self.gnss.summary(now),
            streams={r.name: r.as_dict() for r in self.stream_rates.rates(now)},
        )

    def slow_streams(self) -> list[StreamRate]:
        """The requested streams arriving at under half their confirmed rate for a few seconds (measured now); their
        rates are asked again (:meth:`~onboard.io.mavlink_rates.RateRequests.reask`)."""
        now = self._now()
        slow = self.stream_rates.slow(now, self.stream_rates.rates(now))
        self._rates.reask([r.msg_id for r in slow], now)
        return slow
