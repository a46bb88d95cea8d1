"""Benchmark of ``groundsim run``: real-time factor at ``--rate max`` and pacing jitter at ``--rate realtime``.

``python -m bench.simrate [--scenario P1] [--duration 10] [--modes max,realtime] [--rt-priority N]``.  In process, on
127.0.0.1 only: the simulator publishes its frames to a zenoh subscriber in this process (a
listening session it connects to) and its MAVLink to a UDP socket drained by a thread, so both
emit paths run for real.  Prints:

* ``--rate max``: set-up (JSBSim vehicles, renderer, first frame), loop wall time, real-time
  factor of the loop (``sim_s / loop wall s``) and end to end (set-up included), process CPU
  seconds of the loop, mean ms per frame of flight / render / publish / MAVLink / truth, frames
  received;
* baseline in the same run: the same frames flown and rendered with no sockets and no truth file
  (``SimCore.frame`` in a tight loop), and the loop's cost relative to it;
* ``--rate realtime``: frame-period jitter ``|interval between publications - 1/30 s|`` p50 / p99 /
  max and lateness behind the deadlines, over the scenario; with ``--rt-priority N`` a second
  realtime run at SCHED_FIFO priority N (``groundsim run --rt-priority``), for comparison.

The machine's load average is printed with the numbers: on a shared machine the wall-clock
figures move with it.  Numbers only: nothing here asserts on time.
"""

from __future__ import annotations

import logging
import os
import socket
import sys
import threading
import time

import cv2

from bench import run_benchmark
from bench.options import BenchParser, choices_list, int_between, known_scenario, positive_float
from groundsim.app.cli import realtime_priority
from groundsim.app.run import RateSpec, RunConfig, run
from groundsim.io.ports import free_tcp_port
from groundsim.world.scenario import load_scenario, resolve_scenario_path
from groundsim.world.sim import SimCore
from onboard.io.zenoh_session import ZenohConfig, frame_key, open_session

MODES = ("max", "realtime")  # --modes: the run's RateSpec (as groundsim run --rate)


def _load() -> str:
    try:
        return "load average {:.2f} {:.2f} {:.2f} on {} CPUs".format(*os.getloadavg(), os.cpu_count() or 0)
    except OSError:  # pragma: no cover - not on Linux
        return "load average unknown"


class _Receivers:
    """A zenoh subscriber (frames) and a UDP drain (MAVLink datagrams) on 127.0.0.1."""

    def __init__(self, vehicle: str = "uav1") -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.session = open_session(ZenohConfig(listen=(self.endpoint,)))
        self.frames = 0
        self.sub = self.session.declare_subscriber(frame_key(vehicle), self._on_frame)
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.udp.bind(("127.0.0.1", 0))
        self.udp.settimeout(0.05)
        self.mavlink = f"udpout:127.0.0.1:{self.udp.getsockname()[1]}"
        self.datagrams = 0
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._drain, daemon=True)
        self._thread.start()

    def _on_frame(self, sample) -> None:
        self.frames += 1

    def _drain(self) -> None:
        while not self._done.is_set():
            try:
                self.udp.recv(65536)
                self.datagrams += 1
            except OSError:
                pass

    def reset(self) -> None:
        self.frames = 0
        self.datagrams = 0

    def close(self) -> None:
        self._done.set()
        self._thread.join(1.0)
        self.udp.close()
        self.sub.undeclare()
        self.session.close()


def _run(scenario, duration_s: float, rate: str, rx: _Receivers):
    config = RunConfig(
        scenario,
        duration_s=duration_s,
        rate=RateSpec.parse(rate),
        mavlink=rx.mavlink,
        zenoh=ZenohConfig(connect=(rx.endpoint,), connect_timeout_s=5.0),
    )
    rx.reset()
    c0, w0 = time.process_time(), time.perf_counter()
    report = run(config)
    cpu_s, wall_s = time.process_time() - c0, time.perf_counter() - w0
    time.sleep(0.3)  # frames in flight
    return report, cpu_s, wall_s


def _baseline(scenario, duration_s: float) -> tuple[float, float, int]:
    """Fly + render + truth rows of every frame, no sockets: (set-up s, loop s, frames)."""
    core = SimCore(scenario, 0, duration_s, flight_chunk_s=1.0)
    t0 = time.perf_counter()
    core.frame(0)
    t1 = time.perf_counter()
    for k in range(1, core.frame_count):
        core.frame(k)
    return t1 - t0, time.perf_counter() - t1, core.frame_count


def _realtime(sc, duration_s: float, rx: _Receivers, label: str) -> None:
    rep, cpu_s, _ = _run(sc, duration_s, "realtime", rx)
    j = rep.jitter
    print(
        f"--rate realtime ({label}): {rep.frames} frames in {rep.wall_s:.2f} s (rt x{rep.rt_factor:.3f}),"
        f" CPU {cpu_s:.2f} s; frames received {rx.frames}; per frame ms: "
        + ", ".join(f"{k} {v:.2f}" for k, v in rep.per_frame_ms.items())
        + f"; {_load()}"
    )
    if j is not None:
        print(
            f"             frame-period jitter p50 {j.jitter_p50_ms:.3f} ms, p99 {j.jitter_p99_ms:.3f} ms,"
            f" max {j.jitter_max_ms:.3f} ms; lateness p50 {j.late_p50_ms:.3f} ms, p99 {j.late_p99_ms:.3f} ms,"
            f" max {j.late_max_ms:.3f} ms"
        )


def main(argv=None) -> None:
    ap = BenchParser(prog="python -m bench.simrate", description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", type=known_scenario, default="P1")
    ap.add_argument("--duration", type=positive_float, default=10.0)
    ap.add_argument(
        "--modes",
        type=choices_list(lambda: MODES, "mode"),
        default=list(MODES),
        help="comma-separated: max, realtime (default: both)",
    )
    ap.add_argument(
        "--rt-priority",
        type=int_between(1, 99),  # SCHED_FIFO's priorities (groundsim.app.cli.realtime_priority)
        default=None,
        metavar="N",
        help="also run realtime at SCHED_FIFO priority N (as groundsim run --rt-priority)",
    )
    args = ap.parse_args(argv)
    modes = set(args.modes)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    cv2.setNumThreads(1)  # as the CLI does (groundsim.app.cli)
    sc = load_scenario(resolve_scenario_path(args.scenario))
    print(
        f"bench.simrate: scenario {sc.name}, {args.duration:g} s, {sc.frame_rate_hz:g} Hz, "
        f"{sc.camera.intrinsics.width_px} x {sc.camera.intrinsics.height_px} {sc.ir.encoding}; {_load()}"
    )

    rx = _Receivers()
    try:
        if "max" in modes:
            rep, cpu_s, wall_s = _run(sc, args.duration, "max", rx)
            pf = rep.per_frame_ms
            print(
                f"--rate max:  set-up {rep.setup_s:.2f} s, loop {rep.wall_s:.2f} s for {rep.sim_s:.2f} s simulated:"
                f" real-time factor x{rep.rt_factor:.2f} (loop), x{rep.sim_s / (rep.setup_s + rep.wall_s):.2f} with set-up,"
                f" x{rep.sim_s / wall_s:.2f} with socket opening too"
            )
            print(
                f"             process CPU {cpu_s:.2f} s (all threads); per frame ms: "
                + ", ".join(f"{k} {v:.2f}" for k, v in pf.items())
                + f"; frames received {rx.frames}/{rep.frames}, MAVLink datagrams {rx.datagrams}; {_load()}"
            )
            b_setup, b_loop, n = _baseline(sc, args.duration)
            print(
                f"baseline (fly + render + truth rows, no sockets): set-up {b_setup:.2f} s, loop {b_loop:.2f} s"
                f" ({1e3 * b_loop / max(n - 1, 1):.2f} ms/frame, x{args.duration / b_loop:.2f} real time);"
                f" --rate max loop / baseline loop = {rep.wall_s / b_loop:.2f}"
            )
        if "realtime" in modes:
            _realtime(sc, args.duration, rx, "normal priority")
            if args.rt_priority is not None:
                realtime_priority(args.rt_priority, True)
                try:
                    _realtime(sc, args.duration, rx, f"SCHED_FIFO {args.rt_priority}")
                finally:
                    if hasattr(os, "sched_setscheduler"):
                        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    finally:
        rx.close()


if __name__ == "__main__":
    sys.exit(run_benchmark("simrate", main))
