"""Helpers of ``tests/test_integration.py`` (the simulator and the daemon as two processes, end to end).

Two real processes on 127.0.0.1, wired as ``python -m groundsim demo`` wires them
(:mod:`groundsim.evaluation.demo`: :func:`~groundsim.evaluation.demo.plan_demo` writes the daemon's configuration with the
scenario's camera, pod mount, gimbal and origin, loopback endpoints and
``output.unobservable_positions`` on)::

    python -m onboard --config OUT/onboard.yaml      MAVLink udpin:127.0.0.1:M, zenoh listen tcp/127.0.0.1:Z
    python -m groundsim run --rate R ...             MAVLink udpout:127.0.0.1:M, zenoh connect tcp/127.0.0.1:Z
    this process                                     zenoh connect tcp/127.0.0.1:Z: irtrack/<v>/track, /status

The daemon starts first; the simulator once the daemon's first status message arrived (no frame is
sent before anyone listens).  Both are stopped with SIGTERM, then SIGKILL, whatever happens.

The yardstick (:func:`perfect_centroid_baseline`): the daemon's own sliding-window estimator
(:func:`onboard.pipeline.frame_pipeline.make_estimator` on the very configuration file the daemon read, so the same
window and noise model) fed from the simulator's truth CSV -- the true target pixel plus white noise,
the true camera centre and attitude, each frame's capture time -- exactly as the pipeline feeds it
(``add`` on frames where the target is in the image, ``predict`` on the others).

Scoring (:func:`score_against_truth`): range-normalised error ``mean ||p_hat - p|| / ||p - c||``
(:func:`onboard.estimation.metrics.evaluate`) of the daemon's track and of the baseline, on the same
frames.
"""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# the demo's own child environment, stop, log tail, end-of-run drain and zenoh teardown
from groundsim.evaluation.demo import child_env, close_zenoh, drain_tracks, log_tail, stop_process

__all__ = [
    "PairRun",
    "PairRunError",
    "loopback_daemon_command",
    "run_pair",
    "sim_command_at_rate",
    "truth_arrays",
    "track_arrays",
    "perfect_centroid_baseline",
    "range_normalised_error",
    "Comparison",
    "compare",
]

REPO = Path(__file__).resolve().parents[1]
ONBOARD_CONFIG = REPO / "config" / "onboard.yaml"

DAEMON_READY_TIMEOUT_S = 30.0  # imports on a busy 2-core machine
SIM_SETUP_ALLOWANCE_S = 20.0  # wall seconds beyond duration / rate before the simulator counts as stuck


class PairRunError(AssertionError):
    """A child failed to start, died or hung; the message carries the tail of its log."""


class _DaemonExitedEarly(PairRunError):
    """The daemon exited before its first status (a port taken between picking and binding it?)."""


@dataclass
class PairRun:
    """What one two-process run produced."""

    scenario: object  # groundsim.world.scenario.Scenario
    config_path: Path  # the daemon's configuration file
    truth: dict  # groundsim.world.truth.read_truth_csv of the simulator's truth file
    tracks: list  # irtrack.track/1 dicts in arrival order (schema-validated)
    status: dict | None  # the daemon's last irtrack.status/1
    bad_messages: int
    exit_codes: dict = field(default_factory=dict)
    wall_s: float = 0.0
    sim_wall_s: float = 0.0
    logs: dict = field(default_factory=dict)


def _start(cmd: list[str], log_path: Path, env: dict) -> subprocess.Popen:
    with open(log_path, "wb") as f:  # the child keeps its own descriptor
        return subprocess.Popen(cmd, cwd=REPO, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)


def _raise_if_exited(daemon: subprocess.Popen, log_path: Path, when: str, error: type[PairRunError]) -> None:
    """Raise ``error`` with the tail of the daemon's log if it has exited (``when``: before what or during what)."""
    if daemon.poll() is not None:
        raise error(f"the onboard daemon exited with code {daemon.returncode} {when}:\n{log_tail(log_path)}")


def loopback_daemon_command(zenoh_listen_port: int, health_file) -> list[str]:
    """``python -m onboard`` on 127.0.0.1 from the command line alone: MAVLink udpin on a free port, zenoh listening
    on ``zenoh_listen_port``, ``output.health_file`` set (``"null"``: none)."""
    from groundsim.io.ports import free_udp_port

    return [
        sys.executable,
        "-m",
        "onboard",
        "--mavlink",
        f"udpin:127.0.0.1:{free_udp_port()}",
        "--zenoh-listen",
        f"tcp/127.0.0.1:{zenoh_listen_port}",
        "--set",
        f"output.health_file={health_file}",
    ]


def sim_command_at_rate(plan, rate: str) -> list[str]:
    """The demo's simulator command with ``--rate`` replaced (the demo always runs in real time)."""
    from groundsim.evaluation.demo import sim_command

    cmd = sim_command(plan)
    cmd[cmd.index("--rate") + 1] = str(rate)
    return cmd


def lengthened_scenario(name: str, duration_s: float, out_dir) -> Path:
    """A copy of the shipped scenario ``name`` in ``out_dir/scenarios/`` flown for ``duration_s``; same file
    name, so the run's seeds (and everything else in it) are the shipped scenario's."""
    import re

    from groundsim.world.scenario import reference_scenario_paths

    src = reference_scenario_paths()[name]
    text, n = re.subn(r"(?m)^duration_s:.*$", f"duration_s: {duration_s!r}", src.read_text())
    if n != 1:
        raise ValueError(f"{src}: expected one top-level duration_s line, found {n}")
    dst = Path(out_dir) / "scenarios" / src.name
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text(text)
    return dst


def run_pair(
    scenario: str,
    out_dir,
    *,
    rate: str = "1.0",
    seed: int = 0,
    nav_noise: str | None = None,
    fly_when: threading.Event | None = None,
    flown: threading.Event | None = None,
) -> PairRun:
    """Run the scenario's whole duration through both processes; raise PairRunError on a child failure.

    ``fly_when``: once its daemon is ready, the run waits for this event before it starts the simulator (the daemon
    is watched meanwhile: its exit is a failure), so that the daemon's start overlaps other work.  ``flown``: set as
    soon as the simulator has exited (before the drain, the stop and the truth read), or the run ended otherwise.

    A daemon that exits before it is ready is given one more try on fresh ports (the ports are free when
    picked, not necessarily when bound, on a machine shared with other test runs)."""
    try:
        try:
            return _run_pair_once(scenario, Path(out_dir) / "try1", rate, seed, nav_noise, fly_when, flown)
        except _DaemonExitedEarly:
            return _run_pair_once(scenario, Path(out_dir) / "try2", rate, seed, nav_noise, fly_when, flown)
    finally:
        if flown is not None:
            flown.set()


def _run_pair_once(
    scenario: str,
    out_dir,
    rate: str,
    seed: int,
    nav_noise: str | None = None,
    fly_when: threading.Event | None = None,
    flown: threading.Event | None = None,
) -> PairRun:
    from groundsim.evaluation.demo import TrackStore, daemon_command, plan_demo
    from groundsim.world.scenario import load_scenario, resolve_scenario_path
    from groundsim.world.truth import read_truth_csv
    from onboard.io.zenoh_session import ZenohConfig, open_session

    out = Path(out_dir)
    duration_s = load_scenario(resolve_scenario_path(scenario)).duration_s
    plan = plan_demo(scenario, duration_s, seed, out, str(ONBOARD_CONFIG), nav_noise=nav_noise)
    factor = 1.0 if rate == "realtime" else float(rate)
    env = child_env()
    logs = {"daemon": out / "onboard.log", "sim": out / "sim.log"}
    store = TrackStore()
    daemon = sim = session = None
    subs = []
    run = PairRun(plan.scenario, plan.onboard_config_path, {}, [], None, 0, logs={k: str(v) for k, v in logs.items()})
    wall0 = time.monotonic()
    try:
        daemon = _start(daemon_command(plan), logs["daemon"], env)
        session = open_session(ZenohConfig(connect=(plan.zenoh_endpoint,)))
        subs += store.subscribe(session, plan.vehicle)
        t_ready = time.monotonic() + DAEMON_READY_TIMEOUT_S
        while not store.ready.wait(0.1):
            _raise_if_exited(daemon, logs["daemon"], "before it was ready", _DaemonExitedEarly)
            if time.monotonic() > t_ready:
                raise PairRunError(
                    f"the onboard daemon published no status within {DAEMON_READY_TIMEOUT_S:g} s:\n"
                    f"{log_tail(logs['daemon'])}"
                )
        while fly_when is not None and not fly_when.wait(0.1):
            _raise_if_exited(daemon, logs["daemon"], "while it waited for its flight", PairRunError)
        sim0 = time.monotonic()
        sim = _start(sim_command_at_rate(plan, rate), logs["sim"], env)
        deadline = sim0 + plan.duration_s / factor + SIM_SETUP_ALLOWANCE_S
        while sim.poll() is None:
            _raise_if_exited(daemon, logs["daemon"], "during the run", PairRunError)
            if time.monotonic() > deadline:
                raise PairRunError(
                    f"the simulator still runs {SIM_SETUP_ALLOWANCE_S:g} s past its duration:\n{log_tail(logs['sim'])}"
                )
            time.sleep(0.1)
        run.sim_wall_s = time.monotonic() - sim0
        if flown is not None:
            flown.set()
        if sim.returncode != 0:
            raise PairRunError(f"the simulator exited with code {sim.returncode}:\n{log_tail(logs['sim'])}")
        drain_tracks(store)  # let the daemon finish the last frames
        time.sleep(0.1)
    finally:
        close_zenoh(subs, session)
        run.exit_codes = {"sim": stop_process(sim, "simulator"), "daemon": stop_process(daemon, "onboard daemon")}
        run.wall_s = time.monotonic() - wall0
    run.tracks, run.status = store.snapshot()
    run.bad_messages = store.bad
    run.truth = read_truth_csv(plan.truth_path)
    return run


# --------------------------------------------------------------------------- truth, baseline, scoring


def truth_arrays(truth: dict) -> dict:
    """Per-frame arrays of a truth CSV: time_boot_us (F,), target / camera NED (F, 3), q_ned_from_cam (F, 4),
    truth pixel (F, 2), visible (F,)."""

    def stack(*names):
        return np.column_stack([np.asarray(truth[n], dtype=float) for n in names])

    from onboard.core.frames import quat_from_rotmat, rotmat_from_quat, rotmat_from_rotvec

    cam = stack("cam_n_m", "cam_e_m", "cam_d_m")
    q = stack("q_ned_from_cam_w", "q_ned_from_cam_x", "q_ned_from_cam_y", "q_ned_from_cam_z")
    out = dict(
        time_boot_us=np.asarray(truth["time_boot_us"], dtype=np.int64),
        target_p_ned_m=stack("target_n_m", "target_e_m", "target_d_m"),
        cam_p_ned_m=cam,
        q_ned_from_cam=q,
        uv_px=stack("target_u_px", "target_v_px"),
        visible=np.asarray(truth["target_visible"]) > 0,
    )
    # what the vehicle reported (the simulator's navigation errors, recorded in the truth CSV): the
    # attitude error is a NED rotation vector on the left, the position error the observer's (the lever
    # arm's rotation by the attitude error, < 0.1 mm, is left out)
    if "nav_p_err_n_m" in truth:
        phi = stack("nav_att_err_n_rad", "nav_att_err_e_rad", "nav_att_err_d_rad")
        out["reported_cam_p_ned_m"] = cam + stack("nav_p_err_n_m", "nav_p_err_e_m", "nav_p_err_d_m")
        out["reported_q_ned_from_cam"] = np.array(
            [quat_from_rotmat(rotmat_from_rotvec(f) @ rotmat_from_quat(qq)) for f, qq in zip(phi, q)]
        )
    else:
        out["reported_cam_p_ned_m"], out["reported_q_ned_from_cam"] = cam, q
    return out


def track_arrays(tracks: list, time_boot_us: np.ndarray, origin) -> dict:
    """The daemon's tracks on the truth frames (matched on time_boot_us): position in the scenario's NED
    frame from the WGS84 fields (independent of the daemon's own origin), NaN without one; observable;
    ``sqrt_trace_cov_m`` = sqrt(trace(cov)) from ``sigma_ned_m`` (NaN without)."""
    from onboard.core.frames import ned_from_geodetic

    idx = {int(t): i for i, t in enumerate(time_boot_us)}
    F = len(time_boot_us)
    p = np.full((F, 3), np.nan)
    observable = np.zeros(F, dtype=bool)
    tracked = np.zeros(F, dtype=bool)
    sqrt_trace = np.full(F, np.nan)
    for tr in tracks:
        i = idx.get(int(tr["time_boot_us"]))
        if i is None:
            continue
        tracked[i] = True
        if tr.get("lat_deg") is None:
            continue
        p[i] = np.asarray(ned_from_geodetic(tr["lat_deg"], tr["lon_deg"], tr["alt_m"], origin), dtype=float).reshape(3)
        observable[i] = bool(tr.get("observable"))
        if tr.get("sigma_ned_m") is not None:
            sqrt_trace[i] = float(np.linalg.norm(np.asarray(tr["sigma_ned_m"], dtype=float)))
    return dict(p_ned_m=p, observable=observable, tracked=tracked, sqrt_trace_cov_m=sqrt_trace)


def perfect_centroid_baseline(config_path, truth: dict, pixel_sigma_px: float, rng: np.random.Generator) -> dict:
    """The daemon's estimator (same configuration file) on the truth rows: true pixel + N(0, sigma^2) per
    axis (drawn from ``rng``), the camera pose the vehicle reported (truth plus the simulator's recorded
    navigation errors: the daemon saw no better), capture time ``time_boot_us``; ``add`` where the target
    is in the image, else ``predict`` -- as :class:`onboard.pipeline.frame_pipeline.FramePipeline` feeds it.

    Returns ``p_ned_m`` (F, 3, NaN = no estimate) and ``observable`` (F,)."""
    from onboard.app.config import load_config
    from onboard.core.errors import IrtrackError
    from onboard.pipeline.frame_pipeline import make_estimator

    cfg = load_config(config_path, environ={})
    K = cfg.camera.pinhole()
    est = make_estimator(cfg)
    a = truth_arrays(truth)
    F = a["time_boot_us"].size
    noise = rng.standard_normal((F, 2)) * pixel_sigma_px
    p = np.full((F, 3), np.nan)
    observable = np.zeros(F, dtype=bool)
    has_data = False
    for k in range(F):
        t_s = int(a["time_boot_us"][k]) / 1e6
        r = None
        try:
            if a["visible"][k]:
                r = est.add(
                    t_s, a["uv_px"][k] + noise[k], K, a["reported_cam_p_ned_m"][k], a["reported_q_ned_from_cam"][k]
                )
                has_data = True
            elif has_data:
                r = est.predict(t_s, a["reported_cam_p_ned_m"][k])
        except IrtrackError:
            r = None
        if r is not None and np.all(np.isfinite(r.p_ned_m)):
            p[k] = r.p_ned_m
            observable[k] = bool(r.observable)
    return dict(p_ned_m=p, observable=observable)


def range_normalised_error(truth_p, est_p, cam_p, sel) -> float:
    """``mean ||p_hat - p|| / ||p - c||`` over the selected frames (NaN when none)."""
    from onboard.estimation.metrics import evaluate

    idx = np.flatnonzero(sel)
    if idx.size == 0:
        return math.nan
    return float(evaluate(truth_p[idx], est_p[idx], cam_p[idx]).range_normalised_error)


@dataclass(frozen=True)
class Comparison:
    """The daemon against the perfect-centroid baseline on one frame selection.

    ``daemon_err``: range-normalised error of the daemon's track (fraction); ``baseline_errs``: the
    baseline's, one per noise draw, on the same frames; ``baseline_err``: their median (the yardstick:
    one unlucky draw can pick another motion model and be 10x off, either way)."""

    selection: str
    frames: int
    daemon_err: float
    baseline_errs: tuple

    @property
    def baseline_err(self) -> float:
        return float(np.median(self.baseline_errs)) if self.baseline_errs else math.nan

    @property
    def ratio(self) -> float:
        return self.daemon_err / self.baseline_err if self.baseline_err > 0 else math.inf

    def line(self) -> str:
        draws = " ".join(f"{100 * e:.3f}" for e in self.baseline_errs)
        return (
            f"{self.selection:>10s}: {self.frames:3d} frames, daemon {100 * self.daemon_err:7.3f} %, baseline "
            f"{100 * self.baseline_err:7.3f} % (draws {draws}), ratio {self.ratio:.2f}"
        )


def compare(selection: str, truth: dict, daemon: dict, baselines: list, sel) -> Comparison:
    """Daemon vs every baseline draw on the frames of ``sel`` where all of them have a position."""
    a = truth_arrays(truth)
    sel = np.asarray(sel, dtype=bool) & np.all(np.isfinite(daemon["p_ned_m"]), axis=1)
    for b in baselines:
        sel = sel & np.all(np.isfinite(b["p_ned_m"]), axis=1)
    tp, cp = a["target_p_ned_m"], a["cam_p_ned_m"]
    return Comparison(
        selection,
        int(sel.sum()),
        range_normalised_error(tp, daemon["p_ned_m"], cp, sel),
        tuple(range_normalised_error(tp, b["p_ned_m"], cp, sel) for b in baselines),
    )
