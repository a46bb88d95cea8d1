"""``python -m bench.onboard --scene C1``: the daemon's CPU on a reference scene's flight, in real time.

The flow is ``python -m groundsim demo``'s (:func:`groundsim.evaluation.demo.plan_demo`): the daemon
(``python -m onboard``, its estimator in a worker process as shipped) with the shipped
``config/onboard.yaml`` plus ``imaging.chain`` (``objects`` by default: the chain the scenes need), the
scenario's camera, pod and origin, loopback endpoints; and ``groundsim run --rate realtime`` flying the
scenario (extended to ``duration_s``, its motions continued), rendering its scene at 30 Hz and sending its
telemetry over MAVLink with the scenario's navigation errors (RTK), frames over zenoh.

Timed: from ``SETTLE_S`` after the daemon's first track to its last status message while frames still
arrived.  Printed: CPU seconds per wall second of the daemon's whole process tree (parent + estimator
worker, /proc, as the synthetic latency benchmark reads it) and by thread; the frames it received and
processed in that window (frames/s), so CPU ms per frame and the share of one core it would take at 30 Hz;
from ``WINDOW_FILL_S`` after the first track on (when the run is long enough) the same once its
estimator's window is full.  The simulator's own CPU is printed beside it (it is not the daemon's).

On a shared machine the simulator may fall behind real time (fewer than 30 frames a second reach the
daemon): the "at 30 Hz" figure scales the measured CPU per frame, which assumes the cost per frame does
not depend on the rate.  Numbers only; nothing asserts.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

__all__ = ["SETTLE_S", "WINDOW_FILL_S", "FRAME_RATE_HZ", "window_figures", "bench_scene"]

SETTLE_S = 2.0  # after the first track: rates, TIMESYNC and the chain's first confirmation settle
WINDOW_FILL_S = 20.0  # the estimator's window (config/onboard.yaml estimator.window_s): its CPU grows until full
FRAME_RATE_HZ = 30.0
READY_TIMEOUT_S = 30.0  # the daemon's first status (imports on a loaded machine)


def window_figures(samples: list[tuple], t_from: float) -> dict | None:
    """CPU and frames over the samples from the first at or after ``t_from`` to the last one whose
    frames-in count still grew.  ``samples``: ``(monotonic s, daemon CPU s, CPU s by thread, frames in,
    frames processed)`` in time order.  Returns ``span_s``, ``cpu_s_per_s``, ``frames_in``, ``processed``,
    ``fps`` (processed per s), ``cpu_ms_per_frame``, ``share_at_30hz`` (of one core) and ``by_thread``
    (CPU s per s), or None when the window holds fewer than two samples."""
    first = next((i for i, s in enumerate(samples) if s[0] >= t_from), None)
    if first is None:
        return None
    last = first
    for i in range(first + 1, len(samples)):
        if samples[i][3] > samples[i - 1][3]:
            last = i
    if last == first:
        return None
    a, b = samples[first], samples[last]
    span = b[0] - a[0]
    processed = b[4] - a[4]
    cpu = (b[1] - a[1]) / span
    per_frame_ms = 1e3 * (b[1] - a[1]) / processed if processed else math.nan
    return {
        "span_s": span,
        "cpu_s_per_s": cpu,
        "frames_in": b[3] - a[3],
        "processed": processed,
        "fps": processed / span,
        "cpu_ms_per_frame": per_frame_ms,
        "share_at_30hz": per_frame_ms * FRAME_RATE_HZ / 1e3,
        "by_thread": {k: (v - a[2].get(k, 0.0)) / span for k, v in b[2].items()},
    }


def _print_window(label: str, w: dict | None) -> None:
    if w is None:
        print(f"   {label}: not measured (the run ended first)")
        return
    shown = sorted(((v, k) for k, v in w["by_thread"].items() if v >= 0.002), reverse=True)
    print(
        f"   {label} ({w['span_s']:.0f} s): daemon CPU (parent + estimator worker, /proc) {w['cpu_s_per_s']:.3f} CPU s"
        f" per s; {w['processed']} frames processed of {w['frames_in']} in ({w['fps']:.1f} frames/s):"
        f" {w['cpu_ms_per_frame']:.2f} CPU ms per frame = {w['share_at_30hz']:.3f} of one core at"
        f" {FRAME_RATE_HZ:.0f} Hz (target <= 0.25)"
    )
    print("     by thread, CPU s per s: " + ", ".join(f"{k} {v:.3f}" for v, k in shown))


def bench_scene(scene: str, duration_s: float, cpu_snapshot, chain: str = "objects", seed: int = 0) -> dict:
    """Run the daemon and the simulator on ``scene`` for ``duration_s`` of flight (module docstring) and print
    the figures; returns the windows (:func:`window_figures`, None when not measured).  ``cpu_snapshot(pid)``:
    ``(monotonic s, CPU s of pid's tree, CPU s by thread, wake-ups by thread)``, ``bench.onboard``'s reader."""
    import yaml
    import zenoh  # noqa: F401 - the session below needs it; fail before starting processes

    from bench.scenes3d import onboard_config
    from groundsim.evaluation.demo import child_env, daemon_command, plan_demo, sim_command, stop_process
    from onboard.app.config import config_to_dict
    from onboard.io.zenoh_session import ZenohConfig, open_session, status_key, track_key

    tmp = Path(tempfile.mkdtemp(prefix="irtrack-bench-scene-"))
    daemon = sim = session = None
    try:
        base = tmp / "base.yaml"
        base.write_text(yaml.safe_dump(config_to_dict(onboard_config(None, chain)), sort_keys=False), encoding="utf-8")
        plan = plan_demo(scene, duration_s, seed, tmp / "out", str(base))
        print(
            f"the daemon on {plan.scenario.name} in real time ({plan.duration_s:.0f} s flown by `groundsim run`,"
            f" navigation errors {plan.injected.nav_noise}, imaging.chain {chain}, estimator worker process), 127.0.0.1"
        )
        env = child_env()
        with open(tmp / "daemon.log", "w") as dlog:
            daemon = subprocess.Popen(daemon_command(plan), env=env, stdout=subprocess.DEVNULL, stderr=dlog)
        session = open_session(ZenohConfig(connect=(plan.zenoh_endpoint,)))
        statuses: list[tuple[float, dict]] = []
        tracks: dict = {"n": 0, "position": 0, "first": None, "ids": set(), "states": {}}

        def on_track(sample) -> None:
            j = json.loads(sample.payload.to_bytes())
            tracks["n"] += 1
            tracks["position"] += j.get("ned_m") is not None
            tracks["states"][j.get("state")] = tracks["states"].get(j.get("state"), 0) + 1
            if j.get("track_id") is not None:
                tracks["ids"].add(j["track_id"])
            if tracks["first"] is None:
                tracks["first"] = time.monotonic()

        subs = [
            session.declare_subscriber(track_key(plan.vehicle), on_track),
            session.declare_subscriber(
                status_key(plan.vehicle),
                lambda s: statuses.append((time.monotonic(), json.loads(s.payload.to_bytes()))),
            ),
        ]
        t0 = time.monotonic()
        while not statuses:
            if daemon.poll() is not None or time.monotonic() - t0 > READY_TIMEOUT_S:
                print(f"   the daemon did not start; its log: {(tmp / 'daemon.log').read_text()[-2000:]}")
                return {}
            time.sleep(0.05)
        with open(tmp / "sim.log", "w") as slog:
            sim = subprocess.Popen(sim_command(plan), env=env, stdout=subprocess.DEVNULL, stderr=slog)
        samples: list[tuple] = []
        sim_cpu: list[tuple[float, float]] = []
        seen = 0
        deadline = time.monotonic() + plan.duration_s + 60.0
        while sim.poll() is None and time.monotonic() < deadline:
            if len(statuses) > seen:  # one sample per status message (1 Hz): CPU and the daemon's frame counters
                seen = len(statuses)
                snap = cpu_snapshot(daemon.pid)
                f = statuses[-1][1]["frames"]
                samples.append((snap[0], snap[1], snap[2], int(f["in"]), int(f["processed"])))
                s_snap = cpu_snapshot(sim.pid)
                if math.isfinite(s_snap[1]):
                    sim_cpu.append((s_snap[0], s_snap[1]))
            time.sleep(0.05)
        if daemon.poll() is not None:
            print(f"   the daemon exited ({daemon.returncode}); its log: {(tmp / 'daemon.log').read_text()[-2000:]}")
        if tracks["first"] is None:
            print("   the daemon published no track")
            return {}
        steady_from = tracks["first"] + WINDOW_FILL_S
        windows = {
            "all": window_figures(samples, tracks["first"] + SETTLE_S),
            "steady": window_figures(samples, steady_from) if samples and samples[-1][0] > steady_from + 5 else None,
        }
        last = statuses[-1][1]
        f = last["frames"]
        print(
            f"   {tracks['n']} tracks received ({', '.join(f'{k} {v}' for k, v in tracks['states'].items())};"
            f" {len(tracks['ids'])} track ids), {tracks['position']} with a 3-D position; daemon frames in {f['in']},"
            f" processed {f['processed']}, dropped {f['dropped']}, rejected {f['rejected']};"
            f" median processing {last['processing_ms']['p50']:.2f} ms (status, last 1000 frames)"
        )
        _print_window(f"from {SETTLE_S:.0f} s after the first track", windows["all"])
        _print_window(
            f"steady, from {WINDOW_FILL_S:.0f} s after the first track (estimator window full)", windows["steady"]
        )
        if len(sim_cpu) >= 2:
            print(
                f"   simulator (groundsim run, rendering {plan.scenario.name}; not the daemon's):"
                f" {(sim_cpu[-1][1] - sim_cpu[0][1]) / (sim_cpu[-1][0] - sim_cpu[0][0]):.3f} CPU s per s"
            )
        for s in subs:
            s.undeclare()
        return windows
    finally:
        rc_sim = stop_process(sim, "simulator")
        rc_daemon = stop_process(daemon, "daemon")
        if session is not None:
            session.close()
        if daemon is not None:
            print(f"   simulator exit {rc_sim}, daemon exit {rc_daemon} (SIGTERM)")
        shutil.rmtree(tmp, ignore_errors=True)
