"""Every warm point-like object a track with a stable id, associated in bearing space.

``ObjectTracker(intrinsics).update(image, R_ned_from_cam) -> ObjectsUpdate`` once per frame.

Detection (:mod:`onboard.imaging.objects_detection` over :mod:`onboard.imaging.clutter`): column offsets
removed, dead/hot pixels repaired, the two-scale point contrast thresholded at ``threshold_sigma`` local
(CFAR) noise sigmas; while there is no primary, also the background difference at the strongest points
under that threshold near the optical axis (:mod:`onboard.imaging.objects_search`).  The nouns (parameters,
outputs, the track record, the bearing geometry) are
:mod:`onboard.imaging.objects_model`; this module is the tracker: association, confirmation, the primary target,
over the searches beneath the threshold of :mod:`onboard.imaging.objects_search` (track-aided detection, the
background difference, the primary's occlusion signature); :class:`onboard.imaging.objects_chain.ObjectChain` puts
it behind the daemon's single-target interface.

Tracks live in bearing space: each holds the unit line of sight ``los_ned`` (local NED) and its rate
per frame.  A frame's pose ``R_ned_from_cam`` (OpenCV camera axes) projects the prediction into the
image, so the camera's own rotation (a gimbal slewing, the airframe rolling) moves every prediction
with it and only the objects' own motion is left to the filter; without a pose (None) the camera is
taken as still.  Association is greedy nearest-first on the image distance between prediction and
candidate inside a gate that widens while a track coasts (points of a few pixels: overlap of boxes
means nothing after a one-pixel shift), the confirmed tracks measured on the last frame served before
the others; a candidate within ``OWNED_PX`` of two such tracks' predictions (their images merged) goes to
the one with the most hits, the others coasting on their own rates until the images part.  The filter is an alpha-beta filter on the line of sight
(Kalata 1984, "The tracking index", IEEE TAES 20, 174) re-normalised to a unit vector.

States: ``tentative`` until confirmed (see :class:`ObjectParams`: M of N detections moving
consistently and unlike the background; dropped after ``tentative_misses`` misses), then ``confirmed``; ``coasting`` while it misses (predicted, not measured), for at most
``coast_frames`` frames, then ``lost`` (reported once, then gone).  Ids are never reused.

Primary target (``mode`` auto): the current primary is kept while its track lives (confirmed or
coasting); otherwise, of the tracks measured on this frame with at least ``confirm_hits`` hits on at
least ``primary_hit_ratio`` of their frames and at most ``primary_max_off_axis_rad`` off the optical axis,
the longest-tracked within ``primary_radius_px`` of the principal point (else the nearest to it) becomes it once it is confirmed and measured (the observer's
gimbal points the camera at its target, so of the steady objects the target is the one the camera
centres and holds; a fragment of terrain or cloud there is never confirmed, so never chosen; a track far
off the axis is never chosen, even confirmed: no primary rather than a wrong one).  ``select_point`` (operator) selects the confirmed or coasting track nearest a pixel.  A
change of the primary is reported (``primary_changed``) and is a change of the track's id, on which the pipeline
resets the 3-D estimate (always with this chain: its ids name objects), never silently continued on another
object.  The primary's centre is refined by
:func:`onboard.imaging.detect.measure_blob` (the windowed sub-pixel centroid on the raw frame).

Flat-field events: a frozen frame (identical to the previous one) measures nothing (tracks predicted,
no miss counted); an offset step restarts the defect map.  Frames missing (the frames' times, ``time_boot_us``):
a track is predicted over a short gap as over frozen frames; a gap longer than ``coast_frames`` loses every track
(the next frames acquire afresh).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from onboard.core.counters import RejectCounter
from onboard.core.errors import InputError
from onboard.imaging.clutter import GREY16_PER_GREY8, ClutterParams, PointCandidate, frame_event
from onboard.imaging.detect import Blob, Detection, measure_blob
from onboard.imaging.objects_association import (
    COAST_FIT_MIN,
    OWNED_PX,
    common_shift,
    continue_with,
    fitted_coast,
    merged_to_the_elder,
    relative_to_median,
    track_gate,
)
from onboard.imaging.objects_detection import (
    DEBLEND_MIN_SCORE,
    DEBLEND_RADIUS_PX,
    DIFFERENCE_SIGMA,
    SURROUND_MATCH_RATIO,
    ObjectDetector,
)
from onboard.imaging.objects_model import (
    OBJECT_STATES,
    ObjectParams,
    ObjectsUpdate,
    ObjectTrack,
    StageTimes,
    TrackRecord,
    fit_constant_velocity,
    los_from_pixel,
    objects_message,
    pixel_from_los,
    pixels_from_los,
    unit_vector,
)
from onboard.imaging.objects_search import BelowThreshold
from onboard.imaging.preprocess import ImagingParams, check_frame
from onboard.imaging.tbd import TbdParams, TrackBeforeDetect, frame_steps

__all__ = [
    "GREY16_PER_GREY8",
    "ObjectParams",
    "ObjectTrack",
    "ObjectsUpdate",
    "ObjectTracker",
    "OBJECT_STATES",
    "objects_message",
]

log = logging.getLogger(__name__)

# a track is carried by its surroundings when the median of its last this many tests says so (SURROUND_MATCH_RATIO)
SURROUND_TESTS_KEPT = 15


class ObjectTracker(BelowThreshold):
    """See the module docstring.  ``intrinsics``: :class:`onboard.core.frames.PinholeIntrinsics`
    (its lens distortion, if any, carries the tracks' lines of sight); ``mode`` ``auto`` or ``operator``;
    ``stage_clock``: a clock (seconds) to time each frame's stages by, into :attr:`stages`
    (:class:`~onboard.imaging.objects_model.StageTimes`; None, the default: not timed)."""

    def __init__(
        self,
        intrinsics,
        frame_rate_hz: float = 30.0,
        params: ObjectParams | None = None,
        clutter: ClutterParams | None = None,
        imaging: ImagingParams | None = None,
        mode: str = "auto",
        stage_clock=None,
    ) -> None:
        if mode not in ("auto", "operator"):
            raise InputError(f"ObjectTracker mode must be auto or operator, got {mode!r}")
        self.K = intrinsics
        self.frame_rate_hz = float(frame_rate_hz)
        self.imaging = imaging or ImagingParams()
        self.params = params or self.default_params(self.imaging)
        self.clutter = clutter or ClutterParams()
        self.mode = mode
        self._tracks: list[TrackRecord] = []
        # each object's centre as the last frame's output showed it (a coasting one's prediction through that
        # frame's rotation, not its last measured pixel): where an operator clicks
        self._shown_uv: dict[int, tuple[float, float]] = {}
        self._next_id = 1  # ids from 1, as the track output counts them
        self._primary: int | None = None
        self._frame_index = -1
        self._last_time_us: int | None = None  # the last frame's time (frame_steps: periods since it)
        self._prev: np.ndarray | None = None
        self._prev_median: float | None = None
        self._difference_ids: set[int] = set()  # id() of this frame's background-difference candidates
        self._signature_ids: set[int] = set()  # ... and those of them its occlusion signature found
        self._tbd_ids: set[int] = set()  # id() of this frame's track-before-detect candidates
        self._pred_frame = -1  # the frame _pred_px (each track's predicted pixel) was computed for
        self._pred_px: list[tuple[float, float] | None] = []
        self.stages = StageTimes(stage_clock)  # seconds by stage of the last frame (benchmarks; see StageTimes)
        self.detector = ObjectDetector(intrinsics, self.params, self.clutter, self.stages)
        self.primary_changes = 0
        self.frozen_frames = 0
        self.offset_steps = 0
        self._events = RejectCounter(logger=log)  # this chain's notable events, logged at the reject-log interval
        # gaps in the frames' times longer than a track coasts, over which every track was lost (_forget_after_gap)
        self.gap_losses = 0
        im = self.imaging
        tbd = TbdParams(
            threshold_sigma=im.tbd_threshold_sigma,
            track_threshold_sigma=min(TbdParams.track_threshold_sigma, im.tbd_threshold_sigma),
            max_speed_pxpf=im.tbd_max_speed_pxpf,
        )
        self.tbd = TrackBeforeDetect(intrinsics, tbd) if im.tbd else None

    @staticmethod
    def default_params(imaging: ImagingParams | None = None, **changes) -> ObjectParams:
        """The track management an ``ObjectTracker`` without ``params`` runs: ``ObjectParams`` with
        ``imaging``'s ``primary_max_off_axis_rad`` (the daemon's configuration names it there), ``changes``
        applied."""
        im = imaging or ImagingParams()
        return ObjectParams(**{"primary_max_off_axis_rad": im.primary_max_off_axis_rad, **changes})

    # ------------------------------------------------------------------ geometry
    def _los(self, u: float, v: float, R: np.ndarray) -> np.ndarray:
        return los_from_pixel(self.K, u, v, R)

    def _project(self, los_ned: np.ndarray, R: np.ndarray) -> tuple[float, float] | None:
        return pixel_from_los(self.K, los_ned, R)

    # ------------------------------------------------------------------ detection

    def detect(self, image: np.ndarray) -> list[PointCandidate]:
        """The frame's point candidates (:meth:`ObjectDetector.detect` on the current frame)."""
        # the first acquisition only: the lowered threshold, once a primary has been lost, let a terrain
        # feature be re-acquired in the target's place (the detector's _quiet_noise says where)
        self.detector.acquiring = self._primary is None and self.primary_changes == 0
        return self.detector.detect(image, self._frame_index)

    # ------------------------------------------------------------------ step

    def update(self, image: np.ndarray, R_ned_from_cam=None, time_boot_us: int | None = None) -> ObjectsUpdate:
        """One frame.  ``R_ned_from_cam``: the camera's rotation at the frame's capture, None (the camera taken as
        still), or a function of no argument that returns either: it is called once, after the frame's detection,
        which needs no pose, so a caller that must wait for the telemetry bracketing the capture waits while the
        frame is being detected rather than before."""
        self.stages.start()
        image = check_frame(image)
        self._frame_index += 1
        self.frame_steps = frame_steps(self._last_time_us, time_boot_us, self.frame_rate_hz)
        if self._last_time_us is not None and time_boot_us is not None:
            gap_s = (time_boot_us - self._last_time_us) * 1e-6
            # more frames missing than a track coasts, or the frames' time going back: the stream restarted (the
            # daemon takes no frame out of order), its tracks' predictions of another time (a restarted simulator's
            # first frames had the old primary coast 45 frames off the image)
            if gap_s < 0.0 or round(gap_s * self.frame_rate_hz) - 1 > self.params.coast_frames:
                self._forget_after_gap(gap_s)
        self._last_time_us = time_boot_us
        for t in (t for t in self._tracks if 2 * t.dim_hits < t.hits):  # dropped frames (see tbd.frame_steps)
            t.los = unit_vector(t.los + (self.frame_steps - 1) * t.rate)
        if not callable(R_ned_from_cam):
            R = self._rotation(R_ned_from_cam)  # refused before any of the frame's work
        # step_lsb is in 8-bit grey: a 16-bit frame's grey is 257 times finer (its noise alone moves the
        # median by more than 3 of its steps, and every frame would restart the defect map)
        step = self.clutter.step_lsb * (GREY16_PER_GREY8 if image.dtype == np.uint16 else 1.0)
        event, med = frame_event(image, self._prev, self._prev_median, step)
        self._prev, self._prev_median = image, med
        self.stages.lap("frame event")
        if event == "frozen":
            if callable(R_ned_from_cam):
                R = self._rotation(R_ned_from_cam())
            self.frozen_frames += 1
            for t in self._tracks:  # time passes, nothing is measured: predict without counting a miss
                t.los = unit_vector(t.los + t.rate)
                t.age += 1
            out = self._output(image, R, event, measured=set(), changed=False)
            self.stages.lap("output")
            return out
        if event == "step":
            self.offset_steps += 1
            # logged once an interval, with the count since: two cameras of different encodings alternating on the
            # frame key step the offset at every frame, a log line each
            self._events.count(
                "imaging_offset_step",
                f"frame {self._frame_index}: offset step (flat-field correction); defect map restarted",
                level=logging.INFO,
            )
            self.detector.restart()
        regular = self.detect(image)
        if callable(R_ned_from_cam):
            R = self._rotation(R_ned_from_cam())
        self._shift_predictions(regular, R)
        regular = self._deblended(regular, R)
        self.stages.lap("deblending")
        clean = self.detector.clean
        dim = [] if self.tbd is None or clean is None else self._tbd_candidates(self.tbd, clean, regular, R)
        self._tbd_ids, regular = {id(c) for c in dim}, regular + dim
        self.stages.lap("track-before-detect")
        self.detector.background_motion(R)  # before the aided detections: it may extend their runs
        self._difference_ids = set()
        self._signature_ids = set()
        if self._primary is None:  # its time is the aided detection's stage's
            regular = regular + self._difference_search(regular, R)
        cands = self._aided_candidates(regular, R)
        self.stages.lap("aided detection")
        measured = self._associate(cands, R, len(regular))
        self.stages.lap("association, confirmation")
        changed = self._select(R)
        self._learn_signature(R, measured)
        out = self._output(image, R, event, measured, changed)
        self.stages.lap("primary, output")
        return out

    def _forget_after_gap(self, gap_s: float) -> None:
        """More frames missing before this one than a track may coast (``coast_frames``): every track is lost and
        the next frames acquire afresh, as if those frames had come without a detection.  A gap counts as at most
        ``MAX_FRAME_STEPS`` periods of prediction and one miss (dropped frames on a loaded computer), so a
        primary kept over a long gap (the camera's stream paused for seconds) was predicted a second along its
        rate, tens of pixels off its object, and stayed the primary while it coasted: no other track could be
        chosen meanwhile, track-before-detect (which searches only without a primary) stayed idle, and aided
        detection in its widened gate measured it on noise now and then, so it coasted on.  A target under the
        whole-frame threshold, held until then by its track alone, was never found again.  Track-before-detect's
        integration and the detector's kept frames (the background difference's and the background motion's,
        counted in frames) are of that other time too."""
        self.gap_losses += 1
        why = "back in time" if gap_s < 0 else f"longer than a track coasts ({self.params.coast_frames} frames)"
        self._events.count(  # once an interval: frames that keep going back in time would make it a line a frame
            "imaging_gap_lost_tracks",
            f"frame {self._frame_index}: {gap_s:+.2f} s since the last frame, {why}: every track lost",
            level=logging.INFO,
        )
        self.clear_tracks()
        if self.tbd is not None:
            self.tbd.reset()
        self.detector.forget_frames()

    @staticmethod
    def _rotation(R_ned_from_cam) -> np.ndarray:
        R = np.eye(3) if R_ned_from_cam is None else np.asarray(R_ned_from_cam, dtype=np.float64)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise InputError(f"R_ned_from_cam must be a finite 3 x 3 rotation, got shape {R.shape}")
        return R

    def _deblended(self, cands: list[PointCandidate], R: np.ndarray) -> list[PointCandidate]:
        """``cands`` with the points beside a bright confirmed track measured on the last frame that its light
        hid or pulled (:meth:`ObjectDetector.deblended_candidates`); they start and update tracks as any.
        Only about one with another track (confirmed, coasting or tentative: the fainter object's) predicted
        ``OWNED_PX`` to ``DEBLEND_RADIUS_PX`` from it (nearer, the two images are one: nothing the deblending
        could part, C3's occlusion); elsewhere no track looks for what it hid, and about every bright track
        (C3's birds, its two targets far apart) the squares cost a fifth of the frame's time for the
        same scores (docs/perception.md)."""
        if len(self._tracks) < 2 or not any(c.score >= DEBLEND_MIN_SCORE for c in cands):
            return cands  # no bright point, or one track alone (P1-P3): nothing to project or deblend
        pred = self._predicted_px(R)
        bright = [
            q
            for i, (t, q) in enumerate(zip(self._tracks, pred))
            if q is not None
            and t.confirmed
            and t.misses == 0
            and any(
                j != i
                and r is not None
                and (d := math.hypot(r[0] - q[0], r[1] - q[1])) <= DEBLEND_RADIUS_PX
                and (OWNED_PX < d or (o.confirmed and o.misses > 0))
                for j, (o, r) in enumerate(zip(self._tracks, pred))
            )
        ]
        return self.detector.deblended_candidates(cands, bright, self.params.gate_px)

    def _predicted_px(self, R: np.ndarray) -> list[tuple[float, float] | None]:
        """Each track's predicted pixel on this frame, before association (None: behind the camera), all at
        once and once a frame: one pixel_from_los per track, asked by deblending and aided detection, cost
        more than either's own work on most frames."""
        if self._pred_frame != self._frame_index or len(self._pred_px) != len(self._tracks):
            self._pred_frame, self._pred_px = self._frame_index, []
            if self._tracks:
                self._pred_px = pixels_from_los(self.K, np.array([t.los + t.rate for t in self._tracks]), R)
        return self._pred_px

    def _shift_predictions(self, cands: list[PointCandidate], R: np.ndarray) -> None:
        """Take the frame's common offset out of this frame's predictions (:meth:`_predicted_px`), for every
        use of them (deblending, aided detection, association).  Every prediction of a frame is made through
        that frame's attitude, so its error (RTK's white 0.05 deg: 0.67 px per axis) moves them all alike:
        measured on the tracks it is unambiguous for (:func:`~onboard.imaging.objects_association.common_shift`, on the whole-frame candidates)
        and taken out, two images about to merge are judged on their own geometry (C3 seed 2 under RTK: the
        merged image lay over 2 px from the primary's prediction and went to the other target), and a
        coasting track's gate is searched about where its object is."""
        pred = self._predicted_px(R)
        live, puv, cuv, d, gate = self._gated_distances(pred, cands)
        if len(live) < 2 or not cands:
            return
        held = [self._tracks[i].confirmed and self._tracks[i].misses == 0 for i in live]
        shift = common_shift(puv, cuv, d, gate, held)
        if shift is not None:
            du, dv = float(shift[0]), float(shift[1])
            self._pred_px = [None if q is None else (q[0] + du, q[1] + dv) for q in pred]

    def _tbd_focus_pairs(self, cands: list[PointCandidate], live: list[int], d: np.ndarray) -> list:
        """Association pairs, ranked first, of the primary with each track-before-detect candidate within the
        stage's focus radius of its prediction while the stage follows it (none otherwise)."""
        if self.tbd is None or not self.tbd.following or not self._tbd_ids:
            return []
        a = next((a for a, ti in enumerate(live) if self._tracks[ti].object_id == self._primary), None)
        if a is None:
            return []
        radius = self.tbd.focus_radius_px
        return [
            (False, float(d[a, ci]), live[a], ci)
            for ci, c in enumerate(cands)
            if id(c) in self._tbd_ids and d[a, ci] <= radius
        ]

    def _two_point_px(
        self, t: TrackRecord, q_filter: tuple[float, float] | None, R: np.ndarray
    ) -> tuple[float, float] | None:
        """Where ``t``'s last two measured lines of sight, extrapolated at constant velocity, put it on this frame:
        moved from its filter prediction ``q_filter`` (the frame's common offset taken out) by the difference of
        the two projections through ``R`` (None: either behind the camera)."""
        (f1, z1, *_), (f2, z2, *_) = t.history[-2:]
        if q_filter is None or f2 <= f1:
            return None
        extrapolated = self._project(unit_vector(z2 + (z2 - z1) * ((self._frame_index - f2) / (f2 - f1))), R)
        filtered = self._project(unit_vector(t.los + t.rate), R)
        if extrapolated is None or filtered is None:
            return None
        return q_filter[0] + extrapolated[0] - filtered[0], q_filter[1] + extrapolated[1] - filtered[1]

    def _gated_distances(self, pixels: list[tuple[float, float] | None], cands: list[PointCandidate]):
        """``(live, puv, cuv, d, gate)``: the indices of the tracks with a predicted pixel in ``pixels`` (one per
        track), those pixels (n, 2), the candidates' (m, 2), every track-candidate distance at once (n, m; tens
        of each on a cluttered frame) and each live track's gate (n,); the arrays None without a live track or a
        candidate."""
        live = [i for i, q in enumerate(pixels) if q is not None]
        if not live or not cands:
            return live, None, None, None, None
        puv = np.array([pixels[i] for i in live])
        cuv = np.array([(c.u_px, c.v_px) for c in cands])
        d = np.hypot(puv[:, 0:1] - cuv[None, :, 0], puv[:, 1:2] - cuv[None, :, 1])
        return live, puv, cuv, d, track_gate(self.params, np.array([self._tracks[i].misses for i in live]))

    def _tbd_candidates(
        self, tbd: TrackBeforeDetect, clean: np.ndarray, regular: list[PointCandidate], R: np.ndarray
    ) -> list[PointCandidate]:
        """Track-before-detect's dim points (:mod:`onboard.imaging.tbd`; it follows only a primary it found)."""
        focus = None
        prim = next((t for t in self._tracks if t.object_id == self._primary), None)
        if prim is not None:
            focus = self._project(unit_vector(prim.los + prim.rate), R) or prim.uv
        return tbd.update(clean, R, focus, regular)

    def _associate(self, cands: list[PointCandidate], R: np.ndarray, n_regular: int | None = None) -> set[int]:
        """Greedy nearest-first association, confirmed tracks before tentative ones; ``cands[n_regular:]``
        are track-aided candidates, which update their track but never start one."""
        p = self.params
        n_regular = len(cands) if n_regular is None else n_regular
        pixels = self._predicted_px(R)  # the frame's common offset taken out (_shift_predictions)
        preds = [(unit_vector(t.los + t.rate), q) for t, q in zip(self._tracks, pixels)]
        pairs: list[tuple[bool, float, int, int]] = []
        two_point: set[tuple[int, int]] = set()  # (track, candidate) pairs found about a two-point extrapolation
        live, _, cuv, d, gate = self._gated_distances(pixels, cands)
        if d is not None and gate is not None and cuv is not None:
            fresh = np.array([self._tracks[ti].hits == 1 and not self._tracks[ti].confirmed for ti in live])
            if fresh.any():
                gate = np.where(fresh, np.maximum(gate, p.initiation_gate_px), gate)
            held = [t.confirmed and t.misses == 0 for t in self._tracks]
            li, ci_a = np.nonzero(d <= gate[:, None])
            # confirmed tracks measured on the last frame first: a large bright object (a bird) now and
            # then splits into two candidates; the second starts a tentative track, and nearest-first
            # alone then hands the object to that track whenever its prediction lies nearer, and the
            # confirmed track is lost (C3's bird 2, frames 108-170).  A coasting one competes by distance
            # only: its gate widens to 12 px, and first it would take a new object's candidate from the
            # tentative track on it
            pairs = sorted((not held[live[a]], float(d[a, b]), live[a], int(b)) for a, b in zip(li, ci_a))
            pairs = merged_to_the_elder(pairs, held, [t.hits for t in self._tracks])
            # a tentative track with two hits and nothing in its gate: its third is searched about its two positions'
            # extrapolation.  A second hit 3-4 px on, inside the gate, gets the filter's velocity, a fraction of
            # the object's, and the third then falls just beyond the gate: objects at 3.5-3.9 px a frame were
            # never confirmed (a new track every two frames; C3 seed 3's bird entering the frame at 3 px a frame
            # missed for 25 frames).  Only where the filter's gate is empty, so a slow object's association, and
            # the attitude jitter its two positions carry, are as before
            gated = set(li.tolist())
            for a, ti in enumerate(live):
                t = self._tracks[ti]
                if t.confirmed or t.hits != 2 or a in gated or len(t.history) < 2:
                    continue
                q = self._two_point_px(t, pixels[ti], R)
                if q is None:
                    continue
                dd = np.hypot(cuv[:, 0] - q[0], cuv[:, 1] - q[1])
                for ci in np.flatnonzero(dd <= p.gate_px).tolist():
                    pairs.append((True, float(dd[ci]), ti, ci))
                    two_point.add((ti, ci))
            # track-before-detect following the primary reports its strongest peak near the prediction: that is
            # the primary's measurement, taken first, even beyond the gate.  Its integrated centre lags a
            # manoeuvring dim target by 2-3 px; the peak back on the target, 4-5 px from a prediction that
            # followed the lag, started a tentative track beside the primary, which then coasted on a stale
            # rate out of the stage's focus and was lost (C4 seeds 2 and 4 over 30 s)
            focus = self._tbd_focus_pairs(cands, live, d)
            pairs += focus
            if two_point or focus:
                pairs.sort()
        used_t: set[int] = set()
        used_c: set[int] = set()
        measured: set[int] = set()
        for _, dist, ti, ci in pairs:
            if ti in used_t or ci in used_c:
                continue
            used_t.add(ti)
            used_c.add(ci)
            t, c = self._tracks[ti], cands[ci]
            z = self._los(c.u_px, c.v_px, R)
            pl = preds[ti][0]
            r = z - pl
            n = t.misses + 1
            if c.weak and t.confirmed:
                # a difference taken only at the near threshold: where the track is, not where it goes (bent into
                # its velocity and its fitted coast, such detections carried C2 seed 0's primary off over 30 s)
                t.los = unit_vector(pl + p.alpha * r)
            elif (ti, ci) in two_point:
                f2, z2 = t.history[-1][0], t.history[-1][1]
                t.rate = (z - z2) / max(self._frame_index - f2, 1)
                t.los = z
            elif t.hits == 1 and not t.confirmed and dist > p.gate_px:
                # its second hit, beyond a measured track's gate: a fast object, whose velocity is the two
                # positions' (the filter's beta would take a dozen frames to learn it, each one out of the gate)
                t.rate = (z - t.los) / n
                t.los = z
            else:
                t.los = unit_vector(pl + p.alpha * r)
                t.rate = t.rate + (p.beta / n) * r
            t.uv, t.bbox, t.score = (c.u_px, c.v_px), c.bbox, c.score
            t.hits += 1
            t.misses = 0
            t.age += 1
            t.aided_run = t.aided_run + 1 if ci >= n_regular else 0
            t.difference = c if id(c) in self._difference_ids else None
            t.weak_hit = c.weak
            t.signature_run = t.signature_run + 1 if id(c) in self._signature_ids else 0
            t.dim_hits += id(c) in self._tbd_ids
            # confirmed tracks keep theirs too: an aided run is extended only while it moves unlike its background
            if not (c.weak and t.confirmed):
                t.history.append((self._frame_index, z, c.u_px, c.v_px))
            if t.confirmed and len(t.history) > p.confirm_window:
                del t.history[0]
            measured.add(t.object_id)
        keep: list[TrackRecord] = []
        for ti, t in enumerate(self._tracks):
            if ti in used_t:
                keep.append(t)
                continue
            t.los = preds[ti][0]
            if t.confirmed and t.misses == 0 and len(t.history) >= COAST_FIT_MIN:
                # on the line fitted to its last positions while a constant velocity explains them (within
                # the attitude error's share); a track that turned or stopped coasts on its filter's rate,
                # which has followed the manoeuvre (the line would carry it on the old course)
                _, rms = fit_constant_velocity(self.K, [t.history], R, p.attitude_white_sigma_rad)
                coast = fitted_coast(t.history, self._frame_index) if rms[0] <= p.max_fit_rms_px else None
                if coast is not None:
                    t.los, t.rate = coast
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
                TrackRecord(
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
        measured |= self._confirm(R)
        return measured

    def _confirm(self, R: np.ndarray) -> set[int]:
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
            return set()  # nothing to confirm on this frame: no fits needed
        fitted = [t for t in tentative if len(t.history) >= 3]
        if fitted:
            vel, rms = fit_constant_velocity(
                self.K, [t.history for t in fitted], R, self.params.attitude_white_sigma_rad
            )
            for t, v, r in zip(fitted, vel, rms):
                t.velocity_pxpf = (float(v[0]), float(v[1]))
                t.fit_rms_px = float(r)
        asked: set[int] = set()  # object ids whose surroundings were compared on this frame
        continued: dict[int, TrackRecord] = {}  # coasting tracks found again -> the tentative track they took over

        def carried(o: TrackRecord) -> bool:
            # the median of its last tests, not this frame's alone: C2 seed 1's terrain fragment, a warm spot
            # on a flat field near the frame's edge, matched its surroundings 1.5-4.4x better than 3 px off
            # (median 2.3) but 0.93-1.2x on four frames in a row (field edges, a pixel of error in its
            # displacement); the targets on the reference scenes measure 0.65-1.12
            if o.object_id not in asked:
                asked.add(o.object_id)
                match = self.detector.surroundings_match(o)
                if not math.isnan(match):
                    o.surround_matches = [*o.surround_matches, match][-SURROUND_TESTS_KEPT:]
            return bool(o.surround_matches) and float(np.median(o.surround_matches)) > SURROUND_MATCH_RATIO

        for t in tentative:
            if t.hits < p.confirm_hits or t.misses > 0 or len(t.history) < p.confirm_in_window:
                continue
            fit_limit = p.dim_max_fit_rms_px if 2 * t.dim_hits >= t.hits else p.max_fit_rms_px
            if t.velocity_pxpf is None or t.fit_rms_px > fit_limit:
                continue
            tv = t.velocity_pxpf
            nbrs = [
                o
                for o in tentative
                if o is not t
                and o.velocity_pxpf is not None
                and math.hypot(o.uv[0] - t.uv[0], o.uv[1] - t.uv[1]) <= p.background_radius_px
            ]
            # the background's motion, from each source available; the track must move unlike every one
            frame_bgs = []
            # texture first: the background's motion is measured only when asked for (ObjectDetector)
            if self.detector.textured(t.uv) and self.detector.background_pxpf is not None:
                frame_bgs.append(self.detector.background_pxpf)
                mean_bg = self.detector.background_over_window()
                if mean_bg is not None:
                    frame_bgs.append(mean_bg)
            rels = [math.hypot(tv[0] - b[0], tv[1] - b[1]) for b in frame_bgs]
            if len(nbrs) >= p.background_min_tracks:
                rel_nbrs = relative_to_median(tv, nbrs)
                if (
                    len(nbrs) == 1
                    and rel_nbrs < p.min_relative_speed_pxpf
                    and min(rels, default=math.inf) >= p.min_relative_speed_pxpf
                    and not self.detector.textured(nbrs[0].uv)
                    and not carried(nbrs[0])
                ):
                    # decided by one neighbour alone, on a clear sky and not carried by its surroundings:
                    # another object flying alongside, not a fragment of the background (C3's two targets,
                    # tentative together 0.10-0.15 px/frame apart, frames 14-41, were each other's)
                    rel_nbrs = math.inf
                rels.append(rel_nbrs)
            rel = min(rels, default=math.nan)  # nan: no background to differ from (a clear sky)
            if rel < p.min_relative_speed_pxpf:
                continue
            if carried(t):
                continue
            owner = self._coasting_owner(t, R)
            if owner is not None:
                # the coasting track's object found again (a dim target's duplicate, C4 seed 1 over 30 s: a
                # tentative track took the target's detections beside its coasting primary and was confirmed
                # under a new id, 3 px off): it keeps its id and takes the new track's state
                log.debug("object %d found again by tentative track %d", owner.object_id, t.object_id)
                continue_with(owner, t, p.confirm_window)
                continued[owner.object_id] = t
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
                len(nbrs),
                rel,
            )
        if continued:
            gone = {id(t) for t in continued.values()}
            self._tracks = [t for t in self._tracks if id(t) not in gone]
        return set(continued)

    def _coasting_owner(self, t: TrackRecord, R: np.ndarray) -> TrackRecord | None:
        """The confirmed coasting track whose gate holds the tentative track ``t`` about to be confirmed (the
        nearest prediction, this frame's), or None."""
        p = self.params
        best, best_d = None, math.inf
        for o in self._tracks:
            if not o.confirmed or o.misses == 0:
                continue
            q = self._project(o.los, R)  # coasting: its line of sight is this frame's prediction
            if q is None:
                continue
            d = math.hypot(q[0] - t.uv[0], q[1] - t.uv[1])
            if d <= float(track_gate(p, o.misses)) and d < best_d:
                best, best_d = o, d
        return best

    def _select(self, R: np.ndarray) -> bool:
        alive = {t.object_id: t for t in self._tracks if t.confirmed}
        if self._primary is not None and self._primary in alive:
            return False
        old = self._primary
        self._primary = None
        if self.mode == "auto":
            p, K = self.params, self.K

            def off_centre(t: TrackRecord) -> float:
                return math.hypot(t.uv[0] - K.cx_px, t.uv[1] - K.cy_px)

            def off_axis_rad(t: TrackRecord) -> float:
                return math.atan(math.hypot((t.uv[0] - K.cx_px) / K.fx_px, (t.uv[1] - K.cy_px) / K.fy_px))

            # a steady track that missed this frame still counts (a target dips below the threshold
            # now and then): otherwise a farther one is taken in its place on that frame.  None far off
            # the axis: the gimbal holds its target near the centre, and a confirmed fragment of terrain
            # in a corner made primary would hand the 3-D estimator a confident wrong object, the worst
            # failure; no primary is the honest answer there
            steady = [
                t
                for t in self._tracks
                if t.misses <= p.tentative_misses
                and t.hits >= p.confirm_hits
                and t.hits >= p.primary_hit_ratio * t.age
                and off_axis_rad(t) <= p.primary_max_off_axis_rad
            ]
            if steady:
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
        self._shown_uv = {}

    def select_point(
        self, u_px: float, v_px: float, radius_px: float, rect_px: tuple[float, float, float, float] | None = None
    ) -> int | None:
        """Make the confirmed or coasting track nearest (u, v) within ``radius_px`` the primary; its id,
        or None (the primary is then unchanged).  ``rect_px`` = (x0, y0, x1, y1): only a track whose centre lies
        in it (an operator's box selects what is in the box).  A track's centre is where the last frame's output
        showed it (a coasting track's prediction, which the ground station draws; its last measured pixel lags a
        slewing gimbal or a target behind cloud by tens of pixels); a track that output did not show is not
        selectable."""
        best, best_d = None, radius_px
        for t in self._tracks:
            uv = self._shown_uv.get(t.object_id)
            if uv is None:
                continue
            if rect_px is not None and not (rect_px[0] <= uv[0] <= rect_px[2] and rect_px[1] <= uv[1] <= rect_px[3]):
                continue
            d = math.hypot(uv[0] - u_px, uv[1] - v_px)
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
        self._shown_uv = {o.object_id: (o.u_px, o.v_px) for o in objs}
        return ObjectsUpdate(tuple(objs), self._primary, primary_det, changed, event, self._frame_index)
