"""One flipped bit in a record's opcode of an MCAP recording (https://mcap.dev/spec): every streaming reader refuses it
naming the byte -- replay's and the flight report's (``onboard.app.replay.load_recording``) and
``python -m onboard.record_recover`` (exit 2) -- and ``record_recover --skip-damaged`` recovers past it (exit 3: every
message but those of a chunk whose own opcode was hit).  Before, a misread record ended the read quietly (a chunk
read as a message index ran on to the end of the file; a message index read as the data end record), a chunk read as
a summary offset was dropped unsaid, and a message index read as a message invented one.  Files the recorder writes
(finished, or cut anywhere: in a chunk, right after its data end record, in its summary, in its closing magic) read
as before; a summary that counts otherwise than the data section holds, or points elsewhere, is damage too."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from onboard.app.record_recover import main as recover
from onboard.app.replay import load_recording
from onboard.core.errors import InputError
from onboard.io.mcap_read import read_recording
from tests.onboard.test_record_recover import _recording
from tests.recording_edits import top_records

mcap_reader = pytest.importorskip("mcap.reader")
from mcap.opcode import Opcode  # noqa: E402


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A finished recording of 40 frames with what the daemon records around them, in 64 KB chunks (7 of them)."""
    path = tmp_path_factory.mktemp("damage") / "flight.mcap"
    _recording(path, frames=40)
    assert sum(op == Opcode.CHUNK for _, op, _ in top_records(path.read_bytes())) >= 5
    return path


def _indexed(path) -> list[tuple]:
    """The messages of a complete file, as the `mcap` package's indexed reader reads them in file order."""
    with open(path, "rb") as f:
        return [
            (c.topic, m.log_time, m.publish_time, m.sequence, m.data)
            for _s, c, m in mcap_reader.make_reader(f).iter_messages(log_time_order=False)
        ]


def _streamed(path) -> tuple[list[tuple], str | None]:
    """The messages replay's reader reads, and its cut (None: the file was not cut)."""
    msgs, cut = [], None
    for m in read_recording(str(path)):
        if isinstance(m, dict):
            cut = m.get("truncated", cut)
        else:
            msgs.append((m.topic, m.log_time_ns, m.publish_time_ns, m.sequence, m.data))
    return msgs, cut


def _at(data: bytes, opcode: int, which: str) -> tuple[int, int]:
    """``(byte, length)`` of a top-level record of ``opcode``: its ``first``, ``middle`` or ``last``; for a message
    index, ``first`` and ``last`` of those after the middle chunk."""
    records = top_records(data)
    if opcode == Opcode.MESSAGE_INDEX:
        chunks = [k for k, (_, op, _) in enumerate(records) if op == Opcode.CHUNK]
        k = chunks[len(chunks) // 2] + 1
        run = []
        while records[k][1] == Opcode.MESSAGE_INDEX:
            run.append(records[k])
            k += 1
        pos, _, length = run[0] if which == "first" else run[-1]
        return pos, length
    some = [(pos, length) for pos, op, length in records if op == opcode]
    return some[{"first": 0, "middle": len(some) // 2, "last": -1}[which]]


def _chunk_messages(path, start: int) -> list[tuple]:
    """The messages of the chunk at byte ``start`` of an undamaged file, as :func:`_indexed` gives them."""
    from mcap.stream_reader import StreamReader, breakup_chunk

    with open(path, "rb") as f:
        topics = {cid: c.topic for cid, c in mcap_reader.make_reader(f).get_summary().channels.items()}
        f.seek(start)
        chunk = next(StreamReader(f, skip_magic=True, emit_chunks=True).records)
    return [
        (topics[m.channel_id], m.log_time, m.publish_time, m.sequence, m.data)
        for m in breakup_chunk(chunk)
        if type(m).__name__ == "Message"
    ]


def _refused_everywhere(capsys, path, out, byte: int) -> None:
    """Replay's reader and record_recover refuse ``path``, each naming ``byte``; no OUT is written."""
    with pytest.raises(InputError, match="damaged") as err:
        load_recording(str(path))
    assert f"byte {byte}" in str(err.value)
    capsys.readouterr()
    assert recover([str(path), str(out)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "damaged" in lines[0] and f"byte {byte}" in lines[0], lines
    assert not out.exists()


def _cut_in_its_last_chunk(full: bytes) -> bytes:
    """The recording as a kill leaves it: cut half way through its last chunk."""
    last, length = _at(full, Opcode.CHUNK, "last")
    return full[: last + length // 2]


def _damaged_and_refused(capsys, tmp_path, data: bytes, opcode: int, which: str, change) -> tuple[int, Path, Path]:
    """``data`` with the record :func:`_at` finds changed by ``change(bytes, at)`` written to damaged.mcap, which
    every reader refuses naming the record's byte (:func:`_refused_everywhere`); ``(byte, damaged, out)``."""
    edited = bytearray(data)
    byte, _ = _at(edited, opcode, which)
    change(edited, byte)
    damaged, out = tmp_path / "damaged.mcap", tmp_path / "out.mcap"
    damaged.write_bytes(bytes(edited))
    _refused_everywhere(capsys, damaged, out, byte)
    return byte, damaged, out


def _opcode_set(flipped: int):
    def change(data: bytearray, at: int) -> None:
        data[at] = flipped

    return change


def _length_bit_flipped(bit: int):
    def change(data: bytearray, at: int) -> None:
        data[at + 1 + bit // 8] ^= 1 << (bit % 8)

    return change


def _recovers_all_but_a_hit_chunk(recording, damaged, out, byte: int, opcode: int) -> None:
    """``record_recover --skip-damaged`` keeps every message but those of a chunk whose own record was hit, in the
    file's order, byte for byte (exit 3)."""
    full = _indexed(recording)
    lost = _chunk_messages(recording, byte) if opcode == Opcode.CHUNK else []
    assert recover(["--skip-damaged", str(damaged), str(out)]) == 3
    assert _indexed(out) == [m for m in full if m not in lost]


def _recovers_what_precedes_the_damage(tmp_path, capsys, cut_data: bytes, damaged, out, byte: int) -> None:
    """``record_recover --skip-damaged`` keeps the messages before the damage of a file cut short (a chunk whose
    indexes were hit goes with them): a prefix, shorter than the undamaged cut file's (exit 3); damage before the
    first chunk leaves no message, which is no recovery (exit 2, no OUT)."""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(cut_data)
    if byte < _at(cut_data, Opcode.CHUNK, "first")[0]:
        capsys.readouterr()
        assert recover(["--skip-damaged", str(damaged), str(out)]) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"error: {damaged}: damaged, no message readable (from byte ")
        assert lines[0].endswith(": nothing to recover") and not out.exists()
        return
    assert recover(["--skip-damaged", str(damaged), str(out)]) == 3
    kept = _indexed(out)
    whole, _ = _streamed(cut)
    assert kept == whole[: len(kept)] and len(kept) < len(whole)


#: id -> (the record's opcode, which one, the opcode it is given: one bit flipped)
FINISHED = {
    "chunk_as_summary_offset": (Opcode.CHUNK, "middle", 0x0E),
    "chunk_as_message_index": (Opcode.CHUNK, "middle", 0x07),
    "first_chunk_as_message_index": (Opcode.CHUNK, "first", 0x07),
    "chunk_as_footer": (Opcode.CHUNK, "middle", 0x02),
    "chunk_as_reserved_opcode": (Opcode.CHUNK, "middle", 0x16),
    "chunk_as_private_record": (Opcode.CHUNK, "last", 0x86),
    "message_index_as_data_end": (Opcode.MESSAGE_INDEX, "first", 0x0F),
    "message_index_as_message": (Opcode.MESSAGE_INDEX, "last", 0x05),
    "message_index_as_private_record": (Opcode.MESSAGE_INDEX, "last", 0x87),
    "metadata_as_chunk_index": (Opcode.METADATA, "first", 0x08),
    "metadata_as_summary_offset": (Opcode.METADATA, "first", 0x0E),
    "data_end_as_summary_offset": (Opcode.DATA_END, "first", 0x0E),
    "summary_schema_as_message_index": (Opcode.SCHEMA, "first", 0x07),
    "summary_channel_as_message": (Opcode.CHANNEL, "middle", 0x05),
    "statistics_as_schema": (Opcode.STATISTICS, "first", 0x03),
    "statistics_as_data_end": (Opcode.STATISTICS, "first", 0x0F),
    "chunk_index_as_attachment": (Opcode.CHUNK_INDEX, "last", 0x09),
    "chunk_index_as_private_record": (Opcode.CHUNK_INDEX, "middle", 0x88),
    "metadata_index_as_data_end": (Opcode.METADATA_INDEX, "first", 0x0F),
    "summary_offset_as_data_end": (Opcode.SUMMARY_OFFSET, "middle", 0x0F),
    "summary_offset_as_metadata": (Opcode.SUMMARY_OFFSET, "first", 0x0C),
    "footer_as_schema": (Opcode.FOOTER, "first", 0x03),
    "footer_as_chunk": (Opcode.FOOTER, "first", 0x06),
    "footer_as_private_record": (Opcode.FOOTER, "first", 0x82),
}


@pytest.mark.parametrize("case", list(FINISHED))
def test_a_flipped_opcode_in_a_finished_recording_is_refused_naming_its_byte_and_skip_damaged_recovers_past_it(
    recording, tmp_path, capsys, case
):
    opcode, which, flipped = FINISHED[case]
    assert bin(opcode ^ flipped).count("1") == 1
    byte, damaged, out = _damaged_and_refused(
        capsys, tmp_path, recording.read_bytes(), opcode, which, _opcode_set(flipped)
    )
    _recovers_all_but_a_hit_chunk(recording, damaged, out, byte, opcode)
    assert f"byte {byte}" in capsys.readouterr().err


#: id -> (the record's opcode, which one, the opcode it is given), in a recording cut in its last chunk
CUT = {
    "chunk_as_summary_offset": (Opcode.CHUNK, "middle", 0x0E),
    "chunk_as_message_index": (Opcode.CHUNK, "middle", 0x07),
    "message_index_as_data_end": (Opcode.MESSAGE_INDEX, "first", 0x0F),
    "message_index_as_message": (Opcode.MESSAGE_INDEX, "last", 0x05),
    "metadata_as_chunk_index": (Opcode.METADATA, "first", 0x08),
}


@pytest.mark.parametrize("case", list(CUT))
def test_a_flipped_opcode_in_a_recording_cut_short_is_refused_not_taken_for_its_cut(recording, tmp_path, capsys, case):
    opcode, which, flipped = CUT[case]
    cut = _cut_in_its_last_chunk(recording.read_bytes())
    byte, damaged, out = _damaged_and_refused(capsys, tmp_path, cut, opcode, which, _opcode_set(flipped))
    _recovers_what_precedes_the_damage(tmp_path, capsys, cut, damaged, out, byte)


@pytest.mark.parametrize("where", ["finished", "in_a_chunk", "after_its_data_end", "in_its_summary", "in_its_magic"])
def test_a_recording_finished_or_cut_anywhere_reads_as_before(recording, tmp_path, capsys, where):
    """A cut after the data end record is one the recorder leaves when the disk refuses the summary; a file that
    ends inside its closing magic, one a kill leaves half way through the last write."""
    full = recording.read_bytes()
    records = top_records(full)
    data_end = [pos + 9 + n for pos, op, n in records if op == Opcode.DATA_END][0]
    last, length = _at(full, Opcode.CHUNK, "last")
    size = {
        "finished": len(full),
        "in_a_chunk": last + length // 2,
        "after_its_data_end": data_end,
        "in_its_summary": _at(full, Opcode.CHUNK_INDEX, "middle")[0] + 20,
        "in_its_magic": len(full) - 3,
    }[where]
    path, out = tmp_path / "f.mcap", tmp_path / "out.mcap"
    path.write_bytes(full[:size])
    expected = _indexed(recording)
    if where == "in_a_chunk":
        expected = [m for m in expected if m not in _chunk_messages(recording, last)]
    msgs, cut = _streamed(path)
    assert msgs == expected
    assert cut == (None if where == "finished" else f"it ends at byte {size}")
    assert recover([str(path), str(out)]) == 0
    assert _indexed(out) == expected


#: id -> (the record's opcode, which one, the bit of its length flipped)
LENGTHS = {
    "footer_length_past_the_end": (Opcode.FOOTER, "first", 5),  # 20 -> 52 bytes
    "footer_length_over_the_closing_magic": (Opcode.FOOTER, "first", 3),  # 20 -> 28: the magic read as its field
    "data_end_length": (Opcode.DATA_END, "first", 0),  # 4 -> 5 bytes
    "last_summary_offset_length_past_the_end": (Opcode.SUMMARY_OFFSET, "last", 5),  # 17 -> 49 bytes
    "chunk_length_16_bytes_off": (Opcode.CHUNK, "middle", 4),
}


@pytest.mark.parametrize("case", list(LENGTHS))
def test_a_flipped_length_bit_is_refused_naming_its_record_even_where_it_looks_like_a_cut(
    recording, tmp_path, capsys, case
):
    """A finished file ends with its closing magic: a record whose length runs past the end of such a file, or short of
    the footer, was damaged, not cut (a footer or data end record never grows: a longer one is damage too)."""
    opcode, which, bit = LENGTHS[case]
    byte, damaged, out = _damaged_and_refused(
        capsys, tmp_path, recording.read_bytes(), opcode, which, _length_bit_flipped(bit)
    )
    _recovers_all_but_a_hit_chunk(recording, damaged, out, byte, opcode)


#: id -> (the record's opcode, which one, the bit of its length flipped), in a recording cut in its last chunk
CUT_LENGTHS = {
    "message_index_length_past_the_cut": (Opcode.MESSAGE_INDEX, "first", 24),  # its fields end before the cut
    "metadata_length_over_4_gib": (Opcode.METADATA, "first", 40),
}


@pytest.mark.parametrize("case", list(CUT_LENGTHS))
def test_a_flipped_length_bit_in_a_recording_cut_short_is_not_taken_for_its_cut(recording, tmp_path, capsys, case):
    """A record whose length runs past the end of a file cut short is where the file was cut only if its own fields
    run past it too (a cut cuts them) and the length is one a reader reads at all."""
    opcode, which, bit = CUT_LENGTHS[case]
    cut = _cut_in_its_last_chunk(recording.read_bytes())
    byte, damaged, out = _damaged_and_refused(capsys, tmp_path, cut, opcode, which, _length_bit_flipped(bit))
    _recovers_what_precedes_the_damage(tmp_path, capsys, cut, damaged, out, byte)


def _edited(recording, tmp_path, edit) -> tuple:
    data = bytearray(recording.read_bytes())
    byte = edit(data)
    path = tmp_path / "edited.mcap"
    path.write_bytes(bytes(data))
    return path, byte


def _statistics_counts_one_more(data: bytearray) -> int:
    at, _ = _at(data, Opcode.STATISTICS, "first")
    struct.pack_into("<Q", data, at + 9, struct.unpack_from("<Q", data, at + 9)[0] + 1)  # message_count
    return at


def _statistics_moves_a_message_between_channels(data: bytearray) -> int:
    at, _ = _at(data, Opcode.STATISTICS, "first")
    counts = at + 9 + 8 + 2 + 4 * 5 + 8 + 8 + 4  # its fields before channel_message_counts, and the map's length
    first, second = counts + 2, counts + 10 + 2  # the first two channels' counts (after each channel id)
    struct.pack_into("<Q", data, first, struct.unpack_from("<Q", data, first)[0] + 1)
    struct.pack_into("<Q", data, second, struct.unpack_from("<Q", data, second)[0] - 1)
    return at


def _footer_summary_start_moves(data: bytearray) -> int:
    at, _ = _at(data, Opcode.FOOTER, "first")
    struct.pack_into("<Q", data, at + 9, struct.unpack_from("<Q", data, at + 9)[0] + 1)
    return at


def _summary_offset_moves(data: bytearray) -> int:
    at, _ = _at(data, Opcode.SUMMARY_OFFSET, "middle")
    struct.pack_into("<Q", data, at + 10, struct.unpack_from("<Q", data, at + 10)[0] + 1)  # group_start
    return at


def _chunk_index_moves(data: bytearray) -> int:
    at, _ = _at(data, Opcode.CHUNK_INDEX, "middle")
    struct.pack_into("<Q", data, at + 25, struct.unpack_from("<Q", data, at + 25)[0] + 1)  # chunk_start_offset
    return at


SUMMARY_EDITS = {
    "statistics_count_one_more_message": (_statistics_counts_one_more, r"count \d+ messages in \d+ chunks, the data"),
    "statistics_move_a_message_between_channels": (_statistics_moves_a_message_between_channels, "channel 1:"),
    "footer_summary_start_moved": (_footer_summary_start_moves, "says the summary starts at byte"),
    "summary_offset_moved": (_summary_offset_moves, "records are at bytes"),
    "chunk_index_moved": (_chunk_index_moves, "which the data section read does not hold"),
}


@pytest.mark.parametrize("case", list(SUMMARY_EDITS))
def test_a_summary_that_counts_otherwise_or_points_elsewhere_is_damage(recording, tmp_path, capsys, case):
    edit, says = SUMMARY_EDITS[case]
    path, byte = _edited(recording, tmp_path, edit)
    out = tmp_path / "out.mcap"
    _refused_everywhere(capsys, path, out, byte)
    with pytest.raises(InputError, match=says):
        load_recording(str(path))
    # the data section is whole: every message kept, a new summary written
    assert recover(["--skip-damaged", str(path), str(out)]) == 3
    assert _indexed(out) == _indexed(recording)


def test_a_chunk_cut_out_of_a_finished_recording_is_missed_by_its_summary(recording, tmp_path, capsys):
    """A chunk and its message indexes gone (the file shorter by them): the statistics count its messages, and name
    where the chunk index says it was."""
    full = recording.read_bytes()
    start, length = _at(full, Opcode.CHUNK, "middle")
    end = start + 9 + length
    while full[end] == Opcode.MESSAGE_INDEX:
        end += 9 + struct.unpack_from("<Q", full, end + 1)[0]
    path = tmp_path / "spliced.mcap"
    path.write_bytes(full[:start] + full[end:])
    with pytest.raises(InputError, match="the summary's statistics") as err:
        load_recording(str(path))
    assert f"a chunk at byte {start}" in str(err.value)
    assert recover([str(path), str(tmp_path / "out.mcap")]) == 2


def test_a_message_index_twice_after_its_chunk_is_damage(recording, tmp_path, capsys):
    full = recording.read_bytes()
    start, length = _at(full, Opcode.MESSAGE_INDEX, "first")
    copy = full[start : start + 9 + length]
    path = tmp_path / "twice.mcap"
    path.write_bytes(full[: start + 9 + length] + copy + full[start + 9 + length :])
    with pytest.raises(InputError, match=f"a second message index for channel .* \\(at byte {start + 9 + length}\\)"):
        load_recording(str(path))
