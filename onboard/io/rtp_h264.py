"""H.264 over RTP (RFC 6184, RTP per RFC 3550), pure: access units in -> datagram payloads out.

No sockets, no clocks, no encoder: :class:`RtpH264Packetizer` turns one H.264 access unit (Annex B
byte stream, as libx264 writes it) into RTP packets, and :func:`depacketize` reverses it (for the
tests and for a receiver that assembles access units on the marker bit, as GStreamer's
``rtph264depay`` does in QGroundControl).

Packetisation (RFC 6184 non-interleaved mode, ``packetization-mode=1``):

* every NAL unit no longer than ``max_payload_bytes`` goes as a **single NAL unit packet** (section
  5.6: the payload is the NAL unit, its one-byte header first);
* a longer one as **FU-A fragments** (section 5.8): FU indicator ``F | NRI | 28``, FU header
  ``S | E | 0 | type``, then consecutive slices of the NAL unit's payload (its header byte is carried
  by the indicator and FU header, not repeated); S on the first fragment, E on the last;
* every packet of an access unit carries the same **90 kHz timestamp** (section 5.1), the caller's;
  the **marker bit** is set on the last packet of the access unit (section 5.1), so a receiver can
  decode the picture without waiting for the next one;
* the sequence number increases by one per packet, modulo 2^16; SSRC and payload type are fixed per
  stream (payload type dynamic, 96 by default: ``a=rtpmap:96 H264/90000`` in :func:`sdp`);
* **SPS and PPS in band before every IDR** (so a ground station joins at any IDR): an access unit with
  an IDR slice (type 5) that does not carry them is sent with the last SPS / PPS seen inserted in front
  of its first slice.  Access unit delimiters (type 9) are dropped (RFC 6184 section 5.6 allows any
  NAL unit; they carry nothing a receiver needs and cost a packet each).

RTP header (RFC 3550 section 5.1, 12 bytes, no CSRC, no extension)::

    byte 0: V=2 | P=0 | X=0 | CC=0            = 0x80
    byte 1: M | PT (7 bits)
    bytes 2-3: sequence number, big-endian     bytes 4-7: timestamp     bytes 8-11: SSRC

:func:`rtp_timestamp` maps a capture time in microseconds onto the 90 kHz clock (with the stream's
random offset, RFC 3550 section 5.1), so the receiver sees the frames' true capture spacing.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from onboard.core.errors import InputError

__all__ = [
    "RTP_HEADER_BYTES",
    "RTP_CLOCK_HZ",
    "DEFAULT_PAYLOAD_TYPE",
    "DEFAULT_MAX_PACKET_BYTES",
    "RtpPacket",
    "RtpH264Packetizer",
    "split_annexb",
    "parse_rtp",
    "depacketize",
    "rtp_timestamp",
    "sdp",
]

RTP_HEADER_BYTES = 12
RTP_VERSION = 2
RTP_CLOCK_HZ = 90_000  # RFC 6184 section 8.2.1: H.264 uses a 90 kHz RTP clock
DEFAULT_PAYLOAD_TYPE = 96  # first dynamic payload type (RFC 3551)
DEFAULT_MAX_PACKET_BYTES = 1400  # RTP header + payload: fits a 1500-byte Ethernet MTU with IP/UDP (and tunnel) headers
NAL_SLICE, NAL_IDR, NAL_SEI, NAL_SPS, NAL_PPS, NAL_AUD = 1, 5, 6, 7, 8, 9
NAL_STAP_A, NAL_FU_A = 24, 28
FU_START, FU_END = 0x80, 0x40
_HEADER = struct.Struct("!BBHII")


def split_annexb(data: bytes) -> list[bytes]:
    """The NAL units of an Annex B byte stream (start codes ``00 00 01`` / ``00 00 00 01`` removed).

    Zero bytes after a NAL unit (``trailing_zero_8bits``, the 4-byte start code's leading zero) are not
    part of it (H.264 Annex B.1; a NAL unit ends with its RBSP stop bit); empty units are skipped.
    """
    data = bytes(data)
    out: list[bytes] = []
    i = data.find(b"\x00\x00\x01")
    while i >= 0:
        start = i + 3
        j = data.find(b"\x00\x00\x01", start)
        end = len(data) if j < 0 else j
        nal = data[start:end].rstrip(b"\x00")
        if nal:
            out.append(nal)
        i = j
    return out


@dataclass(frozen=True)
class RtpPacket:
    """One parsed RTP packet: header fields and ``payload`` (bytes after the 12-byte header)."""

    marker: bool
    payload_type: int
    sequence: int
    timestamp: int
    ssrc: int
    payload: bytes


def parse_rtp(datagram: bytes) -> RtpPacket:
    """The RTP packet in ``datagram``; InputError naming the field that is wrong (version, length)."""
    if len(datagram) < RTP_HEADER_BYTES:
        raise InputError(f"RTP packet: {len(datagram)} bytes, shorter than the {RTP_HEADER_BYTES}-byte header")
    b0, b1, seq, ts, ssrc = _HEADER.unpack_from(datagram)
    if b0 >> 6 != RTP_VERSION:
        raise InputError(f"RTP packet: version {b0 >> 6}, expected {RTP_VERSION}")
    cc = b0 & 0x0F
    offset = RTP_HEADER_BYTES + 4 * cc
    if b0 & 0x10:  # header extension: 16-bit profile, 16-bit length in 32-bit words
        if len(datagram) < offset + 4:
            raise InputError("RTP packet: header extension truncated")
        offset += 4 + 4 * struct.unpack_from("!H", datagram, offset + 2)[0]
    end = len(datagram)
    if b0 & 0x20:  # padding: the last byte counts the padding bytes
        end -= datagram[-1]
    if offset > end:
        raise InputError(f"RTP packet: header of {offset} bytes and padding exceed its {len(datagram)} bytes")
    return RtpPacket(bool(b1 & 0x80), b1 & 0x7F, seq, ts, ssrc, bytes(datagram[offset:end]))


def rtp_timestamp(capture_time_us: int, offset: int = 0) -> int:
    """``capture_time_us`` on the 90 kHz RTP clock plus ``offset``, modulo 2^32 (integer maths, no drift)."""
    return (int(capture_time_us) * RTP_CLOCK_HZ // 1_000_000 + int(offset)) % (1 << 32)


class RtpH264Packetizer:
    """Access units -> RTP packets of one stream (module docstring).  Keeps the sequence number and the
    last SPS / PPS; ``ssrc`` and ``first_sequence`` should be random (RFC 3550 section 5.1)."""

    def __init__(
        self,
        ssrc: int,
        payload_type: int = DEFAULT_PAYLOAD_TYPE,
        max_packet_bytes: int = DEFAULT_MAX_PACKET_BYTES,
        first_sequence: int = 0,
    ) -> None:
        if not 0 <= int(ssrc) < 1 << 32:
            raise InputError(f"RTP ssrc must be a 32-bit unsigned integer, got {ssrc!r}")
        if not 96 <= int(payload_type) <= 127:
            raise InputError(f"RTP payload_type must be dynamic (96..127), got {payload_type!r}")
        if not RTP_HEADER_BYTES + 3 <= int(max_packet_bytes) <= 65_507:
            raise InputError(f"RTP max_packet_bytes must be in {RTP_HEADER_BYTES + 3}..65507, got {max_packet_bytes!r}")
        self.ssrc = int(ssrc)
        self.payload_type = int(payload_type)
        self.max_packet_bytes = int(max_packet_bytes)
        self.max_payload_bytes = self.max_packet_bytes - RTP_HEADER_BYTES
        self.sequence = int(first_sequence) % (1 << 16)  # of the next packet
        self.sps: bytes | None = None
        self.pps: bytes | None = None
        self.headers_inserted = 0  # IDR access units that arrived without SPS/PPS and got the cached ones

    def packetize(self, access_unit: bytes, timestamp: int) -> list[bytes]:
        """The RTP packets (whole datagrams) of one access unit (Annex B) at RTP ``timestamp``."""
        if not 0 <= int(timestamp) < 1 << 32:
            raise InputError(f"RTP timestamp must be a 32-bit unsigned integer, got {timestamp!r}")
        return self.packetize_nals(split_annexb(access_unit), int(timestamp))

    def packetize_nals(self, nals: list[bytes], timestamp: int) -> list[bytes]:
        """As :meth:`packetize`, from the NAL units (no start codes) of one access unit."""
        nals = [bytes(n) for n in nals if n and n[0] & 0x1F != NAL_AUD]
        types = [n[0] & 0x1F for n in nals]
        for n, t in zip(nals, types):
            if t == NAL_SPS:
                self.sps = n
            elif t == NAL_PPS:
                self.pps = n
        if NAL_IDR in types and not (NAL_SPS in types and NAL_PPS in types) and self.sps and self.pps:
            first_vcl = next(i for i, t in enumerate(types) if t in (NAL_SLICE, NAL_IDR))
            extra = [h for h, t in ((self.sps, NAL_SPS), (self.pps, NAL_PPS)) if t not in types]
            nals = nals[:first_vcl] + extra + nals[first_vcl:]
            self.headers_inserted += 1
        payloads: list[bytes] = []
        for nal in nals:
            if len(nal) <= self.max_payload_bytes:
                payloads.append(nal)
            else:
                payloads.extend(self._fu_a(nal))
        return [self._packet(p, marker=(i == len(payloads) - 1), timestamp=timestamp) for i, p in enumerate(payloads)]

    def _fu_a(self, nal: bytes) -> list[bytes]:
        indicator = (nal[0] & 0xE0) | NAL_FU_A
        nal_type = nal[0] & 0x1F
        body = nal[1:]
        step = self.max_payload_bytes - 2
        chunks = [body[i : i + step] for i in range(0, len(body), step)]
        out = []
        for i, chunk in enumerate(chunks):
            fu_header = nal_type | (FU_START if i == 0 else 0) | (FU_END if i == len(chunks) - 1 else 0)
            out.append(bytes((indicator, fu_header)) + chunk)
        return out

    def _packet(self, payload: bytes, marker: bool, timestamp: int) -> bytes:
        header = _HEADER.pack(
            RTP_VERSION << 6, (0x80 if marker else 0) | self.payload_type, self.sequence, timestamp, self.ssrc
        )
        self.sequence = (self.sequence + 1) % (1 << 16)
        return header + payload


def depacketize(payloads: list[bytes]) -> list[bytes]:
    """The NAL units carried by RTP payloads (single NAL unit, STAP-A, FU-A) of one access unit, in order.

    InputError on a payload we cannot read: an FU-A that does not start with S, continues without a
    start, or ends without E; an empty payload; a type we do not handle (STAP-B, MTAP, FU-B).
    """
    nals: list[bytes] = []
    frag: bytearray | None = None
    for p in payloads:
        if not p:
            raise InputError("RTP H.264 payload is empty")
        t = p[0] & 0x1F
        if t == NAL_FU_A:
            if len(p) < 2:
                raise InputError("RTP H.264 FU-A payload shorter than its two header bytes")
            fu = p[1]
            if fu & FU_START:
                if frag is not None:
                    raise InputError("RTP H.264 FU-A: a new start before the previous fragment ended")
                frag = bytearray([(p[0] & 0xE0) | (fu & 0x1F)])
            elif frag is None:
                raise InputError("RTP H.264 FU-A: a fragment without its start")
            frag += p[2:]
            if fu & FU_END:
                nals.append(bytes(frag))
                frag = None
            continue
        if frag is not None:
            raise InputError("RTP H.264 FU-A: fragment not ended before the next NAL unit")
        if 1 <= t <= 23:
            nals.append(bytes(p))
        elif t == NAL_STAP_A:
            i = 1
            while i + 2 <= len(p):
                (size,) = struct.unpack_from("!H", p, i)
                if size == 0 or i + 2 + size > len(p):
                    raise InputError(f"RTP H.264 STAP-A: unit of {size} bytes past the payload's end")
                nals.append(bytes(p[i + 2 : i + 2 + size]))
                i += 2 + size
        else:
            raise InputError(f"RTP H.264 payload type {t} not supported (single NAL, STAP-A, FU-A only)")
    if frag is not None:
        raise InputError("RTP H.264 FU-A: access unit ended inside a fragmented NAL unit")
    return nals


def sdp(host: str, port: int, payload_type: int = DEFAULT_PAYLOAD_TYPE, name: str = "irtrack IR") -> str:
    """A session description (RFC 4566, RFC 6184 section 8.2) for the stream a receiver at ``host:port``
    gets: what FFmpeg (``ffplay stream.sdp``), VLC or GStreamer's ``sdpdemux`` open.  No
    ``sprop-parameter-sets``: SPS / PPS come in band before every IDR."""
    family = "IP6" if ":" in host else "IP4"
    return (
        f"v=0\r\no=- 0 0 IN {family} {host}\r\ns={name}\r\nc=IN {family} {host}\r\nt=0 0\r\n"
        f"m=video {int(port)} RTP/AVP {int(payload_type)}\r\n"
        f"a=rtpmap:{int(payload_type)} H264/{RTP_CLOCK_HZ}\r\n"
        f"a=fmtp:{int(payload_type)} packetization-mode=1\r\n"
    )
