"""Replay: a closed-loop run (daemon with the inline estimator + simulator on 127.0.0.1, 10 s) recorded with
--record, replayed by ``python -m onboard.replay`` (a real process): the tracks come back equal, field for field
and bit for bit, to the ones the daemon published; a changed configuration shows as per-frame differences (the
comparison can fail: exit 3); a recording of a worker estimator is compared within the two estimates' sigma, saying why; a file
that is not a recording is refused in one line; Ctrl-C stops it in one line."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from onboard.app.replay import EXIT_CONFIG, EXIT_DIFFERENT, EXIT_OK, main
from onboard.app.replay_compare import compare_objects, compare_tracks, compare_within_sigma
from tests.process_helpers import WatchedCommand
from tests.recording_edits import rewrite_recording

REPO = Path(__file__).resolve().parents[1]
REPLAY_TIMEOUT_S = 240.0
CTRL_C_AFTER_S = 2.0  # after the replay began
REPLAY_START_TIMEOUT_S = 60.0  # imports and reading the recording on a busy 2-core machine


def test_compare_tracks_reports_fields_and_distances():
    a = [
        {"seq": 1, "time_boot_us": 10, "ned_m": [0.0, 0.0, 0.0], "u_px": 1.0, "v_px": 2.0, "state": "tracking"},
        {"seq": 2, "time_boot_us": 20, "ned_m": None, "u_px": None, "v_px": None, "state": "lost"},
        {"seq": 3, "time_boot_us": 30, "state": "lost"},
    ]
    b = [
        {"seq": 1, "time_boot_us": 10, "ned_m": [3.0, 4.0, 0.0], "u_px": 1.0, "v_px": 2.0, "state": "tracking"},
        {"seq": 2, "time_boot_us": 20, "ned_m": None, "u_px": None, "v_px": None, "state": "lost"},
        {"seq": 4, "time_boot_us": 40, "state": "lost"},
    ]
    diffs, matched, unmatched = compare_tracks(a, b)
    assert matched == 2 and unmatched == 2
    assert len(diffs) == 1 and diffs[0].seq == 1 and diffs[0].fields == ("ned_m",) and diffs[0].d_pos_m == 5.0
    assert diffs[0].d_uv_px == 0.0


def test_a_recording_made_before_a_key_the_replay_states_compares_identical():
    """A recording from a daemon before ``los_sigma_bias_deg`` lacks it; its replay states it (the recorded config's
    bias): not a difference, so an older recording still replays identical.  Where both state it, it is compared."""
    rec = {"seq": 1, "time_boot_us": 10, "los_sigma_el_deg": 0.11, "estimate_epoch": 0}
    replayed = {**rec, "los_sigma_bias_deg": 0.1, "compensated_us": 0}
    assert compare_tracks([rec], [replayed]) == ([], 1, 0)
    diffs, _, _ = compare_tracks([{**rec, "los_sigma_bias_deg": 0.2}], [replayed])
    assert [d.fields for d in diffs] == [("los_sigma_bias_deg",)]


def test_a_replayed_track_takes_the_utc_stamp_of_the_recorded_frame():
    """Replayed tracks had null UTC stamps on every frame (the daemon maps the boot clock through the autopilot's
    SYSTEM_TIME, which the pipeline does not see): a replay fed to the fleet fusion fell back to arrival times."""
    from onboard.app.replay import _recorded_utc, _with_recorded_utc
    from tests.fakes import tracking_track

    recorded = [
        {"seq": 7, "time_boot_us": 1_000, "time_unix_us": None, "time_unix_sigma_us": None},
        {"seq": 8, "time_boot_us": 34_333, "time_unix_us": 1_800_000_000_034_333, "time_unix_sigma_us": 310},
        {"seq": 8, "time_boot_us": 34_333, "time_unix_us": 1_800_000_000_034_334, "time_unix_sigma_us": 311},
    ]
    utc_of = _recorded_utc(recorded)
    assert _with_recorded_utc(tracking_track(seq=7, time_boot_us=1_000), utc_of).time_unix_us is None
    assert _with_recorded_utc(tracking_track(seq=9, time_boot_us=34_333), utc_of).time_unix_us is None
    first = _with_recorded_utc(tracking_track(seq=8, time_boot_us=34_333), utc_of)
    second = _with_recorded_utc(tracking_track(seq=8, time_boot_us=34_333), utc_of)  # a duplicated frame: in turn
    assert (first.time_unix_us, first.time_unix_sigma_us) == (1_800_000_000_034_333, 310)
    assert (second.time_unix_us, second.time_unix_sigma_us) == (1_800_000_000_034_334, 311)
    assert _with_recorded_utc(tracking_track(seq=8, time_boot_us=34_333), utc_of).time_unix_us is None


def test_compare_objects_matches_frames_in_order_and_counts_the_identical_ones():
    def frame(t_us: int, index: int, n: int, **extra) -> dict:
        return {"time_boot_us": t_us, "frame_index": index, "objects": [{"id": k} for k in range(n)], **extra}

    recorded = [
        frame(10, 0, 1),
        frame(20, 1, 2),
        frame(20, 1, 3),  # the same key twice (a duplicated frame): matched in turn
        frame(30, 2, 1),  # not replayed
    ]
    replayed = [frame(10, 0, 1), frame(20, 1, 2), frame(20, 1, 4), frame(40, 3, 1)]
    assert compare_objects(recorded, replayed) == (3, 2, 2)  # (matched, identical, unmatched of either list)
    assert compare_objects(replayed, replayed) == (4, 4, 0)


def _track(seq: int, ned_m, cov=None) -> dict:
    return {"seq": seq, "time_boot_us": 1000 * seq, "ned_m": ned_m, "cov_ned_m2": cov}


def test_compare_within_sigma_counts_the_positions_beyond_the_recorded_covariance():
    cov = [[4.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]  # sigma 2 m north, 1 m east and down
    recorded = [
        _track(1, [0.0, 0.0, 0.0], cov),
        _track(2, [0.0, 0.0, 0.0], cov),
        _track(3, [0.0, 0.0, 0.0], cov),
        _track(4, None),
        _track(5, [1.0, 1.0, 1.0], cov),
    ]
    replayed = [
        _track(1, [5.0, 0.0, 0.0]),  # 2.5 sigma north: within
        _track(2, [0.0, 4.0, 0.0]),  # 4 sigma east: beyond
        _track(3, [0.0, 0.0, 0.0]),
        _track(4, [1.0, 2.0, 3.0]),  # a position where the recording had none
        _track(5, None),
    ]
    res = compare_within_sigma(recorded, replayed)
    assert (res.compared, res.beyond, res.position_only_one) == (3, 1, 2)
    assert res.max_sigma == pytest.approx(4.0) and res.gate_sigma == 3.0
    assert compare_within_sigma(recorded, replayed, gate_sigma=2.0).beyond == 2


def test_compare_within_sigma_takes_both_estimates_covariances():
    """Two honest estimates of one target differ by their errors together: a replayed estimate that is itself
    uncertain (another motion model chosen a frame apart, say) is not beyond the recorded one's sigma alone."""
    small = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    large = [[99.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    recorded = [_track(1, [0.0, 0.0, 0.0], small), _track(2, [0.0, 0.0, 0.0], small)]
    replayed = [_track(1, [20.0, 0.0, 0.0], large), _track(2, [0.0, 20.0, 0.0], large)]
    res = compare_within_sigma(recorded, replayed)
    # north: 20 m against sqrt(1 + 99) = 10 m, 2 sigma; east: 20 m against sqrt(2) m, 14.1 sigma
    assert (res.compared, res.beyond) == (2, 1) and res.max_sigma == pytest.approx(20.0 / math.sqrt(2.0))


def test_a_replay_that_tracks_another_object_differs_however_wide_the_covariances():
    """An operator's selection is not replayed: the recording's track moved to another object (a new track_id)
    while the replay stayed on the first.  Two unobservable estimates of targets 350 m apart were within each
    other's 3 sigma, and a worker's recording compared 'within sigma' on every frame; a frame tracking another
    object is now counted apart, not compared, and is a difference whatever the worker."""
    from onboard.app.replay_compare import beyond_a_workers_sigma

    wide = [[1e5, 0.0, 0.0], [0.0, 1e5, 0.0], [0.0, 0.0, 1e5]]  # ~316 m a side: unobservable
    recorded = [{**_track(k, [0.0, 0.0, 0.0], wide), "track_id": 3 if k < 3 else 8} for k in range(1, 6)]
    replayed = [
        {**_track(k, [350.0, 0.0, 0.0] if k >= 3 else [0.0, 0.0, 0.0], wide), "track_id": 3} for k in range(1, 6)
    ]
    res = compare_within_sigma(recorded, replayed)
    assert (res.compared, res.other_object, res.beyond) == (2, 3, 0)
    assert beyond_a_workers_sigma(res)


def test_a_workers_recording_differs_only_beyond_what_its_timing_explains():
    """A few tenths of a per cent of the positions a little beyond 3 sigma are chance (a newcomer's recording of the
    shipped flow: 3 of 691, at most 3.7 sigma); over 1 % beyond, or one past 6 sigma, is a difference."""
    from onboard.app.replay_compare import SigmaComparison, beyond_a_workers_sigma

    assert not beyond_a_workers_sigma(SigmaComparison(691, 3, 3.7, 0, 3.0))
    assert beyond_a_workers_sigma(SigmaComparison(691, 8, 4.1, 0, 3.0))
    assert beyond_a_workers_sigma(SigmaComparison(691, 1, 10.0, 0, 3.0))
    assert not beyond_a_workers_sigma(SigmaComparison(0, 0, 0.0, 0, 3.0))
    # a replay that lost every position (or most) is not the recording, whatever the few it kept look like
    assert beyond_a_workers_sigma(SigmaComparison(0, 0, 0.0, 379, 3.0))
    assert beyond_a_workers_sigma(SigmaComparison(34, 0, 1.0, 345, 3.0))
    assert not beyond_a_workers_sigma(SigmaComparison(378, 1, 4.2, 1, 3.0))  # a first estimate a frame apart
    assert not beyond_a_workers_sigma(SigmaComparison(60, 0, 2.0, 3, 3.0))


@pytest.mark.parametrize("content", [b"", b"not a recording at all\n", b"\x89MCA"], ids=["empty", "text", "cut"])
@pytest.mark.parametrize("with_config", [False, True], ids=["metadata", "config"])
def test_a_file_that_is_not_mcap_is_refused_in_one_line(tmp_path, capsys, content, with_config):
    bad = tmp_path / "flight.mcap"
    bad.write_bytes(content)
    args = [str(bad)] + (["--config", str(REPO / "config" / "onboard.yaml")] if with_config else [])
    assert main(args) == EXIT_CONFIG
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"{bad}: not an MCAP recording ("), err


def test_the_flight_report_option_says_where_the_report_went(tmp_path, capsys):
    assert main([str(tmp_path / "flight.mcap"), "--report", str(tmp_path / "out")]) == EXIT_CONFIG
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"python -m onboard.replay: the flight report moved: python -m groundsim report {tmp_path}/flight.mcap"
    ]


@pytest.fixture
def recorded(recorded_p1_flight):
    """The suite's one recorded P1 flight (tests/conftest.py), read only."""
    return recorded_p1_flight


def _rewritten(src: Path, dst: Path, worker: str, shift) -> Path:
    """A copy of the recording ``src`` whose metadata says the daemon ran ``estimator.worker: worker``, and whose
    recorded track dicts went through ``shift`` (which may change them in place)."""

    def shifted(data: bytes) -> bytes:
        return json.dumps(shift(json.loads(data)), separators=(",", ":")).encode()

    rewrite_recording(src, dst, lambda _t, _i, schema: shifted if schema.startswith("irtrack.track/") else None, worker)
    return dst


def _replay(*args, returncode: int = EXIT_OK) -> subprocess.CompletedProcess:
    p = subprocess.run(
        [sys.executable, "-m", "onboard.replay", *map(str, args)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=REPLAY_TIMEOUT_S,
    )
    assert p.returncode == returncode, f"replay exited {p.returncode}:\n{p.stdout[-2000:]}\n{p.stderr[-3000:]}"
    return p


@pytest.mark.integration
@pytest.mark.slow
def test_replay_reproduces_the_recorded_tracks_bit_for_bit(recorded, tmp_path):
    r = recorded
    assert r.daemon_rc == 0 and r.sim_rc == 0 and len(r.tracks) > 100
    out = tmp_path / "tracks.jsonl"
    p = _replay(r.daemon_mcap, "--compare", "--out", out)
    print(p.stdout)
    replayed = [json.loads(line) for line in out.read_text().splitlines()]
    # what the daemon published over zenoh, every field, floats bit for bit; the UTC stamps too, the recorded
    # frame's (they were null in every replayed track: the daemon makes them from the autopilot's SYSTEM_TIME)
    assert all(t["time_unix_us"] is not None for t in r.tracks[-10:])
    assert replayed == r.tracks
    assert sum(t["ned_m"] is not None for t in replayed) > 50  # with 3-D estimates, not only 2-D tracks
    n = len(r.tracks)
    assert f"compare: {n}/{n} frames identical, 0 differ, 0 unmatched" in p.stdout


@pytest.mark.integration
def test_a_replays_live_view_shows_the_recorded_status_between_the_frames_it_came_between(recorded):
    """The replay's live view advertised the status channel and sent nothing on it (a newcomer's walkthrough: 0 of
    the recording's 33 status messages): it shows the recorded daemon's status now, each before the first frame
    recorded after it."""
    from onboard.app.replay import config_of, load_recording, replay

    rec = load_recording(str(recorded.daemon_mcap))
    assert len(rec.statuses) >= 5 and len(rec.input_log_ns) == len(rec.inputs)

    class Live:
        def __init__(self) -> None:
            self.calls: list = []

        def on_frame(self, frame) -> None:
            self.calls.append("frame")

        def on_status(self, payload: bytes) -> None:
            self.calls.append(json.loads(payload))

        def __getattr__(self, name):  # on_pose, on_track, on_objects: not looked at here
            return lambda *a: None

    live = Live()
    replay(rec, config_of(rec), live=live)
    shown = [c for c in live.calls if c != "frame"]
    assert shown == [json.loads(b) for _, b in rec.statuses]  # every one, in order, as recorded
    frames = [i for i, c in enumerate(live.calls) if c == "frame"]
    between = [i for i, c in enumerate(live.calls) if c != "frame" and frames[0] < i < frames[-1]]
    assert len(between) >= 5  # interleaved with the frames as the daemon published them, not all at one end
    # the daemon's own count of frames in each status rises along the replay
    ins = [c["frames"]["in"] for c in shown]
    assert ins == sorted(ins) and ins[-1] > 100


@pytest.mark.integration
@pytest.mark.slow
def test_replay_with_another_configuration_shows_the_differences(recorded, tmp_path):
    p = _replay(recorded.daemon_mcap, "--compare", "--set", "estimator.pixel_sigma_px=0.9", returncode=EXIT_DIFFERENT)
    last = p.stdout.strip().splitlines()[-1]
    assert last.startswith("compare: ") and " 0 differ" not in last, last
    assert "ned_m" in p.stdout and "|d ned|" in p.stdout


@pytest.mark.integration
@pytest.mark.slow
def test_replay_with_the_tracker_in_a_second_process_gives_the_same_tracks(recorded, tmp_path):
    # the recording's (default) objects chain needs each frame's pose: --jobs 2 says so and replays in one process
    p = _replay(recorded.daemon_mcap, "--jobs", "2", "--compare")
    n = len(recorded.tracks)
    assert f"compare: {n}/{n} frames identical, 0 differ, 0 unmatched" in p.stdout
    assert "--jobs 2: the objects image chain needs each frame's pose, so it replays in one process" in p.stderr
    # the single chain runs in the forked process: where the tracker runs changes nothing in what it gives
    single = ("--set", "imaging.chain=single")
    one, two = tmp_path / "tracks1.jsonl", tmp_path / "tracks2.jsonl"
    _replay(recorded.daemon_mcap, *single, "--out", one)
    p = _replay(recorded.daemon_mcap, *single, "--jobs", "2", "--out", two)
    assert "replays in one process" not in p.stderr
    replayed = [json.loads(line) for line in two.read_text().splitlines()]
    assert replayed == [json.loads(ln) for ln in one.read_text().splitlines()]
    assert sum(t["state"] == "tracking" for t in replayed) > 0.9 * len(replayed)


@pytest.mark.integration
@pytest.mark.slow
def test_a_worker_recording_is_compared_within_its_own_sigma_and_says_why(recorded, tmp_path):
    """The default daemon (estimator.worker: process) records estimates that depend on its timing: --compare says
    so and counts the positions beyond 3 sigma of the recorded covariance (here: the recording's tracks, one moved
    10 sigma, one half a sigma, in a copy that says it came from a process worker)."""
    moved = []

    def shift(track: dict) -> dict:
        if track.get("ned_m") is None or track.get("cov_ned_m2") is None or len(moved) == 2:
            return track
        chol = np.linalg.cholesky(np.asarray(track["cov_ned_m2"]))
        k = 10.0 if not moved else 0.5  # in sigmas of the recorded covariance
        track["ned_m"] = (np.asarray(track["ned_m"]) + chol @ np.array([k, 0.0, 0.0])).tolist()
        moved.append(k)
        return track

    copy = _rewritten(recorded.daemon_mcap, tmp_path / "process.mcap", "process", shift)
    p = _replay(copy, "--compare", returncode=EXIT_DIFFERENT)  # one position beyond 3 sigma
    lines = p.stdout.strip().splitlines()
    n = len(recorded.tracks)
    n_3d = sum(t["ned_m"] is not None and t.get("cov_ned_m2") is not None for t in recorded.tracks)
    assert moved == [10.0, 0.5]
    assert any(
        ln.startswith("compare: recorded with estimator.worker: process, whose estimates depend on its timing")
        and "only estimator.worker: inline recordings do" in ln
        for ln in lines
    ), p.stdout
    # the replay's covariance is the recording's: 10 sigma of one is 10 / sqrt(2) of the two together
    assert (
        f"compare: 3-D positions within 3 sigma of the recorded and replayed covariances: {n_3d - 1}/{n_3d}, 1 beyond "
        "(max 7.07" in p.stdout
    ), p.stdout
    assert lines[-1].startswith(f"compare: {n - 2}/{n} frames identical, 2 differ"), lines[-1]
    # the per-frame lines come after a header saying they are expected for a worker's recording (a newcomer read 78
    # of them as failures of a run that exited 0)
    header = next(i for i, ln in enumerate(lines) if ln.startswith("compare: 2 frames differ in their fields"))
    first_seq = next(i for i, ln in enumerate(lines) if ln.startswith("seq "))
    assert header < first_seq and "a worker's recording: expected" in lines[header]


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(120)
@pytest.mark.parametrize("how", ["ctrl_c", "sigterm"])
def test_ctrl_c_stops_a_replay_in_one_line_with_what_was_written(recorded, tmp_path, how):
    """SIGINT to the process group (a terminal's Ctrl-C; the tracker's process too, with --jobs 2), or SIGTERM to it
    (``timeout``, a job's limit): exit 130, one line naming the frames replayed and the partial --out file,
    no traceback from either process."""
    import signal

    out = tmp_path / "partial.jsonl"
    cmd = WatchedCommand(
        "onboard.replay",
        str(recorded.daemon_mcap),
        "--rate",
        "realtime",
        "--jobs",
        "2",
        "--out",
        str(out),
        watch="stdout",
        new_session=True,
    )
    try:
        cmd.wait_for("frames taken by the pipeline", REPLAY_START_TIMEOUT_S)
        first = cmd.lines[0]  # the recording's summary: the replay starts next
        assert "frames taken by the pipeline" in first, first
        time.sleep(CTRL_C_AFTER_S)  # mid-replay: the 10 s flight replays in real time
        if how == "ctrl_c":
            returncode, _, err = cmd.interrupt(group=True, exit_timeout_s=30)
        else:
            # to the group, as timeout and a job's limit send it: the imaging process gets it too
            returncode, _, err = cmd.interrupt(group=True, exit_timeout_s=30, signum=signal.SIGTERM)
    finally:
        cmd.kill()
    assert returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    # the replay's own log records may come first (a recording made on a loaded machine can hold a gap in its
    # frames, which the replay reports as the daemon did); the interruption itself is one line, the last
    lines = err.strip().splitlines()
    interrupted = [ln for ln in lines if ln.startswith("interrupted: ")]
    assert len(interrupted) == 1 and lines[-1] == interrupted[0], err
    assert all(ln.startswith(("WARNING ", "INFO ", "replay: ")) for ln in lines[:-1]), err  # log, progress lines
    n_written = len(out.read_text().splitlines())
    assert lines[-1].endswith(f"frames replayed; {out}: the {n_written} tracks of those frames"), lines[0]
