"""``groundsim run``: options refused in one line with exit 2 (an unwritable --record, a GNSS dropout after the
end, a bad --vehicle), in this process, one simulated second at most."""

from __future__ import annotations

import pytest

from groundsim.app.cli import main as cli_main
from groundsim.world.nav_errors import GnssDropout
from onboard.core.errors import ConfigError

RUN = ["run", "--scenario", "P1", "--rate", "max", "--duration", "1", "--no-render"]


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    return err[-1]


@pytest.mark.parametrize("where", ["under_a_file", "a_directory", "in_proc"])
def test_an_unwritable_record_path_is_one_line_exit_2(tmp_path, capsys, where):
    if where == "under_a_file":
        (tmp_path / "afile").write_text("")
        path = tmp_path / "afile" / "r.mcap"
    elif where == "a_directory":
        path = tmp_path / "d.mcap"
        path.mkdir()
    else:
        path = "/proc/r.mcap"
    assert cli_main([*RUN, "--record", str(path)]) == 2
    line = _one_line_error(capsys)
    assert line.startswith(f"groundsim run: error: --record {path}: cannot write: "), line


@pytest.mark.parametrize("option, name", [("--truth", "t.csv"), ("--record", "r.mcap")])
def test_truth_and_record_make_missing_folders_and_name_a_file_in_the_way_alike(tmp_path, capsys, option, name):
    """Both outputs make missing folders, as the other commands' --out and the daemon's --record; a file where a
    folder would be made is refused before the run in the same words for both."""
    made = tmp_path / "new" / "deeper" / name
    assert cli_main([*RUN, option, str(made)]) == 0
    assert made.is_file() and made.stat().st_size > 0
    (tmp_path / "afile").write_text("")
    for path in (tmp_path / "afile" / name, tmp_path / "afile" / "sub" / name):
        assert cli_main([*RUN, option, str(path)]) == 2
        assert _one_line_error(capsys) == (
            f"groundsim run: error: {option} {path}: cannot write: {tmp_path / 'afile'} is a file, not a folder"
        )
    assert (tmp_path / "afile").read_text() == ""


def test_a_gnss_dropout_at_or_after_the_end_is_refused(capsys):
    assert cli_main([*RUN, "--gnss-dropout=5:1"]) == 2
    assert "error: --gnss-dropout: expected a start before the run's end (1 s), got 5 s" in _one_line_error(capsys)
    with pytest.raises(ConfigError, match="--gnss-dropout"):
        GnssDropout(1.0, 0.5).check_within(1.0)
    GnssDropout(0.999, 5.0).check_within(1.0)  # starts inside the run: running past the end is fine


def test_a_bad_vehicle_name_names_the_option(capsys):
    assert cli_main([*RUN, "--vehicle", "a/b"]) == 2
    assert "error: --vehicle: vehicle name must be" in _one_line_error(capsys)


def test_outputs_on_the_scenario_file_or_on_each_other_are_refused(tmp_path, capsys):
    from groundsim.world.scenario import scenarios_dir

    scenario = tmp_path / "mine.yaml"
    scenario.write_bytes((scenarios_dir() / "P1.yaml").read_bytes())
    run = ["run", "--scenario", str(scenario), "--rate", "max", "--duration", "1", "--no-render"]
    assert cli_main([*run, "--truth", str(scenario)]) == 2
    assert f"--truth {scenario}: names the input --scenario" in _one_line_error(capsys)
    same = tmp_path / "x.mcap"
    assert cli_main([*run, "--truth", str(same), "--record", str(same)]) == 2
    assert f"--record {same}: names the same file as --truth" in _one_line_error(capsys)
    assert scenario.read_bytes() == (scenarios_dir() / "P1.yaml").read_bytes() and not same.exists()


@pytest.mark.parametrize("kind", ["udpout", "tcp"])
def test_a_mavlink_host_that_does_not_resolve_is_one_line_exit_2(capsys, kind):
    """udpout to a name no resolver knows (.invalid never resolves, RFC 6761): the run had gone on, exit 0, every
    message lost without a word (only the listening kinds' hosts were looked up)."""
    argv = ["run", "--rate", "max", "--duration", "0.2", "--no-render", "--mavlink", f"{kind}:nohost.invalid:1"]
    assert cli_main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(
        f"groundsim run: error: mavlink: cannot open '{kind}:nohost.invalid:1': cannot resolve 'nohost.invalid' ("
    ), err
