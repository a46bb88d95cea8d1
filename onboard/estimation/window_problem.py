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
for a 10 s window); the covariance and the evidence come from a QR square-root factor, which stays
sound where the prior and the data span ~14 decades.  A step that takes the mean range below
``min_range_m`` ends the solve as collapsed (the trajectory shrunk onto the camera track, where the cost
keeps falling).  The Laplace log evidence (MacKay 1992) is conditional on the navigation nuisances at
their MAP values (:meth:`WindowProblem.log_evidence` says why).
"""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass
from typing import Protocol, TypeVar

import numpy as np
import scipy.linalg as sla

from onboard.core.schema import NonNegativeFloat, PositiveFloat, config_dataclass
from onboard.estimation.fastmath import cho_factor_lower, cho_solve_lower, cross3, qr_r
from onboard.estimation.observations import Observations
from onboard.estimation.spline import KnotGrid, fit_controls, gauss_legendre_3

__all__ = ["NoiseModel", "MotionPrior", "WeakPriorSettings", "WindowProblem", "SolveResult", "drain"]

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


_EYE3 = np.eye(3)
_EYE3.flags.writeable = False


def _rodrigues(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix Exp(phi) of one rotation vector (Rodrigues' formula; frames.rotmat_from_rotvec, unbatched)."""
    a = math.sqrt(float(phi @ phi))
    x, y, z = phi.tolist()
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    if a < 1e-9:
        return _EYE3 + K
    return _EYE3 + (math.sin(a) / a) * K + ((1 - math.cos(a)) / (a * a)) * (K @ K)


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
        self.rows = grid.basis(obs.t_s, first, count)
        self.B0 = np.zeros((F, count))  # (F, count) dense basis of p(t_i)
        np.put_along_axis(self.B0, self.rows.index, self.rows.w0, axis=1)
        self.R_cn = np.transpose(obs.R_ned_from_cam, (0, 2, 1))
        self.f = np.stack([obs.fx_px, obs.fy_px], axis=1)
        self.t_ref = 0.5 * (obs.t_s[0] + obs.t_s[-1])
        self.dt = obs.t_s - self.t_ref
        span = None if span_cache is None else span_cache.get((grid, first, count, prior))
        if span is None:
            span = _SpanPrior(grid, first, count, prior)
            if span_cache is not None:
                if len(span_cache) > 64:
                    span_cache.clear()
                span_cache[(grid, first, count, prior)] = span
        self.Bq1, self.Bq2, self.sq_h, self.sq_v = span.Bq1, span.Bq2, span.sq_h, span.sq_v
        self.G, self.P_acc, self.P_turn = span.G, span.P_acc, span.P_turn
        ref = grid.basis(np.array([self.t_ref]), first, count)
        self.ref_idx, self.ref_w0, self.ref_w1, self.ref_w2 = ref.index[0], ref.w0[0], ref.w1[0], ref.w2[0]
        self.p_ref = obs.p_cam_ned_m.mean(axis=0)
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
        #: the positions p(t_i) (F, 3) at the parameters of the last :meth:`evaluate` (its own product, ready
        #: for the collapse check of :meth:`solve_steps`)
        self.last_positions = np.zeros((F, 3))
        #: calls of :meth:`evaluate` so far (the work measure of :meth:`solve_steps`)
        self.evaluations = 0
        self._prior_logdet: float | None = None  # prior_logdet() without a turn rate, computed once
        # flat positions in J of the control-point block, as (F, 4 controls, 2 rows x 3 axes): the
        # layout of w0[f, m] * Mw[f, a, k] with the shortest broadcast (see evaluate)
        rows_fi = np.arange(2 * F).reshape(F, 2)
        self._meas_flat = (
            rows_fi[:, None, :, None] * self.n_params
            + 3 * self.rows.index[:, :, None, None]
            + np.arange(3)[None, None, None, :]
        ).reshape(F, 4, 6)

    # ------------------------------------------------------------------ helpers
    def set_measurement_weights(self, range_m) -> None:
        n = self.noise
        var = n.pixel_sigma_px**2 + (self.f * n.attitude_white_sigma_rad) ** 2
        if n.camera_position_white_sigma_m > 0:
            r = np.full(self.F, 100.0) if range_m is None else np.maximum(np.asarray(range_m, float), 1.0)
            var = var + (self.f * n.camera_position_white_sigma_m / r[:, None]) ** 2
        self.s = self.f / np.sqrt(var)  # (F, 2): normalised-coordinate residual -> standard units

    def positions(self, theta: np.ndarray) -> np.ndarray:
        c = theta[: self.nc].reshape(self.count, 3)
        return np.einsum("fm,fmk->fk", self.rows.w0, c[self.rows.index])

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

    # ------------------------------------------------------------------ residuals and Jacobian
    def evaluate(self, theta: np.ndarray, jacobian: bool = True):
        """Residual vector r (n_rows,), Jacobian (n_rows, n_params) or None, and validity flag.

        Invalid (False) when any predicted direction is not in front of the camera.
        """
        self.evaluations += 1
        F, G, cnt = self.F, self.G, self.count
        c = theta[: self.nc].reshape(cnt, 3)
        X = self.B0 @ c
        self.last_positions = X
        w = X - self.obs.p_cam_ned_m
        if self.i_beta is not None or self.i_gamma is not None:
            w = w + self._offset(theta)
        if self.i_phi is not None:
            phi = theta[self.i_phi : self.i_phi + 3]
            Rphi = _rodrigues(phi)
            w_rot = w @ Rphi.T
        else:
            w_rot = w
        res, M, valid = _project(w_rot, self.R_cn, self.obs.xy_norm, self.s, jacobian)
        r = np.empty(self.n_rows)
        r[: 2 * F] = res.reshape(-1)
        # prior rows
        v = self.Bq1 @ c
        a = self.Bq2 @ c
        om = theta[self.i_omega] if self.i_omega is not None else 0.0
        o = 2 * F
        rp = r[o : o + 3 * G]
        rp[0::3] = self.sq_h * (a[:, 0] + om * v[:, 1])
        rp[1::3] = self.sq_h * (a[:, 1] - om * v[:, 0])
        rp[2::3] = self.sq_v * a[:, 2]
        o += 3 * G
        cr = c[self.ref_idx]
        r[o : o + 3] = (self.ref_w0 @ cr - self.p_ref) / self.config.position_prior_sigma_m
        r[o + 3 : o + 6] = (self.ref_w1 @ cr) / self.config.velocity_prior_sigma_mps
        r[o + 6 : o + 9] = (self.ref_w2 @ cr) / self.sigma_a
        o += 9
        for i0, n, sig in self._nuisances():
            r[o : o + n] = theta[i0 : i0 + n] / sig
            o += n
        if not jacobian:
            return r, None, valid

        J = self._J
        if self.i_phi is not None:
            Mw = M @ Rphi  # d r / d w
            # d r / d phi = -M [w_rot]x, whose rows are w_rot x m
            J[: 2 * F, self.i_phi : self.i_phi + 3] = cross3(w_rot[:, None, :], M).reshape(2 * F, 3)
        else:
            Mw = M
        # the control-point block: 12 non-zeros per row at fixed places (the basis pattern)
        J.reshape(-1)[self._meas_flat] = self.rows.w0[:, :, None] * Mw.reshape(F, 1, 6)
        if self.i_beta is not None:
            J[: 2 * F, self.i_beta : self.i_beta + 3] = Mw.reshape(2 * F, 3)
        if self.i_gamma is not None:
            J[: 2 * F, self.i_gamma : self.i_gamma + 3] = (Mw * self.dt[:, None, None]).reshape(2 * F, 3)
        o = 2 * F
        if self.i_omega is not None:  # the prior rows depend on the turn rate (else: constant rows)
            self._fill_prior_c_jacobian(J[o : o + 3 * G, : self.nc], om)
            J[o : o + 3 * G : 3, self.i_omega] = self.sq_h * v[:, 1]
            J[o + 1 : o + 3 * G : 3, self.i_omega] = -self.sq_h * v[:, 0]
        return r, J, valid

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
    def solve(
        self,
        theta0: np.ndarray,
        max_iterations: int,
        lam0: float = 0.0,
        cost_tol: float = 1e-4,
        want_factor: bool = True,
        min_range_m: float | None = None,
    ) -> SolveResult:
        """Levenberg-Marquardt from theta0: :meth:`solve_steps` run to its end."""
        return drain(self.solve_steps(theta0, max_iterations, lam0, cost_tol, want_factor, min_range_m))

    def solve_steps(
        self,
        theta0: np.ndarray,
        max_iterations: int,
        lam0: float = 0.0,
        cost_tol: float = 1e-4,
        want_factor: bool = True,
        min_range_m: float | None = None,
    ) -> Generator[int, None, SolveResult]:
        """Levenberg-Marquardt from theta0 (More's column scaling), one iteration at a time: yields after each
        iteration the residual evaluations it made (its work: each costs about one normal-equation solve
        more), returns the :class:`SolveResult`.

        Stops when an accepted step lowers the cost (1/2 chi^2) by less than ``cost_tol``, when no
        damping finds a lower cost, or after ``max_iterations``.  Returns a :class:`SolveResult` whose
        factor is (square-root information R, scales) at theta, or None when ``want_factor`` is False.
        Either way ``self.last_jacobian`` is the Jacobian at the returned theta.
        With ``min_range_m``, a step that takes the mean range below it ends the solve as collapsed:
        cost inf and factor None, like a start that put the target behind the camera.
        """
        theta = theta0.copy()
        evaluations = self.evaluations
        r, J, valid = self.evaluate(theta)
        if not valid:
            return SolveResult(theta, math.inf, 0, False, None)
        cost = 0.5 * float(r @ r)
        lam = lam0
        converged = False
        it = 0
        eye = None
        # evaluate() fills one Jacobian buffer in place: J_current says whether it still holds theta's
        J_current = True
        gn_taken = True  # was the last Gauss-Newton step accepted (then the next one likely is too)
        for it in range(1, max_iterations + 1):
            H = J.T @ J
            d = np.sqrt(H.diagonal())
            d[d == 0] = 1.0
            Hs = H / (d[:, None] * d[None, :])
            g = (J.T @ r) / d
            decrease = None
            # Gauss-Newton first (lam = 0): the range direction of a stiff prior has a tiny scaled
            # eigenvalue, and any fixed damping makes LM crawl along it
            for _ in range(12):
                try:
                    if lam == 0.0:
                        ch, _ = cho_factor_lower(Hs)
                    else:
                        eye = np.eye(self.n_params) if eye is None else eye
                        ch, _ = cho_factor_lower(Hs + lam * eye)
                except np.linalg.LinAlgError:
                    lam = max(lam * 10, 1e-9)
                    continue
                step = cho_solve_lower(ch, g)
                if lam == 0.0 and 0.5 * float(g @ step) < 0.1 * cost_tol:
                    # the Gauss-Newton model predicts less than the tolerance: at the minimum already
                    # (saves the damping ladder that would otherwise have to prove it)
                    break
                cand = theta - step / d
                # evaluate the Jacobian with the residual (one call) when the step is likely to be taken: a
                # damped one nearly always is, an undamped one while the last undamped one was; a step
                # refused costs the Jacobian's share of the call, one taken then saves a second call
                r2, J2, ok = self.evaluate(cand, jacobian=lam > 0.0 or gn_taken)
                J_current = J2 is None and J_current
                c2 = 0.5 * float(r2 @ r2) if ok else math.inf
                if lam == 0.0:
                    gn_taken = c2 < cost
                if c2 < cost:
                    decrease = cost - c2
                    theta, cost = cand, c2
                    if (
                        min_range_m is not None
                        and float(np.mean(np.linalg.norm(self.last_positions - self.obs.p_cam_ned_m, axis=1)))
                        < min_range_m
                    ):
                        self.last_jacobian = None
                        return SolveResult(theta, math.inf, it, False, None)
                    lam = lam / 10 if lam > 1e-9 else 0.0
                    if J2 is not None:
                        r, J, J_current = r2, J2, True
                    else:
                        r, J, _ = self.evaluate(theta)
                        J_current = True
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
        if not J_current:
            r, J, _ = self.evaluate(theta)
        self.last_jacobian = J
        return SolveResult(theta, cost, it, converged, self.factor(J) if want_factor else None)

    def factor(self, J: np.ndarray):
        """Square-root information at the solution: upper-triangular R of the column-scaled J (QR),
        and the scales d, so that H = J^T J = D R^T R D.  QR, not Cholesky of J^T J: the prior and
        measurement scales span ~14 decades here and the normal equations lose definiteness."""
        d = np.sqrt(np.einsum("ij,ij->j", J, J))
        d[d == 0] = 1.0
        R = qr_r(J / d)
        return R, d

    def covariance(self, fac) -> np.ndarray:
        R, d = fac
        Rinv = sla.solve_triangular(R, np.eye(R.shape[0]), check_finite=False)
        return (Rinv @ Rinv.T) / np.outer(d, d)

    def point_covariances(self, Sigma: np.ndarray, rows=None) -> np.ndarray:
        """Covariance (N, 3, 3) of p(t) at the basis rows (default: the observations)."""
        rows = self.rows if rows is None else rows
        S = Sigma[: self.nc, : self.nc].reshape(self.count, 3, self.count, 3)
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
