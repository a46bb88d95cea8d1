"""``groundsim eval`` as a command (in process, through ``cli.main``): exit codes, a reused --out, Ctrl-C after
the runs, refused options.  Runs are made to fail at once (``run_lockstep`` replaced) where the test is about
the command, not the chain; one real short run shows a reused folder ends up describing the new run only."""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal

import pytest

from groundsim.app import cli
from groundsim.app.eval_command import EXIT_FAILED, MAX_EVAL_RUNS
from groundsim.evaluation import eval as eval_module
from groundsim.evaluation import report as report_module
from groundsim.io.stop_signals import EXIT_INTERRUPTED
from groundsim.world.scenario import scenarios_dir
from onboard.core.errors import ConfigError

pytestmark = pytest.mark.timeout(120)

FAST = ["--seeds", "1", "--workers", "1", "--duration", "1", "--no-batch", "--no-progress"]


def _cli(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(argv)
    return code, out.getvalue(), err.getvalue()


def _error_lines(err: str) -> list[str]:
    """stderr without the log lines (logfmt: ``level=...``) of the run."""
    return [line for line in err.splitlines() if line.strip() and "level=" not in line and "INFO" not in line]


@pytest.fixture
def failing_runs(monkeypatch):
    """Every run fails at once, as a flight that cannot be made does."""

    def fail(scenario, seed, *_args):
        raise ConfigError(f"{scenario.name} seed {seed}: no flight")

    monkeypatch.setattr(eval_module, "run_lockstep", fail)


@pytest.fixture
def no_runs(monkeypatch):
    """A refusal must come before any run."""

    def never(*_args):
        raise AssertionError("a run started")

    monkeypatch.setattr(eval_module, "run_lockstep", never)


def test_every_run_failed_is_exit_1_in_one_line_without_mot_scoring(tmp_path, failing_runs):
    out = tmp_path / "o"
    code, stdout, err = _cli(["eval", "--scenario", "P1", *FAST, "--out", str(out)])
    assert code == EXIT_FAILED == 1
    assert "1 runs (1 failed)" in stdout
    lines = [line for line in _error_lines(err) if "every run failed" in line]
    assert len(lines) == 1 and str(out / "report.md") in lines[0], err
    assert "MOT scoring failed" not in err and "Traceback" not in err
    assert (out / "mot" / "seqmap.txt").read_text() == "name\n"  # rewritten, listing no sequence
    rep = json.loads((out / "report.json").read_text())
    assert rep["interrupted"] is None and "error" in rep["runs"][0]


def _earlier_report(out):
    """The report.json an earlier eval leaves: what marks ``out`` as an eval's folder."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps({"schema": report_module.SCHEMA, "files": {}}) + "\n")


def _earlier_run_files(out):
    """What an earlier eval (P1 seeds 0-1, P2) left, and files of the user's beside them."""
    _earlier_report(out)
    stale = [
        out / "P2_trajectory.png",
        out / "P2_error.png",
        out / "P2" / "seed0" / "truth.tum",
        out / "P1" / "seed1" / "estimate.tum",
        out / "mot" / "gt" / "P2-RTK-s0" / "gt" / "gt.txt",
        out / "mot" / "trackers" / "irtrack" / "data" / "P2-RTK-s0.txt",
    ]
    kept = [out / "notes.txt", out / "P2" / "notes.txt", out / "mot" / "trackers" / "other" / "data" / "x.txt"]
    for f in stale + kept:
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text("earlier\n")
    (out / "mot" / "seqmap.txt").write_text("name\nP2-RTK-s0\n")
    return stale, kept


def test_a_reused_out_keeps_only_the_new_runs_files_and_the_users(tmp_path):
    out = tmp_path / "o"
    stale, kept = _earlier_run_files(out)
    code, stdout, err = _cli(["eval", "--scenario", "P1", *FAST, "--out", str(out)])
    assert code == 0, err
    assert [f for f in stale if f.exists()] == []
    assert all(f.read_text() == "earlier\n" for f in kept)
    assert not (out / "P1" / "seed1").exists() and not (out / "P2" / "seed0").exists()
    assert (out / "P1" / "seed0" / "truth.tum").is_file() and (out / "P1_trajectory.png").is_file()
    assert (out / "mot" / "seqmap.txt").read_text() == "name\nP1-RTK-s0\n"
    assert sorted(p.name for p in (out / "mot" / "gt").iterdir()) == ["P1-RTK-s0"]
    assert [r["scenario"] for r in json.loads((out / "report.json").read_text())["summary"]] == ["P1"]


def test_a_reused_out_after_failed_runs_lists_no_earlier_sequence(tmp_path, failing_runs):
    out = tmp_path / "o"
    stale, kept = _earlier_run_files(out)
    assert _cli(["eval", "--scenario", "P1", *FAST, "--out", str(out)])[0] == EXIT_FAILED
    assert [f for f in stale if f.exists()] == [] and all(f.is_file() for f in kept)
    assert (out / "mot" / "seqmap.txt").read_text() == "name\n"


def test_ctrl_c_while_the_report_is_written_finishes_it_and_says_where(tmp_path, failing_runs, monkeypatch):
    write = report_module.write_eval_report

    def interrupted_write(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)  # as the terminal's Ctrl-C, once the runs are done
        return write(*args, **kwargs)

    monkeypatch.setattr(report_module, "write_eval_report", interrupted_write)
    out = tmp_path / "o"
    code, _, err = _cli(["eval", "--scenario", "P1", *FAST, "--out", str(out)])
    assert code == EXIT_INTERRUPTED, err
    lines = [line for line in err.splitlines() if line.startswith("interrupted:")]
    assert lines == [f"interrupted: 1 of 1 runs done; report in {out / 'report.md'}; MOT files in {out / 'mot'}"]
    assert (out / "report.md").is_file() and (out / "mot" / "seqmap.txt").is_file()
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler is given back


def _copy_of_p1(tmp_path) -> str:
    """A changed copy of P1 that keeps its ``name: P1``."""
    path = tmp_path / "P1mod.yaml"
    path.write_text((scenarios_dir() / "P1.yaml").read_text().replace("\nname: P1\n", "\n# changed copy\nname: P1\n"))
    return str(path)


@pytest.mark.parametrize(
    "scenario, needle",
    [
        (["P1", "P1"], "are the same file"),
        (["P1", str(scenarios_dir() / "P1.yaml")], "are the same file"),
        (["P1", "COPY"], "are both scenario 'P1'"),
    ],
)
def test_duplicate_scenarios_are_refused_in_one_line(tmp_path, no_runs, scenario, needle):
    scenario = [_copy_of_p1(tmp_path) if s == "COPY" else s for s in scenario]
    code, _, err = _cli(["eval", "--scenario", *scenario, *FAST, "--out", str(tmp_path / "o")])
    assert code == cli.EXIT_ERROR
    lines = _error_lines(err)
    assert len(lines) == 1 and lines[0].startswith("groundsim eval: error: --scenario:") and needle in lines[0], err


@pytest.mark.parametrize("taken", ["mot", "P1"])
def test_an_output_path_taken_by_a_file_is_refused_before_the_runs(tmp_path, no_runs, taken):
    out = tmp_path / "o"
    _earlier_report(out)
    (out / taken).write_text("a file\n")
    code, _, err = _cli(["eval", "--scenario", "P1", *FAST, "--out", str(out)])
    assert code == cli.EXIT_ERROR
    lines = _error_lines(err)
    assert len(lines) == 1 and lines[0].startswith(f"groundsim eval: error: --out {out}") and taken in lines[0], err


def test_a_write_failure_after_the_runs_is_one_line_naming_out(tmp_path, failing_runs):
    out = tmp_path / "o"
    (out / "report.md").mkdir(parents=True)  # a folder where the report goes
    code, _, err = _cli(["eval", "--scenario", "P1", *FAST, "--out", str(out)])
    assert code == cli.EXIT_ERROR
    lines = _error_lines(err)
    assert len(lines) == 1 and lines[0].startswith(f"groundsim eval: error: --out {out}: cannot write"), err
    assert "report.md" in lines[0] and "Traceback" not in err


@pytest.mark.parametrize(
    "argv",
    [
        ["--scenario", "P1", "--seeds", str(MAX_EVAL_RUNS + 1)],
        ["--scenario", "P1", "P2", "--seeds", str(MAX_EVAL_RUNS // 2 + 1)],
        ["--scenario", "P1", "--seeds", "1000000"],
    ],
)
def test_too_many_runs_are_refused_naming_seeds(tmp_path, no_runs, argv):
    code, _, err = _cli(["eval", *argv, "--workers", "1", "--no-progress", "--out", str(tmp_path / "o")])
    assert code == cli.EXIT_ERROR
    lines = _error_lines(err)
    assert len(lines) == 1 and lines[0].startswith("groundsim eval: error: --seeds: at most"), err


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--scenario", "F1"], "--scenario: F1 is a fleet scenario"),
        (["--scenario", "C1", "--gnss-dropout", "5:3"], "--gnss-dropout: expected a start before the run's end (1 s)"),
        (["--scenario", "C1", "--duration=-1"], "--duration: expected a positive number of seconds"),
    ],
    ids=["fleet", "dropout_after_the_end", "negative_duration"],
)
def test_what_eval_cannot_run_is_refused_before_out_is_made(tmp_path, no_runs, extra, needle):
    """A fleet scenario (eval flies one observer's pipeline: the others were left out without a word), a GNSS dropout
    after the run's end, a bad duration: one line, and no --out folder left behind."""
    out = tmp_path / "o"
    code, _, err = _cli(["eval", *FAST, *extra, "--out", str(out)])
    assert code == cli.EXIT_ERROR
    lines = _error_lines(err)
    assert len(lines) == 1 and lines[0].startswith("groundsim eval: error: ") and needle in lines[0], err
    assert not out.exists()


def _users_folder(out):
    """A folder of the user's: a TrackEval tree under mot/ and files named as the eval's own, no eval report."""
    files = [
        out / "report.md",
        out / "performance.png",
        out / "report.json",
        out / "mot" / "gt" / "MOT17-02" / "gt" / "gt.txt",
        out / "mot" / "trackers" / "irtrack" / "data" / "MOT17-02.txt",
        out / "mot" / "seqmap.txt",
        out / "P1" / "seed0" / "truth.tum",
    ]
    for f in files:
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text("the user's\n")
    return files


def test_a_folder_that_is_not_an_earlier_evals_is_refused_untouched_before_the_runs(tmp_path, no_runs):
    out = tmp_path / "o"
    files = _users_folder(out)
    code, _, err = _cli(["eval", "--scenario", "P1", *FAST, "--out", str(out)])
    assert code == cli.EXIT_ERROR
    lines = _error_lines(err)
    assert len(lines) == 1 and lines[0].startswith(f"groundsim eval: error: --out {out}: not empty"), err
    assert "not an earlier groundsim eval's folder" in lines[0] and "Traceback" not in err
    assert all(f.read_text() == "the user's\n" for f in files)


def test_the_report_writer_removes_nothing_from_a_folder_without_an_earlier_report(tmp_path):
    files = _users_folder(tmp_path)
    report_module.clear_eval_report(tmp_path)
    assert all(f.read_text() == "the user's\n" for f in files)


def test_a_folder_of_empty_folders_is_taken(tmp_path, failing_runs):
    """What an eval interrupted before its first run finished leaves (an empty mot/): the next eval writes there."""
    out = tmp_path / "o"
    (out / "mot").mkdir(parents=True)
    assert _cli(["eval", "--scenario", "P1", *FAST, "--out", str(out)])[0] == EXIT_FAILED
    assert report_module.holds_eval_report(out)


def test_without_nav_noise_each_scenario_flies_its_own_case_as_run_and_dataset_do(tmp_path, monkeypatch):
    """A scenario that says ``nav_noise: exact`` was evaluated under RTK, the option's default, with nothing saying
    so; groundsim run, demo and dataset fly its own case.  --nav-noise still overrides it."""
    from groundsim.world.nav_errors import run_nav_case

    flown: list[tuple[str, str]] = []

    def record(scenario, seed, options, *_args):
        flown.append((scenario.name, run_nav_case(scenario, options.injected.nav_noise).name))
        raise ConfigError("recorded, not flown")

    monkeypatch.setattr(eval_module, "run_lockstep", record)
    exact = tmp_path / "P1x.yaml"
    exact.write_text((scenarios_dir() / "P1.yaml").read_text().replace("name: P1", "name: P1x") + "nav_noise: exact\n")
    _cli(["eval", "--scenario", str(exact), "P2", *FAST, "--out", str(tmp_path / "a")])
    assert sorted(flown) == [("P1x", "exact"), ("P2", "RTK")]
    flown.clear()
    _cli(["eval", "--scenario", str(exact), "P2", *FAST, "--nav-noise", "GNSS", "--out", str(tmp_path / "b")])
    assert sorted(flown) == [("P1x", "GNSS"), ("P2", "GNSS")]
