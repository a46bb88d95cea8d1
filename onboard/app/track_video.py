"""``python -m onboard.track_video``: the objects image chain over anyone's video, MOT-format tracks out.

    python -m onboard.track_video INPUT --out tracks.txt [--encoding auto|mono8|mono16] [--fps HZ]
                                  [--box-px N] [--primary-only] [--primary-within-px R]
                                  [--format mot|anti-uav] [--quiet]

``INPUT`` is one of:

* a video file (anything FFmpeg decodes: mp4, avi, mkv ...; read with PyAV), its luma as the frame (mono16 when
  the stream has more than 8 bits per sample, e.g. ``gray16le`` or ``yuv420p10le``);
* a folder of frames: PNG (8- or 16-bit), TIFF, JPEG or BMP files, sorted by name (numbers in names by value:
  ``2.png`` before ``10.png``), read with OpenCV as stored (``IMREAD_UNCHANGED``: a 16-bit PNG stays 16-bit;
  colour frames, and grey frames with an alpha channel, are turned to grey, which the summary line says);
* a sequence folder of a public tracking benchmark: MOT's (its ``seqinfo.ini``, whose ``imDir`` names the frames'
  folder, ``img1/`` when it names none -- an ``imDir`` outside the sequence folder or missing is refused --, whose
  ``frameRate`` is the rate unless ``--fps`` says, and whose ``seqLength`` is checked against the frames; its image
  folder given itself, the ``seqinfo.ini`` above it is read alike), Anti-UAV's (its frames, or its ``IR.mp4`` /
  ``infrared.mp4``, with ``IR_label.json`` / ``infrared.json`` beside).

Every frame goes through the daemon's ``imaging.chain: objects`` (:class:`onboard.imaging.objects.ObjectTracker`,
its default parameters) without a pose: the camera is taken as still, so association is in image space (the
bearings are those of a nominal pinhole, ``fx = fy = width``, which changes nothing in the image).  The output is
the MOT Challenge tracker format, one line per confirmed object measured on a frame::

    frame,id,x,y,w,h,conf,-1,-1,-1

``frame`` from 1; ``x, y`` the box's top-left in MOT's 1-based pixels (the chain's box of the detection, or with
``--box-px N`` an N x N square about its centre, as ``groundsim eval`` writes for point targets); ``conf`` the
detection's contrast over its local threshold.  TrackEval (MOT Challenge 2-D) and ``motmetrics`` read it.

``--primary-only``: only the primary target, the chain's choice in auto mode: the steady object nearest the image
centre, and within ``--primary-within-px`` of it (default 0.15 of the frame's width: the daemon's 0.15 rad off
the axis for a camera pointed at its target; give the half diagonal or more for footage whose target is anywhere).
Frames whose confirmed objects are all farther have no line, which a warning at the end counts.
``--format anti-uav`` writes the Anti-UAV toolkit's result instead (its ``eval`` reads it as a sequence's
``.txt``): ``{"res": [...]}``, one entry per frame from 1 to the last, the primary's ``[x, y, w, h]`` in 0-based
pixels (its ``gt_rect``'s) or ``[]`` where there is none (the toolkit's "absent"; a frame missing from a folder's
numbering too).  With Anti-UAV's label file beside the input (``IR_label.json`` beside ``IR.mp4`` or in the frames'
folder; the 2021 edition's ``infrared.json`` beside ``infrared.mp4``), ``res`` is padded with ``[]`` to the
frames it labels (the toolkit's scorer pairs them in order and stops at the shorter), and a ``res`` longer than
they is warned about.

Frame numbers.  A video's frames are numbered as decoded, from 1.  In a folder whose frame names all end in a
number behind one common prefix (``000001.png``, ``17.png``, ``frame_000001.png``, ``img0000001.jpg``: the MOT and
Anti-UAV conventions, ffmpeg's ``frame_%06d``) the number is the MOT frame, so a missing file leaves a gap rather
than shifting every later frame against the benchmark's truth; names numbered from 0 are moved up by one (MOT
counts from 1).  Gaps are warned about once (how many frames, the first gap), and two files with one number
(``1.png`` and ``0001.png``) are refused.  Names whose numbers are times rather than frame numbers (a median
step over 30, or a last number over 100 times the frame count plus 100 000) are numbered by sorted position from
1, with a WARNING.  Otherwise frames are numbered by their sorted position from 1: an INFO
line says so, a WARNING when most names are numbered (a stray image among the frames is tracked as one).
Frame K is taken ``(K - 1) / fps`` seconds after the first, so the tracks are predicted over a gap as over frames
the daemon drops (over more missing frames than a track coasts, 45, every track is lost); ``--fps`` (or the video's or ``seqinfo.ini``'s rate) sets that time.

Frames must be at least 16 x 16 pixels (the chain's smallest) and of one size: a folder or a video whose frame
size changes is refused at the first frame that differs.  A folder's frame file that does not decode (cut short,
damaged) is skipped, its number a gap as a missing file's, with a warning for the first and the summary line
counting them all; a folder none of whose frames decodes is refused.  A video that decodes with errors (damage the decoder
concealed, or a frame it cannot decode: the frames after that one are not read, so that no later frame number
shifts) or to fewer frames than its container declares (a file cut short) is tracked as far as it decodes, with
one warning saying how far; one whose first frame cannot be decoded is refused.

``--encoding``: ``auto`` takes the frames as stored (the first frame's depth; all must match);
``mono8`` takes a 16-bit frame's high byte (of a 14-bit camera's grey, the 6 highest bits: a dim target's contrast
may not survive it); ``mono16`` widens 8-bit frames full scale to full scale (x 257, folder or video alike).  ``--fps``: the frame rate (default: a video's own,
a MOT sequence's ``seqinfo.ini``'s, else 30).  A progress line goes to stderr every few seconds;
``--quiet`` drops it and the INFO lines.

The tracks are written to a temporary file beside ``--out`` (created with the permissions a new file gets,
``0666`` less the umask) and renamed over it only when the run ends: a run that fails leaves the previous file as
it was (or none), never the tracks of the frames before the failure.  An interrupted run (Ctrl-C) is the exception:
it renames the tracks of the frames done (if any) into place, since they are valid MOT lines of a prefix of the
input; SIGTERM (a job's time limit, ``timeout``) is taken as Ctrl-C.
``--out`` must be a regular file or a new path (a folder, device or pipe is refused); through a symbolic link the
file it points to is replaced, the link kept.  It must not be an input: the video, a frame of the input folder, or
any image file in that folder (a later run would read it as a frame), nor the files that describe the sequence
(``seqinfo.ini``, anything under ``gt/``, Anti-UAV's label file), in the frames' folder or the one above it.

A long input (3 s or more, and three of the chain's 15-frame confirmation windows) on which no object was
confirmed ends with one warning saying why that is likely: the chain confirms point targets, peaked over a few
pixels, so extended targets (an object filling more than a few pixels) and targets too dim against their local
noise are not confirmed.  It still exits 0 with the empty output: a sky with nothing in it has none.

Exit codes: 0 done; 2 bad input -- a missing path, a seqinfo.ini ``imDir`` refused, a frame that cannot be read, frames
of mixed size or depth or too small, two frame files of one number, an output that cannot be written or naming an input
-- in one line naming the file; 130 interrupted by Ctrl-C or SIGTERM (the tracks of the frames done are in the output).
"""

from __future__ import annotations

from onboard.core.blas import single_thread_blas_env

single_thread_blas_env()  # the chain is single-threaded like the daemon's: before numpy is imported

import argparse  # noqa: E402
import contextlib  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Iterator, Sequence  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import TYPE_CHECKING  # noqa: E402

import numpy as np  # noqa: E402

from onboard.app.cli_args import OneLineParser, help_summary, sigterm_as_interrupt  # noqa: E402
from onboard.app.output_files import create_beside, not_a_file, same_file_clash  # noqa: E402
from onboard.core.errors import InputError  # noqa: E402
from onboard.io import frame_input  # noqa: E402
from onboard.io.frame_input import (  # noqa: E402
    ENCODINGS,
    FRAME_SUFFIXES,
    LABEL_NAMES,
    SEQINFO_NAME,
    VIDEO_NAMES,
    FrameSource,
    open_frames,
)

if TYPE_CHECKING:
    from onboard.imaging.objects import ObjectsUpdate

__all__ = [
    "FRAME_SUFFIXES",
    "VIDEO_NAMES",
    "FrameSource",
    "open_frames",
    "mot_rows",
    "track_frames",
    "build_parser",
    "main",
]

log = logging.getLogger(__name__)

EXIT_OK, EXIT_INPUT, EXIT_INTERRUPTED = 0, 2, 130
PROGRESS_EVERY_S = 5.0
#: an input this long (and of LONG_INPUT_WINDOWS confirmation windows) on which nothing was confirmed is warned
#: about: long enough that a point target in it would have been confirmed several times over
LONG_INPUT_S = 3.0
LONG_INPUT_WINDOWS = 3
FORMATS = ("mot", "anti-uav")


def _box(o, box_px: float | None) -> tuple[float, float, float, float]:
    """Object ``o``'s box ``(x, y, w, h)`` in the chain's pixels (pixel i spans [i, i + 1)): its detected box, or a
    ``box_px`` square about its centre."""
    if box_px is None:
        x, y, w, h = o.bbox
        return float(x), float(y), float(w), float(h)
    return o.u_px - box_px / 2, o.v_px - box_px / 2, box_px, box_px


def mot_rows(frame_number: int, update, box_px: float | None = None, primary_only: bool = False) -> list[str]:
    """The MOT lines (``frame,id,x,y,w,h,conf,-1,-1,-1``) of one :class:`~onboard.imaging.objects.ObjectsUpdate`:
    its confirmed objects measured on the frame (``primary_only``: the primary target's only); boxes in MOT's
    1-based pixels, the chain's box or a ``box_px`` square about the centre."""
    rows = []
    for o in update.confirmed:
        if primary_only and o.object_id != update.primary_id:
            continue
        x, y, w, h = _box(o, box_px)
        if not all(math.isfinite(v) for v in (x, y, w, h)):
            continue  # a scorer refuses the whole sequence over one non-finite box (TrackEval does)
        rows.append(f"{frame_number},{o.object_id},{x + 1:.3f},{y + 1:.3f},{w:.3f},{h:.3f},{o.score:.3f},-1,-1,-1\n")
    return rows


def anti_uav_box(update, box_px: float | None = None) -> list[float]:
    """The Anti-UAV toolkit's entry for one frame: the primary target's ``[x, y, w, h]`` (0-based pixels, the box's
    top-left corner, as its ``gt_rect``), or ``[]`` when there is none (the toolkit's "target absent")."""
    for o in update.confirmed:
        if o.object_id == update.primary_id:
            return [round(v, 3) for v in _box(o, box_px)]
    return []


def track_frames(
    frames, fps: float, primary_within_px: float | None = None
) -> Iterator[tuple[int, np.ndarray, ObjectsUpdate]]:
    """``(MOT frame number, pixels, ObjectsUpdate)`` of each frame of ``frames`` (``(MOT frame number, name,
    pixels)``) through a fresh objects chain sized by the first frame; an unusable frame raises
    :class:`InputError` naming it.  Frame K is stamped ``(K - 1) / fps``: a gap in the numbering is time that
    passed, over which the tracks are predicted as over frames a daemon dropped.  ``primary_within_px``: the
    primary rule's radius about the image centre (None: the chain's, ``primary_max_off_axis_rad`` of the nominal
    pinhole)."""
    from onboard.core.frames import PinholeIntrinsics
    from onboard.imaging.objects import ObjectTracker
    from onboard.imaging.preprocess import MIN_FRAME_SIDE_PX

    tracker = None
    for k, name, px in frames:
        if tracker is None:
            h, w = px.shape
            if min(h, w) < MIN_FRAME_SIDE_PX:  # said here in the tool's words, with the path, not the chain's
                raise InputError(
                    f"{name}: frame of {w} x {h} px: frames must be at least {MIN_FRAME_SIDE_PX} x "
                    f"{MIN_FRAME_SIDE_PX} px"
                )
            K = PinholeIntrinsics(float(w), float(w), w / 2.0, h / 2.0, w, h)  # nominal: image space (docstring)
            changes: dict[str, float] = {"attitude_white_sigma_rad": 0.0}
            # no attitude here (every frame in image space): its fits have no attitude error to allow for
            if primary_within_px is not None:
                changes["primary_max_off_axis_rad"] = math.atan(primary_within_px / K.fx_px)
            params = ObjectTracker.default_params(None, **changes)
            tracker = ObjectTracker(K, frame_rate_hz=fps, params=params)
        try:
            upd = tracker.update(px, None, round((k - 1) * 1e6 / fps))
        except InputError as exc:
            raise InputError(f"{name}: {exc}") from None
        yield k, px, upd


def primary_radius_px(width_px: int, primary_within_px: float | None = None) -> float:
    """The primary rule's radius about the image centre, in pixels, for frames ``width_px`` wide."""
    if primary_within_px is not None:
        return primary_within_px
    from onboard.imaging.objects import ObjectTracker

    return width_px * math.tan(ObjectTracker.default_params().primary_max_off_axis_rad)


# --------------------------------------------------------------------------- output


class OutputError(InputError):
    """The output cannot be written; ``path`` as the user gave it, ``reason`` the system's words."""

    def __init__(self, path: str, reason: str) -> None:
        super().__init__(f"{path}: cannot write: {reason}")
        self.path, self.reason = path, reason


class _Replacement:
    """The text file ``path`` written beside it and renamed over it by :meth:`commit` (the module docstring says
    why); :meth:`discard` removes the temporary file of a run that did not commit.  ``OSError`` of the writing,
    closing and renaming becomes :class:`OutputError` naming ``path``."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.target = os.path.realpath(path)  # through a symbolic link: the link is kept, its file replaced
        try:
            mode = os.stat(self.target).st_mode
        except (FileNotFoundError, NotADirectoryError):  # a new file (or a file for a folder: said below)
            mode = None
        except OSError as exc:
            raise OutputError(path, exc.strerror or str(exc)) from None
        refused = not_a_file(mode)
        if refused is not None:
            raise OutputError(path, refused)
        self.existed = mode is not None
        folder = os.path.dirname(self.target)
        existing = folder
        while not os.path.exists(existing):
            existing = os.path.dirname(existing)
        if not os.path.isdir(existing):
            raise OutputError(path, f"{existing} is not a folder")
        try:
            os.makedirs(folder, exist_ok=True)
            self.tmp, fd = create_beside(self.target)
        except OSError as exc:
            raise OutputError(path, exc.strerror or str(exc)) from None
        self.file = os.fdopen(fd, "w", encoding="ascii")
        self.committed = False

    @property
    def untouched(self) -> str:
        """What became of ``path`` when the run did not commit."""
        return f"{self.path} is as it was" if self.existed else f"{self.path} was not created"

    def writelines(self, rows: list[str]) -> None:
        try:
            self.file.writelines(rows)
        except OSError as exc:
            raise OutputError(self.path, exc.strerror or str(exc)) from None

    def commit(self) -> None:
        try:
            self.file.close()
            os.replace(self.tmp, self.target)
        except OSError as exc:
            raise OutputError(self.path, exc.strerror or str(exc)) from None
        self.committed = True

    def discard(self) -> None:
        if not self.committed:
            with contextlib.suppress(OSError):
                self.file.close()
            with contextlib.suppress(OSError):
                os.unlink(self.tmp)


def _input_clash(out_path: str, src: FrameSource) -> str | None:
    """Why ``--out`` cannot be ``out_path`` for the input ``src``, or None: it names the video or a frame file, or
    it is an image file in the frames' folder (a later run would read the tracks as a frame).
    ``same_file_clash`` has already refused a file given as INPUT; this covers what a folder INPUT resolves to."""
    target = os.path.realpath(out_path)
    if os.path.exists(target):
        for path in [src.path] if src.kind == "video" else src.files:
            with contextlib.suppress(OSError):
                if os.path.samefile(target, path):
                    return f"--out {out_path}: names the input {path}; give another file"
    in_folder = src.kind == "folder" and os.path.dirname(target) == os.path.realpath(src.path)
    if in_folder and Path(target).suffix.lower() in FRAME_SUFFIXES:
        return (
            f"--out {out_path}: an image file in the input folder {src.path}, which a later run would read as a "
            f"frame; give another file"
        )
    # the files that describe the sequence (read by this tool or by a scorer): a MOT sequence's seqinfo.ini and
    # gt/, Anti-UAV's label files, beside the frames' folder or one level up (MOT's img1/)
    seq = src.path if src.kind == "folder" else src.path.parent
    for folder in (seq, seq.parent):
        for name in (SEQINFO_NAME, *LABEL_NAMES.values()):
            if target == os.path.realpath(folder / name):
                return f"--out {out_path}: the input's own {name}; give another file"
        gt = os.path.realpath(folder / "gt")
        if os.path.commonpath([target, gt]) == gt:
            return f"--out {out_path}: inside the input's ground truth folder {folder / 'gt'}; give another file"
    return None


# --------------------------------------------------------------------------- entry point


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="python -m onboard.track_video", description=help_summary(__doc__))
    p.add_argument("input", metavar="INPUT", help="a video file, a folder of frames, or a MOT / Anti-UAV sequence")
    p.add_argument("--out", metavar="tracks.txt", required=True, help="the tracks to write (MOT lines, or --format's)")
    p.add_argument("--encoding", choices=ENCODINGS, default="auto", help="pixel depth (default: %(default)s)")
    p.add_argument(
        "--fps",
        type=float,
        help="frame rate: frame K is (K - 1) / fps s after the first (default: the video's; a MOT sequence's "
        "seqinfo.ini; 30 for a folder)",
    )
    p.add_argument(
        "--box-px", type=float, metavar="N", help="write N x N px boxes about the centres instead of the detected ones"
    )
    p.add_argument(
        "--primary-only",
        action="store_true",
        help="only the primary target: the steady object nearest the image centre, within --primary-within-px",
    )
    p.add_argument(
        "--primary-within-px",
        type=float,
        metavar="R",
        help="the primary's farthest distance from the image centre (default: 0.15 of the width, the daemon's "
        "0.15 rad off the axis, for a camera pointed at its target)",
    )
    p.add_argument(
        "--format",
        choices=FORMATS,
        default="mot",
        help="mot: MOT Challenge lines of every confirmed object; anti-uav: the Anti-UAV toolkit's JSON, "
        '{"res": [[x, y, w, h] or [] for each frame]}, the primary target only (default: %(default)s)',
    )
    p.add_argument("--quiet", action="store_true", help="no progress line and no INFO lines")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """The command (the module docstring); SIGTERM is taken as Ctrl-C while it runs."""
    with sigterm_as_interrupt():
        return _main(argv)


def _main(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    # this tool's INFO lines (and its reader's) say how frames were numbered; the chain's own stay at WARNING
    for name in (__name__, frame_input.__name__):
        logging.getLogger(name).setLevel(logging.WARNING if args.quiet else logging.INFO)
    if args.fps is not None and not (math.isfinite(args.fps) and args.fps > 0):
        print(f"--fps: expected a finite rate > 0, got {args.fps}", file=sys.stderr)
        return EXIT_INPUT
    if args.box_px is not None and not (math.isfinite(args.box_px) and args.box_px > 0):
        print(f"--box-px: expected a finite side > 0, got {args.box_px}", file=sys.stderr)
        return EXIT_INPUT
    if args.primary_within_px is not None and not (
        math.isfinite(args.primary_within_px) and args.primary_within_px > 0
    ):
        print(f"--primary-within-px: expected a finite radius > 0, got {args.primary_within_px}", file=sys.stderr)
        return EXIT_INPUT
    primary_only = args.primary_only or args.format == "anti-uav"
    clash = same_file_clash([("--out", args.out)], [("INPUT", args.input)])
    if clash is not None:
        print(clash, file=sys.stderr)
        return EXIT_INPUT
    done = 0
    out: _Replacement | None = None
    boxes: list[list[float]] = []  # --format anti-uav: one entry a frame, frame 1 first
    json_written = False
    try:
        src = open_frames(args.input, args.encoding, args.fps)
        clash = _input_clash(args.out, src)
        if clash is not None:
            raise InputError(clash)
        out = _Replacement(args.out)
        t0 = last = time.monotonic()
        ids: set[int] = set()  # confirmed
        written: set[int] = set()
        lines = 0
        no_primary = 0  # frames with confirmed objects and no primary among them
        size = None
        for k, px, upd in track_frames(src.frames, src.fps, args.primary_within_px):
            if args.format == "anti-uav":
                boxes.extend([] for _ in range(k - 1 - len(boxes)))  # frames missing from the numbering: absent
                boxes.append(anti_uav_box(upd, args.box_px))
                lines += bool(boxes[-1])
            else:
                rows = mot_rows(k, upd, args.box_px, primary_only)
                out.writelines(rows)
                lines += len(rows)
            ids.update(o.object_id for o in upd.confirmed)
            if primary_only:
                written.update(() if upd.primary_id is None else [upd.primary_id])
                no_primary += bool(upd.confirmed) and upd.primary_id not in {o.object_id for o in upd.confirmed}
            else:
                written.update(o.object_id for o in upd.confirmed)
            done += 1  # frames tracked: a folder's frame numbers may have gaps
            now = time.monotonic()
            if not args.quiet and now - last >= PROGRESS_EVERY_S:
                last = now
                of = f"/{src.total} ({100.0 * done / src.total:.0f} %)" if src.total else ""
                rate = done / (now - t0)
                print(f"track_video: frame {done}{of}, {rate:.0f} frames/s, {len(ids)} ids", file=sys.stderr)
            if size is None:
                size = f"{px.shape[1]} x {px.shape[0]} {'mono16' if px.dtype == np.uint16 else 'mono8'}"
                size_px = (px.shape[1], px.shape[0])
        wall = time.monotonic() - t0
        if done == 0:
            raise InputError(f"{src.path}: no frames")
        if args.format == "anti-uav":
            _fit_to_labels(boxes, src, args.out)
            json_written = True  # before the write: an interruption in it must not write the document again
            out.writelines(_anti_uav_json(boxes))
        out.commit()
        if not ids and _long_input(done, src.fps):
            _say_nothing_confirmed(src.path, done, src.fps, "box" if args.format == "anti-uav" else "line")
        if primary_only and no_primary:
            log.warning(
                "%s: on %d of %d frames objects were confirmed but none was the primary: the primary is the steady "
                "object nearest the image centre, confirmed over most of its frames and within %.0f px of the centre "
                "(--primary-within-px widens that): those frames have no %s",
                src.path,
                no_primary,
                done,
                primary_radius_px(int(size_px[0]), args.primary_within_px),
                "box" if args.format == "anti-uav" else "line",
            )
    except InputError as exc:
        if out is None:  # nothing created yet
            print(str(exc), file=sys.stderr)
        elif isinstance(exc, OutputError):
            print(f"{exc} after {done} frames; {out.untouched}", file=sys.stderr)
        else:
            print(f"{exc}; {out.untouched}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        if args.format == "anti-uav" and out is not None and done and not json_written and not out.committed:
            with contextlib.suppress(OutputError):  # said by _interrupted's commit, which fails alike
                out.writelines(_anti_uav_json(boxes))
            log.warning(
                "%s: interrupted: the result holds the first %d frames' boxes only; the Anti-UAV scorer pairs it "
                "with the labels in order and scores that prefix alone",
                args.out,
                len(boxes),
            )
        return _interrupted(out, done)
    finally:
        if out is not None:
            out.discard()
    converted = f"from {' and '.join(sorted(src.converted_from))}; " if src.converted_from else ""
    if src.unreadable:
        bad = src.unreadable
        converted += f"{len(bad)} unreadable skipped, frame{'s' if len(bad) > 1 else ''} {_numbers(bad)}; "
    print(
        f"{src.path}: {done} frames of {size} ({converted}{src.kind}, {src.fps:g} frames/s) -> {len(ids)} object ids "
        f"confirmed, {len(written)} written, {lines} {'boxes' if args.format == 'anti-uav' else 'lines'} in "
        f"{args.out} ({wall:.1f} s, {done / max(wall, 1e-9):.0f} frames/s)"
    )
    return EXIT_OK


def _numbers(unreadable: list[tuple[int, str]], most: int = 5) -> str:
    """The frame numbers of ``unreadable`` frames for the summary line: the first ``most``, then how many more."""
    shown = ", ".join(str(n) for n, _ in unreadable[:most])
    return shown + (f" and {len(unreadable) - most} more" if len(unreadable) > most else "")


def _long_input(frames: int, fps: float) -> bool:
    """Whether ``frames`` at ``fps`` are a long input: ``LONG_INPUT_S`` seconds and ``LONG_INPUT_WINDOWS`` of
    the chain's confirmation windows (a track is confirmed on ``confirm_in_window`` of ``confirm_window``
    frames)."""
    from onboard.imaging.objects_model import ObjectParams

    return frames / fps >= LONG_INPUT_S and frames >= LONG_INPUT_WINDOWS * ObjectParams().confirm_window


def _say_nothing_confirmed(path: Path, frames: int, fps: float, what: str) -> None:
    """One warning for a long input on which the chain confirmed no object: an empty output can be right (a
    sky with nothing in it), but is more often footage whose targets are not the points the chain looks for."""
    from onboard.imaging.clutter import ClutterParams

    p = ClutterParams()
    log.warning(
        "%s: no object confirmed over %d frames (%.1f s at %g frames/s): the output has no %s. The chain confirms "
        "point targets, brighter at their centre than %d px and %d px away: a target more than a few pixels "
        "across (an extended one) is not one, nor one too dim against its local noise",
        path,
        frames,
        frames / fps,
        fps,
        what,
        p.sharp_guard_px,
        p.guard_px,
    )


def _anti_uav_labels(src: FrameSource) -> tuple[Path, int] | None:
    """Anti-UAV's label file of ``src`` (:data:`LABEL_NAMES`: beside its IR.mp4 / infrared.mp4, or in its frames'
    folder) and the frames it scores: the shorter of its ``exist`` and ``gt_rect`` lists, as its scorer zips them
    with ``res``; None when there is none, or (with a warning naming it) when it cannot be read."""
    if src.kind == "video":
        label = LABEL_NAMES.get(src.path.name)
        candidates = [] if label is None else [src.path.parent / label]
    else:
        candidates = [src.path / name for name in LABEL_NAMES.values()]
    for path in candidates:
        if not path.is_file():
            continue
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            log.warning("%s: not read (%s): res is not fitted to its frames", path, exc)
            return None
        lists = [doc[k] for k in ("exist", "gt_rect") if isinstance(doc, dict) and isinstance(doc.get(k), list)]
        if not lists:
            log.warning("%s: no 'exist' or 'gt_rect' list: res is not fitted to its frames", path)
            return None
        return path, min(len(v) for v in lists)
    return None


def _fit_to_labels(boxes: list[list[float]], src: FrameSource, out: str) -> None:
    """``boxes`` (res) padded with ``[]`` (absent) to the frames Anti-UAV's label file beside the input scores,
    or a warning when res is longer.  The toolkit's scorer zips res with the label's lists and stops at the
    shortest: a res cut short (frames missing at the end of a folder's numbering, a video that decoded short)
    would silently leave the last labelled frames unscored, and a longer one its extra entries."""
    labels = _anti_uav_labels(src)
    if labels is None:
        return
    path, n = labels
    if len(boxes) < n:
        log.info("%s: res padded with %d empty entries to the %d frames %s labels", out, n - len(boxes), n, path)
        boxes.extend([] for _ in range(n - len(boxes)))
    elif len(boxes) > n:
        log.warning(
            "%s: res has %d entries, %s labels %d frames: Anti-UAV's scorer pairs them in order and leaves out "
            "the last %d entries (frames the labels do not have, or a numbering that does not match theirs)",
            out,
            len(boxes),
            path,
            n,
            len(boxes) - n,
        )


def _anti_uav_json(boxes: list[list[float]]) -> list[str]:
    return [json.dumps({"res": boxes}, separators=(",", ":")), "\n"]


def _interrupted(out: _Replacement | None, done: int) -> int:
    """Ctrl-C: the tracks of the frames done into place (the module docstring says why), in one line.  Before the
    first frame is done there are none, and a previous output is kept rather than emptied."""
    if out is None or done == 0:
        kept = f"; {out.untouched}" if out is not None else ""
        print(f"interrupted before the first frame was tracked: nothing written{kept}", file=sys.stderr)
        return EXIT_INTERRUPTED
    try:
        if not out.committed:  # interrupted after the run's own commit (its closing words): the file is whole
            out.commit()
    except OutputError as exc:
        print(f"interrupted after {done} frames; {exc}; {out.untouched}", file=sys.stderr)
    else:
        print(f"interrupted: {done} frames tracked; {out.path} holds their tracks", file=sys.stderr)
    return EXIT_INTERRUPTED
