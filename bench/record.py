"""Benchmark of the flight recorder (:mod:`onboard.io.record`): what recording costs per frame.

``python -m bench.record [--frames N] [--compression none|lz4|zstd] [--sync-mb MB] [--dir DIR] [--chain objects|single]``.  Frames are 640 x 512 mono8 with
NETD-like noise (the simulator's noise does not compress much either) at 30 Hz worth of messages:
per frame one RawImage, one frame_input with a pose, one track with a position, three MAVLink datagrams and, as
the default objects image chain has the daemon record them, the pose the chain used and an objects message of
three objects with its annotations (``--chain single``: without those two).
Prints:

* the caller's cost (what the daemon's zenoh and pipeline threads pay): the ``on_*`` calls of one
  frame, CPU us of the calling thread (``time.thread_time``: the machine is shared, wall time would measure
  the neighbours) and wall us (median, p99);
* the writer thread's CPU per frame (protobuf/JSON encoding, chunk compression, write: its own
  ``time.thread_time``; user and kernel from ``/proc/self/task/<tid>/stat``, 10 ms ticks), and whether it
  kept up (drops);
* the recording's cost per frame: callers' CPU + writer CPU (the budget: 0.5 ms);
* file size per frame and per minute at 30 Hz.

``--replay FILE.mcap``: instead, replay speed (``onboard.app.replay`` at ``--rate max``) on a recording: load time, then
three replays in one process (the first pays the lazy imports of the estimator's scipy modules), wall and CPU s,
x real time, the estimator's own CPU per second of flight (``time.thread_time`` around its calls) and the speed it
bounds replay to (lockstep: every frame's estimate before the next frame), a replay without the estimator, and
where the loop's time goes (cProfile cumulative on a last run): the pipeline (its estimator, its imaging and
tracker) and replay's own decoding, poses and JSON.

Numbers only: nothing asserts on time.
"""

from __future__ import annotations

from onboard.core.blas import single_thread_blas_env

single_thread_blas_env()  # before numpy: one BLAS thread, as python -m onboard.replay

import argparse  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from bench import run_benchmark  # noqa: E402
from bench.options import BenchParser, existing_file, nonnegative_number, positive_int, writable_dir  # noqa: E402
from onboard.core.frames import GeodeticOrigin  # noqa: E402
from onboard.core.irframe import IrFrame  # noqa: E402
from onboard.core.pose_types import PoseAt, PoseSample  # noqa: E402
from onboard.core.track import Track, track_to_bytes  # noqa: E402
from onboard.io.record import FlightRecorder, RecordConfig  # noqa: E402

ORIGIN = GeodeticOrigin(47.397742, 8.545594, 488.0)


def _objects_message(frame: IrFrame) -> dict:
    """An ``irtrack.objects/1`` message of three confirmed objects, the first the primary (as the objects chain's)."""
    objects = [
        {
            "id": k + 1,
            "state": "confirmed",
            "u_px": 320.5 + 60.0 * k,
            "v_px": 256.5 - 20.0 * k,
            "box_px": [317.5 + 60.0 * k, 253.5 - 20.0 * k, 6.0, 6.0],
            "los_ned": [0.8, 0.5, -0.3316625],
            "los_sigma_rad": 0.0013,
            "score": 4.2,
            "primary": k == 0,
        }
        for k in range(3)
    ]
    return {
        "schema": "irtrack.objects/1",
        "time_boot_us": int(frame.time_boot_us),
        "time_unix_us": None,
        "time_unix_sigma_us": None,
        "compensated_us": 0,
        "frame_index": int(frame.seq),
        "primary_id": 1,
        "objects": objects,
    }


def main(argv=None) -> int:
    ap = BenchParser(prog="python -m bench.record")
    ap.add_argument("--frames", type=positive_int, default=600)
    ap.add_argument("--compression", default="none", choices=("none", "lz4", "zstd"))
    ap.add_argument("--sync-mb", type=nonnegative_number, default=8.0, help="record.sync_mb (0: never sync/drop pages)")
    ap.add_argument(
        "--dir", type=writable_dir, default=None, help="where the file goes (default: a temporary directory)"
    )
    ap.add_argument(
        "--replay", type=existing_file, metavar="FILE.mcap", help="measure replay speed on this recording instead"
    )
    ap.add_argument(
        "--chain",
        default="objects",
        choices=("objects", "single"),
        help="the image chain whose messages the daemon records (default objects, the daemon's default)",
    )
    args = ap.parse_args(argv)
    if args.replay:
        return bench_replay(args.replay, ap)
    rng = np.random.default_rng(0)
    base = np.clip(np.linspace(60, 140, 512)[:, None] + np.zeros((1, 640)), 0, 255)
    frames = [
        IrFrame(i, 1_000_000 + i * 33_333, np.clip(base + rng.normal(0, 1.0, base.shape), 0, 255).astype(np.uint8))
        for i in range(min(args.frames, 60))
    ]
    q = np.array([1.0, 0.0, 0.0, 0.0])
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        path = os.path.join(d, "bench.mcap")
        rec = FlightRecorder(
            RecordConfig(path=path, compression=args.compression, sync_mb=args.sync_mb), vehicle="uav1"
        )
        rec.start()
        dg = bytes(range(60))
        caller_us, caller_cpu_us = [], []
        c0, w0 = time.process_time(), time.perf_counter()
        for i in range(args.frames):
            fr = frames[i % len(frames)]
            fr = IrFrame(i, 1_000_000 + i * 33_333, fr.pixels)
            pose = PoseAt(
                PoseSample(fr.time_boot_us, [1.0, 2.0, -50.0], [5.0, 0.0, 0.0], q),
                [1.0, 2.0, -50.0],
                q,
                None,
                ORIGIN,
                20_000,
                40_000,
                None,
                0,
            )
            track = Track(
                "uav1",
                fr.seq,
                fr.time_boot_us,
                "tracking",
                track_id=1,
                u_px=320.5,
                v_px=256.5,
                bbox=(310.0, 246.0, 20.0, 20.0),
                lat_deg=47.4,
                lon_deg=8.55,
                alt_m=600.0,
                p_ned_m=(100.0, 50.0, -100.0),
                v_ned_mps=(5.0, 0.0, 0.0),
                cov_p_ned_m2=np.eye(3),
                range_m=150.0,
                origin=ORIGIN,
            )
            payload = track_to_bytes(track)  # the daemon hands the recorder the bytes it published
            t0, c0_ns = time.perf_counter_ns(), time.thread_time_ns()
            for _ in range(3):
                rec.on_mavlink(dg, "autopilot", ("127.0.0.1", 14540))
            rec.on_frame(fr, t0)
            if args.chain == "objects":
                rec.on_frame_input(fr, t0, True, pose, imaging_pose=pose)
                rec.on_objects(_objects_message(fr), fr.seq)
            else:
                rec.on_frame_input(fr, t0, True, pose)
            rec.on_track(track, payload)
            caller_cpu_us.append((time.thread_time_ns() - c0_ns) / 1e3)
            caller_us.append((time.perf_counter_ns() - t0) / 1e3)
            if i == args.frames - 1:
                user_s, sys_s = _thread_times(rec)  # before close: the thread is gone after it
            time.sleep(max(0.0, (i + 1) / 30.0 - (time.perf_counter() - w0)))  # 30 Hz, as a camera
        rec.close(30.0)
        cpu_s = time.process_time() - c0
        wall_s = time.perf_counter() - w0
        size = os.path.getsize(path)
    caller, caller_cpu = np.array(caller_us), np.array(caller_cpu_us)
    writer_ms = rec.writer_cpu_s / args.frames * 1e3
    total_ms = writer_ms + caller_cpu.mean() / 1e3
    print(
        f"recorder, {args.frames} frames 640x512 mono8 at 30 Hz, {args.chain} chain's messages,"
        f" compression {args.compression}, sync every "
        f"{args.sync_mb:g} MB ({rec.syncs} syncs), load {os.getloadavg()[0]:.1f}"
    )
    print(
        f"  callers (on_* of one frame): CPU mean {caller_cpu.mean():.1f} us (thread_time), wall median "
        f"{np.median(caller):.1f} us, p99 {np.percentile(caller, 99):.1f} us"
    )
    split = (
        f"; user {user_s / args.frames * 1e3:.2f} + kernel {sys_s / args.frames * 1e3:.2f} ms by /proc ticks"
        if user_s is not None
        else ""
    )
    print(
        f"  writer thread CPU per frame: {writer_ms:.2f} ms (thread_time{split}; whole process {cpu_s:.2f} CPU s over "
        f"{wall_s:.1f} s wall, making the test messages included); dropped {rec.dropped}, write errors {rec.write_errors}"
    )
    print(f"  recording per frame, callers + writer: {total_ms:.2f} ms of one core (budget 0.5 ms)")
    print(
        f"  file: {size / args.frames / 1e3:.0f} kB per frame, {size / args.frames * 30 * 60 / 1e6:.0f} MB per minute at 30 Hz"
    )
    return 0


def _thread_times(rec) -> tuple[float | None, float | None]:
    """User and kernel CPU s of the recorder's writer thread so far (Linux ``/proc``; None elsewhere)."""
    try:
        with open(f"/proc/self/task/{rec._thread.native_id}/stat") as f:
            fields = f.read().rpartition(")")[2].split()
        tick = os.sysconf("SC_CLK_TCK")
        return int(fields[11]) / tick, int(fields[12]) / tick  # utime, stime (fields 14, 15 of stat(5))
    except (OSError, AttributeError, ValueError, IndexError):
        return None, None


class _TimedEstimator:
    """The pipeline's estimator with the CPU time of its calls summed (``time.thread_time``)."""

    def __init__(self, inner) -> None:
        self.inner, self.cpu_s = inner, 0.0

    def _timed(self, name, *args, **kwargs):
        c0 = time.thread_time()
        try:
            return getattr(self.inner, name)(*args, **kwargs)
        finally:
            self.cpu_s += time.thread_time() - c0

    def add(self, *args, **kwargs):
        return self._timed("add", *args, **kwargs)

    def predict(self, *args, **kwargs):
        return self._timed("predict", *args, **kwargs)

    def reset(self):
        return self._timed("reset")

    def __getattr__(self, name):
        return getattr(self.inner, name)


def bench_replay(path: str, ap: argparse.ArgumentParser) -> int:
    """Replay speed on the recording ``path``; one that cannot be read or holds no frame is refused by
    ``ap`` (a usage mistake: ``--replay``), before anything is measured."""
    import cProfile
    import logging
    import pstats

    import onboard.pipeline.frame_pipeline as fp
    from onboard.app.replay import config_of, load_recording, replay
    from onboard.core.errors import IrtrackError

    logging.disable(logging.WARNING)
    t0 = time.perf_counter()
    try:
        rec = load_recording(path)
    except IrtrackError as exc:  # names the file and what is wrong with it
        ap.error(f"argument --replay: {exc}")
    if not rec.inputs:
        ap.error(f"argument --replay: {path}: no irtrack.frame_input messages: nothing to replay")
    cfg = config_of(rec)
    print(
        f"replay of {path}: {len(rec.inputs)} frames; load {time.perf_counter() - t0:.2f} s; load {os.getloadavg()[0]:.1f}"
    )
    timed: list = []
    make = fp.make_estimator
    fp.make_estimator = lambda config: timed.append(_TimedEstimator(make(config))) or timed[-1]
    try:
        for i in range(3):
            c0 = time.process_time()
            r = replay(rec, cfg)
            cpu = time.process_time() - c0
            est = timed[-1].cpu_s
            print(
                f"  run {i + 1}{' (cold: lazy imports)' if i == 0 else ''}: {r.wall_s:.2f} s wall, {cpu:.2f} CPU s for "
                f"{r.flight_s:.1f} s of flight: x{r.speed_x:.1f} real time (x{r.flight_s / max(cpu, 1e-9):.1f} per CPU s); "
                f"estimator {est:.2f} CPU s = {est / r.flight_s:.3f} s per s of flight, {est / max(cpu, 1e-9) * 100:.0f} % "
                f"-> bound x{r.flight_s / max(est, 1e-9):.1f} with everything else free; the rest "
                f"{(cpu - est) / max(r.frames_fed, 1) * 1e3:.2f} ms per frame"
            )
    finally:
        fp.make_estimator = make
    c0 = time.process_time()
    r = replay(rec, config_of(rec, overrides={"estimator.enabled": (False, "bench")}))
    cpu = time.process_time() - c0
    print(f"  without the estimator (2-D only): {r.wall_s:.2f} s wall, {cpu:.2f} CPU s: x{r.speed_x:.1f} real time")
    pr = cProfile.Profile()
    pr.enable()
    replay(rec, cfg)
    pr.disable()
    st = pstats.Stats(pr).stats

    def cum(name: str, where: str) -> float:  # cumulative time of the functions ``name`` in files ``where``
        return sum(v[3] for k, v in st.items() if k[2] == name and where in k[0])

    total, process = cum("replay", "onboard/app/replay"), cum("process", "onboard/pipeline")
    est, trk = cum("_estimate", "onboard/pipeline"), cum("update", "onboard/imaging/tracker")
    print(
        f"  where the time goes (cProfile cumulative, of the replay loop): pipeline {process / total * 100:.0f} % "
        f"(estimator {est / total * 100:.0f} %, tracker {trk / total * 100:.0f} %, rest of the pipeline "
        f"{(process - est - trk) / total * 100:.0f} %), replay's own decoding/poses/JSON {(total - process) / total * 100:.0f} %"
    )
    return 0


if __name__ == "__main__":
    sys.exit(run_benchmark("record", main, kept="the figures printed above are kept; the recording was temporary"))
