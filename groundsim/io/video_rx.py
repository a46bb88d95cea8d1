"""A ground station's video receivers: H.264 over UDP (RTP or MPEG-TS) -> decoded grey frames, with times.

Decoders for the daemon's IR video (:mod:`onboard.io.video` encodes with libx264; these decode with
FFmpeg's own H.264 decoder through PyAV, as a ground station would), one thread each, so a slow decode
shows as latency, never as a blocked sender:

* :class:`SdpRtpDecoder` -- RTP, independent of our code end to end: FFmpeg's own RTP demuxer and
  H.264 depacketiser, opened through a session description (:func:`onboard.io.rtp_h264.sdp`, written
  to a temporary ``.sdp`` file) exactly as ``ffplay stream.sdp`` would.  FFmpeg's H.264 parser
  re-frames the depacketised NAL units and, ignoring the RTP marker bit, knows a picture is complete
  only when the next one starts: one frame period (33 ms at 30 Hz) of its latency is FFmpeg's.
* :class:`RtpMarkerDecoder` -- RTP the way QGroundControl receives it (GStreamer ``udpsrc !
  rtph264depay ! avdec_h264``): the access unit is assembled from the packets and handed to the
  decoder at its marker bit (our :func:`onboard.io.rtp_h264.depacketize`, then FFmpeg's H.264 decoder
  without a parser).  A lost packet drops its access unit (counted), as ``rtph264depay`` does.
* :class:`UdpTsDecoder` -- MPEG-TS: PyAV reads the socket here and hands the datagrams to FFmpeg's
  MPEG-TS demuxer as a file-like stream.

Each decoded frame is passed to ``on_frame(DecodedFrame)`` on the receiver thread: the luma plane
(``uint8 (H, W)``), its index, and ``decoded_ns`` (``time.monotonic_ns`` after decoding).  The
receivers keep counts (``frames``, ``decode_errors``; ``datagrams`` and ``bytes`` where they own the
socket) and ``error`` (what ended the thread early, or None).  Bounded start (a demuxer probes at most
:data:`PROBE_BYTES`) and bounded stop (socket or read timeout :data:`POLL_S`).
"""

from __future__ import annotations

import logging
import os
import socket
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from groundsim.io.ports import free_rtp_port
from onboard.core.errors import InputError
from onboard.io.rtp_h264 import DEFAULT_PAYLOAD_TYPE, depacketize, parse_rtp, sdp

__all__ = ["DecodedFrame", "UdpTsDecoder", "SdpRtpDecoder", "RtpMarkerDecoder", "PROBE_BYTES"]

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

    def __init__(self, sock: socket.socket, stop: threading.Event, owner: UdpTsDecoder) -> None:
        self._sock, self._stop, self._owner = sock, stop, owner
        self._buf = bytearray()

    def read(self, n: int = -1) -> bytes:
        while not self._buf:
            if self._stop.is_set():
                return b""
            try:
                data = self._sock.recv(65536)
            except TimeoutError:
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


class _Decoding:
    """What every receiver does with decoded pictures and with failures (a mixin: the receiver has
    ``_on_frame``, ``_stop``, ``frames``, ``decode_errors`` and ``error``)."""

    def _emit(self, frame) -> None:
        luma = frame.to_ndarray(format="gray")
        self._on_frame(DecodedFrame(self.frames, luma, time.monotonic_ns()))
        self.frames += 1

    def _failed(self, exc: Exception) -> None:
        """The thread ends on ``exc``: reported through :attr:`error` unless it was stopping anyway."""
        if not self._stop.is_set():
            self.error = f"decode: {type(exc).__name__}: {exc}"

    def _decode_demuxed(self, container, read_timeouts: bool) -> None:
        """Demux ``container``'s video and decode it until EOF or stop, then close it.  An undecodable
        packet counts in ``decode_errors``; ``read_timeouts``: the demuxer's reads time out
        (``av.error.ExitError``), which only means looking at the stop flag again."""
        import av

        try:
            vstream = container.streams.video[0]
            vstream.codec_context.thread_count = 1  # frame threads would hold a frame back per thread
            while not self._stop.is_set():
                try:
                    for packet in container.demux(vstream):
                        try:
                            frames = packet.decode()
                        except av.error.InvalidDataError:
                            self.decode_errors += 1
                            continue
                        for frame in frames:
                            self._emit(frame)
                        if self._stop.is_set():
                            break
                    break  # EOF (or stopped)
                except av.error.ExitError:
                    if not read_timeouts:
                        raise
                    # POLL_S without a packet: look at the stop flag, then wait on
                except av.error.InvalidDataError:
                    self.decode_errors += 1
        except Exception as exc:  # noqa: BLE001 - reported through .error, the owner decides
            self._failed(exc)
        finally:
            try:
                container.close()
            except Exception:  # noqa: BLE001
                pass


class _UdpReceiver(_Decoding):
    """A UDP socket on ``host:port`` (``port`` 0: pick one, see :attr:`port`) read by a daemon thread
    (``_run``) until :meth:`stop`; the counts every receiver keeps."""

    THREAD_NAME = "video-rx"

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
        self._thread = threading.Thread(target=self._run, name=self.THREAD_NAME, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        raise NotImplementedError

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        self._thread.join(timeout_s)
        self._sock.close()


class UdpTsDecoder(_UdpReceiver):
    """Listen on ``host:port`` (``port`` 0 = pick one, see :attr:`port`) and decode until :meth:`stop`."""

    def _run(self) -> None:
        import av

        stream = _SocketStream(self._sock, self._stop, self)
        try:
            container = av.open(
                stream, mode="r", format="mpegts", options={"probesize": str(PROBE_BYTES), "analyzeduration": "0"}
            )
        except Exception as exc:  # noqa: BLE001 - stopped before any data, or garbage
            if not self._stop.is_set():
                self.error = f"open: {type(exc).__name__}: {exc}"
            return
        self._decode_demuxed(container, read_timeouts=False)


class SdpRtpDecoder(_Decoding):
    """RTP H.264 on ``host:port`` through FFmpeg's RTP demuxer and a session description (module
    docstring); ``port`` 0 picks a free even port (:attr:`port`).  Decodes until :meth:`stop`.

    FFmpeg owns the socket (RTP on ``port``, RTCP on ``port + 1``): :attr:`datagrams` stays None.
    The demuxer is opened again every :data:`OPEN_RETRY_S` until it has seen the stream's SPS, and
    its reads time out after :data:`POLL_S` of silence, so :meth:`stop` returns within about a second.
    """

    OPEN_RETRY_S = 1.0

    def __init__(
        self,
        on_frame: Callable[[DecodedFrame], None],
        host: str = "127.0.0.1",
        port: int = 0,
        payload_type: int = DEFAULT_PAYLOAD_TYPE,
    ) -> None:
        self._on_frame = on_frame
        self.port = int(port) or free_rtp_port(host)
        self._dir = tempfile.mkdtemp(prefix="irtrack-sdp-")
        self.sdp_path = os.path.join(self._dir, "stream.sdp")
        with open(self.sdp_path, "w", encoding="ascii") as f:
            f.write(sdp(host, self.port, payload_type))
        self._stop = threading.Event()
        self.datagrams = None
        self.bytes = None
        self.frames = 0
        self.decode_errors = 0
        self.error: str | None = None
        self.opened = threading.Event()  # set once the demuxer has the stream's parameters
        self._thread = threading.Thread(target=self._run, name="video-rx-sdp", daemon=True)
        self._thread.start()

    def _open(self):
        import av

        while not self._stop.is_set():
            try:
                return av.open(
                    self.sdp_path,
                    mode="r",
                    format="sdp",
                    options={
                        "protocol_whitelist": "file,udp,rtp",
                        "probesize": str(PROBE_BYTES),
                        "analyzeduration": "0",
                    },
                    timeout=(self.OPEN_RETRY_S, POLL_S),
                )
            except av.error.ExitError:
                continue  # no SPS yet (no IDR since we listened): listen again
        return None

    def _run(self) -> None:
        try:
            container = self._open()
        except Exception as exc:  # noqa: BLE001 - reported through .error
            self.error = f"open: {type(exc).__name__}: {exc}"
            return
        if container is None:
            return
        self.opened.set()
        self._decode_demuxed(container, read_timeouts=True)

    def stop(self, timeout_s: float = 3.0) -> None:
        self._stop.set()
        self._thread.join(timeout_s)
        try:
            os.remove(self.sdp_path)
            os.rmdir(self._dir)
        except OSError:
            pass


class RtpMarkerDecoder(_UdpReceiver):
    """RTP H.264 on ``host:port`` (``port`` 0: pick one, see :attr:`port`) assembled into access units
    at the marker bit and decoded at once (module docstring).  An access unit with a gap in its
    sequence numbers or a payload :func:`~onboard.io.rtp_h264.depacketize` refuses is dropped
    (``lost_units``); access units before the first IDR reach the decoder, which refuses them (counted in
    ``decode_errors``)."""

    THREAD_NAME = "video-rx-rtp"

    def __init__(self, on_frame: Callable[[DecodedFrame], None], host: str = "127.0.0.1", port: int = 0) -> None:
        self.lost_units = 0  # before the thread starts
        super().__init__(on_frame, host, port)

    def _run(self) -> None:
        import av

        try:
            codec = av.CodecContext.create("h264", "r")
            codec.thread_count = 1
            payloads: list[bytes] = []
            expected, broken = None, False
            while not self._stop.is_set():
                try:
                    data = self._sock.recv(65536)
                except TimeoutError:
                    continue
                except OSError:
                    return
                self.datagrams += 1
                self.bytes += len(data)
                try:
                    pkt = parse_rtp(data)
                except InputError:
                    self.decode_errors += 1
                    continue
                broken |= expected is not None and pkt.sequence != expected
                expected = (pkt.sequence + 1) % (1 << 16)
                payloads.append(pkt.payload)
                if not pkt.marker:
                    continue
                unit, payloads = payloads, []
                if broken:
                    self.lost_units += 1
                    broken = False
                    continue
                try:
                    nals = depacketize(unit)
                except InputError:
                    self.lost_units += 1
                    continue
                annexb = b"".join(b"\x00\x00\x00\x01" + n for n in nals)
                try:
                    frames = codec.decode(av.Packet(annexb))
                except av.error.InvalidDataError:
                    self.decode_errors += 1  # e.g. P-frames before the first IDR
                    continue
                for frame in frames:
                    self._emit(frame)
        except Exception as exc:  # noqa: BLE001 - reported through .error
            self._failed(exc)
