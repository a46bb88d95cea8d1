"""The MAVLink camera component: the pure protocol (commands -> replies), its constants against the
dialect, and the socket adapter on 127.0.0.1 with a pymavlink ground station."""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mav

import onboard.io.camera_description as cd
import onboard.io.camera_protocol as cp
from onboard.core.counters import RejectCounter
from onboard.core.errors import InputError
from onboard.core.track import Track
from onboard.io.camera_description import CameraIdentity, VideoStream
from onboard.io.camera_protocol import CameraCommand, CameraProtocol, TrackResult
from tests.fakes import FakeClock, positioned_track, tracking_track

W, H = 640, 512
GCS = (255, 190)  # QGC's system / component
FX_PX = 764.7058823529411
PITCH_UM = 17.0
ATOL_MM = 1e-9


def _identity() -> CameraIdentity:
    return CameraIdentity.from_intrinsics(FX_PX, W, H, PITCH_UM, "irtrack", "IR tracker")


def _stream() -> VideoStream:
    return VideoStream(
        cd.VIDEO_STREAM_TYPE_MPEG_TS, "5600", 30.0, 2_000_000, W, H, math.degrees(2 * math.atan(W / (2 * FX_PX)))
    )


def _proto(**kw) -> CameraProtocol:
    args = dict(component_id=100, stream=_stream(), image_status_hz=10.0, geo_status_hz=5.0)
    args.update(kw)
    return CameraProtocol(_identity(), W, H, **args)


def _cmd(command: int, *params: float, confirmation: int = 0, src=GCS) -> CameraCommand:
    p = list(params) + [0.0] * (7 - len(params))
    return CameraCommand(command, tuple(p), *src, confirmation=confirmation)


def _track(
    state="tracking", u=320.0, v=256.0, bbox=(310.0, 246.0, 20.0, 20.0), observable=True, position=True
) -> Track:
    kw = dict(state=state, measurement_valid=state == "tracking", u_px=u, v_px=v, bbox=bbox)
    if state in ("searching", "lost"):
        kw.update(track_id=None, u_px=None, v_px=None, bbox=None, measurement_valid=False)
    return positioned_track(observable=observable, **kw) if position else tracking_track(**kw)


def _names(out) -> list[str]:
    return [o.msg for o in out]


def _ack(out):
    acks = [o for o in out if o.msg == "command_ack"]
    assert len(acks) == 1
    return acks[0].fields


# --------------------------------------------------------------------------- constants


def test_constants_are_the_dialects():
    for mod in (cp, cd):
        for name in dir(mod):
            if name.isupper() and hasattr(mav, name):
                assert getattr(mod, name) == getattr(mav, name), f"{mod.__name__}.{name}"
    assert cp.MSG_CAMERA_INFORMATION == mav.MAVLINK_MSG_ID_CAMERA_INFORMATION
    assert cp.MSG_VIDEO_STREAM_INFORMATION == mav.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION
    assert cp.MSG_TRACKING_IMAGE_STATUS == mav.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS
    assert cp.MSG_TRACKING_GEO_STATUS == mav.MAVLINK_MSG_ID_CAMERA_TRACKING_GEO_STATUS


def test_every_outgoing_message_packs_with_pymavlink():
    """The fields of each message are its dialect field names, in types pymavlink packs."""
    codec = mav.MAVLink(None, srcSystem=1, srcComponent=100)
    proto = _proto()
    out = []
    for msg_id in (259, 260, 261, 262, 269, 270, 275, 276):
        out += proto.handle(_cmd(cp.MAV_CMD_REQUEST_MESSAGE, msg_id), 0.0, 1234, _track())[0]
    out += proto.tick(0.0, _track())
    out += proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 2.0), 0.0, 0)[0]  # refused: STATUSTEXT
    assert {
        "camera_information",
        "camera_settings",
        "storage_information",
        "camera_capture_status",
        "video_stream_information",
        "video_stream_status",
        "camera_tracking_image_status",
        "camera_tracking_geo_status",
        "heartbeat",
        "command_ack",
        "statustext",
    } <= set(_names(out))
    for o in out:
        msg = getattr(codec, f"{o.msg}_encode")(**o.fields)
        raw = msg.pack(codec)
        back = mav.MAVLink(None).parse_char(raw)
        assert back is not None and back.get_type() == o.msg.upper()


# --------------------------------------------------------------------------- discovery


@pytest.mark.parametrize("command", [(cp.MAV_CMD_REQUEST_MESSAGE, 259), (cp.MAV_CMD_REQUEST_CAMERA_INFORMATION, 1)])
def test_camera_information_on_request_message_and_the_legacy_command(command):
    out, req = _proto().handle(_cmd(*command), 5.0, 4321)
    assert req is None and _names(out) == ["command_ack", "camera_information"]  # the ACK first
    assert _ack(out)["result"] == mav.MAV_RESULT_ACCEPTED and _ack(out)["command"] == command[0]
    assert out[0].reply_to == GCS and _ack(out)["target_system"] == GCS[0]
    f = out[1].fields
    flags = f["flags"]
    for bit in (
        mav.CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM,
        mav.CAMERA_CAP_FLAGS_HAS_TRACKING_POINT,
        mav.CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE,
        mav.CAMERA_CAP_FLAGS_HAS_TRACKING_GEO_STATUS,
    ):
        assert flags & bit
    assert (f["resolution_h"], f["resolution_v"]) == (W, H)
    assert f["focal_length"] == pytest.approx(13.0, abs=ATOL_MM)  # 764.7 px x 17 um
    assert f["sensor_size_h"] == pytest.approx(W * PITCH_UM / 1000) and f["sensor_size_v"] == pytest.approx(
        H * PITCH_UM / 1000
    )
    assert bytes(f["vendor_name"]).rstrip(b"\0") == b"irtrack" and f["camera_device_id"] == 0
    assert f["time_boot_ms"] == 4321


def test_no_video_stream_no_video_flag_and_stream_requests_denied():
    proto = _proto(stream=None)
    out, _ = proto.handle(_cmd(cp.MAV_CMD_REQUEST_MESSAGE, 259), 0.0, 0)
    assert not out[1].fields["flags"] & mav.CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM
    out, _ = proto.handle(_cmd(cp.MAV_CMD_REQUEST_MESSAGE, 269), 0.0, 0)
    assert _names(out) == ["command_ack"] and _ack(out)["result"] == mav.MAV_RESULT_DENIED


@pytest.mark.parametrize(
    "command",
    [
        (cp.MAV_CMD_REQUEST_MESSAGE, 269, 0),
        (cp.MAV_CMD_REQUEST_MESSAGE, 269, 1),
        (cp.MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION, 0),
    ],
)
def test_video_stream_information_is_a_main_h264_stream_with_the_port_as_uri(command):
    out, _ = _proto().handle(_cmd(*command), 0.0, 0)
    assert _names(out) == ["command_ack", "video_stream_information"]
    f = out[1].fields
    # not flagged THERMAL: QGroundControl opens its main video only from a stream without the flag
    assert f["flags"] == mav.VIDEO_STREAM_STATUS_FLAGS_RUNNING
    assert f["type"] == mav.VIDEO_STREAM_TYPE_MPEG_TS and f["uri"] == b"5600"
    assert f["encoding"] == mav.VIDEO_STREAM_ENCODING_H264 and (f["stream_id"], f["count"]) == (1, 1)
    assert f["hfov"] == 45 and (f["resolution_h"], f["resolution_v"]) == (W, H)  # 2 atan(320 / 764.7) = 45.4 deg


def test_stream_two_does_not_exist():
    out, _ = _proto().handle(_cmd(cp.MAV_CMD_REQUEST_MESSAGE, 269, 2), 0.0, 0)
    assert _ack(out)["result"] == mav.MAV_RESULT_DENIED


@pytest.mark.parametrize(
    "command, reply",
    [
        ((cp.MAV_CMD_REQUEST_CAMERA_SETTINGS, 1), "camera_settings"),
        ((cp.MAV_CMD_REQUEST_STORAGE_INFORMATION, 0, 1), "storage_information"),
        ((cp.MAV_CMD_REQUEST_CAMERA_CAPTURE_STATUS, 1), "camera_capture_status"),
        ((cp.MAV_CMD_REQUEST_VIDEO_STREAM_STATUS, 1), "video_stream_status"),
        ((cp.MAV_CMD_REQUEST_MESSAGE, 260), "camera_settings"),
        ((cp.MAV_CMD_REQUEST_MESSAGE, 261), "storage_information"),
        ((cp.MAV_CMD_REQUEST_MESSAGE, 262), "camera_capture_status"),
    ],
)
def test_what_qgc_discovery_asks_after_camera_information_is_answered(command, reply):
    out, _ = _proto().handle(_cmd(*command), 0.0, 0)
    assert _names(out) == ["command_ack", reply] and _ack(out)["result"] == mav.MAV_RESULT_ACCEPTED


@pytest.mark.parametrize("command", [(cp.MAV_CMD_REQUEST_MESSAGE, 261), (cp.MAV_CMD_REQUEST_STORAGE_INFORMATION, 0, 1)])
def test_storage_information_says_none_and_not_supported(command):
    """No storage: none counted, and status NOT_SUPPORTED ("capacity fields ignored"), not EMPTY (3 vs 0:
    "Storage is missing", a card slot without a card)."""
    out, _ = _proto().handle(_cmd(*command), 0.0, 0)
    info = [o.fields for o in out if o.msg == "storage_information"][0]
    assert info["storage_count"] == 0 and info["status"] == mav.STORAGE_STATUS_NOT_SUPPORTED


@pytest.mark.parametrize("gimbal_device_id", [0, 1, 154])
def test_camera_information_names_the_gimbal_it_is_told(gimbal_device_id):
    proto = _proto()
    proto.gimbal_device_id = gimbal_device_id
    out, _ = proto.handle(_cmd(cp.MAV_CMD_REQUEST_MESSAGE, 259), 0.0, 0)
    info = [o.fields for o in out if o.msg == "camera_information"][0]
    assert info["gimbal_device_id"] == gimbal_device_id and info["camera_device_id"] == 0
    assert cd.camera_information(_identity(), 0, True)["gimbal_device_id"] == 0  # none unless told
    with pytest.raises(InputError, match="gimbal_device_id"):
        _proto(gimbal_device_id=256)


def test_unknown_commands_are_unsupported_and_unknown_messages_denied():
    proto = _proto()
    out, _ = proto.handle(_cmd(mav.MAV_CMD_IMAGE_START_CAPTURE, 0, 0, 1), 0.0, 0)
    assert _ack(out)["result"] == mav.MAV_RESULT_UNSUPPORTED
    for bad in (33, math.nan, -1, 2.5):
        out, _ = proto.handle(_cmd(cp.MAV_CMD_REQUEST_MESSAGE, bad), 0.0, 0)
        assert _ack(out)["result"] == mav.MAV_RESULT_DENIED
    out, _ = proto.handle(_cmd(cp.MAV_CMD_REQUEST_CAMERA_INFORMATION, 7), 0.0, 0)
    assert _ack(out)["result"] == mav.MAV_RESULT_DENIED  # MAV_BOOL: only 0 or 1


def test_command_counters_are_named_and_stay_bounded_whatever_ids_arrive():
    proto = _proto()
    for command in range(1000, 3000):
        proto.handle(_cmd(command), 0.0, 0)
    proto.handle(_cmd(cp.MAV_CMD_REQUEST_MESSAGE, 259), 0.0, 0)
    counters = proto.status()["counters"]
    # 2004, 2005, 2010, 2504 and 2505 are ours; the other 1995 ids share one key
    assert counters["cmd_unsupported"] == 1995
    assert counters["cmd_request_message"] == 1 and counters["cmd_camera_track_point"] == 1
    assert len(counters) < 20
    for command, key in cp._COMMAND_COUNTERS.items():  # the key is the dialect's name of the command
        assert getattr(mav, "MAV_CMD_" + key.removeprefix("cmd_").upper()) == command


@settings(max_examples=300, deadline=None)
@given(
    command=st.sampled_from([0, 16, 400, 511, 512, 521, 522, 525, 527, 2004, 2005, 2010, 2504, 2505, 65535]),
    params=st.lists(
        st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10, 300).map(float)),
        min_size=7,
        max_size=7,
    ),
)
def test_every_command_gets_exactly_one_ack_or_a_deferred_request(command, params):
    proto = _proto()
    out, req = proto.handle(CameraCommand(command, tuple(params), *GCS), 0.0, 0)
    acks = [o for o in out if o.msg == "command_ack"]
    if req is None:
        assert len(acks) == 1 and acks[0].fields["command"] == command
        assert acks[0].fields["result"] in (0, 1, 2, 3, 4)
    else:  # a tracking request: no ACK until the pipeline decides, then exactly one
        assert acks == [] and command in (2004, 2005, 2010)
        done = proto.complete(TrackResult(req.request_id, False, "nothing there"))
        assert [o.fields["result"] for o in done if o.msg == "command_ack"] == [mav.MAV_RESULT_FAILED]
        assert proto.complete(TrackResult(req.request_id, True)) == []  # answered once only


# --------------------------------------------------------------------------- tracking commands


def _image_status(proto, now_s, track):
    return [o for o in proto.tick(now_s, track) if o.msg == "camera_tracking_image_status"][0].fields


def test_track_point_is_converted_to_pixels_and_acked_when_the_pipeline_decides():
    proto = _proto()
    out, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.25, 0.5, 20 / W), 1.0, 0)
    assert out == [] and req.kind == "point"
    assert (req.u_px, req.v_px, req.radius_px) == pytest.approx((160.0, 256.0, 20.0))
    done = proto.complete(TrackResult(req.request_id, True, u_px=161.0, v_px=255.0))
    assert _ack(done)["result"] == mav.MAV_RESULT_ACCEPTED and _ack(done)["command"] == cp.MAV_CMD_CAMERA_TRACK_POINT
    img = _image_status(proto, 1.2, _track(u=160.0, v=256.0))
    assert img["tracking_mode"] == mav.CAMERA_TRACKING_MODE_POINT
    assert (img["point_x"], img["point_y"]) == pytest.approx((0.25, 0.5))
    assert math.isnan(img["rec_top_x"]) and img["camera_device_id"] == 0


def test_a_target_the_tracker_took_on_its_own_after_the_operators_is_no_longer_reported_as_the_click():
    """The operator's object lost, the auto mode took another without passing through 'lost': #275 kept POINT mode
    and the status 'selection_mode: point' for a target nobody clicked (a fault-injection audit on C3)."""
    proto = _proto()
    _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.25, 0.5, 20 / W), 1.0, 0)
    proto.complete(TrackResult(req.request_id, True, u_px=161.0, v_px=255.0, track_id=7))
    selected = _track(u=160.0, v=256.0)
    assert _image_status(proto, 1.2, replace(selected, track_id=7))["tracking_mode"] == mav.CAMERA_TRACKING_MODE_POINT
    img = _image_status(proto, 1.5, replace(selected, track_id=8))
    assert img["tracking_mode"] == mav.CAMERA_TRACKING_MODE_RECTANGLE and math.isnan(img["point_x"])
    assert proto.status()["selection_mode"] == "none"


@pytest.mark.parametrize("box_px, radius", [((150.0, 240.0, 24.0, 16.0), 12.0 / W), (None, math.nan)])
def test_point_status_radius_is_the_tracked_objects_not_the_clicks(box_px, radius):
    """common.xml #275 radius: "Current tracked radius" (normalised to the width): half the larger side of the
    object's box, NaN without a box, whatever search radius the click asked for."""
    proto = _proto()
    _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.25, 0.5, 0.1), 1.0, 0)
    proto.complete(TrackResult(req.request_id, True))
    img = _image_status(proto, 1.2, _track(u=162.0, v=248.0, bbox=box_px))
    assert img["tracking_mode"] == mav.CAMERA_TRACKING_MODE_POINT
    if math.isnan(radius):
        assert math.isnan(img["radius"])
    else:
        assert img["radius"] == pytest.approx(radius, rel=1e-12)


# --------------------------------------------------------------------------- a command while one is pending


@pytest.mark.parametrize(
    "command, params",
    [
        (cp.MAV_CMD_CAMERA_TRACK_POINT, (0.25, 0.5, 20 / W)),
        (cp.MAV_CMD_CAMERA_TRACK_RECTANGLE, (0.4, 0.4, 0.6, 0.6)),
        (cp.MAV_CMD_CAMERA_STOP_TRACKING, ()),
    ],
)
def test_a_retransmission_while_pending_is_acted_on_once_and_answered_in_progress_then_final(command, params):
    """The command protocol: a resend has confirmation > 0 and the same parameters.  Not a second request;
    IN_PROGRESS now (QGC then stops retrying and waits), the decision's ACK once."""
    proto = _proto()
    _, req = proto.handle(_cmd(command, *params), 1.0, 0)
    for confirmation in (1, 2):
        out, again = proto.handle(_cmd(command, *params, confirmation=confirmation), 1.1, 0)
        assert again is None and _names(out) == ["command_ack"]
        ack = _ack(out)
        assert (ack["command"], ack["result"], ack["progress"]) == (command, mav.MAV_RESULT_IN_PROGRESS, 255)
        assert (ack["target_system"], ack["target_component"]) == GCS
    assert proto.pending_requests() == 1
    done = proto.complete(TrackResult(req.request_id, True))
    assert (_ack(done)["command"], _ack(done)["result"]) == (command, mav.MAV_RESULT_ACCEPTED)
    assert not any(o.msg == "command_ack" for o in proto.tick(5.0, None))  # nothing else to answer
    assert proto.status()["counters"]["track_retransmission"] == 2


@pytest.mark.parametrize(
    "accepted, reason, result",
    [(True, None, mav.MAV_RESULT_ACCEPTED), (False, "no warm object there", mav.MAV_RESULT_FAILED)],
)
def test_a_retransmission_after_the_decision_gets_the_same_ack_again_and_no_new_request(accepted, reason, result):
    """The ACK was lost: the sender resends (confirmation > 0, the same parameters) after its timeout.  The command
    protocol asks for the same result again; acted on a second time, the resend would be a new selection at a
    stale point, and its answer could contradict the first's (a FAILED while the first click's target is tracked)."""
    proto = _proto()
    params = (0.25, 0.5, 20 / W)
    _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, *params), 1.0, 0)
    first = proto.complete(TrackResult(req.request_id, accepted, reason))
    assert _ack(first)["result"] == result
    for confirmation, now_s in ((1, 2.2), (2, 3.4)):
        out, again = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, *params, confirmation=confirmation), now_s, 0)
        assert again is None and _names(out) == ["command_ack"]
        ack = _ack(out)
        assert (ack["command"], ack["result"], ack["progress"]) == (cp.MAV_CMD_CAMERA_TRACK_POINT, result, 0)
        assert (ack["target_system"], ack["target_component"]) == GCS
    assert proto.pending_requests() == 0
    assert proto.status()["counters"]["track_retransmission"] == 2
    assert proto.status()["selection_mode"] == ("point" if accepted else "none")


@pytest.mark.parametrize(
    "command, params, result",
    [
        (cp.MAV_CMD_CAMERA_TRACK_POINT, (0.25, 0.5, 20 / W), mav.MAV_RESULT_TEMPORARILY_REJECTED),
        (cp.MAV_CMD_CAMERA_STOP_TRACKING, (), mav.MAV_RESULT_ACCEPTED),
    ],
)
def test_a_retransmission_after_the_timeouts_answer_gets_that_answer_again(command, params, result):
    proto = _proto(track_request_timeout_s=1.0)
    _, req = proto.handle(_cmd(command, *params), 10.0, 0)
    assert _ack(proto.tick(11.0, None))["result"] == result
    out, again = proto.handle(_cmd(command, *params, confirmation=1), 11.2, 0)
    assert again is None and _ack(out)["result"] == result


def test_after_the_decision_a_first_transmission_or_other_parameters_are_a_new_command():
    proto = _proto()
    _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.25, 0.5, 0.03), 1.0, 0)
    proto.complete(TrackResult(req.request_id, True))
    _, same_again = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.25, 0.5, 0.03), 2.0, 0)  # clicked again
    assert same_again is not None and same_again.request_id != req.request_id
    proto.complete(TrackResult(same_again.request_id, True))
    _, other = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.75, 0.5, 0.03, confirmation=1), 3.0, 0)
    assert other is not None
    _, by_other = proto.handle(
        _cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.75, 0.5, 0.03, confirmation=1, src=(254, 190)), 3.0, 0
    )
    assert by_other is not None  # another requester's command, whatever its confirmation


def test_a_retransmission_of_a_command_a_newer_one_replaced_is_not_answered_with_the_old_result():
    """COMMAND_ACK names only the command id: once the sender has sent a newer command of that id, an ACK carrying the
    older one's result would be read as the newer one's answer."""
    proto = _proto()
    _, first = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.25, 0.5, 0.03), 1.0, 0)
    proto.complete(TrackResult(first.request_id, True))
    _, newer = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.75, 0.5, 0.03), 2.0, 0)
    proto.complete(TrackResult(newer.request_id, False, "no warm object there"))
    out, late = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.25, 0.5, 0.03, confirmation=1), 2.5, 0)
    assert late is not None and out == []  # not the first's ACCEPTED: a command of its own


def test_a_retransmission_after_the_window_is_a_new_command():
    proto = _proto()
    _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.25, 0.5, 0.03), 1.0, 0)
    proto.complete(TrackResult(req.request_id, True))
    later = 1.0 + cp.RETRANSMISSION_WINDOW_S + 0.1
    out, again = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.25, 0.5, 0.03, confirmation=1), later, 0)
    assert again is not None and out == []


@pytest.mark.parametrize(
    "second, confirmation",
    [
        ((0.25, 0.5, 20 / W), 0),  # the same click again, as a new command (QGC gave up on the first)
        ((0.75, 0.5, 20 / W), 0),  # another click
        ((0.75, 0.5, 20 / W), 1),  # other parameters: not a retransmission whatever the confirmation says
    ],
)
def test_a_new_track_command_supersedes_the_pending_one_and_only_it_is_answered(second, confirmation):
    """COMMAND_ACK names only the command id: a sender that sends the same id again has given up on the first,
    so the first's ACK would be read as the second's.  The second gets the ACK of what it does."""
    proto = _proto()
    _, first = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.25, 0.5, 20 / W), 1.0, 0)
    out, new = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, *second, confirmation=confirmation), 1.5, 0)
    assert out == [] and new is not None and new.request_id != first.request_id
    assert (new.u_px, new.v_px) == pytest.approx((second[0] * W, second[1] * H))
    assert proto.pending_requests() == 1
    assert proto.complete(TrackResult(first.request_id, True)) == []  # decided by the pipeline, never answered
    done = proto.complete(TrackResult(new.request_id, False, "no warm object there"))
    assert (_ack(done)["command"], _ack(done)["result"]) == (cp.MAV_CMD_CAMERA_TRACK_POINT, mav.MAV_RESULT_FAILED)
    # the tracker took the first click's target: #275 says so although the second click failed
    assert proto.status()["selection_mode"] == "point"
    assert proto.status()["counters"]["track_superseded"] == 1


@pytest.mark.parametrize(
    "command, bad",
    [
        (cp.MAV_CMD_CAMERA_TRACK_POINT, (math.nan, 0.5, 20 / W)),
        (cp.MAV_CMD_CAMERA_TRACK_POINT, (1.5, 0.5, 20 / W)),
        (cp.MAV_CMD_CAMERA_TRACK_POINT, (0.75, 0.5, 20 / W, 101)),  # another camera
        (cp.MAV_CMD_CAMERA_TRACK_RECTANGLE, (0.6, 0.4, 0.4, 0.6)),  # no area
    ],
)
def test_a_malformed_command_is_denied_and_leaves_the_pending_one_to_its_ack(command, bad):
    """A malformed command changes nothing but gets its DENIED: the valid one waiting keeps its request and gets the
    ACK of what the pipeline does with it (superseded, it would be applied and never answered)."""
    proto = _proto()
    good = (0.25, 0.5, 20 / W) if command == cp.MAV_CMD_CAMERA_TRACK_POINT else (0.4, 0.4, 0.6, 0.6)
    _, req = proto.handle(_cmd(command, *good), 1.0, 0)
    out, none = proto.handle(_cmd(command, *bad), 1.1, 0)
    assert none is None and _ack(out)["result"] == mav.MAV_RESULT_DENIED
    assert proto.pending_requests() == 1 and "track_superseded" not in proto.status()["counters"]
    done = proto.complete(TrackResult(req.request_id, True))
    assert (_ack(done)["command"], _ack(done)["result"]) == (command, mav.MAV_RESULT_ACCEPTED)
    # nor does it make the decided one's retransmission a new command
    out, again = proto.handle(_cmd(command, *bad), 1.5, 0)
    out, again = proto.handle(_cmd(command, *good, confirmation=1), 2.2, 0)
    assert again is None and _ack(out)["result"] == mav.MAV_RESULT_ACCEPTED


def test_a_superseded_request_nobody_decides_is_forgotten_without_an_ack_and_never_carried_out():
    proto = _proto(track_request_timeout_s=1.0)
    _, first = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.25, 0.5, 0.03), 10.0, 0)
    _, second = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.75, 0.5, 0.03), 10.5, 0)
    out = proto.tick(11.2, None)  # the first's deadline passed: nothing to say about it
    assert not any(o.msg == "command_ack" for o in out)
    acks = [o.fields for o in proto.tick(11.5, None) if o.msg == "command_ack"]
    assert [a["result"] for a in acks] == [mav.MAV_RESULT_TEMPORARILY_REJECTED]  # the second's, once
    assert proto._superseded == {} and proto.pending_requests() == 0
    # frames resume: the pipeline, deciding its queue in order, may carry out neither (the operator was told the
    # newer click was rejected; the older one, replaced, must not be what the tracker switches to)
    assert not first.claim() and not second.claim()


def test_a_superseded_request_the_pipeline_holds_at_its_deadline_is_decided_by_its_result():
    proto = _proto(track_request_timeout_s=1.0)
    _, first = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.25, 0.5, 0.03), 10.0, 0)
    proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.75, 0.5, 0.03), 10.5, 0)
    assert first.claim()  # the pipeline is applying it this moment
    proto.tick(11.2, None)
    assert proto.complete(TrackResult(first.request_id, True)) == []  # acted on, never answered
    assert proto.status()["selection_mode"] == "point"


def test_another_requester_or_another_command_does_not_supersede():
    proto = _proto()
    _, a = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.25, 0.5, 0.03), 1.0, 0)
    _, b = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.25, 0.5, 0.03, confirmation=1, src=(254, 190)), 1.0, 0)
    _, c = proto.handle(_cmd(cp.MAV_CMD_CAMERA_STOP_TRACKING), 1.0, 0)
    assert None not in (a, b, c) and proto.pending_requests() == 3
    answered = [_ack(proto.complete(TrackResult(r.request_id, True))) for r in (a, b, c)]
    assert [(x["command"], x["target_system"]) for x in answered] == [
        (cp.MAV_CMD_CAMERA_TRACK_POINT, 255),
        (cp.MAV_CMD_CAMERA_TRACK_POINT, 254),
        (cp.MAV_CMD_CAMERA_STOP_TRACKING, 255),
    ]


def test_two_ground_stations_with_the_same_ids_on_different_links_each_get_their_ack():
    """QGC's default ids are 255/190 on every copy: the link a command came on (``via``, the adapter's) tells two
    ground stations apart, so neither supersedes the other and each ACK goes back where its command came from."""
    proto = _proto()
    click = (0.25, 0.5, 0.03)
    _, a = proto.handle(CameraCommand(cp.MAV_CMD_CAMERA_TRACK_POINT, (*click, 0, 0, 0, 0), *GCS, via="A"), 1.0, 0)
    _, b = proto.handle(CameraCommand(cp.MAV_CMD_CAMERA_TRACK_POINT, (*click, 0, 0, 0, 0), *GCS, 1, via="B"), 1.0, 0)
    assert a is not None and b is not None and proto.pending_requests() == 2  # B's resend flag: not A's command
    done_a = proto.complete(TrackResult(a.request_id, True))
    done_b = proto.complete(TrackResult(b.request_id, False, "no warm object there"))
    assert [(o.msg, o.reply_to, o.via) for o in done_a] == [("command_ack", GCS, "A")]
    assert [(o.msg, o.reply_to, o.via) for o in done_b] == [("command_ack", GCS, "B"), ("statustext", GCS, "B")]
    assert (_ack(done_a)["result"], _ack(done_b)["result"]) == (mav.MAV_RESULT_ACCEPTED, mav.MAV_RESULT_FAILED)
    # each one's retransmission gets its own answer
    out, _ = proto.handle(CameraCommand(cp.MAV_CMD_CAMERA_TRACK_POINT, (*click, 0, 0, 0, 0), *GCS, 1, via="A"), 2, 0)
    assert (_ack(out)["result"], out[0].via) == (mav.MAV_RESULT_ACCEPTED, "A")
    # replies to other requests go back on the link too
    out, _ = proto.handle(CameraCommand(cp.MAV_CMD_REQUEST_MESSAGE, (259, 0, 0, 0, 0, 0, 0), *GCS, via="B"), 2, 0)
    assert [o.via for o in out] == ["B", "B"]


def test_a_commands_link_must_be_hashable():
    with pytest.raises(InputError, match="via"):
        CameraCommand(cp.MAV_CMD_CAMERA_TRACK_POINT, (0.5,) * 7, *GCS, via=["A"])


def test_confirmation_must_be_a_uint8():
    with pytest.raises(InputError, match="confirmation"):
        _cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.5, 0.5, 0.1, confirmation=256)


def test_track_rectangle_gives_rectangle_mode_with_point_fields_nan():
    proto = _proto()
    _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0.4, 0.4, 0.6, 0.6), 0.0, 0)
    assert req.kind == "rectangle" and req.rect_px == pytest.approx((256.0, 204.8, 384.0, 307.2))
    proto.complete(TrackResult(req.request_id, True))
    img = [o for o in proto.tick(0.0, _track()) if o.msg == "camera_tracking_image_status"][0].fields
    assert img["tracking_mode"] == mav.CAMERA_TRACKING_MODE_RECTANGLE and math.isnan(img["point_x"])
    assert (img["rec_top_x"], img["rec_bottom_x"]) == pytest.approx((310 / W, 330 / W))


@pytest.mark.parametrize("params", [(1.5, 0.5, 0.1), (0.5, math.nan, 0.1), (0.5, 0.5, -0.1)])
def test_bad_track_point_is_denied_with_a_statustext(params):
    out, req = _proto().handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, *params), 0.0, 0)
    assert req is None and _ack(out)["result"] == mav.MAV_RESULT_DENIED
    assert [o.msg for o in out] == ["command_ack", "statustext"]


def test_track_point_for_another_camera_is_denied():
    out, req = _proto().handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.5, 0.5, 0.1, 101), 0.0, 0)
    assert req is None and _ack(out)["result"] == mav.MAV_RESULT_DENIED
    _, req = _proto().handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.5, 0.5, 0.1, 100), 0.0, 0)
    assert req is not None


def test_refused_selection_is_failed_with_the_reason_in_statustext_and_status():
    proto = _proto()
    _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.1, 0.1, 0.03), 0.0, 0)
    out = proto.complete(TrackResult(req.request_id, False, "no warm object within 20 px of (64, 51) px"))
    assert _ack(out)["result"] == mav.MAV_RESULT_FAILED
    text = [o for o in out if o.msg == "statustext"][0].fields["text"]
    assert text.startswith(b"irtrack: no warm object") and len(text) <= 50
    assert "no warm object" in proto.status()["last_refusal"]


def _reassemble(texts) -> bytes:
    """STATUSTEXT chunks as common.xml has a receiver join them: by ``chunk_seq``, each chunk's text up to its first
    NUL, the one with a NUL the last."""
    joined = b""
    for seq, f in enumerate(sorted(texts, key=lambda f: f["chunk_seq"])):
        assert f["chunk_seq"] == seq
        text = bytes(f["text"]).ljust(cp.STATUSTEXT_MAX_CHARS, b"\0")
        joined += text.split(b"\0")[0]
        if b"\0" in text:
            return joined
    raise AssertionError("no chunk says it is the last (none holds a NUL)")


@pytest.mark.parametrize(
    "reason",
    [
        "no confirmed object within 20 px of (306, 256) px",  # the audit's, cut at its pixel before
        "x" * (2 * cp.STATUSTEXT_MAX_CHARS - len("irtrack: ")),  # a multiple of a chunk: one more to end it
        "y" * (cp.STATUSTEXT_MAX_CHARS - len("irtrack: ") + 1),
    ],
)
def test_a_long_refusal_is_sent_whole_in_statustext_chunks_with_a_nonzero_id(reason):
    """common.xml STATUSTEXT: a non-zero ``id`` ties the chunks of one long text, ``chunk_seq`` numbers them, and a
    NUL in the text marks the last (QGC joins them per component)."""
    proto = _proto()
    _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.48, 0.5, 20 / W), 0.0, 0)
    out = proto.complete(TrackResult(req.request_id, False, reason))
    assert _names(out)[0] == "command_ack" and set(_names(out)[1:]) == {"statustext"}
    chunks = [o.fields for o in out if o.msg == "statustext"]
    assert len(chunks) >= 2 and len({c["id"] for c in chunks}) == 1 and chunks[0]["id"] != 0
    assert all(len(c["text"]) <= cp.STATUSTEXT_MAX_CHARS for c in chunks)
    assert _reassemble(chunks).decode().rstrip() == f"irtrack: {reason}"
    # the next long text is another message: another id
    _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.48, 0.5, 20 / W), 1.0, 0)
    again = [o.fields for o in proto.complete(TrackResult(req.request_id, False, reason)) if o.msg == "statustext"]
    assert again[0]["id"] not in (0, chunks[0]["id"])


def test_a_short_refusal_is_one_statustext_with_id_zero():
    out, _ = _proto().handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 2.0), 0.0, 0)
    (text,) = [o.fields for o in out if o.msg == "statustext"]
    assert (text["id"], text["chunk_seq"]) == (0, 0) and text["text"].startswith(b"irtrack: point (2, 0)")


def test_a_refusal_longer_than_the_chunks_allow_is_cut_and_says_so():
    proto = _proto()
    _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.48, 0.5, 20 / W), 0.0, 0)
    out = proto.complete(TrackResult(req.request_id, False, "frame refused: " + "z" * 1000))
    chunks = [o.fields for o in out if o.msg == "statustext"]
    assert len(chunks) == cp.STATUSTEXT_MAX_CHUNKS
    text = _reassemble(chunks)
    assert text.startswith(b"irtrack: frame refused: zzz") and text.endswith(b"...")
    assert "z" * 1000 in proto.status()["last_refusal"]  # the status keeps it whole


def test_a_request_nobody_decides_is_temporarily_rejected_after_the_timeout():
    proto = _proto(track_request_timeout_s=1.0)
    _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.5, 0.5, 0.03), 10.0, 0)
    assert not any(o.msg == "command_ack" for o in proto.tick(10.9, None))
    out = proto.tick(11.0, None)
    assert _ack(out)["result"] == mav.MAV_RESULT_TEMPORARILY_REJECTED
    assert proto.complete(TrackResult(req.request_id, True)) == []  # too late: already answered
    assert not req.claim()  # and the pipeline, finding it claimed, does not carry it out


def test_a_request_the_pipeline_claimed_is_answered_by_its_result_not_the_timeout():
    proto = _proto(track_request_timeout_s=1.0)
    _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.5, 0.5, 0.03), 10.0, 0)
    assert req.claim()  # the pipeline is applying it as the timeout passes
    assert not any(o.msg == "command_ack" for o in proto.tick(11.5, None))
    assert _ack(proto.complete(TrackResult(req.request_id, True)))["result"] == mav.MAV_RESULT_ACCEPTED


# --------------------------------------------------------------------------- #275 / #276 streams


def _count(out, name):
    return sum(o.msg == name for o in out)


def test_status_streams_only_while_tracking_at_the_asked_rate_and_minus_one_stops():
    proto = _proto(image_status_hz=10.0, geo_status_hz=0.0)
    t, dt = 0.0, 0.01
    idle = []
    for _ in range(100):  # 1 s idle: heartbeats only
        idle += proto.tick(t, None)
        t += dt
    assert _count(idle, "camera_tracking_image_status") == 0 and _count(idle, "heartbeat") == 1
    out, _ = proto.handle(_cmd(cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, 500_000), t, 0)
    assert _ack(out)["result"] == mav.MAV_RESULT_ACCEPTED
    got = []
    for _ in range(400):  # 4 s tracking at 2 Hz
        got += proto.tick(t, _track())
        t += dt
    assert 7 <= _count(got, "camera_tracking_image_status") <= 9
    assert _count(got, "camera_tracking_geo_status") == 0  # default 0 Hz: off until asked
    out, _ = proto.handle(_cmd(cp.MAV_CMD_SET_MESSAGE_INTERVAL, 276, 1_000_000), t, 0)
    out, _ = proto.handle(_cmd(cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, -1), t, 0)
    assert _ack(out)["result"] == mav.MAV_RESULT_ACCEPTED
    got = []
    for _ in range(300):
        got += proto.tick(t, _track())
        t += dt
    assert _count(got, "camera_tracking_image_status") == 0 and 2 <= _count(got, "camera_tracking_geo_status") <= 4
    out, _ = proto.handle(_cmd(cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, 0), t, 0)  # 0 = back to the default 10 Hz
    got = []
    for _ in range(100):
        got += proto.tick(t, _track())
        t += dt
    assert 9 <= _count(got, "camera_tracking_image_status") <= 11
    out, _ = proto.handle(_cmd(cp.MAV_CMD_SET_MESSAGE_INTERVAL, 33, 1000), t, 0)
    assert _ack(out)["result"] == mav.MAV_RESULT_DENIED  # not ours to stream


def test_idle_is_sent_once_when_tracking_ends_and_coasting_is_flagged():
    proto = _proto()
    img = [o.fields for o in proto.tick(0.0, _track(state="coasting")) if o.msg == "camera_tracking_image_status"]
    assert (
        img[0]["tracking_status"] == mav.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE | mav.CAMERA_TRACKING_STATUS_FLAGS_COASTING
    )
    out = proto.tick(0.5, _track(state="lost")) + proto.tick(1.0, None) + proto.tick(2.0, None)
    idle = [o.fields for o in out if o.msg == "camera_tracking_image_status"]
    assert len(idle) == 1 and idle[0]["tracking_status"] == 0 and idle[0]["tracking_mode"] == 0


def test_geo_status_only_for_observable_positions_by_default():
    proto = _proto(geo_status_hz=100.0)
    assert _count(proto.tick(0.0, _track(observable=False)), "camera_tracking_geo_status") == 0
    geo = [o.fields for o in proto.tick(1.0, _track()) if o.msg == "camera_tracking_geo_status"][0]
    assert geo["lat"] == 320010000 and geo["h_acc"] == pytest.approx(math.sqrt(8.0)) and geo["dist"] == 130.0
    assert geo["camera_device_id"] == 0
    loose = _proto(geo_status_hz=100.0, observable_only=False)
    assert _count(loose.tick(0.0, _track(observable=False)), "camera_tracking_geo_status") == 1


def test_heartbeat_is_a_camera():
    hb = [o for o in _proto().tick(0.0, None) if o.msg == "heartbeat"][0].fields
    assert hb["type"] == mav.MAV_TYPE_CAMERA and hb["autopilot"] == mav.MAV_AUTOPILOT_INVALID


def test_identity_refuses_bad_values_naming_the_field():
    with pytest.raises(Exception, match="pixel_pitch_um"):
        CameraIdentity.from_intrinsics(FX_PX, W, H, 0.0)
    with pytest.raises(Exception, match="vendor_name"):
        CameraIdentity("x" * 40, "m", 0, 1.0, 1.0, 1.0, 1, 1)
    with pytest.raises(Exception, match="stream_type"):
        VideoStream(0, "5600", 30.0, 0, W, H, 45.0)


def test_geo_status_asked_before_a_position_is_observable_is_temporarily_rejected():
    """REQUEST_MESSAGE(276) with no observable position: asking again later can work, which DENIED would deny."""
    proto = _proto()
    out, _ = proto.handle(_cmd(cp.MAV_CMD_REQUEST_MESSAGE, 276), 0.0, 0, _track(observable=False))
    assert _names(out) == ["command_ack"] and _ack(out)["result"] == mav.MAV_RESULT_TEMPORARILY_REJECTED
    out, _ = proto.handle(_cmd(cp.MAV_CMD_REQUEST_MESSAGE, 276), 0.0, 0, _track(observable=True))
    assert _names(out) == ["command_ack", "camera_tracking_geo_status"]
    assert _ack(out)["result"] == mav.MAV_RESULT_ACCEPTED


# --------------------------------------------------------------------------- refusals in the shared counter


def _counted_proto(**kw) -> tuple[CameraProtocol, RejectCounter, FakeClock]:
    clock = FakeClock()
    counter = RejectCounter(log_interval_s=10.0, clock=clock, logger=logging.getLogger("test.rejects"))
    return _proto(counter=counter, **kw), counter, clock


def test_every_refusal_is_counted_by_result_in_the_shared_counter_and_logged_once_at_info(caplog):
    proto, counter, clock = _counted_proto(track_request_timeout_s=1.0)
    with caplog.at_level(logging.DEBUG, logger="test.rejects"):
        for _ in range(3):  # a ground station probing for a feature we lack
            proto.handle(_cmd(mav.MAV_CMD_IMAGE_START_CAPTURE, 0, 0, 1), clock(), 0)
        proto.handle(_cmd(cp.MAV_CMD_REQUEST_MESSAGE, 33), clock(), 0)  # not a message we send
        proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 1.5, 0.5, 0.1), clock(), 0)  # a click outside the image
        _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.1, 0.1, 0.03), clock(), 0)
        proto.complete(TrackResult(req.request_id, False, "no warm object near the click"))
        proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0.1, 0.1, 0.2, 0.2), clock(), 0)
        proto.tick(clock() + 1.0, None)  # nobody decided: TEMPORARILY_REJECTED
        proto.handle(_cmd(cp.MAV_CMD_REQUEST_MESSAGE, 259), clock(), 0)  # accepted: not a refusal
    assert counter.counts == {
        "gcs_command_unsupported": 3,
        "gcs_command_denied": 2,
        "gcs_command_failed": 1,
        "gcs_command_temporarily_rejected": 1,
    }
    lines = [r for r in caplog.records if r.name == "test.rejects"]
    assert sorted(r.getMessage().split(":")[0] for r in lines) == [
        "gcs_command_denied",
        "gcs_command_failed",
        "gcs_command_temporarily_rejected",
        "gcs_command_unsupported",
    ]  # once per reason within the log interval
    assert {r.levelno for r in lines} == {logging.INFO}
    text = " ".join(r.getMessage() for r in lines)
    assert f"command {mav.MAV_CMD_IMAGE_START_CAPTURE} from 255/190" in text
    assert "no warm object near the click" in text and "message 33 is not one this camera sends" in text
    # the camera's own counters and last refusal are what they were without the shared counter
    counters = proto.status()["counters"]
    assert counters["cmd_unsupported"] == 3 and counters["ack_3"] == 3 and counters["ack_2"] == 2
    assert counters["ack_4"] == 1 and counters["ack_1"] == 1 and counters["ack_0"] == 1
    assert "no frame to select on" in proto.status()["last_refusal"]


def test_refusals_without_a_shared_counter_are_still_answered():
    out, _ = _proto().handle(_cmd(mav.MAV_CMD_IMAGE_START_CAPTURE), 0.0, 0)
    assert _ack(out)["result"] == mav.MAV_RESULT_UNSUPPORTED


# --------------------------------------------------------------------------- SET_MESSAGE_INTERVAL's fastest rate


@pytest.mark.parametrize("interval_us", [1, 1000, 19_999])
def test_an_interval_faster_than_the_maximum_rate_is_accepted_at_that_rate_and_counted(interval_us):
    """common.xml gives SET_MESSAGE_INTERVAL's interval no lower bound: served at MAX_TRACKING_STATUS_HZ, ACCEPTED,
    and MESSAGE_INTERVAL says the interval applied."""
    proto = _proto(image_status_hz=10.0)
    out, _ = proto.handle(_cmd(cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, interval_us), 0.0, 0)
    assert _ack(out)["result"] == mav.MAV_RESULT_ACCEPTED
    out, _ = proto.handle(_cmd(cp.MAV_CMD_GET_MESSAGE_INTERVAL, 275), 0.0, 0)
    (reply,) = [o.fields for o in out if o.msg == "message_interval"]
    assert reply["interval_us"] == 20_000  # 50 Hz
    t, dt, sent = 0.0, 0.001, 0
    for _ in range(2000):  # 2 s of a main loop turning at 1 kHz
        sent += _count(proto.tick(t, _track()), "camera_tracking_image_status")
        t += dt
    assert 99 <= sent <= 101


def test_a_clamped_interval_is_counted_in_the_shared_counter():
    proto, counter, _ = _counted_proto()
    proto.handle(_cmd(cp.MAV_CMD_SET_MESSAGE_INTERVAL, 276, 1), 0.0, 0)
    assert counter.counts == {"gcs_message_interval_clamped": 1}
    assert cp.MIN_TRACKING_STATUS_INTERVAL_S == pytest.approx(1.0 / cp.MAX_TRACKING_STATUS_HZ)


def test_an_interval_at_the_maximum_rate_or_slower_is_applied_as_asked_and_not_counted():
    proto, counter, _ = _counted_proto()
    for interval_us in (20_000, 500_000, -1, 0):
        out, _ = proto.handle(_cmd(cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, interval_us), 0.0, 0)
        assert _ack(out)["result"] == mav.MAV_RESULT_ACCEPTED
    assert counter.total == 0
    assert proto.message_interval_us(275) == 100_000  # 0: back to the configured 10 Hz


def test_a_heartbeat_asked_for_is_sent_now():
    """REQUEST_MESSAGE(HEARTBEAT): the camera sends heartbeats, so it answers one (it was DENIED, as a message this
    camera does not send)."""
    out, _ = _proto().handle(_cmd(cp.MAV_CMD_REQUEST_MESSAGE, 0), 0.0, 0)
    assert _ack(out)["result"] == mav.MAV_RESULT_ACCEPTED
    (hb,) = [o for o in out if o.msg == "heartbeat"]
    assert hb.fields["type"] == mav.MAV_TYPE_CAMERA and hb.reply_to == GCS


def test_the_status_says_the_target_is_drawn_in_the_video_only_when_it_is():
    drawn = _proto(target_rendered=True)
    img = [o.fields for o in drawn.tick(0.0, _track()) if o.msg == "camera_tracking_image_status"][0]
    rendered = mav.CAMERA_TRACKING_TARGET_DATA_IN_STATUS | mav.CAMERA_TRACKING_TARGET_DATA_RENDERED
    assert img["target_data"] == rendered
    idle = [o.fields for o in drawn.tick(1.0, None) if o.msg == "camera_tracking_image_status"][0]
    assert idle["target_data"] == mav.CAMERA_TRACKING_TARGET_DATA_IN_STATUS  # nothing tracked: nothing drawn
    plain = [o.fields for o in _proto().tick(0.0, _track()) if o.msg == "camera_tracking_image_status"][0]
    assert plain["target_data"] == mav.CAMERA_TRACKING_TARGET_DATA_IN_STATUS


@pytest.mark.parametrize(("overlay", "destination", "rendered"), [(True, "127.0.0.1:5600", True),
                                                                   (False, "127.0.0.1:5600", False),
                                                                   (True, None, False)])  # fmt: skip
def test_the_daemon_says_rendered_when_its_video_draws_the_target(overlay, destination, rendered):
    from onboard.app.components import make_camera_protocol
    from onboard.app.config import build_config

    cfg = build_config({"video": {"overlay": overlay, "destination": destination}})
    assert make_camera_protocol(cfg, cfg.camera.pinhole()).target_rendered is rendered


def test_a_stop_with_no_frames_is_accepted_at_the_timeout_and_carried_out_at_the_next_frame():
    """A stop needs no frame to be right: it was TEMPORARILY_REJECTED ("no frame to select on") and dropped, so the
    old selection came back with the frames."""
    proto = _proto(track_request_timeout_s=1.0)
    _, sel = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 0.5, 0.5, 0.03), 5.0, 0)
    assert sel.claim() and proto.complete(TrackResult(sel.request_id, True))  # tracking a clicked object
    assert proto.selection_mode == mav.CAMERA_TRACKING_MODE_POINT
    _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_STOP_TRACKING), 10.0, 0)
    assert not any(o.msg == "command_ack" for o in proto.tick(10.9, None))
    out = proto.tick(11.0, None)
    assert _ack(out)["result"] == mav.MAV_RESULT_ACCEPTED and not any(o.msg == "statustext" for o in out)
    assert proto.selection_mode == mav.CAMERA_TRACKING_MODE_NONE
    assert req.claim()  # still the pipeline's to carry out when frames come
    assert proto.complete(TrackResult(req.request_id, True)) == []  # answered already: no second ACK


def test_a_heartbeat_period_qgc_would_drop_the_camera_in_is_refused_naming_the_field():
    from onboard.app.config import OnboardConfigError, build_config

    assert build_config({"gcs": {"heartbeat_interval_s": 4.0}}).gcs.heartbeat_interval_s == 4.0
    with pytest.raises(OnboardConfigError, match="gcs.heartbeat_interval_s"):
        build_config({"gcs": {"heartbeat_interval_s": 6.0}})


@pytest.mark.parametrize("timeout", [False, True])
def test_a_retransmission_answered_with_a_refusal_again_is_not_a_second_refusal(timeout):
    """The resend of a refused tracking command gets the refusal's ACK again, but it is the same command refused
    once: the shared counter counts it once (the camera's ``ack_<result>`` counts each answer sent)."""
    proto, counter, clock = _counted_proto(track_request_timeout_s=1.0)
    params = (0.25, 0.5, 20 / W)
    _, req = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, *params), clock(), 0)
    if timeout:
        first, reason = proto.tick(clock() + 1.0, None), "gcs_command_temporarily_rejected"
    else:
        first, reason = proto.complete(TrackResult(req.request_id, False, "no warm object there")), "gcs_command_failed"
    for confirmation in (1, 2):
        out, again = proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, *params, confirmation=confirmation), clock(), 0)
        assert again is None and _ack(out)["result"] == _ack(first)["result"]
    assert counter.counts == {reason: 1}
    assert proto.status()["counters"][f"ack_{_ack(first)['result']}"] == 3
