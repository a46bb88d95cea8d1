"""Benchmark of the flight recorder (:mod:`onboard.record`): what recording costs per frame.

``python -m bench.record [--frames N] [--compression lz4|zstd|none]``.  Frames are 640 x 512 mono8 with
NETD-like noise (the simulator's noise does not compress much either) at 30 Hz worth of messages:
per frame one RawImage, one frame_input with a pose, one track with a position, three MAVLink datagrams.
Prints:

* the caller's cost (what the daemon's zenoh and pipeline threads pay): the ``on_*`` calls of one
  frame, wall us (median, p99);
* the writer thread's CPU per frame (protobuf/JSON encoding, chunk compression, write: its own
  ``time.thread_time``), and whether it kept up (drops);
* file size per frame and per minute at 30 Hz.

Numbers only: nothing asserts on time.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from onboard.frames import GeodeticOrigin
from onboard.irframe import IrFrame
from onboard.pose import PoseAt, PoseSample
from onboard.record import FlightRecorder, RecordSettings
from onboard.track import Track

ORIGIN = GeodeticOrigin(47.397742, 8.545594, 488.0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.record")
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--compression", default="lz4", choices=("lz4", "zstd", "none"))
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    base = np.clip(np.linspace(60, 140, 512)[:, None] + np.zeros((1, 640)), 0, 255)
    frames = [IrFrame(i, 1_000_000 + i * 33_333, np.clip(base + rng.normal(0, 1.0, base.shape), 0, 255).astype(np.uint8))
              for i in range(min(args.frames, 60))]
    q = np.array([1.0, 0.0, 0.0, 0.0])
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "bench.mcap")
        rec = FlightRecorder(RecordSettings(path, compression=args.compression), vehicle="uav1")
        rec.start()
        dg = bytes(range(60))
        caller_us = []
        c0, w0 = time.process_time(), time.perf_counter()
        for i in range(args.frames):
            fr = frames[i % len(frames)]
            fr = IrFrame(i, 1_000_000 + i * 33_333, fr.pixels)
            pose = PoseAt(PoseSample(fr.time_boot_us, [1.0, 2.0, -50.0], [5.0, 0.0, 0.0], q), [1.0, 2.0, -50.0], q, None,
                          ORIGIN, 20_000, 40_000, None, 0)
            track = Track("uav1", fr.seq, fr.time_boot_us, "tracking", track_id=1, u_px=320.5, v_px=256.5,
                          bbox=(310.0, 246.0, 20.0, 20.0), lat_deg=47.4, lon_deg=8.55, alt_m=600.0,
                          p_ned_m=(100.0, 50.0, -100.0), v_ned_mps=(5.0, 0.0, 0.0), cov_p_ned_m2=np.eye(3), range_m=150.0,
                          origin=ORIGIN)
            t0 = time.perf_counter_ns()
            for _ in range(3):
                rec.on_mavlink(dg, "autopilot", ("127.0.0.1", 14540))
            rec.on_frame(fr, t0)
            rec.on_frame_input(fr, t0, True, pose)
            rec.on_track(track, None)
            caller_us.append((time.perf_counter_ns() - t0) / 1e3)
            time.sleep(max(0.0, (i + 1) / 30.0 - (time.perf_counter() - w0)))  # 30 Hz, as a camera
        rec.close(30.0)
        cpu_s = time.process_time() - c0
        wall_s = time.perf_counter() - w0
        size = os.path.getsize(path)
    caller = np.array(caller_us)
    writer_ms = rec.writer_cpu_s / args.frames * 1e3
    print(f"recorder, {args.frames} frames 640x512 mono8 at 30 Hz, compression {args.compression}, load {os.getloadavg()[0]:.1f}")
    print(f"  callers (on_* of one frame): median {np.median(caller):.1f} us, p99 {np.percentile(caller, 99):.1f} us")
    print(f"  writer thread CPU per frame: {writer_ms:.2f} ms (thread_time; whole process {cpu_s:.2f} CPU s over "
          f"{wall_s:.1f} s wall, making the test messages included); dropped {rec.dropped}, write errors {rec.write_errors}")
    print(f"  file: {size / args.frames / 1e3:.0f} kB per frame, {size / args.frames * 30 * 60 / 1e6:.0f} MB per minute at 30 Hz")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
