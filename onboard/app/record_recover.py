"""``python -m onboard.record_recover CUT.mcap WHOLE.mcap``: a recording cut short (a SIGKILLed daemon or
simulator, a power cut) rewritten as a complete, indexed MCAP file.

A recording is written chunk by chunk, its summary and footer last (:mod:`onboard.io.record`): a file whose writer
was killed has whole records up to its last finished chunk, then part of one, and no footer.  A streaming reader
(``mcap.stream_reader.StreamReader``, :mod:`onboard.app.replay`) reads it; the indexed reader most tools open
(``mcap.reader.make_reader(f).iter_messages()``, Foxglove) reads the footer first and refuses it.

This reads the input's whole records (:func:`whole_length`: each record's length walked from the header on, up to
the first that runs past the end of the file) with the `mcap` package's stream reader, and writes them with the
package's writer: the header's profile and library, every schema, channel, metadata record and attachment, and
every message byte for byte (data, log time, publish time, sequence), in the input's order, into uncompressed
chunks with the full summary (chunk, metadata and attachment indexes, statistics).  The part-written record at the
end is left out (a chunk: the messages it held are lost).  A complete input is rewritten the same way.

The output is written to a temporary file beside ``OUT`` and renamed over it once finished
(:mod:`onboard.app.output_files`): an interrupted recovery (Ctrl-C, SIGTERM: one line, exit 130) leaves no
half-written ``OUT`` and no temporary file.

Damage is told from a cut (:func:`onboard.io.mcap_read.damage_at`): a file that ends with its footer was not cut;
a record whose opcode no MCAP record has, or that fits in the file yet cannot be read, is damage (its structure:
the recorder writes chunks without CRCs, so a flipped bit inside a message's data is not seen); so is a chunk
holding another record than a schema, channel or message, or one whose records run past it, or whose message
indexes count other messages than it holds (:class:`onboard.io.mcap_read.ChunkIndexCheck`).  A damaged input is
refused unless ``--skip-damaged``: then a finished file is recovered chunk by chunk through its summary's chunk
index (a damaged chunk left out, the others kept), any other up to the damage, and each part left out is said on
stderr (exit 3).

Refused, with one line naming the file (exit 2): an input that cannot be read, is not MCAP (its first bytes are
not the magic), is cut before its header record, or is damaged (without ``--skip-damaged``); ``OUT`` naming the
input (the cut original is kept), a folder, a device or a pipe.  Exit 1: ``OUT`` cannot be written.  Exit 0:
recovered, with one line on stdout saying what; exit 3: recovered with damaged parts left out; exit 130:
interrupted (Ctrl-C or SIGTERM), nothing written.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import os
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any, BinaryIO

from onboard.app.cli_args import OneLineParser, sigterm_as_interrupt
from onboard.app.output_files import create_beside, output_target, same_file_clash
from onboard.core.errors import InputError
from onboard.io.mcap_chunks import MCAP_MAGIC, RECORD_HEAD
from onboard.io.mcap_read import (
    KNOWN_OPCODES,
    ChunkIndexCheck,
    chunk_records,
    damage_at,
    footer_intact,
    record_overran,
)

__all__ = ["Recovered", "whole_length", "recover", "build_parser", "main"]

EXIT_OK, EXIT_OUTPUT, EXIT_INPUT, EXIT_DROPPED, EXIT_INTERRUPTED = 0, 1, 2, 3, 130
_OPCODE_FOOTER = 0x02
_OPCODE_DATA_END = 0x0F
_SKIP_HINT = "; --skip-damaged recovers the rest"


@dataclass(frozen=True)
class Recovered:
    """What :func:`recover` wrote.  ``whole_bytes``: where the input's last whole record ends (its size when
    ``complete``); ``complete``: the input had its footer."""

    messages: int
    channels: int
    schemas: int
    metadata: int
    attachments: int
    whole_bytes: int
    size_bytes: int
    complete: bool
    dropped: tuple[str, ...] = ()


def whole_length(f: BinaryIO, size: int) -> tuple[int, bool]:
    """``(end, complete)``: the offset where the last whole record of the MCAP stream ``f`` (``size`` bytes,
    positioned anywhere) ends, walking each record's ``(opcode, length)`` from the header on; ``complete`` when it
    ends with its footer and the closing magic (then ``end`` is ``size``).  The walk stops before a record whose
    length runs past the end of the file or whose opcode no MCAP record has: where the file was cut, or damaged
    (:func:`~onboard.io.mcap_read.damage_at` tells which)."""
    pos = len(MCAP_MAGIC)
    while pos + RECORD_HEAD.size <= size:
        f.seek(pos)
        opcode, length = RECORD_HEAD.unpack(f.read(RECORD_HEAD.size))
        end = pos + RECORD_HEAD.size + length
        if end > size or (opcode not in KNOWN_OPCODES and opcode < 0x80):
            break
        if opcode == _OPCODE_FOOTER:
            f.seek(end)
            if end + len(MCAP_MAGIC) == size and f.read(len(MCAP_MAGIC)) == MCAP_MAGIC:
                return size, True
            return end, False
        pos = end
    return pos, False


class _Prefix:
    """The first ``limit`` bytes of ``f`` as a stream (``read`` only): the reader sees a file that ends where the
    last whole record does.  ``count``: the bytes read so far (where the next record starts, between two)."""

    def __init__(self, f: BinaryIO, limit: int) -> None:
        self._f, self._left = f, limit
        self.count = 0

    def read(self, n: int = -1) -> bytes:
        if n < 0 or n > self._left:
            n = self._left
        data = self._f.read(n)
        self._left -= len(data)
        self.count += len(data)
        return data


class _Damaged(Exception):
    """A part of the input that cannot be read: ``what`` says which and why, ``at`` the byte it starts at."""

    def __init__(self, what: str, at: int) -> None:
        super().__init__(what)
        self.what, self.at = what, at


class _Output:
    """The recovered file: the `mcap` package's writer, with the input's schema and channel ids mapped to its own."""

    def __init__(self, out: BinaryIO, profile: str, library: str) -> None:
        from mcap.writer import CompressionType, Writer

        self.writer = Writer(out, compression=CompressionType.NONE)
        self.writer.start(profile=profile, library=library)
        self.schema_ids: dict[int, int] = {0: 0}
        self.channel_ids: dict[int, int] = {}
        self.messages = self.metadata = self.attachments = 0
        # the summary's schemas and channels (a finished file's), for a message whose chunk did not declare them
        self.summary_schemas: dict[int, Any] = {}
        self.summary_channels: dict[int, Any] = {}

    def add(self, record: Any) -> None:
        from mcap.records import Attachment, Channel, Message, Metadata, Schema

        w = self.writer
        if isinstance(record, Schema):
            if record.id not in self.schema_ids:
                self.schema_ids[record.id] = w.register_schema(record.name, record.encoding, record.data)
        elif isinstance(record, Channel):
            if record.id not in self.channel_ids:
                self.channel_ids[record.id] = w.register_channel(
                    record.topic, record.message_encoding, self.schema_ids[record.schema_id], dict(record.metadata)
                )
        elif isinstance(record, Message):
            if record.channel_id not in self.channel_ids and record.channel_id in self.summary_channels:
                channel = self.summary_channels[record.channel_id]
                if channel.schema_id not in self.schema_ids and channel.schema_id in self.summary_schemas:
                    self.add(self.summary_schemas[channel.schema_id])
                self.add(channel)  # KeyError when its schema is nowhere either: the caller says what it left out
            w.add_message(
                self.channel_ids[record.channel_id], record.log_time, record.data, record.publish_time, record.sequence
            )
            self.messages += 1
        elif isinstance(record, Metadata):
            w.add_metadata(record.name, dict(record.metadata))
            self.metadata += 1
        elif isinstance(record, Attachment):
            w.add_attachment(record.create_time, record.log_time, record.name, record.media_type, record.data)
            self.attachments += 1


def _streamed(f: BinaryIO, end: int, src: str) -> Iterator[tuple[int, list]]:
    """The whole records of ``f`` up to ``end`` as ``(byte, records)``: a top-level record alone, or a chunk's records
    together once the message indexes after it have checked them (:class:`~onboard.io.mcap_read.ChunkIndexCheck`);
    :class:`_Damaged` at the first part that cannot be read."""
    from mcap.records import Chunk, Header, MessageIndex
    from mcap.stream_reader import StreamReader

    prefix = _Prefix(f, end)
    reader = StreamReader(prefix, emit_chunks=True).records  # type: ignore[arg-type]
    check = ChunkIndexCheck(src)
    pending: tuple[int, list] | None = None  # a chunk's records, held until its indexes are read
    seen_header = False
    while True:
        at = prefix.count
        index_failed = False
        try:
            record = next(reader, None)
            if record is None:
                break
            if isinstance(record, Header):
                seen_header = True
            elif not seen_header:
                raise InputError(f"{src}: not a readable MCAP file (a {type(record).__name__} before its header)")
            overran = record_overran(f, at, prefix.count)
            if overran is not None:
                raise InputError(f"{src}: damaged: {overran}")
            index_failed = True
            check.add(record, at)
            index_failed = False
            if isinstance(record, Chunk):
                records = chunk_records(record, f"{src}: the chunk at byte {at}")
                check.chunk(records, at)
        except InputError as exc:
            if seen_header and "damaged" in str(exc):
                what = str(exc).removeprefix(f"{src}: ").replace("damaged: ", "")
                if pending is not None and not index_failed:
                    # the chunk held back is whole and its indexes so far agree: the damage is after it
                    yield pending
                    pending = None
                raise _Damaged(what, pending[0] if pending else at) from None
            raise
        except Exception as exc:  # noqa: BLE001 - whatever the reader raised inside the whole records
            if type(exc).__name__ == "EndOfFile":
                # the whole records end between two records: read to the last (none before the header: the file is
                # cut inside it, which the caller says as such, not as damage)
                break
            if pending is not None:
                yield pending
                pending = None
            raise _Damaged(f"the record at byte {at} cannot be read: {type(exc).__name__}: {exc}", at) from None
        if isinstance(record, MessageIndex):
            continue
        if pending is not None:
            yield pending
            pending = None
        if isinstance(record, Chunk):
            pending = (at, records)
        else:
            yield at, [record]
    if pending is not None:
        yield pending


def _summary(f: BinaryIO) -> Any:
    """The file's summary (``mcap.reader``'s), or None when it has none or it cannot be read (damaged too)."""
    from mcap.reader import make_reader

    try:
        f.seek(0)
        return make_reader(f).get_summary()
    except Exception:  # noqa: BLE001 - a damaged summary: the records before the damage are read instead
        return None


def _indexed(f: BinaryIO, src: str, summary: Any, output: _Output, dropped: list[str]) -> None:
    """Every chunk the summary indexes, each read and checked alone: one that cannot be read is left out and said in
    ``dropped``, the others written; then the metadata and attachments it indexes.  For a finished file: its summary
    says where every chunk is, so damage costs the chunks it hit, not the rest of the file."""
    import io

    from mcap.exceptions import EndOfFile
    from mcap.records import Chunk, MessageIndex
    from mcap.stream_reader import StreamReader

    # the chunks' own schema and channel records first; the summary's copies (damage there goes unnoticed by any
    # reader) only for a channel no chunk declared
    output.summary_schemas, output.summary_channels = dict(summary.schemas), dict(summary.channels)
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    for k, ci in enumerate(chunks, start=1):
        size = ci.chunk_length + ci.message_index_length
        raw = os.pread(f.fileno(), size, ci.chunk_start_offset)
        where = f"{src}: the chunk at byte {ci.chunk_start_offset}"
        check = ChunkIndexCheck(where)
        try:
            stream = io.BytesIO(raw)
            records: list = []
            reader = StreamReader(stream, skip_magic=True, emit_chunks=True).records
            with contextlib.suppress(EndOfFile):
                for i in itertools.count():
                    at = ci.chunk_start_offset + stream.tell()
                    record = next(reader, None)
                    if record is None:
                        break
                    if i == 0:
                        if not isinstance(record, Chunk) or stream.tell() != ci.chunk_length:
                            raise InputError(f"{where}: damaged: not the chunk its index says")
                        records = chunk_records(record, where)
                        check.chunk(records, ci.chunk_start_offset)
                    elif isinstance(record, MessageIndex):
                        check.add(record, at)
            if len(raw) != size or not records and ci.message_index_offsets:
                raise InputError(f"{where}: damaged: cut short")
        except Exception as exc:  # noqa: BLE001 - whatever this chunk's bytes raise: it alone is left out
            why = (
                str(exc).removeprefix(f"{where}: ").replace("damaged: ", "")
                if isinstance(exc, InputError)
                else f"{type(exc).__name__}: {exc}"
            )
            dropped.append(
                f"chunk {k} of {len(chunks)} at byte {ci.chunk_start_offset} (log times {ci.message_start_time} to "
                f"{ci.message_end_time} ns) left out: {why}"
            )
            continue
        try:
            for record in records:
                output.add(record)
        except KeyError as exc:  # a channel or schema neither the chunk nor the summary declares
            dropped.append(
                f"chunk {k} of {len(chunks)} at byte {ci.chunk_start_offset}: the records from one naming id "
                f"{exc.args[0]!r}, which neither it nor the summary declares, left out"
            )
    indexed = [("the metadata record", i) for i in summary.metadata_indexes]
    indexed += [("the attachment", i) for i in summary.attachment_indexes]
    for what, index in indexed:  # each record its index points at, read alone
        try:
            raw = os.pread(f.fileno(), index.length, index.offset)
            output.add(next(StreamReader(io.BytesIO(raw), skip_magic=True).records))
        except Exception as exc:  # noqa: BLE001 - whatever these bytes raise: this record alone is left out
            dropped.append(f"{what} {index.name!r} at byte {index.offset} left out: {type(exc).__name__}: {exc}")


def recover(src: str, dst_fd: int, skip_damaged: bool = False) -> Recovered:
    """Stream ``src``'s whole records into a complete MCAP file written to the open descriptor ``dst_fd`` (closed
    here).  Raises :class:`InputError` (one line naming ``src``) for an input it refuses (module docstring).  With
    ``skip_damaged`` a damaged input is recovered but for its damage (``Recovered.dropped`` says what was left out):
    a finished file chunk by chunk through its summary, any other up to the damage."""
    from mcap.records import DataEnd, Header

    try:
        f = open(src, "rb")
    except OSError as exc:
        os.close(dst_fd)
        raise InputError(f"{src}: cannot read: {exc.strerror or exc}") from None
    with f, os.fdopen(dst_fd, "wb") as out:
        size = os.fstat(f.fileno()).st_size
        head = f.read(len(MCAP_MAGIC))
        if head != MCAP_MAGIC:
            what = "the file is empty" if not head else f"it starts with {head!r}, not the MCAP magic"
            raise InputError(f"{src}: not an MCAP file ({what})")
        end, complete = whole_length(f, size)
        damage = None if complete else damage_at(f, size, end)
        if damage is not None and not skip_damaged:
            raise InputError(f"{src}: damaged: {damage}{_SKIP_HINT}")
        dropped: list[str] = []
        output: _Output | None = None
        finished = footer_intact(f, size)
        # a finished file is recovered chunk by chunk through its summary's index (damage costs the chunks it hit)
        summary = _summary(f) if skip_damaged and finished else None
        f.seek(0)
        header = None
        try:
            for _at, records in _streamed(f, end, src):
                if isinstance(records[0], Header):
                    header = records[0]
                    if summary is not None and summary.chunk_indexes:
                        break  # a finished file: read chunk by chunk through its summary, below
                    output = _Output(out, header.profile, header.library)
                    continue
                if isinstance(records[0], DataEnd):
                    break  # the summary section follows: the writer makes its own
                assert output is not None
                for record in records:
                    output.add(record)
        except _Damaged as exc:
            if not skip_damaged:
                raise InputError(f"{src}: damaged: {exc.what}{_SKIP_HINT}") from None
            dropped.append(f"from byte {exc.at} to the end ({size - exc.at} bytes) left out: {exc.what}")
        except KeyError as exc:
            raise InputError(
                f"{src}: not a readable MCAP file (a record names {exc.args[0]!r}, which no earlier record defines)"
            ) from None
        if header is None:
            raise InputError(f"{src}: cut short before its header record ({size} bytes): nothing to recover")
        if output is None:  # skip_damaged on a finished file
            output = _Output(out, header.profile, header.library)
            _indexed(f, src, summary, output, dropped)
        elif damage is not None:
            dropped.append(f"from byte {end} to the end ({size - end} bytes) left out: {damage}")
        output.writer.finish()
        complete = complete or finished
    return Recovered(
        output.messages,
        len(output.channel_ids),
        len(output.schema_ids) - 1,
        output.metadata,
        output.attachments,
        end,
        size,
        complete,
        tuple(dropped),
    )


# --------------------------------------------------------------------------- entry point


class _Parser(OneLineParser):
    error_format = "error: {prog}: {message}"


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="python -m onboard.record_recover",
        description="Rewrite an MCAP recording cut short (SIGKILL, power cut) as a complete, indexed file: every "
        "whole record kept, messages byte for byte.",
        epilog="Exit 0 recovered, 3 recovered with damaged parts left out (--skip-damaged; each said on stderr), 2 "
        "the input refused (not MCAP, damaged, unreadable) or a bad OUT, 1 OUT cannot be written.",
    )
    p.add_argument("input", metavar="IN.mcap", help="the recording cut short (python -m onboard --record ...)")
    p.add_argument("output", metavar="OUT.mcap", help="the complete file to write (written beside, then renamed)")
    p.add_argument(
        "--skip-damaged",
        action="store_true",
        help="recover a damaged input but for its damage: a finished file chunk by chunk (a damaged chunk left out), "
        "any other up to the damage; what was left out is said on stderr (exit 3)",
    )
    return p


def _output_target(src: str, dst: str) -> str:
    """The file ``dst`` names (through a symbolic link); :class:`InputError` when it cannot be written by a
    rename or is the input itself."""
    target, refused = output_target(dst)
    if refused is not None:
        raise InputError(f"{dst}: {refused}")
    clash = same_file_clash([("OUT.mcap", dst)], [("IN.mcap", src)])
    if clash is not None:
        raise InputError(f"{clash} (the cut original is kept)")
    return target


def main(argv: Sequence[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:
        return int(exc.code) if isinstance(exc.code, int) else EXIT_INPUT
    try:
        target = _output_target(args.input, args.output)
        if not os.path.exists(args.input):  # refused before an output file is made
            raise InputError(f"{args.input}: cannot read: no such file")
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    try:
        tmp, fd = create_beside(target)
    except OSError as exc:
        print(f"error: cannot write {args.output}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_OUTPUT
    try:
        with sigterm_as_interrupt():
            result = recover(args.input, fd, skip_damaged=args.skip_damaged)
            os.replace(tmp, target)
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the half-written recovery goes, OUT stays as it was
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        print(f"interrupted: nothing written ({args.output} is as it was, or was not created)", file=sys.stderr)
        return EXIT_INTERRUPTED
    except InputError as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except OSError as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        print(f"error: cannot write {args.output}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_OUTPUT
    r = result
    cut = (
        f"complete already ({r.size_bytes} bytes, with its footer)"
        if r.complete
        else f"cut at byte {r.size_bytes}; its whole records end at byte {r.whole_bytes}"
    )
    if r.dropped and r.complete:
        cut = f"damaged ({r.size_bytes} bytes, with its footer)"
    elif r.dropped:
        cut = f"damaged or cut ({r.size_bytes} bytes); its readable records end at byte {r.whole_bytes}"
    print(
        f"{args.input}: {cut}; wrote {args.output}: {r.messages} messages on {r.channels} channels, "
        f"{r.schemas} schemas, {r.metadata} metadata records, {r.attachments} attachments"
    )
    for what in r.dropped:
        print(f"warning: {args.input}: {what}", file=sys.stderr)
    return EXIT_DROPPED if r.dropped else EXIT_OK
