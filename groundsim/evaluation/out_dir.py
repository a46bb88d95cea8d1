"""The output folder a command writes in: made if missing, refused in one line when it cannot be written.

Every ``groundsim`` command that writes a folder (eval, demo, dataset, campaign, scenes, report) takes it from
:func:`make_out_dir`, so a file in its place, a parent that cannot be made or a folder that refuses files is one
line naming the option, before any run starts.  A command that replaces an earlier run's files in its folder
(eval, dataset, campaign, report) first passes it to :func:`refuse_foreign_out`: it removes and overwrites files
by name, which is safe only in a folder of its own.  What fails later, while the files are written (a full disk,
a file size limit), is one line naming the option too: :func:`writing`.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from onboard.core.errors import ConfigError

__all__ = ["holds_files", "make_out_dir", "refuse_foreign_out", "write_replacing", "writing"]


def make_out_dir(path, option: str = "--out") -> Path:
    """``option``'s directory, created (with its parents) if missing; a ConfigError naming ``option`` when it cannot
    be."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{option} {out}: a file, not a directory; give a directory (made if missing)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{option} {out}: cannot create the directory: {exc.strerror or exc}") from None
    # a directory that exists but cannot be written (its mode, a read-only mount) is said here, in one line,
    # rather than as a traceback from whichever file the command writes first
    try:
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        raise ConfigError(f"{option} {out}: cannot write in the directory: {exc.strerror or exc}") from None
    return out


def writing(out, write: Callable[..., Any], *args: Any, option: str = "--out") -> Any:
    """``write(*args)``, an OSError (disk full, a file too large for the limit, a path taken by a file, no
    permission) as one ConfigError naming ``option``'s folder ``out``, the file when the error names one, and the
    system's reason: the line a command prints, not a traceback from whichever file failed first."""
    try:
        return write(*args)
    except OSError as exc:
        where = f" {exc.filename}" if exc.filename else ""
        raise ConfigError(f"{option} {out}: cannot write{where}: {exc.strerror or exc}") from None


def holds_files(path) -> bool:
    """Whether the folder ``path`` holds anything but folders, at any depth (a symlink counts as a file and is not
    followed).  Stops at the first one found, so a home folder is answered at once."""
    try:
        with os.scandir(path) as entries:
            for entry in entries:
                if not entry.is_dir(follow_symlinks=False) or holds_files(entry.path):
                    return True
    except OSError:  # unreadable: counted as holding files, so that nothing is written into it unseen
        return True
    return False


def refuse_foreign_out(path, earlier: Callable[[Path], bool], what: str, mark: str, option: str = "--out") -> None:
    """A ConfigError naming ``option`` when its folder holds files and not an earlier ``what``'s results
    (``earlier(folder)`` false; ``mark`` says what ``earlier`` looks for).  A missing folder, or one holding only
    empty folders (what an interrupted run that finished nothing leaves), passes."""
    out = Path(path)
    if not out.is_dir() or earlier(out) or not holds_files(out):
        return
    raise ConfigError(
        f"{option} {out}: not empty and not an earlier {what}'s folder (no {mark}); {what} replaces an earlier "
        f"run's files in its folder, so it writes only into a new or empty one or its own: give another {option}"
    )


def write_replacing(path: Path, write: Callable[[Path], Any]) -> Any:
    """``write(tmp)`` into a file beside ``path`` (same suffix), renamed over ``path`` once written; returns what
    ``write`` returns.  A write stopped half way (a kill, a full disk) leaves the earlier file whole, not one
    cut short that reads as complete; ``path`` is left as it is when ``write`` made no file."""
    tmp = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        result = write(tmp)
        if tmp.exists():
            os.replace(tmp, path)
        return result
    finally:
        tmp.unlink(missing_ok=True)
