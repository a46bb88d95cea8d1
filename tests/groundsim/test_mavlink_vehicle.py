"""The simulator's MAVLink vehicle on 127.0.0.1: identity, field units, rates, services, MAVSDK."""

from __future__ import annotations

import contextlib
import math
import os
import socket
import threading
import time

import numpy as np
import pytest

from groundsim.io.mavlink_vehicle import (
    ARDUCOPTER_GUIDED_MODE,
    ARDUCOPTER_LOITER_MODE,
    MavlinkConfigError,
    MavlinkLinkError,
    MavlinkVehicle,
    open_mavlink2,
)
from groundsim.io.ports import free_udp_port
from onboard.core.errors import ConfigError, InputError, IrtrackError
from onboard.core.frames import euler_from_quat, quat_from_euler, quat_multiply
from onboard.io.mavlink_endpoint import parse_endpoint
from onboard.io.mavlink_wire import mavlink2

pytestmark = pytest.mark.timeout(60)

F32_REL = 1e-6  # float32 fields: ~7 significant digits
WAIT_S = 5.0  # any single datagram exchange on loopback completes well within this
GCS_SYS, GCS_COMP = 255, 190
STEP_US = 5000  # lockstep poll period: 200 Hz, a divisor of every stream interval used here

LAT_DEG, LON_DEG = 47.3977419, 8.5455938
ALT_AMSL_M, ALT_REL_M = 488.123, 30.25
V_NED_MPS = (12.34, -5.67, -0.89)
Q_NED_FROM_BODY = tuple(float(x) for x in quat_from_euler(0.1, -0.2, 2.5))
RATES_RADPS = (0.01, -0.02, 0.3)
HEADING_RAD = 2.5


def _timesync(rx, tc1: int, ts1: int) -> None:
    if "target_system" in rx.mav.timesync_encode.__code__.co_varnames:
        rx.mav.timesync_send(tc1, ts1, 1, 1)
    else:  # pymavlink 2.4.50's common.xml predates TIMESYNC's target extension fields
        rx.mav.timesync_send(tc1, ts1)


def _pump_thread(vehicle: MavlinkVehicle, stop: threading.Event, period_s: float) -> threading.Thread:
    """A (not yet started) thread feeding the vehicle its state and polling it on a monotonic clock until ``stop``."""

    def pump():
        t0 = time.monotonic()
        while not stop.is_set():
            now = int((time.monotonic() - t0) * 1e6)
            _state(vehicle, now)
            vehicle.poll(now)
            time.sleep(period_s)

    return threading.Thread(target=pump, daemon=True)


@contextlib.contextmanager
def mavsdk_autopilot(mavsdk):
    """(system, vehicle): a MAVSDK ground station that has discovered a vehicle pumped in real time."""
    port = free_udp_port()
    sdk = mavsdk.Mavsdk(mavsdk.Configuration.create_with_component_type(mavsdk.ComponentType.GROUND_STATION))
    vehicle = MavlinkVehicle(f"udpout:127.0.0.1:{port}")
    stop = threading.Event()
    th = _pump_thread(vehicle, stop, 0.002)
    try:
        sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        th.start()
        system = sdk.first_autopilot(WAIT_S)
        assert system is not None, "MAVSDK did not discover the vehicle"
        yield system, vehicle
    finally:
        stop.set()
        th.join(timeout=WAIT_S)
        sdk.destroy()
        vehicle.close()


def _state(vehicle: MavlinkVehicle, t_us: int, **over):
    kw = dict(
        time_boot_us=t_us,
        lat_deg=LAT_DEG,
        lon_deg=LON_DEG,
        alt_amsl_m=ALT_AMSL_M,
        alt_rel_m=ALT_REL_M,
        v_ned_mps=V_NED_MPS,
        q_ned_from_body=Q_NED_FROM_BODY,
        body_rates_radps=RATES_RADPS,
        heading_rad=HEADING_RAD,
    )
    kw.update(over)
    return vehicle.update_state(**kw)


@pytest.fixture
def link():
    """(receiver, vehicle): a pymavlink 'GCS' on a free udpin port and the vehicle sending to it."""
    port = free_udp_port()
    rx = open_mavlink2(f"udpin:127.0.0.1:{port}", GCS_SYS, GCS_COMP)
    vehicle = MavlinkVehicle(f"udpout:127.0.0.1:{port}", unix_time_at_boot_us=1_700_000_000_000_000)
    try:
        yield rx, vehicle
    finally:
        vehicle.close()
        rx.close()


def _drain(rx, quiet_s: float = 0.1, limit_s: float = WAIT_S) -> list:
    """Every message that arrives until ``quiet_s`` passes with none."""
    out, last, t_end = [], time.monotonic(), time.monotonic() + limit_s
    while time.monotonic() < t_end:
        m = rx.recv_match(blocking=False)
        if m is None:
            if time.monotonic() - last > quiet_s:
                break
            time.sleep(0.002)
            continue
        last = time.monotonic()
        if m.get_type() != "BAD_DATA":
            out.append(m)
    return out


def _lockstep(vehicle, t0_us: int, t1_us: int, step_us: int = STEP_US, gimbal=None) -> None:
    for t in range(t0_us, t1_us, step_us):
        _state(vehicle, t, **({"q_gimbal": gimbal} if gimbal is not None else {}))
        vehicle.poll(t)


def _of(msgs, mtype):
    return [m for m in msgs if m.get_type() == mtype]


def _until(vehicle, now_us: int, rx, mtype: str, pred=lambda m: True):
    """Poll the vehicle at a fixed boot time until ``rx`` sees a matching reply (bounded)."""
    t_end = time.monotonic() + WAIT_S
    while time.monotonic() < t_end:
        vehicle.poll(now_us)
        m = rx.recv_match(type=mtype, blocking=False)
        if m is not None and pred(m):
            return m
        time.sleep(0.002)
    raise AssertionError(f"no {mtype} within {WAIT_S} s")


def _prime(rx, vehicle, t_us: int = 0) -> None:
    """Let the receiver learn the vehicle's address (udpin replies go to known clients)."""
    vehicle.poll(t_us)
    _until(vehicle, t_us, rx, "HEARTBEAT")


# ----------------------------------------------------------------------------- identity and units


@pytest.mark.integration
def test_heartbeat_identifies_an_active_quadrotor_autopilot_in_mavlink2(link):
    rx, vehicle = link
    vehicle.poll(0)
    hb = _until(vehicle, 0, rx, "HEARTBEAT")
    assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
    assert hb.type == 2  # MAV_TYPE_QUADROTOR
    assert hb.autopilot in (0, 12)  # GENERIC or PX4
    assert hb.system_status == 4  # MAV_STATE_ACTIVE
    assert hb.base_mode & 128  # armed
    assert hb.get_msgbuf()[0] == 0xFD  # MAVLink 2 magic


@pytest.mark.parametrize(
    "guided, autopilot, base_mode",
    [
        # common.xml MAV_MODE_GUIDED_ARMED: armed, manual input, stabilised, guided (the generic autopilot's whole mode)
        (False, mavlink2.MAV_AUTOPILOT_GENERIC, 216),
        # ArduCopter (GCS_MAVLINK_Copter::base_mode): MANUAL_INPUT_ENABLED in every mode, GUIDED_ENABLED in LOITER and
        # GUIDED (position control), CUSTOM_MODE_ENABLED beside its custom_mode
        (True, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 216 | 1),
    ],
)
def test_heartbeat_base_mode_is_the_imitated_autopilots(guided, autopilot, base_mode):
    v, got = _captured_vehicle(guided=guided)
    try:
        v.poll(0)
        v._companion_heard = True  # the hand-over: LOITER once more, then GUIDED
        for t_us in (1_000_000, 2_000_000):
            v.poll(t_us)
    finally:
        v.close()
    hbs = _of(got, "HEARTBEAT")
    assert len(hbs) == 3
    assert {(hb.autopilot, hb.base_mode) for hb in hbs} == {(autopilot, base_mode)}
    assert base_mode & mavlink2.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    if guided:  # the same base_mode in LOITER and in GUIDED, as ArduCopter's
        assert [hb.custom_mode for hb in hbs] == [
            ARDUCOPTER_LOITER_MODE,
            ARDUCOPTER_LOITER_MODE,
            ARDUCOPTER_GUIDED_MODE,
        ]


@pytest.mark.integration
def test_attitude_and_position_fields_in_spec_units(link):
    rx, vehicle = link
    t_us = 12_345_678
    _state(vehicle, t_us)
    vehicle.poll(t_us + 500)
    msgs = _drain(rx)
    (att,) = _of(msgs, "ATTITUDE_QUATERNION")
    (pos,) = _of(msgs, "GLOBAL_POSITION_INT")
    (st,) = _of(msgs, "SYSTEM_TIME")
    assert att.time_boot_ms == pos.time_boot_ms == 12_345  # the state's stamp, not poll time
    assert (att.q1, att.q2, att.q3, att.q4) == pytest.approx(Q_NED_FROM_BODY, rel=F32_REL, abs=1e-7)
    assert (att.rollspeed, att.pitchspeed, att.yawspeed) == pytest.approx(RATES_RADPS, rel=F32_REL)
    assert pos.lat == 473977419 and pos.lon == 85455938  # degE7
    assert pos.alt == 488123 and pos.relative_alt == 30250  # mm
    assert (pos.vx, pos.vy, pos.vz) == (1234, -567, -89)  # cm/s NED
    assert pos.hdg == round(math.degrees(HEADING_RAD) * 100)  # cdeg
    # an instant up to 1 ms after poll time, its boot time truncated to ms as an autopilot's
    at_us = st.time_unix_usec - 1_700_000_000_000_000
    assert t_us + 500 <= at_us < t_us + 1500 and st.time_boot_ms == at_us // 1000


@pytest.mark.integration
def test_system_time_boot_ms_is_truncated_half_a_ms_early_on_average_polled_on_whole_ms(link):
    """Polled on the simulation's whole-ms step grid, SYSTEM_TIME's boot time was exact, so a receiver's half-ms
    correction for an autopilot's truncation (onboard.core.utc_clock) read the simulated UTC 0.5 ms late."""
    rx, vehicle = link
    sts = []
    for k in range(1, 121):
        vehicle.poll(k * 1_000_000)
        if k % 10 == 0:  # a few at a time: a burst of 120 seconds' messages overflows the socket's buffer
            sts += _of(_drain(rx, quiet_s=0.02), "SYSTEM_TIME")
    assert len(sts) == 120
    lost_us = [st.time_unix_usec - 1_700_000_000_000_000 - st.time_boot_ms * 1000 for st in sts]
    assert all(0 <= x < 1000 for x in lost_us)
    assert abs(np.mean(lost_us) - 500.0) < 3 * 289 / np.sqrt(len(lost_us))  # uniform on [0, 1 ms): sigma 289 us


@pytest.mark.integration
@pytest.mark.parametrize(
    "heading_rad, hdg_cdeg",
    [
        (0.0, 0),
        (math.pi / 2, 9000),
        (-0.1, round((360 - math.degrees(0.1)) * 100)),
        (2 * math.pi - 1e-9, 0),
        (float("nan"), 65535),
    ],
)
def test_heading_wraps_to_0_35999_and_unknown_is_uint16_max(link, heading_rad, hdg_cdeg):
    rx, vehicle = link
    _state(vehicle, 1000, heading_rad=heading_rad)
    vehicle.poll(1000)
    (pos,) = _of(_drain(rx), "GLOBAL_POSITION_INT")
    assert pos.hdg == hdg_cdeg


@pytest.mark.integration
def test_velocity_beyond_int16_saturates(link):
    rx, vehicle = link
    _state(vehicle, 1000, v_ned_mps=(400.0, -400.0, 1.0))
    vehicle.poll(1000)
    (pos,) = _of(_drain(rx), "GLOBAL_POSITION_INT")
    assert (pos.vx, pos.vy, pos.vz) == (32767, -32767, 100)


# ----------------------------------------------------------------------------- rates


@pytest.mark.integration
def test_lockstep_rates_are_exact_on_the_boot_clock(link):
    """2 s of boot time polled at 200 Hz, faster than real time: 50 Hz / 25 Hz / 1 Hz exactly."""
    rx, vehicle = link
    _lockstep(vehicle, 0, 2_000_000)
    msgs = _drain(rx)
    att = [m.time_boot_ms for m in _of(msgs, "ATTITUDE_QUATERNION")]
    pos = [m.time_boot_ms for m in _of(msgs, "GLOBAL_POSITION_INT")]
    assert len(att) == 100 and len(pos) == 50
    assert set(np.diff(att)) == {20} and set(np.diff(pos)) == {40}
    assert len(_of(msgs, "HEARTBEAT")) == 2 and len(_of(msgs, "SYSTEM_TIME")) == 2
    assert not _of(msgs, "GIMBAL_DEVICE_ATTITUDE_STATUS")


@pytest.mark.integration
def test_unchanged_state_is_not_resent(link):
    rx, vehicle = link
    _state(vehicle, 0)
    for t in range(0, 1_000_000, STEP_US):
        vehicle.poll(t)
    msgs = _drain(rx)
    assert len(_of(msgs, "ATTITUDE_QUATERNION")) == 1 and len(_of(msgs, "GLOBAL_POSITION_INT")) == 1
    assert len(_of(msgs, "HEARTBEAT")) == 1


@pytest.mark.integration
def test_custom_rates_from_the_constructor():
    port = free_udp_port()
    rx = open_mavlink2(f"udpin:127.0.0.1:{port}", GCS_SYS, GCS_COMP)
    with MavlinkVehicle(f"udpout:127.0.0.1:{port}", att_rate_hz=100, pos_rate_hz=10) as vehicle:
        _lockstep(vehicle, 0, 1_000_000)
        msgs = _drain(rx)
    rx.close()
    assert len(_of(msgs, "ATTITUDE_QUATERNION")) == 100 and len(_of(msgs, "GLOBAL_POSITION_INT")) == 10


@pytest.mark.integration
def test_real_time_threaded_rates(link):
    """Pumped by a thread on a monotonic clock (the real-time path): counted on the vehicle's own boot
    clock, not on the test's.  Stamps strictly increase, and no 1 s window of boot time holds more
    messages than the stream's rate (+1 for the window's edges) -- a starved pump sends fewer, never
    more.  The test waits for a number of messages (an event), bounded only by a hang guard."""
    rx, vehicle = link
    stop = threading.Event()
    want_att, want_pos = 75, 38  # 1.5 s of boot time at 50 / 25 Hz: every 1 s window from 0 to 0.5 s is full
    th = _pump_thread(vehicle, stop, 0.001)
    th.start()
    msgs = []
    try:
        t_guard = time.monotonic() + 10 * WAIT_S  # a hang guard, not a measured property
        while len(_of(msgs, "ATTITUDE_QUATERNION")) < want_att or len(_of(msgs, "GLOBAL_POSITION_INT")) < want_pos:
            assert time.monotonic() < t_guard, f"the threaded vehicle stopped sending ({len(msgs)} messages)"
            m = rx.recv_match(blocking=True, timeout=0.1)
            if m is not None:
                msgs.append(m)
    finally:
        stop.set()
        th.join(timeout=WAIT_S)
    for mtype, rate_hz in (("ATTITUDE_QUATERNION", 50), ("GLOBAL_POSITION_INT", 25)):
        stamps = [m.time_boot_ms for m in _of(msgs, mtype)]
        assert all(a < b for a, b in zip(stamps, stamps[1:])), (mtype, stamps)
        busiest = max(sum(t0 <= t < t0 + 1000 for t in stamps) for t0 in stamps)
        assert busiest <= rate_hz + 1, (mtype, busiest, stamps)


# ----------------------------------------------------------------------------- services


@pytest.mark.integration
def test_timesync_request_is_answered_with_our_boot_time(link):
    rx, vehicle = link
    _prime(rx, vehicle, 5_000_000)
    _timesync(rx, 0, 987_654_321_000)
    reply = _until(vehicle, 5_000_000, rx, "TIMESYNC")
    assert reply.tc1 == 5_000_000 * 1000  # ns on the vehicle's boot clock
    assert reply.ts1 == 987_654_321_000
    if hasattr(reply, "target_system"):
        assert (reply.target_system, reply.target_component) == (GCS_SYS, GCS_COMP)


@pytest.mark.integration
def test_timesync_response_is_not_answered(link):
    rx, vehicle = link
    _prime(rx, vehicle)
    _timesync(rx, 123, 456)  # tc1 != 0: somebody's reply, not a request
    deadline = time.monotonic() + WAIT_S  # wait for the event (the vehicle received it), bounded
    while time.monotonic() < deadline and vehicle.counters["rx_TIMESYNC"] == 0:
        vehicle.poll(0)
        time.sleep(0.002)
    assert vehicle.counters["rx_TIMESYNC"] == 1
    assert not _of(_drain(rx, quiet_s=0.1), "TIMESYNC")


def _command(rx, vehicle, now_us, cmd, p1=0.0, p2=0.0, target=(1, 1), use_int=False):
    if use_int:
        rx.mav.command_int_send(*target, 0, cmd, 0, 0, p1, p2, 0, 0, 0, 0, 0)
    else:
        rx.mav.command_long_send(*target, cmd, 0, p1, p2, 0, 0, 0, 0, 0)
    return _until(vehicle, now_us, rx, "COMMAND_ACK", lambda m: m.command == cmd)


@pytest.mark.integration
@pytest.mark.parametrize("use_int", [False, True], ids=["COMMAND_LONG", "COMMAND_INT"])
def test_set_message_interval_changes_the_rate_and_is_acked(link, use_int):
    rx, vehicle = link
    _prime(rx, vehicle)
    ack = _command(rx, vehicle, 0, 511, 31, 100_000, use_int=use_int)  # #31 at 10 Hz
    assert ack.result == 0  # ACCEPTED
    assert (ack.target_system, ack.target_component) == (GCS_SYS, GCS_COMP)
    assert vehicle.message_interval_us(31) == 100_000
    _drain(rx, quiet_s=0.05)
    _lockstep(vehicle, 0, 1_000_000)
    assert len(_of(_drain(rx), "ATTITUDE_QUATERNION")) == 10

    # commands arrive at the last polled time of the previous window, so no stream is due
    assert _command(rx, vehicle, 1_000_000 - STEP_US, 511, 33, -1, use_int=use_int).result == 0  # disable #33
    _drain(rx, quiet_s=0.05)
    _lockstep(vehicle, 1_000_000, 2_000_000)
    msgs = _drain(rx)
    assert len(_of(msgs, "GLOBAL_POSITION_INT")) == 0 and len(_of(msgs, "ATTITUDE_QUATERNION")) == 10

    assert _command(rx, vehicle, 2_000_000 - STEP_US, 511, 31, 0, use_int=use_int).result == 0  # back to default
    assert vehicle.message_interval_us(31) == 20_000
    _drain(rx, quiet_s=0.05)
    _lockstep(vehicle, 2_000_000, 3_000_000)
    assert len(_of(_drain(rx), "ATTITUDE_QUATERNION")) == 50


@pytest.mark.integration
@pytest.mark.parametrize(
    "cmd, p1, p2, result",
    [
        (511, 63, 100_000, 2),  # GLOBAL_POSITION_INT_COV (#63): we do not emit it -> DENIED
        (511, 285, 100_000, 2),  # gimbal status, but not gimballed -> DENIED
        (511, 31.5, 100_000, 2),  # not an integer message id
        (511, 31, -2, 2),  # bad interval
        (511, float("nan"), 1, 2),
        (176, 1, 0, 3),  # MAV_CMD_DO_SET_MODE: UNSUPPORTED
        (400, 1, 0, 3),  # MAV_CMD_COMPONENT_ARM_DISARM: UNSUPPORTED (520, AUTOPILOT_VERSION, is answered)
    ],
)
def test_unsupported_requests_are_refused_with_an_ack(link, cmd, p1, p2, result):
    rx, vehicle = link
    _prime(rx, vehicle)
    ack = _command(rx, vehicle, 0, cmd, p1, p2)
    assert ack.result == result
    assert vehicle.message_interval_us(31) == 20_000
    assert vehicle.counters[{2: "ack_denied", 3: "ack_unsupported"}[result]] == 1


@pytest.mark.integration
def test_command_for_another_system_is_ignored(link):
    rx, vehicle = link
    _prime(rx, vehicle)
    rx.mav.command_long_send(7, 1, 511, 0, 31, 100_000, 0, 0, 0, 0, 0)
    deadline = time.monotonic() + WAIT_S
    while vehicle.counters["rx_COMMAND_LONG"] == 0 and time.monotonic() < deadline:
        vehicle.poll(0)
        time.sleep(0.002)
    assert vehicle.counters["rx_COMMAND_LONG"] == 1
    assert vehicle.message_interval_us(31) == 20_000
    assert not _of(_drain(rx, quiet_s=0.1), "COMMAND_ACK")


@pytest.mark.integration
def test_request_message_sends_one_now(link):
    rx, vehicle = link
    _prime(rx, vehicle)
    _state(vehicle, 0)
    vehicle.poll(0)
    _drain(rx, quiet_s=0.05)
    ack = _command(rx, vehicle, 1000, 512, 33)
    assert ack.result == 0
    (pos,) = _of(_drain(rx), "GLOBAL_POSITION_INT")
    assert pos.lat == 473977419


@pytest.mark.integration
@pytest.mark.parametrize("yaw_frame, flags", [("earth", 8 | 16 | 64), ("vehicle", 4 | 8 | 16 | 32)])
def test_gimballed_vehicle_sends_gimbal_device_attitude_status(yaw_frame, flags):
    """q_gimbal is q_ned_from_gimbal; on the wire: NED as is (earth frame: YAW_IN_EARTH_FRAME | PITCH_LOCK | YAW_LOCK,
    the gimbal aiming at the target, delta_yaw = vehicle yaw), or with the vehicle's yaw taken out as ArduPilot sends
    it (vehicle frame: ROLL_LOCK | PITCH_LOCK | YAW_LOCK | YAW_IN_VEHICLE_FRAME, delta_yaw NaN)."""
    port = free_udp_port()
    rx = open_mavlink2(f"udpin:127.0.0.1:{port}", GCS_SYS, GCS_COMP)
    q_ned_from_gimbal = tuple(float(x) for x in quat_from_euler(0.05, -0.5, 2.2))
    with MavlinkVehicle(
        f"udpout:127.0.0.1:{port}", gimballed=True, gimbal_rate_hz=10, gimbal_yaw_frame=yaw_frame
    ) as vehicle:
        _lockstep(vehicle, 0, 1_000_000, gimbal=q_ned_from_gimbal)
        msgs = _drain(rx)
    rx.close()
    gim = _of(msgs, "GIMBAL_DEVICE_ATTITUDE_STATUS")
    assert len(gim) == 10
    g = gim[3]
    assert g.time_boot_ms == 300 and g.flags == flags and g.gimbal_device_id == 1
    yaw_rad = float(euler_from_quat(np.asarray(Q_NED_FROM_BODY))[2])
    if yaw_frame == "earth":
        assert g.delta_yaw == pytest.approx(yaw_rad, abs=1e-6)
    else:
        assert math.isnan(g.delta_yaw)
    q_wire = np.asarray(g.q, dtype=float)
    q_back = q_wire if yaw_frame == "earth" else quat_multiply(quat_from_euler(0.0, 0.0, yaw_rad), q_wire)
    # same rotation (q and -q are equal)
    assert abs(float(np.dot(q_back, q_ned_from_gimbal))) == pytest.approx(1.0, abs=1e-6)
    if yaw_frame == "vehicle":  # roll/pitch stay horizon-relative, yaw becomes relative to the nose
        r, p, y = (float(a) for a in euler_from_quat(q_wire))
        assert (r, p) == pytest.approx((0.05, -0.5), abs=1e-5)
        assert y == pytest.approx(2.2 - yaw_rad, abs=1e-5)


def test_earth_frame_gimbal_flags_say_the_earth_frame_by_either_rule_and_what_the_gimbal_holds():
    """common.xml #285: YAW_IN_EARTH_FRAME names the q's frame; a receiver of the older rule (no YAW_IN_* flag
    understood) takes YAW_LOCK for the earth frame, so the earth q carries it too.  The simulated gimbal aims at the
    target (pitch and yaw the earth's: PITCH_LOCK, YAW_LOCK); a pan/tilt, its roll follows the mount (no ROLL_LOCK)."""
    from groundsim.io.mavlink_vehicle import gimbal_device_attitude_status
    from onboard.io.mavlink_wire import GimbalDeviceAttitudeStatus, GimbalReference

    q_ned_from_gimbal = tuple(float(x) for x in quat_from_euler(0.05, -0.5, 2.2))
    st = gimbal_device_attitude_status(0, 0, q_ned_from_gimbal, Q_NED_FROM_BODY, "earth")
    f = st.flags
    older_rule_says_earth = bool(f & mavlink2.GIMBAL_DEVICE_FLAGS_YAW_LOCK)
    assert (
        f & mavlink2.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME
        and not f & mavlink2.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME
    )
    assert older_rule_says_earth
    assert f & mavlink2.GIMBAL_DEVICE_FLAGS_PITCH_LOCK and not f & mavlink2.GIMBAL_DEVICE_FLAGS_ROLL_LOCK
    assert GimbalDeviceAttitudeStatus.from_message(st.to_message()).reference == GimbalReference.EARTH


@pytest.mark.integration
def test_gimbal_status_is_not_sent_when_not_gimballed(link):
    rx, vehicle = link
    _lockstep(vehicle, 0, 200_000, gimbal=(1.0, 0.0, 0.0, 0.0))
    assert not _of(_drain(rx), "GIMBAL_DEVICE_ATTITUDE_STATUS")


@pytest.mark.integration
def test_garbage_on_the_wire_is_counted_and_survived(link):
    rx, vehicle = link
    _prime(rx, vehicle)
    (addr,) = rx.clients
    rng = np.random.default_rng(3)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for _ in range(50):
            s.sendto(rng.integers(0, 256, rng.integers(1, 300), dtype=np.uint8).tobytes(), addr)
        good = bytearray(rx.mav.timesync_encode(0, 42).pack(rx.mav))
        good[-1] ^= 0xFF  # bad CRC
        s.sendto(bytes(good), addr)
    deadline = time.monotonic() + WAIT_S  # until the garbage has been read (an event), bounded
    while time.monotonic() < deadline and vehicle.counters.get("rx_bad_data", 0) == 0:
        vehicle.poll(0)  # must not raise
        time.sleep(0.002)
    assert vehicle.counters["rx_bad_data"] >= 1
    assert not any(k.startswith("rx_UNKNOWN") for k in vehicle.counters)  # bounded counter keys
    # still serving; pymavlink's parser may swallow a few frames after garbage before it
    # resyncs, so request periodically, as a real TIMESYNC requester does
    t_end = time.monotonic() + WAIT_S
    reply, k = None, 0
    while reply is None and time.monotonic() < t_end:
        k += 1
        _timesync(rx, 0, 1000 + k)
        for _ in range(20):
            vehicle.poll(0)
            time.sleep(0.002)
        reply = rx.recv_match(type="TIMESYNC", blocking=False)
    assert reply is not None and 1000 < reply.ts1 <= 1000 + k
    assert k <= 10, f"took {k} requests to resync"
    assert not any(k.startswith("rx_UNKNOWN") for k in vehicle.counters)  # all the garbage has been read by now


# ----------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    "connection",
    [
        "",
        "udpout:127.0.0.1",
        "udpout:127.0.0.1:notaport",
        "udpout:127.0.0.1:0",
        "udpout:127.0.0.1:70000",
        "bogus:1:2",
        "14540",
        "udpout::14540",
    ],
)
def test_malformed_connection_strings(connection):
    with pytest.raises(MavlinkConfigError) as e:
        MavlinkVehicle(connection)
    assert isinstance(e.value, IrtrackError) and "\n" not in str(e.value)


def test_the_vehicle_takes_the_daemons_connection_grammar():
    """One parser (onboard.io.mavlink_endpoint.parse_endpoint) for the simulator and the daemon."""
    ep = parse_endpoint("udpout:127.0.0.1:14540")
    assert (ep.kind, ep.host, ep.port) == ("udpout", "127.0.0.1", 14540)
    ep = parse_endpoint("udp:0.0.0.0:14540")
    assert (ep.kind, ep.host, ep.port, ep.listens) == ("udpin", "0.0.0.0", 14540, True)
    assert (parse_endpoint("tcp:localhost:5760").kind, parse_endpoint("tcp:localhost:5760").port) == ("tcp", 5760)
    ep = parse_endpoint("/dev/ttyUSB0,57600")
    assert (ep.kind, ep.device, ep.baud, ep.host, ep.port) == ("serial", "/dev/ttyUSB0", 57600, None, None)


@pytest.mark.integration
def test_udpin_port_in_use_is_a_typed_one_line_error():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        with pytest.raises(MavlinkLinkError) as e:
            MavlinkVehicle(f"udpin:127.0.0.1:{port}")
    assert "in use" in str(e.value) and str(port) in str(e.value) and "\n" not in str(e.value)


@pytest.mark.integration
def test_udpin_port_held_by_another_pymavlink_is_in_use_too():
    port = free_udp_port()
    first = open_mavlink2(f"udpin:127.0.0.1:{port}", 1, 1)  # SO_REUSEADDR, like any pymavlink udpin
    try:
        with pytest.raises(MavlinkLinkError):
            MavlinkVehicle(f"udpin:127.0.0.1:{port}")
    finally:
        first.close()


@pytest.mark.integration
def test_tcp_refused_is_a_link_error():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # bound, not listening: connect is refused
        with pytest.raises(MavlinkLinkError):
            MavlinkVehicle(f"tcp:127.0.0.1:{port}")


@pytest.mark.integration
@pytest.mark.parametrize(
    "field, value",
    [
        ("lat_deg", 91.0),
        ("lon_deg", float("nan")),
        ("alt_amsl_m", float("inf")),
        ("v_ned_mps", (1.0, 2.0)),
        ("q_ned_from_body", (0.0, 0.0, 0.0, 0.0)),
        ("q_ned_from_body", (1.0, 1.0, 0.0, 0.0)),
        ("body_rates_radps", (0.0, float("nan"), 0.0)),
        ("heading_rad", float("inf")),
        ("time_boot_us", -1),
        ("q_gimbal", (2.0, 0.0, 0.0, 0.0)),
    ],
)
def test_bad_state_is_an_input_error_naming_the_field(link, field, value):
    _, vehicle = link
    with pytest.raises(InputError) as e:
        _state(vehicle, 0, **{field: value})
    assert field in str(e.value)


@pytest.mark.parametrize(
    "kw, expected",
    [
        (dict(att_rate_hz=0), "must be in (0, 1000] Hz, got 0"),
        (dict(pos_rate_hz=-1), "must be in (0, 1000] Hz, got -1"),
        (dict(sysid=0), "must be an integer in [1, 255], got 0"),
        (dict(compid=256), "must be an integer in [1, 255], got 256"),
        (dict(att_rate_hz=float("nan")), "must be in (0, 1000] Hz, got nan"),
        (dict(gimbal_yaw_frame="body"), "must be 'earth' or 'vehicle', got 'body'"),
    ],
    ids=["att_rate_0", "pos_rate_negative", "sysid_0", "compid_256", "att_rate_nan", "gimbal_yaw_frame_body"],
)
def test_bad_options(kw, expected):
    (field,) = kw
    with pytest.raises(MavlinkConfigError) as e:
        MavlinkVehicle("udpout:127.0.0.1:9", **kw)
    assert str(e.value) == f"MavlinkVehicle.{field} {expected}"


@pytest.mark.integration
def test_no_environment_side_effects():
    before = os.environ.get("MAVLINK20")
    port = free_udp_port()
    with MavlinkVehicle(f"udpout:127.0.0.1:{port}") as v:
        v.poll(0)
    assert os.environ.get("MAVLINK20") == before


# ----------------------------------------------------------------------------- MAVSDK


@pytest.mark.integration
def test_mavsdk_discovers_the_autopilot_and_reads_position_and_attitude():
    mavsdk = pytest.importorskip("mavsdk")
    from mavsdk.plugins.telemetry.telemetry import Telemetry

    with mavsdk_autopilot(mavsdk) as (system, _):
        assert system.has_autopilot() and system.get_system_id() == 1
        assert int(system.vehicle_type()) == int(mavsdk.Vehicle.MULTICOPTER)
        tel = Telemetry(system)
        deadline = time.monotonic() + WAIT_S
        pos = att = None
        while time.monotonic() < deadline:
            pos, att = tel.position(), tel.attitude_quaternion()
            if not math.isnan(pos.latitude_deg) and not math.isnan(att.w):
                break
            time.sleep(0.05)
        assert pos.latitude_deg == pytest.approx(LAT_DEG, abs=1e-7)
        assert pos.longitude_deg == pytest.approx(LON_DEG, abs=1e-7)
        assert pos.absolute_altitude_m == pytest.approx(ALT_AMSL_M, abs=1e-3)
        assert pos.relative_altitude_m == pytest.approx(ALT_REL_M, abs=1e-3)
        assert (att.w, att.x, att.y, att.z) == pytest.approx(Q_NED_FROM_BODY, abs=1e-6)


@pytest.mark.integration
def test_mavsdk_reads_the_local_position_and_velocity_ned():
    """MAVSDK's telemetry position_velocity_ned is LOCAL_POSITION_NED's: the vehicle holds still over home."""
    mavsdk = pytest.importorskip("mavsdk")
    from mavsdk.plugins.telemetry.telemetry import Telemetry

    with mavsdk_autopilot(mavsdk) as (system, _):
        tel = Telemetry(system)
        deadline = time.monotonic() + WAIT_S
        pv = tel.position_velocity_ned()
        while math.isnan(pv.position.down_m) and time.monotonic() < deadline:  # NaN: none yet
            time.sleep(0.05)
            pv = tel.position_velocity_ned()
        p, vel = pv.position, pv.velocity
        assert (p.north_m, p.east_m, p.down_m) == pytest.approx((0.0, 0.0, -ALT_REL_M), abs=1e-5)
        assert (vel.north_m_s, vel.east_m_s, vel.down_m_s) == pytest.approx(V_NED_MPS, rel=F32_REL)


@pytest.mark.integration
def test_gnss_outage_withholds_global_position_and_reports_no_fix_while_attitude_goes_on():
    port = free_udp_port()
    rx = open_mavlink2(f"udpin:127.0.0.1:{port}", GCS_SYS, GCS_COMP)
    outage = (1_000_000, 2_000_000)
    with MavlinkVehicle(
        f"udpout:127.0.0.1:{port}", unix_time_at_boot_us=1_700_000_000_000_000, gnss_outage_us=outage
    ) as vehicle:
        msgs = []
        for t0_us in range(0, 3_000_000, 500_000):  # drained every 0.5 s: 3 s of streams overflow a socket's buffer
            _lockstep(vehicle, t0_us, t0_us + 500_000)
            msgs += _drain(rx)
    rx.close()
    inside = lambda m: outage[0] <= m.time_boot_ms * 1000 < outage[1]  # noqa: E731
    pos = _of(msgs, "GLOBAL_POSITION_INT")
    att = _of(msgs, "ATTITUDE_QUATERNION")
    assert not any(inside(m) for m in pos)
    assert sum(m.time_boot_ms < 1000 for m in pos) == 25 and sum(m.time_boot_ms >= 2000 for m in pos) >= 20  # 25 Hz
    assert sum(inside(m) for m in att) == 50  # attitude goes on at 50 Hz
    gps = _of(msgs, "GPS_RAW_INT")
    in_fix = [g.fix_type for g in gps if outage[0] <= g.time_usec - 1_700_000_000_000_000 < outage[1]]
    out_fix = [g.fix_type for g in gps if not outage[0] <= g.time_usec - 1_700_000_000_000_000 < outage[1]]
    assert in_fix and set(in_fix) == {mavlink2.GPS_FIX_TYPE_NO_FIX}
    assert out_fix and set(out_fix) == {mavlink2.GPS_FIX_TYPE_3D_FIX}
    # without a fix the speed, course and their accuracy are unknown too (common.xml: UINT16_MAX, 0), not the truth's
    during = [g for g in gps if outage[0] <= g.time_usec - 1_700_000_000_000_000 < outage[1]]
    assert {(g.vel, g.cog, g.vel_acc, g.eph, g.epv) for g in during} == {(65535, 65535, 0, 65535, 65535)}
    after = [g for g in gps if not outage[0] <= g.time_usec - 1_700_000_000_000_000 < outage[1]]
    assert all(g.vel < 65535 and g.vel_acc > 0 for g in after)


# ----------------------------------------------------------------------------- home, relative and ellipsoidal altitude


def _captured_vehicle(**kw):
    """A vehicle whose writes are parsed in process (no datagram leaves): (vehicle, messages so far)."""
    v = MavlinkVehicle("udpout:127.0.0.1:9", unix_time_at_boot_us=1_700_000_000_000_000, **kw)
    parser = mavlink2.MAVLink(None)
    got: list = []

    def write(buf):
        m = parser.parse_char(bytes(buf))
        if m is not None:
            got.append(m)

    v._conn.write = write
    return v, got


def _first_poll(**kw) -> list:
    """What a captured vehicle (:func:`_captured_vehicle` with ``kw``) sends at its first poll of one state."""
    v, got = _captured_vehicle(**kw)
    try:
        _state(v, 0)
        v.poll(0)
    finally:
        v.close()
    return got


def _request_home(v, now_us: int) -> None:
    msg = mavlink2.MAVLink_command_long_message(1, 1, mavlink2.MAV_CMD_GET_HOME_POSITION, 0, 0, 0, 0, 0, 0, 0, 0)
    v._on_command(mavlink2.MAVLink(None).parse_char(bytes(msg.pack(mavlink2.MAVLink(None, 255, 190)))))
    v.poll(now_us)


def test_relative_alt_is_above_the_home_position_the_vehicle_reports():
    """common.xml GLOBAL_POSITION_INT.relative_alt: "Altitude above home".  The simulator's tick states, with its
    navigation errors, through the vehicle: every #33's alt - relative_alt is HOME_POSITION's altitude."""
    from groundsim.world.scenario import load_scenario, resolve_scenario_path
    from groundsim.world.sim import SimCore

    sc = load_scenario(resolve_scenario_path("P1"))
    core = SimCore(sc, 0, 2.0, render=False)
    v, got = _captured_vehicle()
    try:
        for i in range(0, len(core.times_s), 3):
            st = v.update_state(**core.vehicle_state(i), nav_error=core.nav_error(i))
            v.poll(st.time_boot_us)
        _request_home(v, st.time_boot_us + 1)
    finally:
        v.close()
    (home,) = [m for m in got if m.get_type() == "HOME_POSITION"][-1:]
    pos = _of(got, "GLOBAL_POSITION_INT")
    assert len(pos) >= 10 and len({p.alt for p in pos}) > 1  # the observer climbs or sinks: a real check
    assert home.altitude == round(sc.origin.alt_m * 1000)  # the ground it took off from
    for p in pos:
        assert abs(p.alt - p.relative_alt - home.altitude) <= 1  # mm: each rounded once


ATOL_LOCAL_M = 1e-3  # 1 mm: float32 x, y of a few km carry ~0.2 mm


def _command_long(v, cmd: int, p1: float, p2: float = 0.0) -> None:
    msg = mavlink2.MAVLink_command_long_message(1, 1, cmd, 0, p1, p2, 0, 0, 0, 0, 0)
    v._on_command(mavlink2.MAVLink(None).parse_char(bytes(msg.pack(mavlink2.MAVLink(None, GCS_SYS, GCS_COMP)))))


def test_local_position_ned_is_the_position_about_home_with_z_minus_relative_alt():
    """common.xml LOCAL_POSITION_NED (#32), as ArduPilot and PX4 send it about their EKF origin: here HOME_POSITION
    (the first state's lat/lon at the altitude relative_alt is measured from).  The truth: points put at known
    north/east metres from home by pymap3d (the plane tangent at home) and at known heights above it."""
    pymap3d = pytest.importorskip("pymap3d")
    home_alt_m = ALT_AMSL_M - ALT_REL_M
    truth = [  # (north, east, height above home m, v_ned m/s)
        (0.0, 0.0, ALT_REL_M, V_NED_MPS),
        (1234.5, -678.9, 150.25, (-3.5, 20.25, 1.5)),
        (-2500.0, 3100.0, 80.0, (0.0, 0.0, 0.0)),
    ]
    v, got = _captured_vehicle()
    try:
        for k, (n_m, e_m, h_m, v_ned) in enumerate(truth):
            lat, lon, _ = pymap3d.ned2geodetic(n_m, e_m, 0.0, LAT_DEG, LON_DEG, home_alt_m)
            t_us = 1_000_000 * k
            _state(v, t_us, lat_deg=lat, lon_deg=lon, alt_amsl_m=home_alt_m + h_m, alt_rel_m=h_m, v_ned_mps=v_ned)
            v.poll(t_us)
    finally:
        v.close()
    local = _of(got, "LOCAL_POSITION_NED")
    pos = _of(got, "GLOBAL_POSITION_INT")
    assert len(local) == len(truth) == len(pos)
    for m, p, (n_m, e_m, h_m, v_ned) in zip(local, pos, truth):
        assert m.time_boot_ms == p.time_boot_ms  # the state's stamp, as #33's
        assert (m.x, m.y) == pytest.approx((n_m, e_m), abs=ATOL_LOCAL_M)
        assert m.z == pytest.approx(-h_m, rel=F32_REL)
        assert m.z == pytest.approx(-p.relative_alt / 1000.0, abs=1e-3)  # mm: #33 rounds it once
        assert (m.vx, m.vy, m.vz) == pytest.approx(v_ned, rel=F32_REL, abs=1e-6)


def test_local_position_ned_is_streamed_set_requested_and_withheld_without_gnss_as_global_position():
    v, got = _captured_vehicle(pos_rate_hz=25, gnss_outage_us=(3_000_000, 4_000_000))
    try:
        _lockstep(v, 0, 1_000_000)
        assert v.message_interval_us(32) == 40_000  # #33's rate
        _command_long(v, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 32, 100_000)  # at 995 ms, the last poll
        _lockstep(v, 1_000_000, 2_000_000)
        _command_long(v, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 32, -1)
        _lockstep(v, 2_000_000, 2_500_000)
        _command_long(v, mavlink2.MAV_CMD_REQUEST_MESSAGE, 32)
        _lockstep(v, 2_500_000, 3_000_000)
        _command_long(v, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 32, 0)  # the default again
        _lockstep(v, 3_000_000, 5_000_000)
    finally:
        v.close()
    assert [a.result for a in _of(got, "COMMAND_ACK")] == [mavlink2.MAV_RESULT_ACCEPTED] * 4
    ms = [m.time_boot_ms for m in _of(got, "LOCAL_POSITION_NED")]
    default = [t for t in ms if t < 1000]
    at_10hz = [t for t in ms if 1000 <= t < 2000]
    assert len(default) == 25 and set(np.diff(default)) == {40}
    assert at_10hz == [1000, *range(1095, 2000, 100)]  # the new schedule counts from the command (995 ms)
    assert [t for t in ms if 2000 <= t < 3000] == [2500]  # off, but one on request
    assert not [t for t in ms if 3000 <= t < 4000]  # no fix: no position, as #33
    assert len([t for t in ms if t >= 4000]) == 25


def test_gps_raw_int_alt_ellipsoid_is_alt_plus_the_worlds_geoid_undulation():
    from groundsim.io.mavlink_vehicle import GEOID_UNDULATION_M

    got = _first_poll()
    (gps,) = _of(got, "GPS_RAW_INT")
    (pos,) = _of(got, "GLOBAL_POSITION_INT")
    assert gps.alt == pos.alt == round(ALT_AMSL_M * 1000)
    assert gps.alt_ellipsoid == gps.alt + round(GEOID_UNDULATION_M * 1000)


@pytest.mark.parametrize(
    ("case", "fix", "h_mm", "v_mm"),
    [("RTK", mavlink2.GPS_FIX_TYPE_RTK_FIXED, 28, 20), ("GNSS", mavlink2.GPS_FIX_TYPE_3D_FIX, 1500, 1500),
     ("exact", mavlink2.GPS_FIX_TYPE_RTK_FIXED, 10, 10)],
)  # fmt: skip
def test_gps_raw_int_reports_the_navigation_cases_fix_and_accuracy(case, fix, h_mm, v_mm):
    """It said a 3-D fix of 0.5 / 0.8 m whatever the case: an RTK case's 2 cm, a GNSS case's 1.5 m offset alike."""
    from groundsim.world.noise_cases import load_noise_cases
    from onboard.io.mavlink_wire import GpsRawInt

    (gps,) = _of(_first_poll(gnss_accuracy=load_noise_cases()[case].gnss_accuracy_m()), "GPS_RAW_INT")
    assert (gps.fix_type, gps.h_acc, gps.v_acc) == (fix, h_mm, v_mm)
    read = GpsRawInt.from_message(gps)  # as the daemon reads it
    assert (read.h_acc_m, read.v_acc_m) == (h_mm / 1000, v_mm / 1000)


def test_gps_raw_int_without_a_fix_says_its_accuracy_is_unknown():
    (gps,) = _of(_first_poll(gnss_outage_us=(0, 10_000_000)), "GPS_RAW_INT")
    assert (gps.fix_type, gps.satellites_visible, gps.h_acc, gps.v_acc) == (mavlink2.GPS_FIX_TYPE_NO_FIX, 0, 0, 0)


@pytest.mark.integration
@pytest.mark.parametrize("interval_us", [-1, 5_000_000])
def test_the_heartbeat_cannot_be_switched_off_or_slowed(link, interval_us):
    """As PX4: every component heartbeats; SET_MESSAGE_INTERVAL of HEARTBEAT is FAILED (accepted, -1 silenced the
    vehicle: the daemon and every ground station took the link for lost)."""
    rx, vehicle = link
    _prime(rx, vehicle)
    ack = _command(rx, vehicle, 0, 511, 0, interval_us)
    assert ack.result == 4  # MAV_RESULT_FAILED
    assert vehicle.message_interval_us(0) == 1_000_000


@pytest.mark.integration
@pytest.mark.parametrize("via", ["get", "request"])
def test_message_intervals_can_be_asked_as_a_px4_answers(link, via):
    """GET_MESSAGE_INTERVAL (510) and REQUEST_MESSAGE(244, param2 = id): the ACK, then MESSAGE_INTERVAL with the
    stream's interval (-1 off, 0 a message not streamed); both were refused (UNSUPPORTED, DENIED)."""
    rx, vehicle = link
    _prime(rx, vehicle)

    def ask(msg_id: float):
        if via == "get":
            ack = _command(rx, vehicle, 0, 510, msg_id)
        else:
            ack = _command(rx, vehicle, 0, 512, 244, msg_id)
        got = _of(_drain(rx, quiet_s=0.1), "MESSAGE_INTERVAL")
        return ack.result, [(m.message_id, m.interval_us) for m in got]

    assert ask(31) == (0, [(31, 20_000)])
    assert _command(rx, vehicle, 0, 511, 33, -1).result == 0  # position off
    assert ask(33) == (0, [(33, -1)])
    assert ask(63) == (0, [(63, 0)])  # GLOBAL_POSITION_INT_COV: not streamed
    assert ask(31.5) == (2, [])  # not a message id: DENIED, nothing sent


@pytest.mark.integration
def test_a_signing_key_signs_everything_the_vehicle_sends_and_it_takes_only_signed_commands(tmp_path):
    """--mavlink-signing-key: the simulated autopilot with signing on, so that the daemon's signed link can be flown
    against it.  Checked with pymavlink's own signature check (a parser holding the key)."""
    from groundsim.app.cli import _signing_key

    key_file = tmp_path / "k"
    key_file.write_text("a passphrase\n")
    key = _signing_key(str(key_file))
    port = free_udp_port()
    rx = open_mavlink2(f"udpin:127.0.0.1:{port}", GCS_SYS, GCS_COMP)
    rx.setup_signing(key, sign_outgoing=False)  # pymavlink verifies what arrives; sends unsigned below
    vehicle = MavlinkVehicle(f"udpout:127.0.0.1:{port}", unix_time_at_boot_us=1_700_000_000_000_000, signing_key=key)
    try:
        _prime(rx, vehicle)
        got = _drain(rx)
        assert got and all(m._signed for m in got), [m.get_type() for m in got if not m._signed]
        assert rx.mav.signing.goodsig_count >= len(got) and rx.mav.signing.badsig_count == 0
        rx.mav.command_long_send(1, 1, 511, 0, 31, 100_000, 0, 0, 0, 0, 0)  # unsigned: refused
        deadline = time.monotonic() + WAIT_S
        while vehicle.counters["rx_unsigned"] == 0 and time.monotonic() < deadline:
            vehicle.poll(0)
            time.sleep(0.002)
        assert vehicle.counters["rx_unsigned"] == 1 and vehicle.message_interval_us(31) == 20_000
        rx.setup_signing(key, sign_outgoing=True)  # the same command signed: taken
        ack = _command(rx, vehicle, 0, 511, 31, 100_000)
        assert ack.result == 0 and ack._signed and vehicle.message_interval_us(31) == 100_000
    finally:
        vehicle.close()
        rx.close()


def test_a_bad_signing_key_file_is_one_line_naming_the_option(tmp_path):
    from groundsim.app.cli import _signing_key

    with pytest.raises(ConfigError, match=r"^--mavlink-signing-key: expected a readable key file, got '.*absent'"):
        _signing_key(str(tmp_path / "absent"))
    (tmp_path / "empty").write_text("")
    with pytest.raises(ConfigError, match=r"^--mavlink-signing-key: expected 32 raw bytes, .*got an empty key in"):
        _signing_key(str(tmp_path / "empty"))
