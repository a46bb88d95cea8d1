"""``python -m onboard.fuse``: fuse several vehicles' lines of sight into fleet tracks over zenoh.

    python -m onboard.fuse [--vehicles uav1 uav2 ...] [--origin LAT,LON,ALT] [--clock-offset NAME=SECONDS]...
                           [--seconds S] [--max-age-s 2] [--status-interval-s 1]
                           [--attitude-bias-deg 0.1] [--camera-white-m 0.02] [--camera-offset-m 0]
                           [--zenoh-connect ENDPOINT]... [--zenoh-listen ENDPOINT]... [--zenoh-config FILE]
                           [--zenoh-multicast-scouting | --no-zenoh-multicast-scouting]

It subscribes ``irtrack/*/track`` (every vehicle; ``--vehicles`` keeps only those named), turns each track
with a line of sight into a ray in one frame and on one clock (:mod:`onboard.io.fleet_wire`), feeds the
:class:`~onboard.estimation.fleet.FleetTracker` and publishes each updated target on ``irtrack/fleet/track``
and, in each vehicle's own frame, on ``irtrack/<vehicle>/fleet/track``; ``irtrack/fleet/status`` (JSON,
``--status-interval-s``) carries the counts, ``silent`` (vehicles heard before but not for ``--silent-after-s``:
a daemon that stopped; the fleet track goes on with the others, unobservable when one is left, and the vehicle
rejoins with its next line of sight that gates), ``clocks`` (each vehicle's latency floor off the fleet's
median, ms; ``latency_floor_ms``: the floors themselves) and ``clock_inconsistent`` (the vehicles whose ``time_unix_us`` disagrees with the others' beyond
``--clock-tolerance-ms``: :class:`~onboard.io.fleet_wire.ClockConsistency`).  Counted on each change:
``vehicle_silent``, ``clock_inconsistent`` (WARNING, naming the vehicle) and ``vehicle_back`` (INFO).  The zenoh options and their default (connect
``tcp/127.0.0.1:7447``) are :mod:`onboard.app.watch`'s, i.e. the daemon's.

Threads: zenoh's callback only queues ``(key, payload, arrival time)``; one loop drains the queue, adds
every ray, then solves each touched target that is due once and publishes: due when every live vehicle's
frame of the newest camera period is in, or a vehicle is ``max_defer_s`` (50 ms) late on the fleet clock
(:meth:`~onboard.estimation.fleet.FleetTracker.due`), or the queue has been idle for 0.1 s.  Eight vehicles
at 30 Hz then cost one solve per period instead of about two, at no latency from the later frame.
Bad input never stops it and never becomes a fused point: it is counted by reason and logged at most once
per ``--reject-log-interval-s`` per reason: ``not_json``, ``bad_track`` (the schema's reader names the key),
``bad_time_unix_us``, ``no_origin``, ``stale`` / ``future`` (common time more than ``--max-age-s`` before or
after this machine's clock), ``ray_stale``, ``ray_out_of_order``; ``no_line_of_sight`` (a track without a
target) and the tracker's events are counted at DEBUG level.

Exit codes: 0 after ``--seconds`` or on SIGTERM; 130 on Ctrl-C; 2 for invalid options or a session that
cannot open (one line on stderr).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import queue
import signal
import sys
import threading
import time
from collections.abc import Sequence

import numpy as np

from onboard.app.cli_args import OneLineParser, add_zenoh_options, nonnegative_float
from onboard.app.watch import ZENOH_CONNECT_HELP, zenoh_config
from onboard.core.counters import RejectCounter
from onboard.core.errors import InputError, IrtrackError
from onboard.core.frames import GeodeticOrigin
from onboard.estimation.fleet import FleetConfig, FleetTracker
from onboard.estimation.map_estimator import NoiseModel
from onboard.io.fleet_wire import (
    FLEET_NAME,
    FLEET_TRACK_ENCODING,
    TRACKS_KEY_EXPR,
    ClockConsistency,
    CommonClock,
    TimedTrack,
    fleet_track_json,
    fleet_track_key,
    parse_track,
    ray_from_track,
    vehicle_fleet_track_key,
    vehicle_from_track_key,
)
from onboard.io.zenoh_session import check_vehicle_name, open_session

__all__ = ["FLEET_STATUS_SCHEMA", "Fusion", "build_parser", "main"]

log = logging.getLogger(__name__)

FLEET_STATUS_SCHEMA = "irtrack.fleet_status/1"
EXIT_OK, EXIT_CONFIG, EXIT_INTERRUPTED = 0, 2, 130
POLL_S = 0.1


class Fusion:
    """The fusion's step logic without sockets: :meth:`receive` takes one message (its key, payload and
    arrival time on this machine's UTC clock) and returns nothing; :meth:`flush` solves the targets touched
    since the last flush and returns the ``(key, payload dict)`` pairs to publish."""

    def __init__(
        self,
        tracker: FleetTracker,
        clock: CommonClock,
        vehicles: Sequence[str] | None = None,
        origin: GeodeticOrigin | None = None,
        max_age_s: float = 2.0,
        counter: RejectCounter | None = None,
        clock_check: ClockConsistency | None = None,
        silent_after_s: float = 1.0,
    ) -> None:
        self.tracker = tracker
        self.clock = clock
        self.vehicles = None if not vehicles else frozenset(vehicles)
        self.origin = origin
        self.max_age_s = float(max_age_s)
        self.counter = counter or tracker.counter
        self.received = 0
        self.rays = 0
        self.published = 0
        self._touched: set[int] = set()
        self._seq = 0
        self._time_sources: dict[str, str] = {}
        self._origins: dict[str, GeodeticOrigin] = {}
        self._cameras: dict[str, np.ndarray] = {}
        self.clock_check = clock_check if clock_check is not None else ClockConsistency()
        self.silent_after_s = float(silent_after_s)
        self._last_arrival: dict[str, float] = {}  # fusion clock, UTC s: the vehicle's newest track of any kind
        self._silent: set[str] = set()
        self._clock_flagged: set[str] = set()

    def receive(self, key: str, payload: bytes, arrival_unix_s: float) -> None:
        vehicle = vehicle_from_track_key(key)
        if vehicle is None or (self.vehicles is not None and vehicle not in self.vehicles):
            return  # the fusion's own output, or a vehicle not asked for
        self.received += 1
        self._last_arrival[vehicle] = arrival_unix_s
        if vehicle in self._silent:
            self._silent.discard(vehicle)
            self.counter.count("vehicle_back", f"{vehicle}: tracks again", level=logging.INFO)
        try:
            obj = json.loads(payload)
        except (ValueError, UnicodeDecodeError) as exc:
            self.counter.count("not_json", f"{key}: {exc}")
            return
        if not isinstance(obj, dict):
            self.counter.count("bad_track", f"{key}: expected a JSON object, got {type(obj).__name__}")
            return
        try:
            track, time_unix_us = parse_track(obj)
        except InputError as exc:
            reason = "bad_time_unix_us" if "time_unix_us" in str(exc) else "bad_track"
            self.counter.count(reason, f"{key}: {exc}")
            return
        if track.vehicle != vehicle:
            self.counter.count("bad_track", f"{key}: vehicle {track.vehicle!r} on another vehicle's key")
            return
        if time_unix_us is not None:  # every frame times the vehicle's clock, with a target or not
            self.clock_check.add(vehicle, time_unix_us / 1e6, arrival_unix_s)
        los = track.los
        if los is None:
            self.counter.count("no_line_of_sight", key, level=logging.DEBUG)
            return
        if track.origin is None:
            self.counter.count("no_origin", f"{key}: a line of sight without its origin cannot be placed")
            return
        t_s, source = self.clock.time_s(vehicle, track.time_boot_us, time_unix_us, arrival_unix_s)
        if t_s < arrival_unix_s - self.max_age_s:
            self.counter.count("stale", f"{key}: frame {arrival_unix_s - t_s:.3f} s old ({source} time)")
            return
        if t_s > arrival_unix_s + self.max_age_s:
            self.counter.count("future", f"{key}: frame {t_s - arrival_unix_s:.3f} s ahead ({source} time)")
            return
        if self.origin is None:
            self.origin = track.origin
            log.info("fleet origin: %s's, %s", vehicle, track.origin)
        try:
            ray = ray_from_track(TimedTrack(track, t_s, source), self.origin)
        except InputError as exc:
            self.counter.count("bad_track", f"{key}: {exc}")
            return
        self._time_sources[vehicle] = source
        self._origins[vehicle] = track.origin
        self._cameras[vehicle] = np.asarray(los.p_cam_ned_m)
        self.rays += 1
        tid = self.tracker.add(ray)
        if tid is not None:
            self._touched.add(tid)

    def flush(self, force: bool = False) -> list[tuple[str, dict]]:
        """Solve the touched targets that are due (:meth:`FleetTracker.due`; all of them with ``force``)."""
        out: list[tuple[str, dict]] = []
        if self.origin is None:
            return out
        due = {t for t in self._touched if force or self.tracker.due(t)}
        self._touched -= due
        for tid in sorted(due):
            est = self.tracker.solve(tid)
            if est is None:
                continue
            self._seq += 1
            out.append((fleet_track_key(), fleet_track_json(est, self.origin, self._seq, self._time_sources)))
            for vehicle, origin in self._origins.items():
                payload = fleet_track_json(
                    est,
                    self.origin,
                    self._seq,
                    self._time_sources,
                    vehicle=vehicle,
                    vehicle_origin=origin,
                    vehicle_camera_ned_m=self._cameras.get(vehicle),
                )
                out.append((vehicle_fleet_track_key(vehicle), payload))
        self.published += len(out)
        return out

    def watch(self, now_unix_s: float) -> tuple[list[str], dict[str, float], list[str]]:
        """(silent vehicles, clock deviations s, clock-inconsistent vehicles) now; each change is counted."""
        silent = {v for v, t in self._last_arrival.items() if now_unix_s - t > self.silent_after_s}
        for v in sorted(silent - self._silent):
            self.counter.count(
                "vehicle_silent", f"{v}: no track for {now_unix_s - self._last_arrival[v]:.1f} s; fusing the others"
            )
        self._silent = silent
        devs = self.clock_check.deviations_s(now_unix_s)
        flagged = self.clock_check.inconsistent(now_unix_s)
        floors = self.clock_check.floors_s(now_unix_s)
        for v in flagged:
            if v not in self._clock_flagged:
                others = ", ".join(f"{o} {f * 1e3:.1f}" for o, f in floors.items() if o != v)
                self.counter.count(
                    "clock_inconsistent",
                    f"{v}: its frames' shortest arrival lag is {floors[v] * 1e3:.1f} ms (others: {others} ms): its "
                    "time_unix_us is off; check its UTC (SYSTEM_TIME) mapping",
                )
        self._clock_flagged = set(flagged)
        return sorted(silent), devs, flagged

    def status(self, now_unix_s: float | None = None) -> dict:
        """The ``irtrack.fleet_status/1`` dict (module docstring); ``now_unix_s``: the fusion's clock (UTC s)."""
        now_s = time.time() if now_unix_s is None else now_unix_s
        silent, devs, flagged = self.watch(now_s)
        return {
            "schema": FLEET_STATUS_SCHEMA,
            "received": self.received,
            "rays": self.rays,
            "published": self.published,
            "targets": len(self.tracker.targets),
            "vehicles": dict(sorted(self._time_sources.items())),
            "silent": silent,
            "clocks": {v: round(d * 1e3, 2) for v, d in devs.items()},
            "latency_floor_ms": {v: round(f * 1e3, 2) for v, f in self.clock_check.floors_s(now_s).items()},
            "clock_inconsistent": flagged,
            "rejected": self.counter.counts,
        }


_positive = nonnegative_float("expected a number", "expected a number >= 0")


def _origin(text: str) -> GeodeticOrigin:
    try:
        lat, lon, alt = (float(x) for x in text.split(","))
        return GeodeticOrigin(lat, lon, alt)
    except (ValueError, IrtrackError) as exc:
        raise argparse.ArgumentTypeError(
            f"expected LAT,LON,ALT (degrees, degrees, metres), got {text!r} ({exc})"
        ) from None


def _offset(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    try:
        check_vehicle_name(name)
        v = float(value)
        if not sep or not math.isfinite(v):
            raise ValueError
    except (ValueError, IrtrackError):
        raise argparse.ArgumentTypeError(f"expected NAME=SECONDS (UTC minus boot time), got {text!r}") from None
    return name, v


def _vehicle(text: str) -> str:
    try:
        name = check_vehicle_name(text)
    except IrtrackError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if name == FLEET_NAME:
        raise argparse.ArgumentTypeError(f"{FLEET_NAME!r} is the fusion's own key, not a vehicle")
    return name


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="python -m onboard.fuse",
        description="Fuse the vehicles' lines of sight (zenoh irtrack/*/track) into fleet tracks "
        "(irtrack/fleet/track, irtrack/<vehicle>/fleet/track).",
    )
    p.add_argument("--vehicles", nargs="+", type=_vehicle, metavar="NAME", help="only these (default: all)")
    p.add_argument("--origin", type=_origin, help="fleet NED origin LAT,LON,ALT (default: the first vehicle's)")
    p.add_argument(
        "--clock-offset",
        type=_offset,
        action="append",
        default=[],
        metavar="NAME=SECONDS",
        help="UTC minus boot time of a vehicle whose tracks carry no time_unix_us (default: estimated from arrivals)",
    )
    p.add_argument("--seconds", type=_positive, default=0.0, help="stop after S seconds (default 0: until a signal)")
    p.add_argument("--max-age-s", type=_positive, default=2.0, help="refuse frames older or newer than this (2)")
    p.add_argument("--status-interval-s", type=_positive, default=1.0, help="irtrack/fleet/status period (1)")
    p.add_argument("--silent-after-s", type=_positive, default=1.0, help="a vehicle unheard this long is silent (1)")
    p.add_argument(
        "--clock-tolerance-ms", type=_positive, default=10.0, help="name a vehicle whose UTC is this far off (10)"
    )
    p.add_argument("--reject-log-interval-s", type=_positive, default=10.0, help="log each reason at most this often")
    p.add_argument("--attitude-bias-deg", type=_positive, default=0.1, help="attitude bias prior, 1 sigma (0.1)")
    p.add_argument("--camera-white-m", type=_positive, default=0.02, help="white camera-position noise (0.02)")
    p.add_argument("--camera-offset-m", type=_positive, default=0.0, help="camera-position offset prior (0)")
    p.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    add_zenoh_options(
        p,
        connect_help=ZENOH_CONNECT_HELP,
        listen_help="zenoh endpoint to listen on",
        scouting_help=None,
        no_scouting_help=None,
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    noise = NoiseModel(
        attitude_bias_sigma_rad=math.radians(args.attitude_bias_deg),
        camera_position_white_sigma_m=args.camera_white_m,
        camera_position_offset_sigma_m=args.camera_offset_m,
    )
    counter = RejectCounter(log_interval_s=args.reject_log_interval_s, logger=log)
    fusion = Fusion(
        FleetTracker(FleetConfig(), noise, counter),
        CommonClock(dict(args.clock_offset)),
        vehicles=args.vehicles,
        origin=args.origin,
        max_age_s=args.max_age_s,
        clock_check=ClockConsistency(tolerance_s=args.clock_tolerance_ms / 1e3),
        silent_after_s=args.silent_after_s,
    )
    stop = threading.Event()
    session = None
    try:
        settings = zenoh_config(args)
        session = open_session(settings)
        inbox: queue.SimpleQueue = queue.SimpleQueue()
        session.declare_subscriber(
            TRACKS_KEY_EXPR, lambda s: inbox.put((str(s.key_expr), s.payload.to_bytes(), time.time()))
        )
        publishers: dict[str, object] = {}
        status_pub = session.declare_publisher(
            f"irtrack/{FLEET_NAME}/status", encoding=f"application/json;{FLEET_STATUS_SCHEMA}"
        )
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
        which = "all vehicles" if args.vehicles is None else " ".join(args.vehicles)
        log.info("fusing %s from %s on %s", which, TRACKS_KEY_EXPR, ", ".join(settings.connect + settings.listen))
        deadline = None if args.seconds == 0 else time.monotonic() + args.seconds
        next_status = time.monotonic() + args.status_interval_s
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            try:
                item = inbox.get(timeout=POLL_S)
            except queue.Empty:
                item = None
            idle = item is None
            while item is not None:
                fusion.receive(*item)
                try:
                    item = inbox.get_nowait()
                except queue.Empty:
                    item = None
            for key, payload in fusion.flush(force=idle):  # idle: whatever is pending, due or not
                pub = publishers.get(key)
                if pub is None:
                    pub = publishers[key] = session.declare_publisher(key, encoding=FLEET_TRACK_ENCODING)
                pub.put(json.dumps(payload, separators=(",", ":"), allow_nan=False))  # type: ignore[attr-defined]
            if args.status_interval_s > 0 and time.monotonic() >= next_status:
                next_status += args.status_interval_s
                status_pub.put(json.dumps(fusion.status(), separators=(",", ":")))
        status_pub.put(json.dumps(fusion.status(), separators=(",", ":")))
        log.info("stopped: %s", json.dumps(fusion.status()))
        return EXIT_OK
    except IrtrackError as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_CONFIG
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    finally:
        if session is not None:
            session.close()
