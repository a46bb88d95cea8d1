"""onboard.core.schema, the one config system: every field of the onboard config refuses a bad value with
the one-line error naming file and field path; YAML 1.2 floats; round trips of onboard config and noise cases."""

from __future__ import annotations

import dataclasses
import re
from typing import Annotated, Literal

import pydantic
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from groundsim.world.scenario import ScenarioError, load_noise_cases, noise_cases_from_dict
from onboard.app.config import OnboardConfig, OnboardConfigError, _leaf_paths, config_to_dict, load_config
from onboard.core.schema import (
    NOT_A_KEY,
    Integer,
    Number,
    Numbers,
    SchemaError,
    Text,
    build,
    config_dataclass,
    file_keys,
    parse_yaml_text,
)

ONE_LINE = re.compile(r"^[^\n]+$")
NOT_ANY_FIELD = {"x": 1}  # a mapping: no leaf of the onboard config takes one (estimator.sliding aside)
LEAVES = [p for p in _leaf_paths() if p != "estimator.sliding"]


def _nest(path: str, value) -> dict:
    out: dict = {}
    node = out
    parts = path.split(".")
    for part in parts[:-1]:
        node[part] = {}
        node = node[part]
    node[parts[-1]] = value
    return out


@pytest.mark.parametrize("path", LEAVES)
def test_every_field_refuses_a_bad_value_naming_file_and_field(tmp_path, path):
    p = tmp_path / "c.yaml"
    bad = [1, 2] if path == "pose.origin" else NOT_ANY_FIELD  # the one section that may be null
    p.write_text(yaml.safe_dump(_nest(path, bad)), encoding="utf-8")
    with pytest.raises(OnboardConfigError) as ei:
        load_config(p, environ={})
    msg = str(ei.value)
    assert ONE_LINE.match(msg) and msg.startswith(f"{p}: {path}: expected "), msg
    assert msg.endswith(f"got {bad!r}") and ei.value.exit_code == 2, msg


def test_exponent_without_a_dot_is_a_number_in_every_file(tmp_path):
    """YAML 1.1 reads 3e-1 as a string; the one loader reads YAML 1.2 floats (the scenario loader always did)."""
    p = tmp_path / "c.yaml"
    p.write_text("estimator: {pixel_sigma_px: 3e-1, window_s: 2E1}\n", encoding="utf-8")
    e = load_config(p, environ={}).estimator
    assert (e.pixel_sigma_px, e.window_s) == (0.3, 20.0)
    q = tmp_path / "n.yaml"
    q.write_text("a: {pixel_sigma_px: 3e-1, attitude_white_sigma_deg: 5e-2}\n", encoding="utf-8")
    assert load_noise_cases(q)["a"].pixel_sigma_px == 0.3


_SECTION_VALUES = {
    "estimator.pixel_sigma_px": st.floats(1e-3, 100.0),
    "estimator.window_s": st.floats(1e-3, 600.0),
    "pose.wait_ms": st.floats(0.0, 1000.0),
    "mavlink.autopilot_sysid": st.none() | st.integers(1, 255),
    # with the default focal length (765 px) a width past ~17480 px sees 170 deg or more: refused, as no camera has it
    "camera.intrinsics.width_px": st.integers(16, 17000),
    "camera.mount.lever_arm_frd_m": st.lists(st.floats(-10.0, 10.0), min_size=3, max_size=3),
    "zenoh.connect": st.lists(st.sampled_from(["tcp/10.0.0.2:7447", "udp/127.0.0.1:1"]), max_size=2),
    "logging.level": st.sampled_from(["DEBUG", "INFO", "ERROR"]),
    "imaging.kcf_detect_threshold": st.floats(0.0, 1.0),
}


@pytest.mark.parametrize("word", ["yes", "no", "on", "off", "Yes", "OFF"])
def test_only_true_and_false_are_booleans_in_every_file(tmp_path, word):
    # YAML 1.2: a YAML 1.1 boolean word is a string, so a flag refuses it and a name keeps it
    p = tmp_path / "c.yaml"
    p.write_text(f"estimator: {{enabled: {word}}}\n")
    with pytest.raises(OnboardConfigError, match=f"estimator.enabled: expected true or false, got '{word}'$"):
        load_config(p, environ={})
    p.write_text(f"vehicle: {word}\n")
    assert load_config(p, environ={}).vehicle == word
    assert yaml.safe_load("on") is True  # PyYAML's own loader is left as it is


@pytest.mark.parametrize(
    "text, path",
    [
        ("010", "camera.intrinsics.width_px"),  # octal 8 to YAML 1.1, 10 to YAML 1.2
        ("0b11", "camera.intrinsics.width_px"),
        ("1:30", "estimator.window_s"),  # base 60: 90 to YAML 1.1
        ("1:30.5", "estimator.window_s"),
        ("00", "camera.intrinsics.width_px"),
    ],
)
def test_yaml_1_1_number_forms_are_strings_refused_by_their_field(tmp_path, text, path):
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(_nest(path, "X")).replace("X", text))
    with pytest.raises(OnboardConfigError, match=f"^{p}: {re.escape(path)}: expected .*, got '{re.escape(text)}'$"):
        load_config(p, environ={})


@pytest.mark.parametrize(
    "text, value",
    [
        ("0", 0), ("-5", -5), ("+3", 3), ("1_000", 1000), ("0x1F", 31), ("-0", 0),
        ("0.5", 0.5), (".5", 0.5), ("-.5", -0.5), ("1.", 1.0), ("1e-3", 1e-3), ("3e-1", 0.3), ("1.5E+3", 1500.0),
        ("010.5", 10.5), ("1.0e-05", 1e-05),
    ],
)  # fmt: skip
def test_decimal_and_hexadecimal_numbers_read_as_numbers(text, value):
    got = parse_yaml_text(text)
    assert got == value and type(got) is type(value)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    st.dictionaries(st.sampled_from(sorted(_SECTION_VALUES)), st.just(None), max_size=4).flatmap(
        lambda keys: st.fixed_dictionaries({k: _SECTION_VALUES[k] for k in keys})
    )
)
def test_valid_values_round_trip_through_yaml(tmp_path, values):
    raw: dict = {}
    for path, v in values.items():
        node = raw
        for part in path.split(".")[:-1]:
            node = node.setdefault(part, {})
        node[path.rsplit(".", 1)[-1]] = v
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(raw), encoding="utf-8")
    cfg = load_config(p, environ={})
    q = tmp_path / "d.yaml"
    q.write_text(yaml.safe_dump(config_to_dict(cfg)), encoding="utf-8")
    assert load_config(q, environ={}) == cfg


def test_noise_cases_round_trip():
    cases = load_noise_cases()
    back = noise_cases_from_dict(
        {
            n: {
                "description": c.description,
                "pixel_sigma_px": c.pixel_sigma_px,
                "attitude_white_sigma_deg": c.attitude_white_sigma_rad * 180 / 3.141592653589793,
                "attitude_bias_sigma_deg": c.attitude_bias_sigma_rad * 180 / 3.141592653589793,
                "camera_position_white_sigma_m": c.camera_position_white_sigma_m,
                "camera_position_offset_m": c.camera_position_offset_m,
                "camera_position_drift_mps": c.camera_position_drift_mps,
            }
            for n, c in cases.items()
        }
    )
    for n, c in cases.items():
        assert back[n].pixel_sigma_px == c.pixel_sigma_px
        assert back[n].attitude_bias_sigma_rad == pytest.approx(c.attitude_bias_sigma_rad, rel=1e-12)


@pytest.mark.parametrize("field", ["pixel_sigma_px", "attitude_white_sigma_deg", "camera_position_drift_mps"])
@pytest.mark.parametrize("bad", [-1.0, True, "x", None])
def test_every_noise_case_field_refuses_a_bad_value(field, bad):
    doc = {"c": {"pixel_sigma_px": 0.3, field: bad}}
    with pytest.raises(ScenarioError) as ei:
        noise_cases_from_dict(doc, "n.yaml")
    assert str(ei.value).startswith(f"n.yaml: c.{field}: expected a number >= 0, got "), str(ei.value)


def test_default_config_is_the_model_default():
    assert OnboardConfig() == load_config(None, environ={})


# --------------------------------------------------------------------------- the field types


@config_dataclass
class _Fields:
    rate_hz: Annotated[float, Number(0.0, 100.0, lo_open=True)] = 1.0
    port: Annotated[int | None, Integer(1, 65535)] = None
    mode: Annotated[Literal["auto", "operator"], Text()] = "auto"
    xyz: Annotated[tuple[float, float, float], Numbers(3)] = (0.0, 0.0, 0.0)
    label: str = dataclasses.field(default="", metadata=NOT_A_KEY)


@pytest.mark.parametrize(
    "raw, text",
    [
        ({"rate_hz": 0}, "rate_hz: expected a number in (0, 100], got 0"),
        ({"port": 0}, "port: expected an integer in [1, 65535] or null, got 0"),  # `| None`: "or null"
        ({"mode": "Auto"}, "mode: expected one of auto, operator, got 'Auto'; did you mean 'auto'?"),  # the Literal
        ({"xyz": [1, 2]}, "xyz: expected a list of 3 finite numbers, got [1, 2]"),
        ({"label": "x"}, "label: expected a key of the document (rate_hz, port, mode, xyz), got unknown key 'label'"),
    ],
)
def test_the_annotated_form_keeps_one_text_per_field(raw, text):
    with pytest.raises(SchemaError) as ei:
        build(_Fields, raw)
    assert str(ei.value) == f"<_Fields>: {text}"


def test_a_field_the_program_sets_is_given_not_read():
    f = build(_Fields, {"port": 8080, "xyz": [1, 2, 3]}, given={"label": "case"})
    assert (f.port, f.xyz, f.label) == (8080, (1.0, 2.0, 3.0), "case")
    assert file_keys(_Fields) == ("rate_hz", "port", "mode", "xyz")


@pytest.mark.parametrize(
    "annotation",
    [
        Annotated[int, Number(0.0, 1.0)],  # a number field typed int
        Annotated[float, Integer(0, 1)],
        Annotated[tuple[float, float], Numbers(3)],  # the wrong length
    ],
)
def test_a_field_type_on_the_wrong_python_type_is_refused(annotation):
    with pytest.raises(TypeError, match="annotates"):
        pydantic.TypeAdapter(annotation)
