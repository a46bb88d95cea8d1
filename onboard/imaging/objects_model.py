"""The objects chain's nouns and the geometry its modules share.

:class:`ObjectParams` (track management and confirmation), :class:`ObjectTrack` and :class:`ObjectsUpdate`
(one frame's output), :class:`TrackRecord` (one track's mutable state inside the tracker), the bearing
geometry (``los_from_pixel``, ``pixel_from_los``: unit line of sight in local NED <-> pixel through a frame's
``R_ned_from_cam``, OpenCV camera axes; the camera's lens distortion when it has one), the constant-velocity fit the confirmation and the
track-aided runs use, and the published message (:func:`objects_message`).  The detection side is
:mod:`onboard.imaging.objects_detection`, the tracker :mod:`onboard.imaging.objects`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from onboard.core.errors import InputError
from onboard.imaging.clutter import PointCandidate
from onboard.imaging.detect import Detection
from onboard.imaging.signature import Signature

__all__ = [
    "OBJECT_STATES",
    "ObjectParams",
    "ObjectTrack",
    "ObjectsUpdate",
    "StageTimes",
    "TrackRecord",
    "cv_fit",
    "fit_constant_velocity",
    "los_from_pixel",
    "objects_message",
    "pixel_from_los",
    "pixels_from_los",
    "unit_vector",
]

OBJECT_STATES = ("tentative", "confirmed", "coasting", "lost")


@dataclass(frozen=True)
class ObjectParams:
    """Track management (frames at the camera's rate, pixels).  ``gate_px`` association gate of a
    measured track, widened by ``gate_growth_px`` per coasted frame up to ``max_gate_px``; ``initiation_gate_px``
    at least, a tentative track's with one hit (no velocity yet; the second hit sets it);
    ``alpha``, ``beta``: the filter's gains; ``confirm_hits``; ``tentative_misses``; ``coast_frames``;
    ``defect_every``: frames between defect-map updates; ``primary_hit_ratio``: the least fraction of
    its frames a track must have been measured on to be chosen as the primary; ``primary_radius_px``:
    of the steady tracks this close to the principal point the longest-tracked is chosen;
    ``primary_max_off_axis_rad``: no track farther off the optical axis is chosen by the auto rule (the
    gimbal points the camera at its target: a steady track far off the axis is not the target).

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
    it (``ObjectDetector.surroundings_follow``: the background's motion where the track is).
    Measured on C1-C3 (docs/perception.md): this, not a higher threshold, removes the false tracks.

    Track-aided detection (in a confirmed track's gate, ``aided_threshold_factor`` x the threshold):
    ``aided_max_run`` frames in a row, up to ``aided_max_run_moving`` while its positions still move
    unlike the background (fit within ``aided_max_fit_rms_px``: dim positions scatter more), and past that, while
    they do, by the background difference alone (which cancels what moves with the background); one measured mostly
    by track-before-detect, within ``dim_max_fit_rms_px`` (its centres scatter 0.3-0.5 px, more on a noisy pose);
    in a tentative track's with ``confirm_hits`` hits, ``aided_tentative_max_run`` frames in a row (0: never).
    """

    gate_px: float = 4.0
    gate_growth_px: float = 0.5
    max_gate_px: float = 12.0
    # a track with one hit has no velocity yet: its gate holds an object moving up to this many px a frame, and a
    # second hit beyond gate_px sets the velocity (two-point initiation; a bird near the camera on C3 seed 1 crosses
    # 6.5 px a frame)
    initiation_gate_px: float = 10.0
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
    aided_tentative_max_run: int = 1
    primary_radius_px: float = 40.0
    # 8.6 deg, 116 px at the reference 765 px lens: 4-5 times the reference gimbal's pointing error (the
    # target within ~25 px of the centre), and about the central 256 px that track-before-detect searches
    primary_max_off_axis_rad: float = 0.15
    # the camera attitude's white error, 1 sigma per axis (the estimator's attitude_white_sigma_deg, RTK's
    # 0.05 deg): the constant-velocity fits of projected positions allow for it (fit_constant_velocity)
    attitude_white_sigma_rad: float = math.radians(0.05)

    def __post_init__(self) -> None:
        if not 0 < self.alpha <= 1 or not 0 <= self.beta <= 1:
            raise InputError(f"ObjectParams alpha in (0, 1] and beta in [0, 1], got {self.alpha}, {self.beta}")
        if self.confirm_hits < 1 or self.coast_frames < 0 or self.tentative_misses < 0:
            raise InputError("ObjectParams confirm_hits >= 1, coast_frames and tentative_misses >= 0")
        if not 3 <= self.confirm_in_window <= self.confirm_window:
            raise InputError(
                f"ObjectParams 3 <= confirm_in_window <= confirm_window, got {self.confirm_in_window}, {self.confirm_window}"
            )
        if not 0 < self.gate_px <= self.max_gate_px or not self.initiation_gate_px > 0:
            raise InputError(
                "ObjectParams 0 < gate_px <= max_gate_px and initiation_gate_px > 0, got "
                f"{self.gate_px}, {self.max_gate_px}, {self.initiation_gate_px}"
            )
        if self.aided_max_run_moving < self.aided_max_run:
            raise InputError(f"ObjectParams aided_max_run_moving < aided_max_run ({self.aided_max_run})")
        if not 0 < self.primary_max_off_axis_rad < math.pi / 2:
            raise InputError(f"ObjectParams primary_max_off_axis_rad in (0, pi/2), got {self.primary_max_off_axis_rad}")
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
class TrackRecord:
    """One track's state inside the tracker (mutable; :class:`ObjectTrack` is what leaves it)."""

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
    # rotation-compensated image velocity and the rms residual of its constant-velocity fit: refitted on the frames
    # a tentative track may be confirmed (confirmation alone reads them); a confirmed track keeps its last
    velocity_pxpf: tuple[float, float] | None = None
    fit_rms_px: float = math.inf
    aided_run: int = 0  # consecutive frames measured by track-aided detections only
    dim_hits: int = 0  # frames measured by track-before-detect's reports
    difference: PointCandidate | None = None  # this frame's background-difference detection, if that measured it
    # its last surroundings tests (ObjectDetector.surroundings_match: how much better its own displacement fits them)
    surround_matches: list = field(default_factory=list)
    # the primary's occlusion signature, learned on the frames it is measured on (onboard.imaging.signature)
    signature: Signature | None = None
    weak_hit: bool = False  # this frame's measurement was a weak one (a near-threshold difference or the signature's)
    signature_run: int = 0  # consecutive frames measured by its signature alone


class StageTimes:
    """Where a frame's time goes: ``seconds`` by stage of the last frame, read from ``clock`` (a callable
    returning seconds, e.g. ``time.process_time``; None: nothing is timed, the default).  The tracker and
    its detector share one: :meth:`start` at the frame's start, :meth:`lap` at each stage's end charges
    the time since the last lap to that stage (benchmarks read it; the chain never does)."""

    def __init__(self, clock: Callable[[], float] | None = None) -> None:
        self.clock = clock
        self.seconds: dict[str, float] = {}
        self._last = 0.0

    def start(self) -> None:
        if self.clock is not None:
            self.seconds = {}
            self._last = self.clock()

    def lap(self, stage: str) -> None:
        if self.clock is not None:
            now = self.clock()
            self.seconds[stage] = self.seconds.get(stage, 0.0) + now - self._last
            self._last = now


# The tracks are carried from frame to frame as lines of sight: a camera that turns moves a track's pixel by the
# lens's distortion too (several pixels near the edge of a wide lens for a degree of turn), so a distorted camera
# goes through its own model; the pinhole's closed form serves the cameras without distortion, the shipped ones.


def los_from_pixel(K, u: float, v: float, R: np.ndarray) -> np.ndarray:
    """The unit line of sight (local NED) of pixel (u, v) through ``R`` = R_ned_from_cam (camera ``K``)."""
    if K.has_distortion:
        return R @ K.bearing_cam_from_pixel((u, v))
    ray = np.array([(u - K.cx_px) / K.fx_px, (v - K.cy_px) / K.fy_px, 1.0])
    b = R @ ray
    return b / math.sqrt(b.dot(b))  # np.linalg.norm's own formula for a vector, without its overhead


def pixel_from_los(K, los_ned: np.ndarray, R: np.ndarray) -> tuple[float, float] | None:
    """The pixel of a line of sight (local NED) through ``R`` = R_ned_from_cam; None behind the camera."""
    c = R.T @ los_ned
    if c[2] <= 1e-6:
        return None
    if K.has_distortion:
        u, v = K.project(c).tolist()
        return u, v
    return K.fx_px * c[0] / c[2] + K.cx_px, K.fy_px * c[1] / c[2] + K.cy_px


def pixels_from_los(K, los_ned: np.ndarray, R: np.ndarray) -> list[tuple[float, float] | None]:
    """:func:`pixel_from_los` of each row of ``los_ned`` (n, 3; lines of sight, any length), in one product."""
    c = np.asarray(los_ned, dtype=float).reshape(-1, 3) @ R  # rows: R.T @ los
    if K.has_distortion:
        uv = K.project(c).tolist()
        return [(p[0], p[1]) if z > 1e-6 else None for p, z in zip(uv, c[:, 2].tolist(), strict=True)]
    fx, fy, cx, cy = K.fx_px, K.fy_px, K.cx_px, K.cy_px
    return [(fx * x / z + cx, fy * y / z + cy) if z > 1e-6 else None for x, y, z in c.tolist()]


def attitude_jitter_px2(K, u_px, v_px, sigma_rad: float):
    """The variance (px^2, u and v summed) that a white attitude error of ``sigma_rad`` per axis (about the
    camera's three axes) adds to the projection of a line of sight at pixel (u, v) (floats or arrays): the
    pinhole's rotation Jacobian, ``f`` at the principal point, ``f + x^2 / f`` and the roll's lever ``|(x, y)|``
    off it."""
    f = 0.5 * (K.fx_px + K.fy_px)
    x, y = u_px - K.cx_px, v_px - K.cy_px
    return sigma_rad**2 * (2.0 * (x * y / f) ** 2 + (f + x * x / f) ** 2 + (f + y * y / f) ** 2 + x * x + y * y)


def fit_constant_velocity(
    K, histories: list[list], R: np.ndarray, attitude_sigma_rad: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Constant-velocity least-squares fits of tracks' measured lines of sight projected through
    this frame's camera rotation (the camera's own rotation removed), all tracks at once (padded
    rows, weights 0 on the padding): velocities (n, 2) px per frame and rms residuals (n,) px.  The
    rms is the smaller of that fit's and the same fit's on the measured pixels: an attitude that
    jitters or lags the frame (an extrapolated pose) scatters the projected positions of a point
    the image holds still; the velocities stay the projected ones, the frame every track and the
    background motion are compared in."""
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
    vel, rms = cv_fit(f, u, v, w)
    u[row, col] = [e[2] for h in histories for e in h]
    v[row, col] = [e[3] for h in histories for e in h]
    if attitude_sigma_rad > 0.0:
        # each line of sight was made with its own frame's attitude, whose white error moves its projection
        # (RTK: 0.05 deg, 0.67 px per axis at 765 px, more than the 0.5 px the fit allows): the rms beyond
        # that error's share at the track's mean pixel, at its upper ~2-sigma quantile (a chi-square of
        # 2 (m - 2) degrees of freedom for m positions)
        m = w.sum(axis=1)
        s2 = attitude_jitter_px2(K, (w * u).sum(axis=1) / m, (w * v).sum(axis=1) / m, attitude_sigma_rad)
        dof = np.maximum(m - 2.0, 1.0)
        allowance = np.where(m > 2, s2 * (m - 2.0) / m * (1.0 + 2.0 * np.sqrt(1.0 / dof)), 0.0)
        rms = np.sqrt(np.maximum(rms * rms - allowance, 0.0))
    _, rms_px = cv_fit(f, u, v, w)
    return vel, np.minimum(rms, rms_px)


def cv_fit(f: np.ndarray, u: np.ndarray, v: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


def unit_vector(v: np.ndarray) -> np.ndarray:
    """``v`` scaled to unit length (the zero vector as it is)."""
    n = math.sqrt(v.dot(v))
    return v / n if n > 0 else v


def objects_message(
    update: ObjectsUpdate,
    time_boot_us: int,
    time_unix_us: int | None = None,
    time_unix_sigma_us: int | None = None,
    compensated_us: int = 0,
    rays: bool = True,
    attitude_sigma_rad: float = 0.0,
    run_id: str | None = None,
) -> dict:
    """The ``irtrack/<vehicle>/objects`` message of one frame (JSON-ready, schema ``irtrack.objects/1``):
    ``time_boot_us``, ``time_unix_us`` and ``time_unix_sigma_us`` (the frame's UTC and its 1-sigma, us, as in
    the track; null until the daemon maps its boot clock to UTC), ``compensated_us`` (as in the track: the lines of
    sight are of ``time_boot_us`` minus it, the camera's measured latency), ``frame_index``, ``primary_id`` and
    ``objects``, one per confirmed or coasting object: ``id``, ``state``, ``u_px``, ``v_px``, ``box_px`` [x, y, w,
    h], ``los_ned`` (unit line of sight, local NED, or null), ``los_sigma_rad`` (its 1-sigma per axis across it, or
    null: the chain's measurement, 1 px, and ``attitude_sigma_rad``, the camera attitude's error, in quadrature, as
    the track's line of sight counts it), ``score`` (detection contrast over the local threshold, 0 while coasting)
    and ``primary``.  A coasting object's centre is the chain's prediction: its ``los_ned`` and ``los_sigma_rad``
    are null, as the track's on a coasting frame (a prediction carried over a gap in the telemetry or the frames
    went tens of degrees off while a sigma grown by a pixel a frame said a few).  ``rays`` False (the frame has no
    pose, or the daemon withholds its geometry): every ``los_ned`` and ``los_sigma_rad`` null, as the track's.
    ``run_id``: the daemon's run, as the track's (its object ids start again with a new one); the key only when
    given."""

    def measured_ray(o) -> bool:
        return o.los_ned is not None and rays and o.state != "coasting"

    message = {
        "schema": "irtrack.objects/1",
        "time_boot_us": int(time_boot_us),
        "time_unix_us": None if time_unix_us is None else int(time_unix_us),
        "time_unix_sigma_us": None if time_unix_sigma_us is None else int(time_unix_sigma_us),
        "compensated_us": int(compensated_us),
        "frame_index": update.frame_index,
        "primary_id": update.primary_id,
        "objects": [
            {
                "id": o.object_id,
                "state": o.state,
                "u_px": round(o.u_px, 3),
                "v_px": round(o.v_px, 3),
                "box_px": [round(b, 2) for b in o.bbox],
                "los_ned": [round(c, 7) for c in o.los_ned] if o.los_ned is not None and measured_ray(o) else None,
                "los_sigma_rad": math.hypot(o.sigma_rad, attitude_sigma_rad) if measured_ray(o) else None,
                "score": round(o.score, 3),
                "primary": o.object_id == update.primary_id,
            }
            for o in update.objects
            if o.state in ("confirmed", "coasting")
        ],
    }
    if run_id is not None:
        message["run_id"] = run_id
    return message
