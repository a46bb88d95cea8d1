"""The flight recorder's files on disk (:mod:`onboard.io.record`): the names of a rotated recording, a name that
writes over no earlier flight, whether a recording can be written at a path, and the free space it may use."""

from __future__ import annotations

import os

__all__ = [
    "folder_write_problem",
    "free_disk_bytes",
    "free_recording_path",
    "record_path_problem",
    "rotated_path",
    "rotation_base",
    "rotated_paths_after",
]


def rotated_path(path: str, index: int) -> str:
    """``FILE.mcap`` for index 0, ``FILE.<index>.mcap`` after it."""
    if index == 0:
        return path
    stem = path[: -len(".mcap")] if path.endswith(".mcap") else path
    return f"{stem}.{index}.mcap"


def rotation_base(path: str, index: int) -> str | None:
    """The ``FILE.mcap`` whose file ``index`` :func:`rotated_path` names ``path`` (``path`` itself for 0); None when
    ``path`` is not so named (a part renamed by hand)."""
    if index == 0:
        return path
    tail = f".{index}.mcap"
    return path[: -len(tail)] + ".mcap" if path.endswith(tail) else None


def rotated_paths_after(base: str, index: int) -> list[str]:
    """The rotated files of the recording ``base`` (``FILE.mcap``) that exist after file ``index``, in order, up to
    the first missing one."""
    found: list[str] = []
    while os.path.isfile(rotated_path(base, index + 1 + len(found))):
        found.append(rotated_path(base, index + 1 + len(found)))
    return found


def free_recording_path(path: str) -> str:
    """``path`` when neither it nor any of its rotated files (:func:`rotated_path`) exists, else the first of
    ``FILE-1.mcap``, ``FILE-2.mcap`` ... that is free in the same way: a daemon restarted with the same
    ``record.path`` (a container's restart policy) must not write over the flight it recorded before."""
    import glob

    stem = path[: -len(".mcap")] if path.endswith(".mcap") else path

    def taken(s: str) -> bool:
        return os.path.isfile(f"{s}.mcap") or bool(glob.glob(f"{glob.escape(s)}.[0-9]*.mcap"))

    if not taken(stem) or (os.path.lexists(path) and not os.path.isfile(path)):  # a folder there: opening says so
        return path
    n = 1
    while taken(f"{stem}-{n}"):
        n += 1
    return f"{stem}-{n}.mcap"


def folder_write_problem(folder: str) -> str | None:
    """Why no new file can be made in the existing ``folder`` (``FOLDER: the system's words``), or None.  It makes one
    there and removes it at once: permissions alone do not tell (root, a read-only or special file system)."""
    import tempfile

    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".irtrack-check-"):
            pass
    except OSError as exc:
        return f"{folder}: {exc.strerror or exc}"
    return None


def record_path_problem(path: str) -> str | None:
    """Why a recording could not be written at ``path`` (``--check``), or None: a folder there, or the nearest
    existing folder above it (the recorder makes the rest) where a file cannot be made
    (:func:`folder_write_problem`)."""
    p = os.path.abspath(path)
    if os.path.isdir(p):
        return f"{path} is a folder"
    d = os.path.dirname(p)
    while not os.path.lexists(d):
        d = os.path.dirname(d)
    if not os.path.isdir(d):
        return f"{d} is not a folder"
    return folder_write_problem(d)


def free_disk_bytes(path: str) -> int | None:
    """Bytes an unprivileged writer may still write on the file system holding ``path`` (its folder;
    ``statvfs``'s ``f_bavail``), or None when that cannot be read."""
    try:
        st = os.statvfs(os.path.dirname(os.path.abspath(path)) or ".")
    except OSError:
        return None
    return st.f_bavail * st.f_frsize
