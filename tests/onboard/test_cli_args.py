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


@pytest.mark.parametrize("wrapped", [False, True])
def test_a_reader_that_leaves_ends_the_command_quietly_with_141(wrapped):
    """``groundsim campaign ... | head -1`` ended with a BrokenPipeError traceback: Python ignores SIGPIPE, so the
    next print raised wherever it was (and the exit's flush said so again)."""
    import subprocess
    import sys

    main = "lambda: [print('line', i, flush=True) for i in range(200_000)] and 0"
    code = f"import sys; from onboard.app.cli_args import exit_code_of; sys.exit(exit_code_of({main}))"
    if not wrapped:
        code = f"import sys; sys.exit(({main})())"
    writer = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert writer.stdout is not None and writer.stdout.readline() == b"line 0\n"
    writer.stdout.close()  # the reader leaves, as head does after its first line
    _out, err = writer.communicate(timeout=60)
    if wrapped:
        assert (writer.returncode, err) == (141, b"")
    else:  # what an entry point without it does
        assert writer.returncode == 1 and b"BrokenPipeError" in err
