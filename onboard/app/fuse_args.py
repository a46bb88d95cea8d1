"""The command line of ``python -m onboard.fuse``: its options, their parsers and checks, and the zenoh settings made
from them.

:func:`build_parser` declares every option (what each does: its help, and :mod:`onboard.app.fuse`'s docstring);
:func:`check_names` refuses what argparse cannot see alone (a vehicle named twice, an offset or noise for a vehicle
outside ``--vehicles``); :func:`zenoh_settings` turns the zenoh options into the session's settings.  The noise
options' value parsers are :mod:`onboard.app.fuse_noise`'s, beside the noise models they build.  Apart from the
fusion because none of it runs after the start: :class:`~onboard.app.fuse.Fusion` and its loop take the parsed
values.  :func:`build_parser` and :func:`zenoh_settings` are importable from :mod:`onboard.app.fuse` too.
"""

from __future__ import annotations

import argparse
import dataclasses
import math

from onboard.app.cli_args import OneLineParser, add_zenoh_options, nonnegative_float, number_in
from onboard.app.fuse_noise import (
    attitude_bias_deg_arg,
    camera_offset_m_arg,
    camera_white_m_arg,
    vehicle_arg,
    vehicle_noise_arg,
)
from onboard.app.watch import ZENOH_CONNECT_HELP, zenoh_config
from onboard.core.errors import IrtrackError
from onboard.core.frames import GeodeticOrigin
from onboard.core.track import ORIGIN_ALT_RANGE_M
from onboard.io.zenoh_session import ZenohConfig

__all__ = ["build_parser", "check_names", "zenoh_settings"]

_positive = nonnegative_float("expected a number", "expected a number >= 0")


def _origin(text: str) -> GeodeticOrigin:
    try:
        lat, lon, alt = (float(x) for x in text.split(","))
        origin = GeodeticOrigin(lat, lon, alt)
    except (ValueError, IrtrackError) as exc:
        raise argparse.ArgumentTypeError(
            f"expected LAT,LON,ALT (degrees, degrees, metres), got {text!r} ({exc})"
        ) from None
    lo, hi = ORIGIN_ALT_RANGE_M
    if not lo <= origin.alt_m <= hi:
        raise argparse.ArgumentTypeError(f"expected LAT,LON,ALT with ALT in [{lo:g}, {hi:g}] m, got {text!r}")
    return origin


def _offset(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    try:
        vehicle_arg(name)
        v = float(value)
        if not sep or not math.isfinite(v):
            raise ValueError
    except (ValueError, argparse.ArgumentTypeError):
        raise argparse.ArgumentTypeError(f"expected NAME=SECONDS (UTC minus boot time), got {text!r}") from None
    return name, v


def check_names(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse (one line, exit 2) a vehicle named twice in ``--vehicles``, ``--clock-offset`` or ``--vehicle-noise``
    (the last would win without a word) and, with ``--vehicles``, an offset or noise for a vehicle outside it."""
    given = {
        "--vehicles": list(args.vehicles or []),
        "--clock-offset": [name for name, _ in args.clock_offset],
        "--vehicle-noise": [name for name, _ in args.vehicle_noise],
    }
    for option, names in given.items():
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            parser.error(f"{option}: {', '.join(twice)} given more than once")
    if args.vehicles is not None:
        for option in ("--clock-offset", "--vehicle-noise"):
            outside = sorted(set(given[option]) - set(args.vehicles))
            if outside:
                parser.error(f"{option}: {', '.join(outside)} not one of --vehicles {' '.join(args.vehicles)}")


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="python -m onboard.fuse",
        description="Fuse the vehicles' lines of sight (zenoh irtrack/*/track) into fleet tracks "
        "(irtrack/fleet/track, irtrack/<vehicle>/fleet/track).",
    )
    p.add_argument("--vehicles", nargs="+", type=vehicle_arg, metavar="NAME", help="only these (default: all)")
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
    p.add_argument(
        "--max-age-s",
        type=number_in(0.0, 3600.0, lo_open=True),
        default=2.0,
        help="refuse frames older or newer than this (2)",
    )
    p.add_argument(
        "--status-interval-s", type=_positive, default=1.0, help="irtrack/fleet/status period (1; 0: the last only)"
    )
    p.add_argument(
        "--silent-after-s",
        type=number_in(0.0, 3600.0, lo_open=True),
        default=1.0,
        help="a vehicle unheard this long is silent (1)",
    )
    p.add_argument(
        # 0 would name every vehicle of a pair, one of them being always the later
        "--clock-tolerance-ms",
        type=number_in(0.0, 10_000.0, lo_open=True),
        default=10.0,
        help="name a vehicle whose UTC is this far off (10)",
    )
    p.add_argument(
        "--reject-log-interval-s",
        type=_positive,
        default=10.0,
        help="log each reason at most this often; a vehicle's own events (silent, back, clock, name clash) per vehicle (10)",
    )
    p.add_argument(
        "--attitude-bias-deg", type=attitude_bias_deg_arg, default=0.1, help="attitude bias prior, 1 sigma (0.1)"
    )
    p.add_argument("--camera-white-m", type=camera_white_m_arg, default=0.02, help="white camera-position noise (0.02)")
    p.add_argument(
        "--camera-offset-m", type=camera_offset_m_arg, default=0.0, help="camera-position offset prior (0: none)"
    )
    p.add_argument(
        "--vehicle-noise",
        type=vehicle_noise_arg,
        action="append",
        default=[],
        metavar="NAME:KEY=VALUE,...",
        help="one vehicle's noise where it differs from the options above; KEY: attitude_bias_deg, camera_white_m, "
        "camera_offset_m (e.g. uav2:attitude_bias_deg=0.5); repeatable",
    )
    p.add_argument(
        "--max-time-sigma-ms",
        type=number_in(0.001, 10_000.0),  # under a microsecond (the wire's unit) would refuse every line of sight
        default=50.0,
        help="refuse lines of sight whose time_unix_sigma_us is larger (50)",
    )
    p.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    add_zenoh_options(
        p,
        connect_help=ZENOH_CONNECT_HELP,
        listen_help="zenoh endpoint to listen on",
        scouting_help=None,
        no_scouting_help=None,
    )
    p.add_argument(
        "--zenoh-gossip-autoconnect",
        action="store_true",
        help="also dial the peers and routers that other sessions' gossip names (default: only the endpoints given, "
        "as the daemon's zenoh.gossip_autoconnect false); a loopback fleet of peers that meet at one router needs it "
        "(docs/fleet.md)",
    )
    return p


def zenoh_settings(args: argparse.Namespace) -> ZenohConfig:
    """The session's settings: the watcher's options and default endpoint (:func:`onboard.app.watch.zenoh_config`),
    dialing no peer that gossip names unless ``--zenoh-gossip-autoconnect``, as the daemon: those are addresses nobody
    gave the fusion (a router's peers, whatever they listen on), and a direct peer link also goes around a router's
    access control.  It overrides a ``--zenoh-config`` file's ``scouting/gossip/autoconnect``, as the daemon's
    setting does."""
    return dataclasses.replace(zenoh_config(args), gossip_autoconnect=bool(args.zenoh_gossip_autoconnect))
