r"""The least-squares problem of one window: measurement model, motion priors, solve, covariance, evidence.

:class:`WindowProblem` is the MAP problem of one window under one motion prior and one noise model, its
control-point span fixed.  :class:`~onboard.estimation.map_estimator.MapEstimator` builds one per model it
compares, starts it from range hypotheses, and chooses among the solutions (selection, the named result and
the observability verdict are there); the sliding window re-linearises one in place.

Model
-----
The target trajectory is a uniform cubic B-spline ``p(t)`` in local NED (``spline.KnotGrid``,
knots every ``knot_spacing_s``).  For observation i at time ``t_i`` with camera centre ``C_i`` and
attitude ``R_i = R(q_ned_from_cam)``, the predicted camera-frame direction is

    y_i = R_i^T Exp(phi) (p(t_i) - C_i + beta + gamma (t_i - t_ref))

where ``phi`` is a constant attitude bias in NED (INS psi-angle error; ``frames`` docstring),
``beta``/``gamma`` a constant camera-position offset and drift (GNSS error).  Each nuisance is
present only when its prior sigma in :class:`NoiseModel` is non-zero.  The measurement residual
is angular: the difference of ideal normalised image coordinates ``y_xy / y_z - xy_i``, weighted by
``f / sigma_eff`` with ``sigma_eff^2 = sigma_px^2 + (f sigma_att)^2 + (f sigma_pos / range)^2``
(pixel noise, white attitude noise and white camera-position noise mapped to pixels).

Priors (physical units, real timestamps), three families over a grid of intensities ``q``:

- CV, white-noise acceleration:  ``v' = w``;
- CT, coordinated turn:  ``v_h' = omega J v_h + w_h``, ``v_d' = w_d`` (``J`` rotates north into east;
  ``omega`` a constant turn rate, estimated, prior N(0, sigma_omega^2));
- CA, white-noise jerk (constant acceleration):  ``a' = w``;

with ``E[w w^T] = diag(q_h, q_h, q_v) delta(t - s)``, i.e. the negative log prior is
``1/2 integral ||L p||^2_{Q^-1} dt``, integrated exactly on each knot interval (3-point Gauss-Legendre;
the jerk of a cubic spline is constant per interval).  Weak priors on the window's mean position
(1 km), velocity (30 m/s) and acceleration (3 m/s^2; 0.5 m/s^2 for CA) make the posterior proper.

Solve: Gauss-Newton first, Levenberg-Marquardt damping only when a step fails (Marquardt 1963;
More 1978 column scaling), normal equations by Cholesky on the column-scaled Jacobian (~80 unknowns
for a 10 s window), ``J^T J`` and ``J^T r`` built from the Jacobian's knot-interval structure
(:meth:`WindowProblem.normal_matrix`); the covariance and the evidence come from a square-root factor: the
Cholesky factor of those normal equations where they are well conditioned (:meth:`WindowProblem.normal_factor`),
else a QR of the dense Jacobian, which stays sound where the prior and the data span ~14 decades.  A step that takes the mean range below
``min_range_m`` ends the solve as collapsed (the trajectory shrunk onto the camera track, where the cost
keeps falling).  The Laplace log evidence (MacKay 1992) is conditional on the navigation nuisances at
their MAP values (:meth:`WindowProblem.log_evidence` says why).
"""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import numpy as np
import scipy.linalg as sla

from onboard.core.schema import NonNegativeFloat, PositiveFloat, config_dataclass
from onboard.estimation.fastmath import cho_factor_lower, cho_solve_spd_lower, cross3, einsum, qr_r
from onboard.estimation.kernels import (
    add_turn_prior_gram,
    add_turn_prior_transpose,
    linearise_measurements,
    measurement_gradient,
    measurement_gram,
    scale_normal_equations,
    turn_prior_rows,
)
from onboard.estimation.observations import Observations
from onboard.estimation.spline import KnotGrid, fit_controls, gauss_legendre_3

__all__ = [
    "NoiseModel",
    "MotionPrior",
    "WeakPriorSettings",
    "WindowProblem",
    "SolveResult",
    "drain",
    "SHIPPED_PIXEL_SIGMA_PX",
    "SHIPPED_ATTITUDE_WHITE_SIGMA_DEG",
    "SHIPPED_ATTITUDE_BIAS_SIGMA_DEG",
    "SHIPPED_CAMERA_POSITION_WHITE_SIGMA_M",
]

#: the noise the daemon's shipped configuration assumes (its ``estimator`` section's defaults), an RTK-class drone's
#: (config/noise_cases.yaml RTK) with the image chain's centroid noise; what the offline reconstruction assumes too
SHIPPED_PIXEL_SIGMA_PX = 0.3
SHIPPED_ATTITUDE_WHITE_SIGMA_DEG = 0.05
SHIPPED_ATTITUDE_BIAS_SIGMA_DEG = 0.1
SHIPPED_CAMERA_POSITION_WHITE_SIGMA_M = 0.02

_T = TypeVar("_T")


def drain(steps: Generator[int, None, _T]) -> _T:
    """Run an anytime computation to its end (a generator that yields its work as it goes: :meth:`WindowProblem.solve_steps`,
    :meth:`~onboard.estimation.map_estimator.MapEstimator.selection`); its return value."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


@config_dataclass
class NoiseModel:
    """Measurement and navigation noise the estimator assumes (1 sigma per axis); a bad value raises
    :class:`~onboard.core.schema.SchemaError` naming the field (the daemon builds it from its ``estimator``
    section, the simulator from a noise case)."""

    pixel_sigma_px: PositiveFloat = 0.3
    attitude_white_sigma_rad: NonNegativeFloat = 0.0
    attitude_bias_sigma_rad: NonNegativeFloat = 0.0
    camera_position_white_sigma_m: NonNegativeFloat = 0.0
    camera_position_offset_sigma_m: NonNegativeFloat = 0.0
    camera_position_drift_sigma_mps: NonNegativeFloat = 0.0


@dataclass(frozen=True)
class MotionPrior:
    """One motion model of the family set.

    ``jerk=False``: white-noise acceleration with PSDs ``q_*`` in m^2/s^3, plus a coordinated turn
    when ``turn_rate_sigma_radps > 0`` (CV when 0).  ``jerk=True``: white-noise jerk (constant
    acceleration, CA) with PSDs in m^2/s^5 and no turn.
    """

    q_horizontal_m2ps3: float
    q_vertical_m2ps3: float
    turn_rate_sigma_radps: float = 0.3
    jerk: bool = False

    @property
    def family(self) -> str:
        return "ca" if self.jerk else ("ct" if self.turn_rate_sigma_radps > 0 else "cv")


class WeakPriorSettings(Protocol):
    """The settings a :class:`WindowProblem` reads besides its prior and noise model: the sigmas of the weak
    priors on the window's mean position, velocity and acceleration that make the posterior proper
    (:class:`~onboard.estimation.map_estimator.MapConfig` has them, and documents them)."""

    @property
    def position_prior_sigma_m(self) -> float: ...

    @property
    def velocity_prior_sigma_mps(self) -> float: ...

    @property
    def acceleration_prior_sigma_mps2(self) -> float: ...

    @property
    def ca_acceleration_sigma_mps2(self) -> float: ...


#: the span cache's key of the last few windows' constants (WindowProblem), and how many it keeps
_WINDOWS = "windows"
_WINDOWS_KEPT = 4
#: the largest span of the squared diagonal of the Cholesky factor of the scaled normal matrix at which
#: WindowProblem.normal_factor keeps that factor (the log evidence then within ~1e-5 nats of the QR's)
_NORMAL_FACTOR_MAX_SPAN = 1e7
#: what the kernels are passed for a nuisance the problem does not have (an offset, a drift, a rotation)
_NONE = np.zeros(0)
_NONE_3X3 = np.zeros((0, 0))


def _rodrigues(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix Exp(phi) of one rotation vector (Rodrigues' formula ``I + sin(a)/a K + (1 - cos(a))/a^2 K^2``,
    ``K = [phi]x``; frames.rotmat_from_rotvec, unbatched), in scalar arithmetic: it runs once per evaluation."""
    x, y, z = phi.tolist()
    xx, yy, zz = x * x, y * y, z * z
    a2 = xx + yy + zz
    a = math.sqrt(a2)
    if a < 1e-9:
        return np.array([[1.0, -z, y], [z, 1.0, -x], [-y, x, 1.0]])
    s = math.sin(a) / a
    c = (1 - math.cos(a)) / a2
    xy, xz, yz = c * x * y, c * x * z, c * y * z
    return np.array(
        [
            [1.0 - c * (yy + zz), xy - s * z, xz + s * y],
            [xy + s * z, 1.0 - c * (xx + zz), yz - s * x],
            [xz - s * y, yz + s * x, 1.0 - c * (xx + yy)],
        ]
    )


def _project(w_rot: np.ndarray, R_cn: np.ndarray, xy: np.ndarray, s: np.ndarray, jacobian: bool):
    """Angular residuals of directions ``w_rot`` (F, 3) in NED seen by cameras ``R_cn`` (F, 3, 3).

    Returns (residual (F, 2) in standard units, d residual / d w_rot (F, 2, 3) or None, valid).
    """
    y = np.einsum("fij,fj->fi", R_cn, w_rot)
    z = y[:, 2]
    valid = bool((z * z > 1e-12 * np.einsum("fi,fi->f", w_rot, w_rot)).all() and (z > 0).all())
    zs = np.where(z > 1e-9, z, 1e-9)
    pred = y[:, :2] / zs[:, None]
    res = (pred - xy) * s
    if not jacobian:
        return res, None, valid
    k = 1.0 / zs
    # d pred / d w_rot = (R_cn[0] - pred_x R_cn[2]) / z, likewise for y (both rows at once)
    M = (R_cn[:, :2, :] - pred[:, :, None] * R_cn[:, 2:3, :]) * (k[:, None] * s)[:, :, None]
    return res, M, valid


class _SpanPrior:
    """The parts of the prior that depend only on the control span (cached across frames)."""

    def __init__(self, grid: KnotGrid, first: int, count: int, prior: MotionPrior):
        # quadrature over every knot interval of the span
        nodes, weights = gauss_legendre_3()
        seg = np.arange(first, first + count - 3)
        if prior.jerk:
            # the third derivative is constant on each knot interval: one row per interval, whose
            # square times h is the exact integral; "Bq2" then holds the jerk basis
            h = grid.spacing_s
            tq = grid.t_origin_s + (seg + 0.5) * h
            self.Bq1 = np.zeros((seg.size, count))
            self.Bq2 = np.zeros((seg.size, count))
            for m, w3 in enumerate((-1.0, 3.0, -3.0, 1.0)):
                self.Bq2[np.arange(seg.size), seg - first + m] = w3 / h**3
            wq = np.full(seg.size, h)
        else:
            tq = (grid.t_origin_s + (seg[:, None] + nodes[None, :]) * grid.spacing_s).reshape(-1)
            self.Bq1 = grid.dense_basis(tq, first, count, 1)
            self.Bq2 = grid.dense_basis(tq, first, count, 2)
            wq = np.tile(weights, seg.size) * grid.spacing_s
        self.sq_h = np.sqrt(wq / prior.q_horizontal_m2ps3)
        self.sq_v = np.sqrt(wq / prior.q_vertical_m2ps3)
        G = self.G = tq.size
        # prior rows are linear in the controls: J_prior_c(omega) = P_acc + omega * P_turn
        self.P_acc = np.zeros((3 * G, 3 * count))
        self.P_turn = np.zeros((3 * G, 3 * count))
        for ax, sq in ((0, self.sq_h), (1, self.sq_h), (2, self.sq_v)):
            self.P_acc[ax::3, ax::3] = sq[:, None] * self.Bq2
        self.P_turn[0::3, 1::3] = self.sq_h[:, None] * self.Bq1
        self.P_turn[1::3, 0::3] = -self.sq_h[:, None] * self.Bq1
        self._grams: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def grams(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The prior rows' normal matrix as a polynomial in the turn rate: ``(P_acc + omega P_turn)^T (P_acc +
        omega P_turn) = A + omega B + omega^2 C``, returns (A, B, C), computed once per span and prior."""
        if self._grams is None:
            cross = self.P_acc.T @ self.P_turn
            self._grams = (self.P_acc.T @ self.P_acc, cross + cross.T, self.P_turn.T @ self.P_turn)
        return self._grams


class _WindowConstants:
    """What a window's problems share whatever their motion prior and noise model: the basis at the observations,
    the observations laid out observation-last (:meth:`WindowProblem.linearise`), the knot intervals' weights
    (:meth:`WindowProblem.point_covariances`), and per parameter layout the index maps of :meth:`meas_flat`.  Read only."""

    def __init__(self, obs: Observations, grid: KnotGrid, first: int, count: int):
        self.obs, self.key = obs, (grid, first, count)
        F = len(obs)
        self.rows = rows = grid.basis(obs.t_s, first, count)
        self.B0 = np.zeros((F, count))  # (F, count) dense basis of p(t_i)
        np.put_along_axis(self.B0, rows.index, rows.w0, axis=1)
        self.R_cn = np.transpose(obs.R_ned_from_cam, (0, 2, 1))
        self.f = np.stack([obs.fx_px, obs.fy_px], axis=1)
        self.t_ref = 0.5 * (obs.t_s[0] + obs.t_s[-1])
        self.dt = obs.t_s - self.t_ref
        ref = grid.basis(np.array([self.t_ref]), first, count)
        self.ref_idx, self.ref_w0, self.ref_w1, self.ref_w2 = ref.index[0], ref.w0[0], ref.w1[0], ref.w2[0]
        self.p_ref = obs.p_cam_ned_m.mean(axis=0)
        # observation-last copies
        self.p_cam_T = np.ascontiguousarray(obs.p_cam_ned_m.T)
        self.xy_T = np.ascontiguousarray(obs.xy_norm.T)
        self.R_T = np.ascontiguousarray(np.transpose(self.R_cn, (1, 2, 0)))  # R_T[i, j, f] = R_cn[f, i, j]
        self.w0_T = np.ascontiguousarray(rows.w0.T)
        # the observations interval by interval: (intervals, the fullest interval's count), padded with
        # observation 0 at weight 0
        seg = rows.index[:, 0]
        nseg = self.intervals = count - 3
        per_seg = np.bincount(seg, minlength=nseg)
        order = np.argsort(seg, kind="stable")
        slot = np.arange(F) - np.repeat(np.cumsum(per_seg) - per_seg, per_seg)
        width = int(per_seg.max())
        self.interval_slot = np.empty(F, dtype=np.int64)  # observation f's place in (intervals x width)
        self.interval_slot[order] = seg[order] * width + slot
        w0 = np.zeros((nseg, width, 4))
        w0[seg[order], slot] = rows.w0[order]
        # the weights of the interval sums: w0[m] w0[n] (16 columns)
        self.interval_weights = (w0[:, :, :, None] * w0[:, :, None, :]).reshape(nseg, width, 16)
        self._meas_flat: dict[int, np.ndarray] = {}
        self._bearings: np.ndarray | None = None
        self._controls_at: dict[float, np.ndarray] = {}

    def controls_at_range(self, range_m: float) -> np.ndarray:
        """The control points (count, 3) fitted through the measured lines of sight at ``range_m`` (a range
        hypothesis of the multi-start; every model of a selection starts from the same ones)."""
        c = self._controls_at.get(range_m)
        if c is None:
            if self._bearings is None:
                self._bearings = self.obs.bearings_ned()
            c = self._controls_at[range_m] = fit_controls(self.B0, self.obs.p_cam_ned_m + range_m * self._bearings)
        return c

    def meas_flat(self, n_params: int) -> np.ndarray:
        """Flat positions in J (n_params columns) of the control-point block of the measurement rows, in the
        order (2 rows, 4 controls, 3 axes, F)."""
        if n_params not in self._meas_flat:
            F, index = len(self.obs), self.rows.index
            self._meas_flat[n_params] = (
                (2 * np.arange(F) + np.arange(2)[:, None])[:, None, None, :] * n_params
                + 3 * index.T[None, :, None, :]
                + np.arange(3)[None, None, :, None]
            )
        return self._meas_flat[n_params]


@dataclass(frozen=True, eq=False)
class SolveResult:
    """What :meth:`WindowProblem.solve` returns.

    ``theta`` (n_params,) the parameters at the end; ``cost`` 1/2 chi^2 there (inf: the start was invalid,
    or the solve collapsed below ``min_range_m``); ``iterations`` taken; ``converged`` when the cost stopped
    falling (by less than the tolerance, or no damping found a lower cost) before ``max_iterations``;
    ``factor`` the square-root information ``(R, d)`` at ``theta`` (``H = J^T J = D R^T R D``, see
    :meth:`WindowProblem.factor`), None when not asked for or when the cost is inf.
    """

    theta: np.ndarray
    cost: float
    iterations: int
    converged: bool
    factor: tuple[np.ndarray, np.ndarray] | None


class WindowProblem:
    """The least-squares problem of one window with fixed control span, prior and noise model.

    Parameter vector: control points (count x 3, row-major) | omega | phi (3) | beta (3) | gamma (3),
    each nuisance block only when enabled.
    """

    def __init__(
        self,
        obs: Observations,
        grid: KnotGrid,
        first: int,
        count: int,
        prior: MotionPrior,
        noise: NoiseModel,
        config: WeakPriorSettings,
        span_cache: dict | None = None,
    ):
        self.obs, self.grid, self.first, self.count = obs, grid, first, count
        self.prior, self.noise, self.config = prior, noise, config
        self._nuis: list[tuple[int, int, float]] | None = None  # _nuisances(), computed once
        F = len(obs)
        self.F = F
        # what depends only on the window (observations and control span) is shared by the problems of one
        # selection (a dozen motion models on the same rows): the last few windows, newest first, under one key
        # (a selection spread over frames alternates with the sliding window's own, a new one every frame)
        recent = [] if span_cache is None else span_cache.setdefault(_WINDOWS, [])
        win = next((w for w in recent if w.obs is obs and w.key == (grid, first, count)), None)
        if win is None:
            win = _WindowConstants(obs, grid, first, count)
        recent[:] = [win, *(w for w in recent if w is not win)][:_WINDOWS_KEPT]
        self._win = win
        self.rows, self.B0, self.R_cn, self.f, self.t_ref, self.dt = (
            win.rows,
            win.B0,
            win.R_cn,
            win.f,
            win.t_ref,
            win.dt,
        )
        span = None if span_cache is None else span_cache.get((grid, first, count, prior))
        if span is None:
            span = _SpanPrior(grid, first, count, prior)
            if span_cache is not None:
                if len(span_cache) > 64:
                    span_cache.clear()
                span_cache[(grid, first, count, prior)] = span
        self._span = span
        self.Bq1, self.Bq2, self.sq_h, self.sq_v = span.Bq1, span.Bq2, span.sq_h, span.sq_v
        self.G, self.P_acc, self.P_turn = span.G, span.P_acc, span.P_turn
        self.ref_idx, self.ref_w0, self.ref_w1, self.ref_w2 = win.ref_idx, win.ref_w0, win.ref_w1, win.ref_w2
        self.p_ref = win.p_ref
        self.sigma_a = config.ca_acceleration_sigma_mps2 if prior.jerk else config.acceleration_prior_sigma_mps2
        # parameter layout
        self.nc = 3 * count
        k = self.nc
        self.i_omega = k if prior.turn_rate_sigma_radps > 0 else None
        k += self.i_omega is not None
        self.i_phi = k if noise.attitude_bias_sigma_rad > 0 else None
        k += 3 * (self.i_phi is not None)
        self.i_beta = k if noise.camera_position_offset_sigma_m > 0 else None
        k += 3 * (self.i_beta is not None)
        self.i_gamma = k if noise.camera_position_drift_sigma_mps > 0 else None
        k += 3 * (self.i_gamma is not None)
        self.n_params = k
        self.n_rows = 2 * F + 3 * self.G + 9 + (self.n_params - self.nc)
        self.set_measurement_weights(None)
        self._J = self._constant_jacobian_rows()
        self.last_jacobian: np.ndarray | None = None
        #: the positions p(t_i) (F, 3) at the parameters of the last :meth:`evaluate` (its own product)
        self.last_positions = np.zeros((F, 3))
        self._los = np.zeros((3, F))  # and their lines of sight from the camera (the collapse check)
        #: calls of :meth:`evaluate` so far (the work measure of :meth:`solve_steps`)
        self.evaluations = 0
        self._prior_logdet: float | None = None  # prior_logdet() without a turn rate, computed once
        self._local_layout()

    # ------------------------------------------------------------------ helpers
    def set_measurement_weights(self, range_m) -> None:
        n = self.noise
        var = n.pixel_sigma_px**2 + (self.f * n.attitude_white_sigma_rad) ** 2
        if n.camera_position_white_sigma_m > 0:
            r = np.full(self.F, 100.0) if range_m is None else np.maximum(np.asarray(range_m, float), 1.0)
            var = var + (self.f * n.camera_position_white_sigma_m / r[:, None]) ** 2
        self.s = self.f / np.sqrt(var)  # (F, 2): normalised-coordinate residual -> standard units
        self._sT = np.ascontiguousarray(self.s.T)  # (the kernels' observation-last layout)

    def measurement_chi2(self, theta: np.ndarray) -> tuple[np.ndarray, bool]:
        """Each observation's squared normalised residual at ``theta`` (F,), its two image coordinates summed
        (the weights of :meth:`set_measurement_weights`), and whether every predicted direction is in front of
        the camera (:meth:`evaluate`'s flag).  Evaluates without a Jacobian: the linearisation
        :meth:`normal_matrix` reads is untouched."""
        r, valid = self.linearise(theta, jacobian=False)
        m = r[: 2 * self.F].reshape(self.F, 2)
        return np.einsum("fi,fi->f", m, m), bool(valid)

    def exclude_measurements(self, mask) -> None:
        """Leave the observations where ``mask`` (F,) is true out of the solve: weight zero, so they neither pull
        the solution nor add information.  (Not for a problem whose evidence is wanted: that counts every row.)"""
        s = self.s.copy()
        s[np.asarray(mask, dtype=bool)] = 0.0
        self.s = s
        self._sT = np.ascontiguousarray(s.T)

    def positions(self, theta: np.ndarray) -> np.ndarray:
        c = theta[: self.nc].reshape(self.count, 3)
        return einsum("fm,fmk->fk", self.rows.w0, c[self.rows.index])

    def velocities(self, theta: np.ndarray) -> np.ndarray:
        c = theta[: self.nc].reshape(self.count, 3)
        return np.einsum("fm,fmk->fk", self.rows.w1, c[self.rows.index])

    def _offset(self, theta: np.ndarray) -> np.ndarray:
        off = np.zeros((self.F, 3))
        if self.i_beta is not None:
            off += theta[self.i_beta : self.i_beta + 3]
        if self.i_gamma is not None:
            off += self.dt[:, None] * theta[self.i_gamma : self.i_gamma + 3]
        return off

    def theta_from_positions(self, p_ned_m: np.ndarray, omega: float = 0.0) -> np.ndarray:
        """Least-squares control points through per-observation positions (F, 3); nuisances zero."""
        c = fit_controls(self.B0, p_ned_m)
        theta = np.zeros(self.n_params)
        theta[: self.nc] = c.reshape(-1)
        if self.i_omega is not None:
            theta[self.i_omega] = omega
        return theta

    def theta_along_lines_of_sight(self, range_m: float) -> np.ndarray:
        """:meth:`theta_from_positions` of the positions at ``range_m`` along each observation's measured line
        of sight (``obs.bearings_ned()``), the fit computed once per window and range."""
        theta = np.zeros(self.n_params)
        theta[: self.nc] = self._win.controls_at_range(range_m).reshape(-1)
        return theta

    # ------------------------------------------------------------------ residuals and Jacobian
    def evaluate(self, theta: np.ndarray, jacobian: bool = True):
        """Residual vector r (n_rows,), Jacobian (n_rows, n_params) or None, and validity flag.

        Invalid (False) when any predicted direction is not in front of the camera.  The Jacobian is one buffer,
        overwritten by the next evaluation with a Jacobian.
        """
        r, valid = self.linearise(theta, jacobian)
        return r, (self._fill_jacobian() if jacobian else None), valid

    def linearise(self, theta: np.ndarray, jacobian: bool = True) -> tuple[np.ndarray, bool]:
        """The solver's evaluation: :meth:`evaluate` without the dense Jacobian.  Returns (r, valid); with
        ``jacobian`` it keeps the Jacobian's pieces that change with theta (the measurement rows' local columns of
        :meth:`_local_layout`, the turn rate's column), which :meth:`normal_matrix` and :meth:`gradient` read
        until the next linearisation with ``jacobian``.

        The arithmetic of :func:`_project`, the measurement rows in one compiled loop over the observations
        (:func:`~onboard.estimation.kernels.linearise_measurements`, on arrays laid out observation-last).
        """
        self.evaluations += 1
        F, G, cnt = self.F, self.G, self.count
        c = theta[: self.nc].reshape(cnt, 3)
        X, los, r = np.empty((3, F)), np.empty((3, F)), np.empty(self.n_rows)
        Rphi = _rodrigues(theta[self.i_phi : self.i_phi + 3]) if self.i_phi is not None else _NONE_3X3
        beta = theta[self.i_beta : self.i_beta + 3] if self.i_beta is not None else _NONE
        gamma = theta[self.i_gamma : self.i_gamma + 3] if self.i_gamma is not None else _NONE
        win = self._win
        valid = linearise_measurements(
            c, win.rows.index, win.rows.w0, win.p_cam_T, beta, gamma, self.dt, Rphi, win.R_T, win.xy_T, self._sT,
            bool(jacobian), X, los, r[: 2 * F], self._U,
        )  # fmt: skip
        self.last_positions, self._los = X.T, los
        # the prior rows: linear in theta (their rows of J, constant) but the motion prior's with a turn rate
        o = self._fixed_rows
        r[o:] = self._J[o:] @ theta - self._fixed_offset
        om = 0.0
        if self.i_omega is not None:
            om = float(theta[self.i_omega])
            rp = r[2 * F : 2 * F + 3 * G]
            turn_prior_rows(self.Bq1, self.Bq2, self.sq_h, self.sq_v, c, om, rp, self._j_omega, bool(jacobian))
        if jacobian:
            self._omega_lin = om
        return r, valid

    def _mean_range(self) -> float:
        """The mean distance of the positions of the last evaluation from the camera (the collapse check)."""
        los = self._los
        # the sum over F: what .mean() computes (one pairwise sum, then the division), without its wrapper
        return float(np.add.reduce(np.sqrt(einsum("if,if->f", los, los)))) / self.F

    def _fill_jacobian(self) -> np.ndarray:
        """The dense Jacobian of the last :meth:`linearise` with ``jacobian``, in its buffer (the rows that never
        change are there already)."""
        F, G = self.F, self.G
        J, U = self._J, self._U
        # the control-point block: 12 non-zeros per row at fixed places (the basis pattern)
        J.reshape(-1)[self._meas_flat] = self._w0_T[None, :, None, :] * U[:, None, :3, :]
        meas = J[: 2 * F].reshape(F, 2, self.n_params)
        for k, i0 in enumerate(self._nuisance_first):
            meas[:, :, i0 : i0 + 3] = U[:, 3 + 3 * k : 6 + 3 * k].transpose(2, 0, 1)
        if self.i_omega is not None:  # the prior rows depend on the turn rate (else: constant rows)
            o = 2 * F
            self._fill_prior_c_jacobian(J[o : o + 3 * G, : self.nc], self._omega_lin)
            J[o : o + 3 * G, self.i_omega] = self._j_omega
        return J

    def _local_layout(self) -> None:
        """The measurement rows' local Jacobian, from which :meth:`normal_matrix` builds ``J^T J``.

        Row ``(f, a)`` of the measurement block is ``u_fa = d r_fa / d w_f`` (3) times the basis weights
        ``w0[f, m]`` in the 3 columns of each of the four control points m of observation f's knot interval, and
        the navigation nuisances' local columns ``n_fa`` (phi: ``w_rot x m``, beta: ``u``, gamma: ``dt_f u``)
        in theirs.  So with ``U_f = [u_f | n_f]`` (2 rows) and ``P_f = u_f^T U_f`` (3 x (3 + nuisances)), the
        measurement rows' ``J^T J`` is, per knot interval s and its controls m, n:

        - control m, control n: ``sum_f w0[f, m] w0[f, n] P_f[:, :3]`` (the Kronecker structure of the rows);
        - control m, nuisances: ``sum_f w0[f, m] P_f[:, 3:]``;
        - nuisances, nuisances: ``sum_f n_f^T n_f`` over every observation;

        summed observation by observation in one compiled loop (:func:`~onboard.estimation.kernels.measurement_gram`,
        the upper triangle, mirrored).
        """
        F, win = self.F, self._win
        self._nuisance_first = tuple(i0 for i0 in (self.i_phi, self.i_beta, self.i_gamma) if i0 is not None)
        self._U = np.zeros((2, 3 + 3 * len(self._nuisance_first), F))
        self._j_omega = np.zeros(3 * self.G)
        self._w0_T = win.w0_T
        self._meas_flat = win.meas_flat(self.n_params)
        self._nuis_cols = np.array([i0 + k for i0 in self._nuisance_first for k in range(3)], dtype=np.int64)
        # the rows whose part of J^T J is fixed: every row after the measurements' (the motion prior's too
        # without a turn rate; with one, normal_matrix adds them at the turn rate of the evaluation)
        o = 2 * F + (3 * self.G if self.i_omega is not None else 0)
        self._fixed_rows = o
        self._H_fixed = self._J[o:].T @ self._J[o:]
        # r[o:] = J[o:] theta - offset: the weak prior's on the mean position is the only one not at zero
        self._fixed_offset = np.zeros(self.n_rows - o)
        w = 2 * F + 3 * self.G - o
        self._fixed_offset[w : w + 3] = self.p_ref / self.config.position_prior_sigma_m
        self._omega_lin = 0.0  # the turn rate of the last linearisation

    def normal_matrix(self) -> np.ndarray:
        """``J^T J`` (n_params, n_params) at the last evaluation with a Jacobian, from the Jacobian's structure.

        The dense product's matrix up to rounding (its sums run in another order), at a fraction of its cost:
        the measurement rows by knot interval (:meth:`_local_layout`), the motion prior's rows as a polynomial
        in the turn rate (:meth:`_SpanPrior.grams`; constant without one), the other prior rows constant.
        """
        n, win = self.n_params, self._win
        H = np.empty((n, n))
        measurement_gram(self._U, win.rows.index, win.rows.w0, self._nuis_cols, self._H_fixed, H)
        if self.i_omega is not None:
            A, B, C = self._span.grams()
            add_turn_prior_gram(
                H, A, B, C, self._omega_lin, self.Bq1, self.Bq2, self.sq_h, self.sq_v, self._j_omega, self.i_omega
            )
        return H

    def gradient(self, r: np.ndarray) -> np.ndarray:
        """``J^T r`` (n_params,) at the last evaluation with a Jacobian, r its residuals, from the Jacobian's
        structure (as :meth:`normal_matrix`)."""
        F, G, win = self.F, self.G, self._win
        g = np.empty(self.n_params)
        measurement_gradient(self._U, r, win.rows.index, win.rows.w0, self._nuis_cols, g)
        o = self._fixed_rows  # (the motion prior's rows among them without a turn rate)
        if self.i_omega is not None:
            rp = r[2 * F : 2 * F + 3 * G]
            add_turn_prior_transpose(self.Bq1, self.Bq2, self.sq_h, self.sq_v, rp, self._omega_lin, g)
            g[self.i_omega] = self._j_omega @ rp
        g += self._J[o:].T @ r[o:]
        return g

    def measurement_rows(self, theta: np.ndarray, t_s: float, xy_norm, f_px, p_cam_ned_m, R_ned_from_cam):
        """Residual (2,) and Jacobian (2, n_params) of one extra observation at ``t_s`` inside the span
        (the incremental update of the sliding window), weighted like the window's own rows."""
        rows = self.grid.basis(np.array([t_s]), self.first, self.count)
        c = theta[: self.nc].reshape(self.count, 3)
        off = np.zeros(3)
        if self.i_beta is not None:
            off += theta[self.i_beta : self.i_beta + 3]
        if self.i_gamma is not None:
            off += (t_s - self.t_ref) * theta[self.i_gamma : self.i_gamma + 3]
        w = rows.w0[0] @ c[rows.index[0]] - np.asarray(p_cam_ned_m, float) + off
        Rphi = _rodrigues(theta[self.i_phi : self.i_phi + 3]) if self.i_phi is not None else None
        w_rot = w if Rphi is None else Rphi @ w
        f = np.asarray(f_px, float).reshape(1, 2)
        n = self.noise
        var = n.pixel_sigma_px**2 + (f * n.attitude_white_sigma_rad) ** 2
        if n.camera_position_white_sigma_m > 0:
            var = var + (f * n.camera_position_white_sigma_m / max(float(np.linalg.norm(w)), 1.0)) ** 2
        s = f / np.sqrt(var)
        R_cn = np.asarray(R_ned_from_cam, float).T[None]
        res, M, valid = _project(w_rot[None], R_cn, np.asarray(xy_norm, float).reshape(1, 2), s, True)
        Jr = np.zeros((2, self.n_params))
        Mw = M[0] if Rphi is None else M[0] @ Rphi
        for m in range(4):
            k = rows.index[0, m]
            Jr[:, 3 * k : 3 * k + 3] = Mw * rows.w0[0, m]
        if self.i_phi is not None:
            Jr[:, self.i_phi : self.i_phi + 3] = cross3(w_rot[None, :], M[0])
        if self.i_beta is not None:
            Jr[:, self.i_beta : self.i_beta + 3] = Mw
        if self.i_gamma is not None:
            Jr[:, self.i_gamma : self.i_gamma + 3] = Mw * (t_s - self.t_ref)
        return res[0], Jr, valid

    def _constant_jacobian_rows(self) -> np.ndarray:
        """The Jacobian buffer with the rows that never change (weak and nuisance priors) filled in."""
        J = np.zeros((self.n_rows, self.n_params))
        o = 2 * self.F
        if self.i_omega is None:  # no turn rate: the motion prior's rows are constant too
            J[o : o + 3 * self.G, : self.nc] = self._prior_c_jacobian(0.0)
        o += 3 * self.G
        for k in range(3):
            J[o + k, 3 * self.ref_idx + k] = self.ref_w0 / self.config.position_prior_sigma_m
            J[o + 3 + k, 3 * self.ref_idx + k] = self.ref_w1 / self.config.velocity_prior_sigma_mps
            J[o + 6 + k, 3 * self.ref_idx + k] = self.ref_w2 / self.sigma_a
        o += 9
        for i0, n, sig in self._nuisances():
            J[o : o + n, i0 : i0 + n] = np.eye(n) / sig
            o += n
        return J

    def _prior_c_jacobian(self, omega: float) -> np.ndarray:
        """Jacobian of the (3G) prior rows w.r.t. the control points, for a given turn rate."""
        return self.P_acc + omega * self.P_turn

    def _fill_prior_c_jacobian(self, out: np.ndarray, omega: float) -> None:
        """:meth:`_prior_c_jacobian` written into ``out`` (a view of the Jacobian buffer), without temporaries;
        the same two roundings per entry (``omega * P_turn``, then the sum)."""
        np.multiply(self.P_turn, omega, out=out)
        out += self.P_acc

    def prior_logdet(self, theta: np.ndarray) -> float:
        """log det of the prior precision of the model's own parameters (controls, turn rate) at this turn rate."""
        if self.i_omega is None and self._prior_logdet is not None:  # no turn rate: one value per problem
            return self._prior_logdet
        om = theta[self.i_omega] if self.i_omega is not None else 0.0
        Jp = self._prior_c_jacobian(om)
        Jw = np.zeros((9, self.nc))
        for k in range(3):
            Jw[k, 3 * self.ref_idx + k] = self.ref_w0 / self.config.position_prior_sigma_m
            Jw[3 + k, 3 * self.ref_idx + k] = self.ref_w1 / self.config.velocity_prior_sigma_mps
            Jw[6 + k, 3 * self.ref_idx + k] = self.ref_w2 / self.sigma_a
        A = np.vstack([Jp, Jw])
        d = np.sqrt(np.einsum("ij,ij->j", A, A))
        R = qr_r(A / d)
        logdet = 2 * np.sum(np.log(np.abs(np.diag(R)))) + 2 * np.sum(np.log(d))
        if self.i_omega is not None:
            logdet += -2 * math.log(self.prior.turn_rate_sigma_radps)
        else:
            self._prior_logdet = float(logdet)
        return float(logdet)

    def _nuisances(self) -> list[tuple[int, int, float]]:
        """(first column, size, prior sigma) of each nuisance block: turn rate, attitude bias, position
        offset, position drift (those the noise model has)."""
        if self._nuis is not None:
            return self._nuis
        out = []
        if self.i_omega is not None:
            out.append((self.i_omega, 1, self.prior.turn_rate_sigma_radps))
        if self.i_phi is not None:
            out.append((self.i_phi, 3, self.noise.attitude_bias_sigma_rad))
        if self.i_beta is not None:
            out.append((self.i_beta, 3, self.noise.camera_position_offset_sigma_m))
        if self.i_gamma is not None:
            out.append((self.i_gamma, 3, self.noise.camera_position_drift_sigma_mps))
        self._nuis = out
        return out

    # ------------------------------------------------------------------ Levenberg-Marquardt
    def solve(self, theta0: np.ndarray, max_iterations: int, **options: Any) -> SolveResult:
        """Levenberg-Marquardt from theta0: :meth:`solve_steps` run to its end (``options`` its keyword arguments)."""
        return drain(self.solve_steps(theta0, max_iterations, **options))

    def solve_steps(
        self,
        theta0: np.ndarray,
        max_iterations: int,
        lam0: float = 0.0,
        cost_tol: float = 1e-4,
        want_factor: bool = True,
        min_range_m: float | None = None,
        dense_jacobian: bool = True,
    ) -> Generator[int, None, SolveResult]:
        """Levenberg-Marquardt from theta0 (More's column scaling), one iteration at a time: yields after each
        iteration the residual evaluations it made (its work: each costs about one normal-equation solve
        more), returns the :class:`SolveResult`.

        Stops when an accepted step lowers the cost (1/2 chi^2) by less than ``cost_tol``, when no
        damping finds a lower cost, or after ``max_iterations``.  Returns a :class:`SolveResult` whose
        factor is (square-root information R, scales) at theta, or None when ``want_factor`` is False.
        Either way ``self.last_jacobian`` is the Jacobian at the returned theta; with ``dense_jacobian`` False
        it is not formed (None), and the linearisation at theta is left for :meth:`normal_factor`.
        With ``min_range_m``, a step that takes the mean range below it ends the solve as collapsed:
        cost inf and factor None, like a start that put the target behind the camera.
        """
        theta = theta0.copy()
        evaluations = self.evaluations
        r, valid = self.linearise(theta, True)
        if not valid:
            return SolveResult(theta, math.inf, 0, False, None)
        cost = 0.5 * float(r @ r)
        lam = lam0
        converged = False
        it = 0
        eye = None
        # linearise() keeps one linearisation (the Jacobian's pieces) in place: current says whether it is
        # still theta's; the dense Jacobian is filled once, at the end
        current = True
        gn_taken = True  # was the last Gauss-Newton step accepted (then the next one likely is too)
        for it in range(1, max_iterations + 1):
            Hs = self.normal_matrix()  # new arrays: scaled in place
            g = self.gradient(r)
            d = scale_normal_equations(Hs, g)
            decrease = None
            # Gauss-Newton first (lam = 0): the range direction of a stiff prior has a tiny scaled
            # eigenvalue, and any fixed damping makes LM crawl along it
            for _ in range(12):
                try:
                    if lam == 0.0:
                        step = cho_solve_spd_lower(Hs, g)
                    else:
                        eye = np.eye(self.n_params) if eye is None else eye
                        step = cho_solve_spd_lower(Hs + lam * eye, g)
                except np.linalg.LinAlgError:
                    lam = max(lam * 10, 1e-9)
                    continue
                if lam == 0.0 and 0.5 * float(g @ step) < 0.1 * cost_tol:
                    # the Gauss-Newton model predicts less than the tolerance: at the minimum already
                    # (saves the damping ladder that would otherwise have to prove it)
                    break
                cand = theta - step / d
                # linearise with the residual (one call) when the step is likely to be taken: a damped one
                # nearly always is, an undamped one while the last undamped one was; a step refused costs the
                # Jacobian's share of the call, one taken then saves a second call
                with_jacobian = lam > 0.0 or gn_taken
                r2, ok = self.linearise(cand, with_jacobian)
                current = current and not with_jacobian
                c2 = 0.5 * float(r2 @ r2) if ok else math.inf
                if lam == 0.0:
                    gn_taken = c2 < cost
                if c2 < cost:
                    decrease = cost - c2
                    theta, cost = cand, c2
                    if min_range_m is not None and self._mean_range() < min_range_m:
                        self.last_jacobian = None
                        return SolveResult(theta, math.inf, it, False, None)
                    lam = lam / 10 if lam > 1e-9 else 0.0
                    if with_jacobian:
                        r = r2
                    else:
                        r, _ = self.linearise(theta, True)
                    current = True
                    break
                lam = max(lam * 10, 1e-6)
            yield self.evaluations - evaluations
            evaluations = self.evaluations
            if decrease is None:
                converged = True
                break
            if decrease < cost_tol:
                converged = True
                break
        if not current:
            r, _ = self.linearise(theta, True)
        if not dense_jacobian:
            self.last_jacobian = None
            return SolveResult(theta, cost, it, converged, self.normal_factor() if want_factor else None)
        J = self.last_jacobian = self._fill_jacobian()
        return SolveResult(theta, cost, it, converged, self.factor(J) if want_factor else None)

    def factor(self, J: np.ndarray):
        """Square-root information at the solution: upper-triangular R of the column-scaled J (QR),
        and the scales d, so that H = J^T J = D R^T R D.  QR, not Cholesky of J^T J: the prior and
        measurement scales span ~14 decades here and the normal equations lose precision where the scaled
        problem is ill-conditioned (:meth:`normal_factor` uses them where it is not)."""
        d = np.sqrt(np.einsum("ij,ij->j", J, J))
        d[d == 0] = 1.0
        R = qr_r(J / d)
        return R, d

    def normal_factor(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`factor` at the last linearisation with a Jacobian, from the normal equations the solver factorises
        anyway: the Cholesky factor of the column-scaled ``J^T J`` (:meth:`normal_matrix`), ``R^T R = H / (d d^T)``,
        instead of a QR of the dense Jacobian (a tenth of its cost).  The same R up to the rows' signs (which
        neither the covariance nor the log determinant sees) and rounding, but the normal matrix squares the
        Jacobian's condition number, and the log determinant's error grows with it: ~1e-9 nats where the factor's
        squared diagonal spans 1e4, ~1e-6 at 1e7, ~1e-3 at 3e10 (the stiffest CA models, which the QR keeps to
        ~1e-10).  So the QR of the dense Jacobian stays where that span, a lower bound of the scaled condition
        number, exceeds :data:`_NORMAL_FACTOR_MAX_SPAN`, or where the Cholesky factorisation fails."""
        H = self.normal_matrix()
        d = scale_normal_equations(H, _NONE)
        try:
            ch, _ = cho_factor_lower(H)
        except np.linalg.LinAlgError:
            return self.factor(self._fill_jacobian())
        diag = ch.diagonal()
        if diag.max() ** 2 > _NORMAL_FACTOR_MAX_SPAN * diag.min() ** 2:
            return self.factor(self._fill_jacobian())
        return np.tril(ch).T, d

    def covariance(self, fac) -> np.ndarray:
        R, d = fac
        Rinv = sla.solve_triangular(R, np.eye(R.shape[0]), check_finite=False)
        return (Rinv @ Rinv.T) / np.outer(d, d)

    def point_covariances(self, Sigma: np.ndarray, rows=None) -> np.ndarray:
        """Covariance (N, 3, 3) of p(t) at the basis rows (default: the observations)."""
        S = Sigma[: self.nc, : self.nc].reshape(self.count, 3, self.count, 3)
        if rows is None:
            # the observations of a knot interval share its 4 controls: the interval's 4 x 4 blocks of Sigma,
            # weighted by w0[m] w0[l] (the interval weights), one small product per interval
            win = self._win
            span = np.arange(self.count - 3)[:, None] + np.arange(4)
            blocks = S[span[:, :, None], :, span[:, None, :], :].reshape(-1, 16, 9)  # (intervals, 4 x 4, 3 x 3)
            per = np.matmul(win.interval_weights, blocks)  # (intervals, width, 9)
            return per.reshape(-1, 9)[win.interval_slot].reshape(-1, 3, 3)
        idx, w = rows.index, rows.w0
        blocks = S[idx[:, :, None], :, idx[:, None, :], :]  # (N, 4, 4, 3, 3)
        return np.einsum("nm,nl,nmlij->nij", w, w, blocks)

    @property
    def n_model_params(self) -> int:
        """Trajectory controls and turn rate: the parameters a motion model owns (the navigation
        nuisances phi, beta, gamma come after them)."""
        return self.nc + (self.i_omega is not None)

    def log_evidence(self, theta: np.ndarray, cost: float, fac) -> float:
        """Laplace log evidence of the motion model, conditional on the navigation nuisances at their
        MAP values (type-II maximum likelihood for them).

        Marginalising the nuisances too would charge their Occam factor only to models that can
        identify them: a model under which range is unobservable leaves the attitude bias free and so
        "wins" by several nats for knowing less.  Conditioning puts every model on the same footing.
        """
        k = self.n_model_params
        # the model's parameters lead the parameter vector, so the square-root information of their block
        # with the nuisances held fixed is the leading k x k block of the whole one (QR of the first k
        # columns of J: the same column scales, the same Householder steps)
        R, d = fac
        R, d = R[:k, :k], d[:k]
        logdet_H = 2 * np.sum(np.log(np.abs(np.diag(R)))) + 2 * np.sum(np.log(d))
        meas_norm = -np.sum(np.log(1.0 / self.s))  # -sum log sigma (normalised units)
        return float(-cost + 0.5 * self.prior_logdet(theta) - 0.5 * logdet_H + meas_norm)
