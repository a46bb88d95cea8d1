"""``python -m onboard``: the onboard daemon (entry point; see :mod:`onboard.app.service`).

    python -m onboard --config config/onboard.yaml [--vehicle uav1] [--mavlink udpin:127.0.0.1:14540]
                      [--zenoh-connect ENDPOINT]... [--zenoh-listen ENDPOINT]... [--zenoh-config FILE]
                      [--zenoh-multicast-scouting | --no-zenoh-multicast-scouting]
                      [--gcs ENDPOINT]... [--video-udp HOST:PORT] [--record FILE.mcap] [--live-view PORT]
                      [--log-level LEVEL] [--log-format text|json] [--set FIELD.PATH=VALUE]...
                      [--check] [--print-config]

Configuration: built-in defaults < ``--config`` file < ``IRTRACK_<SECTION>_<FIELD>`` environment
variables < command-line options (each option overrides its config field; ``--zenoh-connect`` /
``--zenoh-listen`` given once or more replace the file's list).  ``--check`` validates and exits
0: the values, and what the start would refuse on disk (the zenoh config file, a liveness path that is a
folder or a file with content, or in a folder where no file can be made), its ``ok`` line naming what it checked
(no link is opened); ``--print-config`` prints the effective configuration as YAML and exits.

Exit codes: 0 clean shutdown (SIGTERM / SIGINT / SIGHUP; Ctrl-C too, even while starting, without a
traceback) or successful ``--check``; 2 invalid configuration or options, or a zenoh session that cannot
open (port in use ...), printed as one line on stderr; 1 an unexpected error, or an estimator worker process that
could not be started (logged in one line, once its fork server has failed).
"""

from __future__ import annotations

from onboard.core.blas import single_thread_blas_env

single_thread_blas_env()  # the pipeline is single-threaded by design: before numpy is imported

import argparse  # noqa: E402
import faulthandler  # noqa: E402
import gc  # noqa: E402
import logging  # noqa: E402
import os  # noqa: E402
import signal  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from typing import Any  # noqa: E402

from onboard.app.cli_args import (  # noqa: E402
    OneLineParser,
    add_config_option,
    add_live_view_option,
    add_set_option,
    add_zenoh_options,
    config_overrides,
)

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_CONFIG = 2
SHUTDOWN_BUDGET_S = 1.8  # SIGTERM -> exit: the daemon promises to be gone within 2 s
HARD_EXIT_MARGIN_S = 0.7  # past the budget: faulthandler dumps the stacks and exits (the timer could not)
#: the service's close is done this long before the budget's force exit: the recorder finishes its file by then
CLOSE_MARGIN_S = 0.3

log = logging.getLogger("onboard")
#: a start that takes longer than this to build the service says why (the kernels compile on a first start)
SLOW_START_S = 3.0


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="python -m onboard", description="irtrack onboard daemon: IR target tracking and 3-D reconstruction."
    )
    add_config_option(p, "YAML configuration (default: built-in defaults; see config/onboard.yaml)")
    p.add_argument(
        "--vehicle", help="vehicle name in the zenoh keys irtrack/<vehicle>/... (config: vehicle; default uav1)"
    )
    p.add_argument(
        "--mavlink",
        metavar="CONNECTION",
        help="autopilot link, e.g. udpin:127.0.0.1:14540 (default), udpout:HOST:PORT, tcp:HOST:PORT, "
        "serial:/dev/ttyS0:921600 (config: mavlink.connection)",
    )
    add_zenoh_options(
        p,
        connect_help="zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447; repeatable (config: zenoh.connect)",
        listen_help="zenoh endpoint to listen on; repeatable (config: zenoh.listen)",
        config_help="zenoh JSON5/JSON/YAML config file (config: zenoh.config_file)",
        scouting_help="enable zenoh multicast scouting (off by default; config: zenoh.multicast_scouting)",
    )
    p.add_argument(
        "--gcs",
        metavar="ENDPOINT",
        action="append",
        help="ground-station endpoint of the MAVLink camera component, e.g. udpout:127.0.0.1:14550; "
        "repeatable (config: gcs.endpoints)",
    )
    p.add_argument(
        "--video-udp",
        metavar="HOST:PORT",
        help="send the IR video (H.264 over RTP; MPEG-TS with --set video.transport=mpegts) to this UDP "
        "destination, e.g. 127.0.0.1:5600 (config: video.destination)",
    )
    p.add_argument(
        "--record",
        metavar="FILE.mcap",
        help="record inputs and outputs to this MCAP file (config: record.path; see onboard/io/record.py)",
    )
    add_live_view_option(
        p,
        "serve the channels and a 3-D scene over the Foxglove WebSocket protocol on this port "
        "(bound to live_view.host, 127.0.0.1 by default; config: live_view.port; see onboard/io/live_view.py)",
    )
    p.add_argument(
        "--log-level",
        choices=("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"),
        type=str.upper,
        help="log level (config: logging.level)",
    )
    p.add_argument("--log-format", choices=("text", "json"), help="log line format (config: logging.format)")
    add_set_option(p, "override any config field, e.g. --set estimator.window_s=8; repeatable")
    p.add_argument("--check", action="store_true", help="validate the configuration and exit 0")
    p.add_argument("--print-config", action="store_true", help="print the effective configuration as YAML and exit")
    return p


def _overrides(args: argparse.Namespace) -> dict:
    """Each option's config field, over the ``--set`` ones."""
    fields = (
        ("vehicle", args.vehicle, "--vehicle"),
        ("mavlink.connection", args.mavlink, "--mavlink"),
        ("zenoh.connect", args.zenoh_connect, "--zenoh-connect"),
        ("zenoh.listen", args.zenoh_listen, "--zenoh-listen"),
        ("zenoh.config_file", args.zenoh_config, "--zenoh-config"),
        ("zenoh.multicast_scouting", args.zenoh_scouting, "--zenoh-multicast-scouting"),
        ("gcs.endpoints", args.gcs, "--gcs"),
        ("video.destination", args.video_udp, "--video-udp"),
        ("record.path", args.record, "--record"),
        ("live_view.port", args.live_view, "--live-view"),
        ("logging.level", args.log_level, "--log-level"),
        ("logging.format", args.log_format, "--log-format"),
    )
    return config_overrides(args.set, fields)


# --------------------------------------------------------------------------- main


from onboard.app.logs import setup_logging  # noqa: E402  (the daemon and its estimator process log alike)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _run(args)
    except KeyboardInterrupt:  # a Ctrl-C before the signal handlers are installed: still a clean stop
        print("interrupted while starting: nothing was running yet", file=sys.stderr)
        return EXIT_OK


class _StopSignals:
    """The handler of SIGTERM, SIGINT and SIGHUP: before the service is built a signal is remembered (the
    service is stopped once built, before it serves); after, it asks the service to stop, with a budget."""

    SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)  # SIGHUP: a closed terminal, the same clean exit

    def __init__(self) -> None:
        self.service: Any = None  # the OnboardService, once built
        self.early: list[int] = []  # signals that came while it was being built
        self.deadline_s: float | None = None  # time.monotonic() the service's close must be done by

    def __call__(self, signum: int, _frame: Any) -> None:
        service = self.service
        if service is None:
            self.early.append(signum)
            return
        if service.stopping:
            return
        log.info("signal %s: shutting down", signal.Signals(signum).name)
        self.deadline_s = time.monotonic() + SHUTDOWN_BUDGET_S - CLOSE_MARGIN_S
        service.request_stop()
        # a last resort: whatever hangs, the process is gone within the budget
        timer = threading.Timer(SHUTDOWN_BUDGET_S, _force_exit)
        timer.daemon = True
        timer.start()
        # and if the timer cannot run (a thread stuck in native code holding the GIL, a log write blocked on a
        # full pipe), faulthandler's own C thread dumps every thread's stack to stderr and exits with status 1,
        # without the GIL: the hang is then diagnosable instead of a process that never ends
        faulthandler.dump_traceback_later(SHUTDOWN_BUDGET_S + HARD_EXIT_MARGIN_S, exit=True)


def _run(args: argparse.Namespace) -> int:
    # from the start (importing numpy, scipy, OpenCV and starting the estimator process take a second or
    # more): a Ctrl-C or SIGTERM then is a clean stop too, not a traceback from the middle of an import
    stop = _StopSignals()
    previous = {sig: signal.signal(sig, stop) for sig in stop.SIGNALS}
    try:
        from onboard.app.parent_watch import end_with_parent

        end_with_parent()  # started by a launcher that asked for it (groundsim demo): ends when that process does
        try:
            return _serve(args, stop)
        except RuntimeError as exc:
            # numba caches the compiled kernels as their modules are imported, and refuses to without a folder it
            # may write: the operator's environment, said in one line
            if "no locator available" not in str(exc):
                raise
            print(
                f"numba: no writable cache for the compiled kernels ({exc}): set NUMBA_CACHE_DIR to a folder this "
                "user may write (deploy/README.md, 'Start: the compiled kernels')",
                file=sys.stderr,
            )
            return EXIT_CONFIG
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def raise_open_files_limit() -> int | None:
    """Raise this process's soft limit of open files to its hard limit and return it (None where it cannot be read).
    The live view's server stops accepting for good once a burst of clients has used every descriptor (1024 by
    default on Linux): the hard limit (often 2^20 in a container) leaves the daemon's own files room."""
    try:
        import resource

        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        if hard != resource.RLIM_INFINITY and soft < hard:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
        return resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    except (ImportError, OSError, ValueError):  # not POSIX, or refused: the limit as it is
        return None


def _check_problem(config, checked: list[str]) -> str | None:
    """For ``--check``, what the start would refuse that the configuration's values alone cannot tell, in one line
    (None: nothing): the zenoh config file, read as the session would read it (no session is opened); a recording
    path where no file can be made; a live view host that does not resolve; the liveness path (a folder, a file
    with content: the start's own check) and its folder, where the daemon makes and deletes the file.  Appends the
    name of each check made to ``checked``, for the ``ok`` line."""
    import socket

    from onboard.app.health import claim_health_file, health_folder_problem
    from onboard.core.errors import ConfigError
    from onboard.io.record_files import free_disk_bytes, record_path_problem
    from onboard.io.zenoh_session import DAEMON_CONFIG_FILE_FIELD, ZenohConfigError, build_config

    try:
        build_config(config.zenoh, max_payload_bytes=config.input.max_frame_bytes, file_option=DAEMON_CONFIG_FILE_FIELD)
    except ZenohConfigError as exc:
        return str(exc)
    checked.append("zenoh config")
    if config.record.path:
        problem = record_path_problem(config.record.path)
        if problem is not None:
            return f"record.path: cannot write {problem}"
        free, floor = free_disk_bytes(config.record.path), config.record.min_free_bytes
        if free is not None and free < floor:
            # the start would fly unrecorded (said then as a warning): a check that says a bare 'ok' here is the
            # surprise the operator runs it to avoid; the write test's empty file needs no space at all
            checked.append(
                f"record.path writable but {free / 1e6:.0f} MB free, under record.min_free_mb "
                f"({config.record.min_free_mb:g}): the daemon would fly unrecorded"
            )
        else:
            checked.append("record.path writable")
    if config.live_view.port is not None:
        try:
            socket.getaddrinfo(config.live_view.host, config.live_view.port, type=socket.SOCK_STREAM)
        except OSError as exc:
            return f"live_view.host: cannot resolve {config.live_view.host!r}: {exc.strerror or exc}"
        checked.append("live_view.host resolves")
    if config.output.health_file:
        try:
            claim_health_file(config.output.health_file)
        except ConfigError as exc:
            return str(exc)
        problem = health_folder_problem(config.output.health_file)
        if problem is not None:
            # the daemon would run, its liveness file never made: the container's health check calls it dead
            return f"output.health_file: cannot make {config.output.health_file}: {problem}"
        checked.append("output.health_file writable")
    return None


def _serve(args: argparse.Namespace, stop: _StopSignals) -> int:
    from onboard.app.config import OnboardConfigError, config_to_dict, env_overrides, load_config
    from onboard.core.errors import IrtrackError

    overrides = _overrides(args)
    try:
        config = load_config(args.config, overrides)
    except OnboardConfigError as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_CONFIG
    if stop.early:
        return _stopped_while_starting(stop.early)
    if args.print_config:
        import yaml

        sys.stdout.write(yaml.safe_dump(config_to_dict(config), sort_keys=False))
        return EXIT_OK
    if args.check:
        checked = ["every field"]  # load_config: values, ports, endpoints
        problem = _check_problem(config, checked)
        if problem is not None:
            print(f"{args.config or '(defaults)'}: {problem}", file=sys.stderr)
            return EXIT_CONFIG
        # what was checked, and that no link was tried: an ok says nothing of a peer, an autopilot or a camera;
        # and what was checked beside the file, since the same file checks otherwise without the variables set
        # here or the options given (the container's environment differs from the shell's)
        beside = {**env_overrides(), **overrides}
        with_text = " with " + ", ".join(f"{p} ({src})" for p, (_v, src) in beside.items()) if beside else ""
        print(f"{args.config or '(defaults)'}{with_text}: ok ({', '.join(checked)}; no link opened)")
        return EXIT_OK

    setup_logging(config.logging.level, config.logging.format)
    sys.setswitchinterval(0.001)  # the pipeline, estimator and MAVLink threads share the GIL
    raise_open_files_limit()
    import cv2

    cv2.setNumThreads(1)  # OpenCV's own pool would fight the pipeline for the cores

    from onboard.app.numba_seed import seed_numba_cache

    seed_numba_cache()  # before any compiled kernel is loaded (the image chain's, the estimator's, in its worker too)
    # the first start after an install compiles the numba kernels (10-30 s, silent): said once that is under way
    slow = threading.Timer(
        SLOW_START_S,
        log.info,
        (
            "loading the image chain and the estimator: their compiled kernels are being built (the first start after "
            "an install, 10-30 s; later starts read them from numba's cache)",
        ),
    )
    slow.daemon = True
    slow.start()
    try:
        from onboard.app.service import OnboardService

        built = OnboardService(config)
    except IrtrackError as exc:
        print(f"{args.config or '(defaults)'}: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    finally:
        slow.cancel()
    if stop.early:
        built.close(0.5)
        return _stopped_while_starting(stop.early)
    service = stop.service = built
    if stop.early:  # came between the check and the assignment
        service.request_stop()

    try:
        service.start()
    except IrtrackError as exc:
        service.close(0.5)
        print(str(exc), file=sys.stderr)
        return EXIT_CONFIG
    # what start-up made (modules, config, sessions, the estimator's copy) lives as long as the daemon: out of the
    # collector's generations, so that its full collections walk only what the frames make
    gc.freeze()
    from onboard.app.estimator_worker import EstimatorStartError

    try:
        service.run()
    except EstimatorStartError as exc:  # spawned while the daemon started: one line, as a start that fails
        log.error("%s", exc)
        service.close(0.5, stop.deadline_s)
        return EXIT_ERROR
    except Exception:  # noqa: BLE001 - log, close, non-zero exit
        log.exception("onboard service failed")
        service.close(0.5, stop.deadline_s)
        return EXIT_ERROR
    service.close(0.5, stop.deadline_s)  # within the budget: the recording ends with its summary
    logging.shutdown()
    return EXIT_OK


def _stopped_while_starting(signals: list[int]) -> int:
    print(f"signal {signal.Signals(signals[0]).name} while starting: stopped before serving", file=sys.stderr)
    return EXIT_OK


def _force_exit() -> None:
    log.error("shutdown took longer than %.1f s: exiting now", SHUTDOWN_BUDGET_S)
    logging.shutdown()
    os._exit(EXIT_ERROR)


if __name__ == "__main__":
    sys.exit(main())
