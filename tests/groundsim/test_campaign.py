"""groundsim.evaluation.campaign: spec validation, geometry variants, scoring, resumability, pool == serial."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from groundsim.app.cli import main as cli_main
from groundsim.evaluation.campaign import (
    LOG_NAME,
    append_rows,
    plan_runs,
    read_log,
    run_campaign,
    run_id,
    score_track,
)
from groundsim.evaluation.campaign_report import (
    REPORT_NAME,
    TABLE_NAME,
    confident_wrong_rows,
    table2_rows,
    write_report,
)
from groundsim.evaluation.campaign_spec import (
    Geometry,
    ManoeuvreScaled,
    MovedTarget,
    derive_scenario,
    load_spec,
    spec_from_dict,
)
from groundsim.world.motion import Circular, Cubic
from groundsim.world.scenario import load_scenario, reference_scenario_paths, scenario_digest, scenario_from_dict
from onboard.core.errors import ConfigError
from tests.groundsim.campaign_helpers import (
    campaign_cmd,
    comparable,
    interrupt_campaign,
    resume_campaign,
    run_as_cli,
)

REPO = Path(__file__).resolve().parents[2]
ATOL_M = 1e-9  # 1 nm: the variants are exact transformations of the reference paths
ATOL_MPS2 = 1e-9


def _sc(name="P1"):
    return load_scenario(reference_scenario_paths()[name])


def _spec(tmp_path, **over):
    d = {
        "name": "t",
        "scenarios": ["P1", "P2"],
        "noise": ["RTK", "px0.3"],
        "algorithms": ["paper", "rpekf"],
        "seeds": 2,
        "duration_s": 3.0,
        "geometry": {"manoeuvre_scale": [0.5, 1.0]},
    }
    d.update(over)
    return spec_from_dict(d, source=tmp_path / "spec.yaml", spec_dir=tmp_path)


# --------------------------------------------------------------------------- geometry


def test_manoeuvre_scale_scales_the_acceleration_from_the_same_start():
    base = Circular((21.6, 33.7, -70.0), 40.0, 4.14, -0.2)
    t = np.linspace(0.0, 10.0, 101)
    for m in (0.0, 0.5, 2.0):
        s, b = ManoeuvreScaled(base, m).state(t), base.state(t)
        np.testing.assert_allclose(s.a_ned_mps2, m * b.a_ned_mps2, atol=ATOL_MPS2)
        np.testing.assert_allclose(s.p_ned_m[0], b.p_ned_m[0], atol=ATOL_M)
        np.testing.assert_allclose(s.v_ned_mps[0], b.v_ned_mps[0], atol=ATOL_M)
        # the path integrates its own velocity (a consistent kinematic state)
        np.testing.assert_allclose(np.gradient(s.p_ned_m, t, axis=0)[1:-1], s.v_ned_mps[1:-1], atol=0.05)
    straight = ManoeuvreScaled(base, 0.0).state(t)
    np.testing.assert_allclose(
        straight.v_ned_mps, np.broadcast_to(base.state(t).v_ned_mps[0], (t.size, 3)), atol=ATOL_M
    )


def test_moved_target_rotates_north_towards_east_about_its_start():
    base = Cubic((120.0, 30.0, -85.0), (5.0, 0.0, 0.0))  # heading north
    m = MovedTarget(base, (120.0, 30.0, -85.0), math.radians(90.0), (0.0, 0.0, 0.0))
    s = m.state(np.array([0.0, 2.0]))
    np.testing.assert_allclose(s.p_ned_m[0], (120.0, 30.0, -85.0), atol=ATOL_M)
    np.testing.assert_allclose(s.v_ned_mps[1], (0.0, 5.0, 0.0), atol=ATOL_M)  # now east
    np.testing.assert_allclose(s.p_ned_m[1], (120.0, 40.0, -85.0), atol=ATOL_M)


def test_range_scale_multiplies_the_initial_range_and_keeps_the_target_motion():
    sc = _sc("P1")
    v = derive_scenario(sc, Geometry(range_scale=2.0))
    t = sc.frame_times_s()
    r0 = np.linalg.norm(sc.target_motion(0).state(t).p_ned_m[0] - sc.observer_motion(0).state(t).p_ned_m[0])
    r1 = np.linalg.norm(v.target_motion(0).state(t).p_ned_m[0] - v.observer_motion(0).state(t).p_ned_m[0])
    assert r1 == pytest.approx(2.0 * r0, rel=1e-12)
    np.testing.assert_allclose(
        v.target_motion(0).state(t).v_ned_mps, sc.target_motion(0).state(t).v_ned_mps, atol=ATOL_M
    )
    assert v.name == "P1_r2_a0_m1"


def test_reference_geometry_is_the_scenario_itself_and_gusty_targets_keep_their_disturbance():
    sc = _sc("P1")
    assert derive_scenario(sc, Geometry()) is sc
    g = _sc("P2g")
    v = derive_scenario(g, Geometry(aspect_deg=30.0))
    assert v.target.disturbance == g.target.disturbance
    t = g.frame_times_s()
    # run 3's disturbance is the reference's realisation (same stream), on the rotated base path
    d_ref = g.target_motion(3).state(t).p_ned_m - g.target.base_motion.state(t).p_ned_m
    d_var = v.target_motion(3).state(t).p_ned_m - v.target.base_motion.state(t).p_ned_m
    np.testing.assert_allclose(d_var, d_ref, atol=ATOL_M)


def test_a_geometry_that_collides_or_goes_underground_is_refused_naming_it():
    with pytest.raises(ConfigError, match=r"geometry: .*P1 with range_scale 0\.01.*m at t ="):
        derive_scenario(_sc("P1"), Geometry(range_scale=0.01))
    low = scenario_from_dict(
        {
            "name": "low",
            "observer": {"motion": {"model": "uniform_linear", "p0_ned_m": [0, 0, -60]}},
            "target": {"motion": {"model": "uniform_linear", "p0_ned_m": [100, 0, -5]}},
        }
    )
    with pytest.raises(ConfigError, match=r"above the ground.*the target at -50 m up"):
        derive_scenario(low, Geometry(range_scale=2.0))  # the line of sight goes down: twice the range is underground


# --------------------------------------------------------------------------- spec


@pytest.mark.parametrize(
    "change, field",
    [
        ({"mode": "batch"}, "mode"),
        ({"noise": ["RTK", "RTKK"]}, r"noise\[1\]"),
        ({"scenarios": ["P9"]}, r"scenarios\[0\]"),
        ({"algorithms": ["nope"]}, r"algorithms\[0\]"),
        ({"seeds": 0}, "seeds"),
        ({"seeds": [1, 1]}, "seeds"),
        ({"geometry": {"range_scale": {"min": 2.0, "max": 1.0}, "draws": 2}}, r"geometry\.range_scale\.max"),
        ({"geometry": {"aspect_deg": {"min": 0.0, "max": 90.0}}}, r"geometry\.draws"),
        ({"geometry": {"manoeuvre_scale": [-1.0]}}, r"geometry\.manoeuvre_scale\[0\]"),
        ({"geometry": {"manouvre_scale": [1.0]}}, r"geometry\.manouvre_scale.*did you mean 'manoeuvre_scale'"),
        ({"duration_s": 60.0}, "duration_s"),
        ({"duration_s": 1e-9}, r"duration_s: expected a duration of at least 10 frames of P1, .* got 1e-09$"),
        ({"duration_s": 0.3}, r"duration_s: expected a duration of at least 10 frames of P1, .*\(> 0.3 s at 30 Hz\)"),
        ({"mode": "closed_loop", "noise_model": "case"}, "noise_model"),
        ({"crb": "yes"}, "crb"),
        ({"seed": 3}, "seed.*did you mean 'seeds'"),
    ],
)
def test_bad_specs_name_the_file_and_the_field(tmp_path, change, field):
    with pytest.raises(ConfigError, match=rf"spec\.yaml: .*{field}"):
        _spec(tmp_path, **change)


def test_cli_bad_spec_is_one_line_and_exit_2(tmp_path, capsys):
    p = tmp_path / "bad.yaml"
    p.write_text("scenarios: [P1]\nnoise: [RTK]\nalgorithms: [map]\ngeometry: {range_scale: [0]}\n")
    assert cli_main(["campaign", str(p)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "bad.yaml: geometry.range_scale[0]: expected" in err


def test_random_geometry_draws_are_deterministic_and_in_range(tmp_path):
    geo = {
        "range_scale": {"min": 0.8, "max": 1.5},
        "aspect_deg": {"min": -45.0, "max": 45.0},
        "manoeuvre_scale": [1.0, 2.0],
        "draws": 3,
        "seed": 11,
    }
    a, b = _spec(tmp_path, geometry=geo), _spec(tmp_path, geometry=geo)
    assert a.geometries == b.geometries and len(a.geometries) == 6
    assert all(0.8 <= g.range_scale <= 1.5 and -45 <= g.aspect_deg <= 45 for g in a.geometries)
    assert _spec(tmp_path, geometry={**geo, "seed": 12}).geometries != a.geometries


@pytest.mark.parametrize(
    "geo, got",
    [
        ({"range_scale": {"min": 1.0, "max": 1.00001}, "draws": 5}, "5 draws, 1 distinct"),
        ({"aspect_deg": {"min": 10.0, "max": 10.02}, "manoeuvre_scale": [1.0, 2.0], "draws": 4}, "4 draws, 3 distinct"),
    ],
)
def test_draws_that_rounding_would_collapse_are_refused_naming_the_field(tmp_path, geo, got):
    """The draws are rounded to 4 significant digits: a range too narrow for them gave fewer runs, silently."""
    with pytest.raises(ConfigError) as info:
        _spec(tmp_path, geometry=geo)
    assert str(info.value).startswith(f"{tmp_path / 'spec.yaml'}: geometry.draws: expected at most as many draws as")
    assert f"got {got}; widen the range or ask for fewer draws" in str(info.value)


def test_draws_are_distinct_and_as_many_as_asked_when_the_range_has_room(tmp_path):
    geo = {"range_scale": {"min": 1.0, "max": 1.003}, "draws": 4, "seed": 1}  # 1.000 .. 1.003: 4 values
    assert sorted(g.range_scale for g in _spec(tmp_path, geometry=geo).geometries) == [1.0, 1.001, 1.002, 1.003]


def test_run_ids_are_stable_and_differ_by_every_parameter(tmp_path):
    spec = _spec(tmp_path)
    runs = plan_runs(spec, "x")
    ids = [run_id(r) for r in runs]
    assert len(runs) == spec.run_count == 2 * 2 * 2 * 2 * 2 and len(set(ids)) == len(ids)
    assert ids == [run_id(r) for r in plan_runs(_spec(tmp_path), "x")]
    assert set(ids).isdisjoint(run_id(r) for r in plan_runs(spec, "another onboard config"))


def test_a_scenario_edited_only_in_its_comments_or_layout_keeps_its_run_ids(tmp_path):
    """The run id covers what a scenario file says, not its text: a comment, indentation, key order, a number
    written another way or the description changed reruns nothing (every run had been redone); a value changed
    does."""
    import yaml

    path = tmp_path / "P1.yaml"
    text = reference_scenario_paths()["P1"].read_text()
    path.write_text(text)

    def ids():
        return [run_id(r) for r in plan_runs(_spec(tmp_path, scenarios=["P1.yaml"]), "x")]

    before = ids()
    data = yaml.safe_load(text)
    data["description"] = "another description"
    data["duration_s"] = int(data["duration_s"])  # 10 for 10.0
    reordered = dict(reversed(list(data.items())))
    path.write_text("# a comment only\n" + yaml.safe_dump(reordered, indent=4, sort_keys=False) + "# and another\n")
    assert ids() == before
    data["seed"] = int(data.get("seed", 0)) + 1
    path.write_text(yaml.safe_dump(data))
    assert set(ids()).isdisjoint(before)


def test_the_shipped_example_spec_is_valid():
    spec = load_spec(REPO / "config/campaigns/example.yaml")
    assert spec.mode == "synthetic" and set(spec.algorithms) == {"map", "paper", "rpekf"} and len(spec.geometries) == 3


def test_the_shipped_honesty_spec_plans_the_runs_its_header_says():
    spec = load_spec(REPO / "config/campaigns/honesty.yaml")
    assert spec.run_count == len(plan_runs(spec, "x")) == 1944 and spec.algorithms == ("map",)


# --------------------------------------------------------------------------- scoring


def test_score_track_figures_on_a_constructed_track():
    F = 100
    t = np.arange(F) / 10.0  # 10 s
    truth = np.tile([100.0, 0.0, 0.0], (F, 1))
    cam = np.zeros((F, 3))
    est = truth + [1.0, 0.0, 0.0]  # 1 % of range everywhere
    cov = np.tile(np.eye(3) * 0.25, (F, 1, 1))  # sigma 0.5 m per axis: e = 2 sigma on one axis
    est[:20] = np.nan  # no estimate for 2 s
    obs = np.zeros(F, dtype=bool)
    obs[70:] = True
    s = score_track(t, truth, cam, est, cov, obs)
    assert s["published_frames"] == 80 and s["observable_frames"] == 30
    assert s["err_range_observable_pct"] == pytest.approx(1.0) and s["err_range_final_pct"] == pytest.approx(1.0)
    assert s["observable_share_settled"] == pytest.approx(30 / 50)
    assert s["nees_observable"] == pytest.approx(4.0)  # (1 / 0.5)^2
    assert s["beyond_3sigma_published"] == 0.0  # 1 m < 3 sqrt(0.75)
    assert s["first_observable_s"] == pytest.approx(7.0) and s["settle_s"] == 5.0
    cov_small = np.tile(np.eye(3) * 0.01, (F, 1, 1))
    assert score_track(t, truth, cam, est, cov_small, obs)["beyond_3sigma_published"] == 1.0
    # confident and wrong only where observable: the tight covariance on frames 20-69, honest ones from 70 on
    mixed = np.where(np.arange(F)[:, None, None] < 70, cov_small, cov)
    m = score_track(t, truth, cam, est, mixed, obs)
    assert m["beyond_3sigma_published"] == pytest.approx(50 / 80) and m["beyond_3sigma_observable"] == 0.0
    m = score_track(t, truth, cam, est, np.where(np.arange(F)[:, None, None] < 70, cov, cov_small), obs)
    assert m["beyond_3sigma_published"] == pytest.approx(30 / 80) and m["beyond_3sigma_observable"] == 1.0
    assert math.isnan(score_track(t, truth, cam, est, cov, np.zeros(F, dtype=bool))["beyond_3sigma_observable"])


# --------------------------------------------------------------------------- the log and resumability


def _t2_row(**over) -> dict:
    row = {
        "status": "ok",
        "algorithm": "map",
        "scenario": "P1",
        "noise": "RTK",
        "range_scale": 1.0,
        "aspect_deg": 0.0,
        "manoeuvre_scale": 1.0,
        "duration_s": None,
        "scenario_digest": scenario_digest(reference_scenario_paths()["P1"]),
        "err_range_published_settled_pct": 1.0,
        "beyond_3sigma_published": 0.0,
    }
    row.update(over)
    return row


@pytest.mark.parametrize(
    "over",
    [
        {"manoeuvre_scale": 2.0},  # no run at the reference geometry: medians over other geometries
        {"noise": "exact"},  # not a noise case of the reference study
        {"duration_s": 2.0},  # not the paper's 300 frames
        {"scenario": "C1"},  # not one of the paper's scenarios
        {"scenario_digest": "another file"},  # a file named P1 that says something else
    ],
)
def test_the_paper_figure_stands_only_beside_the_runs_it_applies_to(tmp_path, over):
    """The paper's Table 2 figure is given beside its own scenarios, as shipped, at the reference geometry, flown
    whole, under a reference noise case; '-' elsewhere, and the report's note says so (0.89 % had stood beside P1
    at twice the manoeuvre, without noise, on 2 s flights)."""
    shipped = {"P1": scenario_digest(reference_scenario_paths()["P1"])}
    (ref,), _ = table2_rows([_t2_row()], shipped)
    assert ref["paper_pct"] == pytest.approx(0.89)
    (other,), _ = table2_rows([_t2_row(**over)], shipped)
    assert math.isnan(other["paper_pct"])
    info = {"planned": 1, "reused": 0, "ran": 1, "failed": 0, "wall_s": 1.0, "workers": 1, "interrupted": False}
    write_report(tmp_path, _spec(tmp_path), [_t2_row(**over)], info)
    text = (tmp_path / REPORT_NAME).read_text()
    line = next(x for x in text.splitlines() if x.startswith(f"| {over.get('scenario', 'P1')} |"))
    assert line.split("|")[4].strip() == "-", line
    assert "'-' elsewhere, where the paper has no figure" in text


def test_confident_wrong_rows_count_the_observable_frames_beyond_3_sigma_per_group():
    def row(scenario, man, frames, beyond, status="ok"):
        return {
            "status": status,
            "algorithm": "map",
            "scenario": scenario,
            "manoeuvre_scale": man,
            "range_scale": 1.0,
            "aspect_deg": 0.0,
            "observable_frames": frames,
            "beyond_3sigma_observable": beyond,
        }

    rows = [
        row("P1", 1.0, 100, 0.0),
        row("P1", 3.0, 50, 0.2),  # 10 frames beyond: over 1 %
        row("P2", 3.0, 200, 0.005),  # 1 frame beyond: not over
        row("P2", 1.0, 0, math.nan),  # nothing observable: counted as a run, no frames
        row("P2", 1.0, 40, 1.0, status="failed"),  # failed runs are not figures
    ]
    got = {r["group"]: r for r in confident_wrong_rows(rows)}
    # range and aspect were not swept: no groups of their own (the same figures as every run)
    assert set(got) == {"all runs", "scenario P1", "scenario P2", "manoeuvre_scale 1", "manoeuvre_scale 3"}
    assert got["all runs"] == {
        "algorithm": "map",
        "group": "all runs",
        "runs": 4,
        "observable_frames": 350,
        "beyond_frames": 11,
        "beyond_pct": pytest.approx(100 * 11 / 350),
        "runs_over": 1,
    }
    assert (got["scenario P1"]["beyond_frames"], got["scenario P1"]["runs_over"]) == (10, 1)
    assert (got["manoeuvre_scale 3"]["observable_frames"], got["manoeuvre_scale 3"]["beyond_frames"]) == (250, 11)
    assert got["manoeuvre_scale 1"]["beyond_frames"] == 0 and got["manoeuvre_scale 1"]["runs"] == 2


def test_a_torn_last_line_is_skipped_and_rows_round_trip(tmp_path):
    p = tmp_path / LOG_NAME
    append_rows(p, [{"run_id": "a", "x": 1.5}, {"run_id": "b", "x": None}])
    with p.open("a") as f:
        f.write('{"run_id": "c", "x"')  # a kill in the middle of a write
    done, bad = read_log(p)
    assert set(done) == {"a", "b"} and bad == 1 and done["a"]["x"] == 1.5


def test_a_row_appended_after_a_torn_line_is_a_line_of_its_own(tmp_path):
    """A kill mid-write leaves a fragment without its newline: the next run's row must not be glued onto it
    (it was lost with it, and the table came out a run short)."""
    p = tmp_path / LOG_NAME
    append_rows(p, [{"run_id": "a", "x": 1.5}])
    with p.open("a") as f:
        f.write('{"run_id": "c", "x"')
    append_rows(p, [{"run_id": "d", "x": 2.5}])
    done, bad = read_log(p)
    assert set(done) == {"a", "d"} and bad == 1 and done["d"]["x"] == 2.5
    append_rows(p, [{"run_id": "e", "x": 3.5}])  # a log that ends well gets no blank line
    assert p.read_text().count("\n\n") == 0 and set(read_log(p)[0]) == {"a", "d", "e"}


def test_fresh_with_a_scheduler_that_does_not_answer_changes_nothing(tmp_path, monkeypatch):
    import groundsim.evaluation.campaign as campaign

    out = tmp_path / "out"
    out.mkdir()
    append_rows(out / LOG_NAME, [{"run_id": "a", "x": 1.5}])
    before = (out / LOG_NAME).read_bytes()

    def no_answer(scheduler):
        raise ConfigError(f"--scheduler {scheduler}: no scheduler answered within 10 s")

    monkeypatch.setattr(campaign, "_cluster_client", no_answer)
    with pytest.raises(ConfigError, match="no scheduler answered"):
        run_campaign(_spec(tmp_path), out, fresh=True, scheduler="tcp://127.0.0.1:1", progress=False)
    assert (out / LOG_NAME).read_bytes() == before


def test_a_fresh_campaign_interrupted_before_its_first_result_resumes_with_the_same_command(tmp_path, monkeypatch):
    """--fresh removed runs.jsonl, and it came back only with the first result: interrupted before, the folder held
    the earlier campaign's report and table but no log, and the same command was refused as a foreign folder."""
    import groundsim.evaluation.campaign as campaign

    out = tmp_path / "out"
    out.mkdir()
    append_rows(out / LOG_NAME, [{"run_id": "a", "x": 1.5}])
    (out / "report.md").write_text("the earlier campaign's\n")

    def interrupted(*_a, **_k):
        raise KeyboardInterrupt

    monkeypatch.setattr(campaign, "_jobs", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_campaign(_spec(tmp_path), out, fresh=True, progress=False)
    assert (out / LOG_NAME).read_bytes() == b""  # emptied: the earlier runs are not reused
    spec_file = tmp_path / "spec.yaml"
    spec_file.write_text("scenarios: [P1]\nnoise: [RTK]\nalgorithms: [paper]\nduration_s: 0.5\n")
    # the folder check passes: the run is under way again (and interrupted again: 130), not refused (2)
    assert cli_main(["campaign", str(spec_file), "--out", str(out), "--fresh", "--no-progress"]) == 130


def test_a_figure_of_an_earlier_sweep_does_not_stay_beside_a_report_without_one(tmp_path, monkeypatch):
    import groundsim.evaluation.campaign_plots as plots
    from groundsim.evaluation.campaign_report import FIGURE_NAME, write_report

    (tmp_path / FIGURE_NAME).write_bytes(b"an earlier sweep's figure")
    monkeypatch.setattr(plots, "plot_manoeuvre", lambda *a, **k: False)
    info = {"planned": 0, "reused": 0, "ran": 0, "failed": 0, "wall_s": 0.0, "workers": 1, "interrupted": False}
    files = write_report(tmp_path, _spec(tmp_path), [], info)
    assert FIGURE_NAME not in files and not (tmp_path / FIGURE_NAME).exists()


@pytest.mark.slow
@pytest.mark.multicore
def test_pool_and_serial_give_identical_tables_and_a_rerun_reuses_everything(tmp_path):
    # every dimension varied (scenario, noise, algorithm, geometry: 16 runs); one seed, as a second seed varies
    # nothing the pool could order or merge differently
    spec = _spec(tmp_path, seeds=1)
    r1 = run_campaign(spec, tmp_path / "serial", workers=1, progress=False)
    r2 = run_campaign(spec, tmp_path / "pool", workers=2, progress=False)
    assert r1.ran == r2.ran == spec.run_count and r1.failed == 0
    a = pd.read_csv(tmp_path / "serial" / TABLE_NAME)
    b = pd.read_csv(tmp_path / "pool" / TABLE_NAME)
    pd.testing.assert_frame_equal(comparable(a), comparable(b))
    # the numbers are real: every run published estimates, the bound is finite
    assert (a["published_frames"] > 0).all() and np.isfinite(a["crb_rms_m"]).all()
    r3 = run_campaign(spec, tmp_path / "serial", workers=2, progress=False)
    assert r3.ran == 0 and r3.reused == spec.run_count
    c = pd.read_csv(tmp_path / "serial" / TABLE_NAME)
    pd.testing.assert_frame_equal(comparable(a), comparable(c))
    report = (tmp_path / "serial" / REPORT_NAME).read_text()
    assert (
        "### paper" in report and "### rpekf" in report and (tmp_path / "serial" / "manoeuvre.png").stat().st_size > 0
    )


@pytest.mark.slow
def test_an_interrupted_campaign_resumes_where_it_stopped(tmp_path):
    """SIGINT (Ctrl-C) in the middle: exit 130, the finished runs kept; the same command runs only the
    rest, and the table equals an uninterrupted campaign's."""
    spec_path = tmp_path / "spec.yaml"
    spec_path.write_text(
        "name: t\nscenarios: [P1]\nnoise: [RTK]\nalgorithms: [map, paper]\nseeds: 2\n"
        "duration_s: 4.0\ngeometry: {manoeuvre_scale: [0.5, 1.0, 2.0]}\n"
    )
    out = tmp_path / "out"
    cmd = campaign_cmd(spec_path, out, "--workers", "1")
    done_before = interrupt_campaign(cmd, out, runs_logged=4, hang_s=120, stop_s=60)  # two cases of 6 done
    assert 4 <= done_before < 12

    resume_campaign(cmd, done_before, runs=12, timeout_s=300)
    resumed = pd.read_csv(out / TABLE_NAME)
    ref = run_as_cli(spec_path, tmp_path / "ref", workers=1)
    assert ref.ran == 12
    pd.testing.assert_frame_equal(comparable(resumed), comparable(pd.read_csv(tmp_path / "ref" / TABLE_NAME)))


@pytest.mark.slow
def test_closed_loop_mode_flies_the_variant_through_the_lockstep_pipeline(tmp_path):
    spec = _spec(
        tmp_path,
        mode="closed_loop",
        scenarios=["P1"],
        noise=["RTK"],
        algorithms=["paper"],
        seeds=1,
        duration_s=2.0,
        crb=False,
        geometry={"manoeuvre_scale": [1.0, 1.5]},
    )
    res = run_campaign(spec, tmp_path / "cl", workers=1, progress=False)
    df = pd.read_csv(tmp_path / "cl" / TABLE_NAME)
    assert res.ran == 2 and (df["status"] == "ok").all() and (df["mode"] == "closed_loop").all()
    assert (df["published_frames"] > 0).all() and df["chain_centroid_sigma_px"].lt(0.5).all()
    # the perception figures of the eval: P1's clean sky, its target held from its confirmation (11 frames, which
    # the state accuracy counts as misses)
    assert df["false_tracks_per_min"].eq(0).all() and df["id_switches"].eq(0).all()
    assert df["state_accuracy"].between(0.7, 1.0).all() and df["pd_pct"].eq(100.0).all()  # measured 0.80
    # the variant is the scaled one: 1.5 x the reference observer's commanded acceleration (RMS)
    a = df.set_index("manoeuvre_scale")["observer_accel_rms_mps2"]
    assert a[1.5] == pytest.approx(1.5 * a[1.0], rel=1e-9)
