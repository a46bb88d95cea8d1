"""The estimator worker's wire (:mod:`onboard.app.estimator_worker`): the messages between the daemon and its
estimator process, framed as ``multiprocessing.connection.Connection`` frames them."""

from __future__ import annotations

import dataclasses
import os
import pickle
import select
import struct
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from onboard.estimation.sliding import TrackEstimate

__all__ = [
    "MAX_INTRINSICS_SENT",
    "framed",
    "pack_estimate",
    "recv_msg",
    "row_args",
    "row_message",
    "send_msg",
    "unpack_estimate",
]

# The worker's wire.  A kept frame's row goes out as a flat tuple of Python numbers (its intrinsics by index,
# each object sent once) and its estimate comes back as the dataclass's field values (arrays as lists),
# both through plain ``pickle`` in ``Connection``'s framing (:func:`send_msg`).  Why: ``Connection.send`` pickles with
# ``ForkingPickler``, which copies copyreg's dispatch table on every call, and numpy arrays and dataclasses
# pickle through ``__reduce__``: ~130 us of both processes' CPU per round trip, against ~30 us this way, on
# every kept frame (15 a second).  The numbers are the same floats: ``tolist``/``np.array`` round-trip float64
# exactly (tested).
_PICKLE_PROTOCOL = pickle.HIGHEST_PROTOCOL
_ESTIMATE_FIELDS = tuple(f.name for f in dataclasses.fields(TrackEstimate))
_PACKED_ESTIMATE = "TrackEstimate.fields"  # first item of a packed estimate (an estimate is never a tuple)
MAX_INTRINSICS_SENT = 8  # camera models a worker remembers by index (nearly always one)


_LENGTH = struct.Struct("!i")  # Connection's framing: a signed big-endian length, then the bytes
_LONG_MESSAGE = 0x7FFFFFFF  # longer: Connection's own long header (never, in practice)


def framed(msg: tuple) -> bytes:
    """``msg`` pickled and framed as ``Connection.send_bytes`` frames it (its length first; a long message's
    header for one of 2 GiB or more)."""
    data = pickle.dumps(msg, _PICKLE_PROTOCOL)
    if len(data) >= _LONG_MESSAGE:
        return _LENGTH.pack(-1) + struct.pack("!Q", len(data)) + data
    return _LENGTH.pack(len(data)) + data


def send_msg(conn: Connection, msg: tuple) -> None:
    """``msg`` framed (:func:`framed`), written whole on the blocking pipe's descriptor, in one ``write`` but for
    a long message: ``send_bytes``'s Python layers (checks, a memoryview, the header) cost more than the row,
    twice a round trip.  The worker's side; the parent's never blocks (:meth:`ProcessEstimator._send`)."""
    fd = conn.fileno()  # OSError once closed, as send_bytes
    buf = memoryview(framed(msg))
    while buf:  # a blocking pipe writes it all, but for a signal
        buf = buf[os.write(fd, buf) :]


def _read_some(fd: int, n: int) -> bytes:
    """Up to ``n`` bytes; on a non-blocking descriptor (the parent's end) it waits for them once a message has
    begun, as a blocking one does."""
    while True:
        try:
            return os.read(fd, n)
        except BlockingIOError:
            waiting = select.poll()  # (poll, not select: any descriptor number)
            waiting.register(fd, select.POLLIN)
            waiting.poll()


def _read_exact(fd: int, n: int) -> bytes:
    data = _read_some(fd, n)
    if len(data) == n:
        return data
    parts = [data]
    left = n - len(data)
    while data and left:  # a message longer than the pipe's buffer (a snapshot) comes in pieces
        data = _read_some(fd, left)
        parts.append(data)
        left -= len(data)
    if left:
        raise EOFError("estimator pipe closed")
    return b"".join(parts)


def recv_msg(conn: Connection) -> Any:
    """The next message of :func:`send_msg` (or of ``Connection.send_bytes``): exactly its bytes are read, so the
    pipe's readiness still says whether another one waits."""
    fd = conn.fileno()
    (n,) = _LENGTH.unpack(_read_exact(fd, 4))
    if n == -1:  # Connection's long header
        (n,) = struct.unpack("!Q", _read_exact(fd, 8))
    return pickle.loads(_read_exact(fd, n))


def row_message(epoch: int, args: tuple, k_index: int) -> tuple | None:
    """An observation (:func:`as_observation`) as ``("row", epoch, t, u, v, k_index, p (3), q (4))``; None when
    its arrays are not the float64 (3,) and (4,) a row has (sent whole instead)."""
    t, uv, _, p, q = args
    if p.shape != (3,) or q.shape != (4,) or p.dtype != np.float64 or q.dtype != np.float64 or len(uv) != 2:
        return None
    return ("row", epoch, t, uv[0], uv[1], k_index, *p.tolist(), *q.tolist())


def row_args(msg: tuple, intrinsics: dict) -> tuple:
    """The observation of a ``row`` message, as :func:`as_observation` made it in the parent."""
    return (msg[2], (msg[3], msg[4]), intrinsics[msg[5]], np.array(msg[6:9]), np.array(msg[9:13]))


def pack_estimate(est):
    """A :class:`TrackEstimate` as a tuple of its field values (float64 arrays as lists); anything else as it is."""
    if type(est) is not TrackEstimate:
        return est
    values: list = [_PACKED_ESTIMATE]
    for name in _ESTIMATE_FIELDS:
        v = getattr(est, name)
        if type(v) is np.ndarray:
            if v.dtype != np.float64:
                return est
            v = v.tolist()
        elif type(v) in (list, tuple):  # would be read back as an array (lists) or a packed estimate
            return est
        values.append(v)
    return tuple(values)


def unpack_estimate(packed):
    """The inverse of :func:`pack_estimate`."""
    if type(packed) is not tuple or not packed or packed[0] != _PACKED_ESTIMATE:
        return packed
    values: list[Any] = [np.array(v) if type(v) is list else v for v in packed[1:]]
    return TrackEstimate(*values)
