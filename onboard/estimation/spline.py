"""Uniform cubic B-splines on a global knot grid: the continuous-time trajectory representation.

A trajectory is ``p(t) = sum_k c_k B_k(t)`` with control points ``c_k`` (metres, NED) on knots
``t_origin + k * spacing``.  Segment ``j`` covers ``[t_origin + j h, t_origin + (j+1) h)`` and
uses control points ``j .. j+3``; with ``u = (t - t_origin)/h - j`` the weights are the uniform
cubic B-spline blending functions (de Boor; Qin, "General matrix representations for B-splines",
1998):  B0 = (1-u)^3/6,  B1 = (3u^3 - 6u^2 + 4)/6,  B2 = (-3u^3 + 3u^2 + 3u + 1)/6,  B3 = u^3/6.

The grid is global (anchored once), so a sliding window keeps its control points as it moves:
old points drop off the front, new ones are appended (Furgale et al., "Continuous-time batch
estimation using temporal basis functions", ICRA 2012).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["KnotGrid", "BasisRows", "gauss_legendre_3"]

# uniform cubic B-spline blending: weights = (1, u, u^2, u^3) @ _M0, and its derivatives in u
_M0 = np.array([[1.0, 4.0, 1.0, 0.0], [-3.0, 0.0, 3.0, 0.0], [3.0, -6.0, 3.0, 0.0], [-1.0, 3.0, -3.0, 1.0]]) / 6.0
_M1 = np.array([[-3.0, 0.0, 3.0, 0.0], [6.0, -12.0, 6.0, 0.0], [-3.0, 9.0, -9.0, 3.0]]) / 6.0
_M2 = np.array([[6.0, -12.0, 6.0, 0.0], [-6.0, 18.0, -18.0, 6.0]]) / 6.0


@dataclass(frozen=True)
class BasisRows:
    """Per-time rows of the basis: local control indices (N, 4) and weights for p, p', p''."""

    index: np.ndarray
    w0: np.ndarray
    w1: np.ndarray
    w2: np.ndarray


@dataclass(frozen=True)
class KnotGrid:
    """A global uniform knot grid: ``t_origin_s`` and ``spacing_s``."""

    t_origin_s: float
    spacing_s: float

    def segment(self, t_s) -> np.ndarray:
        return np.floor((np.asarray(t_s, dtype=float) - self.t_origin_s) / self.spacing_s).astype(np.int64)

    def control_span(self, t_first_s: float, t_last_s: float) -> tuple[int, int]:
        """(first global control index, count) covering times in [t_first_s, t_last_s]."""
        j0 = int(self.segment(t_first_s))
        j1 = int(self.segment(t_last_s))
        return j0, j1 - j0 + 4

    def basis(self, t_s, first_index: int, count: int) -> BasisRows:
        """Basis rows at times ``t_s`` for the controls ``first_index .. first_index + count - 1``."""
        t = np.asarray(t_s, dtype=float)
        h = self.spacing_s
        x = (t - self.t_origin_s) / h
        j = np.floor(x).astype(np.int64)
        # a time exactly on the window's last knot belongs to the last segment
        j = np.minimum(j, first_index + count - 4)
        u = (x - j)[..., None]
        # rows of the blending matrices times (1, u, u^2, u^3): one small matmul each, no stacking
        U = np.concatenate([np.ones_like(u), u, u * u, u * u * u], axis=-1)
        w0 = U @ _M0
        w1 = U[..., :3] @ _M1 / h
        w2 = U[..., :2] @ _M2 / (h * h)
        local = (j - first_index)[..., None] + np.arange(4)
        if np.any(local < 0) or np.any(local >= count):
            raise ValueError("time outside the spline's control span")
        return BasisRows(local, w0, w1, w2)

    def dense_basis(self, t_s, first_index: int, count: int, derivative: int = 0) -> np.ndarray:
        """Dense (N, count) basis matrix of p (derivative 0), p' (1) or p'' (2)."""
        rows = self.basis(t_s, first_index, count)
        w = (rows.w0, rows.w1, rows.w2)[derivative]
        B = np.zeros((rows.index.shape[0], count))
        np.put_along_axis(B, rows.index, w, axis=1)
        return B


def fit_controls(B: np.ndarray, values: np.ndarray, smoothing: float = 1e-3) -> np.ndarray:
    """Least-squares control points (count, k) of the spline whose basis matrix at the samples is ``B``
    (N, count), through ``values`` (N, k).  A whisper of second-difference smoothing keeps the controls
    of knot intervals without samples defined."""
    values = np.asarray(values, dtype=float)
    D = np.diff(np.eye(B.shape[1]), n=2, axis=0) * smoothing
    c, *_ = np.linalg.lstsq(
        np.vstack([B, D]), np.vstack([values, np.zeros((D.shape[0],) + values.shape[1:])]), rcond=None
    )
    return c


def gauss_legendre_3() -> tuple[np.ndarray, np.ndarray]:
    """Nodes on [0, 1] and weights (summing to 1) of 3-point Gauss-Legendre quadrature (exact to degree 5)."""
    x = np.array([-np.sqrt(3 / 5), 0.0, np.sqrt(3 / 5)])
    w = np.array([5 / 9, 8 / 9, 5 / 9])
    return (x + 1) / 2, w / 2
