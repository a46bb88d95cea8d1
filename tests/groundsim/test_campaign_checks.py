"""``groundsim campaign``: what is refused before any run (duplicate scenarios, unwritable outputs, --workers 0),
how a geometry error reads (one line, the spec and the field named once), and a damaged run log on resume (its
bad lines skipped, named in one warning, their runs redone)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from groundsim.app.cli import main as cli_main
from groundsim.evaluation.campaign import (
    LOG_NAME,
    append_rows,
    check_outputs,
    read_log,
    reusable_rows,
    run_campaign,
)
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


def test_a_plug_in_that_is_not_a_factory_names_the_spec_and_the_entry(tmp_path):
    with pytest.raises(ConfigError) as info:
        _spec(tmp_path, algorithms=["paper", "os:path"])
    assert str(info.value).startswith(f"{tmp_path / 'spec.yaml'}: algorithms[1]: plug-in 'os:path': expected a class")


def test_a_scenario_file_not_found_says_where_it_was_looked_for(tmp_path):
    """'specs/my.yaml' in a spec inside specs/ is specs/specs/my.yaml: the error said only 'expected a shipped scenario
    ... or a scenario file', not where it had looked (a walkthrough of docs/campaigns.md), as onboard_config's does."""
    with pytest.raises(ConfigError) as info:
        _spec(tmp_path, scenarios=["specs/my.yaml"])
    text = str(info.value)
    assert f"no file {tmp_path / 'specs' / 'my.yaml'}" in text and "relative to the spec's folder" in text


def test_a_fleet_scenario_is_refused_naming_its_entry(tmp_path):
    """A campaign runs one observer per case: F1 had run, scored on its first observer alone, without a word."""
    with pytest.raises(ConfigError) as info:
        _spec(tmp_path, scenarios=["P1", "F1"])
    text = str(info.value)
    assert text.startswith(f"{tmp_path / 'spec.yaml'}: scenarios[1]: expected a scenario of one observer")
    assert "F1" in text and "\n" not in text


def test_a_seed_beyond_the_tables_integers_is_refused_naming_it(tmp_path):
    """The table's seed column is a 64-bit integer: a larger seed ran every run, then failed writing runs.parquet
    (OverflowError), on every run of the same command too."""
    from groundsim.evaluation.campaign_spec import load_spec

    spec = _spec_file(
        tmp_path, "scenarios: [P1]\nnoise: [RTK]\nalgorithms: [paper]\nseeds: [1, 99999999999999999999999]\n"
    )
    with pytest.raises(ConfigError) as info:
        load_spec(spec)
    assert str(info.value).startswith(f"{spec}: seeds[1]: expected an integer") and "\n" not in str(info.value)
    assert _spec(tmp_path, seeds=[2**63 - 1]).seeds == (2**63 - 1,)


def test_relative_paths_are_the_specs_neighbours_wherever_the_command_runs(tmp_path, monkeypatch):
    """A relative scenario file or onboard_config is looked up beside the spec (docs/campaigns.md), not in the current
    directory first: a file of the same name there was used instead, silently."""
    from groundsim.evaluation.campaign_spec import load_spec

    p1 = reference_scenario_paths()["P1"].read_text()
    spec_dir, cwd = tmp_path / "specs", tmp_path / "cwd"
    for d in (spec_dir / "sc", cwd / "sc"):
        d.mkdir(parents=True)
    (spec_dir / "sc" / "mine.yaml").write_text(p1)
    (spec_dir / "onboard.yaml").write_text("vehicle: beside\n")
    (cwd / "sc" / "mine.yaml").write_text(p1.replace("name: P1", "name: WRONG", 1))
    (cwd / "onboard.yaml").write_text("vehicle: wrong\n")
    spec = spec_dir / "spec.yaml"
    spec.write_text("scenarios: [sc/mine.yaml, P2]\nnoise: [RTK]\nalgorithms: [paper]\nonboard_config: onboard.yaml\n")
    monkeypatch.chdir(cwd)
    s = load_spec(Path("..") / "specs" / "spec.yaml")
    assert s.scenario_paths == ((spec_dir / "sc" / "mine.yaml").resolve(), reference_scenario_paths()["P2"])
    assert s.onboard_config == (spec_dir / "onboard.yaml").resolve()
    (spec_dir / "onboard.yaml").unlink()
    with pytest.raises(ConfigError) as info:
        load_spec(Path("..") / "specs" / "spec.yaml")
    assert str(info.value) == (
        f"{Path('..') / 'specs' / 'spec.yaml'}: onboard_config: expected an existing onboard configuration file, "
        f"got '{(spec_dir / 'onboard.yaml').resolve()}'"
    )


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


@pytest.mark.parametrize(
    "address",
    ["tcp://127.0.0.1:notaport", "tcp://[::1", "tcp://127.0.0.1:0", "tcp://127.0.0.1:70000", "tcp://:8786", "tcp://h"],
)
def test_cli_a_malformed_scheduler_address_is_one_line_before_anything(tmp_path, capsys, address):
    """A port that is not one, an unclosed IPv6 bracket: a traceback, a 20 s wait and exit 1 had followed."""
    out = tmp_path / "out"
    argv = ["campaign", str(_spec_file(tmp_path)), "--out", str(out), "--scheduler", address, "--no-progress"]
    assert cli_main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("groundsim campaign: error: --scheduler: expected an address"), err
    assert address in err[0] and not out.exists()


# --------------------------------------------------------------------------- a damaged log on resume


@pytest.fixture(scope="module")
def good_row(tmp_path_factory) -> dict:
    """The row one real run of the one-run spec wrote (its parameters hash to its run id)."""
    tmp_path = tmp_path_factory.mktemp("campaign")
    run_campaign(_spec(tmp_path), tmp_path / "good", workers=1, progress=False)
    (row,) = read_log(tmp_path / "good" / LOG_NAME)[0].values()
    return row


def _line(row) -> bytes:
    return json.dumps(row).encode() + b"\n"


#: one line of each way a log line can fail to be a run's row (the report reads every row it keeps)
DAMAGED = {
    "not UTF-8": lambda row: bytes(range(0x80, 0xC0)) + b"\n",
    "not JSON": lambda row: b'{"run_id": "' + row["run_id"].encode() + b'", "x"\n',
    "run_id a list": lambda row: _line({"run_id": [1, 2]}),
    "run_id only": lambda row: _line({"run_id": row["run_id"]}),
    "a figure that is text": lambda row: _line({**row, "rmse_published_settled_m": "abc"}),
    "a parameter changed": lambda row: _line({**row, "seed": row["seed"] + 1}),
    "an unknown status": lambda row: _line({**row, "status": "weird"}),
    "nested too deep for json": lambda row: b"[" * 100_000 + b"]" * 100_000 + b"\n",
}


@pytest.mark.parametrize("kind", list(DAMAGED))
def test_a_damaged_line_is_skipped_named_once_and_its_run_redone(tmp_path, good_row, kind, caplog):
    out = tmp_path / "out"
    out.mkdir()
    (out / LOG_NAME).write_bytes(DAMAGED[kind](good_row))
    with caplog.at_level(logging.WARNING, logger="groundsim.evaluation.campaign"):
        res = run_campaign(_spec(tmp_path), out, workers=1, progress=False)
    assert (res.planned, res.reused, res.ran, res.failed) == (1, 0, 1, 0)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings == [
        f"{out / LOG_NAME}: 1 line(s) skipped, not a run's row (line 1): cut short by an interruption, damaged or "
        "written by something else; any run they held is run again"
    ]
    table = pd.read_csv(out / TABLE_NAME)
    assert table["run_id"].tolist() == [good_row["run_id"]] and table["status"].tolist() == ["ok"]
    assert "rmse_published_settled_m" in table and np.isfinite(table["rmse_published_settled_m"]).all()


def test_damaged_lines_around_a_good_row_do_not_stop_its_reuse(tmp_path, good_row, caplog):
    out = tmp_path / "out"
    out.mkdir()
    lines = [make(good_row) for make in DAMAGED.values()]
    (out / LOG_NAME).write_bytes(b"".join(lines[:3] + [b"\n", _line(good_row)] + lines[3:]))
    with caplog.at_level(logging.WARNING, logger="groundsim.evaluation.campaign"):
        res = run_campaign(_spec(tmp_path), out, workers=1, progress=False)
    assert (res.reused, res.ran) == (1, 0)  # the good row (line 5) was read past the bad bytes and reused
    (warning,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    # the blank line 4 is not a row and not damaged; the rows after the good one do not replace it
    assert "8 line(s) skipped, not a run's row (line 1, 2, 3, 6, 7, 8, 9, 10)" in warning
    done, bad = reusable_rows(out / LOG_NAME, [good_row["run_id"]])
    assert done == {good_row["run_id"]: good_row} and bad == [1, 2, 3, 6, 7, 8, 9, 10]


def test_the_skipped_lines_listed_are_capped_but_counted(tmp_path, caplog):
    out = tmp_path / "out"
    out.mkdir()
    (out / LOG_NAME).write_bytes(b"\xff\n" * 25)
    with caplog.at_level(logging.WARNING, logger="groundsim.evaluation.campaign"):
        run_campaign(_spec(tmp_path), out, workers=1, progress=False)
    (warning,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert "25 line(s) skipped, not a run's row (line 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, ...)" in warning


def test_rows_of_other_runs_are_kept_unchecked_and_not_warned_about(tmp_path):
    # a row the plan does not name (another spec, an older configuration) is not this campaign's business
    p = tmp_path / LOG_NAME
    append_rows(p, [{"run_id": "elsewhere", "x": [1]}])
    assert reusable_rows(p, ["mine"]) == ({"elsewhere": {"run_id": "elsewhere", "x": [1]}}, [])


_BAD_FIGURES = st.one_of(
    st.text(), st.booleans(), st.lists(st.integers(), max_size=2), st.dictionaries(st.text(), st.integers(), max_size=1)
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    garbage=st.lists(st.binary(max_size=40).filter(lambda b: b"\n" not in b), max_size=6),
    column=st.sampled_from(["rmse_published_settled_m", "range_scale", "seed", "err_range_final_pct", "wall_s"]),
    value=_BAD_FIGURES,
)
def test_any_bytes_or_any_mistyped_figure_is_skipped_never_raised(tmp_path, good_row, garbage, column, value):
    p = tmp_path / LOG_NAME
    p.write_bytes(b"".join(g + b"\n" for g in garbage) + _line(good_row) + _line({**good_row, column: value}))
    done, bad = reusable_rows(p, [good_row["run_id"]])
    assert done == {good_row["run_id"]: good_row}
    assert bad == [i for i, g in enumerate(garbage, start=1) if g.strip()] + [len(garbage) + 2]
    assert read_log(p)[1] == len(bad)


def test_a_campaign_whose_every_run_failed_exits_1_naming_the_first_error(tmp_path, capsys):
    """A plug-in that is no estimator makes every run fail: the command said '1 run now (1 failed)' and exited 0."""
    spec = _spec_file(tmp_path, "scenarios: [P1]\nnoise: [RTK]\nalgorithms: ['os:getcwd']\nduration_s: 1.0\n")
    rc = cli_main(["campaign", str(spec), "--out", str(tmp_path / "out"), "--workers", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 1 and "error: campaign spec: every one of its 1 runs failed; the first: " in err
    ok = _spec_file(tmp_path)
    assert cli_main(["campaign", str(ok), "--out", str(tmp_path / "ok"), "--workers", "1", "--no-progress"]) == 0


def test_cli_a_folder_that_is_not_an_earlier_campaigns_is_refused_untouched(tmp_path, capsys):
    """A campaign overwrites its folder's report.md and table and, with --fresh, removes its runs.jsonl: a folder
    without a campaign's log (a home folder) is refused in one line before anything is written there."""
    out = tmp_path / "mine"
    out.mkdir()
    (out / "report.md").write_text("the user's\n")
    spec = _spec_file(tmp_path)
    assert cli_main(["campaign", str(spec), "--out", str(out), "--fresh", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"--out {out}: not empty and not an earlier groundsim campaign's folder" in err, err
    assert sorted(p.name for p in out.iterdir()) == ["report.md"] and (out / "report.md").read_text() == "the user's\n"


def _files(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.is_file()}


def test_a_folder_of_another_campaign_is_refused_untouched_unless_fresh(tmp_path, capsys):
    """--out naming the folder of another campaign (another name) is one line naming the folder and both campaigns,
    nothing written (it had reused the other's matching runs, appended its own to the other's log and replaced
    the other's table and report); --fresh starts it over there; the same campaign edited (a seed more) resumes."""
    out = tmp_path / "out"
    a = tmp_path / "a.yaml"
    a.write_text("name: a\nscenarios: [P1]\nnoise: [RTK]\nalgorithms: [paper]\nseeds: 1\nduration_s: 1.0\n")
    b = tmp_path / "b.yaml"
    b.write_text("name: b\nscenarios: [P1]\nnoise: [RTK]\nalgorithms: [paper]\nseeds: 2\nduration_s: 1.0\n")
    run = ["--out", str(out), "--workers", "1", "--no-progress"]
    assert cli_main(["campaign", str(a), *run]) == 0
    before = _files(out)
    capsys.readouterr()
    assert cli_main(["campaign", str(b), *run]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err, err
    assert f"--out {out}: holds the runs of campaign 'a' (spec {a}), not of 'b' (spec {b})" in err, err
    assert "--fresh" in err and _files(out) == before
    assert cli_main(["campaign", str(b), *run, "--fresh"]) == 0
    assert {r["seed"] for r in read_log(out / LOG_NAME)[0].values()} == {0, 1}
    assert json.loads((out / "campaign.json").read_text())["name"] == "b"
    b.write_text(b.read_text().replace("seeds: 2", "seeds: 3"))
    capsys.readouterr()
    assert cli_main(["campaign", str(b), *run]) == 0
    assert "2 reused" in capsys.readouterr().out


def test_a_folder_written_before_the_campaign_was_recorded_is_known_by_its_report(tmp_path):
    """A folder of an earlier version (a log, no campaign.json) is another campaign's when its report's title says
    so."""
    out = tmp_path / "out"
    run_campaign(_spec(tmp_path, name="a"), out, workers=1, progress=False)
    (out / "campaign.json").unlink()
    with pytest.raises(ConfigError, match=r"holds the runs of campaign 'a' \(spec unknown\), not of 'b'"):
        run_campaign(_spec(tmp_path, name="b"), out, workers=1, progress=False)
    run_campaign(_spec(tmp_path, name="a"), out, workers=1, progress=False)  # its own: resumed
