"""A ground station's video receiver: MPEG-TS over UDP -> decoded grey frames, with arrival times.

An independent decoder for the daemon's IR video (:mod:`onboard.io.video` encodes with libx264; this
decodes with FFmpeg's own H.264 decoder through PyAV, as a ground station would).  PyAV's FFmpeg has
no ``udp://`` protocol, so :class:`UdpTsDecoder` reads the socket itself and hands the datagrams to
the MPEG-TS demuxer as a file-like stream; one thread does both, so a slow decode shows as latency,
never as a blocked sender.

Each decoded frame is passed to ``on_frame(DecodedFrame)`` on the receiver thread: the luma plane
(``uint8 (H, W)``), its index, and ``decoded_ns`` (``time.monotonic_ns`` after decoding).  The
receiver keeps counts (``datagrams``, ``bytes``, ``frames``, ``decode_errors``).  Bounded start
(the demuxer probes at most :data:`PROBE_BYTES`) and bounded stop (socket timeout :data:`POLL_S`).
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["DecodedFrame", "UdpTsDecoder", "PROBE_BYTES"]

log = logging.getLogger(__name__)

PROBE_BYTES = 64 * 1024  # the demuxer's probe: a few frames of a 2 Mbit/s stream (the default, 5 MB, is 20 s)
POLL_S = 0.1  # socket timeout: how quickly stop() is noticed
RECV_BUFFER_BYTES = 4 * 1024 * 1024


@dataclass(frozen=True)
class DecodedFrame:
    """One decoded picture: ``luma`` uint8 (H, W), ``index`` from 0 in decode order, ``decoded_ns``."""

    index: int
    luma: np.ndarray
    decoded_ns: int


class _SocketStream:
    """File-like ``read`` over a UDP socket for the demuxer: blocks until data or stop (then EOF)."""

    def __init__(self, sock: socket.socket, stop: threading.Event, owner: "UdpTsDecoder") -> None:
        self._sock, self._stop, self._owner = sock, stop, owner
        self._buf = bytearray()

    def read(self, n: int = -1) -> bytes:
        while not self._buf:
            if self._stop.is_set():
                return b""
            try:
                data = self._sock.recv(65536)
            except socket.timeout:
                continue
            except OSError:
                return b""
            self._owner.datagrams += 1
            self._owner.bytes += len(data)
            self._buf += data
        n = len(self._buf) if n is None or n < 0 else min(n, len(self._buf))
        out = bytes(self._buf[:n])
        del self._buf[:n]
        return out


class UdpTsDecoder:
    """Listen on ``host:port`` (``port`` 0 = pick one, see :attr:`port`) and decode until :meth:`stop`."""

    def __init__(self, on_frame: Callable[[DecodedFrame], None], host: str = "127.0.0.1", port: int = 0) -> None:
        self._on_frame = on_frame
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECV_BUFFER_BYTES)
        self._sock.bind((host, port))
        self._sock.settimeout(POLL_S)
        self.port = int(self._sock.getsockname()[1])
        self._stop = threading.Event()
        self.datagrams = 0
        self.bytes = 0
        self.frames = 0
        self.decode_errors = 0
        self.error: str | None = None  # the exception that ended the thread early, if any
        self._thread = threading.Thread(target=self._run, name="video-rx", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import av

        stream = _SocketStream(self._sock, self._stop, self)
        try:
            container = av.open(stream, mode="r", format="mpegts",
                                options={"probesize": str(PROBE_BYTES), "analyzeduration": "0"})
        except Exception as exc:  # noqa: BLE001 - stopped before any data, or garbage
            if not self._stop.is_set():
                self.error = f"open: {type(exc).__name__}: {exc}"
            return
        try:
            vstream = container.streams.video[0]
            vstream.codec_context.thread_count = 1
            while not self._stop.is_set():
                try:
                    packets = container.demux(vstream)
                    for packet in packets:
                        try:
                            frames = packet.decode()
                        except av.error.InvalidDataError:
                            self.decode_errors += 1
                            continue
                        for frame in frames:
                            luma = frame.to_ndarray(format="gray")
                            done = time.monotonic_ns()
                            self._on_frame(DecodedFrame(self.frames, luma, done))
                            self.frames += 1
                        if self._stop.is_set():
                            break
                    break  # EOF (stopped)
                except av.error.InvalidDataError:
                    self.decode_errors += 1
        except Exception as exc:  # noqa: BLE001 - reported through .error, the owner decides
            if not self._stop.is_set():
                self.error = f"decode: {type(exc).__name__}: {exc}"
        finally:
            try:
                container.close()
            except Exception:  # noqa: BLE001
                pass

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        self._thread.join(timeout_s)
        self._sock.close()
