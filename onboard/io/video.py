"""IR video for ground stations: AGC display mapping, track overlay, H.264 in MPEG-TS over UDP.

Pure parts (no sockets, no threads): :func:`agc_limits` / :func:`agc_u8` (the display mapping a
thermal core applies: the 1st..99th percentile of the frame, smoothed over frames, stretched
linearly onto 0..255, so mono16 and mono8 frames look alike and the sky does not flicker),
:func:`draw_overlay` (the track box and its range / 1-sigma), :class:`H264TsEncoder` (PyAV's libx264:
``preset ultrafast``, ``tune zerolatency``, no B-frames, an IDR every ``gop_frames`` frames with the
SPS/PPS repeated, so a ground station can join at any second; MPEG-TS muxing into any ``write``-able).

Adapter: :class:`VideoStreamer` owns a thread and a UDP socket: :meth:`VideoStreamer.submit` (called by
the pipeline thread, never blocks) keeps at most ``queue_length`` frames and drops the oldest when the
encoder is behind (counted as ``dropped``); the thread maps, overlays, encodes and sends the MPEG-TS in
datagrams of 7 x 188 bytes (1316, the customary MPEG-TS-over-UDP payload) to ``destination``.
QGroundControl opens it as an MPEG-TS stream on that UDP port (VIDEO_STREAM_INFORMATION type
MPEG_TS, uri = the port; :mod:`onboard.io.camera_protocol`).
"""

from __future__ import annotations

import collections
import logging
import math
import socket
import threading
import time
from dataclasses import dataclass

import numpy as np

from onboard.core.errors import InputError

__all__ = ["agc_limits", "agc_u8", "AgcState", "draw_overlay", "H264TsEncoder", "VideoStreamer", "TS_DATAGRAM_BYTES"]

log = logging.getLogger(__name__)

TS_PACKET_BYTES = 188
TS_DATAGRAM_BYTES = 7 * TS_PACKET_BYTES  # 1316
AGC_LOW_PCT, AGC_HIGH_PCT = 1.0, 99.0
AGC_SMOOTHING = 0.1  # weight of the newest frame's limits (exponential smoothing)
AGC_MIN_SPAN = 8.0  # grey levels: a flat frame is not stretched into noise
AGC_SAMPLE_STEP = 4  # percentiles over every 4th pixel in each direction (1/16 of the frame)


def agc_limits(pixels: np.ndarray, low_pct: float = AGC_LOW_PCT, high_pct: float = AGC_HIGH_PCT,
               step: int = AGC_SAMPLE_STEP) -> tuple[float, float]:
    """(low, high) input levels of one frame: its ``low_pct`` / ``high_pct`` percentiles (sub-sampled)."""
    if pixels.ndim != 2 or pixels.dtype not in (np.uint8, np.uint16):
        raise InputError(f"video frame must be a 2-D uint8/uint16 array, got {pixels.dtype} {pixels.shape}")
    lo, hi = np.percentile(pixels[::step, ::step], (low_pct, high_pct))
    return float(lo), float(hi)


@dataclass
class AgcState:
    """The smoothed limits (None before the first frame)."""

    low: float | None = None
    high: float | None = None

    def update(self, pixels: np.ndarray, smoothing: float = AGC_SMOOTHING) -> tuple[float, float]:
        lo, hi = agc_limits(pixels)
        if self.low is None:
            self.low, self.high = lo, hi
        else:
            self.low += smoothing * (lo - self.low)
            self.high += smoothing * (hi - self.high)
        return self.low, self.high


def agc_u8(pixels: np.ndarray, low: float, high: float) -> np.ndarray:
    """``pixels`` stretched linearly from [low, high] onto [0, 255] (clipped; span at least AGC_MIN_SPAN)."""
    span = max(high - low, AGC_MIN_SPAN)
    mid = 0.5 * (low + high)
    lo = mid - span / 2
    scale = 255.0 / span
    out = (pixels.astype(np.float32) - np.float32(lo)) * np.float32(scale)
    return np.clip(out, 0.0, 255.0).astype(np.uint8)


def draw_overlay(img_u8: np.ndarray, track) -> np.ndarray:
    """The track's box (white, 1 px) and, with a 3-D position, ``range m +- sigma`` beside it; a copy."""
    import cv2

    out = img_u8.copy()
    if track is None or track.bbox is None or track.state not in ("tracking", "coasting"):
        return out
    x, y, w, h = track.bbox
    p0 = (int(round(x)), int(round(y)))
    p1 = (int(round(x + w)), int(round(y + h)))
    colour = 255 if track.state == "tracking" else 160
    cv2.rectangle(out, p0, p1, colour, 1)
    if track.range_m is not None and track.range_sigma_ratio is not None and math.isfinite(track.range_sigma_ratio):
        text = f"{track.range_m:.0f} m +-{track.range_m * track.range_sigma_ratio:.0f}"
        cv2.putText(out, text, (p1[0] + 4, max(p0[1] + 10, 10)), cv2.FONT_HERSHEY_PLAIN, 0.9, colour, 1)
    return out


class H264TsEncoder:
    """Grey frames -> H.264 in MPEG-TS written to ``sink`` (anything with ``write(bytes)``).

    ``gop_frames``: frames between IDRs (x264 ``keyint`` = ``min-keyint``, no scene-cut IDRs);
    ``bitrate_bps``: target (ABR with a VBV of one second).  The chroma planes are flat (grey video).
    """

    def __init__(self, sink, width_px: int, height_px: int, fps: float = 30.0, bitrate_bps: int = 2_000_000,
                 gop_frames: int = 30) -> None:
        import av

        if width_px % 2 or height_px % 2:
            raise InputError(f"H.264 4:2:0 needs even frame sizes, got {width_px} x {height_px}")
        self.width_px, self.height_px = int(width_px), int(height_px)
        self.fps = float(fps)
        self._container = av.open(sink, mode="w", format="mpegts",
                                  options={"flush_packets": "1"})
        s = self._container.add_stream("libx264", rate=int(round(fps)))
        s.width, s.height, s.pix_fmt = self.width_px, self.height_px, "yuv420p"
        s.bit_rate = int(bitrate_bps)
        g = int(gop_frames)
        s.options = {"preset": "ultrafast", "tune": "zerolatency", "bf": "0", "g": str(g),
                     "x264-params": f"keyint={g}:min-keyint={g}:scenecut=0:repeat-headers=1:"
                                    f"vbv-maxrate={int(bitrate_bps) // 1000}:vbv-bufsize={int(bitrate_bps) // 1000}"}
        s.codec_context.thread_count = 1
        self._stream = s
        self._chroma = np.full((self.height_px // 2, self.width_px), 128, np.uint8)  # U and V planes, flat
        self._n = 0
        self.closed = False

    def encode(self, img_u8: np.ndarray) -> int:
        """Encode and mux one frame; returns the number of packets written."""
        import av

        if img_u8.shape != (self.height_px, self.width_px) or img_u8.dtype != np.uint8:
            raise InputError(f"encoder frame must be uint8 {self.height_px} x {self.width_px}, got {img_u8.dtype} {img_u8.shape}")
        frame = av.VideoFrame.from_ndarray(np.vstack([img_u8, self._chroma]), format="yuv420p")
        frame.pts = self._n
        self._n += 1
        packets = self._stream.encode(frame)
        self._container.mux(packets)
        return len(packets)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self._container.mux(self._stream.encode(None))
        finally:
            self._container.close()


class _UdpTsSink:
    """MPEG-TS bytes -> UDP datagrams of 1316 bytes (whole TS packets)."""

    def __init__(self, host: str, port: int) -> None:
        infos = socket.getaddrinfo(host, port, 0, socket.SOCK_DGRAM)
        family, _, _, _, self.addr = infos[0]
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        self._buf = bytearray()
        self.datagrams = 0
        self.errors = 0

    def write(self, data) -> int:
        self._buf += data
        while len(self._buf) >= TS_DATAGRAM_BYTES:
            self._send(bytes(self._buf[:TS_DATAGRAM_BYTES]))
            del self._buf[:TS_DATAGRAM_BYTES]
        return len(data)

    def flush(self) -> None:
        """Send what is left of whole TS packets (end of a frame: do not hold it for the next)."""
        n = len(self._buf) - len(self._buf) % TS_PACKET_BYTES
        if n:
            self._send(bytes(self._buf[:n]))
            del self._buf[:n]

    def _send(self, datagram: bytes) -> None:
        try:
            self.sock.sendto(datagram, self.addr)
            self.datagrams += 1
        except OSError:
            self.errors += 1  # nobody listening (ICMP refused) or a full buffer: the next frame goes on

    def close(self) -> None:
        self.sock.close()


def parse_destination(text: str, field: str = "video.destination") -> tuple[str, int]:
    """``HOST:PORT`` -> (host, port); InputError naming ``field``."""
    host, sep, port = str(text).rpartition(":")
    if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise InputError(f"{field}: expected HOST:PORT with PORT in 1..65535, got {text!r}")
    return host, int(port)


class VideoStreamer:
    """The encoder thread (module docstring).  ``submit`` from the pipeline thread; ``close`` to stop."""

    def __init__(self, destination: str, width_px: int, height_px: int, fps: float = 30.0,
                 bitrate_bps: int = 2_000_000, gop_s: float = 1.0, overlay: bool = True, queue_length: int = 2) -> None:
        host, port = parse_destination(destination)
        self.destination = destination
        self.port = port
        self.overlay = bool(overlay)
        self._sink = _UdpTsSink(host, port)
        self._encoder = H264TsEncoder(self._sink, width_px, height_px, fps, bitrate_bps,
                                      max(1, int(round(gop_s * fps))))
        self._agc = AgcState()
        self._q: collections.deque = collections.deque()
        self._maxlen = int(queue_length)
        self._cond = threading.Condition(threading.Lock())
        self._stop = False
        self.frames_in = 0
        self.frames_encoded = 0
        self.frames_dropped = 0
        self.errors = 0
        self.encode_ms: collections.deque = collections.deque(maxlen=1000)
        self._thread = threading.Thread(target=self._run, name="irtrack-video", daemon=True)
        self._thread.start()

    def submit(self, pixels: np.ndarray, track=None) -> None:
        """Queue a frame (and its track, for the overlay); never blocks; drops the oldest when full."""
        with self._cond:
            self.frames_in += 1
            while len(self._q) >= self._maxlen:
                self._q.popleft()
                self.frames_dropped += 1
            self._q.append((pixels, track))
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._q and not self._stop:
                    self._cond.wait(0.5)
                if self._stop:
                    return
                pixels, track = self._q.popleft()
            t0 = time.perf_counter()
            try:
                lo, hi = self._agc.update(pixels)
                img = agc_u8(pixels, lo, hi)
                if self.overlay:
                    img = draw_overlay(img, track)
                self._encoder.encode(img)
                self._sink.flush()
                self.frames_encoded += 1
            except Exception as exc:  # noqa: BLE001 - video must never take the daemon down
                self.errors += 1
                if self.errors == 1:
                    log.warning("video encoding failed: %s: %s", type(exc).__name__, exc)
            self.encode_ms.append((time.perf_counter() - t0) * 1000.0)

    def status(self) -> dict:
        ms = np.asarray(self.encode_ms, dtype=float)
        return {
            "destination": self.destination,
            "frames_in": self.frames_in,
            "encoded": self.frames_encoded,
            "dropped": self.frames_dropped,
            "errors": self.errors,
            "datagrams": self._sink.datagrams,
            "encode_ms_p50": float(np.percentile(ms, 50)) if ms.size else None,
            "encode_ms_p99": float(np.percentile(ms, 99)) if ms.size else None,
        }

    def close(self, timeout_s: float = 1.0) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout_s)
        try:
            self._encoder.close()
            self._sink.flush()
        except Exception as exc:  # noqa: BLE001
            log.debug("video close: %s", exc)
        self._sink.close()
