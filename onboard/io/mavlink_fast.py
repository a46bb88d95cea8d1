"""A fast path for the telemetry the daemon receives most: one unsigned MAVLink 2 ``ATTITUDE_QUATERNION`` (100 Hz)
or ``GLOBAL_POSITION_INT`` (25 Hz) alone in a UDP datagram.

pymavlink's parser costs ~22 us a datagram on the development machine (a parser object per datagram, its
byte-by-byte state machine, a header object and the message object); this decodes the same packet with one
``struct`` unpack after the same checks (the length the header states, pymavlink's CRC with the message's
CRC extra), about 5 us, and hands back an object with the interface :meth:`MavlinkLink._handle
<onboard.io.mavlink_link.MavlinkLink>` reads (``get_type``, ``get_srcSystem``, ``get_srcComponent``, the
fields by name, arrays as lists), holding the values pymavlink would give.  Anything else -- MAVLink 1, a
signed packet, several packets or garbage in one datagram, another message, a bad CRC -- returns None and
goes through pymavlink, which counts what it refuses; with signing configured the caller does not use this
at all (the signature must be checked).
"""

from __future__ import annotations

import struct

from pymavlink.dialects.v20 import common as mavlink2

__all__ = ["FAST_MESSAGE_IDS", "TelemetryMessage", "decode_telemetry"]

_MAGIC_V2 = 0xFD
_HEADER_BYTES = 10
_CRC_BYTES = 2
_CRC = struct.Struct("<H")

#: the message ids decoded here
FAST_MESSAGE_IDS = (mavlink2.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT)


def _layout(msgtype) -> tuple[str, tuple[str, ...], tuple[tuple[int, int], ...]]:
    """(name, field names, (first, count) per field in the unpacked wire tuple): pymavlink's field order
    (``orders``, ``lengths``) worked out once; ``count`` > 1 is an array (a list, as pymavlink gives it)."""
    lengths = msgtype.lengths
    spans = []
    for order in msgtype.orders:
        spans.append((sum(lengths[:order]), lengths[order]))
    return msgtype.msgname, tuple(msgtype.fieldnames), tuple(spans)


_TYPES = {mid: (mavlink2.mavlink_map[mid], _layout(mavlink2.mavlink_map[mid])) for mid in FAST_MESSAGE_IDS}


class TelemetryMessage:
    """One decoded message: its fields as attributes (pymavlink's names and values)."""

    def __init__(self, name: str, src_system: int, src_component: int, fields: dict) -> None:
        self.__dict__.update(fields)
        self._name = name
        self._src = (src_system, src_component)

    def get_type(self) -> str:
        return self._name

    def get_srcSystem(self) -> int:  # noqa: N802 - pymavlink's name, read by the link's handler
        return self._src[0]

    def get_srcComponent(self) -> int:  # noqa: N802 - pymavlink's name
        return self._src[1]


def decode_telemetry(data: bytes) -> TelemetryMessage | None:
    """``data`` (one UDP datagram) as a :class:`TelemetryMessage` when it is exactly one unsigned MAVLink 2
    packet of a :data:`FAST_MESSAGE_IDS` message with a good CRC; None otherwise (parse it with pymavlink)."""
    n = len(data)
    if n < _HEADER_BYTES + _CRC_BYTES or data[0] != _MAGIC_V2 or data[2] != 0:  # incompat flags: 1 = signed
        return None
    plen = data[1]
    if n != _HEADER_BYTES + plen + _CRC_BYTES:
        return None
    known = _TYPES.get(data[7] | (data[8] << 8) | (data[9] << 16))
    if known is None:
        return None
    msgtype, (name, fieldnames, spans) = known
    end = _HEADER_BYTES + plen
    crc = mavlink2.x25crc(data[1:end])
    crc.accumulate(bytes((msgtype.crc_extra,)))
    if _CRC.unpack_from(data, end)[0] != crc.crc:
        return None
    size = msgtype.unpacker.size
    payload = data[_HEADER_BYTES:end]
    if plen < size:
        payload += bytes(size - plen)  # MAVLink 2 drops a payload's trailing zeros
    t = msgtype.unpacker.unpack(payload[:size])
    fields = {
        fname: (t[first] if count == 1 else list(t[first : first + count]))
        for fname, (first, count) in zip(fieldnames, spans, strict=True)
    }
    return TelemetryMessage(name, data[5], data[6], fields)
