"""MAV_CMD_GET_MESSAGE_INTERVAL (510) and REQUEST_MESSAGE(244, id) on the camera component: a
MESSAGE_INTERVAL (#244) with the rate SET_MESSAGE_INTERVAL set for #275 / #276 (-1 = off, the
config default after 0), the heartbeat's, 0 ("not available") for anything else; every request
ACKed (common.xml)."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mav

import onboard.io.camera_protocol as cp
from tests.onboard.test_camera_protocol import _ack, _cmd, _proto


def _interval(proto, msg_id: int, via: str = "get") -> tuple[int, dict | None]:
    cmd = (
        _cmd(cp.MAV_CMD_GET_MESSAGE_INTERVAL, msg_id)
        if via == "get"
        else _cmd(cp.MAV_CMD_REQUEST_MESSAGE, cp.MSG_MESSAGE_INTERVAL, msg_id)
    )
    out, req = proto.handle(cmd, 1.0, 1000)
    assert req is None
    ack = _ack(out)
    assert ack["command"] == cmd.command
    replies = [o for o in out if o.msg == "message_interval"]
    assert len(replies) <= 1
    if replies:
        assert out.index(replies[0]) > out.index(next(o for o in out if o.msg == "command_ack"))  # ACK first
    return ack["result"], (replies[0].fields if replies else None)


def test_constants_are_the_dialects():
    assert cp.MAV_CMD_GET_MESSAGE_INTERVAL == mav.MAV_CMD_GET_MESSAGE_INTERVAL
    assert cp.MSG_MESSAGE_INTERVAL == mav.MAVLINK_MSG_ID_MESSAGE_INTERVAL


@pytest.mark.parametrize("via", ["get", "request"])
def test_defaults_then_what_set_message_interval_set(via):
    proto = _proto(image_status_hz=10.0, geo_status_hz=5.0)
    assert _interval(proto, 275, via) == (cp.MAV_RESULT_ACCEPTED, {"message_id": 275, "interval_us": 100_000})
    assert _interval(proto, 276, via)[1]["interval_us"] == 200_000
    proto.handle(_cmd(cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, 500_000), 1.0, 0)  # QGC's 2 Hz
    proto.handle(_cmd(cp.MAV_CMD_SET_MESSAGE_INTERVAL, 276, -1), 1.0, 0)
    assert _interval(proto, 275, via)[1]["interval_us"] == 500_000
    assert _interval(proto, 276, via)[1]["interval_us"] == -1
    proto.handle(_cmd(cp.MAV_CMD_SET_MESSAGE_INTERVAL, 276, 0), 1.0, 0)  # 0 = back to the default
    assert _interval(proto, 276, via)[1]["interval_us"] == 200_000


def test_a_rate_of_zero_in_the_config_is_off_and_the_heartbeat_and_others_are_reported():
    proto = _proto(image_status_hz=0.0, heartbeat_interval_s=1.0)
    assert _interval(proto, 275)[1]["interval_us"] == -1
    assert _interval(proto, 0)[1] == {"message_id": 0, "interval_us": 1_000_000}
    assert _interval(proto, 33)[1] == {"message_id": 33, "interval_us": 0}  # not a message we stream


@pytest.mark.parametrize("bad", [float("nan"), -1.0, 2.5, 70_000.0])
def test_a_malformed_message_id_is_denied_without_a_reply(bad):
    assert _interval(_proto(), bad) == (cp.MAV_RESULT_DENIED, None)


def test_the_reply_packs_with_pymavlink_and_goes_to_the_requester():
    proto = _proto()
    out, _ = proto.handle(_cmd(cp.MAV_CMD_GET_MESSAGE_INTERVAL, 275), 1.0, 0)
    reply = next(o for o in out if o.msg == "message_interval")
    assert reply.reply_to == (255, 190)
    codec = mav.MAVLink(None, srcSystem=1, srcComponent=100)
    back = mav.MAVLink(None).parse_char(codec.message_interval_encode(**reply.fields).pack(codec))
    assert back.get_type() == "MESSAGE_INTERVAL" and (back.message_id, back.interval_us) == (275, 100_000)


@pytest.mark.parametrize("interval_us", [-0.6, 0.4, 1.5])
def test_a_fraction_of_a_microsecond_is_denied_not_rounded_into_a_sentinel(interval_us):
    """param2 is a whole number of microseconds whose -1 (stop) and 0 (default) are sentinels: -0.6 rounded to -1
    stopped the stream, 0.4 to 0 reset it, each ACCEPTED."""
    proto = _proto(image_status_hz=10.0)
    out, _ = proto.handle(_cmd(cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, interval_us), 1.0, 0)
    assert _ack(out)["result"] == cp.MAV_RESULT_DENIED
    assert _interval(proto, 275) == (cp.MAV_RESULT_ACCEPTED, {"message_id": 275, "interval_us": 100_000})


@pytest.mark.parametrize("interval_us", [2**31, 3e9])
def test_an_interval_message_interval_cannot_report_is_denied_and_the_old_one_kept(interval_us):
    """MESSAGE_INTERVAL.interval_us is an int32: an interval beyond it, once accepted, made every later report of it
    fail to pack (and go unsent)."""
    proto = _proto(image_status_hz=10.0)
    out, _ = proto.handle(_cmd(cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, interval_us), 1.0, 0)
    assert _ack(out)["result"] == cp.MAV_RESULT_DENIED
    assert _interval(proto, 275) == (cp.MAV_RESULT_ACCEPTED, {"message_id": 275, "interval_us": 100_000})
    # COMMAND_LONG's params are float32: 2^31 - 1 arrives as 2^31 (refused above); the longest a ground station
    # can ask is the float32 just below, 2147483392 us
    longest = float(np.float32(2147483392.0))
    assert longest < 2**31 - 1 and float(np.float32(2**31 - 1)) == 2**31
    out, _ = proto.handle(_cmd(cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, longest), 1.0, 0)
    assert _ack(out)["result"] == cp.MAV_RESULT_ACCEPTED
    result, reply = _interval(proto, 275)
    codec = mav.MAVLink(None, srcSystem=1, srcComponent=100)
    codec.message_interval_encode(**reply).pack(codec)  # packs
    assert reply["interval_us"] == 2147483392
