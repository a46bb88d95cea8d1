"""bench.fleet_flight's scoring on small synthetic records (the flights themselves print numbers)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.fleet_flight import (
    VEHICLES,
    FlightRecord,
    format_score,
    navigation_floor,
    score_flight,
    triangulate_ned_m,
)
from onboard.core.frames import GeodeticOrigin, geodetic_from_ned

ORIGIN = GeodeticOrigin(32.0, 118.8, 0.0)
RATE_HZ = 30.0
STEPS = 90  # 3 s
BOOT0_US = {"uav1": 5_000_000, "uav2": 41_000_000}  # different boot clocks, as the simulator's
UTC0_US = 1_780_000_000_000_000
ATOL_M = 1e-6  # 1 um
CAMS_NED_M = {"uav1": np.array([0.0, -145.0, -100.0]), "uav2": np.array([0.0, 145.0, -100.0])}
V_CAM_NED_MPS = np.array([3.0, 0.0, 0.0])
P0_TARGET_NED_M = np.array([592.0, -20.0, -120.0])
V_TARGET_NED_MPS = np.array([4.0, 1.5, 0.0])


@settings(max_examples=50, deadline=None)
@given(
    p=st.tuples(*[st.floats(-1000, 1000)] * 3),
    dirs=st.lists(st.tuples(*[st.floats(-1, 1)] * 3), min_size=2, max_size=4),
)
def test_triangulation_finds_the_point_every_ray_passes_through(p, dirs):
    p_ned_m = np.array(p)
    u = np.array(dirs)
    norms = np.linalg.norm(u, axis=1)
    if np.any(norms < 0.1):
        return
    u = u / norms[:, None]
    if np.linalg.matrix_rank(np.array([np.eye(3) - np.outer(x, x) for x in u]).sum(axis=0), tol=1e-3) < 3:
        return  # (nearly) parallel rays: no crossing
    cams = p_ned_m - 300.0 * u
    assert triangulate_ned_m(cams, u) == pytest.approx(p_ned_m, abs=1e-6 * 1000)


def _truth(vehicle: str, yaw_bias_rad: float = 0.0) -> dict:
    k = np.arange(STEPS)
    t_s = k / RATE_HZ
    target = P0_TARGET_NED_M + np.outer(t_s, V_TARGET_NED_MPS)
    cam = CAMS_NED_M[vehicle] + np.outer(t_s, V_CAM_NED_MPS)
    lat, lon, alt = geodetic_from_ned(target, ORIGIN)
    cols = {
        "time_boot_us": BOOT0_US[vehicle] + np.round(t_s * 1e6).astype(np.int64),
        "time_unix_us": UTC0_US + np.round(t_s * 1e6).astype(np.int64),
        "t_s": t_s,
        "target_lat_deg": lat,
        "target_lon_deg": lon,
        "target_alt_m": alt,
        "range_m": np.linalg.norm(target - cam, axis=1),
    }
    for i, a in enumerate("ned"):
        cols[f"target_{a}_m"] = target[:, i]
        cols[f"target_v{a}_mps"] = np.full(STEPS, V_TARGET_NED_MPS[i])
        cols[f"cam_{a}_m"] = cam[:, i]
        cols[f"nav_p_err_{a}_m"] = np.zeros(STEPS)
        cols[f"nav_att_err_{a}_rad"] = np.full(STEPS, yaw_bias_rad if a == "d" else 0.0)
    return cols


def _record(offset_ned_m=(0.0, 0.0, 0.0), sigma_m: float = 1.0) -> FlightRecord:
    """Both daemons track every frame (arriving 10 ms after it); one two-vehicle fleet track per step, 5 ms
    after the later track, at the truth plus ``offset_ned_m`` with an isotropic ``sigma_m``."""
    truth = {v: _truth(v) for v in VEHICLES}
    rec = FlightRecord(truth=truth, sim_start_unix_s=1000.0)
    origin = {"lat_deg": ORIGIN.lat_deg, "lon_deg": ORIGIN.lon_deg, "alt_m": ORIGIN.alt_m}
    for v in VEHICLES:
        t_frame = 1000.0 + truth[v]["t_s"]
        rec.frames_rx[v] = {int(b): float(t) for b, t in zip(truth[v]["time_boot_us"], t_frame)}
        rec.tracks[v] = [
            (
                float(t + 0.010),
                {
                    "time_boot_us": int(b),
                    "time_unix_us": int(u),
                    "los_ned": [1.0, 0.0, 0.0],
                    "observable": False,
                    "ned_m": None,
                    "origin": origin,
                },
            )
            for b, u, t in zip(truth[v]["time_boot_us"], truth[v]["time_unix_us"], t_frame)
        ]
    for k in range(STEPS):
        p = np.array([truth["uav1"][f"target_{a}_m"][k] for a in "ned"]) + np.asarray(offset_ned_m)
        t_us = int(truth["uav1"]["time_unix_us"][k])
        rec.fleet.append(
            (
                1000.0 + truth["uav1"]["t_s"][k] + 0.015,
                {
                    "time_unix_us": t_us,
                    "ned_m": list(p),
                    "origin": origin,
                    "cov_ned_m2": (np.eye(3) * sigma_m**2).tolist(),
                    "observable": True,
                    "vehicles": [{"vehicle": v, "time_unix_us": t_us} for v in VEHICLES],
                },
            )
        )
    return rec


def test_exact_fleet_tracks_score_zero_error_full_share_and_their_latency():
    s = score_flight(_record())
    assert s["time_source"] == "vehicle"
    scored = STEPS - int(RATE_HZ)  # from one second after the first step both track
    assert s["scored_steps"] == scored
    assert s["fleet_position_share"] == pytest.approx(1.0)
    assert s["median_err_ratio"] == pytest.approx(0.0, abs=1e-6)
    assert s["beyond_3sigma_share"] == 0.0 and s["observable_share"] == 1.0
    assert s["latency_p99_s"] == pytest.approx(0.015, abs=1e-6)
    assert s["fuse_latency_p99_s"] == pytest.approx(0.005, abs=1e-6)
    assert s["navigation_floor_err_ratio"] == pytest.approx(0.0, abs=1e-9)
    for v in VEHICLES:
        assert s[f"{v}_alone_observable_share"] == 0.0


def test_an_offset_beyond_three_sigma_is_counted_and_scaled_by_range():
    s = score_flight(_record(offset_ned_m=(0.0, 0.0, 6.0), sigma_m=1.0))  # 6 m > 3 sqrt(3) m
    assert s["beyond_3sigma_share"] == 1.0
    rng = _truth("uav1")["range_m"][int(RATE_HZ) :]
    assert s["median_err_ratio"] == pytest.approx(float(np.median(6.0 / rng)), rel=1e-3)


def test_the_first_second_left_out_of_the_shares_is_scored_apart():
    """The first fused points of the target (the first second, which the shares leave out) are counted on their own:
    observable ones beyond 3 sigma there were invisible in every share."""
    first = int(RATE_HZ)  # steps 0-29: before one second after the first step both track
    s = score_flight(_record())
    assert (s["first_second_tracks"], s["first_second_observable"], s["first_second_confident_wrong"]) == (
        first,
        first,
        0,
    )
    rec = _record()
    for _, obj in rec.fleet[:3]:  # the first three points 6 m off at a 1 m sigma
        obj["ned_m"] = list(np.asarray(obj["ned_m"]) + (0.0, 0.0, 6.0))
    s = score_flight(rec)
    assert s["first_second_confident_wrong"] == 3
    assert s["beyond_3sigma_share"] == 0.0  # the shares do not see them
    assert "first second" in format_score(s, 0) and "3 observable and beyond 3 sigma" in format_score(s, 0)


def test_the_navigation_floor_grows_with_an_attitude_bias():
    bias_rad = math.radians(0.1)
    truth = {"uav1": _truth("uav1", bias_rad), "uav2": _truth("uav2")}
    floor = navigation_floor(truth, range(0, STEPS, 10))
    # one bearing off by the bias: about r * bias / sin(crossing angle) along the other ray, ~0.4 % at F1
    assert 0.002 < floor < 0.006
    assert navigation_floor({v: _truth(v) for v in VEHICLES}, range(0, STEPS, 10)) == pytest.approx(0.0, abs=1e-9)


def test_a_scenario_of_one_observer_is_refused_before_anything_starts(tmp_path, capsys):
    """--flight P1 started the router, both daemons and the fusion before the simulator refused a one-observer
    scenario (exit 1, a walkthrough of docs/fleet.md); refused first now, exit 2, nothing written."""
    from bench.fleet_flight import main_flight

    assert main_flight("P1", 1, None, None, tmp_path / "out", duration_s=5.0) == 2
    assert "--flight P1: expected a scenario of 2 observers (F1), got 1" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_flights_folder_is_cleared_of_a_run_before(tmp_path):
    """A reused --out kept the run before's logs (appended to), score and truth, read as the new flight's when it
    failed (a walkthrough of docs/fleet.md)."""
    from bench.fleet_flight import plan_flight

    out = tmp_path / "seed0"
    out.mkdir()
    for name in ("sim.log", "uav1.log", "score.json", "record.json", "truth.uav1.csv", "notes.txt"):
        (out / name).write_text("old")
    plan_flight("F1", 0, out)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]  # the user's own file stays
