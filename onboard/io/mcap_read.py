"""MCAP recordings read message by message (adapter; replay's and the flight report's): :func:`read_recording`
walks a file with the `mcap` package's stream reader, a file cut short (a killed daemon) up to its last whole
record, and gives each message with where its data lies in the file, so that a frame (:class:`FrameRef`) is read
again from there when used instead of held in memory.  The record layout is :mod:`onboard.io.mcap_chunks`'.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass

from mcap.opcode import Opcode

from onboard.core.errors import InputError
from onboard.io.mcap_chunks import CHUNK_FIXED, MCAP_MAGIC, MESSAGE_FIXED, RECORD_HEAD

__all__ = ["RecordedMessage", "FrameRef", "read_recording"]


@dataclass(frozen=True)
class RecordedMessage:
    """One message; ``data_offset``: where its data lies in the file (a message of an uncompressed chunk, which
    can be read again from there), else None."""

    topic: str
    schema: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    data: bytes
    data_offset: int | None = None


@dataclass(frozen=True)
class FrameRef:
    """A recorded ``foxglove.RawImage``, read from its file when asked (:meth:`raw_image`): a recording's frames
    (~10 MB a second of flight) are not held in memory.  ``data`` holds the message itself where it cannot be
    read again by offset (a compressed chunk, or a record whose layout did not check against the file's bytes)."""

    path: str
    offset: int | None
    size: int
    data: bytes | None = None

    def raw_image(self):
        from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
        from google.protobuf.message import DecodeError

        if self.data is not None:
            data = self.data
        else:
            assert self.offset is not None
            try:
                with open(self.path, "rb") as f:
                    data = os.pread(f.fileno(), self.size, self.offset)
            except OSError as exc:
                raise InputError(
                    f"{self.path}: cannot read the frame at byte {self.offset}: {exc.strerror or exc}"
                ) from None
        img = RawImage()
        try:
            if len(data) != self.size:
                raise DecodeError(f"{len(data)} of its {self.size} bytes")
            img.ParseFromString(data)
        except DecodeError as exc:
            raise InputError(
                f"{self.path}: the frame at byte {self.offset} no longer decodes (the file changed since it was"
                f" read?): {exc}"
            ) from None
        return img


def _message_data_offsets(records: bytes, start: int) -> Iterator[int]:
    """The file offset of each message's data among an uncompressed chunk's ``records`` (which begin at byte
    ``start`` of the file), in order: each record is its opcode, its length and its body, a message's body its
    channel id, sequence, log and publish times, then its data (https://mcap.dev/spec#message-op0x05)."""
    pos, n = 0, len(records)
    while pos + RECORD_HEAD.size <= n:
        opcode, length = RECORD_HEAD.unpack_from(records, pos)
        if opcode == Opcode.MESSAGE:
            yield start + pos + RECORD_HEAD.size + MESSAGE_FIXED
        pos += RECORD_HEAD.size + length


def _bytes_at(f, offset: int, data: bytes) -> bool:
    """Whether the file holds ``data`` at ``offset`` (its first and last 16 bytes): an offset worked out from the
    records' layout is used only where it is checked."""
    n = len(data)
    if n == 0:
        return False
    head, tail = min(16, n), max(0, n - 16)
    return (
        os.pread(f.fileno(), head, offset) == data[:head]
        and os.pread(f.fileno(), n - tail, offset + tail) == data[tail:]
    )


def read_recording(path: str) -> Iterator[RecordedMessage | dict]:
    """Every message of an MCAP file in file order (metadata records as ``{"metadata": name, ...}``),
    with the `mcap` package's stream reader; a file cut short ends at its last complete record and
    yields ``{"truncated": "<reason>"}`` last.  A record the reader cannot parse before the end of the file
    is not a cut but damage: :class:`InputError`.  A message of an uncompressed chunk carries where its data lies
    in the file (``data_offset``)."""
    from mcap.records import Channel, Chunk, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader, breakup_chunk

    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}
    try:
        f = open(path, "rb")
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None
    with f:
        head = f.read(len(MCAP_MAGIC))
        if head != MCAP_MAGIC:  # not even the start of a recording: refused, not read as one cut short
            what = "the file is empty" if not head else f"it starts with {head!r}, not the MCAP magic"
            raise InputError(f"{path}: not an MCAP recording ({what}); give a file of python -m onboard --record")
        f.seek(0)
        try:
            reader = StreamReader(f, emit_chunks=True, validate_crcs=False).records
            while True:
                # the reader reads each record whole, so the file's position between two is where the next starts
                start = f.tell()
                top = next(reader, None)
                if top is None:
                    break
                offsets: Iterator[int | None] = iter(())
                if isinstance(top, Chunk):
                    if top.compression == "":
                        at = start + RECORD_HEAD.size + CHUNK_FIXED + 4 + len(top.compression.encode()) + 8
                        if _bytes_at(f, at, top.data):
                            offsets = _message_data_offsets(top.data, at)
                    inner = breakup_chunk(top, validate_crc=False)
                else:
                    inner = [top]
                    if isinstance(top, Message):  # a message outside any chunk
                        at = start + RECORD_HEAD.size + MESSAGE_FIXED
                        offsets = iter([at if _bytes_at(f, at, top.data) else None])
                for rec in inner:
                    if isinstance(rec, Schema):
                        schemas[rec.id] = rec.name
                    elif isinstance(rec, Channel):
                        channels[rec.id] = (rec.topic, schemas.get(rec.schema_id, ""))
                    elif isinstance(rec, Message):
                        topic, schema = channels.get(rec.channel_id, ("?", ""))
                        data_at = next(offsets, None)
                        yield RecordedMessage(
                            topic, schema, rec.log_time, rec.publish_time, rec.sequence, rec.data, data_at
                        )
                    elif isinstance(rec, Metadata):
                        yield {"metadata": rec.name, **rec.metadata}
        except Exception as exc:  # noqa: BLE001 - whatever the reader raised where the file stops or is damaged
            # a record cut by the end of the file: the reader found no bytes (EndOfFile), fewer than a field's
            # (struct.error) or a partial trailing magic; it read up to the end, which tells a cut from damage
            ended = f.tell() >= os.fstat(f.fileno()).st_size
            short_read = type(exc).__name__ in ("EndOfFile", "InvalidMagic") or isinstance(
                exc, (EOFError, ValueError, struct.error)
            )
            if ended and short_read:
                yield {"truncated": f"it ends at byte {f.tell()}"}
                return
            raise InputError(
                f"{path}: not a readable MCAP file (at byte {f.tell()}): {type(exc).__name__}: {exc}"
            ) from None
