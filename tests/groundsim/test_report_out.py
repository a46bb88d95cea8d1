"""``groundsim report``'s folder and its --truth file: a folder that is not an earlier report's is refused untouched
(the report replaces its plots and summary.json by name), and a --truth file that is no recording is named as
--truth, the simulator's recording, not as the daemon's."""

from __future__ import annotations

import json
import os
from types import SimpleNamespace

import pytest

import onboard.app.replay as replay_module
from groundsim.app import cli
from groundsim.evaluation.flight_report import REPORT_FILES, REPORT_SCHEMA, holds_flight_report


def _one_error_line(capsys) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip() and "level=" not in line]
    assert len(err) == 1, err
    return err[0]


def test_a_folder_that_is_not_an_earlier_reports_is_refused_untouched_before_the_replay(tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "summary.json").write_text('{"my": "notes"}\n')
    (out / "trajectory.png").write_bytes(b"the user's plot")
    flight = tmp_path / "flight.mcap"
    flight.write_bytes(b"not read: the folder is refused first")
    assert cli.main(["report", str(flight), "--out", str(out)]) == cli.EXIT_ERROR
    line = _one_error_line(capsys)
    assert line.startswith(f"groundsim report: error: --out {out}: not empty and not an earlier groundsim report's")
    assert (out / "summary.json").read_text() == '{"my": "notes"}\n'
    assert (out / "trajectory.png").read_bytes() == b"the user's plot"


@pytest.mark.parametrize(
    ("files", "ours"),
    [
        ({}, True),
        ({"summary.json": json.dumps({"schema": REPORT_SCHEMA, "frames": 3}), "notes.txt": "x"}, True),
        ({"summary.json": json.dumps({"frames": 3, "with_3d": 1, "observable": 1, "truth": False})}, True),
        ({"trajectory.png": "plot", "frame.png": "plot"}, True),
        ({"summary.json": json.dumps({"schema": "something/1", "frames": 3})}, False),
        ({"summary.json": "[]"}, False),
        ({"trajectory.png": "plot", "notes.txt": "x"}, False),
    ],
    ids=["empty", "marked", "unmarked_older", "cut_short", "other_schema", "not_a_summary", "other_files"],
)
def test_an_earlier_report_is_told_by_its_summary_or_its_own_names_alone(tmp_path, files, ours):
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    assert set(files) <= set(REPORT_FILES) | {"notes.txt"}
    assert holds_flight_report(tmp_path) is ours


def _stand_in_recording(flight) -> SimpleNamespace:
    """What the report reads of a daemon recording with one frame taken, as ``onboard.replay.load_recording`` gives
    it, for a file ``flight`` that need not exist."""
    path = str(flight)
    return SimpleNamespace(
        inputs=[{}], truncated=None, truth=[], metadata={}, statuses=[], path=path, name=path, files=[path]
    )


def test_a_truth_file_that_is_no_recording_is_named_as_truth_the_simulators(tmp_path, capsys, monkeypatch):
    flight = tmp_path / "flight.mcap"
    truth = tmp_path / "random.mcap"
    truth.write_bytes(b"random bytes, no MCAP")
    real = replay_module.load_recording

    def load(path):  # the flight a daemon recording with frames; --truth read for real
        return _stand_in_recording(flight) if str(path) == str(flight) else real(path)

    monkeypatch.setattr(replay_module, "load_recording", load)
    code = cli.main(["report", str(flight), "--truth", str(truth), "--out", str(tmp_path / "r")])
    assert code == cli.EXIT_ERROR
    line = _one_error_line(capsys)
    assert line.startswith(f"groundsim report: error: --truth {truth}: not an MCAP recording"), line
    assert "groundsim run --record" in line and "onboard --record" not in line


@pytest.mark.skipif(
    not os.path.exists("/dev/full"), reason="needs /dev/full, a file whose writes fail as a full disk's"
)
def test_a_full_disk_while_the_plots_are_saved_is_one_line_naming_out(tmp_path, capsys, monkeypatch):
    import groundsim.evaluation.flight_report as flight_report
    from groundsim.app import report

    flight = tmp_path / "flight.mcap"
    rec = _stand_in_recording(flight)
    result = SimpleNamespace(tracks=[], frames_fed=1, wall_s=0.1, frames_missing=0, frames_refused=0)
    monkeypatch.setattr(replay_module, "load_recording", lambda path: rec)
    monkeypatch.setattr(replay_module, "config_of", lambda rec, path: None)
    monkeypatch.setattr(replay_module, "replay", lambda rec, config, on_input=None: result)
    monkeypatch.setattr(report, "flight_inputs", lambda rec: ({}, {}))

    def save_on_a_full_disk(out, *args):  # as matplotlib's savefig meets it: the PNG's bytes refused
        with open("/dev/full", "wb") as f:
            f.write(b"\x89PNG" * 4096)

    monkeypatch.setattr(flight_report, "write_flight_report", save_on_a_full_disk)
    out = tmp_path / "r"
    assert cli.main(["report", str(flight), "--out", str(out)]) == cli.EXIT_ERROR
    assert _one_error_line(capsys) == f"groundsim report: error: --out {out}: cannot write: No space left on device"
