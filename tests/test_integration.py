"""End to end: the ground simulator and the onboard daemon as two processes over UDP
MAVLink and zenoh on 127.0.0.1; this process subscribes to the track key and scores the track against
the simulator's truth on the three reference scenarios (P1, P2, P3), flown for 20 s instead of their 10 s.

Criterion: the daemon's range-normalised error ``mean ||p_hat - p|| / ||p - c||`` is within
1.5x of what the foundation's estimator reaches from perfect centroids on the same scenario.  The
yardstick (:func:`tests.integration_helpers.perfect_centroid_baseline`) is the daemon's own sliding-window
estimator, built from the very configuration file the daemon read, fed from the truth CSV of the same
run: the true target pixel + 0.3 px white noise (the reference study's px0.3 case), the camera pose the
vehicle reported (the truth plus the simulator's navigation errors, RTK by default, recorded in the
truth CSV: the daemon could not have known better), each frame's capture time.  It is scored on exactly the frames
the daemon's track is scored on; its error is the median of ``BASELINE_DRAWS`` noise draws (one draw can
select another motion model and be 10x off in either direction: P1 measured 1.4-2.6 % for four draws and
25 % for the fifth).

Which frames: the daemon's observable frames (what it publishes by default) when there are at least
``MIN_OBSERVABLE_FRAMES`` of them; otherwise every frame with a 3-D position, observable or not (the
daemon's configuration from :func:`groundsim.evaluation.demo.plan_demo` has ``output.unobservable_positions: true``).
Both comparisons are printed (``pytest -s``).

Why 20 s and exact navigation for this comparison (``FLIGHT_S``, ``NAV_NOISE``): range comes from the
observer's manoeuvre, and within the scenarios' 10 s it is observable on none or a few frames, so the
comparison fell back to unobservable estimates (20-40 % errors) -- noise compared with noise.  Under the
simulator's default RTK navigation errors, even at 20 s, P1's motion models stay ambiguous (a looser model
holds 10-40 % of the posterior), and one run's error is a lottery: on identical input
(same seed) the daemon's observable-frame error measured 0.47-1.28 % over five runs, the yardstick's three
noise draws 0.31-0.85 %, so a 1.5x bound on one run failed about one run in three while every output was
within the precision target (``RTK_MAX_MEDIAN_ERROR``).  With exact navigation the estimate is well determined and the
comparison measures what the daemon adds between the pixels and the 3-D point -- its image chain, its pose
interpolation, its estimator worker -- which is what this comparison is for (measured: daemon 0.03-0.05 %, yardstick
0.12-0.27 %, ratio 0.15-0.25).  The realistic case is asserted on its own terms below
(:func:`test_daemon_under_rtk_navigation_publishes_precise_honest_observable_positions`): the precision
and honesty targets on the observable frames of a 20 s P2 flight under the default RTK errors.  P3 flies
19.5 s: its scripted observer leaves the reference track right after.

Pacing: real time (``--rate 1.0``).  At 2x the daemon dropped up to 26 of 300 frames and its estimator
process fell more than ``estimator.max_extrapolation_s`` behind (P1: no 3-D position at all), which is a
test of the machine rather than of the daemon.

Wall time (:func:`flights`): the three comparison flights are flown at once: a pair of processes took
about half a core at real time with the single image chain (the objects chain, the default now, adds about 0.1
of a core a daemon), so three take 1.5-1.8 of the machine's two cores (measured with the machine
loaded by other work, load average 12: no frame dropped, about 50 s for the three instead of about 40 s
each one after the other).  The RTK flight follows them, while the comparison tests compute their
baselines (three noise draws per scenario, about 2 s of CPU each, one core): again about 1.5 cores.  All
four at once need the whole machine: under the same load they dropped up to 41 of 585 frames, the
simulators fell 12-16 s behind real time and one daemon overran its stop budget -- a test of the machine.
Only the RTK flight's daemon starts with the three comparison daemons, before anything flies (its start is
about 3 s of CPU, which delays no real-time flight; ready, it waits at almost no cost), and its simulator starts
as soon as the three comparison simulators have exited, not after their drain, stop and truth read.
(Selecting the RTK test alone still flies the comparison flights first.)
"""

from __future__ import annotations

import math
import signal
import threading

import numpy as np
import pytest

from tests.integration_helpers import (
    Comparison,
    compare,
    lengthened_scenario,
    perfect_centroid_baseline,
    run_pair,
    track_arrays,
    truth_arrays,
)

SCENARIOS = ("P1", "P2", "P3")
FLIGHT_S = {"P1": 20.0, "P2": 20.0, "P3": 19.5}  # flown seconds (the module docstring says why not 10 s)
NAV_NOISE = "exact"  # the comparison's navigation case (the module docstring says why); the RTK test uses the default
RTK_SCENARIO = "P2"
RTK_MIN_OBSERVABLE_FRAMES = 30
RTK_MAX_MEDIAN_ERROR = 0.02  # precision target: observable runs' median error <= 2 % of range
RTK_MAX_BEYOND_3SIGMA = 0.01  # honesty target: <= 1 % of the points beyond 3 sqrt(trace(cov))
RATE = "1.0"  # --rate of the simulator: real time (see the module docstring)
PIXEL_SIGMA_PX = 0.3  # = groundsim.evaluation.eval.DEFAULT_PIXEL_SIGMA_PX, perfect-centroid noise per axis
BASELINE_DRAWS = 3  # noise draws of the baseline; the yardstick is their median error
MAX_ERROR_RATIO = 1.5  # daemon error / perfect-centroid error: what the daemon's chain may add
MIN_OBSERVABLE_FRAMES = 30  # 1 s at 30 fps: fewer observable frames -> compare on all frames with a position
MIN_SCORED_FRAMES = 30  # the compared selection must hold at least this many frames
MIN_TRACKED_FRACTION = 0.9  # frames of the truth that got a track message from the daemon
SCENARIO_TIMEOUT_S = 150  # one test: the three flights at once (~50 s) then baselines or RTK (~40 s), busy machine
EXIT_OK = (0, -signal.SIGTERM)  # 0, or ended by our SIGTERM before its handler was installed
ATOL_M = 1e-6  # 1 um: geodetic round trip of the synthetic scoring test


def _choose(observable: Comparison, every: Comparison) -> Comparison:
    """The observable comparison when the daemon published enough observable frames, else all frames."""
    return observable if observable.frames >= MIN_OBSERVABLE_FRAMES else every


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """The four flights as futures of :class:`~tests.integration_helpers.PairRun` (a flight that failed fails
    its own test only): the three comparison flights (``SCENARIOS``, ``NAV_NOISE``) at once, one thread per
    pair of processes, then the RTK flight (key ``"RTK"``), which flies while the comparison tests compute
    their baselines in this process (the module docstring says why not all four at once).  The RTK flight's
    daemon starts with the others; its simulator once the three comparison simulators have exited."""
    from concurrent.futures import ThreadPoolExecutor

    out = tmp_path_factory.mktemp("flights")

    def fly(name: str, key: str, nav_noise: str | None, **when):
        d = out / key
        return run_pair(str(lengthened_scenario(name, FLIGHT_S[name], d)), d, rate=RATE, nav_noise=nav_noise, **when)

    pool = ThreadPoolExecutor(len(SCENARIOS) + 1)
    flown = {name: threading.Event() for name in SCENARIOS}  # set by each run, however it ends
    comparisons_flown = threading.Event()
    runs = {name: pool.submit(fly, name, name, NAV_NOISE, flown=flown[name]) for name in SCENARIOS}
    runs["RTK"] = pool.submit(fly, RTK_SCENARIO, "RTK", None, fly_when=comparisons_flown)
    try:
        for event in flown.values():
            event.wait()
    finally:
        comparisons_flown.set()  # whatever happened here: the RTK run must not wait for ever
    yield runs
    pool.shutdown(wait=True)  # each run stops its processes by PID whatever happens


@pytest.mark.integration
@pytest.mark.timeout(SCENARIO_TIMEOUT_S)
@pytest.mark.parametrize("name", SCENARIOS)
def test_daemon_track_matches_truth_within_1p5x_of_perfect_centroids(name, flights):
    from groundsim.evaluation.parallel import limit_blas_threads

    limit_blas_threads(1)  # the baselines run here; the children get OPENBLAS_NUM_THREADS=1 too
    run = flights[name].result()
    truth = truth_arrays(run.truth)
    F = truth["time_boot_us"].size
    daemon = track_arrays(run.tracks, truth["time_boot_us"], run.scenario.origin)
    bases = [
        perfect_centroid_baseline(
            run.config_path, run.truth, PIXEL_SIGMA_PX, run.scenario.rng("eval.centroid_noise", draw)
        )
        for draw in range(BASELINE_DRAWS)
    ]
    obs_cmp = compare("observable", run.truth, daemon, bases, daemon["observable"])
    all_cmp = compare("all", run.truth, daemon, bases, np.ones(F, dtype=bool))
    chosen = _choose(obs_cmp, all_cmp)
    frames = (run.status or {}).get("frames") or {}
    base_obs = [int(b["observable"].sum()) for b in bases]
    report = "\n".join(
        [
            f"{name}: {F} frames simulated, {int(daemon['tracked'].sum())} with a track message, "
            f"{int(np.isfinite(daemon['p_ned_m'][:, 0]).sum())} with a position, {int(daemon['observable'].sum())} "
            f"observable (perfect-centroid estimator: {base_obs} observable); daemon status frames {frames}; "
            f"wall {run.wall_s:.1f} s (simulator {run.sim_wall_s:.1f} s)",
            "  " + obs_cmp.line(),
            "  " + all_cmp.line(),
            f"  scored on: {chosen.selection} frames",
        ]
    )
    print("\n" + report)

    assert run.exit_codes["sim"] == 0 and run.exit_codes["daemon"] in EXIT_OK, f"{run.exit_codes}\n{report}"
    assert run.bad_messages == 0, f"{run.bad_messages} track/status messages failed the schema\n{report}"
    assert F == round(run.scenario.duration_s * run.scenario.frame_rate_hz), report
    assert daemon["tracked"].sum() >= MIN_TRACKED_FRACTION * F, report
    assert chosen.frames >= MIN_SCORED_FRAMES, report
    assert math.isfinite(chosen.daemon_err) and chosen.baseline_err > 0, report
    assert chosen.ratio <= MAX_ERROR_RATIO, report


@pytest.mark.integration
@pytest.mark.timeout(SCENARIO_TIMEOUT_S)
def test_daemon_under_rtk_navigation_publishes_precise_honest_observable_positions(flights):
    """The realistic default end to end: the simulator with its default (RTK) navigation errors, the shipped
    daemon configuration, P2 flown 20 s: observable positions on at least ``RTK_MIN_OBSERVABLE_FRAMES``
    frames, their median error <= 2 % of range, at most 1 % of them beyond 3 sqrt(trace(cov)), and no
    published position (observable or not) beyond 3 sqrt(trace(cov)) on more than 1 % of the frames."""
    run = flights["RTK"].result()
    truth = truth_arrays(run.truth)
    daemon = track_arrays(run.tracks, truth["time_boot_us"], run.scenario.origin)
    has_p = np.all(np.isfinite(daemon["p_ned_m"]), axis=1) & np.isfinite(daemon["sqrt_trace_cov_m"])
    err_m = np.linalg.norm(daemon["p_ned_m"] - truth["target_p_ned_m"], axis=1)
    rng_m = np.linalg.norm(truth["target_p_ned_m"] - truth["cam_p_ned_m"], axis=1)
    beyond = err_m > 3.0 * daemon["sqrt_trace_cov_m"]
    obs = daemon["observable"] & has_p
    n_obs = int(obs.sum())
    report = (
        f"{RTK_SCENARIO} RTK: {truth['time_boot_us'].size} frames, {int(has_p.sum())} with a position, {n_obs} observable; "
        f"observable median error {100 * np.median(err_m[obs] / rng_m[obs]) if n_obs else math.nan:.3f} % of range, "
        f"beyond 3 sigma: observable {int((beyond & obs).sum())}, all {int((beyond & has_p).sum())}"
    )
    print("\n" + report)
    assert run.exit_codes["sim"] == 0 and run.exit_codes["daemon"] in EXIT_OK, f"{run.exit_codes}\n{report}"
    assert run.bad_messages == 0, report
    assert n_obs >= RTK_MIN_OBSERVABLE_FRAMES, report
    assert np.median(err_m[obs] / rng_m[obs]) <= RTK_MAX_MEDIAN_ERROR, report
    assert (beyond & obs).sum() <= RTK_MAX_BEYOND_3SIGMA * n_obs, report
    assert (beyond & has_p).sum() <= RTK_MAX_BEYOND_3SIGMA * has_p.sum(), report


def test_scoring_matches_tracks_to_truth_frames_and_uses_the_median_draw():
    """The scoring itself on a synthetic run: positions from the WGS84 fields, frames matched on
    time_boot_us (an unknown time is ignored), errors normalised by the truth range."""
    from groundsim.world.scenario import load_scenario, scenarios_dir
    from onboard.core.frames import geodetic_from_ned

    origin = load_scenario(scenarios_dir() / "P1.yaml").origin
    F = 4
    t_us = 1_000_000 + np.arange(F, dtype=np.int64) * 33_333
    target = np.array([[100.0, 0.0, -50.0]] * F)
    cam = np.array([[0.0, 0.0, -50.0]] * F)  # range 100 m
    truth = {
        "time_boot_us": t_us,
        "target_u_px": np.full(F, 320.0),
        "target_v_px": np.full(F, 256.0),
        "target_visible": np.ones(F, dtype=np.int64),
    }
    for i, axis in enumerate("ned"):
        truth[f"target_{axis}_m"], truth[f"cam_{axis}_m"] = target[:, i], cam[:, i]
    for c in "wxyz":
        truth[f"q_ned_from_cam_{c}"] = np.full(F, 1.0 if c == "w" else 0.0)
    errs = [2.0, 4.0, 0.0, 9.0]  # metres along east; frame 2 has no position, frame 3 arrives with a wrong time
    tracks = []
    for k in range(F):
        msg = {"time_boot_us": int(t_us[k]) + (7 if k == 3 else 0), "observable": k == 0, "lat_deg": None}
        if k != 2:
            lat, lon, alt = geodetic_from_ned(target[k] + [0.0, errs[k], 0.0], origin)
            msg.update(lat_deg=float(lat), lon_deg=float(lon), alt_m=float(alt))
        tracks.append(msg)
    daemon = track_arrays(tracks, t_us, origin)
    assert daemon["tracked"].tolist() == [True, True, True, False]
    assert daemon["observable"].tolist() == [True, False, False, False]
    np.testing.assert_allclose(daemon["p_ned_m"][1], target[1] + [0.0, 4.0, 0.0], atol=ATOL_M)
    assert np.isnan(daemon["p_ned_m"][2]).all() and np.isnan(daemon["p_ned_m"][3]).all()
    bases = [{"p_ned_m": target + [[0.0, 0.0, e]] * F, "observable": np.zeros(F, bool)} for e in (1.0, 10.0, 2.0)]
    c = compare("all", truth, daemon, bases, np.ones(F, dtype=bool))
    assert c.frames == 2
    assert c.daemon_err == pytest.approx((2.0 + 4.0) / 2 / 100.0, abs=1e-8)
    assert c.baseline_err == pytest.approx(0.02, abs=1e-12)  # median of 1, 10 and 2 m over 100 m
    assert c.ratio == pytest.approx(1.5, abs=1e-6)
    obs = compare("observable", truth, daemon, bases, daemon["observable"])
    assert obs.frames == 1 and _choose(obs, c) is c
