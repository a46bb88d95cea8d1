"""``python -m groundsim report FLIGHT.mcap [FLIGHT.1.mcap ...] [--truth SIM.mcap] [--out DIR]``: plots of a recorded
flight.

The daemon's recording (``python -m onboard --record``) is replayed through a new pipeline with the
recording's own configuration (:func:`onboard.app.replay.replay`: the estimator inline, the recorded frames
and poses), and the replayed tracks are drawn with the eval report's plots
(:func:`groundsim.evaluation.flight_report.write_flight_report`): the trajectory, the error against the
truth when there is one (the simulator's recording of the same run, ``groundsim run --record``, as
``--truth``; else the flight's own ``/groundsim/truth`` channel, if any), and one frame.  The flight report
belongs to the ground side: the onboard package never imports the simulator.  The files of a rotated recording, given
in order, are one flight (:func:`onboard.app.replay.load_flight`, as ``python -m onboard.replay`` reads them: checked
to be one recording's, in order, without a gap); given one file, the report is of that file, and a note names the
files after it.

A ``--truth`` recording that covers only part of the flight (cut short: the simulator killed, a disk full) still
gives the errors of the frames it covers; one note says how much of the flight that is, and ``summary.json``'s
``truth_covers`` records it (:class:`TruthCoverage`), so a median over the first second is not read as the flight's.
"""

from __future__ import annotations

import argparse
import logging
import os
from collections.abc import Mapping
from dataclasses import asdict, dataclass

from groundsim.io.stop_signals import print_interrupted

__all__ = ["TruthCoverage", "add_report", "cmd_report", "flight_inputs", "truth_coverage", "truth_mismatch"]

log = logging.getLogger(__name__)

DEFAULT_OUT = "out/report"
DAEMON_RECORDER = "python -m onboard --record"  # what writes FLIGHT.mcap, as the recording reader's errors say
SIM_RECORDER = "groundsim run --record"  # what writes --truth's file


def add_report(p: argparse.ArgumentParser) -> None:
    """The ``report`` command's options."""
    p.add_argument(
        "mcap",
        metavar="FLIGHT.mcap",
        nargs="+",
        help="a recording of python -m onboard --record; several: the files of one rotated recording, in order "
        "(FLIGHT.mcap FLIGHT.1.mcap ...), reported as one flight",
    )
    p.add_argument(
        "--truth",
        default=None,
        metavar="SIM.mcap",
        help="the simulator's recording of the same run (groundsim run --record): its /groundsim/truth"
        " channel gives the error plot (default: the flight's own truth channel, if any)",
    )
    p.add_argument(
        "--out",
        default=DEFAULT_OUT,
        metavar="DIR",
        help="report directory: new, empty or an earlier report's, whose files are replaced (default: %(default)s)",
    )
    p.add_argument(
        "--config",
        default=None,
        metavar="FILE",
        help="the daemon configuration to replay with (default: the recording's own)",
    )
    p.set_defaults(handler=cmd_report)


def flight_inputs(rec) -> tuple[dict, dict]:
    """``(poses, frames)`` of a :class:`onboard.app.replay.Recording`: the camera position the pipeline used
    for each frame, ``{(seq, time_boot_us): p_cam_ned_m}``, and the pixels of each recorded frame,
    ``{(seq, time_boot_us): (H, W) array}`` (the first copy of a duplicated frame)."""
    from onboard.io.foxglove_messages import irframe_from_rawimage

    poses = {}
    for inp in rec.inputs:
        if inp.get("pose") is not None:
            poses[(int(inp["seq"]), int(inp["time_boot_us"]))] = inp["pose"]["p_cam_ned_m"]
    return poses, _Pixels(rec, irframe_from_rawimage)


class _Pixels(Mapping):
    """``{(seq, time_boot_us): (H, W) pixels}`` of a recording's frames, each read from the file when looked up:
    the report draws one frame, and a flight's frames are ~10 MB a second."""

    def __init__(self, rec, decode) -> None:
        self._rec, self._decode = rec, decode

    def __getitem__(self, key):
        ref, _rx_ns = self._rec.frames[key][0]
        return self._decode(key[0], ref.raw_image(), ref.path).pixels

    def __contains__(self, key) -> bool:  # Mapping's own would read and decode the frame to answer
        return key in self._rec.frames

    def __iter__(self):
        return iter(self._rec.frames)

    def __len__(self) -> int:
        return len(self._rec.frames)


#: a truth recording whose camera looked elsewhere than the flight's telemetry says (median angle between the two
#: optical axes over the frames both have, deg), or whose observer was elsewhere (median, m), is another run's:
#: navigation errors are a tenth of a degree and centimetres (RTK) to a few metres (GNSS); another scenario's
#: camera points at another target (the audit's P1 flight against a P3 truth: 104 deg apart, observers 3 m)
TRUTH_MATCH_MAX_DEG = 5.0
TRUTH_MATCH_MAX_M = 25.0
#: the same angle once the navigation error the truth rows record (``nav_att_err_*_rad``) is put back on their
#: camera: what is left is the telemetry's interpolation and timing (0.05 deg median on a P1 flight, RTK), where
#: the truth of another run whose camera flew the same path turned elsewhere (P1 against P1g, seed 1) stays 1.6 deg
TRUTH_MATCH_NAV_MAX_DEG = 1.0
_NAV_ATT_ERR = ("nav_att_err_n_rad", "nav_att_err_e_rad", "nav_att_err_d_rad")


def truth_mismatch(inputs: list, truth: list) -> str | None:
    """Why ``truth`` (``irtrack.truth/1`` rows) is not the truth of the flight whose pipeline ``inputs`` these are,
    or None: the flight's frames must have truth rows at their capture times, and the camera the truth flew must
    be where, and look where, the flight's telemetry says (medians over the frames both have)."""
    import numpy as np

    from onboard.core.frames import GeodeticOrigin, ned_from_geodetic, rotmat_from_quat, rotmat_from_rotvec

    rows = {int(r["time_boot_us"]): r for r in truth if r.get("time_boot_us") is not None}
    posed = [(int(i["time_boot_us"]), i["pose"]) for i in inputs if i.get("pose") is not None]
    both = [(rows[t], pose) for t, pose in posed if t in rows]
    if not both:
        return f"none of the flight's {len(posed)} posed frames has a truth row at its capture time"
    miss_m, miss_deg = [], []
    with_nav = True  # every row records its navigation error (groundsim's truth does): the tighter bound
    for row, pose in both:
        o = pose["origin"]
        origin = GeodeticOrigin(o["lat_deg"], o["lon_deg"], o["alt_m"])
        truth_ned = ned_from_geodetic(row["observer_lat_deg"], row["observer_lon_deg"], row["observer_alt_m"], origin)
        miss_m.append(float(np.hypot(*(np.asarray(truth_ned[:2]) - np.asarray(pose["p_ned_m"][:2])))))
        R_truth = rotmat_from_quat(np.asarray([row[f"q_ned_from_cam_{c}"] for c in "wxyz"]))
        if all(row.get(k) is not None for k in _NAV_ATT_ERR):  # the camera the telemetry reported (dataset.py's q)
            R_truth = rotmat_from_rotvec(np.asarray([row[k] for k in _NAV_ATT_ERR], dtype=float)) @ R_truth
        else:
            with_nav = False
        axes = rotmat_from_quat(np.asarray(pose["q_ned_from_cam"]))[:, 2] @ R_truth[:, 2]
        miss_deg.append(float(np.degrees(np.arccos(np.clip(axes, -1.0, 1.0)))))
    deg, metres = float(np.median(miss_deg)), float(np.median(miss_m))
    max_deg = TRUTH_MATCH_NAV_MAX_DEG if with_nav else TRUTH_MATCH_MAX_DEG
    if deg > max_deg or metres > TRUTH_MATCH_MAX_M:
        err = " with the navigation error it records" if with_nav else ""
        return (
            f"its camera{err} looked {deg:.1f} deg away from, and its observer was {metres:.0f} m from, where the "
            f"flight's telemetry put them (medians over {len(both)} frames; at most {max_deg:g} deg and "
            f"{TRUTH_MATCH_MAX_M:g} m for one flight): the simulator's recording of another run"
        )
    return None


@dataclass(frozen=True)
class TruthCoverage:
    """How much of a flight a truth recording covers, matched as the report matches them (seq, time_boot_us).

    frames, of_frames
        The flight's frames (its replayed tracks) that have a truth row, and all of them.
    with_3d, of_with_3d
        The same for the frames with a 3-D estimate: the error plot and medians are over ``with_3d`` of them.
    from_s, to_s
        The first and last covered frame, seconds after the flight's first frame (the plots' time axis); None
        when no frame is covered.
    flight_s
        The flight's last frame, seconds after its first.
    cut_short
        Where the truth file was cut (the MCAP reader's words), or None.
    """

    frames: int
    of_frames: int
    with_3d: int
    of_with_3d: int
    from_s: float | None
    to_s: float | None
    flight_s: float
    cut_short: str | None

    @property
    def partial(self) -> bool:
        return self.frames < self.of_frames or self.cut_short is not None

    def note(self, truth_path: str) -> str:
        """The one line that tells the reader of the report how much of the flight its errors cover."""
        what = f"is cut short ({self.cut_short})" if self.cut_short is not None else "covers part of the flight"
        if self.from_s is None:
            span = "none of the flight's frames"
        else:
            span = (
                f"{self.frames} of the flight's {self.of_frames} frames, t = {self.from_s:.1f}..{self.to_s:.1f} s "
                f"of 0..{self.flight_s:.1f} s"
            )
        if self.with_3d:
            errors = f"the errors are of the {self.with_3d} of {self.of_with_3d} frames with a 3-D estimate it covers"
        else:
            errors = f"it covers none of the {self.of_with_3d} frames with a 3-D estimate: the error plot is empty"
        return f"note: --truth {truth_path} {what}: its truth covers {span}; {errors}"


def truth_coverage(tracks: list, truth: list, cut_short: str | None = None) -> TruthCoverage:
    """:class:`TruthCoverage` of ``truth`` (``irtrack.truth/1`` rows) over the flight whose replayed ``tracks``
    (``irtrack.track`` dicts in frame order, at least one) these are; ``cut_short`` the truth file's cut, if any."""
    keys = {(int(r["seq"]), int(r["time_boot_us"])) for r in truth}
    t0_us = int(tracks[0]["time_boot_us"])
    covered = [(int(tr["seq"]), int(tr["time_boot_us"])) in keys for tr in tracks]
    covered_s = [(int(tr["time_boot_us"]) - t0_us) / 1e6 for tr, c in zip(tracks, covered) if c]
    estimated = [c for tr, c in zip(tracks, covered) if tr.get("ned_m") is not None]
    return TruthCoverage(
        frames=len(covered_s),
        of_frames=len(tracks),
        with_3d=sum(estimated),
        of_with_3d=len(estimated),
        from_s=min(covered_s) if covered_s else None,
        to_s=max(covered_s) if covered_s else None,
        flight_s=(int(tracks[-1]["time_boot_us"]) - t0_us) / 1e6,
        cut_short=cut_short,
    )


def _title(rec) -> str:
    """The report's name for the flight: its file, or its first and last file of a rotated recording."""
    files = [os.path.basename(p) for p in rec.files]
    return files[0] if len(files) == 1 else f"{files[0]} .. {files[-1]}"


def cmd_report(args) -> int:
    """Replay the recording, draw the report; print the files written.  Ctrl-C: one line, exit 130."""
    from groundsim.evaluation.flight_report import REPORT_SCHEMA, holds_flight_report, write_flight_report
    from groundsim.evaluation.out_dir import make_out_dir, refuse_foreign_out, writing
    from onboard.app.replay import (
        ReplayProgress,
        config_of,
        load_flight,
        load_recording,
        more_files_note,
        no_frames_text,
        recorder_drops_note,
        replay,
        rotated_part_note,
        stopped_note,
    )
    from onboard.core.errors import InputError

    # the report replaces an earlier one's plots and summary.json by name: only into a folder of its own
    refuse_foreign_out(args.out, holds_flight_report, "groundsim report", f"summary.json of schema {REPORT_SCHEMA}")
    out = make_out_dir(args.out)  # before the replay: a folder that cannot be made fails at once
    before = set(out.glob("*"))
    try:
        rec = load_flight(args.mcap)
        if not rec.inputs:
            raise InputError(no_frames_text(rec))
        if len(rec.files) > 1:
            print(f"one flight in {len(rec.files)} files of a rotated recording: {', '.join(rec.files)}")
        if rec.truncated:
            print(f"note: {rec.name} is cut short ({rec.truncated}): the report covers it to its last chunk")
        for note in (
            rotated_part_note(rec),
            more_files_note(rec, "python -m groundsim report"),
            recorder_drops_note(rec),
            stopped_note(rec),
        ):
            if note is not None:
                print(f"note: {note}")
        truth = rec.truth
        truth_cut = None
        truth_objects = getattr(rec, "truth_objects", [])  # (a stand-in for a Recording may not have it)
        if args.truth:
            try:
                truth_rec = load_recording(args.truth)
            except InputError as exc:
                # the reader's words fit the flight's file, the daemon's recording; --truth is the simulator's
                raise InputError(f"--truth {str(exc).replace(DAEMON_RECORDER, SIM_RECORDER)}") from None
            truth, truth_cut = truth_rec.truth, truth_rec.truncated
            truth_objects = getattr(truth_rec, "truth_objects", [])
            if not truth:
                raise InputError(
                    f"--truth {args.truth}: no /groundsim/truth messages (groundsim run --record writes them)"
                    + (f" before it was cut short ({truth_cut})" if truth_cut else "")
                )
            why = truth_mismatch(rec.inputs, truth)
            if why is not None:
                raise InputError(
                    f"--truth {args.truth}: not the truth of {rec.name}: {why}"
                    + (f" (the file is cut short: {truth_cut})" if truth_cut else "")
                )
        config = config_of(rec, args.config)
        res = replay(rec, config, on_input=ReplayProgress(len(rec.inputs)))  # a line every few seconds
        log.info("replayed %d frames -> %d tracks in %.2f s", res.frames_fed, len(res.tracks), res.wall_s)
        poses, frames = flight_inputs(rec)
        coverage = truth_coverage(res.tracks, truth, truth_cut) if args.truth and res.tracks else None
        # what the replay could not make a track of is said, as onboard.replay says it, and kept in summary.json
        extra: dict = {"frames_missing": res.frames_missing, "frames_refused": res.frames_refused}
        if res.frames_missing or res.frames_refused:
            print(
                f"note: {rec.name}: of the {len(rec.inputs)} frames the daemon took, {res.frames_missing} are missing "
                f"from the file (the recorder dropped them) and {res.frames_refused} were refused in the replay: "
                f"the report is of the {len(res.tracks)} tracks of the rest"
            )
        if coverage is not None and coverage.partial:
            print(coverage.note(args.truth))
            extra["truth_covers"] = asdict(coverage)
        # a full disk while a plot is saved: one line naming --out, as the folder's own checks are
        paths = writing(
            out,
            write_flight_report,
            out,
            res.tracks,
            poses,
            frames,
            truth or None,
            _title(rec),
            extra,
            getattr(res, "objects", None),
            truth_objects,
        )
    except KeyboardInterrupt:
        written = (set(out.glob("*")) - before) if out.is_dir() else set()
        return print_interrupted(f"partial report in {out} ({len(written)} files)" if written else "nothing written")
    print(f"report: {', '.join(str(p) for p in paths)}")
    return 0
