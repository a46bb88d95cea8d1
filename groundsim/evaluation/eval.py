"""``python -m groundsim eval``: the closed loop in lockstep, scored against the truth (issue #5).

One *run* is one (scenario, run seed).  It drives the very objects the onboard daemon drives, through
their step methods, without sockets or threads, as fast as the CPU allows and deterministically::

    SimCore (groundsim.app.run)          fly both vehicles with JSBSim, render the IR frame, truth row
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
navigation errors (``EvalOptions.nav_noise``, ``--nav-noise``, default RTK; :mod:`groundsim.world.nav_errors`,
drawn from ``scenario.rng("nav.errors", seed)``), applied by the very function the MAVLink vehicle
uses.  Stream rates are the ones the daemon's configuration requests (``mavlink.attitude_rate_hz``,
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
selection on the whole flight, once on the pipeline's measured centroids and once on the perfect
centroids; the Bayesian Cramer-Rao bound (:func:`~onboard.estimation.crb.bayesian_crb_rms_m`) of
the flown trajectory is taken with the perfect-centroid solution's motion prior, for the noise
actually simulated (the baseline's pixel noise and the run's navigation-error case: ``crb_rms_m``) and
for the noise model the estimator assumes (``crb_model_rms_m``).

Scoring definitions (:func:`score_run`; metrics from :func:`onboard.estimation.metrics.evaluate`):

- *observable frames*: frames whose Track has a 3-D estimate flagged observable (the daemon publishes
  the unobservable ones too, flagged so, unless ``output.unobservable_positions`` is false) -- the headline;
- *all frames with an estimate*: any finite 3-D estimate, observable or not;
- *continuity*: observable frames / all frames; *2-D continuity*: frames with a valid centroid /
  frames where the target is in the image;
- paper metric ``mean ||e|| / ||X||`` (world origin = the scenario's NED origin, on the ground under
  the observer's start), range-normalised error ``mean ||e|| / range``, RMSE, mean NEES (3 for a
  consistent covariance), fraction beyond 3 sigma;
- centroid error: image-chain centre minus truth pixel on frames with a valid centroid;
- closed-loop figures of issue 9 (:func:`closed_loop_figures`): published 3-D positions on tracking
  frames after 3 s, their honesty (beyond 3 sqrt(trace cov)), observable share after 5 s, median
  error / range on observable frames.

Runs are independent jobs over a process pool (``workers`` processes from a fork server, see
:func:`mp_context`); a tqdm bar on stderr counts frames.  Everything but the timing figures is a function of (scenario, seed, options).
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

from groundsim.evaluation.parallel import progress_bar, quiet_run_logs, run_pool
from groundsim.evaluation.report import BASELINE_FAIL_PCT, RATIO_LIMIT, make_out_dir
from groundsim.world.scenario import DEFAULT_NAV_NOISE, Scenario
from onboard.core.errors import ConfigError, InputError, IrtrackError
from onboard.estimation.metrics import score_frames

__all__ = [
    "DEFAULT_ONBOARD_CONFIG",
    "DEFAULT_PIXEL_SIGMA_PX",
    "EvalOptions",
    "RunResult",
    "EvalResult",
    "TelemetryFeed",
    "limit_blas_threads",
    "onboard_config_for",
    "load_base_config",
    "run_lockstep",
    "score_run",
    "summarise",
    "run_eval",
    "cmd_eval",
]

log = logging.getLogger(__name__)

DEFAULT_ONBOARD_CONFIG = Path("config/onboard.yaml")  # the daemon's shipped configuration (noise model included)
DEFAULT_PIXEL_SIGMA_PX = 0.3  # perfect-centroid baseline noise when the chain measured no centroid (reference px0.3)
ATT_RATE_HZ, POS_RATE_HZ, GIMBAL_RATE_HZ = 50.0, 25.0, 10.0  # MavlinkVehicle's default streams
PROGRESS_EVERY_FRAMES = 10
US_PER_S = 1_000_000


# --------------------------------------------------------------------------- BLAS threads


BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
_OPENBLAS_SETTERS = (
    "scipy_openblas_set_num_threads64_",
    "scipy_openblas_set_num_threads",
    "openblas_set_num_threads64_",
    "openblas_set_num_threads",
)


def limit_blas_threads(n: int = 1) -> int:
    """One BLAS thread per process, now and in child processes; returns the libraries adjusted.

    The estimator's matrices are small: OpenBLAS's worker threads buy nothing there, and on a loaded
    2-core machine their spinning made a whole-flight solve 20x slower (24 s instead of 1.1 s wall,
    measured).  Sets the usual environment variables (for children started later) and calls
    ``*_set_num_threads`` on every OpenBLAS already loaded here (numpy and scipy each bundle one).
    """
    import ctypes

    for var in BLAS_THREAD_VARS:
        os.environ.setdefault(var, str(n))
    import scipy.linalg  # noqa: F401 - loads scipy's own OpenBLAS so that it is adjusted too

    done = 0
    try:
        with open("/proc/self/maps", encoding="ascii", errors="replace") as f:
            paths = {line.split()[-1] for line in f if "openblas" in line.lower() and ".so" in line.split()[-1]}
    except OSError:  # not Linux: the environment variables are all we can do
        return 0
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for sym in _OPENBLAS_SETTERS:
            fn = getattr(lib, sym, None)
            if fn is not None:
                fn(ctypes.c_int(int(n)))
                done += 1
                break
    return done


# --------------------------------------------------------------------------- options and configuration


@dataclass(frozen=True)
class EvalOptions:
    """How each run is made.  ``duration_s`` None = the scenario's; ``pixel_sigma_px`` the baseline's
    centroid noise (None: the image chain's own centroid error measured in the run, see the module
    docstring); ``batch`` adds the whole-flight MAP columns and the CRB; ``keep_frame`` keeps one IR
    frame per run for the report's picture; ``nav_noise``: the telemetry's navigation-error case
    (``config/noise_cases.yaml``; None = the scenario's ``nav_noise``, RTK by default)."""

    duration_s: float | None = None
    pixel_sigma_px: float | None = None
    batch: bool = True
    keep_frame: bool = True
    nav_noise: str | None = DEFAULT_NAV_NOISE
    #: the trajectory estimator, a plug-in name (``onboard.pipeline.plugins``: an ``irtrack.estimators`` entry point or
    #: ``module:Attribute``); None = the daemon's own (the configuration's sliding-window MAP estimator)
    estimator: str | None = None

    def __post_init__(self) -> None:
        d = self.duration_s
        if d is not None and (isinstance(d, bool) or not isinstance(d, (int, float)) or not math.isfinite(d) or d <= 0):
            raise ConfigError(f"--duration: expected a positive number of seconds, got {d!r}")
        s = self.pixel_sigma_px
        if s is not None and (isinstance(s, bool) or not isinstance(s, (int, float)) or not math.isfinite(s) or s < 0):
            raise ConfigError(f"--pixel-sigma: expected a number of pixels >= 0, got {s!r}")
        if self.nav_noise is not None:
            from groundsim.world.nav_errors import resolve_nav_noise

            resolve_nav_noise(self.nav_noise)
        if self.estimator is not None:
            from onboard.pipeline.plugins import load_factory

            load_factory(self.estimator)  # an unknown name fails here, before any run


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
    if hasattr(base.output, "unobservable_positions"):  # the field may go with the output policy of issue 9
        out_kw["unobservable_positions"] = True
    output = dataclasses.replace(base.output, **out_kw)
    return dataclasses.replace(base, camera=camera, pose=pose, output=output)


# --------------------------------------------------------------------------- telemetry as MAVLink carries it


class TelemetryFeed:
    """Offers a :class:`~groundsim.app.run.SimCore`'s observer state to a pose buffer, tick by tick, on
    MavlinkVehicle's stream schedule and with the wire's quantisation (module docstring).

    The state is what the simulated vehicle reports: the truth with the core's navigation error of
    that tick (``core.nav_error(i)``, when the core has one) applied by the same function the MAVLink
    vehicle uses, :func:`groundsim.world.nav_errors.reported_state`.  ``rates_hz``: ``(attitude, position,
    gimbal)`` -- the rates the daemon requests (``mavlink.*_rate_hz`` of its configuration), which the
    simulated vehicle honours; default MavlinkVehicle's own defaults.
    """

    def __init__(
        self,
        core,
        pose_buffer,
        gimballed: bool,
        rates_hz: tuple[float, float, float] = (ATT_RATE_HZ, POS_RATE_HZ, GIMBAL_RATE_HZ),
    ) -> None:
        self.core = core
        self.pose = pose_buffer
        self.gimballed = gimballed
        self.next_tick = 0
        att_hz, pos_hz, gim_hz = (float(x) for x in rates_hz)
        self._interval_us = {"att": round(US_PER_S / att_hz), "pos": round(US_PER_S / pos_hz)}
        if gimballed:
            self._interval_us["gim"] = round(US_PER_S / gim_hz)
        self._due_us = {k: 0 for k in self._interval_us}

    @property
    def exhausted(self) -> bool:
        return self.next_tick >= self.core.tick_count

    def feed_next(self) -> None:
        """Offer the next tick's state (streams due at that tick only), encoded and decoded by
        :mod:`onboard.io.mavlink_wire` as the MAVLink vehicle and the daemon's link do (packed and parsed:
        the wire's quantisation).  The body and gimbal rates are not fed: the lockstep loop waits for the
        bracketing sample instead of extrapolating (the benchmark's accuracy tables are defined so)."""
        from groundsim.world.nav_errors import reported_state
        from onboard.io.mavlink_wire import (
            AttitudeQuaternion,
            GimbalDeviceAttitudeStatus,
            GlobalPositionInt,
            mavlink2,
            wire_roundtrip,
        )

        i = self.next_tick
        self.next_tick += 1
        nav_error = getattr(self.core, "nav_error", None)
        st = reported_state(self.core.vehicle_state(i), None if nav_error is None else nav_error(i))
        now = int(st["time_boot_us"])
        for name, interval in self._interval_us.items():
            if now < self._due_us[name]:
                continue
            if name == "att":
                att = AttitudeQuaternion.from_message(
                    wire_roundtrip(
                        AttitudeQuaternion(
                            now, tuple(st["q_ned_from_body"]), tuple(st["body_rates_radps"])
                        ).to_message()
                    )
                )
                self.pose.add_attitude(att.time_boot_us, att.q_ned_from_body)
            elif name == "pos":
                pos = GlobalPositionInt.from_message(
                    wire_roundtrip(
                        GlobalPositionInt(
                            now,
                            st["lat_deg"],
                            st["lon_deg"],
                            st["alt_amsl_m"],
                            st["alt_rel_m"],
                            tuple(st["v_ned_mps"]),
                            st["heading_rad"],
                        ).to_message()
                    )
                )
                self.pose.add_position(pos.time_boot_us, pos.lat_deg, pos.lon_deg, pos.alt_amsl_m, pos.v_ned_mps)
            elif st["q_gimbal"] is not None:
                gim = GimbalDeviceAttitudeStatus.from_message(
                    wire_roundtrip(
                        GimbalDeviceAttitudeStatus(
                            now, tuple(st["q_gimbal"]), mavlink2.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME
                        ).to_message()
                    )
                )
                self.pose.add_gimbal_status(gim.time_boot_us, gim.q_ref_from_gimbal, gim.reference)
            nxt = self._due_us[name] + interval
            self._due_us[name] = nxt if nxt > now else now + interval

    def feed_for(self, frame_tick: int, time_boot_us: int) -> None:
        """Feed through ``frame_tick``, then on until the pose at ``time_boot_us`` is known or will not be."""
        while self.next_tick <= frame_tick and not self.exhausted:
            self.feed_next()
        while not self.exhausted:
            res = self.pose.lookup(time_boot_us)
            if res.pose is not None or not res.retry:
                return
            self.feed_next()


class _RecordingPoseSource:
    """The pose buffer as the pipeline sees it, remembering the last answer (for the baseline)."""

    def __init__(self, buffer) -> None:
        self.buffer = buffer
        self.counter = buffer.counter
        self.last = None

    @property
    def origin(self):
        return self.buffer.origin

    def pose_at(self, time_boot_us: int):
        self.last = self.buffer.pose_at(time_boot_us)
        return self.last


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


def run_lockstep(
    scenario: Scenario, seed: int, options: EvalOptions | None = None, base_config=None, progress=None
) -> RunResult:
    """One closed-loop run (see the module docstring).  ``base_config``: the daemon's OnboardConfig
    (default: built-in); ``progress(n_frames)`` is called every few frames with the frames just done.

    Raises IrtrackError for a bad scenario/option; the caller decides whether a run may fail alone.
    """
    from groundsim.app.run import SimCore
    from onboard.core.irframe import IrFrame
    from onboard.core.pose import PoseBuffer
    from onboard.pipeline.frame_pipeline import FramePipeline, FrameRejected, make_estimator, make_tracker

    options = options if options is not None else EvalOptions()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    cfg = onboard_config_for(scenario, base_config)
    K = cfg.camera.pinhole()
    core = SimCore(scenario, seed, options.duration_s, render=True, flight_chunk_s=1.0, nav_noise=options.nav_noise)
    buffer = PoseBuffer(cfg.camera.camera_mount(), cfg.pose.buffer_config(), cfg.pose.geodetic_origin())
    source = _RecordingPoseSource(buffer)
    if (
        options.estimator is not None
    ):  # a plug-in (onboard.pipeline.plugins), for the pipeline and its perfect-centroid baseline
        from onboard.pipeline.plugins import build

        make_estimator = lambda c: build(options.estimator, c)  # noqa: E731
    pipeline = FramePipeline(
        cfg, source, make_tracker(cfg), make_estimator(cfg), scenario.origin, counter=buffer.counter
    )
    baseline = make_estimator(cfg)
    m = cfg.mavlink
    feed = TelemetryFeed(core, buffer, core.gimballed, (m.attitude_rate_hz, m.position_rate_hz, m.gimbal_rate_hz))
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

    n_done = F
    for k in range(F):
        i = k * core.ticks_per_frame
        t_frame_us = core.time_boot_us(i)
        feed.feed_for(i, t_frame_us)
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

        source.last = None
        p0 = time.perf_counter()
        try:
            track = pipeline.process(IrFrame(fr.seq, fr.time_boot_us, fr.pixels))
        except FrameRejected as exc:  # counted by the pipeline; the frame has no track
            rejected += 1
            log.debug("frame %d rejected: %s", k, exc)
            track = None
        c.process_ms[k] = (time.perf_counter() - p0) * 1e3
        pose = source.last
        if track is not None:
            c.state[k] = track.state
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

        if options.keep_frame and _better_frame(kept, k, F, track):
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
    for k in range(F):
        b0 = time.perf_counter()
        has_pose = bool(np.all(np.isfinite(c.cam_pose_p[k])))
        est = None
        try:
            if has_pose and c.visible[k]:
                est = baseline.add(
                    float(c.t_s[k]),
                    c.truth_uv_px[k] + base_sigma_px * c.unit_noise[k],
                    K,
                    c.cam_pose_p[k],
                    c.cam_pose_q[k],
                )
                base_has_data = True
            elif base_has_data:
                est = baseline.predict(float(c.t_s[k]), c.cam_pose_p[k] if has_pose else None)
        except IrtrackError as exc:
            log.debug("baseline frame %d: %s", k, exc)
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
    counters.update(
        frames_rejected=rejected,
        estimator_resets=pipeline.estimator_resets,
        kcf_reseeds=getattr(tracker, "kcf_reseeds", 0),
        reacquisitions=getattr(tracker, "reacquisitions", 0),
    )
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
    )


def _batch(
    cfg, K, t_s, uv, meas, truth_uv, visible, cam_p, cam_q, truth_p, scenario, seed, pixel_sigma_px, nav_case=None
) -> dict:
    """Whole-flight MAP on the pipeline's centroids and on perfect centroids, and the Bayesian CRB."""
    from groundsim.evaluation.synth import estimator_noise_model
    from onboard.estimation.crb import bayesian_crb_rms_m
    from onboard.estimation.map_estimator import EstimationError, MapEstimator, NoiseModel
    from onboard.estimation.observations import Observations

    has_pose = np.all(np.isfinite(cam_p), axis=1)
    out: dict = {}
    rng = scenario.rng("eval.batch_centroid_noise", seed)
    noisy_truth_uv = truth_uv + rng.standard_normal(truth_uv.shape) * pixel_sigma_px
    for name, sel, pix in (("pipeline", meas & has_pose, uv), ("perfect", visible & has_pose, noisy_truth_uv)):
        idx = np.flatnonzero(sel & np.all(np.isfinite(pix), axis=1))
        entry: dict = {
            "frames": idx,
            "p_ned_m": None,
            "cov_ned_m2": None,
            "observable": False,
            "model": None,
            "solve_s": 0.0,
            "error": None,
        }
        out[name] = entry
        est = MapEstimator(noise=cfg.estimator.noise_model())
        if idx.size < est.config.min_frames:
            entry["error"] = f"{idx.size} frames with a centroid and a pose (< {est.config.min_frames})"
            continue
        obs = Observations.from_intrinsics(t_s[idx], pix[idx], K, cam_p[idx], cam_q[idx])
        t0 = time.perf_counter()
        try:
            res = est.solve(obs)
        except (EstimationError, InputError) as exc:
            entry["error"] = f"{type(exc).__name__}: {exc}"
            continue
        entry["solve_s"] = time.perf_counter() - t0
        entry.update(
            p_ned_m=np.asarray(res.p_ned_m),
            cov_ned_m2=np.asarray(res.cov_p_ned_m2),
            observable=bool(res.observable),
            model=str(res.model or res.prior.family),
            range_sigma_ratio=float(res.range_sigma_ratio),
        )
        if name == "perfect":
            # the bound of the flown trajectory for the noise actually simulated (the baseline's pixel
            # noise and the telemetry's navigation errors), and for the noise model the estimator assumes
            entry["crb_rms_m"] = entry["crb_model_rms_m"] = math.nan
            try:
                if pixel_sigma_px > 0:
                    simulated = (
                        NoiseModel(pixel_sigma_px=pixel_sigma_px)
                        if nav_case is None
                        else estimator_noise_model(nav_case, pixel_sigma_px=pixel_sigma_px)
                    )
                    sim = MapEstimator(est.config, simulated)
                    entry["crb_rms_m"] = bayesian_crb_rms_m(sim, obs, truth_p[idx], res.prior, res.turn_rate_radps)
                entry["crb_model_rms_m"] = bayesian_crb_rms_m(est, obs, truth_p[idx], res.prior, res.turn_rate_radps)
            except (EstimationError, InputError, np.linalg.LinAlgError) as exc:
                entry["error"] = f"CRB: {type(exc).__name__}: {exc}"
    return out


# --------------------------------------------------------------------------- scoring


#: the closed-loop windows of issue 9 item 5: published positions after the track settles, observability later
PUBLISHED_AFTER_S, OBSERVABLE_AFTER_S = 3.0, 5.0


def closed_loop_figures(r: RunResult) -> dict:
    """Issue 9 item 5's figures of one run, from the pipeline's per-frame outputs (JSON-ready; None = no frame).

    *published*: a finite 3-D position in the frame's Track (lockstep publishes unobservable positions
    too, so this is what the daemon publishes once positions go out whenever the estimate is finite;
    with a daemon that publishes only observable positions it is an upper bound of that);
    ``published_share_after_3s``: published / tracking frames (state ``tracking``) at t >= 3 s;
    ``beyond_3sigma_published``: fraction of published positions with ``||e|| > 3 sqrt(trace cov)``
    (honesty; <= 0.01 asked); ``observable_share_after_5s``: observable / all frames at t >= 5 s;
    ``median_err_range_observable_pct``: median over observable frames of ``||e|| / range``, per cent;
    ``median_err_range_published_after_5s_pct``: the same over every published position at t >= 5 s;
    ``first_observable_s``: time of the first observable frame.
    """
    t = r.t_s - r.t_s[0] if r.t_s.size else r.t_s
    has = r.has_estimate
    obs = has & r.observable
    tracked = (r.state == "tracking") & (t >= PUBLISHED_AFTER_S)
    late = t >= OBSERVABLE_AFTER_S
    e = np.linalg.norm(r.est_p_ned_m - r.truth_p_ned_m, axis=1)
    with np.errstate(invalid="ignore"):
        sig3 = 3.0 * np.sqrt(np.maximum(np.einsum("fii->f", r.est_cov_ned_m2), 0.0))
    pub = has & np.isfinite(sig3)
    return {
        "tracking_frames_after_3s": int(tracked.sum()),
        "published_share_after_3s": float((tracked & has).sum() / tracked.sum()) if tracked.any() else None,
        "published_frames": int(has.sum()),
        "beyond_3sigma_published": float((e[pub] > sig3[pub]).mean()) if pub.any() else None,
        "observable_share_after_5s": float((late & obs).sum() / late.sum()) if late.any() else None,
        "median_err_range_observable_pct": float(np.median(100.0 * e[obs] / r.range_m[obs])) if obs.any() else None,
        # what the verdict withheld: the error of every published position after 5 s, and when the first
        # observable frame came (the window's span, not the estimate, is what P1's weak manoeuvre needs)
        "median_err_range_published_after_5s_pct": (
            float(np.median(100.0 * e[pub & late] / r.range_m[pub & late])) if (pub & late).any() else None
        ),
        "first_observable_s": float(t[obs][0]) if obs.any() else None,
    }


def score_run(r: RunResult) -> dict:
    """The figures of one run (definitions in the module docstring); JSON-ready."""
    if r.error is not None:
        return {"scenario": r.scenario, "seed": r.seed, "error": r.error}
    F = r.frames
    has = r.has_estimate
    obs = has & r.observable
    base_obs = r.base_has_estimate & r.base_observable
    common = obs & base_obs
    out: dict = {
        "scenario": r.scenario,
        "seed": r.seed,
        "frames": F,
        "nav_noise": r.nav_noise,
        "estimator": getattr(r, "estimator", "map"),
        "baseline_pixel_sigma_px": r.baseline_pixel_sigma_px,
        "chain_centroid_sigma_px": r.chain_centroid_sigma_px,
    }
    out["closed_loop"] = closed_loop_figures(r)
    out["online_observable"] = score_frames(r.truth_p_ned_m, r.est_p_ned_m, r.cam_p_ned_m, r.est_cov_ned_m2, obs)
    out["online_all"] = score_frames(r.truth_p_ned_m, r.est_p_ned_m, r.cam_p_ned_m, r.est_cov_ned_m2, has)
    out["perfect_observable"] = score_frames(
        r.truth_p_ned_m, r.base_p_ned_m, r.cam_p_ned_m, r.base_cov_ned_m2, base_obs
    )
    on_c = score_frames(r.truth_p_ned_m, r.est_p_ned_m, r.cam_p_ned_m, None, common)
    pf_c = score_frames(r.truth_p_ned_m, r.base_p_ned_m, r.cam_p_ned_m, None, common)
    out["common_frames"] = int(common.sum())
    out["online_common_err_range_pct"] = None if on_c is None else on_c["err_range_pct"]
    out["perfect_common_err_range_pct"] = None if pf_c is None else pf_c["err_range_pct"]
    out["continuity"] = float(obs.sum() / F) if F else 0.0
    out["estimate_fraction"] = float(has.sum() / F) if F else 0.0
    out["perfect_continuity"] = float(base_obs.sum() / F) if F else 0.0
    vis = int(r.visible.sum())
    out["continuity_2d"] = float((r.measurement_valid & r.visible).sum() / vis) if vis else 0.0
    first = np.flatnonzero(obs)
    out["first_observable_s"] = float(r.t_s[first[0]] - r.t_s[0]) if first.size else None
    first_m = np.flatnonzero(r.measurement_valid)
    out["first_centroid_s"] = float(r.t_s[first_m[0]] - r.t_s[0]) if first_m.size else None
    cm = r.measurement_valid & np.all(np.isfinite(r.truth_uv_px), axis=1)
    if cm.any():
        d = r.uv_px[cm] - r.truth_uv_px[cm]
        out["centroid_rms_px"] = float(np.sqrt(np.mean(np.sum(d**2, axis=1))))
        out["centroid_bias_px"] = [float(x) for x in d.mean(axis=0)]
    else:
        out["centroid_rms_px"], out["centroid_bias_px"] = None, None
    out["range_m"] = [float(np.nanmin(r.range_m)), float(np.nanmax(r.range_m))] if F else None
    tm = r.timing
    pm = np.asarray(tm["process_ms"])
    out["timing"] = {
        "wall_s": tm["wall_s"],
        "cpu_s": tm["cpu_s"],
        "cpu_share": tm["cpu_s"] / max(tm["wall_s"], 1e-9),
        "flight_s": tm["flight_s"],
        "render_s": tm["render_s"],
        "pipeline_s": tm["pipeline_s"],
        "baseline_s": tm["baseline_s"],
        "batch_s": tm["batch_s"],
        "pipeline_fps": float(F / max(pm.sum() / 1e3, 1e-9)),
        "loop_fps": float(F / max(tm["wall_s"], 1e-9)),
        "latency_ms": _percentiles(pm),
        "render_ms": _percentiles(np.asarray(tm["render_ms"])),
    }
    if r.batch is not None:
        b = {}
        for name in ("pipeline", "perfect"):
            e = r.batch[name]
            m = None
            if e.get("p_ned_m") is not None:
                idx = e["frames"]
                m = score_frames(
                    r.truth_p_ned_m[idx], e["p_ned_m"], r.cam_p_ned_m[idx], e["cov_ned_m2"], np.ones(idx.size, bool)
                )
            b[name] = {
                "metrics": m,
                "observable": e["observable"],
                "model": e["model"],
                "solve_s": e["solve_s"],
                "frames": int(len(e["frames"])),
                "error": e["error"],
            }
        b["crb_rms_m"] = r.batch["perfect"].get("crb_rms_m")
        b["crb_model_rms_m"] = r.batch["perfect"].get("crb_model_rms_m")
        out["batch"] = b
    out["counters"] = {str(k): int(v) for k, v in sorted(r.counters.items())}
    return out


def _percentiles(a: np.ndarray) -> dict:
    if a.size == 0:
        return {"p50": None, "p90": None, "p99": None, "max": None, "mean": None}
    p50, p90, p99 = np.percentile(a, [50, 90, 99])
    return {"p50": float(p50), "p90": float(p90), "p99": float(p99), "max": float(a.max()), "mean": float(a.mean())}


def _med(values) -> float | None:
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    return float(np.median(v)) if v else None


def _get(d: dict | None, *keys):
    for k in keys:
        if d is None:
            return None
        d = d.get(k)
    return d


#: per-run figure -> path in score_run's dict, summarised as the median over seeds
SUMMARY_FIELDS = {
    "err_paper_pct": ("online_observable", "err_paper_pct"),
    "err_range_pct": ("online_observable", "err_range_pct"),
    "rmse_m": ("online_observable", "rmse_m"),
    "nees": ("online_observable", "mean_nees"),
    "beyond_3sigma": ("online_observable", "outside_3sigma_trace_fraction"),
    "all_err_range_pct": ("online_all", "err_range_pct"),
    "all_rmse_m": ("online_all", "rmse_m"),
    "perfect_err_range_pct": ("perfect_observable", "err_range_pct"),
    "perfect_rmse_m": ("perfect_observable", "rmse_m"),
    "online_common_err_range_pct": ("online_common_err_range_pct",),
    "perfect_common_err_range_pct": ("perfect_common_err_range_pct",),
    "continuity": ("continuity",),
    "estimate_fraction": ("estimate_fraction",),
    "perfect_continuity": ("perfect_continuity",),
    "continuity_2d": ("continuity_2d",),
    "first_observable_s": ("first_observable_s",),
    "centroid_rms_px": ("centroid_rms_px",),
    "pipeline_fps": ("timing", "pipeline_fps"),
    "loop_fps": ("timing", "loop_fps"),
    "latency_p50_ms": ("timing", "latency_ms", "p50"),
    "latency_p99_ms": ("timing", "latency_ms", "p99"),
    "batch_err_range_pct": ("batch", "pipeline", "metrics", "err_range_pct"),
    "batch_perfect_err_range_pct": ("batch", "perfect", "metrics", "err_range_pct"),
    "crb_rms_m": ("batch", "crb_rms_m"),
    "published_share_after_3s": ("closed_loop", "published_share_after_3s"),
    "beyond_3sigma_published": ("closed_loop", "beyond_3sigma_published"),
    "observable_share_after_5s": ("closed_loop", "observable_share_after_5s"),
    "median_err_range_observable_pct": ("closed_loop", "median_err_range_observable_pct"),
    "median_err_range_published_after_5s_pct": ("closed_loop", "median_err_range_published_after_5s_pct"),
    "closed_loop_first_observable_s": ("closed_loop", "first_observable_s"),
    "baseline_pixel_sigma_px": ("baseline_pixel_sigma_px",),
    "chain_centroid_sigma_px": ("chain_centroid_sigma_px",),
    "crb_model_rms_m": ("batch", "crb_model_rms_m"),
    "batch_perfect_rmse_m": ("batch", "perfect", "metrics", "rmse_m"),
}


def _baseline_failed(pct) -> bool:
    return pct is None or pct > BASELINE_FAIL_PCT


def summarise(scores: list[dict]) -> list[dict]:
    """One row per (scenario, navigation-error case) (first-seen order): medians over seeds, ratios
    and their verdict.  ``label`` is the scenario's name, or ``<scenario>_<nav case>`` when the runs
    mix navigation cases.  A ratio gets no verdict when its baseline failed (perfect centroids
    unobservable or worse than ``BASELINE_FAIL_PCT`` err / range): ``baseline_failed`` /
    ``batch_baseline_failed`` say so, and ``within_ratio`` is None when no ratio has a sound baseline.
    """
    keys: list[tuple[str, str]] = []
    for s in scores:
        k = (s["scenario"], s.get("nav_noise", ""))
        if k not in keys:
            keys.append(k)
    multi = len({k[1] for k in keys}) > 1
    rows = []
    for name, nav in keys:
        runs = [s for s in scores if s["scenario"] == name and s.get("nav_noise", "") == nav]
        ok = [s for s in runs if "error" not in s]
        row: dict = {
            "scenario": name,
            "nav_noise": nav,
            "label": f"{name}_{nav}" if multi else name,
            "runs": len(runs),
            "failed_runs": len(runs) - len(ok),
        }
        for key, path in SUMMARY_FIELDS.items():
            row[key] = _med(_get(s, *path) for s in ok)
        on, pf = row["online_common_err_range_pct"], row["perfect_common_err_range_pct"]
        row["ratio_to_perfect"] = (on / pf) if (on is not None and pf not in (None, 0.0)) else None
        bo, bp = row["batch_err_range_pct"], row["batch_perfect_err_range_pct"]
        row["batch_ratio_to_perfect"] = (bo / bp) if (bo is not None and bp not in (None, 0.0)) else None
        row["baseline_failed"] = _baseline_failed(row["perfect_err_range_pct"])
        row["batch_baseline_failed"] = _baseline_failed(bp)
        ratios = [
            x
            for x, failed in (
                (row["ratio_to_perfect"], row["baseline_failed"]),
                (row["batch_ratio_to_perfect"], row["batch_baseline_failed"]),
            )
            if x is not None and not failed
        ]
        row["within_ratio"] = bool(all(x <= RATIO_LIMIT for x in ratios)) if ratios else None
        rows.append(row)
    return rows


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


_WORKER_QUEUE = None


def _init_worker(queue) -> None:
    global _WORKER_QUEUE
    _WORKER_QUEUE = queue
    limit_blas_threads(1)
    try:
        import cv2

        cv2.setNumThreads(1)
    except Exception:  # noqa: BLE001 - OpenCV threading is an optimisation only
        pass


def _job(args) -> RunResult:
    scenario, seed, options, base_config = args
    q = _WORKER_QUEUE

    def progress(n: int) -> None:
        if q is not None:
            q.put(n)

    try:
        return run_lockstep(scenario, seed, options, base_config, progress)
    except IrtrackError as exc:  # a run that cannot be made (e.g. a flight failure) fails alone
        log.error("%s seed %d: %s", scenario.name, seed, exc)
        return _empty_result(scenario, seed, f"{type(exc).__name__}: {' '.join(str(exc).split())}")


def run_eval(
    scenarios: list[Scenario],
    seeds,
    options: EvalOptions | None = None,
    base_config=None,
    workers: int = 2,
    progress: bool = True,
    config_source: str = "(defaults)",
    nav_noises=None,
) -> EvalResult:
    """All (navigation case, scenario, seed) runs, over ``workers`` processes (1 = in this process), then
    scored.  ``nav_noises``: case names to run each scenario with (default: ``options.nav_noise`` only)."""
    options = options if options is not None else EvalOptions()
    variants = [options] if not nav_noises else [dataclasses.replace(options, nav_noise=n) for n in nav_noises]
    limit_blas_threads(1)  # here and, through the environment, in the worker processes
    seeds = [int(s) for s in seeds]
    if not scenarios:
        raise ConfigError("--scenario: expected at least one scenario")
    if not seeds:
        raise ConfigError("--seeds: expected at least one seed")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"--workers: expected an integer >= 1, got {workers!r}")
    from groundsim.app.run import frame_count

    jobs = [(sc, seed, o, base_config) for o in variants for sc in scenarios for seed in seeds]
    total = 0
    for sc in scenarios:
        if options.duration_s is not None and options.duration_s > sc.duration_s + 1e-9:
            raise ConfigError(
                f"--duration: expected at most {sc.name}'s duration_s ({sc.duration_s:g} s), got {options.duration_s:g}"
            )
        d = sc.duration_s if options.duration_s is None else options.duration_s
        total += frame_count(d, sc.frame_rate_hz) * len(seeds) * len(variants)
    t0 = time.perf_counter()
    bar = None
    results: list = [None] * len(jobs)
    workers = min(workers, len(jobs))
    if workers == 1:
        global _WORKER_QUEUE
        if progress:
            bar = progress_bar(total, "frame", "eval")
        try:
            for n, j in enumerate(jobs):
                sc, seed, opts = j[0], j[1], j[2]
                if bar is not None:
                    bar.set_postfix_str(f"{sc.name} seed {seed}")
                try:
                    results[n] = run_lockstep(sc, seed, opts, base_config, bar.update if bar is not None else None)
                except IrtrackError as exc:
                    log.error("%s seed %d: %s", sc.name, seed, exc)
                    results[n] = _empty_result(sc, seed, f"{type(exc).__name__}: {' '.join(str(exc).split())}")
        finally:
            if bar is not None:
                bar.close()
    else:
        results = _run_pool(jobs, workers, total, progress)
    wall = time.perf_counter() - t0
    scores = [score_run(r) for r in results]
    return EvalResult(results, scores, summarise(scores), wall, workers, options, config_source)


def _run_pool(jobs, workers: int, total: int, progress: bool) -> list:
    bar = None
    try:
        if progress:
            bar = progress_bar(total, "frame", f"eval ({workers} workers)")
        return run_pool(_job, jobs, workers, _init_worker, None if bar is None else bar.update)
    finally:
        if bar is not None:
            bar.close()


# --------------------------------------------------------------------------- command line


DEFAULT_EVAL_SCENARIOS = ("P1", "P2", "P3")


def cmd_eval(args) -> int:
    """The ``eval`` command: run, write the report, print the table and the report's path."""
    import sys

    from groundsim.app.cli import resolve_scenario_path
    from groundsim.evaluation.report import format_closed_loop, format_table2, write_eval_report
    from groundsim.world.scenario import load_scenario

    limit_blas_threads(1)
    quiet_run_logs()  # per-track chatter would drown the progress bar
    names = [n for group in (args.scenario or [list(DEFAULT_EVAL_SCENARIOS)]) for n in group]
    scenarios = [load_scenario(resolve_scenario_path(n)) for n in names]
    if isinstance(args.seeds, bool) or args.seeds < 1:
        raise ConfigError(f"--seeds: expected an integer >= 1, got {args.seeds}")
    workers = args.workers if args.workers is not None else max(1, min(2, os.cpu_count() or 1))
    if workers < 1:
        raise ConfigError(f"--workers: expected an integer >= 1, got {workers}")
    nav_noises = list(dict.fromkeys(args.nav_noise or [DEFAULT_NAV_NOISE]))
    options = EvalOptions(
        duration_s=args.duration,
        pixel_sigma_px=args.pixel_sigma,
        batch=not args.no_batch,
        nav_noise=nav_noises[0],
        estimator=getattr(args, "estimator", None),
    )
    for n in nav_noises[1:]:
        dataclasses.replace(options, nav_noise=n)  # validates every name before anything runs
    base = load_base_config(args.onboard_config)
    source = args.onboard_config or (
        str(DEFAULT_ONBOARD_CONFIG) if DEFAULT_ONBOARD_CONFIG.is_file() else "built-in defaults"
    )
    out = make_out_dir(args.out)
    log.info(
        "eval: %d scenario(s) x %d seed(s), %d worker(s), onboard config %s",
        len(scenarios),
        args.seeds,
        workers,
        source,
    )
    result = run_eval(
        scenarios,
        range(args.seeds),
        options,
        base,
        workers=workers,
        progress=not args.no_progress,
        config_source=source,
        nav_noises=nav_noises,
    )
    files = write_eval_report(out, result)
    descriptions = {sc.name: sc.description.split(":", 1)[-1].strip() for sc in scenarios}
    print(format_table2(result.summary, descriptions))
    print()
    print(format_closed_loop(result.summary))
    failed = sum(1 for s in result.scores if "error" in s)
    print(
        f"\n{len(result.runs)} runs ({failed} failed) in {result.wall_s:.1f} s, estimator {options.estimator or 'map'}; "
        f"report: {files['report.md']}"
    )
    sys.stdout.flush()
    return 0
