"""RTP H.264 packetisation (RFC 6184, RFC 3550): Annex B splitting, single NAL units and FU-A fragments
under the packet size, one timestamp per access unit, the marker on its last packet, consecutive
sequence numbers across the 16-bit wrap, SPS/PPS before every IDR, and the round trip through the
depacketiser; hypothesis for the parsers, fixed bytes for the header layout."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.core.errors import InputError
from onboard.io.rtp_h264 import (
    RTP_HEADER_BYTES,
    RtpH264Packetizer,
    depacketize,
    parse_rtp,
    rtp_timestamp,
    sdp,
    split_annexb,
)

SPS = bytes([0x67, 0x42, 0xC0, 0x1E, 0xDA, 0x02, 0x80])
PPS = bytes([0x68, 0xCE, 0x3C, 0x80])
MAX_PACKET = 64  # small, so short test NAL units fragment


def _nal(nal_type: int, body: bytes, nri: int = 3) -> bytes:
    return bytes([(nri << 5) | nal_type]) + body


def _escape(rbsp: bytes) -> bytes:
    """H.264 section 7.4.1 emulation prevention: 0x03 after two zero bytes that a byte <= 3 follows."""
    out, zeros = bytearray(), 0
    for x in rbsp:
        if zeros >= 2 and x <= 3:
            out.append(3)
            zeros = 0
        out.append(x)
        zeros = zeros + 1 if x == 0 else 0
    return bytes(out)


# a NAL unit as an encoder writes it: no start-code emulation inside (no 00 00 0x with x <= 3), last byte
# non-zero (the RBSP stop bit); types 1..23 (what an encoder emits; 24..31 are RTP aggregation types)
_body = st.binary(min_size=0, max_size=300).map(lambda b: _escape(b) + b"\x80")
nal_units = st.builds(_nal, st.sampled_from([1, 5, 6, 7, 8]), _body, st.integers(0, 3))
non_idr_units = st.builds(_nal, st.sampled_from([1, 6, 7, 8]), _body, st.integers(0, 3))  # IDR insertion: below


@given(st.lists(nal_units, min_size=1, max_size=8), st.lists(st.booleans(), min_size=8, max_size=8), st.integers(0, 3))
def test_split_annexb_recovers_the_nal_units_whatever_the_start_codes(nals, long_codes, trailing_zeros):
    stream = b"".join(
        (b"\x00\x00\x00\x01" if long_codes[i] else b"\x00\x00\x01") + n + b"\x00" * trailing_zeros
        for i, n in enumerate(nals)
    )
    assert split_annexb(stream) == nals


@settings(max_examples=200)
@given(
    st.lists(non_idr_units, min_size=1, max_size=8),
    st.integers(0, 2**32 - 1),
    st.integers(0, 2**16 - 1),
    st.integers(RTP_HEADER_BYTES + 3, 200),
)
def test_packets_fit_carry_one_timestamp_mark_the_last_and_round_trip(nals, ts, seq0, max_packet):
    p = RtpH264Packetizer(ssrc=0xDEADBEEF, max_packet_bytes=max_packet, first_sequence=seq0)
    packets = p.packetize(b"".join(b"\x00\x00\x00\x01" + n for n in nals), ts)
    parsed = [parse_rtp(d) for d in packets]
    assert all(len(d) <= max_packet for d in packets)
    assert [q.sequence for q in parsed] == [(seq0 + i) % 65536 for i in range(len(packets))]
    assert {q.timestamp for q in parsed} == {ts} and {q.ssrc for q in parsed} == {0xDEADBEEF}
    assert [q.marker for q in parsed] == [False] * (len(packets) - 1) + [True]
    assert {q.payload_type for q in parsed} == {96}
    assert depacketize([q.payload for q in parsed]) == nals
    assert p.sequence == (seq0 + len(packets)) % 65536


def test_fu_a_fragments_carry_the_nal_header_in_indicator_and_fu_header():
    nal = _nal(5, bytes(range(1, 200)), nri=3)
    p = RtpH264Packetizer(ssrc=1, max_packet_bytes=MAX_PACKET)
    p.sps, p.pps = SPS, PPS  # an IDR with its parameter sets already seen
    packets = [parse_rtp(d).payload for d in p.packetize_nals([SPS, PPS, nal], 0)]
    assert packets[0] == SPS and packets[1] == PPS  # single NAL unit packets, as they are
    frags = packets[2:]
    step = MAX_PACKET - RTP_HEADER_BYTES - 2
    assert len(frags) == -(-(len(nal) - 1) // step)
    assert all(f[0] == (0x60 | 28) for f in frags)  # F = 0, NRI = 3, type 28 (FU-A)
    assert frags[0][1] == 0x80 | 5 and frags[-1][1] == 0x40 | 5  # S / E bits, original type 5
    assert all(f[1] == 5 for f in frags[1:-1])
    assert b"".join(f[2:] for f in frags) == nal[1:]  # the header byte is not repeated


def test_header_layout_is_rfc3550():
    p = RtpH264Packetizer(ssrc=0x01020304, payload_type=97, first_sequence=0xFFFF)
    a, b = p.packetize_nals([_nal(1, b"\x11"), _nal(1, b"\x22")], 0xA0B0C0D0)
    assert a[:12] == bytes([0x80, 97, 0xFF, 0xFF, 0xA0, 0xB0, 0xC0, 0xD0, 1, 2, 3, 4])
    assert b[:4] == bytes([0x80, 0x80 | 97, 0x00, 0x00])  # marker; the sequence number wrapped


def test_sps_pps_are_sent_before_every_idr_even_when_the_encoder_did_not_repeat_them():
    p = RtpH264Packetizer(ssrc=1)
    first = [parse_rtp(d).payload for d in p.packetize_nals([SPS, PPS, _nal(6, b"\x05\x80"), _nal(5, b"\x88\x80")], 0)]
    assert first == [SPS, PPS, _nal(6, b"\x05\x80"), _nal(5, b"\x88\x80")] and p.headers_inserted == 0
    p_frame = [parse_rtp(d).payload for d in p.packetize_nals([_nal(1, b"\x9a\x80")], 3000)]
    assert p_frame == [_nal(1, b"\x9a\x80")]  # nothing added to a P-frame
    idr = [parse_rtp(d).payload for d in p.packetize_nals([_nal(6, b"\x05\x80"), _nal(5, b"\x88\x80")], 6000)]
    assert idr == [_nal(6, b"\x05\x80"), SPS, PPS, _nal(5, b"\x88\x80")] and p.headers_inserted == 1
    aud = [parse_rtp(d).payload for d in p.packetize_nals([_nal(9, b"\xf0", nri=0), _nal(1, b"\x9a\x80")], 9000)]
    assert aud == [_nal(1, b"\x9a\x80")]  # access unit delimiters are dropped


@given(st.integers(0, 2**40), st.integers(0, 2**32 - 1))
def test_timestamp_is_the_capture_time_on_the_90khz_clock(t_us, offset):
    assert rtp_timestamp(t_us, offset) == (t_us * 9 // 100 + offset) % 2**32
    # one frame at 30 Hz later: 3000 ticks (integer maths, no drift over hours)
    assert (rtp_timestamp(t_us + 1_000_000, offset) - rtp_timestamp(t_us, offset)) % 2**32 == 90_000


def _read_or_refused(read, data, named: str):
    """read(data), or None when it raised an InputError; the error must name ``named``."""
    try:
        return read(data)
    except InputError as exc:
        assert named in str(exc)
        return None


@given(st.binary(max_size=40))
def test_parse_rtp_accepts_or_names_what_is_wrong(data):
    q = _read_or_refused(parse_rtp, data, "RTP packet")
    if q is not None:
        assert len(data) >= RTP_HEADER_BYTES and data[0] >> 6 == 2 and len(q.payload) <= len(data) - RTP_HEADER_BYTES


@given(st.lists(st.binary(max_size=30), max_size=6))
def test_depacketize_accepts_or_names_what_is_wrong(payloads):
    nals = _read_or_refused(depacketize, payloads, "RTP H.264")
    if nals is not None:
        assert all(nals)


def test_depacketize_reads_stap_a_and_refuses_broken_fragments():
    stap = bytes([24]) + struct.pack("!H", len(SPS)) + SPS + struct.pack("!H", len(PPS)) + PPS
    assert depacketize([stap]) == [SPS, PPS]
    with pytest.raises(InputError, match="without its start"):
        depacketize([bytes([0x7C, 0x05, 1, 2])])
    with pytest.raises(InputError, match="ended inside"):
        depacketize([bytes([0x7C, 0x85, 1, 2])])


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"ssrc": -1}, "ssrc"),
        ({"ssrc": 1, "payload_type": 33}, "payload_type"),
        ({"ssrc": 1, "max_packet_bytes": 14}, "max_packet_bytes"),
    ],
)
def test_packetizer_refuses_bad_settings_by_name(kwargs, field):
    with pytest.raises(InputError, match=field):
        RtpH264Packetizer(**kwargs)


def test_sdp_names_the_port_payload_type_and_clock():
    text = sdp("127.0.0.1", 5600)
    assert "m=video 5600 RTP/AVP 96\r\n" in text and "a=rtpmap:96 H264/90000\r\n" in text
    assert "c=IN IP4 127.0.0.1\r\n" in text and "packetization-mode=1" in text
