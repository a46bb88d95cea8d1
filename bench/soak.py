"""Soak: the daemon and the simulator on loopback for N minutes; memory slope and dropped frames.

    python -m bench.soak --minutes 30 [--scenario H1] [--interval 10] [--out out/soak] [--kill-worker-at S]

Not part of CI (the goal: "a 30-minute soak shows RSS slope <= 0.1 MB/min and 0 frames dropped at
30 Hz").  The pair is planned as ``python -m groundsim demo`` plans it (:func:`groundsim.evaluation.demo.plan_demo`:
the scenario's camera, loopback MAVLink and zenoh ports, the shipped onboard config otherwise), with
the scenario extended to the soak's length: H1 by default, a circling observer and a figure-eight
target, periodic, so it can fly for hours.  The simulator runs in real time (30 Hz frames, 50 / 25 Hz
telemetry).

Every ``--interval`` seconds it samples, from ``/proc``, the resident memory (RSS) and the
proportional set size (PSS: shared pages divided among the processes sharing them, so the sum is
not inflated by the pages the estimator worker shares with its fork server) of the daemon and each
of its descendants (the estimator's fork server and worker), and reads the daemon's
``irtrack.status/1`` (frames in / processed / dropped / rejected).  At the end it prints the samples,
the least-squares slope in MB/min of each total after ``--warmup`` seconds, the peaks against the
768 MB container limit (deploy/compose.yaml), and the frame counters.  Numbers are printed, never
asserted.  Exit 0 when both children ran to the end, 1 otherwise.  Children are stopped by their
PIDs (SIGTERM, then SIGKILL after 5 s).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from bench import run_benchmark
from groundsim.evaluation.proc_cpu import children_by_parent

CONTAINER_LIMIT_MB = 768.0  # deploy/compose.yaml, service onboard
FRAME_RATE_HZ = 30.0
STOP_GRACE_S = 5.0
KB_PER_MB = 1024.0


def process_tree(pid: int) -> list[tuple[int, str]]:
    """``pid`` and all its live descendants, each with what it is (a forked child shows its parent's
    command line, so an estimator worker is recognised as the fork server's child)."""
    kids = children_by_parent()
    out, frontier = [], [(pid, None)]
    while frontier:
        p, parent_kind = frontier.pop()
        kind = "estimator worker" if parent_kind == "forkserver" else describe(p)
        out.append((p, kind))
        frontier += [(c, kind) for c in kids.get(p, [])]
    return out


def memory_kb(pid: int) -> tuple[int, int] | None:
    """(RSS, PSS) of ``pid`` in kB, None when it is gone."""
    try:
        fields = {}
        with open(f"/proc/{pid}/smaps_rollup", encoding="ascii") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key in ("Rss", "Pss"):
                    fields[key] = int(value.split()[0])
        return fields["Rss"], fields["Pss"]
    except (OSError, KeyError, ValueError):
        return None


def describe(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            args = f.read().split(b"\0")
    except OSError:
        return "?"
    text = " ".join(a.decode(errors="replace") for a in args if a)
    if "forkserver" in text:
        return "forkserver"
    if "resource_tracker" in text:
        return "resource_tracker"
    if "-m onboard" in text:
        return "daemon"
    if "spawn_main" in text:
        return "estimator worker"  # a spawned one (estimator.worker process before the fork server)
    return text[:40]


def slope_per_min(t_s: list[float], y: list[float]) -> float:
    """Least-squares slope of ``y`` against ``t_s`` in units per minute (nan for < 2 points)."""
    n = len(t_s)
    if n < 2:
        return float("nan")
    mt, my = sum(t_s) / n, sum(y) / n
    var = sum((t - mt) ** 2 for t in t_s)
    if var == 0:
        return float("nan")
    return 60.0 * sum((t - mt) * (v - my) for t, v in zip(t_s, y)) / var


class StatusReader:
    """The daemon's newest ``irtrack.status/1`` through a zenoh client on its loopback listener."""

    def __init__(self, endpoint: str, vehicle: str) -> None:
        import zenoh

        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"client"')
        cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
        cfg.insert_json5("scouting/multicast/enabled", "false")
        self._lock = threading.Lock()
        self.latest: dict | None = None
        self.session = zenoh.open(cfg)
        self.sub = self.session.declare_subscriber(f"irtrack/{vehicle}/status", self._on)
        self.tracks: list[tuple[float, bool]] = []  # (arrival, monotonic s; has a 3-D position)
        self.track_sub = self.session.declare_subscriber(f"irtrack/{vehicle}/track", self._on_track)

    def _on_json(self, sample, keep) -> None:
        """``keep(message)`` under the lock, for a sample that is JSON (others are ignored)."""
        try:
            message = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        with self._lock:
            keep(message)

    def _on_track(self, sample) -> None:
        self._on_json(sample, lambda track: self.tracks.append((time.monotonic(), track.get("ned_m") is not None)))

    def _on(self, sample) -> None:
        self._on_json(sample, lambda status: setattr(self, "latest", status))

    def get(self) -> dict | None:
        with self._lock:
            return self.latest

    def gap_after(self, t_kill: float, horizon_s: float = 10.0) -> tuple[float, int, int]:
        """After ``t_kill`` (monotonic s): the longest time between two consecutive tracks with a 3-D
        position (s, counted from the last one before ``t_kill``), tracks without one, tracks in all."""
        with self._lock:
            tracks = list(self.tracks)
        before = [t for t, has in tracks if has and t < t_kill]
        after = [(t, has) for t, has in tracks if t_kill <= t < t_kill + horizon_s]
        last = before[-1] if before else t_kill
        gap, missing = 0.0, 0
        for t, has in after:
            if has:
                gap = max(gap, t - last)
                last = t
            else:
                missing += 1
        if after and not after[-1][1]:
            gap = max(gap, after[-1][0] - last)
        return gap, missing, len(after)

    def episodes(self, t0: float) -> list[tuple[float, float]]:
        """Stretches of consecutive tracks without a 3-D position: (start s after ``t0``, length s)."""
        with self._lock:
            tracks = list(self.tracks)
        out, start = [], None
        for t, has in tracks:
            if not has and start is None:
                start = t
            elif has and start is not None:
                out.append((start - t0, t - start))
                start = None
        return out

    def close(self) -> None:
        self.track_sub.undeclare()
        self.sub.undeclare()
        self.session.close()


def _connect(plan, daemon: subprocess.Popen, timeout_s: float = 60.0) -> StatusReader:
    """A :class:`StatusReader` once the daemon listens (retried every 0.5 s, bounded)."""
    import zenoh

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return StatusReader(plan.zenoh_endpoint, plan.vehicle)
        except zenoh.ZError:
            if daemon.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(
                    f"the daemon (exit {daemon.poll()}) never listened on {plan.zenoh_endpoint}"
                ) from None
            time.sleep(0.5)


def _stop(proc: subprocess.Popen, name: str) -> int | None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            print(f"{name} (pid {proc.pid}) did not stop in {STOP_GRACE_S:g} s: SIGKILL", flush=True)
            proc.kill()
            proc.wait(STOP_GRACE_S)
    return proc.returncode


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.soak", description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=30.0, help="soak length (default 30)")
    ap.add_argument(
        "--scenario", default="H1", help="scenario name or file, extended to the soak's length (default H1)"
    )
    ap.add_argument("--interval", type=float, default=10.0, help="seconds between memory samples (default 10)")
    ap.add_argument("--warmup", type=float, default=60.0, help="seconds left out of the slope (default 60)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/soak", help="directory for the children's logs and configs")
    ap.add_argument(
        "--kill-worker-at",
        type=float,
        action="append",
        default=[],
        metavar="S",
        help="SIGKILL the estimator worker S seconds in and print the 3-D output gap (repeatable)",
    )
    args = ap.parse_args(argv)
    if not args.minutes > 0 or not args.interval > 0:
        ap.error("--minutes and --interval must be positive")

    from groundsim.evaluation.demo import daemon_command, plan_demo, sim_command

    duration_s = args.minutes * 60.0
    plan = plan_demo(args.scenario, duration_s + 15.0, args.seed, args.out, None)
    if plan.duration_s < duration_s:
        print(
            f"scenario {args.scenario} cannot fly {duration_s:g} s (only {plan.duration_s:g} s): choose another",
            flush=True,
        )
        return 1
    out = Path(args.out)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    print(
        f"soak: {args.minutes:g} min, scenario {plan.scenario.name} (extended), seed {args.seed}, sampling every "
        f"{args.interval:g} s; load average at start {os.getloadavg()[0]:.2f}; logs in {out}/",
        flush=True,
    )
    with open(out / "daemon.log", "w") as dlog, open(out / "sim.log", "w") as slog:
        daemon = subprocess.Popen(daemon_command(plan), stdout=dlog, stderr=subprocess.STDOUT, env=env)
        sim = None
        reader = None
        samples: list[tuple[float, dict[str, tuple[int, int]], dict | None]] = []
        elapsed, final, gaps, episodes = 0.0, None, [], []
        try:
            reader = _connect(plan, daemon)  # the daemon's listener is up
            sim = subprocess.Popen(sim_command(plan), stdout=slog, stderr=subprocess.STDOUT, env=env)
            t0 = time.monotonic()
            next_t = t0
            kills = sorted(args.kill_worker_at)
            killed: list[tuple[float, int]] = []
            print(
                f"{'t_s':>7} {'daemon RSS':>10} {'workers RSS':>11} {'total RSS':>9} {'total PSS':>9} "
                f"{'frames in':>9} {'dropped':>7} {'rejected':>8}  (MB)",
                flush=True,
            )
            while True:
                now = time.monotonic()
                if now >= next_t:
                    mem = {}
                    for pid, kind in process_tree(daemon.pid):
                        m = memory_kb(pid)
                        if m is not None:
                            mem[f"{kind}:{pid}"] = m
                    st = reader.get()
                    samples.append((now - t0, mem, st))
                    d_rss = sum(v[0] for k, v in mem.items() if k.startswith("daemon")) / KB_PER_MB
                    w_rss = sum(v[0] for k, v in mem.items() if not k.startswith("daemon")) / KB_PER_MB
                    fr = (st or {}).get("frames", {})
                    print(
                        f"{now - t0:7.0f} {d_rss:10.1f} {w_rss:11.1f} {sum(v[0] for v in mem.values()) / KB_PER_MB:9.1f} "
                        f"{sum(v[1] for v in mem.values()) / KB_PER_MB:9.1f} {fr.get('in', '-'):>9} "
                        f"{fr.get('dropped', '-'):>7} {fr.get('rejected', '-'):>8}",
                        flush=True,
                    )
                    next_t += args.interval
                if kills and now - t0 >= kills[0]:
                    kills.pop(0)
                    workers = [p for p, kind in process_tree(daemon.pid) if kind == "estimator worker"]
                    for pid in workers:
                        os.kill(pid, signal.SIGKILL)
                        killed.append((time.monotonic(), pid))
                        print(f"{now - t0:7.0f} SIGKILL estimator worker pid {pid}", flush=True)
                    if not workers:
                        print(f"{now - t0:7.0f} no estimator worker to kill", flush=True)
                if now - t0 >= duration_s or daemon.poll() is not None or sim.poll() is not None:
                    break
                time.sleep(min(0.5, max(next_t - time.monotonic(), 0.0)))
            elapsed = time.monotonic() - t0
            time.sleep(1.5)  # one more status after the last frames
            final = reader.get()
            gaps = [(pid, *reader.gap_after(t_kill), *reader.gap_after(t_kill - 10.0)) for t_kill, pid in killed]
            episodes = reader.episodes(t0)
            with open(out / "tracks.csv", "w") as f:  # arrival (s from the start), has a 3-D position; kills marked
                f.write("t_s,has_position\n")
                f.writelines(f"{t - t0:.4f},{int(has)}\n" for t, has in list(reader.tracks))
                f.writelines(f"{t - t0:.4f},kill\n" for t, _pid in killed)
        finally:
            if reader is not None:
                reader.close()
            sim_rc = _stop(sim, "simulator") if sim is not None else None
            daemon_alive = daemon.poll() is None
            daemon_rc = _stop(daemon, "daemon")

    print(
        f"\nran {elapsed:.0f} s; daemon {'stopped by us, exit ' if daemon_alive else 'DIED before the end, exit '}"
        f"{daemon_rc}; simulator exit {sim_rc}; load average at end {os.getloadavg()[0]:.2f}"
    )
    kept = [s for s in samples if s[0] >= args.warmup] or samples
    t = [s[0] for s in kept]
    for label, pick, idx in (
        ("total RSS (daemon + descendants)", lambda k: True, 0),
        ("total PSS (daemon + descendants)", lambda k: True, 1),
        ("daemon RSS", lambda k: k.startswith("daemon"), 0),
        ("estimator worker(s) + fork server RSS", lambda k: not k.startswith("daemon"), 0),
    ):
        y = [sum(v[idx] for k, v in s[1].items() if pick(k)) / KB_PER_MB for s in kept]
        peak = max(sum(v[idx] for k, v in s[1].items() if pick(k)) / KB_PER_MB for s in samples)
        print(
            f"{label:40s}: slope {slope_per_min(t, y):+.3f} MB/min after {args.warmup:g} s "
            f"({y[0]:.1f} -> {y[-1]:.1f} MB), peak {peak:.1f} MB = {100 * peak / CONTAINER_LIMIT_MB:.0f} % "
            f"of the {CONTAINER_LIMIT_MB:g} MB container limit"
        )
    last_mem = samples[-1][1] if samples else {}
    for k, (rss, pss) in sorted(last_mem.items()):
        print(f"  last sample {k:28s} RSS {rss / KB_PER_MB:7.1f} MB  PSS {pss / KB_PER_MB:7.1f} MB")
    for pid, gap, missing, n, gap0, missing0, n0 in gaps:
        print(
            f"killed worker {pid}: longest time without a 3-D position in the track stream {gap:.2f} s "
            f"(30 Hz: {1 / FRAME_RATE_HZ:.3f} s between frames); {missing} of the next {n} tracks without one; "
            f"the 10 s before the kill: {gap0:.2f} s, {missing0} of {n0}"
        )
    if episodes:
        print(
            f"stretches of tracks without a 3-D position (start s, length s): {len(episodes)}; "
            + ", ".join(f"{a:.1f}+{d:.2f}" for a, d in episodes[:40])
            + (" ..." if len(episodes) > 40 else "")
        )
    fr = (final or {}).get("frames", {})
    expected = int(elapsed * FRAME_RATE_HZ)
    print(
        f"frames: ~{expected} sent at {FRAME_RATE_HZ:g} Hz; daemon in {fr.get('in')}, processed {fr.get('processed')}, "
        f"dropped (queue) {fr.get('dropped')}, rejected {fr.get('rejected')}, tracks published {fr.get('published')}"
    )
    rej = (final or {}).get("rejected") or {}
    if rej:
        print("rejected/counted by reason: " + ", ".join(f"{k} {v}" for k, v in sorted(rej.items())))
    return 0 if daemon_alive and elapsed >= duration_s - args.interval else 1


if __name__ == "__main__":
    sys.exit(run_benchmark("soak", main, kept="the samples printed above and the children's logs in --out are kept"))
