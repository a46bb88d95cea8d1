"""Online use of the MAP reconstruction: a sliding window that takes one observation at a time.

Every observation gets a fresh estimate of the target's state at its own time:

- the window keeps the last ``window_s`` seconds (20 s) at most every ``min_spacing_s`` (0.06 s: every
  other frame of a 30 Hz camera), at most ``max_frames`` rows: bounded memory and cost.  Range comes
  from the observer's manoeuvre across the line of sight, so the window's *span* matters far more than
  its frame rate: on P2 under RTK navigation a 20 s window at 15 Hz was observable on 60 % of the
  frames after 5 s (median error 0.44 %) where a 10 s window at 30 Hz, same cost, was on none (median
  error 3.3 %).  A frame closer than ``min_spacing_s`` to the last kept one is not added; it gets the
  newest estimate carried to its time at constant velocity (:meth:`TrackEstimate.propagated`);
- the spline's knot grid is anchored once, so when the window slides, control points are carried
  over (old ones dropped, new ones extrapolated) and the previous solution warm-starts the next;
- each frame runs ``iterations_per_frame`` Gauss-Newton/LM iterations on the whole window with the
  current motion model (a few hundred microseconds to a millisecond for 300 frames);
- the full multi-start, evidence-based model selection of
  :class:`~onboard.estimation.map_estimator.MapEstimator` re-solves the window every quarter of the
  window's span, between ``warmup_reselect_period_s`` (1 s, while the window is young and the estimate
  changes fastest) and ``reselect_period_s`` (5 s, once the window is full): it is the expensive part
  (~0.2-0.4 s of one core), and at 1 Hz it alone cost a third of a core, twice the daemon's budget.
  It is an anytime computation (:meth:`MapEstimator.selection`) spread over the kept frames: when it is
  due, the window's rows are frozen for it, and each frame runs ``selection_work_per_frame`` residual
  evaluations of it (~10-20 ms of CPU; a frame never pays for a whole selection), then updates its own
  estimate with the current model as usual.  The frame that ends it adopts the new model and solution,
  carried from the frozen window to its own and re-solved warm (4-30 kept frames later).  A track's first
  choice is provisional, at once, on its first rows: one model (:data:`PROVISIONAL_MODEL`) from every range
  hypothesis, its estimates published unobservable; the full selection on the same rows follows, spread like
  the others (the choice, and the schedule of the later ones, as when it ran at once).  A selection under
  way is not snapshotted: a restored estimator
  starts it again.  Its result is the batch selection's on those rows, bit for bit; the periods below
  count from the newest of those rows.
  Once the window is full, a selection that confirms the previous one (same motion
  model and intensity, same verdict) doubles the period, up to ``reselect_max_period_s`` (20 s); any
  other outcome sets it back.  The data calls a selection early, after at least ``reselect_period_s``:
  when the newest frames' standardised innovations (the incremental update's residual before its
  step, ~1 per axis while the model follows the target) average more than
  ``reselect_innovation_trigger`` over ``reselect_innovation_frames`` frames (the model no longer
  explains the bearings: the target turned, or accelerated), or when a window last called
  unobservable now pins range at its newest frame as an observable one must (the observer's
  manoeuvre began).

The reported covariance is the chosen model's Laplace posterior at this time, scaled at each model
selection to the batch result's model-averaged, inflated covariance (over the solutions near the
chosen one; ``MapResult.ambiguity`` is the mass of the far ones).  ``observable`` is true only when
the last selection called its window observable (the window's median range sigma below
``observability_max_sigma_range_ratio`` of the range, its residuals through the adequacy test, an ambiguity of
at most ``max_ambiguity``) and the range sigma at this time is below ``edge_sigma_factor`` times that ratio.
An unobservable estimate keeps its position, with its range sigma raised to at least
``unobservable_range_sigma_floor`` of the range and ``unobservable_range_sigma_min_m`` (honest, not
confident).

A target that changes motion model (a racetrack: legs and turns) defeats a selection made over one model
(:mod:`onboard.estimation.consistency`): a CUSUM on the incremental updates' innovations
(``manoeuvre_cusum_threshold``) calls the window unobservable and a selection due at once when the
selected model stops explaining the bearings, and after a model held for half a window no window that
holds the change's onset is called observable (one model over it can explain the bearings at the wrong
range).  Nor is a window that no steady motion explains (every family at its stiffest intensity more than
``MapConfig.model_margin_nats`` below the best model: the target changed its motion in it); such a selection
also confirms a CUSUM firing in a younger window whose onset it holds as a change.  A selection that puts the
frames it shares with an observable selection before it at another range (``selection_consistency_nsigma``)
is called unobservable, and so is one that shares frames with either of two such selections (which of them
is wrong is unknown) until the window has slid past them.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import pickle
from collections import deque
from collections.abc import Generator, Iterable
from dataclasses import dataclass
from typing import Annotated

import numpy as np
import scipy.linalg as sla

from onboard.core.errors import InputError, wrong_sizes
from onboard.core.frames import FrameError, PinholeIntrinsics, check_unit_quat, far_off_image, rotmat_from_quat
from onboard.core.schema import NOT_A_KEY, Bool, Integer, Invalid, Number, config_dataclass
from onboard.estimation.consistency import (
    ConsistencyMonitor,
    ManoeuvreDetector,
    SelectionHistory,
    unsteady_evidence_nats,
)
from onboard.estimation.fastmath import cho_factor_lower, cho_solve_lower, qr_r
from onboard.estimation.map_estimator import (
    EstimationError,
    MapConfig,
    MapEstimator,
    MapResult,
    MotionPrior,
    NoiseModel,
    WindowProblem,
    range_floor,
)
from onboard.estimation.observations import Observations
from onboard.estimation.spline import KnotGrid
from onboard.estimation.state_estimate import StateEstimate

__all__ = [
    "SlidingConfig",
    "TrackEstimate",
    "SlidingWindowEstimator",
    "bearing_sigma_rad",
    "consistency_monitor",
    "process_cov_ned_m2",
]

#: chi-square(2 dof) at 1e-4: a newer bearing farther than this from an estimate is not fused into it
BEARING_GATE_CHI2 = 18.42
#: a full solve leaves out the rows beyond the gate of the solution it starts from only while they are at most this
#: share of the window: more means the starting solution is off (a change of motion, a selection due), not the rows
MAX_EXCLUDED_SHARE = 0.25
#: nor a run of more than this many of the newest rows: bearings that keep leaving the prediction are a change of the
#: target's motion (a stop, a turn) which the solve must follow, not outliers (0.2 s at the 15 Hz the window keeps)
MAX_EXCLUDED_EDGE_ROWS = 3
#: one residual evaluation of the window problem (with its share of the normal equations) costs about as much
#: as this many rows more: ~0.16 ms at 30-75 rows, 0.23 at 150, 0.44 at 300 (P1 RTK, 1 s knots, loaded
#: development machine), i.e. a fixed part and one proportional to the rows; the selection's share of a
#: frame is counted in full-window evaluations with it
EVALUATION_OVERHEAD_ROWS = 100
#: at most this many iterations carry a finished selection's solution to the newest window (it stops at
#: convergence, usually after 1-3)
COMMIT_ITERATIONS = 10
#: the model of a track's provisional first choice (family, intensities): a cruising target's constant velocity,
#: the middle of the q grid.  Solved at once on the track's first rows (~1/4 of a full selection's work there:
#: 5 range hypotheses under one prior instead of 11 models), so the first estimate is not delayed and no step
#: pays for a whole selection; its estimates are published unobservable, with the range floor, until the full
#: selection, started on the next kept frame and spread like any other, replaces it
PROVISIONAL_MODEL = ("cv", (1e-3,))

log = logging.getLogger(__name__)


#: a number of seconds, frames or sigmas the estimator divides by or counts with: above zero
_Positive = Annotated[float, Number(0.0, lo_open=True)]
_NonNegative = Annotated[float, Number(0.0)]


@config_dataclass
class SlidingConfig:
    """The sliding window's settings; a bad value raises :class:`~onboard.core.schema.SchemaError` naming the
    field (the daemon's ``estimator.sliding`` section, built with ``window_s`` from ``estimator.window_s``)."""

    # not a key of estimator.sliding: the daemon sets it from estimator.window_s, the one place it is configured
    window_s: _Positive = dataclasses.field(default=20.0, metadata=NOT_A_KEY)
    # the window holds at most this many kept frames: at a spacing of s seconds, max_frames * s seconds of them
    max_frames: Annotated[int, Integer(10)] = 300
    min_spacing_s: _NonNegative = 0.06
    # the trajectory spline's knot spacing online (MapConfig.knot_spacing_s, 0.5 s in batch): over the 20 s
    # window 1 s knots keep the unknowns as many as 0.5 s knots did over 10 s; on synthetic 40 s RTK flights
    # the same observable shares (70/72/86 % of the frames after 5 s, P1/P2/P3) and errors as 0.5 s, for
    # 40 % less estimator CPU (0.08-0.10 instead of 0.12-0.18 CPU s per s)
    knot_spacing_s: _Positive = 1.0
    min_frames: Annotated[int, Integer(10)] = 30
    min_span_s: _NonNegative = 1.5
    reselect_period_s: _Positive = 5.0
    warmup_reselect_period_s: _Positive = 1.0
    # full window, confirmed selections: the period doubles up to this (module docstring)
    reselect_max_period_s: _Positive = 20.0
    # mean squared standardised innovation per axis over the newest frames that calls a selection early
    reselect_innovation_trigger: _Positive = 4.0
    reselect_innovation_frames: Annotated[int, Integer(1)] = 15
    iterations_per_frame: Annotated[int, Integer(1)] = 1
    resolve_every_frames: Annotated[int, Integer(1)] = 5
    # the model selection runs as an anytime computation spread over the kept frames (module docstring):
    # each frame advances it until it has done this much work, in residual evaluations (with their
    # normal-equation solves, MapEstimator.selection) of a max_frames window, ~0.3-0.45 ms each on the
    # development machine; a younger window's evaluations are cheaper and more of them make one frame's
    # share (EVALUATION_OVERHEAD_ROWS).  No frame pays for a whole selection; 0 runs it at once
    selection_work_per_frame: Annotated[int, Integer(0)] = 30
    # a frame is observable when the last selection's window was and its own range sigma (at the window's
    # newest edge, the least constrained point: ~1.4x the window median on P2) is below this many times
    # MapConfig.observability_max_sigma_range_ratio
    edge_sigma_factor: _Positive = 2.0
    # a published estimate is demoted to unobservable while the estimate of 2 s before, carried to now, fails
    # to predict this frame's bearing within its covariance (onboard.estimation.consistency). Off by default:
    # on synthetic racetrack targets (RTK, 2-minute flights) it takes the positions beyond 3 sigma from 15.8 %
    # to 8.5 %, but on the realistic flow (bench.companion, P2, RTK) it cut the observable share after 5 s
    # from 0.44 to 0.33 with every position honest either way (docs/performance.md, "Honest over minutes")
    consistency_check: Bool = False
    # a target that changes motion model (onboard.estimation.consistency, docs/performance.md "Honest over
    # minutes"): the CUSUM threshold on the newest frames' innovations above which the window is called
    # unobservable and a selection is due at once (ManoeuvreDetector; 0: off), and how many sigmas of range
    # a selection may differ from the observable selections before it on their common frames before it is
    # called unobservable (SelectionHistory; 0: off)
    manoeuvre_cusum_threshold: _NonNegative = 10.0
    selection_consistency_nsigma: _NonNegative = 3.0
    # a new bearing whose normalised innovation against the window's prediction exceeds this (chi-square, 2 dof)
    # is not taken into the solution by its incremental step and no estimate beside it is observable (an outlier,
    # or the first frames of a change the CUSUM has yet to judge; 0: off); 1e-4 of clean bearings
    innovation_gate_chi2: _NonNegative = BEARING_GATE_CHI2

    def __post_init__(self) -> None:
        if self.reselect_max_period_s < self.reselect_period_s:
            raise Invalid(
                "reselect_max_period_s",
                f">= reselect_period_s ({self.reselect_period_s:g})",
                self.reselect_max_period_s,
            )


def process_cov_ned_m2(prior: MotionPrior | None, dt_s: float) -> np.ndarray:
    """The position covariance (3, 3) a motion model's process noise adds over ``dt_s`` seconds from a
    known state (Bar-Shalom, Li, Kirubarajan, *Estimation with Applications to Tracking and Navigation*,
    2001, sections 6.2.2-6.2.3): white-noise acceleration with PSD ``q`` (m^2/s^3) gives ``q dt^3 / 3``
    per axis, white-noise jerk with PSD ``q`` (m^2/s^5) ``q dt^5 / 20``; horizontal PSD on north and
    east, vertical on down.  Zeros for no model.  The coordinated turn's rate is carried at the turn
    the window estimated, not as noise: its uncertainty is in the velocity's covariance."""
    if prior is None or not dt_s > 0:
        return np.zeros((3, 3))
    k = dt_s**5 / 20.0 if prior.jerk else dt_s**3 / 3.0
    return np.diag([prior.q_horizontal_m2ps3 * k, prior.q_horizontal_m2ps3 * k, prior.q_vertical_m2ps3 * k])


@dataclass(frozen=True)
class TrackEstimate(StateEstimate):
    """The target's state at ``t_s`` from the window ending there (NED metres about the local origin)."""

    range_m: float
    range_sigma_ratio: float
    window_frames: int
    model: str
    #: RMS of the standardised residuals at the last model selection (~1 when the camera model and the
    #: noise model are right; NaN before the first selection)
    residual_rms_norm: float = math.nan
    #: p-value of the last selection's block-whiteness adequacy test (low: the model cannot follow the data)
    adequacy_p: float = math.nan
    #: posterior mass of far solutions at the last selection (``MapResult.ambiguity``)
    ambiguity: float = math.nan
    #: the selected motion model, whose process noise :meth:`propagated` adds for the time carried (None:
    #: none selected yet; the velocity's uncertainty alone is then carried)
    motion_prior: MotionPrior | None = None

    def propagated(self, t_s: float, p_cam_ned_m=None) -> TrackEstimate:
        """This estimate carried to ``t_s`` at constant velocity: ``p + v dt``, ``P + dt^2 V + Q(|dt|)``:
        the velocity's uncertainty and the motion model's process noise over the time carried
        (:func:`process_cov_ned_m2`), so an estimate that arrives late, or is carried over frames the
        estimator did not keep up with, is published with a covariance that knows its age.  The
        position-velocity correlation is not kept.  The estimator's own prediction is
        :meth:`SlidingWindowEstimator.predict`.

        ``p_cam_ned_m`` (the camera at ``t_s``) sets the new range and range sigma ratio; without it the
        range keeps the old line of sight's length."""
        dt = float(t_s) - self.t_s
        p = self.p_ned_m + self.v_ned_mps * dt
        P = self.cov_p_ned_m2 + dt * dt * self.cov_v_ned_m2ps2 + process_cov_ned_m2(self.motion_prior, abs(dt))
        rng, ratio = self.range_m, self.range_sigma_ratio
        if p_cam_ned_m is not None:
            los = p - np.asarray(p_cam_ned_m, dtype=float)
            rng = float(np.linalg.norm(los))
            if rng > 0:
                u = los / rng
                ratio = float(math.sqrt(max(u @ P @ u, 0.0)) / rng)
        return dataclasses.replace(
            self, t_s=float(t_s), p_ned_m=p, cov_p_ned_m2=P, range_m=rng, range_sigma_ratio=ratio
        )

    def with_bearing(
        self, p_cam_ned_m, u_ned, sigma_rad: float, cam_sigma_m: float = 0.0, gate_chi2: float = BEARING_GATE_CHI2
    ) -> TrackEstimate | None:
        """This estimate corrected by one line of sight it does not contain (a frame newer than the window
        it was solved from, e.g. an estimate propagated while the worker was busy): the Kalman update of
        the position with the measurement "the target is on the ray ``c + r u``", written linearly as the
        two cross-range offsets ``B (p - c) = 0`` (``B``: an orthonormal basis across ``u``) with noise
        ``(r sigma_rad)^2 + cam_sigma_m^2`` per axis.  The bearing fixes the cross-range position to the
        bearing's accuracy and leaves the range (the along-ray direction) to the window; the velocity
        is unchanged (its correlation with the position is not kept here).

        ``sigma_rad``: the line of sight's 1-sigma per axis (pixel noise over focal length with the
        attitude noise); None when the innovation's Mahalanobis distance^2 exceeds ``gate_chi2`` (the
        bearing and the estimate disagree: not fused)."""
        c = np.asarray(p_cam_ned_m, dtype=float).reshape(3)
        u = np.asarray(u_ned, dtype=float).reshape(3)
        u = u / np.linalg.norm(u)
        d = self.p_ned_m - c
        r = float(np.linalg.norm(d))
        if not (r > 0 and math.isfinite(r) and sigma_rad >= 0):
            return None
        # two unit vectors across u: the null space of u^T
        a = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        b1 = np.cross(u, a)
        b1 /= np.linalg.norm(b1)
        B = np.vstack([b1, np.cross(u, b1)])
        z = B @ d
        P = self.cov_p_ned_m2
        R = np.eye(2) * ((r * sigma_rad) ** 2 + cam_sigma_m**2)
        S = B @ P @ B.T + R
        try:
            cS = sla.cho_factor(S)
        except np.linalg.LinAlgError:
            return None
        if float(z @ sla.cho_solve(cS, z)) > gate_chi2:
            return None
        K = sla.cho_solve(cS, B @ P).T  # P B^T S^-1
        p = self.p_ned_m - K @ z
        IKH = np.eye(3) - K @ B
        P = IKH @ P @ IKH.T + K @ R @ K.T  # Joseph form: symmetric, positive
        los = p - c
        rng = float(np.linalg.norm(los))
        ratio = float(math.sqrt(max(los @ P @ los, 0.0)) / (rng * rng)) if rng > 0 else self.range_sigma_ratio
        return dataclasses.replace(self, p_ned_m=p, cov_p_ned_m2=0.5 * (P + P.T), range_m=rng, range_sigma_ratio=ratio)


@dataclass(frozen=True, eq=False)
class _PendingSelection:
    """A model selection under way: the newest frame's time ``t_s`` of the window it was started on, whether
    that window was full, its rows ``obs``, the running selection (:meth:`MapEstimator.selection`) and whether it
    is the track's provisional first choice (:data:`PROVISIONAL_MODEL`): then ``full_steps`` is the full selection
    on the same rows, run after it."""

    t_s: float
    full: bool
    obs: Observations
    steps: Generator[int, None, MapResult]
    full_steps: Generator[int, None, MapResult] | None = None

    @property
    def provisional(self) -> bool:
        return self.full_steps is not None


def range_floored(est: TrackEstimate, p_cam_ned_m, map_config: MapConfig) -> TrackEstimate:
    """An unobservable ``est`` with ``map_config``'s range floor (:func:`~onboard.estimation.map_estimator.range_floor`)
    along its line of sight from ``p_cam_ned_m``: honest, not confident, wherever it was carried to or whatever
    bearing it was corrected by since it was solved (a bearing update across a floor laid along an older line of
    sight shrinks the range sigma as if a second range had been measured).  An observable one as it is."""
    if est.observable:
        return est
    los = est.p_ned_m - np.asarray(p_cam_ned_m, dtype=float)
    rng = max(float(np.linalg.norm(los)), 1e-9)
    P, ratio = floored_covariance(map_config, est.cov_p_ned_m2, los / rng, est.range_sigma_ratio, rng)
    return dataclasses.replace(est, cov_p_ned_m2=P, range_sigma_ratio=ratio)


def floored_covariance(
    map_config: MapConfig, P: np.ndarray, u: np.ndarray, ratio: float, rng: float
) -> tuple[np.ndarray, float]:
    """An unobservable estimate's covariance ``P`` and range sigma ratio ``ratio`` at range ``rng`` with the range
    floor applied along the unit line of sight ``u``."""
    add, sig_r = range_floor(map_config, u[None], np.array([ratio * rng]), np.array([rng]))
    return P + add[0], float(sig_r[0]) / max(rng, 1e-9)


def bearing_sigma_rad(noise: NoiseModel, intrinsics: PinholeIntrinsics) -> float:
    """One frame's line-of-sight 1-sigma per axis under ``noise``: the pixel noise over the focal length with
    the attitude's white noise and bias (the bias is kept: conservative)."""
    f = math.sqrt(intrinsics.fx_px * intrinsics.fy_px)
    return math.sqrt(
        (noise.pixel_sigma_px / f) ** 2 + noise.attitude_white_sigma_rad**2 + noise.attitude_bias_sigma_rad**2
    )


def consistency_monitor(
    noise: NoiseModel, intrinsics: PinholeIntrinsics, model_hold_s: float = 0.0
) -> ConsistencyMonitor:
    """The :class:`ConsistencyMonitor` of estimates solved under ``noise``: the bearing sigma without the attitude's
    constant bias, which is common to the carried estimate and the new bearing."""
    no_bias = dataclasses.replace(noise, attitude_bias_sigma_rad=0.0)
    return ConsistencyMonitor(bearing_sigma_rad(no_bias, intrinsics), model_hold_s=model_hold_s)


def line_of_sight_unit_ned(uv_px, intrinsics: PinholeIntrinsics, q_ned_from_cam) -> np.ndarray:
    """The unit line of sight in NED through pixel ``uv_px`` (lens distortion removed)."""
    return rotmat_from_quat(np.asarray(q_ned_from_cam, dtype=float)) @ intrinsics.bearing_cam_from_pixel(uv_px)


class SlidingWindowEstimator:
    """Feed observations with :meth:`add`; read the latest :class:`TrackEstimate`.

    A worker that runs the estimator elsewhere (a child process) keeps it through :meth:`snapshot`,
    :meth:`restore` and :meth:`rebuild`, and reads the noise model it was built with (:attr:`noise`).
    """

    #: left out of a snapshot: the MAP solver (its config and caches, ~11 MB pickled), which the estimator
    #: being restored has built for itself, and a model selection under way (a running generator cannot be
    #: pickled; the restored estimator starts it again, as it is still due)
    NOT_SNAPSHOTTED = ("map", "_pending")

    def __init__(
        self, config: SlidingConfig | None = None, noise: NoiseModel | None = None, map_config: MapConfig | None = None
    ):
        self.config = config or SlidingConfig()
        self.map = MapEstimator(map_config or self.default_map_config(self.config), noise or NoiseModel())
        self.reset()

    @staticmethod
    def default_map_config(config: SlidingConfig) -> MapConfig:
        """The :class:`MapConfig` an estimator of ``config`` solves with when given none (a worker that carries its
        estimates outside it applies this config's range floor too: :func:`range_floored`)."""
        return MapConfig(knot_spacing_s=config.knot_spacing_s)

    def reset(self) -> None:
        c = self.config
        self._t: deque = deque(maxlen=c.max_frames)
        self._uv: deque = deque(maxlen=c.max_frames)
        self._k: deque = deque(maxlen=c.max_frames)  # (fx, fy, cx, cy)
        self._p: deque = deque(maxlen=c.max_frames)
        self._q: deque = deque(maxlen=c.max_frames)
        self._R: deque = deque(maxlen=c.max_frames)
        self._grid: KnotGrid | None = None
        self._theta: np.ndarray | None = None
        self._first = 0
        self._prior: MotionPrior | None = None
        self._model = "none"
        self._last_select_t = -math.inf
        self._period_scale = 1.0  # doubles while full-window selections confirm each other (module docstring)
        self._last_choice: tuple | None = None  # (motion prior, observable) of the last selection
        self._innovations: deque = deque(maxlen=c.reselect_innovation_frames)  # mean r^2 per axis
        self._window_observable = False
        self._edge_pinned = False  # the last estimate's own range sigma passed the per-frame test
        self._edge_pinned_at_selection = False  # ... and at the last selection
        self._diag = (math.nan, math.nan, math.nan)  # residual_rms_norm, adequacy_p, ambiguity of the last selection
        self._last_est: TrackEstimate | None = None
        self._consistency: ConsistencyMonitor | None = None  # made at the first row (it needs the intrinsics)
        self._pending: _PendingSelection | None = None  # the model selection under way (module docstring)
        # a change of the target's motion model (SlidingConfig.manoeuvre_cusum_threshold,
        # selection_consistency_nsigma): fired since the last selection ended
        self._manoeuvre = (
            ManoeuvreDetector(threshold=c.manoeuvre_cusum_threshold) if c.manoeuvre_cusum_threshold > 0 else None
        )
        self._manoeuvre_fired = False
        self._manoeuvre_t_s = -math.inf
        self._change_t_s = -math.inf  # the onset of the last change of motion model the innovations showed
        self._provisional = False  # the model in use is the track's provisional first choice (PROVISIONAL_MODEL)
        self._young_onset_t_s = -math.inf  # the onset of a firing in a young window, a change once confirmed
        self._selections = (
            SelectionHistory(c.selection_consistency_nsigma) if c.selection_consistency_nsigma > 0 else None
        )
        self._prob: WindowProblem | None = None
        self._H: np.ndarray | None = None
        self._since_full = 0
        self._excluded_t_s: np.ndarray = np.empty(0)  # the times of the rows the last full solve left out
        # per-frame covariances come from the chosen model's information, inflated like the batch
        # result's; model doubt is the 1 Hz selection's job (its observability verdict gates ours)
        self._cov_scale = self.map.config.sigma_inflation**2
        self.stats = {
            "selections": 0,
            "provisional": 0,
            "updates": 0,
            "incremental": 0,
            "failures": 0,
            "skipped": 0,
            "manoeuvres": 0,
            "inconsistent_selections": 0,
            "unsteady_selections": 0,
            "gated": 0,
            "excluded": 0,
        }

    @property
    def noise(self) -> NoiseModel:
        """The noise model the window is solved with."""
        return self.map.noise

    # ------------------------------------------------------------------ state
    def snapshot(self) -> bytes:
        """This estimator's state, all but the solver, as bytes (~0.9 MB for a full window: the rows, the
        spline solution, the model, the last linearisation); :meth:`restore` puts it back."""
        state = {k: v for k, v in vars(self).items() if k not in self.NOT_SNAPSHOTTED}
        return pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL)

    def restore(self, snapshot: bytes) -> None:
        """Put back the state of :meth:`snapshot` (of an estimator built with the same configuration).
        Raises ValueError for bytes that are not such a snapshot.  Only for snapshots this program made:
        they are unpickled."""
        state = pickle.loads(snapshot)
        if not isinstance(state, dict) or set(state) & set(self.NOT_SNAPSHOTTED):
            raise ValueError("not an estimator snapshot")
        vars(self).update(state)
        self._pending = None

    def rebuild(self, rows: Iterable[tuple]) -> TrackEstimate | None:
        """Replay ``rows`` (:meth:`add`'s arguments, oldest first) into this estimator, reset first, with one
        model selection, on the newest row, instead of one per second of replayed data.

        The earlier rows are only stored (the window trims itself as in normal running): ``min_frames`` is
        out of reach while they go in; rows :meth:`add` refuses are skipped.  The newest row, under the
        real configuration, solves the whole window cold.  Returns the estimate at the newest row (None
        without rows or before the window can be solved); raises InputError when the newest row is refused.
        """
        rows = list(rows)
        self.reset()
        if not rows:
            return None
        config = self.config
        self.config = dataclasses.replace(config, min_frames=1 << 30)
        try:
            for args in rows[:-1]:
                try:
                    self.add(*args)
                except InputError:
                    pass
        finally:
            self.config = config
        # the newest row's selection runs at once: the caller asked for the estimate there
        self.config = dataclasses.replace(config, selection_work_per_frame=0)
        try:
            return self.add(*rows[-1])
        finally:
            self.config = config

    # ------------------------------------------------------------------ input
    def add(
        self, t_s: float, uv_px, intrinsics: PinholeIntrinsics, p_cam_ned_m, q_ned_from_cam
    ) -> TrackEstimate | None:
        """Add one observation; returns the estimate at ``t_s`` (None until the window can be solved).

        Raises InputError for a non-increasing time, non-finite values or a pixel more than an image's width or
        height outside the image (the row is not added).
        """
        t = float(t_s)
        try:
            uv = np.asarray(uv_px, dtype=float).reshape(2)
            p = np.asarray(p_cam_ned_m, dtype=float).reshape(3)
            q = np.asarray(q_ned_from_cam, dtype=float).reshape(4)
        except ValueError:  # a wrong size (numpy's reshape error names no argument): the refusal names them
            wrong = wrong_sizes(
                ("uv_px", uv_px, 2), ("p_cam_ned_m", p_cam_ned_m, 3), ("q_ned_from_cam", q_ned_from_cam, 4)
            )
            raise InputError(f"SlidingWindowEstimator.add: {wrong or 'an argument is not numbers'}") from None
        if not (math.isfinite(t) and np.all(np.isfinite(uv)) and np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            bad = [
                name
                for name, ok in (
                    ("t_s", math.isfinite(t)),
                    ("uv_px", np.all(np.isfinite(uv))),
                    ("p_cam_ned_m", np.all(np.isfinite(p))),
                    ("q_ned_from_cam", np.all(np.isfinite(q))),
                )
                if not ok
            ]
            raise InputError(f"SlidingWindowEstimator.add: {', '.join(bad)} not finite")
        w_px, h_px = intrinsics.width_px, intrinsics.height_px
        if far_off_image(uv[0], w_px) or far_off_image(uv[1], h_px):
            # no camera sees there: a corrupt measurement, which one incremental step would take into the window's
            # solution while the estimate's covariance still says the window's few centimetres
            raise InputError(
                f"SlidingWindowEstimator.add: pixel ({uv[0]:g}, {uv[1]:g}) is far outside the {w_px} x {h_px} image"
            )
        try:
            q = check_unit_quat(q, "SlidingWindowEstimator.add: q_ned_from_cam")
        except FrameError as exc:
            raise InputError(str(exc)) from None
        if self._t and t <= self._t[-1]:
            raise InputError(f"SlidingWindowEstimator.add: t_s {t!r} is not after the previous row's {self._t[-1]!r}")
        if self._t and t - self._t[-1] < self.config.min_spacing_s:
            # not kept (module docstring): the newest estimate, at most min_spacing_s old, carried to this
            # frame's time at constant velocity and seen from its camera (millimetres from the spline's own
            # value at that time, for a tenth of its cost: the spline's covariance there needs the window's
            # information matrix solved again)
            self.stats["skipped"] += 1
            if self._last_est is not None:
                return self.carry(self._last_est, t, p)
            return self.predict(t, p)
        if intrinsics.has_distortion:
            xy = intrinsics.normalized_from_pixel(uv)
            uv = np.asarray((intrinsics.cx_px + intrinsics.fx_px * xy[0], intrinsics.cy_px + intrinsics.fy_px * xy[1]))
        self._t.append(t)
        self._uv.append(uv)
        self._k.append((intrinsics.fx_px, intrinsics.fy_px, intrinsics.cx_px, intrinsics.cy_px))
        self._p.append(p)
        self._q.append(q)
        self._R.append(rotmat_from_quat(q))
        while self._t and self._t[0] < t - self.config.window_s:
            for d in (self._t, self._uv, self._k, self._p, self._q, self._R):
                d.popleft()
        if self._grid is None:
            self._grid = KnotGrid(t, self.map.config.knot_spacing_s)
        if len(self._t) < self.config.min_frames or t - self._t[0] < self.config.min_span_s:
            return None
        for attempt in range(2):
            try:
                est = self._update(t)
                if self.config.consistency_check and est is not None:
                    est = self._checked(est, uv_px, intrinsics, p, q)
                self._last_est = est
                return self._last_est
            except (EstimationError, np.linalg.LinAlgError, FloatingPointError) as exc:
                # a warm update that went wrong (the target behind the camera for the carried-over
                # solution, a singular step): start this frame over from a cold model selection
                self.stats["failures"] += 1
                log.debug("sliding window update failed (attempt %d): %s", attempt + 1, exc)
                self._theta = None
        return None

    def _observations(self) -> Observations:
        k = np.asarray(self._k)
        return Observations.from_checked_rows(
            np.fromiter(self._t, float, len(self._t)),
            np.asarray(self._uv),
            k[:, 0],
            k[:, 1],
            k[:, 2],
            k[:, 3],
            np.asarray(self._p),
            np.asarray(self._q),
            np.asarray(self._R),
        )

    # ------------------------------------------------------------------ solve
    def _update(self, t: float) -> TrackEstimate | None:
        c = self.config
        period = min(c.reselect_period_s, max(c.warmup_reselect_period_s, (t - self._t[0]) / 4.0))
        # full: it spans the window, or holds all the rows it may (a window_s longer than max_frames kept frames
        # span would otherwise never count as full, and its re-selection period never grow)
        full = t - self._t[0] >= 0.95 * c.window_s or len(self._t) >= c.max_frames
        if full:
            period = min(period * self._period_scale, c.reselect_max_period_s)
        inn = self._innovations
        since = t - self._last_select_t
        due = (
            since >= period
            or self._manoeuvre_fired
            or (
                since >= c.reselect_period_s
                and (
                    (len(inn) == inn.maxlen and sum(inn) / len(inn) > c.reselect_innovation_trigger)
                    or (not self._window_observable and self._edge_pinned and not self._edge_pinned_at_selection)
                )
            )
        )
        if self._pending is None and (self._theta is None or self._prior is None or due):
            self._start_selection(t, full)
        pending = self._pending
        if pending is not None:
            res = self._advance_selection()
            if res is not None:
                return self._commit(res, pending, t)
            if self._theta is None or self._prior is None:
                # no solution to update until the selection ends: the newest estimate carried, if any
                return None if self._last_est is None else self.carry(self._last_est, t, self._p[-1])
        if (
            self._since_full + 1 < self.config.resolve_every_frames
            and self._prob is not None
            and t < self._span_end(self._prob)
        ):
            return self._incremental(t)
        return self._resolve(t)

    def _start_selection(self, t: float, full: bool) -> None:
        """Begin a model selection on the window as it is now (its rows are frozen for the selection)."""
        obs = self._observations()
        if self._excluded_t_s.size and not self._manoeuvre_fired:
            # the rows the last full solve found beyond the gate are left out of the selection too: an outlier
            # among them made the selection's fit inadequate, and the window unobservable for as long as it stayed
            # in it.  Not after a manoeuvre: the rows beyond the gate are then the new motion the selection is for
            obs = obs.select(np.flatnonzero(~np.isin(obs.t_s, self._excluded_t_s)))
        warm = None
        if self._theta is not None and self._prob is not None and self._prior is not None:
            warm = self._shift(self.map.problem(obs, self._prior, self._grid))
        # a window the last selection called observable is warm-started alone (plus one fresh range
        # hypothesis); otherwise every range hypothesis too (a warm start alone kept a wrong basin)
        steps = self.map.selection(obs, grid=self._grid, warm=warm, trust_warm=self._window_observable)
        if self._prior is None and self.config.selection_work_per_frame > 0:  # the track's first: provisional
            provisional = self.map.selection(obs, grid=self._grid, models=PROVISIONAL_MODEL)
            self._pending = _PendingSelection(t, full, obs, provisional, full_steps=steps)
            return
        self._pending = _PendingSelection(t, full, obs, steps)

    def _advance_selection(self) -> MapResult | None:
        """Run the selection under way for this frame's share of work; its MapResult when it ended, else None."""
        pending = self._pending
        if pending is None:
            return None
        c = self.config
        if self._prior is None:
            # the track's first choice, on its first min_frames rows, runs at once: nothing is published
            # before it ends, and spread it would delay the first estimate (and what waits on it, guidance)
            # by a few hundred milliseconds.  It is the provisional one (PROVISIONAL_MODEL, 5-35 ms of CPU on
            # the loaded development machine), or with selection_work_per_frame 0 the full selection as before
            budget = 0.0
        else:  # in evaluations of this window: a younger, smaller window's are cheaper (module-level cost model)
            budget = (
                c.selection_work_per_frame
                * (EVALUATION_OVERHEAD_ROWS + c.max_frames)
                / (EVALUATION_OVERHEAD_ROWS + len(pending.obs))
            )
        work = 0
        try:
            while budget <= 0 or work < budget:
                work += next(pending.steps)
        except StopIteration as done:
            self._pending = None
            return done.value
        except BaseException:
            self._pending = None
            raise
        return None

    def _commit(self, res: MapResult, pending: _PendingSelection, t: float) -> TrackEstimate:
        """Adopt a finished selection's model and solution, and give the estimate at ``t`` (the newest frame,
        at or after the newest frame of the window the selection was made on)."""
        pending_t, full, obs = pending.t_s, pending.full, pending.obs
        prob, theta = res.problem, res.theta
        self._prior = res.prior
        self._model = res.model or "map"
        # the window's verdict (batch: median range sigma over the window, ambiguity, adequacy) gates the
        # frames until the next selection; each frame's own range sigma, at the window's newest edge
        # where it is largest, must also stay below edge_sigma_factor x the threshold.  A provisional choice
        # compared no models (no ambiguity, no model doubt): never observable
        self._window_observable = bool(res.observable) and not pending.provisional
        if self._selections is not None and not self._selections.check(
            res.t_s, res.p_ned_m, res.cov_p_model_ned_m2, obs.p_cam_ned_m, self._window_observable
        ):
            # it and an observable selection before it put their common frames at different ranges: a change
            # of motion model neither follows (onboard.estimation.consistency.SelectionHistory)
            self._window_observable = False
            self.stats["inconsistent_selections"] += 1
            log.debug(
                "selection at %.2f s: range %.1f sigma from an earlier one's: unobservable",
                pending_t,
                self._selections.last_max_nsigma,
            )
        if self._manoeuvre is not None:
            unsteady_nats = unsteady_evidence_nats(res.grid_log_evidence)
            if unsteady_nats > self.map.config.model_margin_nats:
                # no steady motion (a family at its stiffest intensity) explains the window as well as process
                # noise does: the target changed its motion in it, and one model over all of it can explain the
                # bearings at the wrong range (onboard.estimation.consistency.unsteady_evidence_nats)
                self._window_observable = False
                self.stats["unsteady_selections"] += 1
                if obs.t_s[0] <= self._young_onset_t_s:
                    self._change_t_s = max(self._change_t_s, self._young_onset_t_s)  # the young firing was a change
                log.debug("selection at %.2f s: no steady motion (%.1f nats): unobservable", pending_t, unsteady_nats)
            if obs.t_s[0] <= self._change_t_s:
                # the window holds a change of the target's motion model the innovations showed: one motion model
                # over all of it can explain the bearings at the wrong range (the selection cannot tell), so
                # no verdict from it until the window has slid past the change
                self._window_observable = False
            if pending_t >= self._manoeuvre_t_s:
                self._manoeuvre_fired = False  # else the manoeuvre began after these rows: the next selection is due
            self._manoeuvre.reset()
        self._diag = (res.residual_rms_norm, res.adequacy_p, res.ambiguity)
        self._edge_pinned_at_selection = self._edge_pinned
        self._innovations.clear()
        self._provisional = pending.provisional
        if pending.full_steps is not None:  # provisional: the full selection on its rows runs from the next frame
            self._pending = _PendingSelection(pending_t, full, obs, pending.full_steps)
            self._last_select_t = -math.inf  # (due at once for an estimator restored before it ends)
            self.stats["provisional"] += 1
        else:
            self._last_select_t = pending_t
            self.stats["selections"] += 1
            choice = (self._prior, self._window_observable)
            confirmed = full and choice == self._last_choice
            self._period_scale = 2.0 * self._period_scale if confirmed else 1.0
            self._last_choice = choice
        # the problem object served several starts: re-linearise at the chosen solution
        prob.set_measurement_weights(np.linalg.norm(prob.positions(theta) - obs.p_cam_ned_m, axis=1))
        _, J, _ = prob.evaluate(theta)
        prob.last_jacobian = J
        # per-frame covariances come from this model's information; scale them so that at the selection's
        # newest frame they equal the batch result's model-averaged, inflated covariance
        H = prob.normal_matrix()  # J^T J from the Jacobian's structure (WindowProblem.normal_matrix)
        own = self._estimate(prob, theta, pending_t, H, p_cam_ned_m=obs.p_cam_ned_m[-1], scale=1.0)
        # the batch covariance before the unobservable range floor (the floor is applied per frame)
        P_last = res.cov_p_model_ned_m2[-1]
        self._cov_scale = max(
            self.map.config.sigma_inflation**2, float(np.trace(P_last) / max(np.trace(own.cov_p_ned_m2), 1e-30))
        )
        if pending_t == t:  # selected on this very window
            self._H = H
            self._theta, self._first, self._prob, self._since_full = theta, prob.first, prob, 0
            return self._estimate(prob, theta, t, self._H)
        # selected on the window of a few frames ago: carried over to this one and solved there to convergence
        # (the rows added since can move a young window's solution more than one iteration's worth)
        self._theta, self._first = theta, prob.first
        return self._resolve(t, COMMIT_ITERATIONS)

    def _resolve(self, t: float, iterations: int | None = None) -> TrackEstimate:
        """``iterations`` (default ``iterations_per_frame``) iterations on the whole window, warm-started from the
        last solution."""
        if self._prior is None:
            raise EstimationError("no motion model selected yet")
        obs = self._observations()
        prob = self.map.problem(obs, self._prior, self._grid)
        theta = self._shift(prob)
        prob.set_measurement_weights(np.linalg.norm(prob.positions(theta) - obs.p_cam_ned_m, axis=1))
        newest_out = self._exclude_outliers(prob, theta)
        sol = prob.solve(theta, max_iterations=iterations or self.config.iterations_per_frame, want_factor=False)
        theta = sol.theta
        if not math.isfinite(sol.cost) or prob.last_jacobian is None:
            raise EstimationError("warm-started window solution is invalid (target behind the camera)")
        self.stats["updates"] += 1
        self._H = prob.normal_matrix()  # at theta: the solve's last linearisation
        self._theta, self._first, self._prob, self._since_full = theta, prob.first, prob, 0
        return self._estimate(prob, theta, t, self._H, demote=newest_out)

    def _exclude_outliers(self, prob: WindowProblem, theta: np.ndarray) -> bool:
        """Leave out of this full solve the bearings beyond the innovation gate of the solution it starts from (the
        last one, carried to this window): the rows added since the last solve are tested against its prediction,
        as the incremental step tests each, and a row the gate left out before is left out again for as long as
        the solution does not come to it.  Without this a full solve weighed an outlier the incremental step had
        gated -- or one that arrived on a full solve's own frame, never tested -- and at the window's newest edge,
        where the spline bends freely, took it in: the estimates after it confidently off.  Only a few rows are
        ever left out: when more than :data:`MAX_EXCLUDED_SHARE` of the window fail the gate the solution started
        from is what is wrong (a selection is then due), and every row is kept.  True when the newest row is left
        out (its estimate, a prediction beside it, is then not called observable, as a gated step's)."""
        self._excluded_t_s = np.empty(0)
        gate = self.config.innovation_gate_chi2
        if gate <= 0 or self._manoeuvre_fired:
            return False
        chi2, valid = prob.measurement_chi2(theta)
        out = chi2 > gate
        edge_run = out.size - (int(np.flatnonzero(~out)[-1]) + 1 if not out.all() else 0)
        if edge_run > MAX_EXCLUDED_EDGE_ROWS:  # the newest bearings all beyond the gate: the motion changed, keep them
            out[out.size - edge_run :] = False
        n = int(out.sum())
        if not valid or n == 0 or n > MAX_EXCLUDED_SHARE * out.size:
            return False
        prob.exclude_measurements(out)
        self._excluded_t_s = prob.obs.t_s[out]
        self.stats["excluded"] += n
        return bool(out[-1])

    def _knots(self) -> KnotGrid:
        """The knot grid, anchored by the first observation (EstimationError before it)."""
        if self._grid is None:
            raise EstimationError("no observation yet: no knot grid")
        return self._grid

    def _span_end(self, prob: WindowProblem) -> float:
        grid = self._knots()
        return grid.t_origin_s + (prob.first + prob.count - 3) * grid.spacing_s

    def _incremental(self, t: float) -> TrackEstimate:
        """One Gauss-Newton step adding only the newest observation to the last full solve's
        information (a rank-2 update); the next full iteration rebuilds the window exactly."""
        prob, theta, H_window = self._prob, self._theta, self._H
        if prob is None or theta is None or H_window is None:
            raise EstimationError("no window solution to update")
        k = self._k[-1]
        xy = ((self._uv[-1][0] - k[2]) / k[0], (self._uv[-1][1] - k[3]) / k[1])
        r, Jr, ok = prob.measurement_rows(theta, t, xy, (k[0], k[1]), self._p[-1], self._R[-1])
        if not ok:
            raise EstimationError("new observation is behind the camera for the current solution")
        self._innovations.append(0.5 * float(r @ r))
        if self._manoeuvre is not None and self._manoeuvre.add(self._innovations[-1], t) and not self._manoeuvre_fired:
            # the selected model no longer explains the bearings: unobservable until a selection, due now, ends
            # (onboard.estimation.consistency.ManoeuvreDetector)
            self._manoeuvre_fired = True
            self._manoeuvre_t_s = t
            self._window_observable = False
            log.debug("manoeuvre at %.2f s (onset %.2f s): unobservable, selection due", t, self._manoeuvre.onset_t_s)
            if self._manoeuvre.onset_t_s - self._t[0] >= 0.5 * self.config.window_s:
                # a change after a model held for half a window at least.  Half, not a whole window: a racetrack's
                # changes in the track's first 20 s mislead as much; steady circling targets pay for it in
                # observable positions (docs/performance.md, "Honest over minutes")
                self._change_t_s = self._manoeuvre.onset_t_s
            elif not self._provisional:
                # in a younger window the model that no longer explains the bearings may only have been chosen on
                # too little data (P1 and P2 fire so in their first 10 s, at no change): a change once a selection
                # over the onset finds no steady motion explaining its window (_commit); the provisional choice
                # compared no models, its misfit says nothing
                self._young_onset_t_s = self._manoeuvre.onset_t_s
            self.stats["manoeuvres"] += 1
        H = H_window + Jr.T @ Jr
        d = np.sqrt(np.diag(H))
        d[d == 0] = 1.0
        ch, _ = cho_factor_lower(H / np.outer(d, d))
        g = Jr.T @ r
        step = cho_solve_lower(ch, g / d) / d
        # the new bearing's normalised innovation, r' (I + J H_window^-1 J')^-1 r = r'r - g' H^-1 g (the matrix
        # inversion lemma, from the factor the step needs anyway)
        gate = self.config.innovation_gate_chi2
        if gate > 0 and float(r @ r - g @ step) > gate:
            # farther from the window's prediction than its noise and the window's own uncertainty allow: an outlier,
            # which one step would pull the newest estimate towards while its covariance still says the window's
            # few centimetres, or the first frames of a change of motion, which the detector above judges.  Not
            # taken into the solution by this step (the next full solve weighs it among the window's rows), and no
            # estimate made beside it is called observable
            return self._gated(prob, theta, t, H_window)
        new_theta = theta - step
        est = self._estimate(prob, new_theta, t, H, chol=(ch, d))
        bearing_ned = self._R[-1] @ np.array((xy[0], xy[1], 1.0))
        if est.range_m < self.map.config.min_range_m or float((est.p_ned_m - self._p[-1]) @ bearing_ned) <= 0.0:
            # the step collapsed the estimate onto the camera or through it, which no mode of the selection may do
            # (min_range_m): kept out of the solution as a gated bearing is, until the next full solve
            return self._gated(prob, theta, t, H_window)
        self._theta, self._H = new_theta, H
        self._since_full += 1
        self.stats["incremental"] += 1
        return est

    def _gated(self, prob: WindowProblem, theta: np.ndarray, t: float, H_window: np.ndarray) -> TrackEstimate:
        """An incremental step not taken: the solution stays as it was, counted, and the frame's estimate from it is
        not observable."""
        self.stats["gated"] += 1
        self._since_full += 1
        return self._estimate(prob, theta, t, H_window, demote=True)

    def _shift(self, prob: WindowProblem) -> np.ndarray:
        """Carry the previous solution to this window's control span; extrapolate new controls."""
        old = self._theta
        if old is None:
            raise EstimationError("no previous solution to carry over")
        old_nc = old.size - (prob.n_params - prob.nc)
        c_old = old[:old_nc].reshape(-1, 3)
        c = np.empty((prob.count, 3))
        off = prob.first - self._first
        for k in range(prob.count):
            j = k + off
            if 0 <= j < c_old.shape[0]:
                c[k] = c_old[j]
            elif j >= c_old.shape[0]:
                c[k] = 2 * c[k - 1] - c[k - 2] if k >= 2 else c_old[-1]
            else:
                c[k] = c_old[0]
        theta = np.empty(prob.n_params)
        theta[: prob.nc] = c.reshape(-1)
        theta[prob.nc :] = old[old_nc:]
        return theta

    def _estimate(
        self,
        prob: WindowProblem,
        theta: np.ndarray,
        t: float,
        H: np.ndarray,
        p_cam_ned_m=None,
        chol=None,
        scale: float | None = None,
        demote: bool = False,
    ) -> TrackEstimate:
        """State and covariance at ``t`` from the information matrix H of the window's parameters (``demote``: not
        observable whatever the window's verdict)."""
        rows = self._knots().basis(np.array([t]), prob.first, prob.count)
        idx = rows.index[0]
        cols = (3 * idx[:, None] + np.arange(3)).reshape(-1)  # the 12 control coordinates that matter
        if chol is None:
            d = np.sqrt(np.diag(H))
            d[d == 0] = 1.0
        else:
            d = chol[1]
        E = np.zeros((prob.n_params, cols.size))
        E[cols, np.arange(cols.size)] = 1.0 / d[cols]
        try:
            ch = chol[0] if chol is not None else cho_factor_lower(H / np.outer(d, d))[0]
            X = cho_solve_lower(ch, E)
        except np.linalg.LinAlgError:
            J = prob.last_jacobian
            X = cho_solve_lower(qr_r(J / d).T, E)
        S = (X[cols] / d[cols][:, None]).reshape(4, 3, 4, 3)  # covariance of the 4 controls
        w0, w1 = rows.w0[0], rows.w1[0]
        k = self._cov_scale if scale is None else scale
        P = k * np.einsum("m,l,milj->ij", w0, w0, S)
        V = k * np.einsum("m,l,milj->ij", w1, w1, S)
        c = theta[: prob.nc].reshape(prob.count, 3)[idx]
        p = w0 @ c
        v = w1 @ c
        los = p - np.asarray(self._p[-1] if p_cam_ned_m is None else p_cam_ned_m, dtype=float)
        rng = float(np.linalg.norm(los))
        u = los / max(rng, 1e-9)
        ratio = float(math.sqrt(max(u @ P @ u, 0.0)) / max(rng, 1e-9))
        neg = bool(np.any(np.diag(P) <= 0))
        cfg = self.map.config
        self._edge_pinned = bool(
            not neg and ratio < self.config.edge_sigma_factor * cfg.observability_max_sigma_range_ratio
        )
        observable = bool(self._window_observable and self._edge_pinned and not demote)
        if not observable:  # honest, not confident (module docstring)
            P, ratio = floored_covariance(cfg, P, u, ratio, rng)
        return TrackEstimate(
            t, p, v, P, V, observable, rng, ratio, len(self._t), self._model, *self._diag, motion_prior=self._prior
        )

    def _checked(self, est: TrackEstimate, uv, intrinsics: PinholeIntrinsics, p, q) -> TrackEstimate:
        """``est`` through the consistency monitor (``SlidingConfig.consistency_check``): demoted, with the
        range floor, while an older estimate carried to now misses this bearing."""
        if self._consistency is None:
            self._consistency = consistency_monitor(self.map.noise, intrinsics)
        los = line_of_sight_unit_ned(uv, intrinsics, q)
        return self._consistency.check(est, p, los, lambda e: self.carry(e, e.t_s, p))

    def carry(self, est: TrackEstimate, t_s: float, p_cam_ned_m) -> TrackEstimate:
        """``est`` propagated to ``t_s`` and seen from ``p_cam_ned_m``; an unobservable one keeps its range
        floor along the new line of sight (honest, not confident: module docstring).  What a frame the
        window does not keep gets (:meth:`add`); the daemon's process worker computes it in the parent
        for such frames, from the worker's answer to the newest kept one (the same numbers, no round trip)."""
        return range_floored(est.propagated(t_s, p_cam_ned_m), p_cam_ned_m, self.map.config)

    def predict(self, t_s: float, p_cam_ned_m=None) -> TrackEstimate | None:
        """The current solution evaluated at ``t_s`` (no new measurement), for coasting frames.

        ``p_cam_ned_m`` (the camera at ``t_s``) sets the range; default: the last observation's camera.
        None outside the spline's span (no extrapolation beyond the last knot interval)."""
        if self._theta is None or self._prior is None or self._H is None or not self._t:
            return None
        t = float(t_s)
        if self._prob is None or t < self._t[0] or t >= self._span_end(self._prob):
            return None
        return self._estimate(self._prob, self._theta, t, self._H, p_cam_ned_m)
