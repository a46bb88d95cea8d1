"""What the command lines share: a parser whose usage mistakes are one line, the zenoh session's options, the
options that override the daemon's configuration (``--config``, ``--set``, ``--live-view``), and SIGTERM taken as
Ctrl-C by the tools that write files (:func:`sigterm_as_interrupt`).

The daemon (``python -m onboard``), ``onboard.watch``, ``onboard.fuse``, ``onboard.reconstruct`` and
``groundsim`` all print a usage mistake as one line on stderr with exit code 2 (argparse's own code), not
argparse's usage block (house style: entry points turn known errors into one line and an exit code).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import re
import signal
import sys
from collections.abc import Callable, Iterable, Iterator
from typing import Any, NoReturn

__all__ = [
    "EXIT_USAGE",
    "EXIT_READER_LEFT",
    "exit_code_of",
    "OneLineParser",
    "add_config_option",
    "add_live_view_option",
    "add_set_option",
    "add_zenoh_options",
    "config_overrides",
    "nonnegative_float",
    "number_in",
    "above_zero",
    "sigterm_as_interrupt",
    "help_summary",
]

EXIT_USAGE = 2  # argparse's own exit code for a usage mistake
EXIT_READER_LEFT = 141  # 128 + SIGPIPE: what a shell reports for a command whose output's reader went away


def exit_code_of(main: Callable[[], int]) -> int:
    """``main()``'s exit code, for an entry point's ``__main__``; :data:`EXIT_READER_LEFT` without a traceback when
    the reader of standard output went away (``... | head``): Python ignores SIGPIPE, so the next write raised
    BrokenPipeError wherever it was, and the exit's flush said so again.  What the command wrote to files before
    (a campaign's log of finished runs) stays; what it would still have printed goes nowhere."""
    try:
        code = main()
        sys.stdout.flush()  # here, not at exit: a reader gone after the last print is this error too
        return code
    except BrokenPipeError:
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_READER_LEFT


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


def above_zero(parse: Callable[[str], float], zero: str) -> Callable[[str], float]:
    """An argparse ``type``: what ``parse`` (a :func:`nonnegative_float`) takes, but 0, refused with ``zero``
    followed by ``, got '<text>'``."""

    def parse_above_zero(text: str) -> float:
        value = parse(text)
        if value <= 0:
            raise argparse.ArgumentTypeError(f"{zero}, got {text!r}")
        return value

    return parse_above_zero


def number_in(lo: float, hi: float, lo_open: bool = False) -> Callable[[str], float]:
    """An argparse ``type``: a number in ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``), refused otherwise with
    ``expected a number in [lo, hi], got '<text>'`` (so a NaN, an infinity and 1e308 read as what they are)."""
    span = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (lo < value <= hi if lo_open else lo <= value <= hi):
            raise argparse.ArgumentTypeError(f"expected a number in {span}, got {text!r}")
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


# The daemon (``python -m onboard``) and its replay (``python -m onboard.replay``) both build an OnboardConfig
# from a file and ``--set`` overrides, and both serve a live view: the options are declared here once, each
# command wording the help its own way (where its configuration comes from).


def add_config_option(p: argparse.ArgumentParser, help_text: str) -> None:
    """``--config FILE``: ``args.config``, the YAML configuration (None when not given)."""
    p.add_argument("--config", metavar="FILE", help=help_text)


def add_set_option(p: argparse.ArgumentParser, help_text: str) -> None:
    """``--set FIELD.PATH=VALUE``, repeatable: ``args.set``, the texts in order (empty when not given); read
    them with :func:`config_overrides`."""
    p.add_argument("--set", metavar="FIELD.PATH=VALUE", action="append", default=[], help=help_text)


def _tcp_port(text: str) -> int:
    """A TCP port to listen on, 1..65535 (as ``live_view.port``), checked when the command line is read."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port 1..65535, got {text!r}") from None
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port 1..65535, got {text!r}")
    return port


def add_live_view_option(p: argparse.ArgumentParser, help_text: str) -> None:
    """``--live-view PORT``: ``args.live_view``, the Foxglove WebSocket port (None when not given), 1..65535."""
    p.add_argument("--live-view", metavar="PORT", type=_tcp_port, help=help_text)


def config_overrides(
    set_texts: Iterable[str], options: Iterable[tuple[str, Any, str]] = ()
) -> dict[str, tuple[Any, str]]:
    """The configuration overrides of a command line, ``{field path: (value, source)}`` as
    :func:`onboard.app.config.load_config` takes them: each ``--set`` text (its value parsed as YAML and its
    path checked against the configuration's fields: :class:`~onboard.app.config.OnboardConfigError` names
    a wrong one), then each ``(field path, value, option)`` of ``options`` whose value was given (not
    None), which wins over a ``--set`` of the same field."""
    from onboard.app.config import parse_set_option  # the configuration's types, only for a command that has one

    out: dict[str, tuple[Any, str]] = {}
    for text in set_texts:
        path, value = parse_set_option(text)
        out[path] = (value, "--set")
    for path, value, option in options:
        if value is not None:
            out[path] = (value, option)
    return out


def _raise_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """While the block runs, SIGTERM (``timeout``, a job's time limit, ``kill``) raises KeyboardInterrupt as Ctrl-C
    does, so a tool's Ctrl-C path (one line, its outputs whole or untouched, no temporary file left) serves both;
    the handler before is put back after.  In a thread other than the main one (a caller's), or where SIGTERM is
    ignored (a launcher's choice), it is left alone."""
    previous = signal.getsignal(signal.SIGTERM)
    if previous is signal.SIG_IGN:  # a launcher that meant the tool to ignore SIGTERM: as Python leaves SIGINT
        yield
        return
    try:
        signal.signal(signal.SIGTERM, _raise_interrupt)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:  # None: a handler set outside Python, which SIG_DFL stands for best
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def help_summary(docstring: str | None) -> str:
    """A module docstring's first paragraph as ``--help`` shows it: reST markup (``code``, :mod:`name`) dropped."""
    first = (docstring or "").split("\n\n")[0]
    return re.sub(r":\w+:`([^`]*)`", r"\1", first).replace("``", "")
