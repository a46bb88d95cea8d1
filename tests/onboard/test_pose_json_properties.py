"""Properties of onboard.io.pose_json (hypothesis): a recorded pose reads back bit for bit, and whatever a recording's
pose object holds, the reader returns a pose whose fields are what the writer writes, or refuses it with
:class:`InputError` naming ``where``: never another exception, never a truncated, coerced or non-finite value.

The writer's fields: ``time_boot_us``, the spans, the extrapolation times, ``epoch`` and ``discontinuities`` integers
>= 0 (the optional gimbal ones null or such an integer), the extrapolation sigmas finite and >= 0."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from onboard.core.errors import InputError
from onboard.core.frames import GeodeticOrigin
from onboard.core.pose_types import PoseAt, PoseSample
from onboard.core.track import ORIGIN_ALT_RANGE_M
from onboard.io.pose_json import pose_from_json, pose_to_json
from tests.onboard.test_record import _pose

QUAT_TOL = 1e-6  # onboard.core.frames.QUAT_NORM_TOL: the reader's unit check, with room for the float's last bits

finite = st.floats(allow_nan=False, allow_infinity=False)
# metres and m/s of any size a float holds, and the edges: 0, -0, the smallest and largest floats
vec3 = st.lists(finite, min_size=3, max_size=3)
micros = st.integers(0, 2**64 - 1)


@st.composite
def unit_quats(draw) -> np.ndarray:
    q = np.array(draw(st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4)))
    n = float(np.linalg.norm(q))
    if n < 0.1:
        q = np.array([1.0, 0.0, 0.0, 0.0])
    else:
        q = q / n
    return q


@st.composite
def poses(draw) -> PoseAt:
    v = [draw(st.one_of(finite, st.just(math.nan))) for _ in range(3)]  # NaN: an unknown velocity axis
    body = PoseSample(draw(micros), np.array(draw(vec3)), np.array(v), draw(unit_quats()))
    gimbal = draw(st.booleans())
    return PoseAt(
        body=body,
        p_cam_ned_m=np.array(draw(vec3)),
        q_ned_from_cam=draw(unit_quats()),
        q_mount_from_gimbal=draw(unit_quats()) if gimbal else None,
        origin=GeodeticOrigin(
            draw(st.floats(-90.0, 90.0)), draw(st.floats(-180.0, 360.0)), draw(st.floats(*ORIGIN_ALT_RANGE_M))
        ),
        att_span_us=draw(micros),
        pos_span_us=draw(micros),
        gimbal_span_us=draw(micros) if gimbal else None,
        epoch=draw(st.integers(0, 2**31)),
        att_extrapolated_us=draw(micros),
        pos_extrapolated_us=draw(micros),
        gimbal_extrapolated_us=draw(micros) if gimbal else None,
        sigma_extrapolation_rad=draw(st.floats(0.0, allow_infinity=False)),
        sigma_extrapolation_m=draw(st.floats(0.0, allow_infinity=False)),
        discontinuities=draw(st.integers(0, 2**31)),
    )


INT_FIELDS = ("time_boot_us", "att_span_us", "pos_span_us", "epoch", "att_extrapolated_us", "pos_extrapolated_us")
OPTIONAL_INT_FIELDS = ("gimbal_span_us", "gimbal_extrapolated_us", "discontinuities")
SIGMA_FIELDS = ("sigma_extrapolation_rad", "sigma_extrapolation_m")
VECTOR_FIELDS = ("p_ned_m", "v_ned_mps", "q_ned_from_body", "p_cam_ned_m", "q_ned_from_cam", "q_mount_from_gimbal")
FIELDS = ("origin", *INT_FIELDS, *OPTIONAL_INT_FIELDS, *SIGMA_FIELDS, *VECTOR_FIELDS)

# what json.loads can hand the reader from a recording: any JSON value, Python's Infinity/NaN and integers of any size
# included; numbers near the edges as often as the rest
json_leaf = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.sampled_from([0, -1, 2**63 - 1, 2**63, 2**64, 2**1100, -(2**1100)]),
    st.floats(),
    st.sampled_from([0.5, 1.5, -0.0, math.inf, -math.inf, math.nan, 1e300]),
    st.text(max_size=4),
    st.sampled_from(["12", "nan", "inf", "1e3"]),
)
json_values = st.recursive(
    json_leaf,
    lambda kids: st.one_of(st.lists(kids, max_size=5), st.dictionaries(st.text(max_size=8), kids, max_size=4)),
    max_leaves=12,
)


def _is_count(v) -> bool:
    return type(v) is int and v >= 0


def check_read_pose(pose: PoseAt) -> None:
    """The documented ranges of a pose the reader accepted."""
    for name in INT_FIELDS:
        v = pose.time_boot_us if name == "time_boot_us" else getattr(pose, name)
        assert _is_count(v), (name, v)
    for name in ("gimbal_span_us", "gimbal_extrapolated_us"):
        v = getattr(pose, name)
        assert v is None or _is_count(v), (name, v)
    assert _is_count(pose.discontinuities), pose.discontinuities
    for name in SIGMA_FIELDS:
        v = getattr(pose, name)
        assert type(v) is float and math.isfinite(v) and v >= 0, (name, v)
    b = pose.body
    assert b.p_ned_m.shape == (3,) and np.all(np.isfinite(b.p_ned_m))
    assert b.v_ned_mps.shape == (3,) and not np.any(np.isinf(b.v_ned_mps))
    assert pose.p_cam_ned_m.shape == (3,) and np.all(np.isfinite(pose.p_cam_ned_m))
    for q in (b.q_ned_from_body, pose.q_ned_from_cam, pose.q_mount_from_gimbal):
        if q is not None:
            assert q.shape == (4,) and abs(float(np.linalg.norm(q)) - 1.0) <= QUAT_TOL
    o = pose.origin
    assert all(math.isfinite(x) for x in (o.lat_deg, o.lon_deg, o.alt_m))
    assert ORIGIN_ALT_RANGE_M[0] <= o.alt_m <= ORIGIN_ALT_RANGE_M[1]  # as a track's origin


@settings(max_examples=60, deadline=None)
@given(poses())
def test_a_pose_reads_back_bit_for_bit_through_json_text(pose):
    text = json.dumps(pose_to_json(pose), allow_nan=False)  # the writer never needs NaN in the text
    back = pose_from_json(json.loads(text), "frame 1")
    assert back is not None
    check_read_pose(back)
    for name in ("p_cam_ned_m", "q_ned_from_cam"):
        assert getattr(back, name).tobytes() == getattr(pose, name).tobytes(), name
    if pose.q_mount_from_gimbal is None:
        assert back.q_mount_from_gimbal is None
    else:
        assert back.q_mount_from_gimbal.tobytes() == pose.q_mount_from_gimbal.tobytes()
    for name in ("p_ned_m", "q_ned_from_body"):
        assert getattr(back.body, name).tobytes() == getattr(pose.body, name).tobytes(), name
    assert np.array_equal(back.body.v_ned_mps, pose.body.v_ned_mps, equal_nan=True)
    assert back.origin == pose.origin
    for name in INT_FIELDS[1:] + OPTIONAL_INT_FIELDS + SIGMA_FIELDS:
        assert getattr(back, name) == getattr(pose, name), name
    assert back.time_boot_us == pose.time_boot_us


def _read_or_refuse(obj) -> PoseAt | None:
    try:
        pose = pose_from_json(obj, "frame 9")
    except InputError as exc:
        assert str(exc).startswith("frame 9: "), str(exc)
        return None
    assert (pose is None) == (obj is None)  # null: no pose (a frame without one)
    if pose is not None:
        check_read_pose(pose)
    return pose


BASE = pose_to_json(_pose(123_456, 3))


@settings(max_examples=200, deadline=None)
@given(field=st.sampled_from(FIELDS), value=json_values)
@example(field="time_boot_us", value=math.inf)  # int(inf): OverflowError escaped the reader
@example(field="att_span_us", value=-math.inf)
@example(field="p_cam_ned_m", value=[2**1100, 0, 0])  # float(2**1100): OverflowError escaped
@example(field="q_ned_from_body", value=[2**1100, 0, 0, 0])
@example(field="time_boot_us", value=1.5)  # read as 1
@example(field="time_boot_us", value=True)  # read as 1
@example(field="time_boot_us", value="12")  # read as 12
@example(field="att_span_us", value=-5)  # kept
@example(field="epoch", value=True)
@example(field="gimbal_span_us", value="abc")  # kept as the string
@example(field="gimbal_extrapolated_us", value=[1])
@example(field="sigma_extrapolation_rad", value="nan")  # read as NaN
@example(field="sigma_extrapolation_m", value=-1.0)
@example(field="discontinuities", value=-1)
@example(field="q_ned_from_body", value=None)  # a 0-d array: IndexError escaped check_unit_quat
@example(field="q_ned_from_cam", value=0.5)
@example(field="origin", value={"lat_deg": 47.0, "lon_deg": 8.0, "alt_m": 1e300})  # read: every replayed position off
def test_any_json_value_in_a_field_reads_as_a_pose_in_range_or_is_refused_naming_where(field, value):
    obj = copy.deepcopy(BASE)
    obj[field] = value
    pose = _read_or_refuse(obj)
    if pose is not None and field in INT_FIELDS + OPTIONAL_INT_FIELDS and value is not None:
        got = pose.time_boot_us if field == "time_boot_us" else getattr(pose, field)
        assert got == value and type(got) is type(value), (field, value, got)  # kept as written, not coerced


@settings(max_examples=60, deadline=None)
@given(json_values)
def test_any_json_value_as_the_pose_object_reads_or_is_refused(value):
    _read_or_refuse(value)


@settings(max_examples=60, deadline=None)
@given(st.sets(st.sampled_from(FIELDS), min_size=1, max_size=4))
def test_a_pose_without_some_fields_is_refused_or_reads_with_their_documented_defaults(missing):
    obj = copy.deepcopy(BASE)
    for name in missing:
        del obj[name]
    pose = _read_or_refuse(obj)
    optional = {"q_mount_from_gimbal", "att_extrapolated_us", "pos_extrapolated_us", *OPTIONAL_INT_FIELDS}
    optional |= set(SIGMA_FIELDS)
    assert (pose is not None) == (missing <= optional), (missing, pose)
    if pose is not None and "discontinuities" in missing:
        assert pose.discontinuities == pose.epoch  # a recording from before resets were counted
