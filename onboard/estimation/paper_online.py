"""``paper``: the paper's closed form run online over a sliding window (a :class:`onboard.pipeline.plugins.TrajectoryEstimator`).

:class:`onboard.estimation.paper.PaperEstimator` solves ``min ||Q X - q||^2 + delta ||D X||^2`` over a
batch of observations (Yao et al. 2022, the paper's eqs.; docstring there).  This adapter keeps the
last ``window_s`` seconds of observations (at most one per ``min_spacing_s``, as the MAP window
does), re-solves on every :meth:`add` and reports the newest row: position ``X[-1]``, velocity the
least-squares slope of the rows in the last ``velocity_span_s``.

The closed form has no covariance.  The estimate reports an isotropic position covariance of
``(range_m * NO_COVARIANCE_SIGMA_RATIO)^2`` (1 sigma = the whole range: "unknown") and is never
``observable``: the daemon would not publish it, and the evaluation scores it on "all frames with an
estimate".  This says honestly what the algorithm knows; it is not a calibrated figure.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from onboard.core.errors import IrtrackError

__all__ = ["PaperWindowConfig", "PaperWindowEstimator", "NO_COVARIANCE_SIGMA_RATIO"]

NO_COVARIANCE_SIGMA_RATIO = 1.0  # reported 1-sigma position uncertainty / range (the closed form has none)


@dataclass(frozen=True)
class PaperWindowConfig:
    window_s: float = 20.0
    min_spacing_s: float = 0.06
    velocity_span_s: float = 1.0

    def __post_init__(self) -> None:
        if not (self.window_s > 0 and self.min_spacing_s >= 0 and self.velocity_span_s > 0):
            raise IrtrackError(f"PaperWindowConfig: invalid values {self}")


class PaperWindowEstimator:
    """The paper's closed form over a sliding window; see the module docstring."""

    def __init__(self, config: PaperWindowConfig | None = None, paper_config=None) -> None:
        from onboard.estimation.paper import PaperConfig, PaperEstimator

        self.config = config or PaperWindowConfig()
        self.solver = PaperEstimator(paper_config or PaperConfig())
        self.reset()

    @classmethod
    def from_config(cls, config) -> PaperWindowEstimator:
        est = getattr(config, "estimator", None)
        window_s = float(getattr(est, "window_s", PaperWindowConfig.window_s))
        return cls(PaperWindowConfig(window_s=window_s))

    def reset(self) -> None:
        self._rows: deque = deque()
        self._last = None

    def add(self, t_s: float, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam):
        from onboard.estimation.map_estimator import EstimationError
        from onboard.estimation.observations import Observations

        t = float(t_s)
        if self._rows and t - self._rows[-1][0] < self.config.min_spacing_s:
            return self.predict(t, p_cam_ned_m)
        self._rows.append(
            (
                t,
                np.asarray(uv_px, dtype=float),
                intrinsics,
                np.asarray(p_cam_ned_m, dtype=float),
                np.asarray(q_ned_from_cam, dtype=float),
            )
        )
        while self._rows and t - self._rows[0][0] > self.config.window_s:
            self._rows.popleft()
        if len(self._rows) < self.solver.config.min_frames:
            return None
        rows = list(self._rows)
        K = rows[-1][2]
        obs = Observations.from_intrinsics(
            np.array([r[0] for r in rows]),
            np.stack([r[1] for r in rows]),
            K,
            np.stack([r[3] for r in rows]),
            np.stack([r[4] for r in rows]),
        )
        try:
            res = self.solver.solve(obs)
        except EstimationError:
            return None
        ts, X = np.asarray(res.t_s), np.asarray(res.p_ned_m)
        sel = ts >= ts[-1] - self.config.velocity_span_s
        if sel.sum() >= 2:
            A = np.stack([np.ones(sel.sum()), ts[sel] - ts[-1]], axis=1)
            v = np.linalg.lstsq(A, X[sel], rcond=None)[0][1]
        else:
            v = np.zeros(3)
        self._last = self._estimate(t, X[-1], v, rows[-1][3], len(rows))
        return self._last

    def predict(self, t_s: float, p_cam_ned_m=None):
        if self._last is None:
            return None
        dt = float(t_s) - self._last.t_s
        cam = self._rows[-1][3] if p_cam_ned_m is None else np.asarray(p_cam_ned_m, dtype=float)
        return self._estimate(
            float(t_s),
            self._last.p_ned_m + dt * self._last.v_ned_mps,
            self._last.v_ned_mps,
            cam,
            self._last.window_frames,
        )

    @staticmethod
    def _estimate(t_s, p, v, p_cam, frames):
        from onboard.estimation.sliding import TrackEstimate

        rng = float(np.linalg.norm(np.asarray(p) - p_cam))
        s2 = (max(rng, 1e-3) * NO_COVARIANCE_SIGMA_RATIO) ** 2
        return TrackEstimate(
            t_s=t_s,
            p_ned_m=np.asarray(p, dtype=float),
            v_ned_mps=np.asarray(v, dtype=float),
            cov_p_ned_m2=s2 * np.eye(3),
            cov_v_ned_m2ps2=s2 * np.eye(3),
            observable=False,
            range_m=rng,
            range_sigma_ratio=NO_COVARIANCE_SIGMA_RATIO,
            window_frames=int(frames),
            model="paper",
            residual_rms_norm=math.nan,
        )
