"""An MCAP writer whose chunks go to the file without being assembled in memory (adapter; the recorder's).

:class:`ChunkWriter` writes the same bytes as the `mcap` package's ``mcap.writer.Writer`` (same records,
same order, same chunk boundaries, same summary: a test writes one stream of messages through both and
compares the files byte for byte), with one difference in *how*: a message's data may be a sequence of
buffers (bytes, memoryviews of numpy arrays), and an uncompressed chunk is written with one ``writev``
of its record headers and those buffers, straight from where they lie.  ``mcap.writer.Writer`` copies a
frame's 330 kB four to five times on its way to the file (the message into the chunk's ``BytesIO``, the
chunk out of it, into the chunk record's ``BytesIO``, out of that, into the file object), each into fresh
memory whose first touch costs page faults; here the kernel's copy into the page cache is the only one.

Compressed chunks (``lz4``, ``zstd``) are joined once and compressed, as the package does.

The small records (header, metadata, schema, channel, message index, chunk index, statistics, summary
offsets, footer) are built by the package's own ``mcap.records`` classes, so their layout is the
package's.  No CRCs unless ``enable_crcs`` (the chunk's ``uncompressed_crc`` and the footer's
``summary_crc``, as the package computes them); the data section CRC is 0 ("not computed"), the
package's default.  Spec: https://mcap.dev/spec.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections import OrderedDict, defaultdict
from collections.abc import Sequence
from typing import Any

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

__all__ = ["ChunkWriter", "MCAP_MAGIC", "RECORD_HEAD", "MESSAGE_FIXED", "CHUNK_FIXED"]

MCAP_MAGIC = struct.pack("<8B", 137, 77, 67, 65, 80, 48, 13, 10)
#: every record's head: its opcode and the length of its body
RECORD_HEAD = struct.Struct("<BQ")
_MESSAGE_HEADER = struct.Struct("<BQHIQQ")  # opcode, record length, channel id, sequence, log time, publish time
#: the message record's fields before its data: channel id, sequence, log time, publish time
MESSAGE_FIXED = 2 + 4 + 8 + 8
#: the chunk record's fields before its compression and records: message start and end times, uncompressed size
#: and CRC
CHUNK_FIXED = 8 + 8 + 8 + 4
_IOV_MAX = 1024


def _record_bytes(record) -> bytes:
    b = RecordBuilder()
    record.write(b)
    return b.end()


class ChunkWriter:
    """MCAP to a file descriptor; the subset of ``mcap.writer.Writer``'s interface the recorder uses.

    ``fd``: an open, writable file descriptor positioned at 0 (the caller opens and closes it).
    ``compression``: ``"none"``, ``"lz4"`` or ``"zstd"``.  :attr:`position` is the file offset written so
    far.  Not thread-safe (one writer thread)."""

    def __init__(self, fd: int, chunk_size: int = 1024 * 1024, compression: str = "none", enable_crcs: bool = False):
        if compression not in ("none", "lz4", "zstd"):
            raise ValueError(f"compression: expected none, lz4 or zstd, got {compression!r}")
        self._fd = fd
        self._chunk_size = int(chunk_size)
        self._compression = compression
        self._crcs = bool(enable_crcs)
        self.position = 0
        self._small = bytearray()  # records outside chunks not yet written
        self._schemas: OrderedDict[int, Schema] = OrderedDict()
        self._channels: OrderedDict[int, Channel] = OrderedDict()
        self._metadata_indexes: list[MetadataIndex] = []
        self._chunk_indexes: list[ChunkIndex] = []
        self._stats = Statistics(
            attachment_count=0,
            channel_count=0,
            channel_message_counts=defaultdict(int),
            chunk_count=0,
            message_count=0,
            metadata_count=0,
            message_start_time=0,
            message_end_time=0,
            schema_count=0,
        )
        self._reset_chunk()

    # ------------------------------------------------------------------ chunk in progress

    def _reset_chunk(self) -> None:
        self._pieces: list = []  # the chunk's records: bytes and buffers, in order
        self._tail = bytearray()  # small pieces being coalesced (written as one iovec)
        self._count = 0  # uncompressed bytes of the chunk's records
        self._n_messages = 0
        self._start_t = 0
        self._end_t = 0
        self._indices: dict[int, list] = {}  # channel id -> [(log time, offset in chunk)], first-seen order
        self._chunk_schemas: list[int] = []  # schemas and channels whose records this chunk holds (first written)
        self._chunk_channels: list[int] = []

    def _append(self, buf) -> None:
        n = len(buf) if isinstance(buf, (bytes, bytearray)) else memoryview(buf).nbytes
        if n < 4096:
            self._tail += buf
        else:
            if self._tail:
                self._pieces.append(bytes(self._tail))
                self._tail = bytearray()
            self._pieces.append(buf)
        self._count += n

    def _chunk_buffers(self) -> list:
        if self._tail:
            self._pieces.append(bytes(self._tail))
            self._tail = bytearray()
        return self._pieces

    # ------------------------------------------------------------------ output

    def _write(self, buffers: Sequence) -> None:
        """All of ``buffers``, in order, at the current position (``writev``, retried on a short write).  A write
        that fails part-way (a full disk: a short write, then ENOSPC) is undone -- the file cut back to where this
        write began -- before the error is raised: the file always ends at a whole record, so it stays readable
        (and :mod:`onboard.app.record_recover` completes it) whatever happens after."""
        bufs = [memoryview(b).cast("B") for b in buffers if len(memoryview(b).cast("B"))]
        start = self.position
        i = 0
        try:
            while i < len(bufs):
                n = os.writev(self._fd, bufs[i : i + _IOV_MAX])
                self.position += n
                while i < len(bufs) and n >= bufs[i].nbytes:
                    n -= bufs[i].nbytes
                    i += 1
                if n:
                    bufs[i] = bufs[i][n:]
        except OSError:
            if self.position != start:
                try:
                    os.ftruncate(self._fd, start)
                    os.lseek(self._fd, start, os.SEEK_SET)
                    self.position = start
                except OSError:
                    pass  # position still says where the file ends
            raise

    def _flush_small(self) -> None:
        if self._small:
            self._write([bytes(self._small)])
            self._small = bytearray()  # kept until written: a failed write may be retried by finish()

    def discard_chunk(self) -> dict[int, int]:
        """Forget the chunk in progress (its messages will not be written: the disk refused it); returns its
        message count per channel id, taken out of the summary's statistics too."""
        lost: dict[int, int] = {cid: len(records) for cid, records in self._indices.items()}
        st = self._stats
        for cid, n in lost.items():
            st.channel_message_counts[cid] -= n
            if st.channel_message_counts[cid] <= 0:
                del st.channel_message_counts[cid]
            st.message_count -= n
        # the statistics' time span shrinks to the chunks written
        if self._chunk_indexes:
            st.message_start_time = min(c.message_start_time for c in self._chunk_indexes)
            st.message_end_time = max(c.message_end_time for c in self._chunk_indexes)
        else:
            st.message_start_time = st.message_end_time = 0
        # a schema or channel whose one record was in this chunk is in no data section now: the summary must not
        # list it either (MCAP: its Schema and Channel records duplicate the data section's)
        for sid in self._chunk_schemas:
            del self._schemas[sid]
            st.schema_count -= 1
        for cid in self._chunk_channels:
            del self._channels[cid]
            st.channel_count -= 1
        self._reset_chunk()
        return lost

    # ------------------------------------------------------------------ the Writer's interface

    def start(self, profile: str = "", library: str = "") -> None:
        self._small += MCAP_MAGIC
        self._small += _record_bytes(Header(profile, library))
        self._flush_small()

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._flush_small()
        rec = _record_bytes(Metadata(name=name, metadata=data))
        self._metadata_indexes.append(MetadataIndex(offset=self.position, length=len(rec), name=name))
        self._stats.metadata_count += 1
        self._small += rec
        self._flush_small()

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        sid = len(self._schemas) + 1
        schema = Schema(id=sid, data=data, encoding=encoding, name=name)
        self._schemas[sid] = schema
        self._stats.schema_count += 1
        self._chunk_schemas.append(sid)
        self._append(_record_bytes(schema))
        self._maybe_finalize_chunk()
        return sid

    def register_channel(self, topic: str, message_encoding: str, schema_id: int, metadata: dict | None = None) -> int:
        cid = len(self._channels) + 1
        channel = Channel(
            id=cid, topic=topic, message_encoding=message_encoding, schema_id=schema_id, metadata=dict(metadata or {})
        )
        self._channels[cid] = channel
        self._stats.channel_count += 1
        self._chunk_channels.append(cid)
        self._append(_record_bytes(channel))
        self._maybe_finalize_chunk()
        return cid

    def add_message(self, channel_id: int, log_time: int, data: Any, publish_time: int, sequence: int = 0) -> None:
        """``data``: bytes, or a list/tuple of buffers that make the message's data when concatenated
        (each kept by reference until its chunk is written: it must not change before)."""
        if isinstance(data, (bytes, bytearray)):
            parts, size = None, len(data)
        else:
            parts = (data,) if isinstance(data, memoryview) else tuple(data)
            size = sum(len(p) if isinstance(p, (bytes, bytearray)) else memoryview(p).nbytes for p in parts)
        st = self._stats
        if st.message_count == 0:
            st.message_start_time = log_time
        elif log_time < st.message_start_time:
            st.message_start_time = log_time
        if log_time > st.message_end_time:
            st.message_end_time = log_time
        st.channel_message_counts[channel_id] += 1
        st.message_count += 1
        if self._n_messages == 0 or log_time < self._start_t:
            self._start_t = log_time
        if log_time > self._end_t:
            self._end_t = log_time
        index = self._indices.get(channel_id)
        if index is None:
            index = self._indices[channel_id] = []
        index.append((log_time, self._count))
        self._n_messages += 1
        head = _MESSAGE_HEADER.pack(Opcode.MESSAGE, MESSAGE_FIXED + size, channel_id, sequence, log_time, publish_time)
        if parts is None and size < 4096:  # the common small message: into the coalescing buffer
            self._tail += head
            self._tail += data
            self._count += len(head) + size
        else:
            self._append(head)
            for p in (data,) if parts is None else parts:
                self._append(p)
        if self._count > self._chunk_size:
            self._finalize_chunk()

    def flush(self) -> None:
        """Finish the chunk in progress (if it has a message) and write everything."""
        self._finalize_chunk()
        self._flush_small()

    def finish(self) -> None:
        """The last chunk, the data end, the summary and the footer (the caller closes the descriptor)."""
        self._finalize_chunk()
        self._small += _record_bytes(DataEnd(0))
        self._flush_small()
        summary_start = self.position
        b = RecordBuilder()
        offsets: list[SummaryOffset] = []

        def group(opcode, records) -> None:
            start = b.count
            for r in records:
                r.write(b)
            offsets.append(
                SummaryOffset(group_opcode=opcode, group_start=summary_start + start, group_length=b.count - start)
            )

        group(Opcode.SCHEMA, self._schemas.values())
        group(Opcode.CHANNEL, self._channels.values())
        group(Opcode.STATISTICS, [self._stats])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.ATTACHMENT_INDEX, [])
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
        summary_offset_start = summary_start + b.count
        for o in offsets:
            o.write(b)
        summary = b.end()
        crc = 0
        if self._crcs:
            crc = zlib.crc32(summary)
            crc = zlib.crc32(
                struct.pack(
                    "<BQQQ", Opcode.FOOTER, 8 + 8 + 4, 0 if not summary else summary_start, summary_offset_start
                ),
                crc,
            )
        footer = _record_bytes(
            Footer(
                summary_start=0 if not summary else summary_start,
                summary_offset_start=summary_offset_start,
                summary_crc=crc,
            )
        )
        self._write([summary, footer, MCAP_MAGIC])

    # ------------------------------------------------------------------ chunks

    def _maybe_finalize_chunk(self) -> None:
        if self._count > self._chunk_size:
            self._finalize_chunk()

    def _finalize_chunk(self) -> None:
        if self._n_messages == 0:
            return  # schemas and channels stay in the next chunk, as the package does
        pieces = self._chunk_buffers()
        uncompressed = self._count
        crc = 0
        if self._crcs:
            for p in pieces:
                crc = zlib.crc32(p, crc)
        if self._compression == "none":
            compression, body = "", pieces
        else:
            joined = b"".join(pieces)
            if self._compression == "lz4":
                import lz4.frame

                compression, body = "lz4", [lz4.frame.compress(joined)]
            else:
                import zstandard

                compression, body = "zstd", [zstandard.compress(joined)]
        body_len = sum(memoryview(p).nbytes for p in body)
        comp = compression.encode()
        head_fields = (
            struct.pack("<QQQI", self._start_t, self._end_t, uncompressed, crc)
            + struct.pack("<I", len(comp))
            + comp
            + struct.pack("<Q", body_len)
        )
        head = struct.pack("<BQ", Opcode.CHUNK, len(head_fields) + body_len) + head_fields
        self._flush_small()
        chunk_start = self.position
        chunk_length = len(head) + body_len
        index_start = chunk_start + chunk_length
        b = RecordBuilder()
        offsets = {}
        for cid, records in self._indices.items():
            offsets[cid] = index_start + b.count
            MessageIndex(channel_id=cid, records=records).write(b)
        index_bytes = b.end()
        self._write([head, *body, index_bytes])
        self._stats.chunk_count += 1
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=self._start_t,
                message_end_time=self._end_t,
                chunk_start_offset=chunk_start,
                chunk_length=chunk_length,
                message_index_offsets=offsets,
                message_index_length=len(index_bytes),
                compression=compression,
                compressed_size=body_len,
                uncompressed_size=uncompressed,
            )
        )
        self._reset_chunk()
