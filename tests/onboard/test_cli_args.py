"""The configuration options the daemon and its replay share (onboard.app.cli_args)."""

from __future__ import annotations

import pytest

from onboard.app.cli_args import (
    OneLineParser,
    add_config_option,
    add_live_view_option,
    add_set_option,
    config_overrides,
)
from onboard.app.config import OnboardConfigError


def _parser() -> OneLineParser:
    p = OneLineParser(prog="t")
    add_config_option(p, "config")
    add_set_option(p, "set")
    add_live_view_option(p, "live view")
    return p


def test_the_options_parse_to_their_names_and_types():
    args = _parser().parse_args(
        ["--config", "a.yaml", "--set", "vehicle=uav2", "--set", "x.y=1", "--live-view", "8765"]
    )
    assert (args.config, args.set, args.live_view) == ("a.yaml", ["vehicle=uav2", "x.y=1"], 8765)
    args = _parser().parse_args([])
    assert (args.config, args.set, args.live_view) == (None, [], None)


@pytest.mark.parametrize("text", ["x", "0", "99999", "-1"])
def test_a_live_view_port_that_is_not_a_port_is_a_usage_error(capsys, text):
    with pytest.raises(SystemExit) as exc:
        _parser().parse_args(["--live-view", text])
    assert exc.value.code == 2
    assert capsys.readouterr().err.startswith(f"t: argument --live-view: expected a port 1..65535, got '{text}'")


def test_overrides_parse_each_set_and_an_option_wins_over_a_set_of_its_field():
    out = config_overrides(
        ["estimator.window_s=8", "mavlink.connection=udpin:127.0.0.1:2", "estimator.window_s=9"],
        [("mavlink.connection", "udpin:127.0.0.1:1", "--mavlink"), ("vehicle", None, "--vehicle")],
    )
    assert out == {
        "estimator.window_s": (9, "--set"),  # the last --set of a field stands
        "mavlink.connection": ("udpin:127.0.0.1:1", "--mavlink"),
    }  # and an option not given (None) overrides nothing


def test_a_set_of_a_field_that_does_not_exist_names_it():
    with pytest.raises(OnboardConfigError, match="estimator.windw_s"):
        config_overrides(["estimator.windw_s=3"])
