"""``groundsim report --truth``: a simulator recording cut short covers only the start of the flight.  The report
says so once (how much of the flight it covers), marks ``summary.json``, and no numpy warning reaches the user.
The recordings and the replay are stand-ins (the report's own code runs, down to the plots): a real pair takes a
daemon and a simulator run (tests/groundsim/test_report.py)."""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path
from types import SimpleNamespace

import pytest

from groundsim.app.report import TruthCoverage, cmd_report, truth_coverage
from onboard.core.frames import GeodeticOrigin, geodetic_from_ned1

ORIGIN = GeodeticOrigin(32.0, 118.8, 10.0)
FRAMES = 20
FRAME_US = 100_000
T0_US = 1_000_000
FIRST_3D = 12  # the estimator's first 3-D estimate: after the cut truth's last row, as in the audit's flight
CUT_AFTER = 10  # the truth recording's last frame
CUT = "it ends at byte 12000000"


def _track(k: int) -> dict:
    p_ned_m = [100.0 + k, 50.0, -30.0]
    track = {"seq": k, "time_boot_us": T0_US + k * FRAME_US, "origin": vars(ORIGIN), "u_px": 320.0, "v_px": 256.0}
    if k >= FIRST_3D:
        track |= {"ned_m": p_ned_m, "cov_ned_m2": [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], "observable": True}
    return track


def _camera(k: int) -> list:
    return [float(k), 0.0, -50.0]


def _truth_row(k: int) -> dict:
    obs = geodetic_from_ned1(*_camera(k), ORIGIN)
    tgt = geodetic_from_ned1(100.0 + k, 50.5, -30.0, ORIGIN)
    return {
        "seq": k,
        "time_boot_us": T0_US + k * FRAME_US,
        "observer_lat_deg": obs[0],
        "observer_lon_deg": obs[1],
        "observer_alt_m": obs[2],
        "target_lat_deg": tgt[0],
        "target_lon_deg": tgt[1],
        "target_alt_m": tgt[2],
        "target_u_px": 320.5,
        "target_v_px": 256.0,
        **dict(zip(("q_ned_from_cam_w", "q_ned_from_cam_x", "q_ned_from_cam_y", "q_ned_from_cam_z"), (1, 0, 0, 0))),
    }


def _input(k: int) -> dict:
    pose = {"p_ned_m": _camera(k), "p_cam_ned_m": _camera(k), "origin": vars(ORIGIN), "q_ned_from_cam": [1, 0, 0, 0]}
    return {"seq": k, "time_boot_us": T0_US + k * FRAME_US, "pose": pose}


def _recording(path: str, *, truth: list, truncated: str | None, inputs: list) -> SimpleNamespace:
    return SimpleNamespace(
        path=path,
        name=path,
        files=[path],
        inputs=inputs,
        truth=truth,
        truncated=truncated,
        frames={},
        metadata={},
        statuses=[],
    )


@pytest.fixture
def cut_truth_flight(monkeypatch, tmp_path):
    """``groundsim report FLIGHT --truth SIM``: SIM cut after frame CUT_AFTER, before the first 3-D estimate."""
    import groundsim.evaluation.report_plots as plots
    import onboard.app.replay as replay_module

    files = {
        "flight.mcap": _recording("flight.mcap", truth=[], truncated=None, inputs=[_input(k) for k in range(FRAMES)]),
        "sim.mcap": _recording(
            "sim.mcap", truth=[_truth_row(k) for k in range(CUT_AFTER + 1)], truncated=CUT, inputs=[]
        ),
    }
    tracks = [_track(k) for k in range(FRAMES)]
    monkeypatch.setattr(replay_module, "load_recording", files.__getitem__)
    monkeypatch.setattr(replay_module, "config_of", lambda rec, path: None)
    monkeypatch.setattr(
        replay_module,
        "replay",
        lambda rec, config, **_: SimpleNamespace(
            tracks=tracks, frames_fed=FRAMES, frames_missing=0, frames_refused=0, wall_s=0.0
        ),
    )
    # the error plot is where a cut truth shows (numpy's warning came from its scale); the trajectory is not drawn
    monkeypatch.setattr(plots, "plot_trajectory", lambda path, run, title: path)
    return argparse.Namespace(mcap=["flight.mcap"], truth="sim.mcap", out=str(tmp_path / "report"), config=None)


def test_a_cut_truth_is_said_once_marked_in_the_summary_and_no_numpy_warning_reaches_the_user(cut_truth_flight, capsys):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert cmd_report(cut_truth_flight) == 0
    assert [str(w.message) for w in caught] == []
    out = capsys.readouterr().out
    notes = [line for line in out.splitlines() if line.startswith("note:")]
    assert notes == [
        f"note: --truth sim.mcap is cut short ({CUT}): its truth covers 11 of the flight's 20 frames, "
        "t = 0.0..1.0 s of 0..1.9 s; it covers none of the 8 frames with a 3-D estimate: the error plot is empty"
    ]
    summary = json.loads((Path(cut_truth_flight.out) / "summary.json").read_text())
    assert summary["truth_covers"] == {
        "frames": 11,
        "of_frames": 20,
        "with_3d": 0,
        "of_with_3d": 8,
        "from_s": 0.0,
        "to_s": 1.0,
        "flight_s": 1.9,
        "cut_short": CUT,
    }


def test_frames_the_replay_could_not_track_are_said_and_counted_in_the_summary(cut_truth_flight, capsys, monkeypatch):
    """20 frames removed from a flight's file had changed its report (its 3-D gone with the track the gap broke)
    with nothing said; onboard.replay said "20 missing from the file"."""
    import onboard.app.replay as replay_module

    tracks = [_track(k) for k in range(FRAMES - 3)]
    monkeypatch.setattr(
        replay_module,
        "replay",
        lambda rec, config, **_: SimpleNamespace(
            tracks=tracks, frames_fed=FRAMES - 2, frames_missing=2, frames_refused=1, wall_s=0.0
        ),
    )
    assert cmd_report(cut_truth_flight) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if "missing from the file" in line]
    assert notes == [
        f"note: flight.mcap: of the {FRAMES} frames the daemon took, 2 are missing from the file (the recorder "
        f"dropped them) and 1 were refused in the replay: the report is of the {FRAMES - 3} tracks of the rest"
    ]
    summary = json.loads((Path(cut_truth_flight.out) / "summary.json").read_text())
    assert (summary["frames_missing"], summary["frames_refused"], summary["frames"]) == (2, 1, FRAMES - 3)


def test_truth_coverage_counts_the_frames_and_the_span_it_covers():
    tracks = [_track(k) for k in range(FRAMES)]
    whole = truth_coverage(tracks, [_truth_row(k) for k in range(FRAMES)])
    assert whole == TruthCoverage(20, 20, 8, 8, 0.0, 1.9, 1.9, None) and not whole.partial
    late = truth_coverage(tracks, [_truth_row(k) for k in range(5, 15)], CUT)
    assert (late.frames, late.with_3d, late.from_s, late.to_s, late.partial) == (10, 3, 0.5, 1.4, True)
    assert "the errors are of the 3 of 8 frames with a 3-D estimate it covers" in late.note("sim.mcap")
    none = truth_coverage(tracks, [], CUT)
    assert (none.frames, none.from_s, none.to_s) == (0, None, None)
    assert "its truth covers none of the flight's frames" in none.note("sim.mcap")
