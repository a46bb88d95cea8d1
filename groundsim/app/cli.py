"""Command line of the ground simulator: ``python -m groundsim <command> [options]``.

Commands are argparse subparsers registered in :data:`COMMANDS`: one ``(name, help, add)`` entry
per command, where ``add(parser)`` declares the command's options and sets
``parser.set_defaults(handler=fn)``; ``fn(args) -> int`` is the command's exit code.  ``run`` is
here; ``eval``, ``demo``, ``dataset`` and ``campaign`` (:mod:`groundsim.evaluation`) and ``report``
(:mod:`groundsim.app.report`) are added the same way, without touching ``run``'s code.  Every command
gets ``--log-level``; the log lines are the daemon's logfmt (:mod:`onboard.app.logs`).

Errors: any :class:`~onboard.core.errors.IrtrackError` escaping a handler (bad scenario, unknown key,
port in use, unreachable zenoh peer, ...) and any command-line mistake are printed as ONE line
``groundsim <command>: error: <message>`` on stderr with exit code 2 (no traceback).  Ctrl-C ends a
command with one line ``interrupted: <what was kept>`` and exit code 130
(:mod:`groundsim.io.stop_signals`).  Heavy modules (JSBSim, zenoh, OpenCV) are imported by the
handlers, not here.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from pathlib import Path

from groundsim.app.report import add_report
from groundsim.io.stop_signals import EXIT_INTERRUPTED, install_stop_signals, print_interrupted
from onboard.app.cli_args import EXIT_USAGE, OneLineParser, exit_code_of
from onboard.app.logs import setup_logging
from onboard.core.errors import ConfigError, IrtrackError

__all__ = ["COMMANDS", "EXIT_ERROR", "EXIT_INTERRUPTED", "build_parser", "main"]

log = logging.getLogger(__name__)

EXIT_ERROR = 2  # bad input of any kind: one line on stderr
DEFAULT_SCENARIO = "P1"
DEFAULT_MAVLINK = "udpout:127.0.0.1:14540"  # = groundsim.io.mavlink_vehicle.DEFAULT_CONNECTION (not imported: pymavlink is slow to load)
DEFAULT_VEHICLE = "uav1"  # = onboard.io.zenoh_session.DEFAULT_VEHICLE
DEFAULT_ZENOH_CONNECT_TIMEOUT_S = 5.0
LOG_LEVELS = ("debug", "info", "warning", "error")


class _Parser(OneLineParser):
    error_format = "{prog}: error: {message} (see --help)"  # as a handler's errors ("groundsim <command>: error: ...")


# --------------------------------------------------------------------------- run


# the options several commands declare, each with its own default or help text


def _scenario_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--scenario",
        default=DEFAULT_SCENARIO,
        metavar="FILE|NAME",
        help="scenario YAML file, or a shipped scenario's name (default: %(default)s)",
    )


def _scenarios_and_seeds_options(p: argparse.ArgumentParser, scenarios: str, seeds: int, seeds_help: str) -> None:
    """``--scenario`` (repeatable lists, default: ``scenarios``) and ``--seeds N``."""
    _scenarios_option(p, scenarios)
    p.add_argument("--seeds", type=int, default=seeds, metavar="N", help=seeds_help)


def _scenarios_option(p: argparse.ArgumentParser, scenarios: str) -> None:
    """``--scenario`` as repeatable lists (default: ``scenarios``)."""
    p.add_argument(
        "--scenario",
        action="append",
        nargs="+",
        default=None,
        metavar="FILE|NAME",
        help=f"scenario YAML file(s) or shipped names, repeatable (default: {scenarios})",
    )


def _duration_option(p: argparse.ArgumentParser, help_text: str, default: float | None = None) -> None:
    p.add_argument("--duration", type=float, default=default, metavar="S", help=help_text)


def _workers_option(p: argparse.ArgumentParser, help_text: str) -> None:
    p.add_argument("--workers", type=int, default=None, metavar="N", help=help_text)


def _run_timeout_option(p: argparse.ArgumentParser, per: str, unenforced: str = "with --workers 1") -> None:
    p.add_argument(
        "--run-timeout",
        type=float,
        default=None,
        metavar="S",
        help=f"wall-clock deadline per {per}, seconds: one still running then (a plug-in that hangs) has its worker"
        " process killed and fails (default: 20 x its simulated seconds + 120 s); needs a pool (2+ workers):"
        f" {unenforced} it is not enforced",
    )


def _onboard_config_option(p: argparse.ArgumentParser, default: str | None, help_text: str) -> None:
    p.add_argument("--onboard-config", default=default, metavar="FILE", help=help_text)


def _nav_noise_option(p: argparse.ArgumentParser, help_text: str, nargs: str | None = None) -> None:
    p.add_argument("--nav-noise", nargs=nargs, default=None, metavar="NAME", help=help_text)


def _camera_clock_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--camera-time-offset-ms",
        default=None,
        metavar="MS[:DRIFT_PPM]",
        help="stamp the frames MS milliseconds late (+ DRIFT_PPM parts per million of the flight time): a camera"
        " clock off the autopilot's (e.g. 50 or 50:20)",
    )


def _gnss_dropout_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--gnss-dropout",
        default=None,
        metavar="START_S:DURATION_S",
        help="a GNSS dropout: from START_S (scenario time) for DURATION_S the vehicle withholds GLOBAL_POSITION_INT"
        " and reports GPS_RAW_INT without a fix, attitude and frames going on (e.g. 8:5)",
    )


def _add_run(p: argparse.ArgumentParser) -> None:
    _scenario_option(p)
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        metavar="N",
        help="run seed: disturbance realisation, render noise, gimbal phases (default: 0)",
    )
    _duration_option(
        p, "simulated seconds (default: the scenario's duration_s; a longer run continues its scripted motions)"
    )
    p.add_argument(
        "--rate",
        default="realtime",
        metavar="realtime|max|FACTOR",
        help="paced to the wall clock, as fast as possible, or FACTOR x real time (default: realtime)",
    )
    p.add_argument(
        "--mavlink",
        action="append",
        default=[],
        metavar="CONN|NAME=CONN",
        help=f"pymavlink connection string (default: {DEFAULT_MAVLINK}); a scenario of several observers takes"
        " NAME=CONN per observer (repeatable; an observer not named sends to udpout:127.0.0.1:<14540 + its index>)",
    )
    p.add_argument(
        "--mavlink-signing-key",
        default=None,
        metavar="FILE",
        help="MAVLink 2 signing: sign every message with the key in FILE and take only verified ones, as an autopilot"
        " with signing on (64 hex digits, 32 raw bytes or a passphrase: the daemon's mavlink.signing_key_file)",
    )
    p.add_argument(
        "--vehicle",
        default=None,
        help=f"zenoh vehicle name: key irtrack/<vehicle>/ir/frame (default: {DEFAULT_VEHICLE}); a scenario of"
        " several observers publishes each on irtrack/<NAME>/ir/frame with its observer's name instead",
    )
    p.add_argument(
        "--utc-error-ms",
        action="append",
        default=[],
        metavar="NAME=MS",
        help="vehicle NAME's SYSTEM_TIME reports UTC off by MS milliseconds (a wrong GNSS time or clock"
        " mapping, for the fusion node's clock check); the truth keeps the true UTC; repeatable",
    )
    p.add_argument(
        "--start-time-utc",
        default=None,
        metavar="now|ISO",
        help="the simulated UTC at scenario time 0 (SYSTEM_TIME, the truth's time_unix_us): an ISO 8601 time"
        " such as 2026-01-01T12:00:00Z, or now (the wall clock at start); default: now with --rate realtime (a real"
        " vehicle's GNSS time, which daemons and the fusion node compare with their own clocks), else the"
        " scenario's start_time_utc, so that runs are reproducible",
    )
    p.add_argument(
        "--zenoh-listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    p.add_argument(
        "--zenoh-connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="zenoh endpoint to connect to (repeatable)",
    )
    p.add_argument(
        "--zenoh-connect-timeout",
        type=float,
        default=DEFAULT_ZENOH_CONNECT_TIMEOUT_S,
        metavar="S",
        help="with --zenoh-connect: fail (exit 2) unless a peer answers within S seconds;"
        " 0 = do not wait, zenoh retries in the background (default: %(default)s)",
    )
    p.add_argument(
        "--zenoh-multicast-scouting", action="store_true", help="enable zenoh multicast scouting (off by default)"
    )
    p.add_argument("--zenoh-config", default=None, metavar="FILE", help="zenoh configuration file (JSON5)")
    _nav_noise_option(
        p,
        "navigation errors of the telemetry: a case of config/noise_cases.yaml (exact, RTK, GNSS, ...;"
        " default: the scenario's nav_noise, RTK unless it says otherwise)",
    )
    _gnss_dropout_option(p)
    _camera_clock_option(p)
    p.add_argument(
        "--truth",
        default=None,
        metavar="PATH",
        help="write the ground-truth CSV here; a scenario of several observers writes one per observer,"
        " PATH's stem + .NAME.csv (out/truth.csv -> out/truth.uav1.csv, out/truth.uav2.csv); missing folders are"
        " made, as --out's of the other commands",
    )
    p.add_argument(
        "--record",
        default=None,
        metavar="FILE.mcap",
        help="record the frames, MAVLink (both ways) and the truth to this MCAP file (onboard/io/record.py); missing"
        " folders are made, as the daemon's --record",
    )
    p.add_argument(
        "--guided",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the vehicle heartbeats as ArduPilot, in LOITER until it has heard the companion (the pilot's hand-over),"
        " then in GUIDED, and its observer flies its scripted motion until the first velocity setpoint (SET_POSITION_TARGET_LOCAL_NED) arrives, then follows the setpoints (the daemon"
        " sends none unless guidance.enabled); a ground station may switch it between LOITER (it holds) and GUIDED"
        " (MAV_CMD_DO_SET_MODE or SET_MODE); --no-guided: a generic autopilot that ignores them (default: guided)",
    )
    p.add_argument(
        "--gimbal-frame",
        choices=("earth", "vehicle"),
        default="earth",
        help="the frame of a gimballed vehicle's GIMBAL_DEVICE_ATTITUDE_STATUS (#285): earth (YAW_IN_EARTH_FRAME |"
        " PITCH_LOCK | YAW_LOCK, delta_yaw = vehicle yaw) or vehicle (ArduPilot's: ROLL_LOCK | PITCH_LOCK | YAW_IN_VEHICLE_FRAME |"
        " YAW_LOCK, delta_yaw NaN, stamped when sent; the daemon turns it with the vehicle's attitude)"
        " (default: %(default)s)",
    )
    p.add_argument(
        "--no-render", action="store_true", help="do not render or publish IR frames (MAVLink and truth only)"
    )
    p.add_argument(
        "--rt-priority",
        type=int,
        default=None,
        metavar="N",
        help="paced runs: ask Linux for SCHED_FIFO priority N (1-99; needs CAP_SYS_NICE, otherwise a"
        " warning and normal priority) so a busy machine does not delay the frames",
    )
    p.set_defaults(handler=_cmd_run)


def _run_config(args):
    """argparse namespace -> RunConfig (scenario loaded, every option validated)."""
    from groundsim.world.scenario import load_scenario, resolve_scenario_path

    scenario = load_scenario(resolve_scenario_path(args.scenario))  # first: a bad file fails fast

    from groundsim.app.run import RateSpec, RunConfig, mavlink_endpoints, parse_start_time, utc_errors
    from groundsim.world.nav_errors import InjectedErrors
    from onboard.io.zenoh_session import check_vehicle_name, config_from_options

    rate = RateSpec.parse(args.rate)
    if args.zenoh_connect_timeout < 0 or args.zenoh_connect_timeout != args.zenoh_connect_timeout:
        raise ConfigError(f"--zenoh-connect-timeout: expected >= 0 seconds, got {args.zenoh_connect_timeout}")
    timeout = args.zenoh_connect_timeout if (args.zenoh_connect and args.zenoh_connect_timeout > 0) else None
    zenoh = config_from_options(
        connect=tuple(args.zenoh_connect),
        listen=tuple(args.zenoh_listen),
        config_file=args.zenoh_config,
        multicast_scouting=True if args.zenoh_multicast_scouting else None,
        connect_timeout_s=timeout,
    )
    if scenario.is_fleet and args.vehicle is not None:
        raise ConfigError(
            f"--vehicle: {scenario.name} has several observers, each published under its own name"
            f" ({', '.join(o.name for o in scenario.observers)}); expected no --vehicle"
        )
    if args.vehicle is not None:
        try:
            check_vehicle_name(args.vehicle)
        except ConfigError as exc:
            raise ConfigError(f"--vehicle: {exc}") from None
    vehicle = args.vehicle or DEFAULT_VEHICLE
    from onboard.app.output_files import same_file_clash

    scenario_file = str(resolve_scenario_path(args.scenario))
    clash = same_file_clash([("--truth", args.truth), ("--record", args.record)], [("--scenario", scenario_file)])
    if clash is not None:
        raise ConfigError(clash)
    for option, path in (("--truth", args.truth), ("--record", args.record)):
        if path:
            _check_output_folder(option, path)
    endpoints = mavlink_endpoints(scenario, args.mavlink, vehicle)
    if not args.no_render and not (
        args.zenoh_connect or args.zenoh_listen or args.zenoh_config or args.zenoh_multicast_scouting
    ):
        # the run is otherwise silent about it: frames "published" to nobody, and the daemon only says no_frames
        log.warning(
            "no --zenoh-connect, --zenoh-listen or --zenoh-config: the IR frames go to a zenoh session no daemon can "
            "reach (multicast scouting is off); e.g. --zenoh-connect tcp/127.0.0.1:7447, the shipped daemon's listener"
        )
    start = args.start_time_utc if args.start_time_utc is not None else ("now" if rate.factor == 1.0 else None)
    return RunConfig(
        scenario=scenario,
        run_seed=args.seed,
        duration_s=args.duration,
        rate=rate,
        mavlink=DEFAULT_MAVLINK if scenario.is_fleet else endpoints[0][1],
        mavlink_by_vehicle=endpoints if scenario.is_fleet else (),
        utc_error_us=utc_errors(scenario, args.utc_error_ms, vehicle),
        start_time_unix_us=parse_start_time(start),
        start_time_now=str(start).strip().lower() == "now",
        vehicle=vehicle,
        zenoh=zenoh,
        truth_path=Path(args.truth) if args.truth else None,
        render=not args.no_render,
        injected=InjectedErrors.from_options(args.nav_noise, args.gnss_dropout, args.camera_time_offset_ms),
        record_path=Path(args.record) if args.record else None,
        guided=bool(getattr(args, "guided", True)),
        gimbal_frame=getattr(args, "gimbal_frame", "earth"),
        signing_key=_signing_key(getattr(args, "mavlink_signing_key", None)),
    )


def _check_output_folder(option: str, path: str) -> None:
    """A ConfigError when a file stands where ``path``'s folder, or one of its missing parents, would be made.  Both
    outputs make missing folders, but met a file in the way in words of their own ('Not a directory' from the truth
    file's open, 'File exists' from the recorder's makedirs)."""
    existing = os.path.dirname(os.path.abspath(path))
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        raise ConfigError(f"{option} {path}: cannot write: {existing} is a file, not a folder")


def _signing_key(path: str | None) -> bytes | None:
    """The --mavlink-signing-key file's key, read as the daemon reads mavlink.signing_key_file."""
    if path is None:
        return None
    from onboard.io.mavlink_signing import SigningKeyError, load_signing_key

    try:
        return load_signing_key(path, None)
    except SigningKeyError as exc:
        raise ConfigError(f"--mavlink-signing-key: expected {exc.expected}, got {exc.got}") from None


def _single_threaded_opencv() -> None:
    """One OpenCV thread: the loop is single-threaded by design and its images are small; worker
    threads only add wake-up latency to a paced run on a busy machine."""
    try:
        import cv2

        cv2.setNumThreads(1)
    except Exception:  # noqa: BLE001 - an optimisation only
        pass


def realtime_priority(priority: int | None, paced: bool) -> None:
    """``--rt-priority``: SCHED_FIFO for this process (threads started later inherit it).

    Opt-in only: a paced loop sleeps most of the time, so it takes little CPU, but a loop that
    cannot keep up would hold a core; not allowed with ``--rate max``.
    """
    if priority is None:
        return
    if not 1 <= priority <= 99:
        raise ConfigError(f"--rt-priority: expected 1..99 (SCHED_FIFO priority), got {priority}")
    if not paced:
        raise ConfigError("--rt-priority: only for a paced --rate (realtime or a factor), not max")
    import os

    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, OSError) as exc:
        log.warning(
            "--rt-priority %d not applied (%s): running at normal priority",
            priority,
            getattr(exc, "strerror", None) or exc,
        )
    else:
        log.info("SCHED_FIFO priority %d", priority)


def _cmd_run(args) -> int:
    """Run; Ctrl-C ends the loop cleanly and exits 130 with one line saying what was written (SIGTERM,
    how the demo stops its simulator, exits 0 as before)."""
    stop = threading.Event()
    received: list[int] = []
    restore = install_stop_signals(stop, received)
    try:
        from onboard.app.parent_watch import end_with_parent

        end_with_parent()  # started by a demo: ends with it, even one killed outright (a SIGTERM, handled above)
        config = _run_config(args)
        if stop.is_set():
            return _run_interrupted(received, None, None)
        realtime_priority(args.rt_priority, config.rate.paced)
        _single_threaded_opencv()
        from groundsim.app.run import run

        report = run(config, stop=stop)
    finally:
        restore()
    return _run_interrupted(received, config, report)


def _run_interrupted(received: list[int], config, report) -> int:
    """0, or (after a SIGINT) the interrupted line and EXIT_INTERRUPTED."""
    if signal.SIGINT not in received:
        return 0
    if report is None or report.frames == 0:
        kept = "nothing written"
    else:
        kept = f"{report.frames} of {report.frames_total} frames sent"
        if config.truth_path is not None:
            where = config.truth_path
            if config.scenario.is_fleet:
                where = where.with_name(f"{where.stem}.<NAME>{where.suffix or '.csv'}")
            kept += f"; truth of those frames in {where}"
        if config.record_path is not None:
            files = report.record_files or (str(config.record_path),)
            kept += f"; recording in {', '.join(files)}"
    return print_interrupted(kept)


# --------------------------------------------------------------------------- eval, demo, dataset, campaign
# (groundsim.evaluation; imported when the command runs, so that `run` starts without them)


def _cmd_eval(args) -> int:
    from groundsim.app.eval_command import cmd_eval

    return cmd_eval(args)


def _cmd_demo(args) -> int:
    from groundsim.evaluation.demo import cmd_demo

    return cmd_demo(args)


def _cmd_dataset(args) -> int:
    from groundsim.evaluation.dataset import cmd_dataset

    return cmd_dataset(args)


def _cmd_campaign(args) -> int:
    from groundsim.evaluation.campaign import cmd_campaign

    return cmd_campaign(args)


def _cmd_scenes(args) -> int:
    from groundsim.evaluation.scenes import cmd_scenes

    return cmd_scenes(args)


def _add_eval(p: argparse.ArgumentParser) -> None:
    _scenarios_and_seeds_options(p, "P1 P2 P3", 5, "run seeds 0..N-1 per scenario (default: %(default)s)")
    p.add_argument(
        "--out",
        default="out/eval",
        metavar="DIR",
        help="report directory: new, empty or an earlier eval's, whose report is replaced (default: %(default)s)",
    )
    _workers_option(p, "worker processes (default: min(2, CPUs))")
    _duration_option(
        p, "simulated seconds per run (default: the scenario's duration_s; longer continues its scripted motions)"
    )
    _run_timeout_option(p, "run")
    p.add_argument(
        "--pixel-sigma",
        type=float,
        default=None,
        metavar="PX",
        help="perfect-centroid baseline noise, px per axis (default: the image chain's own centroid error,"
        " measured per run)",
    )
    _nav_noise_option(
        p,
        "navigation errors of the telemetry, cases of config/noise_cases.yaml; several = every scenario"
        " with each, side by side (default: each scenario's nav_noise, RTK unless it says otherwise;"
        " e.g. --nav-noise RTK exact)",
        nargs="+",
    )
    _gnss_dropout_option(p)
    _camera_clock_option(p)
    p.add_argument(
        "--estimator",
        default=None,
        metavar="NAME",
        help="trajectory estimator plug-in: a name registered under the irtrack.estimators entry point"
        " group (map, paper, rpekf, ...) or module:Attribute (default: the configuration's MAP estimator)",
    )
    p.add_argument(
        "--tracker",
        default=None,
        metavar="NAME",
        help="image chain plug-in: a name registered under the irtrack.trackers entry point group (objects,"
        " single, ...) or module:Attribute (default: the configuration's imaging.chain)",
    )
    p.add_argument("--no-batch", action="store_true", help="skip the whole-flight MAP columns and the CRB")
    p.add_argument(
        "--gimbal-frame",
        choices=("earth", "vehicle"),
        default="earth",
        help="the frame a gimballed observer's #285 is encoded in, as groundsim run --gimbal-frame (default: earth)",
    )
    p.add_argument(
        "--guidance",
        action="store_true",
        help="observer guidance in the loop: the observer flies its scripted motion until the first setpoint, then"
        " the setpoints the daemon's guidance tap and gate send for the configuration's guidance section (as"
        " guidance.enabled: the advice, ended by a lost target or a newer answer); prints the guidance summary",
    )
    _onboard_config_option(
        p,
        None,
        "the daemon's configuration (default: config/onboard.yaml, the shipped one, with the"
        " scenario's camera, mount and origin)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_eval)


def _add_demo(p: argparse.ArgumentParser) -> None:
    _scenario_option(p)
    _duration_option(
        p,
        "seconds to fly in real time; a shorter scenario is extended (default: 20, or as long as the scenario can fly)",
    )
    p.add_argument("--seed", type=int, default=0, metavar="N", help="run seed (default: 0)")
    p.add_argument(
        "--out", default="out/demo", metavar="DIR", help="where the truth, tracks and report go (default: %(default)s)"
    )
    _onboard_config_option(
        p,
        "config/onboard.yaml",
        "the daemon's configuration, with the scenario's camera, mount and origin (default:"
        " %(default)s, the shipped one, found in the installed tree from any folder)",
    )
    _nav_noise_option(
        p,
        "the simulator's navigation errors, a case of config/noise_cases.yaml (default: the scenario's nav_noise, RTK)",
    )
    _gnss_dropout_option(p)
    p.add_argument(
        "--mount-as-configured",
        action="store_true",
        help="the daemon keeps --onboard-config's camera mount instead of the scenario's (a wrong mount"
        " configuration: e.g. the shipped fixed pod flown on a gimballed scenario)",
    )
    p.add_argument(
        "--no-eval",
        dest="with_eval",
        action="store_false",
        help="skip the lockstep evaluation (P1-P3, one seed, ~20-40 s) that follows the live run",
    )
    p.add_argument(
        "--live-view",
        type=int,
        default=None,
        metavar="PORT",
        help="serve the daemon's live view (Foxglove WebSocket) on 127.0.0.1:PORT",
    )
    p.set_defaults(handler=_cmd_demo)


def _add_dataset(p: argparse.ArgumentParser) -> None:
    _scenarios_and_seeds_options(p, "P1", 1, "run seeds SEED0..SEED0+N-1 per scenario (default: %(default)s)")
    p.add_argument("--seed0", type=int, default=0, metavar="N", help="first run seed (default: %(default)s)")
    _nav_noise_option(
        p,
        "navigation errors of the measured camera pose, a case of config/noise_cases.yaml"
        " (default: the scenario's nav_noise, RTK)",
    )
    p.add_argument(
        "--format",
        nargs="+",
        default=["mot"],
        choices=("mot", "coco", "obs"),
        help="label formats: MOT Challenge gt/gt.txt + seqinfo.ini, COCO JSON, obs.csv (python -m onboard.reconstruct's "
        "input: the label's pixel, the measured camera pose), any of them (default: mot)",
    )
    p.add_argument(
        "--bit-depth", type=int, default=None, choices=(8, 16), help="PNG bit depth (default: the scenario's encoding)"
    )
    _duration_option(p, "simulated seconds per sequence (default: the scenario's)")
    p.add_argument(
        "--out",
        default="out/dataset",
        metavar="DIR",
        help="dataset directory: new, empty or an earlier dataset's; a dataset there is replaced, refused if it has "
        "sequences this run does not make (default: %(default)s)",
    )
    _workers_option(p, "worker processes, one sequence each (default: min(2, CPUs))")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_dataset)


def _add_campaign(p: argparse.ArgumentParser) -> None:
    p.add_argument("spec", metavar="SPEC.yaml", help="campaign spec (schema: docs/campaigns.md)")
    p.add_argument(
        "--out",
        default=None,
        metavar="DIR",
        help="results directory: new, empty or an earlier campaign's (its runs.jsonl), whose finished runs are not "
        "redone (default: out/campaigns/<name>)",
    )
    _workers_option(p, "worker processes, 1 = in this process (default: the spec's workers, else min(2, CPUs))")
    _run_timeout_option(
        p,
        "job (a synthetic case's algorithms' runs together, a closed-loop run alone; the default is per run, summed)",
        "with --workers 1 or --scheduler",
    )
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="tcp://HOST:PORT",
        help="run the jobs on this Dask distributed scheduler's workers instead of a local pool (docs/campaigns.md)",
    )
    p.add_argument(
        "--fresh",
        action="store_true",
        help="forget the runs already in DIR/runs.jsonl (another campaign's too) and redo them all",
    )
    p.add_argument("--retry-failed", action="store_true", help="redo the runs recorded as failed")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_campaign)


def _add_scenes(p: argparse.ArgumentParser) -> None:
    _scenarios_option(p, "C1 C2 C3 C4 C5 P2")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="run seed (default: %(default)s)")
    p.add_argument("--every", type=int, default=10, metavar="K", help="measure every K-th frame (default: %(default)s)")
    p.add_argument(
        "--clutter",
        action="store_true",
        help="also count the plain point detector's false point-like objects per frame (docs/scenes.md)",
    )
    p.add_argument("--gallery", default=None, metavar="DIR", help="write one labelled picture per scenario to DIR")
    p.add_argument("--no-stats", action="store_true", help="pictures only (with --gallery)")
    p.set_defaults(handler=_cmd_scenes)


# --------------------------------------------------------------------------- registry and entry point

#: (name, one-line help, add(parser)); every command registers here.
COMMANDS = (
    ("run", "fly, render and emit MAVLink + IR frames (+ truth CSV)", _add_run),
    ("eval", "closed loop in lockstep over scenarios and seeds; writes the evaluation report", _add_eval),
    ("demo", "simulator + onboard daemon on loopback with a live status line, then the error table", _add_demo),
    (
        "dataset",
        "export labelled IR sequences (PNG, labels, camera poses, 3-D truth; MOT, COCO, obs.csv)",
        _add_dataset,
    ),
    ("campaign", "sweep scenarios x geometry x noise x algorithms x seeds; resumable table + report", _add_campaign),
    ("report", "plots of a recorded flight (replayed), against the simulator's truth when given", add_report),
    ("scenes", "measure scenes (cloud cover, target contrast, clutter); labelled pictures", _add_scenes),
)


def build_parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--log-level", default="info", choices=LOG_LEVELS, help="logging level (default: info)")
    parser = _Parser(prog="groundsim", description="irtrack ground simulator")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name, help_text, add in COMMANDS:
        p = sub.add_parser(name, help=help_text, description=help_text, parents=[common])
        add(p)
    return parser


def _configure_logging(level: str) -> None:
    """The daemon's log format (:func:`onboard.app.logs.setup_logging`, logfmt text on stderr): one format
    for both programs, so their logs read and grep alike."""
    setup_logging(level.upper(), "text")


def main(argv=None) -> int:
    """Parse, configure logging, dispatch; IrtrackError and usage errors -> one line, exit 2."""
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    prefix = f"groundsim {command}" if command in {c[0] for c in COMMANDS} else "groundsim"
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # a usage mistake (its line printed) is a return code, as a handler's error
        if exc.code != EXIT_USAGE:  # --help
            raise
        return EXIT_ERROR
    _configure_logging(args.log_level)
    try:
        return int(args.handler(args))
    except IrtrackError as exc:
        print(f"{prefix}: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:  # Ctrl-C before a command's own handling took over (imports, set-up)
        return print_interrupted("nothing written")


def entry() -> int:
    """``python -m groundsim``'s exit code: :func:`main`'s, 141 without a traceback when the reader of its output
    leaves (``... | head``; :func:`onboard.app.cli_args.exit_code_of`), and a command a signal stopped settled
    (:func:`groundsim.io.stop_signals.settle_exit`)."""
    from groundsim.io.stop_signals import settle_exit

    return settle_exit(exit_code_of(main))
