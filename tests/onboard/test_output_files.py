"""Outputs never written over their own inputs or each other (``onboard.app.output_files.same_file_clash``), in
every desk tool that writes files: the tool refuses before it writes anything, naming both, and the input keeps
its bytes."""

from __future__ import annotations

import os

import pytest

from onboard.app.output_files import same_file_clash


def test_same_file_clash_sees_through_relative_paths_links_and_hard_links(tmp_path, monkeypatch):
    src = tmp_path / "in.csv"
    src.write_text("x\n")
    monkeypatch.chdir(tmp_path)
    assert same_file_clash([("-o", "in.csv")], [("OBS.csv", str(src))]) == (
        f"-o in.csv: names the input OBS.csv ({src}); give another file"
    )
    (tmp_path / "link.csv").symlink_to(src)
    assert "names the input" in same_file_clash([("-o", "link.csv")], [("OBS.csv", str(src))])
    os.link(src, tmp_path / "hard.csv")
    assert "names the input" in same_file_clash([("-o", "hard.csv")], [("OBS.csv", str(src))])
    assert same_file_clash([("--out", "a.txt"), ("--objects-out", "./a.txt")]) == (
        "--objects-out ./a.txt: names the same file as --out; give each output its own file"
    )
    assert same_file_clash([("--out", "a.txt"), ("--objects-out", None)], [("IN", str(src))]) is None
    assert same_file_clash([("--out", "new.txt")], [("INPUT", str(tmp_path))]) is None  # a file in the input folder


def _refused(capsys, main, argv, code=2) -> str:
    assert main(argv) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


def test_replay_refuses_an_output_on_its_recording_or_on_the_other_output(tmp_path, capsys):
    from onboard.app.replay import main

    rec = tmp_path / "flight.mcap"
    rec.write_bytes(b"recorded flight bytes")
    assert "names the input MCAP" in _refused(capsys, main, [str(rec), "--out", str(rec)])
    t = tmp_path / "t.jsonl"
    assert "names the same file as --out" in _refused(
        capsys, main, [str(rec), "--out", str(t), "--objects-out", str(t)]
    )
    assert rec.read_bytes() == b"recorded flight bytes" and not t.exists()


def test_reconstruct_refuses_an_output_on_its_observations(tmp_path, capsys):
    from onboard.app.reconstruct import main

    obs = tmp_path / "obs.csv"
    obs.write_text("observations\n")
    line = _refused(capsys, main, [str(obs), "-o", str(obs)])
    assert "names the input OBS.csv" in line
    assert obs.read_text() == "observations\n"


def test_track_video_refuses_an_output_on_its_video(tmp_path, capsys):
    from onboard.app.track_video import main

    vid = tmp_path / "clip.avi"
    vid.write_bytes(b"video bytes")
    assert "names the input INPUT" in _refused(capsys, main, [str(vid), "--out", str(vid)])
    assert vid.read_bytes() == b"video bytes"


@pytest.mark.parametrize("with_summary", [False, True])
def test_reconstruct_outputs_apart_from_the_input_still_pass_the_check(tmp_path, with_summary):
    assert (
        same_file_clash(
            [("-o", str(tmp_path / "o.csv")), ("--summary-json", str(tmp_path / "s.json"))][: 1 + with_summary],
            [("OBS.csv", str(tmp_path / "obs.csv"))],
        )
        is None
    )


@pytest.mark.parametrize("module", ["onboard.replay", "onboard.track_video"])
def test_a_usage_mistake_is_one_line_naming_the_command(module, capsys):
    import importlib

    main = importlib.import_module(module.replace("onboard.", "onboard.app.")).main
    with pytest.raises(SystemExit) as exc:
        main(["--no-such-option"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"python -m {module}: "), err
