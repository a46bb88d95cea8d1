"""``python -m onboard.watch``: print the daemon's tracks as they arrive, then a one-line summary.

    python -m onboard.watch [--vehicle uav1] [--seconds 30] [--json]
                            [--zenoh-connect ENDPOINT]... [--zenoh-listen ENDPOINT]... [--zenoh-config FILE]
                            [--zenoh-multicast-scouting | --no-zenoh-multicast-scouting]

It subscribes ``irtrack/<vehicle>/track`` (schema ``irtrack.track/2``, :mod:`onboard.core.track`; with
``--vehicle fleet`` the fusion's ``irtrack.fleet_track/1``, :func:`format_fleet_track`) and
prints one line per track (:func:`format_track`): the frame's capture time on the autopilot's boot clock,
the tracker's state, then the 3-D position (WGS84 and local NED) with its 1-sigma per NED axis, the range
and its relative sigma when the estimator has one, else the line of sight (azimuth / elevation), else the
pixel; last the quality verdict ``observable yes|no``.  ``--json`` prints the payloads as received, one
per line, for ``jq`` and friends (the start and summary lines then go to stderr).  Tracks that go back and forth
in ``seq`` or ``time_boot_us`` (:data:`TWO_PUBLISHERS_RETURNS` not newer than the one before) are two publishers
on the key, two daemons of one name: said once on stderr (:func:`two_publishers_line`) and in the summary.

The zenoh options are the daemon's (:mod:`onboard.io.zenoh_session`); with no endpoint and no file the
session connects to ``tcp/127.0.0.1:7447``, where the daemon of ``config/onboard_sim.yaml`` listens, with
multicast scouting off.  The watcher may start before the daemon: zenoh keeps retrying the connection.

It stops after ``--seconds`` (0: until Ctrl-C), closes its session (an open zenoh session keeps a Python
process alive) and prints what it received.  Exit codes: 0 after ``--seconds`` with at least one track; 1
after ``--seconds`` with none (so that a script checking the flow, ``onboard.watch --seconds 30 && ...``,
sees a silent daemon as a failure); 130 on Ctrl-C, with the one line ``interrupted: N tracks received,
...``, and 143 with the same line on SIGTERM; 2 for invalid options or a session that cannot open (one line on
stderr).
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TextIO

from onboard.app.cli_args import OneLineParser, add_zenoh_options, nonnegative_float
from onboard.core.errors import InputError, IrtrackError
from onboard.core.track import Track, track_from_json
from onboard.io.zenoh_session import ZenohConfig, config_from_options, open_session, track_key

__all__ = [
    "DEFAULT_CONNECT",
    "ZENOH_CONNECT_HELP",
    "DEFAULT_SECONDS",
    "NO_TRACK_HINT_S",
    "EXIT_OK",
    "EXIT_NO_TRACK",
    "EXIT_CONFIG",
    "EXIT_INTERRUPTED",
    "WatchCounts",
    "format_track",
    "format_fleet_track",
    "summary_line",
    "two_publishers_line",
    "new_run_line",
    "interrupted_line",
    "build_parser",
    "zenoh_config",
    "main",
]

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"  # the zenoh listener of config/onboard_sim.yaml
DEFAULT_SECONDS = 30.0
NO_TRACK_HINT_S = 10.0  # one track per frame once the simulator runs; its start-up takes seconds
EXIT_OK = 0
EXIT_NO_TRACK = 1
EXIT_CONFIG = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports Ctrl-C
EXIT_TERMINATED = 143  # 128 + SIGTERM
POLL_S = 0.1  # longest wait on the queue: the deadline, Ctrl-C and the no-track hint are checked this often
#: this many tracks not newer than the one before are two publishers on the key, said once (a camera or daemon that
#: restarts goes back once)
TWO_PUBLISHERS_RETURNS = 6


@dataclass
class WatchCounts:
    """What was received so far: tracks, those with a line of sight, a 3-D position, an observable one,
    the boot times (s) of the first position and first observable track, and payloads that were not
    tracks (``bad``)."""

    tracks: int = 0
    with_los: int = 0
    with_position: int = 0
    observable: int = 0
    first_position_s: float | None = None
    first_observable_s: float | None = None
    bad: int = 0
    fleet_tracks: int = 0  # of ``tracks``, the fusion's (which carry no line of sight)
    #: tracks not newer than the one before them (``seq`` or ``time_boot_us`` not ahead): one daemon's tracks
    #: only move forward, so these are two publishers interleaving on the key (:data:`TWO_PUBLISHERS_RETURNS`)
    returns: int = 0
    _last: tuple[int, int] | None = None
    #: the daemon runs (tracks' ``run_id``) seen, in the order first seen: more than one, a restart (or two daemons)
    runs: list[str] = field(default_factory=list)

    def add_run(self, track: Track) -> str | None:
        """Note ``track``'s ``run_id``; the line to say when it is a run not seen before after another, else None."""
        run = track.run_id
        if run is None or run in self.runs:
            return None
        self.runs.append(run)
        return None if len(self.runs) == 1 else new_run_line(track.vehicle, self.runs[-2], run)

    def add_order(self, track: Track) -> bool:
        """Note ``track``'s place in the stream; True when it is the :data:`TWO_PUBLISHERS_RETURNS`-th return (say it
        then, once)."""
        here = (track.seq, track.time_boot_us)
        # either number not ahead: two streams whose seq and time are ordered alike go back in both at each switch,
        # two ordered oppositely (the higher seq, the earlier time) in one or the other; a restart goes back once
        back = self._last is not None and (here[0] <= self._last[0] or here[1] <= self._last[1])
        self._last = here
        if back:
            self.returns += 1
        return back and self.returns == TWO_PUBLISHERS_RETURNS

    def add_fleet(self, obj: dict) -> None:
        """One ``irtrack.fleet_track/1`` (the fusion's output): a position always, a line of sight never, its time
        UTC (no boot time, so no "first at t")."""
        self.tracks += 1
        self.fleet_tracks += 1
        if obj.get("lat_deg") is not None:
            self.with_position += 1
        if obj.get("observable"):
            self.observable += 1

    def add(self, track: Track) -> None:
        t_s = track.time_boot_us / 1e6
        self.tracks += 1
        if track.los is not None:
            self.with_los += 1
        if track.lat_deg is not None:
            self.with_position += 1
            if self.first_position_s is None:
                self.first_position_s = t_s
        if track.observable:
            self.observable += 1
            if self.first_observable_s is None:
                self.first_observable_s = t_s


def _f(x: float | None, fmt: str) -> str:
    return "-" if x is None or not math.isfinite(x) else format(x, fmt)


def _why_no_line_of_sight(track: Track) -> str:
    """Why a track with a pixel has no line of sight: no pose; a coasting tracker's predicted centre (never given
    one); or a measured one with a pose, whose geometry the daemon withholds (a zoom, camera or gimbal mismatch: the
    status's ``geometry`` and ``warnings`` name it)."""
    if track.geometry_withheld:
        return "line of sight withheld: see the status's geometry"
    return "predicted, no line of sight" if track.pose_valid else "no pose"


def format_track(track: Track) -> str:
    """One readable line for ``track``: time, state, what it has (position, line of sight or pixel), verdict.

    ``t`` is the frame's capture time on the autopilot's boot clock, seconds (the simulator's clock reads
    1 s at the start of its flight).  The position's ``sigma`` is the 1-sigma per NED axis, metres;
    ``range R m +-P %`` the camera-to-target range and its posterior sigma relative to it."""
    parts = [f"t {track.time_boot_us / 1e6:8.3f} s", f"{track.state:<9}"]
    if track.lat_deg is not None and track.lon_deg is not None and track.alt_m is not None:
        parts.append(f"lat {track.lat_deg:.6f} lon {track.lon_deg:.6f} alt {track.alt_m:.1f} m")
        if track.p_ned_m is not None:
            n, e, d = track.p_ned_m
            parts.append(f"ned {n:.1f} {e:.1f} {d:.1f} m")
        sigma = track.sigma_ned_m
        if sigma is not None:
            parts.append("sigma " + " ".join(_f(s, ".1f") for s in sigma) + " m")
        if track.range_m is not None:
            rel = track.range_sigma_ratio
            parts.append(f"range {track.range_m:.0f} m" + ("" if rel is None else f" +-{100.0 * rel:.1f} %"))
    elif track.los is not None:
        los = track.los
        parts.append(
            f"los az {los.azimuth_deg:.2f} el {los.elevation_deg:.2f} deg"
            f" (sigma {_f(los.sigma_azimuth_deg, '.2f')} {_f(los.sigma_elevation_deg, '.2f')}), no position yet"
        )
    elif track.u_px is not None and track.v_px is not None:
        parts.append(f"pixel {track.u_px:.1f} {track.v_px:.1f} ({_why_no_line_of_sight(track)})")
    else:
        parts.append("no target")
    parts.append("observable " + ("yes" if track.observable else "no"))
    return "  ".join(parts)


def format_fleet_track(obj: dict) -> str:
    """One readable line for an ``irtrack.fleet_track/1`` (``python -m onboard.fuse``'s ``irtrack/fleet/track``):
    the UTC time of day, the fleet's target id, its position (WGS84, NED about the fleet's origin) with the
    1-sigma per axis, the vehicles whose lines of sight it was triangulated from, and the verdict."""
    t_us = obj.get("time_unix_us")
    when = (
        "-"
        if t_us is None
        else time.strftime("%H:%M:%S", time.gmtime(t_us / 1e6)) + f".{int(t_us) % 1_000_000 // 1000:03d}"
    )
    parts = [f"{when} UTC", f"target {obj.get('target_id')}"]
    lat, lon, alt = obj.get("lat_deg"), obj.get("lon_deg"), obj.get("alt_m")
    if lat is not None and lon is not None and alt is not None:
        parts.append(f"lat {lat:.6f} lon {lon:.6f} alt {alt:.1f} m")
    ned = obj.get("ned_m")
    if ned is not None:
        parts.append("ned " + " ".join(_f(x, ".1f") for x in ned) + " m")
    sigma = obj.get("sigma_ned_m")
    if sigma is not None:
        parts.append("sigma " + " ".join(_f(x, ".1f") for x in sigma) + " m")
    vehicles = [v.get("vehicle") for v in obj.get("vehicles") or [] if isinstance(v, dict)]
    parts.append("from " + (", ".join(str(v) for v in vehicles) if vehicles else "-"))
    parts.append("observable " + ("yes" if obj.get("observable") else "no"))
    return "  ".join(parts)


def _fleet_track(payload: bytes) -> dict | None:
    """The payload as an ``irtrack.fleet_track/1`` object, or None when it is not one."""
    import json

    from onboard.io.fleet_wire import FLEET_TRACK_SCHEMA

    try:
        obj = json.loads(payload)
    except (ValueError, RecursionError):  # (RecursionError: nested too deep)
        return None
    return obj if isinstance(obj, dict) and obj.get("schema") == FLEET_TRACK_SCHEMA else None


def fleet_track_line(obj: dict) -> str | None:
    """:func:`format_fleet_track` of ``obj``, or None when its fields are not of their types (any peer may publish
    on the key: a string for a number, 1e30 microseconds, a number for a list must not end the watcher)."""
    try:
        return format_fleet_track(obj)
    except (ValueError, TypeError, OverflowError, OSError, AttributeError):
        return None


def _counts_text(counts: WatchCounts) -> str:
    return f"{counts.with_position} with position, {counts.observable} observable"


def summary_line(counts: WatchCounts, seconds: float) -> str:
    """The closing line: how many tracks, with a line of sight, a position, observable, and when first."""
    if counts.fleet_tracks and counts.fleet_tracks == counts.tracks:  # fused targets: positions, no line of sight
        text = f"summary: {counts.tracks} fleet tracks in {seconds:.1f} s, {counts.with_position} with position"
    else:
        text = (
            f"summary: {counts.tracks} tracks in {seconds:.1f} s, {counts.with_los} with line of sight, "
            f"{counts.with_position} with position"
        )
    if counts.first_position_s is not None:
        text += f" (first at t {counts.first_position_s:.1f} s)"
    text += f", {counts.observable} observable"
    if counts.first_observable_s is not None:
        text += f" (first at t {counts.first_observable_s:.1f} s)"
    if counts.bad:
        text += f"; {counts.bad} payloads were not tracks"
    if len(counts.runs) > 1:
        text += f"; {len(counts.runs)} daemon runs (run_id {', '.join(counts.runs)})"
    if counts.returns >= TWO_PUBLISHERS_RETURNS:
        text += f"; {counts.returns} tracks went back in seq or time: two publishers on the key"
    if counts.tracks + counts.bad == 0:
        text += "; nothing arrived: is the daemon running, and zenoh connected to it?"
    return text


def new_run_line(vehicle: str, before: str, run: str) -> str:
    """The line said when ``vehicle``'s tracks come from a daemon run not seen before (its ``run_id``)."""
    return (
        f"{vehicle}: tracks of a new daemon run (run_id {run} after {before}): the daemon restarted, and its track "
        "ids, estimate_epoch and local NED origin start again (or a second daemon publishes under this name, if "
        "the tracks now go back and forth in time)"
    )


def two_publishers_line(vehicle: str) -> str:
    """The one line said when the tracks go back and forth: two daemons (or cameras) publish as ``vehicle``."""
    return (
        f"the tracks of {vehicle} go back and forth in seq or time: two publishers share the key (two daemons named "
        f"{vehicle}? each one's status warns name_clash); these lines mix two vehicles' or two daemons' tracks"
    )


def interrupted_line(counts: WatchCounts) -> str:
    """The one line printed on Ctrl-C."""
    return f"interrupted: {counts.tracks} tracks received, {_counts_text(counts)}"


_seconds = nonnegative_float("expected a number of seconds", "expected seconds >= 0 (0: until Ctrl-C)")

# the default endpoint as --help words it; onboard.fuse shares it (and zenoh_config)
ZENOH_CONNECT_HELP = (
    f"zenoh endpoint to connect to; repeatable (default {DEFAULT_CONNECT} when no --zenoh-connect, "
    "--zenoh-listen or --zenoh-config is given)"
)


def _vehicle(text: str) -> str:
    """``--vehicle``: one zenoh key chunk, checked when the command line is read (the error names the option)."""
    from onboard.io.zenoh_session import check_vehicle_name

    try:
        return check_vehicle_name(text)
    except IrtrackError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="python -m onboard.watch",
        description="Print the onboard daemon's tracks (zenoh irtrack/<vehicle>/track) as they arrive, "
        "one line each, then a summary.",
    )
    p.add_argument(
        "--vehicle",
        default="uav1",
        type=_vehicle,
        help="vehicle name in the zenoh key irtrack/<vehicle>/track (default uav1)",
    )
    p.add_argument(
        "--seconds",
        metavar="S",
        type=_seconds,
        default=DEFAULT_SECONDS,
        help=f"stop after S seconds (default {DEFAULT_SECONDS:g}; 0 = until Ctrl-C)",
    )
    p.add_argument(
        "--json", action="store_true", help="print the JSON payloads as received, one per line (other lines on stderr)"
    )
    add_zenoh_options(p, connect_help=ZENOH_CONNECT_HELP)
    return p


def zenoh_config(args: argparse.Namespace) -> ZenohConfig:
    """The session's :class:`~onboard.io.zenoh_session.ZenohConfig` from the parsed options."""
    connect = tuple(args.zenoh_connect or ())
    listen = tuple(args.zenoh_listen or ())
    if not connect and not listen and args.zenoh_config is None:
        connect = (DEFAULT_CONNECT,)
    return config_from_options(
        connect=connect, listen=listen, config_file=args.zenoh_config, multicast_scouting=args.zenoh_scouting
    )


def _where(settings: ZenohConfig) -> str:
    parts = [*settings.connect, *(f"listening {ep}" for ep in settings.listen)]
    if settings.config_file is not None:
        parts.append(f"config {settings.config_file}")
    return ", ".join(parts)


def _receive(
    inbox: queue.Queue[bytes],
    counts: WatchCounts,
    *,
    seconds: float,
    as_json: bool,
    out: TextIO,
    err: TextIO,
    hint: str,
    stop: threading.Event | None = None,
) -> None:
    """Print what arrives in ``inbox`` until ``seconds`` have passed (forever for 0) or ``stop`` is set; updates
    ``counts``."""
    start = time.monotonic()
    deadline = None if seconds == 0 else start + seconds
    hinted = False
    while True:
        now = time.monotonic()
        if (deadline is not None and now >= deadline) or (stop is not None and stop.is_set()):
            return
        if not hinted and counts.tracks + counts.bad == 0 and now - start >= NO_TRACK_HINT_S:
            print(hint, file=err, flush=True)
            hinted = True
        wait = POLL_S if deadline is None else min(POLL_S, deadline - now)
        try:
            payload = inbox.get(timeout=max(wait, 0.0))
        except queue.Empty:
            continue
        try:
            track = track_from_json(payload)
        except InputError as exc:
            fleet = _fleet_track(payload)  # --vehicle fleet: the fusion's triangulated targets
            line = None if fleet is None else fleet_track_line(fleet)
            if fleet is not None and line is not None:
                counts.add_fleet(fleet)
                print(payload.decode("utf-8", "replace") if as_json else line, file=out, flush=True)
                continue
            counts.bad += 1
            if as_json:
                print(payload.decode("utf-8", "replace"), file=out, flush=True)
            elif fleet is not None:
                print(f"not a fleet track ({len(payload)} bytes): a field of the wrong type", file=err, flush=True)
            else:
                print(f"not a track ({len(payload)} bytes): {exc}", file=err, flush=True)
            continue
        counts.add(track)
        new_run = counts.add_run(track)
        if new_run is not None:
            print(new_run, file=err, flush=True)
        if counts.add_order(track):
            print(two_publishers_line(track.vehicle), file=err, flush=True)
        print(payload.decode("utf-8", "replace") if as_json else format_track(track), file=out, flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # a usage error, said on one line: its code is the command's
        return exc.code if isinstance(exc.code, int) else EXIT_CONFIG
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    out = sys.stdout
    info = sys.stderr if args.json else sys.stdout
    counts = WatchCounts()
    session = None
    try:
        settings = zenoh_config(args)
        key = track_key(args.vehicle)
        session = open_session(settings)
        inbox: queue.Queue[bytes] = queue.Queue()
        start = time.monotonic()
        session.declare_subscriber(key, lambda sample: inbox.put(sample.payload.to_bytes()))
        until = "until Ctrl-C" if args.seconds == 0 else f"for {args.seconds:g} s (Ctrl-C stops sooner)"
        print(f"watching {key} on {_where(settings)} {until}", file=info, flush=True)
        hint = (
            f"no track on {key} after {NO_TRACK_HINT_S:g} s (still watching): the daemon publishes one per IR "
            f"frame it receives; check that the simulator or camera is running, and the daemon too, with vehicle "
            f"{args.vehicle} and zenoh reachable at {_where(settings)}"
        )
        # Ctrl-C (and SIGTERM: `timeout`, a job's limit, `kill`) while receiving sets a flag instead of raising: a
        # KeyboardInterrupt inside queue.get can leave its lock released twice, and the RuntimeError that follows
        # escaped as a traceback instead of the one line; SIGTERM had ended the process with no line at all
        stop = threading.Event()
        stopped_by: list[int] = []

        def on_signal(signum, _frame) -> None:
            stopped_by.append(signum)
            stop.set()

        # not where a signal is ignored (a shell without job control starts `... &` with Ctrl-C so) nor off the main
        # thread
        main = threading.current_thread() is threading.main_thread()
        caught = [
            sig
            for sig in (signal.SIGINT, signal.SIGTERM)
            if main and signal.getsignal(sig) not in (signal.SIG_IGN, None)
        ]
        previous = {sig: signal.signal(sig, on_signal) for sig in caught}
        try:
            _receive(
                inbox, counts, seconds=args.seconds, as_json=args.json, out=out, err=sys.stderr, hint=hint, stop=stop
            )
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        if stop.is_set():
            print(interrupted_line(counts), file=info, flush=True)
            return EXIT_INTERRUPTED if stopped_by[0] == signal.SIGINT else EXIT_TERMINATED
        session.close()
        session = None
        print(summary_line(counts, time.monotonic() - start), file=info, flush=True)
        return EXIT_OK if counts.tracks else EXIT_NO_TRACK
    except IrtrackError as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_CONFIG
    except KeyboardInterrupt:
        print(interrupted_line(counts), file=info, flush=True)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # `... | head`: the reader left; later writes (and the exit's flush) go nowhere
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
    finally:
        if session is not None:
            session.close()
