"""bench.companion's bad input (one line naming the option, exit 2, before any row runs) and its progress lines
(one as each row starts and one as it ends, naming the row's quota), on runs replaced by stand-ins."""

from __future__ import annotations

import os

import pytest

import bench.companion as companion
import groundsim.evaluation.demo as demo_module


@pytest.fixture
def no_runs(monkeypatch):
    """A refusal must come before any row's run."""

    def never(*_args, **_kwargs):
        raise AssertionError("a run started")

    monkeypatch.setattr(demo_module, "run_demo", never)


def _refused(capsys, argv) -> str:
    """The one line of a refusal: a value checked when the command line is parsed (argparse's exit 2 and words)
    or later, before any row (main's return 2)."""
    try:
        code = companion.main(argv)
    except SystemExit as exc:
        code = exc.code
    assert code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1, err
    return err[0]


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--scenario", "nosuch"], "--scenario: nosuch: (file): expected an existing file or one of the shipped"),
        (["--duration", "-1"], "--duration: expected a finite number > 0"),
        (["--seed", "-1"], "--seed: expected an integer >= 0"),
        (["--nav-noise", "zz"], "--nav-noise: expected one of"),
        (["--config", "{missing}"], "--config {missing}: no such file"),
        (["--config", "{dir}"], "--config {dir}: a directory, not a file"),
        (["--out", "/proc/no-such-dir"], "--out /proc/no-such-dir/unlimited: cannot create the directory"),
    ],
    ids=["scenario", "duration", "seed", "nav_noise", "config_missing", "config_dir", "out"],
)
def test_bad_input_is_one_line_exit_2_before_any_run(tmp_path, capsys, no_runs, argv, needle):
    paths = {"missing": str(tmp_path / "nonexist.yaml"), "dir": str(tmp_path)}
    argv = [a.format(**paths) for a in argv]
    if "--out" not in argv:
        argv += ["--out", str(tmp_path / "o")]
    line = _refused(capsys, argv)
    assert line.startswith(("bench.companion: ", "python -m bench.companion: error: argument ")), line
    assert needle.format(**paths) in line, line
    assert "--onboard-config" not in line


def test_a_quota_above_the_usable_cores_is_refused_naming_them(tmp_path, capsys, no_runs):
    cores = len(os.sched_getaffinity(0))
    line = _refused(capsys, ["--cpu-quota", "0.5", str(cores + 1), "--out", str(tmp_path / "o")])
    assert line.startswith(f"bench.companion: --cpu-quota {cores + 1:g}: more than the {cores} core(s)"), line
    assert not (tmp_path / "o").exists()


def test_each_row_says_when_it_starts_and_ends_with_its_quota(tmp_path, capsys, monkeypatch):
    def row(args, quota, out_root, say):
        label = "unlimited" if quota is None else f"{quota:g} core"
        error = None if quota is None else "the simulator exited with code 1"
        figures = dict(coverage=0.9, observable_after_5s=0.8, honest=0.95, positions=500, daemon_cpu=0.4)
        rest = dict(overload_s=None, first_cause_s=None, throttled=None, error=error, wall_s=21.5)
        return dict(label=label, frames=600, tracks=590, **figures, **rest)

    monkeypatch.setattr(companion, "run_row", row)
    assert companion.main(["--cpu-quota", "0.5", "--out", str(tmp_path / "o")]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("bench.companion: row")]
    assert len(lines) == 4, lines
    assert lines[0].startswith("bench.companion: row 1 of 2, daemon unlimited: P2 RTK 20 s")
    assert lines[1] == "bench.companion: row 1 of 2, daemon unlimited: done in 21.5 s, 590 tracks of 600 frames"
    assert lines[2].startswith("bench.companion: row 2 of 2, daemon quota 0.5 core: P2 RTK 20 s")
    assert lines[3] == (
        "bench.companion: row 2 of 2, daemon quota 0.5 core: done in 21.5 s, 590 tracks of 600 frames;"
        " run problem: the simulator exited with code 1"
    )
