"""onboard.pipeline.plugins: estimators discovered by entry point or module:Attribute and run through the lockstep eval."""

from __future__ import annotations

import math
import sys
import textwrap

import numpy as np
import pytest

from groundsim.app.cli import main as cli_main
from groundsim.evaluation.baselines.rpekf import RangeParameterisedEkf, RpEkfConfig
from groundsim.evaluation.eval import EvalOptions, run_lockstep
from groundsim.evaluation.scoring import score_run
from groundsim.world.scenario import load_scenario, reference_scenario_paths
from onboard.app.config import OnboardConfig
from onboard.core.errors import ConfigError
from onboard.core.frames import PinholeIntrinsics, quat_from_rotmat
from onboard.pipeline.plugins import ESTIMATORS, TrajectoryEstimator, available, build, load_factory

SHORT_S = (
    4.0  # a short lockstep run: enough frames (> 30 after the chain confirms its object) for every estimator to answer
)


def _p1():
    return load_scenario(reference_scenario_paths()["P1"])


def test_our_three_are_registered_as_entry_points():
    assert {"map", "paper", "rpekf"} <= set(available(ESTIMATORS))
    for name in ("map", "paper", "rpekf"):
        assert isinstance(build(name, OnboardConfig()), TrajectoryEstimator)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["map", "paper", "rpekf"])
def test_each_registered_estimator_runs_a_short_eval(name):
    r = run_lockstep(_p1(), 0, EvalOptions(duration_s=SHORT_S, batch=False, keep_frame=False, estimator=name))
    s = score_run(r)
    assert r.error is None and s["estimator"] == name
    assert s["online_all"] is not None and s["online_all"]["err_range_pct"] >= 0  # estimates were published
    assert s["estimate_fraction"] > 0.3


def _write_outside_package(root, dist="outside_est-0.1"):
    """A tiny out-of-tree distribution: a module and a dist-info with an irtrack.estimators entry point."""
    (root / "outside_est.py").write_text(
        textwrap.dedent('''
        import numpy as np

        class Est:
            """Fixed 150 m along the bearing: knows nothing, says so (never observable)."""
            def __init__(self):
                self.n = 0
            def reset(self):
                self.n = 0
            def add(self, t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam):
                self.n += 1
                w, x, y, z = q_ned_from_cam
                R = np.array([[1-2*(y*y+z*z), 2*(x*y-w*z), 2*(x*z+w*y)], [2*(x*y+w*z), 1-2*(x*x+z*z), 2*(y*z-w*x)],
                              [2*(x*z-w*y), 2*(y*z+w*x), 1-2*(x*x+y*y)]])
                d = R @ np.array([(uv_px[0]-intrinsics.cx_px)/intrinsics.fx_px, (uv_px[1]-intrinsics.cy_px)/intrinsics.fy_px, 1.0])
                self.last = Out(t_s, np.asarray(p_cam_ned_m) + 150.0 * d / np.linalg.norm(d), self.n)
                return self.last
            def predict(self, t_s, p_cam_ned_m=None):
                return None

        class Out:
            def __init__(self, t_s, p, n):
                self.t_s, self.p_ned_m, self.v_ned_mps = t_s, p, np.zeros(3)
                self.cov_p_ned_m2 = self.cov_v_ned_m2ps2 = 150.0**2 * np.eye(3)
                self.observable, self.range_m, self.range_sigma_ratio = False, 150.0, 1.0
                self.window_frames, self.model = n, "fixed150"
    ''')
    )
    info = root / f"{dist}.dist-info"
    info.mkdir()
    info.joinpath("METADATA").write_text("Metadata-Version: 2.1\nName: outside-est\nVersion: 0.1\n")
    info.joinpath("entry_points.txt").write_text("[irtrack.estimators]\nfixed150 = outside_est:Est\n")


@pytest.mark.slow
def test_out_of_tree_estimator_through_an_entry_point(tmp_path, monkeypatch):
    _write_outside_package(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("outside_est", None)
    assert "fixed150" in available(ESTIMATORS)
    r = run_lockstep(_p1(), 0, EvalOptions(duration_s=2.0, batch=False, keep_frame=False, estimator="fixed150"))
    s = score_run(r)
    assert r.error is None and s["estimator"] == "fixed150" and s["online_all"] is not None
    assert s["continuity"] == 0.0  # it never claims observability, and the report says so
    assert isinstance(build("outside_est:Est", OnboardConfig()), TrajectoryEstimator)  # the module:Attribute form


def test_bad_names_are_one_line_config_errors(tmp_path, monkeypatch, capsys):
    with pytest.raises(ConfigError, match="--estimator: expected a name registered"):
        load_factory("nope")
    with pytest.raises(ConfigError, match="does not import"):
        load_factory("no_such_module_xyz:Thing")
    with pytest.raises(ConfigError, match="has no attribute"):
        load_factory("math:nothing_here")
    (tmp_path / "half_est.py").write_text("class Half:\n    def add(self, *a):\n        return None\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ConfigError, match="does not implement TrajectoryEstimator"):
        build("half_est:Half", OnboardConfig())
    assert cli_main(["eval", "--estimator", "nope", "--seeds", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--estimator" in err[0]


class BrightestPixel:
    """A tracker plug-in written only against the protocol: the pixel of most local contrast (its 3 x 3 mean over
    its 15 x 15 one) within 100 px of the image's centre, where a gimbal keeps its target; its 3 x 3 centroid."""

    def __init__(self) -> None:
        self.frames = 0

    def update(self, pixels):
        import cv2

        from onboard.imaging import Detection, TrackUpdate
        from onboard.imaging.tracker import TrackState

        img = np.asarray(pixels, dtype=np.float32)
        contrast = cv2.blur(img, (3, 3)) - cv2.blur(img, (15, 15))
        i0, j0 = img.shape[0] // 2 - 100, img.shape[1] // 2 - 100
        centre = contrast[i0 : i0 + 200, j0 : j0 + 200]
        i, j = np.unravel_index(int(np.argmax(centre)), centre.shape)
        i, j = i + i0, j + j0
        win = img[i - 1 : i + 2, j - 1 : j + 2] - float(cv2.blur(img, (15, 15))[i, j])
        win = np.clip(win, 0.0, None)
        self.frames += 1
        if win.sum() <= 0.0:
            return TrackUpdate(TrackState.SEARCHING, None, None, None, None, False, None, None, self.frames - 1)
        jj, ii = np.meshgrid(np.arange(j - 1, j + 2) + 0.5, np.arange(i - 1, i + 2) + 0.5)
        u, v = float((win * jj).sum() / win.sum()), float((win * ii).sum() / win.sum())
        det = Detection(u, v, 9, float(win.max()), float(win.sum()), (j - 1, i - 1, 3, 3), float(img.max()), 10.0)
        return TrackUpdate(TrackState.TRACKING, u, v, (u - 3.0, v - 3.0, 6.0, 6.0), det, True, 1, 0, self.frames - 1)


def test_our_two_image_chains_are_registered_trackers():
    from onboard.imaging import TargetTracker
    from onboard.imaging.objects_chain import ObjectChain
    from onboard.pipeline.plugins import TRACKERS, Tracker

    assert {"objects", "single"} <= set(available(TRACKERS))
    assert isinstance(build("objects", OnboardConfig(), TRACKERS), ObjectChain)
    assert isinstance(build("single", OnboardConfig(), TRACKERS), TargetTracker)
    assert isinstance(build(f"{__name__}:BrightestPixel", OnboardConfig(), TRACKERS), Tracker)


@pytest.mark.slow
def test_a_tracker_plugin_runs_the_lockstep_eval_in_place_of_the_chain():
    """``--tracker module:Attribute``: the plug-in's centroids go to the estimator and its track is scored; on P1's
    clear sky the brightest pixel is the target, so it is on the target and the 3-D is published."""
    opts = dict(duration_s=SHORT_S, batch=False, keep_frame=False)
    r = run_lockstep(_p1(), 0, EvalOptions(**opts, tracker=f"{__name__}:BrightestPixel"))
    s = score_run(r)
    assert r.error is None and s["tracker"] == f"{__name__}:BrightestPixel" and s["estimator"] == "map"
    assert s["perception"]["pd_pct"] > 90.0  # its track is within 3 px of the target
    assert s["estimate_fraction"] > 0.3 and s["online_all"] is not None
    assert score_run(run_lockstep(_p1(), 0, EvalOptions(**opts)))["tracker"] == "objects"  # the configuration's


def test_an_unknown_tracker_is_a_one_line_error_before_any_run(capsys):
    with pytest.raises(ConfigError, match="--tracker: expected a name registered under irtrack.trackers"):
        EvalOptions(tracker="nope")
    assert cli_main(["eval", "--tracker", "nope", "--seeds", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--tracker" in err[0]


def _look_at_q(p_cam, p_tgt):
    z = p_tgt - p_cam
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return quat_from_rotmat(np.stack([x, y, z], axis=1))  # columns: camera axes in NED


def test_rpekf_converges_on_perfect_bearings_from_a_manoeuvring_observer():
    """Exact bearings of a constant-velocity target seen from a circling observer: range becomes
    observable and the bank's mixture converges (a filter stuck on its first hypotheses fails this)."""
    K = PinholeIntrinsics(fx_px=765.0, fy_px=765.0, cx_px=320.0, cy_px=256.0, width_px=640, height_px=512)
    est = RangeParameterisedEkf(RpEkfConfig(pixel_sigma_px=0.05))
    out, filtered, truth = None, [], []
    for k in range(600):  # 20 s at 30 Hz
        t = k / 30.0
        p_cam = np.array([30.0 * math.cos(0.5 * t), 30.0 * math.sin(0.5 * t), -60.0 - 5.0 * math.sin(0.3 * t)])
        p_tgt = np.array([200.0 + 3.0 * t, 50.0 + 2.0 * t, -80.0])
        q = _look_at_q(p_cam, p_tgt)
        out = est.add(t, (320.0, 256.0), K, p_cam, q)  # the target at the principal point: exact bearing
        filtered.append(out.p_ned_m)
        truth.append(p_tgt)
    err = np.linalg.norm(out.p_ned_m - p_tgt)
    assert err / out.range_m < 0.03, (err, out.range_m, out.weights)  # started with hypotheses from 20 m to 2 km
    assert max(out.weights) > 0.9  # the bank settled on one range hypothesis
    assert err < 3.0 * math.sqrt(np.trace(out.cov_p_ned_m2))  # and its covariance is honest about the rest
    assert out.range_sigma_ratio < 0.1
    t_s, p_s, cov_s = est.smoothed()
    assert p_s.shape == (600, 3) and np.all(np.isfinite(cov_s))
    e_filt = np.linalg.norm(np.array(filtered) - truth, axis=1)
    e_smooth = np.linalg.norm(p_s - truth, axis=1)
    assert e_smooth[-1] == pytest.approx(e_filt[-1])  # the last step is the filter's
    assert e_smooth.mean() < 0.5 * e_filt.mean()  # the RTS pass carries the converged range back in time


FAULTS = "tests.groundsim.plugin_faults"


def test_an_estimator_that_calls_sys_exit_fails_its_eval_run_naming_it():
    """SystemExit is not an Exception: it went through the run's wrapper and ended the command (or, in a pool, the
    worker, its run never finished)."""
    from groundsim.evaluation.eval import _job

    opts = EvalOptions(duration_s=1.5, batch=False, keep_frame=False, estimator=f"{FAULTS}:ExitsOnAdd")
    r = _job((_p1(), 0, opts, None))
    assert r.error is not None and r.error.startswith("SystemExit in a run with estimator"), r.error
    assert "ExitsOnAdd" in r.error


@pytest.mark.integration
@pytest.mark.multicore
def test_a_campaign_on_a_pool_with_an_algorithm_that_exits_fails_those_runs_and_keeps_the_others(tmp_path):
    from groundsim.evaluation.campaign import run_campaign
    from groundsim.evaluation.campaign_spec import spec_from_dict

    spec = spec_from_dict(
        {
            "name": "t",
            "scenarios": ["P1"],
            "noise": ["RTK"],
            "algorithms": ["paper", f"{FAULTS}:ExitsOnAdd"],
            "seeds": 2,
            "duration_s": 1.0,
        },
        source=tmp_path / "spec.yaml",
        spec_dir=tmp_path,
    )
    res = run_campaign(spec, tmp_path / "out", workers=2, progress=False)
    assert res.ran == 4 and res.failed == 2
    import pandas as pd

    t = pd.read_csv(tmp_path / "out" / "runs.csv")
    bad = t[t["algorithm"].str.endswith("ExitsOnAdd")]
    assert (bad["status"] == "failed").all() and bad["error"].str.startswith("SystemExit in algorithm").all()
    assert (t[t["algorithm"] == "paper"]["status"] == "ok").all()


@pytest.mark.integration
@pytest.mark.multicore
def test_a_closed_loop_algorithm_that_kills_its_worker_loses_its_own_run_not_the_cases_others(tmp_path):
    """Closed-loop runs share nothing within a case, so each is a job of its own: an algorithm whose plug-in ends the
    pool's worker fails its run (WorkerLost) and the case's other algorithm keeps its row (one job a case had lost
    both)."""
    from groundsim.evaluation.campaign import run_campaign
    from groundsim.evaluation.campaign_spec import spec_from_dict

    spec = spec_from_dict(
        {
            "name": "t",
            "mode": "closed_loop",
            "scenarios": ["P1"],
            "noise": ["RTK"],
            "algorithms": ["paper", f"{FAULTS}:LeavesOnAdd"],
            "seeds": 1,
            "duration_s": 1.0,
            "crb": False,
        },
        source=tmp_path / "spec.yaml",
        spec_dir=tmp_path,
    )
    res = run_campaign(spec, tmp_path / "out", workers=2, progress=False)
    assert res.ran == 2 and res.failed == 1
    import pandas as pd

    t = pd.read_csv(tmp_path / "out" / "runs.csv").set_index("algorithm")
    assert t.loc["paper", "status"] == "ok", t.loc["paper", "error"]
    assert t.loc[f"{FAULTS}:LeavesOnAdd", "error"].startswith("WorkerLost in algorithm")


def test_a_plugin_exception_is_counted_per_frame_in_the_baseline_and_the_loop_not_a_failed_eval(monkeypatch):
    """The daemon skips a frame whose pipeline raises (pipeline_error) and the pipeline counts an estimator's
    exception; the eval's baseline and loop had let the same exceptions end the run with a traceback."""
    from onboard.pipeline.frame_pipeline import FramePipeline

    opts = dict(duration_s=1.5, batch=False, keep_frame=False)
    r = run_lockstep(_p1(), 0, EvalOptions(**opts, estimator=f"{FAULTS}:RaisesSometimes"))
    assert r.error is None and r.counters.get("baseline_estimator_error", 0) > 0, r.counters

    def process(self, frame):  # whatever escapes the pipeline (a plug-in's error it does not catch itself)
        raise RuntimeError("escaped the pipeline")

    monkeypatch.setattr(FramePipeline, "process", process)
    r = run_lockstep(_p1(), 0, EvalOptions(**opts))
    assert r.error is None and r.counters.get("pipeline_error", 0) == r.frames > 0, r.counters


def test_an_algorithm_writing_into_its_inputs_cannot_move_the_next_ones_campaign_row(tmp_path):
    """The algorithms of a synthetic case share its observations: one that wrote into them (a plug-in) had moved
    the pixels and camera positions the next algorithm read (map's row: all estimator errors, nothing published)."""
    from groundsim.evaluation.campaign import run_campaign
    from groundsim.evaluation.campaign_spec import spec_from_dict

    def paper_row(algorithms, out):
        d = {"name": "t", "scenarios": ["P1"], "noise": ["RTK"], "algorithms": algorithms, "seeds": 1}
        spec = spec_from_dict({**d, "duration_s": 1.0}, source=tmp_path / "spec.yaml", spec_dir=tmp_path)
        run_campaign(spec, tmp_path / out, workers=1, progress=False)
        import pandas as pd

        t = pd.read_csv(tmp_path / out / "runs.csv")
        return t[t["algorithm"] == "paper"].iloc[0]

    alone = paper_row(["paper"], "alone")
    after = paper_row([f"{FAULTS}:WritesInputs", "paper"], "after")
    assert after["status"] == "ok" and after["estimator_errors"] == alone["estimator_errors"] == 0
    assert alone["published_frames"] > 0
    for col in ("published_frames", "err_range_published_settled_pct", "rmse_published_settled_m"):
        assert after[col] == alone[col] or (math.isnan(after[col]) and math.isnan(alone[col])), col


def test_the_eval_baseline_gets_read_only_camera_poses():
    """The baseline's camera positions are rows of the poses the batch and the scores read after it."""
    from tests.groundsim.plugin_faults import WritesInputs

    opts = EvalOptions(duration_s=1.5, batch=False, keep_frame=False, estimator=f"{FAULTS}:WritesInputs")
    r = run_lockstep(_p1(), 0, opts)
    baseline = WritesInputs.instances[-1]
    assert r.error is None and baseline.seen_writable and not any(baseline.seen_writable)


@pytest.mark.parametrize(
    "mode, algorithm, counted",
    [("synthetic", "NanPosition", "invalid estimate: "), ("closed_loop", "RaisesSometimes", "estimator_error ")],
)
def test_a_campaign_row_counts_the_estimator_errors(tmp_path, mode, algorithm, counted):
    """A synthetic row dropped an estimate that was not finite without a word; a closed-loop row said 0 errors
    whatever the run's counters held."""
    import pandas as pd

    from groundsim.evaluation.campaign import run_campaign
    from groundsim.evaluation.campaign_spec import spec_from_dict

    d = {"name": "t", "mode": mode, "scenarios": ["P1"], "noise": ["RTK"], "seeds": 1, "crb": False}
    spec = spec_from_dict(
        {**d, "algorithms": [f"{FAULTS}:{algorithm}"], "duration_s": 1.5},
        source=tmp_path / "spec.yaml",
        spec_dir=tmp_path,
    )
    run_campaign(spec, tmp_path / "out", workers=1, progress=False)
    row = pd.read_csv(tmp_path / "out" / "runs.csv").iloc[0]
    assert row["status"] == "ok" and row["estimator_errors"] > 0 and row["error"].startswith(counted), dict(row)
    # the report names the run and its first error (its table row read '-' with nothing saying why: a walkthrough)
    report = (tmp_path / "out" / "report.md").read_text()
    assert "## Runs with estimator errors" in report and f"{int(row['estimator_errors'])} frames, the first: " in report
