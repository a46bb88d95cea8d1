"""The simulated vehicle's guided mode (groundsim.world.guided): scripted motion until the first setpoint, then a
continuous slew to each setpoint within the vehicle's limits; and the lockstep eval closing the loop with it."""

from __future__ import annotations

import numpy as np
import pytest

from groundsim.world.guided import GuidedLimits, GuidedReference
from groundsim.world.motion import Cubic

ATOL_M = 1e-9  # closed-form integration


def test_scripted_until_the_first_setpoint_then_continuous_slew_within_limits():
    base = Cubic((0.0, 0.0, -60.0), (0.0, 8.0, 0.0))
    ref = GuidedReference(base, GuidedLimits(max_speed_mps=10.0, max_climb_rate_mps=1.0, max_accel_mps2=2.0))
    t = np.linspace(0.0, 16.0, 1601)  # the slew of 18 m/s at 2 m/s^2 ends at 13 s
    before = ref.state(t)
    np.testing.assert_allclose(before.p_ned_m, base.state(t).p_ned_m, atol=ATOL_M)
    ref.command(4.0, (0.0, -30.0, -5.0))  # too fast, too steep: clamped; held (no expiry)
    st = ref.state(t)
    early = t < 4.0
    np.testing.assert_allclose(st.p_ned_m[early], before.p_ned_m[early], atol=ATOL_M)
    # continuous at the switch, then within the limits, ending on the clamped setpoint
    assert np.max(np.linalg.norm(np.diff(st.p_ned_m, axis=0), axis=1)) < 0.2
    assert np.max(np.linalg.norm(np.diff(st.v_ned_mps, axis=0), axis=1) / np.diff(t)[0]) <= 2.0 + 1e-6
    np.testing.assert_allclose(st.v_ned_mps[-1], [0.0, -10.0, -1.0], atol=ATOL_M)
    assert np.all(np.hypot(st.v_ned_mps[:, 0], st.v_ned_mps[:, 1]) <= 10.0 + 1e-9)
    assert ref.guided_since_s == 4.0
    with pytest.raises(ValueError, match="back"):
        ref.command(3.0, (0.0, 0.0, 0.0))


def test_a_lapsed_setpoint_brakes_to_a_hover_unless_a_newer_one_comes_first():
    """ArduCopter stops when velocity setpoints stop for GUID_TIMEOUT; the daemon's gate brakes when its advice ends:
    the simulated vehicle kept the last velocity for ever, which hid a daemon that left it flying."""
    from groundsim.world.guided import GUIDED_SETPOINT_TIMEOUT_S

    base = Cubic((0.0, 0.0, -60.0), (0.0, 0.0, 0.0))
    ref = GuidedReference(base, GuidedLimits(max_speed_mps=10.0, max_climb_rate_mps=1.0, max_accel_mps2=2.0))
    ref.command(0.0, (8.0, 0.0, 0.0), valid_until_s=GUIDED_SETPOINT_TIMEOUT_S)
    st = ref.state(np.array([3.0, 5.0, 7.0, 20.0]))
    np.testing.assert_allclose(st.v_ned_mps[:, 0], [6.0, 2.0, 0.0, 0.0], atol=ATOL_M)  # 2 m/s^2 up, then down
    np.testing.assert_allclose(st.p_ned_m[3], st.p_ned_m[2], atol=ATOL_M)  # hovering
    ref.command(2.0, (8.0, 0.0, 0.0), valid_until_s=5.0)  # a newer setpoint before the lapse: the slew goes on
    assert ref.state(np.array([4.0])).v_ned_mps[0, 0] == pytest.approx(8.0)
    assert ref.state(np.array([6.0])).v_ned_mps[0, 0] == pytest.approx(6.0)


def test_eval_guidance_runs_the_daemons_gate_so_a_lost_target_ends_the_advice_at_once():
    """groundsim eval --guidance commanded each advice straight to the simulated vehicle for its whole validity: a
    lost target or a newer answer without a manoeuvre did not end it, where the daemon's gate brakes at once.  It
    runs the daemon's tap and gate now, the simulated vehicle behind a stand-in autopilot link."""
    import dataclasses
    from types import SimpleNamespace

    from groundsim.evaluation.lockstep_guidance import LockstepGuidance
    from groundsim.world.guided import GUIDED_SETPOINT_TIMEOUT_S
    from onboard.app.config import OnboardConfig
    from onboard.core.frames import GeodeticOrigin
    from onboard.core.track import Track
    from onboard.estimation.guidance import BRAKE_S

    commands: list = []
    flight = SimpleNamespace(command_observer=lambda t, v, until: commands.append((t, np.asarray(v, float), until)))
    guidance = LockstepGuidance(OnboardConfig(), flight, home_alt_amsl_m=0.0)
    origin = GeodeticOrigin(32.0, 118.8, 0.0)
    cam = np.array([0.0, 40.0, -60.0])  # 60 m above home, flying east at 8 m/s
    body = SimpleNamespace(p_ned_m=cam, v_ned_mps=np.array([0.0, 8.0, 0.0]))
    pose = SimpleNamespace(p_cam_ned_m=cam, body=body, origin=origin, pos_extrapolated_us=0)
    p = np.array([135.0, 50.0, -80.0])
    u = (p - cam) / np.linalg.norm(p - cam)
    cov = 4.0 * np.eye(3) + (0.5 * np.linalg.norm(p - cam)) ** 2 * np.outer(u, u)  # range unobservable
    track = Track(
        vehicle="uav1",
        seq=1,
        time_boot_us=5_000_000,
        state="tracking",
        origin=origin,
        lat_deg=32.0,
        lon_deg=118.8,
        alt_m=80.0,
        p_ned_m=tuple(p),
        v_ned_mps=(-3.0, -2.0, 0.0),
        cov_p_ned_m2=cov,
        range_m=float(np.linalg.norm(p - cam)),
    )
    position = ("p_ned_m", "lat_deg", "lon_deg", "alt_m", "v_ned_mps", "cov_p_ned_m2", "range_m")
    lost = dataclasses.replace(track, **dict.fromkeys(position))

    def frames(t0_s, n, tr):  # 30 Hz
        for i in range(n):
            t_s = t0_s + i / 30.0
            guidance.frame(t_s, True, pose, dataclasses.replace(tr, time_boot_us=int(t_s * 1e6)))

    frames(5.0, 30, track)  # planned on the first frame; handed over; a setpoint every 0.25 s
    assert len(guidance.advices) == 1 and len(commands) == 3
    assert all(v.any() and until == t + GUIDED_SETPOINT_TIMEOUT_S for t, v, until in commands)
    frames(6.0, 60, lost)  # the target lost: the advice in force (valid to 8 s) ends at the next setpoint
    after = commands[3:]
    assert after and all(not v.any() for _, v, _ in after)  # zero velocity ...
    assert after[0][0] <= 6.25 and after[-1][0] - after[0][0] < BRAKE_S  # ... at once, for BRAKE_S, then nothing
    assert guidance.summary(5.0)["setpoints"] == len(commands) and guidance.summary(5.0)["stops"] == {}


@pytest.mark.slow
def test_eval_with_guidance_leaves_the_straight_line_after_the_first_advice():
    from groundsim.evaluation.eval import EvalOptions, run_lockstep
    from groundsim.world.scenario import load_scenario, resolve_scenario_path

    sc = load_scenario(resolve_scenario_path("H3"))
    r = run_lockstep(sc, 0, EvalOptions(duration_s=5.0, batch=False, keep_frame=False, guidance=True))
    assert r.error is None and r.guidance is not None
    assert r.guidance["advices"] >= 1 and r.guidance["setpoints"] >= 1 and r.guidance["stops"] == {}
    t0 = r.guidance["first_advice_s"]
    # H3's observer flies straight east at 8 m/s: after the advice it leaves that line
    t = r.t_s - r.t_s[0]
    assert np.max(np.abs(r.observer_p_ned_m[t < t0, 0])) < 0.05
    assert np.max(np.abs(r.observer_p_ned_m[t > t0 + 1.5, 0])) > 0.25
    from groundsim.evaluation.scoring import format_guidance_summary, guidance_figures

    assert guidance_figures(r)["first_track_s"] is not None
    row = format_guidance_summary([r]).splitlines()[-1]
    assert row.startswith("| H3 | ") and " | 1 | " in row


@pytest.mark.slow
def test_eval_with_guidance_through_a_gnss_dropout_keeps_the_frames_it_has_fed_past():
    """In a GNSS dropout the lockstep feed looks up to 0.3 s past each frame for the position that brackets it;
    guided flight flies in 0.1 s chunks and kept the latest two, so the frame's own tick had been dropped
    (`groundsim eval --guidance --gnss-dropout 6:3`: IndexError "tick 716 was flown and dropped")."""
    from groundsim.evaluation.eval import EvalOptions, run_lockstep
    from groundsim.world.nav_errors import GnssDropout, InjectedErrors
    from groundsim.world.scenario import load_scenario, resolve_scenario_path

    sc = load_scenario(resolve_scenario_path("H3"))
    injected = InjectedErrors(gnss_dropout=GnssDropout(2.0, 1.0))
    opts = EvalOptions(duration_s=4.0, batch=False, keep_frame=False, guidance=True, injected=injected)
    r = run_lockstep(sc, 0, opts)
    assert r.error is None and r.frames >= 115 and r.counters.get("position_resumed") == 1


@pytest.mark.integration
def test_guided_vehicle_reports_guided_and_takes_the_companions_velocity_setpoints(caplog):
    import logging
    import time

    from groundsim.io.mavlink_vehicle import (
        ARDUCOPTER_GUIDED_MODE,
        ARDUCOPTER_LOITER_MODE,
        MavlinkVehicle,
        open_mavlink2,
    )
    from groundsim.io.ports import free_udp_port
    from onboard.io.mavlink_wire import SetPositionTargetLocalNed, mavlink2

    caplog.set_level(logging.INFO, "groundsim.io.mavlink_vehicle")
    port = free_udp_port()
    rx = open_mavlink2(f"udpin:127.0.0.1:{port}", 1, 191)  # the companion's side
    vehicle = MavlinkVehicle(f"udpout:127.0.0.1:{port}", guided=True)
    try:
        deadline = time.monotonic() + 10.0
        hb = None
        while hb is None and time.monotonic() < deadline:
            vehicle.poll(0)
            hb = rx.recv_match(type="HEARTBEAT", blocking=False)
            time.sleep(0.002)
        assert hb is not None  # LOITER until the pilot hands the vehicle over to the companion it has heard
        assert (hb.autopilot, hb.custom_mode) == (mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, ARDUCOPTER_LOITER_MODE)
        assert hb.base_mode & mavlink2.MAV_MODE_FLAG_SAFETY_ARMED
        rx.mav.send(SetPositionTargetLocalNed(1_000_000, 1, 1, (7.0, 7.0, 7.0)).to_message())  # before: ignored
        # a ground station's heartbeat (another system, MAV_TYPE_GCS) reaching the vehicle first hands nothing over
        gcs = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
        rx.write(gcs.heartbeat_encode(mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 4).pack(gcs))
        modes = []
        now_us = 0
        while now_us < 3_000_000 and time.monotonic() < deadline:
            now_us += 100_000
            vehicle.poll(now_us)
            hb = rx.recv_match(type="HEARTBEAT", blocking=False)
            if hb is not None:
                modes.append(hb.custom_mode)
            time.sleep(0.002)
        assert vehicle.counters["rx_HEARTBEAT"] == 1 and modes and set(modes) == {ARDUCOPTER_LOITER_MODE}, modes
        rx.mav.heartbeat_send(mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        modes = []
        while ARDUCOPTER_GUIDED_MODE not in modes and time.monotonic() < deadline:
            now_us += 100_000  # the vehicle's heartbeats are 1 s apart on its clock
            vehicle.poll(now_us)
            hb = rx.recv_match(type="HEARTBEAT", blocking=False)
            if hb is not None:
                modes.append(hb.custom_mode)
            time.sleep(0.002)
        assert modes[0] == ARDUCOPTER_LOITER_MODE and modes[-1] == ARDUCOPTER_GUIDED_MODE  # one LOITER heard first
        assert vehicle.take_setpoints() == []
        rx.mav.send(SetPositionTargetLocalNed(1_000_000, 1, 1, (2.0, -3.0, 0.5)).to_message())
        rx.mav.send(SetPositionTargetLocalNed(1_000_000, 9, 1, (9.0, 9.0, 9.0)).to_message())  # another system's
        got: list = []
        while len(got) < 1 and time.monotonic() < deadline:
            vehicle.poll(now_us)
            got += vehicle.take_setpoints()
            time.sleep(0.002)
        for _ in range(20):  # the other system's setpoint, if it were taken, would come now
            vehicle.poll(now_us)
            got += vehicle.take_setpoints()
            time.sleep(0.002)
        assert got == [(2.0, -3.0, 0.5)]
        # said once each, from the simulator's side (nothing else there showed the vehicle flew the setpoints)
        said = [r.getMessage() for r in caplog.records if r.name == "groundsim.io.mavlink_vehicle"]
        assert sum("LOITER -> GUIDED" in m for m in said) == 1, said
        assert [m for m in said if "first velocity setpoint" in m] == [
            "guided: first velocity setpoint flown: north 2.00 east -3.00 down 0.50 m/s"
        ]
    finally:
        vehicle.close()
        rx.close()


def test_a_ground_station_takes_the_guided_vehicle_back_to_loiter_and_hands_it_over_again():
    """The simulated autopilot refused every mode change a ground station asked (DO_SET_MODE: UNSUPPORTED; SET_MODE
    dropped), so the gate's 'the pilot took the vehicle back' could not be flown against it.  Now LOITER and GUIDED
    are taken from a ground station, by command or by SET_MODE (acked as ArduPilot acks it): in LOITER the heartbeat
    says so, the setpoints are ignored and the flight is told once to hold; back in GUIDED they are flown again."""
    import time

    from groundsim.io.mavlink_vehicle import (
        ARDUCOPTER_GUIDED_MODE,
        ARDUCOPTER_LOITER_MODE,
        MavlinkVehicle,
        open_mavlink2,
    )
    from groundsim.io.ports import free_udp_port
    from onboard.io.mavlink_wire import SetPositionTargetLocalNed, mavlink2

    port = free_udp_port()
    rx = open_mavlink2(f"udpin:127.0.0.1:{port}", 1, 191)  # the companion's side, and the ground station's here
    vehicle = MavlinkVehicle(f"udpout:127.0.0.1:{port}", guided=True)
    gcs = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
    now = {"us": 0}
    deadline = time.monotonic() + 15.0

    def until(what, pred):
        got = []
        while time.monotonic() < deadline:
            now["us"] += 100_000
            vehicle.poll(now["us"])
            while (m := rx.recv_match(blocking=False)) is not None:
                got.append(m)
            if pred(got):
                return got
            time.sleep(0.002)
        raise AssertionError(f"timed out waiting for {what}: {[m.get_type() for m in got][-10:]}")

    def mode_of(got):
        hbs = [m for m in got if m.get_type() == "HEARTBEAT"]
        return hbs[-1].custom_mode if hbs else None

    def acks(got):
        return [(m.command, m.result) for m in got if m.get_type() == "COMMAND_ACK"]

    custom = mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    try:
        until("a heartbeat", lambda got: mode_of(got) is not None)  # (the udpin side learns where to answer)
        rx.mav.heartbeat_send(mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        until("GUIDED", lambda got: mode_of(got) == ARDUCOPTER_GUIDED_MODE)
        assert vehicle.in_guided and not vehicle.take_hold()
        # the pilot takes the vehicle back: LOITER by command
        rx.write(gcs.command_long_encode(1, 1, mavlink2.MAV_CMD_DO_SET_MODE, 0, custom, ARDUCOPTER_LOITER_MODE,
                                         0, 0, 0, 0, 0).pack(gcs))  # fmt: skip
        got = until("LOITER", lambda got: mode_of(got) == ARDUCOPTER_LOITER_MODE)
        assert (mavlink2.MAV_CMD_DO_SET_MODE, mavlink2.MAV_RESULT_ACCEPTED) in acks(got)
        assert vehicle.take_hold() and not vehicle.take_hold()  # once
        rx.mav.send(SetPositionTargetLocalNed(1_000_000, 1, 1, (5.0, 0.0, 0.0)).to_message())
        until("the setpoint read", lambda got: vehicle.counters["rx_SET_POSITION_TARGET_LOCAL_NED"] >= 1)
        assert vehicle.take_setpoints() == []  # not flown in LOITER
        # a mode the simulator does not fly: refused, the mode kept
        rx.write(gcs.command_long_encode(1, 1, mavlink2.MAV_CMD_DO_SET_MODE, 0, custom, 3, 0, 0, 0, 0, 0).pack(gcs))
        got = until("the refusal", lambda got: acks(got))
        assert acks(got) == [(mavlink2.MAV_CMD_DO_SET_MODE, mavlink2.MAV_RESULT_DENIED)]
        # handed over again, by SET_MODE (acked with its message id, as ArduPilot does)
        rx.write(gcs.set_mode_encode(1, custom, ARDUCOPTER_GUIDED_MODE).pack(gcs))
        got = until("GUIDED again", lambda got: mode_of(got) == ARDUCOPTER_GUIDED_MODE)
        assert (mavlink2.MAVLINK_MSG_ID_SET_MODE, mavlink2.MAV_RESULT_ACCEPTED) in acks(got)
        rx.mav.send(SetPositionTargetLocalNed(1_000_000, 1, 1, (2.0, -3.0, 0.5)).to_message())
        flown: list = []
        until("the setpoint flown", lambda got: bool(flown.extend(vehicle.take_setpoints()) or flown))
        assert flown == [(2.0, -3.0, 0.5)]
    finally:
        vehicle.close()
        rx.close()


def test_a_vehicle_that_is_not_guided_refuses_a_mode_change():
    from groundsim.io.mavlink_vehicle import ARDUCOPTER_LOITER_MODE, MavlinkVehicle
    from onboard.io.mavlink_wire import mavlink2

    vehicle = MavlinkVehicle("udpout:127.0.0.1:9", guided=False)
    try:
        assert vehicle._set_mode(mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, ARDUCOPTER_LOITER_MODE) == (
            mavlink2.MAV_RESULT_UNSUPPORTED
        )
        assert not vehicle.take_hold()
    finally:
        vehicle.close()


def test_a_mode_change_with_a_base_mode_that_is_no_number_is_denied_not_left_unanswered():
    """A COMMAND_LONG's params are floats: DO_SET_MODE with param1 NaN or infinite raised in int() (ValueError,
    OverflowError), counted as rx_handler_error with no COMMAND_ACK for the ground station; as the other commands'
    non-finite params, it is DENIED."""
    from groundsim.io.mavlink_vehicle import ARDUCOPTER_GUIDED_MODE, MavlinkVehicle
    from onboard.io.mavlink_wire import mavlink2

    vehicle = MavlinkVehicle("udpout:127.0.0.1:9", guided=True)
    try:
        for base_mode in (float("nan"), float("inf")):
            assert vehicle._set_mode(base_mode, ARDUCOPTER_GUIDED_MODE) == mavlink2.MAV_RESULT_DENIED
        assert not vehicle.in_guided and not vehicle.take_hold()
    finally:
        vehicle.close()
