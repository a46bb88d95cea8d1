"""Benchmark of the onboard image chain: frames/s of ``TargetTracker.update`` on one core.

``python -m bench.imaging``  (optionally ``taskset -c 0 python -m bench.imaging``).  OpenCV is
held to one thread (``cv2.setNumThreads(1)``).  Frames are synthetic 640 x 512 mono8 (and one
mono16 case): a sky brightening towards the horizon, a warm Gaussian target that wanders about
the image centre as under a pointing gimbal (+- 25 px, up to ~1.5 px/frame), NETD 1 grey.
300 frames (10 s at 30 Hz) are made before timing.  For each case it prints:

* per-frame wall and CPU ms of ``update`` (mean, p50, p95, max) and frames/s from the CPU mean;
* the centre error against the known truth (rms, max) and the states seen;
* baselines measured in the same run: bare OpenCV KCF ``update`` on the raw frame (the paper's
  chain without detection), and one full-frame detection (the ``searching`` path).

The budget is >= 300 frames/s for the whole onboard chain, so about 2 ms here.  Numbers only:
nothing asserts on time.
"""

from __future__ import annotations

import math
import time

import cv2
import numpy as np

from onboard.imaging import ImagingParams, TargetTracker, detect_targets
from onboard.imaging.tracker import create_kcf

H_PX, W_PX = 512, 640
N_FRAMES = 300
BUDGET_MS = 1000.0 / 300.0


def _sky() -> np.ndarray:
    yy, xx = np.mgrid[0:H_PX, 0:W_PX].astype(np.float64)
    return 60.0 + 40.0 * yy / H_PX + 4.0 * (xx / W_PX - 0.5) ** 2


def _truth(n: int) -> np.ndarray:
    k = np.arange(n, dtype=np.float64)
    u = 320.0 + 25.0 * np.sin(2 * math.pi * k / 210.0) + 8.0 * np.sin(2 * math.pi * k / 90.0)
    v = 256.0 + 20.0 * np.sin(2 * math.pi * k / 150.0 + 1.0)
    return np.stack([u, v], axis=1)


def _frames(truth: np.ndarray, amp: float, sigma_px: float, dtype, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    sky = _sky()
    r = int(math.ceil(5 * sigma_px)) + 2
    out = []
    for u, v in truth:
        img = sky + rng.normal(0.0, 1.0, sky.shape)
        i0, j0 = int(v) - r, int(u) - r
        yy, xx = np.mgrid[i0 : i0 + 2 * r + 1, j0 : j0 + 2 * r + 1].astype(np.float64)
        img[i0 : i0 + 2 * r + 1, j0 : j0 + 2 * r + 1] += amp * np.exp(-((xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2) / (2 * sigma_px**2))
        if dtype == np.uint16:
            img *= 257.0
        out.append(np.clip(np.round(img), 0, np.iinfo(dtype).max).astype(dtype))
    return out


def _stats(ms: np.ndarray) -> str:
    return f"mean {ms.mean():6.3f}  p50 {np.percentile(ms, 50):6.3f}  p95 {np.percentile(ms, 95):6.3f}  max {ms.max():6.3f} ms"


def _run_tracker(frames, truth, params):
    tr = TargetTracker(params)
    wall, cpu, err, states = [], [], [], {}
    for f, (u, v) in zip(frames, truth):
        c0, w0 = time.process_time(), time.perf_counter()
        out = tr.update(f)
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
        states[out.state.value] = states.get(out.state.value, 0) + 1
        if out.measurement_valid:
            err.append(math.hypot(out.u_px - u, out.v_px - v))
    return np.array(wall) * 1e3, np.array(cpu) * 1e3, np.array(err), states, tr


def _bare_kcf_ms(frames, truth, params) -> float:
    kcf = create_kcf(params)
    side = params.kcf_box_px
    u, v = truth[0]
    kcf.init(frames[0], (int(u - side / 2), int(v - side / 2), side, side))
    t0 = time.perf_counter()
    for f in frames[1:]:
        kcf.update(f)
    return (time.perf_counter() - t0) / (len(frames) - 1) * 1e3


def _full_frame_ms(frames, params, n: int = 30) -> float:
    t0 = time.perf_counter()
    for f in frames[:n]:
        detect_targets(f, params)
    return (time.perf_counter() - t0) / n * 1e3


def main() -> None:
    cv2.setNumThreads(1)
    params = ImagingParams()
    truth = _truth(N_FRAMES)
    cases = [
        ("mono8, small target (sigma 0.7 px, 60 grey)", 60.0, 0.7, np.uint8),
        ("mono8, medium target (sigma 1.5 px, 80 grey)", 80.0, 1.5, np.uint8),
        ("mono8, large target (sigma 4 px, 120 grey)", 120.0, 4.0, np.uint8),
        ("mono16, medium target (sigma 1.5 px, 80 grey8)", 80.0, 1.5, np.uint16),
    ]
    print(f"onboard.imaging benchmark: {N_FRAMES} frames {W_PX}x{H_PX}, OpenCV {cv2.__version__}, threads {cv2.getNumThreads()}")
    print(f"budget: {BUDGET_MS:.2f} ms/frame for the whole onboard chain (>= 300 frames/s)\n")
    for name, amp, sigma, dtype in cases:
        frames = _frames(truth, amp, sigma, dtype)
        wall, cpu, err, states, tr = _run_tracker(frames, truth, params)
        steady = cpu[1:]  # frame 0 is the full-frame search
        print(name)
        print(f"  update wall : {_stats(wall[1:])}")
        print(f"  update cpu  : {_stats(steady)}  -> {1000.0 / steady.mean():7.0f} frames/s")
        print(f"  first frame (searching, full frame): {cpu[0]:.3f} ms cpu")
        e = err if err.size else np.array([np.nan])
        print(f"  centre error: rms {math.sqrt(float(np.mean(e**2))):.4f} px, max {np.max(e):.4f} px over {err.size} valid frames; states {states}")
        print(f"  KCF re-seeds {tr.kcf_reseeds}, re-acquisitions {tr.reacquisitions}")
        if dtype == np.uint8:
            kcf_ms = _bare_kcf_ms(frames, truth, params)
            full_ms = _full_frame_ms(frames, params)
            print(f"  baseline bare KCF update on the raw frame: {kcf_ms:.3f} ms (update / bare KCF = {wall[1:].mean() / kcf_ms:.2f})")
            print(f"  full-frame detect (searching / re-acquisition path): {full_ms:.3f} ms wall")
        print()


if __name__ == "__main__":
    main()
