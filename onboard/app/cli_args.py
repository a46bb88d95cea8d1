"""What the command lines share: a parser whose usage mistakes are one line, and the zenoh session's options.

The daemon (``python -m onboard``), ``onboard.watch``, ``onboard.fuse``, ``onboard.reconstruct`` and
``groundsim`` all print a usage mistake as one line on stderr with exit code 2 (argparse's own code), not
argparse's usage block (house style: entry points turn known errors into one line and an exit code).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import NoReturn

__all__ = ["EXIT_USAGE", "OneLineParser", "add_zenoh_options", "nonnegative_float"]

EXIT_USAGE = 2  # argparse's own exit code for a usage mistake


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage mistakes are one line on stderr, worded by :attr:`error_format` (``{prog}``,
    ``{message}``; a subclass words it its own way), and exit code 2."""

    error_format = "{prog}: {message}"

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, self.error_format.format(prog=self.prog, message=message) + "\n")


def nonnegative_float(not_a_number: str, negative: str) -> Callable[[str], float]:
    """An argparse ``type``: a finite number >= 0; it refuses other text with ``not_a_number`` and a negative
    or infinite number with ``negative``, each followed by ``, got '<text>'``."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{not_a_number}, got {text!r}") from None
        if not math.isfinite(value) or value < 0:
            raise argparse.ArgumentTypeError(f"{negative}, got {text!r}")
        return value

    return parse


def add_zenoh_options(
    p: argparse.ArgumentParser,
    *,
    connect_help: str,
    listen_help: str = "zenoh endpoint to listen on; repeatable",
    config_help: str = "zenoh JSON5/JSON/YAML config file",
    scouting_help: str | None = "enable zenoh multicast scouting (off by default)",
    no_scouting_help: str | None = "disable zenoh multicast scouting",
) -> None:
    """The zenoh session's options, the same names and meaning in every command that opens one:
    ``args.zenoh_connect`` / ``args.zenoh_listen`` (the repeated endpoints; None when not given),
    ``args.zenoh_config`` (a file or None) and ``args.zenoh_scouting`` (True / False from
    ``--[no-]zenoh-multicast-scouting``, None when neither is given, so that a config file's value stands).
    Each command words the help its own way (where its defaults come from)."""
    p.add_argument("--zenoh-connect", metavar="ENDPOINT", action="append", help=connect_help)
    p.add_argument("--zenoh-listen", metavar="ENDPOINT", action="append", help=listen_help)
    p.add_argument("--zenoh-config", metavar="FILE", help=config_help)
    p.add_argument(
        "--zenoh-multicast-scouting", dest="zenoh_scouting", action="store_true", default=None, help=scouting_help
    )
    p.add_argument("--no-zenoh-multicast-scouting", dest="zenoh_scouting", action="store_false", help=no_scouting_help)
