"""Bayesian Cramer-Rao bound of the reconstruction: the posterior covariance of the linearised problem
at the truth (Van Trees, Detection, Estimation and Modulation Theory I, 1968; Tichavsky et al.,
IEEE TSP 46(5), 1998 for the dynamic case).

The truth trajectory is projected onto the estimator's spline basis (least squares, exact for the
polynomial and circular reference paths to well under a millimetre), the turn rate and nuisances
are set to their true values where known (zero otherwise), and the information matrix is the
Gauss-Newton Hessian of the MAP cost with the same prior and noise model the estimator used.  The
bound per point is ``B(t) H^-1 B(t)^T``; its RMS is ``sqrt(mean trace)``.
"""

from __future__ import annotations

import numpy as np

from onboard.estimation.map_estimator import MapEstimator, MotionPrior
from onboard.estimation.observations import Observations

__all__ = ["bayesian_crb_rms_m"]


def bayesian_crb_rms_m(estimator: MapEstimator, obs: Observations, p_true_ned_m: np.ndarray, prior: MotionPrior,
                       turn_rate_radps: float = 0.0, grid=None) -> float:
    """RMS over the window of sqrt(trace) of the per-point Bayesian CRB, metres."""
    prob = estimator.problem(obs, prior, grid)
    theta = prob.theta_from_positions(np.asarray(p_true_ned_m, dtype=float), omega=turn_rate_radps)
    prob.set_measurement_weights(np.linalg.norm(p_true_ned_m - obs.p_cam_ned_m, axis=1))
    _, J, _ = prob.evaluate(theta)
    Sigma = prob.covariance(prob.factor(J))
    P = prob.point_covariances(Sigma)
    return float(np.sqrt(np.mean(np.einsum("fii->f", P))))
