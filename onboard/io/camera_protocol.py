"""The daemon as a MAVLink camera, pure: commands in -> replies, tracking requests and status out.

No sockets, no clocks: :mod:`onboard.io.gcs_link` translates COMMAND_LONG / COMMAND_INT into
:class:`CameraCommand` and sends each :class:`Outgoing` as the message of the same name (``fields`` are
that message's field names, in its wire units; :func:`onboard.io.mavlink_wire.message_from_fields`).
#275 / #276 are encoded by :mod:`onboard.io.mavlink_wire` (the Track mapping and the field checks live
there).  Times (``now_s``, ``time_boot_ms``) are passed in.

A command's *requester* is its sender's (system, component) and the link it came on (:attr:`CameraCommand.via`,
the adapter's, opaque here).  Replies go back to it (:attr:`Outgoing.reply_to` and ``via``), and one requester's
commands never supersede or answer another's: ground stations share ids (QGC is 255/190 on every copy), so two on
different links are kept apart.

What a ground station sees (MAVLink common.xml; QGroundControl's src/Camera discovery):

* HEARTBEAT every ``heartbeat_interval_s`` as MAV_TYPE_CAMERA (30), MAV_AUTOPILOT_INVALID, from the
  camera component (``gcs.component_id``, default 100 = MAV_COMP_ID_CAMERA) with the autopilot's
  system id.  QGC handles camera messages only from components 100..105 (or the autopilot).
* Requests, each answered by a COMMAND_ACK (MAV_RESULT) and, when ACCEPTED, the message:

  =================================================  ======================================
  command (param)                                    reply
  =================================================  ======================================
  MAV_CMD_REQUEST_MESSAGE (512) param1 = 259         CAMERA_INFORMATION
  MAV_CMD_REQUEST_CAMERA_INFORMATION (521)           CAMERA_INFORMATION
  REQUEST_MESSAGE 260 / REQUEST_CAMERA_SETTINGS 522  CAMERA_SETTINGS (mode video, no zoom/focus)
  REQUEST_MESSAGE 261 / REQUEST_STORAGE_INF. 525     STORAGE_INFORMATION (storage_count 0, status
                                                     NOT_SUPPORTED: we store nothing)
  REQUEST_MESSAGE 262 / REQUEST_CAMERA_CAPT. 527     CAMERA_CAPTURE_STATUS (idle; available_capacity 0:
                                                     common.xml has no "unknown" value for it)
  REQUEST_MESSAGE 269 (param2 stream id, 0 = all)    VIDEO_STREAM_INFORMATION (when a stream is
  / REQUEST_VIDEO_STREAM_INFORMATION 2504 (param1)   configured; else DENIED)
  REQUEST_MESSAGE 270 / REQUEST_VIDEO_STREAM_ST. 2505 VIDEO_STREAM_STATUS
  REQUEST_MESSAGE 275 / 276                          one CAMERA_TRACKING_*_STATUS now
  SET_MESSAGE_INTERVAL (511) 275 / 276               ACCEPTED; param2 us, -1 stops, 0 = default; faster
                                                     than 50 Hz is served at 50 Hz; on its own link (below)
  GET_MESSAGE_INTERVAL (510) param1 = message id     MESSAGE_INTERVAL (#244): interval_us of #275 / #276
  / REQUEST_MESSAGE 244, param2 = message id         on the requester's link (-1 = off), of HEARTBEAT (0);
                                                     0 = "not available" for every other message (we
                                                     stream none)
  MAV_CMD_CAMERA_TRACK_POINT (2004)                  a :class:`TrackRequest`; ACK when the pipeline
  MAV_CMD_CAMERA_TRACK_RECTANGLE (2005)              has decided (:meth:`CameraProtocol.complete`):
  MAV_CMD_CAMERA_STOP_TRACKING (2010)                ACCEPTED, or FAILED with the reason
  anything else                                      UNSUPPORTED
  =================================================  ======================================

  A request for a message id we do not produce is DENIED; a malformed parameter (NaN, a point
  outside 0..1, a rectangle with no area) is DENIED; a tracking command for another camera id
  (param "target camera ID" not 0 nor our component id) is DENIED.  A DENIED tracking command changes
  nothing else: a command of the same id waiting for the pipeline keeps its request and its ACK (the sender
  hears both answers), and one already answered keeps its answer for a retransmission (below).  A tracking request that the
  pipeline does not answer within ``track_request_timeout_s`` (no frames) is TEMPORARILY_REJECTED, but
  a stop, which needs no frame: it is ACCEPTED then and carried out at the next frame.
  A refusal is also sent as STATUSTEXT (severity WARNING) naming the reason, which QGC shows.  A text longer
  than one STATUSTEXT's 50 bytes goes in chunks (common.xml: one non-zero ``id`` for all, ``chunk_seq`` from 0;
  every chunk but the last fills its 50 bytes, and the last one's NUL ends the text), which QGC joins
  (``StatusTextHandler``); at most :data:`STATUSTEXT_MAX_CHUNKS`, a longer text cut and ending in "...".  A
  text that would fill its last chunk gets a trailing space: an empty chunk would end it as well, but QGC shows
  an empty chunk as a missing one (" ... ").
* Refusals in the daemon's reject counter (:class:`~onboard.core.counters.RejectCounter`, the status's
  ``rejected``; logged at INFO, once per reason and log interval): every answer DENIED
  (``gcs_command_denied``), UNSUPPORTED (``gcs_command_unsupported``), FAILED (``gcs_command_failed``) or
  TEMPORARILY_REJECTED (``gcs_command_temporarily_rejected``), with the command, the requester and the
  reason, once per command (the answer repeated to a tracking command's retransmission is no second refusal); a
  SET_MESSAGE_INTERVAL served slower than asked (``gcs_message_interval_clamped``).  INFO, not WARNING: a misclick
  or a ground station probing for features is no fault of ours.  The camera's own ``counters`` (:meth:`CameraProtocol.status`) count every command and every answer by result.
* A tracking command while an earlier one of the same id from the same requester waits for the
  pipeline (the command protocol, mavlink.io services/command; QGC's MavCommandQueue):

  - a retransmission (COMMAND_LONG ``confirmation`` > 0, the same seven parameters) is not acted on
    again; it is answered IN_PROGRESS (progress unknown) at once, and the decision's ACK follows.  The
    sender's timeout was shorter than the decision: IN_PROGRESS tells it the command arrived and
    stops its retries (QGC restarts its timer and tries no more);
  - any other that is not DENIED (``confirmation`` 0, other parameters, or a COMMAND_INT, which has no
    confirmation field) is a new command: it supersedes the waiting one and gets the ACK of what it does.  The
    superseded one gets none: COMMAND_ACK names only the command id, and a sender that sends the
    same id again has given up on the first (QGC refuses to send a command while one of the same id
    to the same component is unanswered), so an ACK for it would be read as the new one's answer.
    The pipeline still decides it first (requests are applied in order on the next frame; the later
    selection wins), and its outcome still sets the selection mode of #275.
* A tracking command once answered (ACCEPTED or FAILED by the pipeline, or at the timeout): a retransmission of
  it (``confirmation`` > 0, the same seven parameters, the same requester) within :data:`RETRANSMISSION_WINDOW_S`
  of the command's arrival gets the same COMMAND_ACK again and is not acted on again.  The sender resends because
  no ACK reached it, and the command protocol wants a resent command to get the same result: acted on again, it
  would be a new selection at a point the target has left, whose answer could contradict the first (FAILED while
  the first's target is tracked).  Only the ACK is repeated, not a refusal's STATUSTEXT (the operator may have
  read it already).  A first transmission (``confirmation`` 0) with the same parameters is a new command (the
  operator clicked again), and so is a retransmission once a newer command of that id came from the requester
  (the older one's ACK would be read as the newer one's answer).
* CAMERA_INFORMATION and VIDEO_STREAM_INFORMATION / STATUS: their fields, and the sensor and stream they describe
  (:class:`~onboard.io.camera_description.CameraIdentity`, :class:`~onboard.io.camera_description.VideoStream`), are
  in :mod:`onboard.io.camera_description`.
* CAMERA_TRACKING_IMAGE_STATUS (#275) and CAMERA_TRACKING_GEO_STATUS (#276) while tracking, on each link at the
  intervals it set by SET_MESSAGE_INTERVAL (defaults ``output.tracking_*_status_hz``; what a link is, and that one
  gone forgets its setting: :class:`~onboard.io.status_schedule.StatusSchedules`); once when the tracking ends,
  with status IDLE (QGC clears its box on it), on each link that was sent an ACTIVE one, then nothing until
  tracking resumes.
  #275's mode is the selection's (POINT for TRACK_POINT, RECTANGLE for TRACK_RECTANGLE and for an
  automatic acquisition); fields of the other mode are NaN.  POINT's ``radius`` is the tracked
  object's (half its box's larger side over the image width), NaN without a box: the command's own
  radius is the search area around the click, not the target.  ACTIVE | COASTING (8) while the
  tracker predicts.  #276 only for a position the estimator calls observable (unless
  ``output.geo_status_unobservable`` is set: ``observable_only`` off); ``camera_device_id`` 0 in both (common.xml: 0 = the sender is a
  MAVLink camera, its component id identifies it).
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

from onboard.core.checks import is_nonnegative_number, require_each
from onboard.core.counters import RejectCounter
from onboard.core.errors import InputError
from onboard.core.selection import TrackRequest, TrackResult
from onboard.core.track import Track
from onboard.io.camera_description import CameraIdentity, VideoStream, camera_information, int_in
from onboard.io.mavlink_wire import (
    CameraTrackingGeoStatus,
    CameraTrackingImageStatus,
    geo_status_fields,
    image_status_fields,
    requested_interval,
    wire_fields,
)
from onboard.io.status_schedule import (
    FOLLOW_DEFAULT,
    MAX_TRACKING_STATUS_HZ,
    MIN_TRACKING_STATUS_INTERVAL_S,
    StatusSchedules,
    advance_due_s,
    interval_of_rate_s,
)

__all__ = [
    "CameraCommand",
    "Outgoing",
    "TrackRequest",
    "TrackResult",
    "CameraProtocol",
]

# common.xml numbers (a test checks them against pymavlink's dialect; the core does not import it)
MAV_TYPE_CAMERA = 30
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_TEMPORARILY_REJECTED = 1
MAV_RESULT_DENIED = 2
MAV_RESULT_UNSUPPORTED = 3
MAV_RESULT_FAILED = 4
MAV_RESULT_IN_PROGRESS = 5
MAV_SEVERITY_WARNING = 4
MAV_SEVERITY_INFO = 6

MAV_CMD_GET_MESSAGE_INTERVAL = 510
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_REQUEST_MESSAGE = 512
MAV_CMD_REQUEST_CAMERA_INFORMATION = 521
MAV_CMD_REQUEST_CAMERA_SETTINGS = 522
MAV_CMD_REQUEST_STORAGE_INFORMATION = 525
MAV_CMD_REQUEST_CAMERA_CAPTURE_STATUS = 527
MAV_CMD_CAMERA_TRACK_POINT = 2004
MAV_CMD_CAMERA_TRACK_RECTANGLE = 2005
MAV_CMD_CAMERA_STOP_TRACKING = 2010
MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION = 2504
MAV_CMD_REQUEST_VIDEO_STREAM_STATUS = 2505

MSG_HEARTBEAT = 0
MSG_MESSAGE_INTERVAL = 244
MSG_CAMERA_INFORMATION = 259
MSG_CAMERA_SETTINGS = 260
MSG_STORAGE_INFORMATION = 261
MSG_CAMERA_CAPTURE_STATUS = 262
MSG_VIDEO_STREAM_INFORMATION = 269
MSG_VIDEO_STREAM_STATUS = 270
MSG_TRACKING_IMAGE_STATUS = 275
MSG_TRACKING_GEO_STATUS = 276

CAMERA_MODE_VIDEO = 1
CAMERA_TRACKING_MODE_NONE = 0
CAMERA_TRACKING_MODE_POINT = 1
CAMERA_TRACKING_MODE_RECTANGLE = 2
CAMERA_TRACKING_STATUS_FLAGS_IDLE = 0
STORAGE_STATUS_NOT_SUPPORTED = 3
#: COMMAND_ACK.progress when it is not known
PROGRESS_UNKNOWN = 255

#: bytes of text in one STATUSTEXT
STATUSTEXT_MAX_CHARS = 50
#: a refusal's STATUSTEXT is sent in at most this many chunks (module docstring): 199 bytes of text, room for every
#: reason of ours; a longer one (an exception's text) is cut
STATUSTEXT_MAX_CHUNKS = 4
#: how long (s) after a tracking command arrived its answer is given again to a retransmission of it.  A sender
#: resends when no ACK came (the ACK may be the one lost): QGC sends a command at most 3 times, an ACK timeout
#: apart (``Vehicle::_mavCommandMaxRetryCount``, ``_mavCommandAckTimeoutMSecs``, 1.2 to 3 s by version), so its
#: last retransmission comes at most 6 s after the first; the rest is room for a slow link
RETRANSMISSION_WINDOW_S = 10.0
#: (requester, command) pairs whose answer is kept for a retransmission; the oldest is forgotten first (ids are
#: sender-chosen)
_MAX_DECIDED = 64
_TRACK_COMMANDS = (MAV_CMD_CAMERA_TRACK_POINT, MAV_CMD_CAMERA_TRACK_RECTANGLE, MAV_CMD_CAMERA_STOP_TRACKING)
#: ``counters`` key of each command we answer; every other command id shares ``cmd_unsupported``, so a
#: sender cycling through ids cannot grow the status JSON (the id is 16 bits on COMMAND_LONG)
_COMMAND_COUNTERS = {
    MAV_CMD_GET_MESSAGE_INTERVAL: "cmd_get_message_interval",
    MAV_CMD_SET_MESSAGE_INTERVAL: "cmd_set_message_interval",
    MAV_CMD_REQUEST_MESSAGE: "cmd_request_message",
    MAV_CMD_REQUEST_CAMERA_INFORMATION: "cmd_request_camera_information",
    MAV_CMD_REQUEST_CAMERA_SETTINGS: "cmd_request_camera_settings",
    MAV_CMD_REQUEST_STORAGE_INFORMATION: "cmd_request_storage_information",
    MAV_CMD_REQUEST_CAMERA_CAPTURE_STATUS: "cmd_request_camera_capture_status",
    MAV_CMD_CAMERA_TRACK_POINT: "cmd_camera_track_point",
    MAV_CMD_CAMERA_TRACK_RECTANGLE: "cmd_camera_track_rectangle",
    MAV_CMD_CAMERA_STOP_TRACKING: "cmd_camera_stop_tracking",
    MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION: "cmd_request_video_stream_information",
    MAV_CMD_REQUEST_VIDEO_STREAM_STATUS: "cmd_request_video_stream_status",
}
_STATUS_INTERVAL_KEYS = {  # ``link_intervals`` key of each scheduled message (:meth:`CameraProtocol.status`)
    MSG_TRACKING_IMAGE_STATUS: "image_status_interval_s",
    MSG_TRACKING_GEO_STATUS: "geo_status_interval_s",
}
#: the shared reject counter's reason for each refusing MAV_RESULT; one reason per result, whatever the
#: command, so that a sender cycling through ids cannot grow the status's ``rejected`` either
_REFUSAL_REASONS = {
    MAV_RESULT_TEMPORARILY_REJECTED: "gcs_command_temporarily_rejected",
    MAV_RESULT_DENIED: "gcs_command_denied",
    MAV_RESULT_UNSUPPORTED: "gcs_command_unsupported",
    MAV_RESULT_FAILED: "gcs_command_failed",
}


@dataclass(frozen=True)
class CameraCommand:
    """A COMMAND_LONG / COMMAND_INT addressed to the camera (``params``: its 7 parameters as floats;
    COMMAND_INT's x/y, as received, are params 5 and 6: MAV_CMD_CAMERA_TRACK_RECTANGLE's target camera id is x).

    ``confirmation``: COMMAND_LONG's (0 = first transmission, 1-255 = retransmissions); 0 for a
    COMMAND_INT, which has no such field.

    ``via``: the link the command came on, as the adapter names it (:class:`~onboard.io.gcs_link.GcsLink`: the
    endpoint and, on ``udpin``, the source address), any hashable value, opaque here.  The requester is the
    sender's ids *and* its link: ground stations share ids (QGC is 255/190 on every copy), so two on different
    links are two requesters; each reply carries ``via`` back (:attr:`Outgoing.via`)."""

    command: int
    params: tuple[float, float, float, float, float, float, float]
    src_system: int
    src_component: int
    confirmation: int = 0
    via: Hashable | None = None

    def __post_init__(self) -> None:
        if len(self.params) != 7:
            raise InputError(f"CameraCommand.params must be 7 numbers, got {len(self.params)}")
        object.__setattr__(self, "params", tuple(float(p) for p in self.params))
        int_in("CameraCommand.confirmation", self.confirmation, 0, 255)
        try:
            hash(self.via)
        except TypeError:
            raise InputError(f"CameraCommand.via must be hashable, got {self.via!r}") from None


@dataclass(frozen=True)
class Outgoing:
    """One message to send: pymavlink name (``"command_ack"``), its fields, and to whom.

    ``reply_to``: ``(system, component)`` of the requester, for an ACK, STATUSTEXT or requested message
    (the adapter sends it where the request came from).  ``via``: the link to send it on: a reply's request's
    :attr:`CameraCommand.via` (None: found by ``reply_to``), or a periodic #275 / #276's link (:meth:`~CameraProtocol.tick`).
    Neither: every ground-station endpoint.
    """

    msg: str
    fields: Mapping[str, Any]
    reply_to: tuple[int, int] | None = None
    via: Hashable | None = None


class _Requester(NamedTuple):
    """Who sent a command: its ids and the link it came on (:attr:`CameraCommand.via`)."""

    system: int
    component: int
    via: Hashable | None

    @property
    def ids(self) -> tuple[int, int]:
        return (self.system, self.component)


@dataclass
class _Pending:
    request: TrackRequest
    command: int
    requester: _Requester
    deadline_s: float
    params: tuple[float, ...]
    received_s: float


@dataclass(frozen=True)
class _Decided:
    """A tracking command's answer, for a retransmission of it (module docstring)."""

    params: tuple[float, ...]
    result: int
    reason: str
    until_s: float


def _same_params(a: tuple[float, ...], b: tuple[float, ...]) -> bool:
    """Equal parameter lists, NaN equal to NaN (a retransmission repeats the bits it was sent with)."""
    return len(a) == len(b) and all(x == y or (math.isnan(x) and math.isnan(y)) for x, y in zip(a, b))


@dataclass
class CameraProtocol:
    """The camera component's state machine.  Drive it from one thread:

    * :meth:`handle` for each command addressed to us -> (replies, a :class:`TrackRequest` or None);
    * :meth:`complete` with the pipeline's :class:`TrackResult` -> the deferred COMMAND_ACK;
    * :meth:`tick` periodically -> heartbeat, due #275/#276, expired requests' ACKs.

    ``width_px``/``height_px``: the image the normalised coordinates refer to.
    ``image_status_hz`` / ``geo_status_hz``: default rates of #275 / #276 (0 = off until asked).
    ``gimbal_device_id``: CAMERA_INFORMATION's (0 = no gimbal); the caller sets it when it learns the
    gimbal (the autopilot link follows one gimbal, :attr:`onboard.io.mavlink_link.MavlinkLink.gimbal_device_id`).
    ``counter``: the daemon's shared reject counter; every refused command is counted there too (module
    docstring, "Refusals"), besides this component's own ``counters``.
    """

    identity: CameraIdentity
    width_px: int
    height_px: int
    component_id: int = 100
    stream: VideoStream | None = None
    image_status_hz: float = 10.0
    geo_status_hz: float = 5.0
    observable_only: bool = True
    heartbeat_interval_s: float = 1.0
    track_request_timeout_s: float = 1.0
    gimbal_device_id: int = 0
    #: the video stream draws the tracked target (``video.overlay``): #275 says so (TARGET_DATA_RENDERED)
    target_rendered: bool = False
    counter: RejectCounter | None = field(default=None, repr=False, compare=False)
    #: the adapter's name of a link (:attr:`CameraCommand.via`) for the status (:meth:`GcsLink.link_name`)
    link_name: Callable[[Hashable], str] = field(default=str, repr=False, compare=False)
    schedules: StatusSchedules = field(init=False)
    counters: dict[str, int] = field(init=False, default_factory=dict)
    last_refusal: str | None = field(init=False, default=None)
    selection_mode: int = field(init=False, default=CAMERA_TRACKING_MODE_NONE)
    _selected_track_id: int | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        int_in("CameraProtocol.component_id", self.component_id, 1, 255)
        int_in("CameraProtocol.gimbal_device_id", self.gimbal_device_id, 0, 255)
        require_each(
            self,
            ("image_status_hz", "geo_status_hz"),
            is_nonnegative_number,
            InputError,
            "CameraProtocol.{name} must be a rate >= 0 Hz, got {value!r}",
        )
        self.schedules = StatusSchedules(
            {
                MSG_TRACKING_IMAGE_STATUS: interval_of_rate_s(self.image_status_hz),
                MSG_TRACKING_GEO_STATUS: interval_of_rate_s(self.geo_status_hz),
            }
        )
        self._next_hb_s = -math.inf
        self._pending: dict[int, _Pending] = {}
        #: requests superseded while the pipeline had them: no ACK, but their outcome still sets the mode
        self._superseded: dict[int, _Pending] = {}
        #: (requester, command) -> the answer of its latest command, while a retransmission of it may come
        self._decided: OrderedDict[tuple[_Requester, int], _Decided] = OrderedDict()
        self._next_request_id = 1
        self._statustext_id = 0
        self._was_tracking = False
        # each link sent an ACTIVE #275 since tracking began (a dict: the IDLEs leave in a fixed order)
        self._status_links: dict[Hashable | None, None] = {}

    # ------------------------------------------------------------------ commands

    def handle(
        self, cmd: CameraCommand, now_s: float, time_boot_ms: int, track: Track | None = None
    ) -> tuple[list[Outgoing], TrackRequest | None]:
        """Answer one command (``track``: the newest track, for a one-shot #275/#276 request)."""
        self._count(_COMMAND_COUNTERS.get(cmd.command, "cmd_unsupported"))
        to = _Requester(cmd.src_system, cmd.src_component, cmd.via)
        c, p = cmd.command, cmd.params
        if c in _TRACK_COMMANDS:
            return self._track_command(cmd, now_s)
        if c == MAV_CMD_SET_MESSAGE_INTERVAL:
            result, reason = self._set_interval(p[0], p[1], now_s, to.via)
            return [self._ack(c, result, to, reason=reason)], None
        if c == MAV_CMD_GET_MESSAGE_INTERVAL:
            return self._reply_interval(c, p[0], to), None
        if c == MAV_CMD_REQUEST_MESSAGE:
            msg_id = _msg_id(p[0])
            if msg_id == MSG_MESSAGE_INTERVAL:
                return self._reply_interval(c, p[1], to), None
            index = p[1] if msg_id in (MSG_VIDEO_STREAM_INFORMATION, MSG_VIDEO_STREAM_STATUS) else 0.0
            return self._request(c, msg_id, index, to, time_boot_ms, track), None
        legacy = {
            MAV_CMD_REQUEST_CAMERA_INFORMATION: MSG_CAMERA_INFORMATION,
            MAV_CMD_REQUEST_CAMERA_SETTINGS: MSG_CAMERA_SETTINGS,
            MAV_CMD_REQUEST_STORAGE_INFORMATION: MSG_STORAGE_INFORMATION,
            MAV_CMD_REQUEST_CAMERA_CAPTURE_STATUS: MSG_CAMERA_CAPTURE_STATUS,
            MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION: MSG_VIDEO_STREAM_INFORMATION,
            MAV_CMD_REQUEST_VIDEO_STREAM_STATUS: MSG_VIDEO_STREAM_STATUS,
        }
        if c in legacy:
            msg_id = legacy[c]
            if msg_id in (MSG_VIDEO_STREAM_INFORMATION, MSG_VIDEO_STREAM_STATUS):
                return self._request(c, msg_id, p[0], to, time_boot_ms, track), None
            if msg_id == MSG_STORAGE_INFORMATION:
                ok, which = p[1] in (0.0, 1.0), "param2"  # param2 = request (MAV_BOOL); 0 from old senders is tolerated
            else:
                ok, which = p[0] in (0.0, 1.0), "param1"
            if not ok:
                return [self._ack(c, MAV_RESULT_DENIED, to, reason=f"{which} is not 0 or 1 (MAV_BOOL)")], None
            return self._request(c, msg_id, 0.0, to, time_boot_ms, track), None
        return [self._ack(c, MAV_RESULT_UNSUPPORTED, to, reason="not a command this camera answers")], None

    def _request(
        self, command: int, msg_id: int | None, index: float, to: _Requester, time_boot_ms: int, track: Track | None
    ) -> list[Outgoing]:
        msgs = self._message(msg_id, index, time_boot_ms, track) if msg_id is not None else None
        if msgs is None and msg_id == MSG_TRACKING_GEO_STATUS:
            # no observable position yet: asking again later can work, which DENIED says it cannot
            return [self._ack(command, MAV_RESULT_TEMPORARILY_REJECTED, to, reason="no observable position yet")]
        if msgs is None:
            if msg_id is None:
                reason = "param1 is not a message id"
            elif msg_id in (MSG_VIDEO_STREAM_INFORMATION, MSG_VIDEO_STREAM_STATUS):
                reason = "no video stream configured" if self.stream is None else f"no video stream {index:g}"
            else:
                reason = f"message {msg_id} is not one this camera sends"
            return [self._ack(command, MAV_RESULT_DENIED, to, reason=reason)]
        # the ACK first, then the message (common.xml: "the message is sent after the ACK"), both to the requester
        return [self._ack(command, MAV_RESULT_ACCEPTED, to)] + [replace(m, reply_to=to.ids, via=to.via) for m in msgs]

    @staticmethod
    def _heartbeat() -> Outgoing:
        return Outgoing(
            "heartbeat",
            dict(
                type=MAV_TYPE_CAMERA,
                autopilot=MAV_AUTOPILOT_INVALID,
                base_mode=0,
                custom_mode=0,
                system_status=MAV_STATE_ACTIVE,
            ),
        )

    def _message(self, msg_id: int, index: float, time_boot_ms: int, track: Track | None) -> list[Outgoing] | None:
        ms = int(time_boot_ms) % 2**32
        if msg_id == MSG_HEARTBEAT:  # sent every heartbeat_interval_s anyway: a request gets one now
            return [self._heartbeat()]
        if msg_id == MSG_CAMERA_INFORMATION:
            info = camera_information(self.identity, ms, self.stream is not None, self.gimbal_device_id)
            return [Outgoing("camera_information", info)]
        if msg_id == MSG_CAMERA_SETTINGS:
            return [
                Outgoing(
                    "camera_settings",
                    dict(
                        time_boot_ms=ms,
                        mode_id=CAMERA_MODE_VIDEO,
                        zoomLevel=math.nan,
                        focusLevel=math.nan,
                        camera_device_id=0,
                    ),
                )
            ]
        if msg_id == MSG_STORAGE_INFORMATION:
            return [
                Outgoing(
                    "storage_information",
                    dict(
                        time_boot_ms=ms,
                        storage_id=1,
                        storage_count=0,
                        status=STORAGE_STATUS_NOT_SUPPORTED,
                        total_capacity=0.0,
                        used_capacity=0.0,
                        available_capacity=0.0,
                        read_speed=0.0,
                        write_speed=0.0,
                        type=0,
                        name=b"",
                        storage_usage=0,
                    ),
                )
            ]
        if msg_id == MSG_CAMERA_CAPTURE_STATUS:
            return [
                Outgoing(
                    "camera_capture_status",
                    dict(
                        time_boot_ms=ms,
                        image_status=0,
                        video_status=0,
                        image_interval=0.0,
                        recording_time_ms=0,
                        available_capacity=0.0,
                        image_count=0,
                        camera_device_id=0,
                    ),
                )
            ]
        if msg_id in (MSG_VIDEO_STREAM_INFORMATION, MSG_VIDEO_STREAM_STATUS):
            if self.stream is None or not math.isfinite(index) or index not in (0.0, 1.0):
                return None
            return [self._stream_message(self.stream, msg_id)]
        if msg_id == MSG_TRACKING_IMAGE_STATUS:
            return [self._image_status(track)]
        if msg_id == MSG_TRACKING_GEO_STATUS:
            out = self._geo_status(track)
            return None if out is None else [out]
        return None

    @staticmethod
    def _stream_message(s: VideoStream, msg_id: int) -> Outgoing:
        common = dict(
            stream_id=1,
            flags=s.flags,
            framerate=s.framerate_hz,
            resolution_h=s.resolution_h_px,
            resolution_v=s.resolution_v_px,
            bitrate=s.bitrate_bps,
            rotation=0,
            hfov=int(round(s.hfov_deg)),
            camera_device_id=0,
        )
        if msg_id == MSG_VIDEO_STREAM_STATUS:
            return Outgoing("video_stream_status", common)
        return Outgoing(
            "video_stream_information",
            dict(
                common,
                count=1,
                type=s.stream_type,
                name=s.name.encode()[:32],
                uri=s.uri.encode()[:160],
                encoding=s.encoding,
            ),
        )

    def message_interval_us(self, msg_id: int, link: Hashable | None = None) -> int:
        """MESSAGE_INTERVAL.interval_us for ``msg_id`` on ``link`` (:attr:`CameraCommand.via`): #275 / #276 as that
        link set them (-1 = off), the heartbeat's,
        0 (common.xml: "not available") for every other message."""
        if msg_id in self.schedules:
            every = self.schedules.interval_s(link, msg_id)
            return -1 if every is None else int(round(every * 1e6))
        if msg_id == MSG_HEARTBEAT:
            return int(round(self.heartbeat_interval_s * 1e6))
        return 0

    def _reply_interval(self, command: int, p_msg_id: float, to: _Requester) -> list[Outgoing]:
        msg_id = _msg_id(p_msg_id)
        if msg_id is None or msg_id > 0xFFFF:  # MESSAGE_INTERVAL.message_id is a uint16
            return [self._ack(command, MAV_RESULT_DENIED, to, reason=f"message id {p_msg_id:g} is not a uint16")]
        return [
            self._ack(command, MAV_RESULT_ACCEPTED, to),
            Outgoing(
                "message_interval",
                dict(message_id=msg_id, interval_us=self.message_interval_us(msg_id, to.via)),
                reply_to=to.ids,
                via=to.via,
            ),
        ]

    def _set_interval(self, p1: float, p2: float, now_s: float, link: Hashable | None) -> tuple[int, str]:
        """SET_MESSAGE_INTERVAL of #275 / #276 on ``link``, the one it came on: (MAV_RESULT, why when refused).  An
        interval shorter than :data:`MIN_TRACKING_STATUS_INTERVAL_S` is applied as that one (module docstring)."""
        msg_id = _msg_id(p1)
        if msg_id is None or msg_id not in self.schedules:
            return MAV_RESULT_DENIED, f"message {p1:g} is not one this camera streams"
        accepted, interval_s = requested_interval(p2, FOLLOW_DEFAULT, lambda us: us / 1e6)
        if not accepted:
            return MAV_RESULT_DENIED, f"interval {p2:g} us is not -1, 0 or a positive interval of at most 2^31-1 us"
        if isinstance(interval_s, float) and interval_s < MIN_TRACKING_STATUS_INTERVAL_S:
            if self.counter is not None:
                self.counter.count(
                    "gcs_message_interval_clamped",
                    f"message {msg_id} every {p2:g} us asked; sent every "
                    f"{MIN_TRACKING_STATUS_INTERVAL_S * 1e6:.0f} us ({MAX_TRACKING_STATUS_HZ:g} Hz at most)",
                    level=logging.INFO,
                )
            interval_s = MIN_TRACKING_STATUS_INTERVAL_S
        self.schedules.set(link, msg_id, interval_s, now_s)
        return MAV_RESULT_ACCEPTED, ""

    def _track_command(self, cmd: CameraCommand, now_s: float) -> tuple[list[Outgoing], TrackRequest | None]:
        c, p, to = cmd.command, cmd.params, _Requester(cmd.src_system, cmd.src_component, cmd.via)
        fields, why = self._track_fields(c, p)
        if fields is None:  # checked first: a refused command leaves the one waiting or answered alone
            return self._refuse(c, MAV_RESULT_DENIED, why, to), None
        for prev_id, pend in list(self._pending.items()):
            if pend.command != c or pend.requester != to:
                continue
            if cmd.confirmation > 0 and _same_params(pend.params, p):  # module docstring: retransmission
                self._count("track_retransmission")
                return [self._ack(c, MAV_RESULT_IN_PROGRESS, to, progress=PROGRESS_UNKNOWN)], None
            self._superseded[prev_id] = self._pending.pop(prev_id)  # module docstring: a new command
            self._count("track_superseded")
        decided = self._decided.get((to, c))
        if decided is not None and cmd.confirmation > 0 and now_s < decided.until_s and _same_params(decided.params, p):
            # module docstring: its ACK was lost; the same answer again, not a second selection, nor a second refusal
            self._count("track_retransmission")
            return [self._ack(c, decided.result, to, reason=decided.reason, repeated=True)], None
        self._decided.pop((to, c), None)  # a new command: an ACK of the older one would be read as its answer
        rid = self._next_request_id
        self._next_request_id += 1
        req = TrackRequest(rid, **fields)
        self._pending[rid] = _Pending(req, c, to, now_s + self.track_request_timeout_s, p, now_s)
        return [], req

    def _track_fields(self, c: int, p: tuple[float, ...]) -> tuple[dict[str, Any] | None, str]:
        """A tracking command's :class:`TrackRequest` fields but the id, in pixels; None and why when it is DENIED."""
        cam_param = {
            MAV_CMD_CAMERA_TRACK_POINT: p[3],
            MAV_CMD_CAMERA_TRACK_RECTANGLE: p[4],
            MAV_CMD_CAMERA_STOP_TRACKING: p[0],
        }[c]
        if cam_param not in (0.0, float(self.component_id)):
            return None, f"camera id {cam_param:g} is not this camera"
        W, H = self.width_px, self.height_px
        if c == MAV_CMD_CAMERA_TRACK_POINT:
            x, y, r = p[0], p[1], p[2]
            if not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in (x, y, r)):
                return None, f"point ({x:g}, {y:g}) radius {r:g} not in 0..1"
            return dict(kind="point", u_px=x * W, v_px=y * H, radius_px=max(r * W, 1.0)), ""
        if c == MAV_CMD_CAMERA_TRACK_RECTANGLE:
            x0, y0, x1, y1 = p[0], p[1], p[2], p[3]
            if not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in (x0, y0, x1, y1)) or x1 <= x0 or y1 <= y0:
                return None, f"rectangle ({x0:g},{y0:g})-({x1:g},{y1:g}) invalid"
            return dict(kind="rectangle", rect_px=(x0 * W, y0 * H, x1 * W, y1 * H)), ""
        return dict(kind="stop"), ""

    def complete(self, result: TrackResult) -> list[Outgoing]:
        """The pipeline decided ``result.request_id``: its COMMAND_ACK (and a STATUSTEXT when refused)."""
        superseded = self._superseded.pop(result.request_id, None)
        if superseded is not None:  # acted on, never answered (module docstring)
            if result.accepted:
                self._accepted(superseded.request.kind, result.track_id)
            return []
        pend = self._pending.pop(result.request_id, None)
        if pend is None:
            return []  # expired already (ACKed TEMPORARILY_REJECTED)
        if not result.accepted:
            reason = result.reason or "refused"
            self._decide(pend, MAV_RESULT_FAILED, reason)
            return self._refuse(pend.command, MAV_RESULT_FAILED, reason, pend.requester)
        self._accepted(pend.request.kind, result.track_id)
        self._decide(pend, MAV_RESULT_ACCEPTED)
        return [self._ack(pend.command, MAV_RESULT_ACCEPTED, pend.requester)]

    def _decide(self, pend: _Pending, result: int, reason: str = "") -> None:
        """Keep ``pend``'s answer for a retransmission of it (module docstring)."""
        key = (pend.requester, pend.command)
        self._decided.pop(key, None)
        self._decided[key] = _Decided(pend.params, result, reason, pend.received_s + RETRANSMISSION_WINDOW_S)
        while len(self._decided) > _MAX_DECIDED:
            self._decided.popitem(last=False)

    def _accepted(self, kind: str, track_id: int | None = None) -> None:
        self.selection_mode = {
            "point": CAMERA_TRACKING_MODE_POINT,
            "rectangle": CAMERA_TRACKING_MODE_RECTANGLE,
            "stop": CAMERA_TRACKING_MODE_NONE,
        }[kind]
        self._selected_track_id = track_id  # the operator's: another track is not (see tick)
        self._count(f"track_{kind}_accepted")

    def pending_requests(self) -> int:
        return len(self._pending)

    # ------------------------------------------------------------------ periodic

    def next_due_s(self) -> float:
        """When :meth:`tick` next has something to send: heartbeat, a tracking request's timeout, or, while
        a target is tracked, a #275/#276 at its interval on a link (a track that begins, or a link that appears, is
        seen at the caller's next turn)."""
        due = [self._next_hb_s, *(p.deadline_s for p in self._pending.values())]
        if self._was_tracking:
            due.append(self.schedules.next_due_s())
        return min(due)

    def tick(self, now_s: float, track: Track | None, links: Iterable[Hashable | None] = (None,)) -> list[Outgoing]:
        """Heartbeat when due, expired tracking requests' ACKs, #275/#276 when due on each of ``links`` (``track``: the
        newest one, None when there is none or it is stale).  ``links``: those there are now (:meth:`GcsLink.links`),
        each on its own schedule (:class:`~onboard.io.status_schedule.StatusSchedules`); the default, None, is all."""
        links = list(links)
        self.schedules.keep(links)
        out: list[Outgoing] = []
        if now_s >= self._next_hb_s:
            out.append(self._heartbeat())
            self._next_hb_s = advance_due_s(self._next_hb_s, self.heartbeat_interval_s, now_s)
        for rid in [r for r, p in self._superseded.items() if now_s >= p.deadline_s]:
            # never decided: claimed, so that frames that resume later cannot carry out a click the operator
            # replaced (and whose replacement may be refused below); when the pipeline holds it this moment,
            # its result decides (complete)
            if self._superseded[rid].request.claim():
                del self._superseded[rid]
        for rid in [r for r, p in self._pending.items() if now_s >= p.deadline_s]:
            if self._pending[rid].command == MAV_CMD_CAMERA_STOP_TRACKING:
                # a stop needs no frame to be right: ACCEPTED now and left to the pipeline, which carries it out
                # at the next frame (refused, the operator's stop was lost and the old selection came back with
                # the frames); a newer selection still comes after it
                pend = self._pending.pop(rid)
                self._accepted(pend.request.kind)
                self._decide(pend, MAV_RESULT_ACCEPTED)
                out.append(self._ack(pend.command, MAV_RESULT_ACCEPTED, pend.requester))
                continue
            if not self._pending[rid].request.claim():
                continue  # the pipeline is applying it this moment: its result decides, on a later tick
            pend = self._pending.pop(rid)
            reason = "no frame to select on (no IR frames arriving)"
            self._decide(pend, MAV_RESULT_TEMPORARILY_REJECTED, reason)
            out += self._refuse(pend.command, MAV_RESULT_TEMPORARILY_REJECTED, reason, pend.requester)
        tracking = track is not None and track.state in ("tracking", "coasting")
        if not tracking:
            if self._was_tracking:
                # one IDLE status to each link that was sent an ACTIVE one this time and is still there: a ground
                # station clears its box on it. A link that turned #275 off after that gets it too: QGC sends its -1
                # after the stop, and an ACTIVE sent between the two would otherwise leave its box drawn for good
                idle = self._image_status(None)
                out += [replace(idle, via=link) for link in self._status_links if link in links]
                self._status_links.clear()
                self._was_tracking = False
            if self.selection_mode != CAMERA_TRACKING_MODE_NONE and track is not None and track.state == "lost":
                self.selection_mode = CAMERA_TRACKING_MODE_NONE
            return out
        self._was_tracking = True
        if (
            self.selection_mode != CAMERA_TRACKING_MODE_NONE
            and self._selected_track_id is not None
            and track is not None
            and track.track_id != self._selected_track_id
        ):
            # the operator's object was lost and the tracker took another on its own (auto mode): that one is no
            # selection, and #275 says so (RECTANGLE, as for any automatic acquisition) rather than the click's mode
            self.selection_mode = CAMERA_TRACKING_MODE_NONE
            self._selected_track_id = None
        build = {MSG_TRACKING_IMAGE_STATUS: self._image_status, MSG_TRACKING_GEO_STATUS: self._geo_status}
        built: dict[int, Outgoing | None] = {}  # each message built once, whichever links it is due on
        for link, msg_id in self.schedules.due(now_s, links):
            if msg_id not in built:
                built[msg_id] = build[msg_id](track)
            msg = built[msg_id]
            if msg is not None:
                out.append(replace(msg, via=link))
                if msg_id == MSG_TRACKING_IMAGE_STATUS:
                    self._status_links[link] = None
        return out

    def _image_status(self, track: Track | None) -> Outgoing:
        mode = (
            self.selection_mode if self.selection_mode != CAMERA_TRACKING_MODE_NONE else CAMERA_TRACKING_MODE_RECTANGLE
        )
        f = image_status_fields(track, self.width_px, self.height_px, mode=mode, rendered=self.target_rendered)
        return Outgoing(
            "camera_tracking_image_status", wire_fields(CameraTrackingImageStatus(**f, camera_device_id=0).to_message())
        )

    def _geo_status(self, track: Track | None) -> Outgoing | None:
        f = geo_status_fields(track, observable_only=self.observable_only)
        if f is None:
            return None
        return Outgoing(
            "camera_tracking_geo_status", wire_fields(CameraTrackingGeoStatus(**f, camera_device_id=0).to_message())
        )

    # ------------------------------------------------------------------ helpers

    def _ack(
        self, command: int, result: int, to: _Requester, progress: int = 0, reason: str = "", repeated: bool = False
    ) -> Outgoing:
        """The COMMAND_ACK; a refusing result is counted in the shared counter with ``reason`` (module docstring),
        unless ``repeated``: the answer again to a retransmission of a command whose refusal is counted already."""
        self._count(f"ack_{result}")
        refusal = _REFUSAL_REASONS.get(result)
        if refusal is not None and self.counter is not None and not repeated:
            # INFO: a refused command is the sender's mistake or a limit of ours, not a fault of the daemon, but
            # an operator asking why a click did nothing finds it in the log
            self.counter.count(
                refusal, f"command {command} from {to.system}/{to.component}: {reason or '-'}", level=logging.INFO
            )
        return Outgoing(
            "command_ack",
            dict(
                command=command,
                result=result,
                progress=progress,
                result_param2=0,
                target_system=to.system,
                target_component=to.component,
            ),
            reply_to=to.ids,
            via=to.via,
        )

    def _refuse(self, command: int, result: int, reason: str, to: _Requester) -> list[Outgoing]:
        self.last_refusal = f"command {command}: {reason}"
        self._statustext_id = self._statustext_id % 0xFFFF + 1  # uint16, 0 = a text in one message
        texts = [
            Outgoing(
                "statustext",
                dict(severity=MAV_SEVERITY_WARNING, text=chunk, id=text_id, chunk_seq=seq),
                reply_to=to.ids,
                via=to.via,
            )
            for chunk, text_id, seq in _statustext_chunks(f"irtrack: {reason}", self._statustext_id)
        ]
        return [self._ack(command, result, to, reason=reason), *texts]

    def _count(self, key: str) -> None:
        self.counters[key] = self.counters.get(key, 0) + 1

    def status(self) -> dict[str, Any]:
        """For the status JSON: rates, selection mode, pending requests, the last refusal, counters.

        ``default_*_status_interval_s``: #275 / #276's interval (s; None = off) on a link that set none;
        ``link_intervals``: each link that set its own (named by :attr:`link_name`), with both of its intervals.

        ``counters``: ``cmd_<name>`` per command we answer and ``cmd_unsupported`` for all others,
        ``ack_<MAV_RESULT>``, ``track_<kind>_accepted``, ``track_retransmission`` (answered IN_PROGRESS while
        pending, or the answer again once decided), ``track_superseded``:
        a bounded set of keys whatever is received."""
        return {
            "component_id": self.component_id,
            "selection_mode": {0: "none", 1: "point", 2: "rectangle"}[self.selection_mode],
            "default_image_status_interval_s": self.schedules.default_interval_s[MSG_TRACKING_IMAGE_STATUS],
            "default_geo_status_interval_s": self.schedules.default_interval_s[MSG_TRACKING_GEO_STATUS],
            "link_intervals": self.schedules.own_settings(self.link_name, _STATUS_INTERVAL_KEYS),
            "pending_track_requests": len(self._pending),
            "last_refusal": self.last_refusal,
            "counters": dict(self.counters),
        }


def _statustext_chunks(text: str, text_id: int) -> list[tuple[bytes, int, int]]:
    """(text, id, chunk_seq) of each STATUSTEXT carrying ``text`` (UTF-8; module docstring): one with id 0 when it
    fits, else chunks of :data:`STATUSTEXT_MAX_CHARS` bytes with ``text_id`` (not 0), the last one shorter."""
    raw, n = text.encode(), STATUSTEXT_MAX_CHARS
    if len(raw) <= n:
        return [(raw, 0, 0)]
    limit = STATUSTEXT_MAX_CHUNKS * n - 1  # the last chunk keeps a byte for the NUL that ends the text
    if len(raw) > limit:
        raw = raw[: limit - 3].decode(errors="ignore").encode() + b"..."  # not inside a character
    if len(raw) % n == 0:
        raw += b" "  # module docstring: a full last chunk has no NUL to end the text
    return [(raw[i : i + n], text_id, seq) for seq, i in enumerate(range(0, len(raw), n))]


def _msg_id(p: float) -> int | None:
    if not math.isfinite(p) or p != int(p) or not 0 <= p < 2**24:
        return None
    return int(p)
