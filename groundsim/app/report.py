"""``python -m groundsim report FLIGHT.mcap [--truth SIM.mcap] [--out DIR]``: plots of a recorded flight.

The daemon's recording (``python -m onboard --record``) is replayed through a new pipeline with the
recording's own configuration (:func:`onboard.app.replay.replay`: the estimator inline, the recorded frames
and poses), and the replayed tracks are drawn with the eval report's plots
(:func:`groundsim.evaluation.flight_report.write_flight_report`): the trajectory, the error against the
truth when there is one (the simulator's recording of the same run, ``groundsim run --record``, as
``--truth``; else the flight's own ``/groundsim/truth`` channel, if any), and one frame.  The flight report
belongs to the ground side: the onboard package never imports the simulator.
"""

from __future__ import annotations

import argparse
import logging
import os

from groundsim.io.stop_signals import print_interrupted

__all__ = ["add_report", "cmd_report", "flight_inputs"]

log = logging.getLogger(__name__)

DEFAULT_OUT = "out/report"


def add_report(p: argparse.ArgumentParser) -> None:
    """The ``report`` command's options."""
    p.add_argument("mcap", metavar="FLIGHT.mcap", help="a recording of python -m onboard --record")
    p.add_argument(
        "--truth",
        default=None,
        metavar="SIM.mcap",
        help="the simulator's recording of the same run (groundsim run --record): its /groundsim/truth"
        " channel gives the error plot (default: the flight's own truth channel, if any)",
    )
    p.add_argument("--out", default=DEFAULT_OUT, metavar="DIR", help="report directory (default: %(default)s)")
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
    frames = {}
    for key, copies in rec.frames.items():
        img, _rx_ns = copies[0]
        frames[key] = irframe_from_rawimage(key[0], img, rec.path).pixels
    return poses, frames


def cmd_report(args) -> int:
    """Replay the recording, draw the report; print the files written.  Ctrl-C: one line, exit 130."""
    from groundsim.evaluation.flight_report import write_flight_report
    from groundsim.evaluation.report import make_out_dir
    from onboard.app.replay import config_of, load_recording, replay
    from onboard.core.errors import InputError

    out = make_out_dir(args.out)  # before the replay: a folder that cannot be made fails at once
    before = set(out.glob("*"))
    try:
        rec = load_recording(args.mcap)
        if not rec.inputs:
            raise InputError(
                f"{args.mcap}: no irtrack.frame_input messages (not a recording of python -m onboard --record?)"
            )
        if rec.truncated:
            print(f"note: {args.mcap} is cut short ({rec.truncated}): the report covers it to its last chunk")
        truth = rec.truth
        if args.truth:
            truth = load_recording(args.truth).truth
            if not truth:
                raise InputError(
                    f"--truth {args.truth}: no /groundsim/truth messages (groundsim run --record writes them)"
                )
        config = config_of(rec, args.config)
        res = replay(rec, config)
        log.info("replayed %d frames -> %d tracks in %.2f s", res.frames_fed, len(res.tracks), res.wall_s)
        poses, frames = flight_inputs(rec)
        paths = write_flight_report(out, res.tracks, poses, frames, truth or None, os.path.basename(rec.path))
    except KeyboardInterrupt:
        written = (set(out.glob("*")) - before) if out.is_dir() else set()
        return print_interrupted(f"partial report in {out} ({len(written)} files)" if written else "nothing written")
    print(f"report: {', '.join(str(p) for p in paths)}")
    return 0
