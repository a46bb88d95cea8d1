"""``python -m groundsim report``: the flight report of a daemon recording, drawn on the ground side (a real
process), against the simulator's recording of the same run."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
REPORT_TIMEOUT_S = 240.0


@pytest.fixture(scope="module")
def recorded(recorded_p1_flight):
    """The session's recorded P1 flight (tests/conftest.py), which the recording and the replay tests read too: the
    report only reads it."""
    return recorded_p1_flight


def _report(*args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "groundsim", "report", *map(str, args)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=REPORT_TIMEOUT_S,
    )


@pytest.mark.integration
@pytest.mark.slow
def test_report_plots_a_recorded_flight_against_the_simulators_truth_then_none_of_them_without_it(recorded, tmp_path):
    out = tmp_path / "report"
    p = _report(recorded.daemon_mcap, "--truth", recorded.sim_mcap, "--out", out)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "report:" in p.stdout
    for name in ("trajectory.png", "errors.png", "frame.png", "objects.png"):  # objects: P1's target alone
        assert (out / name).stat().st_size > 10_000, name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["truth"] is True and summary["frames"] == len(recorded.tracks)
    assert summary["median_track_to_truth_px"] < 1.0  # truth matched frame by frame
    # into the folder just filled, without truth this time: neither an error plot of its own (no truth, no error
    # plot) nor the earlier one (a used folder keeps none of the earlier plots); both must hold for errors.png to go
    p = _report(recorded.daemon_mcap, "--out", out)
    assert p.returncode == 0, p.stderr[-3000:]
    assert not (out / "errors.png").exists() and (out / "trajectory.png").exists()
    assert not (out / "objects.png").exists()  # (no truth of the objects either)


@pytest.mark.subprocess
def test_report_of_a_file_that_is_not_a_daemon_recording_is_one_line_exit_2(tmp_path):
    bogus = tmp_path / "x.mcap"
    bogus.write_bytes(b"not an mcap file at all")
    p = _report(bogus, "--out", tmp_path / "r")
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "groundsim report: error:" in p.stderr, p.stderr


@pytest.mark.integration
def test_a_truth_file_without_truth_and_an_out_that_cannot_be_made_are_refused_before_the_replay(recorded, tmp_path):
    p = _report(recorded.daemon_mcap, "--truth", recorded.daemon_mcap, "--out", tmp_path / "a")
    assert p.returncode == 2, p.stderr[-3000:]
    assert f"--truth {recorded.daemon_mcap}: no /groundsim/truth messages" in p.stderr
    (tmp_path / "afile").write_text("")
    p = _report(recorded.daemon_mcap, "--out", tmp_path / "afile" / "r")
    assert p.returncode == 2 and "cannot create the directory" in p.stderr, p.stderr[-3000:]
    assert "replayed" not in p.stderr  # refused before the replay


def test_a_truth_of_another_run_is_told_from_this_flights_by_where_the_camera_was_and_looked():
    """truth_mismatch: the truth rows' camera against the one the flight's telemetry placed, frame by frame; another
    run's camera looking elsewhere (the audit's case: observers 3 m apart, axes 104 deg) or flying elsewhere, or a
    truth with none of the flight's capture times, is named; a tenth of a degree and decimetres of navigation error
    are one flight."""
    import math

    from groundsim.app.report import TRUTH_MATCH_MAX_DEG, TRUTH_MATCH_MAX_M, truth_mismatch
    from onboard.core.frames import GeodeticOrigin, geodetic_from_ned1

    def q_yaw(deg):
        h = math.radians(deg) / 2  # turned about north: the optical axis (the camera's z) turns by deg
        return [math.cos(h), math.sin(h), 0.0, 0.0]

    origin = GeodeticOrigin(32.0, 118.8, 10.0)
    inputs, truth = [], []
    for k in range(20):
        t_us = 1_000_000 + 33_333 * k
        p = [5.0 * k, 2.0 * k, -100.0]
        inputs.append(
            {"time_boot_us": t_us, "pose": {"p_ned_m": p, "origin": vars(origin), "q_ned_from_cam": q_yaw(30)}}
        )
        lat, lon, alt = geodetic_from_ned1(p[0] + 0.3, p[1] - 0.2, p[2], origin)  # decimetres of navigation error
        row = {"time_boot_us": t_us, "observer_lat_deg": lat, "observer_lon_deg": lon, "observer_alt_m": alt}
        truth.append(
            row
            | dict(zip(("q_ned_from_cam_w", "q_ned_from_cam_x", "q_ned_from_cam_y", "q_ned_from_cam_z"), q_yaw(30.1)))
        )
    assert truth_mismatch(inputs, truth) is None
    elsewhere = []
    for row, inp in zip(truth, inputs):
        p = inp["pose"]["p_ned_m"]
        lat, lon, alt = geodetic_from_ned1(p[0] + 2 * TRUTH_MATCH_MAX_M, p[1], p[2], origin)
        elsewhere.append({**row, "observer_lat_deg": lat, "observer_lon_deg": lon, "observer_alt_m": alt})
    why = truth_mismatch(inputs, elsewhere)
    assert why is not None and "its observer was 50 m from" in why and "medians over 20 frames" in why
    turned = [
        {
            **row,
            **dict(
                zip(
                    ("q_ned_from_cam_w", "q_ned_from_cam_x", "q_ned_from_cam_y", "q_ned_from_cam_z"),
                    q_yaw(30 + 2 * TRUTH_MATCH_MAX_DEG),
                )
            ),
        }
        for row in truth
    ]
    why = truth_mismatch(inputs, turned)
    assert why is not None and why.startswith("its camera looked 10.0 deg away from")
    later = [{**row, "time_boot_us": row["time_boot_us"] + 7} for row in truth]
    assert truth_mismatch(inputs, later) == "none of the flight's 20 posed frames has a truth row at its capture time"


def test_a_truth_whose_camera_is_within_a_few_degrees_is_told_apart_by_the_navigation_error_it_records():
    """groundsim's truth rows record the attitude error the telemetry carried: put back on their camera, the
    flight's own truth matches to interpolation (hundredths of a degree), and another run's camera turned 1.7 deg
    (a P1 flight against a P1g truth: within the 5 deg a truth without that record is allowed) is refused."""
    import math

    import numpy as np

    from groundsim.app.report import TRUTH_MATCH_NAV_MAX_DEG, truth_mismatch
    from onboard.core.frames import GeodeticOrigin, geodetic_from_ned1, quat_from_rotvec, quat_multiply

    def q_about_north(deg):
        h = math.radians(deg) / 2
        return np.array([math.cos(h), math.sin(h), 0.0, 0.0])

    origin = GeodeticOrigin(32.0, 118.8, 10.0)
    phi = np.radians([0.15, -0.1, 0.2])  # RTK-sized attitude error, NED
    inputs, own, other = [], [], []
    for k in range(20):
        t_us = 1_000_000 + 33_333 * k
        p = [5.0 * k, 2.0 * k, -100.0]
        q_true = q_about_north(30.0 + 0.5 * k)
        inputs.append(
            {
                "time_boot_us": t_us,
                "pose": {
                    "p_ned_m": p,
                    "origin": vars(origin),
                    "q_ned_from_cam": list(quat_multiply(quat_from_rotvec(phi), q_true)),
                },
            }
        )
        lat, lon, alt = geodetic_from_ned1(*p, origin)
        row = {"time_boot_us": t_us, "observer_lat_deg": lat, "observer_lon_deg": lon, "observer_alt_m": alt}
        row |= dict(zip(("nav_att_err_n_rad", "nav_att_err_e_rad", "nav_att_err_d_rad"), phi.tolist()))
        keys = ("q_ned_from_cam_w", "q_ned_from_cam_x", "q_ned_from_cam_y", "q_ned_from_cam_z")
        own.append(row | dict(zip(keys, q_true.tolist())))
        other.append(row | dict(zip(keys, q_about_north(30.0 + 0.5 * k + 1.7).tolist())))
    assert truth_mismatch(inputs, own) is None
    why = truth_mismatch(inputs, other)
    assert why is not None and why.startswith("its camera with the navigation error it records looked 1.7 deg away")
    assert f"at most {TRUTH_MATCH_NAV_MAX_DEG:g} deg" in why
    legacy = [{k: v for k, v in r.items() if not k.startswith("nav_att_err")} for r in other]
    assert truth_mismatch(inputs, legacy) is None  # without the record: within the navigation errors' 5 deg
