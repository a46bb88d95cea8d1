"""Bad input to ``bench.onboard``, ``bench.imaging --scene``, the ``--json`` files of ``bench.estimator`` and
``bench.scenes3d``, ``bench.record --dir`` and ``bench.scenes3d --table-from``: one line on stderr naming the option
(or the file), exit code 2, before anything is measured.  Never a traceback, never a run that does not end (an
infinite or NaN duration), never nonsense taken silently (a table of NaN, a count of 0, a negative lag), never a
long run whose results are lost at its end to a ``--json`` path that cannot be written."""

import json
import subprocess
import sys

import pytest

from tests.bench.test_option_refusal import _DRIVER, REPO

pytestmark = pytest.mark.subprocess

# (benchmark and arguments, the option its error names, a text the error also holds); {missing} a file that does
# not exist, {file} a regular file, {dir} a folder, {empty} an empty file, {badyaml} a file that is not YAML,
# {noruns} a --json file without runs
BAD_VALUES = [
    (["bench.onboard", "--latency-s", "inf"], "--latency-s", ""),  # was a run that never ended
    (["bench.onboard", "--latency-s", "nan"], "--latency-s", ""),
    (["bench.onboard", "--latency-s", "0"], "--latency-s", ""),  # was a table of nan
    (["bench.onboard", "--latency-s", "-1"], "--latency-s", ""),
    (["bench.onboard", "--parts-s", "inf"], "--parts-s", ""),  # was a run that never ended
    (["bench.onboard", "--parts-s", "nan"], "--parts-s", ""),
    (["bench.onboard", "--parts-s", "-1"], "--parts-s", ""),
    (["bench.onboard", "--parts-repeats", "0"], "--parts-repeats", ""),
    (["bench.onboard", "--floor-s", "nan"], "--floor-s", ""),
    (["bench.onboard", "--floor-s", "-1"], "--floor-s", ""),
    (["bench.onboard", "--no-latency", "--frames", "0"], "--frames", ""),  # was a ValueError from max()
    (["bench.onboard", "--frames", "-1"], "--frames", ""),
    (["bench.onboard", "--capture-lags-ms", "0", "nan"], "--capture-lags-ms", ""),  # was a traceback mid-run
    (["bench.onboard", "--capture-lags-ms", "-5"], "--capture-lags-ms", ""),
    (["bench.onboard", "--scene", "nosuch"], "--scene", "C1"),  # the shipped scenarios named
    (["bench.onboard", "--scene", "{dir}"], "--scene", "{dir}"),
    (["bench.onboard", "--scene", "{empty}"], "--scene", "{empty}"),
    (["bench.onboard", "--scene", "{badyaml}"], "--scene", "{badyaml}"),
    (["bench.onboard", "--scene", "C1", "--scene-s", "0"], "--scene-s", ""),  # was an error naming --duration
    (["bench.onboard", "--scene", "C1", "--scene-s", "nan"], "--scene-s", ""),
    (["bench.onboard", "--scene", "C1", "--scene-s", "4000"], "--scene-s", "3600"),  # longer than any scenario
    (["bench.onboard", "--scene", "F1"], "--scene", "observers"),  # a fleet: one daemon flies one observer
    (["bench.onboard", "--chain", "bogus"], "--chain", ""),  # was argparse's usage block
    (["bench.imaging", "--scene", "nosuch"], "--scene", "known: "),  # the shipped scenarios named
    (["bench.imaging", "--scene", "P1", "--frames", "0"], "--frames", ""),  # was an error naming --duration
    (["bench.imaging", "--scene", "P1", "--frames", "-5"], "--frames", ""),
    (["bench.imaging", "--scene", "P1", "--seed", "0", "-1"], "--seed", ""),
    (["bench.imaging", "--scene", "P1", "--cache", "{file}"], "--cache", "{file}"),  # was a FileExistsError
    (["bench.imaging", "--scene", "P1", "--repeat", "-3"], "--repeat", ""),  # was one run, silently
    (["bench.imaging", "--scene", "P1", "--chain", "bogus"], "--chain", ""),  # was argparse's usage block
    (["bench.estimator", "--json", "{dir}"], "--json", "{dir}"),  # was a traceback after the whole run
    (["bench.estimator", "--json", "/proc/bench.json"], "--json", "/proc"),
    (["bench.estimator", "--json", "{file}/bench.json"], "--json", "{file}"),  # its folder is a file
    (["bench.scenes3d", "--json", "{dir}"], "--json", "{dir}"),
    (["bench.scenes3d", "--json", "/proc/no/bench.json"], "--json", "/proc"),
    (["bench.record", "--dir", "/proc"], "--dir", "/proc"),  # was a FileNotFoundError
    (["bench.scenes3d", "--table-from", "{noruns}"], "--table-from", "no runs in it"),  # was an empty table, exit 0
]

# (benchmark and arguments, the text its one error line starts with, a text it also holds): a configuration file
# that cannot be read is said by the benchmark, as the project's errors are, once the run reads it
FILE_ERRORS = [
    (["bench.imaging", "--loop", "C1", "--onboard-config", "{missing}"], "bench.imaging: ", "{missing}"),
    (["bench.scenes3d", "--scenes", "C1", "--onboard-config", "{missing}"], "bench.scenes3d: ", "{missing}"),
]


@pytest.fixture(scope="module")
def outcomes(tmp_path_factory):
    """``(BAD_VALUES outcomes, FILE_ERRORS outcomes)``, each case ``{"code", "stderr", "stdout"}`` and its texts with
    the file names put in, every case run in one child process."""
    tmp = tmp_path_factory.mktemp("bad_input")
    (tmp / "file.txt").write_text("a regular file\n")
    (tmp / "empty.yaml").write_text("")
    (tmp / "bad.yaml").write_text("a: [1\n")
    (tmp / "noruns.json").write_text('{"runs": []}')
    (tmp / "dir").mkdir()
    names = {
        "missing": tmp / "missing.yaml",
        "file": tmp / "file.txt",
        "dir": tmp / "dir",
        "empty": tmp / "empty.yaml",
        "badyaml": tmp / "bad.yaml",
        "noruns": tmp / "noruns.json",
    }

    def fill(text: str) -> str:
        return text.format(**{k: str(v) for k, v in names.items()})

    cases = [[fill(a) for a in argv] for argv, _, _ in BAD_VALUES + FILE_ERRORS]
    proc = subprocess.run(
        [sys.executable, "-c", _DRIVER, json.dumps(cases)], cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.splitlines()[-1])
    for case, (_, named, also) in zip(got, BAD_VALUES + FILE_ERRORS):
        case["named"], case["also"] = named, fill(also)
    return got[: len(BAD_VALUES)], got[len(BAD_VALUES) :]


def _one_line(got: dict) -> str:
    assert got["code"] == 2, got["stdout"][-2000:] + got["stderr"][-2000:]
    assert "Traceback" not in got["stderr"], got["stderr"][-3000:]
    lines = got["stderr"].splitlines()
    assert len(lines) == 1, got["stderr"]
    assert got["stdout"] == ""  # refused before anything was measured or printed
    return lines[0]


@pytest.mark.parametrize("k", range(len(BAD_VALUES)), ids=[" ".join(a) for a, _, _ in BAD_VALUES])
def test_a_bad_value_is_refused_on_one_line_naming_the_option(outcomes, k):
    got = outcomes[0][k]
    line = _one_line(got)
    assert f"error: argument {got['named']}: " in line, line
    assert got["also"] in line, line


@pytest.mark.parametrize("k", range(len(FILE_ERRORS)), ids=[" ".join(a) for a, _, _ in FILE_ERRORS])
def test_a_config_file_that_cannot_be_read_is_one_line_from_the_benchmark(outcomes, k):
    got = outcomes[1][k]
    line = _one_line(got)
    assert line.startswith(got["named"]) and got["also"] in line, line


def test_a_failure_part_way_through_a_measurement_is_one_line_and_exit_1_not_bad_input(capsys):
    """Every project error out of a benchmark was exit 2, as if the caller's input were wrong."""
    from bench import run_benchmark
    from onboard.core.errors import ConfigError
    from onboard.estimation.map_estimator import EstimationError

    def failing(exc):
        def main():
            raise exc

        return main

    import signal

    # run_benchmark is a command's whole life: it takes SIGINT and SIGTERM for good; this process goes on
    kept = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        assert run_benchmark("x", failing(EstimationError("solve diverged\nat step 3"))) == 1
        assert capsys.readouterr().err == "bench.x: solve diverged at step 3\n"
        assert run_benchmark("x", failing(ConfigError("f.yaml: a: expected a number"))) == 2
        assert capsys.readouterr().err == "bench.x: f.yaml: a: expected a number\n"
    finally:
        for sig, handler in kept.items():
            signal.signal(sig, handler)
