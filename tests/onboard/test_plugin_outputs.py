"""What the frame pipeline does with a misbehaving estimator's or tracker's output: refused and counted, never
published, never the end of the frame loop (a built-in algorithm with a bug takes the same paths as a plug-in)."""

from __future__ import annotations

import dataclasses
import logging
from types import SimpleNamespace

import numpy as np
import pytest

from onboard.core.errors import InputError
from onboard.estimation.map_estimator import across_range_widened
from onboard.pipeline.frame_pipeline import FrameRejected
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


# --------------------------------------------------------------------------- estimates of the wrong type or shape


def _fields(est, **kw) -> SimpleNamespace:
    """The estimate as another estimator's object would carry it, with ``kw`` changed (``_ABSENT``: the field absent)."""
    d = {k: getattr(est, k) for k in PROTOCOL_FIELDS}
    d.update(kw)
    return SimpleNamespace(**{k: v for k, v in d.items() if v is not _ABSENT})


_ABSENT = object()
PROTOCOL_FIELDS = (
    "t_s",
    "p_ned_m",
    "v_ned_mps",
    "cov_p_ned_m2",
    "cov_v_ned_m2ps2",
    "observable",
    "range_m",
    "range_sigma_ratio",
    "window_frames",
    "model",
)


@pytest.mark.parametrize(
    "spoil, field",
    [
        (lambda est: [1.0, 2.0, 3.0], "no t_s (a list)"),
        (lambda est: "estimate", "no t_s (a str)"),
        (lambda est: _fields(est, p_ned_m=np.array([1.0, 2.0])), "p_ned_m must have the shape (3,)"),
        (lambda est: _fields(est, cov_p_ned_m2=np.eye(2)), "cov_p_ned_m2 must have the shape (3, 3)"),
        (lambda est: _fields(est, cov_v_ned_m2ps2=np.eye(2)), "cov_v_ned_m2ps2 must be None or have the shape"),
        (lambda est: _fields(est, observable=_ABSENT), "no observable"),
        (lambda est: _fields(est, observable="yes"), "observable must be a bool"),
        (lambda est: _fields(est, window_frames=float("nan")), "window_frames must be an integer"),
        (lambda est: _fields(est, window_frames=-1), "window_frames must be an integer"),
        (lambda est: _fields(est, range_m="far"), "range_m must be None or a finite number"),
        (lambda est: _fields(est, range_m=np.inf), "range_m must be None or a finite number"),
        (lambda est: _fields(est, residual_rms_norm="low"), "residual_rms_norm must be None or a number"),
        (lambda est: _fields(est, residual_rms_norm=-1.0), "residual_rms_norm must be None or a number"),
        (lambda est: _fields(est, model=3), "model must be None or a string"),
        (lambda est: _fields(est, p_ned_m=np.full(3, np.nan)), "p_ned_m is not finite"),
        (lambda est: _fields(est, v_ned_mps=np.array([np.inf, 0.0, 0.0])), "v_ned_mps is not finite"),
        (lambda est: _fields(est, cov_p_ned_m2=np.diag([np.inf, 1.0, 1.0])), "cov_p_ned_m2 is not finite"),
        (lambda est: _fields(est, p_ned_m=np.array(["a", "b", "c"], dtype=object)), "TypeError"),
    ],
)
def test_an_estimate_the_pipeline_cannot_read_is_refused_and_counted_naming_the_estimator(spoil, field, caplog):
    rig = _spoilt_rig(spoil)
    with caplog.at_level(logging.WARNING):
        tracks = rig.run(FRAMES)  # the frame loop goes on
    assert all(tr.p_ned_m is None and tr.window_frames == 0 and not tr.observable for tr in tracks)
    assert rig.counter["estimator_output_invalid"] == FRAMES - 9
    assert rig.counter["estimator_error"] == 0
    lines = [r.getMessage() for r in caplog.records if "estimator_output_invalid" in r.getMessage()]
    assert len(lines) == 1 and "SpoiltEstimator" in lines[0] and field in lines[0]


def test_an_estimate_of_lists_and_numpy_scalars_is_read_as_one_of_arrays():
    rig = _spoilt_rig(
        lambda est: _fields(
            est,
            p_ned_m=est.p_ned_m.tolist(),
            cov_p_ned_m2=est.cov_p_ned_m2.tolist(),
            observable=np.bool_(True),
            window_frames=np.int64(est.window_frames),
            range_m=np.float64(est.range_m),
        )
    )
    tracks = rig.run(FRAMES)
    assert all(tr.p_ned_m is not None for tr in tracks[9:])
    assert rig.counter["estimator_output_invalid"] == 0


# --------------------------------------------------------------------------- tracker answers


class SpoiltTracker:
    """The rig's image chain whose updates are passed through ``spoil`` (which may raise)."""

    def __init__(self, inner, spoil):
        self.inner = inner
        self.spoil = spoil

    def update(self, pixels):
        return self.spoil(self.inner.update(pixels))


def _raise(exc):
    raise exc


@pytest.mark.parametrize(
    "spoil, reason, what",
    [
        (lambda upd: None, "tracker_output_invalid", "update returned None"),
        (lambda upd: {"u_px": 1.0, "v_px": 2.0}, "tracker_output_invalid", "no state (a dict)"),
        (lambda upd: dataclasses.replace(upd, u_px=float("nan")), "tracker_output_invalid", "centre"),
        (lambda upd: dataclasses.replace(upd, v_px=float("inf")), "tracker_output_invalid", "centre"),
        (lambda upd: dataclasses.replace(upd, u_px=-0.5), "tracker_output_invalid", "off the"),
        (lambda upd: dataclasses.replace(upd, v_px=1e6), "tracker_output_invalid", "off the"),
        (lambda upd: dataclasses.replace(upd, bbox=(10.0, 10.0, -5.0, 5.0)), "tracker_output_invalid", "bbox"),
        (lambda upd: dataclasses.replace(upd, bbox=(np.nan, 10.0, 5.0, 5.0)), "tracker_output_invalid", "bbox"),
        (lambda upd: dataclasses.replace(upd, bbox=(1.0, 2.0)), "tracker_output_invalid", "bbox"),
        (lambda upd: dataclasses.replace(upd, track_id=0), "tracker_output_invalid", "track_id"),
        (
            lambda upd: SimpleNamespace(**{**dataclasses.asdict(upd), "state": "flying"}),
            "tracker_output_invalid",
            "state must be one of",
        ),
        (lambda upd: _raise(RuntimeError("kcf lost its mind")), "tracker_error", "RuntimeError: kcf lost its mind"),
    ],
)
def test_a_tracker_answer_the_pipeline_cannot_read_refuses_the_frame_counted_naming_the_tracker(
    spoil, reason, what, caplog
):
    rig = Rig(estimator=None)
    rig.pipe.tracker = SpoiltTracker(rig.pipe.tracker, spoil)
    with caplog.at_level(logging.WARNING):
        for k in range(3):
            with pytest.raises(FrameRejected) as info:
                rig.step(k)
            assert info.value.reason == reason
    assert rig.counter[reason] == 3 and rig.pipe.frames_rejected == 3
    lines = [r.getMessage() for r in caplog.records if reason in r.getMessage()]
    assert len(lines) == 1 and "SpoiltTracker" in lines[0] and what in lines[0]
    rig.pipe.tracker = rig.pipe.tracker.inner  # the loop goes on: the next good answer is a track
    assert rig.step(3).state == "tracking"


def test_a_coasting_prediction_off_the_frame_is_a_track_not_a_refusal():
    # a target leaving the frame coasts on its prediction there: not a measurement, so not the tracker's fault
    rig = Rig(estimator=None)
    rig.pipe.tracker = SpoiltTracker(
        rig.pipe.tracker, lambda upd: dataclasses.replace(upd, u_px=-40.0, measurement_valid=False)
    )
    track = rig.step(0)
    assert rig.pipe.frames_rejected == 0 and rig.counter["tracker_output_invalid"] == 0
    assert track.u_px == -40.0


def test_an_estimator_that_raises_is_counted_naming_the_estimator_and_the_exception(caplog):
    rig = Rig(fail=True)
    with caplog.at_level(logging.WARNING):
        tracks = rig.run(3)
    assert all(tr.p_ned_m is None for tr in tracks) and rig.counter["estimator_error"] == 3
    lines = [r.getMessage() for r in caplog.records if "estimator_error" in r.getMessage()]
    assert len(lines) == 1 and "estimator_error: FakeEstimator: RuntimeError: boom" in lines[0]
