"""onboard.io.record: the flight recorder's MCAP files, read back with the `mcap` package's own readers and the
foxglove protobuf schemas (independent of our writer), drop-and-count, rotation, and a SIGKILLed writer."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from onboard.core.frames import GeodeticOrigin
from onboard.core.irframe import IrFrame
from onboard.core.pose_types import PoseAt, PoseSample
from onboard.core.track import Track
from onboard.io.foxglove_messages import irframe_from_rawimage
from onboard.io.record import (
    FRAME_INPUT_TOPIC,
    FlightRecorder,
    RecordConfig,
)
from onboard.io.record_files import free_recording_path, rotated_path

mcap_reader = pytest.importorskip("mcap.reader")
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix  # noqa: E402
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
ORIGIN = GeodeticOrigin(47.397742, 8.545594, 488.0)
CHILD_TIMEOUT_S = 60.0


def _pose(t_us: int, k: int = 0) -> PoseAt:
    rng = np.random.default_rng(k)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    body = PoseSample(t_us, rng.normal(size=3) * 100, np.array([1.0, np.nan, 0.5]), q)
    return PoseAt(body, rng.normal(size=3) * 100, q, None, ORIGIN, 20000, 40000, None, 0, sigma_extrapolation_rad=1e-5)


def _frame(seq: int, dtype=np.uint8) -> IrFrame:
    rng = np.random.default_rng(seq)
    px = rng.integers(0, 255 if dtype == np.uint8 else 16000, size=(48, 64)).astype(dtype)
    return IrFrame(seq, 1_000_000 + seq * 33_333, px)


def _read_all(path) -> list:
    with open(path, "rb") as f:
        r = mcap_reader.make_reader(f)
        return [(s, c, m) for s, c, m in r.iter_messages()]


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_recording_reads_back_with_the_mcap_reader_and_foxglove_schemas(tmp_path, dtype):
    path = tmp_path / "f.mcap"
    rec = FlightRecorder(RecordConfig(path=str(path), chunk_kb=64), vehicle="uav7", metadata={"config_yaml": "a: 1\n"})
    rec.start()
    frames = [_frame(i, dtype) for i in range(20)]
    for i, fr in enumerate(frames):
        rec.on_mavlink(bytes([0xFD, i, 2, 3]), "autopilot", ("127.0.0.1", 14550))
        rec.on_frame(fr, 10_000 + i)
        rec.on_frame_input(fr, 10_000 + i, True, _pose(fr.time_boot_us, i))
        rec.on_track(_track(fr, "uav7", np.diag([4.0, 9.0, 16.0])))
    rec.on_status(b'{"schema":"irtrack.status/1"}')
    rec.close()
    assert rec.dropped == 0 and rec.write_errors == 0
    msgs = _read_all(path)
    by_topic: dict = {}
    for s, c, m in msgs:
        by_topic.setdefault(c.topic, []).append((s, c, m))
    assert {t: len(v) for t, v in by_topic.items()} == {
        "/mavlink/autopilot": 20,
        "irtrack/uav7/ir/frame": 20,
        FRAME_INPUT_TOPIC: 20,
        "/onboard/camera_fix": 20,
        "irtrack/uav7/track": 20,
        "/onboard/target_fix": 20,
        "irtrack/uav7/status": 1,
    }
    s, c, m = by_topic["irtrack/uav7/ir/frame"][5]
    assert (s.name, s.encoding, c.message_encoding) == ("foxglove.RawImage", "protobuf", "protobuf")
    img = RawImage()
    img.ParseFromString(m.data)
    assert img.encoding == ("mono8" if dtype == np.uint8 else "mono16")
    assert (img.width, img.height, img.step) == (64, 48, 64 * np.dtype(dtype).itemsize)
    back = irframe_from_rawimage(m.sequence, img)
    assert back.seq == 5 and back.time_boot_us == frames[5].time_boot_us
    # stamped at receipt (10_005 on the recorder's monotonic clock), on the wall clock; published then too (MCAP:
    # the publish time is the log time when not known), never a monotonic count of nanoseconds
    assert m.log_time == rec.log_time_ns(10_005) and m.publish_time == m.log_time
    assert np.array_equal(back.pixels, frames[5].pixels) and back.pixels.dtype == dtype
    s, c, m = by_topic["/mavlink/autopilot"][3]
    obj = json.loads(m.data)
    assert (s.name, s.encoding, c.message_encoding) == ("irtrack.mavlink_raw/1", "jsonschema", "json")
    assert json.loads(s.data)["properties"]["data"]["contentEncoding"] == "base64"
    import base64

    assert base64.b64decode(obj["data"]) == bytes([0xFD, 3, 2, 3]) and obj["source"] == "127.0.0.1:14550"
    s, c, m = by_topic["/onboard/target_fix"][0]
    fix = LocationFix()
    fix.ParseFromString(m.data)
    assert (fix.latitude, fix.longitude, fix.altitude) == (47.4, 8.5, 500.0)
    assert list(fix.position_covariance) == [9.0, 0, 0, 0, 4.0, 0, 0, 0, 16.0]  # ENU
    times = [m.log_time for _, _, m in msgs]
    assert times == sorted(times)
    with open(path, "rb") as f:
        meta = list(mcap_reader.make_reader(f).iter_metadata())
    assert meta[0].name == "irtrack" and meta[0].metadata["config_yaml"] == "a: 1\n"
    assert meta[0].metadata["vehicle"] == "uav7"


def below_floors(config: RecordConfig, **sizes: float) -> RecordConfig:
    """``config`` with sizes under the section's floors (1 MB files and queue, 16 KB chunks), set past its
    validation, so that a few small frames reach the bounds the recorder enforces."""
    for name, value in sizes.items():
        object.__setattr__(config, name, value)
    return config


def test_backlog_beyond_queue_is_dropped_and_counted_without_blocking(tmp_path):
    rec = FlightRecorder(below_floors(RecordConfig(path=str(tmp_path / "d.mcap")), queue_mb=0.01), vehicle="uav1")
    # not started: nothing drains the queue, so the bound is what stops it
    fr = _frame(1)  # 3072 pixel bytes + 100
    t0 = time.perf_counter()
    ok = [rec.on_frame(fr, i) for i in range(10)]
    took_s = time.perf_counter() - t0
    assert ok == [True, True, True] + [False] * 7
    assert rec.dropped == 7 and rec.dropped_by_topic == {"irtrack/uav1/ir/frame": 7}
    assert rec.stats()["dropped"] == 7
    print(f"10 on_frame calls: {took_s * 1e6 / 10:.1f} us each")


def test_a_second_recording_on_the_same_path_goes_beside_the_first(tmp_path, caplog):
    """A daemon restarted with the same record.path (a container's restart policy) keeps the earlier flight: the new
    recording is FILE-1.mcap, then FILE-2.mcap; a rotated file of an earlier one holds its name as well."""
    path = str(tmp_path / "flight.mcap")
    names = []
    for k in range(3):
        rec = FlightRecorder(RecordConfig(path=path), vehicle="uav1")
        rec.start()
        rec.on_frame(_frame(k), k)
        rec.close(5.0)
        names.append(os.path.basename(rec.files[0]))
    assert names == ["flight.mcap", "flight-1.mcap", "flight-2.mcap"]
    assert "flight.mcap holds an earlier recording, kept; this one is" in caplog.text
    for name in names:  # each whole, each its own frame
        with open(tmp_path / name, "rb") as f:
            assert len(list(mcap_reader.make_reader(f).iter_messages())) >= 1
    other = tmp_path / "other.mcap"
    (tmp_path / "other.1.mcap").write_bytes(b"a rotated file of an earlier recording")
    assert free_recording_path(str(other)) == str(tmp_path / "other-1.mcap")
    assert free_recording_path(str(tmp_path / "new.mcap")) == str(tmp_path / "new.mcap")


def test_rotation_by_size_keeps_max_files(tmp_path):
    path = str(tmp_path / "r.mcap")
    rec = FlightRecorder(
        below_floors(
            RecordConfig(path=path, max_files=2, compression="none", flush_interval_s=0.05),
            max_file_mb=0.02,
            chunk_kb=4,
        ),
        vehicle="uav1",
    )
    rec.start()
    for i in range(30):
        written = rec.messages_written
        rec.on_frame(_frame(i), i)
        # one frame a batch (rotation is checked after each), however slow the writer: wait until it wrote this one
        deadline = time.monotonic() + 10.0
        while rec.messages_written == written and time.monotonic() < deadline:
            time.sleep(0.002)
        assert rec.messages_written > written, f"the writer did not write frame {i} within 10 s"
    rec.close()
    assert rotated_path(path, 3) == str(tmp_path / "r.3.mcap")
    left = sorted(p.name for p in tmp_path.iterdir())
    assert len(left) == 2 and sorted(Path(f).name for f in rec.files) == left
    assert rec.files[-1] != path and rec.files[0] != path  # rotated past the first file, which was deleted
    # every file made but the two kept was deleted, and counted: record.files counts only the kept
    made = int(Path(rec.files[-1]).name.split(".")[1]) + 1
    assert rec.files_deleted == made - 2 == rec.stats()["files_deleted"] and rec.stats()["files"] == 2
    seqs = []
    for name in left:
        for _, _c, m in _read_all(tmp_path / name):
            seqs.append(m.sequence)
    assert seqs == sorted(seqs) and seqs[-1] == 29  # the newest files, whole and readable


def test_a_recording_deleted_while_written_goes_on_in_the_next_file_and_says_so(tmp_path, caplog):
    """A helper's audit deleted the file 10 s into a flight: the recorder wrote on into the unlinked file for the
    rest of it, with record.stopped null and no log line, and the flight's recording was lost whole."""
    import logging

    path = tmp_path / "f.mcap"
    rec = FlightRecorder(below_floors(RecordConfig(path=str(path), flush_interval_s=0.05)), vehicle="uav1")
    rec.start()

    def write(i: int) -> None:
        written = rec.messages_written
        rec.on_frame(_frame(i), i)
        deadline = time.monotonic() + 10.0
        while rec.messages_written == written and time.monotonic() < deadline:
            time.sleep(0.002)

    with caplog.at_level(logging.WARNING, logger="onboard.io.record"):
        for i in range(3):
            write(i)
        os.unlink(path)  # someone tidies the folder mid-flight
        deadline = time.monotonic() + 10.0
        i = 3
        while not rec.lost_files and time.monotonic() < deadline:
            write(i)
            i += 1
        for j in range(i, i + 3):
            write(j)
    rec.close()
    assert rec.lost_files == [str(path)] and rec.stats()["lost_files"] == [str(path)] and rec.stopped is None
    assert rec.files == [str(tmp_path / "f.1.mcap")] and sorted(p.name for p in tmp_path.iterdir()) == ["f.1.mcap"]
    seqs = [m.sequence for _, _c, m in _read_all(tmp_path / "f.1.mcap")]
    assert seqs and seqs[-1] == i + 2  # the frames after the loss, in a complete file
    assert sum("was deleted while recording" in r.getMessage() for r in caplog.records) == 1


def test_a_recording_moved_away_while_written_is_finished_where_it_went_and_not_called_lost(tmp_path):
    path = tmp_path / "m.mcap"
    moved = tmp_path / "kept" / "m-moved.mcap"
    moved.parent.mkdir()
    rec = FlightRecorder(below_floors(RecordConfig(path=str(path), flush_interval_s=0.05)), vehicle="uav1")
    rec.start()
    for i in range(3):
        rec.on_frame(_frame(i), i)
    deadline = time.monotonic() + 10.0
    while rec.messages_written < 3 and time.monotonic() < deadline:
        time.sleep(0.002)
    os.rename(path, moved)  # an operator tidying the folder, the file still whole
    i = 3
    while rec.files == [str(path)] and time.monotonic() < deadline:
        rec.on_frame(_frame(i), i)
        i += 1
        time.sleep(0.01)
    rec.close()
    assert rec.lost_files == [] and rec.files == [str(tmp_path / "m.1.mcap")]
    first = [m.sequence for _, _c, m in _read_all(moved)]
    assert first[:3] == [0, 1, 2]
    with open(moved, "rb") as f:  # complete where it went: the indexed reader finds its summary
        assert mcap_reader.make_reader(f).get_summary() is not None


_CHILD = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, {repo!r})
    from tests.onboard.test_record import _frame
    from onboard.io.record import FlightRecorder, RecordConfig
    rec = FlightRecorder(RecordConfig(path={path!r}, chunk_kb=16, flush_interval_s=0.1), vehicle="uav1")
    rec.start()
    i = 0
    while True:
        rec.on_frame(_frame(i), i)
        i += 1
        if i == 50:
            print("written", flush=True)
        time.sleep(0.005)
""")


@pytest.mark.integration
def test_sigkill_leaves_a_file_that_reads_up_to_its_last_chunk(tmp_path):
    path = tmp_path / "k.mcap"
    child = subprocess.Popen(
        [sys.executable, "-c", _CHILD.format(repo=str(REPO), path=str(path))],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=REPO,
    )
    try:
        t_end = time.monotonic() + CHILD_TIMEOUT_S
        line = b""
        while not line and time.monotonic() < t_end:
            line = child.stdout.readline()
            if child.poll() is not None:
                break
        assert line.strip() == b"written", f"child failed: {child.stderr.read().decode()[-2000:]}"
        time.sleep(0.5)  # some flushes after the 50th frame
        assert child.poll() is None, "the recording child crashed"
        os.kill(child.pid, signal.SIGKILL)
        child.wait(10)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait(10)
    assert child.returncode == -signal.SIGKILL
    from mcap.exceptions import McapError
    from mcap.stream_reader import StreamReader

    seqs, ended = [], None
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f).records:
                if type(rec).__name__ == "Message":
                    seqs.append(rec.sequence)
        except (McapError, EOFError, ValueError) as exc:
            ended = exc
    assert ended is not None  # no footer: it was killed, not closed
    assert len(seqs) >= 50 and seqs == list(range(len(seqs)))
    print(
        f"killed writer: {len(seqs)} frames readable, file {path.stat().st_size} bytes, ended by {type(ended).__name__}"
    )


class SteppedClock:
    """The recorder's monotonic clock, set by the test."""

    def __init__(self, t_ns: int) -> None:
        self.t_ns = t_ns

    def __call__(self) -> int:
        return self.t_ns


WALL0_NS = 1_700_000_000_000_000_000
MONO0_NS = 5_000_000_000


def _track(fr: IrFrame, vehicle: str = "uav1", cov_p_ned_m2=None) -> Track:
    """A track of frame ``fr`` with a position (so with a target fix), its covariance ``cov_p_ned_m2`` (identity)."""
    return Track(
        vehicle,
        fr.seq,
        fr.time_boot_us,
        "tracking",
        track_id=1,
        lat_deg=47.4,
        lon_deg=8.5,
        alt_m=500.0,
        p_ned_m=(1.0, 2.0, 3.0),
        v_ned_mps=(0.0, 0.0, 0.0),
        cov_p_ned_m2=np.eye(3) if cov_p_ned_m2 is None else cov_p_ned_m2,
        range_m=300.0,
        origin=ORIGIN,
    )


def test_log_times_are_the_hand_over_not_the_write(tmp_path):
    # every message queued at known instants, the writer started 10 s later: each log time is its hand-over (or
    # the receipt its caller gave), never the moment the writer wrote it
    clock = SteppedClock(MONO0_NS)
    path = tmp_path / "t.mcap"
    rec = FlightRecorder(RecordConfig(path=str(path)), vehicle="uav1", clock_ns=clock, wall_ns=lambda: WALL0_NS)
    fr = _frame(3)
    clock.t_ns = MONO0_NS + 1_000
    rec.on_frame(fr, MONO0_NS + 500)  # received before it was handed over
    clock.t_ns = MONO0_NS + 2_000
    rec.on_frame_input(fr, MONO0_NS + 500, True, _pose(fr.time_boot_us))
    clock.t_ns = MONO0_NS + 3_000
    rec.on_track(_track(fr))
    clock.t_ns = MONO0_NS + 4_000
    rec.on_status(b'{"schema":"irtrack.status/1"}')
    rec.on_mavlink(b"\xfd\x01", "autopilot", None, "rx", receive_ns=MONO0_NS + 3_500)
    clock.t_ns = MONO0_NS + 10_000_000_000
    rec.start()
    rec.close()
    got = {c.topic: (m.log_time - WALL0_NS, m.publish_time - WALL0_NS) for _s, c, m in _read_all(path)}
    assert got == {
        "irtrack/uav1/ir/frame": (500, 500),
        FRAME_INPUT_TOPIC: (2_000, 2_000),
        "/onboard/camera_fix": (2_000, 2_000),
        "irtrack/uav1/track": (3_000, 3_000),
        "/onboard/target_fix": (3_000, 3_000),
        "irtrack/uav1/status": (4_000, 4_000),
        "/mavlink/autopilot": (3_500, 3_500),
    }


def test_every_channel_is_numbered_by_its_publisher_or_counted(tmp_path):
    path = tmp_path / "n.mcap"
    rec = FlightRecorder(RecordConfig(path=str(path)), vehicle="uav1", json_schemas={"irtrack.truth/1": {}})
    rec.start()
    for seq in (7, 8, 10):  # frames numbered by the camera, with a gap
        fr = _frame(seq)
        rec.on_frame_input(fr, seq, True, _pose(fr.time_boot_us))
        rec.on_track(_track(fr))
        objects = {"schema": "irtrack.objects/1", "time_boot_us": fr.time_boot_us, "primary_id": None, "objects": []}
        rec.on_objects(objects, seq)
        rec.on_status(b'{"schema":"irtrack.status/1"}')
        rec.on_mavlink(b"\xfd", "autopilot")
        rec.on_mavlink(b"\xfd", "gcs", direction="tx")
        rec.on_json("/groundsim/truth", "irtrack.truth/1", {"seq": seq}, sequence=seq + 100)
    rec.close()
    seqs: dict = {}
    for _s, c, m in _read_all(path):
        seqs.setdefault(c.topic, []).append(m.sequence)
    assert seqs == {
        FRAME_INPUT_TOPIC: [7, 8, 10],
        "/onboard/camera_fix": [7, 8, 10],
        "irtrack/uav1/track": [7, 8, 10],
        "/onboard/target_fix": [7, 8, 10],
        "irtrack/uav1/objects": [7, 8, 10],
        "/onboard/object_annotations": [7, 8, 10],
        "irtrack/uav1/status": [0, 1, 2],
        "/mavlink/autopilot": [0, 1, 2],
        "/mavlink/gcs": [0, 1, 2],
        "/groundsim/truth": [107, 108, 110],
    }


def test_a_dropped_message_leaves_a_gap_in_its_channels_count(tmp_path):
    path = tmp_path / "g.mcap"
    rec = FlightRecorder(below_floors(RecordConfig(path=str(path)), queue_mb=0.0025), vehicle="uav1")
    pad = b'{"schema":"irtrack.status/1","pad":"' + b"x" * 860 + b'"}'  # 1000 bytes queued with its overhead
    ok = [rec.on_status(pad) for _ in range(3)]
    assert ok == [True, True, False]  # the 3rd does not fit the 2500-byte queue
    rec.start()
    rec.on_status(pad)
    rec.close()
    assert [m.sequence for _s, _c, m in _read_all(path)] == [0, 1, 3]


class SlowRecorder(FlightRecorder):
    """A recorder whose disk takes ``write_s`` per message (a loaded SD card)."""

    write_s = 0.02

    def _write(self, *args) -> None:
        time.sleep(self.write_s)
        super()._write(*args)


def test_close_with_a_backlog_finishes_the_file_within_its_time(tmp_path):
    # a backlog the writer needs 4 s for, closed with 0.5 s: the rest is dropped and counted, and the file is
    # complete (summary, footer) for the indexed reader -- the daemon's SIGTERM gives its recorder what is left of
    # its 2 s budget, and a force exit would leave the file without its summary
    path = tmp_path / "b.mcap"
    rec = SlowRecorder(RecordConfig(path=str(path)), vehicle="uav1")
    n = 200
    for i in range(n):
        assert rec.on_frame(_frame(i), i)
    rec.start()
    t0 = time.monotonic()
    rec.close(0.5)
    took_s = time.monotonic() - t0
    msgs = _read_all(path)
    written = len(msgs)
    assert 0 < written < n and rec.dropped_at_close == n - written == rec.dropped
    assert [m.sequence for _s, _c, m in msgs] == list(range(written))  # the oldest written, in order
    assert took_s < 0.5 * n * SlowRecorder.write_s  # did not wait for the backlog
    with open(path, "rb") as f:
        summary = mcap_reader.make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count == written
    assert rec.stats()["dropped_at_close"] == n - written
    print(f"closed in {took_s * 1000:.0f} ms with {written} of {n} frames written")


def test_a_full_backlog_is_logged_once_and_the_drops_in_all_at_close(tmp_path, caplog):
    """A starved recorder (record.queue_mb=1 under zstd 64 MB chunks, a 30 s flight) dropped 199 messages, 15 of them
    frame inputs, and the daemon's log said nothing of it: only the status, gone with the daemon, counted them."""
    import logging

    rec = FlightRecorder(below_floors(RecordConfig(path=str(tmp_path / "d.mcap")), queue_mb=0.01), vehicle="uav1")
    with caplog.at_level(logging.WARNING, logger="onboard.io.record"):
        ok = [rec.on_frame(_frame(i), i) for i in range(10)]  # not started: nothing drains the queue
        rec.close(1.0)
    assert ok.count(False) == 7
    said = [r.getMessage() for r in caplog.records]
    assert [m for m in said if "backlog past record.queue_mb" in m] == [
        "recorder: backlog past record.queue_mb (0.01 MB): messages dropped from the recording, the first on "
        "irtrack/uav1/ir/frame (counted per topic, the status's record.dropped_by_topic; said once, the total at close)"
    ]
    assert [m for m in said if "in all" in m] == [
        "recorder: 7 messages dropped from the recording in all (7 on irtrack/uav1/ir/frame)"
    ]


def test_a_deleted_file_is_listed_lost_only_once_the_recording_goes_on_in_the_next(tmp_path, monkeypatch):
    """The daemon's record_file_lost warning, raised from the status while the recorder finished the deleted file,
    said 'the recording goes on in' the deleted file itself: lost_files was filled before the next file was open."""
    path = tmp_path / "f.mcap"
    rec = FlightRecorder(below_floors(RecordConfig(path=str(path), flush_interval_s=0.05)), vehicle="uav1")
    seen = []  # the stats a status could read while the recorder moves on to the next file
    for name in ("_finish", "_open"):
        step = getattr(rec, name)
        monkeypatch.setattr(rec, name, lambda *a, _step=step: (seen.append(rec.stats()), _step(*a))[1])
    rec.start()
    rec.on_frame(_frame(0), 0)
    os.unlink(path)
    deadline = time.monotonic() + 10.0
    i = 1
    while not rec.lost_files and time.monotonic() < deadline:
        rec.on_frame(_frame(i), i)
        i += 1
        time.sleep(0.01)
    seen.append(rec.stats())
    rec.close()
    assert rec.lost_files == [str(path)]
    assert {s["current_file"] for s in seen if s["lost_files"]} == {str(tmp_path / "f.1.mcap")}


def test_a_folder_deleted_and_not_made_again_stops_the_recording_naming_no_deleted_file(tmp_path, caplog):
    """A helper's storage audit (the recording's folder deleted, its parent then read-only): the log said the deleted
    file 'ends there', and the status's current_file was None while the warnings read 'goes on in None'."""
    import logging

    folder = tmp_path / "rec"
    path = folder / "f.mcap"
    rec = FlightRecorder(below_floors(RecordConfig(path=str(path), flush_interval_s=0.05)), vehicle="uav1")
    rec.start()
    rec.on_frame(_frame(0), 0)
    os.unlink(path)
    folder.rmdir()
    folder.write_bytes(b"")  # a file where the folder was: the next recording file cannot be made
    deadline = time.monotonic() + 10.0
    i = 1
    with caplog.at_level(logging.WARNING, logger="onboard.io.record"):
        while rec.stopped is None and time.monotonic() < deadline:
            rec.on_frame(_frame(i), i)
            i += 1
            time.sleep(0.01)
        rec.close()
    assert rec.stopped is not None and rec.lost_files == [str(path)] and rec.stats()["current_file"] is None
    (said,) = [r.getMessage() for r in caplog.records if "stopped recording" in r.getMessage()]
    assert f"{path} ends there" not in said and "no file of the recording is left" in said, said


def test_a_rotation_that_cannot_make_the_next_file_stops_the_recording_naming_it(tmp_path):
    """A read-only recording folder (chattr +i) stopped a flight's recording with 'a rotate failed (Operation not
    permitted)': the file it could not make was not named.  A name taken since start is refused the same way."""
    path = tmp_path / "r.mcap"
    rec = FlightRecorder(
        below_floors(RecordConfig(path=str(path), flush_interval_s=0.05), max_file_mb=0.001), vehicle="uav1"
    )
    rec.start()
    (tmp_path / "r.1.mcap").write_bytes(b"")  # taken after start chose the name
    deadline = time.monotonic() + 10.0
    i = 0
    while rec.stopped is None and time.monotonic() < deadline:
        rec.on_frame(_frame(i), i)
        i += 1
        time.sleep(0.01)
    rec.close()
    assert rec.stopped == f"a rotate failed ({tmp_path / 'r.1.mcap'}: File exists)"
    assert [p.name for p in sorted(tmp_path.iterdir())] == ["r.1.mcap", "r.mcap"]
    assert (tmp_path / "r.1.mcap").read_bytes() == b""
