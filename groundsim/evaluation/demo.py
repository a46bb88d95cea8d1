"""``python -m groundsim demo`` (``make demo``): the simulator and the onboard daemon as two processes
on loopback, a live status line per second, then the error table against the truth.

Wiring (free ports on 127.0.0.1, picked at start)::

    python -m onboard --config OUT/onboard.yaml          MAVLink udpin:127.0.0.1:M, zenoh listen tcp/127.0.0.1:Z
    python -m groundsim run --rate realtime ...          MAVLink udpout:127.0.0.1:M, zenoh connect tcp/127.0.0.1:Z,
                                                         truth CSV OUT/truth.csv
    this process                                         zenoh connect tcp/127.0.0.1:Z: irtrack/<v>/track, /status

The daemon starts first; the simulator is started once the daemon's first status message arrives
(so no frame is sent before anyone listens).  ``OUT/onboard.yaml`` is the daemon's configuration
(``--onboard-config``, default the shipped ``config/onboard.yaml``, noise model included) with the
scenario's camera, pod mount and origin, the loopback endpoints, a liveness file inside OUT and
``output.unobservable_positions`` on, as by default (so the live line can show the range before it is
observable; the table scores both).  A scenario shorter than ``--duration`` is extended as ``groundsim
run`` extends it (its motion models simply continue, :func:`groundsim.world.sim.extend_scenario`); a duration
it cannot fly is refused before anything starts.

Each second one line: simulated frames; frames the daemon processed and dropped and its median
processing time per frame (its status message's ``frames`` and ``processing_ms``); the track state;
the estimated and true range; the live error of the newest 3-D estimate against the truth row of
the same frame (matched on ``time_boot_us``); the CPU share of the two children, each with its own
child processes (``/proc``: CPU seconds / wall seconds, 100 % = one core).

At the end (the simulator finished, or Ctrl-C / SIGTERM): the daemon gets SIGTERM (SIGKILL after
``KILL_AFTER_S``), the table is printed and OUT gets ``report.json``, ``report.md``, ``tracks.jsonl``,
``truth.tum`` / ``estimate.tum``, two plots and the children's logs.  Exit 0 after a clean run; 130 after
Ctrl-C or SIGTERM (one line saying what was kept; the evaluation is not run); 1 when a child failed to start or
died (its log tail is printed).
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from groundsim.evaluation.demo_plan import (
    DemoPlan,
    daemon_command,
    plan_demo,
    sim_command,
)
from groundsim.evaluation.eval import EvalInterrupted, keep_interrupted
from groundsim.io.stop_signals import install_stop_signals, print_interrupted
from groundsim.world.nav_errors import InjectedErrors
from onboard.core.blas import single_thread_blas_env
from onboard.core.errors import InputError, IrtrackError

__all__ = [
    "KILL_AFTER_S",
    "DemoPlan",
    "plan_demo",
    "daemon_command",
    "sim_command",
    "TrackStore",
    "TruthTail",
    "status_line",
    "score_demo",
    "format_demo_table",
    "aligned_arrays",
    "child_env",
    "close_zenoh",
    "drain_tracks",
    "log_tail",
    "stop_process",
    "run_demo",
    "cmd_demo",
]

log = logging.getLogger(__name__)

KILL_AFTER_S = 3.0  # SIGTERM, then SIGKILL after this
DAEMON_READY_TIMEOUT_S = 45.0  # first status from the daemon (imports take tens of seconds on a loaded machine)
SIM_SETUP_ALLOWANCE_S = 30.0  # wall seconds beyond --duration before the simulator is stopped
DRAIN_QUIET_S = 0.5  # after the simulator ends: wait until no track arrived for this long
DRAIN_MAX_S = 3.0
STATUS_PERIOD_S = 1.0
LOG_TAIL_LINES = 15
EXIT_OK, EXIT_FAILED = 0, 1


# --------------------------------------------------------------------------- collectors


class TrackStore:
    """Track and status messages from zenoh callbacks (any thread); parsed tracks kept in arrival order."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.tracks: list[dict] = []
        self.status: dict | None = None
        self.statuses = 0
        self.bad = 0
        self.last_track_mono = None
        self.first_track_mono: float | None = None  # the daemon's first track: frames and telemetry flow
        self.ready = threading.Event()
        #: warning code -> monotonic time of the first status that listed it
        self.warnings_first_mono: dict[str, float] = {}

    def on_track(self, payload: bytes) -> None:
        from onboard.core.track import track_from_json

        try:
            obj = json.loads(bytes(payload))
            track_from_json(obj)  # validates the schema
        except (InputError, ValueError, UnicodeDecodeError):
            with self._lock:
                self.bad += 1
            return
        with self._lock:
            self.tracks.append(obj)
            self.last_track_mono = time.monotonic()
            if self.first_track_mono is None:
                self.first_track_mono = self.last_track_mono

    def on_status(self, payload: bytes) -> None:
        try:
            obj = json.loads(bytes(payload))
        except (ValueError, UnicodeDecodeError):
            with self._lock:
                self.bad += 1
            return
        now = time.monotonic()
        with self._lock:
            self.status = obj
            self.statuses += 1
            for w in obj.get("warnings") or () if isinstance(obj, dict) else ():
                code = w.get("code") if isinstance(w, dict) else None
                if isinstance(code, str):
                    self.warnings_first_mono.setdefault(code, now)
        self.ready.set()

    def subscribe(self, session, vehicle: str) -> list:
        """Declare on the zenoh ``session`` the subscribers of ``vehicle``'s track and status keys that
        feed this store; returns them (for :func:`close_zenoh`)."""
        from onboard.io.zenoh_session import status_key, track_key

        return [
            session.declare_subscriber(track_key(vehicle), lambda s: self.on_track(s.payload.to_bytes())),
            session.declare_subscriber(status_key(vehicle), lambda s: self.on_status(s.payload.to_bytes())),
        ]

    def snapshot(self) -> tuple[list[dict], dict | None]:
        with self._lock:
            return list(self.tracks), self.status


class TruthTail:
    """Reads the simulator's truth CSV as it grows (whole lines only) into ``rows`` by time_boot_us."""

    def __init__(self, path) -> None:
        self.path = Path(path)
        self._pos = 0
        self._header: list[str] | None = None
        self._partial = ""
        self.rows: dict[int, dict] = {}
        self.order: list[int] = []

    def poll(self) -> int:
        """Read what was appended; returns the number of new rows."""
        try:
            with open(self.path, encoding="ascii") as f:
                f.seek(self._pos)
                chunk = f.read()
                self._pos = f.tell()
        except OSError:
            return 0
        text = self._partial + chunk
        lines = text.split("\n")
        self._partial = lines.pop()  # an unfinished last line waits for the next poll
        n = 0
        for line in lines:
            if not line:
                continue
            parts = line.split(",")
            if self._header is None:
                self._header = parts
                continue
            if len(parts) != len(self._header):
                continue
            try:
                row = {k: float(v) for k, v in zip(self._header, parts)}
            except ValueError:
                continue
            t = int(row["time_boot_us"])
            if t not in self.rows:
                self.order.append(t)
            self.rows[t] = row
            n += 1
        return n


# --------------------------------------------------------------------------- pure formatting and scoring


def _truth_p(row: dict):
    return (row["target_n_m"], row["target_e_m"], row["target_d_m"])


def _track_p_ned(track: dict, origin):
    """A track message's position in the scenario's NED frame (from lat/lon/alt: independent of the
    daemon's own origin); None without a position."""
    from onboard.core.frames import ned_from_geodetic

    if track.get("lat_deg") is None:
        return None
    import numpy as np

    return np.asarray(
        ned_from_geodetic(track["lat_deg"], track["lon_deg"], track["alt_m"], origin), dtype=float
    ).reshape(3)


def status_line(
    elapsed_s: float,
    sim_frames: int,
    total_frames: int,
    status: dict | None,
    track: dict | None,
    est_range_m: float | None,
    truth_range_m: float | None,
    err_m: float | None,
    cpu_sim: float | None,
    cpu_daemon: float | None,
) -> str:
    """One live line (pure)."""

    def f(x, fmt):
        return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)

    fr = (status or {}).get("frames") or {}
    lat = (status or {}).get("processing_ms") or {}
    parts = [
        f"[{elapsed_s:5.1f} s]",
        f"sim {sim_frames}/{total_frames} frames",
        f"daemon {fr.get('processed', 0)} processed, {fr.get('dropped', 0)} dropped, "
        f"p50 {f(lat.get('p50'), '.1f')} ms/frame",
    ]
    if track is None:
        parts.append("track -")
    else:
        tid = track.get("track_id")
        parts.append(f"{track.get('state', '?')}{'' if tid is None else f' #{tid}'}")
        if track.get("lat_deg") is not None:
            obs = "observable" if track.get("observable") else "unobservable"
            parts.append(f"range {f(est_range_m, '.1f')} m (truth {f(truth_range_m, '.1f')} m)")
            rel = None if err_m is None or not truth_range_m else 100.0 * err_m / truth_range_m
            parts.append(f"err {f(err_m, '.2f')} m ({f(rel, '.2f')} % of range) {obs}")
        else:
            parts.append(f"no 3-D yet ({track.get('window_frames', 0)} frames in the window)")
    parts.append(
        f"CPU sim {f(None if cpu_sim is None else 100 * cpu_sim, '.0f')} %, daemon "
        f"{f(None if cpu_daemon is None else 100 * cpu_daemon, '.0f')} %"
    )
    return " | ".join(parts)


@dataclass
class DemoOutcome:
    """What the demo measured (also written to report.json)."""

    scenario: str
    seed: int
    duration_s: float
    wall_s: float
    sim_frames: int
    tracks: int
    stopped_early: bool
    sim_exit: int | None
    daemon_exit: int | None
    cpu_share: dict = field(default_factory=dict)
    last_status: dict | None = None
    #: warning code -> seconds from the daemon's first track (frames and telemetry flowing) to the first status
    #: that listed it (negative: before it)
    warnings_after_s: dict = field(default_factory=dict)
    scores: dict = field(default_factory=dict)
    files: dict = field(default_factory=dict)
    error: str | None = None


def aligned_arrays(truth: TruthTail, tracks: list[dict], origin):
    """Arrays over the truth frames: truth, camera, observer, range; track position/cov/observable (NaN = none)."""
    import numpy as np

    order = truth.order
    idx = {t: i for i, t in enumerate(order)}
    F = len(order)
    rows = [truth.rows[t] for t in order]
    t_us = np.array(order, dtype=np.int64)
    tp = np.array([_truth_p(r) for r in rows], dtype=float).reshape(F, 3)
    cp = np.array([(r["cam_n_m"], r["cam_e_m"], r["cam_d_m"]) for r in rows], dtype=float).reshape(F, 3)
    op = np.array([(r["observer_n_m"], r["observer_e_m"], r["observer_d_m"]) for r in rows], dtype=float).reshape(F, 3)
    rng = np.array([r["range_m"] for r in rows], dtype=float)
    uv = np.array([(r["target_u_px"], r["target_v_px"]) for r in rows], dtype=float).reshape(F, 2)
    vis = np.array([r["target_visible"] > 0.5 for r in rows], dtype=bool)
    ep, eP = np.full((F, 3), np.nan), np.full((F, 3, 3), np.nan)
    obs = np.zeros(F, dtype=bool)
    tracked = np.zeros(F, dtype=bool)
    meas = np.zeros(F, dtype=bool)
    state = np.full(F, "", dtype="<U9")
    tuv = np.full((F, 2), np.nan)
    bbox = np.full((F, 4), np.nan)
    for tr in tracks:
        i = idx.get(int(tr["time_boot_us"]))
        if i is None:
            continue
        tracked[i] = True
        state[i] = tr.get("state", "")
        meas[i] = bool(tr.get("measurement_valid"))
        if tr.get("u_px") is not None:
            tuv[i] = (tr["u_px"], tr["v_px"])
        if tr.get("bbox") is not None:
            bbox[i] = tr["bbox"]
        p = _track_p_ned(tr, origin)
        if p is None:
            continue
        ep[i] = p
        cov = tr.get("cov_ned_m2")
        if cov is not None:
            eP[i] = np.asarray([[np.nan if x is None else x for x in row] for row in cov], dtype=float)
        obs[i] = bool(tr.get("observable"))
    return dict(
        t_us=t_us,
        truth_p=tp,
        cam_p=cp,
        obs_p=op,
        range_m=rng,
        truth_uv=uv,
        visible=vis,
        est_p=ep,
        est_P=eP,
        observable=obs,
        tracked=tracked,
        measurement_valid=meas,
        state=state,
        uv=tuv,
        bbox=bbox,
    )


def score_demo(a: dict) -> dict:
    """The demo's figures from :func:`aligned_arrays` arrays (definitions as ``groundsim.evaluation.eval``)."""
    import numpy as np

    from onboard.estimation.metrics import score_frames

    F = int(a["t_us"].size)
    has = np.all(np.isfinite(a["est_p"]), axis=1)
    obs = has & a["observable"]
    cov = a["est_P"]
    cov_ok = np.all(np.isfinite(cov.reshape(F, 9)), axis=1) if F else np.zeros(0, bool)
    out = {
        "frames": F,
        "frames_with_track_message": int(a["tracked"].sum()),
        "frames_with_estimate": int(has.sum()),
        "frames_observable": int(obs.sum()),
        "continuity": float(obs.sum() / F) if F else 0.0,
        "continuity_2d": float((a["measurement_valid"] & a["visible"]).sum() / max(int(a["visible"].sum()), 1)),
        "observable": score_frames(a["truth_p"], a["est_p"], a["cam_p"], cov if cov_ok[obs].all() else None, obs),
        "all": score_frames(a["truth_p"], a["est_p"], a["cam_p"], cov if cov_ok[has].all() else None, has),
    }
    return out


def format_demo_table(scores: dict, outcome: DemoOutcome) -> str:
    """The end-of-demo error table (markdown)."""

    def f(x, fmt=".2f", unit=""):
        return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:{fmt}}{unit}"

    st = outcome.last_status or {}
    lat = st.get("processing_ms") or {}
    lines = [
        f"{outcome.scenario} seed {outcome.seed}: {scores['frames']} frames simulated, {scores['frames_with_track_message']} "
        f"tracked by the daemon, {scores['frames_with_estimate']} with a 3-D estimate, {scores['frames_observable']} observable",
        "",
        "| online track vs truth | frames | paper metric | err / range | RMSE m | mean error m | max error m | NEES |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for label, key in (
        ("observable frames (published with observable: true)", "observable"),
        ("all frames with an estimate", "all"),
    ):
        m = scores.get(key)
        if m is None:
            lines.append(f"| {label} | 0 | - | - | - | - | - | - |")
            continue
        lines.append(
            f"| {label} | {m['frames']} | {f(m['err_paper_pct'], '.2f', ' %')} | {f(m['err_range_pct'], '.2f', ' %')} | "
            f"{f(m['rmse_m'])} | {f(m['mean_error_m'])} | {f(m['max_error_m'])} | {f(m.get('mean_nees'))} |"
        )
    cpu = outcome.cpu_share
    every = scores.get("all") or {}
    beyond = every.get("outside_3sigma_trace_fraction")
    lines += [
        "",
        f"published 3-D positions beyond 3 sigma (||e|| > 3 sqrt(trace cov)): {f(None if beyond is None else 100 * beyond, '.1f', ' %')}"
        f" of {scores['frames_with_estimate']}; warnings (s after the daemon's first track): "
        + (
            ", ".join(f"{c} {t:.1f} s" for c, t in sorted(outcome.warnings_after_s.items(), key=lambda x: x[1]))
            or "none"
        ),
    ]
    lines += [
        "",
        f"continuity {f(100 * scores['continuity'], '.0f', ' %')} (observable / simulated frames), 2-D "
        f"{f(100 * scores['continuity_2d'], '.0f', ' %')}; daemon processing p50 {f(lat.get('p50'), '.1f')} ms, "
        f"p99 {f(lat.get('p99'), '.1f')} ms; CPU share sim {f(_pct(cpu.get('sim')), '.0f', ' %')}, daemon "
        f"{f(_pct(cpu.get('daemon')), '.0f', ' %')}, demo {f(_pct(cpu.get('demo')), '.0f', ' %')} (100 % = one core)",
    ]
    return "\n".join(lines)


def _pct(x):
    return None if x is None else 100.0 * x


# --------------------------------------------------------------------------- processes


def _start(cmd: list[str], log_path: Path, env: dict) -> subprocess.Popen:
    """A child of this demo, started from the main thread, which ends with it even if the demo is killed outright
    (:mod:`onboard.app.parent_watch`: a SIGKILLed demo left its daemon and simulator holding their ports)."""
    from onboard.app.parent_watch import PARENT_PID_ENV

    f = open(log_path, "wb")
    try:
        env = {**env, PARENT_PID_ENV: str(os.getpid())}
        return subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
    finally:
        f.close()  # the child has its own descriptor


def drain_tracks(store: TrackStore, stop: threading.Event | None = None) -> None:
    """After the simulator ends, let the daemon finish the last frames: wait until no track arrived for
    DRAIN_QUIET_S, at most DRAIN_MAX_S (or until ``stop`` is set)."""
    t_end = time.monotonic() + DRAIN_MAX_S
    while time.monotonic() < t_end and not (stop is not None and stop.is_set()):
        last = store.last_track_mono
        if last is not None and time.monotonic() - last > DRAIN_QUIET_S:
            break
        time.sleep(0.05)


def close_zenoh(subscribers, session) -> None:
    """Undeclare the subscribers and close the session, ignoring errors (shutdown path)."""
    for s in subscribers:
        try:
            s.undeclare()
        except Exception:  # noqa: BLE001 - closing
            pass
    if session is not None:
        try:
            session.close()
        except Exception:  # noqa: BLE001 - closing
            pass


def stop_process(proc: subprocess.Popen | None, name: str = "child process") -> int | None:
    """SIGTERM, then SIGKILL after KILL_AFTER_S; returns the exit code (None if never started)."""
    if proc is None:
        return None
    if proc.poll() is None:
        try:
            proc.send_signal(signal.SIGTERM)
        except ProcessLookupError:
            pass
        try:
            proc.wait(KILL_AFTER_S)
        except subprocess.TimeoutExpired:
            log.warning("%s did not stop within %.0f s of SIGTERM: killing it", name, KILL_AFTER_S)
            proc.kill()
            proc.wait()
    return proc.returncode


def log_tail(path: Path, n: int = LOG_TAIL_LINES) -> str:
    """The last ``n`` lines of a child's log, indented, for an error message ("(no log)" if unreadable)."""
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return "(no log)"
    return "\n".join("    " + line for line in lines[-n:])


def child_env() -> dict:
    """The environment for a child process of the demo or the tests: this one's, one BLAS/OpenMP thread
    unless set, unbuffered Python output (the logs show what happened up to a crash)."""
    env = single_thread_blas_env(dict(os.environ))
    env["PYTHONUNBUFFERED"] = "1"
    return env


def run_demo(plan: DemoPlan, stop: threading.Event | None = None, out=None) -> DemoOutcome:
    """Start both children, print a line per second, stop, score, write the files (module docstring)."""
    from groundsim.evaluation.proc_cpu import ProcCpu
    from onboard.io.zenoh_session import ZenohConfig, open_session

    stop = stop if stop is not None else threading.Event()
    out = out if out is not None else (lambda s: print(s, flush=True))
    store = TrackStore()
    truth = TruthTail(plan.truth_path)
    env = child_env()
    daemon = sim = session = None
    subs = []
    cpu_daemon = cpu_sim = None
    wall0 = time.monotonic()
    cpu_demo0 = time.process_time()
    outcome = DemoOutcome(plan.scenario.name, plan.seed, plan.duration_s, 0.0, 0, 0, False, None, None)
    total_frames = (
        plan.scenario.frame_count
        if plan.duration_s >= plan.scenario.duration_s - 1e-9
        else max(1, math.ceil(plan.duration_s * plan.scenario.frame_rate_hz - 1e-9))
    )
    try:
        if plan.truth_path.exists():
            plan.truth_path.unlink()
        out(
            f"demo: scenario {plan.scenario.name} seed {plan.seed}, {plan.duration_s:g} s; onboard daemon "
            f"(MAVLink udp 127.0.0.1:{plan.mavlink_port}, zenoh {plan.zenoh_endpoint}); logs in {plan.out_dir}/"
        )
        daemon = _start(daemon_command(plan), plan.out_dir / "onboard.log", env)
        cpu_daemon = ProcCpu(daemon.pid)
        session = open_session(ZenohConfig(connect=(plan.zenoh_endpoint,)))
        subs += store.subscribe(session, plan.vehicle)
        t_ready = time.monotonic() + DAEMON_READY_TIMEOUT_S
        while not store.ready.wait(0.1):
            if stop.is_set():
                outcome.stopped_early = True
                return _finish(plan, outcome, store, truth, daemon, sim, cpu_daemon, cpu_sim, wall0, cpu_demo0, out)
            if daemon.poll() is not None:
                outcome.error = f"the onboard daemon exited with code {daemon.returncode} before it was ready"
                out(
                    f"demo: {outcome.error}; last lines of {plan.out_dir / 'onboard.log'}:\n{log_tail(plan.out_dir / 'onboard.log')}"
                )
                return _finish(plan, outcome, store, truth, daemon, sim, cpu_daemon, cpu_sim, wall0, cpu_demo0, out)
            if time.monotonic() > t_ready:
                outcome.error = f"the onboard daemon published no status within {DAEMON_READY_TIMEOUT_S:g} s"
                out(f"demo: {outcome.error}; last lines of its log:\n{log_tail(plan.out_dir / 'onboard.log')}")
                return _finish(plan, outcome, store, truth, daemon, sim, cpu_daemon, cpu_sim, wall0, cpu_demo0, out)
        out(f"demo: daemon ready after {time.monotonic() - wall0:.1f} s; starting the simulator (real time)")
        sim = _start(sim_command(plan), plan.out_dir / "sim.log", env)
        cpu_sim = ProcCpu(sim.pid)
        t_sim0 = time.monotonic()
        deadline = t_sim0 + plan.duration_s + SIM_SETUP_ALLOWANCE_S
        next_line = t_sim0 + STATUS_PERIOD_S
        while True:
            if stop.wait(max(0.0, min(next_line - time.monotonic(), 0.1))):
                outcome.stopped_early = True
                break
            finished = sim.poll() is not None
            if time.monotonic() >= next_line or finished:
                next_line += STATUS_PERIOD_S
                truth.poll()
                out(_live_line(time.monotonic() - t_sim0, plan, store, truth, total_frames, cpu_sim, cpu_daemon))
            if finished:
                if sim.returncode != 0:
                    outcome.error = f"the simulator exited with code {sim.returncode}"
                    out(
                        f"demo: {outcome.error}; last lines of {plan.out_dir / 'sim.log'}:\n{log_tail(plan.out_dir / 'sim.log')}"
                    )
                break
            if daemon.poll() is not None:
                outcome.error = f"the onboard daemon exited with code {daemon.returncode} during the run"
                out(f"demo: {outcome.error}; last lines of its log:\n{log_tail(plan.out_dir / 'onboard.log')}")
                break
            if time.monotonic() > deadline:
                out(f"demo: the simulator is still running {SIM_SETUP_ALLOWANCE_S:g} s past its duration: stopping it")
                break
        if not outcome.stopped_early and outcome.error is None:
            drain_tracks(store, stop)
        return _finish(plan, outcome, store, truth, daemon, sim, cpu_daemon, cpu_sim, wall0, cpu_demo0, out)
    finally:
        close_zenoh(subs, session)
        stop_process(sim, "simulator")
        stop_process(daemon, "onboard daemon")


def _live_line(
    elapsed: float, plan: DemoPlan, store: TrackStore, truth: TruthTail, total: int, cpu_sim, cpu_daemon
) -> str:
    import numpy as np

    tracks, status = store.snapshot()
    track = tracks[-1] if tracks else None
    est_r = tru_r = err = None
    for tr in reversed(tracks[-60:]):  # the newest estimate whose truth row is known
        if tr.get("lat_deg") is None:
            continue
        row = truth.rows.get(int(tr["time_boot_us"]))
        if row is None:
            continue
        p = _track_p_ned(tr, plan.scenario.origin)
        cam = np.array([row["cam_n_m"], row["cam_e_m"], row["cam_d_m"]])
        est_r = float(np.linalg.norm(p - cam))
        tru_r = float(row["range_m"])
        err = float(np.linalg.norm(p - np.array(_truth_p(row))))
        track = tr if track is None or track.get("lat_deg") is None else track
        break
    return status_line(
        elapsed,
        len(truth.order),
        total,
        status,
        track,
        est_r,
        tru_r,
        err,
        None if cpu_sim is None else cpu_sim.share_since_last(),
        None if cpu_daemon is None else cpu_daemon.share_since_last(),
    )


def _finish(
    plan, outcome: DemoOutcome, store, truth, daemon, sim, cpu_daemon, cpu_sim, wall0, cpu_demo0, out
) -> DemoOutcome:
    """Stop the children, score, write the files, print the table."""
    for p in (cpu_sim, cpu_daemon):
        if p is not None:
            p.share_since_last()
    outcome.sim_exit = stop_process(sim, "simulator")
    outcome.daemon_exit = stop_process(daemon, "onboard daemon")
    outcome.wall_s = time.monotonic() - wall0
    outcome.cpu_share = {
        "sim": None if cpu_sim is None else cpu_sim.share_overall(),
        "daemon": None if cpu_daemon is None else cpu_daemon.share_overall(),
        "demo": (time.process_time() - cpu_demo0) / max(outcome.wall_s, 1e-9),
    }
    truth.poll()
    tracks, status = store.snapshot()
    outcome.last_status = status
    if store.first_track_mono is not None:
        t0 = store.first_track_mono
        outcome.warnings_after_s = {c: round(t - t0, 3) for c, t in store.warnings_first_mono.items()}
    outcome.sim_frames = len(truth.order)
    outcome.tracks = len(tracks)
    try:
        outcome.files = _write_files(plan, outcome, tracks, truth)
    except (OSError, IrtrackError) as exc:
        out(f"demo: could not write the report files: {exc}")
    if outcome.sim_frames:
        out("")
        out(format_demo_table(outcome.scores, outcome))
    else:
        out("demo: no frame was simulated; nothing to score")
    if outcome.files.get("report.md"):
        out(f"\nreport: {outcome.files['report.md']}")
    return outcome


def _write_files(plan: DemoPlan, outcome: DemoOutcome, tracks: list[dict], truth: TruthTail) -> dict:
    import numpy as np

    from groundsim.evaluation.eval import RunResult
    from groundsim.evaluation.report import json_ready, write_tum
    from groundsim.evaluation.report_plots import plot_errors, plot_trajectory

    d = plan.out_dir
    files = {}
    with open(d / "tracks.jsonl", "w", encoding="utf-8") as f:
        for tr in tracks:
            f.write(json.dumps(tr, separators=(",", ":")) + "\n")
    files["tracks.jsonl"] = str(d / "tracks.jsonl")
    if not truth.order:
        return files
    a = aligned_arrays(truth, tracks, plan.scenario.origin)
    outcome.scores = score_demo(a)
    t = a["t_us"] / 1e6
    write_tum(d / "truth.tum", t, a["truth_p"])
    obs = np.all(np.isfinite(a["est_p"]), axis=1) & a["observable"]
    write_tum(d / "estimate.tum", t[obs], a["est_p"][obs])
    files.update({"truth.tum": str(d / "truth.tum"), "estimate.tum": str(d / "estimate.tum")})
    F = int(a["t_us"].size)
    nan3 = np.full((F, 3), np.nan)
    run = RunResult(
        scenario=plan.scenario.name,
        description=plan.scenario.description,
        seed=plan.seed,
        frames=F,
        t_s=t - t[0],
        time_boot_us=a["t_us"],
        truth_p_ned_m=a["truth_p"],
        cam_p_ned_m=a["cam_p"],
        observer_p_ned_m=a["obs_p"],
        range_m=a["range_m"],
        truth_uv_px=a["truth_uv"],
        visible=a["visible"],
        state=a["state"],
        measurement_valid=a["measurement_valid"],
        uv_px=a["uv"],
        bbox=a["bbox"],
        pose_valid=np.zeros(F, bool),
        est_p_ned_m=a["est_p"],
        est_cov_ned_m2=a["est_P"],
        observable=a["observable"],
        range_sigma_ratio=np.full(F, np.nan),
        base_p_ned_m=nan3,
        base_cov_ned_m2=np.full((F, 3, 3), np.nan),
        base_observable=np.zeros(F, bool),
    )
    title = f"demo: {plan.scenario.name} seed {plan.seed} (real time, two processes)"
    files["trajectory.png"] = str(plot_trajectory(d / "trajectory.png", run, title))
    files["error.png"] = str(plot_errors(d / "error.png", run, title))
    report = {
        "schema": "irtrack.demo/1",
        "generated_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "scenario": plan.scenario.name,
        "seed": plan.seed,
        "duration_s": plan.duration_s,
        "wall_s": outcome.wall_s,
        "stopped_early": outcome.stopped_early,
        "error": outcome.error,
        "exit_codes": {"sim": outcome.sim_exit, "daemon": outcome.daemon_exit},
        "scores": outcome.scores,
        "cpu_share": outcome.cpu_share,
        "daemon_status": outcome.last_status,
        "commands": {"daemon": daemon_command(plan), "sim": sim_command(plan)},
    }
    (d / "report.json").write_text(json.dumps(json_ready(report), indent=1, allow_nan=False) + "\n", encoding="utf-8")
    files["report.json"] = str(d / "report.json")
    md = [
        "# irtrack demo: simulator + onboard daemon on loopback, real time\n",
        f"Generated {report['generated_utc']}. Daemon: `{' '.join(report['commands']['daemon'])}`. "
        f"Simulator: `{' '.join(report['commands']['sim'])}`.\n",
        format_demo_table(outcome.scores, outcome),
        "",
        "Definitions as in `python -m groundsim eval`'s report: observable frames = the positions the daemon "
        "publishes with `observable: true`; it publishes the unobservable ones too "
        "(`output.unobservable_positions: true`, the default), flagged false and scored in the second row.\n",
        "![trajectory](trajectory.png)\n",
        "![error](error.png)\n",
        "TUM files: `evo_ape tum truth.tum estimate.tum`.\n",
    ]
    (d / "report.md").write_text("\n".join(md), encoding="utf-8")
    files["report.md"] = str(d / "report.md")
    return files


# --------------------------------------------------------------------------- command


def cmd_demo(args) -> int:
    """The ``demo`` command (see the module docstring)."""
    stop = threading.Event()
    received: list[int] = []
    restore = install_stop_signals(stop, received, lambda n: print(f"\ndemo: {n}: stopping", file=sys.stderr))
    try:
        for name in ("onboard", "groundsim.app.run", "groundsim.world.flight"):
            logging.getLogger(name).setLevel(max(logging.WARNING, logging.getLogger().getEffectiveLevel()))
        # a bad option fails here, before any process starts or OUT is created
        injected = InjectedErrors.from_options(getattr(args, "nav_noise", None), getattr(args, "gnss_dropout", None))
        plan = plan_demo(
            args.scenario,
            args.duration,
            args.seed,
            args.out,
            args.onboard_config,
            injected.nav_noise,
            mount_as_configured=bool(getattr(args, "mount_as_configured", False)),
            gnss_dropout=injected.gnss_dropout,
            live_view_port=getattr(args, "live_view", None),  # --live-view PORT: passed through to the daemon
        )
        if plan.live_view_port is not None:
            print(
                f"demo: live view for Foxglove at ws://127.0.0.1:{plan.live_view_port} (Open connection -> Foxglove WebSocket)",
                flush=True,
            )
        outcome = run_demo(plan, stop)
        report = outcome.files.get("report.md")
        kept = f"the live run's report in {report}" if report else "nothing written"
        if signal.SIGINT in received or signal.SIGTERM in received:  # a cut run is no success, whichever stopped it
            return print_interrupted(kept)
        if getattr(args, "with_eval", False) and not stop.is_set() and outcome.error is None:
            eval_dir = plan.out_dir / "eval"
            restore()  # Ctrl-C during the evaluation interrupts it: its pool is terminated, its finished runs kept
            try:
                _quick_eval(eval_dir, stop, plan)
            except KeyboardInterrupt as exc:  # EvalInterrupted in its runs, else in the paper table after its report
                ev = keep_interrupted(exc, eval_dir) if isinstance(exc, EvalInterrupted) else "report written"
                return print_interrupted(f"{kept}; the evaluation: {ev}")
        if outcome.error is not None:
            return EXIT_FAILED
        return EXIT_OK
    finally:
        restore()


def _quick_eval(out_dir: Path, stop: threading.Event, plan: DemoPlan) -> None:
    """The lockstep evaluation of P1-P3 with the live run's seed, daemon configuration, navigation-error case
    and GNSS dropout, and its Table-2 style and closed-loop tables.  Each scenario keeps its own camera mount
    (``--mount-as-configured`` is the live run's alone: the lockstep evaluation has no such option), which the
    announcement says."""
    from groundsim.evaluation.eval import EvalOptions, run_eval
    from groundsim.evaluation.parallel import pool_workers
    from groundsim.evaluation.report import format_closed_loop, format_table2, write_eval_report
    from groundsim.world.scenario import load_scenario, reference_scenario_paths
    from onboard.app.config import OnboardConfig, load_config

    paths = reference_scenario_paths()
    scenarios = [load_scenario(paths[n]) for n in ("P1", "P2", "P3") if n in paths]
    source = plan.onboard_config_source
    base = OnboardConfig() if source == "(defaults)" else load_config(source, environ={})
    injected = InjectedErrors(plan.injected.nav_noise, plan.injected.gnss_dropout)
    extras = [f"seed {plan.seed}", f"navigation errors {injected.nav_noise}", f"onboard configuration {source}"]
    if injected.gnss_dropout is not None:
        g = injected.gnss_dropout
        extras.append(f"GNSS dropout {g.start_s:g} s for {g.duration_s:g} s")
    if plan.mount_as_configured:
        extras.append("each scenario's camera mount, not --mount-as-configured")
    print(
        f"\ndemo: lockstep evaluation of P1-P3 ({', '.join(extras)}; `python -m groundsim eval` runs five seeds)",
        flush=True,
    )
    result = run_eval(
        scenarios,
        [plan.seed],
        EvalOptions(injected=injected),
        base,
        workers=pool_workers(None),
        config_source=source,
    )
    files = write_eval_report(out_dir, result)
    print(format_table2(result.summary, {sc.name: sc.description.split(":", 1)[-1].strip() for sc in scenarios}))
    print()
    print(format_closed_loop(result.summary))
    print(f"\nevaluation report: {files['report.md']}", flush=True)
    _paper_baseline_table(scenarios)


def _paper_baseline_table(scenarios) -> None:
    """Our estimator beside the paper's closed form on the same perfect-geometry observations (0.3 px):
    the closed form's collapse toward the camera track under noise is shown, not hidden."""
    from groundsim.evaluation.estimator_eval import format_table, run_cases, summarise
    from groundsim.world.noise_cases import load_noise_cases

    print(
        "\ndemo: the reconstruction core against the paper's closed form (analytic truth, 0.3 px, one seed;"
        " `make bench` runs fifty)",
        flush=True,
    )
    rows = summarise(run_cases(scenarios, [load_noise_cases()["px0.3"]], [0], workers=1))
    print(format_table(rows), flush=True)
