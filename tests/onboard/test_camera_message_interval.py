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


# two QGC copies on one udpin endpoint: the same ids, two peer addresses (GcsLink's via = (endpoint, address))
LINK_A = (0, ("10.0.0.5", 14550))
LINK_B = (0, ("10.0.0.6", 14550))
TICK_S = 0.01  # a main loop turning at 100 Hz


def _on(via, command: int, *params: float):
    p = list(params) + [0.0] * (7 - len(params))
    return cp.CameraCommand(command, tuple(p), 255, 190, via=via)


def _statuses_per_link(proto, t0_s: float, seconds: float, links) -> dict:
    """#275s each link got over ``seconds`` of ticks while a target is tracked."""
    from tests.onboard.test_camera_protocol import _track

    got = {via: 0 for via in links}
    for k in range(int(round(seconds / TICK_S))):
        for o in proto.tick(t0_s + k * TICK_S, _track(), links):
            if o.msg == "camera_tracking_image_status":
                assert o.via in got and o.reply_to is None  # periodic, on one link
                got[o.via] += 1
    return got


def test_set_message_interval_applies_to_the_link_it_came_on_only():
    """mavlink.io message_rates: the interval "only applies to the link (connection) the command was received on".
    QGC sends SET_MESSAGE_INTERVAL(275, -1) with every stop: one copy's stop silenced #275 for every other copy."""
    proto = _proto(image_status_hz=10.0, geo_status_hz=5.0)
    links = [LINK_A, LINK_B]
    assert _statuses_per_link(proto, 0.0, 1.0, links) == {LINK_A: 10, LINK_B: 10}
    out, _ = proto.handle(_on(LINK_A, cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, -1), 1.0, 0)
    assert _ack(out)["result"] == cp.MAV_RESULT_ACCEPTED and out[0].via == LINK_A
    assert _statuses_per_link(proto, 1.0, 1.0, links) == {LINK_A: 0, LINK_B: 10}  # B keeps the default 10 Hz
    proto.handle(_on(LINK_B, cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, 500_000), 2.0, 0)  # QGC's 2 Hz, on B
    assert _statuses_per_link(proto, 2.0, 2.0, links) == {LINK_A: 0, LINK_B: 4}


@pytest.mark.parametrize("ask", ["get", "request"])
def test_get_message_interval_answers_the_requesters_own_link(ask):
    proto = _proto(image_status_hz=10.0)
    proto.handle(_on(LINK_A, cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, -1), 1.0, 0)
    proto.handle(_on(LINK_B, cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, 500_000), 1.0, 0)

    def asked(via):
        cmd = (
            _on(via, cp.MAV_CMD_GET_MESSAGE_INTERVAL, 275)
            if ask == "get"
            else _on(via, cp.MAV_CMD_REQUEST_MESSAGE, cp.MSG_MESSAGE_INTERVAL, 275)
        )
        out, _ = proto.handle(cmd, 1.0, 0)
        (reply,) = [o for o in out if o.msg == "message_interval"]
        assert reply.via == via
        return reply.fields["interval_us"]

    assert (asked(LINK_A), asked(LINK_B), asked((1, None))) == (-1, 500_000, 100_000)  # a third: the default
    proto.handle(_on(LINK_A, cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, 0), 1.0, 0)  # 0: back to the default
    assert (asked(LINK_A), asked(LINK_B)) == (100_000, 500_000)


def test_a_link_that_goes_away_forgets_its_setting_and_comes_back_at_the_default():
    proto = _proto(image_status_hz=10.0)
    proto.handle(_on(LINK_A, cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, -1), 0.0, 0)
    assert _statuses_per_link(proto, 0.0, 1.0, [LINK_A, LINK_B]) == {LINK_A: 0, LINK_B: 10}
    assert [e["link"] for e in proto.status()["link_intervals"]] == [str(LINK_A)]
    _statuses_per_link(proto, 1.0, 1.0, [LINK_B])  # A's peer timed out: the adapter no longer names it
    assert proto.status()["link_intervals"] == [] and proto.message_interval_us(275, LINK_A) == 100_000
    assert _statuses_per_link(proto, 2.0, 1.0, [LINK_A, LINK_B]) == {LINK_A: 10, LINK_B: 10}


def test_the_status_says_the_default_intervals_and_each_links_own():
    proto = _proto(image_status_hz=10.0, geo_status_hz=0.0)
    proto.link_name = lambda via: f"peer {via[1][0]}"
    proto.handle(_on(LINK_B, cp.MAV_CMD_SET_MESSAGE_INTERVAL, 276, 1_000_000), 0.0, 0)
    st = proto.status()
    assert (st["default_image_status_interval_s"], st["default_geo_status_interval_s"]) == (0.1, None)
    assert st["link_intervals"] == [
        {"link": "peer 10.0.0.6", "image_status_interval_s": 0.1, "geo_status_interval_s": 1.0}
    ]


def test_the_schedule_table_is_bounded_whatever_sets_an_interval():
    """Settings from addresses that are no link (a flood, each setting an interval between two ticks) cannot grow
    the table past MAX_LINKS, and the next tick keeps only the links there are."""
    from onboard.io.status_schedule import MAX_LINKS

    proto = _proto()
    for k in range(3 * MAX_LINKS):
        proto.handle(_on((0, ("10.1.0.1", 1000 + k)), cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, -1), 0.0, 0)
    assert len(proto.status()["link_intervals"]) == MAX_LINKS
    proto.tick(0.1, None, [LINK_A])
    assert proto.status()["link_intervals"] == []


def test_a_flood_of_settings_between_two_ticks_does_not_evict_the_links_there_are():
    """The table's bound forgot the least recently added link first: a link there is, set long ago, went before the
    flood's addresses that the next tick drops anyway (GcsLink.poll takes up to 100 commands an endpoint a turn)."""
    from onboard.io.status_schedule import MAX_LINKS

    proto = _proto(image_status_hz=10.0)
    proto.handle(_on(LINK_A, cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, -1), 0.0, 0)
    assert _statuses_per_link(proto, 0.0, 1.0, [LINK_A, LINK_B]) == {LINK_A: 0, LINK_B: 10}
    for k in range(MAX_LINKS + 1):  # in one turn of the main loop, from addresses that are no peer
        proto.handle(_on((0, ("10.1.0.1", 1000 + k)), cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, -1), 1.0, 0)
    assert _statuses_per_link(proto, 1.0, 1.0, [LINK_A, LINK_B]) == {LINK_A: 0, LINK_B: 10}
    assert proto.message_interval_us(275, LINK_A) == -1


def test_the_idle_at_the_end_of_tracking_goes_to_each_link_that_was_sent_an_active_one():
    """A link that turned #275 off before tracking began was sent none and gets no IDLE; one that turned it off
    while tracking (QGC's -1 follows its stop) still gets one, so that an ACTIVE sent between its stop and its -1
    does not leave its box drawn; a link gone gets nothing."""
    from tests.onboard.test_camera_protocol import _track

    link_c = (0, ("10.0.0.7", 14550))
    proto = _proto(image_status_hz=10.0)
    proto.handle(_on(LINK_A, cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, -1), 0.0, 0)
    links = [LINK_A, LINK_B, link_c]
    assert _statuses_per_link(proto, 0.0, 0.5, links) == {LINK_A: 0, LINK_B: 5, link_c: 5}
    proto.handle(_on(LINK_B, cp.MAV_CMD_SET_MESSAGE_INTERVAL, 275, -1), 0.5, 0)
    out = proto.tick(0.6, None, [LINK_A, LINK_B]) + proto.tick(0.7, None, [LINK_A, LINK_B])  # C's peer gone
    idle = [o for o in out if o.msg == "camera_tracking_image_status"]
    assert [(o.via, o.fields["tracking_status"]) for o in idle] == [(LINK_B, 0)]
    # a camera given no links (the default: every link) still says it once
    whole = _proto(image_status_hz=10.0)
    whole.tick(0.0, _track())
    assert [o.via for o in whole.tick(0.1, None) if o.msg == "camera_tracking_image_status"] == [None]
