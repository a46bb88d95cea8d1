"""``python -m groundsim dataset``: labelled IR datasets for training and for other toolchains.

One *sequence* per (scenario, run seed): :class:`groundsim.world.sim.SimCore` flies, renders and gives the
truth of every frame (the same flight, frames and navigation errors as ``groundsim run`` and
``groundsim eval`` for that seed and ``--nav-noise``), and this module writes it out.  Layout of ``--out DIR``::

    DIR/manifest.json                 schema irtrack.dataset/1: scenarios (name, file, sha256), seeds,
                                      nav-noise case, bit depth, formats, sequences (name, frames, size)
    DIR/<seq>/img1/000001.png ...     the IR frames, PNG mono 8 or 16 bit (MOT's 1-based file names)
    DIR/<seq>/labels.csv              per frame: target id, sub-pixel centroid, box, visibility, visibility_state
                                      (visible / occluded / out_of_frame), the camera's sensor_status (ok /
                                      frozen / dropped: its flat-field events)
    DIR/<seq>/cameras.csv             per frame: intrinsics, camera pose true and measured (NED + WGS84)
    DIR/<seq>/truth.csv               the 3-D truth (groundsim.world.truth columns, as ``groundsim run --truth``)
    DIR/<seq>/truth.objects.csv       with a scene: every object per frame (groundsim.world.truth.OBJECT_COLUMNS:
                                      id, class, sub-pixel centroid, box, visible / occluded / out_of_frame,
                                      contrast to the local background in NETD units, warm: above it)
    DIR/<seq>/seqinfo.ini, gt/gt.txt  --format mot: MOT Challenge layout (TrackEval's MotChallenge2DBox reads it)
    DIR/coco.json                     --format coco: COCO detection + 1-keypoint ("centroid") JSON, every sequence
    DIR/<seq>/obs.csv                 --format obs: python -m onboard.reconstruct's input (onboard.app.reconstruct
                                      OBS_COLUMNS): each frame whose image shows the target (in the image, not
                                      behind a cloud, not a dropped or frozen frame), its label's pixel (a
                                      perfect detector's, as an ideal pinhole's) and the camera pose the telemetry
                                      MEASURED (the run's navigation errors), t_s on the scenario's clock

``<seq>`` is ``<scenario>-<nav case>-s<seed>``.  Conventions (``onboard.core.frames``): pixel (i, j) is centred at
(j + 0.5, i + 0.5), so the image spans [0, W] x [0, H] in continuous pixel coordinates; NED about the
scenario origin; quaternions w first, ``q_ned_from_cam`` (OpenCV camera: x right, y down, z forward).

Labels (:func:`target_label`, pure):

* ``u_px, v_px``: the target centre's projection at the TRUE camera pose (:func:`groundsim.world.render.truth_pixel`,
  the renderer's own projection): the sub-pixel centroid a perfect detector would report; NaN behind the camera;
* box ``x_px, y_px, w_px, h_px`` (labels.csv's and COCO's; not MOT's, below): the projected 8 corners of the
  target's body bounding box (the union of ``scenario.ir.target_parts``) joined to the target as drawn (the pixels
  holding >= 10 % of its peak signal, as the scene objects' boxes: the optics' blur spreads a far target's
  sub-pixel body over a few pixels, and a detector's box on the blob must be able to match it), clipped to the
  image;
* ``visibility``: clipped box area / unclipped box area (MOT's meaning: the visible fraction), 0 behind
  the camera or outside the image; ``in_image``: the centre is inside the image (``truth.target_visible``).

A frame whose target is not in the image has no gt.txt line and no COCO annotation; labels.csv keeps it.
gt.txt (MOT 1.1 ground truth): ``frame, id, bb_left, bb_top, bb_width, bb_height, consider, class,
visibility``.  Its box is not the box above but the ``groundsim.evaluation.mot.BOX_SIDE_PX`` (6 px) square about
the label's centroid ``(u_px, v_px)``, in MOT's 1-based pixel coordinates (``bb_left = u_px - 3 + 1``) and not
clipped to the image: ``groundsim eval``'s convention for point targets, whose boxes of a few pixels make IoU
meaningless (a point tracker's box, its blob's pixels or a square about its centre, does not reach IoU 0.5 with a 3 x 3
px blob's box even on the right centre; ``onboard.track_video --box-px 6`` writes the matching squares). labels.csv and
COCO keep the box as drawn (detection). Class 1 (the one class TrackEval's MOT reader evaluates; here: "the target") and
consider 1; a target behind a cloud consider 0 and class ``groundsim.evaluation.mot.HIDDEN_CLASS`` (8, MOT17's
"distractor"), as in ``groundsim eval``'s files: TrackEval leaves the row out of the truth and drops a tracker's box
that matches it (a tracker coasting through the cloud is right), where with any other class it would still count that
box a false positive; visibility the target's visible fraction (labels.csv's ``visibility``: how much of its drawn box
is in the image, not of the square, which may reach past the edge), 0 behind a cloud.
``DIR/seqmaps/irtrack-all.txt`` lists the sequences (TrackEval's ``SEQMAP_FILE``, with ``GT_FOLDER=DIR``,
``SKIP_SPLIT_FOL=True``).  A run into a folder that holds a
dataset replaces the sequences it makes again whole (their files of formats not asked for go too, as does
``coco.json`` when COCO is not asked for); it refuses a folder whose dataset has sequences it would not make.
The earlier manifest, ``coco.json`` and seqmap go before the first sequence is written, and the new ones are
written once every sequence is: a run stopped half way leaves no manifest (its one line names the sequences
not finished), and the same command takes the folder again.

The scene's other objects (a scenario with a ``scene``: ``groundsim.world.render.scene.ObjectLabel``), when
their box is in the image (visible or behind a cloud): MOT id and COCO ``track_id`` = object id + 1 (the
target, object 0, keeps id 1 and its label above); COCO box = the pixels holding >= 10 % of the object's peak
signal, MOT box the square about its centroid as the target's; MOT class :data:`MOT_CLASSES` (other targets 1;
birds, aircraft, glints classes of MOT17 that TrackEval neither evaluates nor treats as distractors, so a
tracker's box on a bird is a false positive), consider and visibility 1 (visible) or 0 (behind a cloud: class 8
then, as the target's); COCO
category :data:`COCO_CATEGORIES` with ``visibility_state``, ``contrast_netd`` (a magnitude) and ``warm`` (the
signal above the local background).
An object behind a cloud, the target included, is a COCO ``iscrowd`` 1 annotation (``visibility_state``
``occluded``, keypoint flag 1): pycocotools' ``COCOeval`` ignores it, neither a miss nor, where a detection
matches it, a false positive, as TrackEval treats the MOT rows of hidden objects (consider 0, class 8)
(``COCOeval`` reads no other "ignore" field: it sets its own from ``iscrowd``).
A frame the camera model dropped (its shutter closed, ``ffc.mode: dropped``) is written as an all-zero image, its
target behind the shutter as behind a cloud.  A frozen frame (``ffc.mode: frozen``: the camera repeats its last
image) shows the target where it was: its COCO annotation, at its position now, is an ignore region (``iscrowd``
1, ``visibility_state`` ``frozen``), its MOT row stays (a tracker coasting through those frames is right), and
labels.csv's ``sensor_status`` says ``frozen``.  An occluded target's COCO ``visibility`` is 0, as MOT's. COCO:
boxes ``[x, y, w, h]`` in continuous 0-based pixels (and as a 4-corner polygon ``segmentation``), one keypoint
``[u, v, 2]`` = the sub-pixel centroid, plus ``track_id``, ``visibility`` (the target's), ``visibility_state`` (every
annotation's: ``visible`` or ``occluded``), ``centroid_px`` on each annotation and ``sequence``, ``frame_index``,
``time_boot_us`` on each image.

Camera pose.  *True*: the flown camera (truth.csv ``cam_*``, ``q_ned_from_cam_*``).  *Measured*: what the
daemon rebuilds from the telemetry the simulated vehicle sends (:func:`groundsim.world.nav_errors.reported_state`
applied to the tick's true state): ``p = p_body_true + dp_err + R_reported lever_arm``, ``q = q(phi_err) (x)
q_ned_from_cam_true`` (the gimbal's earth-frame attitude carries the same error as the body,
:mod:`groundsim.world.nav_errors`).  WGS84 columns from :func:`onboard.core.frames.geodetic_from_ned` of the NED ones.

Deterministic per (scenario, seed, nav case, duration, bit depth): no wall time in any file, PNGs from
OpenCV's encoder at a fixed compression level; sequences are written in parallel by a process pool
(one sequence per job, ``--workers``), frames counted by a tqdm bar on stderr.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import hashlib
import json
import logging
import math
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from groundsim.evaluation.out_dir import make_out_dir, refuse_foreign_out, write_replacing, writing
from groundsim.evaluation.parallel import (
    JobsInterrupted,
    pool_workers,
    progress_bar,
    quiet_run_logs,
    report_progress,
    run_jobs,
)
from groundsim.io.stop_signals import finish_despite_signals, first_signal_stops, print_interrupted
from onboard.core.errors import ConfigError, InputError

__all__ = [
    "DATASET_SCHEMA",
    "FORMATS",
    "TARGET_ID",
    "DatasetOptions",
    "TargetLabel",
    "SequenceSummary",
    "target_label",
    "measured_camera_pose",
    "sequence_name",
    "export_sequence",
    "export_dataset",
    "DatasetInterrupted",
    "cmd_dataset",
]

log = logging.getLogger(__name__)

DATASET_SCHEMA = "irtrack.dataset/1"
FORMATS = ("mot", "coco", "obs")
TARGET_ID = 1  # the one target of a scenario: its MOT id / COCO track_id
MOT_CLASS = 1  # TrackEval's MotChallenge2DBox evaluates class 1 only ("pedestrian" there; "the target" here)
# scene objects: MOT17 classes TrackEval reads but neither evaluates nor counts as distractors (car, bicycle,
# motorbike), so a tracker's box on a bird or an aircraft stays a false positive
MOT_CLASSES = {"target": MOT_CLASS, "aircraft": 3, "bird": 4, "glint": 5}
COCO_CATEGORIES = {"target": TARGET_ID, "bird": 2, "aircraft": 3, "glint": 4}
#: sequences one ``dataset`` command makes at most (each hundreds of frames; a mistyped --seeds otherwise builds a
#: job list of that many before anything is checked or written)
MAX_DATASET_SEQUENCES = 10_000
PNG_COMPRESSION = 3  # cv2.IMWRITE_PNG_COMPRESSION: fixed, so the bytes are a function of the pixels
# a sequence's files that a format or a scene writes (removed before the sequence is written again)
SEQUENCE_FORMAT_FILES = ("gt/gt.txt", "seqinfo.ini", "obs.csv", "truth.objects.csv")
SEQMAP = "seqmaps/irtrack-all.txt"  # --format mot: TrackEval's SEQMAP_FILE, every sequence of the dataset
PROGRESS_EVERY_FRAMES = 10

LABEL_COLUMNS = (
    "frame",
    "seq",
    "time_boot_us",
    "t_s",
    "target_id",
    "u_px",
    "v_px",
    "x_px",
    "y_px",
    "w_px",
    "h_px",
    "visibility",
    "in_image",
    "range_m",
    "visibility_state",
    "sensor_status",
)
_INTRINSIC_COLUMNS = ("fx_px", "fy_px", "cx_px", "cy_px", "width_px", "height_px", "k1", "k2", "p1", "p2", "k3")
_POSE_COLUMNS = ("n_m", "e_m", "d_m", "qw", "qx", "qy", "qz", "lat_deg", "lon_deg", "alt_m")
CAMERA_COLUMNS = (
    ("frame", "seq", "time_boot_us", "t_s")
    + _INTRINSIC_COLUMNS
    + tuple(f"true_{c}" for c in _POSE_COLUMNS)
    + tuple(f"meas_{c}" for c in _POSE_COLUMNS)
)


# --------------------------------------------------------------------------- pure core


def _obs_row(K, t_s: float, u_px: float, v_px: float, p_cam_ned_m, q_ned_from_cam) -> list[str]:
    """One row of ``onboard.reconstruct``'s OBS.csv: the pixel as an ideal pinhole sees it (a distorted camera's
    label undistorted: the reconstruction takes no lens model), the intrinsics, the camera's NED position and
    ``q_ned_from_cam``."""
    if K.has_distortion:
        x, y = K.normalized_from_pixel(np.array([u_px, v_px], dtype=float))
        u_px, v_px = K.fx_px * x + K.cx_px, K.fy_px * y + K.cy_px
    return [_fmt(v) for v in (t_s, u_px, v_px, K.fx_px, K.fy_px, K.cx_px, K.cy_px, *p_cam_ned_m, *q_ned_from_cam)]


@dataclass(frozen=True)
class TargetLabel:
    """One frame's 2-D label.  ``u_px, v_px``: sub-pixel centroid (NaN behind the camera); box
    ``(x_px, y_px, w_px, h_px)`` clipped to the image (zeros when none); ``visibility`` in [0, 1];
    ``in_image``: the centroid lies in [0, W) x [0, H)."""

    u_px: float
    v_px: float
    x_px: float
    y_px: float
    w_px: float
    h_px: float
    visibility: float
    in_image: bool
    occluded: bool = False  # behind a cloud (a scene's label): MOT's consider 0, class 8
    # the camera repeated an earlier image (flat-field correction, ffc.mode frozen): the target is drawn where it
    # was then, so COCO's annotation at its position now is an ignore region (MOT's row stays: a tracker coasting
    # through the frozen frames is right)
    frozen: bool = False

    def __post_init__(self) -> None:
        for name in ("x_px", "y_px", "w_px", "h_px", "visibility"):
            v = float(getattr(self, name))
            if not math.isfinite(v) or (name in ("w_px", "h_px") and v < 0):
                raise InputError(f"TargetLabel.{name}: expected a finite number (>= 0 for sizes), got {v!r}")
        if not 0.0 <= self.visibility <= 1.0:
            raise InputError(f"TargetLabel.visibility: expected a fraction in [0, 1], got {self.visibility!r}")

    @property
    def has_box(self) -> bool:
        return self.in_image and self.w_px > 0.0 and self.h_px > 0.0


def body_box_corners_frd_m(target_parts) -> np.ndarray:
    """(8, 3) corners of the axis-aligned body-frame box around every part (body FRD metres)."""
    centre = np.array([p.center_frd_m for p in target_parts], dtype=float)
    half = np.array([p.half_extent_m for p in target_parts], dtype=float)
    lo, hi = (centre - half).min(axis=0), (centre + half).max(axis=0)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def target_label(
    intrinsics,
    p_cam_ned_m,
    R_ned_from_cam,
    p_target_ned_m,
    R_ned_from_target_body,
    corners_frd_m,
    drawn_box_px: tuple[int, int, int, int] | None = None,
) -> TargetLabel:
    """The label of one frame at the true poses (pure; see the module docstring).

    ``p_*`` (3,) NED metres; ``R_*`` (3, 3); ``corners_frd_m`` (8, 3) from :func:`body_box_corners_frd_m`;
    ``drawn_box_px``: the target as the renderer drew it (``SimFrame.target_box_px``: ``(x0, y0, x1, y1)``,
    inside the image), joined to the body's projected box.
    """
    from groundsim.world.render import truth_pixel

    p_c = np.asarray(p_cam_ned_m, dtype=float)
    R_nc = np.asarray(R_ned_from_cam, dtype=float)
    p_t = np.asarray(p_target_ned_m, dtype=float)
    u, v = truth_pixel(intrinsics, p_c, R_nc, p_t)
    W, H = float(intrinsics.width_px), float(intrinsics.height_px)
    in_image = bool(math.isfinite(u) and math.isfinite(v) and 0.0 <= u < W and 0.0 <= v < H)
    corners_cam = (p_t + np.asarray(corners_frd_m, dtype=float) @ np.asarray(R_ned_from_target_body).T - p_c) @ R_nc
    if np.any(corners_cam[:, 2] <= 0.0):  # a corner behind the camera: no meaningful box
        return TargetLabel(u, v, 0.0, 0.0, 0.0, 0.0, 0.0, in_image)
    uv = intrinsics.project(corners_cam)
    x0, y0 = float(uv[:, 0].min()), float(uv[:, 1].min())
    x1, y1 = float(uv[:, 0].max()), float(uv[:, 1].max())
    if drawn_box_px is not None:
        # the optics' blur spreads a far target's sub-pixel body over a few pixels: the box a detector's box is
        # compared with must hold them (a 2 x 0.8 px body box against its 4 x 3 px blob: IoU 0.13)
        x0, y0 = min(x0, float(drawn_box_px[0])), min(y0, float(drawn_box_px[1]))
        x1, y1 = max(x1, float(drawn_box_px[2])), max(y1, float(drawn_box_px[3]))
    area = (x1 - x0) * (y1 - y0)
    cx0, cy0, cx1, cy1 = max(x0, 0.0), max(y0, 0.0), min(x1, W), min(y1, H)
    if cx1 <= cx0 or cy1 <= cy0 or area <= 0.0:
        return TargetLabel(u, v, 0.0, 0.0, 0.0, 0.0, 0.0, in_image)
    vis = min(1.0, (cx1 - cx0) * (cy1 - cy0) / area)
    return TargetLabel(u, v, cx0, cy0, cx1 - cx0, cy1 - cy0, vis, in_image)


def measured_camera_pose(
    state_true: dict, nav_error, p_body_true_ned_m, mount, origin, q_mount_from_gimbal=None
) -> tuple[np.ndarray, np.ndarray]:
    """The camera pose the daemon rebuilds from the telemetry: ``(p_cam_ned_m, q_ned_from_cam)`` (pure).

    ``state_true``: ``SimCore.vehicle_state(i)``; ``nav_error``: ``SimCore.nav_error(i)`` (None = exact);
    ``p_body_true_ned_m`` (3,): the true observer position; the reported position is it plus the error's
    NED offset (:func:`groundsim.world.nav_errors.reported_state` moves lat/lon/alt by the same offset).
    The reported attitude is relative to the local level at the reported position, turned into ``origin``'s
    NED as the daemon's pose buffer does (:mod:`onboard.core.frames`, "Local level").
    """
    from groundsim.world.nav_errors import reported_state
    from onboard.core.frames import camera_pose_ned, q_ned_from_level, quat_multiply, quat_normalize

    rep = reported_state(state_true, nav_error)
    p_body = np.asarray(p_body_true_ned_m, dtype=float)
    if nav_error is not None:
        p_body = p_body + np.asarray(nav_error.p_err_ned_m, dtype=float)
    q_lv = q_ned_from_level(float(rep["lat_deg"]), float(rep["lon_deg"]), origin)
    q_nb = quat_normalize(quat_multiply(q_lv, np.asarray(rep["q_ned_from_body"], dtype=float)))
    return camera_pose_ned(p_body, q_nb, mount, q_mount_from_gimbal)


def sequence_name(scenario_name: str, nav_case: str, seed: int) -> str:
    return f"{scenario_name}-{nav_case}-s{int(seed)}"


def seqinfo_ini(name: str, frame_rate_hz: float, frames: int, width_px: int, height_px: int) -> str:
    """MOT Challenge ``seqinfo.ini`` text (``[Sequence]``: name, imDir, frameRate, seqLength, imWidth,
    imHeight, imExt).  frameRate is an integer there; a non-integer rate is rounded (labels carry t_s)."""
    return (
        f"[Sequence]\nname={name}\nimDir=img1\nframeRate={int(round(frame_rate_hz))}\nseqLength={frames}\n"
        f"imWidth={width_px}\nimHeight={height_px}\nimExt=.png\n"
    )


def _object_box(lab, intrinsics) -> tuple[float, float, float, float] | None:
    """A scene object's box ``(x, y, w, h)`` clipped to the image, None when it has none there (pure)."""
    if lab.box_px is None or lab.visibility == "out_of_frame":
        return None
    x0, y0, x1, y1 = (float(b) for b in lab.box_px)
    x0, y0 = max(x0, 0.0), max(y0, 0.0)
    x1, y1 = min(x1, float(intrinsics.width_px)), min(y1, float(intrinsics.height_px))
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1 - x0, y1 - y0


def mot_gt_lines(labels: list[tuple[int, TargetLabel]], objects=(), intrinsics=None) -> str:
    """gt.txt text from ``(frame 1-based, label)`` pairs of the target (frames without a box are left out)
    and ``(frame, (ObjectLabel, ...))`` of the scene's other objects (see the module docstring): each box the
    ``BOX_SIDE_PX`` square about the label's centroid, not the box as drawn: a point tracker's box (its blob's few
    pixels, or a fixed square about its centre) does not reach IoU 0.5 with a blob's box of a few pixels even on
    the right centre."""
    from groundsim.evaluation.mot import gt_line

    rows = []
    for frame, lab in labels:
        if lab.has_box:
            cls = None if lab.occluded else MOT_CLASS
            rows.append((frame, TARGET_ID, gt_line(frame, TARGET_ID, lab.u_px, lab.v_px, cls, lab.visibility, 4)))
    for frame, labs in objects:
        for o in labs:
            if _object_box(o, intrinsics) is None:
                continue
            oid = int(o.object_id) + 1
            cls = MOT_CLASSES[o.cls] if o.visibility == "visible" else None
            rows.append((frame, oid, gt_line(frame, oid, o.u_px, o.v_px, cls, 1.0, 4)))
    rows.sort(key=lambda r: (r[0], r[1]))
    return "".join(r[2] for r in rows)


# --------------------------------------------------------------------------- options


@dataclass(frozen=True)
class DatasetOptions:
    """How a dataset is made.  ``duration_s`` None = the scenario's; ``bit_depth`` None = the scenario's
    encoding, else 8 or 16 (the renderer's mono8/mono16); ``formats``: subset of :data:`FORMATS`."""

    nav_noise: str | None = None
    duration_s: float | None = None
    bit_depth: int | None = None
    formats: tuple[str, ...] = ("mot",)

    def __post_init__(self) -> None:
        d = self.duration_s
        if d is not None and (isinstance(d, bool) or not isinstance(d, (int, float)) or not math.isfinite(d) or d <= 0):
            raise ConfigError(f"--duration: expected a positive number of seconds, got {d!r}")
        if self.bit_depth not in (None, 8, 16):
            raise ConfigError(f"--bit-depth: expected 8 or 16, got {self.bit_depth!r}")
        bad = [f for f in self.formats if f not in FORMATS]
        if bad or not self.formats:
            raise ConfigError(f"--format: expected one or more of {', '.join(FORMATS)}, got {', '.join(bad) or 'none'}")
        if self.nav_noise is not None:
            from groundsim.world.nav_errors import resolve_nav_noise

            resolve_nav_noise(self.nav_noise)


def _with_bit_depth(scenario, bit_depth: int | None):
    if bit_depth is None:
        return scenario
    enc = "mono8" if bit_depth == 8 else "mono16"
    return dataclasses.replace(scenario, ir=dataclasses.replace(scenario.ir, encoding=enc))


# --------------------------------------------------------------------------- one sequence (adapter: files)


@dataclass(frozen=True)
class SequenceSummary:
    """What one sequence wrote: ``name``, ``frames``, frames ``labelled`` (a box in the image), image size,
    and the wall seconds it took (printed, never written into the dataset)."""

    name: str
    scenario: str
    seed: int
    nav_noise: str
    frames: int
    labelled: int
    width_px: int
    height_px: int
    frame_rate_hz: float
    wall_s: float
    labels: tuple = ()  # ((frame 1-based, TargetLabel, time_boot_us), ...) for the COCO writer
    objects: tuple = ()  # ((frame 1-based, (ObjectLabel, ...)), ...): the scene's other objects


def _fmt(x) -> str:
    if isinstance(x, (bool, np.bool_)):
        return str(int(x))
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    return repr(float(x))


def _pose_values(p_ned_m, q, origin) -> list:
    from onboard.core.frames import geodetic_from_ned

    lat, lon, alt = geodetic_from_ned(np.asarray(p_ned_m, dtype=float)[None, :], origin)
    return [*map(float, p_ned_m), *map(float, q), float(lat[0]), float(lon[0]), float(alt[0])]


def export_sequence(scenario, seed: int, out_dir, options: DatasetOptions, progress=None) -> SequenceSummary:
    """Fly, render and write one sequence under ``out_dir / sequence_name(...)`` (see the module docstring).
    ``progress(n)`` is called with frames done.  Raises IrtrackError for a run that cannot be made, and a
    ConfigError naming ``--out`` for one whose files cannot be written (a full disk, a file size limit)."""
    return writing(out_dir, _export_sequence, scenario, seed, out_dir, options, progress)


def _write_png(path: Path, pixels: np.ndarray) -> None:
    """``pixels`` as a PNG at ``path``.  Encoded in memory and written by Python, not by ``cv2.imwrite``: that one
    answers a full disk with False alone, after libpng printed its own ``libpng error: Write Error`` on fd 2, so
    the reason was lost and a stray line came before the command's own."""
    import cv2

    ok, png = cv2.imencode(".png", pixels, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
    if not ok:
        raise InputError(f"{path}: the frame ({pixels.dtype}, {pixels.shape}) could not be encoded as PNG")
    try:
        with open(path, "wb") as f:
            f.write(png.tobytes())
    except OSError as exc:  # a write's or the close's error names no file: this one names it
        raise OSError(exc.errno, exc.strerror, str(path)) from None


def _export_sequence(scenario, seed: int, out_dir, options: DatasetOptions, progress=None) -> SequenceSummary:

    from groundsim.world.sim import SimCore
    from groundsim.world.truth import TruthWriter
    from onboard.core.frames import rotmat_from_quat

    t0 = time.perf_counter()
    scenario = _with_bit_depth(scenario, options.bit_depth)
    core = SimCore(scenario, seed, options.duration_s, render=True, flight_chunk_s=1.0, nav_noise=options.nav_noise)
    name = sequence_name(scenario.name, core.nav_noise.name, seed)
    seq_dir = Path(out_dir) / name
    img_dir = seq_dir / "img1"
    img_dir.mkdir(parents=True, exist_ok=True)
    # a run into the same folder replaces the sequence: an earlier one's frames beyond this one's, and its files
    # of formats not asked for now, must not stay beside this one's (a gt.txt of 150 frames next to 30 images)
    for old in img_dir.glob("*.png"):
        old.unlink()
    for old in SEQUENCE_FORMAT_FILES:
        (seq_dir / old).unlink(missing_ok=True)
    with contextlib.suppress(OSError):  # gone when empty; a folder someone put files in stays
        (seq_dir / "gt").rmdir()
    K = scenario.camera.intrinsics
    mount = scenario.camera.mount
    corners = body_box_corners_frd_m(scenario.ir.target_parts)
    origin = scenario.origin
    labels: list[tuple[int, TargetLabel, int]] = []
    objects: list[tuple[int, tuple]] = []
    obs_rows: list[list[str]] = []  # --format obs: reconstruct's rows
    intr = [K.fx_px, K.fy_px, K.cx_px, K.cy_px, int(K.width_px), int(K.height_px), *map(float, K.distortion)]
    done = 0
    with (
        open(seq_dir / "labels.csv", "w", encoding="ascii", newline="") as f_lab,
        open(seq_dir / "cameras.csv", "w", encoding="ascii", newline="") as f_cam,
        TruthWriter(seq_dir / "truth.csv", option="") as truth,  # a path of its own, no --truth given
    ):
        w_lab, w_cam = csv.writer(f_lab, lineterminator="\n"), csv.writer(f_cam, lineterminator="\n")
        w_lab.writerow(LABEL_COLUMNS)
        w_cam.writerow(CAMERA_COLUMNS)
        for k in range(core.frame_count):
            fr = core.frame(k)
            i = k * core.ticks_per_frame
            c = core.flight.chunk_of(i)
            j = i - c.i0
            tr = fr.truth
            frame = k + 1
            pixels = fr.pixels
            if pixels is None and fr.sensor_status == "dropped":  # the camera delivered nothing: a black frame
                dtype = np.uint8 if scenario.ir.encoding == "mono8" else np.uint16
                pixels = np.zeros((int(K.height_px), int(K.width_px)), dtype)
            if pixels is None:
                raise InputError(f"{name}: frame {k} could not be rendered")
            _write_png(img_dir / f"{frame:06d}.png", pixels)
            truth.write(tr, fr.labels)
            others = tuple(o for o in fr.labels if o.object_id != 0 and _object_box(o, K) is not None)
            if others:
                objects.append((frame, others))
            p_cam = np.array([tr.cam_n_m, tr.cam_e_m, tr.cam_d_m])
            q_cam = np.array([tr.q_ned_from_cam_w, tr.q_ned_from_cam_x, tr.q_ned_from_cam_y, tr.q_ned_from_cam_z])
            lab = target_label(
                K,
                p_cam,
                rotmat_from_quat(q_cam),
                [tr.target_n_m, tr.target_e_m, tr.target_d_m],
                rotmat_from_quat(c.tgt_q_ned_from_body[j]),
                corners,
                # a frozen frame repeats an earlier image: its drawn box is where the target was then, not now
                fr.target_box_px if fr.sensor_status != "frozen" else None,
            )
            if any(o.object_id == 0 and o.visibility == "occluded" for o in fr.labels):
                lab = dataclasses.replace(lab, occluded=True)
            if fr.sensor_status == "frozen":
                lab = dataclasses.replace(lab, frozen=True)
            labels.append((frame, lab, fr.time_boot_us))
            w_lab.writerow(
                [
                    frame,
                    fr.seq,
                    fr.time_boot_us,
                    _fmt(tr.t_s),
                    TARGET_ID,
                    _fmt(lab.u_px),
                    _fmt(lab.v_px),
                    _fmt(lab.x_px),
                    _fmt(lab.y_px),
                    _fmt(lab.w_px),
                    _fmt(lab.h_px),
                    _fmt(lab.visibility),
                    int(lab.in_image),
                    _fmt(tr.range_m),
                    "occluded" if lab.occluded else "visible" if lab.in_image else "out_of_frame",
                    fr.sensor_status,
                ]
            )
            q_mg = None if c.q_mount_from_gimbal is None else c.q_mount_from_gimbal[j]
            p_meas, q_meas = measured_camera_pose(
                core.vehicle_state(i), core.nav_error(i), c.obs_p_ned_m[j], mount, origin, q_mg
            )
            # a perfect detector's: not behind a cloud, nor on a black (dropped) or repeated (frozen) image
            shown = lab.in_image and not lab.occluded and fr.sensor_status == "ok"
            if shown and math.isfinite(lab.u_px) and math.isfinite(lab.v_px):
                obs_rows.append(_obs_row(K, tr.t_s, lab.u_px, lab.v_px, p_meas, q_meas))
            w_cam.writerow(
                [
                    frame,
                    fr.seq,
                    fr.time_boot_us,
                    _fmt(tr.t_s),
                    *map(_fmt, intr),
                    *map(_fmt, _pose_values(p_cam, q_cam, origin)),
                    *map(_fmt, _pose_values(p_meas, q_meas, origin)),
                ]
            )
            done += 1
            if progress is not None and done >= PROGRESS_EVERY_FRAMES:
                progress(done)
                done = 0
    if progress is not None and done:
        progress(done)
    if "obs" in options.formats:
        from onboard.app.reconstruct import OBS_COLUMNS

        with open(seq_dir / "obs.csv", "w", encoding="ascii", newline="") as f_obs:
            w_obs = csv.writer(f_obs, lineterminator="\n")
            w_obs.writerow(OBS_COLUMNS)
            w_obs.writerows(obs_rows)
    if "mot" in options.formats:
        (seq_dir / "seqinfo.ini").write_text(
            seqinfo_ini(name, scenario.frame_rate_hz, core.frame_count, int(K.width_px), int(K.height_px)),
            encoding="ascii",
        )
        (seq_dir / "gt").mkdir(exist_ok=True)
        gt = mot_gt_lines([(f, lab) for f, lab, _ in labels], objects, K)
        (seq_dir / "gt" / "gt.txt").write_text(gt, encoding="ascii")
    return SequenceSummary(
        name=name,
        scenario=scenario.name,
        seed=int(seed),
        nav_noise=core.nav_noise.name,
        frames=core.frame_count,
        labelled=sum(1 for _, lab, _ in labels if lab.has_box),
        width_px=int(K.width_px),
        height_px=int(K.height_px),
        frame_rate_hz=float(scenario.frame_rate_hz),
        wall_s=time.perf_counter() - t0,
        labels=tuple(labels),
        objects=tuple(objects),
    )


# --------------------------------------------------------------------------- whole dataset


def _box_polygon(lab: TargetLabel) -> list[float]:
    x0, y0, x1, y1 = (round(a, 4) for a in (lab.x_px, lab.y_px, lab.x_px + lab.w_px, lab.y_px + lab.h_px))
    return [x0, y0, x1, y0, x1, y1, x0, y1]


def coco_document(summaries: list[SequenceSummary], description: str) -> dict:
    """The COCO JSON of the sequences (pure): images in sequence then frame order, ids from 1."""
    images, annotations = [], []
    for s in summaries:
        others = dict(s.objects)
        for frame, lab, t_us in s.labels:
            image_id = len(images) + 1
            images.append(
                {
                    "id": image_id,
                    "file_name": f"{s.name}/img1/{frame:06d}.png",
                    "width": s.width_px,
                    "height": s.height_px,
                    "sequence": s.name,
                    "frame_index": frame,
                    "time_boot_us": int(t_us),
                }
            )
            if lab.has_box:
                ignored = lab.occluded or lab.frozen  # not drawn there: COCOeval's ignore region (iscrowd)
                annotations.append(
                    {
                        "id": len(annotations) + 1,
                        "image_id": image_id,
                        "category_id": TARGET_ID,
                        "bbox": [round(lab.x_px, 4), round(lab.y_px, 4), round(lab.w_px, 4), round(lab.h_px, 4)],
                        "area": round(lab.w_px * lab.h_px, 4),
                        "iscrowd": int(ignored),
                        "segmentation": [_box_polygon(lab)],
                        "keypoints": [float(lab.u_px), float(lab.v_px), 1 if ignored else 2],
                        "num_keypoints": 1,
                        "centroid_px": [float(lab.u_px), float(lab.v_px)],
                        "visibility": 0.0 if lab.occluded else round(lab.visibility, 4),
                        "visibility_state": "occluded" if lab.occluded else "frozen" if lab.frozen else "visible",
                        "track_id": TARGET_ID,
                    }
                )
            for o in others.get(frame, ()):
                box = _object_box(o, _Size(s.width_px, s.height_px))
                if box is None:
                    continue
                x, y, w, h = box
                annotations.append(
                    {
                        "id": len(annotations) + 1,
                        "image_id": image_id,
                        "category_id": COCO_CATEGORIES[o.cls],
                        "bbox": [x, y, w, h],
                        "area": w * h,
                        "iscrowd": int(o.visibility != "visible"),
                        "segmentation": [[x, y, x + w, y, x + w, y + h, x, y + h]],
                        "keypoints": [float(o.u_px), float(o.v_px), 2 if o.visibility == "visible" else 1],
                        "num_keypoints": 1,
                        "centroid_px": [float(o.u_px), float(o.v_px)],
                        "visibility_state": o.visibility,
                        "contrast_netd": round(float(o.contrast_netd), 4),
                        "warm": bool(o.warm),
                        "track_id": int(o.object_id) + 1,
                    }
                )
    return {
        "info": {"description": description, "version": DATASET_SCHEMA},
        "licenses": [],
        "images": images,
        "annotations": annotations,
        "categories": [
            {"id": TARGET_ID, "name": "target", "supercategory": "aircraft", "keypoints": ["centroid"], "skeleton": []}
        ]
        + [
            {"id": cid, "name": name, "supercategory": "object", "keypoints": ["centroid"], "skeleton": []}
            for name, cid in COCO_CATEGORIES.items()
            if cid != TARGET_ID and any(s.objects for s in summaries)
        ],
    }


@dataclass(frozen=True)
class _Size:
    width_px: int
    height_px: int


def _sha256(path) -> str | None:
    if path is None or not Path(path).is_file():
        return None
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _manifest(scenarios, seeds, options: DatasetOptions, summaries: list[SequenceSummary]) -> dict:
    from importlib.metadata import PackageNotFoundError, version

    try:
        ver = version("irtrack")
    except PackageNotFoundError:
        ver = None
    return {
        "schema": DATASET_SCHEMA,
        "irtrack_version": ver,
        "scenarios": [
            {
                "name": sc.name,
                "file": None if sc.source_path is None else str(sc.source_path),
                "sha256": _sha256(sc.source_path),
                "scenario_seed": int(sc.seed),
            }
            for sc in scenarios
        ],
        "seeds": [int(s) for s in seeds],
        "nav_noise": options.nav_noise,
        "duration_s": options.duration_s,
        "bit_depth": options.bit_depth,
        "formats": list(options.formats),
        "target_id": TARGET_ID,
        "sequences": [
            {
                "name": s.name,
                "scenario": s.scenario,
                "seed": s.seed,
                "nav_noise": s.nav_noise,
                "frames": s.frames,
                "labelled_frames": s.labelled,
                "width_px": s.width_px,
                "height_px": s.height_px,
                "frame_rate_hz": s.frame_rate_hz,
            }
            for s in summaries
        ],
        "files": {
            "labels": "<seq>/labels.csv",
            "cameras": "<seq>/cameras.csv",
            "truth": "<seq>/truth.csv",
            "images": "<seq>/img1/%06d.png",
            "mot": "<seq>/gt/gt.txt, <seq>/seqinfo.ini",
            "coco": "coco.json",
            "obs": "<seq>/obs.csv",
        },
    }


class DatasetInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`export_dataset`: ``summaries`` of the sequences written whole (job order),
    ``planned`` the number asked for, ``unfinished`` the names of the others (job order)."""

    def __init__(self, summaries: list, planned: int, unfinished: tuple[str, ...] = ()) -> None:
        super().__init__(f"{len(summaries)} of {planned} sequences written")
        self.summaries = summaries
        self.planned = planned
        self.unfinished = unfinished


def _replaceable(out: Path, names: set[str]) -> None:
    """Refuse an ``out`` whose manifest lists sequences this run would not make again: rewritten, the manifest
    would no longer list them while their files stayed (a dataset that says less than it holds).  The
    sequences it makes again are replaced whole (:func:`export_sequence`)."""
    path = out / "manifest.json"
    if not path.is_file():
        # a run replaces files by name (coco.json, the seqmap, the sequences' files): without a manifest, only a new
        # or empty folder, or one of sequences alone (a dataset interrupted before its manifest), is its own
        refuse_foreign_out(out, _sequences_only, "groundsim dataset", f"manifest.json of schema {DATASET_SCHEMA}")
        earlier = {e.name for e in out.iterdir()} if out.is_dir() else set()
        _refuse_kept(out, earlier - names, "sequences of an interrupted run")
        return
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        if doc.get("schema") != DATASET_SCHEMA:
            raise ValueError(f"schema {doc.get('schema')!r}, not {DATASET_SCHEMA}")
        earlier = {str(q["name"]) for q in doc.get("sequences", [])}
    except (OSError, ValueError, TypeError, KeyError, AttributeError) as exc:
        raise ConfigError(
            f"--out {out}: holds a manifest.json that is not a dataset's ({type(exc).__name__}: {exc}); give "
            f"another --out"
        ) from None
    _refuse_kept(out, earlier - names, "a dataset with sequences")


def _refuse_kept(out: Path, kept_names: set[str], what: str) -> None:
    """Refuse an ``out`` holding sequences (``kept_names``) this run would not make: the manifest it writes would
    not list them while their files stayed (a dataset that says less than it holds)."""
    kept = sorted(kept_names)
    if kept:
        shown = ", ".join(kept[:4]) + (f" and {len(kept) - 4} more" if len(kept) > 4 else "")
        raise ConfigError(
            f"--out {out}: holds {what} this run does not make ({shown}); its manifest would not list them: give "
            f"another --out, or remove the folder first"
        )


def _sequences_only(out: Path) -> bool:
    """Whether every entry of ``out`` is a sequence's folder (it holds img1/): what an interrupted dataset leaves."""
    return all(e.is_dir() and (e / "img1").is_dir() for e in out.iterdir())


def _job(args) -> SequenceSummary:
    scenario, seed, out_dir, options = args
    return export_sequence(scenario, seed, out_dir, options, report_progress)


def export_dataset(
    scenarios, seeds, out_dir, options: DatasetOptions | None = None, workers: int = 1, progress: bool = True
) -> tuple[list[SequenceSummary], float]:
    """Every (scenario, seed) sequence into ``out_dir`` (``workers`` processes; 1 = here), then the
    format files and the manifest.  Returns the summaries (job order) and the wall seconds."""
    from groundsim.world.sim import frame_count

    options = options if options is not None else DatasetOptions()
    seeds = [int(s) for s in seeds]
    if not scenarios:
        raise ConfigError("--scenario: expected at least one scenario")
    for sc in scenarios:
        sc.refuse_fleet("a dataset sequence is one observer's camera")
    twice = sorted({sc.name for sc in scenarios if [s.name for s in scenarios].count(sc.name) > 1})
    if twice:  # their sequences are one folder, written by two jobs at once
        raise ConfigError(f"--scenario: {twice[0]} given twice (a sequence folder is named after the scenario)")
    if not seeds or min(seeds) < 0:
        raise ConfigError(f"--seeds: expected at least one seed >= 0, got {seeds}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"--workers: expected an integer >= 1, got {workers!r}")
    out = make_out_dir(out_dir)
    jobs = [(sc, seed, out, options) for sc in scenarios for seed in seeds]
    from groundsim.world.nav_errors import run_nav_case

    names = [sequence_name(sc.name, run_nav_case(sc, options.nav_noise).name, seed) for sc, seed, *_ in jobs]
    _replaceable(out, set(names))
    _remove_index(out, options)
    total = sum(frame_count(options.duration_s or sc.duration_s, sc.frame_rate_hz) for sc, *_ in jobs)
    bar = None
    if progress:
        n = min(workers, len(jobs))
        bar = progress_bar(total, "frame", f"dataset ({n} worker{'s' if n > 1 else ''})")
    t0 = time.perf_counter()
    try:
        summaries = run_jobs(_job, jobs, min(workers, len(jobs)), None if bar is None else bar.update)
    except JobsInterrupted as exc:
        unfinished = tuple(n for n, r in zip(names, exc.results) if r is None)
        raise DatasetInterrupted([r for r in exc.results if r is not None], len(jobs), unfinished) from None
    finally:
        if bar is not None:
            bar.close()
    # every sequence is written: a signal now waits for the index (a Ctrl-C then ends the command as interrupted,
    # the dataset whole), which it would otherwise leave without its manifest, to be rendered again
    with finish_despite_signals("the dataset's index") as received:
        if "coco" in options.formats:
            desc = f"irtrack dataset: {', '.join(sc.name for sc in scenarios)}; seeds {seeds}"
            _write_ascii(out, "coco.json", json.dumps(coco_document(summaries, desc), indent=1) + "\n")
        if "mot" in options.formats:
            (out / SEQMAP).parent.mkdir(exist_ok=True)
            _write_ascii(out, SEQMAP, "name\n" + "".join(s.name + "\n" for s in summaries))
        # last: a dataset with a manifest is a whole one
        _write_ascii(out, "manifest.json", json.dumps(_manifest(scenarios, seeds, options, summaries), indent=2) + "\n")
    if signal.SIGINT in received:
        raise DatasetInterrupted(summaries, len(jobs))
    return summaries, time.perf_counter() - t0


def _remove_index(out: Path, options: DatasetOptions) -> None:
    """Before the first sequence is touched: the earlier dataset's manifest, coco.json and seqmap go.  They list
    the frames of sequences this run replaces, and a run stopped half way would have left them describing folders
    that no longer hold those frames (an interrupted run leaves no manifest: the one line says so)."""
    if (out / "coco.json").exists() and "coco" not in options.formats:
        log.warning(
            "--out %s: the earlier dataset's coco.json removed (its frames are replaced; --format coco "
            "makes this run's)",
            out,
        )
    for name in ("manifest.json", "coco.json", SEQMAP):
        (out / name).unlink(missing_ok=True)
    with contextlib.suppress(OSError):  # gone when empty, so that the folder is one of sequences alone again
        (out / SEQMAP).parent.rmdir()


def _write_ascii(out: Path, name: str, text: str) -> None:
    """``text`` into the dataset ``out``'s file ``name``, replaced whole
    (:func:`~groundsim.evaluation.out_dir.write_replacing`); a ConfigError naming ``--out`` when it cannot be."""
    path = out / name
    writing(out, write_replacing, path, lambda tmp: tmp.write_text(text, encoding="ascii"))


def cmd_dataset(args) -> int:
    """The ``dataset`` command: export, print one line per sequence and the frames/s.  Ctrl-C or SIGTERM: the
    interrupted line names the sequences written and those not finished, exit 130."""
    from groundsim.world.scenario import load_scenario, refuse_duplicate_scenarios, resolve_scenario_path

    with quiet_run_logs("groundsim.world.truth"), first_signal_stops("the sequences finished"):
        names = [n for group in (args.scenario or [["P1"]]) for n in group]
        paths = [resolve_scenario_path(n) for n in names]
        scenarios = [load_scenario(p) for p in paths]
        refuse_duplicate_scenarios(names, paths, [sc.name for sc in scenarios], "one sequence folder per seed")
        if isinstance(args.seeds, bool) or args.seeds < 1:
            raise ConfigError(f"--seeds: expected an integer >= 1, got {args.seeds}")
        if args.seed0 < 0:
            raise ConfigError(f"--seed0: expected an integer >= 0, got {args.seed0}")
        if args.seed0 + args.seeds - 1 >= 2**63:  # a run seed is 63 bits (groundsim.world.sim), the last one too
            raise ConfigError(
                f"--seed0: expected an integer in [0, 2^63 - {args.seeds}] with --seeds {args.seeds}, got {args.seed0}"
            )
        if len(scenarios) * args.seeds > MAX_DATASET_SEQUENCES:  # its job list is made before the first frame
            raise ConfigError(
                f"--seeds: at most {MAX_DATASET_SEQUENCES} sequences in one dataset (scenarios x seeds), got "
                f"{len(scenarios)} x {args.seeds}; make it in parts with --seed0"
            )
        workers = pool_workers(args.workers)
        options = DatasetOptions(
            nav_noise=args.nav_noise,
            duration_s=args.duration,
            bit_depth=args.bit_depth,
            formats=tuple(dict.fromkeys(args.format)),
        )
        try:
            summaries, wall_s = export_dataset(
                scenarios,
                range(args.seed0, args.seed0 + args.seeds),
                args.out,
                options,
                workers=workers,
                progress=not args.no_progress,
            )
        except DatasetInterrupted as exc:
            done = ", ".join(s.name for s in exc.summaries)
            kept = f"{len(exc.summaries)} of {exc.planned} sequences written in {args.out}{': ' + done if done else ''}"
            if exc.unfinished:
                kept += (
                    f"; not finished: {', '.join(exc.unfinished)} (no manifest; their folders are incomplete or an "
                    "earlier run's)"
                )
            return print_interrupted(kept)
        frames = sum(s.frames for s in summaries)
        for s in summaries:
            print(
                f"{s.name}: {s.frames} frames ({s.labelled} with the target in the image), {s.wall_s:.1f} s, "
                f"{s.frames / s.wall_s:.1f} frames/s in its worker"
            )
        w = min(workers, len(summaries))
        print(
            f"{frames} frames in {wall_s:.1f} s with {w} worker(s): {frames / wall_s:.1f} frames/s, "
            f"{frames / wall_s / w:.1f} frames/s per worker; dataset: {Path(args.out) / 'manifest.json'}"
        )
        sys.stdout.flush()
        return 0
