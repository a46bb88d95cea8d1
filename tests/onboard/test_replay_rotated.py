"""A rotated recording (``FILE.mcap``, ``FILE.1.mcap`` ...) replayed as one flight: ``python -m onboard.replay`` and
``groundsim report`` given its files in order feed one pipeline across them, so the tracks go on over the files'
boundaries as the recording daemon's did; files that are not one recording's, each once, in order, without a gap,
are refused in one line naming the file.  The recording is written by the recorder directly (the service's frame
loop over a synthetic scene, the estimator inline, ``record.max_file_mb`` at its least): no daemon, no sockets."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from onboard.app.flight_parts import FilePart, parts_problem
from onboard.app.replay import EXIT_CONFIG, EXIT_DIFFERENT, EXIT_OK, main
from onboard.io.record_files import rotated_path

N_FRAMES = 120  # 4 s at 30 Hz: the estimator's first 3-D estimate comes at frame ~58, the files rotate every ~9 frames
MAX_FILE_MB = 3.0  # a 640 x 512 frame is 0.33 MB
RX0_NS, FRAME_NS = 1_000_000_000, 33_000_000
LEAD_US = 45_000  # telemetry fed this far past each frame's capture


def _record(path: Path, n: int) -> tuple[list[str], list[dict]]:
    """A recording of ``n`` frames rotated every ``MAX_FILE_MB``: (its files in order, the tracks as published)."""
    from onboard.app.config import build_config
    from onboard.app.observers import FrameResult, RecorderTap, recording_metadata
    from onboard.core.track import track_to_json
    from onboard.io.record import FlightRecorder, RecordingPoseSource
    from tests.onboard.test_pipeline import Rig

    config = build_config(
        {
            "imaging": {"chain": "single"},
            "estimator": {"worker": "inline"},
            # a chunk a frame: the writer turns (and may rotate) after every frame or so
            "record": {"path": str(path), "max_file_mb": MAX_FILE_MB, "chunk_kb": 16},
        }
    )
    rig = Rig(estimator="real", config=config)
    memo = RecordingPoseSource(rig.pose)
    rig.pipe.pose_source = memo
    tap = RecorderTap(FlightRecorder(config.record, vehicle=config.vehicle, metadata=recording_metadata(config)), path)
    tap.start()
    tracks = []
    try:
        for k in range(n):
            rig.feed_until(rig.scene.t_us(k) + LEAD_US)
            frame = rig.scene.frame(k)
            rx_ns = RX0_NS + k * FRAME_NS
            tap.on_received(frame, rx_ns)
            track = rig.pipe.process(frame, rx_ns)
            looked_up, pose, imaging_pose = memo.take_lookups()
            tap.on_frame(frame, FrameResult(rx_ns, looked_up, pose, track, None, None, imaging_pose))
            tracks.append(json.loads(json.dumps(track_to_json(track))))
    finally:
        tap.close(5.0)
    return list(tap.recorder.files), tracks


@pytest.fixture(scope="module")
def rotated(tmp_path_factory) -> tuple[list[str], list[dict]]:
    files, tracks = _record(tmp_path_factory.mktemp("rotated") / "flight.mcap", N_FRAMES)
    assert len(files) >= 4, files  # boundaries before, at and after the first 3-D estimate
    return files, tracks


@pytest.fixture(scope="module")
def other(tmp_path_factory) -> list[str]:
    """Another recording of the same configuration and scene (a second flight of the same daemon)."""
    files, _ = _record(tmp_path_factory.mktemp("other") / "flight.mcap", 30)  # 10 MB: 3 files unless the writer lags
    assert len(files) >= 2, files
    return files


def _frames_in(path: str) -> list[int]:
    from onboard.app.replay import load_recording

    return [int(i["seq"]) for i in load_recording(path).inputs]


def test_a_rotated_recording_replays_as_one_flight_equal_to_the_recorded_tracks(rotated, tmp_path, capsys):
    """Before, each file replayed alone from a fresh pipeline: a later file's tracks lost their 3-D estimate (and a
    frame received before the file began), so no replay gave the flight's tracks."""
    files, recorded = rotated
    out = tmp_path / "tracks.jsonl"
    assert main([*files, "--compare", "--out", str(out)]) == EXIT_OK
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"one flight in {len(files)} files of a rotated recording: {', '.join(files)}"
    assert lines[-1] == f"compare: {N_FRAMES}/{N_FRAMES} frames identical, 0 differ, 0 unmatched"
    replayed = [json.loads(line) for line in out.read_text().splitlines()]
    assert replayed == recorded  # field for field, floats bit for bit, across every boundary
    # a boundary inside the estimate's run: the file after it, replayed alone, starts without the estimate
    later = next(p for p in files[1:] if recorded[_frames_in(p)[0]]["ned_m"] is not None)
    assert main([later, *files[files.index(later) + 1 :], "--compare"]) == EXIT_DIFFERENT
    assert "file " in capsys.readouterr().out


def _refusal(capsys, argv: list[str]) -> str:
    assert main(argv) == EXIT_CONFIG
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.count("\n") == 1, captured
    return captured.err.strip()


def test_files_out_of_order_or_with_a_gap_are_refused_naming_the_file(rotated, capsys):
    files, _ = rotated
    order = "give each file once, in order (FILE.mcap FILE.1.mcap FILE.2.mcap ...; a shell's FILE.*.mcap puts FILE.10"
    assert _refusal(capsys, [files[0], files[2], files[1]]) == (
        f"{files[2]}: file 2 of its recording, given after file 0 ({files[0]}): {order} before FILE.2)"
    )
    assert _refusal(capsys, [files[0], files[1], files[1]]) == (
        f"{files[1]}: file 1 of its recording, given again: {order} before FILE.2)"
    )
    assert _refusal(capsys, [files[0], files[1], files[3]]) == (
        f"{files[3]}: file 3 of its recording, after file 1 ({files[1]}): file 2 missing"
    )
    assert (
        _refusal(capsys, [files[0], files[3]])
        == f"{files[3]}: file 3 of its recording, after file 0 ({files[0]}): files 1..2 missing"
    )


def test_files_of_two_recordings_are_refused_naming_the_file(rotated, other, capsys):
    from onboard.app.replay import load_recording

    files, _ = rotated
    ids = [load_recording(p).metadata["recording_id"] for p in (files[0], other[1])]
    assert ids[0] != ids[1] and len(ids[0]) == 32
    assert _refusal(capsys, [files[0], other[1]]) == (
        f"{other[1]}: of another recording than {files[0]} (recording_id {ids[1]}, not {ids[0]})"
    )


def test_a_flight_from_a_later_file_says_its_start_is_missing_and_one_file_names_the_rest(rotated, capsys):
    files, _ = rotated
    assert main(files[1:3]) == EXIT_OK
    out = capsys.readouterr().out
    assert f"{files[1]}: file 1 of a rotated recording: replayed from its first frame with no tracks" in out
    assert f"; {files[0]} and the files after it are beside it: give them first, in order, to replay the flight" in out
    assert main(files[:1]) == EXIT_OK  # one file: that file, as asked; the note names the others
    assert (
        f"{files[0]}: the recording goes on in {len(files) - 1} more file(s) beside it, not replayed: "
        f"{', '.join(files[1:])}; the whole flight: python -m onboard.replay {' '.join(files)}"
    ) in capsys.readouterr().out.splitlines()


def test_the_recorder_drops_of_a_flight_are_its_last_files_last_status(rotated, capsys, monkeypatch):
    """The recorder counts its drops over the whole recording: the flight's are the last file's last status (a sum
    over the files would count the first file's again)."""
    import dataclasses

    import onboard.app.replay as replay_module

    files, _ = rotated
    said = {files[0]: 2, files[1]: 5}
    load = replay_module.load_recording

    def with_status(path: str):
        status = {"record": {"dropped_by_topic": {"/mavlink/autopilot": said.get(path, 0)}}}
        return dataclasses.replace(load(path), statuses=[(1, json.dumps(status).encode())])

    monkeypatch.setattr(replay_module, "load_recording", with_status)
    assert main(files[:2]) == EXIT_OK
    assert (
        f"{files[0]} (+1 file): the recorder dropped 5 messages (its last status in the last file, "
        "record.dropped_by_topic: 5 on /mavlink/autopilot)"
    ) in capsys.readouterr().out.splitlines()


def test_groundsim_report_reports_the_files_as_one_flight_and_refuses_a_gap(rotated, tmp_path, capsys):
    import argparse

    from groundsim.app.report import add_report

    files, recorded = rotated
    p = argparse.ArgumentParser()
    add_report(p)
    bad = p.parse_args([files[0], files[2], "--out", str(tmp_path / "bad")])
    from onboard.core.errors import InputError

    with pytest.raises(InputError, match=rf"^{files[2]}: file 2 of its recording, after file 0 .*: file 1 missing$"):
        bad.handler(bad)
    args = p.parse_args([*files, "--out", str(tmp_path / "report")])
    assert args.handler(args) == 0
    assert f"one flight in {len(files)} files of a rotated recording" in capsys.readouterr().out
    summary = json.loads((tmp_path / "report" / "summary.json").read_text())
    assert summary["frames_missing"] == 0 and summary["frames_refused"] == 0
    assert summary["frames"] == N_FRAMES  # the whole flight's, each file's 3-D estimates as recorded
    assert summary["with_3d"] == sum(t["ned_m"] is not None for t in recorded)


# --------------------------------------------------------------------------- the check alone (pure)

META = {"vehicle": "uav1", "recorder": "onboard", "config_yaml": "a: 1\n"}


def _part(index: int, started: str, first_us: int | None = None, last_us: int | None = None, **meta) -> FilePart:
    return FilePart(
        rotated_path("f.mcap", index),
        {**META, "file_index": str(index), "started_utc": started, **meta},
        first_us,
        last_us,
    )


@pytest.mark.parametrize(
    "parts, problem",
    [
        pytest.param(
            [_part(0, "2026-01-01T00:00:00", 1, 10), _part(1, "2026-01-01T00:10:00", 11, 20)], None, id="old-files"
        ),
        pytest.param(
            [_part(0, "2026-01-01T00:00:00"), _part(1, "2026-01-01T00:10:00", config_yaml="a: 2\n")],
            "f.1.mcap: of another recording than f.mcap (its metadata config_yaml differs)",
            id="old-files-another-configuration",
        ),
        pytest.param(
            [_part(0, "2026-01-01T00:10:00"), _part(1, "2026-01-01T00:00:00")],
            "f.1.mcap: of another recording than f.mcap (opened at 2026-01-01T00:00:00, before it: "
            "2026-01-01T00:10:00)",
            id="old-files-opened-before",
        ),
        pytest.param(
            [_part(0, "2026-01-01T00:00:00", 1, 10), _part(1, "2026-01-01T00:10:00", 5, 20)],
            "f.1.mcap: of another recording than f.mcap (its first frame, time_boot_us 5, is not after that "
            "file's last, 10)",
            id="old-files-boot-clock-back",
        ),
        pytest.param(
            [_part(0, "2026-01-01T00:00:00"), _part(1, "2026-01-01T00:10:00", recording_id="b")],
            "f.1.mcap: of another recording than f.mcap (recording_id b, not none)",
            id="one-with-an-id",
        ),
        pytest.param(
            [_part(0, "x", recording_id="a"), _part(1, "x", recording_id="a", config_yaml="other")],
            None,
            id="same-id",
        ),
        pytest.param(
            [FilePart("f.mcap", {}), _part(1, "x")],
            "f.mcap: no irtrack metadata: not a file of a recording (python -m onboard --record)",
            id="no-metadata",
        ),
        pytest.param(
            [_part(0, "x", recording_id="a"), _part(1, "x", recording_id="a", file_index="one")],
            "f.1.mcap: metadata file_index 'one' is not a file number",
            id="bad-index",
        ),
    ],
)
def test_parts_are_one_recordings_each_once_in_order(parts, problem):
    assert parts_problem(parts) == problem


@pytest.mark.parametrize("index", ["\u00b2", "\u0662", "-1", ""])
def test_a_file_index_that_is_no_ascii_number_is_refused_in_words_not_a_traceback(index):
    """str.isdigit() holds for a superscript two, which int() cannot read (a ValueError out of the check, and out of
    the notes of a single file's replay); an Arabic-Indic two int() reads as 2, a file number no recorder writes."""
    from onboard.app.replay import Recording, more_files_note, rotated_part_note

    parts = [_part(0, "x", recording_id="a"), _part(1, "x", recording_id="a", file_index=index)]
    assert parts_problem(parts) == f"f.1.mcap: metadata file_index {index!r} is not a file number"
    rec = Recording("f.1.mcap", {**META, "file_index": index}, {}, [], [], [], None, None, None, {})
    assert rotated_part_note(rec) is None and more_files_note(rec, "python -m onboard.replay") is None


def test_an_older_files_start_time_without_a_zone_is_compared_as_utc_not_a_type_error():
    """The recorder writes started_utc with +00:00; a file whose metadata has none (edited, or another writer's) was
    compared with an aware time: TypeError, a traceback instead of the check's line."""
    opened_before = [_part(0, "2026-01-01T00:10:00+00:00"), _part(1, "2026-01-01T00:00:00")]
    assert parts_problem(opened_before) == (
        "f.1.mcap: of another recording than f.mcap (opened at 2026-01-01T00:00:00, before it: "
        "2026-01-01T00:10:00+00:00)"
    )
    assert parts_problem([_part(0, "2026-01-01T00:00:00"), _part(1, "2026-01-01T00:10:00+00:00")]) is None
