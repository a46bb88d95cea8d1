"""``groundsim campaign`` stopped by a signal: a second Ctrl-C while the table and the report are written does not
cut them short, and SIGTERM stops it as Ctrl-C does (the finished runs in the table, the interrupted line)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from groundsim.app.cli import main as cli_main
from groundsim.evaluation.campaign import LOG_NAME, read_log
from groundsim.evaluation.campaign_report import REPORT_NAME, TABLE_NAME
from tests.groundsim.campaign_helpers import campaign_cmd
from tests.process_helpers import descendants, kill_all, wait_gone

REPO = Path(__file__).resolve().parents[2]
EXIT_INTERRUPTED = 130
FIRST_ROW_TIMEOUT_S = 120.0  # hang guard: the first case's rows (imports and a pool's start on a busy machine)
EXIT_TIMEOUT_S = 60.0
GONE_TIMEOUT_S = 2.0  # the pool's processes after the command's exit
# two cases of two algorithms, in this process: the first case's rows are logged before the first Ctrl-C
SPEC = "scenarios: [P1]\nnoise: [RTK]\nalgorithms: [paper, rpekf]\nseeds: 2\nduration_s: 0.5\n"


def _spec_file(tmp_path, body=SPEC):
    p = tmp_path / "spec.yaml"
    p.write_text(body)
    return p


def test_a_second_ctrl_c_while_the_table_is_written_does_not_cut_it_short(tmp_path, monkeypatch, capsys):
    """Ctrl-C after the first case, a second one as the table is written: the table holds every logged run, the
    report is written, the interrupted line says how many runs are done (it had said "nothing written", the table
    a header alone)."""
    import groundsim.evaluation.campaign as campaign

    run_job, write_table = campaign.run_job, campaign.write_table

    started = []

    def first_ctrl_c(job):
        started.append(job)
        if len(started) == 2:  # the terminal's Ctrl-C as the second case starts
            signal.raise_signal(signal.SIGINT)
        return run_job(job)

    def second_ctrl_c(*args, **kwargs):
        signal.raise_signal(signal.SIGINT)
        return write_table(*args, **kwargs)

    monkeypatch.setattr(campaign, "run_job", first_ctrl_c)
    monkeypatch.setattr(campaign, "write_table", second_ctrl_c)
    out = tmp_path / "out"
    rc = cli_main(["campaign", str(_spec_file(tmp_path)), "--out", str(out), "--workers", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == EXIT_INTERRUPTED, err
    logged = len(read_log(out / LOG_NAME)[0])
    assert logged == 2  # the first case's two algorithms
    assert len(pd.read_csv(out / TABLE_NAME)) == logged and (out / REPORT_NAME).is_file()
    lines = [line for line in err.splitlines() if line.startswith("interrupted:")]
    assert lines == [f"interrupted: {logged} of 4 runs done; the same command resumes"], err


def test_a_ctrl_c_as_a_case_is_logged_counts_it_done(tmp_path, monkeypatch, capsys):
    """Ctrl-C arriving while the first case's rows are logged: they are logged and counted together, so the
    interrupted line says what the log holds (it had said 0 of 4 with 2 runs in the log: the signal came between
    the write and the count)."""
    import groundsim.evaluation.campaign as campaign

    append_rows = campaign.append_rows

    def ctrl_c_after_writing(path, rows):
        rows = list(rows)
        append_rows(path, rows)
        if rows:  # not the check that the log opens for appending
            signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(campaign, "append_rows", ctrl_c_after_writing)
    out = tmp_path / "out"
    rc = cli_main(["campaign", str(_spec_file(tmp_path)), "--out", str(out), "--workers", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == EXIT_INTERRUPTED, err
    logged = len(read_log(out / LOG_NAME)[0])
    assert logged == 2  # the first case's two algorithms, and no second case
    lines = [line for line in err.splitlines() if line.startswith("interrupted:")]
    assert lines == [f"interrupted: {logged} of 4 runs done; the same command resumes"], err


def test_signals_held_defers_a_ctrl_c_to_the_end_of_the_block():
    """A SIGINT inside the block is raised as KeyboardInterrupt once the block has run to its end; none is raised
    when none came, and the handler before the block is back after it."""
    from groundsim.io.stop_signals import signals_held

    before = signal.getsignal(signal.SIGINT)
    steps = []
    with pytest.raises(KeyboardInterrupt):
        with signals_held():
            signal.raise_signal(signal.SIGINT)
            steps.append("after the signal")
    assert steps == ["after the signal"]
    with signals_held():
        steps.append("quiet")
    assert steps == ["after the signal", "quiet"] and signal.getsignal(signal.SIGINT) is before


@pytest.mark.parametrize("name", [TABLE_NAME, REPORT_NAME])
def test_a_write_stopped_half_way_leaves_the_earlier_file_whole(tmp_path, monkeypatch, name):
    """The table and the report are written beside their names and renamed over them: a write stopped half way
    (a kill, a full disk) leaves the earlier file as it was, not a file cut short."""
    from pathlib import Path

    import groundsim.evaluation.campaign_report as report
    from groundsim.evaluation.campaign_spec import load_spec

    out = tmp_path / "out"
    out.mkdir()
    (out / name).write_text("the earlier one\n")

    class Stopped(Exception):
        pass

    def half_then_stopped(self, path, *_a, **_k):  # DataFrame.to_csv
        Path(path).write_bytes(b"run_id,mo")
        raise Stopped

    write_text = Path.write_text

    def text_half_then_stopped(path, text, *a, **k):  # Path.write_text
        write_text(path, text[: len(text) // 2], *a, **k)
        raise Stopped

    spec = load_spec(_spec_file(tmp_path))
    info = {"planned": 0, "reused": 0, "ran": 0, "failed": 0, "wall_s": 0.0, "workers": 1, "interrupted": False}
    with pytest.raises(Stopped):
        if name == TABLE_NAME:
            monkeypatch.setattr(pd.DataFrame, "to_csv", half_then_stopped)
            report.write_table(out, [])
        else:
            monkeypatch.setattr(Path, "write_text", text_half_then_stopped)
            report.write_report(out, spec, [], info)
    monkeypatch.undo()
    assert (out / name).read_text() == "the earlier one\n"


@pytest.mark.integration
@pytest.mark.multicore
def test_sigterm_stops_a_campaign_as_ctrl_c_does(tmp_path):
    """SIGTERM to the command alone once a run is logged: the pool ended, the table of every logged run, the
    interrupted line; it had ended at once (exit -15, no line, a leaked-semaphore warning, the table and report
    of an earlier invocation left beside a longer log)."""
    out = tmp_path / "out"
    cmd = campaign_cmd(REPO / "config/campaigns/example.yaml", out, "--workers", "2", "--fresh")
    err_path = tmp_path / "stderr.txt"
    with open(err_path, "w") as err:  # a file, not a pipe: no wait on what the workers hold open
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=err)
    pool: set[int] = set()
    try:
        t_end = time.monotonic() + FIRST_ROW_TIMEOUT_S
        while time.monotonic() < t_end and proc.poll() is None:
            pool |= descendants(proc.pid)
            if (out / LOG_NAME).is_file() and read_log(out / LOG_NAME)[0]:
                break
            time.sleep(0.05)
        assert proc.poll() is None, "the campaign ended before a run was logged"
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(EXIT_TIMEOUT_S)
        assert not wait_gone(pool, GONE_TIMEOUT_S), "the pool outlived the campaign"
        stderr = err_path.read_text()
        assert rc == EXIT_INTERRUPTED, stderr[-3000:]
        logged = len(read_log(out / LOG_NAME)[0])
        lines = [line for line in stderr.splitlines() if line.startswith("interrupted:")]
        assert lines == [f"interrupted: {logged} of 72 runs done; the same command resumes"], stderr[-3000:]
        assert len(pd.read_csv(out / TABLE_NAME)) == logged and (out / REPORT_NAME).is_file()
        assert "Traceback" not in stderr and "leaked semaphore" not in stderr, stderr[-3000:]
    finally:
        kill_all([proc.pid, *pool])


def test_two_quick_sigterms_still_write_the_table_and_the_report(tmp_path, monkeypatch, capsys):
    """The second of two quick SIGTERMs landing as the first is caught, before the finishing holds the signals: it
    is noted, not raised, so the table and the report are written and the interrupted line counts the logged runs
    (it had escaped the campaign: "interrupted: nothing written", no table; measured with two kill -TERM a
    moment apart to a 2-worker campaign)."""
    import groundsim.evaluation.campaign as campaign

    run_job, finishing = campaign.run_job, campaign.finish_despite_signals
    started = []

    def first_sigterm(job):
        started.append(job)
        if len(started) == 2:
            signal.raise_signal(signal.SIGTERM)
        return run_job(job)

    def second_sigterm_first(*args, **kwargs):
        signal.raise_signal(signal.SIGTERM)
        return finishing(*args, **kwargs)

    monkeypatch.setattr(campaign, "run_job", first_sigterm)
    monkeypatch.setattr(campaign, "finish_despite_signals", second_sigterm_first)
    before = signal.getsignal(signal.SIGTERM)
    out = tmp_path / "out"
    rc = cli_main(["campaign", str(_spec_file(tmp_path)), "--out", str(out), "--workers", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == EXIT_INTERRUPTED, err
    logged = len(read_log(out / LOG_NAME)[0])
    assert logged == 2 and len(pd.read_csv(out / TABLE_NAME)) == logged and (out / REPORT_NAME).is_file()
    lines = [line for line in err.splitlines() if line.startswith("interrupted:")]
    assert lines == [f"interrupted: {logged} of 4 runs done; the same command resumes"], err
    assert signal.getsignal(signal.SIGTERM) is before


def test_a_stop_signal_while_python_exits_after_the_interrupted_line_keeps_its_exit_code():
    """``python -m groundsim`` ending on a signal (exit 130, its files written, its line printed) ignores a repeated
    one while Python exits (a pool's finalizers): it had ended killed by SIGTERM (143) after the line."""
    code = (
        "import atexit, os, runpy, signal\n"
        "import groundsim.app.cli as cli\n"
        "cli.main = lambda argv=None: 130\n"
        "atexit.register(lambda: os.kill(os.getpid(), signal.SIGTERM))\n"
        "runpy.run_module('groundsim', run_name='__main__')\n"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert res.returncode == EXIT_INTERRUPTED, (res.returncode, res.stderr[-2000:])


@pytest.fixture
def sigint_ignored():
    """SIGINT ignored, as a non-interactive shell starts a command with ``&``."""
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)


def test_sigint_ignored_on_entry_stays_ignored_and_sigterm_still_stops(sigint_ignored):
    """A command started in the background (SIGINT ignored) is not stopped by SIGINT, not even while a result is
    logged or the report written (signals_held had raised KeyboardInterrupt for it, stopping a campaign that ignored
    it otherwise); SIGTERM stops it as always; SIGINT is still ignored after."""
    from groundsim.io.stop_signals import finish_despite_signals, first_signal_stops, signals_held

    with signals_held():
        signal.raise_signal(signal.SIGINT)
    with finish_despite_signals() as received:
        signal.raise_signal(signal.SIGINT)
    assert received == []
    with pytest.raises(KeyboardInterrupt):
        with first_signal_stops("the report") as received:
            signal.raise_signal(signal.SIGINT)
            signal.raise_signal(signal.SIGTERM)
    assert received == [signal.SIGTERM]
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN


def test_after_the_first_signal_the_others_are_noted_not_raised():
    """first_signal_stops: the first signal raises KeyboardInterrupt, the next ones (either) are noted; the handlers
    before the block are back after it."""
    from groundsim.io.stop_signals import first_signal_stops

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    with first_signal_stops("the report") as received:
        try:
            signal.raise_signal(signal.SIGTERM)
        except KeyboardInterrupt:
            signal.raise_signal(signal.SIGTERM)
            signal.raise_signal(signal.SIGINT)
    assert received == [signal.SIGTERM, signal.SIGTERM, signal.SIGINT]
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
