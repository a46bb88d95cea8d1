"""``python -m groundsim eval``: the closed loop in lockstep, scored against the truth.

One *run* is one (scenario, run seed).  It drives the very objects the onboard daemon drives, through
their step methods, without sockets or threads, as fast as the CPU allows and deterministically::

    SimCore (groundsim.world.sim)        fly both vehicles with JSBSim, render the IR frame, truth row
      -> telemetry, as MAVLink would carry it      PoseBuffer.add_attitude / add_position / add_gimbal_status
      -> IrFrame(seq, time_boot_us, pixels)        FramePipeline.process -> Track     (onboard.pipeline.frame_pipeline)

Telemetry.  The observer's flown state on the simulator's tick grid (120 Hz at 30 fps) is offered to
the pose buffer on the schedule of :class:`groundsim.io.mavlink_vehicle.MavlinkVehicle` (attitude
50 Hz, position 25 Hz, gimbal 10 Hz: a stream is due at a tick when its interval has elapsed) and
with the wire's quantisation, exactly what :mod:`onboard.io.mavlink_link` hands the pose buffer:
``time_boot_ms`` (so the stamp is floored to the millisecond), float32 quaternions, latitude and
longitude in 1e-7 degrees, altitude in millimetres, velocity in cm/s, gimbal in the earth frame.
Before frame ``k`` is processed, telemetry is fed up to its capture tick and then further, tick by
tick, until the pose lookup at the capture time succeeds or stops asking to retry -- the lockstep
analogue of the daemon's ``pose.wait_ms``.  The last frame or two of a run, after the simulation's
last telemetry sample, can have no pose; they are not processed (``RunResult.frames`` counts the
frames that were).

Navigation errors.  The telemetry is what the simulated vehicle reports: the truth with the run's
navigation errors (``EvalOptions.injected``; ``--nav-noise``, default each scenario's ``nav_noise``;
:mod:`groundsim.world.nav_errors`, drawn from ``scenario.rng("nav.errors", seed)``), applied by the very function
the MAVLink vehicle uses.  Stream rates are the ones the daemon's configuration requests (``mavlink.attitude_rate_hz``,
``position_rate_hz``, ``gimbal_rate_hz``), which the simulated vehicle honours.

The onboard configuration is the daemon's shipped one (``config/onboard.yaml``: its estimator noise
model assumes INS-class navigation errors; ``--onboard-config`` for another, built-in defaults when
absent) with the scenario's camera (intrinsics, pod mount, gimbal), the scenario's origin as
``pose.origin`` and unobservable positions published, so that "all frames with an estimate" can be
scored beside the observable ones.  The estimator runs synchronously (the daemon runs it in a worker
that may hand a frame an extrapolated estimate when it is late; lockstep never is).

Perfect-centroid baseline (the yardstick of the image chain).  The same sliding-window estimator,
configured identically, fed on every frame where the target is in the image with the truth pixel
(:func:`groundsim.world.render.truth_pixel` at the true camera pose) plus white Gaussian noise of the image
chain's own centroid error, measured in the same run (:func:`centroid_sigma_px`: RMS per axis of
centroid - truth pixel over the frames with a valid centroid; ``DEFAULT_PIXEL_SIGMA_PX`` when there is
none; ``--pixel-sigma`` overrides it), through the SAME camera poses the pipeline got from its pose
buffer for that frame (navigation errors included), so the baseline differs from the chain only in
where the centroid came from.  It runs after the frame loop (the noise level is known then), on the
recorded poses.  The ratio "image chain / perfect centroids" compares errors on the frames where
both report observable, so a late acquisition by the image chain is not counted against it twice
(continuity is reported separately).  A baseline with no observable frame, or worse than
``BASELINE_FAIL_PCT`` of range, "failed": its ratio gets no verdict.

Batch columns (``batch=True``): :class:`~onboard.estimation.map_estimator.MapEstimator` with model
selection on the whole flight (a flight over 60 s in windows, as ``onboard.reconstruct`` solves a long
file: :mod:`onboard.estimation.windows`), once on the pipeline's measured centroids and once on the perfect
centroids; the Bayesian Cramer-Rao bound (:meth:`~onboard.estimation.crb.BayesianCrb.rms_m`) of
the flown trajectory is taken with the perfect-centroid solution's motion prior (each window's), for the noise
actually simulated (the baseline's pixel noise and the run's navigation-error case: ``crb_rms_m``) and
for the noise model the estimator assumes (``crb_model_rms_m``; ``crb_model_range_sigma_ratio``, that bound's
median range sigma over range: the figure the estimator's observability verdict is held to, at its best).

Scoring: :mod:`groundsim.evaluation.scoring` (its docstring defines every figure).

Runs are independent jobs over a process pool (``workers`` processes from a fork server, see
:func:`groundsim.evaluation.parallel.mp_context`); a tqdm bar on stderr counts frames.  Everything but the timing figures is a function of (scenario, seed, options).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from groundsim.evaluation.parallel import (
    JobsInterrupted,
    auto_deadline_s,
    check_run_timeout,
    limit_blas_threads,
    progress_bar,
    report_progress,
    run_jobs,
)
from groundsim.evaluation.scoring import score_run, summarise
from groundsim.evaluation.telemetry_feed import TelemetryFeed
from groundsim.world.nav_errors import InjectedErrors
from groundsim.world.scenario import DEFAULT_NAV_NOISE, Scenario
from onboard.core.errors import ConfigError, InputError, IrtrackError

__all__ = [
    "DEFAULT_ONBOARD_CONFIG",
    "DEFAULT_PIXEL_SIGMA_PX",
    "EvalOptions",
    "RunResult",
    "EvalResult",
    "EvalInterrupted",
    "keep_interrupted",
    "onboard_config_for",
    "load_base_config",
    "run_lockstep",
    "run_eval",
]

log = logging.getLogger(__name__)

# the daemon's shipped configuration (noise model included), found from this file as the shipped scenarios are: a
# command run from another folder must use it too, not fall back to the built-in defaults without saying so
DEFAULT_ONBOARD_CONFIG = Path(__file__).resolve().parents[2] / "config" / "onboard.yaml"
DEFAULT_PIXEL_SIGMA_PX = 0.3  # perfect-centroid baseline noise when the chain measured no centroid (reference px0.3)
PROGRESS_EVERY_FRAMES = 10


# --------------------------------------------------------------------------- options and configuration


@dataclass(frozen=True)
class EvalOptions:
    """How each run is made.  ``duration_s`` None = the scenario's; ``pixel_sigma_px`` the baseline's
    centroid noise (None: the image chain's own centroid error measured in the run, see the module
    docstring); ``batch`` adds the whole-flight MAP columns and the CRB; ``keep_frame`` keeps one IR
    frame per run for the report's picture; ``injected``: the telemetry's navigation-error case
    (``config/noise_cases.yaml``, RTK by default; None = the scenario's ``nav_noise``), GNSS dropout and camera
    clock error (:class:`groundsim.world.nav_errors.InjectedErrors`: no position telemetry in a dropout's
    window, attitude and frames going on; a camera clock changes the frames' stamps, not their content)."""

    duration_s: float | None = None
    pixel_sigma_px: float | None = None
    batch: bool = True
    keep_frame: bool = True
    injected: InjectedErrors = field(default_factory=lambda: InjectedErrors(DEFAULT_NAV_NOISE))
    #: the trajectory estimator, a plug-in name (``onboard.pipeline.plugins``: an ``irtrack.estimators`` entry point or
    #: ``module:Attribute``); None = the daemon's own (the configuration's sliding-window MAP estimator)
    estimator: str | None = None
    #: the image chain, a plug-in name (an ``irtrack.trackers`` entry point -- ``objects``, ``single`` -- or
    #: ``module:Attribute``); None = the configuration's (``imaging.chain``)
    tracker: str | None = None
    #: observer guidance in the loop: the simulated observer flies its scripted motion until the first setpoint, then
    #: the setpoints the daemon's guidance tap and gate send for the configuration's ``guidance`` section
    #: (``groundsim.evaluation.lockstep_guidance``, ``groundsim.world.guided``)
    guidance: bool = False
    #: frames sent the instant they are captured, the daemon's wait for their rotation (``imaging.pose_wait_ms``):
    #: each frame gets the telemetry up to its capture, then the samples that come within this many us until its
    #: rotation is bracketed, else its rotation extrapolated; None: every frame's telemetry fed until it brackets
    #: the frame (a camera whose frames arrive after their telemetry)
    rotation_wait_us: int | None = None
    #: the frame a gimballed observer's #285 is encoded in (``groundsim run --gimbal-frame``): ``earth`` or
    #: ``vehicle`` (ArduPilot's: the daemon turns it with the vehicle's attitude stream)
    gimbal_frame: str = "earth"

    def __post_init__(self) -> None:
        from groundsim.io.vehicle_messages import check_gimbal_frame

        check_gimbal_frame(self.gimbal_frame)
        d = self.duration_s
        if d is not None and (isinstance(d, bool) or not isinstance(d, (int, float)) or not math.isfinite(d) or d <= 0):
            raise ConfigError(f"--duration: expected a positive number of seconds, got {d!r}")
        s = self.pixel_sigma_px
        if s is not None and (isinstance(s, bool) or not isinstance(s, (int, float)) or not math.isfinite(s) or s < 0):
            raise ConfigError(f"--pixel-sigma: expected a number of pixels >= 0, got {s!r}")
        if not isinstance(self.injected, InjectedErrors):
            raise ConfigError(f"EvalOptions.injected must be an InjectedErrors, got {type(self.injected).__name__}")
        if self.estimator is not None:
            from onboard.pipeline.plugins import load_factory

            load_factory(self.estimator)  # an unknown name fails here, before any run
        if self.tracker is not None:
            from onboard.pipeline.plugins import TRACKERS, load_factory

            load_factory(self.tracker, TRACKERS, "--tracker")

    def with_nav_noise(self, nav_noise: str | None) -> EvalOptions:
        """These options with another navigation-error case (the other injected errors kept)."""
        return dataclasses.replace(self, injected=dataclasses.replace(self.injected, nav_noise=nav_noise))


def load_base_config(path: str | os.PathLike | None = None):
    """The daemon's configuration: ``path``, else ``config/onboard.yaml`` (the shipped one) if it exists,
    else the built-in defaults.  Environment variables are ignored (a lockstep run must be reproducible)."""
    from onboard.app.config import OnboardConfig, load_config

    if path is not None:
        return load_config(path, environ={})
    if DEFAULT_ONBOARD_CONFIG.is_file():
        return load_config(DEFAULT_ONBOARD_CONFIG, environ={})
    return OnboardConfig()


def onboard_config_for(scenario: Scenario, base=None):
    """``base`` (an OnboardConfig; default built-in) with the scenario's camera, origin and
    ``output.unobservable_positions`` on (see the module docstring)."""
    from onboard.app.config import CameraConfig, IntrinsicsConfig, MountConfig, OnboardConfig, OriginConfig
    from onboard.core.frames import euler_from_quat

    base = base if base is not None else OnboardConfig()
    K = scenario.camera.intrinsics
    m = scenario.camera.mount
    roll, pitch, yaw = (math.degrees(float(a)) for a in euler_from_quat(np.asarray(m.q_body_from_mount, dtype=float)))
    camera = CameraConfig(
        intrinsics=IntrinsicsConfig(
            fx_px=float(K.fx_px),
            fy_px=float(K.fy_px),
            cx_px=float(K.cx_px),
            cy_px=float(K.cy_px),
            width_px=int(K.width_px),
            height_px=int(K.height_px),
            distortion=tuple(float(k) for k in K.distortion),
        ),
        mount=MountConfig(
            lever_arm_frd_m=tuple(float(a) for a in m.lever_arm_frd_m),
            roll_deg=roll,
            pitch_deg=pitch,
            yaw_deg=yaw,
            gimballed=bool(scenario.camera.gimbal is not None),
        ),
    )
    o = scenario.origin
    pose = dataclasses.replace(base.pose, origin=OriginConfig(lat_deg=o.lat_deg, lon_deg=o.lon_deg, alt_m=o.alt_m))
    out_kw = {"health_file": None}
    if hasattr(base.output, "unobservable_positions"):  # a configuration without the output policy field
        out_kw["unobservable_positions"] = True
    output = dataclasses.replace(base.output, **out_kw)
    return dataclasses.replace(base, camera=camera, pose=pose, output=output)


# --------------------------------------------------------------------------- one run


@dataclass(frozen=True, eq=False)
class RunResult:
    """Everything one lockstep run produced, as arrays over its F frames (NaN = none).

    Truth: ``t_s``, ``time_boot_us``, ``truth_p_ned_m`` (F, 3), ``cam_p_ned_m`` (F, 3, the true
    camera centre), ``observer_p_ned_m`` (F, 3), ``range_m``, ``truth_uv_px`` (F, 2), ``visible``.
    Online track: ``state`` (F,) str, ``measurement_valid``, ``uv_px``, ``bbox``, ``pose_valid``,
    ``est_p_ned_m``, ``est_cov_ned_m2`` (F, 3, 3), ``observable``, ``range_sigma_ratio``.
    Perfect-centroid baseline: ``base_p_ned_m``, ``base_cov_ned_m2``, ``base_observable``.
    ``batch``: dict of whole-flight results (or None); ``timing``: seconds and per-frame ms arrays;
    ``counters``: reject/event counts; ``frame``: one IR frame with its track for the picture (or None);
    ``error``: a one-line failure (then most arrays are empty); ``nav_noise``: the telemetry's
    navigation-error case; ``chain_centroid_sigma_px``: the image chain's centroid error per axis
    (RMS over valid centroids, NaN when none); ``baseline_pixel_sigma_px``: the baseline's noise.
    """

    scenario: str
    description: str
    seed: int
    frames: int
    t_s: np.ndarray
    time_boot_us: np.ndarray
    truth_p_ned_m: np.ndarray
    cam_p_ned_m: np.ndarray
    observer_p_ned_m: np.ndarray
    range_m: np.ndarray
    truth_uv_px: np.ndarray
    visible: np.ndarray
    state: np.ndarray
    measurement_valid: np.ndarray
    uv_px: np.ndarray
    bbox: np.ndarray
    pose_valid: np.ndarray
    est_p_ned_m: np.ndarray
    est_cov_ned_m2: np.ndarray
    observable: np.ndarray
    range_sigma_ratio: np.ndarray
    base_p_ned_m: np.ndarray
    base_cov_ned_m2: np.ndarray
    base_observable: np.ndarray
    batch: dict | None = None
    timing: dict = field(default_factory=dict)
    counters: dict = field(default_factory=dict)
    frame: dict | None = None
    error: str | None = None
    nav_noise: str = ""
    baseline_pixel_sigma_px: float = math.nan
    chain_centroid_sigma_px: float = math.nan
    estimator: str = "map"  # EvalOptions.estimator: the plug-in that made est_* and base_* (batch columns stay MAP)
    tracker: str = "objects"  # EvalOptions.tracker, or the configuration's imaging.chain when it names none
    #: with EvalOptions.guidance: advices planned, the first one's time from the first frame (s), manoeuvres, updates,
    #: skips, setpoints sent, the gate's stops (LockstepGuidance.summary)
    guidance: dict | None = None
    mot_gt: str = ""  # gt.txt of every object (groundsim.evaluation.mot)
    mot_tracker: str = ""  # the pipeline's objects, MOT tracker lines
    #: the run's perception figures (groundsim.evaluation.mot.PerceptionScore): Pd, false tracks a minute, id
    #: switches, the selected target's Anti-UAV state accuracy
    perception: dict = field(default_factory=dict)
    #: the GNSS dropout's window, scenario seconds [start, end) (None: none), and the scenario time the daemon's
    #: watchdog first named it (``gnss_dropout``) from the frames' poses (NaN: never)
    gnss_window_s: tuple[float, float] | None = None
    gnss_warning_t_s: float = math.nan
    #: the camera clock's offset estimate at the end (``TimeOffsetEstimate.as_dict``) with the scenario times of the
    #: first measured frame, the first confident estimate and the first ``camera_time_offset`` warning (NaN: never),
    #: the largest confident |estimate| (``max_abs_confident_ms``), ``injected_ms`` and ``warned``; None when
    #: ``time_offset.enabled`` is false
    time_offset: dict | None = None
    #: (F,) the frame's track had a line of sight (None: not recorded)
    los_valid: np.ndarray | None = None

    @property
    def has_estimate(self) -> np.ndarray:
        return np.all(np.isfinite(self.est_p_ned_m), axis=1)

    @property
    def base_has_estimate(self) -> np.ndarray:
        return np.all(np.isfinite(self.base_p_ned_m), axis=1)


def _result_columns(F: int) -> dict[str, np.ndarray]:
    """RunResult's per-frame arrays for F frames by field name, holding nothing yet (NaN, False, '')."""
    nan = math.nan
    return dict(
        t_s=np.full(F, nan),
        time_boot_us=np.zeros(F, dtype=np.int64),
        truth_p_ned_m=np.full((F, 3), nan),
        cam_p_ned_m=np.full((F, 3), nan),
        observer_p_ned_m=np.full((F, 3), nan),
        range_m=np.full(F, nan),
        truth_uv_px=np.full((F, 2), nan),
        visible=np.zeros(F, dtype=bool),
        state=np.empty(F, dtype="<U9"),
        measurement_valid=np.zeros(F, dtype=bool),
        pose_valid=np.zeros(F, dtype=bool),
        los_valid=np.zeros(F, dtype=bool),
        uv_px=np.full((F, 2), nan),
        bbox=np.full((F, 4), nan),
        est_p_ned_m=np.full((F, 3), nan),
        est_cov_ned_m2=np.full((F, 3, 3), nan),
        observable=np.zeros(F, dtype=bool),
        range_sigma_ratio=np.full(F, nan),
        base_p_ned_m=np.full((F, 3), nan),
        base_cov_ned_m2=np.full((F, 3, 3), nan),
        base_observable=np.zeros(F, dtype=bool),
    )


def _empty_result(scenario: Scenario, seed: int, error: str) -> RunResult:
    return RunResult(scenario.name, scenario.description, seed, 0, **_result_columns(0), error=error)


def centroid_sigma_px(uv_px, truth_uv_px, sel) -> float | None:
    """The image chain's centroid error, 1 sigma per axis: RMS of (centroid - truth pixel) over both
    axes of the selected frames (bias included); None when no frame is selected."""
    ok = np.asarray(sel, dtype=bool) & np.all(np.isfinite(uv_px), axis=1) & np.all(np.isfinite(truth_uv_px), axis=1)
    if not ok.any():
        return None
    d = np.asarray(uv_px)[ok] - np.asarray(truth_uv_px)[ok]
    return float(np.sqrt(np.mean(d**2)))


def _estimate_row(est) -> tuple[np.ndarray, np.ndarray, bool]:
    """(p (3,), cov (3, 3), observable) of a TrackEstimate, NaN when absent or not finite."""
    if est is None:
        return np.full(3, np.nan), np.full((3, 3), np.nan), False
    p = np.asarray(est.p_ned_m, dtype=float)
    P = np.asarray(est.cov_p_ned_m2, dtype=float)
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(P))):
        return np.full(3, np.nan), np.full((3, 3), np.nan), False
    return p, P, bool(est.observable)


def _better_frame(kept: dict | None, k: int, F: int, track) -> bool:
    """Keep the frame with a track box nearest the middle of the run (the middle one without any)."""
    has_box = track is not None and track.bbox is not None
    if kept is None:
        return has_box or k == F // 2
    if not has_box:
        return False
    return kept["bbox"] is None or abs(k - F // 2) < abs(kept["k"] - F // 2)


#: flight chunk with guidance in the loop, s: an advice takes effect at most this late
GUIDED_FLIGHT_CHUNK_S = 0.1


def run_lockstep(
    scenario: Scenario, seed: int, options: EvalOptions | None = None, base_config=None, progress=None
) -> RunResult:
    """One closed-loop run (see the module docstring).  ``base_config``: the daemon's OnboardConfig
    (default: built-in); ``progress(n_frames)`` is called every few frames with the frames just done.

    Raises IrtrackError for a bad scenario/option; the caller decides whether a run may fail alone.
    """
    from groundsim.evaluation.lockstep_guidance import LockstepGuidance
    from groundsim.evaluation.mot import PerceptionScore, gt_rows, tracker_positions, tracker_rows, unscorable_objects
    from groundsim.world.sim import CAMERA_ZOOM, SimCore
    from onboard.core.irframe import IrFrame
    from onboard.core.pose import PoseBuffer
    from onboard.io.record import RecordingPoseSource
    from onboard.pipeline.frame_pipeline import FramePipeline, FrameRejected, make_estimator, make_tracker

    options = options if options is not None else EvalOptions()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    cfg = onboard_config_for(scenario, base_config)
    K = cfg.camera.pinhole()
    # guided: fly short chunks, so that an advice takes effect within a few frames (the ticks flown ahead keep their path)
    chunk_s = GUIDED_FLIGHT_CHUNK_S if options.guidance else 1.0
    core = SimCore(
        scenario, seed, options.duration_s, render=True, flight_chunk_s=chunk_s, nav_noise=options.injected.nav_noise
    )
    # the daemon's guidance tap and setpoint gate; home is the scenario's origin on the ground
    guidance = LockstepGuidance(cfg, core.flight, scenario.origin.alt_m) if options.guidance else None
    buffer = PoseBuffer(cfg.camera.camera_mount(), cfg.pose, cfg.pose.geodetic_origin())
    source = RecordingPoseSource(buffer)  # remembers the pose the pipeline got, for the baseline
    if (
        options.estimator is not None
    ):  # a plug-in (onboard.pipeline.plugins), for the pipeline and its perfect-centroid baseline
        from onboard.pipeline.plugins import build

        make_estimator = lambda c: build(options.estimator, c)  # noqa: E731
    if options.tracker is not None:
        from onboard.pipeline.plugins import TRACKERS, build

        tracker = build(options.tracker, cfg, TRACKERS, "--tracker")
    else:
        tracker = make_tracker(cfg)
    pipeline = FramePipeline(cfg, source, tracker, make_estimator(cfg), scenario.origin, counter=buffer.counter)
    baseline = make_estimator(cfg)
    m = cfg.mavlink
    gd = options.injected.gnss_dropout
    feed = TelemetryFeed(
        core,
        buffer,
        core.gimballed,
        (m.attitude_rate_hz, m.position_rate_hz, m.gimbal_rate_hz),
        None if gd is None else gd.boot_window_us(core.boot_start_us),
        body_rates=options.rotation_wait_us is not None,
        gimbal_frame=options.gimbal_frame,
    )
    gnss_warning_t_s = math.nan
    # the daemon's own checks (gnss_dropout, camera_time_offset), on the frames' time
    from onboard.app.watchdog import Watchdog

    watchdog = Watchdog(
        started_s=0.0, frame_key="", zenoh_where="", mavlink_connection="", camera_size_px=(K.width_px, K.height_px)
    )
    clock = options.injected.camera_clock
    offset_times = {
        "first_measurement_t_s": math.nan,
        "confident_t_s": math.nan,
        "warning_t_s": math.nan,
        "max_abs_confident_ms": math.nan,
    }
    rng = scenario.rng("eval.centroid_noise", seed)

    F = core.frame_count
    nan = math.nan
    # the run's per-frame columns (RunResult's arrays, then the ones it does not keep), cut together to
    # the frames processed if the run stops early
    c = SimpleNamespace(
        **_result_columns(F),
        cam_pose_p=np.full((F, 3), nan),
        cam_pose_q=np.full((F, 4), nan),
        render_ms=np.zeros(F),
        process_ms=np.zeros(F),
        baseline_ms=np.zeros(F),
        unit_noise=rng.standard_normal((F, 2)),  # the baseline's centroid noise, scaled once the chain's error is known
    )
    rejected = 0
    kept = None
    done_since = 0
    mot_gt: list[str] = []
    mot_tracker: list[str] = []
    perception = PerceptionScore(scenario.frame_rate_hz)
    unscorable = 0  # tracked objects the MOT file leaves out (a centre not a finite number)

    n_done = F
    for k in range(F):
        i = k * core.ticks_per_frame
        t_frame_us = core.time_boot_us(i)
        # a frame stamped late is looked up at its stamp: the daemon waits for that telemetry, so does the feed
        stamped = None if clock is None else clock.stamp_us(t_frame_us, core.tick_time_s(i))
        late_us = 0 if stamped is None else max(stamped - t_frame_us, 0)
        if options.rotation_wait_us is None:
            feed.feed_for(i, t_frame_us + late_us)
        else:
            feed.feed_for_rotation(i, t_frame_us + late_us, options.rotation_wait_us)
        if feed.exhausted and buffer.lookup(t_frame_us).pose is None:
            # the simulation ends before a telemetry sample after this frame: the run's last frame or two
            # can have no pose in lockstep (nor in a real run that stops there); they are not processed
            n_done = k
            log.debug(
                "%s seed %d: frames %d.. after the last telemetry sample are not processed", scenario.name, seed, k
            )
            break
        r0 = core.render_s
        fr = core.frame(k)
        c.render_ms[k] = (core.render_s - r0) * 1e3
        tr = fr.truth
        c.t_s[k], c.time_boot_us[k] = tr.t_s, fr.time_boot_us
        c.truth_p_ned_m[k] = (tr.target_n_m, tr.target_e_m, tr.target_d_m)
        c.cam_p_ned_m[k] = (tr.cam_n_m, tr.cam_e_m, tr.cam_d_m)
        c.observer_p_ned_m[k] = (tr.observer_n_m, tr.observer_e_m, tr.observer_d_m)
        c.range_m[k] = tr.range_m
        c.truth_uv_px[k] = (tr.target_u_px, tr.target_v_px)
        c.visible[k] = bool(tr.target_visible)

        p0 = time.perf_counter()
        track = None
        took_frame = False  # the frame went to the pipeline (the daemon's taps see it, track or not)
        if fr.pixels is not None:  # None: the camera model dropped the frame (its shutter was closed)
            stamp = fr.time_boot_us if clock is None else clock.stamp_us(fr.time_boot_us, tr.t_s)
            if stamp is None:  # an early camera clock's stamp before the autopilot's boot: not sent
                rejected += 1
                log.debug("frame %d stamped before the autopilot's boot by the camera clock: not sent", k)
            else:
                took_frame = True
                try:
                    track = pipeline.process(IrFrame(fr.seq, stamp, fr.pixels, zoom=CAMERA_ZOOM))
                except FrameRejected as exc:  # counted by the pipeline; the frame has no track
                    rejected += 1
                    log.debug("frame %d rejected: %s", k, exc)
                except Exception as exc:  # noqa: BLE001 - as the daemon's loop: a plug-in's error skips one frame
                    buffer.counter.count("pipeline_error", f"{type(exc).__name__}: {' '.join(str(exc).split())}")
        c.process_ms[k] = (time.perf_counter() - p0) * 1e3
        _, pose = source.take()
        if gd is not None and track is not None:
            watchdog.navigation(float(tr.t_s), pipeline.last_position_age_s)
            if math.isnan(gnss_warning_t_s) and gd.active(float(tr.t_s)) and "gnss_dropout" in watchdog.warned:
                gnss_warning_t_s = float(tr.t_s)
        if track is not None and pipeline.time_offset is not None:
            _time_offset_times(
                offset_times, float(tr.t_s), track, pipeline, watchdog, cfg.time_offset.warn_threshold_ms
            )
        if track is not None:
            c.state[k] = track.state
            c.los_valid[k] = track.los is not None
            c.measurement_valid[k] = track.measurement_valid
            if track.u_px is not None:
                c.uv_px[k] = (track.u_px, track.v_px)
            if track.bbox is not None:
                c.bbox[k] = track.bbox
            c.pose_valid[k] = track.pose_valid
            if track.has_position:
                c.est_p_ned_m[k] = track.p_ned_m
                c.est_cov_ned_m2[k] = track.cov_p_ned_m2
                c.observable[k] = track.observable
                c.range_sigma_ratio[k] = nan if track.range_sigma_ratio is None else track.range_sigma_ratio
        if pose is not None:
            c.cam_pose_p[k], c.cam_pose_q[k] = pose.p_cam_ned_m, pose.q_ned_from_cam
        if guidance is not None:
            guidance.frame(float(tr.t_s), took_frame, pose, track)
        mot_gt += gt_rows(k + 1, fr.labels, (tr.target_u_px, tr.target_v_px), bool(tr.target_visible))
        objects = getattr(pipeline.tracker, "last_objects", None)  # the objects chain's; None for the single chain
        if track is not None:
            mot_tracker += tracker_rows(k + 1, objects, track)
            unscorable += unscorable_objects(objects, track)
        perception.add(
            [(o.object_id, o.u_px, o.v_px, o.visibility == "visible", o.contrast_netd) for o in fr.labels]
            if fr.labels
            else [(0, float(tr.target_u_px), float(tr.target_v_px), bool(tr.target_visible), None)],
            {} if track is None else tracker_positions(objects, track),
            None
            if track is None or track.u_px is None or track.state not in ("tracking", "coasting")
            else (track.u_px, track.v_px),
            processed=track is not None,
        )

        if options.keep_frame and fr.pixels is not None and _better_frame(kept, k, F, track):
            kept = dict(
                k=k,
                t_s=float(tr.t_s),
                pixels=fr.pixels.copy(),
                bbox=None if track is None or track.bbox is None else tuple(track.bbox),
                uv_px=None if track is None or track.u_px is None else (track.u_px, track.v_px),
                truth_uv_px=(tr.target_u_px, tr.target_v_px),
                state=None if track is None else track.state,
                range_m=tr.range_m,
            )
        done_since += 1
        if progress is not None and done_since >= PROGRESS_EVERY_FRAMES:
            progress(done_since)
            done_since = 0
    if progress is not None and done_since + (F - n_done) > 0:
        progress(done_since + (F - n_done))  # the bar counts the frames planned

    if n_done < F:
        c = SimpleNamespace(**{name: a[:n_done] for name, a in vars(c).items()})
        F = n_done

    # perfect-centroid baseline: truth pixel + white noise of the chain's own centroid error (or the
    # --pixel-sigma override), through the SAME camera poses the pipeline got for each frame
    chain_sigma_px = centroid_sigma_px(c.uv_px, c.truth_uv_px, c.measurement_valid & c.visible)
    if options.pixel_sigma_px is not None:
        base_sigma_px = float(options.pixel_sigma_px)
    else:
        base_sigma_px = DEFAULT_PIXEL_SIGMA_PX if chain_sigma_px is None else chain_sigma_px
    base_has_data = False
    # the baseline gets rows of the poses the batch and the scores read after it: read-only, so that a plug-in
    # writing into its inputs fails its own frame and cannot move the other figures
    c.cam_pose_p.setflags(write=False)
    c.cam_pose_q.setflags(write=False)
    for k in range(F):
        b0 = time.perf_counter()
        has_pose = bool(np.all(np.isfinite(c.cam_pose_p[k])))
        est = None
        try:
            if has_pose and c.visible[k]:
                uv = c.truth_uv_px[k] + base_sigma_px * c.unit_noise[k]
                est = baseline.add(
                    float(c.t_s[k]),
                    (float(uv[0]), float(uv[1])),  # a tuple, as the pipeline passes it
                    K,
                    c.cam_pose_p[k],
                    c.cam_pose_q[k],
                )
                base_has_data = True
            elif base_has_data:
                est = baseline.predict(float(c.t_s[k]), c.cam_pose_p[k] if has_pose else None)
        except IrtrackError as exc:
            log.debug("baseline frame %d: %s", k, exc)
        except Exception as exc:  # noqa: BLE001 - a plug-in's error, as in the pipeline: this frame has no estimate
            buffer.counter.count(
                "baseline_estimator_error", f"{type(exc).__name__}: {' '.join(str(exc).split())}", level=logging.DEBUG
            )
        c.base_p_ned_m[k], c.base_cov_ned_m2[k], c.base_observable[k] = _estimate_row(est)
        c.baseline_ms[k] = (time.perf_counter() - b0) * 1e3

    batch = None
    batch_s = 0.0
    if options.batch:
        b0 = time.perf_counter()
        batch = _batch(
            cfg,
            K,
            c.t_s,
            c.uv_px,
            c.measurement_valid,
            c.truth_uv_px,
            c.visible,
            c.cam_pose_p,
            c.cam_pose_q,
            c.truth_p_ned_m,
            scenario,
            seed,
            base_sigma_px,
            core.nav_noise,
        )
        batch_s = time.perf_counter() - b0

    wall = time.perf_counter() - wall0
    timing = dict(
        wall_s=wall,
        cpu_s=time.process_time() - cpu0,
        flight_s=core.flight.flight_s,
        render_s=float(c.render_ms.sum() / 1e3),
        pipeline_s=float(c.process_ms.sum() / 1e3),
        baseline_s=float(c.baseline_ms.sum() / 1e3),
        batch_s=batch_s,
        render_ms=c.render_ms,
        process_ms=c.process_ms,
        baseline_ms=c.baseline_ms,
    )
    tracker = pipeline.tracker
    counters = dict(buffer.counter.counts)
    counters.update(frames_rejected=rejected, estimator_resets=pipeline.estimator_resets)
    if unscorable:
        counters["objects_not_finite"] = unscorable
    # the single chain's own counters; the objects chain has none of them (a 0 would read as a measurement)
    counters.update({k: getattr(tracker, k) for k in ("kcf_reseeds", "reacquisitions") if hasattr(tracker, k)})
    return RunResult(
        scenario=scenario.name,
        description=scenario.description,
        seed=int(seed),
        frames=F,
        **{name: getattr(c, name) for name in _result_columns(0)},
        batch=batch,
        timing=timing,
        counters=counters,
        frame=kept,
        nav_noise=core.nav_noise.name,
        baseline_pixel_sigma_px=base_sigma_px,
        chain_centroid_sigma_px=math.nan if chain_sigma_px is None else chain_sigma_px,
        estimator=options.estimator or "map",
        tracker=options.tracker or cfg.imaging.chain,
        guidance=None if guidance is None else guidance.summary(float(c.t_s[0]) if F else None),
        mot_gt="".join(mot_gt),
        mot_tracker="".join(mot_tracker),
        perception=perception.figures(),
        gnss_window_s=None if gd is None else (gd.start_s, gd.start_s + gd.duration_s),
        gnss_warning_t_s=gnss_warning_t_s,
        time_offset=None
        if pipeline.time_offset_estimate is None
        else {
            **pipeline.time_offset_estimate.as_dict(),
            **offset_times,
            "injected_ms": None if clock is None else clock.offset_ms,
            "warned": "camera_time_offset" in watchdog.warned,
        },
    )


def _time_offset_times(times: dict, t_s: float, track, pipeline, watchdog, threshold_ms: float) -> None:
    """Scenario times of the first measured frame, the first confident clock-offset estimate and the first
    ``camera_time_offset`` warning (the daemon's watchdog, on the frame's time); the largest confident |estimate|."""
    if track.measurement_valid and math.isnan(times["first_measurement_t_s"]):
        times["first_measurement_t_s"] = t_s
    est = pipeline.time_offset_estimate
    watchdog.camera_time_offset(t_s, est, threshold_ms)
    if est.confident:
        if math.isnan(times["confident_t_s"]):
            times["confident_t_s"] = t_s
        times["max_abs_confident_ms"] = float(np.nanmax([times["max_abs_confident_ms"], abs(est.estimate_ms)]))
    if math.isnan(times["warning_t_s"]) and "camera_time_offset" in watchdog.warned:
        times["warning_t_s"] = t_s


#: how often over a flight the bound the online verdict is held to is taken (:func:`_batch`)
CAUSAL_BOUND_EVERY_S = 0.5


def _batch(
    cfg, K, t_s, uv, meas, truth_uv, visible, cam_p, cam_q, truth_p, scenario, seed, pixel_sigma_px, nav_case=None
) -> dict:
    """Whole-flight MAP on the pipeline's centroids and on perfect centroids, and the Bayesian CRB."""
    from groundsim.evaluation.synth import estimator_noise_model
    from onboard.estimation.crb import bayesian_crb_in_windows, online_verdict_bound_ratios
    from onboard.estimation.map_estimator import EstimationError, MapEstimator, NoiseModel
    from onboard.estimation.observations import Observations
    from onboard.estimation.sliding import SlidingWindowEstimator
    from onboard.estimation.windows import DEFAULT_WINDOW_S, solvable_rows, solve_in_windows

    has_pose = np.all(np.isfinite(cam_p), axis=1)
    out: dict = {}
    rng = scenario.rng("eval.batch_centroid_noise", seed)
    noisy_truth_uv = truth_uv + rng.standard_normal(truth_uv.shape) * pixel_sigma_px
    for name, sel, pix in (("pipeline", meas & has_pose, uv), ("perfect", visible & has_pose, noisy_truth_uv)):
        est = MapEstimator(noise=cfg.estimator.noise_model())
        idx = np.flatnonzero(sel & np.all(np.isfinite(pix), axis=1))
        # a few frames far from the rest of a long flight (a short sighting between long losses) get no batch
        # estimate rather than cost the run its whole batch
        idx = idx[solvable_rows(t_s[idx], DEFAULT_WINDOW_S, est.config.min_frames)]
        entry: dict = {
            "frames": idx,
            "p_ned_m": None,
            "cov_ned_m2": None,
            "observable": False,
            "model": None,
            "solve_s": 0.0,
            "windows": 0,
            "error": None,
        }
        out[name] = entry
        if idx.size < est.config.min_frames:
            entry["error"] = f"{idx.size} frames with a centroid and a pose (< {est.config.min_frames})"
            continue
        obs = Observations.from_intrinsics(t_s[idx], pix[idx], K, cam_p[idx], cam_q[idx])
        t0 = time.perf_counter()
        try:
            res = solve_in_windows(est.solve, obs, DEFAULT_WINDOW_S, est.config.min_frames)
        except (EstimationError, InputError) as exc:
            entry["error"] = f"{type(exc).__name__}: {exc}"
            continue
        entry["solve_s"] = time.perf_counter() - t0
        entry.update(
            p_ned_m=np.asarray(res.p_ned_m),
            cov_ned_m2=np.asarray(res.cov_p_ned_m2),
            observable=bool(res.observable),
            model=str(res.model or "mixed"),
            range_sigma_ratio=float(res.range_sigma_ratio),
            windows=len(res.windows),
        )
        if name == "perfect":
            # the bound of the flown trajectory for the noise actually simulated (the baseline's pixel
            # noise and the telemetry's navigation errors), and for the noise model the estimator assumes
            entry["crb_rms_m"] = entry["crb_model_rms_m"] = entry["crb_model_range_sigma_ratio"] = math.nan
            try:
                if pixel_sigma_px > 0:
                    simulated = (
                        NoiseModel(pixel_sigma_px=pixel_sigma_px)
                        if nav_case is None
                        else estimator_noise_model(nav_case, pixel_sigma_px=pixel_sigma_px)
                    )
                    sim = MapEstimator(est.config, simulated)
                    entry["crb_rms_m"] = bayesian_crb_in_windows(sim, res, obs, truth_p[idx]).rms_m()
                model_bound = bayesian_crb_in_windows(est, res, obs, truth_p[idx])
                entry["crb_model_rms_m"] = model_bound.rms_m()
                entry["crb_model_range_sigma_ratio"] = model_bound.range_sigma_ratio()
                # what the online verdict could say at best, every half second: its figure at the bound of the
                # sliding window's own rows up to that time, solved as the window solves them
                sliding = cfg.estimator.sliding_config()
                online = MapEstimator(SlidingWindowEstimator.default_map_config(sliding), est.noise)
                t_eval = t_s[0] + np.arange(1.0, t_s[-1] - t_s[0] + 1e-9, CAUSAL_BOUND_EVERY_S)
                entry["causal_bound_t_s"] = t_eval - t_s[0]
                entry["causal_bound_range_sigma_ratio"] = online_verdict_bound_ratios(
                    online, res, obs, truth_p[idx], t_eval, sliding
                )
            except (EstimationError, InputError, np.linalg.LinAlgError) as exc:
                entry["error"] = f"CRB: {type(exc).__name__}: {exc}"
    return out


# --------------------------------------------------------------------------- many runs


@dataclass(frozen=True, eq=False)
class EvalResult:
    """Runs (in job order), their scores and the per-scenario summary; ``wall_s`` of the whole eval."""

    runs: list
    scores: list
    summary: list
    wall_s: float
    workers: int
    options: EvalOptions
    config_source: str


class EvalInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`run_eval`: ``result`` holds the runs that finished (scored and summarised, in job
    order), ``planned`` the number of runs asked for."""

    def __init__(self, result: EvalResult, planned: int) -> None:
        super().__init__(f"{len(result.runs)} of {planned} runs done")
        self.result = result
        self.planned = planned


def _plugins(options: EvalOptions) -> str:
    """The plug-ins a run loads, for its error line: ``estimator X, tracker Y`` (the defaults left out)."""
    named = [
        f"{kind} {name}" for kind, name in (("estimator", options.estimator), ("tracker", options.tracker)) if name
    ]
    return ", ".join(named) or "the configuration's estimator and chain"


def _job(args) -> RunResult:
    """One run, in a pool worker or here; a run that cannot be made (e.g. a flight failure) fails alone.

    Any exception but Ctrl-C fails the run, SystemExit too: a plug-in is foreign code, and its sys.exit() in a
    pool worker ended the worker with its job unfinished (the pool waited for it for ever); in this process it
    ended the command with the plug-in's exit code, the runs already done lost."""
    scenario, seed, options, base_config = args
    try:
        return run_lockstep(scenario, seed, options, base_config, report_progress)
    except IrtrackError as exc:
        log.error("%s seed %d: %s", scenario.name, seed, exc)
        return _empty_result(scenario, seed, f"{type(exc).__name__}: {' '.join(str(exc).split())}")
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # noqa: BLE001 - foreign code: whatever it raises fails this run alone
        error = f"{type(exc).__name__} in a run with {_plugins(options)}: {' '.join(str(exc).split())}"
        log.error("%s seed %d: %s", scenario.name, seed, error)
        return _empty_result(scenario, seed, error)


def _lost_job(args, why: str) -> RunResult:
    """The failed run of a job whose pool worker ended under it (a plug-in's os._exit, a crash)."""
    scenario, seed, options, _ = args
    error = f"WorkerLost in a run with {_plugins(options)}: {why}"
    log.error("%s seed %d: %s", scenario.name, seed, error)
    return _empty_result(scenario, seed, error)


def run_eval(
    scenarios: list[Scenario],
    seeds,
    options: EvalOptions | None = None,
    base_config=None,
    workers: int = 2,
    progress: bool = True,
    config_source: str = "(defaults)",
    nav_noises=None,
    run_timeout_s: float | None = None,
) -> EvalResult:
    """All (navigation case, scenario, seed) runs, over ``workers`` processes (1 = in this process), then
    scored.  ``nav_noises``: case names to run each scenario with (default: ``options.injected.nav_noise`` only).
    ``run_timeout_s``: each run's wall-clock deadline on a pool, a run past it failed (None: 20 x its simulated
    seconds + 120 s, :func:`~groundsim.evaluation.parallel.auto_deadline_s`); not enforced in this process."""
    options = options if options is not None else EvalOptions()
    variants = [options] if not nav_noises else [options.with_nav_noise(n) for n in nav_noises]
    limit_blas_threads(1)  # here and, through the environment, in the worker processes
    seeds = [int(s) for s in seeds]
    if not scenarios:
        raise ConfigError("--scenario: expected at least one scenario")
    if not seeds:
        raise ConfigError("--seeds: expected at least one seed")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"--workers: expected an integer >= 1, got {workers!r}")
    from groundsim.world.sim import extend_scenario, frame_count

    run_timeout_s = check_run_timeout(run_timeout_s)

    def deadline_s(job) -> float:
        sc, _, o, _ = job
        if run_timeout_s is not None:
            return run_timeout_s
        return auto_deadline_s(sc.duration_s if o.duration_s is None else o.duration_s)

    jobs = [(sc, seed, o, base_config) for o in variants for sc in scenarios for seed in seeds]
    total = 0
    for sc in scenarios:
        if options.duration_s is not None:
            extend_scenario(sc, options.duration_s)  # a model that cannot run longer fails here, before any run
        d = sc.duration_s if options.duration_s is None else options.duration_s
        total += frame_count(d, sc.frame_rate_hz) * len(seeds) * len(variants)
    t0 = time.perf_counter()
    workers = min(workers, len(jobs))
    bar = None
    if progress:
        bar = progress_bar(total, "frame", "eval" if workers == 1 else f"eval ({workers} workers)")
    try:
        results = run_jobs(
            _job, jobs, workers, None if bar is None else bar.update, on_lost=_lost_job, deadline_s=deadline_s
        )
    except JobsInterrupted as exc:
        done = [r for r in exc.results if r is not None]
        scores = [score_run(r) for r in done]
        wall = time.perf_counter() - t0
        partial = EvalResult(done, scores, summarise(scores), wall, workers, options, config_source)
        raise EvalInterrupted(partial, len(jobs)) from None
    finally:
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - t0
    scores = [score_run(r) for r in results]
    return EvalResult(results, scores, summarise(scores), wall, workers, options, config_source)


def keep_interrupted(exc: EvalInterrupted, out_dir) -> str:
    """What an interrupted eval keeps: the report of its finished runs, written into ``out_dir`` (nothing
    when none finished); returns the words saying so, e.g. ``"2 of 6 runs done; partial report in ..."``."""
    from groundsim.evaluation.report import write_eval_report

    kept = "nothing written"
    if exc.result.runs:
        kept = f"partial report in {write_eval_report(out_dir, exc.result, planned=exc.planned)['report.md']}"
    return f"{len(exc.result.runs)} of {exc.planned} runs done; {kept}"
