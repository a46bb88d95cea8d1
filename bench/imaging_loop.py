"""The image chain in the closed loop: the daemon's pipeline on the simulator's telemetry, scored per run.

``python -m bench.imaging --loop C4 C5 [--seeds 3] [--nav-noise RTK] [--onboard-config FILE]``.  Each
(scenario, seed) is one :func:`groundsim.evaluation.eval.run_lockstep` run (the very ``FramePipeline`` the
daemon drives, its poses from the simulated MAVLink telemetry with the run's navigation errors, each frame's
telemetry fed until it brackets the frame: what the daemon's chain gets since it waits for that telemetry,
``imaging.pose_wait_ms``), with ``imaging.chain: objects`` on top of ``--onboard-config`` (default the shipped
configuration).  Deterministic: a function of (scenario, seed, options), whatever the machine's load; the
real-time loop (``groundsim demo``) adds the daemon's queue and the telemetry's timing.  Per run it prints:

* ``conf s``: seconds from the target's first visible frame to the first frame the daemon's track is
  ``tracking`` within 3 px of the target (``nan``: never);
* ``after``: of the visible frames from then on, those ``tracking`` within 3 px;
* ``false/min``: confirmed objects (``irtrack/<vehicle>/objects``) farther than 3 px from every labelled
  object on more than half of their frames, per minute; ``ids``: object ids confirmed over the run;
* ``on defect``: frames of a confirmed object within 2 px of a dead or hot pixel of the camera model (the
  scenario's ``scene.sensor``; ``-`` without one);
* ``ffc s``: per flat-field event (``scene.sensor.ffc``), seconds from the shutter closing to the first frame
  the track is ``tracking`` within 3 px of the target again (``-`` without events; ``nan``: not again).

Numbers only: nothing asserts.
"""

from __future__ import annotations

import math
import time

import numpy as np

MATCH_PX = 3.0
DEFECT_PX = 2.0


def _mot(lines: str) -> dict[int, list[tuple[int, float, float]]]:
    """MOT lines -> frame (1-based) -> [(id, u, v)] (the box centres)."""
    out: dict[int, list[tuple[int, float, float]]] = {}
    for ln in lines.splitlines():
        f = ln.split(",")
        if len(f) < 6:
            continue
        x, y, w, h = (float(a) for a in f[2:6])
        out.setdefault(int(f[0]), []).append((int(f[1]), x - 1.0 + w / 2, y - 1.0 + h / 2))
    return out


def defect_pixels(scenario, seed: int) -> np.ndarray:
    """(n, 2) pixel centres (u, v) of the camera model's dead and hot pixels (empty without a sensor model):
    the pixels at 0 or full scale on a frame of uniform mid-scale radiance."""
    from groundsim.world.sim import SimCore

    if not scenario.scene.sensor.enabled:
        return np.zeros((0, 2))
    core = SimCore(scenario, seed, duration_s=1.0 / scenario.frame_rate_hz)
    _, sensor = core.scene()
    from groundsim.world.render.planck import band_radiance

    ir = scenario.ir
    L = float(band_radiance(0.5 * (ir.t_min_k + ir.t_max_k), tuple(ir.band_um)))
    K = scenario.camera.intrinsics
    counts = sensor.counts(np.full((K.height_px, K.width_px), L, np.float32), 0.0, 0)
    i, j = np.nonzero((counts == 0) | (counts >= sensor.full_scale))
    return np.stack([j + 0.5, i + 0.5], axis=1)


def ffc_frames(scenario, n_frames: int) -> list[int]:
    """Frame indices where the shutter closes (``scene.sensor.ffc``)."""
    s = scenario.scene.sensor
    if not s.enabled or not s.ffc.enabled:
        return []
    fr = scenario.frame_rate_hz
    out, t = [], s.ffc.first_s
    while t * fr < n_frames:
        out.append(int(math.ceil(t * fr - 1e-9)))
        t += s.ffc.period_s
    return out


def score_run(r, scenario, defects: np.ndarray) -> dict:
    fr = float(scenario.frame_rate_hz)
    vis = np.asarray(r.visible, dtype=bool)
    d = np.hypot(r.uv_px[:, 0] - r.truth_uv_px[:, 0], r.uv_px[:, 1] - r.truth_uv_px[:, 1])
    on = (r.state == "tracking") & (d <= MATCH_PX) & vis
    first_vis = int(np.argmax(vis)) if vis.any() else None
    first_on = int(np.argmax(on)) if on.any() else None
    conf = (first_on - first_vis) / fr if first_on is not None and first_vis is not None else math.nan
    after = 100.0 * float(on[first_on:][vis[first_on:]].mean()) if first_on is not None else math.nan
    gt, tr = _mot(r.mot_gt), _mot(r.mot_tracker)
    rec: dict[int, list[int]] = {}
    on_defect = 0
    for k, rows in tr.items():
        g = gt.get(k, [])
        for oid, u, v in rows:
            a = rec.setdefault(oid, [0, 0])
            a[0] += 1
            a[1] += all(math.hypot(u - gu, v - gv) > MATCH_PX for _, gu, gv in g)
            if len(defects) and float(np.min(np.hypot(defects[:, 0] - u, defects[:, 1] - v))) <= DEFECT_PX:
                on_defect += 1
    minutes = r.frames / fr / 60.0
    false = sum(1 for n, off in rec.values() if off > 0.5 * n)
    ffc = []
    for k0 in ffc_frames(scenario, r.frames):
        back = np.nonzero(on[k0:])[0]
        ffc.append(float(back[0]) / fr if len(back) else math.nan)
    return dict(
        frames=r.frames,
        confirm_s=conf,
        tracked_after=after,
        false_per_min=false / minutes if minutes else math.nan,
        ids=len(rec),
        on_defect=on_defect if scenario.scene.sensor.enabled else None,
        ffc_s=ffc,
    )


def main(argv: list[str]) -> None:
    from bench.options import BenchParser, known_nav_noise, name_in, nonnegative_number, positive_int
    from groundsim.evaluation.eval import EvalOptions, load_base_config, run_lockstep
    from groundsim.world.nav_errors import InjectedErrors
    from groundsim.world.scenario import load_scenario, reference_scenario_paths, scenarios_dir

    ap = BenchParser(prog="python -m bench.imaging --loop", description=__doc__.splitlines()[0])
    ap.add_argument(
        "--loop",
        nargs="+",
        required=True,
        type=name_in(reference_scenario_paths, "scenario"),
        help="scenario names (config/scenarios), e.g. C4 C5",
    )
    ap.add_argument("--seeds", type=positive_int, default=3, help="run seeds 0..N-1 (default 3)")
    ap.add_argument(
        "--nav-noise", type=known_nav_noise, default="RTK", help="navigation-error case (config/noise_cases.yaml)"
    )
    ap.add_argument("--onboard-config", default=None, help="the daemon's configuration (default: the shipped one)")
    ap.add_argument(
        "--rotation-wait-ms",
        type=nonnegative_number,
        default=None,
        help="frames sent at their capture instant: each waits at most this long for the samples that bracket its"
        " rotation, else takes it extrapolated (the daemon's imaging.pose_wait_ms); default: every frame's"
        " telemetry fed until it brackets the frame",
    )
    # '--scene --help' (or '--loop --help'): the mode's help, not 'expected at least one argument' for the mode's
    # option, which argparse says before it reads --help
    a = ap.parse_args(["--help"] if {"-h", "--help"} & set(argv) else argv)
    import dataclasses

    base = load_base_config(a.onboard_config)
    base = dataclasses.replace(base, imaging=dataclasses.replace(base.imaging, chain="objects"))
    print(
        f"objects chain in the lockstep loop (navigation {a.nav_noise}); match {MATCH_PX:.0f} px; "
        "conf s / after: the daemon's track tracking on the target"
    )
    print(
        f"{'scene':<6s} {'seed':>4s} {'frames':>6s} {'conf s':>6s} {'after':>6s} {'false/min':>9s} {'ids':>4s}"
        f" {'on defect':>9s} {'ffc s':>10s} {'wall s':>6s}"
    )
    for name in a.loop:
        sc = load_scenario(scenarios_dir() / f"{name}.yaml")
        for seed in range(a.seeds):
            t0 = time.perf_counter()
            opts = EvalOptions(
                batch=False,
                injected=InjectedErrors(a.nav_noise),
                rotation_wait_us=None if a.rotation_wait_ms is None else round(a.rotation_wait_ms * 1000),
            )
            r = run_lockstep(sc, seed, opts, base)
            s = score_run(r, sc, defect_pixels(sc, seed))
            ffc = " ".join(f"{x:.2f}" for x in s["ffc_s"]) or "-"
            od = "-" if s["on_defect"] is None else str(s["on_defect"])
            print(
                f"{name:<6s} {seed:4d} {s['frames']:6d} {s['confirm_s']:6.2f} {s['tracked_after']:5.1f}%"
                f" {s['false_per_min']:9.1f} {s['ids']:4d} {od:>9s} {ffc:>10s} {time.perf_counter() - t0:6.0f}",
                flush=True,
            )
