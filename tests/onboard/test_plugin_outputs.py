"""What the frame pipeline does with a misbehaving estimator's or tracker's output: refused and counted, never
published, never the end of the frame loop (a built-in algorithm with a bug takes the same paths as a plug-in)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from onboard.core.errors import InputError
from onboard.estimation.map_estimator import across_range_widened
from tests.fakes import positioned_track
from tests.onboard.test_pipeline import FakeEstimator, Rig

FRAMES = 16  # the fake estimator answers from its 10th observation on


class SpoiltEstimator(FakeEstimator):
    """The fake estimator whose estimates are passed through ``spoil``."""

    def __init__(self, scene, spoil):
        super().__init__(scene)
        self.spoil = spoil

    def _estimate(self, t_s, p_cam=None):
        est = super()._estimate(t_s, p_cam)
        return None if est is None else self.spoil(est)


def _spoilt_rig(spoil) -> Rig:
    rig = Rig(estimator=None)
    rig.est = SpoiltEstimator(rig.scene, spoil)
    rig.pipe.estimator = rig.est
    return rig


# --------------------------------------------------------------------------- covariances


NON_SYMMETRIC = np.array([[4.0, 1e4, 0.0], [-1e4, 9.0, 0.0], [0.0, 0.0, 1.0]])
INDEFINITE = np.array([[1.0, 100.0, 0.0], [100.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # eigenvalues 101, -99, 1


@pytest.mark.parametrize("name", ["cov_p_ned_m2", "cov_v_ned_m2ps2"])
@pytest.mark.parametrize("cov", [NON_SYMMETRIC, INDEFINITE], ids=["non-symmetric", "indefinite"])
def test_a_covariance_no_distribution_has_is_refused(name, cov):
    with pytest.raises(InputError, match=f"Track.{name} must be symmetric positive semi-definite"):
        positioned_track(**{name: cov})


def test_covariances_with_round_off_and_rank_deficiency_pass():
    a = np.array([[3.0, 1.0, 0.5], [0.2, 2.0, 1.0], [0.0, 0.0, 0.0]]) * 1e3
    singular = a @ a.T  # rank 2, exactly PSD
    rounded = singular.copy()
    rounded[0, 1] *= 1.0 + 1e-12  # an estimator's asymmetric round-off
    u = np.array([0.6, 0.8, 0.0])
    along = 1e6 * np.outer(u, u) + np.eye(3)  # an unobservable range: 1 km sigma along, 1 m across
    for cov in (np.zeros((3, 3)), singular, rounded, along, across_range_widened(along, u, 50.0)):
        assert np.array_equal(positioned_track(cov_p_ned_m2=cov).cov_p_ned_m2, cov)


@pytest.mark.parametrize("cov", [NON_SYMMETRIC, INDEFINITE], ids=["non-symmetric", "indefinite"])
def test_an_estimate_with_an_impossible_covariance_publishes_no_position(cov):
    rig = _spoilt_rig(lambda est: dataclasses.replace(est, cov_p_ned_m2=cov))
    tracks = rig.run(FRAMES)
    assert all(tr.p_ned_m is None for tr in tracks)
    assert rig.counter["estimator_output_invalid"] == FRAMES - 9
