"""The MAVLink wire module (onboard.io.mavlink_wire): every typed value encoded, packed, parsed by
pymavlink's own parser and decoded equals the input within the message's quantisation; bad values are
refused naming the message and the field; one connection-string grammar."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mav

from onboard.core.errors import InputError
from onboard.core.pose import GimbalReference
from onboard.io import mavlink_wire as wire
from onboard.io.mavlink_wire import (
    SystemTime,
    Timesync,
    command_ack_message,
    message_from_fields,
    parse_datagram,
    set_message_interval_message,
    wire_fields,
    wire_roundtrip,
)
from tests.fuzz_budget import fuzz_settings

DEGE7_TOL_DEG = 0.5e-7  # lat/lon rounded to 1e-7 deg
MM_TOL_M = 0.5e-3  # altitudes in whole mm
CMPS_TOL_MPS = 0.5e-2  # velocities in whole cm/s
CDEG_TOL_RAD = math.radians(0.005)  # heading in whole cdeg
F32_REL = 2**-23  # float32 mantissa
ROUND_TRIP = fuzz_settings(200)  # examples per round trip in `make test` (IRTRACK_FUZZ_EXAMPLES for more)

TIME_US = st.integers(0, 2**32 * 1000 - 1)  # within one time_boot_ms wrap
UNIT = st.floats(-1.0, 1.0)
RATE = st.floats(-50.0, 50.0)
NORM = st.one_of(st.just(math.nan), st.floats(0.0, 1.0))


def _f32(x: float) -> float:
    return float(abs(x) * F32_REL + 1e-38)


def _close(a, b, tol) -> bool:
    return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol


@ROUND_TRIP
@given(TIME_US, st.tuples(UNIT, UNIT, UNIT, UNIT), st.tuples(RATE, RATE, RATE))
def test_attitude_quaternion_round_trip(t_us, q, w):
    back = wire.AttitudeQuaternion.from_message(wire_roundtrip(wire.AttitudeQuaternion(t_us, q, w).to_message()))
    assert back.time_boot_us == t_us // 1000 * 1000
    assert all(_close(a, b, _f32(b)) for a, b in zip(back.q_ned_from_body + back.omega_frd_rps, q + w))


@ROUND_TRIP
@given(
    TIME_US,
    st.floats(-90, 90),
    st.floats(-180, 180),
    st.floats(-1e5, 1e5),
    st.floats(-1e5, 1e5),
    st.tuples(*[st.floats(-327.67, 327.67)] * 3),
    st.one_of(st.just(math.nan), st.floats(-10.0, 10.0)),
)
def test_global_position_int_round_trip(t_us, lat, lon, alt, alt_rel, v, hdg):
    back = wire.GlobalPositionInt.from_message(
        wire_roundtrip(wire.GlobalPositionInt(t_us, lat, lon, alt, alt_rel, v, hdg).to_message())
    )
    assert back.time_boot_us == t_us // 1000 * 1000
    assert abs(back.lat_deg - lat) <= DEGE7_TOL_DEG + 1e-15 and abs(back.lon_deg - lon) <= DEGE7_TOL_DEG + 1e-15
    assert abs(back.alt_amsl_m - alt) <= MM_TOL_M + 1e-9 and abs(back.alt_rel_m - alt_rel) <= MM_TOL_M + 1e-9
    assert all(abs(a - b) <= CMPS_TOL_MPS + 1e-12 for a, b in zip(back.v_ned_mps, v))
    if math.isnan(hdg):
        assert math.isnan(back.heading_rad)
    else:  # [0, 2 pi) on the wire
        d = (back.heading_rad - hdg + math.pi) % (2 * math.pi) - math.pi
        assert abs(d) <= CDEG_TOL_RAD + 1e-12


@pytest.mark.parametrize(
    "heading_deg, hdg_cdeg",
    [(359.999, 0), (-0.001, 0), (359.994, 35999), (360.0, 0), (0.004, 0), (0.006, 1), (90.0, 9000), (-90.0, 27000)],
)
def test_global_position_int_heading_is_whole_cdeg_below_36000(heading_deg, hdg_cdeg):
    """common.xml: hdg in [0, 35999] cdeg (65535: unknown); a heading that rounds up to 360.00 deg is 0."""
    msg = wire_roundtrip(
        wire.GlobalPositionInt(0, 47.0, 8.0, 500.0, heading_rad=math.radians(heading_deg)).to_message()
    )
    assert msg.hdg == hdg_cdeg


@ROUND_TRIP
@given(
    TIME_US,
    st.tuples(UNIT, UNIT, UNIT, UNIT),
    st.sampled_from(
        [
            mav.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME,
            mav.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME,
            mav.GIMBAL_DEVICE_FLAGS_YAW_LOCK,
            0,
        ]
    ),
    st.tuples(*[st.one_of(st.just(math.nan), RATE)] * 3),
    st.integers(0, 2**32 - 1),
)
def test_gimbal_device_attitude_status_round_trip(t_us, q, flags, w, failure):
    sent = wire.GimbalDeviceAttitudeStatus(t_us, q, flags, w, 0.5, failure)
    back = wire.GimbalDeviceAttitudeStatus.from_message(wire_roundtrip(sent.to_message()))
    assert back.time_boot_us == t_us // 1000 * 1000 and (back.flags, back.failure_flags) == (flags, failure)
    assert all(_close(a, b, _f32(b)) for a, b in zip(back.q_ref_from_gimbal + back.omega_ref_rps, q + w))
    assert back.reference == sent.reference
    assert back.reference == (
        GimbalReference.VEHICLE if flags in (mav.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME, 0) else GimbalReference.EARTH
    )


@ROUND_TRIP
@given(st.integers(-(2**63), 2**63 - 1), st.integers(-(2**63), 2**63 - 1), st.integers(0, 2**64 - 1), TIME_US)
def test_timesync_and_system_time_round_trip(tc1, ts1, unix_us, t_us):
    back = Timesync.from_message(wire_roundtrip(Timesync(tc1, ts1).to_message()))
    assert (back.tc1_ns, back.ts1_ns, back.is_request) == (tc1, ts1, tc1 == 0)
    st_back = SystemTime.from_message(wire_roundtrip(SystemTime(unix_us, t_us).to_message()))
    assert (st_back.time_unix_us, st_back.time_boot_us) == (unix_us, t_us // 1000 * 1000)


@ROUND_TRIP
@given(st.integers(0, 255), st.sampled_from([0, 1, 2]), st.integers(0, 255), st.tuples(*[NORM] * 7), st.integers(0, 6))
def test_camera_tracking_image_status_round_trip(status, mode, data, coords, dev):
    sent = wire.CameraTrackingImageStatus(status, mode, data, *coords, dev)
    back = wire.CameraTrackingImageStatus.from_message(wire_roundtrip(sent.to_message()))
    assert (back.tracking_status, back.tracking_mode, back.target_data, back.camera_device_id) == (
        status,
        mode,
        data,
        dev,
    )
    assert all(
        _close(getattr(back, n), getattr(sent, n), _f32(getattr(sent, n)))
        for n in wire.CameraTrackingImageStatus._COORDS
    )


ACC = st.one_of(st.just(math.nan), st.floats(0.0, 1e4))
VEL = st.one_of(st.just(math.nan), st.floats(-1e3, 1e3))


@ROUND_TRIP
@given(
    st.floats(-90, 90),
    st.floats(-180, 180),
    st.floats(-1e4, 1e4),
    st.tuples(ACC, ACC, VEL, VEL, VEL, ACC, ACC, VEL, ACC),
)
def test_camera_tracking_geo_status_round_trip(lat, lon, alt, rest):
    sent = wire.CameraTrackingGeoStatus(lat, lon, alt, *rest)
    back = wire.CameraTrackingGeoStatus.from_message(wire_roundtrip(sent.to_message()))
    assert abs(back.lat_deg - lat) <= DEGE7_TOL_DEG + 1e-15 and abs(back.lon_deg - lon) <= DEGE7_TOL_DEG + 1e-15
    for name in (
        "alt_m",
        "h_acc_m",
        "v_acc_m",
        "vel_n_mps",
        "vel_e_mps",
        "vel_d_mps",
        "vel_acc_mps",
        "dist_m",
        "hdg_rad",
        "hdg_acc_rad",
    ):
        assert _close(getattr(back, name), getattr(sent, name), _f32(getattr(sent, name))), name


@ROUND_TRIP
@given(
    st.integers(0, 2**50),
    st.floats(-90, 90),
    st.floats(-180, 180),
    st.floats(-1e4, 1e4),
    st.tuples(*[st.floats(-1e3, 1e3)] * 3),
    st.floats(0, 1e4),
    st.floats(0, 1e4),
)
def test_follow_target_round_trip(t_us, lat, lon, alt, v, h_acc, v_acc):
    back = wire.FollowTarget.from_message(
        wire_roundtrip(wire.FollowTarget(t_us, lat, lon, alt, v, h_acc, v_acc).to_message())
    )
    assert back.time_boot_us == t_us // 1000 * 1000
    assert abs(back.lat_deg - lat) <= DEGE7_TOL_DEG + 1e-15 and abs(back.lon_deg - lon) <= DEGE7_TOL_DEG + 1e-15
    assert all(
        _close(a, b, _f32(b))
        for a, b in zip((back.alt_m, back.h_acc_m, back.v_acc_m, *back.v_ned_mps), (alt, h_acc, v_acc, *v))
    )


def test_heartbeat_commands_and_generic_messages_round_trip():
    hb = wire.Heartbeat(mav.MAV_TYPE_CAMERA, mav.MAV_AUTOPILOT_INVALID, 0, 7, mav.MAV_STATE_ACTIVE)
    assert wire.Heartbeat.from_message(wire_roundtrip(hb.to_message())) == hb
    cmd = wire_roundtrip(set_message_interval_message(7, 1, 285, 20_000, 300))
    assert (cmd.command, cmd.param1, cmd.param2, cmd.confirmation) == (
        mav.MAV_CMD_SET_MESSAGE_INTERVAL,
        285.0,
        20000.0,
        255,
    )
    ack = wire_roundtrip(command_ack_message(511, mav.MAV_RESULT_DENIED, 255, 190))
    assert (ack.command, ack.result, ack.target_system, ack.target_component) == (511, 2, 255, 190)
    m = message_from_fields("message_interval", dict(message_id=275, interval_us=100_000))
    assert wire_fields(wire_roundtrip(m)) == dict(message_id=275, interval_us=100_000)
    assert parse_datagram(b"\x00\x01\x02")[0].get_type() == "BAD_DATA"


@pytest.mark.parametrize(
    "value, field",
    [
        (wire.AttitudeQuaternion(1000, (math.nan, 0, 0, 1)), "ATTITUDE_QUATERNION.q_ned_from_body[0]"),
        (wire.AttitudeQuaternion(-1, (1, 0, 0, 0)), "ATTITUDE_QUATERNION.time_boot_us"),
        (wire.AttitudeQuaternion(0, (1, 0, 0)), "ATTITUDE_QUATERNION.q_ned_from_body"),
        (wire.GlobalPositionInt(0, 91.0, 8.0, 500.0), "GLOBAL_POSITION_INT.lat_deg"),
        (wire.GlobalPositionInt(0, 47.0, 8.0, 500.0, 0.0, (400.0, 0.0, 0.0)), "GLOBAL_POSITION_INT.v_ned_mps[0]"),
        (wire.GlobalPositionInt(0, 47.0, 8.0, 3e6), "GLOBAL_POSITION_INT.alt_amsl_m"),
        (wire.GimbalDeviceAttitudeStatus(0, (1, 0, 0, 0), 1 << 16), "GIMBAL_DEVICE_ATTITUDE_STATUS.flags"),
        (wire.CameraTrackingImageStatus(1, 3), "CAMERA_TRACKING_IMAGE_STATUS.tracking_mode"),
        (wire.CameraTrackingImageStatus(1, 1, point_x=1.5), "CAMERA_TRACKING_IMAGE_STATUS.point_x"),
        (wire.CameraTrackingGeoStatus(47.0, math.nan, 0, 1, 1, 0, 0, 0, 0), "CAMERA_TRACKING_GEO_STATUS.lon_deg"),
        (wire.CameraTrackingGeoStatus(47.0, 8.0, 0, -1.0, 1, 0, 0, 0, 0), "CAMERA_TRACKING_GEO_STATUS.h_acc_m"),
        (wire.CameraTrackingGeoStatus(47.0, 8.0, 0, 1, 1, math.inf, 0, 0, 0), "CAMERA_TRACKING_GEO_STATUS.vel_n_mps"),
        (wire.FollowTarget(0, 47.0, 8.0, 0.0, (0, 0, 0), -1.0, 1.0), "FOLLOW_TARGET.h_acc_m"),
        (Timesync(2**63, 0), "TIMESYNC.tc1_ns"),
        (wire.Heartbeat(256, 0), "HEARTBEAT.mav_type"),
    ],
)
def test_bad_values_are_refused_naming_the_message_and_field(value, field):
    with pytest.raises(InputError) as e:
        value.to_message()
    assert str(e.value).startswith(field), str(e.value)


def test_decoding_passes_hostile_values_on_for_the_pose_buffer_to_judge():
    raw = mav.MAVLink_attitude_quaternion_message(5, math.nan, 0, 0, 0, 0, 0, 0, [0.0] * 4)
    assert math.isnan(wire.AttitudeQuaternion.from_message(wire_roundtrip(raw)).q_ned_from_body[0])
    sentinel = mav.MAVLink_global_position_int_message(5, 2**31 - 1, 2**31 - 1, 0, 0, 0, 0, 0, 65535)
    back = wire.GlobalPositionInt.from_message(wire_roundtrip(sentinel))
    assert back.lat_deg == pytest.approx(214.7483647) and math.isnan(back.heading_rad)
