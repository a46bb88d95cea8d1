"""The benchmarks without options of their own refuse an unknown one by name instead of starting their default
run (which takes minutes) as if it had not been given; ``--help`` lists what they take.  A bad option value is
refused the same way, on one line naming the option, before anything is measured: never a traceback (a NaN
rate, a missing file, an unknown scenario), never a run that measures nothing (a count of 0)."""

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name", ["flight", "render", "imaging"])
def test_unknown_option_is_refused_by_name(name):
    proc = subprocess.run(
        [sys.executable, "-m", f"bench.{name}", "--scenes", "C1"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "unrecognized arguments: --scenes C1" in proc.stderr
    assert proc.stdout == ""  # nothing of the default run started


def test_help_lists_the_flags():
    proc = subprocess.run(
        [sys.executable, "-m", "bench.render", "--help"], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    assert "--reference-scenes" in proc.stdout and "--stages" in proc.stdout


@pytest.mark.parametrize("mode, flag", [("--scene", "--misses"), ("--loop", "--seeds")])
def test_each_imaging_mode_takes_help_without_its_mode_argument(mode, flag):
    """'bench.imaging --scene --help' said 'expected at least one argument' (the top-level help says each mode has its
    own --help)."""
    proc = subprocess.run(
        [sys.executable, "-m", "bench.imaging", mode, "--help"], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    assert flag in proc.stdout


# (benchmark and arguments, the option its error names); {missing} a file that does not exist, {garbage} a
# file of text that is neither JSON nor MCAP, {foreign} JSON runs of another benchmark, {nodir} a directory that
# does not exist
BAD_VALUES = [
    (["bench.fleet", "--rate", "nan"], "--rate"),
    (["bench.fleet", "--rate", "0"], "--rate"),  # was "nan ms"
    (["bench.fleet", "--seconds", "-1"], "--seconds"),
    (["bench.fleet", "--rate", "0.5", "--seconds", "1"], "--seconds"),  # not one camera period
    (["bench.fleet", "--vehicles", "0"], "--vehicles"),
    (["bench.estimator", "--scenarios", "P1,NOPE"], "--scenarios"),  # was a KeyError after the speed part
    (["bench.estimator", "--noises", "NOPE"], "--noises"),
    (["bench.estimator", "--verdict", "--noises", "NOPE"], "--noises"),
    (["bench.estimator", "--seeds", "0"], "--seeds"),
    (["bench.estimator", "--seeds", "-1"], "--seeds"),
    (["bench.estimator", "--workers", "0"], "--workers"),
    (["bench.record", "--replay", "{missing}"], "--replay"),
    (["bench.record", "--replay", "{garbage}"], "--replay"),
    (["bench.record", "--dir", "{nodir}"], "--dir"),
    (["bench.record", "--frames", "0"], "--frames"),
    (["bench.guidance", "--updates", "-1"], "--updates"),  # was an UnboundLocalError
    (["bench.guidance", "--updates", "0"], "--updates"),
    (["bench.honesty", "--from-json", "{missing}"], "--from-json"),
    (["bench.honesty", "--from-json", "{garbage}"], "--from-json"),
    (["bench.honesty", "--families", "circling,nope"], "--families"),
    (["bench.scenes3d", "--table-from", "{missing}"], "--table-from"),
    (["bench.scenes3d", "--table-from", "{foreign}"], "--table-from"),  # another benchmark's runs
    (["bench.scenes3d", "--scenes", "NOPE"], "--scenes"),
    (["bench.simrate", "--scenario", "NOPE"], "--scenario"),
    (["bench.simrate", "--modes", "bogus"], "--modes"),  # was exit 0, nothing measured
    (["bench.simrate", "--rt-priority", "0"], "--rt-priority"),
    (["bench.time_offset", "--scenarios", "NOPE"], "--scenarios"),  # was a traceback from the worker pool
    (["bench.time_offset", "--seeds", "0"], "--seeds"),
    (["bench.imaging", "--loop", "C4", "--seeds", "-1"], "--seeds"),
    (["bench.imaging", "--loop", "NOPE"], "--loop"),
    (["bench.video", "--frames", "-1"], "--frames"),
    (["bench.video", "--frames", "0", "--latency-frames", "0"], "--frames"),
    (["bench.reconstruct", "--durations", "0"], "--durations"),
    (["bench.reconstruct", "--whole-up-to", "-1"], "--whole-up-to"),
    (["bench.reconstruct", "--window-s", "0"], "--window-s"),  # the windowed run must have windows
]


# every case runs in one child process, each as python -m would run it, with the argv it would get (one
# interpreter start instead of one per case: the cases only parse their command lines); a case that were not
# refused would start measuring, which the child's time limit stops
_DRIVER = r"""
import contextlib, io, json, runpy, sys, traceback
out = []
for argv in json.loads(sys.argv[1]):
    module, args = argv[0], argv[1:]
    err, std = io.StringIO(), io.StringIO()
    code = None
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(std):
        try:
            sys.argv = [module, *args]
            runpy.run_module(module, run_name="__main__", alter_sys=True)  # as python -m MODULE ARGS
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        except BaseException:
            traceback.print_exc()
            code = 1
    out.append({"code": code, "stderr": err.getvalue(), "stdout": std.getvalue()})
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def refusals(tmp_path_factory):
    """``{case index: {"code", "stderr", "stdout"}}`` of every BAD_VALUES case, run in one child process."""
    import json

    tmp = tmp_path_factory.mktemp("refusals")
    garbage = tmp / "garbage.txt"
    garbage.write_text("neither JSON nor MCAP\n")
    foreign = tmp / "foreign.json"
    foreign.write_text('{"runs": [{"family": "circling"}]}')
    paths = {"missing": tmp / "missing.json", "garbage": garbage, "foreign": foreign, "nodir": tmp / "no"}
    cases = [[a.format(**{k: str(v) for k, v in paths.items()}) for a in argv] for argv, _ in BAD_VALUES]
    proc = subprocess.run(
        [sys.executable, "-c", _DRIVER, json.dumps(cases)], cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return dict(enumerate(json.loads(proc.stdout.splitlines()[-1])))


@pytest.mark.parametrize("k", range(len(BAD_VALUES)), ids=[" ".join(a) for a, _ in BAD_VALUES])
def test_a_bad_value_is_refused_on_one_line_naming_the_option(refusals, k):
    option = BAD_VALUES[k][1]
    got = refusals[k]
    assert got["code"] == 2, got["stdout"][-2000:] + got["stderr"][-2000:]
    assert "Traceback" not in got["stderr"], got["stderr"][-3000:]
    lines = got["stderr"].splitlines()
    assert len(lines) == 1, got["stderr"]
    assert f"error: argument {option}: " in lines[0], lines[0]
    assert got["stdout"] == ""  # refused before anything was measured or printed


def test_the_suite_takes_help_and_names_an_unknown_benchmark(capsys):
    from bench.__main__ import main

    assert main(["--help"]) == 0
    assert "python -m bench [NAME ...]" in capsys.readouterr().out
    assert main(["estimator", "nope"]) == 2  # refused before any benchmark starts
    captured = capsys.readouterr()
    assert captured.out == "" and "unknown benchmark(s) nope" in captured.err
