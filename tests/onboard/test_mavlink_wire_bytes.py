"""No change on the wire: the bytes our senders write, compared with bytes captured before the MAVLink
wire module replaced their hand-written encoders.

Every sender is driven through its usual path with fixed inputs and fixed clocks, and its writes are
captured (no datagram leaves the process):

* the simulated vehicle (``groundsim.io.mavlink_vehicle.MavlinkVehicle``): every stream it emits, the
  gimbal in both yaw frames, a saturated velocity and an unknown heading, TIMESYNC and COMMAND_ACK replies;
* the daemon's autopilot link (``onboard.io.mavlink_link.MavlinkLink``): HEARTBEAT, SET_MESSAGE_INTERVAL,
  TIMESYNC request and reply, #275, #276, FOLLOW_TARGET;
* the camera component (``onboard.io.gcs_link.GcsLink`` sending ``CameraProtocol``'s messages): every
  message it answers with, the periodic #275 / #276 and the heartbeat.

``tests/onboard/data/mavlink_wire_golden.json`` holds the captured bytes (hex) per case;
``IRTRACK_WRITE_GOLDEN=1`` rewrites it (only ever from a commit whose wire output is the reference).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mav

from tests.fakes import FakeClock

GOLDEN = Path(__file__).parent / "data" / "mavlink_wire_golden.json"
UNIX_AT_BOOT_US = 1_700_000_000_000_000
_captured: dict[str, list[str]] = {}


def _packed(msg, sysid: int, compid: int = 1) -> bytes:
    codec = mav.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    return bytes(msg.pack(codec))


def _parsed(msg, sysid: int, compid: int = 1):
    return mav.MAVLink(None).parse_char(_packed(msg, sysid, compid))


def _check(case: str, writes: list[bytes]) -> None:
    hexes = [b.hex() for b in writes]
    assert hexes, f"{case}: nothing was written"
    if os.environ.get("IRTRACK_WRITE_GOLDEN") == "1":
        _captured[case] = hexes
        data = json.loads(GOLDEN.read_text()) if GOLDEN.exists() else {}
        data[case] = hexes
        GOLDEN.parent.mkdir(parents=True, exist_ok=True)
        GOLDEN.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
        return
    golden = json.loads(GOLDEN.read_text())
    assert case in golden, f"{case}: no golden bytes"
    assert len(hexes) == len(golden[case]), (
        f"{case}: {len(hexes)} messages written, {len(golden[case])} in the golden file"
    )
    for k, (got, want) in enumerate(zip(hexes, golden[case])):
        assert got == want, f"{case}: message {k} differs:\n got  {got}\n want {want}"


# --------------------------------------------------------------------------- the simulated vehicle


def _vehicle(gimbal_yaw_frame: str):
    from groundsim.io.mavlink_vehicle import MavlinkVehicle

    v = MavlinkVehicle(
        "udpout:127.0.0.1:9", gimballed=True, gimbal_yaw_frame=gimbal_yaw_frame, unix_time_at_boot_us=UNIX_AT_BOOT_US
    )
    writes: list[bytes] = []
    v._conn.write = lambda buf: writes.append(bytes(buf))
    return v, writes


def _state(v, t_us: int, **over) -> None:
    from onboard.core.frames import quat_from_euler, quat_multiply

    q_body = quat_from_euler(0.05, -0.1, 2.0)
    kw = dict(
        time_boot_us=t_us,
        lat_deg=32.0123456789,
        lon_deg=118.7654321987,
        alt_amsl_m=123.4567,
        alt_rel_m=80.1234,
        v_ned_mps=(12.345, -6.789, 0.456),
        q_ned_from_body=tuple(q_body),
        body_rates_radps=(0.01, -0.02, 0.03),
        heading_rad=2.0,
        q_gimbal=tuple(quat_multiply(q_body, quat_from_euler(0.0, -0.5, 0.1))),
    )
    kw.update(over)
    v.update_state(**kw)


@pytest.mark.parametrize("gimbal_yaw_frame", ["earth", "vehicle"])
def test_vehicle_streams_are_byte_identical(gimbal_yaw_frame):
    v, writes = _vehicle(gimbal_yaw_frame)
    try:
        for k in range(12):  # 0 .. 1.1 s: every stream at least once, #31 / #33 / #285 several times
            t = 100_000 * k
            _state(v, t + 3_456)
            v.poll(t + 5_000)
        _state(v, 2_000_000, v_ned_mps=(400.0, -400.0, 1.0), heading_rad=math.nan)  # saturated, unknown heading
        v.poll(2_100_000)
        v._on_timesync(_parsed(mav.MAVLink_timesync_message(0, 123_456_789), 255, 190))
        for cmd, p1, p2 in (
            (mav.MAV_CMD_SET_MESSAGE_INTERVAL, 31, 10_000),
            (mav.MAV_CMD_REQUEST_MESSAGE, 242, 0),
            (mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1, 0),
            (mav.MAV_CMD_DO_SET_MODE, 0, 0),
        ):
            v._on_command(_parsed(mav.MAVLink_command_long_message(1, 1, cmd, 0, p1, p2, 0, 0, 0, 0, 0), 255, 190))
        v.poll(2_200_000)
    finally:
        v.close()
    _check(f"vehicle_{gimbal_yaw_frame}", writes)


# --------------------------------------------------------------------------- the daemon's autopilot link


def test_autopilot_link_output_is_byte_identical():
    from onboard.core.counters import RejectCounter
    from onboard.core.frames import CameraMount, GeodeticOrigin
    from onboard.core.pose import PoseBuffer
    from onboard.io.follow import follow_target
    from onboard.io.mavlink_link import MavlinkConfig, MavlinkLink
    from onboard.io.mavlink_wire import CameraTrackingGeoStatus, CameraTrackingImageStatus
    from tests.onboard.test_camera_protocol import _track

    clock = FakeClock(1000.0)
    counters = RejectCounter(clock=clock)
    pose = PoseBuffer(mount=CameraMount(gimballed=True), origin=GeodeticOrigin(32.0, 118.8, 0.0), counter=counters)
    link = MavlinkLink(
        # the rate the golden bytes were captured with: this compares encoders, not the default's value
        MavlinkConfig(connection="udpout:127.0.0.1:9", autopilot_sysid=7, lock_settle_s=0.0, attitude_rate_hz=50.0),
        pose,
        counters,
        gimballed=True,
        clock=clock,
        clock_ns=clock.ns,
    )
    writes: list[bytes] = []
    inbox: list[bytes] = []
    link._transport.write = lambda buf: writes.append(bytes(buf))
    link._transport.read = lambda: (inbox.pop(0), ("127.0.0.1", 14555)) if inbox else None
    try:
        link.tick()  # HEARTBEAT (pinned system id)
        inbox.append(
            _packed(
                mav.MAVLink_heartbeat_message(
                    mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, 0, 0, mav.MAV_STATE_ACTIVE, 3
                ),
                7,
            )
        )
        link.poll()
        link.tick()  # SET_MESSAGE_INTERVAL #31, TIMESYNC request
        inbox.append(
            _packed(
                mav.MAVLink_command_ack_message(
                    mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAV_RESULT_ACCEPTED, 0, 0, 7, 191
                ),
                7,
            )
        )
        inbox.append(_packed(mav.MAVLink_timesync_message(0, 987_654_321), 7))
        link.poll()  # TIMESYNC reply, next SET_MESSAGE_INTERVAL
        clock.t_s += 1.5
        link.tick()  # retry, heartbeat, TIMESYNC
        for mode, where in (
            (mav.CAMERA_TRACKING_MODE_POINT, dict(point_x=0.25, point_y=0.75, radius=0.01)),
            (
                mav.CAMERA_TRACKING_MODE_RECTANGLE,
                dict(rec_top_x=0.1, rec_top_y=0.2, rec_bottom_x=0.3, rec_bottom_y=0.4),
            ),
        ):
            assert link.send_tracking_image_status(
                CameraTrackingImageStatus(mav.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE, mode, **where)
            )
        assert link.send_tracking_geo_status(
            CameraTrackingGeoStatus(
                47.123456789,
                -122.5,
                512.25,
                3.0,
                5.0,
                10.0,
                -2.0,
                0.5,
                1.5,
                dist_m=130.0,
                hdg_rad=0.3,
                hdg_acc_rad=0.05,
            )
        )
        assert link.send_tracking_geo_status(
            CameraTrackingGeoStatus(-33.9, 151.2, -10.0, 1.0, 2.0, math.nan, math.nan, math.nan, math.nan)
        )
        assert link.send_follow_target(follow_target(_track(observable=True)))
    finally:
        link.close()
    _check("autopilot_link", writes)


# --------------------------------------------------------------------------- the camera component


def test_camera_component_output_is_byte_identical():
    import onboard.io.camera_protocol as cp
    from onboard.io.gcs_link import GcsLink
    from tests.onboard.test_camera_protocol import _cmd, _proto, _track

    gcs = GcsLink(["udpout:127.0.0.1:9"], component_id=100)
    writes: list[bytes] = []
    gcs._conns[0].write = lambda buf: writes.append(bytes(buf))
    proto = _proto()
    out = []
    try:
        gcs.set_system_id(1)
        for msg_id in (259, 260, 261, 262, 269, 270, 275, 276):
            out += proto.handle(_cmd(cp.MAV_CMD_REQUEST_MESSAGE, msg_id), 0.0, 1234, _track())[0]
        out += proto.handle(_cmd(cp.MAV_CMD_GET_MESSAGE_INTERVAL, 275), 0.0, 1234)[0]
        out += proto.handle(_cmd(cp.MAV_CMD_CAMERA_TRACK_POINT, 2.0), 0.0, 0)[0]  # refused: ACK + STATUSTEXT
        out += proto.tick(0.0, _track())
        out += proto.tick(1.0, _track(state="coasting", bbox=None))
        out += proto.tick(2.0, _track(state="lost"))  # one IDLE #275
        for o in out:
            assert gcs.send(o) == 1
    finally:
        gcs.close()
    assert len(writes) == len(out)
    _check("camera_component", writes)


def test_golden_file_covers_every_case():
    if os.environ.get("IRTRACK_WRITE_GOLDEN") == "1":
        pytest.skip("writing the golden file")
    golden = json.loads(GOLDEN.read_text())
    assert set(golden) == {"vehicle_earth", "vehicle_vehicle", "autopilot_link", "camera_component", "lockstep_feed"}
    assert all(np.all([len(h) > 0 for h in v]) for v in golden.values())


# --------------------------------------------------------------------------- the lockstep eval's telemetry feed


class _RecordingPose:
    """What TelemetryFeed hands the pose buffer, as exact text (floats in hex)."""

    def __init__(self) -> None:
        self.calls: list[bytes] = []

    @staticmethod
    def _text(v) -> str:
        if v is None:
            return "None"
        if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
            return str(int(v))
        if isinstance(v, (float, np.floating)):
            return float(v).hex()
        if hasattr(v, "value"):  # GimbalReference
            return str(v.value)
        return "[" + ",".join(_RecordingPose._text(x) for x in np.asarray(v, dtype=float).ravel()) + "]"

    def _add(self, name, *args) -> bool:
        self.calls.append(f"{name}({';'.join(self._text(a) for a in args)})".encode())
        return True

    def add_attitude(self, *args):
        return self._add("attitude", *args)

    def add_position(self, *args):
        return self._add("position", *args)

    def add_gimbal_status(self, *args):
        return self._add("gimbal", *args)


class _TurningCore:
    """SimCore's telemetry interface: a banking, climbing observer with a slewing gimbal, 120 Hz ticks."""

    tick_rate_hz = 120.0
    tick_count = 240

    def vehicle_state(self, i: int) -> dict:
        from onboard.core.frames import quat_from_euler, quat_multiply

        t = i / self.tick_rate_hz
        q_body = quat_from_euler(0.2 * math.sin(t), 0.05 * t, 1.0 + 0.3 * t)
        return dict(
            time_boot_us=1_000_123 + round(t * 1e6),
            lat_deg=32.0 + 1.234567e-5 * t,
            lon_deg=118.8 - 3.3e-6 * t,
            alt_amsl_m=100.0 + 1.23456 * t,
            alt_rel_m=60.0 + t,
            v_ned_mps=np.array([10.0 + t, -3.456, -1.23456]),
            q_ned_from_body=q_body,
            body_rates_radps=np.array([0.2 * math.cos(t), 0.05, 0.3]),
            heading_rad=1.0,
            q_gimbal=quat_multiply(q_body, quat_from_euler(0.0, -0.3 - 0.1 * t, 0.2)),
        )


def test_lockstep_telemetry_feed_hands_the_pose_buffer_the_same_values():
    from groundsim.evaluation.eval import TelemetryFeed

    rec = _RecordingPose()
    feed = TelemetryFeed(_TurningCore(), rec, gimballed=True)
    while not feed.exhausted:
        feed.feed_next()
    _check("lockstep_feed", rec.calls)
