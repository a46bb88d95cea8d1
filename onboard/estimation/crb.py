"""Bayesian Cramer-Rao bound of the reconstruction: the posterior covariance of the linearised problem
at the truth (Van Trees, Detection, Estimation and Modulation Theory I, 1968; Tichavsky et al.,
IEEE TSP 46(5), 1998 for the dynamic case).

The truth trajectory is projected onto the estimator's spline basis (least squares, exact for the
polynomial and circular reference paths to well under a millimetre), the turn rate and nuisances
are set to their true values where known (zero otherwise), and the information matrix is the
Gauss-Newton Hessian of the MAP cost with the same prior and noise model the estimator used.  The
bound per point is ``B(t) H^-1 B(t)^T``; its RMS is ``sqrt(mean trace)``.

:meth:`BayesianCrb.efficient_error_range_pct` turns the bound into the figure an accuracy table reports: an
efficient estimator's errors are Gaussian with the bound's joint covariance over the whole window,
so drawing from it gives the distribution of the per-run "mean error / range" -- the floor against
which a median over a handful of seeds has to be read (a 10-seed median of that skewed, scale-error
dominated figure scatters by a factor of ~3 between its 5th and 95th percentiles).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from onboard.estimation.map_estimator import MapEstimator, MotionPrior, WindowProblem, range_sigma_ratios
from onboard.estimation.observations import Observations
from onboard.estimation.sliding import SlidingConfig
from onboard.estimation.spline import KnotGrid
from onboard.estimation.windows import WindowedSolution, stitch

__all__ = [
    "BayesianCrb",
    "WindowedCrb",
    "bayesian_crb",
    "bayesian_crb_in_windows",
    "online_verdict_bound_ratios",
    "predicted_point_covariance",
]


@dataclass(frozen=True)
class BayesianCrb:
    """The bound of one window at the truth (:func:`bayesian_crb`): ``problem``, the window problem
    linearised there; ``covariance``, the bound on its full parameter covariance; ``p_true_ned_m`` and
    ``p_cam_ned_m`` (F, 3), the truth and the camera positions it was computed for.  Each figure below is
    read from this one factorisation: the callers that report several compute it once."""

    problem: WindowProblem
    covariance: np.ndarray
    p_true_ned_m: np.ndarray
    p_cam_ned_m: np.ndarray

    def point_covariances(self) -> np.ndarray:
        """(F, 3, 3): the bound per window point, ``B(t) H^-1 B(t)^T``."""
        return self.problem.point_covariances(self.covariance)

    def rms_m(self) -> float:
        """RMS over the window of sqrt(trace) of the per-point bound, metres."""
        return _rms_m(self.point_covariances())

    def range_sigma_ratio(self) -> float:
        """Median over the window of the bound's range sigma over the true range: the smallest
        ``range_sigma_ratio`` an estimator that knows the motion model could honestly report."""
        return _range_sigma_ratio(self.point_covariances(), self.p_true_ned_m, self.p_cam_ned_m)

    def efficient_error_range_pct(self, draws: int = 4000, rng: np.random.Generator | None = None) -> np.ndarray:
        """Per-run "mean over the window of ||e|| / range" (percent) of ``draws`` runs of an efficient estimator.

        Each draw is one window's error, Gaussian with the bound's joint covariance (the errors of
        neighbouring points are strongly correlated: they share the range scale).
        """
        prob = self.problem
        S = self.covariance[: prob.nc, : prob.nc]
        # eigen-decomposition rather than Cholesky: the bound can be numerically semi-definite
        lam, V = np.linalg.eigh(0.5 * (S + S.T))
        L = V * np.sqrt(np.maximum(lam, 0.0))
        rng = rng or np.random.default_rng(0)
        c = (rng.standard_normal((draws, S.shape[0])) @ L.T).reshape(draws, prob.count, 3)
        e = np.einsum("fm,nfmk->nfk", prob.rows.w0, c[:, prob.rows.index])
        rng_m = np.linalg.norm(self.p_true_ned_m - self.p_cam_ned_m, axis=1)
        return np.mean(np.linalg.norm(e, axis=2) / rng_m, axis=1) * 100.0


def _rms_m(P: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.einsum("fii->f", P))))


def _range_sigma_ratio(P: np.ndarray, p_true_ned_m: np.ndarray, p_cam_ned_m: np.ndarray) -> float:
    return float(np.median(range_sigma_ratios(P, p_true_ned_m, p_cam_ned_m)))


@dataclass(frozen=True)
class WindowedCrb:
    """The bound of a reconstruction solved in windows (:func:`bayesian_crb_in_windows`): each row's bound from
    the window its estimate was taken from.  The figures are :class:`BayesianCrb`'s."""

    covariances: np.ndarray  # (F, 3, 3)
    p_true_ned_m: np.ndarray
    p_cam_ned_m: np.ndarray

    def point_covariances(self) -> np.ndarray:
        return self.covariances

    def rms_m(self) -> float:
        return _rms_m(self.covariances)

    def range_sigma_ratio(self) -> float:
        return _range_sigma_ratio(self.covariances, self.p_true_ned_m, self.p_cam_ned_m)


def bayesian_crb_in_windows(
    estimator: MapEstimator, solution: WindowedSolution, obs: Observations, p_true_ned_m: np.ndarray
) -> BayesianCrb | WindowedCrb:
    """The bound of ``solution`` (:func:`~onboard.estimation.windows.solve_in_windows` of ``obs``) for
    ``estimator``'s noise model: each window's :func:`bayesian_crb` with the motion prior and turn rate that
    window's solution chose, each row's from the window that row's estimate came from.  One window: that
    window's :func:`bayesian_crb` itself."""
    p_true = np.asarray(p_true_ned_m, dtype=float)
    windows, results = solution.windows, solution.results
    if len(windows) == 1:
        return bayesian_crb(estimator, obs, p_true, results[0].prior, results[0].turn_rate_radps)
    parts = []
    for w, res in zip(windows, results):
        part = slice(w.first, w.stop)
        bound = bayesian_crb(estimator, obs.select(part), p_true[part], res.prior, res.turn_rate_radps)
        parts.append(bound.point_covariances())
    return WindowedCrb(stitch(windows, parts, len(obs)), p_true, np.asarray(obs.p_cam_ned_m, dtype=float))


def bayesian_crb(
    estimator: MapEstimator,
    obs: Observations,
    p_true_ned_m: np.ndarray,
    prior: MotionPrior,
    turn_rate_radps: float = 0.0,
    grid=None,
) -> BayesianCrb:
    """The bound of ``estimator``'s window problem on ``obs`` at the truth ``p_true_ned_m`` (F, 3), with
    ``prior`` and the turn rate ``turn_rate_radps`` (module docstring)."""
    p_true = np.asarray(p_true_ned_m, dtype=float)
    prob = estimator.problem(obs, prior, grid)
    theta = prob.theta_from_positions(p_true, omega=turn_rate_radps)
    prob.set_measurement_weights(np.linalg.norm(p_true - obs.p_cam_ned_m, axis=1))
    _, J, _ = prob.evaluate(theta)
    return BayesianCrb(prob, prob.covariance(prob.factor(J)), p_true, np.asarray(obs.p_cam_ned_m, dtype=float))


def predicted_point_covariance(
    estimator: MapEstimator,
    obs: Observations,
    p_true_ned_m: np.ndarray,
    prior: MotionPrior,
    t_eval_s: float,
    *,
    state_prior: tuple[float, np.ndarray] | None = None,
    information_scale: float = 1.0,
    grid=None,
) -> np.ndarray:
    """The bound's (3, 3) covariance of the target position at ``t_eval_s`` from bearings not yet taken.

    ``obs`` are predicted observations (a planned camera path looking at the predicted target
    ``p_true_ned_m``); the information matrix is the same Gauss-Newton Hessian as
    :func:`bayesian_crb` (same motion prior, noise model and nuisances), each measurement row
    weighted by ``sqrt(information_scale)`` (``information_scale`` bearings per predicted one: the
    estimator keeps more frames than the prediction needs to sample), plus, when ``state_prior =
    (t_s, I)`` is given, what is already known: a Gaussian prior on ``x = (p(t_s), v(t_s))`` with
    information ``I`` (6, 6), i.e. the rows ``S A`` with ``S^T S = I`` and ``A`` the spline's
    position and velocity basis at ``t_s`` (the information form of a Kalman prediction-update;
    Van Trees 1968, Tichavsky et al. 1998).  ``t_s`` and ``t_eval_s`` lie within ``obs``' span.
    """
    p_true = np.asarray(p_true_ned_m, dtype=float)
    # the window problem as the estimator builds it, minus the camera-track smoothing: a planned path has no
    # white noise to smooth
    grid = grid or KnotGrid(float(obs.t_s[0]), estimator.config.knot_spacing_s)
    first, count = grid.control_span(float(obs.t_s[0]), float(obs.t_s[-1]))
    prob = WindowProblem(obs, grid, first, count, prior, estimator.noise, estimator.config, estimator._span_cache)
    theta = prob.theta_from_positions(p_true)
    prob.set_measurement_weights(np.linalg.norm(p_true - obs.p_cam_ned_m, axis=1))
    prob.s = prob.s * np.sqrt(float(information_scale))
    _, J, _ = prob.evaluate(theta)
    if state_prior is not None:
        t_s, info = state_prior
        rows = grid.basis(np.array([float(t_s)]), first, count)
        A = np.zeros((6, prob.n_params))
        for m in range(4):
            k = int(rows.index[0, m])
            A[0:3, 3 * k : 3 * k + 3] = rows.w0[0, m] * np.eye(3)
            A[3:6, 3 * k : 3 * k + 3] = rows.w1[0, m] * np.eye(3)
        lam, V = np.linalg.eigh(0.5 * (info + info.T))  # S = sqrt(Lambda) V^T: no Cholesky of a near-singular I
        S = np.sqrt(np.maximum(lam, 0.0))[:, None] * V.T
        J = np.vstack([J, S @ A])
    # only p(t_eval) = B theta is wanted: B Sigma B^T = X^T X with R^T X = (B / d)^T, three right-hand sides
    # instead of the whole inverse
    R, d = prob.factor(J)
    rows = grid.basis(np.array([float(t_eval_s)]), first, count)
    B = np.zeros((3, prob.n_params))
    for m in range(4):
        k = int(rows.index[0, m])
        B[:, 3 * k : 3 * k + 3] = rows.w0[0, m] * np.eye(3)
    X = sla.solve_triangular(R, (B / d).T, trans="T", check_finite=False)
    return X.T @ X


def online_verdict_bound_ratios(
    estimator: MapEstimator,
    solution: WindowedSolution,
    obs: Observations,
    p_true_ned_m: np.ndarray,
    t_eval_s: np.ndarray,
    sliding: SlidingConfig,
) -> np.ndarray:
    """At each time of ``t_eval_s``: the figure the online estimator's verdict at that time compares with
    ``observability_max_sigma_range_ratio`` (once its reported sigmas are the Laplace ones times
    ``sigma_inflation``), at the Bayesian CRB: ``max(median, newest / edge_sigma_factor)`` of the bound's range
    sigma over the true range, the median over the rows the sliding window holds then, the newest at its newest
    row.  The window is ``sliding``'s: the rows of the ``window_s`` up to the newest row at or before that time,
    thinned as it keeps them (a row closer than ``min_spacing_s`` to the last kept one left out), nan while it holds
    fewer than ``min_frames`` rows or spans less than ``min_span_s`` (it publishes nothing then).  ``estimator``:
    the one the window solves with (its knot spacing); each time takes the motion prior and turn rate of the window
    of ``solution`` that took its newest row.  A local bound that knows the motion model: blind to a second
    explanation of the bearings far from the truth."""
    p_true = np.asarray(p_true_ned_m, dtype=float)
    t = np.asarray(obs.t_s, dtype=float)
    kept = []
    last = -math.inf
    for i, ti in enumerate(t):
        if ti - last >= sliding.min_spacing_s:
            kept.append(i)
            last = ti
    kept_idx = np.asarray(kept, dtype=np.int64)
    owner = np.empty(t.size, dtype=np.int64)
    for k, w in enumerate(solution.windows):
        owner[w.take_first : w.take_stop] = k
    out = np.full(np.shape(t_eval_s), math.nan)
    for j, te in enumerate(np.asarray(t_eval_s, dtype=float)):
        hi = int(np.searchsorted(t[kept_idx], te, side="right"))
        if hi == 0:
            continue
        newest = kept_idx[hi - 1]
        lo = int(np.searchsorted(t[kept_idx], t[newest] - sliding.window_s, side="left"))
        rows = kept_idx[lo:hi]
        if rows.size < sliding.min_frames or t[newest] - t[rows[0]] < sliding.min_span_s:
            continue
        res = solution.results[owner[newest]]
        bound = bayesian_crb(estimator, obs.select(rows), p_true[rows], res.prior, res.turn_rate_radps)
        ratio = range_sigma_ratios(bound.point_covariances(), bound.p_true_ned_m, bound.p_cam_ned_m)
        out[j] = max(float(np.median(ratio)), float(ratio[-1]) / sliding.edge_sigma_factor)
    return out
