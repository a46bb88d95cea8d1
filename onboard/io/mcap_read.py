"""MCAP recordings read record by record (adapter; replay's, the flight report's and record_recover's).

:class:`RecordWalk` is the one place these streaming reads go through: it walks a file's top-level records from its
header on, each read by the `mcap` package's record classes within the length its head gives, and checks each where
it stands (:class:`LayoutCheck`).  :func:`read_recording` gives each message with where its data lies in the file, so
that a frame (:class:`FrameRef`) is read again from there when used instead of held in memory.  The record layout is
:mod:`onboard.io.mcap_chunks`'.

A cut is told from damage: a file cut short (a killed daemon) ends in a record whose length runs past the end of the
file, and is read up to it.  That record's own fields must run past the end too (the writers put nothing after a
record's fields: a cut cuts them), its length must be one the mcap package reads (up to 4 GiB), and the file must
not end with the closing magic (the last thing a writer writes).  Anything else a reader cannot take is damage,
refused naming the byte (:class:`RecordDamage`) and the record before it (a damaged length there sends a reader into
the middle of other bytes).  The layout the checks hold a file to is the specification's
(https://mcap.dev/spec#file-structure), as irtrack's writers (the recorder's
:class:`~onboard.io.mcap_chunks.ChunkWriter`, the `mcap` package's writer record_recover writes with) write it:

- a footer of 20 bytes and a data end record of 4 (the specification says they will not grow);
- the header first; in the data section only schemas, channels, messages, chunks, message indexes, attachments,
  metadata and, last, the data end record; after it only the summary (schemas, channels, statistics, chunk,
  attachment and metadata indexes, grouped by kind), then summary offsets, then the footer and the closing magic.
  An opcode the specification reserves without defining a record for it (0x00, 0x10-0x7F) is damage, and so is a
  private record (0x80-0xFF) outside a chunk: the specification's lists of what the data section and the summary
  hold do not include them, irtrack's writers write none, and a reader that skipped one would skip a record whose
  opcode lost or gained its top bit;
- right after each chunk, its message indexes: exactly one per channel it holds messages on, each listing as many
  messages as the chunk holds on that channel (https://mcap.dev/spec#message-index-op0x07; both writers index every
  chunk, so a chunk with messages and no index is damage); a message index after anything but a chunk or another
  message index is damage;
- where the file has a summary, it counts what the data section holds: the statistics' message, chunk, metadata and
  attachment counts and per-channel message counts; a chunk index for each chunk, where that chunk is; the
  footer's summary start right after the data end record, its summary offset start at the first summary offset,
  and each summary offset where its group is.

A file cut short stays a cut wherever the cut is, in the data section or in its summary (the recorder writes the
data end record, then the summary, which a full disk can refuse): the rules judge the records before the cut.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from onboard.core.errors import InputError
from onboard.io.mcap_chunks import CHUNK_FIXED, MCAP_MAGIC, MESSAGE_FIXED, RECORD_HEAD

__all__ = [
    "RecordedMessage",
    "FrameRef",
    "TopRecord",
    "RecordDamage",
    "RecordWalk",
    "LayoutCheck",
    "ChunkIndexCheck",
    "KNOWN_OPCODES",
    "read_recording",
    "read_record",
    "record_name",
    "footer_intact",
    "chunk_records",
]

#: the opcodes the MCAP specification defines (https://mcap.dev/spec#records); 0x80-0xFF are for private records
KNOWN_OPCODES = frozenset(int(o) for o in Opcode)
#: a footer record: its opcode, its length (8 + 8 + 4) and its body, then the closing magic
_FOOTER_BYTES = RECORD_HEAD.size + 20
_RECOVER_HINT = "; python -m onboard.record_recover --skip-damaged writes the rest to a new file"
#: the only records a chunk may hold (https://mcap.dev/spec#chunk-op0x06)
_CHUNK_OPCODES = frozenset((Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE))
#: the records the data section may hold after its header (https://mcap.dev/spec#data-section)
_DATA_OPCODES = frozenset(
    (
        Opcode.SCHEMA,
        Opcode.CHANNEL,
        Opcode.MESSAGE,
        Opcode.ATTACHMENT,
        Opcode.CHUNK,
        Opcode.MESSAGE_INDEX,
        Opcode.METADATA,
        Opcode.DATA_END,
    )
)
#: the records the summary section may hold (https://mcap.dev/spec#summary-section)
_SUMMARY_OPCODES = frozenset(
    (
        Opcode.SCHEMA,
        Opcode.CHANNEL,
        Opcode.CHUNK_INDEX,
        Opcode.ATTACHMENT_INDEX,
        Opcode.METADATA_INDEX,
        Opcode.STATISTICS,
    )
)
#: the longest record read (``mcap.stream_reader.StreamReader``'s default ``record_size_limit``)
_RECORD_LIMIT = 4 * 2**30
#: the records the specification says will not be extended (https://mcap.dev/spec#records), by their lengths
_FIXED_LENGTHS: dict[int, int] = {Opcode.FOOTER: 8 + 8 + 4, Opcode.DATA_END: 4}
_NAMES: dict[int, str] = {
    Opcode.HEADER: "a header",
    Opcode.FOOTER: "a footer",
    Opcode.SCHEMA: "a schema",
    Opcode.CHANNEL: "a channel",
    Opcode.MESSAGE: "a message",
    Opcode.CHUNK: "a chunk",
    Opcode.MESSAGE_INDEX: "a message index",
    Opcode.CHUNK_INDEX: "a chunk index",
    Opcode.ATTACHMENT: "an attachment",
    Opcode.ATTACHMENT_INDEX: "an attachment index",
    Opcode.STATISTICS: "a statistics record",
    Opcode.METADATA: "a metadata record",
    Opcode.METADATA_INDEX: "a metadata index",
    Opcode.SUMMARY_OFFSET: "a summary offset",
    Opcode.DATA_END: "a data end record",
}
_READERS: dict[int, Any] = {
    Opcode.HEADER: Header.read,
    Opcode.FOOTER: Footer.read,
    Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read,
    Opcode.CHUNK: Chunk.read,
    Opcode.MESSAGE_INDEX: MessageIndex.read,
    Opcode.CHUNK_INDEX: ChunkIndex.read,
    Opcode.ATTACHMENT: Attachment.read,
    Opcode.ATTACHMENT_INDEX: AttachmentIndex.read,
    Opcode.STATISTICS: Statistics.read,
    Opcode.METADATA: Metadata.read,
    Opcode.METADATA_INDEX: MetadataIndex.read,
    Opcode.SUMMARY_OFFSET: SummaryOffset.read,
    Opcode.DATA_END: DataEnd.read,
}


def record_name(opcode: int) -> str:
    """A record by its opcode, for a message: ``a chunk index (0x08)``."""
    return f"{_NAMES.get(opcode, 'a record')} ({opcode:#04x})"


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


class RecordDamage(InputError):
    """Damage in an MCAP file: ``what`` says which record and why (without the file's name: the reader adds it);
    ``at``: where the part it costs begins (a chunk whose message indexes disagree with it costs the chunk);
    ``in_summary``: it lies after the data section, whose records were all read."""

    def __init__(self, what: str, at: int, in_summary: bool = False) -> None:
        super().__init__(what)
        self.what, self.at, self.in_summary = what, at, in_summary


@dataclass(frozen=True)
class TopRecord:
    """A record of the data section: ``start`` its byte, ``end`` the byte after it, ``record`` the `mcap` package's
    record, ``records`` a chunk's records (:func:`chunk_records`, checked by its message indexes) or ``[record]``."""

    start: int
    end: int
    record: Any
    records: list


def footer_intact(f, size: int) -> bool:
    """Whether the file ``f`` (``size`` bytes) ends with a footer record and the closing magic, as a finished
    recording does: such a file was not cut, so a record that cannot be read in it is damage."""
    if size < 2 * len(MCAP_MAGIC) + _FOOTER_BYTES:
        return False
    tail = os.pread(f.fileno(), _FOOTER_BYTES + len(MCAP_MAGIC), size - _FOOTER_BYTES - len(MCAP_MAGIC))
    opcode, length = RECORD_HEAD.unpack_from(tail, 0)
    return opcode == Opcode.FOOTER and length == 20 and tail.endswith(MCAP_MAGIC)


def _ends_closed(f, size: int) -> bool:
    """Whether the file ``f`` (``size`` bytes) ends with the closing magic, as only a finished file does (its writer
    writes the magic last): a record of it that runs past the end, or a last one cut short, was damaged, not cut."""
    n = len(MCAP_MAGIC)
    return size >= 2 * n + RECORD_HEAD.size and os.pread(f.fileno(), n, size - n) == MCAP_MAGIC


class _RunsPast(Exception):
    """A record's fields run past the length its head gives."""


class _Body:
    """The body of a record (``length`` bytes from ``start`` of ``f``) as the stream the `mcap` package's record
    classes read: a read past its end raises :class:`_RunsPast`.  The package's own stream hands a short read on,
    so a damaged field length was read on into the records after it, or to the end of the file (a cut, then)."""

    def __init__(self, f: BinaryIO, start: int, length: int) -> None:
        f.seek(start)
        self._f, self._left = f, length

    def read(self, n: int = -1) -> bytes:
        if n < 0 or n > self._left:
            raise _RunsPast
        data = self._f.read(n)
        if len(data) != n:  # the file shrank under the reader
            raise _RunsPast
        self._left -= n
        return data


def read_record(f: BinaryIO, start: int, opcode: int, length: int) -> Any:
    """The record at byte ``start`` of ``f`` whose head gives ``opcode`` (one :data:`KNOWN_OPCODES` holds) and
    ``length``, read by the `mcap` package's class for it within its ``length`` bytes; fields after those the class
    knows are skipped, as the specification lets a record grow.  :class:`RecordDamage` when its fields run past its
    length or do not parse."""
    stream = ReadDataStream(_Body(f, start + RECORD_HEAD.size, length))  # type: ignore[arg-type]
    try:
        if opcode == Opcode.MESSAGE:
            return Message.read(stream, length)
        return _READERS[opcode](stream)
    except _RunsPast:
        why = f"it says {length} bytes but its fields run past them"
    except Exception as exc:  # noqa: BLE001 - whatever its fields raise (a string that is not UTF-8, ...): damaged
        why = f"{type(exc).__name__}: {exc}"
    raise RecordDamage(f"the record at byte {start} cannot be read: {why}", start)


def _fields_fit(f: BinaryIO, start: int, opcode: int, available: int) -> bool:
    """Whether the fields of the record at byte ``start`` (``opcode``), whose length runs past the end of the file,
    all lie in the ``available`` bytes after its head: the writers put nothing after a record's fields, so a cut
    cuts them; a record whose fields end within the file had its length damaged.  A message's data is as long as
    its record says: it always runs past."""
    if opcode == Opcode.MESSAGE:
        return False
    try:
        read_record(f, start, opcode, available)
    except RecordDamage:
        return False
    return True


def chunk_records(chunk: Chunk, start: int) -> list:
    """The records of ``chunk`` (the chunk at byte ``start``), read in one pass and checked as they are: each a
    schema, channel or message (the only records a chunk holds) that ends where its length says, within the chunk.
    The package's ``breakup_chunk`` skips a record of any other opcode and reads one whose length runs past the
    chunk's end as holding the rest of it, both without an error: damage would lose messages unsaid.
    :class:`RecordDamage` (costing the chunk) for damage."""
    from mcap.stream_reader import get_chunk_data_stream

    where = f"the chunk at byte {start}"
    try:
        stream, size = get_chunk_data_stream(chunk, validate_crc=True)
    except Exception as exc:  # noqa: BLE001 - its data does not decompress, or fails its CRC
        raise RecordDamage(f"{where}: its records cannot be read: {type(exc).__name__}: {exc}", start) from None
    records: list = []
    while stream.count < size:
        pos = stream.count
        if pos + RECORD_HEAD.size > size:
            raise RecordDamage(f"{where}: {size - pos} bytes at byte {pos} of a chunk are not a whole record", start)
        opcode = stream.read1()
        length = stream.read8()
        if opcode not in _CHUNK_OPCODES:
            raise RecordDamage(f"{where}: a record of opcode {opcode:#04x} at byte {pos} of a chunk", start)
        end = pos + RECORD_HEAD.size + length
        if end > size:
            raise RecordDamage(
                f"{where}: a record at byte {pos} of a chunk (log times {chunk.message_start_time} to "
                f"{chunk.message_end_time} ns) runs past the chunk's {size} bytes",
                start,
            )
        try:
            if opcode == Opcode.MESSAGE:
                records.append(Message.read(stream, length))
            else:
                records.append((Channel if opcode == Opcode.CHANNEL else Schema).read(stream))
        except Exception as exc:  # noqa: BLE001 - whatever its fields raise: this record is damaged
            raise RecordDamage(
                f"{where}: the record at byte {pos} of a chunk cannot be read: {type(exc).__name__}: {exc}", start
            ) from None
        if stream.count != end:
            raise RecordDamage(
                f"{where}: the record at byte {pos} of a chunk does not end where its length says", start
            )
    return records


class ChunkIndexCheck:
    """The message indexes after one chunk (the one at byte ``start``, whose records are ``records``), fed as they
    come and checked against the messages read from it: exactly one per channel the chunk holds messages on, listing
    as many (https://mcap.dev/spec#message-index-op0x07).  A message whose length was damaged can take in the
    messages after it in its chunk and still end at the chunk's end, which nothing else notices; its chunk's index
    still counts them.  A channel without messages may have an index that lists none: it loses nothing."""

    def __init__(self, records: list, start: int) -> None:
        counts: dict[int, int] = {}
        for r in records:
            if isinstance(r, Message):
                counts[r.channel_id] = counts.get(r.channel_id, 0) + 1
        self._counts, self._start = counts, start
        self._indexed: set[int] = set()

    def add(self, index: MessageIndex, at: int) -> None:
        """The message index at byte ``at``; :class:`RecordDamage` (costing the chunk) when it disagrees."""
        cid, s = index.channel_id, self._start
        if cid in self._indexed:
            raise RecordDamage(f"the chunk at byte {s} has a second message index for channel {cid} (at byte {at})", s)
        self._indexed.add(cid)
        read = self._counts.get(cid, 0)
        if len(index.records) != read:
            raise RecordDamage(
                f"the chunk at byte {s} holds {read} message{'s' * (read != 1)} on channel {cid}, its index (the "
                f"record at byte {at}) lists {len(index.records)}",
                s,
            )

    def unindexed(self) -> str | None:
        """Why the indexes read so far leave a channel the chunk holds messages on without one (once they end); None
        when they do not."""
        missing = sorted(set(self._counts) - self._indexed)
        if not missing:
            return None
        return (
            f"the chunk at byte {self._start} holds messages on channel{'s' * (len(missing) > 1)} "
            f"{', '.join(map(str, missing))}, which no message index after it lists"
        )


class LayoutCheck:
    """The top-level records of one MCAP file, fed in file order, checked where each stands (the module docstring's
    rules): :meth:`head` before a record is read (its opcode, there), :meth:`add` once it is (what it counts and
    where it points), :meth:`end` when the file has been read to its footer or to its cut.  No I/O: the caller
    reads.  :attr:`data_end`: the byte after the data end record, once read; :attr:`last`: the opcode of the last
    record :meth:`head` let begin."""

    def __init__(self) -> None:
        self.section = "header"  # then data, summary (after the data end record), offsets, end (the footer read)
        self.data_end: int | None = None
        self.last = 0  # the opcode of the last record :meth:`head` let begin
        self._groups: dict[int, tuple[int, int]] = {}  # a summary group's opcode -> its first byte, the byte after it
        self._group = 0
        self._offsets_start: int | None = None
        self._offsets: list[tuple[int, SummaryOffset]] = []
        self._chunks: dict[int, int] = {}  # a chunk's byte -> its length, as read
        self._messages: dict[int, int] = {}  # channel id -> messages read
        self._metadata = self._attachments = 0
        self._statistics: tuple[int, Statistics] | None = None
        self._chunk_indexes: list[tuple[int, ChunkIndex]] = []

    def head(self, opcode: int, start: int, length: int) -> str | None:
        """Why a record of ``opcode`` (``length`` bytes) may not begin at byte ``start``, here; None when it may."""
        if opcode not in KNOWN_OPCODES:
            if opcode >= 0x80:
                return (
                    f"the record at byte {start} has opcode {opcode:#04x}, a private record's, which irtrack's writers "
                    "never write (nor does the specification list one outside a chunk)"
                )
            return f"the record at byte {start} has opcode {opcode:#04x}, which no MCAP record has"
        name, section = record_name(opcode), self.section
        fixed = _FIXED_LENGTHS.get(opcode)
        if fixed is not None and length != fixed:
            return f"the record at byte {start} is {name} of {length} bytes, not {fixed}: that record never grows"
        if section == "header":
            if opcode != Opcode.HEADER:
                return f"its first record, at byte {start}, is {name}, not a header"
            self.section = "data"
        elif opcode == Opcode.HEADER:
            return f"the record at byte {start} is {name}: only the file's first record is one"
        elif section == "data":
            if opcode == Opcode.FOOTER:
                return f"the record at byte {start} is {name}, before the data section's end (its data end record)"
            if opcode not in _DATA_OPCODES:
                return f"the record at byte {start} is {name}, which belongs after the data section's end, not in it"
            if opcode == Opcode.MESSAGE_INDEX and self.last not in (Opcode.CHUNK, Opcode.MESSAGE_INDEX):
                return (
                    f"the record at byte {start} is {name}, which follows a chunk or another message index, "
                    f"not {record_name(self.last)}"
                )
            if opcode == Opcode.DATA_END:
                self.section, self.data_end = "summary", start + RECORD_HEAD.size + length
        elif section == "summary":
            if opcode == Opcode.SUMMARY_OFFSET:
                self.section, self._offsets_start = "offsets", start
            elif opcode == Opcode.FOOTER:
                self.section = "end"
            elif opcode not in _SUMMARY_OPCODES:
                return (
                    f"the record at byte {start} is {name}, after the data section's end (at byte {self.data_end}) "
                    "where only the summary comes"
                )
            elif opcode != self._group:
                if opcode in self._groups:
                    return (
                        f"the record at byte {start} is {name}, whose group in the summary ended before it (the "
                        "summary's records are grouped by kind)"
                    )
                self._group = opcode
        elif section == "offsets":
            if opcode == Opcode.FOOTER:
                self.section = "end"
            elif opcode != Opcode.SUMMARY_OFFSET:
                return (
                    f"the record at byte {start} is {name}, among the summary offsets (from byte "
                    f"{self._offsets_start} only more of them and the footer come)"
                )
        self.last = opcode
        return None

    def add(self, record: Any, start: int, end: int, records: list) -> None:
        """The record :meth:`head` let begin at ``start``, read (``end`` the byte after it; ``records`` a chunk's
        records, else ``[record]``)."""
        if self.section == "data" or isinstance(record, DataEnd):
            if isinstance(record, Chunk):
                self._chunks[start] = end - start
            elif isinstance(record, Metadata):
                self._metadata += 1
            elif isinstance(record, Attachment):
                self._attachments += 1
            for r in records:
                if isinstance(r, Message):
                    self._messages[r.channel_id] = self._messages.get(r.channel_id, 0) + 1
            return
        if self.section == "summary":
            first, _ = self._groups.get(self._group, (start, end))
            self._groups[self._group] = (first, end)
        if isinstance(record, Statistics):
            self._statistics = (start, record)
        elif isinstance(record, ChunkIndex):
            self._chunk_indexes.append((start, record))
        elif isinstance(record, SummaryOffset):
            self._offsets.append((start, record))

    def end(self, footer: Footer | None, footer_start: int) -> RecordDamage | None:
        """The damage the summary read shows (it counts otherwise than the data section read, or points elsewhere
        than where its records are), or None; ``footer`` None: the file was cut at byte ``footer_start`` (its
        summary, if any, is judged as far as it was read)."""
        lost = self._counted_otherwise()
        listed = {ci.chunk_start_offset: (at, ci) for at, ci in self._chunk_indexes}
        for at, ci in self._chunk_indexes:
            if self._chunks.get(ci.chunk_start_offset) != ci.chunk_length:
                what = (
                    f"the chunk index at byte {at} lists a chunk at byte {ci.chunk_start_offset} ({ci.chunk_length} "
                    "bytes), which the data section read does not hold"
                )
                if lost is not None:  # the summary counts more than was read, and says where it was
                    return RecordDamage(f"{lost}; {what}", ci.chunk_start_offset)
                return RecordDamage(what, at, in_summary=True)
        if lost is not None:
            return RecordDamage(lost, self.data_end or footer_start)
        if footer is None:
            return None
        if listed:
            for start in self._chunks:
                if start not in listed:
                    return RecordDamage(f"the chunk at byte {start} has no chunk index in the summary", start, True)
        if footer.summary_start and footer.summary_start != self.data_end:
            return RecordDamage(
                f"the footer (at byte {footer_start}) says the summary starts at byte {footer.summary_start}, not "
                f"right after the data end record (byte {self.data_end})",
                footer_start,
                True,
            )
        offsets_at = self._offsets_start if self._offsets_start is not None else footer_start
        if footer.summary_offset_start and footer.summary_offset_start != offsets_at:
            return RecordDamage(
                f"the footer (at byte {footer_start}) says the summary offsets start at byte "
                f"{footer.summary_offset_start}, not {offsets_at}",
                footer_start,
                True,
            )
        return self._offsets_elsewhere()

    def _counted_otherwise(self) -> str | None:
        """How the statistics count otherwise than what the data section read holds, or None."""
        if self._statistics is None:
            return None
        at, st = self._statistics
        read = sum(self._messages.values())
        said = []
        if st.message_count != read or st.chunk_count != len(self._chunks):
            said.append(
                f"{st.message_count} messages in {st.chunk_count} chunks, the data section read holds {read} in "
                f"{len(self._chunks)}"
            )
        counts = {cid: n for cid, n in st.channel_message_counts.items() if n}
        if counts and counts != self._messages:
            said += [
                f"channel {cid}: {counts.get(cid, 0)} messages, {self._messages.get(cid, 0)} read"
                for cid in sorted(set(counts) | set(self._messages))
                if counts.get(cid, 0) != self._messages.get(cid, 0)
            ]
        if st.metadata_count != self._metadata:
            said.append(f"{st.metadata_count} metadata records, {self._metadata} read")
        if st.attachment_count != self._attachments:
            said.append(f"{st.attachment_count} attachments, {self._attachments} read")
        if not said:
            return None
        return f"the summary's statistics (the record at byte {at}) count {'; '.join(said)}"

    def _offsets_elsewhere(self) -> RecordDamage | None:
        """The summary offset that says its group is elsewhere than where its records are, or a group none finds."""
        if not self._offsets:
            return None
        found = set()
        for at, o in self._offsets:
            group = self._groups.get(o.group_opcode)
            said = (o.group_start, o.group_start + o.group_length)
            if (group is None and o.group_length) or (group is not None and group != said):
                where = f"bytes {group[0]} to {group[1]}" if group else "nowhere"
                return RecordDamage(
                    f"the summary offset at byte {at} says the summary's {record_name(o.group_opcode)} records are "
                    f"at bytes {said[0]} to {said[1]}; they are {where}",
                    at,
                    True,
                )
            found.add(o.group_opcode)
        for opcode, (first, _) in self._groups.items():
            if opcode not in found:
                return RecordDamage(
                    f"the summary's {record_name(opcode)} records (from byte {first}) have no summary offset",
                    first,
                    True,
                )
        return None


class RecordWalk:
    """Every record of the MCAP file ``f`` (named ``src``; positioned anywhere) from its header on, each read within
    the length its head gives (:func:`read_record`) and checked where it stands (:class:`LayoutCheck`,
    :class:`ChunkIndexCheck`).  Iterating gives the data section's records in file order (:class:`TopRecord`: the
    header, schemas, channels, messages, attachments, metadata, and chunks once their message indexes have checked
    them); the data end record, the message indexes and the summary are checked, not given.  The walk ends at the
    footer (:attr:`complete`) or where the file was cut (:attr:`cut_at`: at a record whose length runs past the end
    of a file without its footer; what was read before it is given).  Damage raises :class:`RecordDamage`, a first
    record that is not a header :class:`InputError`."""

    def __init__(self, f: BinaryIO, src: str) -> None:
        self._f, self._src = f, src
        self.size = os.fstat(f.fileno()).st_size
        self.layout = LayoutCheck()
        self.complete = False
        self.cut_at: int | None = None

    def _in_summary(self, opcode: int) -> bool:
        """Whether damage to a record of ``opcode`` read here lies in the summary, the data section read whole: a
        record the data section holds after its end says that end record was a damaged one instead."""
        return self.layout.data_end is not None and (opcode in _SUMMARY_OPCODES or opcode not in _DATA_OPCODES)

    def __iter__(self) -> Iterator[TopRecord]:
        f, size, layout = self._f, self.size, self.layout
        pos = len(MCAP_MAGIC)
        pending: TopRecord | None = None  # a chunk, given once its message indexes have checked it
        index: ChunkIndexCheck | None = None
        last = pos  # the last record's byte
        while True:
            head = os.pread(f.fileno(), RECORD_HEAD.size, pos)
            if len(head) < RECORD_HEAD.size:
                if _ends_closed(f, size):
                    raise RecordDamage(
                        f"the record at byte {last} ({record_name(layout.last)}) ends at byte {pos}, {size - pos} bytes "
                        "before the end of the file, which ends with its closing magic: it was not cut, and its footer "
                        "is not where the records end",
                        last if pending is None else pending.start,
                        layout.data_end is not None,
                    )
                break
            opcode, length = RECORD_HEAD.unpack(head)
            unindexed = None
            if index is not None and opcode != Opcode.MESSAGE_INDEX:
                unindexed = index.unindexed()
                if unindexed is not None:
                    unindexed += f" (after the record at byte {last} comes {record_name(opcode)}, at byte {pos})"
                else:
                    assert pending is not None
                    yield pending
                    pending = index = None
            costs = pending.start if pending is not None else pos
            first, before = layout.section == "header", record_name(layout.last)
            why = layout.head(opcode, pos, length)
            if why is not None and first:
                raise InputError(f"{self._src}: not a readable MCAP file ({why})")
            if why is not None:
                # a damaged length in the record before sends a reader here, into the middle of other bytes
                why += f" (the record before it: {before} at byte {last})"
            why = why or unindexed
            if why is not None:
                raise RecordDamage(why, costs, self._in_summary(opcode))
            end = pos + RECORD_HEAD.size + length
            if end > size:
                if _ends_closed(f, size):
                    why = "the file ends with its closing magic: it was not cut"
                elif length > _RECORD_LIMIT:
                    why = "no record is that long: the mcap package refuses to read one over 4 GiB"
                elif _fields_fit(f, pos, opcode, size - pos - RECORD_HEAD.size):
                    why = "its fields end within the file: a cut would have cut them"
                else:
                    break  # the file was cut in this record
                raise RecordDamage(
                    f"the record at byte {pos} says {length} bytes, past the end of the file, but {why} (the record "
                    f"before it: {before} at byte {last})",
                    costs,
                    self._in_summary(opcode),
                )
            try:
                record = read_record(f, pos, opcode, length)
            except RecordDamage as exc:
                what = f"{exc.what} (the record before it: {before} at byte {last})"
                raise RecordDamage(what, costs, self._in_summary(opcode)) from None
            if isinstance(record, MessageIndex):
                assert index is not None  # head() lets one follow a chunk or another message index only
                index.add(record, pos)
                last, pos = pos, end
                continue
            records = chunk_records(record, pos) if isinstance(record, Chunk) else [record]
            layout.add(record, pos, end, records)
            if isinstance(record, Footer):
                self._closing(record, pos, end)
                return
            if layout.section == "data":
                top = TopRecord(pos, end, record, records)
                if isinstance(record, Chunk):
                    pending, index = top, ChunkIndexCheck(records, pos)
                else:
                    yield top
            last, pos = pos, end
        self.cut_at = pos
        if pending is not None:  # its indexes read so far agree with it; the rest were cut
            yield pending
        damage = layout.end(None, pos)
        if damage is not None:
            raise damage

    def _closing(self, footer: Footer, start: int, end: int) -> None:
        """After the footer at byte ``start``: the closing magic, then the end of the file; the summary's counts."""
        tail = os.pread(self._f.fileno(), len(MCAP_MAGIC) + 1, end)
        if tail != MCAP_MAGIC and not (len(tail) < len(MCAP_MAGIC) and MCAP_MAGIC.startswith(tail)):
            raise RecordDamage(
                f"the footer at byte {start} is not followed by the closing magic and the end of the file", start, True
            )
        damage = self.layout.end(footer, start)
        if damage is not None:
            raise damage
        if tail == MCAP_MAGIC:
            self.complete = True
        else:  # cut in its closing magic
            self.cut_at = end


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
    """Every message of an MCAP file in file order (metadata records as ``{"metadata": name, ...}``), through
    :class:`RecordWalk`; a file cut short ends at its last complete record and yields ``{"truncated": "<reason>"}``
    last.  Damage (the module docstring; a message of an undeclared channel too) is not a cut: :class:`InputError`
    naming the byte, with the way to recover the rest.  A message of an uncompressed chunk carries where its data
    lies in the file (``data_offset``)."""
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
        walk = RecordWalk(f, path)
        try:
            for top in walk:
                offsets: Iterator[int | None] = iter(())
                start, rec = top.start, top.record
                if isinstance(rec, Chunk):
                    if rec.compression == "":
                        at = start + RECORD_HEAD.size + CHUNK_FIXED + 4 + 8
                        if _bytes_at(f, at, rec.data):
                            offsets = _message_data_offsets(rec.data, at)
                elif isinstance(rec, Message):  # a message outside any chunk
                    at = start + RECORD_HEAD.size + MESSAGE_FIXED
                    offsets = iter([at if _bytes_at(f, at, rec.data) else None])
                for rec in top.records:
                    if isinstance(rec, Schema):
                        schemas[rec.id] = rec.name
                    elif isinstance(rec, Channel):
                        channels[rec.id] = (rec.topic, schemas.get(rec.schema_id, ""))
                    elif isinstance(rec, Message):
                        if rec.channel_id not in channels:
                            raise RecordDamage(
                                f"a message at log time {rec.log_time} ns (the record at byte {start}) names channel "
                                f"{rec.channel_id}, which no channel record before it declares",
                                start,
                            )
                        topic, schema = channels[rec.channel_id]
                        yield RecordedMessage(
                            topic, schema, rec.log_time, rec.publish_time, rec.sequence, rec.data, next(offsets, None)
                        )
                    elif isinstance(rec, Metadata):
                        yield {"metadata": rec.name, **rec.metadata}
        except RecordDamage as exc:
            raise InputError(f"{path}: damaged: {exc.what}{_RECOVER_HINT}") from None
        if walk.cut_at is not None:
            yield {"truncated": f"it ends at byte {walk.size}"}
