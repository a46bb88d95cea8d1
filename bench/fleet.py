"""Fleet fusion at scale: N vehicles x R Hz of synthetic lines of sight through one zenoh router.

    python -m bench.fleet [--vehicles 8] [--rate 30] [--seconds 20]
    python -m bench.fleet --accuracy      # the core alone: two drones 200 m apart, a target at ~800 m
    python -m bench.fleet --flight F1 [--seeds N] [--kill-at 15]   # end to end: bench.fleet_flight

This process opens a zenoh router on a free loopback port, N vehicle sessions (one publisher each on
``irtrack/<vehicle>/track``, ``irtrack.track/2`` with ``time_unix_us``) and a subscriber; ``python -m
onboard.fuse`` runs as a child connected to the router.  Every session but the router's is a zenoh
*client* (a config file with ``mode: "client"``): with eclipse-zenoh 1.10, peer-mode sessions that listen
on nothing, connected to a router, did not receive each other's data through it (measured here), which
clients behind a router do.  Every camera period all N vehicles publish the
line of sight of one target (:mod:`groundsim.evaluation.fleet_synth`: a ring of vehicles ~300 m across,
the target ~800 m away, RTK-class errors), paced by the wall clock; the payloads are built before the run.

It prints:

- the fusion's CPU (its process, ``/proc``): CPU seconds per wall second over the publishing window;
- drops: lines of sight published vs taken by the fusion (its ``irtrack/fleet/status``), the rejected by
  reason, and camera periods whose frames never reached a fleet track;
- the period of the first fleet track with every vehicle (a stamped vehicle's lines of sight wait for the clock
  check's verdict, its 20th frame), then latency from the later of a period's frames (the last of the N published) to
  the first fleet track that contains all N of them (every vehicle's newest line of sight at or after that period),
  p50 / p99 / max, over the periods from that first one;
- the machine: cores, load average, and the speed probe of :func:`bench.machine_speed_ms`.

``--accuracy`` runs the core without zenoh (:class:`~onboard.estimation.fleet_tracker.FleetTracker` stepped per
frame): two observers 200 m apart flying straight and level at 12 m/s, a target ~800 m away, 10 s at 30 Hz,
5 seeds, for attitude-bias sigmas of 0.1 deg (the shipped RTK noise case), 0.02 deg and 0: the share of
estimates called observable after the first second, the median error over range, the median reported range
sigma over range and the mean NEES.

Numbers, no assertions (the issue's goals are printed beside them).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from bench import machine_speed_ms
from bench.fleet_flight import open_router
from bench.options import BenchParser, positive_float, positive_int
from groundsim.evaluation.fleet_synth import SynthTarget, SynthVehicle, measure, track_payload
from groundsim.evaluation.proc_cpu import ProcCpu
from groundsim.io.ports import free_tcp_port
from onboard.core.blas import single_thread_blas_env
from onboard.core.frames import GeodeticOrigin
from onboard.io.fleet_wire import fleet_track_key
from onboard.io.zenoh_session import TRACK_ENCODING, ZenohConfig, open_session, track_key

REPO = Path(__file__).resolve().parents[1]
ORIGIN = GeodeticOrigin(32.0, 118.8, 20.0)
GOALS = "goals: fusion <= 0.3 of a core, nothing dropped, latency p99 <= 50 ms on loopback"
START_TIMEOUT_S = 30.0
DRAIN_S = 2.0  # after the last period: time for the last fleet tracks to arrive


def _scene(n: int, rng: np.random.Generator) -> tuple[list[SynthVehicle], SynthTarget]:
    vehicles = []
    for i in range(n):
        a = 2 * math.pi * i / n
        vehicles.append(
            SynthVehicle(
                f"uav{i + 1}",
                (150.0 * math.cos(a), 150.0 * math.sin(a), -100.0 - 5.0 * i),
                (6.0, 0.0, 0.0),
                attitude_error_rad=tuple(rng.normal(0.0, math.radians(0.1), 3)),
            )
        )
    return vehicles, SynthTarget((800.0, 100.0, -150.0), (-5.0, 3.0, 0.5))


def accuracy(seeds: int = 5) -> None:
    """Print the fleet core's accuracy on two straight-and-level observers (module docstring)."""
    from onboard.estimation.fleet import FleetConfig, Ray
    from onboard.estimation.fleet_tracker import FleetTracker
    from onboard.estimation.map_estimator import NoiseModel

    white_rad = math.hypot(0.3 / 764.7, math.radians(0.05))  # 0.3 px on a Vue Pro 640, 0.05 deg attitude noise
    print("two observers 200 m apart, straight and level at 12 m/s; target ~800 m away at 10 m/s; 10 s at 30 Hz")
    for bias_deg in (0.1, 0.02, 0.0):
        errs, observable, ratios, nees = [], [], [], []
        for seed in range(seeds):
            rng = np.random.default_rng(seed)
            bias_rad = math.radians(bias_deg)
            noise = NoiseModel(**{"attitude_bias_sigma_rad": bias_rad, "camera_position_white_sigma_m": 0.02})
            obs = [
                SynthVehicle(
                    name,
                    (0.0, y_m, -100.0),
                    (12.0, 0.0, 0.0),
                    attitude_error_rad=tuple(rng.normal(0.0, bias_rad, 3)),
                )
                for name, y_m in (("uav1", -100.0), ("uav2", 100.0))
            ]
            tgt = SynthTarget((800.0, 50.0, -150.0), (10.0, -3.0, 0.0))
            tracker = FleetTracker(FleetConfig(), noise)
            for k in range(300):
                t = k / 30
                for v in obs:
                    m = measure(v, tgt, t, rng, white_rad, bias_rad, 0.02)
                    tracker.add(Ray(v.name, 1, t, m.p_cam_ned_m, m.los_ned, m.sigma_az_rad, m.sigma_el_rad))
                for tid in tracker.targets:
                    if t > 1.0 and tracker.due(tid) and (est := tracker.solve(tid)) is not None:
                        p = tgt.p_ned_m(est.t_s)
                        d = est.p_ned_m - p
                        errs.append(float(np.linalg.norm(d) / np.linalg.norm(p - obs[0].camera_ned_m(est.t_s))))
                        observable.append(est.observable)
                        ratios.append(est.range_sigma_ratio)
                        nees.append(float(d @ np.linalg.solve(est.cov_p_ned_m2, d)))
        print(
            f"  attitude bias {bias_deg:g} deg: observable {100 * np.mean(observable):.0f} % of {len(errs)} estimates, "
            f"median error {100 * np.median(errs):.2f} % of range, median range sigma {100 * np.median(ratios):.2f} %, "
            f"mean NEES {np.mean(nees):.2f} ({seeds} seeds: one bias draw each)"
        )


def main(argv=None) -> int:
    p = BenchParser(prog="python -m bench.fleet", description=__doc__.split("\n\n")[0])
    p.add_argument("--vehicles", type=positive_int, default=8)
    p.add_argument("--rate", type=positive_float, default=30.0, help="camera rate per vehicle, Hz (30)")
    p.add_argument("--seconds", type=positive_float, default=20.0, help="publishing time (20)")
    p.add_argument("--accuracy", action="store_true", help="the core's accuracy on two observers, no zenoh")
    p.add_argument("--flight", metavar="SCENARIO", help="fly SCENARIO (F1) end to end instead (bench.fleet_flight)")
    p.add_argument("--seeds", type=positive_int, default=1, help="--flight: runs, seeds 0..N-1 (1)")
    p.add_argument("--kill-at", type=float, default=None, metavar="S", help="--flight: SIGKILL uav2's daemon at S s")
    p.add_argument("--restart-at", type=float, default=None, metavar="S", help="--flight: restart it at S s (kill + 5)")
    p.add_argument("--out", default="out/fleet", help="--flight: logs, truth and scores (out/fleet)")
    p.add_argument("--duration", type=positive_float, default=None, help="--flight: flight length, s (the scenario's)")
    p.add_argument(
        "--utc-error",
        action="append",
        default=[],
        metavar="NAME=MS",
        help="--flight: vehicle NAME's SYSTEM_TIME reports UTC MS ms off (groundsim run --utc-error-ms); the fusion's"
        " clock check should name it; repeatable",
    )
    args = p.parse_args(argv)
    if not args.flight and not args.accuracy and int(args.seconds * args.rate) < 1:
        p.error(f"argument --seconds: {args.seconds:g} s at --rate {args.rate:g} Hz is not one camera period")
    if args.flight:
        from bench.fleet_flight import main_flight
        from groundsim.app.run import utc_errors
        from groundsim.world.scenario import load_scenario, resolve_scenario_path
        from onboard.core.errors import ConfigError

        try:  # groundsim run's own parsing of --utc-error-ms, against the scenario's vehicle names
            scenario = load_scenario(resolve_scenario_path(args.flight))
            errors = [(name, us / 1000.0) for name, us in utc_errors(scenario, args.utc_error, "uav1")]
        except ConfigError as exc:
            p.error(str(exc).replace("--utc-error-ms", "--utc-error"))
        return main_flight(
            args.flight, args.seeds, args.kill_at, args.restart_at, args.out, args.duration, tuple(errors)
        )
    if args.accuracy:
        accuracy()
        return 0
    n, rate, seconds = args.vehicles, args.rate, args.seconds
    periods = int(seconds * rate)
    rng = np.random.default_rng(8)
    vehicles, target = _scene(n, rng)
    print(f"building {periods} periods x {n} vehicles of lines of sight ...", flush=True)
    frames = [
        [measure(v, target, k / rate, rng, 0.3e-3, math.radians(0.1), 0.02) for v in vehicles] for k in range(periods)
    ]

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    router = open_router(endpoint, gossip=None)
    tmp = tempfile.TemporaryDirectory(prefix="bench-fleet-")
    client_cfg = os.path.join(tmp.name, "client.json5")
    with open(client_cfg, "w", encoding="utf-8") as f:
        f.write('{mode: "client"}\n')
    sessions = []
    fuse = None
    lock = threading.Lock()
    fleet: list[tuple[float, dict]] = []
    status: list[dict] = []
    try:
        env = single_thread_blas_env(dict(os.environ))
        fuse = subprocess.Popen(
            [sys.executable, "-m", "onboard.fuse", "--zenoh-connect", endpoint, "--zenoh-config", client_cfg]
            + ["--log-level", "WARNING", "--status-interval-s", "0.5"],
            cwd=REPO,
            env=env,
        )
        settings = ZenohConfig(connect=(endpoint,), config_file=client_cfg)
        sub = open_session(settings)
        sessions.append(sub)
        ready = threading.Event()

        def on_fleet(sample) -> None:
            t = time.time()
            with lock:
                fleet.append((t, json.loads(sample.payload.to_bytes())))

        def on_status(sample) -> None:
            with lock:
                status.append(json.loads(sample.payload.to_bytes()))
            ready.set()

        sub.declare_subscriber(fleet_track_key(), on_fleet)
        sub.declare_subscriber("irtrack/fleet/status", on_status)
        pubs = []
        for v in vehicles:
            s = open_session(settings)
            sessions.append(s)
            pubs.append(s.declare_publisher(track_key(v.name), encoding=TRACK_ENCODING))
        if not ready.wait(START_TIMEOUT_S):
            print("bench.fleet: no status from python -m onboard.fuse within 30 s", file=sys.stderr)
            return 1
        t0 = time.time() + 0.5
        payloads = [
            [
                json.dumps(
                    track_payload(v.name, k, int(1e6 + k * 1e6 / rate), los, ORIGIN, int(round((t0 + k / rate) * 1e6)))
                ).encode()
                for v, los in zip(vehicles, row)
            ]
            for k, row in enumerate(frames)
        ]
        cpu = ProcCpu(fuse.pid)
        time.sleep(max(0.0, t0 - time.time()))
        cpu0, w0 = cpu.cpu_s() or 0.0, time.monotonic()
        last_pub = np.zeros(periods)
        for k in range(periods):
            time.sleep(max(0.0, t0 + k / rate - time.time()))
            for pub, payload in zip(pubs, payloads[k]):
                pub.put(payload)
            last_pub[k] = time.time()
        cpu1, w1 = cpu.cpu_s() or 0.0, time.monotonic()
        time.sleep(DRAIN_S)
        with lock:
            received = list(fleet)
            final = status[-1] if status else {}
    finally:
        for s in sessions:
            s.close()
        if fuse is not None:
            fuse.terminate()
            try:
                fuse.wait(timeout=10)
            except subprocess.TimeoutExpired:
                fuse.kill()
                fuse.wait()
        router.close()
        tmp.cleanup()

    # the first fleet track containing every vehicle's frame of period k
    first_s = np.full(periods, np.nan)
    k_start = periods  # the period of the first fleet track with every vehicle: the clock check's verdict before it
    for t_rx, msg in received:
        contrib = msg.get("vehicles") or []
        if len(contrib) < n:
            continue
        newest = min(c["time_unix_us"] for c in contrib) / 1e6
        k_max = int(math.floor((newest - t0) * rate + 1e-3))  # times are whole microseconds: round-off, not a period
        k_start = min(k_start, k_max)
        for k in range(max(0, k_max - 60), min(k_max, periods - 1) + 1):
            if math.isnan(first_s[k]) or t_rx < first_s[k]:
                first_s[k] = t_rx
    # a stamped vehicle's rays wait for the clock check's verdict (its 20th frame): the periods before the first fleet
    # track with every vehicle are that start, said apart, not the fusion's latency
    k_start = min(k_start, periods)
    lat_ms = np.full(periods, np.nan)
    lat_ms[k_start:] = (first_s[k_start:] - last_pub[k_start:]) * 1e3
    ok = lat_ms[np.isfinite(lat_ms)]
    missing = int(np.sum(~np.isfinite(lat_ms[k_start:])))
    observable = sum(1 for _, m in received if m.get("observable"))
    sent = periods * n
    cores = os.cpu_count()
    load = os.getloadavg()
    print(f"bench.fleet: {n} vehicles x {rate:g} Hz for {seconds:g} s through one zenoh router on 127.0.0.1")
    print(f"  fusion CPU: {(cpu1 - cpu0) / (w1 - w0):.3f} of a core ({cpu1 - cpu0:.2f} CPU s over {w1 - w0:.1f} s)")
    print(
        f"  lines of sight: {sent} published, {final.get('rays', '?')} taken by the fusion "
        f"({final.get('received', '?')} tracks received); rejected: {final.get('rejected', {})}; "
        f"events: {final.get('events', {})}"
    )
    never = [int(k) + k_start for k in np.flatnonzero(~np.isfinite(lat_ms[k_start:]))]
    print(
        f"  fleet tracks: {len(received)} received, {observable} observable; the first with all {n} vehicles at "
        f"period {k_start} (the clock check's verdict: {k_start / rate * 1e3:.0f} ms of frames); periods after it "
        f"never in one: {missing} of {periods - k_start} {never[:10]}"
    )
    slowest = [int(k) for k in np.argsort(np.nan_to_num(lat_ms, nan=-1.0))[::-1][:5]]
    print(f"  slowest periods: {slowest} ({', '.join(f'{lat_ms[k]:.0f}' for k in slowest)} ms)")
    if ok.size:
        p50, p99 = np.percentile(ok, [50, 99])
        print(f"  latency, later frame -> fleet track: p50 {p50:.1f} ms, p99 {p99:.1f} ms, max {ok.max():.1f} ms")
    print(f"  {GOALS}")
    print(
        f"  machine: {cores} cores, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} (shared), "
        f"speed probe {machine_speed_ms():.0f} ms"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
