"""MCAP recordings read message by message (adapter; replay's and the flight report's): :func:`read_recording`
walks a file with the `mcap` package's stream reader, a file cut short (a killed daemon) up to its last whole
record, and gives each message with where its data lies in the file, so that a frame (:class:`FrameRef`) is read
again from there when used instead of held in memory.  The record layout is :mod:`onboard.io.mcap_chunks`'.
A cut is told from damage (:func:`damage_at`, :func:`chunk_records`, :class:`ChunkIndexCheck`, shared with
:mod:`onboard.app.record_recover`): a file cut short is read to its cut, a damaged one refused.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass

from mcap.opcode import Opcode

from onboard.core.errors import InputError
from onboard.io.mcap_chunks import CHUNK_FIXED, MCAP_MAGIC, MESSAGE_FIXED, RECORD_HEAD

__all__ = [
    "RecordedMessage",
    "FrameRef",
    "ChunkIndexCheck",
    "KNOWN_OPCODES",
    "read_recording",
    "record_overran",
    "footer_intact",
    "damage_at",
    "chunk_records",
]

#: the opcodes the MCAP specification defines (https://mcap.dev/spec#opcodes); 0x80-0xFF are for user records
KNOWN_OPCODES = frozenset(int(o) for o in Opcode)
#: a footer record: its opcode, its length (8 + 8 + 4) and its body, then the closing magic
_FOOTER_BYTES = RECORD_HEAD.size + 20
_RECOVER_HINT = "; python -m onboard.record_recover --skip-damaged writes the rest to a new file"
#: the only records a chunk may hold (https://mcap.dev/spec#chunk-op0x06)
_CHUNK_OPCODES = frozenset((Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE))


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


def footer_intact(f, size: int) -> bool:
    """Whether the file ``f`` (``size`` bytes) ends with a footer record and the closing magic, as a finished
    recording does: such a file was not cut, so a record that cannot be read in it is damage."""
    if size < 2 * len(MCAP_MAGIC) + _FOOTER_BYTES:
        return False
    tail = os.pread(f.fileno(), _FOOTER_BYTES + len(MCAP_MAGIC), size - _FOOTER_BYTES - len(MCAP_MAGIC))
    opcode, length = RECORD_HEAD.unpack_from(tail, 0)
    return opcode == Opcode.FOOTER and length == 20 and tail.endswith(MCAP_MAGIC)


def damage_at(f, size: int, start: int) -> str | None:
    """Why the record at byte ``start`` of ``f`` (which a reader could not read) is damage, not where the file was
    cut, or None when a cut explains it.  A cut leaves a last record whose length runs past the end of a file
    without a footer; anything else -- the file has its footer, the record's opcode is none the specification
    defines, or its declared length fits in the file (so the bytes are there but do not parse) -- is damage."""
    if footer_intact(f, size):
        return f"the record at byte {start} cannot be read, and the file ends with its footer: it was not cut"
    head = os.pread(f.fileno(), RECORD_HEAD.size, start)
    if len(head) < RECORD_HEAD.size:
        return None
    opcode, length = RECORD_HEAD.unpack(head)
    if opcode not in KNOWN_OPCODES and opcode < 0x80:
        return f"the record at byte {start} has opcode {opcode:#04x}, which no MCAP record has"
    if start + RECORD_HEAD.size + length <= size:
        return f"the record at byte {start} ({length} bytes, within the file) cannot be read"
    return None


def record_overran(f, start: int, end: int) -> str | None:
    """Why the record the reader read from ``start`` to ``end`` (positions of ``f``) is damaged, or None: it must end
    where its own length says.  The `mcap` package reads a chunk's fields by their own lengths, so a chunk whose
    data length was damaged is read on to the end of the file (a compressed chunk decompresses all the same),
    which then looks like a cut."""
    if start == 0:  # the first read takes the magic before the header record
        start = len(MCAP_MAGIC)
    head = os.pread(f.fileno(), RECORD_HEAD.size, start)
    if len(head) < RECORD_HEAD.size:
        return None
    _opcode, length = RECORD_HEAD.unpack(head)
    if end != start + RECORD_HEAD.size + length:
        return (
            f"the record at byte {start} cannot be read: it says {length} bytes but its fields take "
            f"{end - start - RECORD_HEAD.size}"
        )
    return None


def chunk_records(chunk, where: str) -> list:
    """The records of ``chunk`` (an ``mcap.records.Chunk``), read in one pass and checked as they are: each a
    schema, channel or message (the only records a chunk holds) that ends where its length says, within the chunk.
    The package's ``breakup_chunk`` skips a record of any other opcode and reads one whose length runs past the
    chunk's end as holding the rest of it, both without an error: damage would lose messages unsaid.
    :class:`InputError` naming ``where`` (the file and the chunk) for damage."""
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import get_chunk_data_stream

    stream, size = get_chunk_data_stream(chunk, validate_crc=True)
    records: list = []
    while stream.count < size:
        pos = stream.count
        if pos + RECORD_HEAD.size > size:
            raise InputError(f"{where}: damaged: {size - pos} bytes at byte {pos} of a chunk are not a whole record")
        opcode = stream.read1()
        length = stream.read8()
        if opcode not in _CHUNK_OPCODES:
            raise InputError(f"{where}: damaged: a record of opcode {opcode:#04x} at byte {pos} of a chunk")
        end = pos + RECORD_HEAD.size + length
        if end > size:
            raise InputError(
                f"{where}: damaged: a record at byte {pos} of a chunk (log times {chunk.message_start_time} to "
                f"{chunk.message_end_time} ns) runs past the chunk's {size} bytes"
            )
        try:
            if opcode == Opcode.MESSAGE:
                records.append(Message.read(stream, length))
            else:
                records.append((Channel if opcode == Opcode.CHANNEL else Schema).read(stream))
        except Exception as exc:  # noqa: BLE001 - whatever its fields raise: this record is damaged
            raise InputError(
                f"{where}: damaged: the record at byte {pos} of a chunk cannot be read: {type(exc).__name__}: {exc}"
            ) from None
        if stream.count != end:
            raise InputError(
                f"{where}: damaged: the record at byte {pos} of a chunk does not end where its length says"
            )
    return records


class ChunkIndexCheck:
    """The message index records that follow a chunk, checked against the messages read from it: per channel as many
    entries as messages.  A message whose length was damaged can take in the messages after it in its chunk and
    still end at the chunk's end, which nothing else notices; its chunk's index still counts them."""

    def __init__(self, where: str) -> None:
        self._where = where
        self._counts: dict[int, int] | None = None
        self._start = 0

    def chunk(self, records: list, start: int) -> None:
        from mcap.records import Message

        counts: dict[int, int] = {}
        for r in records:
            if isinstance(r, Message):
                counts[r.channel_id] = counts.get(r.channel_id, 0) + 1
        self._counts, self._start = counts, start

    def add(self, record, start: int) -> None:
        """Any top-level record, in file order (``start`` its byte): a message index is checked, any other record but
        a chunk ends the run of indexes that belong to the last chunk."""
        from mcap.records import Chunk, MessageIndex

        if isinstance(record, MessageIndex):
            if self._counts is None:
                return
            read = self._counts.get(record.channel_id, 0)
            if len(record.records) != read:
                raise InputError(
                    f"{self._where}: damaged: the chunk at byte {self._start} holds {read} message{'s' * (read != 1)} "
                    f"on channel {record.channel_id}, its index (the record at byte {start}) lists "
                    f"{len(record.records)}"
                )
        elif not isinstance(record, Chunk):
            self._counts = None


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
    yields ``{"truncated": "<reason>"}`` last.  Damage is not a cut (:func:`damage_at`: a record that cannot be
    read in a file that ends with its footer, of an unknown opcode, or that fits in the file; a chunk
    :func:`chunk_records` or its message indexes refuse; a message of an undeclared channel): :class:`InputError`
    naming the byte, with the way to recover the rest.  A message of an uncompressed chunk carries where its data
    lies in the file (``data_offset``)."""
    from mcap.records import Channel, Chunk, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

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
        start = 0
        index_check = ChunkIndexCheck(path)
        try:
            reader = StreamReader(f, emit_chunks=True, validate_crcs=False).records
            while True:
                # the reader reads each record whole, so the file's position between two is where the next starts
                start = f.tell()
                top = next(reader, None)
                if top is None:
                    break
                offsets: Iterator[int | None] = iter(())
                overran = record_overran(f, start, f.tell())
                if overran is not None:
                    raise InputError(f"{path}: damaged: {overran}")
                index_check.add(top, start)
                if isinstance(top, Chunk):
                    if top.compression == "":
                        at = start + RECORD_HEAD.size + CHUNK_FIXED + 4 + len(top.compression.encode()) + 8
                        if _bytes_at(f, at, top.data):
                            offsets = _message_data_offsets(top.data, at)
                    inner = chunk_records(top, f"{path}: the chunk at byte {start}")
                    index_check.chunk(inner, start)
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
                        if rec.channel_id not in channels:
                            raise InputError(
                                f"{path}: damaged: a message at log time {rec.log_time} ns (the record at byte {start})"
                                f" names channel {rec.channel_id}, which no channel record before it declares"
                            )
                        topic, schema = channels[rec.channel_id]
                        data_at = next(offsets, None)
                        yield RecordedMessage(
                            topic, schema, rec.log_time, rec.publish_time, rec.sequence, rec.data, data_at
                        )
                    elif isinstance(rec, Metadata):
                        yield {"metadata": rec.name, **rec.metadata}
        except InputError as exc:
            raise InputError(f"{exc}{_RECOVER_HINT}" if "damaged" in str(exc) else str(exc)) from None
        except Exception as exc:  # noqa: BLE001 - whatever the reader raised where the file stops or is damaged
            # a record cut by the end of the file: the reader found no bytes (EndOfFile), fewer than a field's
            # (struct.error) or a partial trailing magic; it read up to the end.  That alone does not tell a cut from
            # damage (a damaged length can send the reader to the end too): damage_at judges the record it failed on
            size = os.fstat(f.fileno()).st_size
            ended = f.tell() >= size
            short_read = type(exc).__name__ in ("EndOfFile", "InvalidMagic") or isinstance(
                exc, (EOFError, ValueError, struct.error)
            )
            damage = damage_at(f, size, start)
            if ended and short_read and damage is None:
                yield {"truncated": f"it ends at byte {f.tell()}"}
                return
            why = damage or f"at byte {f.tell()}: {type(exc).__name__}: {exc}"
            raise InputError(f"{path}: damaged, not readable as a recording: {why}{_RECOVER_HINT}") from None
