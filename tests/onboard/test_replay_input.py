"""``python -m onboard.replay`` on recordings it must refuse or judge: copies of one small in-process recording (the
objects chain's, :func:`tests.onboard.test_objects_output._record`), cut short or with a message changed or left
out by the `mcap` package's writer.  A damaged message, a file cut before its first message and a recording without
frame inputs are refused in one line (the flight report refuses them alike); an output that cannot be written is
refused before the replay, with nothing written; ``--compare`` exits 3 when the replay differs from the recording."""

from __future__ import annotations

import errno
import json
import os
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from onboard.app.replay import EXIT_CONFIG, EXIT_DIFFERENT, EXIT_OK, main
from onboard.core.errors import InputError
from onboard.io.record import FRAME_INPUT_TOPIC, IMAGING_POSE_TOPIC
from tests.recording_edits import Edit, rewrite_recording

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "config" / "onboard.yaml"
N_FRAMES = 8
FRAME_TOPIC = "irtrack/uav1/ir/frame"
TRACK_TOPIC = "irtrack/uav1/track"
OBJECTS_TOPIC = "irtrack/uav1/objects"
DAMAGED_INDEX = 2  # the message changed on its topic, counted from 0
REPORT_TIMEOUT_S = 120.0  # a child process importing the simulator on a busy 2-core machine

#: a message's bytes -> the damaged bytes, or None to leave the message out


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    from tests.onboard.test_objects_output import _record

    path = tmp_path_factory.mktemp("replay_input") / "flight.mcap"
    _record(path, N_FRAMES)
    return path


def _copy(src: Path, dst: Path, topic: str | None = None, edit: Edit | None = None, worker: str | None = None) -> int:
    """Copy the recording ``src`` to ``dst``, ``edit`` applied to message ``DAMAGED_INDEX`` on ``topic`` and
    ``worker`` (when given) set as the metadata's ``estimator.worker``.  Returns the edited message's log time (ns),
    0 when none was edited."""
    return _rewrite(src, dst, lambda t, i: edit if t == topic and i == DAMAGED_INDEX else None, worker)


def _rewrite(src: Path, dst: Path, edit_of: Callable[[str, int], Edit | None], worker: str | None = None) -> int:
    """:func:`rewrite_recording` with ``edit_of(topic, index on that topic)``."""
    return rewrite_recording(src, dst, lambda topic, index, _schema: edit_of(topic, index), worker)


def _without_topic(src: Path, dst: Path, topic: str) -> None:
    """Copy ``src`` to ``dst`` without any message on ``topic``."""
    _rewrite(src, dst, lambda t, _i: (lambda data: None) if t == topic else None)


def _json_edit(change: Callable[[dict], object]) -> Edit:
    """An edit of a JSON message: ``change`` gets the decoded object and returns the new one."""
    return lambda data: json.dumps(change(json.loads(data))).encode()


def _without(key: str) -> Edit:
    return _json_edit(lambda obj: {k: v for k, v in obj.items() if k != key})


def _with(**fields) -> Edit:
    return _json_edit(lambda obj: {**obj, **fields})


def _json_error(data: bytes) -> str:
    """What the JSON decoder says of ``data``."""
    try:
        json.loads(data)
    except ValueError as exc:
        return str(exc)
    raise AssertionError(f"{data!r} is JSON")


def _cut_json(data: bytes) -> bytes:
    return data[:-3]


DAMAGE = {  # id: (topic, edit, what the error line says is wrong, given the edited message's original bytes)
    "frame_input_not_json": (FRAME_INPUT_TOPIC, _cut_json, lambda d: f"not JSON ({_json_error(_cut_json(d))})"),
    "frame_input_without_seq": (FRAME_INPUT_TOPIC, _without("seq"), lambda d: "no field 'seq'"),
    "frame_input_seq_a_string": (FRAME_INPUT_TOPIC, _with(seq="7"), lambda d: "field 'seq' is \"7\", not an integer"),
    "frame_input_without_received_ns": (FRAME_INPUT_TOPIC, _without("received_ns"), lambda d: "no field 'received_ns'"),
    "frame_input_pose_without_origin": (
        FRAME_INPUT_TOPIC,
        _json_edit(lambda obj: {**obj, "pose": {k: v for k, v in obj["pose"].items() if k != "origin"}}),
        lambda d: "field 'pose': missing field 'origin'",
    ),
    "frame_input_withheld_a_string": (
        FRAME_INPUT_TOPIC,
        _with(withheld_because="camera_mismatch"),
        lambda d: "field 'withheld_because' is \"camera_mismatch\", not a list of strings",
    ),
    "frame_input_an_array": (
        FRAME_INPUT_TOPIC,
        _json_edit(lambda obj: [1, 2]),
        lambda d: "[1, 2] is not a JSON object",
    ),
    "rawimage_cut": (
        FRAME_TOPIC,
        lambda data: data[: len(data) // 2],
        lambda d: "Error parsing message with type 'foxglove.RawImage': Wire format was corrupt",
    ),
    "track_not_json": (TRACK_TOPIC, lambda data: b"{", lambda d: f"not JSON ({_json_error(b'{')})"),
    "track_ned_of_two": (
        TRACK_TOPIC,
        _with(ned_m=[1.0, 2.0]),
        lambda d: "field 'ned_m' is [1.0, 2.0], not null or 3 numbers",
    ),
    "imaging_pose_without_pose": (IMAGING_POSE_TOPIC, _without("pose"), lambda d: "no field 'pose'"),
    "objects_without_frame_index": (OBJECTS_TOPIC, _without("frame_index"), lambda d: "no field 'frame_index'"),
}


def _original(src: Path, topic: str, index: int) -> bytes:
    from mcap.reader import make_reader

    with open(src, "rb") as f:
        on_topic = [m.data for _, ch, m in make_reader(f).iter_messages() if ch.topic == topic]
    return on_topic[index]


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_message_is_refused_in_one_line_naming_the_file_topic_index_and_log_time(
    recording, tmp_path, capsys, damage
):
    topic, edit, what = DAMAGE[damage]
    bad = tmp_path / "damaged.mcap"
    log_ns = _copy(recording, bad, topic, edit)
    out = tmp_path / "tracks.jsonl"
    assert main([str(bad), "--compare", "--out", str(out)]) == EXIT_CONFIG
    captured = capsys.readouterr()
    expected = (
        f"{bad}: message {DAMAGED_INDEX} on {topic} (log time {log_ns} ns) is damaged: "
        f"{what(_original(recording, topic, DAMAGED_INDEX))}"
    )
    assert captured.err.splitlines() == [expected]
    assert captured.out == "" and not out.exists()  # nothing replayed, nothing written


@pytest.mark.subprocess
@pytest.mark.parametrize("kind", ["damaged", "no_frame_inputs"])
def test_the_flight_report_refuses_the_same_recordings_in_the_same_words(recording, tmp_path, capsys, kind):
    """``groundsim report`` reads recordings through the same :func:`onboard.app.replay.load_recording`."""
    bad = tmp_path / f"{kind}.mcap"
    if kind == "damaged":
        _copy(recording, bad, FRAME_INPUT_TOPIC, _without("seq"))
    else:
        _without_topic(recording, bad, FRAME_INPUT_TOPIC)
    assert main([str(bad), "--config", str(CONFIG)]) == EXIT_CONFIG
    replay_line = capsys.readouterr().err.strip()
    p = subprocess.run(
        [sys.executable, "-m", "groundsim", "report", str(bad), "--out", str(tmp_path / "report")],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=REPORT_TIMEOUT_S,
    )
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip().splitlines() == [f"groundsim report: error: {replay_line}"]


def test_a_recording_without_frame_inputs_is_refused_in_the_flight_reports_words(recording, tmp_path, capsys):
    other = tmp_path / "other.mcap"
    _without_topic(recording, other, FRAME_INPUT_TOPIC)
    out = tmp_path / "oo.jsonl"
    assert main([str(other), "--config", str(CONFIG), "--out", str(out)]) == EXIT_CONFIG
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [  # a daemon's recording (its configuration in the metadata) with no frame
        f"{other}: the daemon recorded no frame taken (no irtrack.frame_input messages): no IR frames reached it "
        "while it recorded (the simulator or camera not running, or not on its zenoh key)"
    ]
    assert captured.out == "" and not out.exists()


@pytest.mark.parametrize("n_bytes", [8, 20], ids=["magic_only", "cut_in_the_header"])
@pytest.mark.parametrize("with_config", [False, True], ids=["metadata", "config"])
def test_a_file_cut_before_its_first_message_is_refused_as_cut_short(recording, tmp_path, capsys, n_bytes, with_config):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[:n_bytes])
    assert main([str(cut)] + (["--config", str(CONFIG)] if with_config else [])) == EXIT_CONFIG
    assert capsys.readouterr().err.splitlines() == [
        f"{cut}: file cut short before its first message (it ends at byte {n_bytes})"
    ]


def test_a_file_cut_after_some_frames_replays_them_and_says_it_was_cut(recording, tmp_path, capsys):
    cut = tmp_path / "cut.mcap"
    data = recording.read_bytes()
    cut.write_bytes(data[: len(data) * 3 // 4])
    assert main([str(cut)]) == EXIT_OK
    first = capsys.readouterr().out.splitlines()[0]
    assert first.endswith(f"; file cut short (it ends at byte {len(data) * 3 // 4}): read to its last chunk"), first
    assert " 0 frames taken" not in first


@pytest.mark.parametrize("option", ["--out", "--objects-out"])
@pytest.mark.parametrize("where", ["missing_folder", "under_a_file", "a_folder"])
def test_an_output_that_cannot_be_written_is_refused_before_the_replay(recording, tmp_path, capsys, option, where):
    (tmp_path / "file").write_text("")
    bad, code = {
        "missing_folder": (tmp_path / "nowhere" / "out.jsonl", errno.ENOENT),
        "under_a_file": (tmp_path / "file" / "out.jsonl", errno.ENOTDIR),
        "a_folder": (tmp_path, errno.EISDIR),
    }[where]
    good = tmp_path / "good.jsonl"  # the other output, writable: not written either
    other = "--objects-out" if option == "--out" else "--out"
    assert main([str(recording), option, str(bad), other, str(good), "--compare"]) == EXIT_CONFIG
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [f"{bad}: cannot write: {os.strerror(code)}"]
    assert captured.out == "" and not good.exists()


def test_a_refused_replay_leaves_an_existing_output_as_it_was(recording, tmp_path, capsys):
    bad = tmp_path / "damaged.mcap"
    _copy(recording, bad, FRAME_INPUT_TOPIC, _without("seq"))
    out = tmp_path / "tracks.jsonl"
    out.write_text("yesterday's tracks\n")
    assert main([str(bad), "--out", str(out)]) == EXIT_CONFIG
    assert out.read_text() == "yesterday's tracks\n"


def _lost(track: dict) -> dict:
    return {**track, "state": "lost" if track["state"] != "lost" else "tracking"}


COMPARED = {  # id: (the recording's estimator.worker, topic, edit, exit code, the compare lines expected)
    "same": ("inline", None, None, EXIT_OK, [f"compare: {N_FRAMES}/{N_FRAMES} frames identical, 0 differ"]),
    "track_differs": (
        "inline",
        TRACK_TOPIC,
        _json_edit(_lost),
        EXIT_DIFFERENT,
        [f"compare: {N_FRAMES - 1}/{N_FRAMES} frames identical, 1 differ, 0 unmatched"],
    ),
    "track_missing": (
        "inline",
        TRACK_TOPIC,
        lambda data: None,
        EXIT_DIFFERENT,
        [f"compare: {N_FRAMES - 1}/{N_FRAMES - 1} frames identical, 0 differ, 1 unmatched"],
    ),
    "objects_differ": (
        "process",
        OBJECTS_TOPIC,
        _with(primary_id=-1),
        EXIT_DIFFERENT,
        [f"compare: objects: {N_FRAMES - 1}/{N_FRAMES} frames identical, 1 differ, 0 unmatched"],
    ),
    # a worker's recording: its estimates depend on the worker's timing, so only positions beyond the recorded
    # sigma, frames in one list only and objects count against the replay
    "worker_track_differs_off_the_positions": (
        "process",
        TRACK_TOPIC,
        _json_edit(_lost),
        EXIT_OK,
        [f"compare: {N_FRAMES - 1}/{N_FRAMES} frames identical, 1 differ, 0 unmatched"],
    ),
}


@pytest.mark.parametrize("case", list(COMPARED))
def test_compare_exits_3_when_the_replay_differs_from_the_recording(recording, tmp_path, capsys, case):
    worker, topic, edit, code, lines = COMPARED[case]
    copy = tmp_path / "flight.mcap"
    _copy(recording, copy, topic, edit, worker=worker)
    assert main([str(copy), "--compare"]) == code
    out = capsys.readouterr().out.splitlines()
    assert all(any(ln.startswith(want) for ln in out) for want in lines), out


def test_a_bad_set_on_a_recordings_configuration_names_the_option_not_the_file():
    import types

    import yaml

    from onboard.app.config import OnboardConfigError, build_config, config_to_dict
    from onboard.app.replay import config_of

    rec = types.SimpleNamespace(
        path="F.mcap", metadata={"config_yaml": yaml.safe_dump(config_to_dict(build_config({})))}
    )
    with pytest.raises(OnboardConfigError, match=r"^--set: camera.intrinsics.fx_px: expected a number in \(0, "):
        config_of(rec, None, {"camera.intrinsics.fx_px": (-1.0, "--set")})
    assert config_of(rec, None, {"camera.intrinsics.fx_px": (400.0, "--set")}).camera.intrinsics.fx_px == 400.0


@pytest.mark.parametrize(
    "text, said",
    [
        ("imaging: [chain", "F.mcap (metadata config_yaml): not YAML: "),
        ("hello", "F.mcap (metadata config_yaml): expected a mapping of configuration sections, got str"),
        ("- a", "F.mcap (metadata config_yaml): expected a mapping of configuration sections, got list"),
    ],
)
def test_a_recordings_configuration_that_is_not_a_mapping_is_refused_naming_the_metadata(text, said):
    """It had ended replay and report in a traceback (yaml's ParserError, AttributeError on a str)."""
    import types

    from onboard.app.replay import config_of

    with pytest.raises(InputError) as info:
        config_of(types.SimpleNamespace(path="F.mcap", metadata={"config_yaml": text}))
    assert str(info.value).startswith(said) and "\n" not in str(info.value)


def _truth_message(**change) -> bytes:
    from groundsim.world.truth import TruthRow, truth_json

    row = TruthRow(
        7, 32.0, 35.0, 100.0, 32.001, 35.0, 160.0, 320.0, 256.0, 1, 3, 0.1, *([0.0] * 12), 1.0, 0.0, 0.0, 0.0, 150.0
    )
    return json.dumps({**truth_json(row), **change}).encode()


@pytest.mark.parametrize(
    "change, said",
    [
        ({"target_lat_deg": float("nan")}, "field 'target_lat_deg' is NaN, not a finite number"),
        ({"target_lat_deg": None}, "field 'target_lat_deg' is null, not a finite number"),
        ({"observer_alt_m": "160"}, "field 'observer_alt_m' is \"160\", not a finite number"),
        ({"q_ned_from_cam_w": None}, "field 'q_ned_from_cam_w' is null, not a finite number"),
        ({"target_u_px": "x"}, "field 'target_u_px' is \"x\", not a finite number"),
        ({"nav_att_err_e_rad": float("inf")}, "field 'nav_att_err_e_rad' is Infinity, not a finite number"),
    ],
)
def test_a_truth_row_the_report_cannot_read_is_damaged_naming_the_field(change, said):
    """A NaN target latitude had made the report's error plot drop its frames unsaid; a missing or mistyped field
    ended it in a traceback."""
    from onboard.app.recorded_messages import truth_row

    with pytest.raises(ValueError, match=re.escape(said)):
        truth_row(_truth_message(**change))


def test_a_truth_row_without_a_field_the_report_reads_is_damaged_and_a_null_pixel_is_not():
    from onboard.app.recorded_messages import truth_row

    row = json.loads(_truth_message())
    del row["target_lon_deg"]
    with pytest.raises(ValueError, match="no field 'target_lon_deg'"):
        truth_row(json.dumps(row).encode())
    assert truth_row(_truth_message(target_u_px=None, target_v_px=None))["target_u_px"] is None  # behind the camera


def test_a_recording_from_before_the_chain_field_replays_with_the_single_chain_it_ran():
    """A recording's configuration names every field; one without ``imaging.chain`` predates the field, when the
    single chain was the only one: it replays with that chain, not today's default, unless told otherwise."""
    import types

    import yaml

    from onboard.app.config import build_config, config_to_dict
    from onboard.app.replay import config_of

    def recording(drop_chain: bool):
        raw = config_to_dict(build_config({}))
        if drop_chain:
            del raw["imaging"]["chain"]
        return types.SimpleNamespace(path="F.mcap", metadata={"config_yaml": yaml.safe_dump(raw)})

    assert config_of(recording(True)).imaging.chain == "single"
    assert config_of(recording(False)).imaging.chain == "objects"  # recorded with the objects chain
    assert config_of(recording(True), None, {"imaging.chain": ("objects", "--set")}).imaging.chain == "objects"


# --------------------------------------------------------------------------- frames read from the file


def test_frames_are_read_again_from_where_the_indexed_reader_finds_them(recording):
    """The recording's frames are not held in memory: each is where it lies in the file, and the bytes there are
    the message the `mcap` package's indexed reader (another reader than replay's) gives, in order."""
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
    from mcap.reader import make_reader

    from onboard.app.replay import load_recording

    rec = load_recording(str(recording))
    refs = [ref for copies in rec.frames.values() for ref, _rx in copies]
    assert len(refs) == N_FRAMES
    assert all(ref.data is None and ref.offset is not None for ref in refs)
    with open(recording, "rb") as f:
        images = [m.data for _s, ch, m in make_reader(f).iter_messages() if ch.topic == FRAME_TOPIC]
        assert len(images) == N_FRAMES
        for ref, data in zip(sorted(refs, key=lambda r: r.offset), images):
            assert os.pread(f.fileno(), ref.size, ref.offset) == data
            assert ref.raw_image() == RawImage.FromString(data)


@pytest.mark.parametrize("compression", ["lz4", "zstd"])
def test_a_recording_of_compressed_chunks_keeps_its_frames_and_replays_as_recorded(
    recording, tmp_path, capsys, compression
):
    from onboard.app.replay import load_recording

    packed = tmp_path / f"{compression}.mcap"
    rewrite_recording(recording, packed, lambda *_: None, compression=compression)
    refs = [ref for copies in load_recording(str(packed)).frames.values() for ref, _rx in copies]
    assert len(refs) == N_FRAMES and all(ref.offset is None and ref.data is not None for ref in refs)
    assert main([str(packed), "--compare"]) == EXIT_OK, capsys.readouterr().err


def test_a_frame_whose_file_changed_after_loading_is_refused_naming_the_file_and_byte(recording, tmp_path):
    from onboard.app.replay import load_recording

    copy = tmp_path / "copy.mcap"
    copy.write_bytes(recording.read_bytes())
    rec = load_recording(str(copy))
    ref = max((ref for copies in rec.frames.values() for ref, _rx in copies), key=lambda r: r.offset)
    os.truncate(copy, ref.offset + ref.size // 2)  # the last frame cut in half
    with pytest.raises(InputError, match=rf"{copy}: the frame at byte {ref.offset} no longer decodes"):
        ref.raw_image()
    copy.unlink()
    with pytest.raises(InputError, match=rf"{copy}: cannot read the frame at byte {ref.offset}"):
        ref.raw_image()


@pytest.mark.parametrize("jobs", [1, 2])
def test_a_frame_cut_after_loading_stops_the_replay_in_one_error_with_either_job_count(
    recording, tmp_path, capfd, jobs
):
    """With ``--jobs 2`` the forked imaging process meets the cut frame first: it stops without a traceback of its
    own and the replay reports the frame as one process does."""
    from onboard.app.replay import config_of, load_recording, replay

    copy = tmp_path / "copy.mcap"
    copy.write_bytes(recording.read_bytes())
    rec = load_recording(str(copy))
    config = config_of(rec, None, {"imaging.chain": ("single", "--set")})  # the objects chain runs in one process
    ref = sorted((r for copies in rec.frames.values() for r, _rx in copies), key=lambda r: r.offset)[3]
    os.truncate(copy, ref.offset + 10)
    with pytest.raises(InputError, match=rf"{copy}: the frame at byte {ref.offset} no longer decodes"):
        replay(rec, config, jobs=jobs)
    assert "Traceback" not in capfd.readouterr().err


def test_a_recording_without_chunks_is_read_by_offset_and_replays_as_recorded(recording, tmp_path, capsys):
    from onboard.app.replay import load_recording

    flat = tmp_path / "flat.mcap"
    rewrite_recording(recording, flat, lambda *_: None, chunked=False)
    refs = [ref for copies in load_recording(str(flat)).frames.values() for ref, _rx in copies]
    assert len(refs) == N_FRAMES and all(ref.offset is not None and ref.data is None for ref in refs)
    assert main([str(flat), "--compare"]) == EXIT_OK, capsys.readouterr().err


def test_the_flight_report_reads_only_the_frame_it_draws(recording, monkeypatch):
    """Asking whether a frame is in the report's frames reads nothing; drawing one reads that one."""
    from groundsim.app.report import flight_inputs
    from onboard.app.replay import load_recording
    from onboard.io.mcap_read import FrameRef

    reads = []
    real = FrameRef.raw_image
    monkeypatch.setattr(FrameRef, "raw_image", lambda self: reads.append(self.offset) or real(self))
    rec = load_recording(str(recording))
    _poses, frames = flight_inputs(rec)
    keys = list(rec.frames)
    assert all(k in frames for k in keys) and ("nope", 0) not in frames and len(frames) == N_FRAMES
    assert reads == []
    assert frames[keys[3]].shape == (512, 640) and len(reads) == 1


def test_a_recording_of_frame_inputs_without_their_images_is_refused(recording, tmp_path, capsys):
    """record.frames: false keeps the pipeline's inputs but not the pixels: a replay would feed nothing and print
    zeros with exit 0."""
    from mcap.reader import make_reader

    with open(recording, "rb") as f:
        (frames,) = {c.topic for c in make_reader(f).get_summary().channels.values() if c.topic.endswith("/ir/frame")}
    bare = tmp_path / "bare.mcap"
    _without_topic(recording, bare, frames)
    out = tmp_path / "oo.jsonl"
    assert main([str(bare), "--config", str(CONFIG), "--out", str(out)]) == EXIT_CONFIG
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"{bare}: ") and "none of their images recorded" in err[0]
    assert not out.exists()


def test_a_long_replay_says_how_far_it_is_every_few_seconds(monkeypatch, capsys):
    import onboard.app.replay as replay_module

    clock = iter([100.0, 101.0, 106.0, 107.0, 112.5])
    monkeypatch.setattr(replay_module.time, "monotonic", lambda: next(clock))
    line = replay_module.ReplayProgress(40)
    for n in range(1, 5):
        line(n)
    assert capsys.readouterr().err.splitlines() == [
        "replay: 2/40 frames (5 %), 0 frames/s",
        "replay: 4/40 frames (10 %), 0 frames/s",
    ]


@pytest.mark.parametrize(
    "topic, schema", [(FRAME_INPUT_TOPIC, "irtrack.frame_input/2"), ("irtrack/uav1/track", "irtrack.track/9")]
)
def test_a_message_of_a_version_replay_does_not_read_is_refused_naming_it(tmp_path, topic, schema):
    """It had been read as the version replay knows, whatever its fields had come to mean."""
    from mcap.writer import Writer

    from onboard.app.replay import load_recording

    path = tmp_path / "newer.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(schema, "jsonschema", b"{}")
        cid = w.register_channel(topic, "json", sid)
        w.add_message(cid, log_time=5, publish_time=5, data=b'{"seq": 1, "time_boot_us": 2}')
        w.finish()
    with pytest.raises(InputError) as info:
        load_recording(str(path))
    assert str(info.value) == (
        f"{path}: message 0 on {topic} (log time 5 ns) is of schema {schema!r}, a version this replay does not read "
        f"(it reads {'irtrack.frame_input/1' if 'frame' in schema else 'irtrack.track/1, irtrack.track/2'}): "
        "a newer irtrack's?"
    )


def test_frame_inputs_the_recorder_dropped_are_said_from_its_last_status(recording, tmp_path, capsys, monkeypatch):
    """A frame input the recorder dropped (its backlog full) leaves no trace in the file: replay said it replayed
    every frame the pipeline took while it fed fewer; the daemon's status in the file counts the drops."""
    import dataclasses

    import onboard.app.replay as replay_module

    holey = tmp_path / "holey.mcap"
    _copy(recording, holey, FRAME_INPUT_TOPIC, lambda data: None)
    said = {"record": {"dropped_by_topic": {FRAME_INPUT_TOPIC: 1, "/mavlink/autopilot": 3}}}
    statuses = [(1, json.dumps({"record": {"dropped_by_topic": {}}}).encode()), (2, json.dumps(said).encode())]
    load = replay_module.load_recording
    monkeypatch.setattr(
        replay_module, "load_recording", lambda path: dataclasses.replace(load(path), statuses=statuses)
    )
    assert main([str(holey)]) == EXIT_OK
    assert capsys.readouterr().out.splitlines()[1] == (
        f"{holey}: the recorder dropped 4 messages (its last status in the file, record.dropped_by_topic: 3 on "
        f"/mavlink/autopilot, 1 on {FRAME_INPUT_TOPIC}); 1 frames the daemon's pipeline took are not in the file, so "
        "not replayed: the tracks after the first of them need not be the flight's"
    )
    assert replay_module.recorder_drops_note(dataclasses.replace(load(holey), statuses=statuses[:1])) is None


def test_a_later_file_of_a_rotated_recording_is_said_to_replay_from_a_fresh_start(recording, capsys, monkeypatch):
    """Replaying rec.1.mcap of a recording rotated at record.max_file_mb=40 gave 0 of 120 frames of objects matched
    and '11 frames tracking another object (track_id; operator selections are not replayed)': the daemon's pipeline
    had gone on from rec.mcap's frames, the replay's started afresh, and nothing said so."""
    import dataclasses

    import onboard.app.replay as replay_module

    load = replay_module.load_recording
    for index, said in (("0", False), ("2", True)):
        monkeypatch.setattr(
            replay_module,
            "load_recording",
            lambda path, i=index: (lambda r: dataclasses.replace(r, metadata={**r.metadata, "file_index": i}))(
                load(path)
            ),
        )
        assert main([str(recording)]) == EXIT_OK
        lines = capsys.readouterr().out.splitlines()
        assert (
            f"{recording}: file 2 of a rotated recording: replayed from its first frame with no tracks, while the "
            "daemon's pipeline went on from the 2 file(s) before it: tracks (their ids, their 3-D), objects and their "
            "frame_index need not be the recorded ones; a frame received before the file began is in the one before "
            "(missing from this one)" in lines
        ) is said
