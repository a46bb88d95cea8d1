r"""Error metrics of a reconstructed trajectory against the truth, and covariance consistency.

All inputs are local NED metres, one row per observation (N rows):

- paper relative error (PAPER.md section 5): ``mean_i ||X_hat_i - X_i|| / ||X_i - O||`` with ``O``
  the world origin of the paper metric (``origin_ned_m``; default the local NED origin, which for
  the reference scenarios is the ground point under the observer's start).  It depends on where
  the origin is, so it is reported but never used to compare geometries;
- range-normalised error: ``mean_i ||X_hat_i - X_i|| / ||X_i - C_i||`` (``C_i`` the camera centre),
  the figure REFERENCE_SCENARIOS.md quotes;
- RMSE ``sqrt(mean_i ||X_hat_i - X_i||^2)`` in metres, and per NED axis.

With a covariance ``P_i`` (N, 3, 3) of each estimated point:

- NEES ``e_i^T P_i^-1 e_i`` per point, its mean, and the two-sided 95 % interval of the mean NEES
  of N independent 3-dof chi-square variables, ``[chi2.ppf(0.025, 3N), chi2.ppf(0.975, 3N)] / N``
  (Bar-Shalom, Li & Kirubarajan, Estimation with Applications to Tracking and Navigation, 2001,
  section 5.4).  Points of one smoothed window are strongly correlated, so this interval is too
  narrow for them; read it as a guide, not a test;
- honesty check: the fraction of points with ``||e_i|| > 3 sqrt(trace P_i)``.  Whatever the error
  distribution, if ``E||e||^2 = trace P`` then at most 1/9 of the points can exceed that bound
  (Markov); for a Gaussian error with the reported covariance it is far rarer (isotropic:
  P(chi2_3 > 27) = 6e-6).  A non-negligible fraction means the reported covariance is
  overconfident;
- per-axis fraction ``|e_k| > 3 sigma_k`` (Gaussian expectation 0.27 % per axis).

Covariances must be finite, symmetric and positive definite at every point (a reported zero or
negative variance is a bug in the estimator, not something to average over): anything else raises
:class:`onboard.core.errors.InputError` naming the point.  ``bayesian_crb`` is not here (the lead's).

This is the one scoring path: the closed-loop evaluation (``groundsim eval``), the estimator harness
(``bench.estimator``, ``groundsim.evaluation.estimator_eval``), the campaign's batch figure and the
demo all score through :func:`evaluate` (per-frame arrays) or :func:`score_frames` (a selection of
frames -> a JSON-ready dict with the per-cent figures the tables print).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy.special import gammaincinv

from onboard.core.errors import InputError

__all__ = ["ErrorReport", "evaluate", "nees_interval_95", "nees_per_point", "score_frames"]

#: relative asymmetry tolerated in a covariance before it is rejected as not symmetric
COV_SYMMETRY_RTOL = 1e-6


@dataclass(frozen=True)
class ErrorReport:
    """Errors of N estimated points (fractions, not per cent; metres).

    Covariance fields are None when no covariance was given.  ``error_norm_m`` (N,) and ``nees``
    (N,) keep the per-point values for plots.
    """

    frames: int
    paper_relative_error: float
    range_normalised_error: float
    rmse_m: float
    rmse_ned_m: tuple[float, float, float]
    mean_error_m: float
    max_error_m: float
    error_norm_m: np.ndarray
    mean_nees: float | None = None
    nees_interval_95: tuple[float, float] | None = None
    nees_consistent: bool | None = None
    outside_3sigma_trace_fraction: float | None = None
    outside_3sigma_axis_fraction: tuple[float, float, float] | None = None
    nees: np.ndarray | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.frames, int) or self.frames < 1:
            raise InputError(f"ErrorReport.frames must be an int >= 1, got {self.frames!r}")

    def summary(self) -> dict:
        """The scalar fields as a JSON-ready dict (per-point arrays left out, non-finite -> None)."""
        out = {}
        for k, v in asdict(self).items():
            if k in ("error_norm_m", "nees"):
                continue
            if isinstance(v, tuple):
                v = [_json_float(x) for x in v]
            elif isinstance(v, float):
                v = _json_float(v)
            out[k] = v
        return out


def _json_float(x):
    return float(x) if x is not None and math.isfinite(x) else None


def nees_per_point(e_ned_m, cov_ned_m2, singular: float = math.nan) -> np.ndarray:
    """``e_i' P_i^-1 e_i`` per row of errors (N, 3) and covariances (N, 3, 3); ``singular`` for a row whose
    covariance cannot be inverted (NaN: left out of a mean; inf: beyond any bound)."""
    e = np.asarray(e_ned_m, dtype=float).reshape(-1, 3)
    P = np.asarray(cov_ned_m2, dtype=float).reshape(-1, 3, 3)
    try:
        return np.einsum("fi,fi->f", e, np.linalg.solve(P, e[:, :, None])[:, :, 0])
    except np.linalg.LinAlgError:  # one singular row fails the whole stack: row by row
        out = np.full(len(e), singular)
        for i in range(len(e)):
            with contextlib.suppress(np.linalg.LinAlgError):
                out[i] = float(e[i] @ np.linalg.solve(P[i], e[i]))
        return out


def nees_interval_95(frames: int, dof: int = 3) -> tuple[float, float]:
    """Two-sided 95 % interval of the mean of ``frames`` independent chi-square(dof) variables."""
    if frames < 1 or dof < 1:
        raise InputError(f"nees_interval_95: frames and dof must be >= 1, got {frames}, {dof}")
    n = frames * dof
    # chi2.ppf(p, n) = 2 gammaincinv(n / 2, p)
    return float(2.0 * gammaincinv(n / 2, 0.025) / frames), float(2.0 * gammaincinv(n / 2, 0.975) / frames)


def _points(name: str, a, n: int | None = None) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=float)
    except (TypeError, ValueError) as e:
        raise InputError(f"evaluate: {name} must be numbers, shape (N, 3): {e}") from None
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] < 1:
        raise InputError(f"evaluate: {name} must have shape (N, 3) with N >= 1, got {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise InputError(f"evaluate: {name} has {arr.shape[0]} rows, truth_p_ned_m has {n}")
    bad = ~np.all(np.isfinite(arr), axis=1)
    if np.any(bad):
        raise InputError(f"evaluate: {name} row {int(np.argmax(bad))} is not finite")
    return arr


def _check_cov(cov, n: int) -> np.ndarray:
    try:
        P = np.asarray(cov, dtype=float)
    except (TypeError, ValueError) as e:
        raise InputError(f"evaluate: cov must be numbers, shape (N, 3, 3): {e}") from None
    if P.shape != (n, 3, 3):
        raise InputError(f"evaluate: cov must have shape ({n}, 3, 3), got {P.shape}")
    bad = ~np.all(np.isfinite(P.reshape(n, 9)), axis=1)
    if np.any(bad):
        raise InputError(f"evaluate: cov[{int(np.argmax(bad))}] is not finite")
    asym = np.max(np.abs(P - np.transpose(P, (0, 2, 1))), axis=(1, 2))
    scale = np.max(np.abs(P), axis=(1, 2))
    bad = asym > COV_SYMMETRY_RTOL * np.maximum(scale, 1e-300)
    if np.any(bad):
        raise InputError(f"evaluate: cov[{int(np.argmax(bad))}] is not symmetric")
    P = 0.5 * (P + np.transpose(P, (0, 2, 1)))
    lam_min = np.linalg.eigvalsh(P)[:, 0]
    bad = lam_min <= 0.0
    if np.any(bad):
        i = int(np.argmax(bad))
        raise InputError(f"evaluate: cov[{i}] is not positive definite (smallest eigenvalue {lam_min[i]:.3g} m^2)")
    return P


def evaluate(truth_p_ned_m, est_p_ned_m, cam_p_ned_m, cov=None, origin_ned_m=(0.0, 0.0, 0.0)) -> ErrorReport:
    """Errors of ``est_p_ned_m`` against ``truth_p_ned_m`` (both (N, 3)) seen from cameras at
    ``cam_p_ned_m`` (N, 3); ``cov`` (N, 3, 3) the estimate's covariance or None; ``origin_ned_m``
    the world origin of the paper metric.  Pure; raises InputError on malformed input."""
    X = _points("truth_p_ned_m", truth_p_ned_m)
    n = X.shape[0]
    Xh = _points("est_p_ned_m", est_p_ned_m, n)
    C = _points("cam_p_ned_m", cam_p_ned_m, n)
    origin = _points("origin_ned_m", np.atleast_2d(np.asarray(origin_ned_m, dtype=object)), 1)[0]
    e = Xh - X
    en = np.linalg.norm(e, axis=1)
    d_origin = np.linalg.norm(X - origin, axis=1)
    rng = np.linalg.norm(X - C, axis=1)
    if np.any(d_origin == 0.0):
        raise InputError(
            f"evaluate: truth row {int(np.argmax(d_origin == 0.0))} is at the origin; the paper's relative error is undefined"
        )
    if np.any(rng == 0.0):
        raise InputError(f"evaluate: truth row {int(np.argmax(rng == 0.0))} coincides with the camera; range is zero")
    kw = {}
    if cov is not None:
        P = _check_cov(cov, n)
        nees = np.einsum("fi,fi->f", e, np.linalg.solve(P, e[:, :, None])[:, :, 0])
        lo, hi = nees_interval_95(n)
        mean_nees = float(np.mean(nees))
        trace = np.einsum("fii->f", P)
        sig = np.sqrt(np.einsum("fii->fi", P))
        kw = dict(
            mean_nees=mean_nees,
            nees_interval_95=(lo, hi),
            nees_consistent=bool(lo <= mean_nees <= hi),
            outside_3sigma_trace_fraction=float(np.mean(en > 3.0 * np.sqrt(trace))),
            outside_3sigma_axis_fraction=tuple(float(f) for f in np.mean(np.abs(e) > 3.0 * sig, axis=0)),
            nees=nees,
        )
    rmse_n, rmse_e, rmse_d = (float(v) for v in np.sqrt(np.mean(e**2, axis=0)))
    return ErrorReport(
        frames=n,
        paper_relative_error=float(np.mean(en / d_origin)),
        range_normalised_error=float(np.mean(en / rng)),
        rmse_m=float(np.sqrt(np.mean(en**2))),
        rmse_ned_m=(rmse_n, rmse_e, rmse_d),
        mean_error_m=float(np.mean(en)),
        max_error_m=float(np.max(en)),
        error_norm_m=en,
        **kw,
    )


def score_frames(truth_p_ned_m, est_p_ned_m, cam_p_ned_m, cov, selected) -> dict | None:
    """:func:`evaluate` on the rows where ``selected`` (N,) is true, as a JSON-ready dict: the fields of
    :meth:`ErrorReport.summary` plus ``err_range_pct`` and ``err_paper_pct`` (per cent).  None when no
    row is selected.  ``cov`` (N, 3, 3) or None; a covariance :func:`evaluate` refuses (not finite,
    not symmetric, not positive definite) is reported under ``note`` and the errors are scored without
    it -- a bad covariance is shown, not hidden, and does not lose the error figures."""
    idx = np.flatnonzero(np.asarray(selected, dtype=bool))
    if idx.size == 0:
        return None
    truth, est, cam = (np.asarray(a, dtype=float)[idx] for a in (truth_p_ned_m, est_p_ned_m, cam_p_ned_m))
    note = None
    try:
        rep = evaluate(truth, est, cam, None if cov is None else np.asarray(cov, dtype=float)[idx])
    except InputError as exc:
        if cov is None:
            raise
        note = f"covariance not scored: {exc}"
        rep = evaluate(truth, est, cam, None)
    d = rep.summary()
    d["err_range_pct"] = 100.0 * rep.range_normalised_error
    d["err_paper_pct"] = 100.0 * rep.paper_relative_error
    if note:
        d["note"] = note
    return d
