"""Liveness probe for the container: ``python -m onboard.health`` exits 0 while the pipeline lives.

Contract between the daemon and the probe (the Dockerfile's ``HEALTHCHECK`` runs the probe):

* The daemon's pipeline thread calls :func:`mark_alive` on every turn of its loop, *including*
  idle turns (its queue wait must time out at least once a second), so a daemon waiting for a
  camera stays healthy and a pipeline thread that is dead or stuck stops touching the file.
* The file is ``$IRTRACK_HEALTH_FILE``, default ``/tmp/irtrack-alive``.  Only its modification time
  matters: it is empty, and the daemon refuses to start on a path that holds anything else
  (:func:`claim_health_file`), since it deletes the file when it stops.
* The probe first checks that the path holds what the daemon writes there, an empty regular file: a
  folder, a device or a file with content is something else that happens to be touched (``/tmp`` is, by
  every process that writes into it), and its mtime proves nothing about the pipeline.
* The probe reads the file's mtime and the wall clock (both ``CLOCK_REALTIME``, the only clock two
  processes share through a file) and calls the pipeline alive when
  ``-FUTURE_TOLERANCE_S <= now - mtime <= max_age_s`` (``max_age_s`` default 5 s).  An mtime more
  than ``FUTURE_TOLERANCE_S`` in the future means the wall clock stepped back (GNSS/NTP time set
  after boot, common on a companion computer) and the file no longer proves anything; the next
  touch repairs it within a loop turn, so a step costs at most one failed probe, which the
  ``HEALTHCHECK --retries`` absorb.  A forward step behaves the same way.

Exit codes follow Docker's HEALTHCHECK contract: 0 healthy, 1 unhealthy.  Docker reserves 2, so
bad options are reported as unhealthy (1) with one "usage error" line naming the option, never as argparse's 2.
One line goes to stdout either way (Docker keeps it in ``docker inspect``'s health log).

Only the standard library is imported: the probe runs every few seconds and must start fast.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import stat
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NoReturn

from onboard.app.output_files import file_kind
from onboard.core.checks import is_finite_number, is_positive_number
from onboard.core.errors import ConfigError

__all__ = [
    "DEFAULT_HEALTH_FILE",
    "HEALTH_FILE_ENV",
    "DEFAULT_MAX_AGE_S",
    "FUTURE_TOLERANCE_S",
    "EXIT_HEALTHY",
    "EXIT_UNHEALTHY",
    "Liveness",
    "judge_liveness",
    "health_file_path",
    "check_liveness",
    "claim_health_file",
    "health_folder_problem",
    "release_health_file",
    "mark_alive",
    "main",
]

DEFAULT_HEALTH_FILE = "/tmp/irtrack-alive"
HEALTH_FILE_ENV = "IRTRACK_HEALTH_FILE"
DEFAULT_MAX_AGE_S = 5.0
FUTURE_TOLERANCE_S = 1.0  # mtime this far ahead of "now" is a clock step, not a heartbeat

EXIT_HEALTHY = 0
EXIT_UNHEALTHY = 1

REASON_OK = "ok"
REASON_MISSING = "missing"
REASON_STALE = "stale"
REASON_FUTURE = "future"
REASON_FOREIGN = "foreign"
REASON_UNREADABLE = "unreadable"


@dataclass(frozen=True)
class Liveness:
    """The probe's verdict.

    alive
        True when the file was touched within ``max_age_s``.
    reason
        ``"ok"``, ``"missing"`` (no file), ``"stale"`` (older than ``max_age_s``),
        ``"future"`` (mtime more than :data:`FUTURE_TOLERANCE_S` ahead: wall clock stepped back),
        ``"foreign"`` (the path holds something the daemon does not write: a folder, a file with content) or
        ``"unreadable"`` (the path cannot be looked at: a folder on it this user may not search, ...).
    age_s
        ``now - mtime`` in seconds (negative when the mtime is ahead), None when missing, foreign or unreadable.
    max_age_s
        The limit used.
    foreign
        What the path holds instead of a liveness file (``"is a folder"``, ``"holds 10 bytes"``), exactly
        when ``reason`` is ``"foreign"``; else None.
    error
        Why the path cannot be looked at (the system's words: ``"Permission denied"``), exactly when ``reason`` is
        ``"unreadable"``; else None.
    """

    alive: bool
    reason: str
    age_s: float | None
    max_age_s: float
    foreign: str | None = None
    error: str | None = None

    def __post_init__(self) -> None:
        reasons = (REASON_OK, REASON_MISSING, REASON_STALE, REASON_FUTURE, REASON_FOREIGN, REASON_UNREADABLE)
        if self.reason not in reasons:
            raise ValueError(f"Liveness.reason: unknown reason {self.reason!r}")
        if self.alive != (self.reason == REASON_OK):
            raise ValueError(f"Liveness.alive={self.alive} contradicts reason {self.reason!r}")
        if (self.age_s is None) != (self.reason in (REASON_MISSING, REASON_FOREIGN, REASON_UNREADABLE)):
            raise ValueError("Liveness.age_s must be None exactly when reason is 'missing', 'foreign' or 'unreadable'")
        if (self.foreign is None) == (self.reason == REASON_FOREIGN):
            raise ValueError("Liveness.foreign must say what the path holds exactly when reason is 'foreign'")
        if (self.error is None) == (self.reason == REASON_UNREADABLE):
            raise ValueError("Liveness.error must say why the path cannot be read exactly when reason is 'unreadable'")

    def describe(self, path: str) -> str:
        """One line for the health log."""
        if self.foreign is not None:
            return (
                f"NOT alive: {path} {self.foreign}: the pipeline's liveness file is an empty regular file, so "
                f"--file or ${HEALTH_FILE_ENV} names something else"
            )
        if self.error is not None:
            return f"NOT alive: cannot look at {path}: {self.error}"
        if self.age_s is None:  # exactly when the file is missing (__post_init__)
            return f"NOT alive: {path} does not exist (the pipeline has not started or cannot write it)"
        if self.reason == REASON_OK:
            return f"alive: {path} touched {self.age_s:.1f} s ago (limit {self.max_age_s:g} s)"
        if self.reason == REASON_STALE:
            return f"NOT alive: {path} last touched {self.age_s:.1f} s ago (limit {self.max_age_s:g} s)"
        return (
            f"NOT alive: {path} touched {-self.age_s:.1f} s in the future "
            "(wall clock stepped back; the next touch repairs it)"
        )


def _check_max_age(max_age_s: float) -> float:
    if not is_positive_number(max_age_s):
        raise ConfigError(f"max_age_s: expected a positive finite number of seconds, got {max_age_s!r}")
    return float(max_age_s)


def judge_liveness(mtime_s: float | None, now_s: float, max_age_s: float = DEFAULT_MAX_AGE_S) -> Liveness:
    """Pure verdict from the file's mtime (None: no file) and the current wall-clock time, both in s."""
    max_age_s = _check_max_age(max_age_s)
    if mtime_s is None:
        return Liveness(False, REASON_MISSING, None, max_age_s)
    for name, value in (("mtime_s", mtime_s), ("now_s", now_s)):
        if not is_finite_number(value):
            raise ConfigError(f"{name}: expected a finite time in seconds, got {value!r}")
    age_s = float(now_s) - float(mtime_s)
    if age_s < -FUTURE_TOLERANCE_S:
        return Liveness(False, REASON_FUTURE, age_s, max_age_s)
    if age_s > max_age_s:
        return Liveness(False, REASON_STALE, age_s, max_age_s)
    return Liveness(True, REASON_OK, age_s, max_age_s)


def health_file_path(environ: Mapping[str, str] | None = None) -> str:
    """``$IRTRACK_HEALTH_FILE`` when set, else :data:`DEFAULT_HEALTH_FILE`; a set-but-empty value is an error."""
    env = os.environ if environ is None else environ
    value = env.get(HEALTH_FILE_ENV)
    if value is None:
        return DEFAULT_HEALTH_FILE
    if not value.strip():
        raise ConfigError(f"{HEALTH_FILE_ENV}: expected a file path, got an empty value")
    return value


def _not_a_liveness_file(st: os.stat_result) -> str | None:
    """What ``st`` holds when it is not what :func:`mark_alive` makes (an empty regular file), else None."""
    if not stat.S_ISREG(st.st_mode):
        return f"is {file_kind(st.st_mode)}"
    if st.st_size:
        return f"holds {st.st_size} bytes"
    return None


def check_liveness(path: str, max_age_s: float = DEFAULT_MAX_AGE_S, now_s: float | None = None) -> Liveness:
    """Stat ``path`` and judge it; ``now_s`` defaults to ``time.time()`` (wall clock, like mtimes).  A path that
    holds anything but an empty regular file is ``"foreign"``: the daemon never writes anything else there, so its
    mtime is some other writer's."""
    max_age_s = _check_max_age(max_age_s)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return judge_liveness(None, 0.0, max_age_s)
    except OSError as exc:  # there may well be a fresh file there: 'does not exist' would send the reader astray
        return Liveness(False, REASON_UNREADABLE, None, max_age_s, error=exc.strerror or str(exc))
    foreign = _not_a_liveness_file(st)
    if foreign is not None:
        return Liveness(False, REASON_FOREIGN, None, max_age_s, foreign)
    return judge_liveness(st.st_mtime, time.time() if now_s is None else now_s, max_age_s)


def claim_health_file(path: str, field: str = "output.health_file") -> None:
    """Refuse (``ConfigError`` naming ``field``) a liveness path that holds anything but an empty regular file:
    the daemon touches the file while it runs and deletes it when it stops, so a path set by mistake onto a
    real file would lose that file.  An empty file (one a daemon that died left behind) is taken over."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return
    except OSError as exc:
        raise ConfigError(f"{field}: cannot check {path}: {exc.strerror or exc}") from None
    foreign = _not_a_liveness_file(st)
    if foreign is not None:
        raise ConfigError(
            f"{field}: {path} exists and {foreign}: a liveness file is an empty regular file, and the daemon "
            f"deletes it when it stops; point {field} at a file of its own"
        )


def health_folder_problem(path: str) -> str | None:
    """Why the daemon could not keep a liveness file at ``path`` (``--check``), or None: it creates the file in its
    folder and deletes it there when it stops, so the folder must exist and take a new file.  One is made there and
    removed at once: permissions alone do not tell (root, a read-only file system)."""
    from onboard.io.record_files import folder_write_problem

    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        return f"{folder} is not a folder" if os.path.lexists(folder) else f"{folder}: no such folder"
    return folder_write_problem(folder)


def release_health_file(path: str) -> None:
    """Delete the liveness file when it is still an empty regular file (what :func:`mark_alive` makes); leave
    anything else (a file someone wrote into meanwhile) in place."""
    with contextlib.suppress(OSError):  # already gone: nothing claims the daemon alive
        if _not_a_liveness_file(os.lstat(path)) is None:
            os.unlink(path)


def mark_alive(path: str | None = None) -> None:
    """Set ``path``'s mtime to now, creating the file if needed (the daemon's side of the contract).

    ``path`` defaults to :func:`health_file_path`.  Raises ``OSError`` when the file cannot be
    written (read-only filesystem, missing directory): the caller logs it once and carries on.
    """
    target = health_file_path() if path is None else path
    try:
        os.utime(target, None)
    except FileNotFoundError:
        with open(target, "a", encoding="utf-8"):
            pass


class _ProbeArgumentError(Exception):
    pass


class _ProbeParser(argparse.ArgumentParser):
    """argparse exits with 2 on bad options; a HEALTHCHECK must not (Docker reserves 2)."""

    def error(self, message: str) -> NoReturn:
        raise _ProbeArgumentError(message)


def _build_parser() -> argparse.ArgumentParser:
    parser = _ProbeParser(
        prog="python -m onboard.health",
        description="Exit 0 when the irtrack pipeline touched its liveness file recently, else 1.",
    )
    parser.add_argument(
        "--file",
        default=None,
        help=f"liveness file (default: ${HEALTH_FILE_ENV} or {DEFAULT_HEALTH_FILE})",
    )
    parser.add_argument(
        "--max-age-s",
        type=float,
        default=DEFAULT_MAX_AGE_S,
        help=f"oldest acceptable touch, seconds (default {DEFAULT_MAX_AGE_S:g})",
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Probe entry point; returns :data:`EXIT_HEALTHY` or :data:`EXIT_UNHEALTHY`, prints one line."""
    try:
        args = _build_parser().parse_args(argv)
        path = args.file if args.file is not None else health_file_path()
        verdict = check_liveness(path, args.max_age_s)
    except _ProbeArgumentError as exc:
        # the usage's mistake, not the daemon's state: said first (still exit 1, a HEALTHCHECK must not get 2); a
        # typo read 'NOT alive: bad option ...' like a dead daemon (a walkthrough of deploy/README)
        print(f"usage error (the daemon's liveness was not checked): {exc}; python -m onboard.health [--file PATH]")
        return EXIT_UNHEALTHY
    except ConfigError as exc:
        print(f"NOT alive: {exc}")
        return EXIT_UNHEALTHY
    print(verdict.describe(path))
    return EXIT_HEALTHY if verdict.alive else EXIT_UNHEALTHY


if __name__ == "__main__":
    sys.exit(main())
