"""The float fast paths of onboard.core.pose give what its numpy paths give.

Inputs: twin buffers get the same messages, one as usual (Python floats take the fast path), the other
with the fast path switched off (:func:`numpy_paths_only`: every input goes to the numpy code): same
return values, same counters and messages, bit-identical stored rows -- for valid input and for every
kind of invalid one.  Queries: :func:`reference_lookup` is the numpy formulation the float look-up
replaced (onboard.core.frames' functions, the public dataclasses' validation); the float look-up must
give the same bits in every field.
"""

from __future__ import annotations

import bisect
import contextlib
import dataclasses
import logging
import math
from unittest import mock

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from onboard.core import frames as F
from onboard.core import pose as P
from onboard.core.counters import RejectCounter
from onboard.core.errors import InputError
from onboard.core.frames import (
    CameraMount,
    FrameError,
    GeodeticOrigin,
    camera_pose_ned,
    euler_from_quat,
    ned_from_geodetic,
    quat_conjugate,
    quat_from_euler,
    quat_from_rotvec,
    quat_multiply,
    quat_normalize,
    quat_slerp,
    rotvec_from_quat,
)
from onboard.core.pose import (
    US_PER_S,
    GimbalReference,
    PoseBuffer,
)
from onboard.core.pose_config import PoseConfig, extrapolation_sigma
from onboard.core.pose_types import PoseAt, PoseLookup, PoseSample

# inputs of 1e200 and the like: the numpy paths overflow on them (and warn) before they reject them
pytestmark = pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")

ORIGIN = GeodeticOrigin(47.3977, 8.5456, 488.0)


def bits(a) -> bytes:
    """Exact representation (sign of zero and NaN included) of a float array or scalar."""
    return np.asarray(a, dtype=np.float64).tobytes()


def numpy_paths_only():
    """Inputs go to the numpy code, as before the fast paths (which take only what ``_plain_floats`` passes)."""
    return mock.patch.object(P, "_plain_floats", lambda v, n: None)


def feed(bufs: list[PoseBuffer], method: str, *args) -> list[bool]:
    """``bufs[0].<method>(*args)`` as usual and ``bufs[1].<method>(*args)`` on the numpy paths only."""
    with contextlib.ExitStack() as stack:
        results = [getattr(bufs[0], method)(*args)]
        stack.enter_context(numpy_paths_only())
        results.append(getattr(bufs[1], method)(*args))
    return results


class Log(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def twin_buffers(**kw) -> tuple[list[PoseBuffer], list[Log]]:
    bufs, logs = [], []
    for k in range(2):
        handler = Log()
        logger = logging.getLogger(f"test_pose_fast_paths.{k}")
        logger.propagate = False
        logger.handlers[:] = [handler]
        logger.setLevel(logging.DEBUG)
        bufs.append(PoseBuffer(counter=RejectCounter(log_interval_s=0.0, logger=logger), **kw))
        logs.append(handler)
    return bufs, logs


def assert_same_state(bufs: list[PoseBuffer], logs: list[Log]) -> None:
    a, b = bufs
    assert a.counter.counts == b.counter.counts
    assert logs[0].lines == logs[1].lines
    assert a.origin == b.origin and a.reboots == b.reboots and a.discontinuities == b.discontinuities
    for sa, sb in ((a._att, b._att), (a._pos, b._pos), (a._gim, b._gim)):
        assert sa.t_us == sb.t_us
        assert [bits(r) for r in sa.values] == [bits(r) for r in sb.values]
        assert all(r.dtype == np.float64 and r.ndim == 1 for r in sa.values)


# --------------------------------------------------------------------------- the numpy reference


def _ref_gimbal_rate(buf: PoseBuffer):
    g = buf._gim
    if not g.t_us:
        return None
    last = g.values[-1]
    if np.all(np.isfinite(last[4:])):
        return last[4:]
    t_last = g.t_us[-1]
    k = bisect.bisect_left(g.t_us, t_last - P.GIMBAL_RATE_WINDOW_US)
    if len(g.t_us) - k < 2:
        return None
    q_inv = quat_conjugate(last[:4])
    num = np.zeros(3)
    den = 0.0
    for i in range(k, len(g.t_us) - 1):
        tau = (g.t_us[i] - t_last) / US_PER_S
        dq = quat_multiply(g.values[i][:4], q_inv)
        num += tau * rotvec_from_quat(dq if dq[0] >= 0 else -dq)
        den += tau * tau
    return num / den if den > 0 else None


def _ref_interp_position(buf: PoseBuffer, j0, j1, s, dt_s):
    r0 = buf._pos.values[j0]
    if j0 == j1:
        return r0[:3].copy(), r0[3:6].copy()
    r1 = buf._pos.values[j1]
    p0, v0, p1, v1 = r0[:3], r0[3:6], r1[:3], r1[3:6]
    have_v = bool(np.all(np.isfinite(v0)) and np.all(np.isfinite(v1)))
    v = (1.0 - s) * v0 + s * v1 if have_v else (p1 - p0) / dt_s
    if have_v and buf.config.position_interp == "hermite":
        s2, s3 = s * s, s * s * s
        h00, h10, h01, h11 = 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2
        return h00 * p0 + h10 * dt_s * v0 + h01 * p1 + h11 * dt_s * v1, v
    return (1.0 - s) * p0 + s * p1, v


def _ref_q_mount_from_gimbal(buf: PoseBuffer, q_ref_from_gimbal, q_ned_from_body):
    if buf._gim_ref == GimbalReference.MOUNT:
        return q_ref_from_gimbal
    if buf._gim_ref == GimbalReference.VEHICLE:
        yaw_rad = float(euler_from_quat(q_ned_from_body)[2])
        q_ned_from_gimbal = quat_multiply(quat_from_euler(0.0, 0.0, yaw_rad), q_ref_from_gimbal)
    else:
        q_ned_from_gimbal = q_ref_from_gimbal
    q_mount_from_ned = quat_conjugate(quat_multiply(q_ned_from_body, buf.mount.q_body_from_mount))
    return quat_normalize(quat_multiply(q_mount_from_ned, q_ned_from_gimbal))


def reference_lookup(buf: PoseBuffer, time_boot_us, extrapolate: bool = False) -> PoseLookup:
    """PoseBuffer.lookup as it was written on numpy arrays before the float paths."""
    if isinstance(time_boot_us, bool) or not isinstance(time_boot_us, (int, np.integer)) or time_boot_us < 0:
        return PoseLookup(None, "time_invalid")
    t = int(time_boot_us)
    if buf._origin is None:
        return PoseLookup(None, "no_origin")
    c, h = buf.config, buf.horizons

    def b_or_x(stream, horizon_us, can):
        b = stream.bracket(t)
        if b[0] is not None or not extrapolate or b[1] != f"{stream.name}_not_yet" or not can():
            return b
        if t - stream.t_us[-1] > horizon_us:
            return None, f"{stream.name}_extrapolation_limit", True
        return len(stream.t_us) - 1, P._AFTER, 0.0

    ba = b_or_x(buf._att, h.attitude_us, lambda: bool(np.all(np.isfinite(buf._att.values[-1][4:]))))
    if ba[0] is None:
        return PoseLookup(None, ba[1], ba[2])
    pos_h = max(h.position_us, c.dead_reckoning_us)  # dead reckoning through a GNSS gap extends position's horizon
    bp = b_or_x(buf._pos, pos_h, lambda: bool(np.all(np.isfinite(buf._pos.values[-1][3:6]))))
    if extrapolate and bp[0] is None and bp[1] == "position_gap" and buf._pos.t_us[0] < t:
        j = int(np.searchsorted(buf._pos.t_us, t, side="right")) - 1
        if bool(np.all(np.isfinite(buf._pos.values[j][3:6]))):
            if t - buf._pos.t_us[j] <= pos_h:
                bp = (j, P._AFTER, 0.0)
            elif j == len(buf._pos.t_us) - 1:
                bp = (None, "position_extrapolation_limit", True)
    if bp[0] is None:
        return PoseLookup(None, bp[1], bp[2])
    bg = None
    if buf.mount.gimballed:
        bg = b_or_x(buf._gim, h.gimbal_us, lambda: _ref_gimbal_rate(buf) is not None)
        if bg[0] is None:
            return PoseLookup(None, bg[1], bg[2])
    att_x_us = pos_x_us = 0
    i0, i1, a = ba
    if i1 is P._AFTER:
        att_x_us = t - buf._att.t_us[i0]
        row = buf._att.values[i0]
        q_nb = quat_normalize(quat_multiply(row[:4], quat_from_rotvec(row[4:] * (att_x_us / US_PER_S))))
        att_span = 0
    else:
        v0 = buf._att.values[i0][:4]
        q_nb = v0 if i0 == i1 else quat_slerp(v0, buf._att.values[i1][:4], a)
        att_span = buf._att.t_us[i1] - buf._att.t_us[i0]
    j0, j1, s = bp
    if j1 is P._AFTER:
        pos_x_us = t - buf._pos.t_us[j0]
        row = buf._pos.values[j0]
        p_ned, v_ned = row[:3] + row[3:6] * (pos_x_us / US_PER_S), row[3:6].copy()
        pos_span = 0
    else:
        pos_span = buf._pos.t_us[j1] - buf._pos.t_us[j0]
        p_ned, v_ned = _ref_interp_position(buf, j0, j1, s, pos_span / US_PER_S)
    q_mg = gim_span = gim_x_us = None
    sigma_rad = extrapolation_sigma(att_x_us / US_PER_S, c.body_rate_sigma_rps, c.angular_accel_sigma_rps2)
    if bg is not None:
        k0, k1, g = bg
        if k1 is P._AFTER:
            gim_x_us = t - buf._gim.t_us[k0]
            w_ref = _ref_gimbal_rate(buf)
            q_ref = quat_normalize(
                quat_multiply(quat_from_rotvec(w_ref * (gim_x_us / US_PER_S)), buf._gim.values[k0][:4])
            )
            gim_span = 0
            sigma_rad = math.hypot(
                sigma_rad,
                extrapolation_sigma(gim_x_us / US_PER_S, c.gimbal_rate_sigma_rps, c.angular_accel_sigma_rps2),
            )
        else:
            gim_x_us = 0
            gim_span = buf._gim.t_us[k1] - buf._gim.t_us[k0]
            g0 = buf._gim.values[k0][:4]
            q_ref = g0 if k0 == k1 else quat_slerp(g0, buf._gim.values[k1][:4], g)
        q_mg = _ref_q_mount_from_gimbal(buf, q_ref, q_nb)
    q_lv = buf._pos.values[j0][6:]
    if q_lv.tolist() != [1.0, 0.0, 0.0, 0.0]:  # the local level's attitude into the origin's NED
        q_nb = quat_normalize(quat_multiply(q_lv, q_nb))
    p_cam, q_nc = camera_pose_ned(p_ned, q_nb, buf.mount, q_mg)
    body = PoseSample(t, p_ned, v_ned, q_nb)
    sigma_m = extrapolation_sigma(pos_x_us / US_PER_S, c.velocity_sigma_mps, c.accel_sigma_mps2)
    pose = PoseAt(
        body, p_cam, q_nc, q_mg, buf._origin, att_span, pos_span, gim_span, buf.reboots,
        att_x_us, pos_x_us, gim_x_us, sigma_rad, sigma_m, buf.discontinuities,
    )  # fmt: skip
    return PoseLookup(pose)


def assert_same_value(a, b, name: str) -> None:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        assert isinstance(a, np.ndarray) and isinstance(b, np.ndarray), name
        assert a.dtype == b.dtype == np.float64 and a.shape == b.shape, name
        assert bits(a) == bits(b), f"{name}: {a.tolist()} != {b.tolist()}"
        assert not a.flags.writeable and not b.flags.writeable, name
    elif isinstance(a, float) or isinstance(b, float):
        assert type(a) is type(b) and bits(a) == bits(b), f"{name}: {a!r} != {b!r}"
    else:
        assert type(a) is type(b) and a == b, f"{name}: {a!r} != {b!r}"


def assert_same_pose(got: PoseAt | None, want: PoseAt | None) -> None:
    assert (got is None) == (want is None)
    if got is None or want is None:
        return
    assert type(got) is PoseAt and type(got.body) is PoseSample
    for f in dataclasses.fields(PoseAt):
        if f.name == "body":
            for g in dataclasses.fields(PoseSample):
                assert_same_value(getattr(got.body, g.name), getattr(want.body, g.name), f"body.{g.name}")
        else:
            assert_same_value(getattr(got, f.name), getattr(want, f.name), f.name)
    with pytest.raises(dataclasses.FrozenInstanceError):
        got.body.time_boot_us = 0  # type: ignore[misc]


def assert_lookup_matches_reference(buf: PoseBuffer, t_us, extrapolate: bool) -> PoseLookup:
    got, want = buf.lookup(t_us, extrapolate=extrapolate), reference_lookup(buf, t_us, extrapolate)
    assert (got.reason, got.retry) == (want.reason, want.retry)
    assert_same_pose(got.pose, want.pose)
    return got


# --------------------------------------------------------------------------- quaternion helpers

finite = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)
quats = st.tuples(finite, finite, finite, finite).filter(lambda q: math.sqrt(sum(c * c for c in q)) > 1e-6)


@settings(max_examples=300, deadline=None)
@given(quats, quats, st.floats(-0.5, 1.5), st.tuples(finite, finite, finite))
def test_float_quaternion_kernels_are_frames_single_paths_bit_for_bit(q0, q1, alpha, phi):
    a, b = np.array(q0), np.array(q1)
    assert bits(F.quat_multiply1(q0, q1)) == bits(quat_multiply(a, b))
    assert bits(F.quat_normalize1(q0)) == bits(quat_normalize(a))
    assert bits(F.quat_conjugate1(q0)) == bits(quat_conjugate(a))
    assert bits(F.quat_slerp1(q0, q1, alpha)) == bits(quat_slerp(a, b, alpha))
    assert bits(F.quat_from_rotvec1(*phi)) == bits(quat_from_rotvec(np.array(phi)))
    assert bits(F.quat_from_rotvec1(*(1e-9 * c for c in phi))) == bits(quat_from_rotvec(1e-9 * np.array(phi)))
    for q in (q0, (1.0, 1e-13 * q0[1], 1e-13 * q0[2], 0.0), (-0.5, 1e-13 * q0[1], 0.0, 1e-14 * q0[3])):
        assert bits(F.rotvec_from_quat1(q)) == bits(rotvec_from_quat(np.array(q)))


@pytest.mark.parametrize("q", [(0.0, 0.0, 0.0, 0.0), (math.nan, 0.0, 0.0, 1.0), (math.inf, 0.0, 0.0, 0.0)])
def test_float_normalize_refuses_what_frames_refuses(q):
    with pytest.raises(FrameError, match="zero or not finite") as fast:
        F.quat_normalize1(q)
    with pytest.raises(FrameError) as ref:
        quat_normalize(np.array(q))
    assert str(fast.value) == str(ref.value)


# --------------------------------------------------------------------------- inputs

unit_quats = quats.map(lambda q: tuple(float(c) for c in quat_normalize(np.array(q))))
#: quaternions whose norm straddles the accepted band 1 +- QUAT_NORM_TOL
scaled_quats = st.tuples(unit_quats, st.floats(0.998, 1.002)).map(lambda qs: tuple(c * qs[1] for c in qs[0]))
any_float = st.floats(allow_nan=True, allow_infinity=True)
odd_quats = st.tuples(any_float, any_float, any_float, any_float)
rates = st.one_of(
    st.none(),
    st.tuples(finite, finite, finite),
    st.just((math.nan, math.nan, math.nan)),
    st.tuples(any_float, any_float, any_float),
)

BAD_QUATS = {
    "nan": ((math.nan, 0.0, 0.0, 1.0), "attitude_not_finite"),
    "inf": ((math.inf, 0.0, 0.0, 0.0), "attitude_not_finite"),
    "zero": ((0.0, 0.0, 0.0, 0.0), "attitude_zero"),
    "tiny": ((1e-7, 0.0, 0.0, 0.0), "attitude_zero"),
    "not_unit": ((1.01, 0.0, 0.0, 0.0), "attitude_not_unit"),
    "huge": ((1e200, 1e200, 0.0, 0.0), "attitude_not_unit"),
    "three": ((1.0, 0.0, 0.0), "attitude_shape"),
    "five": ((1.0, 0.0, 0.0, 0.0, 0.0), "attitude_shape"),
    "string": ("1,0,0,0", "attitude_shape"),
    "strings": (("1", "0", "0", "0"), None),  # numpy converts numeric strings: stored
    "word": (("w", "x", "y", "z"), "attitude_shape"),
    "none": (None, "attitude_shape"),
    "nested": (((1.0, 0.0), (0.0, 0.0)), "attitude_shape"),
}
BAD_RATES = {
    "none": (None, None),
    "all_nan": ((math.nan, math.nan, math.nan), None),
    "partial_nan": ((math.nan, 0.1, 0.2), "attitude_rate_invalid"),
    "inf": ((0.1, math.inf, 0.2), "attitude_rate_invalid"),
    "two": ((0.1, 0.2), "attitude_rate_invalid"),
    "string": ("abc", "attitude_rate_invalid"),
    "none_items": ((None, None, None), None),  # NaN each: unknown
    "row": ([[0.1, 0.2, 0.3]], None),  # reshaped to 3
    "ints": ((1, 2, 3), None),
}


@pytest.mark.parametrize("name", BAD_QUATS)
def test_every_kind_of_bad_quaternion_is_judged_as_before(name):
    q, reason = BAD_QUATS[name]
    bufs, logs = twin_buffers(origin=ORIGIN)
    results = feed(bufs, "add_attitude", 1_000, q, (0.1, 0.2, 0.3))
    assert results[0] == results[1] == (reason is None)
    if reason is not None:
        assert bufs[0].counter.counts == {reason: 1}
    assert_same_state(bufs, logs)


@pytest.mark.parametrize("name", BAD_RATES)
def test_every_kind_of_bad_rate_is_judged_as_before(name):
    w, reason = BAD_RATES[name]
    bufs, logs = twin_buffers(origin=ORIGIN)
    q = (0.5, 0.5, 0.5, 0.5)
    assert feed(bufs, "add_attitude", 1_000, q, w) == [True, True]
    assert bufs[0].counter.counts == ({reason: 1} if reason else {})
    assert_same_state(bufs, logs)
    row = bufs[0]._att.values[-1]
    assert bits(row[:4]) == bits([0.5, 0.5, 0.5, 0.5])
    if reason or w is None:
        assert np.all(np.isnan(row[4:]))


@pytest.mark.parametrize("t", [-1, 1.5, True, "7", None, np.int64(5), 2**40])
def test_times_are_judged_as_before(t):
    bufs, logs = twin_buffers(origin=ORIGIN)
    q = (1.0, 0.0, 0.0, 0.0)
    r = feed(bufs, "add_attitude", t, q)
    r += feed(bufs, "add_position", t, 47.4, 8.55, 500.0, (1.0, 2.0, 3.0))
    r += feed(bufs, "add_gimbal_status", t, q, GimbalReference.MOUNT)
    assert len(set(r)) == 1
    assert r[0] == (isinstance(t, (int, np.integer)) and not isinstance(t, bool) and t >= 0)
    assert_same_state(bufs, logs)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.tuples(st.one_of(unit_quats, scaled_quats, odd_quats), rates, st.integers(-5_000, 60_000)), max_size=12
    ),
    st.sampled_from(list(GimbalReference)),
)
def test_attitude_and_gimbal_streams_of_floats_equal_those_of_numpy_scalars(samples, reference):
    bufs, logs = twin_buffers(origin=ORIGIN)
    t = 1_000_000
    for q, w, dt in samples:
        t += dt
        results = feed(bufs, "add_attitude", t, q, w)
        assert results[0] == results[1]
        results = feed(bufs, "add_gimbal_status", t + 3, q, reference, w)
        assert results[0] == results[1]
    assert_same_state(bufs, logs)


velocities = st.one_of(
    st.none(),
    st.tuples(finite, finite, finite),
    st.tuples(any_float, any_float, any_float),
    st.just((1.0, 2.0)),
    st.just("fast"),
)
ned_points = st.tuples(*(st.floats(-3000.0, 3000.0),) * 3)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.tuples(st.one_of(ned_points, st.tuples(any_float, any_float, any_float), st.just((1.0, 2.0))), velocities),
        max_size=12,
    )
)
# a position far out of range, refused, then judged against by the next one's step check: its square overflowed
@example(
    samples=[
        ((0.0, 0.0, 0.0), None),
        ((0.0, 0.0, 0.0), None),
        ((1.0, 2.0), None),
        ((0.0, 0.0, 0.0), None),
        ((0.0, 0.0, 1.3407807929942597e154), (0.0, 0.0, 0.0)),
        ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
    ]
)
def test_ned_position_streams_of_floats_equal_those_of_numpy_scalars(samples):
    bufs, logs = twin_buffers(origin=ORIGIN, config=PoseConfig(max_speed_mps=3000.0, jump_reset_count=2))
    for k, (p, v) in enumerate(samples):
        t = 1_000_000 + 40_000 * k
        results = feed(bufs, "add_position_ned", t, p, v)
        assert results[0] == results[1]
    assert_same_state(bufs, logs)


@pytest.mark.parametrize("factor", [1.0 - 1e-15, 1.0 - 1e-16, 1.0, 1.0 + 1e-16, 1.0 + 1e-15, 1.0 - 2e-9, 1.0 + 2e-9])
def test_a_step_at_the_speed_limit_is_judged_by_numpys_norm(factor):
    """The jump test compares a float norm only far from the limit; near it numpy's norm decides, as before."""
    config = PoseConfig(max_speed_mps=200.0)
    buf = PoseBuffer(origin=ORIGIN, config=config, counter=RejectCounter(log_interval_s=3600.0))
    p0 = np.array([123.456, -78.9, -50.25])
    step = np.array([3.0, 4.0, 12.0]) / 13.0 * 8.0 * factor  # 200 m/s over 40 ms: 8 m
    assert buf.add_position_ned(1_000_000, p0.tolist())
    stored = buf.add_position_ned(1_040_000, (p0 + step).tolist())
    assert stored == (float(np.linalg.norm((p0 + step) - p0)) <= 200.0 * 0.04)
    assert buf.counter["position_jump"] == (not stored)


def test_geodetic_positions_are_stored_as_ned_from_geodetic_gives_them():
    bufs, logs = twin_buffers()
    # moves of a few centimetres a sample, as the velocity says within pose.max_position_step_m (no jump)
    samples = [(47.3977 + 4e-7 * k, 8.5456 - 1.2e-6 * k, 488.0 - 0.012 * k, (1.1, -2.2, 0.3)) for k in range(20)]
    samples[5] = (math.nan, 8.5, 500.0, None)
    samples[7] = (0.0, 0.0, 500.0, None)
    samples[9] = (47.4, 8.5, 1e6, None)
    samples[11] = (*samples[11][:3], (math.nan, 0.0, 0.0))
    for k, (lat, lon, alt, v) in enumerate(samples):
        t = 1_000_000 + 40_000 * k
        results = feed(bufs, "add_position", t, lat, lon, alt, v)
        assert results[0] == results[1]
    assert_same_state(bufs, logs)
    assert bufs[0].counter.counts == {
        "position_not_finite": 1,
        "position_zero": 1,
        "position_alt_out_of_range": 1,
        "position_velocity_invalid": 1,
    }
    origin = bufs[0].origin
    for row, (lat, lon, alt, _) in zip(bufs[0]._pos.values, [s for k, s in enumerate(samples) if k not in (5, 7, 9)]):
        assert bits(row[:3]) == bits(ned_from_geodetic(lat, lon, alt, origin))


# --------------------------------------------------------------------------- queries


def _fill(buf: PoseBuffer, rng: np.random.Generator, att_rates: str, pos_v: str, gim_rates: str, reference) -> None:
    """0.8 s of attitude and gimbal (50 Hz, jittered) and position (25 Hz, from a point with signed zeros, moved
    by the mean of each two velocities and up to 0.5 m more a sample, within pose.max_position_step_m: no jump;
    every fifth velocity unknown)."""
    p = np.array([0.0, -0.0, 12.5])
    v_prev = None
    # attitudes a vehicle and a gimbal can take 20 ms apart (random, up to ~6 deg a sample): a larger turn than the
    # rates allow is an attitude reset, which restarts the stream
    att = rng.uniform(-1.0, 1.0, 3)
    gim = rng.uniform(-0.5, 0.5, 3)
    for k in range(40):
        t = 1_000_000 + 20_000 * k + int(rng.integers(0, 2_000))
        att = att + rng.uniform(-0.05, 0.05, 3)
        q = tuple(float(c) for c in quat_from_euler(*att))
        w = None if att_rates == "none" else tuple(float(c) for c in rng.normal(0.0, 0.5, 3))
        buf.add_attitude(t, q, w)
        gim = gim + rng.uniform(-0.05, 0.05, 3)
        g = tuple(float(c) for c in quat_from_euler(*gim))
        gw = (math.nan,) * 3 if gim_rates == "nan" else tuple(float(c) for c in rng.normal(0.0, 0.2, 3))
        buf.add_gimbal_status(t + int(rng.integers(0, 5_000)), g, reference, gw)
        if k % 2 == 0:
            tp = 1_000_000 + 20_000 * k + 7_000
            v = None if pos_v == "none" or k % 10 == 4 else tuple(float(c) for c in rng.normal(0.0, 3.0, 3))
            if k and v is not None and v_prev is not None:
                p = p + 0.5 * 0.04 * (np.asarray(v_prev) + np.asarray(v))
            assert buf.add_position_ned(tp, p.tolist(), v)
            p = p + rng.uniform(-0.25, 0.25, 3)
            v_prev = v


MOUNTS = {
    "shipped": CameraMount(),
    "arm": CameraMount((0.12, -0.03, 0.05), tuple(float(c) for c in quat_from_euler(0.01, -0.3, 0.02))),
    "gimbal": CameraMount((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), gimballed=True),
    "gimbal_arm": CameraMount((0.1, 0.0, -0.02), tuple(float(c) for c in quat_from_euler(0, 0, 0.3)), True),
}


LOOKUP_CASES = [
    (mount, reference, rates, interp)
    for mount in MOUNTS
    for reference in (GimbalReference if MOUNTS[mount].gimballed else [GimbalReference.MOUNT])
    for rates in (("reported", "nan") if MOUNTS[mount].gimballed else ("reported",))
    for interp in ("hermite", "linear")
]


@pytest.mark.parametrize("case", range(len(LOOKUP_CASES)), ids=["-".join(map(str, c)) for c in LOOKUP_CASES])
def test_lookup_gives_the_bits_of_the_numpy_formulation(case):
    mount, reference, rates, interp = LOOKUP_CASES[case]
    rng = np.random.default_rng(case)
    buf = PoseBuffer(
        mount=MOUNTS[mount],
        origin=ORIGIN,
        config=PoseConfig(position_interp=interp),
        counter=RejectCounter(log_interval_s=3600.0),
    )
    _fill(buf, rng, "reported", "reported", rates, reference)
    times = [int(t) for t in rng.integers(900_000, 1_900_000, 300)]
    times += buf._att.t_us[:5] + buf._pos.t_us[:5] + buf._gim.t_us[:5]  # on a sample: no interpolation
    times += [buf._att.t_us[-1] + dt for dt in (1, 5_000, 20_000, 35_000, 60_000)]  # extrapolation and beyond
    kinds = set()
    for t in times:
        for extrapolate in (False, True):
            res = assert_lookup_matches_reference(buf, t, extrapolate)
            kinds.add(res.reason if res.pose is None else res.pose.mode)
    assert {"interpolated", "extrapolated"} <= kinds


@pytest.mark.parametrize("att_rates, pos_v", [("none", "reported"), ("reported", "none"), ("none", "none")])
def test_lookup_without_rates_or_velocity_gives_the_bits_of_the_numpy_formulation(att_rates, pos_v):
    rng = np.random.default_rng(7)
    buf = PoseBuffer(mount=MOUNTS["arm"], origin=ORIGIN, counter=RejectCounter(log_interval_s=3600.0))
    _fill(buf, rng, att_rates, pos_v, "reported", GimbalReference.MOUNT)
    for t in [int(t) for t in rng.integers(900_000, 1_900_000, 200)] + [buf._att.t_us[-1] + 3_000]:
        for extrapolate in (False, True):
            assert_lookup_matches_reference(buf, t, extrapolate)


@pytest.mark.parametrize("t", [-1, True, 1.5, "1000", None, np.int64(1_100_000)])
def test_odd_query_times_give_the_reference_answer(t):
    buf = PoseBuffer(origin=ORIGIN)
    _fill(buf, np.random.default_rng(1), "reported", "reported", "reported", GimbalReference.MOUNT)
    assert_lookup_matches_reference(buf, t, True)
    assert_lookup_matches_reference(PoseBuffer(), 1_100_000, True)  # no origin


def test_pose_at_counts_as_before():
    buf = PoseBuffer(origin=ORIGIN, counter=RejectCounter(log_interval_s=3600.0))
    _fill(buf, np.random.default_rng(3), "reported", "reported", "reported", GimbalReference.MOUNT)
    t_last = buf._att.t_us[-1]
    for t in (1_300_000, t_last + 4_000, t_last + 500_000, 10):
        res = reference_lookup(buf, t, True)
        assert_same_pose(buf.pose_at(t), res.pose)
        assert buf.last_miss_reason == res.reason
    assert buf.counter.counts == {"pose_extrapolated": 1, "pose_attitude_gap": 1, "pose_attitude_before_buffer": 1}


def test_a_computed_pose_that_the_dataclasses_would_refuse_still_raises_their_error():
    """Absurd but finite input: a camera centre that overflows raises what PoseAt raises."""
    buf = PoseBuffer(mount=CameraMount((1e308, 0.0, 0.0)), origin=ORIGIN)
    buf.add_attitude(1_000_000, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    buf.add_position_ned(1_000_000, (1.5e308, 2.0, 3.0), (0.0, 0.0, 0.0))
    with pytest.raises(InputError, match="PoseAt.p_cam_ned_m must be finite") as got:
        buf.lookup(1_000_000)
    with pytest.raises(InputError) as want:
        reference_lookup(buf, 1_000_000)
    assert str(got.value) == str(want.value)


def test_finite_values_whose_sum_overflows_are_still_a_pose():
    buf = PoseBuffer(origin=ORIGIN)
    buf.add_attitude(1_000_000, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    buf.add_position_ned(1_000_000, (1.5e308, 1.5e308, 3.0), (0.0, 0.0, 0.0))
    assert assert_lookup_matches_reference(buf, 1_000_000, False).pose is not None


def test_the_public_dataclasses_still_validate_what_callers_pass():
    with pytest.raises(InputError, match="PoseSample.q_ned_from_body"):
        PoseSample(0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (2.0, 0.0, 0.0, 0.0))
    with pytest.raises(InputError, match="PoseSample.p_ned_m must be finite"):
        PoseSample(0, (math.nan, 0.0, 0.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))
    body = PoseSample(0, (0.0, 0.0, 0.0), (math.nan,) * 3, (1.0, 0.0, 0.0, 0.0))
    with pytest.raises(InputError, match="PoseAt.q_ned_from_cam"):
        PoseAt(body, (0.0, 0.0, 0.0), (math.inf, 0.0, 0.0, 0.0), None, ORIGIN, 0, 0, None, 0)
