"""``python -m onboard.record_recover CUT.mcap WHOLE.mcap``: a recording cut short (a SIGKILLed daemon or
simulator, a power cut) rewritten as a complete, indexed MCAP file.

A recording is written chunk by chunk, its summary and footer last (:mod:`onboard.io.record`): a file whose writer
was killed has whole records up to its last finished chunk, then part of one, and no footer.  A streaming reader
(``mcap.stream_reader.StreamReader``, :mod:`onboard.app.replay`) reads it; the indexed reader most tools open
(``mcap.reader.make_reader(f).iter_messages()``, Foxglove) reads the footer first and refuses it.

This reads the input's records through :class:`onboard.io.mcap_read.RecordWalk` (each read within its own length
from the header on, up to the footer or the first that runs past the end of the file), and writes them with the
package's writer: the header's profile and library, every schema, channel, metadata record and attachment, and
every message byte for byte (data, log time, publish time, sequence), in the input's order, into uncompressed
chunks with the full summary (chunk, metadata and attachment indexes, statistics).  The part-written record at the
end is left out (a chunk: the messages it held are lost).  A complete input is rewritten the same way.

The output is written to a temporary file beside ``OUT`` and renamed over it once finished
(:mod:`onboard.app.output_files`): an interrupted recovery (Ctrl-C, SIGTERM: one line, exit 130) leaves no
half-written ``OUT`` and no temporary file.

Damage is told from a cut as :mod:`onboard.io.mcap_read` tells it: a record that runs past the end of a file
without its footer is where it was cut; anything else a reader cannot take is damage -- a record that cannot be read
within its length, one where the MCAP specification puts no such record (a summary record, a second header, an
opcode no record has or a private one before the data end record; a data record after it), a chunk holding another
record than a schema, channel or message or whose message indexes disagree with it, a summary that counts other
messages or chunks than the data section holds (its structure: the recorder writes chunks without CRCs, so a
flipped bit inside a message's data is not seen).  A damaged input is refused unless ``--skip-damaged``: then a
finished file whose data section is damaged is recovered chunk by chunk through its summary's chunk index (a
damaged chunk left out, the others kept), one whose summary alone is damaged keeps every record of its data
section (the writer makes a new summary), any other is kept up to the damage; each part left out is said on
stderr (exit 3).

Refused, with one line naming the file (exit 2): an input that cannot be read, is not MCAP (its first bytes are
not the magic), is cut before its header record or before its first message (inside its first chunk), holds no
message, or is damaged (without ``--skip-damaged``; with it, when no message is left); ``OUT`` naming the input
(the cut original is kept), a folder, a device or a pipe, or a file that exists and is not empty (a recovery never
writes over one; an empty one is taken).  No ``OUT`` is written when refused.  Exit 1: ``OUT`` cannot be written.
Exit 0: recovered, with one line on stdout saying what; exit 3: recovered with damaged parts left out; exit 130:
interrupted (Ctrl-C or SIGTERM), nothing written.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, BinaryIO

from mcap.opcode import Opcode
from mcap.records import Header, Message

from onboard.app.cli_args import OneLineParser, sigterm_as_interrupt
from onboard.app.output_files import create_beside, output_target, same_file_clash
from onboard.core.errors import InputError
from onboard.io.mcap_chunks import MCAP_MAGIC, RECORD_HEAD
from onboard.io.mcap_read import (
    KNOWN_OPCODES,
    ChunkIndexCheck,
    RecordDamage,
    RecordWalk,
    chunk_records,
    footer_intact,
    read_record,
    record_name,
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
    (:class:`~onboard.io.mcap_read.RecordWalk` tells which)."""
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


def _summary(f: BinaryIO) -> Any:
    """The file's summary (``mcap.reader``'s) when it can guide a recovery chunk by chunk: it indexes chunks, as many
    as its statistics count; else None (none, or it cannot be read: damaged too)."""
    from mcap.reader import make_reader

    try:
        f.seek(0)
        summary = make_reader(f).get_summary()
    except Exception:  # noqa: BLE001 - a damaged summary: the records before the damage are read instead
        return None
    if summary is None or not summary.chunk_indexes:
        return None
    if summary.statistics is not None and summary.statistics.chunk_count != len(summary.chunk_indexes):
        return None
    return summary


def _indexed_chunk(f: BinaryIO, ci: Any) -> tuple[list, str | None]:
    """The records of the chunk ``ci`` (a chunk index) points at, read alone and checked by the message indexes after
    it, and what is wrong with those indexes when they cannot check it (a record among them that is not one, or
    cannot be read, or a channel without one): the chunk is whole, its indexes are not, and the writer makes new ones.
    :class:`RecordDamage` when the chunk is not there or its indexes disagree with it."""
    start = ci.chunk_start_offset
    head = os.pread(f.fileno(), RECORD_HEAD.size, start)
    opcode, length = RECORD_HEAD.unpack(head) if len(head) == RECORD_HEAD.size else (0, 0)
    if opcode != Opcode.CHUNK or RECORD_HEAD.size + length != ci.chunk_length:
        raise RecordDamage(f"not the chunk its index says ({record_name(opcode)} at byte {start})", start)
    records = chunk_records(read_record(f, start, opcode, length), start)
    check = ChunkIndexCheck(records, start)
    pos, stop = start + ci.chunk_length, start + ci.chunk_length + ci.message_index_length
    while pos < stop:
        head = os.pread(f.fileno(), RECORD_HEAD.size, pos)
        opcode, length = RECORD_HEAD.unpack(head) if len(head) == RECORD_HEAD.size else (0, stop)
        if opcode != Opcode.MESSAGE_INDEX:
            return records, f"its message indexes: {record_name(opcode)} at byte {pos}, not a message index"
        if pos + RECORD_HEAD.size + length > stop:
            return (
                records,
                f"its message indexes: the one at byte {pos} runs past their {ci.message_index_length} bytes",
            )
        try:
            index = read_record(f, pos, opcode, length)
        except RecordDamage as exc:
            return records, f"its message indexes: {exc.what}"
        check.add(index, pos)
        pos += RECORD_HEAD.size + length
    return records, check.unindexed()


def _indexed(f: BinaryIO, summary: Any, output: _Output, dropped: list[str]) -> None:
    """Every chunk the summary indexes, each read and checked alone: one that cannot be read is left out and said in
    ``dropped``, the others written (one whose message indexes alone are damaged too, said); then the metadata and
    attachments it indexes.  For a finished file: its summary says where every chunk is, so damage costs the chunks
    it hit, not the rest of the file."""
    # the chunks' own schema and channel records first; the summary's copies (damage there goes unnoticed by any
    # reader) only for a channel no chunk declared
    output.summary_schemas, output.summary_channels = dict(summary.schemas), dict(summary.channels)
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    for k, ci in enumerate(chunks, start=1):
        where = (
            f"chunk {k} of {len(chunks)} at byte {ci.chunk_start_offset} (log times {ci.message_start_time} to "
            f"{ci.message_end_time} ns)"
        )
        try:
            records, indexes_damaged = _indexed_chunk(f, ci)
        except RecordDamage as exc:
            dropped.append(f"{where} left out: {exc.what.removeprefix(f'the chunk at byte {ci.chunk_start_offset}: ')}")
            continue
        if indexes_damaged is not None:
            n = sum(isinstance(r, Message) for r in records)
            dropped.append(f"{where}: kept ({n} messages) without the check of {indexes_damaged}")
        try:
            for record in records:
                output.add(record)
        except KeyError as exc:  # a channel or schema neither the chunk nor the summary declares
            dropped.append(
                f"chunk {k} of {len(chunks)} at byte {ci.chunk_start_offset}: the records from one naming id "
                f"{exc.args[0]!r}, which neither it nor the summary declares, left out"
            )
    indexed = [("the metadata record", i, Opcode.METADATA) for i in summary.metadata_indexes]
    indexed += [("the attachment", i, Opcode.ATTACHMENT) for i in summary.attachment_indexes]
    for what, index, kind in indexed:  # each record its index points at, read alone
        try:
            head = os.pread(f.fileno(), RECORD_HEAD.size, index.offset)
            opcode, length = RECORD_HEAD.unpack(head) if len(head) == RECORD_HEAD.size else (0, 0)
            if opcode != kind or RECORD_HEAD.size + length != index.length:
                raise RecordDamage(f"{record_name(opcode)} of {RECORD_HEAD.size + length} bytes there", index.offset)
            output.add(read_record(f, index.offset, opcode, length))
        except RecordDamage as exc:
            dropped.append(f"{what} {index.name!r} at byte {index.offset} left out: {exc.what}")


def recover(src: str, dst_fd: int, skip_damaged: bool = False) -> Recovered:
    """Stream ``src``'s whole records into a complete MCAP file written to the open descriptor ``dst_fd`` (closed
    here).  Raises :class:`InputError` (one line naming ``src``) for an input it refuses (module docstring).  With
    ``skip_damaged`` a damaged input is recovered but for its damage (``Recovered.dropped`` says what was left out):
    a finished file chunk by chunk through its summary (damage in the summary alone costs nothing but it: the data
    section read is kept), any other up to the damage."""
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
        walk = RecordWalk(f, src)
        dropped: list[str] = []
        output: _Output | None = None
        header = None
        readable = size
        try:
            for top in walk:
                if isinstance(top.record, Header):
                    header = top.record
                    output = _Output(out, header.profile, header.library)
                    continue
                assert output is not None
                for record in top.records:
                    output.add(record)
        except RecordDamage as exc:
            if header is None or not skip_damaged:
                raise InputError(f"{src}: damaged: {exc.what}{_SKIP_HINT if header else ''}") from None
            # a finished file whose data section is damaged: its summary says where every chunk is
            summary = None if exc.in_summary or not footer_intact(f, size) else _summary(f)
            if summary is not None:
                out.seek(0)
                out.truncate()
                output = _Output(out, header.profile, header.library)
                _indexed(f, summary, output, dropped)
                if not dropped:
                    dropped.append(f"{exc.what}: every chunk its summary indexes read whole")
            elif exc.in_summary:
                dropped.append(f"its summary, from byte {exc.at} (a new one is written): {exc.what}")
            else:
                dropped.append(f"from byte {exc.at} to the end ({size - exc.at} bytes) left out: {exc.what}")
                readable = exc.at
        except KeyError as exc:
            raise InputError(
                f"{src}: not a readable MCAP file (a record names {exc.args[0]!r}, which no earlier record defines)"
            ) from None
        if header is None or output is None:
            raise InputError(f"{src}: cut short before its header record ({size} bytes): nothing to recover")
        complete = walk.complete or footer_intact(f, size)
        if output.messages == 0:  # a file of no message is no recovery: said as a cut before the header is
            if dropped:
                what = f"damaged, no message readable ({dropped[0]})"
            elif complete:
                what = f"holds no message ({size} bytes, with its footer)"
            else:
                whole = walk.cut_at if walk.cut_at is not None else readable
                what = f"cut short before its first message ({size} bytes; its whole records end at byte {whole})"
            raise InputError(f"{src}: {what}: nothing to recover")
        output.writer.finish()
    return Recovered(
        output.messages,
        len(output.channel_ids),
        len(output.schema_ids) - 1,
        output.metadata,
        output.attachments,
        walk.cut_at if walk.cut_at is not None else readable,
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
        "the input refused (not MCAP, damaged, unreadable, no message to recover) or a bad OUT (one that exists and "
        "is not empty is never written over), 1 OUT cannot be written.",
    )
    p.add_argument("input", metavar="IN.mcap", help="the recording cut short (python -m onboard --record ...)")
    p.add_argument("output", metavar="OUT.mcap", help="the complete file to write (written beside, then renamed)")
    p.add_argument(
        "--skip-damaged",
        action="store_true",
        help="recover a damaged input but for its damage: a finished file chunk by chunk (a damaged chunk left out; "
        "damage in its summary alone costs no message: a new one is written), any other up to the damage; what was "
        "left out is said on stderr (exit 3)",
    )
    return p


def _refuse_existing(dst: str, target: str) -> None:
    """:class:`InputError` when ``target`` (the file ``dst`` names) holds anything: a recovery never replaces a file,
    as the daemon never records over one, because OUT is as likely an earlier recording as a stale recovery.  An
    empty file is taken (one made ready for the output)."""
    try:
        size = os.stat(target).st_size
    except OSError:
        return
    if size > 0:
        raise InputError(f"{dst}: exists already ({size} bytes); give a new file or remove it first")


def _output_target(src: str, dst: str) -> str:
    """The file ``dst`` names (through a symbolic link); :class:`InputError` when it cannot be written by a
    rename, is the input itself or exists and is not empty."""
    target, refused = output_target(dst)
    if refused is not None:
        raise InputError(f"{dst}: {refused}")
    clash = same_file_clash([("OUT.mcap", dst)], [("IN.mcap", src)])
    if clash is not None:
        raise InputError(f"{clash} (the cut original is kept)")
    _refuse_existing(dst, target)
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
            _refuse_existing(args.output, target)  # a file made there while this recovery ran is kept too
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
