"""Fuzz target: the MAVLink input, datagram by datagram, with hypothesis.

The subject is :meth:`onboard.io.mavlink_link.MavlinkLink.poll` on a UDP link: each datagram goes
through the per-datagram parser, the signing check, the identity rules and the handlers into a
real :class:`~onboard.core.pose.PoseBuffer`.  The link's socket is real (bound on 127.0.0.1) but its
``read`` is fed from memory, so thousands of datagrams run per second; the socket path itself is
tested in ``tests/onboard/test_mavlink_hostile.py``.

Properties, for any datagrams (random bytes, mutated valid packets, valid packets with any field
values, signed and unsigned):

* ``poll`` never raises, and no datagram ends in a catch-all (``mavlink_handler_error``: one of
  our handlers threw);
* every datagram is accounted for: it is decoded into a message the link uses or ignores by rule
  (another system, a type we do not read), or a rejection is counted (``mavlink_bad_data``,
  ``mavlink_truncated``, ``mavlink_unknown_id``, ``mavlink_datagram_too_large``, the signing
  reasons, ``mavlink_recv_error`` when pymavlink itself throws, the pose buffer's reasons); a
  telemetry sample the pose buffer does not take is counted;
* a valid packet is decoded whatever garbage came before or after it, in other datagrams, or in the
  same datagram before it when that garbage holds no MAVLink start byte (0xFD / 0xFE: a start byte
  in garbage claims the bytes after it, as on a serial stream; the packet is then lost, counted).

Budget: ``tests/fuzz_budget.py`` (``IRTRACK_FUZZ_EXAMPLES`` runs it longer).
"""

from __future__ import annotations

import time

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mav  # noqa: E402

from groundsim.io.ports import free_udp_port  # noqa: E402
from onboard.core.frames import GeodeticOrigin  # noqa: E402
from onboard.core.pose import PoseBuffer  # noqa: E402
from onboard.io.mavlink_link import MavlinkConfig  # noqa: E402
from tests.fuzz_budget import fuzz_settings, timeout_s  # noqa: E402
from tests.onboard.test_mavlink_link import loopback_link  # noqa: E402

AP_SYSID = 1
KEY = bytes(range(32))
FOREIGN_KEY = bytes(32)  # another network's key
SIGNING_EPOCH_S = 1420070400  # MAVLink 2 signing timestamps count from 2015-01-01
CATCH_ALL = "mavlink_handler_error"  # one of our handlers threw: a bug, never an accepted outcome
START_BYTES = (0xFD, 0xFE)
I32 = st.integers(-(2**31), 2**31 - 1)
U32 = st.integers(0, 2**32 - 1)
F32 = st.floats(width=32)  # NaN and infinities included

pytestmark = pytest.mark.timeout(timeout_s(120))


class RecordingPose(PoseBuffer):
    """The real pose buffer, recording what the link gave it and what it answered."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.calls: list[tuple[str, int, bool]] = []

    def add_attitude(self, time_boot_us, *args, **kwargs):
        ok = super().add_attitude(time_boot_us, *args, **kwargs)
        self.calls.append(("attitude", time_boot_us, ok))
        return ok

    def add_position(self, time_boot_us, *args, **kwargs):
        ok = super().add_position(time_boot_us, *args, **kwargs)
        self.calls.append(("position", time_boot_us, ok))
        return ok

    def add_gimbal_status(self, time_boot_us, *args, **kwargs):
        ok = super().add_gimbal_status(time_boot_us, *args, **kwargs)
        self.calls.append(("gimbal", time_boot_us, ok))
        return ok


class Harness:
    """A MavlinkLink on a real 127.0.0.1 socket whose reads come from ``feed``."""

    def __init__(self, signed: bool = False, gimballed: bool = True) -> None:
        cfg = MavlinkConfig(autopilot_sysid=AP_SYSID)
        self.clock, self.counter, self.pose, self.link = loopback_link(
            free_udp_port(),
            GeodeticOrigin(47.0, 8.0, 400.0),
            gimballed=gimballed,
            config=cfg,
            link_kw={"signing_key": KEY if signed else None},
            pose_cls=RecordingPose,
            log_interval_s=1e9,  # counted, logged once
        )
        self._inbox: list[tuple[bytes, tuple[str, int]]] = []
        self.sent: list[bytes] = []
        t = self.link._transport  # the test seam: reads from memory, writes recorded
        t.read = lambda: self._inbox.pop(0) if self._inbox else None
        t.write = self.sent.append

    def feed(self, datagram: bytes, addr=("127.0.0.1", 40000)) -> tuple[int, dict[str, int], int]:
        """One datagram through poll(); returns (messages decoded, counts added, pose calls added)."""
        before_rx, before = self.link.messages_rx, self.counter.counts
        before_calls = len(self.pose.calls)
        self._inbox.append((bytes(datagram), addr))
        self.link.poll()  # must not raise
        assert not self._inbox
        after = self.counter.counts
        added = {k: v - before.get(k, 0) for k, v in after.items() if v != before.get(k, 0)}
        return self.link.messages_rx - before_rx, added, len(self.pose.calls) - before_calls

    def close(self) -> None:
        self.link.close()


def packer(sysid: int = AP_SYSID, compid: int = 1, signed: bool = False, key: bytes = KEY) -> mav.MAVLink:
    m = mav.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    if signed:
        m.signing.secret_key = key
        m.signing.sign_outgoing = True
        m.signing.link_id = 0
        m.signing.timestamp = int((time.time() - SIGNING_EPOCH_S) * 100_000)  # now, in 10 us units, as a signer does
    return m


# --------------------------------------------------------------------------- strategies


@st.composite
def telemetry(draw):
    """A message the link reads, with any field values its wire types allow."""
    kind = draw(st.sampled_from(["att", "pos", "gimbal", "timesync", "ack", "heartbeat"]))
    if kind == "att":
        return mav.MAVLink_attitude_quaternion_message(
            draw(U32), *[draw(F32) for _ in range(7)], [draw(F32) for _ in range(4)]
        )
    if kind == "pos":
        return mav.MAVLink_global_position_int_message(
            draw(U32),
            draw(I32),
            draw(I32),
            draw(I32),
            draw(I32),
            *[draw(st.integers(-(2**15), 2**15 - 1)) for _ in range(3)],
            draw(st.integers(0, 2**16 - 1)),
        )
    if kind == "gimbal":
        return mav.MAVLink_gimbal_device_attitude_status_message(
            0,
            0,
            draw(U32),
            draw(st.integers(0, 2**16 - 1)),
            [draw(F32) for _ in range(4)],
            draw(F32),
            draw(F32),
            draw(F32),
            draw(U32),
            draw(F32),
            draw(F32),
            draw(st.integers(0, 255)),
        )
    if kind == "timesync":
        return mav.MAVLink_timesync_message(
            draw(st.integers(-(2**63), 2**63 - 1)), draw(st.integers(-(2**63), 2**63 - 1))
        )
    if kind == "ack":
        return mav.MAVLink_command_ack_message(
            draw(st.integers(0, 2**16 - 1)),
            draw(st.integers(0, 255)),
            draw(st.integers(0, 255)),
            draw(I32),
            draw(st.integers(0, 255)),
            draw(st.integers(0, 255)),
        )
    return mav.MAVLink_heartbeat_message(
        draw(st.integers(0, 255)),
        draw(st.integers(0, 255)),
        draw(st.integers(0, 255)),
        draw(U32),
        draw(st.integers(0, 255)),
        3,
    )


@st.composite
def packet(draw, signed: st.SearchStrategy[bool] = st.just(False), key: bytes = KEY):  # noqa: B008 (a strategy default, built once)
    """A valid MAVLink 2 packet, unsigned or signed with ``key``, from the autopilot's or another id."""
    msg = draw(telemetry())
    sysid = draw(st.sampled_from([AP_SYSID, AP_SYSID, 42, 255]))
    compid = draw(st.sampled_from([1, 1, 154, 191]))
    return bytes(msg.pack(packer(sysid, compid, signed=draw(signed), key=key)))


@st.composite
def mutated(draw, key: bytes = KEY):
    """A valid packet, then truncated, extended, with bytes flipped, or spliced into another (the result
    may still hold the valid packet whole, e.g. with bytes appended)."""
    data = bytearray(draw(packet(st.booleans(), key)))
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["truncate", "flip", "insert", "append", "splice", "v1"]))
        if op == "truncate" and data:
            del data[draw(st.integers(0, len(data) - 1)) :]
        elif op == "flip" and data:
            i = draw(st.integers(0, len(data) - 1))
            data[i] ^= draw(st.integers(1, 255))
        elif op == "insert":
            i = draw(st.integers(0, len(data)))
            data[i:i] = draw(st.binary(min_size=1, max_size=8))
        elif op == "append":
            data += draw(st.binary(max_size=64))
        elif op == "splice":
            other = draw(packet(key=key))
            i = draw(st.integers(0, len(data)))
            data[i:] = other[draw(st.integers(0, len(other) - 1)) :]
        elif op == "v1" and data:
            data[0] = 0xFE  # a v2 packet claiming to be v1
    return bytes(data)


oversized = st.integers(4481, 6000).map(lambda n: b"\xfd" * n)  # over the parse limit: dropped unparsed
garbage = st.one_of(st.binary(max_size=400), mutated(), oversized)
garbage_without_start_byte = st.binary(max_size=200).map(lambda b: bytes(x for x in b if x not in START_BYTES))


def _accounted(n_msgs: int, added: dict[str, int], pose_calls: int, h: Harness) -> None:
    assert CATCH_ALL not in added, added
    if n_msgs == 0:
        assert sum(added.values()) >= 1, "a datagram yielded nothing and nothing was counted"
    for kind, _t, ok in h.pose.calls[len(h.pose.calls) - pose_calls :]:
        if not ok:
            assert added, f"the pose buffer refused a {kind} sample without counting it"


# --------------------------------------------------------------------------- targets


@fuzz_settings(ci_default=300)
@given(datagrams=st.lists(st.one_of(garbage, packet(st.booleans())), min_size=1, max_size=12), signed=st.booleans())
def test_any_datagrams_never_raise_and_every_one_is_accounted_for(datagrams, signed):
    h = Harness(signed=signed)
    try:
        for i, d in enumerate(datagrams):
            h.clock.t_s += 0.01
            if not d:
                continue  # an empty datagram carries nothing (the link skips it)
            n, added, calls = h.feed(d, ("127.0.0.1", 40000 + i % 3))
            _accounted(n, added, calls, h)
    finally:
        h.close()


@fuzz_settings(ci_default=300)
@given(msgs=st.lists(telemetry(), min_size=1, max_size=10), gimballed=st.booleans())
def test_valid_packets_with_any_field_values_are_used_or_refused_with_a_count(msgs, gimballed):
    """NaN/inf quaternions, out-of-range positions, random stamps, rates and acks from the autopilot."""
    h = Harness(gimballed=gimballed)
    try:
        p = packer()
        for m in msgs:
            h.clock.t_s += 0.02
            n, added, calls = h.feed(bytes(m.pack(p)))
            assert n == 1 and CATCH_ALL not in added and "mavlink_recv_error" not in added, added
            _accounted(n, added, calls, h)
    finally:
        h.close()


@fuzz_settings(ci_default=300)
@given(
    before=st.lists(garbage, max_size=6),
    after=st.lists(garbage, max_size=6),
    prefix=garbage_without_start_byte,
    suffix=st.binary(max_size=200),
    signed=st.booleans(),
    same_sender=st.booleans(),
)
def test_a_valid_packet_is_decoded_whatever_garbage_surrounds_it(before, after, prefix, suffix, signed, same_sender):
    h = Harness(signed=signed)
    try:
        t_ms = 5000
        p = packer(signed=signed)
        sender = ("127.0.0.1", 40000)
        garbage_sender = sender if same_sender else ("127.0.0.1", 40001)

        def genuine(framing=lambda b: b) -> None:
            nonlocal t_ms
            t_ms += 20
            pkt = bytes(
                mav.MAVLink_attitude_quaternion_message(t_ms, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, [0.0] * 4).pack(p)
            )
            n, added, _ = h.feed(framing(pkt), sender)
            assert ("attitude", t_ms * 1000, True) in h.pose.calls, (added, h.pose.calls[-3:])

        # the autopilot heartbeats, as any does: the garbage may hold a valid heartbeat of its identity from another
        # address, a second sender then (refused), not the autopilot the link follows
        quadrotor = mav.MAVLink_heartbeat_message(2, mav.MAV_AUTOPILOT_PX4, 0, 0, mav.MAV_STATE_ACTIVE, 3)
        h.feed(bytes(quadrotor.pack(p)), sender)
        genuine()
        for g in before:
            h.feed(g, garbage_sender)
        genuine()  # alone in its datagram, after any garbage datagrams
        genuine(lambda pkt: prefix + pkt + suffix)  # inside a datagram, garbage (no start byte) before, anything after
        for g in after:
            h.feed(g, garbage_sender)
        genuine()
        assert CATCH_ALL not in h.counter.counts
    finally:
        h.close()


@fuzz_settings(ci_default=200)
@given(datagrams=st.lists(st.one_of(packet(st.booleans(), FOREIGN_KEY), mutated(FOREIGN_KEY)), min_size=1, max_size=8))
def test_a_signed_link_uses_no_unsigned_or_foreign_key_packet(datagrams):
    """With signing on, nothing unsigned or signed with another key reaches the pose buffer."""
    h = Harness(signed=True)
    try:
        for d in datagrams:
            h.clock.t_s += 0.01
            if not d:
                continue
            before = len(h.pose.calls)
            n, added, calls = h.feed(d)
            assert len(h.pose.calls) == before, (d.hex(), h.pose.calls[before:])
            _accounted(n, added, calls, h)
    finally:
        h.close()
