"""``python -m onboard.track_video``: synthetic thermal sequences with warm points moving on a known path -- a
folder of 16-bit PNG frames, a MOT sequence folder (img1/, 8-bit), an mp4 written by PyAV -- through the real
command; the MOT lines read back: one id per object for the whole sequence, distinct ids, centres where the
points were drawn, frames numbered from 1, nothing else confirmed.  Bad inputs: one line naming the file, exit 2.
The output is replaced only when the run ends (or is interrupted): a bad frame or a full disk leaves it as it was."""

from __future__ import annotations

import errno
import logging
import math
import os
import stat
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

import onboard.app.track_video as track_video
from onboard.app.track_video import EXIT_INPUT, main, open_frames
from tests.process_helpers import run_module

W_PX, H_PX = 192, 144
N_FRAMES = 45
SETTLE_FRAMES = 14  # the chain confirms after 12 of 15 frames (ObjectParams): earlier frames unchecked
CENTRE_TOL_PX = 0.5  # lossless frames: a 0.7 px Gaussian on noise, its centroid
CENTRE_TOL_MP4_PX = 1.0  # H.264 at crf 12
MIN_FRAMES_FOUND = 0.9  # of the frames after SETTLE_FRAMES, per object
CLI_TIMEOUT_S = 120.0


def _truth(k: int) -> list[tuple[float, float]]:
    """The centres (u, v) of three objects on frame k (pixel i spans [i, i + 1)): two crossing paths far apart
    and one slow."""
    return [
        (30.3 + 1.2 * k, 40.6 + 0.3 * k),
        (160.7 - 1.1 * k, 100.2 - 0.2 * k),
        (96.5 + 0.2 * k, 20.4 + 0.1 * k),
    ]


def _frame(k: int, sky: float, noise: float, amp: float, dtype) -> np.ndarray:
    rng = np.random.default_rng(k)
    yy, xx = np.mgrid[0:H_PX, 0:W_PX].astype(np.float64)
    img = sky + 0.05 * sky * yy / H_PX + rng.normal(0.0, noise, (H_PX, W_PX))
    for u, v in _truth(k):
        img += amp * np.exp(-((xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2) / (2 * 0.7**2))
    return np.clip(np.round(img), 0, np.iinfo(dtype).max).astype(dtype)


def _mono16(k: int) -> np.ndarray:
    return _frame(k, 3000.0, 8.0, 400.0, np.uint16)


def _mono8(k: int) -> np.ndarray:
    return _frame(k, 60.0, 0.7, 45.0, np.uint8)


def _run(*args: str) -> subprocess.CompletedProcess:
    return run_module(
        "onboard.track_video",
        *args,
        timeout_s=CLI_TIMEOUT_S,
        env={"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"},
    )


def _read_mot(path: Path) -> list[tuple[int, int, float, float, float, float, float]]:
    rows = []
    for line in path.read_text().splitlines():
        f = line.split(",")
        assert len(f) == 10 and f[7:] == ["-1", "-1", "-1"]
        rows.append((int(f[0]), int(f[1]), *map(float, f[2:7])))
    return rows


def _check_tracks(rows, tol_px: float) -> None:
    """Each truth object followed by one id of its own on >= MIN_FRAMES_FOUND of the settled frames; every line
    of a settled frame on a truth object (no false confirmed track)."""
    assert rows and min(r[0] for r in rows) >= 1 and max(r[0] for r in rows) <= N_FRAMES
    ids_of: list[set[int]] = [set() for _ in _truth(0)]
    found = [0] * len(ids_of)
    for frame, oid, x, y, w, h, conf in rows:
        k = frame - 1  # MOT frames from 1
        u, v = x - 1 + w / 2, y - 1 + h / 2  # MOT's 1-based box -> the centre in the chain's pixels
        d = [math.hypot(u - tu, v - tv) for tu, tv in _truth(k)]
        j = int(np.argmin(d))
        assert d[j] <= tol_px, (frame, oid, u, v)
        assert conf > 0
        if k >= SETTLE_FRAMES:
            ids_of[j].add(oid)
            found[j] += 1
    settled = N_FRAMES - SETTLE_FRAMES
    assert all(n >= MIN_FRAMES_FOUND * settled for n in found), found
    assert all(len(s) == 1 for s in ids_of), ids_of
    assert len(set.union(*ids_of)) == len(ids_of)  # distinct ids


def test_a_folder_of_16_bit_pngs_through_the_command(tmp_path):
    seq = tmp_path / "seq16"
    seq.mkdir()
    for k in range(N_FRAMES):
        assert cv2.imwrite(str(seq / f"{k + 1}.png"), _mono16(k))  # unpadded names: sorted by value
    out = tmp_path / "out" / "tracks.txt"
    res = _run(str(seq), "--out", str(out))
    assert res.returncode == 0, res.stderr
    assert f"{N_FRAMES} frames of {W_PX} x {H_PX} mono16 (folder" in res.stdout
    _check_tracks(_read_mot(out), CENTRE_TOL_PX)


def test_an_mp4_through_the_command_and_a_mot_sequence_folder(tmp_path):
    av = pytest.importorskip("av")
    mp4 = tmp_path / "ir.mp4"
    c = av.open(str(mp4), mode="w")
    s = c.add_stream("libx264", rate=25)
    s.width, s.height, s.pix_fmt = W_PX, H_PX, "yuv420p"
    s.options = {"crf": "12", "preset": "ultrafast"}
    for k in range(N_FRAMES):
        frame = av.VideoFrame.from_ndarray(_mono8(k), format="gray")
        c.mux(s.encode(frame))
    c.mux(s.encode(None))
    c.close()
    out = tmp_path / "mp4.txt"
    res = _run(str(mp4), "--out", str(out), "--box-px", "6")
    assert res.returncode == 0, res.stderr
    assert "mono8 (video, 25 frames/s)" in res.stdout
    rows = _read_mot(out)
    assert all(r[4] == 6.0 and r[5] == 6.0 for r in rows)
    _check_tracks(rows, CENTRE_TOL_MP4_PX)
    # a MOT sequence folder: its frames in img1/ (8-bit), in process: the same chain
    mot = tmp_path / "MOT-01"
    (mot / "img1").mkdir(parents=True)
    for k in range(N_FRAMES):
        cv2.imwrite(str(mot / "img1" / f"{k + 1:06d}.png"), _mono8(k))
    out2 = tmp_path / "mot.txt"
    assert main([str(mot), "--out", str(out2), "--quiet"]) == 0
    _check_tracks(_read_mot(out2), CENTRE_TOL_PX)
    prim = tmp_path / "primary.txt"
    assert main([str(mot), "--out", str(prim), "--quiet", "--primary-only"]) == 0
    assert len({r[1] for r in _read_mot(prim) if r[0] > SETTLE_FRAMES}) == 1  # one target


def test_encoding_is_taken_from_the_pngs_or_converted(tmp_path):
    seq = tmp_path / "s"
    seq.mkdir()
    cv2.imwrite(str(seq / "a.png"), _mono16(0))
    src = open_frames(str(seq))
    number, name, px = next(src.frames)
    assert number == 1 and name == str(seq / "a.png")
    assert px.dtype == np.uint16 and np.array_equal(px, _mono16(0))
    _, _, px8 = next(open_frames(str(seq), "mono8").frames)
    assert px8.dtype == np.uint8 and np.array_equal(px8, (_mono16(0) >> 8).astype(np.uint8))
    assert src.fps == 30.0 and open_frames(str(seq), fps=9.0).fps == 9.0


@pytest.mark.parametrize("case", ["missing", "none_decodes", "mixed_size", "mixed_depth", "empty"])
def test_bad_input_is_one_line_naming_the_file_and_exit_2(tmp_path, capsys, case):
    seq = tmp_path / "seq"
    seq.mkdir()
    for k in range(3):
        cv2.imwrite(str(seq / f"{k:03d}.png"), _mono8(k))
    bad = seq / "001.png"
    if case == "none_decodes":
        for p in seq.iterdir():
            p.write_bytes(b"\x89PNG\r\n\x1a\n not really")
    elif case == "mixed_size":
        cv2.imwrite(str(bad), _mono8(1)[:-8])
    elif case == "mixed_depth":
        cv2.imwrite(str(bad), _mono16(1))
    elif case == "empty":
        for p in seq.iterdir():
            p.unlink()
    target = tmp_path / "nowhere" if case == "missing" else seq
    code = main([str(target), "--out", str(tmp_path / "t.txt"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == EXIT_INPUT and len(err.splitlines()) == 1
    named = {"missing": str(target), "empty": str(seq), "none_decodes": f"{seq}: none of its 3 frame files"}
    assert err.startswith(named.get(case, str(bad))), err


def test_a_corrupt_png_is_skipped_as_a_gap_in_one_warning_with_the_decoders_words(tmp_path, capfd, caplog):
    """libpng prints its error on file descriptor 2 itself, past ``sys.stderr`` (capsys does not see it): the
    decoder's words go into the tool's one warning instead of a line of their own before it.  The frame is skipped,
    its number a gap (one bad file among thousands ended the whole run in an error, nothing written), and the
    summary counts it."""
    seq = tmp_path / "seq"
    seq.mkdir()
    for k in range(8):
        cv2.imwrite(str(seq / f"{k:03d}.png"), _mono8(k))
    for name in ("001.png", "005.png"):
        data = bytearray((seq / name).read_bytes())
        idat = data.index(b"IDAT") + 4  # the compressed pixels: a valid header, then a broken zlib stream
        data[idat + 8 : idat + 24] = bytes(range(16))
        (seq / name).write_bytes(bytes(data))
    out = tmp_path / "t.txt"
    code = main([str(seq), "--out", str(out), "--quiet"])
    said = capfd.readouterr()
    assert code == 0 and said.err == "", said.err  # libpng's own line too went into the warning
    (warned,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warned.startswith(f"{seq / '001.png'}: cannot read this frame") and "libpng" in warned, warned
    assert warned.endswith("skipped, frame number 2 left as a gap (the summary counts any more)"), warned
    assert "6 frames of" in said.out and "2 unreadable skipped, frames 2, 6;" in said.out, said.out
    src = open_frames(str(seq))
    assert [n for n, _, _ in src.frames] == [1, 3, 4, 5, 7, 8] and [n for n, _ in src.unreadable] == [2, 6]


# --------------------------------------------------------------------------- the output: replaced only on success


def _small_seq(folder: Path, n: int = 3) -> Path:
    folder.mkdir()
    for k in range(n):
        cv2.imwrite(str(folder / f"{k:03d}.png"), _mono8(k))
    return folder


def _temporary_files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


class _FullDisk:
    """The temporary output's file with ``writelines`` or ``close`` failing as on a full disk."""

    def __init__(self, f, fail: str) -> None:
        self.f, self.fail = f, fail

    def _full(self) -> OSError:
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def writelines(self, rows) -> None:
        if self.fail == "write":
            raise self._full()
        self.f.writelines(rows)

    def close(self) -> None:
        self.f.close()
        if self.fail == "close":
            raise self._full()


@pytest.mark.parametrize("fail", ["write", "close"])
def test_a_write_error_is_one_line_and_leaves_the_output_as_it_was(tmp_path, capsys, monkeypatch, fail):
    seq = _small_seq(tmp_path / "seq")
    out = tmp_path / "t.txt"
    out.write_text("previous\n")
    init = track_video._Replacement.__init__

    def full_disk_init(self, path):
        init(self, path)
        self.file = _FullDisk(self.file, fail)

    monkeypatch.setattr(track_video._Replacement, "__init__", full_disk_init)
    code = main([str(seq), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    done = 0 if fail == "write" else 3  # the first frame's write fails; the close after the last frame
    assert code == EXIT_INPUT
    assert err == f"{out}: cannot write: No space left on device after {done} frames; {out} is as it was\n"
    assert out.read_text() == "previous\n" and _temporary_files(tmp_path) == []


@pytest.mark.parametrize("existed", [True, False], ids=["existing", "new"])
def test_a_bad_frame_mid_input_leaves_the_output_as_it_was(tmp_path, capsys, existed):
    seq = _small_seq(tmp_path / "seq")
    bad = seq / "003.png"
    cv2.imwrite(str(bad), _mono8(3)[:-8])  # after three good frames, one of another size: refused
    out = tmp_path / "t.txt"
    if existed:
        out.write_text("previous\n")
    code = main([str(seq), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    kept = f"{out} is as it was" if existed else f"{out} was not created"
    assert code == EXIT_INPUT and err.startswith(f"{bad}: frame of") and err.endswith(f"; {kept}\n"), err
    assert (out.read_text() == "previous\n") if existed else not out.exists()
    assert _temporary_files(tmp_path) == []


@pytest.mark.parametrize("after", [0, 2], ids=["before_a_frame", "after_two_frames"])
def test_ctrl_c_keeps_the_tracks_of_the_frames_done(tmp_path, capsys, monkeypatch, after):
    """The documented Ctrl-C path: the frames done are renamed into place; with none done the previous output
    stays."""
    seq = _small_seq(tmp_path / "seq")
    out = tmp_path / "t.txt"
    out.write_text("previous\n")
    real = track_video.track_frames

    def interrupted(frames, fps, *rest):
        for k, item in enumerate(real(frames, fps, *rest)):
            if k == after:
                raise KeyboardInterrupt
            yield item

    monkeypatch.setattr(track_video, "track_frames", interrupted)
    code = main([str(seq), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == track_video.EXIT_INTERRUPTED and len(err.splitlines()) == 1
    if after:
        assert err == f"interrupted: {after} frames tracked; {out} holds their tracks\n"
        assert out.read_text() == ""  # two frames: nothing confirmed yet, and the previous lines gone
    else:
        assert err.startswith("interrupted before the first frame") and err.endswith(f"{out} is as it was\n")
        assert out.read_text() == "previous\n"
    assert _temporary_files(tmp_path) == []


@pytest.mark.parametrize("umask", [0o022, 0o027], ids=["umask022", "umask027"])
def test_the_output_gets_the_permissions_of_a_new_file(tmp_path, umask):
    seq = _small_seq(tmp_path / "seq")
    out = tmp_path / "t.txt"
    old = os.umask(umask)
    try:
        assert main([str(seq), "--out", str(out), "--quiet"]) == 0
    finally:
        os.umask(old)
    assert stat.S_IMODE(out.stat().st_mode) == 0o666 & ~umask


@pytest.mark.parametrize(
    "option, value, expected",
    [
        ("--fps", "inf", "--fps: expected a finite rate > 0, got inf"),
        ("--fps", "nan", "--fps: expected a finite rate > 0, got nan"),
        ("--box-px", "inf", "--box-px: expected a finite side > 0, got inf"),
        ("--box-px", "0", "--box-px: expected a finite side > 0, got 0.0"),
    ],
)
def test_rates_and_sides_must_be_finite_and_positive(tmp_path, capsys, option, value, expected):
    seq = _small_seq(tmp_path / "seq", n=1)
    out = tmp_path / "t.txt"
    assert main([str(seq), "--out", str(out), "--quiet", option, value]) == EXIT_INPUT
    assert capsys.readouterr().err == expected + "\n"
    assert not out.exists()


@pytest.mark.parametrize("case", ["file_as_folder", "file_as_grandparent", "folder", "pipe"])
def test_an_output_path_that_cannot_be_a_file_is_one_line(tmp_path, capsys, case):
    seq = _small_seq(tmp_path / "seq", n=1)
    afile = tmp_path / "afile"
    afile.write_text("x\n")
    if case == "pipe":
        os.mkfifo(tmp_path / "pipe")
    out, reason = {
        "file_as_folder": (afile / "t.txt", f"{afile} is not a folder"),
        "file_as_grandparent": (afile / "sub" / "t.txt", f"{afile} is not a folder"),
        "folder": (seq, "it is a folder: give the path of a file"),
        "pipe": (tmp_path / "pipe", "it is a pipe: give the path of a file"),
    }[case]
    assert main([str(seq), "--out", str(out), "--quiet"]) == EXIT_INPUT
    assert capsys.readouterr().err == f"{out}: cannot write: {reason}\n"
    assert afile.read_text() == "x\n" and _temporary_files(tmp_path) == []


def test_a_file_that_is_not_a_video_says_why_once(tmp_path, capsys):
    pytest.importorskip("av")
    fake = tmp_path / "fake.mp4"
    fake.write_text("not a video\n")
    assert main([str(fake), "--out", str(tmp_path / "t.txt"), "--quiet"]) == EXIT_INPUT
    err = capsys.readouterr().err
    assert err == f"{fake}: not a video FFmpeg reads: Invalid data found when processing input\n", err


def _converted_frame(k: int, layout: str) -> np.ndarray:
    """Frame k in BGR (``colour``) or BGRA (``colour+alpha``, ``grey+alpha``: equal colour planes) as OpenCV
    writes and reads them."""
    px = np.repeat(_mono8(k)[:, :, None], 3 if layout == "colour" else 4, axis=2)
    if layout != "grey+alpha":
        px[:, :, 1] //= 2  # green differs from blue and red: a colour frame
    if layout != "colour":
        px[:, :, 3] = 255
    return px


@pytest.mark.parametrize("layout", ["colour", "colour+alpha", "grey+alpha"])
def test_frames_turned_to_grey_are_said_in_the_summary(tmp_path, capsys, layout):
    seq = tmp_path / "seq"
    seq.mkdir()
    for k in range(3):
        assert cv2.imwrite(str(seq / f"{k}.png"), _converted_frame(k, layout))
    assert main([str(seq), "--out", str(tmp_path / "t.txt"), "--quiet"]) == 0
    assert f"3 frames of {W_PX} x {H_PX} mono8 (from {layout}; folder, 30 frames/s)" in capsys.readouterr().out


def test_a_grey_and_alpha_png_is_said_to_be_grey_and_alpha(tmp_path, capsys):
    """A PNG of colour type 4 (grey with alpha), which OpenCV hands over as BGRA with equal colour planes."""
    image = pytest.importorskip("PIL.Image")
    seq = tmp_path / "seq"
    seq.mkdir()
    for k in range(3):
        image.fromarray(np.stack([_mono8(k), np.full((H_PX, W_PX), 255, np.uint8)], axis=2), "LA").save(
            seq / f"{k}.png"
        )
    assert main([str(seq), "--out", str(tmp_path / "t.txt"), "--quiet"]) == 0
    assert "mono8 (from grey+alpha; folder" in capsys.readouterr().out


def test_grey_frames_are_not_said_to_be_converted(tmp_path, capsys):
    seq = _small_seq(tmp_path / "seq")
    assert main([str(seq), "--out", str(tmp_path / "t.txt"), "--quiet"]) == 0
    assert "mono8 (folder, 30 frames/s)" in capsys.readouterr().out


def test_a_folder_that_cannot_be_listed_is_one_line(tmp_path, monkeypatch, capsys):
    from pathlib import Path

    from onboard.app import track_video

    folder = tmp_path / "frames"
    folder.mkdir()

    def refuse(self):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(Path, "iterdir", refuse)
    assert track_video.main([str(folder), "--out", str(tmp_path / "t.txt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"{folder}: cannot list the folder: Permission denied"]


def _mot_folder(folder: Path, skip: range = range(0)) -> Path:
    (folder / "img1").mkdir(parents=True)
    for k in range(N_FRAMES):
        if k + 1 not in skip:
            cv2.imwrite(str(folder / "img1" / f"{k + 1:06d}.png"), _mono8(k))
    return folder


def _ids_by_object(rows, tol_px: float = CENTRE_TOL_PX) -> list[set[int]]:
    """The ids matched to each truth object on the settled frames."""
    ids_of: list[set[int]] = [set() for _ in _truth(0)]
    for frame, oid, x, y, w, h, _ in rows:
        if frame - 1 >= SETTLE_FRAMES:
            u, v = x - 1 + w / 2, y - 1 + h / 2
            d = [math.hypot(u - tu, v - tv) for tu, tv in _truth(frame - 1)]
            assert min(d) <= tol_px, (frame, oid, u, v)
            ids_of[int(np.argmin(d))].add(oid)
    return ids_of


def test_a_gap_in_the_numbering_is_time_the_tracks_are_predicted_over(tmp_path, caplog):
    """Ten frames missing from a MOT folder: each object keeps its one id across the gap (its motion carried over
    the frames' time), and the frames after it keep the names' numbers."""
    seq = _mot_folder(tmp_path / "MOT-02", skip=range(20, 30))
    out = tmp_path / "t.txt"
    assert main([str(seq), "--out", str(out), "--quiet"]) == 0
    rows = _read_mot(out)
    assert not {r[0] for r in rows} & set(range(20, 30)) and max(r[0] for r in rows) == N_FRAMES
    ids_of = _ids_by_object(rows)
    assert all(len(ids) == 1 for ids in ids_of), ids_of
    assert any(r[0] > 30 for r in rows) and len(set.union(*ids_of)) == 3


def test_anti_uav_format_is_the_toolkits_json_one_entry_a_frame(tmp_path):
    """``--format anti-uav``: ``{"res": [...]}`` with one entry per frame from 1 to the last (a frame missing from
    the numbering an empty entry), the primary's 0-based ``[x, y, w, h]`` or ``[]``, as the Anti-UAV toolkit's
    ``eval`` reads them (``len(pred) == 4`` a box, ``len(pred) in (0, 1)`` "absent")."""
    import json

    seq = _mot_folder(tmp_path / "MOT-03", skip=range(40, 41))
    out = tmp_path / "res.json"
    args = ["--quiet", "--format", "anti-uav", "--box-px", "6", "--primary-within-px", "200"]  # anywhere in frame
    assert main([str(seq), "--out", str(out), *args]) == 0
    res = json.loads(out.read_text())["res"]
    assert len(res) == N_FRAMES and res[39] == [] and all(len(b) in (0, 4) for b in res)
    boxed = [(k, b) for k, b in enumerate(res) if b]
    assert boxed and all(k >= SETTLE_FRAMES - 4 for k, _ in boxed)  # none before the chain confirms
    for k, (x, y, w, h) in boxed:
        assert w == h == 6.0
        u, v = x + w / 2, y + h / 2  # 0-based: the chain's own pixels
        assert min(math.hypot(u - tu, v - tv) for tu, tv in _truth(k)) <= CENTRE_TOL_PX
    assert sum(map(bool, res)) >= 0.8 * (N_FRAMES - SETTLE_FRAMES)


def test_a_primary_that_never_comes_near_the_centre_is_warned_not_silent(tmp_path, capsys, caplog):
    seq = _mot_folder(tmp_path / "MOT-04")
    out = tmp_path / "t.txt"
    assert main([str(seq), "--out", str(out), "--quiet", "--primary-only", "--primary-within-px", "1"]) == 0
    assert out.read_text() == ""
    (warned,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert "objects were confirmed but none was the primary" in warned and "within 1 px of the centre" in warned
    assert "3 object ids confirmed, 0 written, 0 lines" in capsys.readouterr().out
    wide = tmp_path / "wide.txt"
    assert main([str(seq), "--out", str(wide), "--quiet", "--primary-only", "--primary-within-px", "200"]) == 0
    assert len({r[1] for r in _read_mot(wide) if r[0] > SETTLE_FRAMES}) == 1


def test_a_mot_sequences_seqinfo_gives_the_rate_and_its_length_is_checked(tmp_path, caplog):
    (tmp_path / "MOT-05").mkdir()
    seq = _small_seq(tmp_path / "MOT-05" / "img1", n=4).parent
    (seq / "seqinfo.ini").write_text("[Sequence]\nname=MOT-05\nimDir=img1\nframeRate=14\nseqLength=5\nimExt=.png\n")
    assert open_frames(str(seq)).fps == 14.0 and open_frames(str(seq / "img1")).fps == 14.0
    assert open_frames(str(seq), fps=9.0).fps == 9.0  # --fps wins
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert warned and all("seqLength is 5, the folder holds 4 frames numbered up to 4" in m for m in warned)
    (seq / "seqinfo.ini").write_text("[Sequence]\nframeRate=fast\n")
    caplog.clear()
    assert open_frames(str(seq)).fps == 30.0
    assert any("frameRate = 'fast' is not a number > 0" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("fmt", ["mot", "anti-uav"])
def test_sigterm_ends_the_run_as_ctrl_c_does(tmp_path, capsys, monkeypatch, caplog, fmt):
    """A job's time limit or ``timeout`` sends SIGTERM: the frames done are kept (an Anti-UAV result with their
    entries), no temporary file is left, and the handler the caller had is back afterwards."""
    import signal

    seq = _small_seq(tmp_path / "seq", n=5)
    out = tmp_path / "t.txt"
    real = track_video.track_frames

    def terminated(frames, fps, *rest):
        for k, item in enumerate(real(frames, fps, *rest)):
            if k == 2:
                os.kill(os.getpid(), signal.SIGTERM)
            yield item

    monkeypatch.setattr(track_video, "track_frames", terminated)
    before = signal.getsignal(signal.SIGTERM)
    assert main([str(seq), "--out", str(out), "--quiet", "--format", fmt]) == track_video.EXIT_INTERRUPTED
    assert capsys.readouterr().err == f"interrupted: 2 frames tracked; {out} holds their tracks\n"
    assert out.exists() and _temporary_files(tmp_path) == []
    if fmt == "anti-uav":
        import json

        assert json.loads(out.read_text()) == {"res": [[], []]}  # nothing confirmed in two frames
        # a scorer pairs res with the labels in order: said, since it would score that prefix alone
        assert any("the first 2 frames' boxes only" in r.getMessage() for r in caplog.records)
    assert signal.getsignal(signal.SIGTERM) == before
