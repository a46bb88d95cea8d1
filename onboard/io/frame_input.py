"""Frames of anyone's video or image folder, read as the image chain takes them: ``open_frames(path)``.

The reading side of ``python -m onboard.track_video`` (:mod:`onboard.app.track_video`), whose docstring is the
manual of what is read and how: ``INPUT`` (a video FFmpeg decodes, read with PyAV; a folder of PNG, TIFF, JPEG or
BMP frames read with OpenCV as stored; a MOT sequence folder with its ``seqinfo.ini``; an Anti-UAV sequence's
frames or ``IR.mp4`` / ``infrared.mp4``), "Frame numbers" (a folder's names give the MOT frame numbers, gaps kept),
the one frame size and depth, and ``--encoding`` (``auto``, ``mono8``, ``mono16``).  Here that is done once, for
any caller: a :class:`FrameSource` holds the frame rate, the frame count where known and the iterator of
``(MOT frame number, name, pixels)``; every input it cannot take is one :class:`~onboard.core.errors.InputError`
naming the file (and, for a ``seqinfo.ini`` key, the key); what it can take but doubts (gaps in the numbering, numbers that
look like times, a ``seqLength`` that disagrees, a damaged video) is one warning on this module's logger.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from onboard.core.errors import InputError

__all__ = [
    "FRAME_SUFFIXES",
    "VIDEO_NAMES",
    "LABEL_NAMES",
    "SEQINFO_NAME",
    "ENCODINGS",
    "FrameSource",
    "open_frames",
]

log = logging.getLogger(__name__)

FRAME_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp")
#: the video a benchmark's sequence folder holds instead of frames (Anti-UAV: IR.mp4, its 2021 edition infrared.mp4)
VIDEO_NAMES = ("IR.mp4", "infrared.mp4")
#: Anti-UAV's label file beside its video or in its frames' folder, ``{"exist": [0 or 1 a frame], "gt_rect": [[x,
#: y, w, h] or [] a frame], ...}``: IR_label.json (the 2020 edition and Anti-UAV410), infrared.json (2021)
LABEL_NAMES = {"IR.mp4": "IR_label.json", "infrared.mp4": "infrared.json"}
DEFAULT_FOLDER_FPS = 30.0
SEQINFO_NAME = "seqinfo.ini"
DEFAULT_IM_DIR = "img1"  # MOT's image folder when seqinfo.ini names none
#: a folder whose frame numbers step by more than this (median) is named by something else (times): numbered by
#: position.  A benchmark's own numbering steps by 1; a subsampled one (every 10th frame kept) by a few
MAX_NUMBER_STEP = 30
#: ... and a folder whose last number exceeds MAX_NUMBER_SPAN times its frame count plus MAX_NUMBER_OFFSET (a
#: subsequence cut from a long recording keeps its numbers below that)
MAX_NUMBER_SPAN = 100
MAX_NUMBER_OFFSET = 100_000
ENCODINGS = ("auto", "mono8", "mono16")


def _natural_key(name: str) -> list:
    """Sort key of a file name with its digit runs compared by value (``2.png`` before ``10.png``)."""
    return [int(part) if part.isdecimal() else part.lower() for part in re.split(r"(\d+)", name)]


@dataclass
class FrameSource:
    """Where the frames come from: ``path`` (the video file or the frames' folder), ``kind`` ``video`` or
    ``folder``, ``fps``, ``total`` (frames, None when the container does not say), ``files`` (a folder's frame
    files, in frame order; empty for a video) and ``frames``: the iterator of ``(MOT frame number, name,
    pixels)`` -- the name the file's path (a video's: ``PATH frame K``), the pixels 2-D uint8 or uint16, in the
    encoding asked for.  ``converted_from`` fills as ``frames`` is read: the layouts (``colour``,
    ``colour+alpha``, ``grey+alpha``) of the frames turned to grey; ``unreadable`` too: a folder's frame files that
    did not decode, each ``(MOT frame number, the reason)``, skipped as a gap in the numbering."""

    path: Path
    kind: str
    fps: float
    total: int | None
    frames: Iterator[tuple[int, str, np.ndarray]]
    converted_from: set[str] = field(default_factory=set)
    files: list[Path] = field(default_factory=list)
    unreadable: list[tuple[int, str]] = field(default_factory=list)


def _frame_files(folder: Path) -> list[Path]:
    try:
        return sorted(
            (p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in FRAME_SUFFIXES),
            key=lambda p: _natural_key(p.name),
        )
    except OSError as exc:  # a folder that cannot be listed (permissions): one line, as for a frame
        raise InputError(f"{folder}: cannot list the folder: {exc.strerror or exc}") from None


_NUMBERED = re.compile(r"(.*?)([0-9]+)")


def _numbered(folder: Path, files: list[Path]) -> tuple[list[Path], list[int]]:
    """``files`` (sorted by name) in frame order and their MOT frame numbers (the rules of ``python -m onboard.track_video``'s docstring, "Frame numbers"); logs
    the numbering when it is not the names' own, and the gaps."""
    parts = [_NUMBERED.fullmatch(p.stem) for p in files]
    prefixes = {m.group(1) for m in parts if m is not None}
    if None in parts or len(prefixes) != 1:
        odd = next((p for p, m in zip(files, parts) if m is None), None)
        if odd is None:  # numbered, but behind different prefixes
            by_prefix = {m.group(1): p for p, m in zip(files, parts) if m is not None}
            odd = next(iter(sorted(by_prefix.values(), key=lambda p: _natural_key(p.name))[1:]), files[0])
        numbered = sum(m is not None for m in parts)
        # most names numbered alike and one odd: a stray file (a cover image, a frame renamed) is more likely than
        # a folder that means its sorted order
        level = logging.WARNING if numbered * 2 > len(files) else logging.INFO
        log.log(
            level,
            "%s: not every frame name is a number behind one prefix (%s): MOT frames are numbered by sorted "
            "position from 1%s",
            folder,
            odd.name,
            ", and it is tracked as a frame" if level == logging.WARNING else "",
        )
        return files, list(range(1, len(files) + 1))

    def number(p: Path) -> int:
        m = _NUMBERED.fullmatch(p.stem)
        assert m is not None  # every stem matched above
        return int(m.group(2))

    ordered = sorted(files, key=number)  # stable: names of one number stay in name order
    steps = np.diff([number(p) for p in ordered])
    if len(steps) and float(np.median(steps)) > MAX_NUMBER_STEP:
        # names that are times (ms or us since an epoch), not frame numbers: each step would be dozens of frame
        # periods, and an Anti-UAV result padded to the last "frame" would not fit in memory
        log.warning(
            "%s: the numbers in the frame names step by a median %g (%s, %s ...): not frame numbers (times?): MOT "
            "frames are numbered by sorted position from 1",
            folder,
            float(np.median(steps)),
            ordered[0].name,
            ordered[1].name,
        )
        return ordered, list(range(1, len(ordered) + 1))
    if number(ordered[-1]) > MAX_NUMBER_SPAN * len(ordered) + MAX_NUMBER_OFFSET:
        # small steps but huge numbers: times of a fast camera (ms at 34 frames/s or more, from an epoch or a
        # recording's start), not frame numbers; kept, they would pad an Anti-UAV result to millions of frames
        log.warning(
            "%s: the numbers in the frame names reach %d for %d frames (%s ... %s): not frame numbers (times?): "
            "MOT frames are numbered by sorted position from 1",
            folder,
            number(ordered[-1]),
            len(ordered),
            ordered[0].name,
            ordered[-1].name,
        )
        return ordered, list(range(1, len(ordered) + 1))
    for before, path in zip(ordered, ordered[1:]):
        if number(before) == number(path):
            raise InputError(
                f"{path}: frame number {number(path)} again ({before.name} has it): MOT frame numbers come "
                f"from the names; remove or rename one"
            )
    shift = 1 if number(ordered[0]) == 0 else 0  # MOT frames count from 1
    if shift:
        log.info("%s: frames numbered from 0 (%s): MOT frame = the number in the name + 1", folder, ordered[0].name)
    numbers = [number(p) + shift for p in ordered]
    missing = numbers[-1] - len(numbers)
    if missing:
        # the i-th frame (from 0) is MOT frame i + 1 up to the first gap
        i = next(i for i, n in enumerate(numbers) if n != i + 1)
        first, last = i + 1 - shift, numbers[i] - 1 - shift
        gap = f"{first}" if first == last else f"{first} to {last}"
        log.warning(
            "%s: %d frame%s missing from the numbering up to %s, the first gap %s (before %s); MOT frames keep "
            "the numbers in the names, and the tracks are predicted over the gaps",
            folder,
            missing,
            "" if missing == 1 else "s",
            ordered[-1].name,
            gap,
            ordered[i].name,
        )
    return ordered, numbers


def _sequence_section(path: Path) -> dict[str, str] | None:
    """The ``[Sequence]`` values of the MOT ``seqinfo.ini`` at ``path`` (keys lower-cased, as configparser reads
    them; {} without that section); None when there is no such file or, with a warning naming it, when it cannot
    be read."""
    import configparser

    if not path.is_file():
        return None
    parser = configparser.ConfigParser()
    try:
        parser.read(path, encoding="utf-8")
    except (configparser.Error, OSError, UnicodeDecodeError) as exc:
        log.warning("%s: not read (%s): its image folder, frame rate and length are not used", path, exc)
        return None
    return dict(parser["Sequence"]) if parser.has_section("Sequence") else {}


def _im_dir(section: dict[str, str] | None) -> str:
    """The image folder a ``[Sequence]`` section names (``imDir``), MOT's ``img1`` when it names none."""
    raw = (section or {}).get("imdir", "").strip()
    return raw or DEFAULT_IM_DIR


def _image_folder(seq: Path) -> tuple[Path | None, dict[str, str] | None]:
    """The frames' folder of the MOT sequence folder ``seq`` (its ``seqinfo.ini``'s ``imDir``; ``img1/`` when it
    names none; None when that folder is absent and was not named) and the ``[Sequence]`` values.  An ``imDir``
    that leaves ``seq`` (absolute, ``..``) or names no folder in it is an :class:`InputError` naming the key:
    the frames are where the sequence's truth says, not wherever a folder of that name happens to be."""
    ini = seq / SEQINFO_NAME
    section = _sequence_section(ini)
    named = (section or {}).get("imdir", "").strip()
    if not named:
        folder = seq / DEFAULT_IM_DIR
        return (folder if folder.is_dir() else None), section
    where = f"{ini}: [Sequence] imDir = {named!r}"
    rel = os.path.normpath(named)
    if os.path.isabs(rel) or rel == os.curdir or rel.split(os.sep)[0] == os.pardir:
        raise InputError(f"{where}: not a folder inside the sequence folder {seq}")
    folder = seq / rel
    if not folder.is_dir():
        raise InputError(f"{where}: no such folder in {seq}")
    return folder, section


def _describing_section(folder: Path) -> tuple[Path, dict[str, str]] | None:
    """The ``seqinfo.ini`` (path and ``[Sequence]`` values) describing the frames in ``folder``: its own, else
    the one in the folder above when that one's image folder (``imDir``, else ``img1``) is ``folder``."""
    for ini in (folder / SEQINFO_NAME, folder.parent / SEQINFO_NAME):
        section = _sequence_section(ini)
        if section is not None and (ini.parent == folder or os.path.normpath(_im_dir(section)) == folder.name):
            return ini, section
    return None


def _seqinfo(path: Path, section: dict[str, str]) -> tuple[float | None, int | None]:
    """A MOT sequence's ``seqinfo.ini`` (``path``, its ``[Sequence]`` values ``section``): its ``frameRate`` and
    ``seqLength`` (None where absent or not a positive number; a warning names a value that is not)."""
    values: dict[str, float | None] = {}
    for key in ("frameRate", "seqLength"):
        raw = section.get(key.lower())
        try:
            v = None if raw is None else float(raw)
        except ValueError:
            v = None
        if raw is not None and (v is None or not math.isfinite(v) or v <= 0):
            log.warning("%s: [Sequence] %s = %r is not a number > 0: not used", path, key, raw)
            v = None
        values[key] = v
    length = values["seqLength"]
    return values["frameRate"], None if length is None else int(length)


def _convert(px: np.ndarray, encoding: str, where: str) -> np.ndarray:
    """``px`` (2-D uint8/uint16) in ``encoding`` (``auto``: as it is)."""
    if px.dtype not in (np.uint8, np.uint16):
        raise InputError(f"{where}: pixels of type {px.dtype}: expected 8- or 16-bit grey")
    if encoding == "mono8" and px.dtype == np.uint16:
        return (px >> 8).astype(np.uint8)
    if encoding == "mono16" and px.dtype == np.uint8:
        # full scale to full scale (x 257), as FFmpeg widens a video's 8-bit luma to gray16le: the same frames give
        # the same 16-bit pixels from a folder and from a video, and the chain's 16-bit levels see 8-bit contrasts
        # at their own scale
        return px.astype(np.uint16) * np.uint16(257)
    return px


#: OpenCV's own log lines (``[ WARN:0@0.024] global grfmt_png.cpp:855 read_chunk ...``): the words after it
_OPENCV_LOG_PREFIX = re.compile(r"^\[\s*[A-Z]+:[^\]]*\]\s*(?:global\s+)?\S+:\d+\s+")


@contextlib.contextmanager
def _fd2_captured() -> Iterator[list[str]]:
    """File descriptor 2 into a temporary file while the block runs; the list holds what was written there,
    stripped, once the block ends.  The image libraries OpenCV decodes with (libpng, libjpeg, libtiff) print
    their errors on fd 2 themselves, past Python's ``sys.stderr``: a corrupt frame would otherwise print a
    ``libpng error: ...`` line before this tool's own one line."""
    import tempfile

    said: list[str] = []
    sys.stderr.flush()
    with tempfile.TemporaryFile() as sink:
        saved = os.dup(2)
        try:
            os.dup2(sink.fileno(), 2)
            yield said
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            said.extend(line.strip() for line in sink.read().decode("utf-8", "replace").splitlines() if line.strip())


def _read_image(path: Path) -> tuple[np.ndarray, str | None]:
    """The frame's grey pixels and the layout it was converted from (``colour``, ``colour+alpha``,
    ``grey+alpha``; None when it was grey).  A frame that does not decode is one :class:`InputError` naming it,
    with the decoder's own words (which it would otherwise have printed on fd 2 before that line)."""
    import cv2

    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise InputError(f"{path}: cannot read this frame: {exc.strerror or exc}") from None
    with _fd2_captured() as said:
        try:
            px = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        except cv2.error:  # a header OpenCV refuses before decoding: no image, as for a corrupt one
            px = None
    if px is None:
        why = f": {_OPENCV_LOG_PREFIX.sub('', said[-1])}" if said else ""  # the last is the one that stopped it
        raise InputError(f"{path}: cannot read this frame (not an image OpenCV decodes, or truncated{why})")
    if px.ndim == 3 and px.shape[2] == 1:
        return px[:, :, 0], None
    if px.ndim == 3:
        alpha = px.shape[2] == 4
        # OpenCV hands a grey+alpha PNG over as BGRA with three equal colour planes
        grey = alpha and np.array_equal(px[:, :, 0], px[:, :, 1]) and np.array_equal(px[:, :, 1], px[:, :, 2])
        layout = "grey+alpha" if grey else "colour+alpha" if alpha else "colour"
        return cv2.cvtColor(px, cv2.COLOR_BGRA2GRAY if alpha else cv2.COLOR_BGR2GRAY), layout
    return px, None


def _folder_frames(
    files: list[Path], numbers: list[int], encoding: str, converted_from: set[str], unreadable: list[tuple[int, str]]
) -> Iterator[tuple[int, str, np.ndarray]]:
    """The frames of ``files``.  A file that does not decode (a frame cut short by a copy, a damaged sector) is
    skipped, its number left as a gap as a missing file's is, and said once (a WARNING for the first; ``unreadable``
    keeps them all for the summary): one bad file among thousands no longer cost the whole run.  A folder none of
    whose files decodes is refused, naming the first (and no warning comes before that one line)."""
    first: tuple[tuple[int, ...], np.dtype, Path] | None = None
    for number, path in zip(numbers, files):
        try:
            px, layout = _read_image(path)
        except InputError as exc:
            unreadable.append((number, str(exc)))
            if first is not None and len(unreadable) == 1:
                _warn_unreadable(unreadable[0])
            continue
        if first is None and unreadable:  # the frames before the first that decodes were unreadable
            _warn_unreadable(unreadable[0])
        if layout is not None:
            converted_from.add(layout)
        if first is None:
            first = (px.shape, px.dtype, path)
        elif px.shape != first[0]:
            raise InputError(
                f"{path}: frame of {px.shape[1]} x {px.shape[0]} px, the first ({first[2].name}) is "
                f"{first[0][1]} x {first[0][0]}: all frames must have one size"
            )
        elif px.dtype != first[1] and encoding == "auto":
            raise InputError(
                f"{path}: {8 * px.dtype.itemsize}-bit frame, the first ({first[2].name}) is "
                f"{8 * first[1].itemsize}-bit: give --encoding mono8 or mono16 to convert"
            )
        yield number, str(path), _convert(px, encoding, str(path))
    if first is None and unreadable:
        raise InputError(
            f"{files[0].parent}: none of its {len(files)} frame files decodes; the first: {unreadable[0][1]}"
        )


def _warn_unreadable(first: tuple[int, str]) -> None:
    log.warning("%s; skipped, frame number %d left as a gap (the summary counts any more)", first[1], first[0])


def _av_reason(exc: Exception) -> str:
    """FFmpeg's words for ``exc``, without PyAV's ``[Errno N]`` and the path the message already names."""
    return getattr(exc, "strerror", None) or str(exc)


def _video_frames(path: Path, encoding: str) -> tuple[float, int | None, Iterator[tuple[int, str, np.ndarray]]]:
    import av
    import av.logging

    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError) as exc:
        raise InputError(f"{path}: not a video FFmpeg reads: {_av_reason(exc)}") from None
    if not container.streams.video:
        container.close()
        raise InputError(f"{path}: no video stream")
    stream = container.streams.video[0]
    rate = stream.average_rate or stream.guessed_rate
    fps = float(rate) if rate else DEFAULT_FOLDER_FPS
    total = int(stream.frames) or None
    # a container without a frame count (Matroska, MPEG-TS) says its duration, in AV_TIME_BASE units (us)
    duration_s = container.duration / 1e6 if container.duration else None
    deep = any(c.bits > 8 for c in stream.format.components) if stream.format is not None else False
    wide = encoding == "mono16" or (encoding == "auto" and deep)

    def frames() -> Iterator[tuple[int, str, np.ndarray]]:
        k = corrupt = 0
        stopped = None  # why decoding stopped before the end: a packet the decoder refused
        first: tuple[int, ...] | None = None
        # FFmpeg conceals damage and goes on, saying so only in its log, which PyAV drops unless a level is set:
        # the log is turned on for the decoding, its lines captured (not printed) and its errors counted
        level = av.logging.get_level()
        errors_before = av.logging.get_last_error()[0]
        av.logging.set_level(av.logging.ERROR)
        try:
            with av.logging.Capture(local=False) as logs:  # the decoder's threads log too
                for frame in container.decode(stream):
                    k += 1
                    corrupt += bool(frame.is_corrupt)
                    px = np.ascontiguousarray(frame.to_ndarray(format="gray16le" if wide else "gray"))
                    if first is None:
                        first = px.shape
                    elif px.shape != first:  # as a folder's: the chain is sized by the first frame
                        raise InputError(
                            f"{path}: frame {k} is {px.shape[1]} x {px.shape[0]} px, the first is "
                            f"{first[1]} x {first[0]}: all frames must have one size"
                        )
                    yield k, f"{path} frame {k}", px
        except av.error.FFmpegError as exc:
            if k == 0:
                raise InputError(f"{path}: frame {k + 1} cannot be decoded: {_av_reason(exc)}") from None
            # damage the decoder cannot conceal: the frames before it are kept, as a file cut short there would be
            # (the frames after it are not read: a frame skipped would shift every later MOT frame number)
            stopped = f"frame {k + 1} cannot be decoded ({_av_reason(exc)}), the frames after it are not read"
        finally:
            av.logging.set_level(level)
            container.close()
        errors = av.logging.get_last_error()[0] - errors_before
        short = _short_by(k, total, duration_s, fps)
        if short or errors or corrupt or stopped:
            said = [short] if short else [f"decoded {k} frames"]
            if stopped:
                said.append(stopped)
            if errors:
                first_error = next(
                    (f"[{name}] {text.strip()}" for lvl, name, text in logs if lvl <= av.logging.ERROR), ""
                )
                said.append(f"{errors} decoder error{'s' if errors > 1 else ''} (the first: {first_error})")
            if corrupt:
                said.append(f"{corrupt} frame{'s' if corrupt > 1 else ''} marked corrupt")
            log.warning(
                "%s: %s: the file is damaged or cut short; tracks are of the frames decoded", path, "; ".join(said)
            )

    return fps, total, frames()


def _short_by(decoded: int, declared: int | None, duration_s: float | None, fps: float) -> str | None:
    """What ``decoded`` frames fall short of, in words: the container's frame count ``declared`` (differing), or
    the frames its ``duration_s`` at ``fps`` implies (fewer by more than one, the rounding of where a duration
    ends); None when neither is known or they agree."""
    if declared:
        return None if decoded == declared else f"decoded {decoded} of {declared} frames declared"
    if duration_s:
        implied = round(duration_s * fps)
        if decoded < implied - 1:
            at = f"{duration_s:g} s at {fps:g} frames/s"
            return f"decoded {decoded} of about {implied} frames its duration implies ({at})"
    return None


def open_frames(input_path: str, encoding: str = "auto", fps: float | None = None) -> FrameSource:
    """The :class:`FrameSource` of ``input_path`` (the module docstring's layouts); :class:`InputError` naming the path when it
    is missing or holds no frames."""
    if encoding not in ENCODINGS:
        raise InputError(f"--encoding: expected one of {', '.join(ENCODINGS)}, got {encoding!r}")
    path = Path(input_path)
    if not path.exists():
        raise InputError(f"{path}: no such file or folder")
    if path.is_dir():
        files = _frame_files(path)
        described: tuple[Path, dict[str, str]] | None = None
        if files:
            described = _describing_section(path)
        else:  # a MOT sequence folder: the frames are in its image folder
            images, section = _image_folder(path)
            if images is not None:
                described = None if section is None else (path / SEQINFO_NAME, section)
                path, files = images, _frame_files(images)
        if not files:
            video = next((path / n for n in VIDEO_NAMES if (path / n).is_file()), None)
            if video is None:
                raise InputError(
                    f"{path}: no frames ({', '.join(FRAME_SUFFIXES)} files), no img1/ (nor a seqinfo.ini's imDir) "
                    f"and no {' or '.join(VIDEO_NAMES)} in this folder"
                )
            path = video
        else:
            seq_rate, seq_length = _seqinfo(*described) if described is not None else (None, None)
            rate = fps if fps is not None else seq_rate if seq_rate is not None else DEFAULT_FOLDER_FPS
            converted_from: set[str] = set()
            unreadable: list[tuple[int, str]] = []
            files, numbers = _numbered(path, files)
            if seq_length is not None and (numbers[-1] != seq_length or len(numbers) != seq_length):
                log.warning(
                    "%s: seqinfo.ini's seqLength is %d, the folder holds %d frames numbered up to %d: the truth "
                    "counts frames this run does not have, or the folder frames the truth does not%s",
                    path,
                    seq_length,
                    len(numbers),
                    numbers[-1],
                    " (TrackEval refuses a sequence whose tracks go beyond seqLength: fix seqinfo.ini or the folder)"
                    if numbers[-1] > seq_length
                    else "",
                )
            frames = _folder_frames(files, numbers, encoding, converted_from, unreadable)
            return FrameSource(path, "folder", rate, len(files), frames, converted_from, files, unreadable)
    video_fps, total, decoded = _video_frames(path, encoding)
    return FrameSource(path, "video", video_fps if fps is None else fps, total, decoded)
