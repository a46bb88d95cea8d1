"""Output files of the desk tools (``python -m onboard.track_video``, ``onboard.reconstruct``): what a path that is
not a regular file is called in an error, and a temporary file beside an output, renamed over it once written."""

from __future__ import annotations

import os
import secrets
import stat
from collections.abc import Sequence

__all__ = ["create_beside", "file_kind", "not_a_file", "output_target", "same_file_clash"]


def file_kind(mode: int) -> str:
    """What a file of ``st_mode`` ``mode`` that is not a regular file is, in words ("a folder", "a device" ...)."""
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISFIFO(mode):
        return "a pipe"
    return "a socket" if stat.S_ISSOCK(mode) else "not a regular file"


def not_a_file(mode: int | None) -> str | None:
    """Why an output path whose ``st_mode`` is ``mode`` (None: it does not exist) cannot be written by renaming a
    file over it -- the rename would replace a folder, device or pipe -- or None when it can."""
    if mode is None or stat.S_ISREG(mode):
        return None
    return f"it is {file_kind(mode)}: give the path of a file"


def output_target(path: str) -> tuple[str, str | None]:
    """The file ``path`` names (through a symbolic link: the link is kept, its file replaced) and why a rename
    cannot replace it (:func:`not_a_file`), or None: it can, or it does not exist or cannot be reached (writing it
    then says why)."""
    target = os.path.realpath(path)
    try:
        mode: int | None = os.stat(target).st_mode
    except OSError:
        mode = None
    return target, not_a_file(mode)


def create_beside(target: str) -> tuple[str, int]:
    """A new, empty temporary file in ``target``'s folder: its path and a descriptor open for writing.  Created
    with mode 0666, which the kernel reduces by the umask (and any default ACL) as for a plain ``open()``;
    ``tempfile.mkstemp`` would make it 0600 and the renamed output private."""
    folder, name = os.path.split(target)
    while True:
        tmp = os.path.join(folder, f".{name}.{secrets.token_hex(4)}.tmp")
        try:
            return tmp, os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            continue  # a name already taken: draw another


def _same(a: str, b: str) -> bool:
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:  # two names of one file (a hard link)
        return os.path.samefile(a, b)
    except OSError:
        return False


def same_file_clash(outputs: Sequence[tuple[str, str]], inputs: Sequence[tuple[str, str]] = ()) -> str | None:
    """Why these outputs cannot all be written, or None: one names an input's file (writing it would destroy the
    input it is made from) or another output's (one would replace the other).  Each item is ``(what, path)``,
    ``what`` the option or argument that gave it; empty paths are skipped, and so is an input folder (an output
    naming it is no file: the tool's own check says so)."""
    outs = [(w, p) for w, p in outputs if p]
    for i, (what, path) in enumerate(outs):
        for in_what, in_path in inputs:
            if in_path and not os.path.isdir(in_path) and _same(path, in_path):
                return f"{what} {path}: names the input {in_what} ({in_path}); give another file"
        for other_what, other in outs[:i]:
            if _same(path, other):
                return f"{what} {path}: names the same file as {other_what}; give each output its own file"
    return None
