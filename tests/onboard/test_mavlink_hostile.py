"""Hostile MAVLink input: per-datagram parsing, replies only to the autopilot, identity lock,
unknown ids, signing.  Loopback on 127.0.0.1 only, fake clock, bounded waits."""

from __future__ import annotations

import logging
import os
import select
import socket
import struct
import time

import pytest
from pymavlink.dialects.v20 import common as mav

from onboard.io.mavlink_link import LINK_CONNECTED, LINK_WAITING, MavlinkConfig
from onboard.io.mavlink_wire import CameraTrackingGeoStatus, SystemTime
from tests.fakes import FakeAutopilot
from tests.onboard.test_mavlink_link import AP_SYSID, WAIT_S, Rig

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60)]

N_TRUNCATED = 200
RSS_BUDGET_BYTES = 5 * 1024 * 1024  # 50 000 unknown ids leave RSS within 5 MB
N_UNKNOWN = 50_000


class Stranger:
    """Another local socket: sends whatever it is given to the link's port and records what comes back."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.dest = ("127.0.0.1", port)
        self.mav = mav.MAVLink(None, srcSystem=42, srcComponent=1)

    def send(self, data: bytes) -> None:
        self.sock.sendto(data, self.dest)

    def pack(self, msg, sysid: int = 42, compid: int = 1) -> bytes:
        self.mav.srcSystem, self.mav.srcComponent = sysid, compid
        return bytes(msg.pack(self.mav))

    def received(self) -> list[bytes]:
        out = []
        while True:
            try:
                out.append(self.sock.recv(65535))
            except BlockingIOError:
                return out

    def close(self) -> None:
        self.sock.close()


def heartbeat_msg(mav_type=mav.MAV_TYPE_QUADROTOR):
    return mav.MAVLink_heartbeat_message(mav_type, mav.MAV_AUTOPILOT_PX4, 0, 0, mav.MAV_STATE_ACTIVE, 3)


def attitude_msg(t_ms: int):
    return mav.MAVLink_attitude_quaternion_message(t_ms, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, [0.0] * 4)


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


@pytest.fixture
def stranger(rig):
    s = Stranger(rig.port)
    yield s
    s.close()


# --------------------------------------------------------------------------- per-datagram input


@pytest.mark.parametrize("from_stranger", [False, True], ids=["same-sender", "other-sender"])
def test_a_truncated_datagram_costs_only_itself(rig, stranger, from_stranger):
    rig.connect()
    before = rig.pose.sizes()["attitude"]
    for k in range(N_TRUNCATED):
        full = stranger.pack(attitude_msg(10_000 + 20 * k), sysid=AP_SYSID)
        cut = full[: len(full) // 2]  # header says 32 payload bytes; half of them arrive
        (stranger.send if from_stranger else rig.ap.raw)(cut)
        rig.ap.attitude(1000 * (10_000 + 20 * k + 10), [1, 0, 0, 0])
        if k % 20 == 19:  # keep the socket buffer from overflowing on a loaded box
            assert rig.drive(lambda k=k: rig.counters["mavlink_truncated"] == k + 1)
    assert rig.drive(lambda: rig.pose.sizes()["attitude"] - before == N_TRUNCATED)
    assert rig.counters["mavlink_truncated"] == N_TRUNCATED
    assert rig.pose.sizes()["attitude"] - before == N_TRUNCATED  # 200/200 valid datagrams decoded


def test_garbage_and_other_systems_never_receive_anything(rig, stranger):
    stranger.send(b"\xfd\x09\x00\x00")  # 4 bytes of a header
    stranger.send(os.urandom(120))
    stranger.send(stranger.pack(heartbeat_msg(), sysid=42))  # another "autopilot", one heartbeat
    stranger.send(
        stranger.pack(
            mav.MAVLink_heartbeat_message(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3),
            sysid=255,
            compid=190,
        )
    )
    rig.connect()
    # the link sends heartbeats, TIMESYNC, rate requests and tracking status: all to the autopilot only
    for _ in range(3):
        rig.clock.t_s += 1.0
        rig.link.send_tracking_geo_status(CameraTrackingGeoStatus(47.0, 8.0, 500.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.1))
        stranger.send(os.urandom(50))
        assert rig.drive(lambda: len(rig.ap.got("CAMERA_TRACKING_GEO_STATUS")) >= 1)
    rig.drive(lambda: False, timeout_s=0.2)
    assert rig.ap.got("HEARTBEAT") and rig.ap.got("TIMESYNC")
    assert stranger.received() == []
    assert rig.link.autopilot_sysid == AP_SYSID
    assert rig.link.peer_address[1] == rig.ap.conn.port.getsockname()[1]


def test_replies_follow_the_locked_autopilot_only_when_it_heartbeats_from_a_new_address(rig, stranger):
    rig.connect()
    stranger.send(stranger.pack(attitude_msg(9_000), sysid=AP_SYSID))  # telemetry alone does not move the peer
    assert rig.drive(lambda: rig.counters["autopilot_other_address"] == 1)  # nor is it used
    assert rig.link.peer_address[1] == rig.ap.conn.port.getsockname()[1] and rig.pose.sizes()["attitude"] == 0
    rig.clock.t_s += rig.link.config.heartbeat_timeout_s + 0.1  # the old address silent: the autopilot moved
    stranger.send(stranger.pack(heartbeat_msg(), sysid=AP_SYSID))  # (a router restart)
    assert rig.drive(lambda: rig.counters["autopilot_address_changed"] == 1)
    assert rig.link.peer_address == stranger.sock.getsockname()


def test_oversized_datagram_is_dropped_unparsed(rig, stranger):
    rig.connect()
    stranger.send(b"\xfd" * 60_000)
    rig.ap.attitude(9_000_000, [1, 0, 0, 0])
    assert rig.drive(lambda: rig.pose.sizes()["attitude"] == 1)
    assert rig.counters["mavlink_datagram_too_large"] == 1


def test_empty_datagrams_are_counted_at_debug_and_cost_nothing_else(rig, stranger, caplog):
    rig.connect()
    with caplog.at_level(logging.DEBUG, logger="onboard.core.counters"):
        for _ in range(3):
            stranger.send(b"")
        rig.ap.attitude(9_000_000, [1, 0, 0, 0])
        assert rig.drive(lambda: rig.counters["mavlink_empty_datagram"] == 3 and rig.pose.sizes()["attitude"] == 1)
    (line,) = [r for r in caplog.records if r.getMessage().startswith("mavlink_empty_datagram")]  # once per interval
    assert line.levelno == logging.DEBUG and str(stranger.sock.getsockname()[1]) in line.getMessage()
    assert rig.link.state == LINK_CONNECTED and stranger.received() == []


# --------------------------------------------------------------------------- identity


def test_a_stray_early_heartbeat_does_not_win_the_lock(rig, stranger):
    stranger.send(stranger.pack(heartbeat_msg(), sysid=42))
    assert rig.drive(lambda: rig.link.messages_rx == 1)
    rig.clock.t_s += 0.1
    rig.connect()
    assert rig.link.autopilot_sysid == AP_SYSID and rig.link.state == LINK_CONNECTED
    stranger.send(stranger.pack(attitude_msg(5_000), sysid=42))
    rig.ap.attitude(5_020_000, [1, 0, 0, 0])
    assert rig.drive(lambda: rig.pose.sizes()["attitude"] == 1)
    # the stray system keeps heartbeating after the lock: warned about, never followed
    stranger.send(stranger.pack(heartbeat_msg(), sysid=42))
    assert rig.drive(lambda: rig.counters["second_autopilot"] == 1)
    assert rig.link.autopilot_sysid == AP_SYSID and stranger.received() == []


def test_two_autopilots_heartbeating_before_the_lock_are_ambiguous(rig, stranger):
    for k in range(4):
        if k:
            rig.clock.t_s += 1.0
        stranger.send(stranger.pack(heartbeat_msg(), sysid=42))
        rig.ap.heartbeat()
        n = 2 * (k + 1)
        assert rig.drive(lambda n=n: rig.link.messages_rx == n)
    assert rig.link.state == LINK_WAITING and rig.link.autopilot_sysid is None
    assert rig.counters["autopilot_ambiguous"] >= 1
    assert stranger.received() == []


def test_pinned_sysid_locks_at_once_and_ignores_others():
    r = Rig(config=MavlinkConfig(autopilot_sysid=AP_SYSID))
    s = Stranger(r.port)
    try:
        s.send(s.pack(heartbeat_msg(), sysid=42))
        r.ap.heartbeat()
        assert r.drive(lambda: r.link.state == LINK_CONNECTED)
        assert r.link.autopilot_sysid == AP_SYSID and r.counters["second_autopilot"] == 1
    finally:
        s.close()
        r.close()


@pytest.fixture
def twin(rig):
    """A second vehicle with the autopilot's system id, sending to the link's port from an address of its own."""
    t = FakeAutopilot(rig.port, sysid=AP_SYSID, mav_type=mav.MAV_TYPE_FIXED_WING)
    yield t
    t.close()


def address(ap) -> tuple[str, int]:
    """Where the link hears ``ap`` from (its socket is bound to every interface and sends over loopback)."""
    return ("127.0.0.1", ap.conn.port.getsockname()[1])


def test_a_second_sender_of_the_autopilots_identity_is_refused_while_the_first_is_alive(rig, twin):
    rig.connect()
    rig.clock.t_s += 1.0
    # the twin's telemetry first (before its heartbeat), then its heartbeat, then more of everything it sends
    twin.attitude(9_300_000, [0.0, 1.0, 0.0, 0.0])  # upside down, 0.3 s ahead on its own clock
    assert rig.drive(lambda: rig.counters["autopilot_other_address"] == 1)
    twin.heartbeat()
    assert rig.drive(lambda: rig.counters["autopilot_duplicate"] == 1)
    twin.attitude(9_320_000, [0.0, 1.0, 0.0, 0.0])
    twin.position(9_320_000, 47.5, 8.6, 900.0)
    twin.send(SystemTime(1_800_000_000_000_000 + 9_320_000, 9_320_000))
    for k in range(5):
        rig.ap.attitude(9_000_000 + 20_000 * k, [1.0, 0.0, 0.0, 0.0])
    assert rig.drive(lambda: rig.counters["autopilot_duplicate_refused"] == 3 and rig.pose.sizes()["attitude"] == 5)
    assert rig.pose.sizes()["position"] == 0 and rig.link.utc_clock.mapping is None
    # its next heartbeat, still within the followed one's heartbeat_timeout_s, moves nothing either
    rig.clock.t_s += 3.9
    twin.heartbeat()
    assert rig.drive(lambda: rig.counters["autopilot_duplicate"] == 2)
    assert rig.counters["autopilot_address_changed"] == 0
    assert rig.link.peer_address == address(rig.ap) and rig.link.heartbeat_age_s() == pytest.approx(4.9)
    (dup,) = rig.link.duplicate_senders()
    assert (dup.sysid, dup.compid, dup.followed, dup.other) == (AP_SYSID, 1, address(rig.ap), address(twin))
    # replies (heartbeats, TIMESYNC) stay with the first
    rig.ap.heartbeat()
    before = len(rig.ap.got("HEARTBEAT"))
    rig.clock.t_s += 1.0
    assert rig.drive(lambda: len(rig.ap.got("HEARTBEAT")) > before)
    twin.pump()
    assert twin.received == [] and rig.link.state == LINK_CONNECTED


def test_a_second_sender_while_the_followed_one_is_silent_says_how_long(rig, twin, caplog):
    """A router restarted on a new port (MAVProxy killed and started again within 1.5 s: its first heartbeat from the
    new port 3.0 s after the last one from the old): refused as a second sender until the old address times out, as
    before, but the warning says the followed address is silent, not only 'two vehicles with one system id'."""
    rig.connect()
    rig.clock.t_s += 3.0
    with caplog.at_level(logging.WARNING, logger="onboard"):
        twin.heartbeat()
        assert rig.drive(lambda: rig.counters["autopilot_duplicate"] == 1)
    (dup,) = rig.link.duplicate_senders()
    assert dup.followed_silent_s == pytest.approx(3.0)
    assert f"{address(rig.ap)[0]}:{address(rig.ap)[1]} silent for 3.0 s: a router restarted" in dup.silence()
    assert any("silent for 3.0 s" in r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)
    assert rig.link.peer_address == address(rig.ap)  # still refused until heartbeat_timeout_s
    # the followed one heard again, the second half a second later: two live senders, no silence named
    rig.ap.heartbeat()
    assert rig.drive(lambda: rig.link.heartbeat_age_s() == pytest.approx(0.0))
    rig.clock.t_s += 0.5
    twin.heartbeat()
    assert rig.drive(lambda: rig.counters["autopilot_duplicate"] == 2)
    (dup,) = rig.link.duplicate_senders()
    assert dup.followed_silent_s == pytest.approx(0.5) and dup.silence() == ""


@pytest.mark.parametrize("heard_before", [False, True], ids=["new-address", "second-sender-before"])
def test_the_autopilot_moved_after_its_address_went_silent_is_followed(rig, twin, heard_before):
    rig.connect()
    if heard_before:  # a second sender while the first was alive, then the first falls silent
        twin.heartbeat()
        assert rig.drive(lambda: rig.counters["autopilot_duplicate"] == 1)
    rig.clock.t_s += rig.link.config.heartbeat_timeout_s + 0.1  # the first address silent past the timeout
    rig.link.tick()
    assert rig.counters["autopilot_lost"] == 1 and rig.link.duplicate_senders() == []
    twin.heartbeat()
    assert rig.drive(lambda: rig.counters["autopilot_address_changed"] == 1)
    assert rig.link.peer_address == address(twin) and rig.link.state == LINK_CONNECTED
    twin.attitude(9_000_000, [1.0, 0.0, 0.0, 0.0])
    assert rig.drive(lambda: rig.pose.sizes()["attitude"] == 1)
    assert rig.counters["autopilot_duplicate"] == int(heard_before) and rig.link.duplicate_senders() == []
    # the old address back while the new one is alive is now the second sender
    rig.ap.heartbeat()
    assert rig.drive(lambda: rig.counters["autopilot_duplicate"] == 1 + int(heard_before))
    assert rig.link.peer_address == address(twin)
    (dup,) = rig.link.duplicate_senders()
    assert (dup.followed, dup.other) == (address(twin), address(rig.ap))


# --------------------------------------------------------------------------- bounded memory


def _rss_bytes() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _unknown_packet(msg_id: int, seq: int) -> bytes:
    """A well-formed MAVLink 2 frame (header, 8-byte payload, any CRC) with a message id the dialect lacks."""
    payload = struct.pack("<Q", msg_id)
    header = struct.pack("<BBBBBBBHB", 0xFD, len(payload), 0, 0, seq & 0xFF, AP_SYSID, 1, msg_id & 0xFFFF, msg_id >> 16)
    return header + payload + b"\x00\x00"


def _unknown_ids(start: int, n: int):
    known = set(mav.mavlink_map)
    mid = start
    while n:
        if mid not in known:
            yield mid
            n -= 1
        mid += 1


def test_unknown_message_ids_are_counted_and_leave_memory_bounded(rig, stranger):
    rig.connect()

    def blast(ids):
        sent = 0
        for mid in ids:
            stranger.send(_unknown_packet(mid, sent))
            sent += 1
            if sent % 200 == 0:  # drain as we go: the kernel would drop the excess otherwise
                deadline = time.monotonic() + WAIT_S
                while time.monotonic() < deadline and select.select([rig.link.fileno()], [], [], 0)[0]:
                    rig.link.poll(max_messages=500)
        rig.drive(lambda: not select.select([rig.link.fileno()], [], [], 0)[0])
        return sent

    blast(_unknown_ids(20_000, 2_000))  # warm-up: allocator pools, logging of the first one
    rss0 = _rss_bytes()
    n0 = rig.counters["mavlink_unknown_id"]
    blast(_unknown_ids(100_000, N_UNKNOWN))
    grown = _rss_bytes() - rss0
    counted = rig.counters["mavlink_unknown_id"] - n0
    print(f"{N_UNKNOWN} unknown ids sent, {counted} counted, RSS grew {grown / 1e6:.2f} MB")
    assert counted >= 0.95 * N_UNKNOWN  # loopback may drop a few under load; none is kept either way
    assert grown <= RSS_BUDGET_BYTES
    assert rig.link.state == LINK_CONNECTED


# --------------------------------------------------------------------------- MAVLink 2 signing

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))


@pytest.fixture
def signed_rig():
    r = Rig(config=MavlinkConfig(autopilot_sysid=AP_SYSID), signing_key=KEY, signing_link_id=3)
    r.ap.conn.setup_signing(KEY, sign_outgoing=True, link_id=1)
    r.close_also = None
    yield r
    if r.close_also is not None:
        r.close_also.close()
    r.close()


def _signed(msg, key: bytes, timestamp: int, sysid: int = AP_SYSID, link_id: int = 2) -> bytes:
    m = mav.MAVLink(None, srcSystem=sysid, srcComponent=1)
    m.signing.secret_key, m.signing.sign_outgoing, m.signing.link_id, m.signing.timestamp = (
        key,
        True,
        link_id,
        timestamp,
    )
    return bytes(msg.pack(m))


def test_signed_link_uses_signed_packets_and_signs_its_own(signed_rig):
    r = signed_rig
    r.connect()
    r.ap.attitude(9_000_000, [1, 0, 0, 0])
    assert r.drive(lambda: r.pose.sizes()["attitude"] == 1)
    assert r.drive(lambda: r.ap.got("HEARTBEAT"))
    assert all(m._signed for m in r.ap.received)  # the fake autopilot verified every one with the key
    assert r.ap.conn.mav.signing.badsig_count == 0 and r.ap.conn.mav.signing.goodsig_count >= 2


def test_signed_link_refuses_unsigned_v1_wrong_key_and_replayed_packets(signed_rig):
    r = signed_rig
    stranger = Stranger(r.port)
    r.close_also = stranger
    r.connect()
    now_ts = r.ap.conn.mav.signing.timestamp
    stranger.send(stranger.pack(attitude_msg(9_000), sysid=AP_SYSID))  # unsigned MAVLink 2
    v1 = mav.MAVLink(None, srcSystem=AP_SYSID, srcComponent=1)
    stranger.send(bytes(attitude_msg(9_010).pack(v1, force_mavlink1=True)))  # MAVLink 1 (downgrade, CVE-2020-10283)
    stranger.send(_signed(attitude_msg(9_020), OTHER_KEY, now_ts + 10**9))  # unknown key, far-future stamp
    good = _signed(attitude_msg(9_030), KEY, now_ts + 100)
    r.ap.raw(good)
    assert r.drive(lambda: r.pose.sizes()["attitude"] == 1)  # only the genuine one, despite the future-stamped forgery
    stranger.send(good)  # replayed verbatim
    stranger.send(
        _signed(attitude_msg(9_040), KEY, now_ts - 10**8, link_id=9)
    )  # a new stream stamped 1000 s in the past
    assert r.drive(lambda: r.counters["mavlink_signature_replay"] == 1 and r.counters["mavlink_signature_stale"] == 1)
    c = r.counters
    assert (c["mavlink_unsigned"], c["mavlink_v1_refused"], c["mavlink_signature_bad"]) == (1, 1, 1)
    assert r.pose.sizes()["attitude"] == 1
    assert stranger.received() == []
    # the link's own count of them, which the watchdog keeps out of "MAVLink heard" (a wrong key is no link)
    assert r.link.status().messages_refused == 5


def test_signing_key_sources_and_errors(tmp_path):
    from onboard.app.config import build_config
    from onboard.core.errors import ConfigError
    from onboard.io.mavlink_signing import load_signing_key

    hexkey = KEY.hex()
    f = tmp_path / "key"
    f.write_text(hexkey + "\n")
    assert load_signing_key(str(f), None) == KEY
    f.write_bytes(KEY)
    assert load_signing_key(str(f), None) == KEY
    assert load_signing_key(None, "K", {"K": hexkey}) == KEY
    assert len(load_signing_key(None, "K", {"K": "a passphrase"})) == 32
    assert load_signing_key(None, None) is None
    with pytest.raises(ConfigError, match="mavlink.signing_key_env"):
        load_signing_key(None, "MISSING", {})
    with pytest.raises(ConfigError, match="mavlink.signing_key_file"):
        build_config({"mavlink": {"signing_key_file": str(tmp_path / "absent")}})
    f.write_text("\n")
    with pytest.raises(ConfigError, match="mavlink.signing_key_file"):
        build_config({"mavlink": {"signing_key_file": str(f)}})
    f.write_text(hexkey)
    assert build_config({"mavlink": {"signing_key_file": str(f)}}).mavlink.signing_key() == KEY


def test_a_key_in_hex_is_taken_as_hex_or_refused_and_a_passphrase_line_is_text(tmp_path):
    """Mistakes --check passed, each silently a key other than the autopilot's (a walkthrough of deploy/README's
    signing set-up): 62 hex digits hashed as a passphrase; od's spaced hex (the tr step forgotten) hashed as one; a
    31-character passphrase and its newline (32 bytes) taken as a raw key, newline included."""
    import hashlib

    from onboard.core.errors import ConfigError
    from onboard.io.mavlink_signing import load_signing_key

    f = tmp_path / "key"
    spaced = " ".join(KEY.hex()[i : i + 4] for i in range(0, 64, 4))  # od -An -tx1 style, the spaces not removed
    f.write_text(spaced + "\n")
    assert load_signing_key(str(f), None) == KEY
    f.write_text(KEY.hex()[:62] + "\n")
    with pytest.raises(ConfigError, match="expected 64 hex digits for a key in hex, got 62 hex digits"):
        load_signing_key(str(f), None)
    f.write_bytes(b"q" * 31 + b"\n")
    assert load_signing_key(str(f), None) == hashlib.sha256(b"q" * 31).digest()
    f.write_bytes(bytes(range(22, 54)))  # 32 raw bytes: a key, whatever they spell
    assert load_signing_key(str(f), None) == bytes(range(22, 54))


def test_a_bad_signing_key_is_one_plain_line_naming_the_field_and_the_file(tmp_path):
    """It read "mavlink.signing_key_file (PATH): expected a readable ... key, got expected 32 raw bytes ..., got an
    empty key", the path inside the field's name (so the source was blamed as '(defaults) with --set')."""
    from onboard.app.config import OnboardConfigError, load_config

    empty = tmp_path / "empty.key"
    empty.write_text("\n")
    cases = {
        (("mavlink.signing_key_file", (str(empty), "--set")),): (
            f"--set: mavlink.signing_key_file: expected 32 raw bytes, 64 hex digits or a passphrase, got an empty key "
            f"in '{empty}'"
        ),
        (("mavlink.signing_key_file", (str(empty), "--set")), ("mavlink.signing_key_env", ("K", "--set"))): (
            f"--set: mavlink.signing_key_file: expected it or mavlink.signing_key_env, not both, got both ('{empty}', "
            "'K')"
        ),
    }
    for overrides, line in cases.items():
        with pytest.raises(OnboardConfigError) as err:
            load_config(None, dict(overrides), environ={})
        assert str(err.value) == line


def test_signed_packets_without_a_key_are_used_and_counted_once(caplog):
    """A vehicle that signs while the daemon has no key: its packets are taken (unverified: nothing to check them
    with), and mavlink_signed_without_key is counted once, at INFO, naming the sender and the key to configure."""
    r = Rig(config=MavlinkConfig(autopilot_sysid=AP_SYSID))
    r.ap.conn.setup_signing(KEY, sign_outgoing=True, link_id=1)
    try:
        with caplog.at_level(logging.INFO, logger="onboard.core.counters"):
            r.ap.heartbeat()  # no r.connect(): the signing autopilot refuses our unsigned rate requests
            assert r.drive(lambda: r.link.state == LINK_CONNECTED)
            r.ap.attitude(9_000_000, [1, 0, 0, 0])
            r.ap.attitude(9_010_000, [1, 0, 0, 0])
            assert r.drive(lambda: r.pose.sizes()["attitude"] == 2)
        assert r.counters["mavlink_signed_without_key"] == 1
        (rec,) = [x for x in caplog.records if "mavlink_signed_without_key" in x.getMessage()]
        assert rec.levelno == logging.INFO
        assert f"from {AP_SYSID}/1" in rec.getMessage() and "mavlink.signing_key_file" in rec.getMessage()
    finally:
        r.close()


def test_a_udpout_link_takes_datagrams_from_its_router_only():
    """``udpout`` (the daemon sending to a router that listens, which keeps both ports across a router restart): its
    socket was bound to every interface on an ephemeral port and read whatever anyone sent there as the autopilot's
    link.  Now it is bound to the route's address (loopback) and takes datagrams from the fixed address only; a
    router not (yet) listening costs no exception."""
    from onboard.io.mavlink_transport import UdpTransport

    router = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    router.bind(("127.0.0.1", 0))
    t = UdpTransport("udpout", "127.0.0.1", router.getsockname()[1], ())
    try:
        t.write(b"hb")
        data, ours = router.recvfrom(64)
        assert data == b"hb" and ours[0] == "127.0.0.1" and t.sock.getsockname()[0] == "127.0.0.1"
        stranger.sendto(b"forged", ours)
        router.sendto(b"telemetry", ours)
        got = []
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline and not got:
            select.select([t.fileno()], [], [], 0.05)
            item = t.read()
            if item is not None and item[0]:
                got.append(item)
        time.sleep(0.05)  # the stranger's datagram was sent first: it would be read by now
        item = t.read()
        rest = [] if item is None else [item]
        assert [d for d, _ in got + rest] == [b"telemetry"]
        router.close()  # the router restarting: nobody listens on the port
        for _ in range(3):
            t.write(b"hb")  # ICMP port unreachable comes back: not an error of ours
            time.sleep(0.02)
    finally:
        t.close()
        stranger.close()
        router.close()
