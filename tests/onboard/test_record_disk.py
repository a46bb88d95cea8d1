"""onboard.io.record on a disk that fills: the recording stops with a file that the `mcap` package's readers read
(complete and indexed when the summary still fits, whole records up to the cut otherwise), every message handed over
either written or counted as dropped, and the reason in the stats."""

from __future__ import annotations

import errno
import os
import time
from pathlib import Path

import numpy as np
import pytest

import onboard.io.mcap_chunks as mcap_chunks
import onboard.io.record as record
from onboard.app.record_recover import main as recover_main
from onboard.app.record_recover import whole_length
from onboard.core.irframe import IrFrame
from onboard.io.record import FlightRecorder, RecordConfig

mcap_reader = pytest.importorskip("mcap.reader")
from mcap.exceptions import EndOfFile  # noqa: E402
from mcap.records import Message  # noqa: E402
from mcap.stream_reader import StreamReader  # noqa: E402

FRAME_BYTES = 256 * 256
REAL_WRITEV = os.writev


def _frame(seq: int) -> IrFrame:
    px = np.full((256, 256), seq % 251, dtype=np.uint8)
    return IrFrame(seq, 1_000_000 + seq * 33_333, px)


class Disk:
    """A file system of ``capacity`` bytes for the recording's file (its size is what is used): a write that does
    not fit writes what fits, and the next raises ENOSPC, as a real full disk does; ``frozen``: nothing more fits."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.frozen = False
        self.refused = 0

    def writev(self, fd, bufs):
        room = 0 if self.frozen else self.capacity - os.fstat(fd).st_size
        want = sum(memoryview(b).nbytes for b in bufs)
        if want <= room:
            return REAL_WRITEV(fd, bufs)
        if room <= 0:
            self.refused += 1
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        first = memoryview(bufs[0]).cast("B")
        return REAL_WRITEV(fd, [first[: min(room, first.nbytes)]])


def _record_until_stopped(rec: FlightRecorder, n_max: int = 200) -> int:
    handed = 0
    for seq in range(n_max):
        rec.on_frame(_frame(seq), time.monotonic_ns())
        handed += 1
        if rec.stopped is not None:
            break
        time.sleep(0.002)
    else:
        raise AssertionError("the recorder never stopped")
    for seq in range(n_max, n_max + 5):  # after the stop: dropped and counted, never written
        assert rec.on_frame(_frame(seq), time.monotonic_ns()) is False
        handed += 1
    rec.close()
    return handed


def _config(tmp_path, **kw) -> RecordConfig:
    return RecordConfig(path=str(tmp_path / "f.mcap"), chunk_kb=256, flush_interval_s=0.05, **kw)


def test_a_refused_write_finishes_the_file_without_the_chunk_it_tore(tmp_path, monkeypatch):
    disk = Disk(capacity=900_000)  # three chunks of ~4 frames; the fourth is torn, the summary still fits
    monkeypatch.setattr(mcap_chunks.os, "writev", disk.writev)
    rec = FlightRecorder(_config(tmp_path, min_free_mb=0.0), vehicle="uav1")
    rec.start()
    handed = _record_until_stopped(rec)
    assert disk.refused >= 1 and "write failed" in rec.stopped and rec.stats()["stopped"] == rec.stopped
    assert rec.write_errors >= 1
    # complete and indexed: the reader that reads the footer first opens it, and its statistics count what is there
    with open(rec.files[-1], "rb") as f:
        reader = mcap_reader.make_reader(f)
        summary = reader.get_summary()
        seqs = [m.sequence for _s, _c, m in reader.iter_messages()]
    assert seqs == list(range(len(seqs))) and len(seqs) == rec.messages_written >= 8
    stats = summary.statistics
    assert stats.message_count == len(seqs) and stats.chunk_count == len(summary.chunk_indexes)
    assert stats.message_end_time == max(c.message_end_time for c in summary.chunk_indexes)
    # nothing lost silently
    assert rec.messages_written + rec.dropped == handed
    assert rec.dropped_by_topic[rec.frame_topic] == rec.dropped


def test_a_disk_that_stays_full_leaves_whole_records_that_recover_reads(tmp_path, monkeypatch):
    disk = Disk(capacity=900_000)
    real = disk.writev

    def writev(fd, bufs):
        try:
            return real(fd, bufs)
        except OSError:
            disk.frozen = True  # the truncation's bytes are taken by someone else at once
            raise

    monkeypatch.setattr(mcap_chunks.os, "writev", writev)
    rec = FlightRecorder(_config(tmp_path, min_free_mb=0.0), vehicle="uav1")
    rec.start()
    handed = _record_until_stopped(rec)
    assert "write failed" in rec.stopped and rec.messages_written + rec.dropped == handed
    monkeypatch.setattr(mcap_chunks.os, "writev", REAL_WRITEV)
    cut = rec.files[-1]
    size = os.path.getsize(cut)
    with open(cut, "rb") as f:  # no torn record: the file ends exactly where its last whole record does
        assert whole_length(f, size) == (size, False)
        f.seek(0)
        messages = []
        with pytest.raises(EndOfFile):  # how the streaming reader ends a file without its summary
            for r in StreamReader(f, skip_magic=False).records:
                messages += [r] if isinstance(r, Message) else []
    assert [m.sequence for m in messages] == list(range(rec.messages_written))
    whole = tmp_path / "whole.mcap"
    assert recover_main([cut, str(whole)]) == 0
    with open(whole, "rb") as f:
        assert sum(1 for _ in mcap_reader.make_reader(f).iter_messages()) == rec.messages_written


def test_free_space_under_the_floor_stops_the_recording_with_a_complete_file(tmp_path, monkeypatch):
    free = {"bytes": 10**12}
    monkeypatch.setattr(record, "free_disk_bytes", lambda path: free["bytes"])
    rec = FlightRecorder(_config(tmp_path, min_free_mb=200.0), vehicle="uav1")
    rec.start()
    for seq in range(10):
        rec.on_frame(_frame(seq), time.monotonic_ns())
    free["bytes"] = 150 * 1_000_000
    handed = 10 + _record_until_stopped(rec)
    assert "150 MB free, under record.min_free_mb (200)" == rec.stopped and rec.write_errors == 0
    with open(rec.files[-1], "rb") as f:
        reader = mcap_reader.make_reader(f)
        n = sum(1 for _ in reader.iter_messages())
        # the file itself says why it ends before the flight did, to the mcap package's reader too
        said = {m.name: m.metadata for m in reader.iter_metadata()}
    assert n == rec.messages_written >= 10 and rec.messages_written + rec.dropped == handed
    assert said[record.STOPPED_METADATA]["reason"] == rec.stopped and said[record.STOPPED_METADATA]["stopped_utc"]
    from onboard.app.replay import load_recording, stopped_note

    loaded = load_recording(rec.files[-1])
    assert loaded.stopped["reason"] == rec.stopped
    note = stopped_note(loaded)
    assert "the recording stopped before the flight ended" in note and rec.stopped in note


def test_no_room_at_start_records_nothing_and_says_so(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(record, "free_disk_bytes", lambda path: 5 * 1_000_000)
    rec = FlightRecorder(_config(tmp_path), vehicle="uav1")
    rec.start()
    assert rec.on_frame(_frame(0), time.monotonic_ns()) is False
    rec.close()
    assert rec.dropped == 1 and rec.messages_written == 0 and [Path(f).name for f in rec.files] == ["f.mcap"]
    with open(rec.files[0], "rb") as f:  # finished at once: the configuration, no message
        reader = mcap_reader.make_reader(f)
        assert reader.get_summary().statistics.message_count == 0
        said = {m.name: m.metadata for m in reader.iter_metadata()}
    assert rec.stopped == "5 MB free, under record.min_free_mb (200)"
    assert set(said) == {"irtrack", record.STOPPED_METADATA} and said[record.STOPPED_METADATA]["reason"] == rec.stopped
    assert "not recording to" in caplog.text and "min_free_mb" in caplog.text


def test_a_disk_with_no_room_for_the_header_flies_unrecorded_and_leaves_no_torn_file(tmp_path, monkeypatch, caplog):
    """A helper's storage audit (the recording's tmpfs full at start): the first file's header was refused, start raised,
    and the daemon exited 2 -- no tracking at all -- while a disk with a few MB free flew unrecorded; a 0-byte f.mcap
    was left behind and 'cannot finish ?' logged at shutdown."""
    disk = Disk(capacity=0)
    monkeypatch.setattr(mcap_chunks.os, "writev", disk.writev)
    rec = FlightRecorder(_config(tmp_path, min_free_mb=0.0), vehicle="uav1")
    with caplog.at_level("WARNING", logger="onboard.io.record"):
        rec.start()
        assert rec.on_frame(_frame(0), time.monotonic_ns()) is False
        rec.close()
    assert disk.refused >= 1 and rec.stopped is not None and "No space left on device" in rec.stopped
    assert rec.dropped == 1 and rec.files == [] and rec.stats()["current_file"] is None
    assert list(tmp_path.iterdir()) == []
    said = [r.getMessage() for r in caplog.records]
    assert said[0].startswith(f"recorder: not recording to {tmp_path / 'f.mcap'}: no room to start it"), said
    assert not any("cannot finish" in m for m in said), said


def test_the_floor_is_read_from_the_recordings_file_system(tmp_path):
    st = os.statvfs(tmp_path)
    free = record.free_disk_bytes(str(tmp_path / "f.mcap"))
    assert free is not None and abs(free - st.f_bavail * st.f_frsize) < 64 * 1024 * 1024
    assert record.free_disk_bytes(str(tmp_path / "missing" / "f.mcap")) is None


def test_a_failed_sync_stops_the_recording_without_discarding_what_no_write_refused(tmp_path, monkeypatch):
    """fdatasync failing (EIO) stops the recording as a refused write does, but no chunk was refused: the one in
    progress is finished with the file, not discarded."""

    def eio(fd):
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(record.os, "fdatasync", eio)
    rec = FlightRecorder(_config(tmp_path, min_free_mb=0.0, sync_mb=0.3), vehicle="uav1")
    rec.start()
    handed = _record_until_stopped(rec)
    assert rec.stopped.startswith("a sync failed") and rec.messages_written + rec.dropped == handed
    with open(rec.files[-1], "rb") as f:
        n = sum(1 for _ in mcap_reader.make_reader(f).iter_messages())
    assert n == rec.messages_written > 0


def test_a_discarded_chunk_takes_the_schema_and_channel_first_written_in_it_out_of_the_summary(tmp_path, monkeypatch):
    """MCAP: the summary's Schema and Channel records duplicate the data section's.  A channel first registered in
    the chunk the disk refused stayed in the summary (and its statistics) with no record in the data section."""
    from mcap.records import Channel, Schema

    path = tmp_path / "d.mcap"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    try:
        w = mcap_chunks.ChunkWriter(fd, chunk_size=1 << 20)
        w.start(library="test")
        s1 = w.register_schema("a", "jsonschema", b"{}")
        c1 = w.register_channel("/a", "json", s1)
        w.add_message(c1, 1, b"{}", 1)
        w.flush()  # the first chunk: on disk
        s2 = w.register_schema("b", "jsonschema", b"{}")
        c2 = w.register_channel("/b", "json", s2)
        w.add_message(c2, 2, b"{}", 2)
        monkeypatch.setattr(mcap_chunks.os, "writev", lambda *_a: (_ for _ in ()).throw(OSError(errno.ENOSPC, "full")))
        with pytest.raises(OSError):
            w.flush()
        assert w.discard_chunk() == {c2: 1}
        monkeypatch.setattr(mcap_chunks.os, "writev", REAL_WRITEV)
        w.finish()
    finally:
        os.close(fd)
    with open(path, "rb") as f:
        data_section = [r for r in StreamReader(f, skip_magic=False).records if isinstance(r, (Schema, Channel))]
        f.seek(0)
        summary = mcap_reader.make_reader(f).get_summary()
    in_data = {(type(r).__name__, r.id) for r in data_section}
    assert in_data == {("Schema", s1), ("Channel", c1)}
    assert set(summary.schemas) == {s1} and set(summary.channels) == {c1}
    assert (summary.statistics.schema_count, summary.statistics.channel_count) == (1, 1)


def test_a_rotation_whose_next_file_has_no_room_leaves_no_torn_file(tmp_path, monkeypatch, caplog):
    """The review of the full-disk-at-start fix: the same refusal at a rotation (the next file's header) left
    FILE.1.mcap torn on disk and in no list, for a replay of the rotated files to trip on.  Now it is removed and the
    recording stops, the file before it whole."""
    from tests.onboard.test_record import below_floors

    def writev(fd, bufs):
        if os.readlink(f"/proc/self/fd/{fd}").endswith("f.1.mcap"):  # the second file: no room at all
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return REAL_WRITEV(fd, bufs)

    monkeypatch.setattr(mcap_chunks.os, "writev", writev)
    rec = FlightRecorder(below_floors(_config(tmp_path, min_free_mb=0.0), max_file_mb=0.3), vehicle="uav1")
    rec.start()
    with caplog.at_level("WARNING", logger="onboard.io.record"):
        handed = _record_until_stopped(rec)
    assert "rotate failed" in rec.stopped and "No space left on device" in rec.stopped
    assert [Path(f).name for f in rec.files] == ["f.mcap"] and sorted(p.name for p in tmp_path.iterdir()) == ["f.mcap"]
    with open(rec.files[0], "rb") as f:  # whole and indexed, to the mcap package's reader
        n = sum(1 for _ in mcap_reader.make_reader(f).iter_messages())
    assert n == rec.messages_written >= 4 and rec.messages_written + rec.dropped == handed
    assert any(f"{tmp_path / 'f.mcap'} ends there" in r.getMessage() for r in caplog.records)
