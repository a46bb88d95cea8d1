"""The scene benchmark's scoring (bench.imaging_scenes): Pd over the warm target frames, the missed frames,
and its frame cache refusing labels written before they carried ``warm``."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.imaging_scenes import (
    LABEL_FIELDS,
    SceneRun,
    frame_ranges,
    load_cache,
    miss_cause,
    misses_line,
    point_line,
    score,
)
from onboard.core.frames import PinholeIntrinsics

RATE_HZ = 30.0
N_FRAMES = 90  # the first 30 (1 s) are not counted: Pd counts frames 30..89
COLD_FROM = 60  # the target is colder than its background from this frame on
MISSED_WARM = (30, 31, 32)  # warm frames the fake chain misses
TARGET_UV = (20.5, 10.5)


class _FakeChain:
    """Reports one confirmed track on the target on the warm frames it does not miss, none otherwise."""

    stage_s = None

    def __init__(self) -> None:
        self.k = 0

    def update(self, image, R_ned_from_cam):
        k, self.k = self.k, self.k + 1
        if k < COLD_FROM and k not in MISSED_WARM:
            return [(7, *TARGET_UV)], 7
        return [], None


def _run() -> SceneRun:
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 255, (32, 40), dtype=np.uint8) for _ in range(N_FRAMES)]
    labels = [[(0, "target", *TARGET_UV, "visible", 8.0, k < COLD_FROM)] for k in range(N_FRAMES)]
    R = np.repeat(np.eye(3)[None], N_FRAMES, axis=0)
    intr = PinholeIntrinsics(50.0, 50.0, 20.0, 16.0, 40, 32)
    return SceneRun("fake", frames, labels, R, intr, RATE_HZ)


def test_pd_warm_counts_only_the_frames_where_the_target_is_warm():
    s = score(_run(), _FakeChain())
    counted = N_FRAMES - int(RATE_HZ)  # 60
    warm = COLD_FROM - int(RATE_HZ)  # 30
    assert s["pd_target"] == pytest.approx(100.0 * (warm - len(MISSED_WARM)) / counted)  # 45 %
    assert s["pd_warm"] == pytest.approx(100.0 * (warm - len(MISSED_WARM)) / warm)  # 90 %
    assert s["target_counted"] == counted
    assert [(k, w) for k, w, _ in s["misses"]] == [(k, True) for k in MISSED_WARM] + [
        (k, False) for k in range(COLD_FROM, N_FRAMES)
    ]
    assert all(c in ("edge", "surround", "faint", "other") for _, w, c in s["misses"] if w)
    assert all(c is None for _, w, c in s["misses"] if not w)
    line = misses_line(s["misses"], s["target_counted"])
    assert (
        "missed on 33 of 60 frames" in line and "warm 3 (" in line and "): 30-32;" in line and "cold 30: 60-89" in line
    )


def test_pd_point_counts_the_warm_frames_where_the_target_is_a_point_against_its_surround():
    """On a flat field the warm target is a point on every frame (10 grey over the field): Pd point is the fake
    chain's 27 of the 30 counted warm frames; with a road 40 grey brighter 3 px from it, it is a point on none."""
    for road, counted in ((False, 30), (True, 0)):
        run = _run()
        j, i = int(TARGET_UV[0]), int(TARGET_UV[1])
        for k, f in enumerate(run.frames):
            f[:] = 60
            if road:
                f[:, j + 3 :] = 100
            if k < COLD_FROM:
                f[i - 1 : i + 1, j - 1 : j + 1] = 70
        s = score(run, _FakeChain())
        assert s["point_counted"] == counted
        if counted:
            assert s["pd_point"] == pytest.approx(100.0 * (counted - len(MISSED_WARM)) / counted)
            assert "(30 of 60 counted frames): Pd 90.0 %" in point_line(s)
        else:
            assert np.isnan(s["pd_point"])


def test_misses_line_counts_the_warm_misses_by_cause():
    misses = [(5, True, "surround"), (6, True, "surround"), (7, True, "faint"), (9, False, None)]
    line = misses_line(misses, 20)
    assert "warm 3 (brighter surround 2, <= 2 grey 1): 5-7; cold 1: 9" in line
    assert "warm 0: -; cold 0: -" in misses_line([], 20)


def _flat(grey: int, dtype=np.uint8) -> np.ndarray:
    return np.full((64, 64), grey, dtype)


@pytest.mark.parametrize(
    "draw, cause",
    [
        # a 2 x 2 target 10 grey over a flat field: seen by any threshold the chain might set
        (lambda f: f.__setitem__((slice(31, 33), slice(31, 33)), 70), "other"),
        # the same target 1 grey over the field: the 8-bit grey's own step
        (lambda f: f.__setitem__((slice(31, 33), slice(31, 33)), 61), "faint"),
        # 10 grey over the field, with a road 40 grey brighter 3 px to its right: its point contrast is negative
        (
            lambda f: (
                f.__setitem__((slice(0, 64), slice(35, 64)), 100),
                f.__setitem__((slice(31, 33), slice(31, 33)), 70),
            ),
            "surround",
        ),
    ],
)
def test_miss_cause(draw, cause):
    f = _flat(60)
    draw(f)
    assert miss_cause(f, 32.0, 32.0) == cause
    assert miss_cause(f, 2.0, 32.0) == "edge"


def test_miss_cause_reads_16_bit_grey_as_8_bit():
    f = _flat(60 * 257, np.uint16)
    f[31:33, 31:33] = 60 * 257 + 300  # 1.2 grey8
    assert miss_cause(f, 32.0, 32.0) == "faint"
    f[31:33, 31:33] = 60 * 257 + 2570  # 10 grey8
    assert miss_cause(f, 32.0, 32.0) == "other"


def test_frame_ranges():
    assert frame_ranges([9, 3, 4, 5, 11, 12]) == "3-5, 9, 11-12"
    assert frame_ranges([]) == ""


def test_cache_without_warm_is_not_read(tmp_path):
    def write(path, label):
        frames = np.empty(1, dtype=object)
        frames[0] = np.zeros((2, 2), np.uint8)
        labels = np.empty(1, dtype=object)
        labels[0] = [label]
        np.savez(path, frames=frames, labels=labels, R=np.eye(3)[None])

    old = (0, "target", 1.0, 1.0, "visible", 5.0)
    write(tmp_path / "old.npz", old)
    write(tmp_path / "new.npz", (*old, False))
    assert LABEL_FIELDS == len(old) + 1
    assert load_cache(tmp_path / "old.npz") is None  # read as all warm, it would count a cold target
    frames, labels, R = load_cache(tmp_path / "new.npz")
    assert labels[0][0][-1] is False and frames[0].shape == (2, 2) and R.shape == (1, 3, 3)


def test_terrain_resolution_renders_and_caches_apart(tmp_path):
    """``--terrain-resolution``: C2's frames with its terrain looked up at full resolution (the default) or at half,
    cached under their own names (frames cached before the default changed, untagged, are read only as half), the
    labels' positions the same; a scene without terrain as it is."""
    from bench.imaging_scenes import render_scene, world_digest

    full = render_scene("C2", 0, 2, tmp_path)
    half = render_scene("C2", 0, 2, tmp_path, terrain_resolution="half")
    names = sorted(p.name for p in tmp_path.iterdir())
    d = world_digest("C2")  # the simulator's source and the scenario's file: a change renders them again
    assert names == [f"C2-mono8-fullterrain-s0-0.067-{d}.npz", f"C2-mono8-s0-0.067-{d}.npz"]
    again = render_scene("C2", 0, 2, tmp_path, terrain_resolution="full")  # read back from its cache
    assert np.array_equal(again.frames[1], full.frames[1])
    assert len(full.frames) == len(half.frames) == 2
    assert not np.array_equal(full.frames[0], half.frames[0])
    # the same target where it is: the terrain's sampling moves no label
    assert [lb[2:4] for lb in full.labels[0]] == [lb[2:4] for lb in half.labels[0]]
    render_scene("C4", 0, 1, tmp_path, terrain_resolution="half")  # no terrain: the one name
    assert any(p.name.startswith("C4-mono16-s0-") for p in tmp_path.iterdir())


def test_seeds_summary_counts_the_seeds_that_reach_95_percent():
    from bench.imaging_scenes import seeds_summary

    runs = [
        (0, {"pd": 96.3, "pd_point": 97.0, "HOTA": 0.855, "false_per_min": 0.0}),
        (1, {"pd": 70.1, "pd_point": 99.0, "HOTA": 0.612, "false_per_min": 6.0}),
        (4, {"pd": 95.0, "pd_point": math.nan, "HOTA": 0.951, "false_per_min": 0.0}),
    ]
    line = seeds_summary("C2", "objects", runs)
    assert "seeds 0, 1, 4" in line and "Pd 96.3 / 70.1 / 95.0 %" in line
    assert ">= 95 % on 2 of 3" in line and "at most 6.0" in line and "HOTA 0.612-0.951" in line
    assert "a warm point 97.0 / 99.0 / nan % (>= 95 % on 2 of 2 with such frames)" in line
    assert "CPU" not in line  # no frames' times: no cost said


def test_seeds_summary_gives_the_cpu_median_over_every_frame_beside_each_seeds():
    from bench.imaging_scenes import seeds_summary

    runs = [
        (
            0,
            {
                "pd": 99.0,
                "pd_point": 99.0,
                "HOTA": 0.8,
                "false_per_min": 0.0,
                "cpu_ms_frames": [1.0, 2.0, 9.0],
                "cpu_ms_p50": 2.0,
            },
        ),
        (
            1,
            {
                "pd": 99.0,
                "pd_point": 99.0,
                "HOTA": 0.8,
                "false_per_min": 0.0,
                "cpu_ms_frames": [3.0, 4.0, 4.5],
                "cpu_ms_p50": 4.0,
            },
        ),
    ]
    line = seeds_summary("C3", "objects", runs)
    assert "CPU ms per frame p50 3.50 over all 6 frames (2.00-4.00 by seed)" in line


def test_duration_flies_past_the_scenarios_end_and_caches_apart(tmp_path):
    """``--duration``: P1 (10 s) flown 10.5 s, its motions continued: 315 frames, the last labelled, cached
    under its own duration; the default stays the scenario's 300."""
    from bench.imaging_scenes import render_scene, world_digest

    longer = render_scene("P1", 0, None, tmp_path, duration_s=10.5)
    assert len(longer.frames) == 315 and longer.labels[-1]
    assert [p.name for p in tmp_path.iterdir()] == [f"P1-mono8-s0-10.500-{world_digest('P1')}.npz"]
    assert len(render_scene("P1", 0, 3, tmp_path, duration_s=10.5).frames) == 3  # --frames still the first N


@pytest.mark.parametrize("bad", ["0", "-3", "nan"])
def test_duration_refuses_what_is_not_seconds(bad, capsys):
    from bench.imaging_scenes import main

    with pytest.raises(SystemExit) as exc:
        main(["--scene", "P1", "--duration", bad])
    assert exc.value.code == 2 and "--duration" in capsys.readouterr().err


def test_the_chains_get_the_attitude_the_telemetry_reports(tmp_path):
    """By default the scenario's navigation errors (RTK): each frame's camera attitude is the truth rotated by
    the error the simulated autopilot reports at that frame's tick, as ``groundsim eval`` draws it; ``exact``
    gives the truth, which is what the cache holds."""
    from bench.imaging_scenes import render_scene
    from groundsim.world.scenario import load_scenario, scenarios_dir
    from groundsim.world.sim import SimCore
    from onboard.core.frames import quat_from_rotvec, rotmat_from_quat

    rtk = render_scene("P1", 0, 3, tmp_path)
    exact = render_scene("P1", 0, 3, tmp_path, nav_noise="exact")  # read back from the cache
    _, _, R_cached = load_cache(next(tmp_path.iterdir()))
    assert (rtk.nav_noise, exact.nav_noise) == ("RTK", "exact")
    np.testing.assert_array_equal(exact.R_ned_from_cam, R_cached)
    core = SimCore(load_scenario(scenarios_dir() / "P1.yaml"), 0, duration_s=3 / 30.0, render=False)
    for k in range(3):
        phi = core.nav_error(k * core.ticks_per_frame).att_err_ned_rad
        expected = rotmat_from_quat(quat_from_rotvec(phi)) @ R_cached[k]
        np.testing.assert_allclose(rtk.R_ned_from_cam[k], expected, atol=1e-12)
        # RTK: 0.1 deg bias, 0.05 deg white per axis; the rotation between the two is phi's size
        angle = np.arccos(np.clip((np.trace(rtk.R_ned_from_cam[k] @ R_cached[k].T) - 1) / 2, -1, 1))
        assert angle == pytest.approx(np.linalg.norm(phi), abs=1e-9) and 0 < angle < np.radians(0.6)


def test_an_unknown_nav_noise_is_refused_naming_the_file(capsys):
    from bench.imaging_scenes import main

    with pytest.raises(SystemExit) as exc:
        main(["--scene", "P1", "--nav-noise", "rtk"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "noise_cases.yaml" in err and "--nav-noise" in err and "did you mean 'RTK'" in err


def test_repeated_runs_keep_each_frames_least_time_for_the_summary(monkeypatch):
    """With --repeat, every per-frame time the summary reads is the frame's least over the runs, as its median is."""
    import bench.imaging_scenes as sc

    runs = iter(
        [
            {"ms_frames": [3.0, 1.0, 5.0], "cpu_ms_frames": [3.0, 1.0, 5.0], "stage_ms_frames": []},
            {"ms_frames": [2.0, 4.0, 1.0], "cpu_ms_frames": [2.0, 4.0, 1.0], "stage_ms_frames": []},
        ]
    )
    monkeypatch.setattr(sc, "score", lambda run, chain: next(runs))
    s = sc.score_repeated(None, lambda run, stages: None, 2)
    assert s["cpu_ms_frames"] == [2.0, 1.0, 1.0] and s["ms_frames"] == [2.0, 1.0, 1.0]
    assert s["cpu_ms_p50"] == 1.0


def test_chain_single_is_the_tracker_chain_as_the_daemon_names_it(tmp_path, capsys):
    """imaging.chain, eval --tracker and bench.companion --chain call it 'single'; this bench refused the name
    ('invalid choice') and knew it only as 'tracker' (a newcomer's walkthrough)."""
    from bench.imaging_scenes import main

    main(["--scene", "P2", "--chain", "single", "--frames", "3", "--cache", str(tmp_path)])
    rows = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("P2 ")]
    assert len(rows) == 1 and rows[0].split()[1] == "tracker"


def test_plots_draw_the_runs_objects_timeline_from_its_mot_lines(tmp_path, capsys):
    from bench.imaging_scenes import _plot_objects
    from groundsim.evaluation.mot import object_timeline

    run = _run()
    s = score(run, _FakeChain())
    tl = object_timeline(s["mot_gt"], s["mot_tracker"])
    (rows,) = tl["objects"].values()  # the target: tracked by id 7 on the warm frames the chain does not miss
    assert [f - 1 for f, _, tid in rows if tid == 7] == [k for k in range(COLD_FROM) if k not in MISSED_WARM]
    assert tl["false"] == {}
    _plot_objects(tmp_path, "fake", 3, "objects", s, run)
    assert (tmp_path / "fake-s3-objects.png").read_bytes()[:4] == b"\x89PNG"
    assert "objects timeline: " in capsys.readouterr().out
