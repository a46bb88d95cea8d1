"""The telemetry fast path (:mod:`onboard.io.mavlink_fast`) against pymavlink's parser on the same bytes: the
same message with the same values, or None (and pymavlink decides) -- never a different message."""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink2

from onboard.io.mavlink_fast import decode_telemetry

F32 = st.floats(width=32, allow_nan=True, allow_infinity=True)
I32 = st.integers(-(2**31), 2**31 - 1)
I16 = st.integers(-(2**15), 2**15 - 1)
U32 = st.integers(0, 2**32 - 1)
U16 = st.integers(0, 2**16 - 1)
U8 = st.integers(0, 255)

ATTITUDE = st.builds(
    mavlink2.MAVLink_attitude_quaternion_message,
    U32,
    F32,
    F32,
    F32,
    F32,
    F32,
    F32,
    F32,
    st.lists(F32, min_size=4, max_size=4),
)
POSITION = st.builds(mavlink2.MAVLink_global_position_int_message, U32, I32, I32, I32, I32, I16, I16, I16, U16)


def _packed(msg, sysid: int, compid: int, seq: int, v1: bool = False) -> bytes:
    mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    mav.seq = seq
    return bytes(msg.pack(mav, force_mavlink1=v1))


def _pymavlink(data: bytes):
    """pymavlink's reading of one datagram: the messages it yields (BAD_DATA included)."""
    mav = mavlink2.MAVLink(None)
    mav.robust_parsing = True
    out, m = [], mav.parse_char(data)
    while m is not None:
        out.append(m)
        m = mav.parse_char(b"")
    return out


def _same_value(a, b) -> bool:
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(map(_same_value, a, b))
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return type(a) is type(b) and a == b


def _assert_same(fast, msg) -> None:
    assert fast.get_type() == msg.get_type()
    assert (fast.get_srcSystem(), fast.get_srcComponent()) == (msg.get_srcSystem(), msg.get_srcComponent())
    for name in msg.fieldnames:
        assert _same_value(getattr(fast, name), getattr(msg, name)), name


@settings(max_examples=150, deadline=None)
@given(msg=st.one_of(ATTITUDE, POSITION), sysid=U8, compid=U8, seq=U8)
def test_a_telemetry_datagram_reads_as_pymavlink_reads_it(msg, sysid, compid, seq):
    data = _packed(msg, sysid, compid, seq)
    (want,) = _pymavlink(data)
    got = decode_telemetry(data)
    assert got is not None
    _assert_same(got, want)


@settings(max_examples=150, deadline=None)
@given(
    msg=st.one_of(ATTITUDE, POSITION),
    where=st.integers(0, 60),
    xor=st.integers(1, 255),
    cut=st.integers(0, 3),
    extra=st.binary(max_size=3),
)
def test_damaged_bytes_are_left_to_pymavlink_or_read_as_it_reads_them(msg, where, xor, cut, extra):
    data = bytearray(_packed(msg, 1, 1, 0))
    data[where % len(data)] ^= xor
    damaged = bytes(data[: len(data) - cut]) + extra
    got = decode_telemetry(damaged)
    if got is not None:  # only a packet pymavlink also reads as this one message
        (want,) = _pymavlink(damaged)
        _assert_same(got, want)


def test_what_is_not_one_unsigned_v2_telemetry_packet_goes_to_pymavlink():
    att = mavlink2.MAVLink_attitude_quaternion_message(1000, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, [0.0] * 4)
    hb = mavlink2.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3)
    one = _packed(att, 1, 1, 0)
    assert decode_telemetry(one) is not None
    assert decode_telemetry(one + one) is None  # two packets in one datagram
    assert decode_telemetry(_packed(hb, 1, 1, 0)) is None  # another message
    assert decode_telemetry(_packed(att, 1, 1, 0, v1=True)) is None  # MAVLink 1
    signed = bytearray(one)
    signed[2] |= mavlink2.MAVLINK_IFLAG_SIGNED
    assert decode_telemetry(bytes(signed)) is None
    assert decode_telemetry(b"") is None and decode_telemetry(one[:11]) is None
