"""What the benchmarks' command lines share: a parser whose usage mistakes are one line and argparse ``type``
checks for their option values.

A bad value is refused when the command line is parsed, before any measurement starts, as argparse words it
(``python -m bench.<name>: error: argument --x: ...``, exit code 2) on one line: never a traceback, never a
run that measures nothing (a count of 0, a rate of NaN).  The number checks are
:func:`onboard.app.cli_args.nonnegative_float`'s (the daemon's commands'), with its wording.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from collections.abc import Callable, Iterable
from typing import Any

from onboard.app.cli_args import OneLineParser, above_zero, nonnegative_float

__all__ = [
    "BenchParser",
    "cannot_write_in",
    "choices_list",
    "existing_dir",
    "existing_file",
    "int_between",
    "json_runs",
    "known_nav_noise",
    "known_scenario",
    "name_in",
    "nonnegative_int",
    "nonnegative_number",
    "output_file",
    "positive_float",
    "positive_int",
    "writable_dir",
]


class BenchParser(OneLineParser):
    """argparse whose usage mistake is its own last line alone: ``<prog>: error: <message>`` (no usage block)."""

    error_format = "{prog}: error: {message}"


#: a finite number >= 0 (a size whose 0 switches something off)
nonnegative_number = nonnegative_float("expected a number", "expected a finite number >= 0")


#: a finite number > 0 (a rate, a duration)
positive_float = above_zero(
    nonnegative_float("expected a number", "expected a finite number > 0"), "expected a finite number > 0"
)


def int_between(low: int, high: int | None = None) -> Callable[[str], int]:
    """An argparse ``type``: an integer >= ``low`` (and <= ``high`` when given)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if high is not None and not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected an integer in {low}..{high}, got {text!r}")
        if value < low:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}")
        return value

    return parse


positive_int = int_between(1)  # a count of seeds, workers, frames, updates
nonnegative_int = int_between(0)  # a count whose 0 skips a part


def existing_file(text: str) -> str:
    """The name of a file that exists (a missing one is refused before the benchmark reads it)."""
    if not os.path.isfile(text):
        raise argparse.ArgumentTypeError(f"no such file: {text!r}")
    return text


def existing_dir(text: str) -> str:
    """The name of a directory that exists."""
    if not os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"no such directory: {text!r}")
    return text


def cannot_write_in(folder: str) -> str | None:
    """Why no file can be made in ``folder``, made if missing (as :func:`write_json` makes it), or None: it can.
    Nothing is made: a missing folder is judged by its nearest existing parent, which must be a folder that takes
    a new file (a temporary one, gone at once; a file mode or a read-only mount says no only when tried)."""
    probe = os.path.abspath(folder or ".")
    while not os.path.lexists(probe):
        probe = os.path.dirname(probe)
    if not os.path.isdir(probe):
        return f"{probe} is not a folder"
    try:
        with tempfile.TemporaryFile(dir=probe):
            pass
    except OSError as exc:
        return f"cannot write in {probe}: {exc.strerror or exc}"
    return None


def output_file(text: str) -> str:
    """An argparse ``type``: the path of a file a benchmark writes once its run is over (its ``--json``), tried
    when the command line is read: a path found unwritable only at the end would lose the whole run's results."""
    if not text:
        raise argparse.ArgumentTypeError("expected the path of a file, got ''")
    if os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"{text!r} is a folder: give the path of a file")
    if os.path.exists(text):  # replaced, or a device such as /dev/stdout written through
        if not os.access(text, os.W_OK):
            raise argparse.ArgumentTypeError(f"cannot write {text!r}: permission denied")
        return text
    why = cannot_write_in(os.path.dirname(text))
    if why is not None:
        raise argparse.ArgumentTypeError(f"{text!r}: {why}")
    return text


def writable_dir(text: str) -> str:
    """An argparse ``type``: an existing folder that takes a new file (``/proc`` exists and takes none)."""
    why = cannot_write_in(existing_dir(text))
    if why is not None:
        raise argparse.ArgumentTypeError(why)
    return text


def json_runs(text: str) -> list[dict]:
    """The ``runs`` list of a benchmark's ``--json`` file (``{"runs": [{...}, ...]}``), read at parse time."""
    try:
        with open(text, encoding="utf-8") as fh:
            doc: Any = json.load(fh)
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"cannot read {text!r}: {exc.strerror or exc}") from None
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, bad UTF-8
        raise argparse.ArgumentTypeError(f"{text!r} is not JSON ({exc})") from None
    runs = doc.get("runs") if isinstance(doc, dict) else None
    if not isinstance(runs, list) or not all(isinstance(r, dict) for r in runs):
        raise argparse.ArgumentTypeError(
            f"{text!r} has no 'runs' list of objects (not a --json file of this benchmark?)"
        )
    return runs


def _known_names(names: list[str], known: Callable[[], Iterable[str]], what: str) -> list[str]:
    have = list(known())
    unknown = [n for n in names if n not in have]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown {what} {', '.join(map(repr, unknown))} (known: {', '.join(have)})")
    return names


def name_in(known: Callable[[], Iterable[str]], what: str) -> Callable[[str], str]:
    """One of the names ``known()`` gives (called when the option is given: a scenario directory, a
    noise-case file); another is refused naming the known ones."""

    def parse(text: str) -> str:
        return _known_names([text], known, what)[0]

    return parse


def choices_list(known: Callable[[], Iterable[str]], what: str) -> Callable[[str], list[str]]:
    """Comma-separated names, each one of ``known()`` (as :func:`name_in`)."""

    def parse(text: str) -> list[str]:
        names = [n.strip() for n in text.split(",")]
        if not all(names):
            raise argparse.ArgumentTypeError(f"expected comma-separated {what} names, got {text!r}")
        return _known_names(names, known, what)

    return parse


def known_scenario(text: str) -> str:
    """A scenario (``groundsim``'s ``--scenario``: a shipped one's name or a file), read at parse time: an
    unknown name is refused naming the shipped ones, a file that is not a scenario by its first error."""
    from groundsim.world.scenario import load_scenario, resolve_scenario_path
    from onboard.core.errors import IrtrackError

    try:
        load_scenario(resolve_scenario_path(text))
    except IrtrackError as exc:  # ScenarioError: one line, the file, the field and what was expected
        raise argparse.ArgumentTypeError(str(exc)) from None
    except OSError as exc:  # a directory, an unreadable file
        raise argparse.ArgumentTypeError(f"cannot read {text!r}: {exc.strerror or exc}") from None
    return text


def known_nav_noise(text: str) -> str:
    """A navigation-error case (``config/noise_cases.yaml``, or ``exact``), as ``groundsim``'s ``--nav-noise``."""
    from groundsim.world.nav_errors import resolve_nav_noise
    from onboard.core.errors import IrtrackError

    try:
        resolve_nav_noise(text)
    except IrtrackError as exc:  # "<file>: --nav-noise: expected one of ..., got '<text>'"
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text
