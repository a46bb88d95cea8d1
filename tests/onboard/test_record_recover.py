"""onboard.app.record_recover (``python -m onboard.record_recover``): a recording cut in the middle of a chunk, as a
SIGKILL leaves it, which the `mcap` package's indexed reader refuses, rewritten as a complete file that reader
reads: every whole record kept, messages byte for byte; bad input refused in one line naming the file."""

from __future__ import annotations

import os
import struct

import numpy as np
import pytest

from onboard.app.record_recover import main, whole_length
from onboard.io.record import FlightRecorder, RecordConfig
from tests.onboard.test_record import _frame, _pose, _track

mcap_reader = pytest.importorskip("mcap.reader")
from mcap.exceptions import McapError  # noqa: E402
from mcap.writer import CompressionType, Writer  # noqa: E402


def _recording(path, frames: int = 60) -> None:
    """A recording of ``frames`` frames with everything the daemon records around them, in 64 KB chunks."""
    rec = FlightRecorder(
        RecordConfig(path=str(path), chunk_kb=64), vehicle="uav1", metadata={"config_yaml": "vehicle: uav1\n"}
    )
    rec.start()
    for i in range(frames):
        fr = _frame(i, np.uint16)
        rec.on_mavlink(bytes([0xFD, i]), "autopilot", ("127.0.0.1", 14550))
        rec.on_frame(fr, 1_000 + i)
        rec.on_frame_input(fr, 1_000 + i, True, _pose(fr.time_boot_us, i))
        rec.on_track(_track(fr))
        if i % 10 == 0:
            rec.on_status(b'{"schema":"irtrack.status/1"}')
    rec.close()


def _in_file_order(path) -> tuple[list, list, list]:
    """``(messages, channels, metadata)`` of a complete file, read by the indexed reader in file order."""
    with open(path, "rb") as f:
        r = mcap_reader.make_reader(f)
        msgs = [
            (c.topic, s.name, s.data, m.log_time, m.publish_time, m.sequence, m.data)
            for s, c, m in r.iter_messages(log_time_order=False)
        ]
        summary = r.get_summary()
        channels = sorted((c.topic, c.message_encoding, c.metadata) for c in summary.channels.values())
        meta = [(m.name, m.metadata) for m in r.iter_metadata()]
    return msgs, channels, meta


def _chunk_bounds(path) -> list[tuple[int, int]]:
    with open(path, "rb") as f:
        return [
            (ci.chunk_start_offset, ci.chunk_length) for ci in mcap_reader.make_reader(f).get_summary().chunk_indexes
        ]


def _streamed_messages(path) -> int:
    """How many messages the `mcap` package's stream reader reads from the start of ``path`` before its end."""
    from mcap.stream_reader import StreamReader

    n = 0
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f).records:
                n += type(rec).__name__ == "Message"
        except Exception:  # noqa: BLE001 - the cut: whichever error the reader gives there
            pass
    return n


def _cut(src, dst, size: int) -> None:
    with open(src, "rb") as f:
        data = f.read(size)
    with open(dst, "wb") as f:
        f.write(data)


def test_a_recording_cut_mid_chunk_is_recovered_whole_for_the_indexed_reader(tmp_path, capsys):
    full, cut, out = tmp_path / "full.mcap", tmp_path / "cut.mcap", tmp_path / "whole.mcap"
    _recording(full)
    chunks = _chunk_bounds(full)
    assert len(chunks) >= 6
    k = len(chunks) // 2
    start, length = chunks[k]
    _cut(full, cut, start + length // 2)  # in the middle of chunk k, as a SIGKILL leaves a file
    with open(cut, "rb") as f, pytest.raises(McapError):
        list(mcap_reader.make_reader(f).iter_messages())  # the indexed reader reads a garbage footer
    assert main([str(cut), str(out)]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"{cut}: cut at byte {start + length // 2}; its whole records end at byte {start};")
    msgs, channels, meta = _in_file_order(out)
    full_msgs, full_channels, full_meta = _in_file_order(full)
    # the messages of the whole chunks (as the package's stream reader reads the cut file), every field byte for
    # byte, in the file's order; those of chunk k on are lost
    assert len(msgs) == _streamed_messages(cut) > 0
    assert msgs == full_msgs[: len(msgs)]
    assert len(msgs) < len(full_msgs)
    assert meta == full_meta and meta[0][1]["config_yaml"] == "vehicle: uav1\n"
    assert {c[0] for c in channels} <= {c[0] for c in full_channels}
    assert {"irtrack/uav1/ir/frame", "/onboard/frame_input", "irtrack/uav1/track"} <= {c[0] for c in channels}
    # what the recovered file says of itself: its statistics count its messages
    with open(out, "rb") as f:
        assert mcap_reader.make_reader(f).get_summary().statistics.message_count == len(msgs)
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]  # written beside and renamed


def test_schemas_metadata_and_attachments_are_kept(tmp_path, capsys):
    # a file the mcap package wrote (zstd chunks, an attachment and two metadata records between them), cut in
    # its last chunk
    full, cut, out = tmp_path / "a.mcap", tmp_path / "a.cut.mcap", tmp_path / "a.whole.mcap"
    with open(full, "wb") as f:
        w = Writer(f, chunk_size=2048, compression=CompressionType.ZSTD)
        w.start(profile="ros2", library="test")
        sid = w.register_schema("s/1", "jsonschema", b'{"type":"object"}')
        cid = w.register_channel("/a", "json", sid, {"k": "v"})
        w.add_metadata("first", {"x": "1"})
        for i in range(40):
            w.add_message(cid, 1_000 + i, b'{"i":%d,"pad":"%s"}' % (i, b"y" * 200), 2_000 + i, i)
            if i == 20:
                w.add_attachment(5, 6, "cal.yaml", "text/yaml", b"fx: 400\n")
                w.add_metadata("second", {"y": "2"})
        w.finish()
    chunks = _chunk_bounds(full)
    start, length = chunks[-1]
    _cut(full, cut, start + length - 3)
    assert main([str(cut), str(out)]) == 0
    assert "1 attachments" in capsys.readouterr().out
    with open(out, "rb") as f:
        r = mcap_reader.make_reader(f)
        assert r.get_header().profile == "ros2"
        msgs = [
            (s.name, s.data, c.topic, c.metadata, m.data, m.log_time, m.publish_time, m.sequence)
            for s, c, m in r.iter_messages()
        ]
        atts = [(a.name, a.media_type, a.create_time, a.log_time, a.data) for a in r.iter_attachments()]
        meta = [(m.name, m.metadata) for m in r.iter_metadata()]
    n = _streamed_messages(cut)
    assert 20 < n == len(msgs) < 40
    assert msgs[7] == (
        "s/1",
        b'{"type":"object"}',
        "/a",
        {"k": "v"},
        b'{"i":7,"pad":"%s"}' % (b"y" * 200),
        1_007,
        2_007,
        7,
    )
    assert atts == [("cal.yaml", "text/yaml", 5, 6, b"fx: 400\n")]
    assert meta == [("first", {"x": "1"}), ("second", {"y": "2"})]


def test_whole_length_of_a_complete_file_is_its_size(tmp_path):
    full = tmp_path / "c.mcap"
    _recording(full)
    size = full.stat().st_size
    with open(full, "rb") as f:
        assert whole_length(f, size) == (size, True)


def _refused(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    return err[0]


def test_bad_input_is_refused_in_one_line_naming_the_file(tmp_path, capsys):
    full, out = tmp_path / "f.mcap", tmp_path / "out.mcap"
    _recording(full)
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording\n")
    assert _refused(capsys, [str(text), str(out)]).startswith(f"error: {text}: not an MCAP file")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    assert _refused(capsys, [str(empty), str(out)]) == f"error: {empty}: not an MCAP file (the file is empty)"
    # damage inside a whole chunk (the first record in it given an impossible length): not a cut
    damaged = tmp_path / "d.mcap"
    data = bytearray(full.read_bytes())
    start, _ = _chunk_bounds(full)[1]
    comp_len_at = start + 1 + 8 + 8 + 8 + 8 + 4
    (comp_len,) = struct.unpack_from("<I", data, comp_len_at)
    first_record = comp_len_at + 4 + comp_len + 8
    struct.pack_into("<Q", data, first_record + 1, 2**40)
    damaged.write_bytes(bytes(data))
    line = _refused(capsys, [str(damaged), str(out)])
    assert line.startswith(f"error: {damaged}: damaged: the chunk at byte {start}: a record at byte 0 of a chunk (log ")
    assert (
        _refused(capsys, [str(full), str(full)])
        == f"error: OUT.mcap {full}: names the input IN.mcap ({full}); give another file (the cut original is kept)"
    )
    assert _refused(capsys, [str(full), str(tmp_path)]).startswith(f"error: {tmp_path}: it is a folder")
    missing = tmp_path / "gone.mcap"
    assert _refused(capsys, [str(missing), str(out)]) == f"error: {missing}: cannot read: no such file"
    assert not out.exists() and not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


def _chunk_messages(path, k: int) -> int:
    """The messages of the ``k``-th chunk of a complete file (by its message indexes)."""
    from mcap.records import MessageIndex
    from mcap.stream_reader import StreamReader

    start, length = _chunk_bounds(path)[k]
    with open(path, "rb") as f:
        f.seek(start + length)
        n = 0
        for rec in StreamReader(f, skip_magic=True).records:
            if not isinstance(rec, MessageIndex):
                break
            n += len(rec.records)
    return n


def test_damage_in_a_finished_file_is_never_taken_for_a_cut_and_skip_damaged_keeps_every_other_chunk(tmp_path, capsys):
    """One flipped bit in a finished recording: the chunk opcode of chunk k (the reader then took the rest of the file
    for the record it became, and called the file cut there: replay read the first k chunks, exit 0), or the length of
    a message that then took in the messages after it in its chunk and still ended at the chunk's end (nothing
    noticed).  Both are damage, said naming the byte; --skip-damaged recovers every other chunk, exit 3."""
    from onboard.app.replay import load_recording
    from onboard.core.errors import InputError

    full = tmp_path / "full.mcap"
    _recording(full)
    full_msgs, _, full_meta = _in_file_order(full)
    k = len(_chunk_bounds(full)) // 2
    start, length = _chunk_bounds(full)[k]
    lost = _chunk_messages(full, k)
    opcode = bytearray(full.read_bytes())
    opcode[start] ^= 0x01  # chunk (0x06) -> message index (0x07)
    swallow = bytearray(full.read_bytes())
    # the chunk's first record (its records begin after the chunk's fixed fields and compression string)
    comp_len_at = start + 1 + 8 + 8 + 8 + 8 + 4
    (comp_len,) = struct.unpack_from("<I", swallow, comp_len_at)
    records_at = comp_len_at + 4 + comp_len + 8
    chunk_end = start + 1 + 8 + struct.unpack_from("<Q", swallow, start + 1)[0]
    pos = records_at
    while swallow[pos] != 0x05:  # the first message of the chunk: its length made to run to the chunk's end
        pos += 9 + struct.unpack_from("<Q", swallow, pos + 1)[0]
    struct.pack_into("<Q", swallow, pos + 1, chunk_end - pos - 9)
    # (replay may refuse the swallowing message's own data first, which the message decode checks: damaged either way)
    for name, data, says, replay_says in (
        ("opcode", opcode, f"the record at byte {start} cannot be read", f"the record at byte {start} cannot be read"),
        ("swallow", swallow, f"the chunk at byte {start} holds 1 message on channel", "damaged"),
    ):
        damaged, out = tmp_path / f"{name}.mcap", tmp_path / f"{name}-out.mcap"
        damaged.write_bytes(bytes(data))
        with pytest.raises(InputError, match="damaged") as err:
            load_recording(str(damaged))
        assert replay_says in str(err.value)
        assert main([str(damaged), str(out)]) == 2 and says in capsys.readouterr().err
        assert main(["--skip-damaged", str(damaged), str(out)]) == 3
        captured = capsys.readouterr()
        assert f"chunk {k + 1} of " in captured.err and f"at byte {start}" in captured.err
        msgs, _, meta = _in_file_order(out)
        assert len(msgs) == len(full_msgs) - lost and meta == full_meta
        kept = {m[3:6] + (m[0],) for m in msgs}  # (log time, publish time, sequence, topic)
        assert kept <= {m[3:6] + (m[0],) for m in full_msgs}


def test_a_compressed_chunk_whose_data_length_is_damaged_is_damage_and_the_chunks_before_it_are_kept(tmp_path, capsys):
    """The mcap reader reads a chunk's data by its own length field: a damaged one ran on to the end of a cut file,
    the decompressor ignored the extra bytes, and the read stopped at the end: a cut, 'read to its last chunk'.  A
    record must end where its own length says.  --skip-damaged keeps every chunk before it, the last one too."""
    from onboard.app.replay import load_recording
    from onboard.core.errors import InputError

    full = tmp_path / "full.mcap"
    rec = FlightRecorder(RecordConfig(path=str(full), chunk_kb=64, compression="lz4"), vehicle="uav1")
    rec.start()
    for i in range(60):
        rec.on_frame(_frame(i, np.uint16), 1_000 + i)
        rec.on_track(_track(_frame(i, np.uint16)))
    rec.close()
    chunks = _chunk_bounds(full)
    k = len(chunks) // 2
    start, _ = chunks[k]
    before = sum(_chunk_messages(full, j) for j in range(k))
    data = bytearray(full.read_bytes()[: chunks[-1][0] + 100])  # cut inside the last chunk: no footer
    comp_len_at = start + 1 + 8 + 8 + 8 + 8 + 4
    (comp_len,) = struct.unpack_from("<I", data, comp_len_at)
    struct.pack_into("<Q", data, comp_len_at + 4 + comp_len, 10**6)  # the chunk's data length, past the cut
    damaged, out = tmp_path / "d.mcap", tmp_path / "out.mcap"
    damaged.write_bytes(bytes(data))
    with pytest.raises(InputError, match=f"the record at byte {start} cannot be read: it says"):
        load_recording(str(damaged))
    assert main(["--skip-damaged", str(damaged), str(out)]) == 3
    assert f"from byte {start} to the end" in capsys.readouterr().err
    msgs, _, _ = _in_file_order(out)
    assert len(msgs) == before > 0


@pytest.mark.parametrize("size", [8, 12, 30])
def test_a_file_cut_inside_its_header_is_said_to_be_cut_not_damaged(tmp_path, capsys, size):
    full, cut, out = tmp_path / "f.mcap", tmp_path / "c.mcap", tmp_path / "out.mcap"
    _recording(full)
    _cut(full, cut, size)
    assert _refused(capsys, [str(cut), str(out)]) == (
        f"error: {cut}: cut short before its header record ({size} bytes): nothing to recover"
    )
    assert not out.exists()


@pytest.mark.parametrize("size", [100, 5400])
def test_a_file_cut_inside_its_first_chunk_has_nothing_to_recover(tmp_path, capsys, size):
    """Cut after its header but before the end of its first chunk: no message is whole, and a file of none is no
    recovery (it had said 'wrote ... 0 messages', exit 0, and left that file)."""
    full, cut, out = tmp_path / "f.mcap", tmp_path / "c.mcap", tmp_path / "out.mcap"
    _recording(full)
    assert size < _chunk_bounds(full)[0][0] + _chunk_bounds(full)[0][1]
    _cut(full, cut, size)
    line = _refused(capsys, [str(cut), str(out)])
    assert line.startswith(f"error: {cut}: cut short before its first message ({size} bytes; its whole records end ")
    assert line.endswith(": nothing to recover")
    assert not out.exists() and not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


def test_an_existing_output_is_never_written_over_an_empty_one_is_taken(tmp_path, capsys):
    full, cut, out = tmp_path / "f.mcap", tmp_path / "c.mcap", tmp_path / "out.mcap"
    _recording(full)
    _cut(full, cut, full.stat().st_size // 2)
    earlier = full.read_bytes()
    out.write_bytes(earlier)  # an earlier, complete recording given as OUT by mistake
    assert _refused(capsys, [str(cut), str(out)]) == (
        f"error: {out}: exists already ({len(earlier)} bytes); give a new file or remove it first"
    )
    assert out.read_bytes() == earlier and not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]
    link = tmp_path / "link.mcap"  # through a symbolic link: the file it names
    link.symlink_to(out)
    assert _refused(capsys, [str(cut), str(link)]).startswith(f"error: {link}: exists already")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    assert main([str(cut), str(empty)]) == 0
    assert f"wrote {empty}: " in capsys.readouterr().out
    assert 0 < len(_in_file_order(empty)[0]) < len(_in_file_order(full)[0])


@pytest.mark.parametrize("signum", ["SIGINT", "SIGTERM"])
def test_an_interrupted_recovery_leaves_no_temporary_file_and_says_so(tmp_path, capsys, monkeypatch, signum):
    import signal

    import onboard.app.record_recover as record_recover

    full, out = tmp_path / "f.mcap", tmp_path / "out.mcap"
    _recording(full)
    out.write_bytes(b"")  # an empty OUT is taken (one that holds anything is refused before recovering)

    def stopped(*_a, **_k):
        os.kill(os.getpid(), getattr(signal, signum))
        raise AssertionError("the signal should have ended the recovery")

    monkeypatch.setattr(record_recover, "recover", stopped)
    before = signal.getsignal(signal.SIGTERM)
    assert main([str(full), str(out)]) == 130
    assert capsys.readouterr().err == f"interrupted: nothing written ({out} is as it was, or was not created)\n"
    assert out.read_bytes() == b"" and not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]
    assert signal.getsignal(signal.SIGTERM) == before
