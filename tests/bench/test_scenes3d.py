"""bench.scenes3d (a scene's 3-D against its clean-sky twin) and bench.onboard_scene's CPU window: the twin's
definition, the per-run figures, their pairing and pooling over seeds, and one tiny run of the command."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from bench.onboard_scene import FRAME_RATE_HZ, window_figures
from bench.scenes3d import ON_TARGET_PX, PULLED_PX, clean_twin, main, noise_twin, pair_row, run_figures
from groundsim.world.scenario import load_scenario, scenarios_dir
from groundsim.world.sim import SimCore

ATOL_M = 1e-9  # same flight: identical numbers, not merely close


def _run(err_m, sigma_m, range_m=100.0, observable=None, uv_off_px=None, seed=0, name="C9", visible=None,
         cross_m=None, resets=0):  # fmt: skip
    """A RunResult-like object of len(err_m) frames: the estimate err_m (NaN: none) north of the truth (along the
    line of sight from the camera at the origin) and cross_m (default 0) east of it (across), an isotropic
    covariance of sigma_m per axis, the measured centre uv_off_px (NaN: none) off the truth pixel along u."""
    err = np.asarray(err_m, dtype=float)
    F = err.size
    cross = np.zeros(F) if cross_m is None else np.asarray(cross_m, dtype=float)
    truth = np.tile([100.0, 0.0, 0.0], (F, 1))
    est = truth + np.stack([err, cross, np.zeros(F)], axis=1)
    cov = np.stack([np.eye(3) * s**2 for s in np.broadcast_to(np.asarray(sigma_m, float), (F,))])
    off = np.zeros(F) if uv_off_px is None else np.asarray(uv_off_px, dtype=float)
    truth_uv = np.tile([320.0, 256.0], (F, 1))
    return SimpleNamespace(
        scenario=name,
        seed=seed,
        frames=F,
        error=None,
        t_s=1.0 + np.arange(F) / 30.0,
        truth_p_ned_m=truth,
        cam_p_ned_m=np.zeros((F, 3)),
        est_p_ned_m=est,
        est_cov_ned_m2=cov,
        range_m=np.full(F, range_m),
        observable=np.zeros(F, bool) if observable is None else np.asarray(observable, bool),
        visible=np.ones(F, bool) if visible is None else np.asarray(visible, bool),
        measurement_valid=np.isfinite(off),
        uv_px=truth_uv + np.stack([off, np.zeros(F)], axis=1),
        truth_uv_px=truth_uv,
        counters={"estimator_resets": resets},
    )


# ---------------------------------------------------------------------------- the twin


@pytest.mark.parametrize("name", ["C3", "C5"])
def test_clean_twin_switches_the_scene_off_and_keeps_everything_else(name):
    sc = load_scenario(scenarios_dir() / f"{name}.yaml")
    twin = clean_twin(sc)
    assert sc.scene.has_content or sc.scene.sensor.enabled
    assert not twin.scene.has_content and not twin.scene.sensor.enabled and twin.other_targets == ()
    for field in ("name", "seed", "observer", "target", "camera", "ir", "origin", "duration_s", "nav_noise"):
        assert getattr(twin, field) == getattr(sc, field), field


@pytest.mark.parametrize("twin_of", [clean_twin, lambda sc: noise_twin(sc, 2)], ids=["twin", "noise twin"])
def test_clean_twin_flies_the_same_flight_with_the_same_navigation_errors(twin_of):
    # C3 has a second target and distractors: none of them may shift the observer's, the target's or the
    # navigation errors' random streams; nor may the noise twin's renamed render-noise stream
    sc = load_scenario(scenarios_dir() / "C3.yaml")
    kw = dict(duration_s=1.0, render=False, flight_chunk_s=1.0)  # one chunk: every tick kept
    a, b = SimCore(sc, 1, **kw), SimCore(twin_of(sc), 1, **kw)
    assert b.scene_enabled is False and a.scene_enabled is True
    for i in (0, 37, a.tick_count - 1):
        sa, sb = a.vehicle_state(i), b.vehicle_state(i)
        np.testing.assert_allclose(sa["q_ned_from_body"], sb["q_ned_from_body"], atol=ATOL_M)
        assert (sa["lat_deg"], sa["lon_deg"], sa["alt_amsl_m"]) == (sb["lat_deg"], sb["lon_deg"], sb["alt_amsl_m"])
        np.testing.assert_allclose(sa["q_gimbal"], sb["q_gimbal"], atol=ATOL_M)
        ea, eb = a.nav_error(i), b.nav_error(i)
        for k, v in vars(ea).items():
            np.testing.assert_allclose(np.asarray(v, float), np.asarray(getattr(eb, k), float), atol=ATOL_M)
    ta, tb = a.frame(20).truth, b.frame(20).truth
    assert (ta.target_n_m, ta.target_e_m, ta.target_d_m) == (tb.target_n_m, tb.target_e_m, tb.target_d_m)
    assert (ta.target_u_px, ta.target_v_px) == (tb.target_u_px, tb.target_v_px)


def test_noise_twin_changes_the_render_noise_and_nothing_else():
    sc = load_scenario(scenarios_dir() / "C3.yaml")
    twin, n1, n2 = clean_twin(sc), noise_twin(sc, 1), noise_twin(sc, 2)
    assert n1.other_targets == () and not n1.scene.has_content and n1.seed == sc.seed
    draw = lambda s, stream: s.rng(stream, 1).integers(0, 2**62, 4).tolist()  # noqa: E731
    for stream in ("nav.errors", "gimbal.pointing_phase", "target.disturbance", "render.scene", "render.sensor"):
        assert draw(n1, stream) == draw(twin, stream), stream
    assert len({tuple(draw(s, "render.noise")) for s in (twin, n1, n2)}) == 3
    assert draw(noise_twin(sc, 0), "render.noise") == draw(twin, "render.noise")
    # the pixels differ by the noise alone: the same frame of the twin and its noise twin, rendered
    kw = dict(duration_s=1.0, render=True, flight_chunk_s=1.0)
    fa, fb = SimCore(twin, 1, **kw).frame(5), SimCore(n1, 1, **kw).frame(5)
    diff = fa.pixels.astype(float) - fb.pixels.astype(float)
    assert np.any(diff != 0) and abs(float(diff.mean())) < 0.5  # zero-mean noise, not a moved target
    assert (fa.truth.target_u_px, fa.truth.target_v_px) == (fb.truth.target_u_px, fb.truth.target_v_px)


# ---------------------------------------------------------------------------- per-run figures


def test_run_figures_scores_published_positions_only():
    nan = math.nan
    # frames: no estimate, 2 m (sigma 1: inside 3 sigma = 3 sqrt(3) = 5.2 m), 6 m (outside), 4 m observable
    r = _run([nan, 2.0, 6.0, 4.0], 1.0, range_m=200.0, observable=[False, False, False, True],
             uv_off_px=[nan, 1.0, ON_TARGET_PX + 0.5, 0.0])  # fmt: skip
    f = run_figures(r, twin=False)
    assert f.positions == 3 and f.frame.tolist() == [1, 2, 3]
    np.testing.assert_allclose(f.err_m, [2.0, 6.0, 4.0])
    np.testing.assert_allclose(f.err_range_pct, [1.0, 3.0, 2.0])
    assert f.beyond_3sigma.tolist() == [False, True, False]
    assert f.observable.tolist() == [False, False, True]
    assert (f.visible, f.on_target) == (4, 2)  # no centre on frame 0; 3.5 px off on frame 2
    assert f.first_position_s == pytest.approx(1 / 30.0)
    assert f.pulled == 1 and f.max_pull_px == pytest.approx(1.0)  # frame 1's 1 px; frame 3 dead on
    np.testing.assert_allclose(f.angle_mrad, 0.0, atol=1e-12)  # errors along the line of sight only


def test_run_figures_angular_error_is_across_the_line_of_sight():
    # camera at the origin, truth 100 m north: 1 m east is atan(1/100) whatever the along-range error
    r = _run([0.0, 50.0, -20.0, 0.0], 1.0, cross_m=[1.0, 1.0, 1.0, 0.0], uv_off_px=[0.2, PULLED_PX + 0.01, 2.9, 3.1],
             resets=2)  # fmt: skip
    f = run_figures(r, twin=False)
    np.testing.assert_allclose(
        f.angle_mrad, 1e3 * np.array([math.atan(1 / 100), math.atan(1 / 150), math.atan(1 / 80), 0.0]), rtol=1e-12
    )
    assert (f.on_target, f.pulled, f.resets) == (3, 2, 2)  # 0.2 px is not pulled, 3.1 px is not on target
    assert f.max_pull_px == pytest.approx(2.9)


def test_run_figures_of_a_failed_run_has_no_positions():
    r = SimpleNamespace(scenario="C1", seed=3, frames=0, error="FlightError: boom")
    f = run_figures(r, twin=True)
    assert f.error == "FlightError: boom" and f.positions == 0 and f.twin


# ---------------------------------------------------------------------------- pairing and pooling


def test_pair_row_pools_seeds_and_forms_both_ratios():
    nan = math.nan
    scene = [
        run_figures(_run([nan, 3.0, 3.0, 9.0], 10.0, seed=0), False),
        run_figures(_run([3.0, 3.0, nan], 10.0, seed=1), False),
    ]
    twin = [
        run_figures(_run([2.0, 2.0, 2.0, 2.0], 10.0, seed=0), True),
        run_figures(_run([nan, 1.0, 1.0], 10.0, seed=1), True),
    ]
    row = pair_row(scene, twin)
    s, t = row["scene"], row["twin"]
    assert (s["positions"], t["positions"], s["frames"]) == (5, 6, 7)
    assert s["median_err_m"] == 3.0 and t["median_err_m"] == 2.0  # pooled: [3, 3, 9, 3, 3] and [2, 2, 2, 2, 1, 1]
    assert row["ratio"] == pytest.approx(1.5)
    # common (seed, frame): seed 0 frames 1-3 (3, 3, 9 vs 2, 2, 2), seed 1 frame 1 (3 vs 1)
    assert row["common_positions"] == 4
    assert row["ratio_common"] == pytest.approx(np.median([3, 3, 9, 3]) / np.median([2, 2, 2, 1]))
    assert s["beyond_3sigma"] == 0.0 and row["met"] is True  # 1.5 is within "at most 1.5x"
    assert math.isnan(s["median_err_observable_range_pct"])  # no position flagged observable


def test_pair_row_medians_of_observable_positions_alone():
    f = run_figures(_run([1.0, 5.0, 3.0, 7.0], 10.0, range_m=100.0, observable=[False, True, True, False]), False)
    row = pair_row([f], [f])
    assert row["scene"]["median_err_observable_range_pct"] == pytest.approx(4.0)  # of 5 and 3 m at 100 m
    assert row["scene"]["observable"] == pytest.approx(0.5)


def test_pair_row_verdict_fails_on_dishonest_positions_and_survives_a_failed_run():
    scene = [run_figures(_run([1.0] * 98 + [50.0, 50.0], 1.0, seed=0), False)]  # 2 % beyond 3 sigma
    twin = [
        run_figures(_run([1.0] * 100, 1.0, seed=0), True),
        run_figures(SimpleNamespace(scenario="C9", seed=1, frames=0, error="x"), True),
    ]
    row = pair_row(scene, twin)
    assert row["scene"]["beyond_3sigma"] == pytest.approx(0.02)
    assert row["ratio"] == pytest.approx(1.0) and row["met"] is False
    assert row["twin"]["failed"] == 1 and row["twin"]["runs"] == 2


def test_pair_row_angular_ratio_and_noise_spread():
    scene = [run_figures(_run([5.0] * 4, 10.0, cross_m=[2.0] * 4, seed=s, uv_off_px=[0.5] * 4, resets=1), False)
             for s in (0, 1)]  # fmt: skip
    twin = [run_figures(_run([2.0] * 4, 10.0, cross_m=[1.0] * 4, seed=s), True) for s in (0, 1)]
    # draw 1 pooled over its two seeds: median of [1, 1, 1, 1, 6, 6, 6, 6] = 3.5 m; draw 2: 4 m
    noise = [
        run_figures(_run([1.0] * 4, 10.0, seed=0), True, 1),
        run_figures(_run([6.0] * 4, 10.0, seed=1), True, 1),
        run_figures(_run([4.0] * 4, 10.0, seed=0), True, 2),
    ]
    row = pair_row(scene, twin, noise)
    # camera at the origin, truth 100 m north: the scene 5 m along and 2 m across, the twin 2 m along and 1 across
    assert row["angular_ratio"] == pytest.approx(math.atan2(2.0, 105.0) / math.atan2(1.0, 102.0), rel=1e-12)
    assert row["ratio"] == pytest.approx(math.hypot(5.0, 2.0) / math.hypot(2.0, 1.0))
    assert row["noise_medians"] == pytest.approx([math.hypot(2.0, 1.0), 3.5, 4.0])  # % of the 100 m range
    assert row["noise_spread"] == pytest.approx(4.0 / math.hypot(2.0, 1.0))
    assert (row["scene"]["pulled"], row["scene"]["resets"], row["twin"]["pulled"]) == (8, 2, 0)
    assert math.isnan(pair_row(scene, twin)["noise_spread"])  # no noise twins: no spread


def test_pair_row_without_twin_positions_has_no_verdict():
    row = pair_row([run_figures(_run([1.0, 2.0], 1.0), False)], [run_figures(_run([math.nan] * 2, 1.0), True)])
    assert math.isnan(row["ratio"]) and row["met"] is None and row["common_positions"] == 0


# ---------------------------------------------------------------------------- bench.onboard --scene's window


def test_window_figures_take_the_window_while_frames_arrive():
    # (t, cpu s, by thread, frames in, processed): 30 frames/s in for 3 s, then the simulator has stopped
    samples = [
        (0.0, 1.0, {"pipe": 0.5}, 0, 0),
        (1.0, 1.2, {"pipe": 0.6}, 30, 29),
        (2.0, 1.4, {"pipe": 0.7}, 60, 59),
        (3.0, 1.6, {"pipe": 0.8}, 90, 89),
        (4.0, 1.61, {"pipe": 0.8}, 90, 89),  # idle: not in the window
    ]
    w = window_figures(samples, t_from=1.0)
    assert w["span_s"] == 2.0 and w["processed"] == 60 and w["frames_in"] == 60
    assert w["cpu_s_per_s"] == pytest.approx(0.2) and w["fps"] == pytest.approx(30.0)
    assert w["cpu_ms_per_frame"] == pytest.approx(400.0 / 60)
    assert w["share_at_30hz"] == pytest.approx(w["cpu_ms_per_frame"] * FRAME_RATE_HZ / 1e3)
    assert w["by_thread"]["pipe"] == pytest.approx(0.1)
    assert window_figures(samples, t_from=3.5) is None  # no frames arrived after it


# ---------------------------------------------------------------------------- the command


def test_command_pairs_each_scene_run_with_its_twin_and_writes_json(tmp_path, capsys, monkeypatch):
    # the loop itself is groundsim eval's (tested there; a real run takes tens of seconds here): stand in for it
    # with runs whose error says what they were given, the scene (3 m) or its twin (2 m), per seed
    calls = []

    def fake_run_lockstep(scenario, seed, options, cfg, progress=None):
        twin = not (scenario.scene.has_content or scenario.scene.sensor.enabled)
        calls.append((scenario.name, seed, twin, options.duration_s, options.injected.nav_noise, cfg.imaging.chain))
        return _run([2.0 if twin else 3.0] * 4, 10.0, seed=seed, name=scenario.name)

    monkeypatch.setattr("groundsim.evaluation.eval.run_lockstep", fake_run_lockstep)
    out = tmp_path / "s.json"
    assert main(["--scenes", "C1", "C4", "--seeds", "2", "--duration", "12", "--json", str(out)]) == 0
    assert sorted(calls) == sorted(
        (name, seed, twin, 12.0, "RTK", "objects") for name in ("C1", "C4") for seed in (0, 1) for twin in (False, True)
    )
    text = capsys.readouterr().out
    assert "C4 s1 twin :" in text and "| C1 | 2 | 8 / 8 | 3.0 / 2.0 |" in text
    doc = json.loads(out.read_text())
    assert [r["scenario"] for r in doc["rows"]] == ["C1", "C4"]
    for row in doc["rows"]:
        assert row["ratio"] == pytest.approx(1.5) and row["common_positions"] == 8 and row["met"] is True
    # the same lines again from the file, nothing run
    calls.clear()
    assert main(["--table-from", str(out)]) == 0
    again = capsys.readouterr().out
    assert calls == [] and again.strip() == text[text.index("   C1 s0") :].strip()


def test_command_flies_noise_twins_and_drops_other_targets(tmp_path, capsys, monkeypatch):
    from bench.scenes3d import NoiseTwinScenario

    calls = []

    def fake_run_lockstep(scenario, seed, options, cfg, progress=None):
        draw = scenario.render_noise_draw if isinstance(scenario, NoiseTwinScenario) else None
        twin = not (scenario.scene.has_content or scenario.scene.sensor.enabled)
        calls.append((seed, twin, draw, len(scenario.other_targets)))
        err = 3.0 if not twin else (2.0 if draw is None else 2.0 + draw)  # the twins' medians 2, 3, 4 m
        return _run([err] * 4, 10.0, seed=seed, name=scenario.name)

    monkeypatch.setattr("groundsim.evaluation.eval.run_lockstep", fake_run_lockstep)
    out = tmp_path / "s.json"
    argv = ["--scenes", "C3", "--seeds", "1", "--noise-twins", "2", "--no-other-targets", "--json", str(out)]
    assert main(argv) == 0
    # the scene without its second target (C3 has one), the twin, noise twins 1 and 2
    assert sorted(calls, key=str) == sorted([(0, False, None, 0), (0, True, None, 0), (0, True, 1, 0), (0, True, 2, 0)],
                                            key=str)  # fmt: skip
    text = capsys.readouterr().out
    assert "C3 s0 twin2:" in text and "no other targets" in text
    row = json.loads(out.read_text())["rows"][0]
    assert row["noise_medians"] == pytest.approx([2.0, 3.0, 4.0]) and row["noise_spread"] == pytest.approx(2.0)
    assert row["ratio"] == pytest.approx(1.5)  # against the twin, not the noise twins
    assert load_scenario(scenarios_dir() / "C3.yaml").other_targets  # the premise: C3 has another target
