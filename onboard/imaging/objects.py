"""Every warm point-like object a track with a stable id, associated in bearing space.

``ObjectTracker(intrinsics).update(image, R_ned_from_cam) -> ObjectsUpdate`` once per frame.

Detection (:mod:`onboard.imaging.clutter`): column offsets removed, dead/hot pixels repaired, the
two-scale point contrast thresholded at ``threshold_sigma`` local (CFAR) noise sigmas.

Tracks live in bearing space: each holds the unit line of sight ``los_ned`` (local NED) and its rate
per frame.  A frame's pose ``R_ned_from_cam`` (OpenCV camera axes) projects the prediction into the
image, so the camera's own rotation (a gimbal slewing, the airframe rolling) moves every prediction
with it and only the objects' own motion is left to the filter; without a pose (None) the camera is
taken as still.  Association is greedy nearest-first on the image distance between prediction and
candidate inside a gate that widens while a track coasts (points of a few pixels: overlap of boxes
means nothing after a one-pixel shift).  The filter is an alpha-beta filter on the line of sight
(Kalata 1984, "The tracking index", IEEE TAES 20, 174) re-normalised to a unit vector.

States: ``tentative`` until confirmed (see :class:`ObjectParams`: M of N detections moving
consistently and unlike the background; dropped after ``tentative_misses`` misses), then ``confirmed``; ``coasting`` while it misses (predicted, not measured), for at most
``coast_frames`` frames, then ``lost`` (reported once, then gone).  Ids are never reused.

Primary target (``mode`` auto): the current primary is kept while its track lives (confirmed or
coasting); otherwise, of the tracks measured on this frame with at least ``confirm_hits`` hits on at
least ``primary_hit_ratio`` of their frames, the longest-tracked within ``primary_radius_px`` of the
principal point (else the nearest to it) becomes it once it is confirmed and measured (the observer's
gimbal points the camera at its target, so of the steady objects the target is the one the camera
centres and holds; a fragment of terrain or cloud there is never confirmed, so never chosen).  ``select_point`` (operator) selects the confirmed or coasting track nearest a pixel.  A
change of the primary is reported (``primary_changed``) so a 3-D estimate is reset, never silently
continued on another object.  The primary's centre is refined by
:func:`onboard.imaging.detect.measure_blob` (the windowed sub-pixel centroid on the raw frame).

Flat-field events: a frozen frame (identical to the previous one) measures nothing (tracks predicted,
no miss counted); an offset step restarts the defect map.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from onboard.core.errors import InputError
from onboard.imaging.clutter import (
    ClutterParams,
    DefectMap,
    PointCandidate,
    background_difference,
    cfar_threshold,
    column_offsets,
    difference_peak,
    frame_event,
    local_noise_coarse,
    point_candidates,
    point_contrast,
    rotation_shift_px,
    surround_residuals,
)
from onboard.imaging.detect import Blob, Detection, measure_blob
from onboard.imaging.preprocess import ImagingParams, check_frame
from onboard.imaging.tbd import TbdParams, TrackBeforeDetect, frame_steps

__all__ = [
    "ObjectParams",
    "ObjectTrack",
    "ObjectsUpdate",
    "ObjectTracker",
    "ObjectChain",
    "OBJECT_STATES",
    "objects_message",
]

log = logging.getLogger(__name__)

OBJECT_STATES = ("tentative", "confirmed", "coasting", "lost")
BACKGROUND_SCALE = 4  # the background motion is measured on frames this many times smaller
NOISE_FACTOR = 4  # the local noise (CFAR) is estimated on a grid this many times coarser
TEXTURE_RING_PX = 32  # the texture about a track is sampled this far from it (beyond the noise window's half)
GREY16_PER_GREY8 = 257.0  # 65535 / 255
TEXTURE_REFERENCE_PERCENTILE = 10  # texture is judged against the frame's quietest tenth, not its median
DIFFERENCE_LAG = 8  # frames between the two frames of a track-aided background difference
DIFFERENCE_HALF_PX = 16  # half-side of its square
DIFFERENCE_SIGMA = 5.0  # its threshold in its own noise sigmas
DIFFERENCE_GATE_PX = 3.0  # its gate about the track's prediction
SURROUND_MATCH_RATIO = 1.5  # a track's own displacement must fit its surroundings that much better to call them one
STRIPE_EVERY = 8  # frames between column-offset measurements (and at once after an offset step)


@dataclass(frozen=True)
class ObjectParams:
    """Track management (frames at the camera's rate, pixels).  ``gate_px`` association gate of a
    measured track, widened by ``gate_growth_px`` per coasted frame up to ``max_gate_px``;
    ``alpha``, ``beta``: the filter's gains; ``confirm_hits``; ``tentative_misses``; ``coast_frames``;
    ``defect_every``: frames between defect-map updates; ``primary_hit_ratio``: the least fraction of
    its frames a track must have been measured on to be chosen as the primary; ``primary_radius_px``:
    of the steady tracks this close to the principal point the longest-tracked is chosen.

    Confirmation (M of N with consistent motion in bearing space, moving unlike the background):
    besides ``confirm_hits`` hits, the track must have been measured on ``confirm_in_window`` of the
    last ``confirm_window`` frames, its lines of sight over them projected through this frame's
    rotation (the camera's own rotation removed) must fit a constant image velocity within
    ``max_fit_rms_px`` rms (a fragment of a cloud edge or a thin streak slides back and forth along
    it), and its velocity must differ by ``min_relative_speed_pxpf`` px per frame from the
    background's: the median velocity of the other tentative tracks within ``background_radius_px``
    when there are ``background_min_tracks`` (the local clutter: cloud-edge or terrain fragments
    move with their background), else, where the track lies on texture (local noise over
    ``textured_noise_ratio`` times the frame's quietest tenth), the frame's dominant motion measured by
    phase correlation over ``background_frames`` frames (accepted when its peak response is at least
    ``background_min_response``; and its mean over the window).  On a clear sky there is no
    background to differ from: no test.  Last, the texture about the track must not have moved with
    it (``_surroundings_follow``: the background's motion where the track is).
    Measured on C1-C3 (docs/perception.md): this, not a higher threshold, removes the false tracks.

    Track-aided detection (in a confirmed track's gate, ``aided_threshold_factor`` x the threshold):
    ``aided_max_run`` frames in a row, up to ``aided_max_run_moving`` while its positions still move
    unlike the background (fit within ``aided_max_fit_rms_px``: dim positions scatter more); one measured mostly
    by track-before-detect, within ``dim_max_fit_rms_px`` (its centres scatter 0.3-0.5 px, more on a noisy pose).
    """

    gate_px: float = 4.0
    gate_growth_px: float = 0.5
    max_gate_px: float = 12.0
    alpha: float = 0.6
    beta: float = 0.15
    confirm_hits: int = 5
    tentative_misses: int = 2
    coast_frames: int = 45
    defect_every: int = 4
    primary_hit_ratio: float = 0.8
    confirm_window: int = 15
    confirm_in_window: int = 12
    max_fit_rms_px: float = 0.5
    background_radius_px: float = 120.0
    background_min_tracks: int = 1
    min_relative_speed_pxpf: float = 0.15
    background_frames: int = 4
    background_min_response: float = 0.1
    textured_noise_ratio: float = 2.0
    aided_threshold_factor: float = 0.35
    aided_max_run: int = 10
    aided_max_run_moving: int = 90
    aided_max_fit_rms_px: float = 1.0
    dim_max_fit_rms_px: float = 1.0
    primary_radius_px: float = 40.0

    def __post_init__(self) -> None:
        if not 0 < self.alpha <= 1 or not 0 <= self.beta <= 1:
            raise InputError(f"ObjectParams alpha in (0, 1] and beta in [0, 1], got {self.alpha}, {self.beta}")
        if self.confirm_hits < 1 or self.coast_frames < 0 or self.tentative_misses < 0:
            raise InputError("ObjectParams confirm_hits >= 1, coast_frames and tentative_misses >= 0")
        if not 3 <= self.confirm_in_window <= self.confirm_window:
            raise InputError(
                f"ObjectParams 3 <= confirm_in_window <= confirm_window, got {self.confirm_in_window}, {self.confirm_window}"
            )
        if self.aided_max_run_moving < self.aided_max_run:
            raise InputError(f"ObjectParams aided_max_run_moving < aided_max_run ({self.aided_max_run})")
        if self.background_frames < 1 or not 0 < self.aided_threshold_factor <= 1:
            raise InputError(
                "ObjectParams background_frames >= 1 and aided_threshold_factor in (0, 1], got "
                f"{self.background_frames}, {self.aided_threshold_factor}"
            )


@dataclass(frozen=True)
class ObjectTrack:
    """One object on one frame.  ``object_id`` stable; ``state`` one of :data:`OBJECT_STATES`;
    ``u_px, v_px`` the measured centre (the prediction while coasting); ``bbox`` (x, y, w, h) pixels;
    ``los_ned`` unit line of sight in local NED (None without a pose); ``sigma_rad`` its 1-sigma
    angular uncertainty; ``score`` the detection's contrast over its local threshold (0 while
    coasting); ``hits`` frames measured; ``age_frames`` frames since it started."""

    object_id: int
    state: str
    u_px: float
    v_px: float
    bbox: tuple[float, float, float, float]
    los_ned: tuple[float, float, float] | None
    sigma_rad: float
    score: float
    hits: int
    age_frames: int


@dataclass(frozen=True)
class ObjectsUpdate:
    """Output of one frame: ``objects`` every live track (tentative ones included); ``primary_id`` the
    selected target's id (None: none); ``primary`` its refined detection on this frame (None when not
    measured); ``primary_changed`` the selection changed on this frame; ``event`` ``ok`` / ``frozen``
    / ``step``; ``frame_index``."""

    objects: tuple[ObjectTrack, ...]
    primary_id: int | None
    primary: Detection | None
    primary_changed: bool
    event: str
    frame_index: int

    @property
    def confirmed(self) -> tuple[ObjectTrack, ...]:
        """The objects measured on this frame whose track is confirmed."""
        return tuple(o for o in self.objects if o.state == "confirmed")


@dataclass
class _Track:
    object_id: int
    los: np.ndarray  # unit line of sight, NED
    rate: np.ndarray  # its change per frame
    uv: tuple[float, float]
    bbox: tuple[int, int, int, int]
    hits: int = 1
    misses: int = 0
    age: int = 1
    confirmed: bool = False
    score: float = 0.0
    history: list = field(default_factory=list)  # (frame index, los, u, v) of its last measured frames
    velocity_pxpf: tuple[float, float] | None = None  # rotation-compensated image velocity, this frame
    fit_rms_px: float = math.inf  # rms residual of that constant-velocity fit
    aided_run: int = 0  # consecutive frames measured by track-aided detections only
    dim_hits: int = 0  # frames measured by track-before-detect's reports
    difference: PointCandidate | None = None  # this frame's background-difference detection, if that measured it


class ObjectTracker:
    """See the module docstring.  ``intrinsics``: :class:`onboard.core.frames.PinholeIntrinsics`
    (distortion ignored: the bearing is the pinhole's); ``mode`` ``auto`` or ``operator``."""

    def __init__(
        self,
        intrinsics,
        frame_rate_hz: float = 30.0,
        params: ObjectParams | None = None,
        clutter: ClutterParams | None = None,
        imaging: ImagingParams | None = None,
        mode: str = "auto",
    ) -> None:
        if mode not in ("auto", "operator"):
            raise InputError(f"ObjectTracker mode must be auto or operator, got {mode!r}")
        self.K = intrinsics
        self.frame_rate_hz = float(frame_rate_hz)
        self.params = params or ObjectParams()
        self.clutter = clutter or ClutterParams()
        self.imaging = imaging or ImagingParams()
        self.mode = mode
        self._tracks: list[_Track] = []
        self._next_id = 1  # ids from 1, as the track output counts them
        self._primary: int | None = None
        self._frame_index = -1
        self._last_time_us: int | None = None  # the last frame's time (frame_steps: periods since it)
        self._defects: DefectMap | None = None
        self._prev: np.ndarray | None = None
        self._prev_median: float | None = None
        self._window: np.ndarray | None = None
        self._noise: np.ndarray | None = None  # the last frame's local noise sigma (grey), coarse grid
        self._noise_median = 0.0
        self._noise_floor = 0.0  # the least textured tenth of the frame's local noise (grey)
        self._noise_floor_frame = -1
        self._contrast: np.ndarray | None = None  # the last frame's point contrast and CFAR threshold
        self._threshold: np.ndarray | None = None
        self._stripes: np.ndarray | None = None  # column offsets, re-measured every STRIPE_EVERY frames
        self._coarse: list[tuple[int, np.ndarray, np.ndarray]] = []  # (frame, coarse image, R) of recent frames
        self._background_pxpf: tuple[float, float] | None = None  # the frame's dominant background motion
        self._background_history: list[tuple[int, tuple[float, float]]] = []  # (frame, that motion) of recent frames
        self._difference_ids: set[int] = set()  # id() of this frame's background-difference candidates
        self._tbd_ids: set[int] = set()  # id() of this frame's track-before-detect candidates
        self._poses: dict[int, np.ndarray] = {}  # frame -> R_ned_from_cam, the last confirm_window frames
        self._recent: list[tuple[int, np.ndarray]] = []  # (frame, its pixels) of the last confirm_window
        self.primary_changes = 0
        self.frozen_frames = 0
        self.offset_steps = 0
        im = self.imaging
        tbd = TbdParams(
            threshold_sigma=im.tbd_threshold_sigma,
            track_threshold_sigma=min(TbdParams.track_threshold_sigma, im.tbd_threshold_sigma),
            max_speed_pxpf=im.tbd_max_speed_pxpf,
        )
        self.tbd = TrackBeforeDetect(intrinsics, tbd) if im.tbd else None
        self._clean: np.ndarray | None = None  # the last frame, fixed pattern handled (float32)

    # ------------------------------------------------------------------ geometry

    def _los(self, u: float, v: float, R: np.ndarray) -> np.ndarray:
        K = self.K
        ray = np.array([(u - K.cx_px) / K.fx_px, (v - K.cy_px) / K.fy_px, 1.0])
        b = R @ ray
        return b / np.linalg.norm(b)

    def _project(self, los_ned: np.ndarray, R: np.ndarray) -> tuple[float, float] | None:
        c = R.T @ los_ned
        if c[2] <= 1e-6:
            return None
        K = self.K
        return K.fx_px * c[0] / c[2] + K.cx_px, K.fy_px * c[1] / c[2] + K.cy_px

    # ------------------------------------------------------------------ detection

    def detect(self, image: np.ndarray) -> list[PointCandidate]:
        """The frame's point candidates (fixed pattern handled first; updates the defect map)."""
        p = self.clutter
        img = image.astype(np.float32)
        k = self._frame_index
        # a confirming track's surroundings are compared over its window (the raw frames: the fixed
        # pattern stays put while the scene moves, adding alike to every displacement tried)
        self._recent = [r for r in self._recent if r[0] > k - self.params.confirm_window]
        self._recent.append((k, image.copy() if image.dtype == np.uint8 else img.copy()))
        if p.destripe:
            if self._stripes is None or self._stripes.shape[0] != img.shape[1] or self._frame_index % STRIPE_EVERY == 0:
                self._stripes = column_offsets(img, p.stripe_window_px)  # they drift over minutes: every few frames
            img -= self._stripes[None, :]  # in place on the frame's float copy (remove_column_offsets, one pass less)
        if self._defects is None or self._defects.mask.shape != img.shape:
            self._defects = DefectMap(img.shape, max(p.defect_frames // self.params.defect_every, 2), p.defect_fraction)
        if self._frame_index % self.params.defect_every == 0:
            # the outlier level from the previous frame's noise (the noise is measured after the repair)
            sigma = max(p.defect_outlier_sigma * self._noise_median, 2.0 * p.min_threshold_lsb)
            self._defects.update(img, sigma)
        img = self._defects.repair(img)
        self._clean = img
        # one 3 x 3 box mean serves the noise estimate and the contrast's surround cells
        box3 = cv2.blur(img, (3, 3), borderType=cv2.BORDER_REPLICATE) if p.cell_px == 3 else None
        # the CFAR threshold on the coarse grid, then to full size: one full-size pass instead of three
        noise = local_noise_coarse(img, p.noise_window_px, NOISE_FACTOR, full=False, box3=box3)
        self._noise = noise
        if (self._frame_index + 1) % self.params.defect_every == 0:  # read by the next defect update only
            self._noise_median = float(np.median(noise))
        h, w = img.shape
        threshold = cv2.resize(
            cfar_threshold(noise, p.threshold_sigma, p.min_threshold_lsb), (w, h), interpolation=cv2.INTER_LINEAR
        )
        contrast = point_contrast(img, p, box3)
        self._contrast, self._threshold = contrast, threshold
        return point_candidates(contrast, threshold, p)

    def _aided_candidates(self, cands: list[PointCandidate], R: np.ndarray) -> list[PointCandidate]:
        """Track-aided detection: inside the gate of each confirmed track (measured or coasting) that no
        candidate falls in, the strongest component of the point contrast above ``aided_threshold_factor``
        times the CFAR threshold.  Where an object is already known the prior is strong and a lower
        threshold costs few false alarms (a gate is ~0.1 % of the frame); it bridges the frames where a
        dim or flickering object dips below the whole-frame threshold.  Candidates are added to ``cands``
        (a new list)."""
        p = self.params
        contrast, threshold = self._contrast, self._threshold
        if contrast is None or threshold is None or p.aided_threshold_factor >= 1.0:
            return cands
        h, w = contrast.shape
        out = list(cands)
        self._difference_ids = set()
        for t in self._tracks:
            # a track held only by aided detections for long may have slid onto clutter: it must be
            # seen by the whole-frame threshold again, unless it still moves unlike its textured
            # background (a fragment of terrain or cloud it slid onto would move with it)
            if not t.confirmed or (
                t.aided_run >= p.aided_max_run
                and (t.aided_run >= p.aided_max_run_moving or not self._moves_unlike_background(t, R))
            ):
                continue
            puv = self._project(_unit(t.los + t.rate), R)
            if puv is None:
                continue
            gate = min(p.gate_px + p.gate_growth_px * t.misses, p.max_gate_px)
            if any(math.hypot(c.u_px - puv[0], c.v_px - puv[1]) <= gate for c in out):
                continue
            r = int(math.ceil(gate)) + 2
            x0, y0 = max(int(puv[0]) - r, 0), max(int(puv[1]) - r, 0)
            x1, y1 = min(int(puv[0]) + r + 1, w), min(int(puv[1]) + r + 1, h)
            if x1 - x0 < 3 or y1 - y0 < 3:
                continue
            roi = point_candidates(
                contrast[y0:y1, x0:x1], threshold[y0:y1, x0:x1] * np.float32(p.aided_threshold_factor), self.clutter
            )
            best = None
            for c in roi:
                u, v = c.u_px + x0, c.v_px + y0
                if math.hypot(u - puv[0], v - puv[1]) <= gate and (best is None or c.score > best.score):
                    best = dataclasses.replace(
                        c, u_px=u, v_px=v, bbox=(c.bbox[0] + x0, c.bbox[1] + y0, c.bbox[2], c.bbox[3])
                    )
            if best is None:
                best = self._difference_candidate(t, puv, gate, R)
                if best is not None:
                    self._difference_ids.add(id(best))
            if best is not None:
                out.append(best)
        return out

    def _difference_candidate(self, t: _Track, puv: tuple[float, float], gate: float, R: np.ndarray):
        """Track-aided detection against the background (where its motion is known): this frame minus the
        one ``DIFFERENCE_LAG`` frames earlier registered on the prediction's surroundings, searched about
        the camera's rotation plus that motion (:func:`onboard.imaging.clutter.background_difference`)."""
        k = self._frame_index
        bg = self._background_over_window()
        # another object in the square moves unlike the background too: whose difference is whose is
        # ambiguous (at C3's crossing it swapped the two targets' ids)
        if any(
            o is not t and o.confirmed and max(abs(o.uv[0] - puv[0]), abs(o.uv[1] - puv[1])) <= DIFFERENCE_HALF_PX
            for o in self._tracks
        ):
            return None
        old, R0 = dict(self._recent).get(k - DIFFERENCE_LAG), self._poses.get(k - DIFFERENCE_LAG)
        if bg is None or old is None or R0 is None or not self._recent or self._recent[-1][0] != k:
            return None
        # where the background now at puv was DIFFERENCE_LAG frames ago: the rotation's share, then its own motion
        p0 = self._project(self._los(puv[0], puv[1], R), R0)
        if p0 is None:
            return None
        du, dv = puv[0] - p0[0] + bg[0] * DIFFERENCE_LAG, puv[1] - p0[1] + bg[1] * DIFFERENCE_LAG
        diff, _ = background_difference(self._recent[-1][1], old, puv, (du, dv), DIFFERENCE_HALF_PX)
        # a tighter gate than the point's: the difference keeps residuals of sharp field edges a few px away
        return difference_peak(
            diff, puv, min(gate, DIFFERENCE_GATE_PX), DIFFERENCE_SIGMA, self.clutter.min_threshold_lsb
        )

    # ------------------------------------------------------------------ step

    def update(self, image: np.ndarray, R_ned_from_cam=None, time_boot_us: int | None = None) -> ObjectsUpdate:
        image = check_frame(image)
        self._frame_index += 1
        self.frame_steps = frame_steps(self._last_time_us, time_boot_us, self.frame_rate_hz)
        self._last_time_us = time_boot_us
        for t in (t for t in self._tracks if 2 * t.dim_hits < t.hits):  # dropped frames (see tbd.frame_steps)
            t.los = _unit(t.los + (self.frame_steps - 1) * t.rate)
        R = np.eye(3) if R_ned_from_cam is None else np.asarray(R_ned_from_cam, dtype=np.float64)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise InputError(f"R_ned_from_cam must be a finite 3 x 3 rotation, got shape {R.shape}")
        # step_lsb is in 8-bit grey: a 16-bit frame's grey is 257 times finer (its noise alone moves the
        # median by more than 3 of its steps, and every frame would restart the defect map)
        step = self.clutter.step_lsb * (GREY16_PER_GREY8 if image.dtype == np.uint16 else 1.0)
        event, med = frame_event(image, self._prev, self._prev_median, step)
        self._prev, self._prev_median = image, med
        if event == "frozen":
            self.frozen_frames += 1
            for t in self._tracks:  # time passes, nothing is measured: predict without counting a miss
                t.los = _unit(t.los + t.rate)
                t.age += 1
            return self._output(image, R, event, measured=set(), changed=False)
        if event == "step":
            self.offset_steps += 1
            log.info("frame %d: offset step (flat-field correction); defect map restarted", self._frame_index)
            if self._defects is not None:
                self._defects.reset()
            self._stripes = None
        regular = self.detect(image)
        dim = [] if self.tbd is None or self._clean is None else self._tbd_candidates(self.tbd, self._clean, regular, R)
        self._tbd_ids, regular = {id(c) for c in dim}, regular + dim
        self._background_motion(image, R)  # before the aided detections: it may extend their runs
        cands = self._aided_candidates(regular, R)
        measured = self._associate(cands, R, len(regular))
        changed = self._select(R)
        return self._output(image, R, event, measured, changed)

    def _tbd_candidates(
        self, tbd: TrackBeforeDetect, clean: np.ndarray, regular: list[PointCandidate], R: np.ndarray
    ) -> list[PointCandidate]:
        """Track-before-detect's dim points (:mod:`onboard.imaging.tbd`; it follows only a primary it found)."""
        focus = None
        prim = next((t for t in self._tracks if t.object_id == self._primary), None)
        if prim is not None:
            focus = self._project(_unit(prim.los + prim.rate), R) or prim.uv
        return tbd.update(clean, R, focus, regular)

    def _associate(self, cands: list[PointCandidate], R: np.ndarray, n_regular: int | None = None) -> set[int]:
        """Greedy nearest-first association; ``cands[n_regular:]`` are track-aided candidates, which
        update their track but never start one."""
        p = self.params
        n_regular = len(cands) if n_regular is None else n_regular
        preds = []
        for t in self._tracks:
            pl = _unit(t.los + t.rate)
            preds.append((pl, self._project(pl, R)))
        pairs: list[tuple[float, int, int]] = []
        live = [ti for ti, (_, puv) in enumerate(preds) if puv is not None]
        if live and cands:
            # every track-candidate distance at once (tens of each on a cluttered frame)
            puv_a = np.array([preds[ti][1] for ti in live])
            cuv = np.array([(c.u_px, c.v_px) for c in cands])
            d = np.hypot(puv_a[:, 0:1] - cuv[None, :, 0], puv_a[:, 1:2] - cuv[None, :, 1])
            gate = np.minimum(
                p.gate_px + p.gate_growth_px * np.array([self._tracks[ti].misses for ti in live]), p.max_gate_px
            )
            li, ci_a = np.nonzero(d <= gate[:, None])
            pairs = sorted((float(d[a, b]), live[a], int(b)) for a, b in zip(li, ci_a))
        used_t: set[int] = set()
        used_c: set[int] = set()
        measured: set[int] = set()
        for _, ti, ci in pairs:
            if ti in used_t or ci in used_c:
                continue
            used_t.add(ti)
            used_c.add(ci)
            t, c = self._tracks[ti], cands[ci]
            z = self._los(c.u_px, c.v_px, R)
            pl = preds[ti][0]
            r = z - pl
            n = t.misses + 1
            t.los = _unit(pl + p.alpha * r)
            t.rate = t.rate + (p.beta / n) * r
            t.uv, t.bbox, t.score = (c.u_px, c.v_px), c.bbox, c.score
            t.hits += 1
            t.misses = 0
            t.age += 1
            t.aided_run = t.aided_run + 1 if ci >= n_regular else 0
            t.difference = c if id(c) in self._difference_ids else None
            t.dim_hits += id(c) in self._tbd_ids
            # confirmed tracks keep theirs too: an aided run is extended only while it moves unlike its background
            t.history.append((self._frame_index, z, c.u_px, c.v_px))
            if t.confirmed and len(t.history) > p.confirm_window:
                del t.history[0]
            measured.add(t.object_id)
        keep: list[_Track] = []
        for ti, t in enumerate(self._tracks):
            if ti in used_t:
                keep.append(t)
                continue
            t.los = preds[ti][0]
            t.misses += 1
            t.age += 1
            t.score = 0.0
            limit = p.coast_frames if t.confirmed else p.tentative_misses
            if t.misses > limit or preds[ti][1] is None:
                if t.confirmed:
                    log.debug("object %d lost after %d frames without a detection", t.object_id, t.misses)
                continue
            keep.append(t)
        for ci, c in enumerate(cands[:n_regular]):
            if ci in used_c:
                continue
            los = self._los(c.u_px, c.v_px, R)
            keep.append(
                _Track(
                    self._next_id,
                    los,
                    np.zeros(3),
                    (c.u_px, c.v_px),
                    c.bbox,
                    score=c.score,
                    history=[(self._frame_index, los, c.u_px, c.v_px)],
                )
            )
            measured.add(self._next_id)
            self._next_id += 1
        self._tracks = keep
        self._confirm(R)
        return measured

    def _background_motion(self, image: np.ndarray, R: np.ndarray) -> None:
        """The dominant image motion of the background over the last ``background_frames`` frames, the
        camera's rotation removed (px per frame, in this frame's image), by phase correlation of
        ``BACKGROUND_SCALE`` times smaller frames (Kuglin & Hines 1975); None on a featureless frame
        (a clear sky: the correlation peak is weak and the shift meaningless)."""
        p = self.params
        h, w = image.shape
        small = cv2.resize(
            np.asarray(image, dtype=np.float32),
            (w // BACKGROUND_SCALE, h // BACKGROUND_SCALE),
            interpolation=cv2.INTER_AREA,
        )
        k = self._frame_index
        self._coarse = [c for c in self._coarse if c[0] >= k - p.background_frames]
        self._background_pxpf = None
        if self._coarse and self._coarse[0][1].shape == small.shape:
            k0, old, R0 = self._coarse[0]
            if self._window is None or self._window.shape != small.shape:
                self._window = cv2.createHanningWindow((small.shape[1], small.shape[0]), cv2.CV_32F)
            (du, dv), response = cv2.phaseCorrelate(old, small, self._window)
            if response >= p.background_min_response:
                # where a point at infinity seen at the image centre on frame k0 is now: the rotation's share
                shift = rotation_shift_px(self.K, self.K.cx_px, self.K.cy_px, R0, R)
                if shift is not None:
                    ru, rv = shift
                    n = k - k0
                    self._background_pxpf = (
                        (du * BACKGROUND_SCALE - ru) / n,
                        (dv * BACKGROUND_SCALE - rv) / n,
                    )
        self._coarse.append((k, small, R))
        self._poses = {q: r for q, r in self._poses.items() if q > k - p.confirm_window}
        self._poses[k] = R
        self._background_history = [b for b in self._background_history if b[0] > k - p.confirm_window]
        if self._background_pxpf is not None:
            self._background_history.append((k, self._background_pxpf))

    def _surroundings_follow(self, t: _Track) -> bool:
        """The texture about the track on the oldest of its recent frames, moved by the track's own image
        displacement since, matches this frame's ``SURROUND_MATCH_RATIO`` times better than moved 2 px
        otherwise (:func:`onboard.imaging.clutter.surround_residuals`): the background's motion where
        the track is, which the frame-wide one misses (looking down at a slant the nearer ground flows
        ~30 % faster than the whole frame, C2) and no neighbour track always stands for."""
        if len(t.history) < 2:
            return False
        k0, _, u0, v0 = t.history[0]
        old = next((img for k, img in self._recent if k == k0), None)
        cur = self._recent[-1][1] if self._recent and self._recent[-1][0] == self._frame_index else None
        if old is None or cur is None:
            return False
        # the displacement from a straight-line fit of its measured pixels (each jitters by tenths of a px)
        f = np.array([e[0] for e in t.history], dtype=np.float64)
        slope = np.polyfit(f, np.array([(e[2], e[3]) for e in t.history]), 1)[0] * (self._frame_index - k0)
        own, alt = surround_residuals(cur, old, t.uv, (float(slope[0]), float(slope[1])))
        log.debug("surroundings of %d: own %.3f alt %.3f", t.object_id, own, alt)
        return bool(own * SURROUND_MATCH_RATIO < alt)  # False when either is nan (too few pixels)

    def _background_over_window(self) -> tuple[float, float] | None:
        """The frame's background motion averaged over the ``confirm_window`` frames a velocity is fitted
        over (one 4-frame estimate wanders by 0.1-0.2 px/frame); None unless measured on half of them."""
        hist = self._background_history
        if 2 * len(hist) < self.params.confirm_window:
            return None
        m = np.mean(np.array([b[1] for b in hist]), axis=0)
        return float(m[0]), float(m[1])

    def _confirm(self, R: np.ndarray) -> None:
        """Confirm the tentative tracks that pass the M-of-N, constant-velocity and moves-unlike-its-
        background tests (see :class:`ObjectParams`)."""
        p = self.params
        k = self._frame_index
        tentative = [t for t in self._tracks if not t.confirmed]
        for t in tentative:
            t.history = [h for h in t.history if h[0] > k - p.confirm_window]
            t.velocity_pxpf = None
        if not any(
            t.hits >= p.confirm_hits and t.misses == 0 and len(t.history) >= p.confirm_in_window for t in tentative
        ):
            return  # nothing to confirm on this frame: no fits needed
        fitted = [t for t in tentative if len(t.history) >= 3]
        if fitted:
            vel, rms = self._fit_all([t.history for t in fitted], R)
            for t, v, r in zip(fitted, vel, rms):
                t.velocity_pxpf = (float(v[0]), float(v[1]))
                t.fit_rms_px = float(r)
        for t in tentative:
            if t.hits < p.confirm_hits or t.misses > 0 or len(t.history) < p.confirm_in_window:
                continue
            fit_limit = p.dim_max_fit_rms_px if 2 * t.dim_hits >= t.hits else p.max_fit_rms_px
            if t.velocity_pxpf is None or t.fit_rms_px > fit_limit:
                continue
            bg = [
                o.velocity_pxpf
                for o in tentative
                if o is not t
                and o.velocity_pxpf is not None
                and math.hypot(o.uv[0] - t.uv[0], o.uv[1] - t.uv[1]) <= p.background_radius_px
            ]
            # the background's motion, from each source available; the track must move unlike every one
            backgrounds = []
            if len(bg) >= p.background_min_tracks:
                backgrounds.append(np.median(np.asarray(bg), axis=0))
            if self._background_pxpf is not None and self._textured(t):
                backgrounds.append(np.asarray(self._background_pxpf))
                mean_bg = self._background_over_window()
                if mean_bg is not None:
                    backgrounds.append(np.asarray(mean_bg))
            rel = min(
                (math.hypot(t.velocity_pxpf[0] - vb[0], t.velocity_pxpf[1] - vb[1]) for vb in backgrounds),
                default=math.nan,
            )
            if rel < p.min_relative_speed_pxpf:
                continue
            if self._surroundings_follow(t):
                continue
            t.confirmed = True
            log.debug(
                "object %d confirmed at (%.1f, %.1f): rms %.2f px, velocity (%.2f, %.2f) px/frame, %d background"
                " tracks, relative %.2f px/frame",
                t.object_id,
                t.uv[0],
                t.uv[1],
                t.fit_rms_px,
                t.velocity_pxpf[0],
                t.velocity_pxpf[1],
                len(bg),
                rel,
            )

    def _moves_unlike_background(self, t: _Track, R: np.ndarray) -> bool:
        """The background's motion is known (no: a clear sky) and the track's last ``confirm_window``
        frames' positions (``confirm_hits`` at least) fit a constant velocity within
        ``aided_max_fit_rms_px`` differing from it by ``min_relative_speed_pxpf``."""
        p, bg = self.params, self._background_over_window()
        recent = [h for h in t.history if h[0] > self._frame_index - p.confirm_window]
        if bg is None or len(recent) < max(p.confirm_hits, 3):
            return False
        vel, rms = self._fit_all([recent], R)
        rel = math.hypot(float(vel[0, 0]) - bg[0], float(vel[0, 1]) - bg[1])
        return bool(rms[0] <= p.aided_max_fit_rms_px and rel >= p.min_relative_speed_pxpf)

    def _textured(self, t: _Track) -> bool:
        """The track lies where the local noise (texture) is ``textured_noise_ratio`` times the frame's
        median: cloud or terrain, whose motion the frame's background motion stands for; on a clear
        sky there is no background to differ from."""
        noise = self._noise
        if noise is None:
            return False
        h, w = noise.shape  # the coarse grid: NOISE_FACTOR pixels a cell
        # sampled on a ring about the track, not under it: a bright point raises its own local noise
        r = TEXTURE_RING_PX
        samples = [
            noise[
                min(max((int(t.uv[1]) + di) // NOISE_FACTOR, 0), h - 1),
                min(max((int(t.uv[0]) + dj) // NOISE_FACTOR, 0), w - 1),
            ]
            for di, dj in ((-r, 0), (r, 0), (0, -r), (0, r), (-r, -r), (-r, r), (r, -r), (r, r))
        ]
        if self._noise_floor_frame != self._frame_index:  # once a frame, and only when asked
            self._noise_floor = float(np.percentile(noise, TEXTURE_REFERENCE_PERCENTILE))
            self._noise_floor_frame = self._frame_index
        return bool(float(np.median(samples)) > self.params.textured_noise_ratio * self._noise_floor)

    def _fit_all(self, histories: list[list], R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Constant-velocity least-squares fits of tracks' measured lines of sight projected through
        this frame's camera rotation (the camera's own rotation removed), all tracks at once (padded
        rows, weights 0 on the padding): velocities (n, 2) px per frame and rms residuals (n,) px.  The
        rms is the smaller of that fit's and the same fit's on the measured pixels: an attitude that
        jitters or lags the frame (an extrapolated pose) scatters the projected positions of a point
        the image holds still; the velocities stay the projected ones, the frame every track and the
        background motion are compared in."""
        K = self.K
        n = len(histories)
        width = max(len(h) for h in histories)
        los = np.array([e[1] for h in histories for e in h])
        c = los @ R  # rows: R.T @ los
        z = np.maximum(c[:, 2], 1e-6)
        row = np.repeat(np.arange(n), [len(h) for h in histories])
        col = np.concatenate([np.arange(len(h)) for h in histories])
        w = np.zeros((n, width))
        f = np.zeros((n, width))
        w[row, col] = 1.0
        f[row, col] = [e[0] for h in histories for e in h]
        u = np.zeros((n, width))
        v = np.zeros((n, width))
        u[row, col] = K.fx_px * c[:, 0] / z
        v[row, col] = K.fy_px * c[:, 1] / z
        vel, rms = _cv_fit(f, u, v, w)
        u[row, col] = [e[2] for h in histories for e in h]
        v[row, col] = [e[3] for h in histories for e in h]
        _, rms_px = _cv_fit(f, u, v, w)
        return vel, np.minimum(rms, rms_px)

    def _select(self, R: np.ndarray) -> bool:
        alive = {t.object_id: t for t in self._tracks if t.confirmed}
        if self._primary is not None and self._primary in alive:
            return False
        old = self._primary
        self._primary = None
        if self.mode == "auto":
            p, K = self.params, self.K
            # a steady track that missed this frame still counts (a target dips below the threshold
            # now and then): otherwise a farther one is taken in its place on that frame
            steady = [
                t
                for t in self._tracks
                if t.misses <= p.tentative_misses and t.hits >= p.confirm_hits and t.hits >= p.primary_hit_ratio * t.age
            ]
            if steady:

                def off_centre(t: _Track) -> float:
                    return math.hypot(t.uv[0] - K.cx_px, t.uv[1] - K.cy_px)

                # where the gimbal points: of the steady tracks about the centre the longest-tracked one
                # (two objects near one line of sight: the one the camera has been holding), else the nearest
                central = [t for t in steady if off_centre(t) <= p.primary_radius_px]
                if central:
                    best = max(central, key=lambda t: (t.hits, -off_centre(t), -t.object_id))
                else:
                    best = min(steady, key=lambda t: (off_centre(t), t.object_id))
                # chosen once confirmed, i.e. once it has moved unlike its background, and measured on
                # this frame: a fragment of terrain or cloud near the centre is never chosen, and until
                # the steady track nearest the centre is confirmed no other is taken in its place
                if best.confirmed and best.misses == 0:
                    self._primary = best.object_id
        if self._primary != old:
            self.primary_changes += 1
            log.info("primary target: object %s (was %s)", self._primary, old)
            return True
        return False

    def clear_primary(self) -> None:
        """No primary target (until the next selection or, in auto mode, the next frame's choice)."""
        if self._primary is not None:
            self.primary_changes += 1
            log.info("primary target: none (was object %d)", self._primary)
        self._primary = None

    def clear_tracks(self) -> None:
        """Forget every track and the primary; ids are not reused."""
        self.clear_primary()
        self._tracks = []

    def select_point(self, u_px: float, v_px: float, radius_px: float) -> int | None:
        """Make the confirmed or coasting track nearest (u, v) within ``radius_px`` the primary; its id,
        or None (the primary is then unchanged)."""
        best, best_d = None, radius_px
        for t in self._tracks:
            d = math.hypot(t.uv[0] - u_px, t.uv[1] - v_px)
            if t.confirmed and d <= best_d:
                best, best_d = t, d
        if best is None:
            return None
        if best.object_id != self._primary:
            self.primary_changes += 1
            log.info("primary target: object %d selected by the operator (was %s)", best.object_id, self._primary)
        self._primary = best.object_id
        return best.object_id

    def _output(self, image: np.ndarray, R: np.ndarray, event: str, measured: set[int], changed: bool) -> ObjectsUpdate:
        objs = []
        primary_det = None
        sigma_rad = 1.0 / self.K.fx_px
        for t in self._tracks:
            if not t.confirmed:
                state = "tentative"
            elif t.object_id in measured:
                state = "confirmed"
            else:
                state = "coasting"
            if state == "coasting":
                puv = self._project(t.los, R)
                if puv is None:
                    continue
                u, v = puv
            else:
                u, v = t.uv
            x, y, w, h = t.bbox
            box = (u - w / 2, v - h / 2, float(w), float(h))
            if t.object_id == self._primary and state == "confirmed" and t.difference is not None:
                # measured against the background only: a centroid on the raw frame there is pulled towards
                # the field edge beside it (C2: 0.98 px rms in v against ~0.3 px for the difference's own)
                c, (ih, iw) = t.difference, image.shape
                raw = float(image[min(max(int(v), 0), ih - 1), min(max(int(u), 0), iw - 1)])
                # contrast and flux: the difference's; snr: its peak in its noise sigmas (unless the floor set its threshold)
                primary_det = Detection(
                    u, v, c.area_px, c.peak, c.peak * c.area_px, c.bbox, raw, c.score * DIFFERENCE_SIGMA
                )
            elif t.object_id == self._primary and state == "confirmed":
                # a point only track-before-detect saw: its integrated centre is the measurement (the single
                # frame's centroid fails or wanders by pixels at a few NETD)
                det = None if self.tbd is None else self.tbd.detection_at(t.uv, image)
                if det is None:
                    det = measure_blob(image, Blob(t.bbox, max(w * h, 1), t.score), self.imaging, 0.0)
                    if det is not None and math.hypot(det.u_px - u, det.v_px - v) > self.params.gate_px:
                        det = None
                if det is not None:
                    primary_det = det
                    u, v = det.u_px, det.v_px
            los = tuple(float(a) for a in self._los(u, v, R))
            objs.append(
                ObjectTrack(
                    t.object_id,
                    state,
                    float(u),
                    float(v),
                    box,
                    los,  # type: ignore[arg-type]
                    sigma_rad * (1 + t.misses),
                    float(t.score),
                    t.hits,
                    t.age,
                )
            )
        return ObjectsUpdate(tuple(objs), self._primary, primary_det, changed, event, self._frame_index)


def _cv_fit(f: np.ndarray, u: np.ndarray, v: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row-wise least-squares fits ``(u, v) = a + b f`` over the entries with weight ``w`` 1 (padding
    0): the slopes (n, 2) and the rms residuals (n,)."""
    cnt = w.sum(axis=1, keepdims=True)
    fc = (f - (w * f).sum(axis=1, keepdims=True) / cnt) * w
    uc = (u - (w * u).sum(axis=1, keepdims=True) / cnt) * w
    vc = (v - (w * v).sum(axis=1, keepdims=True) / cnt) * w
    den = np.maximum((fc * fc).sum(axis=1), 1e-12)
    vu = (fc * uc).sum(axis=1) / den
    vv = (fc * vc).sum(axis=1) / den
    ru = (uc - vu[:, None] * fc) * w
    rv = (vc - vv[:, None] * fc) * w
    return np.stack([vu, vv], axis=1), np.sqrt((ru * ru + rv * rv).sum(axis=1) / cnt[:, 0])


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else v


class ObjectChain:
    """:class:`ObjectTracker` behind :class:`~onboard.imaging.TargetTracker`'s interface: the primary
    target as a :class:`~onboard.imaging.TrackUpdate` (``track_id`` = its object id, so a change of
    selection is a new track id and the frame pipeline restarts the 3-D estimate and says so), every
    object in :attr:`last_objects`.  ``uses_pose``: the frame pipeline passes each frame's
    ``R_ned_from_cam`` to :meth:`update` (None when it has no pose yet: the last one is kept, the
    camera taken as still since)."""

    uses_pose = True

    def __init__(
        self, intrinsics, params: ImagingParams | None = None, mode: str = "auto", frame_rate_hz: float = 30.0
    ) -> None:
        self.objects = ObjectTracker(intrinsics, frame_rate_hz, imaging=params, mode=mode)
        self.mode = mode
        self.last_objects: ObjectsUpdate | None = None
        self.rejected_frames = 0
        self._R: np.ndarray | None = None
        self._last_primary: int | None = None

    def update(self, image: np.ndarray, R_ned_from_cam: np.ndarray | None = None, time_boot_us: int | None = None):
        try:
            image = check_frame(image)
        except InputError:
            self.rejected_frames += 1
            raise
        if R_ned_from_cam is not None:
            self._R = np.asarray(R_ned_from_cam, dtype=np.float64)
        out = self.objects.update(image, self._R, time_boot_us)
        self.last_objects = out
        return self._track_update(out)

    def _track_update(self, out: ObjectsUpdate):
        from onboard.imaging.tracker import TrackState, TrackUpdate

        prim = next((o for o in out.objects if o.object_id == out.primary_id), None)
        lost = self._last_primary is not None and self._last_primary != out.primary_id
        self._last_primary = out.primary_id
        if prim is None:
            state = TrackState.LOST if lost else TrackState.SEARCHING
            return TrackUpdate(state, None, None, None, None, False, None, None, out.frame_index)
        if prim.state == "confirmed" and out.primary is not None:
            d = out.primary
            return TrackUpdate(
                TrackState.TRACKING,
                d.u_px,
                d.v_px,
                prim.bbox,
                d,
                not d.touches_border,
                prim.object_id,
                0,
                out.frame_index,
            )
        misses = max(prim.age_frames - prim.hits, 1)
        return TrackUpdate(
            TrackState.COASTING, prim.u_px, prim.v_px, prim.bbox, None, False, prim.object_id, misses, out.frame_index
        )

    def select_point(self, image: np.ndarray, u_px: float, v_px: float, radius_px: float):
        """Update on ``image``, then make the object nearest (u, v) within ``radius_px`` the primary;
        its TrackUpdate, or None (nothing there: the selection is unchanged)."""
        self.update(image, None)
        sel = self.objects.select_point(u_px, v_px, radius_px)
        if sel is None or self.last_objects is None:
            return None
        self.objects.mode = self.mode  # a selection ends a stop's hold
        # this frame measured the object already (before it was selected): reported from its track,
        # not fit for 3-D; the next frame measures it as the primary
        self.last_objects = dataclasses.replace(self.last_objects, primary_id=sel, primary=None, primary_changed=True)
        return self._track_update(self.last_objects)

    def select_rectangle(self, image: np.ndarray, rect_px: tuple[float, float, float, float]):
        x0, y0, x1, y1 = rect_px
        return self.select_point(image, 0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.5 * math.hypot(x1 - x0, y1 - y0))

    def stop(self) -> None:
        """Drop the selection and hold: no automatic choice until the next selection."""
        self.objects.mode = "operator"
        self.objects.clear_primary()

    def reset(self) -> None:
        """Forget every track (ids continue)."""
        self.objects.clear_tracks()


def objects_message(
    update: ObjectsUpdate, time_boot_us: int, time_unix_us: int | None = None, time_unix_sigma_us: int | None = None
) -> dict:
    """The ``irtrack/<vehicle>/objects`` message of one frame (JSON-ready, schema ``irtrack.objects/1``):
    ``time_boot_us``, ``time_unix_us`` and ``time_unix_sigma_us`` (the frame's UTC and its 1-sigma, us, as in
    the track; null until the daemon maps its boot clock to UTC), ``frame_index``, ``primary_id`` and ``objects``, one per confirmed or coasting
    object: ``id``, ``state``, ``u_px``, ``v_px``, ``box_px`` [x, y, w, h], ``los_ned`` (unit line of
    sight, local NED, or null), ``los_sigma_rad`` (its 1-sigma), ``score`` (detection contrast over
    the local threshold, 0 while coasting) and ``primary``."""
    return {
        "schema": "irtrack.objects/1",
        "time_boot_us": int(time_boot_us),
        "time_unix_us": None if time_unix_us is None else int(time_unix_us),
        "time_unix_sigma_us": None if time_unix_sigma_us is None else int(time_unix_sigma_us),
        "frame_index": update.frame_index,
        "primary_id": update.primary_id,
        "objects": [
            {
                "id": o.object_id,
                "state": o.state,
                "u_px": round(o.u_px, 3),
                "v_px": round(o.v_px, 3),
                "box_px": [round(b, 2) for b in o.bbox],
                "los_ned": None if o.los_ned is None else [round(c, 7) for c in o.los_ned],
                "los_sigma_rad": o.sigma_rad,
                "score": round(o.score, 3),
                "primary": o.object_id == update.primary_id,
            }
            for o in update.objects
            if o.state in ("confirmed", "coasting")
        ],
    }
