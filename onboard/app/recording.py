"""A recorded flight as replay holds it (:class:`Recording`), and the one-line notes on it that replay and the flight
report print besides its tracks.

:func:`onboard.app.replay.load_recording` and :func:`~onboard.app.replay.load_flight` read a file (or a rotated
recording's files) into a :class:`Recording`; ``python -m onboard.replay`` and ``python -m groundsim report`` then say
what the tracks alone do not: messages the recorder dropped (:func:`recorder_drops_note`), a recording that stopped
before the flight ended (:func:`stopped_note`), a flight replayed from a later file (:func:`rotated_part_note`) or
whose later files were not given (:func:`more_files_note`), and why a recording has nothing to replay
(:func:`no_frames_text`).  Apart from the replay because none of it feeds the pipeline: it reads the recording's
fields (and, for the rotated files, which files lie beside it), never a frame.  Everything is importable from
:mod:`onboard.app.replay` too.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field

from onboard.io.record import FRAME_INPUT_TOPIC

__all__ = [
    "Recording",
    "recorder_drops",
    "recorder_drops_note",
    "stopped_note",
    "rotated_part_note",
    "more_files_note",
    "no_frames_text",
]


@dataclass
class Recording:
    """What replay needs of a file: config text, frames by (seq, time), the pipeline's inputs, tracks, truth, and
    the objects image chain's objects (``irtrack.objects/1`` dicts in file order; empty without that chain)."""

    path: str
    metadata: dict[str, str]
    frames: dict  # (seq, time_boot_us) -> list of (FrameRef, publish time ns) (duplicates kept in order)
    inputs: list  # frame_input dicts in file order
    tracks: list  # recorded track dicts in file order
    truth: list  # irtrack.truth/1 dicts (groundsim recordings)
    first_log_ns: int | None
    last_log_ns: int | None
    truncated: str | None
    counts: dict
    objects: list = field(default_factory=list)
    imaging_poses: dict = field(default_factory=dict)  # (seq, time_boot_us) -> irtrack.imaging_pose/1 dicts in order
    # the recorded daemon's status messages, (log time ns, JSON bytes as published), and each frame input's log time:
    # the live view shows the status as it was, between the frames it came between
    statuses: list = field(default_factory=list)
    input_log_ns: list = field(default_factory=list)
    # the files of a rotated recording replayed as one flight, in order (:func:`~onboard.app.replay.load_flight`;
    # ``path`` is the first); empty for one file
    parts: list = field(default_factory=list)
    # the recorder's irtrack.stopped metadata (reason, stopped_utc) when it stopped before the flight ended, else None
    stopped: dict | None = None
    # the simulator's irtrack.truth_objects/1 dicts in file order (every object's label a frame; groundsim recordings)
    truth_objects: list = field(default_factory=list)

    @property
    def files(self) -> list[str]:
        """The files this recording was read from, in order."""
        return list(self.parts) or [self.path]

    @property
    def name(self) -> str:
        """The recording in a message: its file, or its first file and how many more."""
        more = len(self.files) - 1
        return self.path if more == 0 else f"{self.path} (+{more} file{'s' if more > 1 else ''})"


def recorder_drops(rec: Recording) -> dict[str, int]:
    """Messages the recorder dropped, per topic (its backlog past ``record.queue_mb``, or after it stopped), as the
    last status in the file that says so has it (``record.dropped_by_topic``: over the whole recording, rotated files
    before this one included, up to that status); {} when none says.  Of a flight of several files
    (:func:`~onboard.app.replay.load_flight`) that is its last file's last status: the count is the recording's, so it
    is the flight's (a sum over the files would count each earlier file's drops again), with the files before the
    first given (:func:`rotated_part_note`) included.  The file cannot show them itself: a frame input
    the recorder dropped leaves no trace in it (the frame's ``seq`` gap reads as the daemon's frame queue dropping
    the frame), and replay feeds the pipeline fewer frames than the daemon's took."""
    for _log_ns, data in reversed(rec.statuses):
        try:
            by_topic = json.loads(data)["record"]["dropped_by_topic"]
            return {str(t): n for t, n in by_topic.items() if isinstance(n, int) and n > 0}
        except (ValueError, KeyError, TypeError, AttributeError):  # a status without the recorder's section
            continue
    return {}


def recorder_drops_note(rec: Recording) -> str | None:
    """One line on :func:`recorder_drops` for the replay and the flight report (None: no drop said)."""
    drops = recorder_drops(rec)
    if not drops:
        return None
    inputs = drops.get(FRAME_INPUT_TOPIC, 0)
    return (
        f"{rec.name}: the recorder dropped {sum(drops.values())} messages (its last status in the "
        f"{'file' if len(rec.files) == 1 else 'last file'}, "
        f"record.dropped_by_topic: {', '.join(f'{n} on {t}' for t, n in sorted(drops.items()))})"
        + (
            f"; {inputs} frames the daemon's pipeline took are not in the file, so not replayed: the tracks after "
            "the first of them need not be the flight's"
            if inputs
            else ""
        )
    )


def stopped_note(rec: Recording) -> str | None:
    """One line when the recorder stopped before the flight ended (its ``irtrack.stopped`` metadata), else None: the
    replay ends where the recording did, not where the flight did."""
    stopped = getattr(rec, "stopped", None)  # (a stand-in for a Recording may not have it)
    if stopped is None:
        return None
    reason = str(stopped.get("reason") or "no reason given")
    at = stopped.get("stopped_utc")
    return (
        f"{rec.name}: the recording stopped before the flight ended{f' (at {at})' if at else ''}: {reason}; the "
        "flight went on unrecorded, so the replay ends where the recording did"
    )


def rotated_part_note(rec: Recording) -> str | None:
    """One line when ``rec`` starts at a later file of a rotated recording (its first file's ``file_index`` past 0:
    the daemon's ``FILE.N.mcap``), else None.  The daemon's pipeline went on from the earlier files' frames with their
    tracks, ids and frame count; replay starts it afresh at this file's first frame.  When file 0 is beside it, the
    line says to give it first."""
    from onboard.app.flight_parts import index_of
    from onboard.io.record_files import rotation_base

    index = index_of(rec.metadata.get("file_index", "0"))
    if not index:
        return None
    base = rotation_base(rec.path, index)
    beside = (
        f"; {base} and the files after it are beside it: give them first, in order, to replay the flight"
        if base is not None and os.path.isfile(base)
        else ""
    )
    return (
        f"{rec.path}: file {index} of a rotated recording: replayed from its first frame with no tracks, while the "
        f"daemon's pipeline went on from the {int(index)} file(s) before it: tracks (their ids, their 3-D), objects "
        "and their frame_index need not be the recorded ones; a frame received before the file began is in the one "
        f"before (missing from this one){beside}"
    )


def more_files_note(rec: Recording, command: str) -> str | None:
    """One line when the rotated recording ``rec`` was read from goes on in files beside its last that were not
    given (``FILE.N.mcap`` after it), naming them and the ``command`` line that gives the whole flight; else None.
    They are not read by themselves: the file named is the file replayed (quick; a first file's ``--compare``
    holds alone), and a flight of twelve files is the user's to ask for."""
    from onboard.app.flight_parts import index_of
    from onboard.io.record_files import rotated_path, rotated_paths_after, rotation_base

    first = index_of(rec.metadata.get("file_index", "0"))
    if first is None:
        return None
    base = rotation_base(rec.path, first)
    if base is None:
        return None
    more = rotated_paths_after(base, first + len(rec.files) - 1)
    if not more:
        return None
    before = [rotated_path(base, i) for i in range(first)]
    flight = (before if all(os.path.isfile(p) for p in before) else []) + rec.files + more
    return (
        f"{rec.files[-1]}: the recording goes on in {len(more)} more file(s) beside it, not replayed: "
        f"{', '.join(more)}; the whole flight: {command} {' '.join(flight)}"
    )


def no_frames_text(rec: Recording) -> str:
    """Why a recording without ``irtrack.frame_input`` messages has nothing to replay: a daemon's recording (its
    configuration in the metadata) made while no IR frame came, or not a daemon's recording at all."""
    if rec.metadata.get("config_yaml") is not None:
        return (
            f"{rec.name}: the daemon recorded no frame taken (no irtrack.frame_input messages): no IR frames reached "
            "it while it recorded (the simulator or camera not running, or not on its zenoh key)"
        )
    return f"{rec.name}: no irtrack.frame_input messages (not a recording of python -m onboard --record?)"
