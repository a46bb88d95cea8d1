"""Navigation errors of the simulated telemetry (groundsim.world.nav_errors) and where they are applied."""

from __future__ import annotations

import math
import socket
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groundsim.app import cli
from groundsim.evaluation.eval import EvalOptions
from groundsim.evaluation.telemetry_feed import TelemetryFeed
from groundsim.io.mavlink_vehicle import MSG_GIMBAL_DEVICE_ATTITUDE_STATUS, MavlinkVehicle
from groundsim.world.nav_errors import (
    NAV_ERROR_STREAM,
    CameraClockError,
    GnssDropout,
    InjectedErrors,
    NavErrorModel,
    NavErrorSample,
    offset_geodetic,
    parse_camera_time_offset,
    parse_gnss_dropout,
    reported_state,
    resolve_nav_noise,
)
from groundsim.world.scenario import ScenarioError, load_noise_cases, load_scenario, scenario_from_dict, scenarios_dir
from groundsim.world.sim import SimCore
from onboard.app.config import OnboardConfig
from onboard.core.errors import ConfigError
from onboard.core.frames import (
    CameraMount,
    GeodeticOrigin,
    ned_from_geodetic,
    quat_conjugate,
    quat_from_euler,
    quat_multiply,
    rotvec_from_quat,
)
from onboard.core.pose import PoseBuffer
from onboard.core.pose_config import PoseConfig
from tests.groundsim.test_eval import _FakeCore

P1 = scenarios_dir() / "P1.yaml"
N_TICKS = 20_000  # statistics over this many samples: sample std within ~1 % (3 sigma ~ 1.5 %)
STD_RTOL = 0.03
ATOL_RAD = 1e-12
ATOL_M = 1e-5  # 10 um: a NED offset at a point against its flat-Earth reading (curvature |d|^2 / 2R: 6 um at 8.7 m)
T_GRID_S = np.arange(N_TICKS) / 120.0


@pytest.fixture(scope="module")
def cases():
    return load_noise_cases()


def _model(case, seed: int, scenario=None):
    sc = scenario if scenario is not None else load_scenario(P1)
    return NavErrorModel(case, sc.rng(NAV_ERROR_STREAM, seed), T_GRID_S)


# --------------------------------------------------------------------------- the model


def test_deterministic_per_seed_and_different_across_seeds(cases):
    a, b, c = _model(cases["GNSS"], 3), _model(cases["GNSS"], 3), _model(cases["GNSS"], 4)
    np.testing.assert_array_equal(a.att_err_ned_rad(), b.att_err_ned_rad())
    np.testing.assert_array_equal(a.p_err_ned_m(), b.p_err_ned_m())
    assert not np.allclose(a.bias_ned_rad, c.bias_ned_rad)
    assert not np.allclose(a.offset_ned_m, c.offset_ned_m) and not np.allclose(a.drift_ned_mps, c.drift_ned_mps)
    assert not np.allclose(a.att_white_ned_rad[:10], c.att_white_ned_rad[:10])


def test_own_stream_leaves_the_other_streams_alone():
    sc = load_scenario(P1)
    before = sc.rng("render.noise", 2).standard_normal(5)
    _model(load_noise_cases()["RTK"], 2, sc)
    np.testing.assert_array_equal(sc.rng("render.noise", 2).standard_normal(5), before)


@pytest.mark.parametrize("name", ["RTK", "GNSS"])
def test_statistics_match_the_noise_case(cases, name):
    case = cases[name]
    m = _model(case, 0)
    # white attitude noise: per-axis sample std; the bias is the same at every sample
    att = m.att_err_ned_rad()
    white = att - m.bias_ned_rad
    np.testing.assert_allclose(white.std(axis=0), case.attitude_white_sigma_rad, rtol=STD_RTOL)
    np.testing.assert_allclose(
        att.mean(axis=0), m.bias_ned_rad, atol=4 * case.attitude_white_sigma_rad / math.sqrt(N_TICKS)
    )
    # the bias over many runs has the case's sigma
    biases = np.array([_model(case, s).bias_ned_rad for s in range(300)])
    np.testing.assert_allclose(biases.std(), case.attitude_bias_sigma_rad, rtol=0.1)
    # position: offset and drift of the case's size, white noise of its sigma
    assert np.linalg.norm(m.offset_ned_m) == pytest.approx(case.camera_position_offset_m, rel=1e-12)
    assert np.linalg.norm(m.drift_ned_mps) == pytest.approx(case.camera_position_drift_mps, rel=1e-12)
    p = m.p_err_ned_m()
    wpos = p - m.offset_ned_m - T_GRID_S[:, None] * m.drift_ned_mps
    if case.camera_position_white_sigma_m > 0:
        np.testing.assert_allclose(wpos.std(axis=0), case.camera_position_white_sigma_m, rtol=STD_RTOL)
    else:
        np.testing.assert_allclose(wpos, 0.0, atol=1e-12)


def test_exact_case_is_zero(cases):
    m = _model(cases["exact"], 5)
    assert np.all(m.att_err_ned_rad() == 0) and np.all(m.p_err_ned_m() == 0)
    assert m.sample(7).is_zero


def test_reported_velocity_is_the_derivative_of_the_reported_position_without_its_white_part(cases):
    m = _model(cases["GNSS"], 1)
    i, j = 100, 1300
    si, sj = m.sample(i), m.sample(j)
    slope = ((sj.p_err_ned_m - m.p_white_ned_m[j]) - (si.p_err_ned_m - m.p_white_ned_m[i])) / (
        T_GRID_S[j] - T_GRID_S[i]
    )
    np.testing.assert_allclose(slope, si.v_err_ned_mps, atol=1e-12)
    np.testing.assert_array_equal(si.v_err_ned_mps, sj.v_err_ned_mps)


# --------------------------------------------------------------------------- applying a sample


def _truth_state():
    return dict(
        time_boot_us=2_000_000,
        lat_deg=32.001,
        lon_deg=118.802,
        alt_amsl_m=60.0,
        alt_rel_m=60.0,
        v_ned_mps=np.array([0.0, 4.0, 0.0]),
        q_ned_from_body=quat_from_euler(0.02, -0.05, 1.0),
        body_rates_radps=np.zeros(3),
        heading_rad=1.0,
        q_gimbal=quat_from_euler(0.0, -0.3, 0.7),
    )


def test_reported_state_applies_the_sample_to_position_velocity_and_both_attitudes():
    err = NavErrorSample(np.array([1e-3, -2e-3, 3e-3]), np.array([1.5, -0.7, 0.4]), np.array([0.03, -0.04, 0.01]))
    st = _truth_state()
    rep = reported_state(st, err)
    origin = GeodeticOrigin(st["lat_deg"], st["lon_deg"], st["alt_amsl_m"])
    np.testing.assert_allclose(
        ned_from_geodetic(rep["lat_deg"], rep["lon_deg"], rep["alt_amsl_m"], origin), err.p_err_ned_m, atol=ATOL_M
    )
    d_alt_m = rep["alt_amsl_m"] - st["alt_amsl_m"]
    assert rep["alt_rel_m"] - st["alt_rel_m"] == pytest.approx(d_alt_m, abs=1e-12)  # moves with the AMSL altitude
    assert d_alt_m == pytest.approx(-0.4, abs=ATOL_M)  # 0.4 m down; the Earth's curvature over 1.7 m is 0.2 um
    np.testing.assert_allclose(rep["v_ned_mps"], st["v_ned_mps"] + err.v_err_ned_mps, atol=1e-15)
    for key in ("q_ned_from_body", "q_gimbal"):  # R_rep R_true^T = Exp(phi), in NED
        dq = quat_multiply(rep[key], quat_conjugate(st[key]))
        np.testing.assert_allclose(rotvec_from_quat(dq), err.att_err_ned_rad, atol=1e-12)
    assert rep["heading_rad"] != st["heading_rad"] and abs(rep["heading_rad"] - st["heading_rad"]) < 0.01
    assert st["lat_deg"] == 32.001 and rep is not st  # the input is not modified
    assert reported_state(st, None) == st


@settings(max_examples=60, deadline=None)
@given(
    lat=st.floats(-80, 80),
    lon=st.floats(-180, 179.999),
    alt=st.floats(-100, 5000),
    d=st.lists(st.floats(-5, 5), min_size=3, max_size=3),
)
def test_offset_geodetic_is_the_ned_offset_at_the_point(lat, lon, alt, d):
    lat2, lon2, alt2 = offset_geodetic(lat, lon, alt, d)
    assert -180.0 <= lon2 < 180.0
    # exact geodesy (onboard.core.frames) about the point; the bound is the first-order formula's it replaced
    bound_m = float(np.dot(d, d)) * (1.0 + abs(math.tan(math.radians(lat)))) / 6.3e6 + 1e-7  # + the ECEF round trip
    np.testing.assert_allclose(ned_from_geodetic(lat2, lon2, alt2, GeodeticOrigin(lat, lon, alt)), d, atol=bound_m)


# --------------------------------------------------------------------------- simulator, truth, vehicle, feed


def test_simcore_truth_rows_record_the_injected_errors_and_stay_exact():
    sc = load_scenario(P1)
    exact, rtk = SimCore(sc, 2, 0.5, render=False, nav_noise="exact"), SimCore(sc, 2, 0.5, render=False)
    assert rtk.nav_noise.name == "RTK" == sc.nav_noise  # the default
    assert rtk.vehicle_state(3)["lat_deg"] == exact.vehicle_state(3)["lat_deg"]  # vehicle_state is the truth
    for k in (0, 5, 14):
        i = k * rtk.ticks_per_frame
        row, row0 = rtk.frame(k).truth, exact.frame(k).truth
        err = rtk.nav_error(i)
        np.testing.assert_array_equal(
            [row.nav_att_err_n_rad, row.nav_att_err_e_rad, row.nav_att_err_d_rad], err.att_err_ned_rad
        )
        np.testing.assert_array_equal([row.nav_p_err_n_m, row.nav_p_err_e_m, row.nav_p_err_d_m], err.p_err_ned_m)
        assert np.linalg.norm(err.att_err_ned_rad) > 0
        # the truth itself does not depend on the navigation errors
        assert (row.observer_lat_deg, row.cam_n_m, row.q_ned_from_cam_w, row.target_u_px) == (
            row0.observer_lat_deg,
            row0.cam_n_m,
            row0.q_ned_from_cam_w,
            row0.target_u_px,
        )
        assert row0.nav_att_err_n_rad == row0.nav_p_err_d_m == 0.0


@pytest.mark.integration
def test_vehicle_reports_the_state_with_the_error_applied():
    port = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    port.bind(("127.0.0.1", 0))
    err = NavErrorSample(np.array([2e-3, 0.0, -1e-3]), np.array([0.5, 0.2, -0.1]), np.array([0.05, 0.0, 0.0]))
    st = _truth_state()
    with MavlinkVehicle(f"udpout:127.0.0.1:{port.getsockname()[1]}", gimballed=True) as v:
        s = v.update_state(**st, nav_error=err)
    port.close()
    rep = reported_state(st, err)
    assert (s.lat_deg, s.lon_deg, s.alt_amsl_m) == (rep["lat_deg"], rep["lon_deg"], rep["alt_amsl_m"])
    np.testing.assert_allclose(s.q_ned_from_gimbal, rep["q_gimbal"], atol=1e-15)
    np.testing.assert_allclose(s.v_ned_mps, rep["v_ned_mps"], atol=1e-15)


@pytest.mark.integration
def test_vehicle_honours_gimbal_status_at_100_hz():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    st = _truth_state()
    with MavlinkVehicle(f"udpout:127.0.0.1:{rx.getsockname()[1]}", gimballed=True) as v:
        v.poll(1_000_000)
        assert v._set_message_interval(float(MSG_GIMBAL_DEVICE_ATTITUDE_STATUS), 10_000.0) == 0  # ACCEPTED
        for i in range(240):  # 2 s of the simulator's 120 Hz ticks, a new state every tick
            t_us = 1_000_000 + round(i * 1e6 / 120)
            st["time_boot_us"] = t_us
            v.update_state(**st)
            v.poll(t_us)
        sent = v.counters[f"tx_{MSG_GIMBAL_DEVICE_ATTITUDE_STATUS}"]
    rx.close()
    assert 180 <= sent <= 201  # ~100 Hz over 2 s (a 10 ms schedule sampled on 8.3 ms ticks)


class _Core(_FakeCore):
    """test_eval's level observer flying north at 10 m/s (no gimbal), with navigation errors."""

    def __init__(self, seconds: float, case) -> None:
        super().__init__(seconds, gimbal=False)
        self.model = NavErrorModel(case, np.random.default_rng(9), np.arange(self.tick_count) / self.tick_rate_hz)

    def nav_error(self, i: int):
        return self.model.sample(i)


def test_telemetry_feed_injects_the_same_errors_as_the_vehicle():
    case = resolve_nav_noise("GNSS")
    core = _Core(1.0, case)
    buf = PoseBuffer(CameraMount(), PoseConfig(), core.origin)
    feed = TelemetryFeed(core, buf, gimballed=False)
    while not feed.exhausted:
        feed.feed_next()
    i = 60  # t = 0.5 s: a #33 sample (every 40 ms = 4.8 ticks: tick 60 is due) and a #31 one
    pose = buf.pose_at(core.vehicle_state(i)["time_boot_us"])
    err = core.nav_error(i)
    # the offset (1.5 m) and drift dominate: the reported position is the truth moved by the error
    np.testing.assert_allclose(pose.body.p_ned_m, np.array([5.0, 0.0, -60.0]) + err.p_err_ned_m, atol=0.03)
    np.testing.assert_allclose(rotvec_from_quat(pose.body.q_ned_from_body), err.att_err_ned_rad, atol=1e-6)


def test_telemetry_feed_encodes_the_gimbal_as_the_vehicle_does():
    """The lockstep eval's #285 (--gimbal-frame) is the simulated vehicle's, and either frame gives the pose buffer
    the same gimbal: the vehicle frame is turned back with the attitude stream."""
    from onboard.io.mavlink_wire import GimbalReference

    sc = load_scenario(P1)
    got = {}
    for frame, ref in (("earth", GimbalReference.EARTH), ("vehicle", GimbalReference.VEHICLE)):
        core = SimCore(sc, 0, 1.0, render=False, nav_noise="exact")
        buf = PoseBuffer(CameraMount(gimballed=True), PoseConfig(), sc.origin)
        feed = TelemetryFeed(core, buf, gimballed=True, gimbal_frame=frame)
        while not feed.exhausted:
            feed.feed_next()
        assert buf._gim_ref == ref
        got[frame] = buf.pose_at(core.time_boot_us(60)).q_mount_from_gimbal  # a gimbal sample (10 Hz: every 12 ticks)
    assert abs(float(np.dot(got["earth"], got["vehicle"]))) == pytest.approx(1.0, abs=1e-12)


def test_eval_gimbal_frame_is_validated():
    with pytest.raises(ConfigError, match="--gimbal-frame"):
        EvalOptions(gimbal_frame="body")


# --------------------------------------------------------------------------- options and files


def test_bad_nav_noise_name_is_one_line_exit_2(capsys):
    assert cli.main(["run", "--nav-noise", "rtk", "--no-render"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert (
        "noise_cases.yaml: --nav-noise: expected one of px0.3, RTK, GNSS, exact, got 'rtk'; did you mean 'RTK'?"
        in err[0]
    )
    with pytest.raises(ConfigError, match=r"noise_cases.yaml: --nav-noise: expected one of .*got 'nope'"):
        InjectedErrors("nope")


def test_scenario_nav_noise_key_is_validated():
    doc = {
        "name": "x",
        "observer": {"motion": {"model": "cubic", "p0_ned_m": [0, 0, -60]}},
        "target": {"motion": {"model": "cubic", "p0_ned_m": [100, 0, -60]}},
    }
    assert scenario_from_dict(doc).nav_noise == "RTK"
    assert scenario_from_dict({**doc, "nav_noise": "GNSS"}).nav_noise == "GNSS"
    with pytest.raises(ScenarioError, match=r"^<dict>: nav_noise: expected one of px0.3, RTK, GNSS, exact, got 'gps'"):
        scenario_from_dict({**doc, "nav_noise": "gps"})


def test_eval_and_demo_default_to_rtk_and_the_shipped_daemon_config():
    from groundsim.evaluation.eval import DEFAULT_ONBOARD_CONFIG

    assert EvalOptions().injected == InjectedErrors("RTK")
    repo = Path(__file__).resolve().parents[2]
    assert DEFAULT_ONBOARD_CONFIG == repo / "config" / "onboard.yaml" and DEFAULT_ONBOARD_CONFIG.is_file()
    parser = cli.build_parser()
    assert parser.parse_args(["eval"]).nav_noise is None  # cmd_eval: None -> [DEFAULT_NAV_NOISE]
    assert parser.parse_args(["demo"]).onboard_config == "config/onboard.yaml"
    assert isinstance(OnboardConfig().mavlink.gimbal_rate_hz, float)


@pytest.mark.parametrize("bad", ["5", "a:b", "-1:5", "3:-2", "3:inf", ""])
def test_gnss_dropout_option_names_itself_when_bad(bad):
    with pytest.raises(ConfigError, match="--gnss-dropout"):
        parse_gnss_dropout(bad)


def test_gnss_dropout_window_on_the_boot_clock():
    d = parse_gnss_dropout("8:5")
    assert (d.start_s, d.duration_s) == (8.0, 5.0)
    assert d.active(8.0) and d.active(12.999) and not d.active(13.0) and not d.active(7.99)
    assert d.boot_window_us(1_000_000) == (9_000_000, 14_000_000)


def test_camera_clock_error_stamps_frames_late_with_a_drift():
    c = parse_camera_time_offset("50:20")
    assert (c.offset_ms, c.drift_ppm) == (50.0, 20.0)
    assert c.stamp_us(1_000_000, 0.0) == 1_050_000
    assert c.stamp_us(101_000_000, 100.0) == 101_000_000 + 50_000 + 2_000  # 20 ppm of 100 s = 2 ms
    assert parse_camera_time_offset("-12.5").stamp_us(1_000_000, 5.0) == 987_500
    # an early clock's stamp before the autopilot's boot is none (the lockstep eval crashed on it: a negative stamp)
    assert parse_camera_time_offset("-1500").stamp_us(1_000_000, 1.0) is None
    for bad in ("", "x", "50:y", "inf"):
        with pytest.raises(ConfigError, match="--camera-time-offset-ms"):
            parse_camera_time_offset(bad)


def test_injected_errors_from_the_options_text():
    inj = InjectedErrors.from_options("GNSS", "8:5", "50:20")
    assert inj == InjectedErrors("GNSS", GnssDropout(8.0, 5.0), CameraClockError(50.0, 20.0))
    assert inj.run_options() == ["--nav-noise", "GNSS", "--gnss-dropout", "8:5", "--camera-time-offset-ms", "50:20"]
    assert InjectedErrors.from_options(None, "", None) == InjectedErrors()  # empty text: not given
    assert InjectedErrors().run_options() == []  # the scenario's own case, nothing injected
    with pytest.raises(ConfigError, match="--gnss-dropout"):
        InjectedErrors.from_options("RTK", "8")
    with pytest.raises(ConfigError, match="gnss_dropout must be a GnssDropout"):
        InjectedErrors(gnss_dropout="8:5")


_OPTION_FLOATS = st.floats(0.0, 1e6, allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None)
@given(start_s=_OPTION_FLOATS, duration_s=_OPTION_FLOATS, offset_ms=_OPTION_FLOATS, drift_ppm=_OPTION_FLOATS)
def test_injected_errors_round_trip_through_the_run_options(start_s, duration_s, offset_ms, drift_ppm):
    """What demo passes to its ``groundsim run`` is read back to the same errors, to the last bit."""
    inj = InjectedErrors("exact", GnssDropout(start_s, duration_s), CameraClockError(-offset_ms, drift_ppm))
    argv = inj.run_options()
    text = dict(zip(argv[::2], argv[1::2]))
    back = InjectedErrors.from_options(text["--nav-noise"], text["--gnss-dropout"], text["--camera-time-offset-ms"])
    assert back == inj
