"""Benchmark of groundsim.world.render: frames/s of the IR rasteriser on one core.

``python -m bench.render``.  Renders 640 x 512 frames (FLIR Vue Pro 640 intrinsics) of a default
F450-class target in view, with NETD noise (40 mK) and optics blur (0.6 px) on, and prints ms/frame
(mean, median, p95, max), frames/s and the breakdown (background, target ROI, noise + quantise) for:

* moving: observer attitude changes every frame (background recomputed each frame), target at
  60-250 m moving across the image: the realistic case;
* static camera (background reused, target moving), mono16, and close range (target ~35 px wide);
* baselines measured in the same run: a fresh per-frame normal draw + full-frame Gaussian blur +
  numpy round/clip (what the noise bank and the LUT-side blur avoid), and the renderer's setup;
* scene content (``groundsim.world.render.scene``) and the camera model (``sensor``), moving camera:
  clouds, terrain, clouds + terrain + sensor (AGC, FPN, FFC, vignetting), the same with distractors
  (5 birds, an aircraft, a glint), each through ``SceneContent.render`` and ``Sensor.apply`` (or
  ``IrRenderer.quantise`` without the sensor);
* clutter: a plain point detector (``groundsim.world.render.clutter``: 15 x 15 local mean, 5 sigma of the
  temporal noise, blobs <= 50 px) on mono16 frames without a target: false point-like objects per
  frame on the clean sky, under clouds and over terrain;
* the reference scenes C1-C5 (``config/scenarios/C*.yaml``): their own scene and camera model, along
  their own flown camera, target(s) and distractors, through ``SceneContent.render`` and
  ``Sensor.apply`` (or ``IrRenderer.quantise``) -- the renderer's share of ``groundsim run`` on them
  (the flight is flown beforehand, outside the timing).  ``python -m bench.render --reference-scenes``
  runs only these; ``--reference-scenes --stages`` also prints where each scene's time goes (CPU ms per
  frame: texture look-ups (remap), cv2.pyrUp, sky and ground, the whole background, objects, quantise or
  camera model).

The process is pinned to one CPU and OpenCV to one thread, so the numbers are single-core; both
wall time and this process's CPU time are printed (on a shared machine the wall time includes
waiting for the CPU).
Numbers only: nothing here asserts on time.
"""

from __future__ import annotations

import math
import os
import sys
import time

import numpy as np

from bench import parse_flags, pin_to_one_cpu, run_benchmark

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
        f"{'scene case':<47s} {'mean':>6s} {'median':>6s} {'p95':>6s} {'max':>6s} {'cpu':>6s}  (ms/frame; scene.render +"
        " sensor.apply or quantise; budget 250 fps = 4.00 ms)"
    )
    scene_cases(intr, base)
    clutter_counts(intr, base)
    reference_scene_cases()
    print(
        f"load average {' '.join(f'{x:.1f}' for x in os.getloadavg())} on {os.cpu_count()} CPUs "
        "(wall times grow with other load; CPU time less so)"
    )


SCENE_FRAMES = 150
SCENE_CONFIGS = {
    "clouds": {"clouds": {"enabled": True}},
    "terrain": {"terrain": {"enabled": True}},
    "clouds + terrain + sensor": {
        "clouds": {"enabled": True},
        "terrain": {"enabled": True},
        "sensor": {
            "enabled": True,
            "agc": {"enabled": True},
            "fpn": {"enabled": True},
            "ffc": {"enabled": True, "period_s": 20.0, "first_s": 2.0},
            "vignetting": {"enabled": True},
        },
    },
}
DISTRACTORS = {
    "birds": {"count": 5, "center_ned_m": [150.0, 30.0, -100.0], "spread_m": 60.0},
    "aircraft": [{"p0_ned_m": [3000.0, -400.0, -600.0]}],
    "glints": [{"p_ned_m": [400.0, 120.0, 0.0]}],
}


def _scene_poses(n: int, height_m: float, pitch_deg: float, target_range_m: float = 150.0):
    """Per-frame (t_s, p_cam, R_ned_from_cam, p_target, R_ned_from_target) of a camera moving and turning."""
    from onboard.core.frames import CameraMount, camera_pose_ned, quat_from_euler, rotmat_from_quat

    mount = CameraMount.from_euler_deg((0.1, 0.0, 0.05), pitch_deg=pitch_deg)
    out = []
    for k in range(n):
        t = k / 30.0
        p_body = np.array([6.0 * t, 2.0 * t, -height_m])
        q_body = quat_from_euler(0.02 * math.sin(2.1 * t), 0.02 * math.sin(1.3 * t + 0.4), 0.2 * t)
        p_cam, q_cam = camera_pose_ned(p_body, q_body, mount)
        R_nc = rotmat_from_quat(q_cam)
        b = np.array([0.2 * math.sin(0.9 * t), 0.15 * math.sin(0.5 * t + 1.0), 1.0])
        p_t = p_cam + R_nc @ (b / np.linalg.norm(b)) * target_range_m
        out.append((t, p_cam, R_nc, p_t, rotmat_from_quat(quat_from_euler(0.1, -0.05, 0.5 * t))))
    return out


def _run_scene(scene, renderer, sensor, poses, ground_d_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(wall ms, CPU ms) per frame of scene.render + sensor.apply (or renderer.quantise); a pose is
    ``(t, p_cam, R_nc, p_t, R_nt)``, then whatever else scene.render takes after ``ground_d_m``."""
    wall, cpu = [], []
    for k, (t, p_cam, R_nc, p_t, R_nt, *rest) in enumerate(poses):
        c0, t0 = time.process_time(), time.perf_counter()
        frame = scene.render(t, p_cam, R_nc, p_t, R_nt, ground_d_m, *rest)
        if sensor is not None:
            sensor.apply(frame.radiance, t, k)
        else:
            renderer.quantise(frame.radiance)
        if k >= WARMUP_FRAMES:
            wall.append((time.perf_counter() - t0) * 1e3)
            cpu.append((time.process_time() - c0) * 1e3)
    return np.asarray(wall), np.asarray(cpu)


def scene_cases(intr, base) -> None:
    """Frames/s of the scene content and the camera model, moving camera, target in view."""
    from groundsim.world.render import IrRenderer
    from groundsim.world.render.scene import SceneContent
    from groundsim.world.render.scene_config import scene_config_from_dict
    from groundsim.world.render.sensor import Sensor

    geometry = {"clouds": (100.0, 8.0), "terrain": (200.0, -30.0), "clouds + terrain + sensor": (120.0, -4.0)}
    for name, raw in [*SCENE_CONFIGS.items(), ("clouds + terrain + sensor + distractors", None)]:
        if raw is None:
            raw = {**SCENE_CONFIGS["clouds + terrain + sensor"], "distractors": DISTRACTORS}
            height, pitch = geometry["clouds + terrain + sensor"]
        else:
            height, pitch = geometry[name]
        cfg = scene_config_from_dict(raw)
        renderer = IrRenderer(intr, base, seed=1)
        t0 = time.perf_counter()
        scene = SceneContent.from_config(cfg, renderer, seed=1)
        sensor = Sensor(cfg.sensor, intr, base, seed=1) if cfg.sensor.enabled else None
        setup_s = time.perf_counter() - t0
        wall, cpu = _run_scene(scene, renderer, sensor, _scene_poses(SCENE_FRAMES + WARMUP_FRAMES, height, pitch))
        print(
            f"scene: {name:<40s} {wall.mean():6.2f} {np.median(wall):6.2f} {np.percentile(wall, 95):6.2f}"
            f" {wall.max():6.2f} {cpu.mean():6.2f} {1e3 / wall.mean():6.0f} fps wall, {1e3 / cpu.mean():4.0f} fps CPU"
            f" | h {height:.0f} m, pitch {pitch:+.0f} deg, setup {setup_s:.1f} s"
        )


def clutter_counts(intr, base, n_frames: int = 20) -> dict[str, float]:
    """Mean false point-like detections per frame (no target) on the clean sky, under clouds, over terrain."""
    from dataclasses import replace

    from groundsim.world.render import IrRenderer
    from groundsim.world.render.clutter import point_detections
    from groundsim.world.render.scene import SceneContent
    from groundsim.world.render.scene_config import scene_config_from_dict

    ir16 = replace(base, encoding="mono16")
    cases = {
        "clean sky": ({}, 100.0, 8.0),
        "clouds": (SCENE_CONFIGS["clouds"], 100.0, 8.0),
        "terrain": (SCENE_CONFIGS["terrain"], 200.0, -30.0),
    }
    out = {}
    for name, (raw, height, pitch) in cases.items():
        renderer = IrRenderer(intr, ir16, seed=2)
        scene = SceneContent.from_config(scene_config_from_dict(raw), renderer, seed=2)
        counts = []
        for t, p_cam, R_nc, _, _ in _scene_poses(n_frames, height, pitch):
            img = renderer.quantise(scene.render(t, p_cam, R_nc, None, None, 0.0).radiance)
            counts.append(len(point_detections(img, renderer.noise_sigma_grey)))
        out[name] = float(np.mean(counts))
        print(
            f"clutter: {name:<10s} {out[name]:6.1f} false point-like objects per frame"
            f" (min {min(counts)}, max {max(counts)}, {n_frames} frames; h {height:.0f} m, pitch {pitch:+.0f} deg)"
        )
    return out


REFERENCE_SCENES = ("C1", "C2", "C3", "C4", "C5")
REFERENCE_FRAMES = 150


def reference_scenes_main() -> None:
    """``python -m bench.render --reference-scenes``: only the reference scenes, one core."""
    pin_to_one_cpu("not pinned (no sched_setaffinity)")
    import cv2

    cv2.setNumThreads(1)
    reference_scene_cases(stages="--stages" in sys.argv[1:])


STAGES = (
    "remap",
    "cv2.pyrUp",
    "sky/ground",
    "background",
    "objects",
    "quantise/camera",
)


class _StageClock:
    """CPU time per stage of the reference scenes' frames (``--stages``): the texture look-ups (every
    ``cv2.remap`` call, the terrain's, and ``kernels.remap_pair``, the clouds'), every ``cv2.pyrUp`` call
    (the cloud weights' second step is inside the compositing kernel), the renderer's sky and ground
    (``IrRenderer.base_radiance`` or ``base_radiance_and_copy``), the whole background with clouds and terrain
    (``SceneContent.render_background``, the kernels and the sky included), the objects
    (``SceneContent.draw_objects``: ray casting, occlusion, labels) and the noise and quantisation or the
    camera model.  Wraps those functions while it is active (the wrappers add ~1 us a call)."""

    def __init__(self) -> None:
        self.ms = dict.fromkeys(STAGES, 0.0)
        self._saved: list[tuple[object, str, object]] = []

    def _wrap(self, owner, name: str, stage: str) -> None:
        f = getattr(owner, name)
        ms = self.ms

        def timed(*a, **k):
            c0 = time.process_time()
            try:
                return f(*a, **k)
            finally:
                ms[stage] += (time.process_time() - c0) * 1e3

        self._saved.append((owner, name, f))
        setattr(owner, name, timed)

    def __enter__(self) -> _StageClock:
        import cv2

        from groundsim.world.render import IrRenderer, scene
        from groundsim.world.render.scene import SceneContent
        from groundsim.world.render.sensor import Sensor

        for owner, name, stage in (
            (cv2, "remap", "remap"),
            (scene, "remap_pair", "remap"),
            (cv2, "pyrUp", "cv2.pyrUp"),
            (IrRenderer, "base_radiance", "sky/ground"),
            (IrRenderer, "base_radiance_and_copy", "sky/ground"),
            (SceneContent, "render_background", "background"),
            (SceneContent, "background_and_copy", "background"),
            (SceneContent, "draw_objects", "objects"),
            (IrRenderer, "quantise", "quantise/camera"),
            (Sensor, "apply", "quantise/camera"),
        ):
            self._wrap(owner, name, stage)
        return self

    def __exit__(self, *exc) -> None:
        for owner, name, f in reversed(self._saved):
            setattr(owner, name, f)
        self._saved.clear()


def reference_scene_cases(n_frames: int = REFERENCE_FRAMES, stages: bool = False) -> None:
    """Frames/s of the renderer on the reference scenes C1-C5, along each scenario's flown poses; with
    ``stages`` (``--stages``) also the CPU ms per frame of each stage (:class:`_StageClock`)."""
    from groundsim.world.scenario import load_scenario, scenarios_dir
    from groundsim.world.sim import GROUND_D_M, SimCore
    from onboard.core.frames import rotmat_from_quat

    print(
        f"{'reference scene':<47s} {'mean':>6s} {'median':>6s} {'p95':>6s} {'max':>6s} {'cpu':>6s}  (ms/frame; scene.render +"
        " sensor.apply or quantise, the scenario's own poses; budget 250 fps = 4.00 ms)"
    )
    for name in REFERENCE_SCENES:
        sc = load_scenario(scenarios_dir() / f"{name}.yaml")
        core = SimCore(sc, 0, duration_s=min(sc.duration_s, (n_frames + WARMUP_FRAMES) / sc.frame_rate_hz))
        t0 = time.perf_counter()
        scene, sensor = core.scene()
        setup_s = time.perf_counter() - t0
        poses = []
        for k in range(core.frame_count):
            i = k * core.ticks_per_frame
            c = core.flight.chunk_of(i)
            j = i - c.i0
            others = core.other_targets_at(i)
            poses.append(
                (
                    float(c.t_s[j]),
                    c.cam_p_ned_m[j].copy(),
                    rotmat_from_quat(c.cam_q_ned_from_cam[j]),
                    c.tgt_p_ned_m[j].copy(),
                    rotmat_from_quat(c.tgt_q_ned_from_body[j]),
                    others,
                )
            )
        wall, cpu = _run_scene(scene, core.renderer(), sensor, poses, GROUND_D_M)
        print(
            f"{name}: {sc.description[:42]:<42s} {wall.mean():6.2f} {np.median(wall):6.2f} {np.percentile(wall, 95):6.2f}"
            f" {wall.max():6.2f} {cpu.mean():6.2f} {1e3 / wall.mean():6.0f} fps wall, {1e3 / cpu.mean():4.0f} fps CPU"
            f" | setup {setup_s:.1f} s"
        )
        if stages:
            # a second pass over the same poses with the stage clocks on (the first one stays unwrapped)
            with _StageClock() as clock:
                _, cpu_staged = _run_scene(scene, core.renderer(), sensor, poses, GROUND_D_M)
            n = len(poses)
            print(
                f"{name} stages, CPU ms/frame (total {cpu_staged.mean():.2f}; the background includes the sky and"
                " the kernels it calls): " + ", ".join(f"{k} {v / n:.2f}" for k, v in clock.ms.items())
            )


if __name__ == "__main__":
    flags = parse_flags(
        "python -m bench.render",
        __doc__.splitlines()[0],
        {
            "--reference-scenes": "only the reference scenes C1-C5",
            "--stages": "with --reference-scenes: where each scene's time goes",
        },
    )
    sys.exit(run_benchmark("render", reference_scenes_main if flags.reference_scenes else main))
