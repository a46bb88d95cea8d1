"""What the single-vehicle and the fleet estimates of a target share: its state at one time in a local NED
frame and the observability verdict on it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["StateEstimate"]


@dataclass(frozen=True)
class StateEstimate:
    """The target's state at ``t_s`` (s): position ``p_ned_m`` and velocity ``v_ned_mps`` (3,), their
    covariances ``cov_p_ned_m2`` and ``cov_v_ned_m2ps2`` (3, 3) and ``observable``, the estimator's verdict.
    :class:`~onboard.estimation.sliding.TrackEstimate` and :class:`~onboard.estimation.fleet.FleetEstimate`
    add what each knows besides."""

    t_s: float
    p_ned_m: np.ndarray
    v_ned_mps: np.ndarray
    cov_p_ned_m2: np.ndarray
    cov_v_ned_m2ps2: np.ndarray
    observable: bool

    @property
    def sigma_ned_m(self) -> np.ndarray:
        """The position's 1-sigma per NED axis (m)."""
        return np.sqrt(np.maximum(np.diag(self.cov_p_ned_m2), 0.0))
