"""Single-target tracker: detection for precision, OpenCV KCF for continuity.

One call of :meth:`TargetTracker.update` per frame.  Modes (``mode``): ``auto`` acquires by
itself (below); ``operator`` never does: a track starts only by :meth:`TargetTracker.select_point`
(the warm object nearest a point within a radius) or :meth:`TargetTracker.select_rectangle` (the
object in a rectangle), each called instead of ``update`` on a frame, and re-acquisition never
jumps to another object.  :meth:`TargetTracker.stop` ends the track and holds either mode idle
until the next selection.  States (:class:`TrackState`):

``searching``  no track yet (or after :meth:`reset`): full-frame detection; the detection with
               the largest flux starts a track (new ``track_id``) and seeds KCF.
``tracking``   this frame's centre is a blob centroid (``measurement_valid`` unless the blob's
               centroid window touches the image border).
``coasting``   no blob this frame, ``1 <= frames_since_measurement < lost_frames``.  For the
               first ``coast_frames`` frames the KCF centre (if KCF still locks) is reported as
               ``u_px, v_px`` with ``measurement_valid = False``; after that ``u_px, v_px`` are None.
``lost``       ``lost_frames`` frames without a blob: the track is dropped; full-frame detection
               continues, and the next detection starts a new track.

Per frame while a track exists: predict the centre (last centroid + constant pixel velocity);
pre-process a region of interest around it (the KCF search patch grown by ``roi_margin_px``);
run KCF on the double-thresholded residual of that region (:func:`kcf_image_u8`, the paper's
KCF input; the rest of KCF's 8-bit frame stays black); detect blobs in the region and take the
one nearest KCF's centre (or the prediction when KCF fails or lands farther than
``kcf_gate_px`` from the prediction).  KCF is re-seeded on the blob when it failed or drifted
more than ``max_drift_px`` from the centroid.  No blob in the region: the
full frame is searched (re-acquisition after a jump); a blob found within ``coast_frames``
frames and ``reacquire_gate_px`` of the prediction keeps the track id, otherwise it starts a
new one (the association is no longer trusted; the estimator should start a new segment).

``update`` raises :class:`~onboard.core.errors.InputError` only for a frame that is not a 2-D
uint8/uint16 array (the tracker state is then unchanged and ``rejected_frames`` counts it); any
pixel content is handled.  A change of frame size ends the current track (state ``lost``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum

import cv2
import numpy as np

from onboard.core.errors import InputError
from onboard.imaging.detect import Detection, find_blobs, measure_blob
from onboard.imaging.preprocess import ImagingParams, Preprocessed, Region, check_frame, kcf_image_u8, preprocess_frame

__all__ = ["TRACKER_MODES", "TrackState", "TrackUpdate", "TargetTracker", "create_kcf"]

log = logging.getLogger(__name__)

VELOCITY_SMOOTHING = 0.5  # weight of the newest pixel-velocity sample in the constant-velocity prediction
TRACKER_MODES = ("auto", "operator")  # automatic acquisition, or only what an operator selects
KCF_FULL_SCALE_HIGHS = 2.0  # KCF sees the residual saturated at this many Th_high: the blob's shape, not its heat


class TrackState(str, Enum):
    SEARCHING = "searching"
    TRACKING = "tracking"
    COASTING = "coasting"
    LOST = "lost"


@dataclass(frozen=True)
class TrackUpdate:
    """The tracker's output for one frame.

    ``u_px, v_px``: target centre in the frames.py pixel convention, None when this frame has no
    image measurement (blob centroid when ``detection`` is set, KCF box centre while coasting);
    ``bbox``: (x, y, w, h) KCF / predicted box in pixels, None without a track;
    ``measurement_valid``: True only when the centre is a blob centroid fit for 3-D
    reconstruction; ``track_id``: id of the current track (increments per new track), None
    without one; ``frames_since_measurement``: 0 on a measured frame, None without a track;
    ``frame_index``: 0-based count of accepted frames; ``kcf_ok``: KCF's update located the
    target in this frame (False on a frame where KCF is (re-)seeded from a detection).
    """

    state: TrackState
    u_px: float | None
    v_px: float | None
    bbox: tuple[float, float, float, float] | None
    detection: Detection | None
    measurement_valid: bool
    track_id: int | None
    frames_since_measurement: int | None
    frame_index: int
    kcf_ok: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.state, TrackState):
            raise InputError(f"TrackUpdate.state must be a TrackState, got {self.state!r}")
        if (self.u_px is None) != (self.v_px is None):
            raise InputError("TrackUpdate.u_px and v_px must both be set or both be None")
        if self.measurement_valid and (self.detection is None or self.u_px is None):
            raise InputError("TrackUpdate.measurement_valid requires a detection and a centre")
        if self.state == TrackState.TRACKING and self.detection is None:
            raise InputError("TrackUpdate.state 'tracking' requires a detection")
        if self.state in (TrackState.SEARCHING, TrackState.LOST) and self.track_id is not None:
            raise InputError(f"TrackUpdate.track_id must be None in state {self.state.value!r}")


def create_kcf(params: ImagingParams):
    """An OpenCV KCF tracker on grey features only (no colour names, no PCA worth speaking of).

    ``desc_pca = desc_npca = GRAY`` with ``compressed_size = 1``: the contrib implementation needs
    both feature sets non-empty, and the default (CN) needs 3 channels.  Works across
    opencv-contrib 4.x (``TrackerKCF_create``) and 5.x (``TrackerKCF.create``).
    """
    p = cv2.TrackerKCF_Params()  # type: ignore[attr-defined]  # opencv-contrib: cv2's stubs list the main modules
    p.desc_pca = cv2.TrackerKCF_GRAY if hasattr(cv2, "TrackerKCF_GRAY") else cv2.TRACKER_KCF_GRAY
    p.desc_npca = p.desc_pca
    p.compressed_size = 1
    p.detect_thresh = float(params.kcf_detect_threshold)
    factory = getattr(cv2.TrackerKCF, "create", None) or cv2.TrackerKCF_create  # type: ignore[attr-defined]  # as above
    return factory(p)


def _box4(box: Sequence[float]) -> tuple[float, float, float, float]:
    """An (x, y, w, h) box (OpenCV's, a detection's) as four floats."""
    x, y, w, h = box
    return float(x), float(y), float(w), float(h)


class TargetTracker:
    """Detection + KCF single-target tracker (see the module docstring). Not thread-safe."""

    def __init__(self, params: ImagingParams | None = None, mode: str = "auto") -> None:
        self.params = params if params is not None else ImagingParams()
        if not isinstance(self.params, ImagingParams):
            raise InputError(f"params must be an ImagingParams, got {type(self.params).__name__}")
        if mode not in TRACKER_MODES:
            raise InputError(f"tracker mode must be one of {', '.join(TRACKER_MODES)}, got {mode!r}")
        self.mode = mode
        self._hold = False  # STOP_TRACKING: no automatic acquisition until the next selection
        self.selections = 0
        self.rejected_frames = 0
        self.kcf_reseeds = 0
        self.reacquisitions = 0
        self._next_track_id = 1
        self._frame_index = 0
        self._shape: tuple[int, int] | None = None
        self._buf = np.zeros((0, 0), dtype=np.uint8)  # KCF's input image, allocated at the frame size
        self._buf_region: Region | None = None
        self._drop_track(TrackState.SEARCHING)

    # ------------------------------------------------------------------ public

    def reset(self) -> None:
        """Forget the track (state ``searching``); counters and track ids continue."""
        self._drop_track(TrackState.SEARCHING)
        self._clear_buffer()

    @property
    def state(self) -> TrackState:
        return self._state

    @property
    def holding(self) -> bool:
        """True after :meth:`stop` until the next selection (no automatic acquisition meanwhile)."""
        return self._hold

    def _admit(self, image: np.ndarray) -> np.ndarray:
        try:
            image = check_frame(image)
        except InputError:
            self.rejected_frames += 1
            raise
        if image.shape != self._shape:
            if self._shape is not None:
                log.warning("frame size changed from %s to %s: tracker reset", self._shape, image.shape)
            self._shape = image.shape
            self._buf = np.zeros(image.shape, dtype=np.uint8)
            self._buf_region = None
            if self._track_id is not None:
                self._drop_track(TrackState.LOST)
        return image

    # ------------------------------------------------------------------ operator selection

    def select_point(self, image: np.ndarray, u_px: float, v_px: float, radius_px: float) -> TrackUpdate | None:
        """Track the warm object nearest ``(u_px, v_px)`` within ``radius_px`` on this frame.

        Distance = from the point to the object's thresholded box (0 inside it), ties broken by the
        distance to its centroid.  Found: a new track starts on it (a new ``track_id``) and its
        :class:`TrackUpdate` for this frame is returned (the frame is consumed, do not ``update`` it
        too).  Nothing within the radius: None, the tracker unchanged and the frame not consumed.
        """
        image = self._admit(image)
        best, best_key = None, None
        for d in self._all_detections(image):
            x, y, w, h = d.bbox
            dx = max(x - u_px, 0.0, u_px - (x + w))
            dy = max(y - v_px, 0.0, v_px - (y + h))
            gap = math.hypot(dx, dy)
            if gap > radius_px:
                continue
            key = (gap, math.hypot(d.u_px - u_px, d.v_px - v_px))
            if best_key is None or key < best_key:
                best, best_key = d, key
        return self._select(image, best)

    def select_rectangle(self, image: np.ndarray, rect_px: tuple[float, float, float, float]) -> TrackUpdate | None:
        """Track the warm object whose centroid lies in ``rect_px`` = (x0, y0, x1, y1) (the strongest,
        by flux, when several do); as :meth:`select_point` otherwise."""
        image = self._admit(image)
        x0, y0, x1, y1 = rect_px
        inside = [d for d in self._all_detections(image) if x0 <= d.u_px <= x1 and y0 <= d.v_px <= y1]
        return self._select(image, max(inside, key=lambda d: d.flux) if inside else None)

    def stop(self) -> None:
        """End the current track (state ``searching``) and hold: no automatic acquisition until the
        next :meth:`select_point` / :meth:`select_rectangle`."""
        self._drop_track(TrackState.SEARCHING)
        self._clear_buffer()
        self._hold = True

    def _all_detections(self, image: np.ndarray) -> list[Detection]:
        pre = preprocess_frame(image, self.params, None)
        out = []
        for blob in find_blobs(pre, self.params):
            d = measure_blob(image, blob, self.params, pre.noise_sigma)
            if d is not None:
                out.append(d)
        return out

    def _select(self, image: np.ndarray, det: Detection | None) -> TrackUpdate | None:
        if det is None:
            return None
        self._hold = False
        self.selections += 1
        try:
            self._start_track(image, det)
            return self._measured(det, kcf_ok=False)
        finally:
            self._frame_index += 1

    # ------------------------------------------------------------------ frames

    def update(self, image: np.ndarray) -> TrackUpdate:
        """Process one frame (2-D uint8/uint16, see the module docstring)."""
        image = self._admit(image)
        try:
            if self._track_id is None:
                out = self._search(image)
            else:
                out = self._follow(image)
        finally:
            self._frame_index += 1
        return out

    # ------------------------------------------------------------------ states

    def _drop_track(self, state: TrackState) -> None:
        self._state = state
        self._track_id: int | None = None
        self._kcf = None
        self._kcf_box: tuple[float, float, float, float] | None = None
        self._kcf_scale = 1.0
        self._box_px = self.params.kcf_box_px
        self._uv = (0.0, 0.0)  # the track's position, set when a track starts (read only while there is one)
        self._vel = (0.0, 0.0)
        self._misses = 0

    def _search(self, image: np.ndarray) -> TrackUpdate:
        if self._hold or self.mode == "operator":  # wait for an operator's selection
            return TrackUpdate(self._state, None, None, None, None, False, None, None, self._frame_index)
        det, _ = self._full_frame_best(image)
        if det is None:
            return TrackUpdate(self._state, None, None, None, None, False, None, None, self._frame_index)
        self._start_track(image, det)
        return self._measured(det, kcf_ok=False)

    def _follow(self, image: np.ndarray) -> TrackUpdate:
        p = self.params
        h, w = image.shape
        n = self._misses + 1
        pu, pv = self._uv[0] + self._vel[0] * n, self._uv[1] + self._vel[1] * n
        roi = Region.around(pu, pv, self._box_px + p.roi_margin_px, w, h)
        if self._kcf_box is not None:  # KCF searches twice its box around its last box
            bx, by, bw, bh = self._kcf_box
            roi = roi.union(Region.around(bx + bw / 2, by + bh / 2, int(math.ceil(max(bw, bh))), w, h))
        pre = preprocess_frame(image, p, roi)
        kcf_box = self._kcf_step(pre)  # None: KCF lost it (or has no track)
        if (
            kcf_box is not None
            and math.hypot(kcf_box[0] + kcf_box[2] / 2 - pu, kcf_box[1] + kcf_box[3] / 2 - pv) > p.kcf_gate_px
        ):
            kcf_box = None  # KCF jumped (onto noise or clutter): not a plausible motion
        kcf_ok = kcf_box is not None
        ref = (kcf_box[0] + kcf_box[2] / 2, kcf_box[1] + kcf_box[3] / 2) if kcf_box is not None else (pu, pv)
        det = self._nearest(image, pre, ref)
        if det is not None:
            if kcf_box is None or math.hypot(ref[0] - det.u_px, ref[1] - det.v_px) > p.max_drift_px:
                self.kcf_reseeds += 1
                self._seed_kcf(image, det, pre)
                kcf_ok = False  # KCF missed or drifted off the blob on this frame
            else:
                self._kcf_box = kcf_box
            self._advance(det)
            return self._measured(det, kcf_ok)
        # no blob near the prediction: look everywhere (re-acquisition after a jump)
        full, _ = self._full_frame_best(image)
        if full is not None:
            self.reacquisitions += 1
            keep = self._misses <= p.coast_frames and math.hypot(full.u_px - pu, full.v_px - pv) <= p.reacquire_gate_px
            if not keep and self.mode == "operator":
                full = None  # never jump to another object than the operator's: coast, then lose it
        if full is not None:
            if keep:
                self._advance(full)
                self._seed_kcf(image, full, None)
            else:
                self._start_track(image, full)
            log.debug("re-acquired at (%.1f, %.1f), track %s", full.u_px, full.v_px, self._track_id)
            return self._measured(full, False)
        self._misses += 1
        if self._misses >= p.lost_frames:
            log.info("track %s lost after %d frames without a blob", self._track_id, self._misses)
            self._drop_track(TrackState.LOST)
            self._clear_buffer()
            return TrackUpdate(TrackState.LOST, None, None, None, None, False, None, None, self._frame_index)
        self._state = TrackState.COASTING
        kcf_ok = kcf_ok and self._misses <= p.coast_frames
        u: float | None
        v: float | None
        if kcf_box is not None and kcf_ok:
            self._kcf_box = kcf_box
            u, v = kcf_box[0] + kcf_box[2] / 2, kcf_box[1] + kcf_box[3] / 2
            box = _box4(kcf_box)
        else:
            if self._misses > p.coast_frames:
                self._kcf, self._kcf_box = None, None
            u = v = None
            s = float(self._box_px)
            box = (pu - s / 2, pv - s / 2, s, s)
        return TrackUpdate(
            TrackState.COASTING, u, v, box, None, False, self._track_id, self._misses, self._frame_index, bool(kcf_ok)
        )

    # ------------------------------------------------------------------ helpers

    def _full_frame_best(self, image: np.ndarray) -> tuple[Detection | None, Preprocessed]:
        pre = preprocess_frame(image, self.params, None)
        best = None
        for blob in find_blobs(pre, self.params):
            d = measure_blob(image, blob, self.params, pre.noise_sigma)
            if d is not None and (best is None or d.flux > best.flux):
                best = d
        return best, pre

    def _nearest(self, image: np.ndarray, pre: Preprocessed, ref: tuple[float, float]) -> Detection | None:
        best, best_d2 = None, math.inf
        for blob in find_blobs(pre, self.params):
            d = measure_blob(image, blob, self.params, pre.noise_sigma)
            if d is None:
                continue
            d2 = (d.u_px - ref[0]) ** 2 + (d.v_px - ref[1]) ** 2
            if d2 < best_d2:
                best, best_d2 = d, d2
        return best

    def _start_track(self, image: np.ndarray, det: Detection) -> None:
        self._drop_track(TrackState.TRACKING)
        self._track_id = self._next_track_id
        self._next_track_id += 1
        log.info("track %d started at (%.1f, %.1f)", self._track_id, det.u_px, det.v_px)
        self._uv = (det.u_px, det.v_px)
        self._seed_kcf(image, det, None)

    def _advance(self, det: Detection) -> None:
        n = self._misses + 1
        vu, vv = (det.u_px - self._uv[0]) / n, (det.v_px - self._uv[1]) / n
        a = VELOCITY_SMOOTHING
        self._vel = (a * vu + (1 - a) * self._vel[0], a * vv + (1 - a) * self._vel[1])
        self._uv = (det.u_px, det.v_px)
        self._misses = 0

    def _measured(self, det: Detection, kcf_ok: bool) -> TrackUpdate:
        self._state = TrackState.TRACKING
        self._misses = 0
        box = _box4(self._kcf_box if self._kcf_box is not None else det.bbox)
        return TrackUpdate(
            TrackState.TRACKING,
            det.u_px,
            det.v_px,
            box,
            det,
            not det.touches_border,
            self._track_id,
            0,
            self._frame_index,
            bool(kcf_ok),
        )

    def _clear_buffer(self) -> None:
        if self._buf_region is not None:
            self._buf[self._buf_region.slices()] = 0
        self._buf_region = None

    def _fill_buffer(self, pre: Preprocessed) -> None:
        self._clear_buffer()
        kcf_image_u8(pre, self._kcf_scale, out=self._buf[pre.region.slices()])
        self._buf_region = pre.region

    def _kcf_step(self, pre: Preprocessed) -> tuple[float, float, float, float] | None:
        """KCF's box on this frame, or None (no KCF, or it lost the target)."""
        if self._kcf is None:
            self._clear_buffer()
            return None
        self._fill_buffer(pre)
        try:
            ok, box = self._kcf.update(self._buf)
        except cv2.error as exc:  # a KCF failure must never stop the chain
            log.warning("KCF update failed (%s); re-seeding from detection", exc.err if hasattr(exc, "err") else exc)
            self._kcf, self._kcf_box = None, None
            return None
        if not ok:
            return None
        return _box4(box)

    def _seed_kcf(self, image: np.ndarray, det: Detection, pre: Preprocessed | None) -> None:
        """(Re)initialise KCF on a box centred on ``det`` over the thresholded residual."""
        p = self.params
        h, w = image.shape
        side = int(min(max(p.kcf_box_px, math.ceil(p.kcf_box_scale * max(det.bbox[2], det.bbox[3]))), p.kcf_max_box_px))
        self._box_px = side
        region = Region.around(det.u_px, det.v_px, side + p.roi_margin_px, w, h)
        if pre is None or not (
            pre.region.x0_px <= region.x0_px
            and pre.region.y0_px <= region.y0_px
            and pre.region.x1_px >= region.x1_px
            and pre.region.y1_px >= region.y1_px
        ):
            pre = preprocess_frame(image, p, region)
        self._kcf_scale = max(KCF_FULL_SCALE_HIGHS * pre.threshold_high, 1e-6)
        self._fill_buffer(pre)
        box = (int(round(det.u_px - side / 2)), int(round(det.v_px - side / 2)), side, side)
        try:
            kcf = create_kcf(p)
            kcf.init(self._buf, box)
        except cv2.error as exc:
            log.warning("KCF init failed (%s); tracking by detection only", exc)
            self._kcf, self._kcf_box = None, None
            return
        self._kcf = kcf
        self._kcf_box = _box4(box)
