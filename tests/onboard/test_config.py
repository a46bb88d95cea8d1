"""onboard.app.config: strict YAML -> typed config, one-line errors, env/CLI overrides; the shipped file."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from onboard.app.config import (
    OnboardConfig,
    OnboardConfigError,
    _leaf_paths,
    build_config,
    config_to_dict,
    env_overrides,
    load_config,
    parse_set_option,
)
from onboard.core.errors import ConfigError
from onboard.core.frames import quat_from_euler

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "config" / "onboard.yaml"
ATOL_DEG_AS_RAD = 1e-12  # exact conversion
ATOL_Q = 1e-12
ONE_LINE = re.compile(r"^[^\n]+$")


def write(tmp_path: Path, text: str, name: str = "c.yaml") -> str:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return str(p)


# --------------------------------------------------------------------------- defaults and the shipped file


def test_defaults_are_valid_and_convert_to_core_objects():
    c = OnboardConfig()
    assert c.vehicle == "uav1"
    assert c.mavlink.connection == "udpin:127.0.0.1:14540" and c.mavlink.autopilot_sysid == 1
    assert c.zenoh.multicast_scouting is False and c.zenoh.connect == () and c.zenoh.listen == ()
    K = c.camera.pinhole()
    assert (K.width_px, K.height_px, K.cx_px, K.cy_px) == (640, 512, 320.0, 256.0)
    assert K.fx_px == pytest.approx(13e-3 / 17e-6, rel=1e-12)
    b = c.pose
    assert (b.att_max_gap_us, b.pos_max_gap_us, b.window_us, b.reboot_threshold_us) == (
        100_000,
        300_000,
        5_000_000,
        1_000_000,
    )
    n = c.estimator.noise_model()
    assert n.attitude_bias_sigma_rad == pytest.approx(math.radians(0.1), abs=ATOL_DEG_AS_RAD)
    assert n.pixel_sigma_px == 0.3
    lc = c.mavlink
    assert (lc.component_id, lc.autopilot_compid, lc.heartbeat_timeout_s) == (191, 1, 5.0)


def test_pose_wait_and_extrapolation_defaults():
    """A frame is held a few ms at most, then extrapolated; #285 at 50 Hz."""
    c = OnboardConfig()
    assert c.pose.wait_ms == 5.0 and c.mavlink.gimbal_rate_hz == 50.0
    assert c.mavlink.gimbal_rate_hz == 50.0
    b = c.extrapolation_horizons()
    assert (b.attitude_us, b.gimbal_us, b.position_us) == (
        36_351,
        24_595,
        50_000,
    )
    assert c.pose.body_rate_sigma_rps == pytest.approx(math.radians(0.1), abs=ATOL_DEG_AS_RAD)
    # without a bearing noise to bound them, the horizons are the configured cap
    assert c.pose.extrapolation_horizons().attitude_us == 50_000
    # a tighter noise fraction shortens attitude and gimbal, never position
    t = build_config({"pose": {"extrapolation_noise_fraction": 0.1}}).extrapolation_horizons()
    assert t.attitude_us < b.attitude_us and t.gimbal_us < b.gimbal_us
    assert t.position_us == 50_000
    off = build_config({"pose": {"max_extrapolation_ms": 0}}).extrapolation_horizons()
    assert (off.attitude_us, off.position_us, off.gimbal_us) == (0, 0, 0)


def test_shipped_file_equals_defaults():
    assert config_to_dict(load_config(SHIPPED, environ={})) == config_to_dict(OnboardConfig())


def test_shipped_file_documents_every_field():
    """Every leaf field appears in config/onboard.yaml as a key with a comment on its line.

    ``imaging`` is the exception by design: its fields belong to (and are documented in)
    ``ImagingParams``, which the file points to, so the file cannot go stale when they change.
    """
    text = SHIPPED.read_text(encoding="utf-8")
    assert re.search(r"^imaging: \{\}\s+#.*ImagingParams", text, re.M)
    for path in _leaf_paths():
        if path.startswith("imaging."):
            continue
        key = path.rsplit(".", 1)[-1]
        lines = [ln for ln in text.splitlines() if re.match(rf"^\s*(# )?{re.escape(key)}:", ln)]
        assert lines, f"{path} is not in {SHIPPED.name}"
        assert any("#" in ln.split(":", 1)[1] for ln in lines), f"{path} has no comment in {SHIPPED.name}"


def test_print_config_round_trips(tmp_path):
    data = config_to_dict(OnboardConfig())
    p = write(tmp_path, yaml.safe_dump(data))
    assert config_to_dict(load_config(p, environ={})) == data


def test_conversions_of_non_default_values(tmp_path):
    p = write(
        tmp_path,
        """
camera:
  intrinsics: {fx_px: 800, fy_px: 790, width_px: 320, height_px: 256, cx_px: 161.5}
  mount: {lever_arm_frd_m: [0.1, 0, 0.05], pitch_deg: -10, gimballed: true}
pose: {attitude_max_gap_ms: 40.5, origin: {lat_deg: 32, lon_deg: 118.8, alt_m: 12}}
estimator: {attitude_white_sigma_deg: 0.5}
""",
    )
    c = load_config(p, environ={})
    K = c.camera.pinhole()
    assert (K.fx_px, K.fy_px, K.cx_px, K.cy_px, K.width_px) == (800.0, 790.0, 161.5, 128.0, 320)
    m = c.camera.camera_mount()
    assert m.gimballed and m.lever_arm_frd_m == (0.1, 0.0, 0.05)
    q = quat_from_euler(0.0, math.radians(-10.0), 0.0)
    assert max(abs(a - b) for a, b in zip(m.q_body_from_mount, q)) < ATOL_Q
    assert c.pose.att_max_gap_us == 40_500
    # the 50 ms extrapolation horizon is capped by the attitude gap; 0.5 deg white attitude noise
    # widens the bearing noise, so the noise bound does not shorten it further
    b = c.extrapolation_horizons()
    assert b.attitude_us == 40_500 and b.position_us == 50_000
    o = c.pose.geodetic_origin()
    assert (o.lat_deg, o.lon_deg, o.alt_m) == (32.0, 118.8, 12.0)
    assert c.estimator.noise_model().attitude_white_sigma_rad == pytest.approx(math.radians(0.5), abs=ATOL_DEG_AS_RAD)


@pytest.mark.parametrize("text", ["", "# nothing but a comment\n", "---\n", "~\n"])
def test_an_empty_config_file_is_refused_not_run_on_the_defaults(tmp_path, text):
    """An empty or comment-only --config file ran on the built-in defaults and --check said ok."""
    path = write(tmp_path, text)
    with pytest.raises(OnboardConfigError) as err:
        load_config(path, environ={})
    assert str(err.value) == f"{path}: (document): expected a mapping of config sections, got an empty document"
    assert err.value.exit_code == 2


def test_empty_sections_mean_defaults(tmp_path):
    assert config_to_dict(load_config(write(tmp_path, "mavlink:\nimaging:\n"), environ={})) == config_to_dict(
        OnboardConfig()
    )
    assert config_to_dict(load_config(write(tmp_path, "{}\n"), environ={})) == config_to_dict(OnboardConfig())
    assert config_to_dict(load_config(None, environ={})) == config_to_dict(OnboardConfig())  # no file: the defaults


# --------------------------------------------------------------------------- errors


BAD = [
    # (yaml text, field path, fragment of "expected ...", fragment of "got ...", hint or None)
    ("mavlnk: {}", "mavlnk", "a key of the document", "unknown key 'mavlnk'", "did you mean 'mavlink'?"),
    (
        "mavlink: {conection: udpin:1.2.3.4:5}",
        "mavlink.conection",
        "a key of mavlink",
        "unknown key",
        "did you mean 'connection'?",
    ),
    ("mavlink: {attitude_rate_hz: -1}", "mavlink.attitude_rate_hz", "a number in (0, 1000]", "-1", None),
    ("mavlink: {attitude_rate_hz: true}", "mavlink.attitude_rate_hz", "a number", "true", None),
    ("mavlink: {connection: 'udpin:nohost'}", "mavlink.connection", "a connection like", "'udpin:nohost'", None),
    (
        "mavlink: {heartbeat_interval_s: 5, heartbeat_timeout_s: 2}",
        "mavlink.heartbeat_timeout_s",
        "> mavlink.heartbeat_interval_s",
        "2",
        None,
    ),
    ("mavlink: {poll_rate_hz: 50}", "mavlink.poll_rate_hz", "[100, 10000]", "50", None),
    ("mavlink: {autopilot_sysid: 256}", "mavlink.autopilot_sysid", "an integer in [1, 255] or null", "256", None),
    ("zenoh: {connect: [bogus]}", "zenoh.connect[0]", "<protocol>/<address>", "'bogus'", None),
    ("zenoh: {listen: 7}", "zenoh.listen", "a list of strings", "7", None),
    ("camera: {intrinsics: {width_px: 640.0}}", "camera.intrinsics.width_px", "an integer", "640.0", None),
    ("camera: {intrinsics: {fx_px: 1e300}}", "camera.intrinsics.fx_px", "a number in (0, 1e+07]", "1e+300", None),
    ("camera: {intrinsics: {cx_px: 900}}", "camera.intrinsics.cx_px", "inside the image", "900", None),
    (
        "camera: {intrinsics: {distortion: [0, 0, 0]}}",
        "camera.intrinsics.distortion",
        "a list of 5 finite numbers",
        "[0, 0, 0]",
        None,
    ),
    (
        "camera: {intrinsics: {distortion: [0, 0, .nan, 0, 0]}}",
        "camera.intrinsics.distortion[2]",
        "a finite number",
        "nan",
        None,
    ),
    (
        "camera: {intrinsics: {distortion: [-1.0, 0, 0, 0, 0]}}",  # no ideal point reaches the corners
        "camera.intrinsics.distortion",
        "can be inverted over the whole image",
        "(-1.0, 0.0, 0.0, 0.0, 0.0)",
        "check the calibration's signs and scale (OpenCV's order, normalised coordinates)",
    ),
    (
        "camera: {mount: {lever_arm_frd_m: [1, 2]}}",
        "camera.mount.lever_arm_frd_m",
        "a list of 3 finite numbers",
        "[1, 2]",
        None,
    ),
    ("camera: {mount: {gimballed: 'yes'}}", "camera.mount.gimballed", "true or false", "'yes'", None),
    ("camera: {lens: {}}", "camera.lens", "a key of camera", "unknown key 'lens'", None),
    ("imaging: {min_area_px: 0}", "imaging.min_area_px", "in [1, 16777216]", "0", None),
    (
        "imaging: {min_areapx: 3}",
        "imaging.min_areapx",
        "a key of imaging",
        "unknown key",
        "did you mean 'min_area_px'?",
    ),
    ("imaging: {mean_kernel_px: 4}", "imaging.mean_kernel_px", "odd", "4", None),
    ("imaging: {threshold_high_sigma: 1.0}", "imaging.threshold_high_sigma", ">= threshold_low_sigma", "1.0", None),
    ("estimator: {window_s: 0}", "estimator.window_s", "a number in (0, 600]", "0", None),
    (
        "estimator: {sliding: {max_frame: 300}}",
        "estimator.sliding.max_frame",
        "a key of estimator.sliding",
        "unknown key",
        "did you mean 'max_frames'?",
    ),
    ("estimator: {sliding: {max_frames: 300.5}}", "estimator.sliding.max_frames", "an integer >= 10", "300.5", None),
    (
        "estimator: {sliding: {consistency_check: 'no'}}",
        "estimator.sliding.consistency_check",
        "true or false",
        "'no'",
        None,
    ),
    (
        "estimator: {sliding: {edge_sigma_factor: -1}}",
        "estimator.sliding.edge_sigma_factor",
        "a number > 0",
        "-1",
        None,
    ),
    ("estimator: {sliding: {min_spacing_s: .inf}}", "estimator.sliding.min_spacing_s", "a number >= 0", "inf", None),
    ("estimator: {sliding: {window_s: 5}}", "estimator.sliding.window_s", "as estimator.window_s", "unknown key", None),
    (
        "estimator: {sliding: {reselect_max_period_s: 1}}",
        "estimator.sliding.reselect_max_period_s",
        ">= reselect_period_s",
        "1",
        None,
    ),
    (
        "pose: {position_interp: hermit}",
        "pose.position_interp",
        "one of hermite, linear",
        "'hermit'",
        "did you mean 'hermite'?",
    ),
    ("pose: {attitude_max_gap_ms: 9000}", "pose.attitude_max_gap_ms", "<= pose.window_s", "9000", None),
    ("pose: {origin: {lat_deg: 91, lon_deg: 0, alt_m: 0}}", "pose.origin.lat_deg", "[-90, 90]", "91", None),
    ("pose: {max_extrapolation_ms: -1}", "pose.max_extrapolation_ms", "[0, 10000]", "-1", None),
    ("pose: {body_rate_sigma_dps: .nan}", "pose.body_rate_sigma_dps", "a number in [0, 1000]", "nan", None),
    ("pose: {extrapolation_noise_fraction: 'a'}", "pose.extrapolation_noise_fraction", "a number", "'a'", None),
    ("mavlink: {gimbal_rate_hz: 0}", "mavlink.gimbal_rate_hz", "(0, 1000]", "0", None),
    ("pose: {origin: [1, 2]}", "pose.origin", "a mapping", "[1, 2]", None),
    ("pose: {origin: {lat_deg: 47, lon_deg: 8.5}}", "pose.origin.alt_m", "a value (required)", "missing", None),
    ("pose: {origin: {}}", "pose.origin.lat_deg", "a value (required)", "missing", None),
    ("output: {tracking_geo_status_hz: -5}", "output.tracking_geo_status_hz", "[0, 100]", "-5", None),
    ("output: {health_interval_s: 10}", "output.health_interval_s", "[0.05, 2.5]", "10", None),
    ("logging: {level: info}", "logging.level", "one of DEBUG, INFO", "'info'", "did you mean 'INFO'?"),
    ("gcs: {component_id: 1}", "gcs.component_id", "an integer in [100, 105]", "1", None),  # the autopilot's
    ("gcs: {component_id: 106}", "gcs.component_id", "an integer in [100, 105]", "106", None),  # not a camera's
    ("input: {time_reset_threshold_s: 0}", "input.time_reset_threshold_s", "a number in [0.001, 3600]", "0", None),
    # 20 characters, 40 bytes in UTF-8: CAMERA_INFORMATION's field holds 32 bytes
    ("gcs: {vendor_name: ÄÖÜäöüßÄÖÜäöüßÄÖÜäöü}", "gcs.vendor_name", "at most 32 bytes", "ÄÖÜäöüß", None),
    ("gcs: {model_name: ÄÖÜäöüßÄÖÜäöüßÄÖÜäöü}", "gcs.model_name", "at most 32 bytes", "ÄÖÜäöüß", None),
    ("vehicle: 'uav 1'", "vehicle", "one zenoh key chunk", "'uav 1'", None),
    ("- a\n- b", "(document)", "a mapping of sections", "['a', 'b']", None),
    ("vehicle: a\nvehicle: b\n", "line 2, column 1", "valid YAML", "duplicate key 'vehicle'", None),
    ("mavlink: [1, 2\n", "line 2, column 1", "valid YAML", "expected ',' or ']'", None),
]


@pytest.mark.parametrize("text, path, expected, got, hint", BAD, ids=[b[1] + ":" + b[3][:12] for b in BAD])
def test_bad_file_gives_one_line_naming_file_field_and_expectation(tmp_path, text, path, expected, got, hint):
    p = write(tmp_path, text)
    with pytest.raises(OnboardConfigError) as ei:
        load_config(p, environ={})
    msg = str(ei.value)
    assert ONE_LINE.match(msg), msg
    assert msg.startswith(f"{p}: {path}: expected "), msg
    assert expected in ei.value.expected, msg
    assert got in ei.value.got, msg
    if hint:
        assert msg.endswith(hint), msg
    assert ei.value.exit_code == 2 and isinstance(ei.value, ConfigError)


def test_an_empty_config_path_is_refused_not_read_as_the_current_folder():
    """``--config "$CFG"`` with CFG unset: it said ": (file): expected a file, got a directory"."""
    for empty in ("", "  "):
        with pytest.raises(
            OnboardConfigError, match=r"^\(empty path\): \(file\): expected a YAML file path, got '\s*'$"
        ):
            load_config(empty, environ={})


@pytest.mark.parametrize("value", [9e-7, 1e-4])
def test_a_time_reset_threshold_below_a_millisecond_is_refused(value):
    """Below 1 us it passed the check and then stopped the daemon's start with a traceback (counted in whole us)."""
    with pytest.raises(ConfigError, match="input.time_reset_threshold_s"):
        build_config({"input": {"time_reset_threshold_s": value}})


@pytest.mark.parametrize(
    "endpoint", ["tcp/127.0.0.1:7447,tcp/127.0.0.1:7448", "tcp/127.0.0.1:7447 ", "tcp/a:1 tcp/b:2"]
)
def test_several_zenoh_endpoints_in_one_text_are_refused_naming_the_field(endpoint):
    """A comma-separated list in one variable passed the port check and never connected, silently."""
    with pytest.raises(ConfigError, match=r"zenoh.connect\[0\]: expected one zenoh endpoint"):
        build_config({"zenoh": {"connect": [endpoint]}})


@pytest.mark.parametrize(
    "endpoint",
    ["unixsock-stream//tmp/my dir/z.sock", "tls/h:7447#root_ca_certificate=/etc/my ca.pem", "tcp/10.0.0.1:7447?a=1,2"],
)
def test_commas_and_spaces_outside_a_host_are_zenohs_to_judge(endpoint):
    """A unix socket's path and an endpoint's metadata or config may hold them (zenoh accepts such endpoints)."""
    assert build_config({"zenoh": {"connect": [endpoint]}}).zenoh.connect == (endpoint,)


def test_missing_file(tmp_path):
    with pytest.raises(OnboardConfigError, match=r"nope\.yaml: \(file\): expected an existing file, got no such file$"):
        load_config(tmp_path / "nope.yaml", environ={})


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.recursive(
        st.none() | st.booleans() | st.integers(-(10**6), 10**6) | st.floats(allow_nan=True) | st.text(max_size=8),
        lambda kids: (
            st.lists(kids, max_size=3)
            | st.dictionaries(
                st.sampled_from(
                    [
                        "vehicle",
                        "mavlink",
                        "zenoh",
                        "camera",
                        "intrinsics",
                        "mount",
                        "imaging",
                        "pose",
                        "origin",
                        "connection",
                        "fx_px",
                        "width_px",
                        "min_area_px",
                        "window_s",
                        "level",
                        "x",
                    ]
                ),
                kids,
                max_size=4,
            )
        ),
        max_leaves=12,
    )
)
def test_any_document_either_builds_or_fails_with_one_config_line(doc):
    try:
        cfg = build_config(doc, "fuzz.yaml")
    except OnboardConfigError as exc:
        assert ONE_LINE.match(str(exc)) and str(exc).startswith("fuzz.yaml: ")
    else:
        assert isinstance(cfg, OnboardConfig)


# --------------------------------------------------------------------------- overrides


def test_environment_overrides_file_and_cli_overrides_environment(tmp_path):
    p = write(tmp_path, "vehicle: fromfile\nmavlink: {connection: 'udpin:0.0.0.0:1000', attitude_rate_hz: 20}\n")
    env = {
        "IRTRACK_MAVLINK_CONNECTION": "udpin:127.0.0.1:2000",
        "IRTRACK_VEHICLE": "fromenv",
        "IRTRACK_CAMERA_INTRINSICS_FX_PX": "500",
        "IRTRACK_ZENOH_CONNECT": "[tcp/10.0.0.2:7447]",
        "IRTRACK_HEALTH_FILE": "/run/alive",
        "IRTRACK_SOMETHING_ELSE": "ignored",
        "PATH": os.environ.get("PATH", ""),
    }
    c = load_config(p, {"vehicle": ("fromcli", "--vehicle")}, environ=env)
    assert c.vehicle == "fromcli"
    assert c.mavlink.connection == "udpin:127.0.0.1:2000"
    assert c.mavlink.attitude_rate_hz == 20.0  # the file's, untouched by env
    assert c.camera.intrinsics.fx_px == 500.0 and c.camera.intrinsics.fy_px == pytest.approx(764.70588, rel=1e-6)
    assert c.zenoh.connect == ("tcp/10.0.0.2:7447",)
    assert c.output.health_file == "/run/alive"


def test_bad_environment_value_names_the_variable():
    with pytest.raises(OnboardConfigError) as ei:
        load_config(None, environ={"IRTRACK_MAVLINK_ATTITUDE_RATE_HZ": "-3"})
    assert (
        str(ei.value)
        == "env IRTRACK_MAVLINK_ATTITUDE_RATE_HZ: mavlink.attitude_rate_hz: expected a number in (0, 1000], got -3"
    )


def test_a_lever_arm_of_kilometres_is_refused_naming_the_field():
    for arm in ([1e9, 0.0, 0.0], [0.0, -1e9, 0.0], [0.0, 0.0, -50.5]):  # either way along any axis
        with pytest.raises(OnboardConfigError, match=r"camera.mount.lever_arm_frd_m: expected offsets within \+-50 m"):
            build_config({"camera": {"mount": {"lever_arm_frd_m": arm}}})
    assert (
        build_config({"camera": {"mount": {"lever_arm_frd_m": [0.3, 0.0, -0.1]}}}).camera.mount.lever_arm_frd_m[0]
        == 0.3
    )


def test_the_edges_of_the_gcs_and_input_ranges_are_accepted():
    """The other side of the refusals in BAD: MAVLink camera ids 100 and 105 (MAV_COMP_ID_CAMERA..CAMERA6), a name of
    exactly 32 bytes in 16 characters, a time reset threshold of 1 ms."""
    for cid in (100, 105):
        assert build_config({"gcs": {"component_id": cid}}).gcs.component_id == cid
    name = "ÄÖÜäöüßÄÖÜäöüßÄÖ"  # 16 characters, 32 bytes
    assert len(name.encode()) == 32 and build_config({"gcs": {"vendor_name": name}}).gcs.vendor_name == name
    assert build_config({"input": {"time_reset_threshold_s": 1e-3}}).input.time_reset_threshold_s == 1e-3


def test_a_whole_section_in_one_variable_is_refused_not_ignored():
    with pytest.raises(
        OnboardConfigError,
        match=r"^env IRTRACK_CAMERA: \(name\): expected one IRTRACK_<SECTION>_<FIELD> variable per field, got 'IRTRACK_CAMERA'$",
    ):
        env_overrides({"IRTRACK_CAMERA": "{intrinsics: 5}"})
    assert env_overrides({"IRTRACK_EXTRAS": "sim"}) == {}  # a tool's own variable: not ours


def test_unknown_variable_of_a_known_section_is_an_error_with_a_hint():
    with pytest.raises(OnboardConfigError, match=r"did you mean 'IRTRACK_MAVLINK_CONNECTION'\?$"):
        env_overrides({"IRTRACK_MAVLINK_CONECTION": "x"})


@pytest.mark.parametrize(
    "name, hint",
    [
        ("IRTRACK_MAVLNK_CONNECTION", "IRTRACK_MAVLINK_CONNECTION"),
        ("IRTRACK_VEHICLES", "IRTRACK_VEHICLE"),
        ("IRTRACK_HEALTHFILE", "IRTRACK_HEALTH_FILE"),
    ],
)
def test_a_misspelt_section_is_an_error_too(name, hint):
    with pytest.raises(OnboardConfigError, match=rf"got '{name}'; did you mean '{hint}'\?$"):
        env_overrides({name: "x"})


def test_the_tools_own_variables_are_not_taken_for_misspellings():
    tools = (
        "IRTRACK_EXTRAS",
        "IRTRACK_FUZZ_EXAMPLES",
        "IRTRACK_NUMBA_CACHE_SEED",
        "IRTRACK_PARENT_PID",
        "IRTRACK_WRITE_GOLDEN",
    )
    assert env_overrides(dict.fromkeys(tools, "1")) == {}


def test_the_health_file_alias_must_agree_with_its_field_and_not_be_empty():
    both = {"IRTRACK_HEALTH_FILE": "/tmp/a", "IRTRACK_OUTPUT_HEALTH_FILE": "/tmp/b"}
    with pytest.raises(OnboardConfigError, match="output.health_file: expected the value of IRTRACK_HEALTH_FILE"):
        load_config(None, environ=both)
    same = load_config(None, environ={**both, "IRTRACK_OUTPUT_HEALTH_FILE": "/tmp/a"})
    assert same.output.health_file == "/tmp/a"
    with pytest.raises(OnboardConfigError, match="IRTRACK_HEALTH_FILE: output.health_file: expected a file path"):
        load_config(None, environ={"IRTRACK_HEALTH_FILE": " "})
    assert load_config(None, environ={"IRTRACK_OUTPUT_HEALTH_FILE": ""}).output.health_file is None  # null: none


@pytest.mark.parametrize(("value", "shown"), [("/tmp/other", "'/tmp/other'"), (None, "null")])
def test_a_command_line_health_file_must_agree_with_the_probes_variable(value, shown):
    # the container's HEALTHCHECK reads IRTRACK_HEALTH_FILE: a daemon touching another file (or none) is called dead
    env = {"IRTRACK_HEALTH_FILE": "/tmp/irtrack-alive"}
    override = {"output.health_file": (value, "--set")}
    with pytest.raises(OnboardConfigError) as err:
        load_config(None, overrides=override, environ=env)
    line = str(err.value)
    assert line.startswith("--set: output.health_file: expected the value of IRTRACK_HEALTH_FILE")
    assert "'/tmp/irtrack-alive'" in line and line.endswith(f"got {shown}") and "\n" not in line
    assert err.value.exit_code == 2
    same = {"output.health_file": ("/tmp/irtrack-alive", "--set")}
    assert load_config(None, overrides=same, environ=env).output.health_file == "/tmp/irtrack-alive"
    # without the variable the probe's path is not known here: the option stands
    assert load_config(None, overrides=override, environ={}).output.health_file == value


def test_a_cross_field_error_names_the_override_beside_the_file(tmp_path):
    # the file's heartbeat_timeout_s is refused because of the environment's interval: both are named
    p = write(tmp_path, "mavlink: {heartbeat_timeout_s: 5}")
    with pytest.raises(OnboardConfigError) as ei:
        load_config(p, environ={"IRTRACK_MAVLINK_HEARTBEAT_INTERVAL_S": "10"})
    assert str(ei.value).startswith(
        f"{p} with env IRTRACK_MAVLINK_HEARTBEAT_INTERVAL_S: mavlink.heartbeat_timeout_s: expected a timeout >"
    )
    # an override of another section is not named
    q = write(tmp_path, "mavlink: {heartbeat_interval_s: 9, heartbeat_timeout_s: 5}", "d.yaml")
    with pytest.raises(OnboardConfigError) as ei:
        load_config(q, {"vehicle": ("uav9", "--vehicle")}, environ={})
    assert str(ei.value).startswith(f"{q}: mavlink.heartbeat_timeout_s: expected a timeout >")


@pytest.mark.parametrize("port", ["7447\u00b2", "\u0667\u0664\u0664\u0667"])
def test_a_zenoh_port_of_other_digits_than_ascii_is_refused_naming_the_field(port):
    """A superscript two passes str.isdigit and made int() raise ValueError (a traceback, not the one line); Arabic-
    Indic digits were read as a port."""
    with pytest.raises(OnboardConfigError) as ei:
        load_config(None, {"zenoh.listen": ([f"tcp/127.0.0.1:{port}"], "--zenoh-listen")}, environ={})
    assert str(ei.value).startswith("--zenoh-listen: zenoh.listen[0]:")


def test_cli_error_names_the_option():
    with pytest.raises(OnboardConfigError) as ei:
        load_config(None, {"zenoh.listen": (["nope"], "--zenoh-listen")}, environ={})
    assert str(ei.value).startswith("--zenoh-listen: zenoh.listen[0]: expected a zenoh endpoint")


def test_set_option_parses_yaml_values_and_refuses_unknown_paths():
    assert parse_set_option("estimator.window_s=8") == ("estimator.window_s", 8)
    assert parse_set_option("zenoh.connect=[tcp/1.2.3.4:7447]") == ("zenoh.connect", ["tcp/1.2.3.4:7447"])
    assert parse_set_option("pose.origin=null") == ("pose.origin", None)
    with pytest.raises(OnboardConfigError, match="did you mean 'estimator.window_s'"):
        parse_set_option("estimator.windw_s=3")
    with pytest.raises(OnboardConfigError, match="FIELD.PATH=VALUE"):
        parse_set_option("estimator.window_s")


@pytest.mark.subprocess
@pytest.mark.timeout(60)
def test_daemon_exits_2_with_one_line_on_a_bad_config(tmp_path):
    p = write(tmp_path, "mavlink:\n  attitude_rate_hz: fast\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("IRTRACK_")}
    proc = subprocess.run(
        [sys.executable, "-m", "onboard", "--config", p], capture_output=True, text=True, timeout=60, env=env, cwd=REPO
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert lines == [f"{p}: mavlink.attitude_rate_hz: expected a number in (0, 1000], got 'fast'"]
    assert proc.stdout == ""


@pytest.mark.parametrize(
    "text, where, expected",
    [
        ("vehicle: " + "[" * 5000 + "]" * 5000 + "\n", "line 1, column 73", "YAML nested at most 64 levels deep"),
        (
            "vehicle:\n  - &a0 [x, x, x]\n"
            + "".join(f"  - &a{i} [*a{i - 1}, *a{i - 1}, *a{i - 1}]\n" for i in range(1, 20)),
            "line 3, column 10",
            "YAML without aliases (write each value out)",
        ),
    ],
    ids=["nested 5000 deep", "alias bomb"],
)
def test_check_refuses_a_hostile_yaml_file_in_one_line(tmp_path, capsys, text, where, expected):
    # refused while composing: neither the recursion of 5000 levels nor the 3^19 strings of the aliases is made
    from onboard.app.main import main

    p = write(tmp_path, text)
    assert main(["--check", "--config", p]) == 2
    err = capsys.readouterr().err.strip()
    assert ONE_LINE.match(err) and err.startswith(f"{p}: {where}: expected {expected}, got "), err


def test_a_peer_that_only_connects_and_dials_no_gossiped_peer_is_warned_it_may_meet_none():
    """Connect endpoints, no listener, gossip dialing off, no zenoh file: a peer the router introduces can neither
    reach the daemon nor be dialed by it (a zenoh 1.10 router does not relay between peers)."""
    from onboard.app.components import zenoh_unreachable_hint

    lone = build_config({"zenoh": {"connect": ["tcp/10.0.0.2:7447"]}})
    hint = zenoh_unreachable_hint(lone)
    assert hint is not None and "tcp/10.0.0.2:7447" in hint and "zenoh.listen" in hint
    for zenoh in (
        {"connect": ["tcp/10.0.0.2:7447"], "listen": ["tcp/127.0.0.1:0"]},
        {"connect": ["tcp/10.0.0.2:7447"], "gossip_autoconnect": True},
        {"connect": []},
    ):
        assert zenoh_unreachable_hint(build_config({"zenoh": zenoh})) is None


def test_where_zenoh_listens_names_a_config_files_endpoints_not_none(tmp_path):
    """The no_frames warning said 'connect none (--zenoh-connect); listen none' for a daemon whose zenoh file connects
    over TLS (a walkthrough of deploy/README's ACL set-up): with a file, its endpoints are the file's, plus any given."""
    from onboard.app.components import zenoh_where

    f = tmp_path / "client.json5"
    f.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7447"] } }\n')
    where = zenoh_where(build_config({"zenoh": {"config_file": str(f), "listen": ["tcp/127.0.0.1:0"]}}))
    assert f"connect as {f} sets it" in where and f"listen as {f} sets it and tcp/127.0.0.1:0" in where
    assert "none" not in where
    assert "connect none (--zenoh-connect)" in zenoh_where(build_config({}))


def test_no_writable_numba_cache_is_one_line_and_exit_2(monkeypatch, capsys):
    """numba refuses to cache a kernel as its module is imported when no folder is writable (the image's read-only
    tree with NUMBA_CACHE_DIR unset): a 30-line traceback even for --check; now one line naming NUMBA_CACHE_DIR."""
    import onboard.app.main as daemon_main

    def no_locator(*_a, **_k):
        raise RuntimeError("cannot cache function 'linearise_measurements': no locator available for file 'k.py'")

    monkeypatch.setattr(daemon_main, "_serve", no_locator)
    assert daemon_main.main(["--check"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("numba: no writable cache for the compiled kernels (cannot cache")
    assert "set NUMBA_CACHE_DIR to a folder this user may write" in err[0]

    def other(*_a, **_k):
        raise RuntimeError("something else")

    monkeypatch.setattr(daemon_main, "_serve", other)
    with pytest.raises(RuntimeError, match="something else"):  # any other error is not dressed up as this one
        daemon_main.main(["--check"])


@pytest.mark.parametrize("section", ["follow", "guidance"])
def test_follow_or_guidance_on_without_the_estimator_is_refused(section):
    """Both act on the 3-D track: with the estimator off they were accepted, on and never acting."""
    with pytest.raises(ConfigError, match=rf"^\(defaults\): {section}.enabled: expected false while estimator.enabled"):
        build_config({section: {"enabled": True}, "estimator": {"enabled": False}})
    assert getattr(build_config({section: {"enabled": True}}), section).enabled


def test_follow_settings_without_enabled_are_refused_not_silently_off():
    with pytest.raises(ConfigError, match=r"^\(defaults\): follow.enabled: expected true .*sets rate_hz"):
        build_config({"follow": {"rate_hz": 2.0}})
    assert not build_config({"follow": {"enabled": False, "rate_hz": 2.0}}).follow.enabled


@pytest.mark.parametrize("blocker", ["file", "folder"])
def test_the_start_names_a_file_where_the_recording_folder_goes_or_a_folder_at_its_path(tmp_path, blocker):
    """A helper's storage audit: --record under a file, or at a folder, exited 2 with 'cannot write ...: File
    exists', which named neither; --check said 'is not a folder' / 'is a folder'."""
    from onboard.app.observers import RecorderTap
    from onboard.core.errors import InputError
    from onboard.io.record import FlightRecorder, RecordConfig

    if blocker == "file":
        (tmp_path / "sd").write_text("x")
        path, why = tmp_path / "sd" / "f.mcap", f"{tmp_path / 'sd'} is not a folder"
    else:
        (tmp_path / "f.mcap").mkdir()
        path, why = tmp_path / "f.mcap", f"{tmp_path / 'f.mcap'} is a folder"
    tap = RecorderTap(FlightRecorder(RecordConfig(path=str(path))), str(path))
    with pytest.raises(InputError) as err:
        tap.start()
    assert str(err.value) == f"record.path: cannot write {path}: {why}"


def test_check_refuses_what_the_start_would_a_recording_folder_it_cannot_write_or_a_live_view_host_unknown(
    tmp_path, capsys
):
    """--check said ok, then the start exited 2: a recording under a file, a live view host that does not resolve."""
    from onboard.app.main import main

    blocker = tmp_path / "not-a-folder"
    blocker.write_text("x")
    assert main(["--check", "--record", str(blocker / "sub" / "f.mcap")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"(defaults): record.path: cannot write {blocker} is not a folder", err
    assert main(["--check", "--live-view", "8765", "--set", "live_view.host=nonexistent.invalid"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("(defaults): live_view.host: cannot resolve 'nonexistent.invalid': "), err
    # a recording in a folder still to be made is fine (the recorder makes it), and nothing is left behind
    assert main(["--check", "--record", str(tmp_path / "new" / "f.mcap")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["not-a-folder"]


@pytest.mark.parametrize(
    ("intrinsics", "field", "expected"),
    [
        ({"fx_px": 1e-9}, "fx_px", "a focal length giving a field of view under 170 deg (at least 28 px for 640 px)"),
        ({"fy_px": 10.0}, "fy_px", "a focal length giving a field of view under 170 deg (at least 22.4 px for 512 px)"),
        ({"fy_px": 300.0}, "fy_px", "within a factor 2 of fx_px"),
    ],
)
def test_intrinsics_no_camera_has_are_refused_naming_the_field(intrinsics, field, expected):
    """A focal length in metres (fx 1e-9: a 180 deg pinhole) or pixels four times taller than wide were accepted."""
    with pytest.raises(ConfigError, match=rf"camera\.intrinsics\.{field}: expected {re.escape(expected)}"):
        build_config({"camera": {"intrinsics": intrinsics}})
    assert build_config({"camera": {"intrinsics": {"fx_px": 30.0, "fy_px": 30.0}}}).camera.intrinsics.fx_px == 30.0


def test_the_daemon_raises_its_open_files_limit_to_the_hard_one():
    """A burst of live-view clients using every descriptor (1024 by default) stopped its server for good."""
    import resource

    from onboard.app.main import raise_open_files_limit

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    try:
        low = min(soft, 256) if hard == resource.RLIM_INFINITY else min(256, hard)
        resource.setrlimit(resource.RLIMIT_NOFILE, (low, hard))
        got = raise_open_files_limit()
        assert got == (low if hard == resource.RLIM_INFINITY else hard)
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
