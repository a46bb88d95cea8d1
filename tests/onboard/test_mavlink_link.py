"""MavlinkLink against the fake autopilot (tests/fakes.py) on 127.0.0.1 (same process, no threads, fake clock)."""

from __future__ import annotations

import dataclasses
import logging
import math
import select
import socket
import time
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mav

from groundsim.io.ports import free_udp_port
from onboard.core.counters import RejectCounter
from onboard.core.errors import ConfigError, InputError
from onboard.core.frames import (
    CameraMount,
    GeodeticOrigin,
    euler_from_quat,
    ned_from_geodetic,
    q_ned_from_level,
    quat_from_euler,
    quat_multiply,
    quat_rotate,
)
from onboard.core.pose import PoseBuffer
from onboard.io.mavlink_link import LINK_CONNECTED, LINK_LOST, LINK_WAITING, MavlinkConfig, MavlinkLink
from onboard.io.mavlink_rates import REASK_S
from onboard.io.mavlink_wire import (
    CameraTrackingGeoStatus,
    CameraTrackingImageStatus,
    GimbalDeviceAttitudeStatus,
    GpsRawInt,
    Heartbeat,
    SystemTime,
    Timesync,
    command_ack_message,
    pack,
)
from tests.fakes import FakeAutopilot, FakeClock, silent_tcp_server

pytestmark = [pytest.mark.integration, pytest.mark.timeout(30)]

WAIT_S = 3.0  # upper bound on any single wait for a loopback event
AP_SYSID = 7
ATOL_M = 0.02  # GLOBAL_POSITION_INT quantisation: 1e-7 deg ~ 1.1 cm, alt 1 mm
ATOL_RAD = 1e-6  # float32 quaternion on the wire
TIMESYNC_TOL_US = 20_000  # one-way delay asymmetry on a loaded 2-core box, generous
LAT0, LON0, ALT0 = 47.3977, 8.5456, 488.0
UNPINNED = MavlinkConfig(autopilot_sysid=None)  # lock onto whichever autopilot heartbeats


def loopback_link(
    port: int,
    origin: GeodeticOrigin,
    *,
    gimballed: bool,
    config: MavlinkConfig | None = None,
    link_kw: dict[str, Any] | None = None,
    pose_cls: type[PoseBuffer] = PoseBuffer,
    **counter_kw,
) -> tuple[FakeClock, RejectCounter, PoseBuffer, MavlinkLink]:
    """(clock, counter, pose, link): a MavlinkLink on udpin 127.0.0.1:``port`` on a fake clock, feeding a fresh
    ``pose_cls`` buffer at ``origin`` and counting into a fresh RejectCounter (``counter_kw``)."""
    clock = FakeClock()
    counter = RejectCounter(clock=clock, **counter_kw)
    pose = pose_cls(mount=CameraMount(gimballed=gimballed), origin=origin, counter=counter)
    config = dataclasses.replace(UNPINNED if config is None else config, connection=f"udpin:127.0.0.1:{port}")
    link = MavlinkLink(config, pose, counter, gimballed=gimballed, clock=clock, **(link_kw or {}))
    return clock, counter, pose, link


class Rig:
    def __init__(self, gimballed: bool = False, config: MavlinkConfig | None = None, **link_kw: Any) -> None:
        self.port = free_udp_port()
        origin = GeodeticOrigin(LAT0, LON0, ALT0)
        self.clock, self.counters, self.pose, self.link = loopback_link(
            self.port, origin, gimballed=gimballed, config=config, link_kw=link_kw
        )
        self.ap = FakeAutopilot(self.port, sysid=AP_SYSID, mav_type=mav.MAV_TYPE_FIXED_WING)

    def step(self) -> None:
        self.link.poll()
        self.link.tick()
        self.ap.pump()

    def drive(self, cond, timeout_s: float = WAIT_S) -> bool:
        """Run both ends until cond() holds; waits on the sockets, bounded in time."""
        deadline = time.monotonic() + timeout_s
        fds = [self.link.fileno(), self.ap.conn.port.fileno()]
        while time.monotonic() < deadline:
            self.step()
            if cond():
                return True
            select.select(fds, [], [], 0.005)
        return False

    def heartbeats(self, n: int, sysid: int = AP_SYSID) -> None:
        """``n`` autopilot heartbeats 1 s apart on the fake clock, each handled before the next."""
        for k in range(n):
            if k:
                self.clock.t_s += 1.0
            before = self.link.messages_rx
            self.ap.as_component(sysid, 1)
            self.ap.heartbeat()
            self.ap.as_component(AP_SYSID, 1)
            assert self.drive(lambda before=before: self.link.messages_rx > before)

    def connect(self) -> None:
        """Heartbeats until the unpinned lock settles (1.5 s: the third one), then the rate requests."""
        if self.link.autopilot_sysid is None:
            self.heartbeats(3)
        else:
            self.ap.heartbeat()
        assert self.drive(
            lambda: self.link.state == LINK_CONNECTED and self.link.rates_confirmed == set(self.link.rate_plan)
        )

    def close(self) -> None:
        self.link.close()
        self.ap.close()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


# --------------------------------------------------------------------------- connection


def test_connects_heartbeats_requests_rates_and_fills_pose_buffer(rig):
    assert rig.link.state == LINK_WAITING
    rig.connect()
    ap = rig.ap
    assert sorted((mid, us) for mid, us, _ in ap.commands) == [(31, 10_000), (33, 40_000)]
    assert all(conf == 0 for *_, conf in ap.commands)
    # heartbeat as an onboard computer, with the autopilot's system id
    assert rig.drive(lambda: ap.got("HEARTBEAT"))
    hb = ap.got("HEARTBEAT")[0]
    assert (hb.type, hb.autopilot) == (mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID)
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (AP_SYSID, mav.MAV_COMP_ID_ONBOARD_COMPUTER)
    cmd = [m for m in ap.got("COMMAND_LONG")][0]
    assert (cmd.target_system, cmd.target_component) == (AP_SYSID, 1)

    # 10 m/s north, nose 30 deg right, 1 s of telemetry
    q = quat_from_euler(0.0, 0.0, math.radians(30.0))
    dlat_per_m = 1.0 / 111_180.0
    for k in range(51):
        ap.attitude(1000 * (1000 + 20 * k), q)
        if k % 2 == 0:
            ap.position(1000 * (1000 + 20 * k), LAT0 + 10.0 * 0.02 * k * dlat_per_m, LON0, ALT0 + 1.0, (10.0, 0.0, 0.0))
    assert rig.drive(lambda: rig.pose.sizes()["attitude"] == 51 and rig.pose.sizes()["position"] == 26)
    pose = rig.pose.pose_at(1_510_000)
    assert pose is not None
    expected = ned_from_geodetic(LAT0 + 10.0 * 0.51 * dlat_per_m, LON0, ALT0 + 1.0, GeodeticOrigin(LAT0, LON0, ALT0))
    assert expected[0] == pytest.approx(5.1, abs=0.01)  # ~111.18 km per degree of latitude here
    np.testing.assert_allclose(pose.body.p_ned_m, expected, atol=ATOL_M)
    assert pose.body.p_ned_m[2] == pytest.approx(-1.0, abs=ATOL_M)  # 1 m above the origin: down is negative
    # velocity and attitude are the local level's where the vehicle is, 5 m north: turned into the origin's NED
    q_lv = q_ned_from_level(LAT0 + 10.0 * 0.51 * dlat_per_m, LON0, GeodeticOrigin(LAT0, LON0, ALT0))
    np.testing.assert_allclose(pose.body.v_ned_mps, quat_rotate(q_lv, [10.0, 0.0, 0.0]), atol=1e-6)  # cm/s wire
    assert pose.body.v_ned_mps[2] > 5e-6  # the local north dips below the origin's horizon
    np.testing.assert_allclose(pose.body.q_ned_from_body, quat_multiply(q_lv, q), atol=ATOL_RAD)
    assert rig.counters.total == 0
    assert rig.link.home_alt_amsl_m == pytest.approx(ALT0 + 1.0, abs=ATOL_M)  # relative_alt 0: home is right here
    # the next sample (on course, 11 m north at 1.1 s, 4 m below its home) says its home is 5 m above the first one's
    ap.position(2_100_000, LAT0 + 11.0 * dlat_per_m, LON0, ALT0 + 1.0, (10.0, 0.0, 0.0), alt_rel_m=-4.0)
    assert rig.drive(lambda: abs(rig.link.home_alt_amsl_m - (ALT0 + 5.0)) < 1.0)
    assert rig.link.home_alt_amsl_m == pytest.approx(ALT0 + 5.0, abs=ATOL_M)  # alt - relative_alt
    # a GNSS dropout's #33 (lat = lon = 0, zero altitudes) is refused by the pose buffer: no home of 0 m from it
    ap.position(2_140_000, 0.0, 0.0, 0.0, alt_rel_m=0.0)
    assert rig.drive(lambda: rig.counters.counts.get("position_zero", 0) == 1)
    assert rig.link.home_alt_amsl_m == pytest.approx(ALT0 + 5.0, abs=ATOL_M)


def test_survives_random_bytes_bad_crc_and_bad_values(rig):
    rig.connect()
    ap = rig.ap
    rng = np.random.default_rng(7)
    for _ in range(5):
        ap.raw(bytes(rng.integers(0, 256, size=120, dtype=np.uint8)))
    good = Heartbeat(mav.MAV_TYPE_FIXED_WING, mav.MAV_AUTOPILOT_PX4).to_message()
    bad = bytearray(pack(good, codec=ap.conn.mav))
    bad[-3] ^= 0xFF  # a payload byte: the CRC no longer matches
    ap.raw(bytes(bad))
    # hostile values the typed encoders refuse go as raw messages
    ap.send(mav.MAVLink_attitude_quaternion_message(2000, math.nan, 0, 0, 0, 0, 0, 0, [0.0] * 4))
    ap.attitude(2_020_000, [0, 0, 0, 0])
    ap.position(2_000_000, 0.0, 0.0, 0.0)  # GPS dropout
    ap.send(
        mav.MAVLink_global_position_int_message(2040, 2**31 - 1, 2**31 - 1, 0, 0, 0, 0, 0, 0)
    )  # INT32_MAX sentinels
    for k in range(20):  # then good telemetry again (a junk datagram may swallow one)
        ap.attitude(1000 * (3000 + 20 * k), [1, 0, 0, 0])
    assert rig.drive(lambda: rig.pose.sizes()["attitude"] >= 18 and rig.counters["attitude_zero"] == 1)
    c = rig.counters
    assert c["mavlink_bad_data"] >= 2  # the CRC failure and at least one junk datagram
    assert c["attitude_not_finite"] == 1 and c["attitude_zero"] == 1
    assert c["position_zero"] == 1 and c["position_out_of_range"] == 1
    assert rig.pose.sizes()["position"] == 0  # no bad fix became a sample
    assert rig.link.state == LINK_CONNECTED


def test_lost_after_heartbeat_timeout_then_recovers_and_rerequests(rig):
    rig.connect()
    rig.clock.t_s += 4.9
    rig.link.tick()
    assert rig.link.state == LINK_CONNECTED
    assert rig.link.heartbeat_age_s() == pytest.approx(4.9)  # what the setpoint gate judges by its own timeout
    rig.clock.t_s += 0.2  # 5.1 s without a heartbeat
    rig.link.tick()
    assert rig.link.state == LINK_LOST and rig.counters["autopilot_lost"] == 1
    assert rig.link.status().rates_confirmed == ()
    n_before = len(rig.ap.commands)
    rig.ap.heartbeat()
    assert rig.drive(lambda: rig.link.state == LINK_CONNECTED and rig.link.rates_confirmed == {31, 33})
    assert len(rig.ap.commands) == n_before + 2
    st = rig.link.status()
    assert st.link_losses == 1 and st.state == LINK_CONNECTED and st.heartbeat_age_s == 0.0
    assert rig.link.heartbeat_age_s() == 0.0


def test_rate_request_retried_until_accepted_and_refusal_counted(rig):
    ap = rig.ap
    ap.results[31] = [None, mav.MAV_RESULT_TEMPORARILY_REJECTED]  # silence, then "try later"
    ap.results[33] = [mav.MAV_RESULT_DENIED]
    rig.heartbeats(3)
    assert rig.drive(lambda: len(ap.commands) == 1)
    rig.clock.t_s += 1.01
    assert rig.drive(lambda: len(ap.commands) == 2)
    rig.clock.t_s += 1.01
    assert rig.drive(lambda: 31 in rig.link.rates_confirmed and 33 in rig.link.rates_refused)
    assert [(mid, conf) for mid, _, conf in ap.commands] == [(31, 0), (31, 1), (31, 2), (33, 0)]
    assert rig.counters["rate_request_refused"] == 1
    assert rig.link.status().rates_refused == (33,)


def test_ack_for_another_requester_is_ignored(rig):
    ap = rig.ap
    ap.results[31] = [None]
    rig.heartbeats(3)
    assert rig.drive(lambda: len(ap.commands) == 1)
    ap.send(command_ack_message(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAV_RESULT_ACCEPTED, 255, 190))  # for a GCS
    rig.drive(lambda: False, timeout_s=0.2)
    assert rig.link.rates_confirmed == set() and rig.link.status().rates_pending == (31, 33)


def test_timesync_maps_local_clock_to_autopilot_boot_clock(rig):
    rig.connect()
    for k in range(4):
        rig.clock.t_s += 1.0
        assert rig.drive(lambda k=k: rig.link.clock_sync.n_samples == k + 1)
    assert rig.link.status().clock_synced
    now_ns = time.monotonic_ns()
    truth_us = (now_ns - rig.ap.boot_ns) / 1000
    assert abs(rig.link.to_boot_us(now_ns) - truth_us) < TIMESYNC_TOL_US
    # the autopilot's own request is answered with our time and its ts1 mirrored
    rig.ap.send(Timesync(0, 123_456_789))
    assert rig.drive(lambda: any(m.ts1 == 123_456_789 for m in rig.ap.got("TIMESYNC")))
    reply = [m for m in rig.ap.got("TIMESYNC") if m.ts1 == 123_456_789][0]
    assert abs(reply.tc1 - time.monotonic_ns()) < 1_000_000_000


def test_timesync_answers_of_another_component_do_not_set_the_boot_clock(rig):
    """A gimbal or a companion's router on the autopilot's system answers our broadcast-era requests with its own
    clock: counted, never used; the autopilot's own answers are."""
    rig.connect()
    assert rig.drive(lambda: rig.link.clock_sync.n_samples == 1)  # the request sent on connecting
    rig.ap.as_component(AP_SYSID, mav.MAV_COMP_ID_GIMBAL)
    for _ in range(3):
        rig.clock.t_s += 1.0
        n = len(rig.ap.got("TIMESYNC"))
        assert rig.drive(lambda n=n: len(rig.ap.got("TIMESYNC")) > n)
        rig.drive(lambda: False, timeout_s=0.05)
    assert rig.link.clock_sync.n_samples == 1 and rig.counters["timesync_foreign"] == 3
    rig.ap.as_component(AP_SYSID, 1)
    rig.clock.t_s += 1.0
    assert rig.drive(lambda: rig.link.clock_sync.n_samples == 2)


def test_reboot_resets_pose_and_clock_and_rerequests_rates(rig):
    rig.connect()
    for k in range(3):
        rig.clock.t_s += 1.0
        assert rig.drive(lambda k=k: rig.link.clock_sync.n_samples == k + 1)
    n_before = len(rig.ap.commands)
    rig.ap.attitude(60_000_000, [1, 0, 0, 0])
    for t_ms in (800, 820, 840):  # time_boot_ms went back, three samples agree: the autopilot rebooted
        rig.ap.attitude(1000 * t_ms, [1, 0, 0, 0])
    assert rig.drive(lambda: rig.pose.reboots == 1 and len(rig.ap.commands) == n_before + 2)
    assert rig.counters["reboot"] == 1
    assert rig.pose.sizes()["attitude"] == 1
    assert rig.link.clock_sync.n_samples == 0 and rig.link.to_boot_us(time.monotonic_ns()) is None


def test_system_time_maps_the_boot_clock_to_utc_and_a_reboot_forgets_it(rig):
    """SYSTEM_TIME of the autopilot feeds the UTC mapping (whole ms of boot time, half a ms added back); the same
    message from another component does not; the autopilot's reboot clears it."""
    rig.connect()
    unix0_us = 1_800_000_000_000_000
    rig.ap.as_component(AP_SYSID, 154)  # a gimbal's clock is not the autopilot's
    rig.ap.send(SystemTime(unix0_us + 500, 500))
    for k in range(1, 4):
        rig.ap.as_component(AP_SYSID, 1)
        rig.ap.send(SystemTime(unix0_us + k * 1_000_000 + 700, k * 1_000_000 + 700))
    assert rig.drive(lambda: rig.link.utc_clock.mapping is not None)
    m = rig.link.utc_clock.mapping
    assert m.n_samples == 3
    utc_us, sigma_us = m.at(3_500_000)
    assert abs(utc_us - (unix0_us + 3_500_000)) <= 2 * sigma_us and sigma_us < 1000
    rig.ap.send(SystemTime(0, 4_000_000))  # no GNSS time: refused, counted
    assert rig.drive(lambda: rig.counters["utc_no_time"] == 1)
    rig.ap.attitude(60_000_000, [1, 0, 0, 0])
    for t_ms in (800, 820, 840):  # the autopilot rebooted
        rig.ap.attitude(1000 * t_ms, [1, 0, 0, 0])
    assert rig.drive(lambda: rig.pose.reboots == 1)
    assert rig.link.utc_clock.mapping is None and rig.link.utc_clock.resets == 1


def test_other_systems_and_non_autopilot_heartbeats_are_ignored(rig):
    ap = rig.ap
    ap.as_component(AP_SYSID, 190)
    ap.heartbeat(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID)
    ap.as_component(AP_SYSID, 1)
    ap.heartbeat(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID)
    rig.drive(lambda: False, timeout_s=0.2)
    assert rig.link.state == LINK_WAITING and rig.link.autopilot_sysid is None
    rig.connect()
    ap.as_component(42, 1)  # another vehicle on the same link
    ap.attitude(5_000_000, [1, 0, 0, 0])
    ap.as_component(AP_SYSID, 1)
    ap.attitude(5_020_000, [1, 0, 0, 0])
    assert rig.drive(lambda: rig.pose.sizes()["attitude"] == 1)
    rig.drive(lambda: False, timeout_s=0.1)
    assert rig.pose.sizes()["attitude"] == 1 and rig.link.autopilot_sysid == AP_SYSID


def test_other_systems_and_components_are_counted_at_debug_and_never_used(rig, caplog):
    """A ground station, a companion and another vehicle on the link: counted in the status's rejected counts by
    why, logged at DEBUG only (normal traffic), and none of their telemetry reaches the pose buffer."""
    ap = rig.ap
    ap.attitude(4_980_000, [1, 0, 0, 0])  # before the unpinned lock settles: nobody is followed yet
    assert rig.drive(lambda: rig.counters["mavlink_before_lock"] == 1)
    rig.connect()
    with caplog.at_level(logging.DEBUG, logger="onboard.core.counters"):
        ap.as_component(42, 1)  # another vehicle
        ap.attitude(5_000_000, [1, 0, 0, 0])
        ap.as_component(255, 190)  # a ground station
        ap.heartbeat(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID)
        ap.as_component(AP_SYSID, 190)  # a GCS-typed heartbeat from the autopilot's system
        ap.heartbeat(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID)
        ap.as_component(AP_SYSID, mav.MAV_COMP_ID_ONBOARD_COMPUTER2)  # a companion relaying telemetry
        ap.attitude(5_010_000, [1, 0, 0, 0])
        ap.position(5_010_000, LAT0, LON0, ALT0)
        ap.as_component(AP_SYSID, 1)
        ap.attitude(5_020_000, [1, 0, 0, 0])
        assert rig.drive(
            lambda: rig.counters["mavlink_foreign_system"] == 2 and rig.counters["mavlink_foreign_component"] == 3
        )
        assert rig.drive(lambda: rig.pose.sizes()["attitude"] == 1)
    assert rig.pose.sizes() == {**rig.pose.sizes(), "attitude": 1, "position": 0}
    lines = [r for r in caplog.records if r.getMessage().startswith("mavlink_foreign")]
    assert lines and {r.levelno for r in lines} == {logging.DEBUG}
    assert any(
        "HEARTBEAT (MAV_TYPE 6, MAV_AUTOPILOT 8) from component 190 of the autopilot's system" in r.getMessage()
        for r in lines
    )
    assert rig.link.autopilot_sysid == AP_SYSID and rig.link.state == LINK_CONNECTED


def _nan_gimbal_status(t_ms: int, gimbal_device_id: int = 0):
    """A #285 with a NaN quaternion (the typed encoder refuses one: the raw pymavlink message)."""
    nan = math.nan
    return mav.MAVLink_gimbal_device_attitude_status_message(
        0,
        0,
        t_ms,
        mav.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME,
        [nan] * 4,
        nan,
        nan,
        nan,
        0,
        nan,
        nan,
        gimbal_device_id,
    )


def test_a_gimbal_report_without_an_attitude_neither_picks_the_gimbal_nor_counts_as_a_report():
    """A NaN quaternion from another gimbal first: the camera's gimbal, heard next, is still the one followed."""
    r = Rig(gimballed=True)
    try:
        r.connect()
        r.ap.as_component(AP_SYSID, mav.MAV_COMP_ID_GIMBAL)
        before = r.link.messages_rx
        r.ap.send(_nan_gimbal_status(900))
        assert r.drive(lambda: r.link.messages_rx > before)
        assert r.link.gimbal_device_id is None and r.link.gimbal_reports == 0
        assert r.counters["gimbal_attitude_invalid"] == 1
        r.ap.as_component(AP_SYSID, 1)
        q_g = quat_from_euler(0.0, math.radians(-40.0), 0.0)
        r.ap.send(
            GimbalDeviceAttitudeStatus(
                1_000_000, tuple(q_g), mav.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME, gimbal_device_id=1
            )
        )
        assert r.drive(lambda: r.pose.sizes()["gimbal"] == 1)
        assert r.link.gimbal_device_id == 1 and r.link.gimbal_reports == 1 and r.counters["second_gimbal"] == 0
    finally:
        r.close()


@pytest.mark.parametrize("gimballed", [False, True], ids=["fixed", "gimballed"])
def test_gimbal_reports_count_only_reports_with_an_attitude(gimballed):
    """The watchdog's gimbal_mismatch reads gimbal_reports: a garbage #285 must not raise it on a fixed mount nor
    clear it on a gimballed one."""
    r = Rig(gimballed=gimballed)
    try:
        r.connect()
        before = r.link.messages_rx
        r.ap.send(_nan_gimbal_status(900, gimbal_device_id=1))
        assert r.drive(lambda: r.link.messages_rx > before)
        assert r.link.gimbal_reports == 0 and r.counters["gimbal_attitude_invalid"] == 1
        r.ap.send(GimbalDeviceAttitudeStatus(1_000_000, (1.0, 0.0, 0.0, 0.0), 0, gimbal_device_id=1))
        assert r.drive(lambda: r.link.gimbal_reports == 1)
    finally:
        r.close()


def test_gimbal_status_reaches_the_pose_buffer():
    r = Rig(gimballed=True)
    try:
        r.connect()
        assert (285, 20_000) in [(mid, us) for mid, us, _ in r.ap.commands]  # 50 Hz: a sample within 20 ms of a frame
        q_g = quat_from_euler(0.0, math.radians(-40.0), 0.0)
        for k in range(3):
            r.ap.send(
                GimbalDeviceAttitudeStatus(
                    1000 * (1000 + 100 * k),
                    tuple(q_g),
                    mav.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME,
                    gimbal_device_id=0,
                )
            )
        # a second gimbal (its own component) on the same vehicle: never mixed into the camera's pose
        r.ap.as_component(AP_SYSID, mav.MAV_COMP_ID_GIMBAL)
        r.ap.send(
            GimbalDeviceAttitudeStatus(
                1_050_000, (1.0, 0.0, 0.0, 0.0), mav.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME, gimbal_device_id=0
            )
        )
        assert r.drive(lambda: r.pose.sizes()["gimbal"] == 3 and r.counters["second_gimbal"] == 1)
        assert r.link.gimbal_device_id == 1
        for t in (1000, 1050, 1100, 1150, 1200):
            r.pose.add_attitude(t * 1000, quat_from_euler(0.0, 0.0, math.radians(90.0)))
            r.pose.add_position_ned(t * 1000, [0.0, 0.0, -50.0])
        pose = r.pose.pose_at(1_100_000)
        # vehicle frame: 40 deg down, along the nose (east)
        axis = quat_rotate(pose.q_ned_from_cam, [0.0, 0.0, 1.0])
        np.testing.assert_allclose(axis, [0.0, math.cos(math.radians(40)), math.sin(math.radians(40))], atol=1e-6)
    finally:
        r.close()


def test_a_separate_gimbal_component_waits_for_timesync():
    """A gimbal device of its own (component 154, gimbal_device_id 0) stamps on its own clock: its samples wait for
    TIMESYNC; the autopilot's gimbal 2 (ArduPilot's MNT2) is another gimbal; the configured id picks the camera's."""
    r = Rig(gimballed=True, config=dataclasses.replace(UNPINNED, gimbal_device_id=mav.MAV_COMP_ID_GIMBAL))
    try:
        r.connect()
        r.ap.send(GimbalDeviceAttitudeStatus(1_000_000, (1.0, 0.0, 0.0, 0.0), 0, gimbal_device_id=2))
        r.ap.as_component(AP_SYSID, mav.MAV_COMP_ID_GIMBAL)
        r.ap.send(GimbalDeviceAttitudeStatus(77_000, (1.0, 0.0, 0.0, 0.0), 0, gimbal_device_id=0))
        assert r.drive(lambda: r.counters["gimbal_clock_unsynced"] == 1 and r.counters["second_gimbal"] == 1)
        assert r.pose.sizes()["gimbal"] == 0 and r.link.gimbal_device_id == mav.MAV_COMP_ID_GIMBAL
    finally:
        r.close()


def test_body_rates_and_gimbal_rates_reach_the_pose_buffer_for_extrapolation():
    """#31 rollspeed/pitchspeed/yawspeed are body FRD rad/s; #285 angular_velocity is in q's frame."""
    r = Rig(gimballed=True)
    try:
        r.connect()
        w_frd = np.array([0.0, 0.0, 0.5])  # yawing right at 0.5 rad/s
        w_earth = np.array([0.0, 0.2, 0.0])  # gimbal pitching up at 0.2 rad/s about east
        q_g = quat_from_euler(0.0, math.radians(-40.0), 0.0)
        r.ap.attitude(1_000_000, [1, 0, 0, 0], w_frd)
        r.ap.send(
            GimbalDeviceAttitudeStatus(
                1_000_000, tuple(q_g), mav.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME, tuple(w_earth), gimbal_device_id=0
            )
        )
        assert r.drive(lambda: r.pose.sizes()["attitude"] == 1 and r.pose.sizes()["gimbal"] == 1)
        r.pose.add_position_ned(1_000_000, [0.0, 0.0, -50.0], [0.0, 0.0, 0.0])
        pose = r.pose.pose_at(1_020_000)  # 20 ms past every sample
        assert pose is not None and pose.mode == "extrapolated", r.pose.last_miss_reason
        assert pose.att_extrapolated_us == 20_000 and pose.gimbal_extrapolated_us == 20_000
        yaw = float(euler_from_quat(pose.body.q_ned_from_body)[2])
        assert yaw == pytest.approx(0.5 * 0.020, abs=1e-6)  # float32 on the wire
        # earth-frame gimbal: the optical axis (gimbal x) pitched up by 0.2 rad/s x 20 ms
        axis = quat_rotate(pose.q_ned_from_cam, [0.0, 0.0, 1.0])
        el = math.asin(-axis[2])
        assert el == pytest.approx(math.radians(-40.0) + 0.2 * 0.020, abs=1e-6)
    finally:
        r.close()


# --------------------------------------------------------------------------- output


def test_tracking_status_messages_on_the_wire(rig):
    rig.connect()
    assert rig.link.send_tracking_geo_status(
        CameraTrackingGeoStatus(47.123456789, -122.5, 512.25, 3.0, 5.0, 10.0, -2.0, 0.5, 1.5, dist_m=800.0, hdg_rad=0.3)
    )
    assert rig.link.send_tracking_image_status(
        CameraTrackingImageStatus(
            mav.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE,
            mav.CAMERA_TRACKING_MODE_POINT,
            point_x=0.25,
            point_y=0.75,
            radius=0.01,
        )
    )
    assert rig.drive(lambda: rig.ap.got("CAMERA_TRACKING_GEO_STATUS") and rig.ap.got("CAMERA_TRACKING_IMAGE_STATUS"))
    geo = rig.ap.got("CAMERA_TRACKING_GEO_STATUS")[0]
    assert (geo.lat, geo.lon) == (471234568, -1225000000)
    assert geo.alt == pytest.approx(512.25) and geo.tracking_status == mav.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
    assert (geo.vel_n, geo.vel_e, geo.vel_d) == pytest.approx((10.0, -2.0, 0.5))
    assert geo.dist == pytest.approx(800.0) and math.isnan(geo.hdg_acc)
    assert (geo.get_srcSystem(), geo.get_srcComponent()) == (AP_SYSID, 191)
    img = rig.ap.got("CAMERA_TRACKING_IMAGE_STATUS")[0]
    assert (img.tracking_mode, img.target_data) == (
        mav.CAMERA_TRACKING_MODE_POINT,
        mav.CAMERA_TRACKING_TARGET_DATA_IN_STATUS,
    )
    assert (img.point_x, img.point_y) == pytest.approx((0.25, 0.75)) and math.isnan(img.rec_top_x)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(lat_deg=91.0), "lat_deg"),
        (dict(lon_deg=math.nan), "lon_deg"),
        (dict(h_acc_m=-1.0), "h_acc_m"),
        (dict(vel_n_mps=math.inf), "vel_n_mps"),
        (dict(tracking_status=256), "tracking_status"),
    ],
)
def test_geo_status_rejects_bad_fields_by_name(rig, kwargs, field):
    args = dict(
        lat_deg=47.0,
        lon_deg=8.0,
        alt_m=500.0,
        h_acc_m=1.0,
        v_acc_m=1.0,
        vel_n_mps=0.0,
        vel_e_mps=0.0,
        vel_d_mps=0.0,
        vel_acc_mps=0.1,
    )
    args.update(kwargs)
    with pytest.raises(InputError, match=field):
        rig.link.send_tracking_geo_status(CameraTrackingGeoStatus(**args))


def test_image_status_rejects_bad_fields_by_name(rig):
    with pytest.raises(InputError, match="point_x"):
        rig.link.send_tracking_image_status(CameraTrackingImageStatus(1, 1, point_x=1.5))
    with pytest.raises(InputError, match="tracking_mode"):
        rig.link.send_tracking_image_status(CameraTrackingImageStatus(1, 3))


def test_bad_rates_and_config_are_config_errors():
    pose = PoseBuffer()
    with pytest.raises(ConfigError, match="attitude_rate_hz"):
        MavlinkLink(MavlinkConfig(connection="udpin:127.0.0.1:1", attitude_rate_hz=0), pose, RejectCounter())
    with pytest.raises(ConfigError, match="heartbeat_timeout_s"):
        MavlinkConfig(heartbeat_timeout_s=-1)
    with pytest.raises(ConfigError, match="gimballed"):
        MavlinkLink(MavlinkConfig(connection="udpin:127.0.0.1:1"), pose, RejectCounter(), gimballed=True)


def test_unopenable_connection_is_counted_and_retried():
    clock = FakeClock()
    counters = RejectCounter(clock=clock)
    port = free_udp_port()  # nothing listens on this TCP port: connect is refused
    link = MavlinkLink(
        dataclasses.replace(UNPINNED, connection=f"tcp:127.0.0.1:{port}"), PoseBuffer(), counters, clock=clock
    )
    assert counters["mavlink_open_failed"] == 1 and link.poll() == 0
    link.tick()  # too early to retry
    assert counters["mavlink_open_failed"] == 1
    clock.t_s += 2.5
    link.tick()
    assert counters["mavlink_open_failed"] == 2 and link.state == LINK_WAITING
    link.close()


def _tcp_server() -> socket.socket:
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    server.settimeout(WAIT_S)
    return server


def _heartbeat_bytes() -> bytes:
    codec = mav.MAVLink(None, srcSystem=AP_SYSID, srcComponent=1)
    return bytes(codec.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, 0, 0, 0).pack(codec))


def _poll_until(link: MavlinkLink, cond) -> bool:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        link.poll()
        link.tick()
        if cond():
            return True
        time.sleep(0.005)
    return False


def _connects_and_hears(link: MavlinkLink, server: socket.socket) -> None:
    """The link's dial gets through to ``server``, and a heartbeat sent there is handled (its first message)."""
    assert _poll_until(link, lambda: link.fileno() is not None)
    peer, _ = server.accept()
    with peer:
        peer.sendall(_heartbeat_bytes())
        assert _poll_until(link, lambda: link.messages_rx == 1)


def test_a_tcp_autopilot_that_closes_the_connection_is_dialled_again_after_the_reopen_interval(capsys):
    """pymavlink's own reconnection dialled again inside every read, printing "Attempting reconnect" to stdout,
    and its connection kept the closed socket's descriptor for the main loop's select (another file's once the
    number was reused).  Now the loss is counted once, the link closed, and dialled again after reopen_interval_s."""
    server = _tcp_server()
    port = server.getsockname()[1]
    clock = FakeClock()
    counters = RejectCounter(clock=clock)
    config = dataclasses.replace(UNPINNED, connection=f"tcp:127.0.0.1:{port}", autopilot_sysid=AP_SYSID)
    link = MavlinkLink(config, PoseBuffer(), counters, clock=clock)
    try:
        peer, _ = server.accept()
        peer.sendall(_heartbeat_bytes())
        assert _poll_until(link, lambda: link.messages_rx == 1) and link.fileno() is not None
        assert link.state == LINK_CONNECTED and link.autopilot_mode is not None
        peer.close()
        server.close()  # the autopilot restarts: nobody listens for a while
        assert _poll_until(link, lambda: counters["mavlink_connection_lost"] == 1)
        # lost at once, its mode forgotten: a setpoint gate reading "connected" and the old GUIDED would send on
        assert link.state == LINK_LOST and link.autopilot_mode is None and link.link_losses == 1
        for _ in range(20):  # not dialled at every poll
            link.poll()
            link.tick()
        assert link.fileno() is None and link.open_error == "closed by the autopilot"
        assert counters["mavlink_open_failed"] == 0 and counters["mavlink_recv_error"] == 0
        server = socket.create_server(("127.0.0.1", port))
        server.settimeout(WAIT_S)
        clock.t_s += UNPINNED.reopen_interval_s
        link.tick()
        again, _ = server.accept()
        with again:
            again.sendall(_heartbeat_bytes())
            assert _poll_until(link, lambda: link.messages_rx == 2 and link.state == LINK_CONNECTED)
        assert link.open_error is None and counters["mavlink_connection_lost"] == 1
        assert capsys.readouterr().out == ""
    finally:
        link.close()
        server.close()


def test_a_tcp_autopilot_that_does_not_answer_never_blocks_the_loop():
    """pymavlink connected in its constructor, blocking: against an address that drops the packets the daemon's
    start and then its main loop waited for the kernel to give up, two minutes.  Here the autopilot's accept queue
    is full, so its host drops our connection's packets as such a host would."""
    from onboard.io.mavlink_transport import TCP_CONNECT_TIMEOUT_S

    server, filler = silent_tcp_server(WAIT_S)
    clock = FakeClock()
    counters = RejectCounter(clock=clock)
    config = dataclasses.replace(UNPINNED, connection=f"tcp:127.0.0.1:{server.getsockname()[1]}")
    t0 = time.monotonic()
    link = MavlinkLink(config, PoseBuffer(), counters, clock=clock)
    try:
        assert link.poll() == 0 and link.fileno() is None and link.seconds_to_next_due() < 0.1
        link.tick()
        assert time.monotonic() - t0 < 1.0 and counters["mavlink_open_failed"] == 0  # under way, not waited for
        clock.t_s += TCP_CONNECT_TIMEOUT_S
        link.tick()
        assert (
            counters["mavlink_open_failed"] == 1 and link.open_error == f"no answer within {TCP_CONNECT_TIMEOUT_S:g} s"
        )
        # the autopilot takes connections again: the next dial gets through
        first, _ = server.accept()
        first.close()
        filler.close()
        server.settimeout(WAIT_S)
        clock.t_s += config.reopen_interval_s
        _connects_and_hears(link, server)
    finally:
        link.close()
        filler.close()
        server.close()


def test_a_tcp_autopilot_named_by_host_is_looked_up_off_the_loop(monkeypatch):
    """A host name was resolved inside connect, blocking the main loop for the resolver's timeouts where no name
    server answers (a vehicle off the network), again at every redial: it is looked up on a thread of its own, the
    link dialling once it has the address; a name without one is counted, not raised."""
    import threading

    import onboard.io.mavlink_transport as transport

    server = _tcp_server()
    port = server.getsockname()[1]
    gate = threading.Event()
    real = socket.getaddrinfo

    def slow_resolver(host, *args):
        assert gate.wait(WAIT_S)  # a name server that takes its time
        return real("127.0.0.1" if host == "autopilot.local" else host, *args)

    monkeypatch.setattr(transport.socket, "getaddrinfo", slow_resolver)
    clock = FakeClock()
    counters = RejectCounter(clock=clock)
    link = MavlinkLink(dataclasses.replace(UNPINNED, connection=f"tcp:autopilot.local:{port}"), PoseBuffer(), counters)
    try:
        link.poll()
        link.tick()
        assert link.fileno() is None and counters.total == 0  # under way, the loop not held
        gate.set()
        _connects_and_hears(link, server)
    finally:
        link.close()
        server.close()
    bad = MavlinkLink(dataclasses.replace(UNPINNED, connection="tcp:no-such-host.invalid:5760"), PoseBuffer(), counters)
    try:
        assert _poll_until(bad, lambda: counters["mavlink_open_failed"] == 1)
        assert bad.open_error.startswith("no address for 'no-such-host.invalid'")
    finally:
        bad.close()


def test_a_name_lookup_under_way_does_not_hold_the_process_at_exit():
    """The lookups ran on a pool's thread, which Python joins at exit: a daemon told to stop while a name server did
    not answer stayed for the resolver's timeouts, past a container's stop timeout."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent("""
        import socket, time
        import onboard.io.mavlink_transport as t
        from onboard.io.mavlink_endpoint import parse_endpoint
        real = socket.getaddrinfo
        def silent(host, *a):
            time.sleep(30)  # a name server that does not answer
            return real("127.0.0.1", *a)
        t.socket.getaddrinfo = silent
        t.TcpDial(parse_endpoint("tcp:autopilot.local:5760"), time.monotonic()).close()
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=20, check=False)
    assert done.returncode == 0, done.stderr.decode()


def test_gps_raw_int_is_decoded_into_the_gnss_state_and_a_bad_fix_type_counted(rig):
    """GPS_RAW_INT of the autopilot (not requested: its default stream) sets ``link.gnss`` and the status's
    ``gnss``; another component's is ignored; a fix type outside GPS_FIX_TYPE is counted and dropped."""
    rig.connect()
    assert rig.link.gnss is None and rig.link.status().gnss is None
    assert 24 not in rig.link.rate_plan  # an autopilot streams it unasked
    rig.clock.t_s = 50.0
    rig.ap.send(GpsRawInt(1_800_000_000_000_000, mav.GPS_FIX_TYPE_3D_FIX, 14, 0.8, 1.2, 0.5, 0.8))
    assert rig.drive(lambda: rig.link.gnss is not None)
    g = rig.link.gnss
    assert (g.fix, g.satellites, g.hdop, g.h_acc_m, g.received_s, g.degraded_since_s) == (
        "3d",
        14,
        0.8,
        0.5,
        50.0,
        None,
    )
    rig.ap.as_component(AP_SYSID, 154)  # not the autopilot: ignored
    rig.ap.send(GpsRawInt(0, mav.GPS_FIX_TYPE_NO_FIX, 0))
    rig.ap.as_component(AP_SYSID, 1)
    rig.ap.send(GpsRawInt(0, 42, 3))  # out of range: counted, the state kept
    rig.clock.t_s = 51.0
    rig.ap.send(GpsRawInt(1_800_000_001_000_000, mav.GPS_FIX_TYPE_NO_FIX, 0))
    assert rig.drive(lambda: rig.link.gnss.fix_type == mav.GPS_FIX_TYPE_NO_FIX)
    assert rig.counters["gps_raw_fix_type"] == 1
    rig.clock.t_s = 52.5
    s = rig.link.status().gnss
    assert (s["fix"], s["satellites"], s["age_s"], s["degraded_s"], s["hdop"]) == ("no_fix", 0, 1.5, 1.5, None)


def test_a_second_link_on_a_port_another_holds_is_refused_and_counted_not_shared(rig, caplog):
    """A second daemon on the first one's udpin port: its open fails (counted, retried) instead of binding beside
    it, where the kernel would hand each datagram to one of the two; the first one still gets every heartbeat."""
    with caplog.at_level(logging.WARNING):
        _clock, counter, _pose, second = loopback_link(rig.port, GeodeticOrigin(LAT0, LON0, ALT0), gimballed=False)
    try:
        assert second.fileno() is None
        assert counter["mavlink_open_failed"] == 1
        assert f"mavlink_open_failed: udpin:127.0.0.1:{rig.port}: [Errno 98] Address already in use" in caplog.text
        assert second.open_error == "[Errno 98] Address already in use"  # what the no_mavlink warning names
        assert rig.link.open_error is None
        rig.heartbeats(2)
        assert rig.drive(lambda: rig.link.status().messages_rx >= 2)
    finally:
        second.close()


@pytest.mark.parametrize("gimballed", [False, True])
def test_with_the_cameras_gimbal_named_another_gimbals_reports_say_nothing_about_the_mount(gimballed):
    """mavlink.gimbal_device_id set: only that device's reports count for the watchdog's gimbal check, so a
    daylight camera's gimbal neither withholds a fixed IR pod's directions nor hides that the IR pod's gimbal is
    silent; the named gimbal's reports still count."""
    r = Rig(gimballed=gimballed, config=dataclasses.replace(UNPINNED, gimbal_device_id=2))
    try:
        r.connect()
        before = r.link.messages_rx
        r.ap.send(GimbalDeviceAttitudeStatus(1_000_000, (1.0, 0.0, 0.0, 0.0), 0, gimbal_device_id=1))
        assert r.drive(lambda: r.link.messages_rx > before)
        assert r.link.gimbal_reports == 0
        r.ap.send(GimbalDeviceAttitudeStatus(1_020_000, (1.0, 0.0, 0.0, 0.0), 0, gimbal_device_id=2))
        assert r.drive(lambda: r.link.gimbal_reports == 1)
    finally:
        r.close()


def test_a_timesync_answer_on_another_clock_or_in_other_units_is_refused(rig):
    """An autopilot answering TIMESYNC in microseconds (or on the UNIX epoch, which common.xml allows) was taken:
    the boot clock mapping came out 1000 times off, and with it the gimbal samples and latency it stamps."""
    rig.connect()
    assert rig.drive(lambda: rig.link.clock_sync.n_samples == 1)
    real = rig.ap.boot_ns_now
    rig.ap.attitude(real() // 1000, [1, 0, 0, 0])
    assert rig.drive(lambda: rig.link._boot_seen is not None)
    rig.ap.boot_ns_now = lambda: real() // 1000  # microseconds where nanoseconds are due
    for k in range(2):
        rig.clock.t_s += 1.0
        rig.ap.attitude(real() // 1000, [1, 0, 0, 0])
        assert rig.drive(lambda k=k: rig.counters["timesync_implausible"] == k + 1)
    assert rig.link.clock_sync.n_samples == 1  # none of them used
    rig.ap.boot_ns_now = real
    rig.clock.t_s += 1.0
    rig.ap.attitude(real() // 1000, [1, 0, 0, 0])
    assert rig.drive(lambda: rig.link.clock_sync.n_samples == 2)


def test_utc_is_not_seeded_while_the_receiver_reports_no_fix(rig):
    """Before a GNSS fix an autopilot's UTC is an RTC's or a ground station's (the time-handling audit: 2 s off
    stamped every frame at a 0.34 ms sigma); the mapping waits for a fixed receiver, then seeds as before."""
    rig.connect()
    unix0_us = 1_800_000_000_000_000
    rig.ap.send(GpsRawInt(5, mav.GPS_FIX_TYPE_NO_FIX))
    for k in range(1, 4):
        rig.ap.send(SystemTime(unix0_us + k * 1_000_000 + 700, k * 1_000_000 + 700))
    assert rig.drive(lambda: rig.counters["utc_without_fix"] == 3)
    assert rig.link.utc_clock.mapping is None
    rig.ap.send(GpsRawInt(6, mav.GPS_FIX_TYPE_3D_FIX))
    for k in range(4, 7):
        rig.ap.send(SystemTime(unix0_us + k * 1_000_000 + 700, k * 1_000_000 + 700))
    assert rig.drive(lambda: rig.link.utc_clock.mapping is not None and rig.link.utc_clock.mapping.n_samples == 3)


def test_a_stream_slower_than_its_accepted_rate_is_measured_and_named():
    """An autopilot that ACCEPTS 100 Hz attitude and sends 20 Hz (ArduPilot caps a stream without a word): the status
    says both rates, and slow_streams names it once its rate was confirmed a few seconds ago."""
    from onboard.core.stream_rate import SLOW_PERSIST_S
    from onboard.io.mavlink_wire import AttitudeQuaternion

    r = Rig(config=dataclasses.replace(UNPINNED, attitude_rate_hz=100.0, position_rate_hz=25.0))
    try:
        r.connect()
        assert r.link.slow_streams() == []
        t_us = [1_000_000]

        def a_second_at_20_hz() -> None:
            """20 attitudes, then a second on the link's clock, a heartbeat and a status (the looks the rate is
            measured over)."""
            for _ in range(20):
                t_us[0] += 50_000
                before = r.link.messages_rx
                r.ap.send(AttitudeQuaternion(t_us[0], (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0)))
                assert r.drive(lambda before=before: r.link.messages_rx > before)
            r.clock.t_s += 1.0
            r.ap.heartbeat()
            r.link.status()

        for _ in range(int(SLOW_PERSIST_S) + 3):
            a_second_at_20_hz()
        st = r.link.status().streams["ATTITUDE_QUATERNION"]
        assert st["msg_id"] == 31 and st["requested_hz"] == 100.0
        assert st["measured_hz"] == pytest.approx(20.0, abs=1.0)
        assert r.link.status().streams["GLOBAL_POSITION_INT"]["measured_hz"] == 0.0
        r.clock.t_s += 1e-4  # the daemon's watchdog asks just after the link's status, on the same thread
        n_before = len(r.ap.commands)
        assert {s.name for s in r.link.slow_streams()} == {"ATTITUDE_QUATERNION", "GLOBAL_POSITION_INT"}
        # asked again (a ground station sharing the link may have lowered them), ACCEPTED, the measure going on
        assert r.drive(lambda: len(r.ap.commands) == n_before + 2 and not r.link.status().rates_pending)
        assert sorted(mid for mid, _, _ in r.ap.commands[n_before:]) == [31, 33]
        asked = []  # commands sent by each second, the streams still slow (an autopilot that caps them)
        for _ in range(int(REASK_S)):
            a_second_at_20_hz()
            assert len(r.link.slow_streams()) == 2
            r.drive(lambda: False, timeout_s=0.05)
            asked.append(len(r.ap.commands) - n_before)
        assert asked[: int(REASK_S) - 2] == [2] * (int(REASK_S) - 2) and asked[-1] == 4  # again only after REASK_S
    finally:
        r.close()
