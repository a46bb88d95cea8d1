"""The simulated vehicle as a ground station sees it: SYS_STATUS, EXTENDED_SYS_STATE,
HOME_POSITION, AUTOPILOT_VERSION, GPS_RAW_INT, ATTITUDE, BATTERY_STATUS, parameters, an empty
mission; and MAVSDK (an independent client) reading health, home, GPS and battery with no request
DENIED.  Everything on 127.0.0.1, bounded waits."""

from __future__ import annotations

import math
import threading
import time

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mav

from groundsim.io.mavlink_vehicle import BATTERY_CELLS, DEFAULT_PARAMS, MavlinkVehicle
from groundsim.io.ports import free_udp_port
from tests.groundsim.test_mavlink_vehicle import (
    ALT_AMSL_M,
    ALT_REL_M,
    LAT_DEG,
    LON_DEG,
    WAIT_S,
    _pump_thread,
    mavsdk_autopilot,
)


@pytest.fixture
def gcs():
    """(rx, vehicle, pump stop event): a pymavlink ground station and a vehicle pumped in real time."""
    port = free_udp_port()
    rx = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190)
    rx.mav = mav.MAVLink(rx, srcSystem=255, srcComponent=190)
    vehicle = MavlinkVehicle(f"udpout:127.0.0.1:{port}")
    stop = threading.Event()
    th = _pump_thread(vehicle, stop, 0.002)
    th.start()
    try:
        assert rx.recv_match(type="HEARTBEAT", blocking=True, timeout=WAIT_S) is not None
        yield rx, vehicle
    finally:
        stop.set()
        th.join(WAIT_S)
        vehicle.close()
        rx.close()


def _collect(rx, types: set[str], seconds: float) -> dict[str, list]:
    out: dict[str, list] = {t: [] for t in types}
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        m = rx.recv_match(blocking=True, timeout=0.05)
        if m is not None and m.get_type() in out:
            out[m.get_type()].append(m)
    return out


@pytest.mark.integration
def test_streams_at_the_usual_rates_with_sane_fields(gcs):
    rx, _ = gcs
    got = _collect(rx, {"SYS_STATUS", "EXTENDED_SYS_STATE", "GPS_RAW_INT", "ATTITUDE", "BATTERY_STATUS"}, 2.2)
    assert len(got["SYS_STATUS"]) >= 2 and len(got["EXTENDED_SYS_STATE"]) >= 2 and len(got["BATTERY_STATUS"]) >= 2
    assert len(got["GPS_RAW_INT"]) >= 8 and len(got["ATTITUDE"]) >= 15  # 5 Hz, 10 Hz
    ss = got["SYS_STATUS"][-1]
    assert ss.onboard_control_sensors_health & mav.MAV_SYS_STATUS_SENSOR_GPS
    assert ss.onboard_control_sensors_health == ss.onboard_control_sensors_present
    assert 0 < ss.battery_remaining <= 100 and ss.voltage_battery > 3500 * BATTERY_CELLS
    gps = got["GPS_RAW_INT"][-1]
    assert gps.fix_type == mav.GPS_FIX_TYPE_3D_FIX and gps.satellites_visible > 6
    assert gps.lat == round(LAT_DEG * 1e7) and gps.lon == round(LON_DEG * 1e7)
    assert got["EXTENDED_SYS_STATE"][-1].landed_state == mav.MAV_LANDED_STATE_IN_AIR
    bat = got["BATTERY_STATUS"][-1]
    assert (
        list(bat.voltages[:BATTERY_CELLS]) == [bat.voltages[0]] * BATTERY_CELLS and bat.voltages[BATTERY_CELLS] == 65535
    )
    att = got["ATTITUDE"][-1]
    assert all(math.isfinite(x) for x in (att.roll, att.pitch, att.yaw))


@pytest.mark.integration
@pytest.mark.parametrize(
    "command, p1, reply",
    [
        (mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION, "AUTOPILOT_VERSION"),
        (mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1, "AUTOPILOT_VERSION"),
        (mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_HOME_POSITION, "HOME_POSITION"),
        (mav.MAV_CMD_GET_HOME_POSITION, 0, "HOME_POSITION"),
    ],
)
def test_requests_are_accepted_and_answered(gcs, command, p1, reply):
    rx, _ = gcs
    rx.mav.command_long_send(1, 1, command, 0, p1, 0, 0, 0, 0, 0, 0)
    ack = rx.recv_match(type="COMMAND_ACK", blocking=True, timeout=WAIT_S)
    assert ack is not None and ack.command == command and ack.result == mav.MAV_RESULT_ACCEPTED
    msg = rx.recv_match(type=reply, blocking=True, timeout=WAIT_S)
    assert msg is not None
    if reply == "HOME_POSITION":
        # the first state's position, at the altitude its relative altitude is measured from
        assert msg.latitude == round(LAT_DEG * 1e7) and msg.altitude == round((ALT_AMSL_M - ALT_REL_M) * 1000)
    else:
        assert msg.capabilities & mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2


@pytest.mark.integration
def test_parameters_list_read_set_and_an_empty_mission(gcs):
    rx, _ = gcs
    rx.mav.param_request_list_send(1, 1)
    got = {}
    end = time.monotonic() + WAIT_S
    while len(got) < len(DEFAULT_PARAMS) and time.monotonic() < end:
        m = rx.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.2)
        if m is not None:
            got[m.param_id] = (m.param_value, m.param_index, m.param_count)
    assert set(got) == {n for n, _ in DEFAULT_PARAMS}
    assert sorted(i for _, i, _ in got.values()) == list(range(len(DEFAULT_PARAMS)))
    assert all(c == len(DEFAULT_PARAMS) for _, _, c in got.values())
    rx.mav.param_set_send(1, 1, b"BAT_CAPACITY", 4200.0, mav.MAV_PARAM_TYPE_REAL32)
    m = rx.recv_match(
        type="PARAM_VALUE", blocking=True, timeout=WAIT_S, condition="PARAM_VALUE.param_id=='BAT_CAPACITY'"
    )
    assert m is not None and m.param_value == 4200.0
    rx.mav.param_request_read_send(1, 1, b"MAV_SYS_ID", -1)
    m = rx.recv_match(type="PARAM_VALUE", blocking=True, timeout=WAIT_S, condition="PARAM_VALUE.param_id=='MAV_SYS_ID'")
    assert m is not None and m.param_value == 1.0
    for mission_type in (mav.MAV_MISSION_TYPE_MISSION, mav.MAV_MISSION_TYPE_FENCE, mav.MAV_MISSION_TYPE_RALLY):
        rx.mav.mission_request_list_send(1, 1, mission_type)
        m = rx.recv_match(type="MISSION_COUNT", blocking=True, timeout=WAIT_S)
        assert m is not None and m.count == 0 and m.mission_type == mission_type and m.target_system == 255


@pytest.mark.integration
@pytest.mark.timeout(60)
def test_mavsdk_reads_health_home_gps_and_battery_with_nothing_denied():
    mavsdk = pytest.importorskip("mavsdk")
    from mavsdk.plugins.telemetry.telemetry import Telemetry

    with mavsdk_autopilot(mavsdk) as (system, vehicle):
        tel = Telemetry(system)
        deadline = time.monotonic() + 15.0
        health = home = gps = battery = None
        while time.monotonic() < deadline:
            health, home, gps, battery = tel.health(), tel.home(), tel.gps_info(), tel.battery()
            if (
                health.is_global_position_ok
                and health.is_home_position_ok
                and not math.isnan(home.latitude_deg)
                and gps.num_satellites > 0
                and not math.isnan(battery.remaining_percent)
                and battery.remaining_percent > 0
            ):
                break
            time.sleep(0.1)
        assert health.is_gyrometer_calibration_ok and health.is_accelerometer_calibration_ok
        assert health.is_global_position_ok and health.is_home_position_ok, health
        assert home.latitude_deg == pytest.approx(LAT_DEG, abs=1e-7)
        assert home.absolute_altitude_m == pytest.approx(ALT_AMSL_M - ALT_REL_M, abs=1e-3)  # what relative_alt is above
        assert gps.num_satellites == 14 and int(gps.fix_type) >= 3
        assert 0 < battery.remaining_percent <= 100 and battery.voltage_v > 3.5 * BATTERY_CELLS
        time.sleep(1.0)  # let any late request arrive and be answered
        assert vehicle.counters["ack_denied"] == 0, dict(vehicle.counters)
