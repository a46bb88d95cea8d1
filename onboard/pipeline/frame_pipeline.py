"""Per-frame processing, pure: IR frame -> pose at capture time -> imaging -> estimator -> Track.

No sockets, no threads, no sleeping: the daemon (:mod:`onboard.app.service`) drives a
:class:`FramePipeline` from its pipeline thread, and the lockstep evaluation drives the very same
object frame by frame.  One call::

    track = pipeline.process(frame, received_mono_ns)          # an IrFrame
    track = pipeline.process_payload(payload, received_mono_ns)  # wire bytes, decoded here

Steps of :meth:`FramePipeline.process` (time ``t = frame.time_boot_us``, boot clock):

1. Admission (stateful, needs no pixels but a resend's): frame size equals the configured camera; then
   :class:`~onboard.pipeline.admission.FrameAdmission` on (seq, capture time): each refused frame is
   counted under what is wrong with it (``frame_duplicate``, ``frame_duplicate_conflict``: the last taken frame's seq
   and stamp with other pixels, ``frame_out_of_order``, ``frame_time_ahead``, ``frame_time_behind``) and costs only
   itself; a clock step, an autopilot
   reboot or a sender restart is accepted once a run of mutually consistent frames confirms it
   (``frame_time_reset``, ``frame_stream_restart``: the estimator restarts; ``frame_sequence_reset``;
   ``frame_sequence_repeated``: the last frame's sequence number again, the capture time on).  After a
   step the telemetry did not share, the frames get no pose (``pose_clock_apart``, :attr:`FramePipeline.clock_apart_s`)
   until their stamps are within the threshold of the telemetry's again.  Then the frame's zoom (IRF1's field,
   :attr:`~onboard.core.irframe.IrFrame.stated_zoom`): one stated more than
   :data:`~onboard.core.irframe.ZOOM_TOLERANCE` from 1.0 is not the zoom ``camera.intrinsics`` were calibrated at,
   so every bearing made from them is off by the zoom's ratio: the frame's line of sight and 3-D position are
   withheld (``zoom_mismatch`` in :attr:`FramePipeline.withheld_because`, decided on the frame itself, not a frame
   late) and its row reaches neither the estimator nor the clock-offset estimator (step 4, 7); the 2-D track goes
   on.  A zoom no zoom can be (NaN, inf, negative) is read as not stated and counted (``frame_zoom_invalid``).
2. Imaging: ``tracker.update(pixels)`` (the single chain, :class:`~onboard.imaging.TargetTracker`); a chain that
   ``uses_pose`` (the objects chain) gets ``t`` (frames the daemon dropped are time its tracks must be predicted
   over) and a function that returns the camera's rotation at ``t``, which it calls once it has detected the
   frame's points: after the optional ``chain_pose_wait(t)`` hook (the daemon waits there for the telemetry that
   brackets ``t``, ``imaging.pose_wait_ms``: the chain registers frames with it, and an extrapolated rotation's
   noise costs a dim target its confirmation), so the wait overlaps the detection.
3. Pose at ``t`` (after imaging, so that late telemetry has more time to arrive): the optional
   ``pose_wait(t)`` hook lets the daemon wait for telemetry that lags; then ``pose_source.pose_at(t)``
   (counted by the pose buffer when missing).  No pose: the frame still gets a 2-D track.
4. Estimator: reset on a new track id (a new target association), on a lost track, on a reboot and
   on a position or attitude reset (a GNSS step or an attitude estimate's reset the pose buffer found:
   :attr:`PoseAt.discontinuities` changed, counted as ``estimator_pose_reset``), before the first frame after
   the break reaches it;
   ``add`` only when the tracker's ``measurement_valid`` and a pose exist; otherwise ``predict``
   (coasting, or no pose). A pose whose position is dead-reckoned (a GNSS gap) past the
   camera-position noise the estimator assumes is never added: the frame's estimate is the window's
   last one coasted to it and corrected by its line of sight (:mod:`onboard.pipeline.coast`).
5. Track: image fields always; the line of sight in local NED with its 1-sigma
   (:func:`onboard.core.track.line_of_sight_ned`, from ``estimator.pixel_sigma_px`` and the attitude white
   and bias sigmas, the bias's share stated as ``los_sigma_bias_deg``) whenever there is a target centre and a
   pose, with or without an estimate;
   position fields (WGS84 through :func:`onboard.core.frames.geodetic_from_ned`) whenever the estimate is
   finite and an origin is known, ``observable`` grading them (``output.unobservable_positions:
   false`` publishes them only when observable, as ``irtrack.track/1`` did).
6. Residual consistency: ``residual_rms_norm`` is the estimator's own figure when it gives one (RMS
   of the standardised residuals at its last model selection), else the RMS over the last
   ``RESIDUAL_WINDOW_S`` of frames of ``|uv_measured - uv_projected| / s``, the estimate projected
   through the frame's pose, per image axis, with ``s^2 = s_px^2 + f^2 (s_w^2 + s_b^2) +
   f^2 s_perp^2 / range^2`` (``s_perp^2`` the estimate's position variance across the line of
   sight, per axis).  About 1 or below when camera and noise model match; a mount or intrinsics
   mismatch drives it far above (:mod:`onboard.app.watchdog` warns).
7. Camera clock (``time_offset``): every frame with a measured target feeds
   :class:`~onboard.estimation.time_offset.TimeOffsetEstimator` with its bearing and the pose at its own
   stamp (and the estimate's range, once there is one).  While the estimator's ``compensated_ms`` is not 0,
   step 3 looks the pose up a second time, at ``t - compensated_ms``, and that pose (the last looked up: a
   recorder keeps it) makes the estimator's rows, the line of sight and the 3-D output; the track keeps the
   frame's stamp.  A compensation that moved by more than ``COMPENSATION_REBUILD_MS`` since the estimator's
   window was made makes the window's rows again with the poses at their stamps minus the new compensation,
   interpolated in the poses looked up at the frames' stamps (:mod:`onboard.pipeline.restamp`), and hands them
   to the estimator's ``rebuild`` (one model selection, no window lost: its rows made with the old compensation
   would disagree with the new ones); an estimator without ``rebuild`` is restarted instead, beyond
   ``COMPENSATION_RESTART_MS`` only.
   The offset estimator starts again on an autopilot reboot and on a frame-stream restart or clock step; a
   position reset only closes the block it is filling (its fit takes the camera's positions, the clock is the same).

Refused frames raise :class:`FrameRejected` (``reason``) after being counted as ``frame_<reason>``
in the shared :class:`~onboard.core.counters.RejectCounter`: ``frame_short``, ``frame_magic``,
``frame_version``, ``frame_encoding``, ``frame_dims``, ``frame_size``, ``frame_too_large``,
``frame_field`` (decode, :mod:`onboard.core.irframe`), ``frame_dims_mismatch``, ``frame_duplicate``,
``frame_duplicate_conflict``,
``frame_out_of_order``, ``frame_time_ahead``, ``frame_time_behind``, ``frame_image`` (the tracker refused the
frame's pixels); and, the tracker at fault, not the frame, ``tracker_error`` (``update`` raised) and
``tracker_output_invalid`` (its answer is no track update: None, a centre or box not finite, a measured centre off the
frame, a negative box size, a track id below 1, an unknown state; :func:`~onboard.pipeline.answer_checks.tracker_problem`).  Notable accepted
events: ``frame_time_reset``, ``frame_sequence_reset``, ``frame_sequence_repeated``, ``frame_stream_restart``, ``frame_encoding_changed`` (INFO: mono8
and mono16 alternating, a camera's mode or a second publisher), ``frame_zoom_invalid`` (step 1), ``estimator_pose_reset``
(step 4).  Estimator problems never refuse a frame: they are counted as ``estimator_input`` (it refused its
input), ``estimator_error`` (it raised) or ``estimator_output_invalid`` (its answer is not an estimate of the
protocol, :mod:`onboard.pipeline.plugins`: a field missing or of the wrong type or shape, a position, velocity,
covariance or range not finite, a covariance not symmetric positive semi-definite) and the frame gets no 3-D.
"""

from __future__ import annotations

import collections
import logging
import math
import time
from collections.abc import Callable
from typing import Any, NoReturn, Protocol

import numpy as np

from onboard.core.counters import RejectCounter
from onboard.core.errors import InputError
from onboard.core.frames import GeodeticOrigin, PinholeIntrinsics, geodetic_from_ned, rotmat_from_quat
from onboard.core.irframe import (
    ENCODING_MONO8,
    ENCODING_MONO16,
    IrFrame,
    IrFrameError,
    decode_irframe,
)
from onboard.core.pose_types import PoseAt
from onboard.core.status import RollingStats
from onboard.core.track import LineOfSight, Track, line_of_sight_ned
from onboard.estimation.map_estimator import across_range_widened
from onboard.estimation.time_offset import TimeOffsetEstimate, TimeOffsetEstimator
from onboard.pipeline.admission import FrameAdmission
from onboard.pipeline.answer_checks import estimate_problem, frame_shape_hw, tracker_problem
from onboard.pipeline.coast import coast_estimate
from onboard.pipeline.factories import make_estimator, make_tracker
from onboard.pipeline.restamp import StampPoseHistory
from onboard.pipeline.withholding import ZOOM_MISMATCH, Withholding

__all__ = [
    "FrameRejected",
    "PoseSource",
    "Estimator",
    "FramePipeline",
    "TRACKER_REFUSALS",
    "ACCEPTED_FRAME_EVENTS",
    "ZOOM_MISMATCH",
    "make_estimator",
    "make_tracker",
]

log = logging.getLogger(__name__)

US_PER_S = 1_000_000
#: the least camera-position error (1 sigma, m) that makes a frame coast instead of joining the window: 50 ms of
#: extrapolation adds 6 mm, a dead-reckoned second 1 m
CAMERA_SIGMA_FLOOR_M = 0.02
RESIDUAL_WINDOW_S = 1.0  # own reprojection-residual statistic: RMS over this much of the latest frames
#: a change of the camera clock's compensation beyond this makes the estimator's window again (``rebuild``): its rows
#: made with the old one would disagree with the new ones, and the offset estimator moves it only a few times a flight
COMPENSATION_REBUILD_MS = 0.5
#: an estimator without ``rebuild`` is restarted instead, which loses its window: only beyond this (50 ms at 0.1 rad/s
#: of camera rotation: 5 mrad, ten times the noise)
COMPENSATION_RESTART_MS = 10.0
#: operator requests waiting for a frame at most: a ground station resending every 5 ms to a camera without frames
#: queued thousands (3 MB of memory per 5000), each decided by the camera's timeout all the same
MAX_QUEUED_SELECTIONS = 64
#: counter keys of frames refused for their tracker's fault (:meth:`FramePipeline.process`), not the frame's
TRACKER_REFUSALS = ("tracker_output_invalid", "tracker_error")
#: ``frame_*`` counter keys of events on frames that were taken (module docstring), not refusals: the status's
#: ``frames.rejected`` sums every other ``frame_*`` key
ACCEPTED_FRAME_EVENTS = frozenset(
    ("frame_time_reset", "frame_sequence_reset", "frame_sequence_repeated", "frame_stream_restart")
    + ("frame_encoding_changed", "frame_zoom_invalid")
)


class FrameRejected(InputError):
    """A frame refused by the pipeline; ``reason`` is the counter key without the ``frame_`` prefix."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


class PoseSource(Protocol):
    """What the pipeline needs of a pose buffer (:class:`~onboard.core.pose.PoseBuffer` is one)."""

    def pose_at(self, time_boot_us: int) -> PoseAt | None: ...


class Estimator(Protocol):
    """The sliding-window estimator's interface (:class:`~onboard.estimation.sliding.SlidingWindowEstimator`)."""

    def add(self, t_s: float, uv_px, intrinsics: PinholeIntrinsics, p_cam_ned_m, q_ned_from_cam): ...

    def predict(self, t_s: float, p_cam_ned_m=None): ...

    def reset(self) -> None: ...


def _track_key(pose: PoseAt) -> tuple[int, int]:
    """Where ``pose`` is on the camera's pose track: (reboots, breaks of any kind) so far.  A pose source of a test
    or a recording may not carry the break count: then reboots only."""
    return int(pose.epoch), int(getattr(pose, "discontinuities", 0))


#: the configuration sections the pipeline reads (of the daemon's ``onboard.app.config.OnboardConfig``: the
#: pipeline depends on their fields, not on the application's config class)
CONFIG_SECTIONS = ("vehicle", "camera", "imaging", "gcs", "estimator", "input", "output")


class FramePipeline:
    """Frame -> Track, one call per frame (see the module docstring).  Not thread-safe.

    ``config``: the daemon's :class:`OnboardConfig` (``OnboardConfig()`` for defaults).
    ``pose_source``: has ``pose_at(time_boot_us)``; ``origin``: the local NED origin to report when
    neither the frame's pose nor the pose source has one (a pose's own origin names its estimate).  ``tracker``: has ``update(pixels) -> TrackUpdate``.
    ``estimator``: the sliding-window interface, or None (2-D only).  ``counter``: where refusals
    are counted (default: the pose source's ``counter`` if it has one).  ``pose_wait``: called with
    the frame time before the pose lookup (the daemon waits there for lagging telemetry);
    ``chain_pose_wait``: the same before the image chain's rotation (a chain that ``uses_pose``).
    ``clock_ns``: monotonic clock for the timing statistics.
    """

    def __init__(
        self,
        config: Any,
        pose_source: PoseSource | None,
        tracker,
        estimator: Estimator | None = None,
        origin: GeodeticOrigin | None = None,
        *,
        counter: RejectCounter | None = None,
        pose_wait: Callable[[int], object] | None = None,
        chain_pose_wait: Callable[[int], object] | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        stats_window: int = 1000,
    ) -> None:
        missing = [name for name in CONFIG_SECTIONS if not hasattr(config, name)]
        if missing:
            raise InputError(
                f"FramePipeline config lacks the section(s) {missing} "
                f"(an onboard.app.config.OnboardConfig has them), got {type(config).__name__}"
            )
        if origin is not None and not isinstance(origin, GeodeticOrigin):
            raise InputError(f"FramePipeline origin must be a GeodeticOrigin or None, got {type(origin).__name__}")
        self.config = config
        self.vehicle = config.vehicle
        # the daemon's run (onboard.core.track.new_run_id), stamped on every track; None: none stated (a replay)
        self.run_id: str | None = None
        self.intrinsics = config.camera.pinhole()
        self.pose_source = pose_source
        self.tracker = tracker
        self.estimator = estimator
        self.origin = origin
        self.counter = counter if counter is not None else getattr(pose_source, "counter", None) or RejectCounter()
        self.pose_wait = pose_wait
        self.chain_pose_wait = chain_pose_wait
        self._clock_ns = clock_ns
        self.processing_ms = RollingStats(stats_window)
        self.pose_wait_ms = RollingStats(stats_window)
        self.imaging_ms = RollingStats(stats_window)
        self.estimator_ms = RollingStats(stats_window)
        self.frames_processed = 0
        self.frames_rejected = 0
        self.estimator_resets = 0
        self.last_track: Track | None = None
        self._shift_us = 0  # the camera-clock compensation the current frame's pose was looked up with, us
        self._admission = FrameAdmission(
            int(config.input.time_reset_threshold_s * US_PER_S), config.input.sequence_restart_count
        )
        self._est_track_id: int | None = None
        # (epoch, discontinuities) of the last pose: a change is a break in the camera's pose track
        self._pose_track: tuple[int, int] | None = None
        self._est_has_data = False
        self._window_est = None  # the newest estimate the window solved: what a dead-reckoned frame coasts from
        self.frames_coasted = 0
        #: how old the newest position sample was at the last frame's capture time (s; inf: past the dead-reckoning
        #: limit; None: no pose for another reason).  The daemon's watchdog names a GNSS dropout from it.
        self.last_position_age_s: float | None = None
        #: how far (s) the last frame's stamp stood from the telemetry's newest sample while the stream's clock stands
        #: apart from the telemetry's (:attr:`onboard.pipeline.admission.FrameAdmission.apart_us`: the frames get no
        #: pose); None: the clocks agree.  The daemon's watchdog warns ``camera_clock_apart`` from it.
        self.clock_apart_s: float | None = None
        self._encoding: int | None = None  # the last accepted frame's (an IrFrame encoding code)
        self._last_taken: IrFrame | None = None  # the last accepted frame: a resend of it is compared pixel by pixel
        self._withholding = Withholding()  # what withholds the geometry: the daemon's codes, the frame's zoom
        self._last_withheld: tuple[str, ...] = ()  # what withheld the last frame's (last_withheld)
        self._last_p_cam_ned_m: np.ndarray | None = None  # the newest frame's camera, for a frame without a pose
        ec = config.estimator
        # a pose whose position is dead-reckoned beyond the camera-position noise the window assumes coasts
        self._camera_sigma_m = max(float(ec.camera_position_white_sigma_m), CAMERA_SIGMA_FLOOR_M)
        self._coast_max_s = float(getattr(getattr(config, "pose", None), "dead_reckoning_max_s", 10.0))
        self._pixel_sigma_px = float(ec.pixel_sigma_px)
        #: the camera attitude's 1-sigma per axis the lines of sight carry (the track's; the objects message's too)
        self.attitude_sigma_rad = math.radians(math.hypot(ec.attitude_white_sigma_deg, ec.attitude_bias_sigma_deg))
        #: ... and its constant part, which each line of sight states (``los_sigma_bias_deg``): a fleet fusion takes
        #: it as this vehicle's attitude-bias prior instead of being configured with it a second time
        self.attitude_bias_sigma_rad = math.radians(ec.attitude_bias_sigma_deg)
        f_px = math.sqrt(self.intrinsics.fx_px * self.intrinsics.fy_px)
        self._bearing_sigma_rad = math.hypot(self._pixel_sigma_px / f_px, self.attitude_sigma_rad)
        self._residuals: collections.deque = collections.deque()  # (time_boot_us, z_u^2 + z_v^2)
        # (TrackRequest, on_done): any thread appends; bounded, as the pipeline takes them only with frames
        self._selections: collections.deque = collections.deque(maxlen=MAX_QUEUED_SELECTIONS)
        to = getattr(config, "time_offset", None)  # a test's config may lack the section: then none
        #: the camera clock's offset estimator (None: ``time_offset.enabled`` false); step 7 of the module docstring
        self.time_offset = TimeOffsetEstimator(to.params()) if to is not None and to.enabled else None
        self._window_comp_ms = 0.0  # the clock compensation the estimator's window was made with
        # the estimator's rows (time_boot_us, (u, v)) and the poses at the frames' stamps, to make the window again
        # at a new compensation (step 7); kept only with the offset estimator on
        window_s = float((getattr(ec, "sliding", None) or {}).get("window_s", getattr(ec, "window_s", 20.0)))
        self._window_rows: collections.deque = collections.deque()
        self._window_span_us = int(round(window_s * US_PER_S))
        self._stamp_poses = StampPoseHistory(window_s + 1.0)
        self.window_restamps = 0  # windows made again at a new compensation
        self.last_selection: dict[str, Any] | None = None  # the last operator request decided: kind, accepted, reason

    # ------------------------------------------------------------------ public

    @property
    def withheld_because(self) -> tuple[str, ...]:
        """The warnings that withhold the line of sight and the 3-D position now (the image fields still go out):
        those the daemon sets from its watchdog (``gimbal_mismatch``, ``camera_mismatch``), then
        :data:`ZOOM_MISMATCH` while the last frame taken states a zoom the intrinsics are not for (decided here,
        frame by frame: :class:`~onboard.pipeline.withholding.Withholding`).  Read once per frame: another thread
        sets it."""
        return self._withholding.codes

    @withheld_because.setter
    def withheld_because(self, codes: tuple[str, ...]) -> None:
        self._withholding.set_by_daemon(codes)

    @property
    def last_withheld(self) -> tuple[str, ...]:
        """The codes that withheld the last frame's line of sight and 3-D position (:attr:`withheld_because` as that
        frame was processed; empty: published; a frame refused before that step: the codes in force as it came).
        Recorded with the frame, so that a replay, which has neither the daemon's watchdog nor its links, withholds
        the same frames."""
        return self._last_withheld

    @property
    def last_zoom(self) -> float | None:
        """The zoom the last frame taken stated (IRF1's field, relative to the calibrated one); None: not stated."""
        return self._withholding.last_zoom

    @property
    def zoom_withheld(self) -> bool:
        """The last frame taken had its geometry withheld for its stated zoom (its hysteresis included): what the
        watchdog's ``zoom_mismatch`` says, from this one decision."""
        return self._withholding.zoom_off

    @property
    def frames_withheld_zoom(self) -> int:
        """Frames whose line of sight and 3-D position were withheld for their stated zoom."""
        return self._withholding.frames_withheld_zoom

    def reset(self) -> None:
        """Forget the stream (sequence/time), the track and the estimate; counters continue."""
        self._admission.reset()
        self._last_taken = None
        if hasattr(self.tracker, "reset"):
            self.tracker.reset()
        self._reset_estimator("pipeline reset")

    def request_selection(self, request, on_done: Callable[[Any], None]) -> None:
        """Queue an operator's :class:`~onboard.io.camera_protocol.TrackRequest` (point, rectangle or stop)
        for the next processed frame; ``on_done`` gets its :class:`~onboard.io.camera_protocol.TrackResult`
        from the thread that runs :meth:`process`.  Thread-safe (one deque append).

        On that frame, before imaging: ``stop`` ends the track and holds the tracker idle (accepted);
        ``point`` / ``rectangle`` select on the frame (:meth:`TargetTracker.select_point` /
        ``select_rectangle``): found, the new track is this frame's and the 3-D estimate restarts;
        nothing there, refused with the reason and the frame is tracked as usual.  Without frames at most
        :data:`MAX_QUEUED_SELECTIONS` wait: a newer one pushes the oldest out (counted ``selection_dropped``),
        which the camera answers as it answers any request that waited too long.
        """
        if len(self._selections) >= MAX_QUEUED_SELECTIONS:
            self.counter.count(
                "selection_dropped",
                f"request {request.request_id} pushed the oldest of {MAX_QUEUED_SELECTIONS} waiting for a frame out",
                level=logging.DEBUG,
            )
        self._selections.append((request, on_done))

    def _selects_the_followed_object(self, sel) -> bool:
        """Whether a selection names the object the estimate follows: the objects chain's ids name objects (the
        single chain starts a new track on any selection)."""
        return (
            self.config.imaging.chain == "objects"
            and self._est_has_data
            and sel.track_id is not None
            and sel.track_id == self._est_track_id
        )

    def _apply_selections(self, pixels, pose: dict | None = None):
        """Decide the queued requests on this frame; the frame's TrackUpdate when one selected a target.
        ``pose``: the frame's ``R_ned_from_cam`` (a function, as :meth:`process` passes it) and ``time_boot_us``,
        for a chain that ``uses_pose``."""
        from onboard.core.selection import TrackResult

        upd = None
        while self._selections:
            req, on_done = self._selections.popleft()
            if not req.claim():
                # the camera decided it without a frame: it timed out (answered TEMPORARILY_REJECTED, counted and
                # logged there) or a newer command from its sender replaced it (never answered): not carried out,
                # and no fault here to warn of (a ground station resending every 5 ms to a camera without frames
                # queues thousands of these, whose first frame logged a WARNING saying each was answered)
                self.counter.count(
                    "selection_expired",
                    f"request {req.request_id} ({req.kind}) decided without a frame (timed out or replaced)",
                    level=logging.DEBUG,
                )
                continue
            result = None
            try:
                if req.kind == "stop":
                    if hasattr(self.tracker, "stop"):
                        self.tracker.stop()
                    upd = None
                    self._reset_estimator("operator stop")
                    result = TrackResult(req.request_id, True)
                else:
                    if req.kind == "point":
                        sel = self.tracker.select_point(pixels, req.u_px, req.v_px, req.radius_px, **(pose or {}))
                        where = f"in {req.radius_px:.0f} px of ({req.u_px:.0f},{req.v_px:.0f})"
                    else:
                        sel = self.tracker.select_rectangle(pixels, req.rect_px, **(pose or {}))
                        x0, y0, x1, y1 = req.rect_px
                        where = f"in ({x0:.0f},{y0:.0f})-({x1:.0f},{y1:.0f})"
                    if sel is None:
                        # the objects chain selects among the objects it has confirmed (tracked a few frames); pixels
                        # as the image's, and short: with the camera's "irtrack: " the usual refusal fits one
                        # STATUSTEXT's 50 bytes (a longer one is chunked, which simple tools show in pieces)
                        what = "tracked object" if self.config.imaging.chain == "objects" else "warm object"
                        result = TrackResult(req.request_id, False, f"no {what} {where}")
                    else:
                        upd = sel
                        if self._selects_the_followed_object(sel):
                            # a click on the box the ground station draws is "yes, that one" (and a ground station
                            # resends a command whose ACK it lost): the estimate already follows that object
                            log.info(
                                "operator selection (%s) of object %s, which the estimate follows: kept",
                                req.kind,
                                sel.track_id,
                            )
                        else:
                            self._reset_estimator(f"operator selection ({req.kind})")
                        result = TrackResult(req.request_id, True, u_px=sel.u_px, v_px=sel.v_px, track_id=sel.track_id)
            except InputError as exc:
                result = TrackResult(req.request_id, False, f"frame refused: {exc}")
            except Exception as exc:  # noqa: BLE001 - a selection bug must not stop the frame loop
                self.counter.count("selection_error", f"{type(exc).__name__}: {exc}")
                result = TrackResult(req.request_id, False, f"selection failed: {type(exc).__name__}")
            self.last_selection = {"kind": req.kind, "accepted": result.accepted, "reason": result.reason or None}
            try:
                on_done(result)
            except Exception as exc:  # noqa: BLE001
                self.counter.count("selection_error", f"on_done: {type(exc).__name__}: {exc}")
        return upd

    def process_payload(self, payload, received_mono_ns: int | None = None) -> Track:
        """Decode a wire payload (:func:`onboard.core.irframe.decode_irframe`), then :meth:`process`."""
        try:
            frame = decode_irframe(payload, max_bytes=self.config.input.max_frame_bytes)
        except IrFrameError as exc:
            self._refuse(exc.reason, str(exc))
        return self.process(frame, received_mono_ns)

    def process(self, frame: IrFrame, received_mono_ns: int | None = None) -> Track:
        """One frame -> its :class:`Track`; raises :class:`FrameRejected` (counted) for a refused frame."""
        t0 = self._clock_ns()
        self._last_withheld = self._withholding.codes  # a frame refused before its own decision: the codes in force
        if not isinstance(frame, IrFrame):
            self._refuse("field", f"expected an IrFrame, got {type(frame).__name__}")
        K = self.intrinsics
        if frame.width_px != K.width_px or frame.height_px != K.height_px:
            self._refuse(
                "dims_mismatch",
                f"frame is {frame.width_px} x {frame.height_px}, the camera is "
                f"{K.width_px} x {K.height_px} (camera.intrinsics)",
            )
        self._admit(frame)
        self._withholding.follow_zoom(frame, self.counter)
        # while the stream's clock stands apart from the telemetry's, no pose: none is waited for or looked up
        apart_us = self._admission.apart_us
        self.clock_apart_s = None if apart_us is None else apart_us / US_PER_S
        encoding = frame.encoding
        if encoding != self._encoding and self._encoding is not None:
            # a camera switching modes, or a second publisher on the key: the image chain's statistics start again
            names = {ENCODING_MONO8: "mono8", ENCODING_MONO16: "mono16"}
            self.counter.count(
                "frame_encoding_changed",
                f"frame seq {frame.seq} is {names[encoding]}, the stream's were {names[self._encoding]}",
                level=logging.INFO,
            )
        self._encoding = encoding

        waited_ns = 0
        uses_pose = getattr(self.tracker, "uses_pose", False)

        def rotation():
            # called by the chain once the frame is detected (which needs no pose): the wait for the telemetry
            # that brackets the capture overlaps the detection instead of coming before it
            nonlocal waited_ns
            if self.chain_pose_wait is not None and apart_us is None:
                waited_ns += self._timed_wait(self.chain_pose_wait, frame.time_boot_us - self._compensation_us())
            return self._camera_rotation(frame.time_boot_us)

        i0 = self._clock_ns()
        try:
            chain_pose = {"R_ned_from_cam": rotation, "time_boot_us": frame.time_boot_us} if uses_pose else None
            upd = self._apply_selections(frame.pixels, chain_pose) if self._selections else None
            if upd is None and uses_pose:
                upd = self.tracker.update(frame.pixels, rotation, frame.time_boot_us)
            elif upd is None:
                upd = self.tracker.update(frame.pixels)
        except InputError as exc:
            self._refuse("image", f"tracker refused the frame: {exc}")
        except Exception as exc:  # noqa: BLE001 - a tracker bug costs its frame, never the frame loop
            self._refuse_tracker("tracker_error", f"{type(self.tracker).__name__}: {type(exc).__name__}: {exc}")
        problem = tracker_problem(upd, frame_shape_hw(frame.pixels))
        if problem is not None:  # everything below reads it unguarded
            self._refuse_tracker("tracker_output_invalid", f"{type(self.tracker).__name__}: {problem}")
        self.imaging_ms.add((self._clock_ns() - i0 - waited_ns) / 1e6)
        state = upd.state.value if hasattr(upd.state, "value") else str(upd.state)

        t_us = frame.time_boot_us
        if self.pose_wait is not None and self.pose_source is not None and apart_us is None:
            waited_ns += self._timed_wait(self.pose_wait, t_us)
        stamp_pose = pose = None
        self._shift_us = 0
        if apart_us is not None:
            self.counter.count(
                "pose_clock_apart",
                f"frame seq {frame.seq} is stamped {apart_us / US_PER_S:+.3f} s from the telemetry's newest sample, "
                "since a step of the camera's clock the telemetry did not share: no pose (no line of sight, no 3-D) "
                "until the two clocks agree",
            )
        elif self.pose_source is not None:
            try:
                stamp_pose = pose = self.pose_source.pose_at(t_us)
                shift_us = self._compensation_us()
                # whether or not the stamp has a pose (the offset estimator's input only): a camera stamping later
                # than the telemetry can be extrapolated has none once the image chain waits for the capture's
                if shift_us:  # looked up last: the pose the frame's 3-D is made with
                    pose = self.pose_source.pose_at(t_us - shift_us)
                    self._shift_us = shift_us  # the track says so: its line of sight is of the stamp minus this
            except Exception as exc:  # noqa: BLE001 - a pose source bug costs this frame its 3-D only
                self.counter.count("pose_error", f"{type(exc).__name__}: {exc}")
        # before anything made with the frame's pose: the first pose past a break must meet an empty window
        self._follow_pose_track(stamp_pose)
        if pose is not stamp_pose:
            self._follow_pose_track(pose)
            if stamp_pose is not None and pose is not None and _track_key(stamp_pose) != _track_key(pose):
                stamp_pose = None  # the telemetry broke between the two look-ups: the stamp's pose is of the old track
        if stamp_pose is not None and self.time_offset is not None:
            self._stamp_poses.append(t_us, stamp_pose.q_ned_from_cam, stamp_pose.p_cam_ned_m)

        self.last_position_age_s = self._position_age_s(pose)
        self._follow_compensation()
        withheld, cleared, level = self._withholding.follow()
        self._last_withheld = withheld
        if cleared:  # the window holds rows made with the wrong camera, or is as old as the frames withheld
            self._reset_estimator(f"{', '.join(cleared)} cleared", level)
        e0 = self._clock_ns()
        est = None
        if not self._withholding.zoom_off:
            # a zoomed frame's bearing, made with the calibrated focal length, is off by the zoom's ratio: unlike a
            # camera_mismatch (whose residuals are what clears it) nothing needs it, and it would bend both estimates
            est = self._estimate(upd, pose, t_us)
            self._time_offset_add(upd, stamp_pose, est, t_us)
        self.estimator_ms.add((self._clock_ns() - e0) / 1e6)
        track = self._track(frame, upd, state, pose, est, withheld)
        self.last_track = track
        self.frames_processed += 1
        self.pose_wait_ms.add(waited_ns / 1e6)
        self.processing_ms.add((self._clock_ns() - t0 - waited_ns) / 1e6)
        return track

    def _camera_rotation(self, t_us: int):
        """R_ned_from_cam at ``t_us`` for an image chain that associates in bearing space (None without
        a pose yet: the chain keeps its last one); never waits for telemetry."""
        if self.pose_source is None or self._admission.apart_us is not None:
            return None
        try:
            pose = self.pose_source.pose_at(t_us - self._compensation_us())
        except Exception:  # noqa: BLE001 - counted where the frame's own pose is looked up below
            return None
        return None if pose is None else rotmat_from_quat(pose.q_ned_from_cam)

    # ------------------------------------------------------------------ admission

    def _refuse(self, reason: str, message: str) -> NoReturn:
        self.frames_rejected += 1
        self.counter.count(f"frame_{reason}", message)
        raise FrameRejected(reason, message)

    def _refuse_tracker(self, reason: str, message: str) -> NoReturn:
        """Refuse a frame the tracker failed on: counted under ``reason`` itself (not a ``frame_`` key: the frame was
        fine), raised as :class:`FrameRejected` with that reason."""
        self.frames_rejected += 1
        self.counter.count(reason, message)
        raise FrameRejected(reason, message)

    def _admit(self, frame: IrFrame) -> None:
        """Admit the frame or refuse it, counted under its reason (:mod:`onboard.pipeline.admission`)."""
        reference_us = None
        if self._admission.wants_reference(frame.seq, frame.time_boot_us):
            # the attitude's newest time: it streams on through a GNSS dropout, where the newest time both attitude
            # and position cover stands still, and a camera pausing there would seem to stand apart from it
            newest = getattr(self.pose_source, "newest_rotation_time_boot_us", None) or getattr(
                self.pose_source, "newest_time_boot_us", None
            )
            try:
                reference_us = newest() if callable(newest) else None
            except Exception:  # noqa: BLE001 - without a telemetry reference the first frame is taken as it is
                reference_us = None
        verdict = self._admission.admit(frame.seq, frame.time_boot_us, reference_us)
        if not verdict.accepted:
            last = self._last_taken
            if (
                verdict.reason == "duplicate"
                and last is not None
                and (last.seq, last.time_boot_us) == (frame.seq, frame.time_boot_us)
                and not np.array_equal(last.pixels, frame.pixels)
            ):
                # two images claim one capture (a second sender on the key, a corrupted resend): the first was taken,
                # and it may be the wrong one; only the last taken frame's pixels are kept to compare with
                self._refuse(
                    "duplicate_conflict",
                    f"{verdict.message}, with other pixels than the frame taken: a second sender on the frame key, "
                    "or a corrupted resend",
                )
            self._refuse(verdict.reason, verdict.message)
        self._last_taken = frame
        if verdict.reason:
            detail = verdict.message + ("; estimator restarted" if verdict.restart else "")
            self.counter.count(f"frame_{verdict.reason}", detail)
        if verdict.restart:
            self._reset_estimator(verdict.reason.replace("_", " "))
            if self.time_offset is not None:  # a clock step or a restarted camera: its offset may have changed
                self.time_offset.reset()

    # ------------------------------------------------------------------ estimation

    def _reset_estimator(self, why: str, level: int = logging.INFO) -> None:
        if self.estimator is not None and self._est_has_data:
            try:
                self.estimator.reset()
            except Exception as exc:  # noqa: BLE001
                self.counter.count(
                    "estimator_error", f"{type(self.estimator).__name__}.reset: {type(exc).__name__}: {exc}"
                )
            self.estimator_resets += 1
            log.log(level, "estimator reset: %s", why)
        self._est_has_data = False
        self._est_track_id = None
        self._window_est = None
        self._window_rows.clear()
        self._residuals.clear()

    def _estimate(self, upd, pose: PoseAt | None, t_us: int):
        if self.estimator is None:
            return None
        tid = upd.track_id
        if tid is None:
            if self._est_has_data:
                self._reset_estimator("no track")
            return None
        if tid != self._est_track_id:
            # the objects chain's ids name objects: another id is another object, whatever reset_on_new_track says
            # (the estimate is never silently handed to it); the single chain's new id may be its target re-found
            if self._est_track_id is not None and (
                self.config.estimator.reset_on_new_track or self.config.imaging.chain == "objects"
            ):
                self._reset_estimator(f"new track {tid}")
            self._est_track_id = tid
        t_s = t_us / US_PER_S
        try:
            if pose is not None and getattr(pose, "sigma_extrapolation_m", 0.0) > self._camera_sigma_m:
                return self._checked(self._coast(upd, pose, t_s))
            if upd.measurement_valid and pose is not None:
                self._est_has_data = True
                if self.time_offset is not None:
                    self._window_rows.append((t_us, (upd.u_px, upd.v_px)))
                    while self._window_rows[0][0] < t_us - self._window_span_us:
                        self._window_rows.popleft()
                est = self._checked(
                    self.estimator.add(
                        t_s, (upd.u_px, upd.v_px), self.intrinsics, pose.p_cam_ned_m, pose.q_ned_from_cam
                    )
                )
                self._window_est = est if est is not None else self._window_est
                return est
            if not self._est_has_data:
                return None
            return self._checked(self.estimator.predict(t_s, None if pose is None else pose.p_cam_ned_m))
        except InputError as exc:
            self.counter.count("estimator_input", str(exc))
        except Exception as exc:  # noqa: BLE001 - the estimator must never stop the frame loop
            self.counter.count("estimator_error", f"{type(self.estimator).__name__}: {type(exc).__name__}: {exc}")
        return None

    def _checked(self, est):
        """``est``, or None (counted ``estimator_output_invalid``) when it is not an estimate the pipeline can read:
        every later step reads it unguarded."""
        if est is None:
            return None
        problem = estimate_problem(est)
        if problem is None:
            return est
        self.counter.count("estimator_output_invalid", f"{type(self.estimator).__name__}: {problem}")
        return None

    def _follow_pose_track(self, pose: PoseAt | None) -> None:
        """Start the 3-D estimate again when ``pose`` is past a break in the camera's pose track (module docstring,
        step 4): an autopilot reboot (``epoch``) or a position reset (``discontinuities``)."""
        if pose is None:
            return
        key = _track_key(pose)
        last, self._pose_track = self._pose_track, key
        if last is None or key == last:
            return
        self._stamp_poses.clear()  # a window made again at a new compensation takes poses of the new track only
        if key[0] != last[0]:
            self._reset_estimator("autopilot reboot")
            if self.time_offset is not None:  # the autopilot's clock started again
                self.time_offset.reset()
            return
        had_data = self._est_has_data
        self._reset_estimator("camera pose reset (a GNSS step or an attitude reset)")
        if self.time_offset is not None:  # same clock, a new pose track: the block ends at the break, the blocks stay
            self.time_offset.close_block()
        self.counter.count(
            "estimator_pose_reset",
            f"pose discontinuity {key[1]} at time_boot_us={pose.time_boot_us}: the camera's position or attitude "
            f"stepped (a GNSS jump, an attitude estimate's reset: the pose buffer's position_reset / attitude_reset / "
            f"gimbal_reset); 3-D estimate started again" + ("" if had_data else " (it had no rows)"),
        )

    def _position_age_s(self, pose: PoseAt | None) -> float | None:
        if pose is not None:
            return getattr(pose, "pos_extrapolated_us", 0) / US_PER_S  # a pose source of a test may not say
        miss = getattr(self.pose_source, "last_miss_reason", None)
        return math.inf if miss == "position_extrapolation_limit" else None

    def _coast(self, upd, pose: PoseAt, t_s: float):
        """A frame whose camera position is dead-reckoned: the window's last estimate coasted to it
        (:mod:`onboard.pipeline.coast`), never an observation of the window."""
        self.frames_coasted += 1
        base = self._window_est
        if base is None or not self._est_has_data or t_s - base.t_s > self._coast_max_s:
            return None
        u_ned = None
        if upd.measurement_valid and upd.u_px is not None:
            u_ned = rotmat_from_quat(pose.q_ned_from_cam) @ self.intrinsics.bearing_cam_from_pixel((upd.u_px, upd.v_px))
            u_ned = u_ned / np.linalg.norm(u_ned)
        return coast_estimate(
            base,
            t_s,
            pose.p_cam_ned_m,
            pose.sigma_extrapolation_m,
            u_ned,
            self._bearing_sigma_rad,
            self.config.estimator.coast_accel_sigma_mps2,
        )

    # ------------------------------------------------------------------ camera clock

    @property
    def time_offset_estimate(self) -> TimeOffsetEstimate | None:
        """The camera clock's offset now (None: ``time_offset.enabled`` false)."""
        return None if self.time_offset is None else self.time_offset.estimate

    def _follow_compensation(self) -> None:
        """Make the estimator's window again when the clock compensation moved by more than
        ``COMPENSATION_REBUILD_MS`` since the window was made (restart one without ``rebuild``, beyond
        ``COMPENSATION_RESTART_MS`` only); a window that starts takes the compensation of now."""
        comp_ms = self._compensation_us() / 1000.0
        moved_ms = abs(comp_ms - self._window_comp_ms)
        if self._est_has_data and moved_ms > COMPENSATION_REBUILD_MS:
            if callable(getattr(self.estimator, "rebuild", None)) or moved_ms > COMPENSATION_RESTART_MS:
                why = f"camera clock compensation now {comp_ms:.1f} ms (was {self._window_comp_ms:.1f} ms)"
                if not self._restamp_window(comp_ms, why):
                    self._reset_estimator(why)
        if not self._est_has_data:
            self._window_comp_ms = comp_ms

    def _restamp_window(self, comp_ms: float, why: str) -> bool:
        """The estimator's window made again with each row's pose at its stamp minus ``comp_ms`` (step 7); False
        when it cannot be (no ``rebuild``, no row with a pose there, the rebuild failed): restart it then."""
        rebuild = getattr(self.estimator, "rebuild", None)
        if not callable(rebuild) or not self._window_rows:
            return False
        t_us = np.fromiter((r[0] for r in self._window_rows), dtype=np.int64, count=len(self._window_rows))
        q, p, ok = self._stamp_poses.poses_at(t_us - int(round(comp_ms * 1000.0)))
        rows = [
            (int(t_us[i]) / US_PER_S, self._window_rows[i][1], self.intrinsics, p[i], q[i]) for i in np.flatnonzero(ok)
        ]
        if not rows:
            return False
        try:
            est = rebuild(rows)
        except Exception as exc:  # noqa: BLE001 - a failed rebuild costs the window, never the frame loop
            self.counter.count(
                "estimator_error",
                f"{type(self.estimator).__name__}.rebuild at a new clock compensation: {type(exc).__name__}: {exc}",
            )
            return False
        kept = {int(t_us[i]) for i in np.flatnonzero(ok)}
        self._window_rows = collections.deque(r for r in self._window_rows if r[0] in kept)
        est = self._checked(est)
        self._window_est = est if est is not None else self._window_est
        self._window_comp_ms = comp_ms
        self.window_restamps += 1
        log.info("estimator window made again (%d of %d rows): %s", len(rows), len(t_us), why)
        return True

    def _timed_wait(self, wait: Callable[[int], object], t_us: int) -> int:
        """Call a telemetry wait hook at ``t_us``; the ns it took.  A failing wait is counted
        (``pose_wait_error``) and never loses the frame."""
        w0 = self._clock_ns()
        try:
            wait(t_us)
        except Exception as exc:  # noqa: BLE001 - a failing wait must not lose the frame
            self.counter.count("pose_wait_error", f"{type(exc).__name__}: {exc}")
        return self._clock_ns() - w0

    def _compensation_us(self) -> int:
        return 0 if self.time_offset is None else int(round(self.time_offset.compensated_ms * 1000.0))

    def _time_offset_add(self, upd, stamp_pose: PoseAt | None, est, t_us: int) -> None:
        """Feed the offset estimator with the frame's bearing and the pose at its own stamp (step 7)."""
        if self.time_offset is None or stamp_pose is None or not upd.measurement_valid or upd.u_px is None:
            return
        range_m = getattr(est, "range_m", None) if est is not None else None
        if range_m is not None and not (math.isfinite(float(range_m)) and float(range_m) > 0):
            range_m = None  # no range yet: the estimator's default (the estimate hardly depends on it)
        v = stamp_pose.body.v_ned_mps
        if not np.isfinite(v).all():
            self.counter.count(
                "time_offset_no_velocity", "the pose has no velocity: frame not used for the clock offset"
            )
            return
        try:
            self.time_offset.add(
                t_us / US_PER_S,
                self.intrinsics.bearing_cam_from_uv(upd.u_px, upd.v_px),
                stamp_pose.q_ned_from_cam,
                stamp_pose.p_cam_ned_m,
                v,
                None if range_m is None else float(range_m),
                upd.track_id,
            )
        except InputError as exc:
            self.counter.count("time_offset_input", str(exc))
        except Exception as exc:  # noqa: BLE001 - the clock estimate must never stop the frame loop
            self.counter.count("time_offset_error", f"{type(exc).__name__}: {exc}")

    # ------------------------------------------------------------------ output

    def _origin(self, pose: PoseAt | None) -> GeodeticOrigin | None:
        # the estimate is in the frame of the poses it was made from: their origin names it, whatever the pipeline
        # was configured with (a replay's --set pose.origin must not move the recorded target); the configured
        # origin serves only a pose source that has none
        if pose is not None:
            return pose.origin
        source_origin = getattr(self.pose_source, "origin", None)
        return source_origin if source_origin is not None else self.origin

    def _line_of_sight(self, upd, pose: PoseAt | None) -> LineOfSight | None:
        # measured centres only: a coasting tracker's centre is its prediction, whose error no pixel sigma bounds
        # (after a gap in the telemetry or the frames, 3-66 deg off while the sigma said 0.11 deg)
        if pose is None or upd.u_px is None or not upd.measurement_valid:
            return None
        try:
            return line_of_sight_ned(
                (upd.u_px, upd.v_px),
                self.intrinsics,
                pose.q_ned_from_cam,
                pose.p_cam_ned_m,
                self._pixel_sigma_px,
                self.attitude_sigma_rad,
                self.attitude_bias_sigma_rad,
            )
        except (InputError, ValueError, FloatingPointError) as exc:
            self.counter.count("los_invalid", str(exc))
            return None

    def _residual_rms_norm(self, upd, pose: PoseAt | None, est, t_us: int) -> float | None:
        """The estimator's ``residual_rms_norm`` if it has one, else ours (module docstring, step 6)."""
        if est is None:
            return None
        theirs = getattr(est, "residual_rms_norm", math.nan)
        if theirs is not None and math.isfinite(theirs):
            return float(theirs)
        if upd.measurement_valid and pose is not None:
            z2 = self._standardised_residual_sq(upd, pose, est)
            if z2 is not None:
                self._residuals.append((t_us, z2))
        while self._residuals and self._residuals[0][0] < t_us - RESIDUAL_WINDOW_S * US_PER_S:
            self._residuals.popleft()
        if not self._residuals:
            return None
        return math.sqrt(sum(z for _, z in self._residuals) / (2.0 * len(self._residuals)))

    def _standardised_residual_sq(self, upd, pose: PoseAt, est) -> float | None:
        K = self.intrinsics
        R = rotmat_from_quat(pose.q_ned_from_cam)
        d_ned = np.asarray(est.p_ned_m, dtype=float) - pose.p_cam_ned_m
        rng = float(np.linalg.norm(d_ned))
        uv = K.project(R.T @ d_ned)
        if rng <= 0 or not np.all(np.isfinite(uv)):
            return None  # the estimate behind the camera: no reprojection
        los = d_ned / rng
        C = np.asarray(est.cov_p_ned_m2, dtype=float)
        perp_var_m2 = max(float(np.trace(C) - los @ C @ los), 0.0) / 2.0
        f2 = K.fx_px * K.fy_px
        s2 = self._pixel_sigma_px**2 + f2 * (self.attitude_sigma_rad**2 + perp_var_m2 / rng**2)
        du, dv = upd.u_px - uv[0], upd.v_px - uv[1]
        return float((du * du + dv * dv) / s2)

    def _across_range_widened(self, p_ned_m: np.ndarray, cov_p_ned_m2) -> np.ndarray:
        """An unobservable position's covariance as published: widened across the line of sight from the newest
        camera position for the range it does not know (:func:`~onboard.estimation.map_estimator.across_range_widened`)."""
        cam = self._last_p_cam_ned_m
        if cam is None:
            return np.asarray(cov_p_ned_m2, dtype=float)
        los = p_ned_m - np.asarray(cam, dtype=float)
        rng = float(np.linalg.norm(los))
        return across_range_widened(cov_p_ned_m2, los / rng, rng) if rng > 0 else np.asarray(cov_p_ned_m2, dtype=float)

    def _track(
        self, frame: IrFrame, upd, state: str, pose: PoseAt | None, est, withheld_because: tuple[str, ...]
    ) -> Track:
        withheld = bool(withheld_because)
        residual = None
        if withheld and est is not None:
            # the image fields only, but the residual figure still goes out: it is what clears camera_mismatch
            residual = self._residual_rms_norm(upd, pose, est, frame.time_boot_us)
            est = None
        origin = self._origin(pose)
        if pose is not None:
            self._last_p_cam_ned_m = pose.p_cam_ned_m
        base = dict(
            vehicle=self.vehicle,
            seq=frame.seq,
            time_boot_us=frame.time_boot_us,
            state=state,
            track_id=upd.track_id,
            measurement_valid=bool(upd.measurement_valid),
            u_px=upd.u_px,
            v_px=upd.v_px,
            bbox=upd.bbox,
            pose_valid=pose is not None,
            los=None if withheld else self._line_of_sight(upd, pose),
            origin=origin,
            compensated_us=self._shift_us if pose is not None else 0,
            estimate_epoch=self.estimator_resets,  # the track says when its estimate started again
            run_id=self.run_id,
        )
        if est is None:
            if residual is not None:
                base["residual_rms_norm"] = residual
            return Track(**base)
        base.update(
            observable=bool(est.observable),
            window_frames=int(est.window_frames),
            residual_rms_norm=self._residual_rms_norm(upd, pose, est, frame.time_boot_us),
        )
        show = est.observable or self.config.output.unobservable_positions
        # finite: checked when the estimator answered (_checked); without a range, no position
        if not (show and origin is not None and getattr(est, "range_m", None) is not None):
            return Track(**base)
        try:
            p = np.asarray(est.p_ned_m, dtype=float)
            lat, lon, alt = geodetic_from_ned(p, origin)
            lon_deg = (float(lon) + 180.0) % 360.0 - 180.0
            p_n, p_e, p_d = p.tolist()
            cov_v = getattr(est, "cov_v_ned_m2ps2", None)
            ratio = getattr(est, "range_sigma_ratio", None)
            return Track(
                **base,
                lat_deg=float(lat),
                lon_deg=lon_deg,
                alt_m=float(alt),
                p_ned_m=(p_n, p_e, p_d),
                v_ned_mps=est.v_ned_mps,
                cov_p_ned_m2=est.cov_p_ned_m2 if est.observable else self._across_range_widened(p, est.cov_p_ned_m2),
                cov_v_ned_m2ps2=cov_v if cov_v is not None and np.all(np.isfinite(cov_v)) else None,
                range_m=float(est.range_m),
                range_sigma_ratio=None if ratio is None or math.isnan(ratio) else float(ratio),
                model=getattr(est, "model", None),
            )
        except (InputError, ValueError, TypeError) as exc:
            self.counter.count("estimator_output_invalid", str(exc))
            return Track(**base)
