"""``groundsim campaign``: what is refused before any run (duplicate scenarios, unwritable outputs, --workers 0)
and how a geometry error reads (one line, the spec and the field named once)."""

from __future__ import annotations

import pytest

from groundsim.app.cli import main as cli_main
from groundsim.evaluation.campaign import LOG_NAME, check_outputs, run_campaign
from groundsim.evaluation.campaign_report import TABLE_NAME
from groundsim.evaluation.campaign_spec import spec_from_dict
from groundsim.world.scenario import reference_scenario_paths
from onboard.core.errors import ConfigError


def _spec(tmp_path, **over):
    d = {"name": "t", "scenarios": ["P1"], "noise": ["RTK"], "algorithms": ["paper"], "seeds": 1, "duration_s": 1.0}
    d.update(over)
    return spec_from_dict(d, source=tmp_path / "spec.yaml", spec_dir=tmp_path)


def _spec_file(tmp_path, body="scenarios: [P1]\nnoise: [RTK]\nalgorithms: [paper]\nduration_s: 1.0\n"):
    p = tmp_path / "spec.yaml"
    p.write_text(body)
    return p


@pytest.mark.parametrize("second", ["p1", "P1.yaml"])
def test_the_same_scenario_file_twice_is_refused_naming_the_entry(tmp_path, second):
    if second == "P1.yaml":
        second = str(reference_scenario_paths()["P1"])
    with pytest.raises(ConfigError, match=r"spec\.yaml: scenarios\[1\]: expected .*scenarios\[0\] is the same file"):
        _spec(tmp_path, scenarios=["P1", second])


def test_two_files_of_the_same_scenario_name_are_refused(tmp_path):
    copy = tmp_path / "copy.yaml"
    copy.write_text(reference_scenario_paths()["P1"].read_text())
    with pytest.raises(ConfigError, match=r"scenarios\[1\]: expected a scenario whose name is not scenarios\[0\]'s"):
        _spec(tmp_path, scenarios=["P1", "copy.yaml"])


def test_a_geometry_error_names_the_spec_and_the_field_once(tmp_path):
    with pytest.raises(ConfigError) as info:
        _spec(tmp_path, geometry={"range_scale": [0.01]})
    msg = str(info.value)
    assert msg.count("spec.yaml") == 1 and msg.count("geometry:") == 1, msg


@pytest.mark.parametrize("name", [LOG_NAME, TABLE_NAME])
def test_an_output_that_is_a_directory_is_refused_before_any_run(tmp_path, name):
    (tmp_path / "out" / name).mkdir(parents=True)
    with pytest.raises(ConfigError, match=rf"{name}: cannot write"):
        check_outputs(tmp_path / "out")
    with pytest.raises(ConfigError, match=rf"{name}: cannot write"):
        run_campaign(_spec(tmp_path), tmp_path / "out", workers=1, progress=False)
    assert not (tmp_path / "out" / TABLE_NAME).is_file()


def test_cli_output_directory_is_one_line_exit_2(tmp_path, capsys):
    out = tmp_path / "out"
    (out / LOG_NAME).mkdir(parents=True)
    assert cli_main(["campaign", str(_spec_file(tmp_path)), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"{LOG_NAME}: cannot write" in err


@pytest.mark.parametrize("workers", ["0", "-1"])
def test_cli_workers_below_one_is_refused(tmp_path, capsys, workers):
    out = tmp_path / "out"
    assert cli_main(["campaign", str(_spec_file(tmp_path)), "--out", str(out), "--workers", workers]) == 2
    assert "--workers: expected an integer >= 1" in capsys.readouterr().err
    assert not out.exists()
