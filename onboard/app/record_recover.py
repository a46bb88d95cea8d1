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
(:mod:`onboard.app.output_files`): an interrupted recovery leaves no half-written ``OUT``.

Refused, with one line naming the file (exit 2): an input that cannot be read, is not MCAP (its first bytes are
not the magic), is cut before its header record, or is damaged before its end (a record the reader cannot parse
that the end of the file does not explain); ``OUT`` naming the input (the cut original is kept), a folder, a
device or a pipe.  Exit 1: ``OUT`` cannot be written.  Exit 0: recovered, with one line on stdout saying what.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any, BinaryIO

from onboard.app.cli_args import OneLineParser
from onboard.app.output_files import create_beside, output_target, same_file_clash
from onboard.core.errors import InputError
from onboard.io.mcap_chunks import MCAP_MAGIC, RECORD_HEAD

__all__ = ["Recovered", "whole_length", "recover", "build_parser", "main"]

EXIT_OK, EXIT_OUTPUT, EXIT_INPUT = 0, 1, 2
_OPCODE_FOOTER = 0x02
_OPCODE_DATA_END = 0x0F


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


def whole_length(f: BinaryIO, size: int) -> tuple[int, bool]:
    """``(end, complete)``: the offset where the last whole record of the MCAP stream ``f`` (``size`` bytes,
    positioned anywhere) ends, walking each record's ``(opcode, length)`` from the header on; ``complete`` when it
    ends with its footer and the closing magic (then ``end`` is ``size``).  A record whose length runs past the end
    of the file is where the file was cut: ``end`` stops before it."""
    pos = len(MCAP_MAGIC)
    while pos + RECORD_HEAD.size <= size:
        f.seek(pos)
        opcode, length = RECORD_HEAD.unpack(f.read(RECORD_HEAD.size))
        end = pos + RECORD_HEAD.size + length
        if end > size:
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
    last whole record does."""

    def __init__(self, f: BinaryIO, limit: int) -> None:
        self._f, self._left = f, limit

    def read(self, n: int = -1) -> bytes:
        if n < 0 or n > self._left:
            n = self._left
        data = self._f.read(n)
        self._left -= len(data)
        return data


def _records(records: Iterator[Any], src: str) -> Iterator[Any]:
    """``records`` with each chunk's records in its place, a chunk checked whole first: every record in it must end
    within it and the last at its end (the package's ``breakup_chunk`` reads a record whose length runs past the
    chunk's end as one that holds the rest of the chunk, without an error: damage would lose messages unsaid)."""
    from mcap.records import Chunk
    from mcap.stream_reader import breakup_chunk, get_chunk_data_stream

    for record in records:
        if not isinstance(record, Chunk):
            yield record
            continue
        stream, size = get_chunk_data_stream(record)
        pos = 0
        while pos < size:
            if pos + RECORD_HEAD.size > size:
                length = -1
            else:
                stream.read1()
                length = stream.read8()
            if length < 0 or pos + RECORD_HEAD.size + length > size:
                raise InputError(
                    f"{src}: damaged: a record at byte {pos} of a chunk (log times {record.message_start_time} to "
                    f"{record.message_end_time} ns) runs past the chunk's {size} bytes"
                )
            stream.read(length)
            pos += RECORD_HEAD.size + length
        yield from breakup_chunk(record, validate_crc=False)


def recover(src: str, dst_fd: int) -> Recovered:
    """Stream ``src``'s whole records into a complete MCAP file written to the open descriptor ``dst_fd`` (closed
    here).  Raises :class:`InputError` (one line naming ``src``) for an input it refuses (module docstring)."""
    from mcap.records import Attachment, Channel, DataEnd, Header, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import CompressionType, Writer

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
        f.seek(0)
        writer: Any = None
        schema_ids: dict[int, int] = {0: 0}
        channel_ids: dict[int, int] = {}
        n_messages = n_metadata = n_attachments = 0
        record: Any = None
        try:
            for record in _records(StreamReader(_Prefix(f, end), emit_chunks=True).records, src):  # type: ignore[arg-type]
                if isinstance(record, Header):
                    writer = Writer(out, compression=CompressionType.NONE)
                    writer.start(profile=record.profile, library=record.library)
                    continue
                if writer is None:
                    raise InputError(f"{src}: not a readable MCAP file (a {type(record).__name__} before its header)")
                if isinstance(record, DataEnd):
                    break  # the summary section follows: the writer makes its own
                if isinstance(record, Schema):
                    if record.id not in schema_ids:
                        schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
                elif isinstance(record, Channel):
                    if record.id not in channel_ids:
                        channel_ids[record.id] = writer.register_channel(
                            record.topic, record.message_encoding, schema_ids[record.schema_id], dict(record.metadata)
                        )
                elif isinstance(record, Message):
                    writer.add_message(
                        channel_ids[record.channel_id],
                        record.log_time,
                        record.data,
                        record.publish_time,
                        record.sequence,
                    )
                    n_messages += 1
                elif isinstance(record, Metadata):
                    writer.add_metadata(record.name, dict(record.metadata))
                    n_metadata += 1
                elif isinstance(record, Attachment):
                    writer.add_attachment(
                        record.create_time, record.log_time, record.name, record.media_type, record.data
                    )
                    n_attachments += 1
        except KeyError as exc:
            what = "a message" if isinstance(record, Message) else "a channel"
            raise InputError(
                f"{src}: not a readable MCAP file ({what} names {exc.args[0]!r}, which no earlier record defines)"
            ) from None
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - whatever the reader raised inside the whole records: damage
            if type(exc).__name__ == "EndOfFile" and writer is not None:
                pass  # the whole records end between two records: read to the last
            else:
                raise InputError(
                    f"{src}: damaged: a record its reader cannot parse before the point the file was cut (byte "
                    f"{end}): {type(exc).__name__}: {exc}"
                ) from None
        if writer is None:
            raise InputError(f"{src}: cut short before its header record ({size} bytes): nothing to recover")
        writer.finish()
    return Recovered(n_messages, len(channel_ids), len(schema_ids) - 1, n_metadata, n_attachments, end, size, complete)


# --------------------------------------------------------------------------- entry point


class _Parser(OneLineParser):
    error_format = "error: {prog}: {message}"


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="python -m onboard.record_recover",
        description="Rewrite an MCAP recording cut short (SIGKILL, power cut) as a complete, indexed file: every "
        "whole record kept, messages byte for byte.",
        epilog="Exit 0 recovered, 2 the input refused (not MCAP, damaged, unreadable) or a bad OUT, 1 OUT cannot "
        "be written.",
    )
    p.add_argument("input", metavar="IN.mcap", help="the recording cut short (python -m onboard --record ...)")
    p.add_argument("output", metavar="OUT.mcap", help="the complete file to write (written beside, then renamed)")
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
        result = recover(args.input, fd)
        os.replace(tmp, target)
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
    print(
        f"{args.input}: {cut}; wrote {args.output}: {r.messages} messages on {r.channels} channels, "
        f"{r.schemas} schemas, {r.metadata} metadata records, {r.attachments} attachments"
    )
    return EXIT_OK
