"""``python -m groundsim scenes``: what a scenario's scene holds, measured on its own rendered frames.

For each scenario (default: the reference scenes C1-C5 and clean P2), flown and rendered by
:class:`groundsim.world.sim.SimCore` exactly as ``groundsim run`` / ``eval`` / ``dataset`` render it, on
every ``every``-th frame:

* ``cloud_cover``: the fraction of the image above the horizon covered by cloud of opacity >= 0.5
  (the cover the camera *sees*, not the layer's ``cover_fraction``);
* ``in_front_of_cloud``: the fraction of frames whose target centre is in the image, in front of a cloud
  of opacity >= 0.5 (the layer farther than the target on that pixel); ``behind_cloud``: its label ``occluded``,
  hidden by a cloud (its contrast through it under 3 NETD) or inside a nearer object's box (printed as "occluded");
  ``cloud_edge_crossings``: how often the target went from in front of a cloud to clear sky or back
  (between consecutive measured frames);
* ``contrast_netd``: the target's peak |signal - local background| in NETD units (its label's
  ``contrast_netd``), median, 10th and 90th percentile, and the fraction of frames with >= 3 NETD;
  ``warm_ge_3_netd`` the fraction with >= 3 NETD *and* the target above its local background (its label's
  ``warm``): the contrast is a magnitude, and a target colder than the roof it hides is a cold point;
* ``false_points_per_frame`` (``--clutter``): detections of the plain point detector
  (:func:`groundsim.world.render.clutter.point_detections`: 15 x 15 local mean, 5 sigma of the temporal
  noise, blobs <= 50 px) farther than ``MATCH_PX`` from every object's box, per frame.  The detector
  runs on the mono16 image (the renderer's grey map at 16 bit, or the camera model's raw counts), whose
  temporal noise sigma is known exactly: it measures the scene's clutter, not the 8-bit quantisation.

``--gallery DIR`` writes one picture per scenario (:func:`gallery_image`: the frame as the scenario
outputs it, mono8, beside the same frame with every labelled object's box, id and class drawn) for
``docs/scenes.md``.

Everything here reads the simulator's frames; nothing is written into a dataset.  Pure functions over a
:class:`SimCore` plus :func:`cmd_scenes`, the command.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from onboard.core.errors import ConfigError

__all__ = [
    "REFERENCE_SCENES",
    "MATCH_PX",
    "SceneStats",
    "measure_scene",
    "false_points",
    "gallery_image",
    "cmd_scenes",
]

log = logging.getLogger(__name__)

REFERENCE_SCENES = ("C1", "C2", "C3", "C4", "C5", "P2")
MATCH_PX = 3.0  # a detection this close to an object's box is that object, not clutter
OPAQUE_ALPHA = 0.5  # "cloud" on a pixel: opacity at least this (as the labels' "occluded")
GALLERY_FRAME_S = 5.0  # the gallery shows the frame nearest this time


@dataclass(frozen=True)
class SceneStats:
    """What :func:`measure_scene` measured on ``frames`` frames of one scenario (see the module docstring)."""

    scenario: str
    frames: int
    cloud_cover: float
    in_front_of_cloud: float
    cloud_edge_crossings: int
    behind_cloud: float
    target_in_image: float
    contrast_netd_p10: float
    contrast_netd_median: float
    contrast_netd_p90: float
    contrast_ge_3_netd: float
    warm_ge_3_netd: float
    objects_per_frame: float
    false_points_per_frame: float | None

    def line(self) -> str:
        fp = "" if self.false_points_per_frame is None else f", false points/frame {self.false_points_per_frame:.1f}"
        if math.isnan(self.contrast_netd_median):
            contrast = "contrast n/a (no scene: no object labels)"
        else:
            contrast = (
                f"contrast NETD median {self.contrast_netd_median:.1f} (p10 {self.contrast_netd_p10:.1f}, p90"
                f" {self.contrast_netd_p90:.1f}), >= 3 NETD on {100 * self.contrast_ge_3_netd:.0f} % of frames"
                f" (warm on {100 * self.warm_ge_3_netd:.0f} %)"
            )
        return (
            f"{self.scenario}: {self.frames} frames; cloud cover seen {100 * self.cloud_cover:.0f} %; target in image"
            f" {100 * self.target_in_image:.0f} %, in front of cloud {100 * self.in_front_of_cloud:.0f} %"
            f" ({self.cloud_edge_crossings} cloud edges crossed), occluded {100 * self.behind_cloud:.0f} % (behind"
            " cloud or a nearer object);"
            f" {contrast}; {self.objects_per_frame:.1f} objects/frame{fp}"
        )


def _mono16(scenario):
    """The scenario rendering 16-bit images (raw counts with the camera model): the detector's input."""
    return dataclasses.replace(scenario, ir=dataclasses.replace(scenario.ir, encoding="mono16"))


def _noise_sigma(core) -> float:
    """Temporal noise, 1 sigma, in the units of ``core``'s (mono16) pixels."""
    _, sensor = core.scene() if core.scene_enabled else (None, None)
    if sensor is not None:
        return float(sensor.noise_sigma_counts)
    return float(core.renderer().noise_sigma_grey)


def false_points(image, labels, noise_sigma: float) -> int:
    """Point-like detections of ``image`` farther than :data:`MATCH_PX` from every labelled object's box
    (or centre, for an object without a box)."""
    from groundsim.world.render.clutter import point_detections

    det = point_detections(image, noise_sigma)
    if det.shape[0] == 0:
        return 0
    near = np.zeros(det.shape[0], bool)
    for lab in labels:
        if lab.box_px is not None:
            x0, y0, x1, y1 = lab.box_px
            dx = np.maximum(np.maximum(x0 - det[:, 0], det[:, 0] - x1), 0.0)
            dy = np.maximum(np.maximum(y0 - det[:, 1], det[:, 1] - y1), 0.0)
            near |= np.hypot(dx, dy) <= MATCH_PX
        elif math.isfinite(lab.u_px) and math.isfinite(lab.v_px):
            near |= np.hypot(det[:, 0] - lab.u_px, det[:, 1] - lab.v_px) <= MATCH_PX
    return int(np.count_nonzero(~near))


def _sky_fraction_opaque(background, R_ned_from_cam, intrinsics) -> tuple[float, int]:
    """(opaque cloud pixels / pixels above the horizon, pixels above the horizon) on a 4 px grid."""
    st = 4
    u = np.arange(0, intrinsics.width_px, st) + 0.5
    v = np.arange(0, intrinsics.height_px, st) + 0.5
    uu, vv = np.meshgrid(u, v)
    x = (uu - intrinsics.cx_px) / intrinsics.fx_px
    y = (vv - intrinsics.cy_px) / intrinsics.fy_px
    R = np.asarray(R_ned_from_cam)
    up = (R[2, 0] * x + R[2, 1] * y + R[2, 2]) < 0.0  # NED down component < 0: the ray climbs
    n = int(np.count_nonzero(up))
    if n == 0:
        return 0.0, 0
    alpha = background.cloud_alpha[::st, ::st][: up.shape[0], : up.shape[1]]
    return float(np.count_nonzero(alpha[up] >= OPAQUE_ALPHA)) / n, n


def measure_scene(scenario, run_seed: int = 0, every: int = 10, clutter: bool = True) -> SceneStats:
    """Fly and render every ``every``-th frame of ``scenario`` (mono16) and measure it (module docstring)."""
    from groundsim.world.sim import GROUND_D_M, SimCore
    from onboard.core.frames import rotmat_from_quat

    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ConfigError(f"--every: expected an integer >= 1, got {every!r}")
    core = SimCore(_mono16(scenario), run_seed, render=True, flight_chunk_s=1.0)
    intr = scenario.camera.intrinsics
    cover, in_front, behind, in_image, contrast, warm, n_obj, fps = [], [], [], [], [], [], [], []
    for k in range(0, core.frame_count, every):
        fr = core.frame(k)
        labels = fr.labels
        if core.scene_enabled:
            scene, _ = core.scene()
            i = k * core.ticks_per_frame
            c = core.flight.chunk_of(i)
            j = i - c.i0
            R_nc = rotmat_from_quat(c.cam_q_ned_from_cam[j])
            bg = scene.render_background(c.cam_p_ned_m[j], R_nc, GROUND_D_M)
            frac, n_sky = _sky_fraction_opaque(bg, R_nc, intr)
            if n_sky:
                cover.append(frac)
            tgt = next((lab for lab in labels if lab.object_id == 0), None)
        else:
            tgt, bg = None, None
        tr = fr.truth
        seen = bool(tr.target_visible)
        in_image.append(seen)
        front = False
        if seen and bg is not None:
            iv, iu = int(tr.target_v_px), int(tr.target_u_px)
            front = bool(bg.cloud_alpha[iv, iu] >= OPAQUE_ALPHA and bg.depth_m[iv, iu] > tr.range_m)
        in_front.append(front)
        behind.append(tgt is not None and tgt.visibility == "occluded")
        if tgt is not None and tgt.visibility != "out_of_frame":
            contrast.append(tgt.contrast_netd)
            warm.append(bool(tgt.warm))
        n_obj.append(sum(1 for lab in labels if lab.visibility != "out_of_frame") if labels else int(seen))
        if clutter and fr.pixels is not None:
            fps.append(false_points(fr.pixels, labels or _target_only(tr), _noise_sigma(core)))
    con = np.asarray(contrast) if contrast else np.full(1, math.nan)
    return SceneStats(
        scenario=scenario.name,
        frames=len(in_image),
        cloud_cover=float(np.mean(cover)) if cover else 0.0,
        in_front_of_cloud=float(np.mean(in_front)),
        cloud_edge_crossings=int(np.count_nonzero(np.diff(np.asarray(in_front, dtype=np.int8)))),
        behind_cloud=float(np.mean(behind)),
        target_in_image=float(np.mean(in_image)),
        contrast_netd_p10=float(np.percentile(con, 10)),
        contrast_netd_median=float(np.median(con)),
        contrast_netd_p90=float(np.percentile(con, 90)),
        contrast_ge_3_netd=float(np.mean(con >= 3.0)) if contrast else 0.0,
        warm_ge_3_netd=float(np.mean((con >= 3.0) & np.asarray(warm, dtype=bool))) if contrast else 0.0,
        objects_per_frame=float(np.mean(n_obj)),
        false_points_per_frame=float(np.mean(fps)) if clutter and fps else (None if not clutter else 0.0),
    )


@dataclass(frozen=True)
class _TargetOnly:
    """The target of a scene-less frame as a label-like record (its centre only) for :func:`false_points`."""

    u_px: float
    v_px: float
    box_px: None = None


def _target_only(tr) -> tuple:
    return (_TargetOnly(tr.target_u_px, tr.target_v_px),)


# --------------------------------------------------------------------------- gallery

_CLASS_COLOURS_BGR = {"target": (0, 0, 255), "bird": (0, 200, 255), "aircraft": (255, 160, 0), "glint": (255, 0, 255)}


def _to_mono8(pixels: np.ndarray) -> np.ndarray:
    """A frame for display: mono8 as it is; mono16 stretched between its 0.5 and 99.5 % points."""
    if pixels.dtype == np.uint8:
        return pixels
    lo, hi = np.percentile(pixels, (0.5, 99.5))
    return np.clip((pixels.astype(np.float32) - lo) * (255.0 / max(hi - lo, 1.0)), 0, 255).astype(np.uint8)


def gallery_image(pixels: np.ndarray, labels, truth=None) -> np.ndarray:
    """(H, 2 W, 3) uint8 BGR: the frame, and beside it the same frame with each object's box (2 px outside
    its labelled box, so the object's own pixels stay visible), id and class; occluded objects dashed
    grey.  A scene-less frame (``labels`` empty) marks the truth row's target centre."""
    import cv2

    grey = _to_mono8(pixels)
    left = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    right = left.copy()
    marks = []
    for lab in labels:
        if lab.visibility == "out_of_frame" or lab.box_px is None:
            continue
        x0, y0, x1, y1 = lab.box_px
        marks.append((lab.object_id, lab.cls, lab.visibility, (x0 - 3, y0 - 3, x1 + 2, y1 + 2)))
    if not labels and truth is not None and truth.target_visible:
        u, v = int(truth.target_u_px), int(truth.target_v_px)
        marks.append((0, "target", "visible", (u - 6, v - 6, u + 6, v + 6)))
    marks.sort(key=lambda m: m[2] == "visible")  # visible objects drawn last, over occluded ones
    for oid, cls, vis, (x0, y0, x1, y1) in marks:
        if vis == "visible":
            colour, text_y = _CLASS_COLOURS_BGR.get(cls, (0, 255, 0)), max(int(y0) - 3, 9)
        else:  # grey, its name under the box (an occluding object's name is above)
            colour, text_y = (160, 160, 160), int(y1) + 11
        cv2.rectangle(right, (int(x0), int(y0)), (int(x1), int(y1)), colour, 1)
        name = f"{oid} {cls}" + ("" if vis == "visible" else f" ({vis})")
        cv2.putText(right, name, (int(x0), text_y), cv2.FONT_HERSHEY_PLAIN, 0.8, colour, 1)
    return np.concatenate([left, right], axis=1)


def write_gallery(scenario, out_dir, run_seed: int = 0, t_s: float = GALLERY_FRAME_S) -> Path:
    """``<out_dir>/<scenario>.png``: :func:`gallery_image` of the frame nearest ``t_s`` as the scenario outputs it
    (the first one after it that the camera delivered, where its model dropped that one: a shutter closed for a flat
    field correction at that time stopped the whole command)."""
    import cv2

    from groundsim.evaluation.out_dir import make_out_dir
    from groundsim.world.sim import SimCore

    core = SimCore(scenario, run_seed, render=True, flight_chunk_s=1.0)
    k_show = min(int(round(t_s * core.frame_rate_hz)), core.frame_count - 1)
    fr = None
    k = 0
    # every frame up to it: the camera model's AGC follows the scene in time
    while k < core.frame_count and (k <= k_show or fr is None or fr.pixels is None):
        fr = core.frame(k)
        k += 1
    if fr is None or fr.pixels is None:
        raise ConfigError(f"{scenario.name}: the camera model dropped every frame from {k_show} on: no picture")
    out = make_out_dir(out_dir, "--gallery")
    path = out / f"{scenario.name}.png"
    if not cv2.imwrite(str(path), gallery_image(fr.pixels, fr.labels, fr.truth), [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise ConfigError(f"--gallery {out}: cannot write {path}")
    return path


# --------------------------------------------------------------------------- the command


def cmd_scenes(args) -> int:
    """The ``scenes`` command: one line of figures per scenario; pictures with ``--gallery``."""
    from groundsim.evaluation.out_dir import make_out_dir
    from groundsim.evaluation.parallel import quiet_run_logs
    from groundsim.io.stop_signals import print_interrupted
    from groundsim.world.scenario import load_scenario, resolve_scenario_path

    if args.no_stats and args.gallery is None:
        raise ConfigError("--no-stats: pictures only, so --gallery DIR is needed (else there is nothing to do)")
    if args.no_stats and args.clutter:
        raise ConfigError("--clutter: a figure of the measurement, which --no-stats leaves out; give one of them")
    names = [n for group in (args.scenario or [list(REFERENCE_SCENES)]) for n in group]
    # every file read before the first scene is measured: a typo in the last name fails at once, not minutes in
    scenarios = [load_scenario(resolve_scenario_path(name)) for name in names]
    if args.gallery is not None:
        make_out_dir(args.gallery, "--gallery")
    pictures: list[Path] = []
    with quiet_run_logs():
        try:
            for sc in scenarios:
                if args.gallery is not None:
                    path = write_gallery(sc, args.gallery, args.seed)
                    pictures.append(path)
                    print(f"{sc.name}: {path} ({path.stat().st_size / 1024:.0f} KB)")
                if not args.no_stats:
                    print(measure_scene(sc, args.seed, args.every, clutter=args.clutter).line(), flush=True)
        except KeyboardInterrupt:  # the pictures written so far are whole: said, not "nothing written"
            kept = f"{len(pictures)} picture(s) written in {args.gallery}" if pictures else "nothing written"
            return print_interrupted(kept)
    return 0
