"""The camera clock's offset against the autopilot's, estimated online from the target's line of sight.

Model.  A frame stamped ``t`` (boot clock) but captured at ``t - dt`` (``dt > 0``: the stamp is late, as an
unmeasured USB/CSI buffer or encoder latency makes it) is given the pose at ``t``: the attitude
``R = R_ned_from_cam`` and the camera position ``p_c``.  With ``dR/dt = [w]x R`` (``w_ned`` the camera's angular
rate in NED), ``b`` the target's bearing in the camera frame and ``u = R b``, the target point that pose puts at
range ``rho`` is, to first order in ``dt``::

    p_c(t) + rho u(t) = P(t - dt) + dt * (v_c + rho * (w_ned x u))

``P`` the target's true position, ``v_c`` the camera's velocity.  Over a block of frames (``block_s``, 3 s)
the target moves as a polynomial of degree ``poly_degree`` (2: constant acceleration) in time, ``P(t - dt)``
included, while the regressor ``x = v_c + rho (w x u)`` carries what the attitude does that the target's
motion cannot: a gimbal's pointing corrections, the airframe's attitude loop, turbulence.  Per block the
rows are the two components across the line of sight in radians (divided by ``rho``) and one along it that
only holds the target's mean range near ``rho`` (sigma ``range_sigma_frac`` of it, its linear change over the
block left free: without it the fit's range is free, and a target riding along with the camera explains a
short block about as well as the true one; held constant, a range that moved by 10 m in a block biased a
noise-free record by 5 to 15 ms); ``dt`` enters the rows across only.  Projecting the rows
``y = p_c + rho u`` and the regressor off the polynomial's and the range's columns
(Frisch-Waugh-Lovell) leaves the block's sums; the blocks of the last ``window_s`` (60 s) pool into::

    dt_hat = sum(r_z . r_y) / sum(r_z . r_x),   sigma_dt^2 = s^2 sum(r_z . r_z) / sum(r_z . r_x)^2

an instrumental-variable estimate: ``w_ned`` is the rotation between the reported attitudes ``rate_span_s``
(0.2 s) apart around the frame, ``rotvec(R(t+h) R(t-h)^T) / 2h``, and the attitude's white noise
differentiated that way is a large part of ``x`` (0.05 deg of noise is 6 mrad/s); ordinary least squares would
shrink ``dt_hat`` by the noise's share of ``sum r_x^2`` (13 % at 0.03 deg in the tests' geometry).  The
instrument ``z`` is the same regressor from the attitudes two frames further out on each side: other telemetry
samples, so its noise is independent of ``x``'s and of the frame's own.  ``s^2`` is the larger of the pooled
residual variance and the weighted scatter of the blocks' own ``dt`` around ``dt_hat`` (the telemetry's
interpolation and the centroid's errors are correlated from frame to frame; the scatter sees that).

The range ``rho`` is the 3-D estimator's when the caller has one (``default_range_m`` before): it scales the
attitude's part of both ``y`` and ``x`` alike, so the estimate hardly depends on it (measured on P2 lockstep
records with exact navigation: 50 ms injected, block estimates within 1.5 ms whether ``rho`` was the true range,
the estimator's early one at half of it, 50 m, 300 m or 1 km).  Reference: the same idea as camera-IMU
temporal calibration from rotational motion (Furgale, Rehder and Siegwart, IROS 2013, which estimates ``dt``
inside a continuous-time batch); here linearised and online, with the target's line of sight in place of the
calibration pattern.

Excitation.  A camera that holds the target perfectly still in the image while flying straight sees no offset
at all: the line of sight labelled ``t`` is then the true one at ``t``.  ``sigma_dt`` says how much motion there
was; the estimate is ``confident`` once ``sigma_ms <= confident_sigma_ms`` (8) over at least ``min_blocks`` (2)
blocks, ``estimating`` before, ``unknown`` with no block yet.  A block is closed early (and used if long enough)
on a gap in the measurements, a new track or a time going backwards; a block whose residual RMS is
``outlier_factor`` (5) times the median of the blocks before (a centroid jumping between objects) is refused and
counted.  But a camera clock that stepped or drifts makes every later block such an outlier against the pool's
offset, and a pool that refused them all held the old offset, confident, for the rest of the flight (0 ms after a
step to -300 ms in the tests; -31 ms of a drift to -300 in the daemon): ``MOVED_RUN_BLOCKS`` (2) blocks refused in a
row that each fit their own pooled offset within the same limit (which a jumping centroid does not) take the pool's
place, the offset having moved, as a clock step is confirmed elsewhere by consecutive frames that agree.  The block
length and the degree were chosen on P2 lockstep records (RTK noise, 30 s): 3 s and degree 2 recovered 50 ms as 48.1 +- 4.2 ms and 0 ms as 2.7 +- 3.7 ms, both confident 7 s in; 2.5 s, 4 s or degree 3
absorbed most of the gimbal's 3 to 7 s pointing motion into the target's polynomial (sigma 8 to 30 ms); longer
blocks let the target's and observer's model errors in.

Consistency.  Most blocks after a step or along a drift are no outliers (at the bearings' noise their residuals
hardly grow), and a pool of them is a mixture of offsets: -300 ms followed by 0 read -247 +- 32 ms in the daemon,
within ``max_offset_ms``, and the pose lookup compensated 247 ms that no longer existed; a drift from 0 to -300 ms
over 20 s read -83 +- 35, never significant.  So after each block the pool is tested as one offset, and its oldest
blocks dropped until it passes: the newest consistent run is the offset now.  Each block's ``dt_k`` has the variance
``sigma_k^2 + floor^2 + (rel dt_k)^2``, ``sigma_k`` from its own residuals, ``floor`` (:data:`BLOCK_DT_FLOOR_MS`,
10 ms) what a constant offset's blocks scatter beyond it (P1/P2 lockstep records, RTK noise: 0 to 10.9 ms; the
residuals' frame-to-frame correlation) and ``rel`` (:data:`BLOCK_DT_REL`, 10 %) the first-order model's error at a
large offset, and the pool fails on either of two chi-square tests at :data:`CONSISTENT_TAIL`
(1e-4): the blocks' scatter about the pooled ``dt_hat`` on ``n - 1`` degrees of freedom (a step), and the older
blocks' mean against the newer ones' at the split where they differ most, on one degree, the tail shared among the
``n - 1`` splits (a drift, whose blocks each differ from the next by less than the scatter test sees).  Of every run
of consecutive blocks of a constant offset, the worst reached 0.59 of either limit on those lockstep records (a pair
of blocks 56 ms apart at 0 ms) and 0.57 in the tests' geometry (90 runs of 36 s, bearing noise 0.1 to 1 mrad),
without ``rel`` (which only lowers them).  A drift is followed with a lag: a block's floor hides a drift of 7 ms/s
between neighbours, and the last drifting blocks stay in the pool after the drift stops (2.6 to 3.1 sigmas off the
offset, within 31 ms, 15 s after a drift to -150 ms in the tests).
A cut pool lets go of the compensation (below): its value was of the blocks dropped; and it takes none before
``SIGNIFICANT_MIN_BLOCKS`` (3) blocks (nor does a pool restarted by refused blocks): in the daemon a constant -300 ms
gave runs of blocks from -175 to -418 ms, each with a sigma of a few ms, and two of them that agreed, confident at
-176 +- 7 ms, were compensated while the offset was -300.  The warning does not wait: the offset is there either way.

Significance.  Whether the offset is beyond a threshold (the warning's question) needs less than a confident
estimate: :meth:`TimeOffsetEstimate.significantly_beyond` asks for the estimate beyond it by two sigmas, the
sigma a confident estimate's or one pooled over ``SIGNIFICANT_MIN_BLOCKS`` (3) blocks, whose scatter then checks
it.  A weakly excited camera (the gimbal's pointing motion a few mrad/s) gives 20 to 30 ms per block, and a sigma
under 8 ms takes tens of seconds, while 50 ms against a 20 ms threshold is plain after three blocks.

Compensation (the caller's): look the pose up at ``t - compensated_ms`` instead of ``t``.  The estimator always
takes the pose at the frame's own stamp, so it estimates the whole offset, compensated or not;
:attr:`TimeOffsetEstimator.compensated_ms` takes the estimate when it is first significantly beyond
``min_compensated_ms`` (within ``max_offset_ms``): compensating 50 ms as 46 +- 13 leaves 4 ms, not 50.  It takes a
confident estimate again when that leaves it by more than two sigmas, or when that rests on twice the information
of the one it holds (its variance halved: ``REFINE_VARIANCE_RATIO``), and holds its value otherwise (the offset
belongs to the camera, not to the target: a lost track does not make it go away), until the offset moves: a pool
cut by the consistency tests or restarted by refused blocks sets it back to 0, and the new pool starts it again once
significant.  Each move makes the caller's 3-D
window again (one model selection), so block noise is no reason to move; but the first value taken rests on two or
three blocks, and held against the two-sigma test alone it could stay for the whole flight further off than the
estimate beside it, the later sigmas shrinking as fast as the difference (docs/performance.md, "A camera clock off
the autopilot's").  The variance halves only a few times per flight (the sigma of a full window stops shrinking).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np
from scipy.special import chdtri

from onboard.core.checks import is_positive_number, require_each
from onboard.core.errors import InputError, wrong_sizes
from onboard.core.frames import quat_conjugate, quat_multiply, rotmat_from_quat, rotvec_from_quat

__all__ = [
    "TimeOffsetParams",
    "TimeOffsetEstimate",
    "TimeOffsetEstimator",
    "STATES",
    "SIGNIFICANT_MIN_BLOCKS",
    "REFINE_VARIANCE_RATIO",
]

STATES = ("unknown", "estimating", "confident")
MS_PER_S = 1000.0
FREE_RANGE_TERMS = 1  # the range's change over a block left free: linear (module docstring)
#: blocks pooled before a sigma that is not yet confident is trusted for a warning: from three on, the blocks'
#: scatter bounds it from below (a sigma from the residuals alone misses their frame-to-frame correlation)
SIGNIFICANT_MIN_BLOCKS = 3
#: the compensation takes a confident estimate whose variance is at most this share of the one it holds (module
#: docstring, "Compensation"): twice the information, whatever the difference
REFINE_VARIANCE_RATIO = 0.5
#: refused blocks in a row that agree on an offset of their own restart the pool from them (module docstring)
MOVED_RUN_BLOCKS = 2
#: beyond its sigma from its own residuals, a block's ``dt`` scatters by up to this under a constant offset (the
#: residuals' frame-to-frame correlation, module docstring): P1/P2 lockstep records with RTK noise, 0 and 50 ms,
#: 10 to 13 blocks each, scattered by 0 to 10.9 ms more than their residual sigmas (root-sum-square)
BLOCK_DT_FLOOR_MS = 10.0
#: and by this share of itself: the model is first order in ``dt``, and in the daemon with a faked autopilot the
#: blocks of a constant -300 ms read -240 to -400 ms, each with a sigma under 1 ms (the tests' geometry: -265 on
#: average); without it those blocks were cut from each other and the warning came one block later
BLOCK_DT_REL = 0.1
#: the chi-square tail beyond which the pool's blocks are a mixture of offsets, not one (module docstring,
#: "Consistency")
CONSISTENT_TAIL = 1e-4
#: a frame's numbers kept for its block: bearing (3), q_ned_from_cam (4), camera position (3), velocity (3)
ROW_SIZE = 13


def _unit_ned(bearing_cam: np.ndarray, q_ned_from_cam: np.ndarray) -> np.ndarray:
    """(N, 3) unit lines of sight in NED, ``R(q) b / |b|`` for (N, 3) bearings and (N, 4) attitudes.

    Bit for bit what ``rotmat_from_quat(q) @ (b / np.linalg.norm(b))`` gives frame by frame (``norm`` of a
    vector is a dot product, and a stacked ``matmul`` makes each row's products as the single one does), so a
    block gives the same sums whether its lines of sight are made per frame or here, once per block."""
    b = bearing_cam
    sq = np.matmul(b[:, None, :], b[:, :, None])[:, 0, 0]
    return np.matmul(rotmat_from_quat(q_ned_from_cam), (b / np.sqrt(sq)[:, None])[:, :, None])[:, :, 0]


def _consistent(blocks) -> bool:
    """The blocks' offsets are one offset (module docstring, "Consistency"), by two chi-square tests of
    :data:`CONSISTENT_TAIL` over the blocks that measure it (``s_zx > 0``), each weighed by
    ``v_k = sigma_k^2 + floor^2 + (rel dt_k)^2`` (``sigma_k^2 = s_k^2 s_zz / s_zx^2`` from the block's own
    residuals at its own ``dt_k``, ``floor`` :data:`BLOCK_DT_FLOOR_MS`, ``rel`` :data:`BLOCK_DT_REL`):

    * their scatter, ``sum((dt_k - dt_hat)^2 / v_k)`` on ``n - 1`` degrees of freedom (``dt_hat`` the pooled
      estimate): a step of the clock;
    * the older blocks against the newer, ``(mean_old - mean_new)^2 / (var_old + var_new)`` (means weighed by
      ``1 / v_k``) on one degree, at the split that differs most, the tail shared among the ``n - 1`` splits: a
      drift, whose blocks each differ from the next by less than the scatter test sees."""
    used = [k for k in blocks if k.s_zx > 0 and k.s_zz > 0]
    n = len(used)
    if n < 2:
        return True
    dt = np.array([k.dt_s() for k in used])
    floor_s2 = (BLOCK_DT_FLOOR_MS / MS_PER_S) ** 2
    v = np.array([k.residual_var(k.dt_s()) * k.s_zz / k.s_zx**2 for k in used]) + floor_s2 + (BLOCK_DT_REL * dt) ** 2
    dt_hat = sum(k.s_zy for k in used) / sum(k.s_zx for k in used)
    if float(np.sum((dt - dt_hat) ** 2 / v)) > float(chdtri(n - 1, CONSISTENT_TAIL)):
        return False
    w = 1.0 / v
    cw, cwdt = np.cumsum(w)[:-1], np.cumsum(w * dt)[:-1]  # the first m blocks, m = 1 .. n - 1
    mean_old, mean_new = cwdt / cw, (np.sum(w * dt) - cwdt) / (np.sum(w) - cw)
    z2 = (mean_old - mean_new) ** 2 / (1.0 / cw + 1.0 / (np.sum(w) - cw))
    return float(np.max(z2)) <= float(chdtri(1, CONSISTENT_TAIL / (n - 1)))


@dataclass(frozen=True)
class TimeOffsetParams:
    """Tuning of :class:`TimeOffsetEstimator` (module docstring); times in seconds unless ``_ms``."""

    block_s: float = 3.0
    poly_degree: int = 2
    rate_span_s: float = 0.2
    window_s: float = 60.0
    confident_sigma_ms: float = 8.0
    min_blocks: int = 2
    max_offset_ms: float = 250.0
    compensate: bool = True
    #: compensation starts only for an offset beyond this by two sigmas: a smaller one is absorbed by the 3-D
    #: estimator's attitude-bias nuisance, while each start of compensation restarts its window; and on a flight
    #: without an offset a confident estimate can still read 15-20 ms (measured), which must not cost a restart
    min_compensated_ms: float = 20.0
    outlier_factor: float = 5.0
    #: the range's 1-sigma as a fraction of itself (the along-the-line-of-sight rows' weight)
    range_sigma_frac: float = 3.0
    #: the range assumed while the caller has none (the estimate hardly depends on it: module docstring)
    default_range_m: float = 300.0
    #: a gap between measurements longer than this closes the block
    max_gap_s: float = 0.25

    def __post_init__(self) -> None:
        require_each(
            self,
            (
                "block_s",
                "rate_span_s",
                "range_sigma_frac",
                "default_range_m",
                "window_s",
                "confident_sigma_ms",
                "max_offset_ms",
                "min_compensated_ms",
                "outlier_factor",
            ),
            is_positive_number,
            InputError,
            "TimeOffsetParams.{name} must be a positive number, got {value!r}",
        )
        if not isinstance(self.poly_degree, int) or not 0 <= self.poly_degree <= 6:
            raise InputError(f"TimeOffsetParams.poly_degree must be an integer in 0..6, got {self.poly_degree!r}")
        if not isinstance(self.min_blocks, int) or self.min_blocks < 1:
            raise InputError(f"TimeOffsetParams.min_blocks must be a positive integer, got {self.min_blocks!r}")
        if self.rate_span_s >= self.block_s / 2:
            raise InputError(
                f"TimeOffsetParams.rate_span_s ({self.rate_span_s}) must be under half of block_s ({self.block_s})"
            )


@dataclass(frozen=True)
class TimeOffsetEstimate:
    """The offset now: ``estimate_ms`` (positive: frames stamped late) with ``sigma_ms`` (None while
    ``state`` is ``unknown``), ``compensated_ms`` (what the caller subtracts from the stamp for its pose
    lookup), ``blocks`` / ``frames`` pooled, ``refused_blocks`` so far, ``excitation_mradps`` (RMS of the
    high-passed regressor ``w x u``: the motion the estimate rests on)."""

    estimate_ms: float | None
    sigma_ms: float | None
    state: str
    compensated_ms: float
    blocks: int
    frames: int
    refused_blocks: int
    excitation_mradps: float | None

    @property
    def confident(self) -> bool:
        return self.state == "confident"

    def significantly_beyond(self, threshold_ms: float) -> bool:
        """The offset is beyond ``threshold_ms`` by more than two sigmas, with a sigma that can be trusted: a
        confident estimate's, or one pooled over ``SIGNIFICANT_MIN_BLOCKS`` blocks (their scatter checks it).

        A test of the offset against the threshold, not a demand for precision (module docstring)."""
        if self.estimate_ms is None or self.sigma_ms is None:
            return False
        if not (self.confident or self.blocks >= SIGNIFICANT_MIN_BLOCKS):
            return False
        return abs(self.estimate_ms) - 2.0 * self.sigma_ms > threshold_ms

    def as_dict(self) -> dict:
        r = lambda x, n: None if x is None else round(float(x), n)  # noqa: E731
        return {
            "estimate_ms": r(self.estimate_ms, 2),
            "sigma_ms": r(self.sigma_ms, 2),
            "state": self.state,
            "compensated_ms": round(float(self.compensated_ms), 2),
            "blocks": int(self.blocks),
            "frames": int(self.frames),
            "refused_blocks": int(self.refused_blocks),
            "excitation_mradps": r(self.excitation_mradps, 2),
        }


@dataclass(frozen=True)
class _Block:
    """One block's sums after projecting off the target's trajectory: ``r_y`` the target positions the stamped
    poses give, ``r_x`` the regressor, ``r_z`` its instrument (module docstring)."""

    t_end_s: float
    s_zx: float
    s_zy: float
    s_zz: float
    s_xx: float
    s_xy: float
    s_yy: float
    dof: int
    frames: int

    def dt_s(self) -> float:
        return self.s_zy / self.s_zx

    def residual_var(self, dt_s: float) -> float:
        """Mean square of ``r_y - dt r_x`` per degree of freedom."""
        return max(self.s_yy - 2.0 * dt_s * self.s_xy + dt_s * dt_s * self.s_xx, 0.0) / max(self.dof, 1)


class TimeOffsetEstimator:
    """``add(t_s, bearing_cam, q_ned_from_cam, track_id)`` once per frame with a measured target and a
    pose at the frame's stamp; :attr:`estimate` is updated when a block closes.  Not thread-safe."""

    def __init__(self, params: TimeOffsetParams | None = None) -> None:
        self.params = params if params is not None else TimeOffsetParams()
        self._blocks: collections.deque[_Block] = collections.deque()
        self._t: list[float] = []
        #: the block's frames as they came, (13,) each: bearing in the camera frame, q_ned_from_cam, camera position
        #: and velocity (the line of sight in NED is made once per block, in :meth:`close_block`)
        self._frames: list[np.ndarray] = []
        self._r: list[float] = []
        self._track_id: object = None
        self._refused = 0
        #: the blocks refused in a row, the newest last: agreeing on another offset, they restart the pool
        self._refused_run: collections.deque[_Block] = collections.deque(maxlen=MOVED_RUN_BLOCKS)
        self._compensated_ms = 0.0
        #: the sigma of the estimate the compensation holds (None: none held)
        self._compensated_sigma_ms: float | None = None
        #: the pool was cut or restarted since it last held SIGNIFICANT_MIN_BLOCKS blocks: the offset has just moved
        self._young = False
        self.estimate = self._summarise()

    @property
    def compensated_ms(self) -> float:
        return self._compensated_ms

    def reset(self) -> None:
        """Forget everything (the clocks changed: an autopilot reboot, a camera restart); no compensation."""
        self._blocks.clear()
        self._refused_run.clear()
        self._young = False
        self._clear_block()
        self._compensated_ms = 0.0
        self._compensated_sigma_ms = None
        self.estimate = self._summarise()

    def add(
        self,
        t_s: float,
        bearing_cam,
        q_ned_from_cam,
        p_cam_ned_m,
        v_cam_ned_mps,
        range_m: float | None = None,
        track_id: object = None,
    ) -> TimeOffsetEstimate:
        """One frame: its stamp (s), the target's bearing in the camera frame (3,), the reported pose at the
        stamp (attitude (w, x, y, z), camera position and velocity in NED), the track it belongs to.
        Returns :attr:`estimate`."""
        t = float(t_s)
        # one array for the frame, checked at once: this runs on every frame of the daemon's pipeline thread, and
        # numpy's per-call overhead on four small arrays was most of its cost
        row = np.concatenate((bearing_cam, q_ned_from_cam, p_cam_ned_m, v_cam_ned_mps), axis=None, dtype=float)
        if (
            row.size != ROW_SIZE
            or np.size(bearing_cam) != 3
            or np.size(q_ned_from_cam) != 4
            or np.size(p_cam_ned_m) != 3
        ):
            wrong = wrong_sizes(
                ("bearing_cam", bearing_cam, 3),
                ("q_ned_from_cam", q_ned_from_cam, 4),
                ("p_cam_ned_m", p_cam_ned_m, 3),
                ("v_cam_ned_mps", v_cam_ned_mps, 3),
            )
            raise InputError(f"TimeOffsetEstimator.add: {wrong}")
        r = self.params.default_range_m if range_m is None else float(range_m)
        if not (math.isfinite(t) and np.isfinite(row).all()):
            # named only here, once something is wrong: the check above stays one call per frame
            bad = [
                name
                for name, ok in (
                    ("t_s", math.isfinite(t)),
                    ("bearing_cam", np.isfinite(row[0:3]).all()),
                    ("q_ned_from_cam", np.isfinite(row[3:7]).all()),
                    ("p_cam_ned_m", np.isfinite(row[7:10]).all()),
                    ("v_cam_ned_mps", np.isfinite(row[10:13]).all()),
                )
                if not ok
            ]
            raise InputError(f"TimeOffsetEstimator.add: {', '.join(bad)} not finite")
        if not (math.isfinite(r) and r > 0):
            raise InputError(f"TimeOffsetEstimator.add: range_m must be a positive number, got {range_m!r}")
        if self._t and (track_id != self._track_id or t <= self._t[-1] or t - self._t[-1] > self.params.max_gap_s):
            self.close_block()
        if self._t and t - self._t[0] >= self.params.block_s:
            self.close_block()
        if not self._t:
            self._track_id = track_id
        self._t.append(t)
        self._frames.append(row)
        self._r.append(r)
        return self.estimate

    def close_block(self) -> None:
        """End the block being filled (used when long enough) and start an empty one."""
        t, r = np.array(self._t), np.array(self._r)
        rows = np.array(self._frames).reshape(-1, ROW_SIZE)
        self._clear_block()
        if t.size < 2:
            return
        q, pc, vc = rows[:, 3:7].copy(), rows[:, 7:10].copy(), rows[:, 10:13].copy()
        u = _unit_ned(rows[:, 0:3].copy(), q)
        block = self._block_sums(t, u, q, pc, vc, r)
        if block is None:
            return
        moved = False
        if len(self._blocks) >= 3:
            dt_s = self.estimate.estimate_ms / MS_PER_S if self.estimate.estimate_ms is not None else 0.0
            rms = [math.sqrt(k.residual_var(dt_s)) for k in self._blocks]
            limit = self.params.outlier_factor * float(np.median(rms))
            if math.sqrt(block.residual_var(dt_s)) > limit:
                self._refused += 1
                self._refused_run.append(block)
                if not self._offset_moved(limit):
                    self.estimate = self._summarise()
                    return
                # the offset moved: the refused blocks agree on another one, at which they fit as well as the pool
                # did at its own; what the pool holds is of the offset before
                self._blocks.clear()
                self._blocks.extend(list(self._refused_run)[:-1])
                moved = True
            self._refused_run.clear()
        self._blocks.append(block)
        while self._blocks and self._blocks[0].t_end_s < block.t_end_s - self.params.window_s:
            self._blocks.popleft()
        # blocks that disagree beyond their own sigmas are two offsets or more (a clock that stepped, or drifts), not
        # one: the newest consistent run is the offset now, and a value compensated from the blocks before it is of
        # an offset that is gone (module docstring, "Consistency")
        while len(self._blocks) > 1 and not _consistent(self._blocks):
            self._blocks.popleft()
            moved = True
        if moved:
            self._release_compensation()
            self._young = True
        elif len(self._blocks) >= SIGNIFICANT_MIN_BLOCKS:
            self._young = False
        self.estimate = self._summarise()
        p = self.params
        e = self.estimate
        # just after the offset moved, two blocks that agree may still be two of a run whose blocks do not (the
        # model's error at a large offset): the compensation waits for a third, whose scatter checks the sigma (the
        # warning does not: the offset is there either way)
        settled = not self._young or len(self._blocks) >= SIGNIFICANT_MIN_BLOCKS
        if p.compensate and settled and e.estimate_ms is not None and abs(e.estimate_ms) <= p.max_offset_ms:
            # started by the same test as the warning (an offset of 50 ms compensated as 46 +- 13 leaves 4, not
            # 50); moved by a confident estimate that left it by two sigmas or rests on twice its information (each
            # move makes the caller's 3-D window again, and a block's noise is no reason to: module docstring)
            sigma_ms = e.sigma_ms if e.sigma_ms is not None else 0.0
            held = self._compensated_sigma_ms
            start = not self._compensated_ms and e.significantly_beyond(p.min_compensated_ms)
            moved = e.confident and abs(e.estimate_ms - self._compensated_ms) > 2.0 * sigma_ms
            refined = e.confident and held is not None and sigma_ms**2 <= REFINE_VARIANCE_RATIO * held**2
            if start or (self._compensated_ms and (moved or refined)):
                self._compensated_ms = float(e.estimate_ms)
                self._compensated_sigma_ms = sigma_ms
                self.estimate = self._summarise()

    # ------------------------------------------------------------------ internals

    def _offset_moved(self, limit: float) -> bool:
        """The last :data:`MOVED_RUN_BLOCKS` blocks were all refused and agree on an offset of their own: each fits
        it within ``limit`` (the outlier test's, from the pool's residuals at the pool's offset).  A centroid jumping
        between objects fits no offset; a camera clock that stepped or drifts fits the new one as well as the pool fit
        the old (module docstring, "Excitation")."""
        run = self._refused_run
        if len(run) < MOVED_RUN_BLOCKS:
            return False
        s_zx = sum(k.s_zx for k in run)
        if s_zx <= 0:
            return False
        dt_s = sum(k.s_zy for k in run) / s_zx
        return all(math.sqrt(k.residual_var(dt_s)) <= limit for k in run)

    def _release_compensation(self) -> None:
        """The offset moved: what the compensation holds was estimated from blocks of the offset before (or from a
        mixture), so the pose lookup goes back to the stamp until the new pool is significant in its own right."""
        self._compensated_ms = 0.0
        self._compensated_sigma_ms = None

    def _clear_block(self) -> None:
        self._t, self._frames, self._r = [], [], []
        self._track_id = None

    def _block_sums(self, t, u, q, p_cam, v_cam, r_m) -> _Block | None:
        p = self.params
        n = t.size
        step_s = float(np.median(np.diff(t)))
        m = max(1, int(round(p.rate_span_s / 2.0 / step_s))) if step_s > 0 else 1
        idx = np.arange(m + 2, n - m - 2)
        n_par = 3 * (p.poly_degree + 1) + FREE_RANGE_TERMS
        if idx.size < n_par:
            return None
        uu, pc, vc, tt = u[idx], p_cam[idx], v_cam[idx], t[idx]
        # the camera's rate in NED, centred on each frame: rotvec(R(t+h) R(t-h)^T) / 2h, once over
        # frames k -+ m (the regressor), once over k -+ (m + 2) (its instrument: other telemetry samples)
        g, g_iv = (np.cross(self._rate_ned(t, q, idx, j), uu) for j in (m, m + 2))
        # each frame's axes: two across the line of sight (e1, e2), one along it (u)
        e1 = np.cross(uu, [0.0, 0.0, 1.0])
        flat = np.linalg.norm(e1, axis=1) < 1e-6
        e1[flat] = np.cross(uu[flat], [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
        e2 = np.cross(uu, e1)
        tau = (2.0 * tt - tt[0] - tt[-1]) / max(tt[-1] - tt[0], 1e-9)
        L = np.polynomial.legendre.legvander(tau, p.poly_degree)  # (N, d+1)
        # one range for the block (the caller's median: its scale hardly matters, module docstring); the along rows
        # hold the target's mean range to it but leave its linear change over the block free (a nuisance column)
        rng_m = np.full(idx.size, float(np.median(r_m[idx])))
        A, y = self._rows(e1, e2, uu, pc, rng_m, L)
        free = np.zeros((idx.size, 3, FREE_RANGE_TERMS))
        free[:, 2, :] = L[:, 1 : 1 + FREE_RANGE_TERMS] / (p.range_sigma_frac * rng_m[:, None])
        A = np.hstack([A, free.reshape(3 * idx.size, FREE_RANGE_TERMS)])
        # the regressor across the line of sight only: along it, the range is the estimator's, not the stamp's
        across = np.array([1.0, 1.0, 0.0])
        W = self._weights(e1, e2, uu, rng_m)
        x = (np.einsum("kij,kj->ki", W, vc + rng_m[:, None] * g) * across).reshape(-1)
        z = (np.einsum("kij,kj->ki", W, vc + rng_m[:, None] * g_iv) * across).reshape(-1)
        Q, _ = np.linalg.qr(A)
        r_y, r_x, r_z = (v - Q @ (Q.T @ v) for v in (y, x, z))
        return _Block(
            t_end_s=float(t[-1]),
            s_zx=float(r_z @ r_x),
            s_zy=float(r_z @ r_y),
            s_zz=float(r_z @ r_z),
            s_xx=float(r_x @ r_x),
            s_xy=float(r_x @ r_y),
            s_yy=float(r_y @ r_y),
            dof=int(3 * idx.size - n_par - 1),
            frames=int(idx.size),
        )

    def _weights(self, e1, e2, uu, rng_m) -> np.ndarray:
        """(N, 3, 3): rows in radians across the line of sight, and one along it that only holds the target near
        the range (sigma ``range_sigma_frac`` of it; without it the fit's range is free: module docstring)."""
        return np.stack([e1, e2, uu / self.params.range_sigma_frac], axis=1) / rng_m[:, None, None]

    def _rows(self, e1, e2, uu, pc, rng_m, L) -> tuple[np.ndarray, np.ndarray]:
        """The target's polynomial columns ``A`` (3N, 3(d+1)) and the rows ``y`` (3N,) of ``p_c + rho u``."""
        W = self._weights(e1, e2, uu, rng_m)
        A = np.einsum("kij,kl->kijl", W, L).reshape(3 * uu.shape[0], -1)
        y = np.einsum("kij,kj->ki", W, pc + rng_m[:, None] * uu).reshape(-1)
        return A, y

    @staticmethod
    def _rate_ned(t: np.ndarray, q: np.ndarray, idx: np.ndarray, j: int) -> np.ndarray:
        q_rel = quat_multiply(q[idx + j], quat_conjugate(q[idx - j]))
        q_rel *= np.where(q_rel[:, :1] < 0.0, -1.0, 1.0)  # q and -q are one rotation: take the short way
        return rotvec_from_quat(q_rel) / (t[idx + j] - t[idx - j])[:, None]

    def _summarise(self) -> TimeOffsetEstimate:
        p = self.params
        blocks = list(self._blocks)
        frames = sum(k.frames for k in blocks)
        s_zx = sum(k.s_zx for k in blocks)
        s_zz = sum(k.s_zz for k in blocks)
        if not blocks or s_zx <= 0 or s_zz <= 0:
            return TimeOffsetEstimate(
                None, None, "unknown", self._compensated_ms, len(blocks), frames, self._refused, None
            )
        dt_s = sum(k.s_zy for k in blocks) / s_zx
        # the instrumental-variable estimate's variance: s^2 sum(r_z^2) / (sum(r_z r_x))^2
        var = sum(k.residual_var(dt_s) * k.dof for k in blocks) / max(sum(k.dof for k in blocks), 1)
        used = [k for k in blocks if k.s_zx > 0]
        if len(used) >= 3:
            scatter = sum(k.s_zx**2 / k.s_zz * (k.dt_s() - dt_s) ** 2 for k in used) / (len(used) - 1)
            var = max(var, scatter)
        sigma_ms = math.sqrt(var * s_zz) / s_zx * MS_PER_S
        confident = len(blocks) >= p.min_blocks and sigma_ms <= p.confident_sigma_ms
        return TimeOffsetEstimate(
            estimate_ms=dt_s * MS_PER_S,
            sigma_ms=sigma_ms,
            state="confident" if confident else "estimating",
            compensated_ms=self._compensated_ms,
            blocks=len(blocks),
            frames=frames,
            refused_blocks=self._refused,
            excitation_mradps=math.sqrt(s_zx / max(2 * frames, 1)) * 1e3,
        )
