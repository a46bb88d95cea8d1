"""The ``mavlink`` section of the daemon's configuration: :class:`MavlinkConfig`, which the autopilot link
(:class:`onboard.io.mavlink_link.MavlinkLink`) takes as is, checked when it is loaded."""

from __future__ import annotations

from typing import Annotated

from pymavlink.dialects.v20 import common as mavlink2

from onboard.core.errors import ConfigError
from onboard.core.schema import Integer, Invalid, Number, SchemaError, Text, config_dataclass
from onboard.io.mavlink_endpoint import parse_endpoint
from onboard.io.mavlink_signing import SigningKeyError, load_signing_key

__all__ = ["DEFAULT_CONNECTION", "MavlinkConfig", "parse_connection"]

DEFAULT_CONNECTION = "udpin:127.0.0.1:14540"

#: one grammar for every MAVLink connection string: :func:`onboard.io.mavlink_endpoint.parse_endpoint`
parse_connection = parse_endpoint

#: MAVLink system and component ids
ComponentId = Annotated[int, Integer(1, 255)]
IntervalS = Annotated[float, Number(0.0, 60.0, lo_open=True)]
RateHz = Annotated[float, Number(0.0, 1000.0, lo_open=True)]
_CONNECTION_TEXT = "a connection like udpin:0.0.0.0:14540, udpout:HOST:PORT, tcp:HOST:PORT or serial:/dev/ttyX[:BAUD]"


@config_dataclass
class MavlinkConfig:
    """The ``mavlink`` section of the daemon's configuration (``config/onboard.yaml``; composed by
    :class:`onboard.app.config.OnboardConfig`), which :class:`~onboard.io.mavlink_link.MavlinkLink` takes as is.  Seconds on the
    link's ``clock``; ids are MAVLink system/component ids.

    ``connection``: the autopilot endpoint; ``attitude_rate_hz`` / ``position_rate_hz`` /
    ``gimbal_rate_hz``: the stream rates requested (#31, #33, #285 when the pod is gimballed).  Attitude at
    100 Hz, as PX4 streams it on a companion link: the objects chain registers each frame with the attitude
    samples that bracket its capture and waits for the later one, up to half as long as at 50 Hz.  An autopilot
    that grants less only lengthens that wait (``imaging.pose_wait_ms`` bounds it).

    ``autopilot_sysid``: the system to follow.  None: lock onto a system whose ``autopilot_compid``
    heartbeats as an autopilot (MAV_TYPE not GCS/onboard/gimbal/camera/ADS-B, MAV_AUTOPILOT not INVALID)
    for ``lock_settle_s`` (first to latest heartbeat, no gap over ``heartbeat_timeout_s``) while no
    other system does so with two or more heartbeats (then nothing is locked and
    ``autopilot_ambiguous`` is counted: pin the id).  A stray heartbeat cannot win.  After the lock,
    another system heartbeating as an autopilot is counted (``second_autopilot``), never followed; on ``udpin``,
    the followed system/component heartbeating from a second address while the first is alive (heard within
    ``heartbeat_timeout_s``) is a second vehicle with the same id: refused and warned (``autopilot_duplicate``).

    ``gimbal_device_id``: the gimbal the camera is on (a gimballed mount), as CAMERA_INFORMATION names it:
    the gimbal device's component id, or 1-6 for a gimbal its manager (e.g. the autopilot) speaks for
    (GIMBAL_DEVICE_ATTITUDE_STATUS's ``gimbal_device_id``).  None: the first one heard.  Another gimbal's
    attitude is counted (``second_gimbal``) and never mixed into the pose.

    ``signing_key_file`` / ``signing_key_env``: where the MAVLink 2 signing key is read from
    (:meth:`signing_key`); with a key, unsigned, MAVLink 1, wrongly signed, replayed and stale packets
    are refused and counted, and everything we send is signed.
    """

    connection: Annotated[str, Text()] = DEFAULT_CONNECTION
    attitude_rate_hz: RateHz = 100.0
    position_rate_hz: RateHz = 25.0
    gimbal_rate_hz: RateHz = 50.0
    heartbeat_interval_s: IntervalS = 1.0
    heartbeat_timeout_s: Annotated[float, Number(0.0, 600.0, lo_open=True)] = 5.0
    command_retry_s: IntervalS = 1.0
    timesync_interval_s: IntervalS = 1.0
    reopen_interval_s: IntervalS = 2.0
    autopilot_sysid: Annotated[int | None, Integer(1, 255)] = 1
    lock_settle_s: Annotated[float, Number(0.0, 60.0)] = 1.5
    signing_key_file: Annotated[str | None, Text()] = None
    signing_key_env: Annotated[str | None, Text()] = None
    autopilot_compid: ComponentId = mavlink2.MAV_COMP_ID_AUTOPILOT1
    component_id: ComponentId = mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER
    poll_rate_hz: Annotated[float, Number(100.0, 10000.0)] = 200.0
    gimbal_device_id: Annotated[int | None, Integer(1, 255)] = None

    def __post_init__(self) -> None:
        try:
            parse_connection(self.connection, "mavlink.connection")
        except ConfigError as exc:
            msg = str(exc).split(": ", 1)[-1]
            raise Invalid("connection", _CONNECTION_TEXT, got_text=f"{self.connection!r} ({msg})") from None
        if self.heartbeat_timeout_s <= self.heartbeat_interval_s:
            raise Invalid(
                "heartbeat_timeout_s",
                f"a timeout > mavlink.heartbeat_interval_s ({self.heartbeat_interval_s:g})",
                self.heartbeat_timeout_s,
            )
        self._read_signing_key()  # an unreadable or empty key fails at --check, naming its field

    def _read_signing_key(self) -> bytes | None:
        try:
            return load_signing_key(self.signing_key_file, self.signing_key_env)
        except SigningKeyError as exc:
            raise Invalid(exc.field.removeprefix("mavlink."), exc.expected, got_text=exc.got) from None

    def signing_key(self) -> bytes | None:
        """The MAVLink 2 signing key (reads ``signing_key_file`` or the ``signing_key_env`` variable), None = unsigned."""
        try:
            return self._read_signing_key()
        except Invalid as exc:
            raise SchemaError.make("<MavlinkConfig>", f"mavlink.{exc.field}", exc.expected, exc.got_text) from None
