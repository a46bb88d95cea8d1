"""The output folder a command writes in: made if missing, refused in one line when it cannot be written.

Every ``groundsim`` command that writes a folder (eval, demo, dataset, campaign, scenes, report) takes it from
:func:`make_out_dir`, so a file in its place, a parent that cannot be made or a folder that refuses files is one
line naming the option, before any run starts.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from onboard.core.errors import ConfigError

__all__ = ["make_out_dir"]


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
