"""``python -m onboard.track_video`` on inputs that are not quite what a benchmark promises: a frame folder whose
numbering has gaps, starts at 0, is not numeric or repeats a number; a video whose frame size changes, that was
cut short or damaged; an ``--out`` that would overwrite an input; frames smaller than the chain takes.  Each
input is a few tiny synthetic frames written here (OpenCV PNGs, PyAV videos); the command runs in process."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

import onboard.app.track_video as track_video
from onboard.app.track_video import EXIT_INPUT, EXIT_OK, main, open_frames

SIDE_PX = 32  # above the chain's 16 x 16 minimum, small enough to keep each test fast
LOGGERS = ("onboard.app.track_video", "onboard.io.frame_input")  # the command and its reader


def _noise(k: int, h_px: int = SIDE_PX, w_px: int = SIDE_PX) -> np.ndarray:
    """Frame k: noise about a grey sky (nothing for the chain to confirm; these tests are about the input)."""
    return np.random.default_rng(k).integers(40, 80, (h_px, w_px), dtype=np.uint8)


def _folder(folder: Path, names: list[str], side_px: int = SIDE_PX) -> Path:
    folder.mkdir()
    for k, name in enumerate(names):
        assert cv2.imwrite(str(folder / name), _noise(k, side_px, side_px))
    return folder


def _records(caplog, level: int) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name in LOGGERS and r.levelno == level]


def _frame_numbers_written(monkeypatch, tmp_path: Path, folder: Path) -> list[int]:
    """The MOT frame numbers main writes for ``folder``: one line per frame, whatever the chain confirms."""
    monkeypatch.setattr(track_video, "mot_rows", lambda k, upd, box_px=None, primary_only=False: [f"{k}\n"])
    out = tmp_path / "t.txt"
    assert main([str(folder), "--out", str(out)]) == EXIT_OK
    return [int(line) for line in out.read_text().splitlines()]


# --------------------------------------------------------------------------- folder numbering


def test_frame_numbers_come_from_the_names_and_a_gap_is_warned_once(tmp_path, monkeypatch, caplog):
    names = [f"{n:06d}.png" for n in (1, 2, 5, 6, 8)]  # 3, 4 and 7 missing
    seq = _folder(tmp_path / "seq", names)
    assert _frame_numbers_written(monkeypatch, tmp_path, seq) == [1, 2, 5, 6, 8]
    warned = _records(caplog, logging.WARNING)
    assert len(warned) == 1, warned
    assert warned[0].startswith(f"{seq}: 3 frames missing") and "the first gap 3 to 4 (before 000005.png)" in warned[0]


def test_a_numbering_without_gaps_says_nothing(tmp_path, monkeypatch, caplog):
    seq = _folder(tmp_path / "seq", [f"{n}.png" for n in (1, 2, 3)])
    assert _frame_numbers_written(monkeypatch, tmp_path, seq) == [1, 2, 3]
    assert _records(caplog, logging.WARNING) == [] and _records(caplog, logging.INFO) == []


def test_names_numbered_from_0_are_moved_up_by_one(tmp_path, monkeypatch, caplog):
    seq = _folder(tmp_path / "seq", ["000.png", "001.png", "003.png"])
    assert _frame_numbers_written(monkeypatch, tmp_path, seq) == [1, 2, 4]
    assert any("numbered from 0 (000.png)" in m for m in _records(caplog, logging.INFO))
    (warned,) = _records(caplog, logging.WARNING)
    assert "1 frame missing" in warned and "the first gap 2 (before 003.png)" in warned  # the names' numbers


def test_names_that_are_not_all_numbers_are_numbered_by_position_and_said_once(tmp_path, monkeypatch, caplog):
    seq = _folder(tmp_path / "seq", ["b.png", "a.png", "c.png"])
    assert _frame_numbers_written(monkeypatch, tmp_path, seq) == [1, 2, 3]
    assert [m for m in _records(caplog, logging.INFO) if "position" in m] == [
        f"{seq}: not every frame name is a number behind one prefix (a.png): MOT frames are numbered by sorted "
        "position from 1"
    ]


def test_names_with_a_prefix_are_numbered_by_their_number(tmp_path, monkeypatch, caplog):
    """ffmpeg's ``frame_%06d``, ``img0000001.jpg``: the number behind the common prefix is the frame's, so a
    missing file is a gap, not a shift of every later frame."""
    seq = _folder(tmp_path / "seq", ["frame_000001.png", "frame_000002.png", "frame_000004.png", "frame_000010.png"])
    assert _frame_numbers_written(monkeypatch, tmp_path, seq) == [1, 2, 4, 10]
    (warned,) = _records(caplog, logging.WARNING)
    assert "6 frames missing" in warned and "the first gap 3 (before frame_000004.png)" in warned


def test_a_stray_file_in_a_numbered_folder_is_warned_about(tmp_path, monkeypatch, caplog):
    seq = _folder(tmp_path / "seq", ["000001.png", "000002.png", "000003.png", "cover.png"])
    assert _frame_numbers_written(monkeypatch, tmp_path, seq) == [1, 2, 3, 4]
    (warned,) = _records(caplog, logging.WARNING)
    assert "(cover.png)" in warned and "by sorted position" in warned and "tracked as a frame" in warned


def test_names_numbered_behind_different_prefixes_are_numbered_by_position(tmp_path, monkeypatch, caplog):
    seq = _folder(tmp_path / "seq", ["a1.png", "a2.png", "b1.png"])
    assert _frame_numbers_written(monkeypatch, tmp_path, seq) == [1, 2, 3]
    (warned,) = _records(caplog, logging.WARNING)
    assert "(b1.png)" in warned


def test_two_files_of_one_number_are_refused_naming_both(tmp_path, capsys):
    seq = _folder(tmp_path / "seq", ["1.png", "0001.png", "2.png"])
    assert main([str(seq), "--out", str(tmp_path / "t.txt"), "--quiet"]) == EXIT_INPUT
    err = capsys.readouterr().err
    assert err.startswith(f"{seq / '1.png'}: frame number 1 again (0001.png has it)"), err
    assert len(err.splitlines()) == 1 and not (tmp_path / "t.txt").exists()


def test_frames_are_yielded_with_their_numbers_and_full_paths(tmp_path):
    seq = _folder(tmp_path / "seq", ["000002.png", "000004.png"])
    assert [(k, name) for k, name, _ in open_frames(str(seq)).frames] == [
        (2, str(seq / "000002.png")),
        (4, str(seq / "000004.png")),
    ]


def test_frames_smaller_than_the_chain_takes_are_refused_in_the_tools_words(tmp_path, capsys):
    seq = _folder(tmp_path / "seq", ["000001.png", "000002.png"], side_px=8)
    assert main([str(seq), "--out", str(tmp_path / "t.txt"), "--quiet"]) == EXIT_INPUT
    err = capsys.readouterr().err
    assert err.startswith(f"{seq / '000001.png'}: frame of 8 x 8 px: frames must be at least 16 x 16 px"), err


# --------------------------------------------------------------------------- nothing confirmed


@pytest.mark.parametrize("fps", [15.0, 30.0], ids=["3_s", "1.5_s"])
def test_a_long_input_with_nothing_confirmed_says_why_once_and_exits_0(tmp_path, caplog, fps):
    """45 frames of noise: at 15 frames/s (3 s, three confirmation windows) the empty output is warned about
    once, naming the likely causes; at 30 frames/s (1.5 s) it is too short to say.  Exit 0 either way."""
    seq = _folder(tmp_path / "seq", [f"{n:06d}.png" for n in range(1, 46)])
    out = tmp_path / "t.txt"
    assert main([str(seq), "--out", str(out), "--fps", str(fps), "--quiet"]) == EXIT_OK
    assert out.read_text() == ""
    warned = [m for m in _records(caplog, logging.WARNING) if "no object confirmed" in m]
    if fps == 15.0:
        (line,) = warned
        assert line.startswith(f"{seq}: no object confirmed over 45 frames (3.0 s at 15 frames/s)"), line
        assert "more than a few pixels" in line and "too dim" in line
    else:
        assert warned == []


# --------------------------------------------------------------------------- a MOT sequence's seqinfo.ini


def _mot_sequence(seq: Path, im_dir: str | None, frames_in: str) -> Path:
    """A MOT sequence folder: seqinfo.ini (at 12 frames/s, its imDir ``im_dir`` or none) and three frames in
    ``frames_in``."""
    seq.mkdir()
    _folder(seq / frames_in, [f"{n:06d}.png" for n in (1, 2, 3)])
    key = "" if im_dir is None else f"imDir={im_dir}\n"
    (seq / "seqinfo.ini").write_text(f"[Sequence]\nname={seq.name}\n{key}frameRate=12\nseqLength=3\nimExt=.png\n")
    return seq


@pytest.mark.parametrize(("im_dir", "frames_in"), [("images", "images"), (None, "img1"), ("img1", "img1")])
def test_the_frames_are_in_the_folder_seqinfo_names(tmp_path, im_dir, frames_in):
    seq = _mot_sequence(tmp_path / "MOT-01", im_dir, frames_in)
    src = open_frames(str(seq))
    assert src.path == seq / frames_in and src.fps == 12.0 and [p.name for p in src.files][0] == "000001.png"
    # the image folder given itself: its sequence's seqinfo.ini still gives the rate
    assert open_frames(str(seq / frames_in)).fps == 12.0


@pytest.mark.parametrize(
    ("im_dir", "why"),
    [
        ("../elsewhere", "not a folder inside the sequence folder"),
        ("/tmp", "not a folder inside the sequence folder"),
        ("pictures", "no such folder in"),
    ],
)
def test_an_imdir_outside_the_sequence_or_missing_is_one_line_naming_the_key(tmp_path, capsys, im_dir, why):
    seq = _mot_sequence(tmp_path / "MOT-02", im_dir, "img1")
    (tmp_path / "elsewhere").mkdir()
    assert main([str(seq), "--out", str(tmp_path / "t.txt"), "--quiet"]) == EXIT_INPUT
    err = capsys.readouterr().err
    assert err.startswith(f"{seq / 'seqinfo.ini'}: [Sequence] imDir = {im_dir!r}: {why}"), err
    assert len(err.splitlines()) == 1


# --------------------------------------------------------------------------- --out naming an input


@pytest.mark.parametrize("case", ["a_frame", "a_new_image", "the_video_of_a_sequence"])
def test_an_output_on_an_input_of_a_folder_is_refused(tmp_path, capsys, case):
    seq = _folder(tmp_path / "seq", ["000001.png", "000002.png"])
    before = (seq / "000001.png").read_bytes()
    if case == "the_video_of_a_sequence":  # an Anti-UAV folder: the video read is IR.mp4 inside it
        for p in list(seq.iterdir()):
            p.unlink()
        _write_video(seq / "IR.mp4", [_noise(k) for k in range(3)])
        before = (seq / "IR.mp4").read_bytes()
    out, said = {
        "a_frame": (seq / "000001.png", f"names the input {seq / '000001.png'}"),
        "a_new_image": (seq / "tracks.PNG", f"an image file in the input folder {seq}"),
        "the_video_of_a_sequence": (seq / "IR.mp4", f"names the input {seq / 'IR.mp4'}"),
    }[case]
    assert main([str(seq), "--out", str(out), "--quiet"]) == EXIT_INPUT
    err = capsys.readouterr().err
    assert err.startswith(f"--out {out}: {said}") and len(err.splitlines()) == 1, err
    kept = seq / ("IR.mp4" if case == "the_video_of_a_sequence" else "000001.png")
    assert kept.read_bytes() == before
    assert case != "a_new_image" or not out.exists()


@pytest.mark.parametrize(
    "relative, said",
    [
        ("seqinfo.ini", "the input's own seqinfo.ini"),
        ("img1/seqinfo.ini", "the input's own seqinfo.ini"),
        ("gt/gt.txt", "inside the input's ground truth folder"),
        ("img1/IR_label.json", "the input's own IR_label.json"),
    ],
)
def test_an_output_on_the_files_describing_the_sequence_is_refused(tmp_path, capsys, relative, said):
    """A MOT sequence (seqinfo.ini, gt/, frames in img1/) or an Anti-UAV folder's label file: files this tool or a
    scorer reads, which a run would have overwritten with its tracks."""
    seq = tmp_path / "seq"
    seq.mkdir()
    _folder(seq / "img1", ["000001.png", "000002.png"])
    (seq / "seqinfo.ini").write_text("[Sequence]\nimDir=img1\nframeRate=30\nseqLength=2\n")
    (seq / "gt").mkdir()
    (seq / "gt" / "gt.txt").write_text("1,1,1,1,6,6,1,1,1.0\n")
    out = seq / relative
    before = out.read_bytes() if out.exists() else None
    assert main([str(seq / "img1"), "--out", str(out), "--quiet"]) == EXIT_INPUT
    err = capsys.readouterr().err
    assert err.startswith(f"--out {out}: {said}") and len(err.splitlines()) == 1, err
    assert (out.read_bytes() if out.exists() else None) == before


def test_mono16_widens_an_8_bit_folder_as_ffmpeg_widens_an_8_bit_video(tmp_path):
    """Full scale to full scale (x 257) from a folder, as FFmpeg's gray16le does from a video of the same frames."""
    frames = [_noise(k) for k in range(3)]
    seq = tmp_path / "seq"
    seq.mkdir()
    for k, px in enumerate(frames):
        assert cv2.imwrite(str(seq / f"{k + 1:06d}.png"), px)
    px16 = next(open_frames(seq, "mono16").frames)[2]
    assert px16.dtype == np.uint16 and np.array_equal(px16, frames[0].astype(np.uint16) * 257)
    video = tmp_path / "v.mkv"
    av = pytest.importorskip("av")
    c = av.open(str(video), mode="w")
    s = c.add_stream("ffv1", rate=30)  # lossless: the decoded frames are the written ones
    s.height, s.width, s.pix_fmt = SIDE_PX, SIDE_PX, "gray"
    for px in frames:
        c.mux(s.encode(av.VideoFrame.from_ndarray(px, format="gray")))
    c.mux(s.encode(None))
    c.close()
    assert np.array_equal(next(open_frames(video, "mono16").frames)[2], px16)


def test_a_text_output_in_the_input_folder_is_allowed(tmp_path):
    seq = _folder(tmp_path / "seq", ["000001.png", "000002.png"])
    assert main([str(seq), "--out", str(seq / "tracks.txt"), "--quiet"]) == EXIT_OK


# --------------------------------------------------------------------------- videos


def _write_video(path: Path, frames: list[np.ndarray], options: dict[str, str] | None = None) -> Path:
    av = pytest.importorskip("av")
    c = av.open(str(path), mode="w")
    s = c.add_stream("libx264", rate=30)
    s.height, s.width = frames[0].shape
    s.pix_fmt = "yuv420p"
    s.options = {"preset": "ultrafast", **(options or {})}
    for px in frames:
        c.mux(s.encode(av.VideoFrame.from_ndarray(px, format="gray")))
    c.mux(s.encode(None))
    c.close()
    return path


def test_a_video_whose_frame_size_changes_is_refused_at_that_frame(tmp_path, capsys):
    """Two MPEG-TS streams back to back (a stream can change its size there), as a folder of two sizes is."""
    a = _write_video(tmp_path / "a.ts", [_noise(k) for k in range(3)])
    b = _write_video(tmp_path / "b.ts", [_noise(k, SIDE_PX, 48) for k in range(3)])
    ts = tmp_path / "ab.ts"
    ts.write_bytes(a.read_bytes() + b.read_bytes())
    out = tmp_path / "t.txt"
    assert main([str(ts), "--out", str(out), "--quiet"]) == EXIT_INPUT
    err = capsys.readouterr().err
    assert err == (
        f"{ts}: frame 4 is 48 x {SIDE_PX} px, the first is {SIDE_PX} x {SIDE_PX}: all frames must have one size; "
        f"{out} was not created\n"
    )


@pytest.mark.parametrize("cut", [False, True], ids=["intact", "cut_in_half"])
def test_a_video_cut_short_is_tracked_as_far_as_it_decodes_with_a_warning(tmp_path, caplog, capsys, cut):
    """Matroska declares no frame count, only its duration (20 frames at 30 frames/s here)."""
    mkv = _write_video(tmp_path / "v.mkv", [_noise(k) for k in range(20)])
    if cut:
        data = mkv.read_bytes()
        mkv.write_bytes(data[: len(data) // 2])
    assert main([str(mkv), "--out", str(tmp_path / "t.txt"), "--quiet"]) == EXIT_OK
    warned = _records(caplog, logging.WARNING)
    if not cut:
        assert warned == []
        return
    assert len(warned) == 1, warned
    decoded = int(capsys.readouterr().out.split(": ")[1].split(" frames")[0])
    assert 0 < decoded < 20
    assert warned[0].startswith(f"{mkv}: decoded {decoded} of about 20 frames its duration implies"), warned


def _mp4_with_its_middle_packet(tmp_path, damage):
    """A 12-frame mp4 (faststart) whose middle frame's packet bytes ``damage(packet_bytes)`` replaced."""
    av = pytest.importorskip("av")
    mp4 = _write_video(tmp_path / "v.mp4", [_noise(k, 64, 64) for k in range(12)], {"movflags": "faststart"})
    with av.open(str(mp4)) as c:
        packets = [p for p in c.demux(video=0) if p.size]
    victim = packets[len(packets) // 2]
    data = bytearray(mp4.read_bytes())
    data[victim.pos : victim.pos + victim.size] = damage(bytes(data[victim.pos : victim.pos + victim.size]))
    mp4.write_bytes(bytes(data))
    return mp4


def _flip_16_middle_bytes(packet: bytes) -> bytes:
    m = len(packet) // 2
    return packet[:m] + bytes(x ^ 0x5A for x in packet[m : m + 16]) + packet[m + 16 :]


def test_a_damaged_video_that_decodes_to_the_end_is_warned_about_once(tmp_path, caplog):
    """Bytes flipped inside one frame's slice data (away from the length prefixes, so the decoder can go on):
    FFmpeg conceals the damage and says so only in its log."""
    mp4 = _mp4_with_its_middle_packet(tmp_path, _flip_16_middle_bytes)
    assert main([str(mp4), "--out", str(tmp_path / "t.txt"), "--quiet"]) == EXIT_OK
    (warned,) = _records(caplog, logging.WARNING)
    assert warned.startswith(f"{mp4}: decoded 12 frames; ") and "decoder error" in warned, warned


def test_a_frame_the_decoder_cannot_decode_ends_the_video_there_its_frames_before_kept(tmp_path, caplog, capsys):
    """A packet overwritten whole (its NAL length prefix too): FFmpeg cannot conceal it and PyAV raises.  That ended
    the run in an error with nothing written, the frames before it tracked for nothing, where a file cut short at
    the same place is tracked as far as it decodes; the frames after it are not read, so none takes an earlier
    one's number."""
    mp4 = _mp4_with_its_middle_packet(tmp_path, lambda packet: bytes(len(packet)))  # its length prefix too
    out = tmp_path / "t.txt"
    assert main([str(mp4), "--out", str(out), "--quiet"]) == EXIT_OK
    assert out.is_file()
    assert capsys.readouterr().out.startswith(f"{mp4}: 6 frames of 64 x 64 mono8")
    (warned,) = _records(caplog, logging.WARNING)
    assert warned.startswith(f"{mp4}: decoded 6 of 12 frames declared; frame 7 cannot be decoded ("), warned
    assert "the frames after it are not read" in warned


def test_a_video_whose_first_frame_cannot_be_decoded_is_refused(tmp_path, capsys):
    av = pytest.importorskip("av")
    mp4 = _write_video(tmp_path / "v.mp4", [_noise(k, 64, 64) for k in range(4)], {"movflags": "faststart"})
    with av.open(str(mp4)) as c:
        first = next(p for p in c.demux(video=0) if p.size)
    data = bytearray(mp4.read_bytes())
    data[first.pos : first.pos + first.size] = bytes(first.size)
    mp4.write_bytes(bytes(data))
    out = tmp_path / "t.txt"
    assert main([str(mp4), "--out", str(out), "--quiet"]) == EXIT_INPUT
    assert capsys.readouterr().err.startswith(f"{mp4}: frame 1 cannot be decoded: ")
    assert not out.exists()


def test_names_that_are_times_are_numbered_by_position_and_said(tmp_path, monkeypatch, caplog):
    """Frames named by a clock (ms since an epoch: a step of ~33 a frame) are not frame numbers: taken as such, every
    frame was a 30-frame gap to the tracker and an Anti-UAV result was padded to 1.7e12 entries."""
    seq = _folder(tmp_path / "seq", [f"{1_700_000_000_000 + 33 * k}.png" for k in range(4)])
    assert _frame_numbers_written(monkeypatch, tmp_path, seq) == [1, 2, 3, 4]
    (warned,) = _records(caplog, logging.WARNING)
    assert "step by a median 33" in warned and "numbered by sorted position" in warned


def test_names_that_are_times_of_a_fast_camera_are_numbered_by_position_and_said(tmp_path, monkeypatch, caplog):
    """Milliseconds at 60 frames/s step by 17, under the step test's 30: the size of the numbers against the frame
    count says they are times (taken as frame numbers, 2 million missing frames were warned about and an Anti-UAV
    result padded to them)."""
    seq = _folder(tmp_path / "seq", [f"{2_000_000 + 17 * k}.png" for k in range(4)])
    assert _frame_numbers_written(monkeypatch, tmp_path, seq) == [1, 2, 3, 4]
    (warned,) = _records(caplog, logging.WARNING)
    assert "reach 2000051 for 4 frames" in warned and "numbered by sorted position" in warned


def test_a_subsequence_cut_from_a_long_recording_keeps_its_numbers(tmp_path, monkeypatch):
    seq = _folder(tmp_path / "seq", [f"{n:06d}.png" for n in (5000, 5001, 5002)])
    assert _frame_numbers_written(monkeypatch, tmp_path, seq) == [5000, 5001, 5002]


def test_a_subsampled_numbering_keeps_its_numbers(tmp_path, monkeypatch):
    seq = _folder(tmp_path / "seq", [f"{n:06d}.png" for n in (1, 11, 21, 31)])  # every 10th frame kept
    assert _frame_numbers_written(monkeypatch, tmp_path, seq) == [1, 11, 21, 31]


# --------------------------------------------------------------------------- Anti-UAV's label file


def _labels(path: Path, frames: int) -> Path:
    """Anti-UAV's label file (``exist``, ``gt_rect``, one entry a frame) for ``frames`` frames."""
    path.write_text(json.dumps({"exist": [1] * frames, "gt_rect": [[10, 10, 4, 4]] * frames}))
    return path


@pytest.mark.parametrize("labelled", [8, 5, 3])
def test_an_anti_uav_res_is_padded_to_its_label_files_frames(tmp_path, caplog, labelled):
    """Anti-UAV410's layout (frames and IR_label.json in one folder): the toolkit's scorer zips res with
    ``exist`` and ``gt_rect``, so a res shorter than the labels (the last frames missing from the folder) would
    leave their frames unscored: it is padded with ``[]`` (absent); a longer one is warned about."""
    seq = _folder(tmp_path / "02_6319", [f"{n:06d}.png" for n in range(1, 6)])
    label = _labels(seq / "IR_label.json", labelled)
    out = tmp_path / "02_6319.txt"
    assert main([str(seq), "--out", str(out), "--format", "anti-uav"]) == EXIT_OK
    res = json.loads(out.read_text())["res"]
    assert res == [[]] * max(labelled, 5)  # noise: nothing confirmed
    warned = _records(caplog, logging.WARNING)
    if labelled < 5:
        (line,) = warned
        assert line.startswith(f"{out}: res has 5 entries, {label} labels 3 frames"), line
    else:
        assert warned == []
        padded = [m for m in _records(caplog, logging.INFO) if "padded" in m]
        assert padded == (
            [f"{out}: res padded with 3 empty entries to the 8 frames {label} labels"] if labelled > 5 else []
        )


@pytest.mark.parametrize(("video", "label"), [("IR.mp4", "IR_label.json"), ("infrared.mp4", "infrared.json")])
def test_a_video_s_res_is_padded_to_the_label_file_beside_it(tmp_path, video, label):
    seq = tmp_path / "20190925_101846_1_1"
    seq.mkdir()
    _write_video(seq / video, [_noise(k) for k in range(4)])
    _labels(seq / label, 7)
    for given in (seq, seq / video):  # the sequence folder or its video
        out = tmp_path / "res.txt"
        assert main([str(given), "--out", str(out), "--format", "anti-uav", "--quiet"]) == EXIT_OK
        assert json.loads(out.read_text())["res"] == [[]] * 7


def test_a_label_file_that_cannot_be_read_is_warned_about_and_res_left_as_it_is(tmp_path, caplog):
    seq = _folder(tmp_path / "seq", [f"{n:06d}.png" for n in range(1, 4)])
    (seq / "IR_label.json").write_text("{not json")
    out = tmp_path / "res.txt"
    assert main([str(seq), "--out", str(out), "--format", "anti-uav", "--quiet"]) == EXIT_OK
    assert json.loads(out.read_text())["res"] == [[]] * 3
    (line,) = _records(caplog, logging.WARNING)
    assert line.startswith(f"{seq / 'IR_label.json'}: not read (") and "res is not fitted" in line


def test_a_box_that_is_not_finite_is_not_written():
    """TrackEval refuses a whole sequence over one non-finite value: such an object is left out of its frame."""
    from types import SimpleNamespace

    good = SimpleNamespace(object_id=1, bbox=(10, 20, 3, 3), u_px=11.5, v_px=21.5, score=4.0)
    bad = SimpleNamespace(object_id=2, bbox=(10, 20, 3, 3), u_px=math.nan, v_px=21.5, score=4.0)
    upd = SimpleNamespace(confirmed=[good, bad], primary_id=1)
    assert track_video.mot_rows(7, upd) == [
        "7,1,11.000,21.000,3.000,3.000,4.000,-1,-1,-1\n",
        "7,2,11.000,21.000,3.000,3.000,4.000,-1,-1,-1\n",
    ]
    assert track_video.mot_rows(7, upd, box_px=6.0) == ["7,1,9.500,19.500,6.000,6.000,4.000,-1,-1,-1\n"]


def test_a_frame_name_with_a_digit_int_cannot_read_sorts_without_an_error():
    """``_natural_key`` compares digit runs by value: a run of digits ``int`` cannot read (a superscript two between
    two numbers, which str.isdigit holds) raised ValueError before any frame was read."""
    from onboard.io.frame_input import _natural_key

    assert sorted(["1\u00b22.png", "10.png", "2.png"], key=_natural_key) == ["1\u00b22.png", "2.png", "10.png"]
