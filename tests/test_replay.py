"""Issue 13's Done-when, replay part: a closed-loop run (daemon with the inline estimator + simulator on 127.0.0.1,
10 s) recorded with --record, replayed by ``python -m onboard.replay`` (a real process): the tracks come back
equal, field for field and bit for bit, to the ones the daemon published; a changed configuration shows as
per-frame differences (the comparison can fail)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from onboard.app.replay import compare_tracks
from tests.onboard.test_record_daemon import record_pair

REPO = Path(__file__).resolve().parents[1]
REPLAY_TIMEOUT_S = 240.0


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


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    return record_pair(tmp_path_factory.mktemp("replay"))


def _replay(*args) -> subprocess.CompletedProcess:
    p = subprocess.run(
        [sys.executable, "-m", "onboard.replay", *map(str, args)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=REPLAY_TIMEOUT_S,
    )
    assert p.returncode == 0, f"replay exited {p.returncode}:\n{p.stdout[-2000:]}\n{p.stderr[-3000:]}"
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
    assert replayed == r.tracks  # what the daemon published over zenoh, every field, floats bit for bit
    assert sum(t["ned_m"] is not None for t in replayed) > 50  # with 3-D estimates, not only 2-D tracks
    n = len(r.tracks)
    assert f"compare: {n}/{n} frames identical, 0 differ, 0 unmatched" in p.stdout


@pytest.mark.integration
@pytest.mark.slow
def test_replay_with_another_configuration_shows_the_differences(recorded, tmp_path):
    p = _replay(recorded.daemon_mcap, "--compare", "--set", "estimator.pixel_sigma_px=0.9")
    last = p.stdout.strip().splitlines()[-1]
    assert last.startswith("compare: ") and " 0 differ" not in last, last
    assert "ned_m" in p.stdout and "|d ned|" in p.stdout


@pytest.mark.integration
@pytest.mark.slow
def test_replay_report_plots_a_recorded_flight_against_the_simulators_truth(recorded, tmp_path):
    out = tmp_path / "report"
    p = _replay(recorded.daemon_mcap, "--report", out, "--truth", recorded.sim_mcap)
    assert "report:" in p.stdout
    for name in ("trajectory.png", "errors.png", "frame.png"):
        assert (out / name).stat().st_size > 10_000, name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["truth"] is True and summary["with_3d"] > 50
    assert summary["median_track_to_truth_px"] < 1.0  # truth matched frame by frame
    _replay(recorded.daemon_mcap, "--report", tmp_path / "no_truth")  # asserts exit 0
    assert not (tmp_path / "no_truth" / "errors.png").exists() and (tmp_path / "no_truth" / "trajectory.png").exists()


@pytest.mark.integration
@pytest.mark.slow
def test_replay_with_the_tracker_in_a_second_process_gives_the_same_tracks(recorded, tmp_path):
    out = tmp_path / "tracks2.jsonl"
    p = _replay(recorded.daemon_mcap, "--jobs", "2", "--compare", "--out", out)
    replayed = [json.loads(line) for line in out.read_text().splitlines()]
    assert replayed == recorded.tracks  # the forked imaging process changes where the tracker runs, not what it gives
    n = len(recorded.tracks)
    assert f"compare: {n}/{n} frames identical, 0 differ, 0 unmatched" in p.stdout
