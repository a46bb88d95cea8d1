"""Two drones, one target, end to end: F1 through a zenoh router, two daemons and the fusion node, scored.

    python -m bench.fleet --flight F1 [--seeds N] [--kill-at 15 [--restart-at 20]] [--duration S] [--out out/fleet]

One run per seed, every process real and on 127.0.0.1 (the deployment of deploy/compose.fleet.yaml on one
machine, free ports instead of the fixed ones)::

    this process        zenoh router, tcp/127.0.0.1:R (gossip on, as deploy/zenoh-router.json5)
    python -m onboard --config config/fleet/uavN.yaml --mavlink udpin:127.0.0.1:M_N --zenoh-connect tcp/...:R
    python -m onboard.fuse --vehicles uav1 uav2 --zenoh-connect tcp/127.0.0.1:R --zenoh-listen tcp/127.0.0.1:0
                        --zenoh-gossip-autoconnect
    python -m groundsim run --scenario F1 --rate realtime --start-time-utc now --mavlink uavN=udpout:...:M_N ...
    this process        a peer on the router: irtrack/*/ir/frame, irtrack/*/track, irtrack/fleet/track

Every session is a zenoh peer that listens on an ephemeral loopback port: the router's gossip introduces
them (a zenoh 1.10 router does not relay between peers).  The simulator starts once both daemons and the
fusion node published a status; ``--start-time-utc now`` puts the simulated UTC on this machine's clock,
which the fusion's staleness check compares against.  ``--kill-at T``: the uav2 daemon is SIGKILLed T
seconds into the flight (the flight's time: the newest frame's, which a loaded machine's simulator lets fall
behind the wall clock) and started again at ``--restart-at`` (default T + 5).

Scoring (:func:`score_flight`, pure): a *step* is one simulator tick (both vehicles' frames of it share
the truth's ``t_s``).  A step is *tracked* by a vehicle when its daemon's track of that frame carries a line
of sight.  Each fleet track is matched to the step of its newest line of sight (the contribution times
put on each vehicle's frames by the fusion's own :class:`~onboard.io.fleet_wire.CommonClock` replayed over
the tracks as they arrived here: the tracks' ``time_unix_us``, else the arrival clock) and scored against the truth
target at its time, in the fleet track's own NED frame: error over the true range from that vehicle's
camera, beyond 3 sigma = ``||e|| > 3 sqrt(trace cov)`` (as ``groundsim eval``).  The share with a fleet
position: of the steps from one second after the first step both vehicles track (to the end, or to the
kill), those that are the newest step of a fleet track with both vehicles.  Latency: for each such step, the
first fleet track containing both vehicles' frames of it or later, minus the later arrival of the two
frames here (the frames' wall arrival on this machine: the simulator publishes at capture time).
Each vehicle alone: its own track's verdict and error over the same steps.  The first second, left out of the
shares, is counted apart: its two-vehicle fleet tracks (the target's first fused points), how many are observable,
and how many of those are beyond 3 sigma.

Numbers, no assertions; the issue's goals are printed beside them.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
VEHICLES = ("uav1", "uav2")
#: the processes of a flight, each with its log in the flight's folder
LOG_NAMES = (*VEHICLES, "fuse", "sim")
FLEET_CONFIGS = {v: REPO / "config" / "fleet" / f"{v}.yaml" for v in VEHICLES}
READY_TIMEOUT_S = 60.0  # imports and zenoh on a loaded 2-core machine
SIM_ALLOWANCE_S = 30.0  # wall seconds beyond the flight before the simulator counts as stuck
DRAIN_S = 1.5
SETTLE_S = 1.0  # the first second in which both vehicles track is not scored (the words)
RESTART_FLIGHT_S = 25.0  # with a kill: the flight goes on this long after the restart
FUSE_MAX_AGE_S = 30.0  # the fusion's --max-age-s here (see FlightPlan.fuse_command)
GOALS = (
    "goals: fleet position >= 95 % of steps, observable, median <= 0.5 % of range, <= 1 % beyond 3 sigma, "
    "each vehicle alone unobservable; latency p99 <= 50 ms; kill: continues within 1 s, fused again within 2 s"
)

__all__ = ["FlightRecord", "FlightPlan", "plan_flight", "run_flight", "score_flight", "format_score"]


# --------------------------------------------------------------------------- what a run records


@dataclass
class FlightRecord:
    """What one run collected (wall times are this machine's ``time.time()``, seconds)."""

    truth: dict  # vehicle -> groundsim.world.truth.read_truth_csv arrays
    frames_rx: dict = field(default_factory=dict)  # vehicle -> {time_boot_us: first arrival}
    tracks: dict = field(default_factory=dict)  # vehicle -> [(arrival, irtrack.track/2 dict)]
    fleet: list = field(default_factory=list)  # [(arrival, irtrack.fleet_track/1 dict)]
    fleet_status: dict | None = None
    sim_start_unix_s: float = math.nan  # the simulator's --start-time-utc now, approximately (its spawn)
    kill_unix_s: float | None = None
    kill_sim_s: float | None = None  # the flight's time at the kill (the newest frame's), s
    restart_unix_s: float | None = None
    killed: str | None = None
    pids: list = field(default_factory=list)  # every child started (the tests check that none is left)
    sim_pacing: str = ""  # the simulator's last pacing line (how far its frames fell behind the wall clock)
    clock_status: list = field(default_factory=list)  # [(arrival, the fleet status's clock_inconsistent, clocks)]
    utc_error_ms: dict = field(default_factory=dict)  # vehicle -> the UTC error injected in its SYSTEM_TIME, ms


class _Collector:
    """zenoh callbacks (any thread) into a :class:`FlightRecord`."""

    def __init__(self, record: FlightRecord) -> None:
        self.rec = record
        self.lock = threading.Lock()
        self.status: dict[str, float] = {}
        self.first_boot_us: dict[str, int] = {}
        self.flight_s = 0.0  # the newest frame's time since each vehicle's first (= scenario time), s

    def on_frame(self, sample) -> None:
        from onboard.core.irframe import decode_irframe

        t = time.time()
        vehicle = str(sample.key_expr).split("/")[1]
        try:
            boot_us = decode_irframe(sample.payload.to_bytes()).time_boot_us
        except Exception:  # noqa: BLE001 - a bad frame is the daemon's business, not the score's
            return
        with self.lock:
            self.rec.frames_rx.setdefault(vehicle, {}).setdefault(boot_us, t)
            first = self.first_boot_us.setdefault(vehicle, boot_us)
            self.flight_s = max(self.flight_s, (boot_us - first) / 1e6)

    def on_track(self, sample) -> None:
        t = time.time()
        parts = str(sample.key_expr).split("/")
        try:
            obj = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        with self.lock:
            if parts[1] == "fleet":
                self.rec.fleet.append((t, obj))
            else:
                self.rec.tracks.setdefault(parts[1], []).append((t, obj))

    def on_status(self, sample) -> None:
        parts = str(sample.key_expr).split("/")
        with self.lock:
            self.status[parts[1]] = time.time()
            if parts[1] == "fleet":
                try:
                    self.rec.fleet_status = st = json.loads(sample.payload.to_bytes())
                except ValueError:
                    return
                if isinstance(st, dict):
                    self.rec.clock_status.append((time.time(), st.get("clock_inconsistent"), st.get("clocks")))


# --------------------------------------------------------------------------- processes


@dataclass(frozen=True)
class FlightPlan:
    scenario: str
    seed: int
    out_dir: Path
    router_port: int
    mavlink_ports: dict
    duration_s: float | None = None
    utc_error_ms: tuple = ()  # ((vehicle, ms), ...): groundsim run --utc-error-ms

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.router_port}"

    def daemon_command(self, vehicle: str) -> list[str]:
        return [
            sys.executable,
            "-m",
            "onboard",
            "--config",
            str(FLEET_CONFIGS[vehicle]),
            "--mavlink",
            f"udpin:127.0.0.1:{self.mavlink_ports[vehicle]}",
            "--zenoh-connect",
            self.endpoint,
            "--set",
            f"output.health_file={self.out_dir / (vehicle + '.alive')}",
        ]

    def fuse_command(self) -> list[str]:
        return [
            sys.executable,
            "-m",
            "onboard.fuse",
            "--vehicles",
            *VEHICLES,
            "--zenoh-connect",
            self.endpoint,
            "--zenoh-listen",
            "tcp/127.0.0.1:0",
            # the daemons dial nothing they were not given: the fusion dials them, as the router's gossip names them
            "--zenoh-gossip-autoconnect",
            "--status-interval-s",
            "0.5",
            # the simulator's clocks are the flight's: on a loaded machine its "real time" slips seconds behind
            # the wall clock (measured: 3.4 s at load 18 on 2 cores), which the fusion's staleness guard (2 s by
            # default, meant for vehicles whose clocks follow UTC) would take for stale frames
            "--max-age-s",
            f"{FUSE_MAX_AGE_S:g}",
        ]

    def sim_command(self) -> list[str]:
        mav = [a for v in VEHICLES for a in ("--mavlink", f"{v}=udpout:127.0.0.1:{self.mavlink_ports[v]}")]
        dur = [] if self.duration_s is None else ["--duration", f"{self.duration_s:g}"]
        return [
            sys.executable,
            "-m",
            "groundsim",
            "run",
            "--scenario",
            self.scenario,
            "--seed",
            str(self.seed),
            *dur,
            "--rate",
            "realtime",
            "--start-time-utc",
            "now",
            *mav,
            "--zenoh-connect",
            self.endpoint,
            "--zenoh-listen",
            "tcp/127.0.0.1:0",
            "--zenoh-connect-timeout",
            "10",
            "--truth",
            str(self.out_dir / "truth.csv"),
            *[a for v, ms in self.utc_error_ms for a in ("--utc-error-ms", f"{v}={ms:g}")],
        ]


def plan_flight(
    scenario: str, seed: int, out_dir, duration_s: float | None = None, utc_error_ms: tuple = ()
) -> FlightPlan:
    from groundsim.io.ports import free_tcp_port, free_udp_port

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    # a flight's own files from a run before in this folder: its logs are appended to (across a daemon's restart
    # within one flight) and a failed flight left the last one's score and truth to be read as its own
    stale = [out / f"{name}.log" for name in LOG_NAMES] + [out / "score.json", out / "record.json"]
    stale += list(out.glob("truth*.csv"))
    for path in stale:
        path.unlink(missing_ok=True)
    ports = {v: free_udp_port() for v in VEHICLES}
    return FlightPlan(scenario, int(seed), out, free_tcp_port(), ports, duration_s, tuple(utc_error_ms))


def open_router(endpoint: str, gossip: bool | None = True):
    """A zenoh router in this process listening on ``endpoint``, configured as deploy/zenoh-router.json5 (gossip
    on, no multicast); ``gossip=None`` leaves gossip to zenoh's default (bench.fleet, whose sessions are all
    clients of this router)."""
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps("router"))
    cfg.insert_json5("listen/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    if gossip is not None:
        cfg.insert_json5("scouting/gossip/enabled", json.dumps(gossip))
    return zenoh.open(cfg)


def _start(cmd: list[str], log_path: Path) -> subprocess.Popen:
    from groundsim.evaluation.demo import child_env

    with open(log_path, "ab") as f:  # the child keeps its own descriptor
        return subprocess.Popen(
            cmd, cwd=REPO, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=child_env()
        )


class FlightError(RuntimeError):
    """A child failed to start, died or hung; the message carries the tail of its log."""


def run_flight(
    plan: FlightPlan,
    kill_at_s: float | None = None,
    restart_at_s: float | None = None,
    drain_s: float = DRAIN_S,
    record: FlightRecord | None = None,
) -> FlightRecord:
    """Start the router, the daemons, the fusion and the simulator; record (into ``record`` if given: what was
    collected survives a failure) until the simulator ends; stop all children (SIGTERM, then SIGKILL) whatever
    happens.  Raises :class:`FlightError` on a child's failure."""
    from groundsim.evaluation.demo import log_tail, stop_process
    from groundsim.world.truth import read_truth_csv
    from onboard.io.zenoh_session import ZenohConfig, open_session

    rec = FlightRecord(truth={}) if record is None else record
    col = _Collector(rec)
    logs = {name: plan.out_dir / f"{name}.log" for name in LOG_NAMES}
    procs: dict[str, subprocess.Popen | None] = {}
    router = open_router(plan.endpoint)
    session = None
    try:
        # a peer on the ground, as the fleet's: it meets the daemons through the router's gossip
        session = open_session(
            ZenohConfig(connect=(plan.endpoint,), listen=("tcp/127.0.0.1:0",), gossip_autoconnect=None)
        )
        session.declare_subscriber("irtrack/*/ir/frame", col.on_frame)
        session.declare_subscriber("irtrack/*/track", col.on_track)
        session.declare_subscriber("irtrack/*/status", col.on_status)
        for v in VEHICLES:
            procs[v] = _start(plan.daemon_command(v), logs[v])
        procs["fuse"] = _start(plan.fuse_command(), logs["fuse"])
        rec.pids += [p.pid for p in procs.values() if p is not None]
        t_end = time.monotonic() + READY_TIMEOUT_S
        while set(col.status) < {*VEHICLES, "fleet"}:
            for name, p in procs.items():
                if p is not None and p.poll() is not None:
                    raise FlightError(f"{name} exited with code {p.returncode}:\n{log_tail(logs[name])}")
            if time.monotonic() > t_end:
                raise FlightError(f"no status from {sorted({*VEHICLES, 'fleet'} - set(col.status))} in time")
            time.sleep(0.1)
        rec.sim_start_unix_s = time.time()
        procs["sim"] = sim = _start(plan.sim_command(), logs["sim"])
        rec.pids.append(sim.pid)
        victim = VEHICLES[1]
        restart_at_s = None if kill_at_s is None else (kill_at_s + 5.0 if restart_at_s is None else restart_at_s)
        # a loaded machine slows the simulator's "real time" itself (measured: x0.6 at load 15 on 2 cores)
        deadline = time.monotonic() + 2.0 * (plan.duration_s or 30.0) + SIM_ALLOWANCE_S
        while sim.poll() is None:
            now = col.flight_s  # kill and restart on the flight's clock, which a loaded simulator slows
            if kill_at_s is not None and rec.kill_unix_s is None and now >= kill_at_s:
                procs[victim].kill()  # type: ignore[union-attr]
                rec.kill_unix_s, rec.kill_sim_s, rec.killed = time.time(), now, victim
                procs[victim].wait()  # type: ignore[union-attr]
            if restart_at_s is not None and rec.kill_unix_s is not None and rec.restart_unix_s is None:
                if now >= restart_at_s:
                    rec.restart_unix_s = time.time()
                    procs[victim] = _start(plan.daemon_command(victim), logs[victim])
                    rec.pids.append(procs[victim].pid)  # type: ignore[union-attr]
            if time.monotonic() > deadline:
                raise FlightError(f"the simulator still runs past its flight:\n{log_tail(logs['sim'])}")
            time.sleep(0.02)
        if sim.returncode != 0:
            raise FlightError(f"the simulator exited with code {sim.returncode}:\n{log_tail(logs['sim'])}")
        time.sleep(drain_s)
    finally:
        if session is not None:
            session.close()
        for name in ("sim", "fuse", *VEHICLES):
            stop_process(procs.get(name), name)
        router.close()
    for v in VEHICLES:
        rec.truth[v] = read_truth_csv(plan.out_dir / f"truth.{v}.csv")
    pacing = [line for line in logs["sim"].read_text(errors="replace").splitlines() if "pacing:" in line]
    rec.sim_pacing = pacing[-1].split("pacing:", 1)[1].strip().rstrip('"') if pacing else ""
    return rec


# --------------------------------------------------------------------------- scoring


def _fleet_clock(rec: FlightRecord, vehicle: str) -> np.ndarray:
    """The fleet-clock time (UTC s) of each of ``vehicle``'s frames (truth rows) as the fusion put them: the
    fusion's own :class:`~onboard.io.fleet_wire.CommonClock` replayed over the tracks in the order and at the
    times they arrived here (a millisecond or so after the fusion got them).  Its arrival-time offset follows
    the simulator's clock when a loaded machine lets that slip behind the wall clock, so no one offset would
    do.  NaN for a frame without a track."""
    from onboard.io.fleet_wire import CommonClock

    truth = rec.truth[vehicle]
    index = {int(b): k for k, b in enumerate(truth["time_boot_us"])}
    out = np.full(len(index), math.nan)
    clock = CommonClock()
    for t_rx, obj in rec.tracks.get(vehicle, []):
        k = index.get(int(obj.get("time_boot_us", -1)))
        if k is None or obj.get("los_ned") is None:
            continue
        t_s, _ = clock.time_s(vehicle, obj["time_boot_us"], obj.get("time_unix_us"), t_rx)
        out[k] = t_s
    return out


def _nearest(t_frames: np.ndarray, t: float) -> int:
    """The frame whose fleet time is nearest ``t`` (NaN frames never)."""
    return int(np.nanargmin(np.abs(t_frames - t)))


def _truth_ned(truth: dict, k: int, dt_s: float, origin) -> np.ndarray:
    """The true target at step ``k`` plus ``dt_s`` (its velocity), in the NED frame of ``origin``."""
    from onboard.core.frames import ned_from_geodetic

    p = ned_from_geodetic(truth["target_lat_deg"][k], truth["target_lon_deg"][k], truth["target_alt_m"][k], origin)
    v = np.array([truth["target_vn_mps"][k], truth["target_ve_mps"][k], truth["target_vd_mps"][k]])
    return np.asarray(p, dtype=float) + v * dt_s


def _origin_of(obj: dict):
    from onboard.core.frames import GeodeticOrigin

    o = obj["origin"]
    return GeodeticOrigin(o["lat_deg"], o["lon_deg"], o["alt_m"])


def score_flight(rec: FlightRecord) -> dict:
    """The issue's numbers of one run (module docstring); fractions in 0..1, times in seconds."""
    truth = rec.truth
    n_steps = min(len(truth[v]["t_s"]) for v in VEHICLES)
    t_step = truth[VEHICLES[0]]["t_s"][:n_steps]
    boot_index = {v: {int(b): k for k, b in enumerate(truth[v]["time_boot_us"][:n_steps])} for v in VEHICLES}
    # steps each vehicle tracked (its daemon's track of that frame has a line of sight), and its own estimates
    tracked = {v: np.zeros(n_steps, bool) for v in VEHICLES}
    alone: dict[str, list] = {v: [] for v in VEHICLES}  # (step, observable, err/range or nan)
    vehicle_time = False
    for v in VEHICLES:
        for _, obj in rec.tracks.get(v, []):
            k = boot_index[v].get(int(obj.get("time_boot_us", -1)))
            if k is None or obj.get("los_ned") is None:
                continue
            tracked[v][k] = True
            vehicle_time = vehicle_time or obj.get("time_unix_us") is not None
            err = math.nan
            if obj.get("ned_m") is not None and obj.get("origin") is not None:
                origin = _origin_of(obj)
                p = _truth_ned(truth[v], k, 0.0, origin)
                err = float(np.linalg.norm(np.asarray(obj["ned_m"]) - p) / truth[v]["range_m"][k])
            alone[v].append((k, bool(obj.get("observable")), err))
    both = tracked[VEHICLES[0]] & tracked[VEHICLES[1]]
    if not both.any():
        return {"steps": n_steps, "both_tracked": 0}
    k_first = int(np.flatnonzero(both)[0])
    t_from = t_step[k_first] + SETTLE_S
    t_kill = rec.kill_sim_s
    window = (t_step >= t_from) & (True if t_kill is None else t_step < t_kill)
    source = "vehicle" if vehicle_time else "arrival"
    fclock = {v: _fleet_clock(rec, v) for v in VEHICLES}
    frame_rx = {
        v: np.array([rec.frames_rx.get(v, {}).get(int(b), math.nan) for b in truth[v]["time_boot_us"][:n_steps]])
        for v in VEHICLES
    }
    # fleet tracks: the step of each contribution, the newest step, the error
    fleet_rows = []  # (arrival, newest step, {vehicle: step}, observable, err/range, beyond3)
    for t_rx, obj in rec.fleet:
        contrib = {}
        for c in obj.get("vehicles") or []:
            v = c.get("vehicle")
            if v in fclock and np.isfinite(fclock[v]).any():
                contrib[v] = _nearest(fclock[v], c["time_unix_us"] / 1e6)
        if not contrib or obj.get("ned_m") is None:
            continue
        t_est = obj["time_unix_us"] / 1e6
        v_new = max(contrib, key=lambda v: fclock[v][contrib[v]])
        k = _nearest(fclock[v_new], t_est)
        k = min(k, n_steps - 1)
        origin = _origin_of(obj)
        p = _truth_ned(truth[v_new], k, t_est - fclock[v_new][k], origin)
        e = np.asarray(obj["ned_m"], dtype=float) - p
        rng = float(truth[v_new]["range_m"][k])
        cov = np.asarray(obj["cov_ned_m2"], dtype=float)
        beyond = float(np.linalg.norm(e)) > 3.0 * math.sqrt(max(float(np.trace(cov)), 0.0))
        fleet_rows.append((t_rx, k, contrib, bool(obj.get("observable")), float(np.linalg.norm(e)) / rng, beyond))
    both_rows = [r for r in fleet_rows if len(r[2]) == len(VEHICLES) and window[r[1]]]
    # the first second, left out of the shares, holds the target's first fused points (the first from one line of
    # sight per vehicle, the least redundancy a fused point has): counted on their own, so that a confident wrong
    # point there is not invisible
    first_rows = [r for r in fleet_rows if len(r[2]) == len(VEHICLES) and t_step[r[1]] < t_from]
    steps_with = {r[1] for r in both_rows}
    scored_steps = np.flatnonzero(window & both)
    out: dict = {
        "steps": n_steps,
        "both_tracked": int(both.sum()),
        "first_both_t_s": float(t_step[k_first]),
        "time_source": source,
        "scored_steps": int(window.sum()),
        "fleet_position_share": len(steps_with & set(np.flatnonzero(window))) / max(1, int(window.sum())),
        "fleet_tracks": len(fleet_rows),
        "fleet_tracks_both": len(both_rows),
        "first_second_tracks": len(first_rows),
        "first_second_observable": sum(1 for r in first_rows if r[3]),
        "first_second_confident_wrong": sum(1 for r in first_rows if r[3] and r[5]),
    }
    out["navigation_floor_err_ratio"] = navigation_floor(truth, scored_steps[::10])
    if both_rows:
        errs = np.array([r[4] for r in both_rows])
        out["observable_share"] = float(np.mean([r[3] for r in both_rows]))
        out["median_err_ratio"] = float(np.median(errs))
        out["p90_err_ratio"] = float(np.percentile(errs, 90))
        out["beyond_3sigma_share"] = float(np.mean([r[5] for r in both_rows]))
    for v in VEHICLES:
        rows = [r for r in alone[v] if window[r[0]]]
        errs = np.array([r[2] for r in rows if math.isfinite(r[2])])
        out[f"{v}_alone_observable_share"] = float(np.mean([r[1] for r in rows])) if rows else math.nan
        out[f"{v}_alone_median_err_ratio"] = float(np.median(errs)) if errs.size else math.nan
    # latency: step k's later frame arrival -> the first fleet track with both vehicles at k or later
    lat = []
    rows_sorted = sorted((r for r in fleet_rows if len(r[2]) == len(VEHICLES)), key=lambda r: r[0])
    for k in scored_steps:
        later = max(frame_rx[v][k] for v in VEHICLES)
        if not math.isfinite(later):
            continue
        first = next((r[0] for r in rows_sorted if all(s >= k for s in r[2].values()) and r[0] >= later), None)
        if first is not None:
            lat.append(first - later)
    if lat:
        out["latency_p50_s"], out["latency_p99_s"] = (float(x) for x in np.percentile(lat, [50, 99]))
        out["latency_max_s"] = float(np.max(lat))
        out["latency_n"] = len(lat)
    # the fusion's share of it: the later of the two vehicles' tracks of step k -> the same fleet track
    track_rx = {v: np.full(n_steps, math.nan) for v in VEHICLES}
    for v in VEHICLES:
        for t_rx, obj in rec.tracks.get(v, []):
            k = boot_index[v].get(int(obj.get("time_boot_us", -1)))
            if k is not None and obj.get("los_ned") is not None and not math.isfinite(track_rx[v][k]):
                track_rx[v][k] = t_rx
    fuse_lat = []
    for k in scored_steps:
        later = max(track_rx[v][k] for v in VEHICLES)
        first = next((r[0] for r in rows_sorted if all(s >= k for s in r[2].values()) and r[0] >= later), None)
        if math.isfinite(later) and first is not None:
            fuse_lat.append(first - later)
    if fuse_lat:
        out["fuse_latency_p50_s"], out["fuse_latency_p99_s"] = (float(x) for x in np.percentile(fuse_lat, [50, 99]))
        daemon = [
            max(track_rx[v][k] - frame_rx[v][k] for v in VEHICLES)
            for k in scored_steps
            if all(math.isfinite(track_rx[v][k] - frame_rx[v][k]) for v in VEHICLES)
        ]
        if daemon:
            out["daemon_latency_p50_s"], out["daemon_latency_p99_s"] = (
                float(x) for x in np.percentile(daemon, [50, 99])
            )
    if rec.kill_unix_s is not None:
        out.update(_score_kill(rec, fleet_rows))
    return out


def triangulate_ned_m(c_ned_m: np.ndarray, u_ned: np.ndarray) -> np.ndarray:
    """The point closest, in the least-squares sense, to rays ``c_i + s u_i`` (shapes (N, 3), ``u`` unit):
    ``sum_i (I - u_i u_i^T) p = sum_i (I - u_i u_i^T) c_i``."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, u in zip(c_ned_m, u_ned):
        P = np.eye(3) - np.outer(u, u)
        A += P
        b += P @ c
    return np.linalg.solve(A, b)


def navigation_floor(truth: dict, steps) -> float:
    """Median over ``steps`` of the range-normalised error of triangulating the target from perfect pixels
    with the navigation errors the simulator injected (each vehicle's camera position error and attitude
    error: ``u_reported = R_err u_true``, ``R_err`` the truth's rotation vector): what no fusion of these
    two vehicles' lines of sight can undo on a straight-and-level flight, where the constant attitude bias is
    not observable."""
    errs = []
    for k in steps:
        cams, rays = [], []
        p_true = None
        for v in VEHICLES:
            t = truth[v]
            p_true = np.array([t[f"target_{a}_m"][k] for a in "ned"])
            c = np.array([t[f"cam_{a}_m"][k] for a in "ned"])
            u = (p_true - c) / np.linalg.norm(p_true - c)
            theta = np.array([t[f"nav_att_err_{a}_rad"][k] for a in "ned"])
            u_rep = u + np.cross(theta, u)  # small rotation
            cams.append(c + np.array([t[f"nav_p_err_{a}_m"][k] for a in "ned"]))
            rays.append(u_rep / np.linalg.norm(u_rep))
        p = triangulate_ned_m(np.array(cams), np.array(rays))
        errs.append(float(np.linalg.norm(p - p_true) / truth[VEHICLES[0]]["range_m"][k]))
    return float(np.median(errs)) if errs else math.nan


def _score_kill(rec: FlightRecord, fleet_rows: list) -> dict:
    """Kill and restart: how soon the fleet track goes on without the killed vehicle, what it says then, and
    how soon after the restart both vehicles are fused again."""
    killed, other = rec.killed, next(v for v in VEHICLES if v != rec.killed)
    kill = rec.kill_unix_s
    out: dict = {"killed": killed}
    after = [r for r in fleet_rows if r[0] > kill]
    alone = next((r for r in after if set(r[2]) == {other}), None)
    gaps = np.diff([kill] + [r[0] for r in after if rec.restart_unix_s is None or r[0] < rec.restart_unix_s])
    out["max_gap_after_kill_s"] = float(gaps.max()) if gaps.size else math.nan
    if alone is not None:
        out["continue_alone_s"] = alone[0] - kill
        solo = [r for r in after if set(r[2]) == {other}]
        out["alone_observable_share"] = float(np.mean([r[3] for r in solo]))
        out["alone_beyond_3sigma_share"] = float(np.mean([r[5] for r in solo]))
        out["alone_median_err_ratio"] = float(np.median([r[4] for r in solo]))
    if rec.restart_unix_s is not None:
        restart = rec.restart_unix_s
        first_track = next((t for t, obj in rec.tracks.get(killed, []) if t > restart), None)
        first_los = next(
            (t for t, obj in rec.tracks.get(killed, []) if t > restart and obj.get("los_ned") is not None), None
        )
        back = next((r for r in fleet_rows if r[0] > restart and killed in r[2] and len(r[2]) == len(VEHICLES)), None)
        out["restart_first_track_s"] = None if first_track is None else first_track - restart
        out["restart_first_los_s"] = None if first_los is None else first_los - restart
        out["fused_again_s"] = None if back is None else back[0] - restart
        out["fused_again_after_los_s"] = None if back is None or first_los is None else back[0] - first_los
    return out


def _pct(x) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{100 * x:.2f} %"


def _ms(x) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{1000 * x:.0f} ms"


def format_score(s: dict, seed: int) -> str:
    if not s.get("both_tracked"):
        return f"seed {seed}: the two vehicles never tracked the target on the same step ({s.get('steps')} steps)"
    lines = [
        f"seed {seed}: both vehicles track from t = {s['first_both_t_s']:.2f} s; {s['scored_steps']} steps scored "
        f"(from one second later{', to the kill' if 'killed' in s else ''}); time source {s['time_source']}",
        f"  fleet: position on {_pct(s['fleet_position_share'])} of steps, observable {_pct(s.get('observable_share'))},"
        f" median error {_pct(s.get('median_err_ratio'))} of range (p90 {_pct(s.get('p90_err_ratio'))}),"
        f" beyond 3 sigma {_pct(s.get('beyond_3sigma_share'))} ({s['fleet_tracks_both']} two-vehicle tracks)",
        f"  first second (left out above): {s['first_second_tracks']} two-vehicle tracks, "
        f"{s['first_second_observable']} observable, {s['first_second_confident_wrong']} observable and beyond 3 sigma",
        f"  the navigation floor: perfect pixels with the injected navigation errors triangulate to a median "
        f"{_pct(s.get('navigation_floor_err_ratio'))} of range",
    ]
    for v in VEHICLES:
        lines.append(
            f"  {v} alone: observable {_pct(s[f'{v}_alone_observable_share'])},"
            f" median error {_pct(s[f'{v}_alone_median_err_ratio'])} of range"
        )
    if "latency_n" in s:
        lines.append(
            f"  latency, later frame -> fleet track: p50 {_ms(s['latency_p50_s'])}, p99 {_ms(s['latency_p99_s'])},"
            f" max {_ms(s['latency_max_s'])} ({s['latency_n']} steps)"
        )
    if "fuse_latency_p50_s" in s:
        lines.append(
            f"    of which: frame -> the slower daemon's track p50 {_ms(s.get('daemon_latency_p50_s'))}, p99 "
            f"{_ms(s.get('daemon_latency_p99_s'))}; later vehicle track -> fleet track p50 "
            f"{_ms(s['fuse_latency_p50_s'])}, p99 {_ms(s['fuse_latency_p99_s'])}"
        )
    if "killed" in s:
        lines.append(
            f"  kill {s['killed']}: fleet track on the other alone after {_ms(s.get('continue_alone_s'))} (longest gap "
            f"{_ms(s.get('max_gap_after_kill_s'))}); alone: observable {_pct(s.get('alone_observable_share'))}, "
            f"beyond 3 sigma {_pct(s.get('alone_beyond_3sigma_share'))}, median error "
            f"{_pct(s.get('alone_median_err_ratio'))}"
        )
        if "fused_again_s" in s:
            lines.append(
                f"  restart: its first track after {_ms(s['restart_first_track_s'])}, first line of sight after "
                f"{_ms(s['restart_first_los_s'])}; fused again {_ms(s['fused_again_s'])} after the restart "
                f"({_ms(s['fused_again_after_los_s'])} after its first line of sight)"
            )
    if s.get("clock_statuses"):
        named = ", ".join(f"{v} after {t:.1f} s" for v, t in s["clock_first_named_s"].items()) or "nobody"
        lines.append(
            f"  clock check: injected UTC errors {s['utc_error_ms'] or 'none'}; named inconsistent: {named}; "
            f"{s['clock_statuses_naming']} of {s['clock_statuses']} fleet statuses name someone"
        )
    return "\n".join(lines)


def clock_figures(rec: FlightRecord) -> dict:
    """The fusion node's clock check over the flight: when each vehicle was first named inconsistent (s after the
    simulator's start) and how many fleet statuses named anyone."""
    first: dict[str, float] = {}
    naming = 0
    for t, names, _ in rec.clock_status:
        if names:
            naming += 1
            for v in names:
                first.setdefault(v, t - rec.sim_start_unix_s)
    return {
        "utc_error_ms": dict(rec.utc_error_ms),
        "clock_first_named_s": first,
        "clock_statuses": len(rec.clock_status),
        "clock_statuses_naming": naming,
    }


def save_record(rec: FlightRecord, path) -> None:
    """Everything but the truth (the run's truth files are beside it) as JSON, for :func:`load_record`."""
    data = {k: v for k, v in rec.__dict__.items() if k != "truth"}
    data["frames_rx"] = {v: [[b, t] for b, t in f.items()] for v, f in rec.frames_rx.items()}
    Path(path).write_text(json.dumps(data), encoding="utf-8")


def load_record(run_dir) -> FlightRecord:
    """A run's FlightRecord from its directory (record.json and the truth files)."""
    from groundsim.world.truth import read_truth_csv

    run = Path(run_dir)
    data = json.loads((run / "record.json").read_text(encoding="utf-8"))
    data["frames_rx"] = {v: {int(b): t for b, t in pairs} for v, pairs in data["frames_rx"].items()}
    rec = FlightRecord(truth={v: read_truth_csv(run / f"truth.{v}.csv") for v in VEHICLES})
    for k, v in data.items():
        setattr(rec, k, v)
    return rec


def main_flight(
    scenario: str,
    seeds: int,
    kill_at_s: float | None,
    restart_at_s: float | None,
    out_dir,
    duration_s: float | None = None,
    utc_error_ms: tuple = (),
) -> int:
    """``python -m bench.fleet --flight``: run and print each seed, then the medians over seeds.  With a kill and
    no ``duration_s``, the flight is extended to RESTART_FLIGHT_S past the restart: a daemon's cold start alone
    (imports, MAVLink lock) took 10-14 s on this shared, loaded machine."""
    from bench import machine_speed_ms
    from groundsim.world.scenario import load_scenario, resolve_scenario_path
    from onboard.core.errors import IrtrackError

    try:
        views = load_scenario(resolve_scenario_path(scenario)).observer_views()
    except IrtrackError as exc:
        print(f"--flight {scenario}: {exc}", file=sys.stderr)
        return 2
    if len(views) < len(VEHICLES):
        # refused before the router, two daemons and the fusion are started for a simulator that refuses it
        print(
            f"--flight {scenario}: expected a scenario of {len(VEHICLES)} observers (F1), got {len(views)}",
            file=sys.stderr,
        )
        return 2
    if kill_at_s is not None:
        restart_at_s = kill_at_s + 5.0 if restart_at_s is None else restart_at_s
        if duration_s is None:
            duration_s = max(30.0, restart_at_s + RESTART_FLIGHT_S)
    scores = []
    for seed in range(seeds):
        plan = plan_flight(scenario, seed, Path(out_dir) / f"seed{seed}", duration_s, utc_error_ms)
        print(f"flying {scenario}, seed {seed} (realtime; logs in {plan.out_dir}) ...", flush=True)
        try:
            rec = run_flight(plan, kill_at_s, restart_at_s)
        except FlightError as exc:
            print(f"seed {seed}: failed: {exc}", flush=True)
            continue
        save_record(rec, plan.out_dir / "record.json")
        rec.utc_error_ms = dict(utc_error_ms)
        s = score_flight(rec) | clock_figures(rec)
        scores.append(s)
        print(format_score(s, seed), flush=True)
        print(f"  simulator pacing: {rec.sim_pacing or 'n/a'}", flush=True)
        with open(plan.out_dir / "score.json", "w", encoding="utf-8") as f:
            json.dump(s, f, indent=1)
    if len(scores) > 1:
        med = {k: float(np.nanmedian([s.get(k, math.nan) for s in scores])) for k in ("median_err_ratio",)}
        print(f"over {len(scores)} seeds: median of the median errors {_pct(med['median_err_ratio'])} of range")
    print(f"  {GOALS}")
    load = os.getloadavg()
    print(f"  machine: {os.cpu_count()} cores, load {load[0]:.2f} (shared), speed probe {machine_speed_ms():.0f} ms")
    return 0 if scores else 1
