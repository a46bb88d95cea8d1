r"""The source paper's "smooth constraint" closed form: the reconstruction baseline.

Method (PAPER.md section 4, after Dai Y. et al., 2012; Yao et al., Infrared and Laser Engineering
51(2):20210901, 2022).  For frame i with intrinsics ``K_i`` (that row's fx, fy, cx, cy), camera
centre ``C_i`` and ``R_i = R_cam_from_ned`` (the transpose of ``Observations.R_ned_from_cam``), the
3 x 4 projection matrix in pixel units is

    P_i = K_i [R_i | -R_i C_i].

Eliminating the projective depth from ``lambda_i [m_i, n_i, 1]^T = P_i [X_i; 1]`` leaves two linear
equations per frame, ``Q_i X_i = q_i`` with

    Q_i = [P_i,1 - m_i P_i,3 ; P_i,2 - n_i P_i,3]   (first three columns, 2 x 3)
    q_i = -(the same two rows' fourth column)       (2,)

where ``P_i,k`` is row k and ``(m_i, n_i)`` the observed pixel.  With X = [X_1; ..; X_F] (3F,),
Q = blockdiag(Q_i), q = [q_1; ..; q_F] and a finite-difference operator D over consecutive frames,

    minimise  ||Q X - q||^2 + delta ||D X||^2,    X = (Q^T Q + delta D^T D)^-1 Q^T q.

``D`` is the first- (``X_{i+1} - X_i``) or second-order (``X_{i+2} - 2 X_{i+1} + X_i``) difference
applied to each NED axis.  Like the paper, it counts frames and ignores the timestamps: uneven
sampling or dropped frames distort the smoothness term (a gap is penalised as one step).  The
pixel used is the ideal (undistorted) one, ``m_i = fx xy_norm_x + cx``; it equals ``u_px`` when the
pixels carry no lens distortion (the paper has none).

The normal matrix is symmetric positive definite and banded in the interleaved unknown order
(x_1, y_1, z_1, x_2, ...): ``Q^T Q`` is 3 x 3 block diagonal and ``D^T D`` couples frames up to
``order`` apart, so the lower bandwidth is ``3 * order``; it is solved by banded Cholesky
(``scipy.linalg.cholesky_banded``), O(F), and checked by one step of iterative refinement whose
gradient comes from the unsquared residuals.  Forming ``Q^T Q`` squares the condition number of
the stacked system ``[Q; sqrt(delta) D]``: at the paper's operating point (delta = 1, noisy
pixels) that is harmless (the Cholesky and QR answers agree to 1e-6 of range on the reference
scenarios), but near the collapse family (noise-free pixels, tiny delta, second-order D) it
exceeds 1/eps.  When the refinement correction exceeds ``PaperEstimator.refinement_tol``
(relative) or the factorisation fails, the stacked problem is solved by a dense complete
orthogonal factorisation instead (LAPACK gelsy: the minimum-norm, i.e. pseudo-inverse, solution;
O(F^3), ~0.1-0.3 s at F = 300), up to ``PaperEstimator.max_dense_frames``.

Note that with noise-free pixels the data term vanishes on every trajectory that lies on the
measured rays, so delta does not move the minimiser at all: the smoothness term alone picks the
point on each ray.  The truth is that minimiser only when ``D X = 0`` for the true path (a
constant-velocity target with second-order D); with first-order D the noise-free answer is
biased (39 % of range on P1).

No covariance: the cost is algebraic (pixel error times depth, plus an unweighted smoothness term
in metres) and has no noise model, so there is nothing to propagate; ``PaperResult.sigma_ned_m``
is NaN.

Known failure (REFERENCE_SCENARIOS.md): ``X_i = C_i`` zeroes every data row, so with pixel noise the
smoothness term pulls the estimate onto the camera track (tens of per cent of range with the
first-order D at delta = 1, and ~100 % with the second-order D).  It is kept as the paper's
baseline, not as an estimator to rely on.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from onboard.core.checks import is_positive_number
from onboard.core.errors import ConfigError
from onboard.estimation.map_estimator import EstimationError
from onboard.estimation.observations import Observations

__all__ = [
    "PaperConfig",
    "PaperResult",
    "PaperEstimator",
    "projection_matrices",
    "projection_rows",
    "difference_stencil",
    "difference_operator",
    "normal_matrix_banded",
    "banded_to_dense",
]

log = logging.getLogger(__name__)

_STENCILS = {1: np.array([-1.0, 1.0]), 2: np.array([1.0, -2.0, 1.0])}


@dataclass(frozen=True)
class PaperConfig:
    """``delta``: weight of the smoothness term (> 0, paper default 1); ``order``: 1 or 2 (D)."""

    delta: float = 1.0
    order: int = 1

    def __post_init__(self) -> None:
        if not is_positive_number(self.delta):
            raise ConfigError(f"PaperConfig.delta must be a finite number > 0, got {self.delta!r}")
        if isinstance(self.order, bool) or self.order not in _STENCILS:
            raise ConfigError(f"PaperConfig.order must be 1 or 2, got {self.order!r}")

    @property
    def min_frames(self) -> int:
        """Fewest frames for which D has a row (order + 1)."""
        return self.order + 1


@dataclass(frozen=True)
class PaperResult:
    """The closed-form estimate, one row per observation (F rows).

    ``p_ned_m`` (F, 3); ``cost = data_cost + delta * smooth_cost`` at the solution, with
    ``data_cost = ||Q X - q||^2`` (pixel-metre units) and ``smooth_cost = ||D X||^2`` (m^2);
    ``solver``: ``"banded_cholesky"``, ``"dense_qr"`` (normal equations inaccurate or singular) or
    ``"banded_cholesky_inaccurate"`` (too many frames for the dense fallback); ``refinement_rel``:
    relative size of the Cholesky solution's refinement step (inf when it failed); ``solve_ms``: wall time.
    There is no covariance (see the module docstring): ``cov_p_ned_m2`` is None.
    """

    t_s: np.ndarray
    p_ned_m: np.ndarray
    cost: float
    data_cost: float
    smooth_cost: float
    delta: float
    order: int
    solver: str
    refinement_rel: float
    solve_ms: float
    method: str = "paper"
    cov_p_ned_m2: None = None

    @property
    def sigma_ned_m(self) -> np.ndarray:
        """NaN (F, 3): the algebraic cost carries no uncertainty."""
        return np.full(self.p_ned_m.shape, np.nan)


def projection_matrices(obs: Observations) -> np.ndarray:
    """``P_i = K_i [R_cam_from_ned | -R_cam_from_ned C_i]`` in pixels, shape (F, 3, 4)."""
    R_cn = np.transpose(obs.R_ned_from_cam, (0, 2, 1))
    Rt = np.concatenate([R_cn, -np.einsum("fij,fj->fi", R_cn, obs.p_cam_ned_m)[:, :, None]], axis=2)
    # K @ Rt with K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], row by row
    P = np.empty_like(Rt)
    P[:, 0] = obs.fx_px[:, None] * Rt[:, 0] + obs.cx_px[:, None] * Rt[:, 2]
    P[:, 1] = obs.fy_px[:, None] * Rt[:, 1] + obs.cy_px[:, None] * Rt[:, 2]
    P[:, 2] = Rt[:, 2]
    return P


def projection_rows(obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """The paper's per-frame equations ``Q_i X_i = q_i``: ``Q`` (F, 2, 3) and ``q`` (F, 2).

    The observed pixel is the ideal one, ``(fx x + cx, fy y + cy)`` from ``obs.xy_norm`` (equal to
    ``uv_px`` without lens distortion).
    """
    P = projection_matrices(obs)
    m = obs.fx_px * obs.xy_norm[:, 0] + obs.cx_px
    n = obs.fy_px * obs.xy_norm[:, 1] + obs.cy_px
    rows = np.stack([P[:, 0, :] - m[:, None] * P[:, 2, :], P[:, 1, :] - n[:, None] * P[:, 2, :]], axis=1)
    return rows[:, :, :3], -rows[:, :, 3]


def difference_stencil(order: int) -> np.ndarray:
    """Coefficients of one row of D: order 1 -> (-1, 1), order 2 -> (1, -2, 1)."""
    if order not in _STENCILS:
        raise ConfigError(f"difference order must be 1 or 2, got {order!r}")
    return _STENCILS[order].copy()


def difference_operator(frame_count: int, order: int) -> np.ndarray:
    """Dense (F - order, F) finite-difference matrix over consecutive frames (per axis; for tests
    and small problems, the solver never forms it)."""
    c = difference_stencil(order)
    rows = max(frame_count - order, 0)
    D = np.zeros((rows, frame_count))
    for k, ck in enumerate(c):
        D[np.arange(rows), np.arange(rows) + k] = ck
    return D


def _dtd_bands(frame_count: int, order: int) -> np.ndarray:
    """Diagonals of D^T D: ``out[m, i] = (D^T D)[i + m, i]`` for m = 0..order, shape (order+1, F)."""
    c = difference_stencil(order)
    rows = frame_count - order
    out = np.zeros((order + 1, frame_count))
    if rows <= 0:
        return out
    r = np.arange(rows)
    for a in range(order + 1):
        for b in range(a, order + 1):
            # row r of D touches frames r + a and r + b; contributes c_a c_b to (r + b, r + a)
            np.add.at(out[b - a], r + a, c[a] * c[b])
    return out


def normal_matrix_banded(Q: np.ndarray, q: np.ndarray, delta: float, order: int) -> tuple[np.ndarray, np.ndarray]:
    """``Q^T Q + delta D^T D`` in ``solveh_banded`` lower form and ``Q^T q``, interleaved unknowns.

    Returns ``ab`` (3 order + 1, 3F) with ``ab[d, j] = A[j + d, j]``, and ``b`` (3F,).
    """
    F = Q.shape[0]
    ab = np.zeros((3 * order + 1, 3 * F))
    # lower triangle of the 3 x 3 blocks Q_i^T Q_i: ab[a - c, 3i + c] = sum_r Q[i, r, a] Q[i, r, c]
    for a in range(3):
        for c in range(a + 1):
            ab[a - c, c::3] = Q[:, 0, a] * Q[:, 0, c] + Q[:, 1, a] * Q[:, 1, c]
    bands = _dtd_bands(F, order)
    for m in range(order + 1):
        for k in range(3):
            ab[3 * m, k::3] += delta * bands[m]
    b = (Q[:, 0, :] * q[:, 0:1] + Q[:, 1, :] * q[:, 1:2]).reshape(-1)
    return ab, b


def banded_to_dense(ab: np.ndarray) -> np.ndarray:
    """The symmetric matrix of a lower-form band ``ab`` (for the singular fallback and tests)."""
    u, n = ab.shape[0] - 1, ab.shape[1]
    A = np.zeros((n, n))
    for d in range(u + 1):
        idx = np.arange(n - d)
        A[idx + d, idx] = ab[d, : n - d]
        A[idx, idx + d] = ab[d, : n - d]
    return A


def _residual_gradient(Q: np.ndarray, q: np.ndarray, delta: float, order: int, X: np.ndarray) -> np.ndarray:
    """Gradient ``Q^T (Q X - q) + delta D^T D X`` (F, 3), from the unsquared residuals."""
    F = X.shape[0]
    c = difference_stencil(order)
    r = np.einsum("fri,fi->fr", Q, X) - q
    DX = sum(ck * X[k : F - order + k] for k, ck in enumerate(c))
    g = np.einsum("fri,fr->fi", Q, r)
    for k, ck in enumerate(c):
        g[k : F - order + k] += delta * ck * DX
    return g


def _stacked_lstsq(Q: np.ndarray, q: np.ndarray, delta: float, order: int) -> np.ndarray:
    """Minimum-norm solution of ``[Q; sqrt(delta) D] X = [q; 0]`` by dense complete orthogonal
    factorisation (LAPACK gelsy): the pseudo-inverse form, condition number not squared."""
    F = Q.shape[0]
    A = np.zeros((2 * F + 3 * (F - order), 3 * F))
    rows = 2 * np.arange(F)
    for r in range(2):
        for k in range(3):
            A[rows + r, 3 * np.arange(F) + k] = Q[:, r, k]
    base = 2 * F + 3 * np.arange(F - order)
    for j, cj in enumerate(difference_stencil(order)):
        for k in range(3):
            A[base + k, 3 * (np.arange(F - order) + j) + k] = math.sqrt(delta) * cj
    rhs = np.concatenate([q.reshape(-1), np.zeros(3 * (F - order))])
    return sla.lstsq(A, rhs, lapack_driver="gelsy", check_finite=False)[0]


def _solve(Q, q, delta, order, refinement_tol, max_dense_frames) -> tuple[np.ndarray, str, float]:
    """Banded Cholesky of the normal equations, checked by one iterative-refinement step.

    The normal matrix squares the condition number of the stacked system; near the collapse
    family (noise-free data, tiny delta, second-order D) it exceeds 1/eps and the Cholesky
    solution is noise.  The refinement correction ``dx = -A^-1 g`` (g the gradient from the
    unsquared residuals) exposes that; above ``refinement_tol`` relative, the stacked problem is
    solved by QR instead (up to ``max_dense_frames``).  Returns ``(x (F, 3), solver, |dx|/|x|)``.
    """
    F = Q.shape[0]
    ab, b = normal_matrix_banded(Q, q, delta, order)
    try:
        cf = sla.cholesky_banded(ab, lower=True, check_finite=False)
        x = sla.cho_solve_banded((cf, True), b, check_finite=False).reshape(F, 3)
        dx = sla.cho_solve_banded(
            (cf, True), -_residual_gradient(Q, q, delta, order, x).reshape(-1), check_finite=False
        ).reshape(F, 3)
        rel = float(np.linalg.norm(dx) / max(float(np.linalg.norm(x)), 1e-300))
        if not math.isfinite(rel):
            raise np.linalg.LinAlgError("non-finite refinement")
        if rel <= refinement_tol:
            return x + dx, "banded_cholesky", rel
    except (np.linalg.LinAlgError, ValueError):
        x, rel = None, math.inf
    if F <= max_dense_frames:
        log.debug(
            "paper closed form: normal equations inaccurate (refinement %.3g); solving the stacked system by QR", rel
        )
        return _stacked_lstsq(Q, q, delta, order).reshape(F, 3), "dense_qr", rel
    if x is None:
        raise EstimationError(
            f"the paper's normal matrix is singular and {F} frames exceed the dense fallback "
            f"limit of {max_dense_frames}"
        )
    log.warning(
        "paper closed form: normal equations inaccurate (refinement %.3g relative) and %d frames exceed the "
        "dense fallback limit; keeping the refined Cholesky solution",
        rel,
        F,
    )
    return x + dx, "banded_cholesky_inaccurate", rel


class PaperEstimator:
    """``PaperEstimator(PaperConfig(delta, order)).solve(obs) -> PaperResult`` (pure, no state)."""

    #: relative size of one iterative-refinement correction above which the normal-equation
    #: solution is not trusted and the stacked least-squares problem is solved by QR instead
    refinement_tol = 1e-4
    #: the dense fallback costs O(F^3); above this many frames the refined Cholesky solution is kept
    max_dense_frames = 2000

    def __init__(self, config: PaperConfig | None = None):
        self.config = config or PaperConfig()

    def solve(self, obs: Observations) -> PaperResult:
        cfg = self.config
        F = len(obs)
        if F < cfg.min_frames:
            raise EstimationError(
                f"the paper's closed form with order-{cfg.order} D needs at least "
                f"{cfg.min_frames} observations, got {F}"
            )
        t0 = time.perf_counter()
        Q, q = projection_rows(obs)
        x, solver, refinement = _solve(Q, q, cfg.delta, cfg.order, self.refinement_tol, self.max_dense_frames)
        solve_ms = (time.perf_counter() - t0) * 1e3
        if not np.all(np.isfinite(x)):
            raise EstimationError("the paper's closed form gave a non-finite solution (degenerate geometry)")
        X = x.reshape(F, 3)
        data = float(np.sum((np.einsum("fri,fi->fr", Q, X) - q) ** 2))
        c = difference_stencil(cfg.order)
        DX = sum(ck * X[k : F - cfg.order + k] for k, ck in enumerate(c))
        smooth = float(np.sum(DX**2))
        return PaperResult(
            t_s=obs.t_s.copy(),
            p_ned_m=X,
            cost=data + cfg.delta * smooth,
            data_cost=data,
            smooth_cost=smooth,
            delta=float(cfg.delta),
            order=int(cfg.order),
            solver=solver,
            refinement_rel=refinement,
            solve_ms=solve_ms,
        )
