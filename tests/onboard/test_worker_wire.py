"""The estimator worker's wire (:mod:`onboard.app.estimator_worker`): rows and estimates as tuples of Python
numbers through plain pickle, read back as the very values that went in (bit for bit, dtypes and shapes)."""

from __future__ import annotations

import math
import pickle

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.app.estimator_wire import pack_estimate, row_args, row_message, unpack_estimate
from onboard.app.estimator_worker import as_observation
from onboard.core.frames import PinholeIntrinsics
from onboard.estimation.sliding import TrackEstimate
from onboard.estimation.window_problem import MotionPrior

FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64)
FINITE = st.floats(min_value=-1e9, max_value=1e9, allow_nan=False)


def _same(a, b) -> bool:
    """Equal as the worker's caller sees them: arrays of the same dtype, shape and bits; NaN equal to NaN."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            type(a) is type(b)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and a.tobytes() == b.tobytes()  # bit for bit: -0.0 and NaN payloads included
        )
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a):
        return math.isnan(b)
    return type(a) is type(b) and a == b


def _estimate(values: list[float], prior: MotionPrior | None, observable: bool, model: str) -> TrackEstimate:
    v = np.array(values[:24], dtype=float)
    return TrackEstimate(
        t_s=values[24],
        p_ned_m=v[0:3],
        v_ned_mps=v[3:6],
        cov_p_ned_m2=v[6:15].reshape(3, 3),
        cov_v_ned_m2ps2=v[15:24].reshape(3, 3),
        observable=observable,
        range_m=values[25],
        range_sigma_ratio=values[26],
        window_frames=int(abs(values[27])) % 1000 if math.isfinite(values[27]) else 7,
        model=model,
        residual_rms_norm=values[28],
        adequacy_p=values[29],
        ambiguity=values[30],
        motion_prior=prior,
    )


PRIORS = st.one_of(
    st.none(),
    st.builds(MotionPrior, FINITE, FINITE, FINITE, st.booleans()),
)


@settings(max_examples=100, deadline=None)
@given(
    values=st.lists(FLOATS, min_size=31, max_size=31),
    prior=PRIORS,
    observable=st.booleans(),
    model=st.text(max_size=12),
)
def test_an_estimate_reads_back_as_the_same_values(values, prior, observable, model):
    est = _estimate(values, prior, observable, model)
    packed = pack_estimate(est)
    assert type(packed) is tuple  # the compact form, not the object
    got = unpack_estimate(pickle.loads(pickle.dumps(packed, pickle.HIGHEST_PROTOCOL)))
    assert type(got) is TrackEstimate
    for name in TrackEstimate.__dataclass_fields__:
        assert _same(getattr(got, name), getattr(est, name)), name


def test_what_is_not_a_plain_estimate_goes_as_it_is():
    est = _estimate([1.0] * 31, None, True, "cv")
    f32 = TrackEstimate(**{**est.__dict__, "p_ned_m": np.zeros(3, dtype=np.float32)})
    for value in (None, f32, "text", 3):
        assert pack_estimate(value) is value
        assert unpack_estimate(value) is value
    assert _same(unpack_estimate(pack_estimate(f32)).p_ned_m, f32.p_ned_m)


@settings(max_examples=100, deadline=None)
@given(
    t=FINITE,
    uv=st.tuples(FLOATS, FLOATS),
    p=st.lists(FLOATS, min_size=3, max_size=3),
    q=st.lists(FLOATS, min_size=4, max_size=4),
    k_index=st.integers(0, 7),
)
def test_a_row_reads_back_as_the_observation_the_parent_made(t, uv, p, q, k_index):
    K = PinholeIntrinsics.vue_pro_640()
    args = as_observation(t, uv, K, p, q)
    msg = row_message(3, args, k_index)
    assert msg is not None and msg[:2] == ("row", 3)
    got = row_args(pickle.loads(pickle.dumps(msg, pickle.HIGHEST_PROTOCOL)), {k_index: K})
    assert len(got) == len(args) and got[2] is K
    for a, b in zip((got[0], *got[1], got[3], got[4]), (args[0], *args[1], args[3], args[4]), strict=True):
        assert _same(a, b)


def test_a_row_of_another_shape_is_sent_whole():
    K = PinholeIntrinsics.vue_pro_640()
    assert row_message(0, as_observation(1.0, (1.0, 2.0), K, np.zeros((3, 1)), np.ones(4)), 0) is None
    assert row_message(0, as_observation(1.0, (1.0, 2.0), K, np.zeros(3), np.ones(5)), 0) is None
