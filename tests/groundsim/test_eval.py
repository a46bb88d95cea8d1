"""``groundsim eval`` and its report: telemetry feed, scoring, TUM/APE, report files, a real lockstep run.

Scoring and report tests use hand-built runs whose errors are known exactly; one short P1 run goes
through the real chain (JSBSim -> render -> telemetry -> FramePipeline) and is repeated to show the
lockstep is deterministic.  evo (if installed) must read our TUM files and agree with our APE RMSE.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groundsim.app import cli
from groundsim.evaluation.eval import (
    EvalOptions,
    EvalResult,
    RunResult,
    onboard_config_for,
    run_eval,
    run_lockstep,
)
from groundsim.evaluation.report import (
    ape_rmse_m,
    closed_loop_notes,
    format_closed_loop,
    read_tum,
    write_eval_report,
    write_tum,
)
from groundsim.evaluation.scoring import (
    bound_ratio_limit,
    closed_loop_figures,
    format_gnss_dropout,
    gnss_dropout_figures,
    score_run,
    summarise,
)
from groundsim.evaluation.telemetry_feed import FEED_LEAD_MAX_US, TelemetryFeed
from groundsim.world.scenario import load_scenario, scenarios_dir
from onboard.app.config import OnboardConfig
from onboard.core.errors import ConfigError, InputError
from onboard.core.frames import GeodeticOrigin, quat_from_euler
from onboard.core.pose import PoseBuffer
from onboard.core.pose_config import PoseConfig
from onboard.estimation.map_estimator import MapConfig

pytestmark = pytest.mark.timeout(120)

P1 = scenarios_dir() / "P1.yaml"
TUM_ATOL_M = 1e-6  # TUM files keep micrometres
TUM_ATOL_S = 1e-6  # and microseconds
SCORE_RTOL = 1e-12  # scoring is exact arithmetic on known errors
MAX_CENTROID_RMS_PX = 0.5  # the image chain on P1's bright target (measured ~0.05 px)
MIN_MEASURED_FRACTION = 0.9  # frames with a valid centroid among frames with the target in view, once confirmed
CONFIRM_FRAMES = 12  # the default (objects) chain tracks an object once confirmed: 11 frames, 0.37 s at 30 Hz
LOCKSTEP_DURATION_S = 1.5  # 45 frames: enough for the chain, short for the suite
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


# --------------------------------------------------------------------------- helpers


def _synthetic_run(
    name="S1",
    seed=0,
    F=40,
    err_m=(1.0, 0.0, 0.0),
    obs_from=10,
    base_err_m=(0.0, 2.0, 0.0),
    base_from=5,
    cov_diag_m2=1.0,
    batch=None,
) -> RunResult:
    """A run with exactly known errors: the estimate is truth + err_m from frame obs_from on
    (observable), the baseline truth + base_err_m from base_from on; isotropic covariance."""
    t = np.arange(F) / 30.0
    truth = np.column_stack([100.0 + 2.0 * t, 50.0 - t, -80.0 + 0.0 * t])
    cam = np.column_stack([0.0 * t, 4.0 * t, -60.0 + 0.0 * t])
    rng = np.linalg.norm(truth - cam, axis=1)
    est = np.full((F, 3), np.nan)
    est[obs_from:] = truth[obs_from:] + np.asarray(err_m)
    cov = np.full((F, 3, 3), np.nan)
    cov[obs_from:] = np.eye(3) * cov_diag_m2
    observable = np.zeros(F, bool)
    observable[obs_from:] = True
    base = np.full((F, 3), np.nan)
    base[base_from:] = truth[base_from:] + np.asarray(base_err_m)
    base_cov = np.full((F, 3, 3), np.nan)
    base_cov[base_from:] = np.eye(3)
    base_obs = np.zeros(F, bool)
    base_obs[base_from:] = True
    uv = np.column_stack([320.0 + 0.0 * t, 256.0 + 0.0 * t])
    meas = np.ones(F, bool)
    meas[:2] = False
    pm = np.linspace(1.0, 10.0, F)
    pixels = np.full((64, 80), 40, np.uint8)
    pixels[30:33, 40:43] = 120
    return RunResult(
        scenario=name,
        description=f"{name}: synthetic",
        seed=seed,
        frames=F,
        t_s=t,
        time_boot_us=(1_000_000 + np.round(t * 1e6)).astype(np.int64),
        truth_p_ned_m=truth,
        cam_p_ned_m=cam,
        observer_p_ned_m=cam.copy(),
        range_m=rng,
        truth_uv_px=uv + 0.1,
        visible=np.ones(F, bool),
        state=np.full(F, "tracking"),
        measurement_valid=meas,
        uv_px=uv,
        bbox=np.tile([312.0, 248.0, 16.0, 16.0], (F, 1)),
        pose_valid=np.ones(F, bool),
        est_p_ned_m=est,
        est_cov_ned_m2=cov,
        observable=observable,
        range_sigma_ratio=np.full(F, 0.01),
        base_p_ned_m=base,
        base_cov_ned_m2=base_cov,
        base_observable=base_obs,
        batch=batch,
        timing=dict(
            wall_s=2.0,
            cpu_s=1.5,
            flight_s=0.1,
            render_s=0.2,
            pipeline_s=float(pm.sum() / 1e3),
            baseline_s=0.1,
            batch_s=0.0,
            render_ms=np.full(F, 5.0),
            process_ms=pm,
            baseline_ms=np.full(F, 2.0),
        ),
        counters={"pose_position_not_yet": 1},
        frame=dict(
            k=F // 2,
            t_s=float(t[F // 2]),
            pixels=pixels,
            bbox=(33.0, 23.0, 16.0, 16.0),
            uv_px=(41.5, 31.5),
            truth_uv_px=(41.4, 31.6),
            state="tracking",
            range_m=float(rng[F // 2]),
        ),
    )


def _batch_for(run: RunResult, err_pipeline=0.5, err_perfect=0.4) -> dict:
    idx = np.arange(run.frames)
    return {
        "pipeline": {
            "frames": idx,
            "p_ned_m": run.truth_p_ned_m + [err_pipeline, 0, 0],
            "cov_ned_m2": np.tile(np.eye(3), (run.frames, 1, 1)),
            "observable": True,
            "model": "cv",
            "solve_s": 0.1,
            "error": None,
        },
        "perfect": {
            "frames": idx,
            "p_ned_m": run.truth_p_ned_m + [0, err_perfect, 0],
            "cov_ned_m2": np.tile(np.eye(3), (run.frames, 1, 1)),
            "observable": True,
            "model": "cv",
            "solve_s": 0.1,
            "error": None,
            "crb_rms_m": 0.3,
            "crb_model_rms_m": 0.9,
        },
    }


# --------------------------------------------------------------------------- TUM and APE


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)), min_size=1, max_size=30))
def test_tum_round_trip_keeps_micrometres(tmp_path_factory, points):
    path = tmp_path_factory.mktemp("tum") / "x.tum"
    p = np.asarray(points, dtype=float)
    t = 1.0 + np.arange(len(p)) / 30.0
    assert write_tum(path, t, p) == len(p)
    t2, p2 = read_tum(path)
    np.testing.assert_allclose(t2, t, atol=TUM_ATOL_S, rtol=0)
    np.testing.assert_allclose(p2, p, atol=TUM_ATOL_M, rtol=0)
    first = next(line for line in path.read_text().splitlines() if not line.startswith("#"))
    assert first.split()[4:] == ["0", "0", "0", "1"]  # identity quaternion, qw last


def test_tum_skips_rows_without_a_position(tmp_path):
    t = np.arange(5) / 30.0
    p = np.arange(15, dtype=float).reshape(5, 3)
    p[1, 2] = np.nan
    assert write_tum(tmp_path / "e.tum", t, p) == 4
    t2, _ = read_tum(tmp_path / "e.tum")
    np.testing.assert_allclose(t2, t[[0, 2, 3, 4]], atol=TUM_ATOL_S)


def test_read_tum_names_the_bad_line(tmp_path):
    f = tmp_path / "bad.tum"
    f.write_text("# header\n0.0 1 2 3 0 0 0 1\n0.1 1 2 3 0 0 0\n")
    with pytest.raises(InputError, match=r"bad.tum: line 3: expected 8 numbers"):
        read_tum(f)
    f.write_text("0.0 1 2 x 0 0 0 1\n")
    with pytest.raises(InputError, match=r"line 1: not numbers"):
        read_tum(f)


def test_ape_rmse_is_evo_default_association_without_alignment():
    t = np.arange(100) / 30.0
    ref = np.column_stack([t, 2 * t, 0 * t])
    est_t = t[20:60] + 0.004  # within evo's 0.01 s
    est = ref[20:60] + np.array([3.0, 4.0, 0.0])  # a constant 5 m offset: no alignment may remove it
    rmse, n = ape_rmse_m(t, ref, est_t, est)
    assert n == 40
    assert rmse == pytest.approx(5.0, rel=SCORE_RTOL)
    # beyond max_diff nothing matches; the order of the arguments does not matter for the RMSE
    assert ape_rmse_m(t, ref, t[20:60] + 0.02, est)[1] == 0
    assert ape_rmse_m(est_t, est, t, ref) == pytest.approx((5.0, 40), rel=SCORE_RTOL)


def test_evo_reads_our_tum_files_and_agrees(tmp_path):
    evo_file_interface = pytest.importorskip(
        "evo.tools.file_interface", reason="evo not installed (pip install evo to run this cross-check)"
    )
    from evo.core import metrics, sync

    run = _synthetic_run()
    t = run.time_boot_us / 1e6
    obs = run.observable
    write_tum(tmp_path / "truth.tum", t, run.truth_p_ned_m)
    write_tum(tmp_path / "estimate.tum", t[obs], run.est_p_ned_m[obs])
    ref = evo_file_interface.read_tum_trajectory_file(str(tmp_path / "truth.tum"))
    est = evo_file_interface.read_tum_trajectory_file(str(tmp_path / "estimate.tum"))
    ref, est = sync.associate_trajectories(ref, est)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    ours = score_run(run)["online_observable"]["rmse_m"]
    assert ape.get_statistic(metrics.StatisticsType.rmse) == pytest.approx(ours, rel=1e-6)


# --------------------------------------------------------------------------- telemetry feed


class _FakeCore:
    """SimCore's telemetry interface on a 120 Hz tick grid: a level observer flying north at 10 m/s."""

    tick_rate_hz = 120.0

    def __init__(self, seconds: float, gimbal=True) -> None:
        self.tick_count = int(seconds * self.tick_rate_hz)
        self.origin = GeodeticOrigin(32.0, 118.8, 0.0)
        self.gimbal = gimbal

    def time_boot_us(self, i: int) -> int:
        return 1_000_000 + round(i / self.tick_rate_hz * 1e6)

    def vehicle_state(self, i: int) -> dict:
        from onboard.core.frames import geodetic_from_ned

        t = i / self.tick_rate_hz
        lat, lon, alt = geodetic_from_ned(np.array([10.0 * t, 0.0, -60.0]), self.origin)
        return dict(
            time_boot_us=1_000_000 + round(t * 1e6),
            lat_deg=float(lat),
            lon_deg=float(lon),
            alt_amsl_m=float(alt),
            alt_rel_m=float(alt),
            v_ned_mps=np.array([10.0, 0.0, 0.0]),
            q_ned_from_body=np.array([1.0, 0, 0, 0]),
            body_rates_radps=np.zeros(3),
            heading_rad=0.0,
            q_gimbal=quat_from_euler(0.0, -0.2, 0.3) if self.gimbal else None,
        )


def test_telemetry_feed_rates_stamps_and_quantisation():
    core = _FakeCore(2.0)
    from onboard.core.frames import CameraMount

    buf = PoseBuffer(CameraMount(gimballed=True), PoseConfig(), core.origin)
    feed = TelemetryFeed(core, buf, gimballed=True)
    while not feed.exhausted:
        feed.feed_next()
    sizes = buf.sizes()
    assert sizes == {"attitude": 100, "position": 50, "gimbal": 20}  # 50, 25, 10 Hz over 2 s
    # stamps are MAVLink time_boot_ms: whole milliseconds
    for stream in (buf._att, buf._pos, buf._gim):
        assert all(t % 1000 == 0 for t in stream.t_us)
    # positions within the 1e-7 deg (~1.1 cm) / 1 mm quantisation of the truth
    pose = buf.pose_at(1_500_000)  # t = 0.5 s
    assert pose is not None
    np.testing.assert_allclose(pose.body.p_ned_m, [5.0, 0.0, -60.0], atol=0.03)


def test_telemetry_feed_for_waits_for_the_bracketing_sample():
    core = _FakeCore(1.0, gimbal=False)
    from onboard.core.frames import CameraMount

    buf = PoseBuffer(CameraMount(), PoseConfig(), core.origin)
    feed = TelemetryFeed(core, buf, gimballed=False)
    t_frame_us = 1_000_000 + round(10 / 30 * 1e6)  # frame 10, tick 40
    feed.feed_for(40, t_frame_us)
    assert buf.lookup(t_frame_us).pose is not None
    assert feed.next_tick <= 40 + 6  # fed only until a position sample after the frame (40 ms = 5 ticks)


def test_telemetry_feed_withholds_position_in_a_gnss_dropout_and_feed_for_stops_short_of_its_end():
    core = _FakeCore(3.0, gimbal=False)
    from groundsim.world.nav_errors import parse_gnss_dropout
    from onboard.core.frames import CameraMount

    dropout = parse_gnss_dropout("1:1")
    window = dropout.boot_window_us(1_000_000)
    assert window == (2_000_000, 3_000_000)
    buf = PoseBuffer(CameraMount(), PoseConfig(), core.origin)
    feed = TelemetryFeed(core, buf, gimballed=False, gnss_outage_us=window)
    t_frame_us = 2_500_000  # mid-dropout: the feed goes at most FEED_LEAD_MAX_US past it, then dead reckoning
    feed.feed_for(int(1.5 * 120), t_frame_us)
    assert core.time_boot_us(feed.next_tick - 1) <= t_frame_us + FEED_LEAD_MAX_US
    assert buf._pos.t_us[-1] < window[0] and buf._att.t_us[-1] >= t_frame_us
    pose = buf.pose_at(t_frame_us)
    assert pose is not None and pose.pos_extrapolated_us > 500_000
    np.testing.assert_allclose(pose.body.p_ned_m, [15.0, 0.0, -60.0], atol=0.05)  # 10 m/s north, dead-reckoned
    while not feed.exhausted:
        feed.feed_next()
    assert not [t for t in buf._pos.t_us if window[0] <= t < window[1]] and buf.counter["position_resumed"] == 1


def test_gnss_dropout_figures_count_the_window_frames():
    r = _synthetic_run("A", 0)
    F = r.frames
    los = np.ones(F, bool)
    los[5] = False
    t0, t1 = float(r.t_s[4]), float(r.t_s[14])
    r = dataclasses.replace(r, gnss_window_s=(t0, t1), gnss_warning_t_s=t0 + 0.2, los_valid=los)
    f = gnss_dropout_figures(r)
    in_gap = (r.t_s >= t0) & (r.t_s < t1) & r.visible & r.measurement_valid
    assert f["frames"] == int(in_gap.sum()) == 10
    assert f["los"] == pytest.approx(0.9) and f["warning_after_s"] == pytest.approx(0.2)
    assert f["position"] == pytest.approx(float((in_gap & r.has_estimate).sum()) / 10)
    assert gnss_dropout_figures(dataclasses.replace(r, gnss_window_s=None)) is None
    assert "warned after" in format_gnss_dropout([r])
    # one eval flies a seed once per noise case: the rows say which
    text = format_gnss_dropout([dataclasses.replace(r, nav_noise="RTK"), dataclasses.replace(r, nav_noise="exact")])
    assert [line.split()[:3] for line in text.splitlines()[2:]] == [["A", "RTK", "s0"], ["A", "exact", "s0"]]


@pytest.mark.parametrize("err_m, beyond_trace, beyond_ellipsoid", [(1.0, 0.0, 0.0), (3.9, 0.0, 1.0), (400.0, 1.0, 1.0)])
def test_the_ellipsoid_figure_sees_an_error_across_a_covariance_the_trace_test_passes(
    err_m, beyond_trace, beyond_ellipsoid
):
    """cov = diag(100^2, 1, 1) m^2: 3 sqrt(trace) = 300 m; an error of 3.9 m along the tight axis is 3.9 sigma there
    (NEES 15.2 > 14.16): inside the trace's test, beyond the ellipsoid."""
    r = _synthetic_run("A", 0, err_m=(0.0, err_m, 0.0))
    cov = np.where(np.isfinite(r.est_cov_ned_m2), np.diag([100.0**2, 1.0, 1.0]), np.nan)
    f = closed_loop_figures(dataclasses.replace(r, est_cov_ned_m2=cov))
    assert f["beyond_3sigma_published"] == beyond_trace and f["beyond_3sigma_ellipsoid_published"] == beyond_ellipsoid


@pytest.mark.parametrize("err_m, beyond", [(7.0, 1.0), (5.9, 0.0)])
def test_the_honesty_figures_hold_the_error_to_three_square_roots_of_the_trace(err_m, beyond):
    """cov = 4/3 I: trace 4 m^2, 3 sigma (trace) = 3 sqrt(4) = 6 m; an error of 7 m is beyond it, 5.9 m inside
    (three times the trace, 12 m, would hold both)."""
    r = _synthetic_run("A", 0, err_m=(0.0, err_m, 0.0), cov_diag_m2=4.0 / 3.0)
    assert closed_loop_figures(r)["beyond_3sigma_published"] == beyond
    t0, t1 = float(r.t_s[12]), float(r.t_s[30])  # all frames in the window have an estimate
    f = gnss_dropout_figures(dataclasses.replace(r, gnss_window_s=(t0, t1), gnss_warning_t_s=t0))
    assert f["position"] == 1.0 and f["beyond_3sigma"] == beyond


# --------------------------------------------------------------------------- configuration


def test_onboard_config_takes_the_scenarios_camera_and_origin():
    sc = load_scenario(P1)
    cfg = onboard_config_for(sc, OnboardConfig())
    K = cfg.camera.pinhole()
    assert (K.fx_px, K.cx_px, K.width_px, K.height_px) == (
        sc.camera.intrinsics.fx_px,
        sc.camera.intrinsics.cx_px,
        640,
        512,
    )
    m = cfg.camera.camera_mount()
    q, q_sc = np.asarray(m.q_body_from_mount), np.asarray(sc.camera.mount.q_body_from_mount)
    assert min(np.abs(q - q_sc).max(), np.abs(q + q_sc).max()) < 1e-12
    np.testing.assert_allclose(m.lever_arm_frd_m, sc.camera.mount.lever_arm_frd_m, atol=1e-15)
    assert m.gimballed is True
    assert cfg.pose.geodetic_origin() == sc.origin
    assert cfg.output.unobservable_positions is True
    assert cfg.output.health_file is None


def test_eval_options_reject_bad_values():
    with pytest.raises(ConfigError, match="--duration"):
        EvalOptions(duration_s=0.0)
    with pytest.raises(ConfigError, match="--pixel-sigma"):
        EvalOptions(pixel_sigma_px=-1.0)


# --------------------------------------------------------------------------- scoring


def test_score_run_on_known_errors():
    run = _synthetic_run(batch=None)
    F = run.frames
    s = score_run(run)
    on = s["online_observable"]
    assert on["frames"] == F - 10
    assert on["rmse_m"] == pytest.approx(1.0, rel=SCORE_RTOL)
    assert on["err_range_pct"] == pytest.approx(100 * np.mean(1.0 / run.range_m[10:]), rel=SCORE_RTOL)
    paper = 100 * np.mean(1.0 / np.linalg.norm(run.truth_p_ned_m[10:], axis=1))
    assert on["err_paper_pct"] == pytest.approx(paper, rel=SCORE_RTOL)
    assert on["mean_nees"] == pytest.approx(1.0, rel=SCORE_RTOL)  # e = (1, 0, 0), P = I
    assert s["perfect_observable"]["rmse_m"] == pytest.approx(2.0, rel=SCORE_RTOL)
    assert s["common_frames"] == F - 10
    assert s["online_common_err_range_pct"] / s["perfect_common_err_range_pct"] == pytest.approx(0.5, rel=1e-9)
    assert s["continuity"] == pytest.approx((F - 10) / F)
    assert s["perfect_continuity"] == pytest.approx((F - 5) / F)
    assert s["continuity_2d"] == pytest.approx((F - 2) / F)
    assert s["first_observable_s"] == pytest.approx(10 / 30.0)
    assert s["centroid_rms_px"] == pytest.approx(math.sqrt(0.02), rel=1e-9)
    assert s["timing"]["latency_ms"]["max"] == pytest.approx(10.0)
    json.dumps(s, default=float)  # JSON-ready


def test_score_run_reports_a_refused_covariance_instead_of_failing():
    run = _synthetic_run()
    bad = run.est_cov_ned_m2.copy()
    bad[20] = -np.eye(3)
    s = score_run(dataclasses.replace(run, est_cov_ned_m2=bad))
    assert s["online_observable"]["rmse_m"] == pytest.approx(1.0)
    assert s["online_observable"]["mean_nees"] is None
    assert "not positive definite" in s["online_observable"]["note"]


def test_score_run_without_observable_frames_and_a_failed_run():
    run = _synthetic_run(obs_from=40)  # never observable
    s = score_run(run)
    assert s["online_observable"] is None and s["continuity"] == 0.0 and s["first_observable_s"] is None
    # the target never in the image: no 2-D continuity to measure ('-' in the report), not 0 %
    assert score_run(dataclasses.replace(run, visible=np.zeros(len(run.t_s), bool)))["continuity_2d"] is None
    failed = dataclasses.replace(run, error="FlightError: boom")
    assert score_run(failed) == {"scenario": "S1", "seed": 0, "error": "FlightError: boom"}


def test_summarise_medians_ratios_and_verdict():
    runs = [_synthetic_run("A", seed=k, err_m=(e, 0, 0)) for k, e in enumerate((1.0, 3.0, 2.0))]
    runs = [dataclasses.replace(r, batch=_batch_for(r, 0.5, 0.4)) for r in runs]
    runs.append(dataclasses.replace(_synthetic_run("B", err_m=(4.0, 0, 0)), batch=None))
    scores = [score_run(r) for r in runs]
    rows = {r["scenario"]: r for r in summarise(scores)}
    a = rows["A"]
    assert a["runs"] == 3 and a["failed_runs"] == 0
    assert a["rmse_m"] == pytest.approx(2.0)  # median of 1, 3, 2
    assert a["ratio_to_perfect"] == pytest.approx(1.0, rel=1e-9)  # 2 m vs 2 m on common frames
    assert a["batch_ratio_to_perfect"] == pytest.approx(0.5 / 0.4, rel=1e-9)
    assert a["crb_rms_m"] == pytest.approx(0.3)
    assert a["within_ratio"] is True
    b = rows["B"]
    assert b["ratio_to_perfect"] == pytest.approx(2.0, rel=1e-9) and b["batch_ratio_to_perfect"] is None
    assert b["within_ratio"] is False
    # no batch run (eval --no-batch): not a failed baseline, and the verdict line does not say it failed
    assert a["batch_baseline_failed"] is False and b["batch_baseline_failed"] is None


def test_the_share_observable_at_the_bound_counts_the_half_seconds_after_5_s():
    run = _synthetic_run("A", F=330, obs_from=300)  # 11 s, observable from 10 s: 1 s of the 6 after 5 s
    limit = bound_ratio_limit()
    batch = _batch_for(run)
    t = np.arange(1.0, 11.0, 0.5)  # 1 .. 10.5 s: 12 samples at or after 5 s
    ratio = np.where(t < 8.0, 2 * limit, 0.5 * limit)  # under the limit from 8 s: 6 of the 12
    ratio[t == 9.0] = np.nan  # too few rows then: not observable
    batch["perfect"].update(causal_bound_t_s=t, causal_bound_range_sigma_ratio=ratio)
    s = score_run(dataclasses.replace(run, batch=batch))
    assert s["closed_loop"]["observable_share_after_5s_at_bound"] == pytest.approx(5 / 12)
    assert score_run(dataclasses.replace(run, batch=None))["closed_loop"]["observable_share_after_5s_at_bound"] is None
    # the closed-loop table: the bound's share beside the run's, and a miss the bound shares said to be the flight's
    row = summarise([score_run(dataclasses.replace(run, batch=batch))])[0]
    line = format_closed_loop([row]).splitlines()[-1]
    assert line.endswith("| 42 % |")
    assert row["observable_share_after_5s"] == pytest.approx(30 / 180)
    assert "**miss** (the bound's too)" in line
    batch["perfect"]["causal_bound_range_sigma_ratio"] = np.full(t.size, 0.5 * limit)
    line = format_closed_loop(summarise([score_run(dataclasses.replace(run, batch=batch))])).splitlines()[-1]
    assert line.endswith("| 100 % |") and "the bound's too" not in line


def test_a_chain_off_its_target_gets_a_note_under_the_closed_loop_table():
    rows = [
        {"scenario": "C3", "label": "C3", "chain_centroid_sigma_px": 108.4},
        {"scenario": "P1", "label": "P1", "chain_centroid_sigma_px": 0.03},
        {"scenario": "P2", "label": "P2", "chain_centroid_sigma_px": None},
    ]
    notes = closed_loop_notes(rows)
    assert len(notes) == 1 and notes[0].startswith("- C3: the image chain's centroids lie 108.4 px (RMS)")
    assert "objects chain (the default)" in notes[0] and "imaging: {chain: single}" in notes[0]
    assert closed_loop_notes(rows[1:]) == []
    # the table carries them: after its last row, a blank line, then the notes
    with_notes = format_closed_loop(rows).splitlines()
    assert with_notes[-2:] == ["", notes[0]] and with_notes[-3].startswith("| P2 |")
    assert format_closed_loop(rows[1:]).splitlines()[-1].startswith("| P2 |")


def test_the_bound_ratio_limit_is_the_verdicts_threshold_over_the_sigma_inflation():
    c = MapConfig()
    assert bound_ratio_limit() == pytest.approx(c.observability_max_sigma_range_ratio / c.sigma_inflation)


# --------------------------------------------------------------------------- report files


def test_write_eval_report_files_tables_and_ape(tmp_path):
    from groundsim.evaluation.mot import gt_line, square_box

    runs = [dataclasses.replace(_synthetic_run("A", seed=k), batch=None) for k in range(2)]
    runs.append(_synthetic_run("B", seed=0))
    # A's first run has the MOT files of a scene (B's none): the objects timeline is drawn from them
    runs[0] = dataclasses.replace(
        runs[0],
        mot_gt="".join(gt_line(k + 1, 1, 320.0, 256.0, 1, 1.0) for k in range(runs[0].frames)),
        mot_tracker="".join(f"{k + 1},4,{square_box(320.2, 256.0)},1,-1,-1,-1\n" for k in range(12, runs[0].frames)),
    )
    scores = [score_run(r) for r in runs]
    result = EvalResult(runs, scores, summarise(scores), 3.0, 1, EvalOptions(), "built-in defaults")
    files = write_eval_report(tmp_path, result)
    for key in ("A_trajectory", "A_error", "A_frame", "A_objects", "B_trajectory", "performance"):
        data = Path(files[key]).read_bytes()
        assert data[:8] == PNG_MAGIC and len(data) > 10_000, key
    assert "B_objects" not in files
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["schema"] == "irtrack.eval/1"
    assert [r["scenario"] for r in rep["summary"]] == ["A", "B"]
    # the APE of the TUM files (evo's way) equals the online RMSE of the report
    for s in rep["runs"]:
        ape = rep["tum_ape"][f"{s['scenario']}/seed{s['seed']}"]
        assert ape["rmse_m"] == pytest.approx(s["online_observable"]["rmse_m"], rel=1e-6)
        assert ape["matched"] == s["online_observable"]["frames"]
    assert (tmp_path / "A" / "seed1" / "estimate_perfect.tum").is_file()
    md = (tmp_path / "report.md").read_text()
    assert "| scenario | geometry | paper Table 2 |" in md
    assert "| A | synthetic | - | " in md
    assert "![performance](performance.png)" in md and "evo_ape tum A/seed0/truth.tum A/seed0/estimate.tum" in md


def test_a_run_with_no_observable_frame_is_named_and_not_the_evo_example(tmp_path):
    """Its estimate.tum holds the header line only, which evo refuses with a message about the columns: the report
    says which runs those are, and its evo command names a run whose file has poses."""
    first = _synthetic_run("A", seed=0)
    runs = [
        dataclasses.replace(first, batch=None, frame=None, observable=np.zeros_like(first.observable)),
        dataclasses.replace(_synthetic_run("A", seed=1), batch=None, frame=None),
    ]
    scores = [score_run(r) for r in runs]
    write_eval_report(tmp_path, EvalResult(runs, scores, summarise(scores), 1.0, 1, EvalOptions(), "built-in"))
    assert [ln for ln in (tmp_path / "A" / "seed0" / "estimate.tum").read_text().splitlines() if ln[:1] != "#"] == []
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["tum_ape"]["A/seed0"]["estimate_poses"] == 0 < rep["tum_ape"]["A/seed1"]["estimate_poses"]
    md = (tmp_path / "report.md").read_text()
    assert "No frame was observable in A/seed0: `estimate.tum` there holds its header line only" in md
    assert "evo_ape tum A/seed1/truth.tum A/seed1/estimate.tum" in md and "evo_ape tum A/seed0" not in md


def test_an_interrupted_evals_report_says_it_is_partial(tmp_path):
    runs = [dataclasses.replace(_synthetic_run("A", seed=0), batch=None, frame=None)]
    scores = [score_run(r) for r in runs]
    result = EvalResult(runs, scores, summarise(scores), 1.0, 1, EvalOptions(), "built-in defaults")
    write_eval_report(tmp_path, result, planned=3)
    assert json.loads((tmp_path / "report.json").read_text())["interrupted"] == "1 of 3 runs"
    assert "**interrupted: 1 of 3 runs**" in (tmp_path / "report.md").read_text()
    write_eval_report(tmp_path, result)  # complete: no such line
    assert json.loads((tmp_path / "report.json").read_text())["interrupted"] is None
    assert "interrupted" not in (tmp_path / "report.md").read_text()


# --------------------------------------------------------------------------- the real chain


@pytest.fixture(scope="module")
def lockstep_pair():
    sc = load_scenario(P1)
    opts = EvalOptions(duration_s=LOCKSTEP_DURATION_S, batch=False)
    return sc, run_lockstep(sc, 3, opts), run_lockstep(sc, 3, opts)


def test_lockstep_run_goes_through_the_image_chain(lockstep_pair):
    sc, r, _ = lockstep_pair
    planned = round(LOCKSTEP_DURATION_S * sc.frame_rate_hz)
    F = r.frames
    # the last frame or two, after the run's last telemetry sample, are not processed
    assert planned - 2 <= F <= planned and r.error is None
    np.testing.assert_allclose(np.diff(r.t_s), 1 / sc.frame_rate_hz, atol=1e-9)
    assert np.all(np.isfinite(r.truth_p_ned_m)) and np.all(r.visible)
    assert r.pose_valid.all()
    measured = r.measurement_valid & r.visible
    first = int(np.argmax(measured))
    assert measured.any() and first <= CONFIRM_FRAMES
    assert measured[first:].sum() >= MIN_MEASURED_FRACTION * r.visible[first:].sum()
    d = r.uv_px[measured] - r.truth_uv_px[measured]
    assert math.sqrt(np.mean(np.sum(d**2, axis=1))) < MAX_CENTROID_RMS_PX
    assert set(np.unique(r.state)) <= {"tracking", "coasting", "searching", "lost"}
    s = score_run(r)
    assert 0.0 <= s["continuity"] <= 1.0 and s["continuity_2d"] >= MIN_MEASURED_FRACTION * (F - first) / F
    assert r.frame is not None and r.frame["pixels"].shape == (512, 640)
    assert r.timing["pipeline_s"] > 0 and len(r.timing["process_ms"]) == F


def test_lockstep_is_deterministic(lockstep_pair):
    _, a, b = lockstep_pair
    for name in (
        "truth_p_ned_m",
        "uv_px",
        "est_p_ned_m",
        "est_cov_ned_m2",
        "base_p_ned_m",
        "observable",
        "measurement_valid",
        "state",
    ):
        assert np.array_equal(
            getattr(a, name), getattr(b, name), equal_nan=name not in ("observable", "measurement_valid", "state")
        ), name


def test_run_eval_in_a_pool_matches_in_process(lockstep_pair):
    sc, a, _ = lockstep_pair
    opts = EvalOptions(duration_s=0.5, batch=False, keep_frame=False)
    pooled = run_eval([sc], [3], opts, workers=2, progress=False)
    assert pooled.workers == 1  # one job: no pool needed
    two = run_eval([sc, sc], [3], opts, workers=2, progress=False)
    assert two.workers == 2 and len(two.runs) == 2
    np.testing.assert_array_equal(two.runs[0].uv_px, two.runs[1].uv_px)
    n = two.runs[0].frames
    np.testing.assert_array_equal(two.runs[0].uv_px, a.uv_px[:n])  # the same frames as the longer run's first ones


def test_eval_duration_beyond_the_scenarios_continues_its_motion(lockstep_pair):
    """--duration longer than the scenario's duration_s: the scripted motion continues (no refusal), the
    first frames are the scenario's own."""
    sc, a, _ = lockstep_pair
    short = dataclasses.replace(sc, duration_s=0.5)
    opts = EvalOptions(duration_s=1.0, batch=False, keep_frame=False)
    res = run_eval([short], [3], opts, workers=1, progress=False)
    r = res.runs[0]
    assert r.error is None and 28 <= r.frames <= 30 and r.t_s[-1] > 0.9
    n = min(r.frames, a.frames)
    np.testing.assert_array_equal(r.uv_px[:n], a.uv_px[:n])


# --------------------------------------------------------------------------- command line


def _cli(argv):
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = cli.main(argv)
    return code, err.getvalue()


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["eval", "--seeds", "0"], "--seeds: expected an integer >= 1"),
        (["eval", "--scenario", "no_such_scenario.yaml"], "no_such_scenario.yaml"),
        (["eval", "--scenario", "P1", "--duration", "3601"], "--duration: expected at most 3600 s"),
        (["eval", "--workers", "0"], "--workers: expected an integer >= 1"),
        (["eval", "--pixel-sigma", "-1"], "--pixel-sigma"),
    ],
)
def test_eval_cli_rejects_bad_options_in_one_line(tmp_path, argv, needle):
    code, err = _cli(argv + ["--out", str(tmp_path / "o"), "--no-progress"])
    assert code == cli.EXIT_ERROR
    lines = [line for line in err.splitlines() if line.strip() and "INFO" not in line]
    assert len(lines) == 1 and lines[0].startswith("groundsim eval: error:") and needle in lines[0], err


def test_frames_sent_at_capture_get_their_rotation_extrapolated_when_the_wait_is_short():
    """rotation_wait_us (frames sent the instant they are captured, the daemon's imaging.pose_wait_ms): with no wait
    every frame's pose is extrapolated past its newest samples with the attitude's body rates, as in the daemon
    (without the rates, lockstep's own feed, a lookup past the newest sample found no pose at all); the default
    feeds each frame's telemetry until it brackets the frame, and nothing is extrapolated."""
    sc = load_scenario(P1)
    counts, frames = {}, 0
    for wait_us in (None, 0):
        r = run_lockstep(
            sc, 3, EvalOptions(duration_s=LOCKSTEP_DURATION_S, batch=False, keep_frame=False, rotation_wait_us=wait_us)
        )
        counts[wait_us], frames = r.counters, r.frames
        assert np.isfinite(r.uv_px).all(axis=1).sum() >= r.frames - 12  # tracked either way after its first 11 frames
    assert counts[None].get("pose_extrapolated", 0) == 0
    # the frames' poses extrapolated, each counted once (its image chain's look-up and its own were counted apart:
    # 74 for 45 frames); a frame stamped on an attitude sample's time needs none
    assert frames - 12 <= counts[0].get("pose_extrapolated", 0) <= frames
    assert counts[0].get("pose_attitude_not_yet", 0) == 0
