"""Benchmark of the single image chain (``imaging.chain: single``): frames/s of ``TargetTracker.update`` on one core.

The daemon's default chain, ``objects``, is measured on rendered scenes by ``--scene`` (:mod:`bench.imaging_scenes`).

``python -m bench.imaging``  (optionally ``taskset -c 0 python -m bench.imaging``).  OpenCV is
held to one thread (``cv2.setNumThreads(1)``).  Frames are synthetic 640 x 512 mono8 (and one
mono16 case): a sky brightening towards the horizon, a warm Gaussian target that wanders about
the image centre as under a pointing gimbal (+- 25 px, up to ~1.5 px/frame), NETD 1 grey.
300 frames (10 s at 30 Hz) are made before timing.  For each case it prints:

* per-frame wall and CPU ms of ``update`` (mean, p50, p95, max) and frames/s from the CPU mean;
* the centre error against the known truth (rms, max) and the states seen;
* baselines measured in the same run: bare OpenCV KCF ``update`` on the raw frame (the paper's
  chain without detection), and one full-frame detection (the ``searching`` path);
* on frames from the simulator's IR renderer (``groundsim.world.render``, default F450 target and
  FLIR Vue Pro settings, horizon in view) at 100-500 m: states, centre minus the projected body
  centre (mean, std) and the blob's contrast, for mono8 and mono16.

The budget is >= 300 frames/s for the whole onboard single chain, so about 2 ms here.  Numbers only:
nothing asserts on time.
"""

from __future__ import annotations

import math
import sys
import time

import cv2
import numpy as np

from bench import parse_flags, run_benchmark
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
        img[i0 : i0 + 2 * r + 1, j0 : j0 + 2 * r + 1] += amp * np.exp(
            -((xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2) / (2 * sigma_px**2)
        )
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


def _rendered(encoding: str, range_m: float, n: int = 40):
    """Track n rendered frames of a target ``range_m`` ahead, 15 m above a camera at 70 m,
    with a slowly wandering pointing error; return (states, errors (n, 2), last detection)."""
    from groundsim.world.render.raster import IrRenderer, truth_pixel
    from groundsim.world.render.settings import IrSettings
    from onboard.core.frames import R_MOUNT_FROM_CAM, PinholeIntrinsics, quat_from_euler, rotmat_from_quat

    K = PinholeIntrinsics.vue_pro_640()
    renderer = IrRenderer(K, IrSettings(encoding=encoding), seed=1)
    tracker = TargetTracker(ImagingParams())
    states: dict[str, int] = {}
    errs = []
    out = None
    for k in range(n):
        p_cam = np.array([0.0, 0.0, -70.0])
        p_t = np.array([range_m, 2.0 * math.sin(0.1 * k) + 0.03 * k, -85.0])
        d = p_t - p_cam
        yaw = math.atan2(d[1], d[0]) + 0.004 * math.sin(0.3 * k)
        pitch = math.atan2(-d[2], math.hypot(d[0], d[1])) + 0.003 * math.cos(0.2 * k)
        R_nc = rotmat_from_quat(quat_from_euler(0.0, pitch, yaw)) @ R_MOUNT_FROM_CAM
        img = renderer.render(p_cam, R_nc, p_t, rotmat_from_quat(quat_from_euler(0.02, -0.05, 0.3)))
        u, v = truth_pixel(K, p_cam, R_nc, p_t)
        out = tracker.update(img)
        states[out.state.value] = states.get(out.state.value, 0) + 1
        if out.measurement_valid:
            errs.append((out.u_px - u, out.v_px - v))
    return states, np.array(errs).reshape(-1, 2), out.detection if out is not None else None


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
    print(
        f"onboard.imaging benchmark, the single chain (TargetTracker): {N_FRAMES} frames {W_PX}x{H_PX},"
        f" OpenCV {cv2.__version__}, threads {cv2.getNumThreads()}"
    )
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
        print(
            f"  centre error: rms {math.sqrt(float(np.mean(e**2))):.4f} px, max {np.max(e):.4f} px over {err.size} valid frames; states {states}"
        )
        print(f"  KCF re-seeds {tr.kcf_reseeds}, re-acquisitions {tr.reacquisitions}")
        if dtype == np.uint8:
            kcf_ms = _bare_kcf_ms(frames, truth, params)
            full_ms = _full_frame_ms(frames, params)
            print(
                f"  baseline bare KCF update on the raw frame: {kcf_ms:.3f} ms (update / bare KCF = {wall[1:].mean() / kcf_ms:.2f})"
            )
            print(f"  full-frame detect (searching / re-acquisition path): {full_ms:.3f} ms wall")
        print()
    print("frames from groundsim.world.render (F450 quad, default IrSettings, horizon in view), 40 frames each:")
    for encoding in ("mono8", "mono16"):
        for range_m in (100.0, 160.0, 300.0, 500.0):
            states, e, det = _rendered(encoding, range_m)
            err = (
                f"mean ({e[:, 0].mean():+.3f}, {e[:, 1].mean():+.3f}) std ({e[:, 0].std():.3f}, {e[:, 1].std():.3f}) px"
                if len(e)
                else "no valid centre"
            )
            extra = f", contrast {det.contrast:.1f}, snr {det.snr:.0f}" if det is not None else ""
            print(f"  {encoding:6s} {range_m:5.0f} m: {states}; centre - body centre {err}{extra}")


if __name__ == "__main__":
    if "--loop" in sys.argv[1:]:
        from bench.imaging_loop import main as loop_main

        sys.exit(run_benchmark("imaging", lambda: loop_main(sys.argv[1:])))
    if "--scene" in sys.argv[1:]:
        from bench.imaging_scenes import main as scenes_main

        sys.exit(run_benchmark("imaging", lambda: scenes_main(sys.argv[1:])))
    parse_flags(
        "python -m bench.imaging",
        __doc__.splitlines()[0] + "  With no option it runs the synthetic and renderer cases.  '--scene NAME ...'"
        " (bench.imaging_scenes): the chains on rendered scenario frames; '--loop NAME ...' (bench.imaging_loop):"
        " the chain in the closed loop; each has its own --help.",
    )
    sys.exit(run_benchmark("imaging", main))
