"""The camera component's ``udpin`` endpoint under hostile input: who receives what, per-datagram
parsing, peer timeout and cap.  Loopback on 127.0.0.1 only, fake clock, bounded waits."""

from __future__ import annotations

import errno
import logging
import os
import select
import socket
import time

import pytest
from pymavlink.dialects.v20 import common as mav

from groundsim.io.ports import free_udp_port
from onboard.core.counters import RejectCounter
from onboard.core.errors import ConfigError
from onboard.io.camera_protocol import CameraCommand, TrackResult
from onboard.io.gcs_link import MAX_PEERS, PEER_TIMEOUT_S, GcsLink
from tests.fakes import FakeClock, silent_tcp_server
from tests.onboard.test_camera_protocol import _proto

pytestmark = [pytest.mark.integration, pytest.mark.timeout(30)]

WAIT_S = 3.0  # upper bound on any single wait for a loopback event
SYSID = 1
GCS = (255, 190)  # QGC's system / component
CUT_DATAGRAM = b"\xfd\x40\x00\x00\x00"  # a MAVLink 2 header announcing 64 payload bytes, cut after 5
N_ROUNDS = 5
X_TOL = 1e-6  # a normalised coordinate through COMMAND_LONG's float32


class Peer:
    """A local UDP socket speaking to the camera port; records every MAVLink message sent back to it."""

    def __init__(self, port: int, sysid: int = GCS[0], compid: int = GCS[1]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.addr = self.sock.getsockname()
        self.dest = ("127.0.0.1", port)
        self.mav = mav.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.key: bytes | None = None
        self.got: list = []

    def raw(self, data: bytes) -> None:
        self.sock.sendto(data, self.dest)

    def send(self, msg) -> None:
        self.raw(bytes(msg.pack(self.mav)))
        self.mav.seq = (self.mav.seq + 1) % 256

    def heartbeat(self) -> None:
        self.send(mav.MAVLink_heartbeat_message(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 4, 3))

    def request_camera_information(self) -> None:
        self.send(
            mav.MAVLink_command_long_message(
                SYSID, 100, mav.MAV_CMD_REQUEST_MESSAGE, 0, mav.MAVLINK_MSG_ID_CAMERA_INFORMATION, 0, 0, 0, 0, 0, 0
            )
        )

    def drain(self) -> list:
        """Parse what arrived (each datagram alone) into ``got``; returns the number of datagrams."""
        n = 0
        while True:
            try:
                data = self.sock.recv(65535)
            except BlockingIOError:
                return n
            n += 1
            parser = mav.MAVLink(None)
            parser.robust_parsing = True
            parser.signing.secret_key = self.key  # with a key only verified packets count (``_signed``)
            self.got += [m for m in parser.parse_buffer(data) or [] if m.get_type() != "BAD_DATA"]

    def types(self, name: str) -> list:
        return [m for m in self.got if m.get_type() == name]

    def close(self) -> None:
        self.sock.close()


class Rig:
    """A GcsLink on ``udpin:127.0.0.1:PORT`` with a fake clock, a counter and the camera protocol."""

    def __init__(self, before: tuple[str, ...] = (), **link_kw) -> None:
        """``before``: endpoints listed before the ``udpin`` one."""
        self.port = free_udp_port()
        self.clock = FakeClock()
        self.counters = RejectCounter(clock=self.clock)
        endpoints = [*before, f"udpin:127.0.0.1:{self.port}"]
        self.link = GcsLink(endpoints, 100, counter=self.counters, clock=self.clock, **link_kw)
        self.link.set_system_id(SYSID)
        self.proto = _proto()
        self.peers: list[Peer] = []
        self.commands: list[CameraCommand] = []

    def peer(self, **kw) -> Peer:
        p = Peer(self.port, **kw)
        self.peers.append(p)
        return p

    def drive(self, cond, timeout_s: float = WAIT_S) -> bool:
        """Poll the link (answering commands through the protocol) and drain the peers until ``cond()``."""
        deadline = time.monotonic() + timeout_s
        while True:
            for c in self.link.poll():
                self.commands.append(c)
                for out in self.proto.handle(c, self.clock(), 0)[0]:
                    self.link.send(out)
            for p in self.peers:
                p.drain()
            if cond():
                return True
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            select.select(self.link.filenos() + [p.sock for p in self.peers], [], [], min(left, 0.01))

    def heartbeat_out(self) -> int:
        return sum(self.link.send(o) for o in self.proto.tick(self.clock(), None) if o.msg == "heartbeat")

    def close(self) -> None:
        self.link.close()
        for p in self.peers:
            p.close()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def _became_peer(rig: Rig, peer: Peer) -> bool:
    return rig.drive(lambda: peer.addr in rig.link.peers()[0])


JUNK = {
    "garbage": lambda p: p.raw(b"not mavlink at all"),
    "cut": lambda p: p.raw(CUT_DATAGRAM),
    "random": lambda p: p.raw(os.urandom(200)),
    # a well-framed MAVLink 2 packet of an id the dialect lacks: pymavlink cannot check its CRC
    "unknown_id": lambda p: p.raw(b"\xfd\x01\x00\x00\x00\x2a\x01\xff\xff\xff\x00\x12\x34"),
    "silent": lambda p: None,
}


@pytest.mark.parametrize("junk", sorted(JUNK))
def test_a_stranger_that_sent_nothing_valid_receives_nothing(rig, junk):
    gcs, stranger = rig.peer(), rig.peer(sysid=77, compid=1)
    JUNK[junk](stranger)
    gcs.heartbeat()
    assert _became_peer(rig, gcs)
    for _ in range(3):
        rig.clock.t_s += 1.0
        JUNK[junk](stranger)
        assert rig.heartbeat_out() == 1
    assert rig.drive(lambda: len(gcs.types("HEARTBEAT")) == 3)
    assert stranger.drain() == 0
    assert rig.link.peers() == [[gcs.addr]]


def test_a_ground_station_gets_every_ack_despite_cut_datagrams_from_another_address(rig):
    gcs, stranger = rig.peer(), rig.peer(sysid=77, compid=1)
    for k in range(N_ROUNDS):
        stranger.raw(CUT_DATAGRAM)
        gcs.request_camera_information()
        assert rig.drive(lambda k=k: len(gcs.types("COMMAND_ACK")) == k + 1)
        rig.clock.t_s += 1.0
        assert rig.heartbeat_out() == 1
    assert rig.drive(lambda: len(gcs.types("HEARTBEAT")) == N_ROUNDS)
    acks = gcs.types("COMMAND_ACK")
    assert [a.result for a in acks] == [mav.MAV_RESULT_ACCEPTED] * N_ROUNDS
    assert len(gcs.types("CAMERA_INFORMATION")) == N_ROUNDS
    assert rig.counters["gcs_truncated"] == N_ROUNDS
    assert stranger.drain() == 0


def test_a_cut_datagram_from_the_same_address_costs_only_itself(rig):
    gcs = rig.peer()
    for k in range(N_ROUNDS):
        gcs.raw(CUT_DATAGRAM)
        gcs.request_camera_information()
        assert rig.drive(lambda k=k: len(gcs.types("COMMAND_ACK")) == k + 1)
    assert len(rig.commands) == N_ROUNDS


def test_command_long_confirmation_reaches_the_protocol_and_a_resend_is_answered_in_progress(rig):
    """COMMAND_LONG's confirmation tells a resend from a new command; COMMAND_INT has none (0)."""
    gcs = rig.peer()
    point = (0.25, 0.5, 0.03, 0.0, 0.0, 0.0, 0.0)
    for confirmation in (0, 1):
        gcs.send(mav.MAVLink_command_long_message(SYSID, 100, mav.MAV_CMD_CAMERA_TRACK_POINT, confirmation, *point))
    assert rig.drive(lambda: len(gcs.types("COMMAND_ACK")) == 1)
    assert [c.confirmation for c in rig.commands] == [0, 1]
    (ack,) = gcs.types("COMMAND_ACK")
    assert (ack.command, ack.result, ack.progress) == (mav.MAV_CMD_CAMERA_TRACK_POINT, mav.MAV_RESULT_IN_PROGRESS, 255)
    gcs.send(
        mav.MAVLink_command_int_message(
            SYSID, 100, 0, mav.MAV_CMD_CAMERA_STOP_TRACKING, 0, 0, 0.0, 0.0, 0.0, 0.0, 0, 0, 0.0
        )
    )
    assert rig.drive(lambda: len(rig.commands) == 3)
    assert rig.commands[2].command == mav.MAV_CMD_CAMERA_STOP_TRACKING and rig.commands[2].confirmation == 0


def test_a_reply_goes_to_the_address_of_the_command_only(rig):
    gcs, other = rig.peer(), rig.peer(sysid=200, compid=190)
    other.heartbeat()
    assert _became_peer(rig, other)
    gcs.request_camera_information()
    assert rig.drive(lambda: len(gcs.types("CAMERA_INFORMATION")) == 1)
    rig.clock.t_s += 1.0
    assert rig.heartbeat_out() == 1  # a periodic message, to both peers: shows other's socket is served
    assert rig.drive(lambda: gcs.types("HEARTBEAT") and other.types("HEARTBEAT"))
    assert [m.get_type() for m in other.got] == ["HEARTBEAT"]


def test_ground_stations_with_the_same_ids_on_two_endpoints_and_two_addresses_each_get_their_own_ack():
    """Three ground stations, all QGC's default 255/190: one on a ``udpout`` endpoint, two at different addresses of
    a ``udpin`` one.  Each click is decided by the pipeline; each station gets its own ACK only (keyed by the ids
    alone, the later clicks superseded the earlier and every ACK went where the ids spoke last)."""
    out_port = free_udp_port()
    a = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # the station the udpout endpoint sends to
    a.bind(("127.0.0.1", out_port))
    a.setblocking(False)
    rig = Rig(before=(f"udpout:127.0.0.1:{out_port}",))
    try:
        hb = [o for o in rig.proto.tick(0.0, None) if o.msg == "heartbeat"][0]
        assert rig.link.send(hb) == 1  # udpout only: the udpin endpoint has no peer yet
        select.select([a], [], [], WAIT_S)
        _, link_addr = a.recvfrom(65535)  # where the udpout endpoint sends from, which A answers
        b1, b2 = rig.peer(), rig.peer()
        clicks = {"a": 0.2, "b1": 0.5, "b2": 0.8}
        a_mav = mav.MAVLink(None, srcSystem=GCS[0], srcComponent=GCS[1])
        a.sendto(_click(clicks["a"]).pack(a_mav), link_addr)
        b1.send(_click(clicks["b1"]))
        b2.send(_click(clicks["b2"]))
        commands: list[CameraCommand] = []
        deadline = time.monotonic() + WAIT_S
        while len(commands) < 3 and time.monotonic() < deadline:
            commands += rig.link.poll()
            select.select(rig.link.filenos(), [], [], 0.01)
        assert len(commands) == 3
        request_of = {c.params[0]: rig.proto.handle(c, rig.clock(), 0)[1] for c in commands}
        assert rig.proto.pending_requests() == 3
        accepted = {"a": True, "b1": False, "b2": True}
        for name, x in clicks.items():
            (req,) = [r for x_sent, r in request_of.items() if abs(x_sent - x) < X_TOL]
            result = TrackResult(req.request_id, accepted[name], "nothing there")
            for out in rig.proto.complete(result):
                assert rig.link.send(out) == 1
        assert rig.drive(lambda: b1.types("COMMAND_ACK") and b2.types("COMMAND_ACK"))
        select.select([a], [], [], WAIT_S)
        a_got = mav.MAVLink(None).parse_buffer(a.recv(65535)) or []
        got = {
            name: [m.result for m in msgs if m.get_type() == "COMMAND_ACK"]
            for name, msgs in (("a", a_got), ("b1", b1.got), ("b2", b2.got))
        }
        assert got == {"a": [mav.MAV_RESULT_ACCEPTED], "b1": [mav.MAV_RESULT_FAILED], "b2": [mav.MAV_RESULT_ACCEPTED]}
    finally:
        rig.close()
        a.close()


def _click(x: float):
    return mav.MAVLink_command_long_message(SYSID, 100, mav.MAV_CMD_CAMERA_TRACK_POINT, 0, x, 0.5, 0.03, 0, 0, 0, 0)


def test_a_silent_peer_is_dropped_after_the_timeout_and_readmitted_when_heard(rig):
    a, b = rig.peer(), rig.peer(sysid=254, compid=190)
    a.heartbeat()
    assert _became_peer(rig, a)
    rig.clock.t_s += PEER_TIMEOUT_S - 0.5
    b.heartbeat()
    assert _became_peer(rig, b)
    assert rig.heartbeat_out() == 1  # a is still within the timeout
    assert rig.drive(lambda: len(a.types("HEARTBEAT")) == 1 and len(b.types("HEARTBEAT")) == 1)

    rig.clock.t_s += 1.0  # a silent for PEER_TIMEOUT_S + 0.5
    assert rig.link.peers() == [[b.addr]]
    assert rig.heartbeat_out() == 1
    assert rig.drive(lambda: len(b.types("HEARTBEAT")) == 2)
    assert len(a.types("HEARTBEAT")) == 1

    a.heartbeat()
    assert _became_peer(rig, a)
    rig.clock.t_s += PEER_TIMEOUT_S + 0.5  # both silent now: nobody to send to
    assert rig.heartbeat_out() == 0
    assert rig.link.peers() == [[]]


def test_peers_beyond_the_cap_get_replies_only_counted_and_logged_once(rig, caplog):
    inside = [rig.peer(sysid=200 + k) for k in range(MAX_PEERS)]
    for p in inside:
        p.heartbeat()
        assert _became_peer(rig, p)
    extra = rig.peer(sysid=199)
    with caplog.at_level(logging.WARNING, logger="onboard.io.gcs_link"):
        for _ in range(3):
            extra.heartbeat()
        extra.request_camera_information()
        assert rig.drive(lambda: len(extra.types("COMMAND_ACK")) == 1)
    assert rig.counters["gcs_peer_refused"] == 4  # 3 heartbeats and the command, from the refused address
    assert sum("ground-station peers already" in r.getMessage() for r in caplog.records) == 1
    rig.clock.t_s += 1.0
    assert rig.heartbeat_out() == 1
    assert rig.drive(lambda: all(len(p.types("HEARTBEAT")) == 1 for p in inside))
    assert extra.types("HEARTBEAT") == []
    assert len(rig.link.peers()[0]) == MAX_PEERS

    # one peer falls silent: the next message from the extra address makes it a peer
    rig.clock.t_s += PEER_TIMEOUT_S - 0.5
    for p in inside[1:]:
        p.request_camera_information()  # refreshes the peer; its ACK shows it was read
    assert rig.drive(lambda: all(len(p.types("COMMAND_ACK")) == 1 for p in inside[1:]))
    rig.clock.t_s += 1.0
    extra.heartbeat()
    assert _became_peer(rig, extra)
    assert inside[0].addr not in rig.link.peers()[0]


def test_udpout_sends_to_its_address_whoever_else_speaks():
    port = free_udp_port()
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", port))
    listener.settimeout(WAIT_S)
    link = GcsLink([f"udpout:127.0.0.1:{port}"], 100)
    try:
        link.set_system_id(SYSID)
        assert link.peers() == [[]]
        hb = [o for o in _proto().tick(0.0, None) if o.msg == "heartbeat"]
        assert link.send(hb[0]) == 1
        parser = mav.MAVLink(None)
        assert parser.parse_buffer(listener.recv(65535))[0].get_type() == "HEARTBEAT"
    finally:
        link.close()
        listener.close()


def test_udpout_takes_commands_from_its_ground_station_only():
    port = free_udp_port()
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", port))
    listener.settimeout(WAIT_S)
    stranger = Peer(port, sysid=77, compid=77)
    link = GcsLink([f"udpout:127.0.0.1:{port}"], 100)
    try:
        link.set_system_id(SYSID)
        hb = [o for o in _proto().tick(0.0, None) if o.msg == "heartbeat"]
        assert link.send(hb[0]) == 1
        _, link_addr = listener.recvfrom(65535)
        # the port the camera sends from is no udpin: a STOP from an address nobody configured is not a command
        stop = mav.MAVLink_command_long_message(SYSID, 100, mav.MAV_CMD_CAMERA_STOP_TRACKING, 0, 0, 0, 0, 0, 0, 0, 0)
        stranger.dest = link_addr
        stranger.send(stop)
        request = mav.MAVLink_command_long_message(
            SYSID, 100, mav.MAV_CMD_REQUEST_MESSAGE, 0, mav.MAVLINK_MSG_ID_CAMERA_INFORMATION, 0, 0, 0, 0, 0, 0
        )
        listener.sendto(bytes(request.pack(mav.MAVLink(None, srcSystem=GCS[0], srcComponent=GCS[1]))), link_addr)
        commands: list = []
        deadline = time.monotonic() + WAIT_S
        while not commands and time.monotonic() < deadline:
            commands += link.poll()
            time.sleep(0.01)
        commands += link.poll()  # the stranger's datagram was sent first: it would have come with the ground station's
        assert [(c.command, c.src_system) for c in commands] == [(mav.MAV_CMD_REQUEST_MESSAGE, GCS[0])]
    finally:
        link.close()
        listener.close()
        stranger.close()


def test_udpout_to_a_host_name_is_pinned_once_it_resolves_and_one_that_does_not_is_no_error():
    """pymavlink puts the address a name resolves to in place of the name at its first send; a name that does not
    resolve leaves the name, and the socket unconnected, with nothing counted against the link's sends."""
    counters = RejectCounter()
    link = GcsLink([f"udpout:localhost:{free_udp_port()}", "udpout:no-such-host.invalid:14550"], 100, counter=counters)
    try:
        link.set_system_id(SYSID)
        hb = [o for o in _proto().tick(0.0, None) if o.msg == "heartbeat"]
        link.send(hb[0])
        assert link._conns[0].port.getpeername()[0] == "127.0.0.1"
        with pytest.raises(OSError):
            link._conns[1].port.getpeername()
        assert "gcs_tx_error" not in counters.counts
    finally:
        link.close()


def test_udpout_to_a_multicast_group_still_takes_its_members_answers():
    """A member answers from its own address, not the group's: the socket is left unconnected."""
    link = GcsLink([f"udpout:239.255.77.1:{free_udp_port()}"], 100)
    try:
        link.set_system_id(SYSID)
        hb = [o for o in _proto().tick(0.0, None) if o.msg == "heartbeat"]
        link.send(hb[0])  # written or not (a host without a multicast route): the address is looked up
        link.send(hb[0])
        with pytest.raises(OSError):
            link._conns[0].port.getpeername()
    finally:
        link.close()


@pytest.mark.parametrize(
    "kw, expected",
    [
        (dict(peer_timeout_s=0.0), "expected seconds > 0, got 0.0"),
        (dict(peer_timeout_s=True), "expected seconds > 0, got True"),  # a bool is not a number of seconds
        (dict(max_peers=0), "expected an integer >= 1, got 0"),
        (dict(max_peers=2.0), "expected an integer >= 1, got 2.0"),
    ],
    ids=["peer_timeout_0", "peer_timeout_bool", "max_peers_0", "max_peers_float"],
)
def test_bad_peer_settings_are_refused(kw, expected):
    (field,) = kw
    with pytest.raises(ConfigError) as e:
        GcsLink(["udpout:127.0.0.1:9"], 100, **kw)
    assert str(e.value) == f"GcsLink.{field}: {expected}"


# --------------------------------------------------------------------------- MAVLink 2 signing

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))


def _sign_with(peer: Peer, key: bytes) -> Peer:
    """``peer`` sends signed with ``key`` and keeps only what it receives verified with ``KEY``."""
    peer.mav.signing.secret_key, peer.mav.signing.sign_outgoing, peer.mav.signing.link_id = key, True, 1
    peer.mav.signing.timestamp = int((time.time() - 1420070400) * 100_000)
    peer.key = KEY
    return peer


@pytest.fixture
def signed_rig():
    r = Rig(signing_key=KEY)
    yield r
    r.close()


def test_with_a_key_the_camera_answers_signed_commands_only_and_signs_its_answers(signed_rig):
    """An unsigned or wrongly signed command (a click that would move the tracked target) is refused and counted,
    makes no peer and gets no answer; a command signed with the key is answered, signed."""
    rig = signed_rig
    unsigned, wrong, good = rig.peer(), _sign_with(rig.peer(), OTHER_KEY), _sign_with(rig.peer(), KEY)
    unsigned.request_camera_information()
    wrong.request_camera_information()
    assert rig.drive(lambda: sum(rig.counters.counts.get(k, 0) for k in ("gcs_unsigned", "gcs_signature_bad")) == 2)
    assert rig.counters.counts["gcs_unsigned"] == 1 and rig.counters.counts["gcs_signature_bad"] == 1
    assert rig.commands == [] and rig.link.peers() == [[]]
    good.request_camera_information()
    assert rig.drive(lambda: good.types("CAMERA_INFORMATION"))
    assert [(m.get_type(), m._signed) for m in good.got] == [("COMMAND_ACK", True), ("CAMERA_INFORMATION", True)]
    assert [c.command for c in rig.commands] == [mav.MAV_CMD_REQUEST_MESSAGE]
    assert rig.link.peers() == [[good.addr]]
    assert unsigned.got == [] and wrong.got == []


def test_with_a_key_udpout_signs_what_it_sends_and_refuses_unsigned_commands():
    port = free_udp_port()
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", port))
    listener.settimeout(WAIT_S)
    counters = RejectCounter()
    link = GcsLink([f"udpout:127.0.0.1:{port}"], 100, counter=counters, signing_key=KEY)
    try:
        link.set_system_id(SYSID)
        hb = [o for o in _proto().tick(0.0, None) if o.msg == "heartbeat"]
        assert link.send(hb[0]) == 1
        data, link_addr = listener.recvfrom(65535)
        signed = mav.MAVLink(None)
        signed.signing.secret_key = KEY
        (msg,) = signed.parse_buffer(data)
        assert msg.get_type() == "HEARTBEAT" and msg._signed and signed.signing.goodsig_count == 1
        # an unsigned command back to the port the link sends from: refused, counted
        cmd = mav.MAVLink_command_long_message(
            SYSID, 100, mav.MAV_CMD_REQUEST_MESSAGE, 0, mav.MAVLINK_MSG_ID_CAMERA_INFORMATION, 0, 0, 0, 0, 0, 0
        )
        listener.sendto(bytes(cmd.pack(mav.MAVLink(None, srcSystem=GCS[0], srcComponent=GCS[1]))), link_addr)
        deadline = time.monotonic() + WAIT_S
        while counters.counts.get("gcs_unsigned", 0) == 0 and time.monotonic() < deadline:
            assert link.poll() == []
            time.sleep(0.01)
        assert counters.counts.get("gcs_unsigned") == 1
        # the same command signed with the key: taken
        gcs = mav.MAVLink(None, srcSystem=GCS[0], srcComponent=GCS[1])
        gcs.signing.secret_key, gcs.signing.sign_outgoing, gcs.signing.link_id = KEY, True, 1
        gcs.signing.timestamp = int((time.time() - 1420070400) * 100_000)
        listener.sendto(bytes(cmd.pack(gcs)), link_addr)
        commands: list = []
        deadline = time.monotonic() + WAIT_S
        while not commands and time.monotonic() < deadline:
            commands += link.poll()
            time.sleep(0.01)
        assert [c.command for c in commands] == [mav.MAV_CMD_REQUEST_MESSAGE]
    finally:
        link.close()
        listener.close()


def test_a_signing_key_of_the_wrong_size_is_refused():
    with pytest.raises(ConfigError, match="signing_key"):
        GcsLink(["udpout:127.0.0.1:9"], 100, signing_key=b"short")


def test_a_tcp_ground_station_not_up_yet_is_dialled_again_not_fatal(capsys):
    """A ground station the camera dials over TCP may start after the vehicle: its refusal stopped the daemon's
    start (exit 2, after pymavlink slept 3 s printing to stdout); it is counted and dialled again."""
    from groundsim.io.ports import free_tcp_port
    from onboard.io.gcs_link import TCP_REDIAL_S

    port = free_tcp_port()
    clock = FakeClock()
    counters = RejectCounter(clock=clock)
    t0 = time.monotonic()
    link = GcsLink([f"tcp:127.0.0.1:{port}"], 100, counter=counters, clock=clock)
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        assert time.monotonic() - t0 < 1.0  # no retries slept inside pymavlink
        assert counters.counts["gcs_open_failed"] == 1 and link.filenos() == []
        link.set_system_id(SYSID)
        hb = [o for o in _proto().tick(0.0, None) if o.msg == "heartbeat"][0]
        assert link.send(hb) == 0  # nobody yet: nothing sent, nothing raised
        server.bind(("127.0.0.1", port))
        server.listen(1)
        server.settimeout(WAIT_S)
        clock.t_s += TCP_REDIAL_S / 2
        link.poll()
        assert link.filenos() == []  # not before its time
        clock.t_s += TCP_REDIAL_S
        link.poll()
        peer, _ = server.accept()
        with peer:
            assert link.send(hb) == 1
            peer.settimeout(WAIT_S)
            (msg,) = mav.MAVLink(None).parse_buffer(peer.recv(65535))
            assert msg.get_type() == "HEARTBEAT" and (msg.get_srcSystem(), msg.get_srcComponent()) == (SYSID, 100)
        # the ground station goes away: marked, dropped and dialled again every TCP_REDIAL_S, not at every poll
        # (pymavlink's own reconnection tried at each one, printing "Attempting reconnect" to stdout)
        for _ in range(20):
            link.poll()
            time.sleep(0.01)
        link.poll()
        assert counters.counts["gcs_link_lost"] == 1 and link.filenos() == [] and link.send(hb) == 0
        clock.t_s += TCP_REDIAL_S
        link.poll()
        again, _ = server.accept()  # dialled again
        with again:
            assert link.send(hb) == 1
        assert capsys.readouterr().out == ""
    finally:
        link.close()
        server.close()


def test_a_tcp_ground_station_that_does_not_answer_never_blocks_the_loop():
    """pymavlink connected in its constructor, blocking: against an address that drops the packets the daemon's
    main loop (the autopilot's telemetry among its work) waited for the kernel to give up, minutes.  Here the
    ground station's accept queue is full, so its host drops our connection's packets as such a host would."""
    from onboard.io.gcs_link import TCP_CONNECT_TIMEOUT_S, TCP_REDIAL_S

    server, filler = silent_tcp_server(WAIT_S)
    clock = FakeClock()
    counters = RejectCounter(clock=clock)
    t0 = time.monotonic()
    link = GcsLink([f"tcp:127.0.0.1:{server.getsockname()[1]}"], 100, counter=counters, clock=clock)
    try:
        link.set_system_id(SYSID)
        hb = [o for o in _proto().tick(0.0, None) if o.msg == "heartbeat"][0]
        assert link.send(hb) == 0 and link.poll() == [] and link.filenos() == []
        assert time.monotonic() - t0 < 1.0 and "gcs_open_failed" not in counters.counts  # under way, not waited for
        clock.t_s += TCP_CONNECT_TIMEOUT_S
        link.poll()
        assert counters.counts["gcs_open_failed"] == 1 and link.filenos() == []
        # the ground station takes connections again: the next dial gets through
        first, _ = server.accept()
        first.close()
        filler.close()
        server.settimeout(WAIT_S)
        clock.t_s += TCP_REDIAL_S
        deadline = time.monotonic() + WAIT_S
        while not link.filenos() and time.monotonic() < deadline:
            link.poll()
            time.sleep(0.01)
        peer, _ = server.accept()
        with peer:
            assert link.send(hb) == 1
            peer.settimeout(WAIT_S)
            (msg,) = mav.MAVLink(None).parse_buffer(peer.recv(65535))
            assert msg.get_type() == "HEARTBEAT"
        assert time.monotonic() - t0 < 2 * WAIT_S
    finally:
        link.close()
        filler.close()
        server.close()


def test_a_dial_without_a_free_descriptor_is_counted_and_tried_again(monkeypatch):
    """socket() itself was outside the dial's error handling: out of descriptors, poll() (which never raises)
    raised OSError into the daemon's main loop."""
    import onboard.io.mavlink_transport as transport_module
    from onboard.io.gcs_link import TCP_REDIAL_S

    def no_descriptor(*_a, **_k):
        raise OSError(errno.EMFILE, os.strerror(errno.EMFILE))

    clock = FakeClock()
    counters = RejectCounter(clock=clock)
    monkeypatch.setattr(transport_module.socket, "socket", no_descriptor)
    link = GcsLink(["tcp:127.0.0.1:9"], 100, counter=counters, clock=clock)
    try:
        clock.t_s += TCP_REDIAL_S
        assert link.poll() == [] and link.filenos() == []
        assert counters.counts["gcs_open_failed"] == 2
    finally:
        link.close()


def test_each_peer_gets_the_tracking_status_on_its_own_schedule_and_its_own_sequence_numbers():
    """Two ground stations with the same ids on one udpin port: one's SET_MESSAGE_INTERVAL(275, -1) stops #275 for it
    alone (MAVLink: it applies to the link it came on), and each sees an unbroken sequence of packet numbers from
    the camera (a gap is a lost packet to QGC) although each gets messages the other does not."""
    from tests.onboard.test_camera_protocol import _track

    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # a udpout ground station, listed first
    sink.bind(("127.0.0.1", 0))
    rig = Rig(before=(f"udpout:127.0.0.1:{sink.getsockname()[1]}",))
    try:
        a, b = rig.peer(), rig.peer()
        a.heartbeat()
        b.heartbeat()
        assert rig.drive(lambda: len(rig.link.peers()[1]) == 2)
        assert rig.link.links() == [(0, None), (1, a.addr), (1, b.addr)]
        assert rig.link.link_name((1, a.addr)) == f"udpin:127.0.0.1:{rig.port} from {a.addr[0]}:{a.addr[1]}"
        assert rig.link.link_name((0, None)) == rig.link.endpoints[0]
        a.send(
            mav.MAVLink_command_long_message(SYSID, 100, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 275, -1, 0, 0, 0, 0, 0)
        )
        assert rig.drive(lambda: a.types("COMMAND_ACK"))
        for _ in range(10):  # 1 s of ticks at 10 Hz, the default
            for out in rig.proto.tick(rig.clock(), _track(), rig.link.links()):
                rig.link.send(out)
            rig.clock.t_s += 0.1
        assert rig.drive(lambda: len(b.types("CAMERA_TRACKING_IMAGE_STATUS")) == 10)
        assert a.types("CAMERA_TRACKING_IMAGE_STATUS") == [] and len(a.types("HEARTBEAT")) >= 1
        for p in (a, b):
            seqs = [m.get_seq() for m in p.got if m.get_srcComponent() == 100]
            assert seqs == list(range(len(seqs))), seqs
    finally:
        rig.close()
        sink.close()
