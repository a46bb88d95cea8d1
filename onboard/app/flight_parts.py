"""The files of one rotated recording (:mod:`onboard.io.record`: ``FILE.mcap``, ``FILE.1.mcap``, ...) replayed as one
flight (``python -m onboard.replay`` and ``python -m groundsim report`` given several files): whether the files are
parts of one recording, each once, in order, without a gap.

One recording is told by its metadata's ``recording_id`` (the recorder writes the same random id in every file).
Files of an older recorder have none; they are checked on what they have: the same vehicle, recorder and
configuration, each file opened (``started_utc``) no earlier than the one before, and its first frame after that one's
last on the vehicle's boot clock.  Another flight of the same daemon with the same configuration passes that only
when its files fall in order after the first flight's, which a recording id rules out.  Pure: metadata and frame
times in, the refusal's words out (the caller raises them)."""

from __future__ import annotations

import datetime
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

__all__ = ["FilePart", "file_index", "index_of", "parts_problem"]

#: the metadata fields an older recorder's files (without a ``recording_id``) must agree on to be one recording's
SAME_IN_EVERY_FILE = ("vehicle", "recorder", "config_yaml")


@dataclass(frozen=True)
class FilePart:
    """One file of a recording as the check reads it: its ``irtrack`` metadata (``{}`` when it has none) and the
    boot-clock times of its first and last frame input (None without any)."""

    path: str
    metadata: Mapping[str, str]
    first_frame_us: int | None = None
    last_frame_us: int | None = None


def file_index(part: FilePart) -> int | str:
    """The part's ``file_index`` (0 for the first file of a recording), or why it has none that reads as one."""
    if not part.metadata:
        return f"{part.path}: no irtrack metadata: not a file of a recording (python -m onboard --record)"
    text = part.metadata.get("file_index", "0")
    index = index_of(text)
    if index is None:
        return f"{part.path}: metadata file_index {text!r} is not a file number"
    return index


def index_of(text: str) -> int | None:
    """A metadata ``file_index`` as the recorder writes it (ASCII digits) read as a number, else None.  Not
    ``str.isdigit`` alone: it holds for a superscript two, which ``int`` cannot read, and for other scripts' digits."""
    return int(text) if text.isascii() and text.isdigit() else None


def _started(part: FilePart) -> datetime.datetime | None:
    """When the file was opened; a time without a zone is taken as UTC, what the field's name says (compared with
    the recorder's own, which says +00:00, it would raise TypeError)."""
    try:
        t = datetime.datetime.fromisoformat(part.metadata["started_utc"])
    except (KeyError, TypeError, ValueError):
        return None
    return t if t.tzinfo is not None else t.replace(tzinfo=datetime.UTC)


def _other_recording(part: FilePart, first: FilePart, before: FilePart) -> str | None:
    """Why ``part`` is not of ``first``'s recording (``before``: the part given just before it), or None."""
    ids = part.metadata.get("recording_id"), first.metadata.get("recording_id")
    if ids[0] is not None or ids[1] is not None:
        if ids[0] == ids[1]:
            return None
        return (
            f"{part.path}: of another recording than {first.path} (recording_id {ids[0] or 'none'}, not "
            f"{ids[1] or 'none'})"
        )
    for name in SAME_IN_EVERY_FILE:
        if part.metadata.get(name) != first.metadata.get(name):
            return f"{part.path}: of another recording than {first.path} (its metadata {name} differs)"
    t, t_before = _started(part), _started(before)
    if t is not None and t_before is not None and t < t_before:
        return (
            f"{part.path}: of another recording than {before.path} (opened at {part.metadata['started_utc']}, before "
            f"it: {before.metadata['started_utc']})"
        )
    if part.first_frame_us is not None and before.last_frame_us is not None:
        if part.first_frame_us <= before.last_frame_us:
            return (
                f"{part.path}: of another recording than {before.path} (its first frame, time_boot_us "
                f"{part.first_frame_us}, is not after that file's last, {before.last_frame_us})"
            )
    return None


def parts_problem(parts: Sequence[FilePart]) -> str | None:
    """Why ``parts`` (in the order given) are not one recording's files each once, in order, without a gap -- one
    line naming the file that is wrong and what is wrong with it -- or None.  The first need not be file 0 (an
    older file deleted by ``record.max_files``): the caller says so."""
    if not parts:
        return "no recording given"
    indexes = []
    for part in parts:
        index = file_index(part)
        if isinstance(index, str):
            return index
        indexes.append(index)
    for k in range(1, len(parts)):
        part, before = parts[k], parts[k - 1]
        other = _other_recording(part, parts[0], before)
        if other is not None:
            return other
        index, index_before = indexes[k], indexes[k - 1]
        if index == index_before + 1:
            continue
        later = set(indexes[k + 1 :])
        if index <= index_before or any(i in later for i in range(index_before + 1, index)):
            given = "again" if index == index_before else f"after file {index_before} ({before.path})"
            return (
                f"{part.path}: file {index} of its recording, given {given}: give each file once, in order "
                "(FILE.mcap FILE.1.mcap FILE.2.mcap ...; a shell's FILE.*.mcap puts FILE.10 before FILE.2)"
            )
        missing = f"file {index_before + 1}" if index == index_before + 2 else f"files {index_before + 1}..{index - 1}"
        return (
            f"{part.path}: file {index} of its recording, after file {index_before} ({before.path}): {missing} missing"
        )
    return None
