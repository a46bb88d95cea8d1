"""Benchmark of groundsim.world.render: frames/s of the IR rasteriser on one core.

``python -m bench.render``.  Renders 640 x 512 frames (FLIR Vue Pro 640 intrinsics) of a default
F450-class target in view, with NETD noise (40 mK) and optics blur (0.6 px) on, and prints ms/frame
(mean, median, p95, max), frames/s and the breakdown (background, target ROI, noise + quantise) for:

* moving: observer attitude changes every frame (background recomputed each frame), target at
  60-250 m moving across the image: the realistic case;
* static camera (background reused, target moving), mono16, and close range (target ~35 px wide);
* baselines measured in the same run: a fresh per-frame normal draw + full-frame Gaussian blur +
  numpy round/clip (what the noise bank and the LUT-side blur avoid), and the renderer's setup.

The process is pinned to one CPU and OpenCV to one thread, so the numbers are single-core; both
wall time and this process's CPU time are printed (on a shared machine the wall time includes
waiting for the CPU).
Numbers only: nothing here asserts on time.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np

from bench import pin_to_one_cpu

N_FRAMES = 300
WARMUP_FRAMES = 10


def _scenario(n: int, range_m: tuple[float, float], wobble_rad: float, seed: int = 7, static_camera: bool = False):
    """Per-frame (p_cam, R_ned_from_cam, p_target, R_ned_from_target, ground_d) with the target in view."""
    from onboard.core.frames import CameraMount, camera_pose_ned, quat_from_euler, rotmat_from_quat

    rng = np.random.default_rng(seed)
    mount = CameraMount.from_euler_deg((0.1, 0.0, 0.05), pitch_deg=-5.0)
    intr_half_fov = (0.3, 0.25)  # rad, a margin inside 45 x 37 deg
    frames = []
    for k in range(n):
        t = k / 30.0
        tc = 0.0 if static_camera else t
        p_body = np.array([4.0 * tc, 1.0 * tc, -100.0 - 0.5 * tc])
        roll = wobble_rad * math.sin(2.1 * tc)
        pitch = math.radians(3.0) + wobble_rad * math.sin(1.3 * tc + 0.4)
        yaw = 0.2 * tc
        q_body = quat_from_euler(roll, pitch, yaw)
        p_cam, q_cam = camera_pose_ned(p_body, q_body, mount)
        R_nc = rotmat_from_quat(q_cam)
        rng_m = range_m[0] + (range_m[1] - range_m[0]) * (0.5 + 0.5 * math.sin(0.7 * t))
        x = intr_half_fov[0] * math.sin(0.9 * t)
        y = intr_half_fov[1] * math.sin(0.5 * t + 1.0)
        b = np.array([x, y, 1.0]) / math.sqrt(x * x + y * y + 1.0)
        p_t = p_cam + R_nc @ b * rng_m
        R_nt = rotmat_from_quat(quat_from_euler(*(0.2 * rng.standard_normal(2)), 0.5 * t))
        frames.append((p_cam, R_nc, p_t, R_nt, 0.0))
    return frames


def _run(renderer, frames) -> dict[str, np.ndarray]:
    for f in frames[:WARMUP_FRAMES]:
        renderer.render(*f)
    total, cpu, bg, tgt, nq, roi, ss, reused = [], [], [], [], [], [], [], []
    for f in frames:
        c0, t0 = time.process_time(), time.perf_counter()
        renderer.render(*f)
        total.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
        tm = renderer.last_timing
        bg.append(tm.background_ms)
        tgt.append(tm.target_ms)
        nq.append(tm.noise_quantise_ms)
        roi.append(tm.target_roi_px)
        ss.append(tm.supersample)
        reused.append(tm.background_reused)
    return {
        k: np.asarray(v, dtype=float)
        for k, v in dict(total=total, cpu=cpu, bg=bg, tgt=tgt, nq=nq, roi=roi, ss=ss, reused=reused).items()
    }


def _report(name: str, r: dict[str, np.ndarray]) -> None:
    t = r["total"]
    print(
        f"{name:<44s} {t.mean():6.2f} {np.median(t):6.2f} {np.percentile(t, 95):6.2f} {t.max():6.2f}"
        f" {r['cpu'].mean():6.2f} {1e3 / t.mean():6.0f} fps | bg {r['bg'].mean():5.2f} target {r['tgt'].mean():5.2f}"
        f" noise+q {r['nq'].mean():5.2f} | ROI {r['roi'].mean():5.0f} px, ss {r['ss'].mean():4.1f},"
        f" bg reused {100 * r['reused'].mean():3.0f} %"
    )


def main() -> None:
    pinned = pin_to_one_cpu("not pinned (no sched_setaffinity)")
    import cv2

    cv2.setNumThreads(1)
    from dataclasses import replace

    from groundsim.world.render import IrRenderer, IrSettings
    from onboard.core.frames import PinholeIntrinsics

    intr = PinholeIntrinsics.vue_pro_640()
    base = IrSettings()
    print(
        f"groundsim.world.render benchmark: {intr.width_px} x {intr.height_px}, {N_FRAMES} frames per case, "
        f"{pinned}, cv2 threads {cv2.getNumThreads()}"
    )
    print(
        f"NETD {base.netd_k * 1e3:.0f} mK, blur sigma {base.blur_sigma_px} px, supersample <= {base.supersample},"
        f" target rays <= {base.max_target_rays}"
    )

    t0 = time.perf_counter()
    renderer = IrRenderer(intr, base, seed=1)
    setup_ms = (time.perf_counter() - t0) * 1e3
    print(
        f"renderer setup (rays, sky table, noise bank): {setup_ms:.1f} ms; noise sigma "
        f"{renderer.noise_sigma_grey:.3f} grey"
    )
    print(
        f"{'case':<44s} {'mean':>6s} {'median':>6s} {'p95':>6s} {'max':>6s} {'cpu':>6s}  (ms/frame: wall, and"
        " CPU time of this process; breakdown = wall means)"
    )

    moving = _scenario(N_FRAMES, (60.0, 250.0), wobble_rad=0.02)
    r_moving = _run(renderer, moving)
    _report("mono8, moving camera + target 60-250 m", r_moving)

    static = _scenario(N_FRAMES, (60.0, 250.0), wobble_rad=0.02, static_camera=True)
    _report("mono8, static camera (bg reused)", _run(IrRenderer(intr, base, seed=1), static))
    _report(
        "mono16, moving camera + target 60-250 m",
        _run(IrRenderer(intr, replace(base, encoding="mono16"), seed=1), moving),
    )
    _report(
        "mono8, moving, close target 10-14 m",
        _run(IrRenderer(intr, base, seed=1), _scenario(N_FRAMES, (10.0, 14.0), 0.02)),
    )
    _report(
        "mono8, moving, no noise no blur",
        _run(IrRenderer(intr, replace(base, netd_k=0.0, blur_sigma_px=0.0), seed=1), moving),
    )

    # baseline: what a straightforward full-frame pipeline spends per frame on the steps avoided here
    rng = np.random.default_rng(0)
    img = np.full((intr.height_px, intr.width_px), 100.0, dtype=np.float32)
    times = []
    for _ in range(100):
        t0 = time.perf_counter()
        x = img + rng.standard_normal(img.shape, dtype=np.float32) * np.float32(0.155)
        x = cv2.GaussianBlur(x, (5, 5), 0.6)
        np.clip(np.rint(x), 0, 255).astype(np.uint8)
        times.append((time.perf_counter() - t0) * 1e3)
    naive = float(np.mean(times))
    ours = float(r_moving["nq"].mean())
    print(
        f"baseline full-frame normal draw + blur + round/clip: {naive:.2f} ms/frame vs noise bank + fused "
        f"add/quantise {ours:.2f} ms/frame (x{naive / max(ours, 1e-9):.1f})"
    )
    print(
        f"budget check: 125 fps = 8.00 ms/frame; moving case mean {r_moving['total'].mean():.2f} ms wall "
        f"({1e3 / r_moving['total'].mean():.0f} fps), {r_moving['cpu'].mean():.2f} ms CPU "
        f"({1e3 / r_moving['cpu'].mean():.0f} fps)"
    )
    print(
        f"load average {' '.join(f'{x:.1f}' for x in os.getloadavg())} on {os.cpu_count()} CPUs "
        "(wall times grow with other load; CPU time less so)"
    )


if __name__ == "__main__":
    main()
