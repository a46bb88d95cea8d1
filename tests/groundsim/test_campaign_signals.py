"""``groundsim campaign`` stopped by a signal: a second Ctrl-C while the table and the report are written does not
cut them short, and SIGTERM stops it as Ctrl-C does (the finished runs in the table, the interrupted line)."""

from __future__ import annotations

import signal

import pandas as pd
import pytest

from groundsim.app.cli import main as cli_main
from groundsim.evaluation.campaign import LOG_NAME, read_log
from groundsim.evaluation.campaign_report import REPORT_NAME, TABLE_NAME

EXIT_INTERRUPTED = 130
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
