"""IR video for ground stations: AGC display mapping, track overlay, H.264 over UDP as RTP or MPEG-TS.

Pure parts (no sockets, no threads): :func:`agc_limits` / :func:`agc_u8` (the display mapping a
thermal core applies: the 1st..99th percentile of the frame, smoothed over frames, stretched
linearly onto 0..255, so mono16 and mono8 frames look alike and the sky does not flicker),
:func:`draw_overlay` (the track box and its range / 1-sigma; with the objects image chain every object's box and
id, the selected target's drawn white and thicker), and two encoders over PyAV's libx264
with the same settings (``preset ultrafast``, ``tune zerolatency``, no B-frames, an IDR at least every
``gop_s`` of capture time -- whatever the camera's rate or the frames dropped -- with the SPS/PPS repeated, so a
ground station can join at any second; grey levels as limited-range luma, said so in the stream):
:class:`H264RtpEncoder` (access units packetised as RTP, RFC 6184, by
:class:`onboard.io.rtp_h264.RtpH264Packetizer`: 90 kHz timestamps from each frame's capture time, the
marker bit on an access unit's last packet) and :class:`H264TsEncoder` (MPEG-TS muxing into any
``write``-able, its 90 kHz time stamps from the capture times too).  Both streams' stamps always move forward:
where the capture clock steps back (a camera or autopilot restart), they go on one frame period after the last
(:class:`_StreamClock`; counted in the status's ``video.clock_resets``); a gap forward keeps its time.

Adapter: :class:`VideoStreamer` owns a thread and a UDP socket: :meth:`VideoStreamer.submit` (called by
the pipeline thread, never blocks) keeps at most ``queue_length`` frames and drops the oldest when the
encoder is behind (counted as ``dropped``); the thread maps, overlays, encodes and sends to
``destination``, by ``transport``:

* ``rtp`` (default): one RTP packet per datagram, at most 1400 bytes.  A receiver that assembles the
  picture at its marker bit (QGroundControl's GStreamer ``rtph264depay``) decodes it at once: capture
  -> decoded p99 ~25-40 ms on loopback; FFmpeg's RTP demuxer (``ffplay stream.sdp``), whose parser waits
  for the next picture, p99 ~60-65 ms (``python -m bench.video``, a loaded 2-core machine).
  QGroundControl opens it as VIDEO_STREAM_INFORMATION type RTPUDP (1) with uri = the port (it listens
  on ``udp://0.0.0.0:PORT``); FFmpeg / VLC through the session description of
  :func:`onboard.io.rtp_h264.sdp`.
* ``mpegts``: MPEG-TS in datagrams of 7 x 188 bytes (1316, the customary MPEG-TS-over-UDP payload);
  type MPEG_TS (3), QGC opens ``mpegts://0.0.0.0:PORT``.  MPEG-TS carries video without a length, so a
  demuxer knows a picture is complete only when the next one starts: about two frame periods more
  latency than RTP (p99 ~90-100 ms).

(:mod:`onboard.io.camera_protocol` advertises the stream; the mapping is
:func:`onboard.io.camera_description.video_stream_type`.)
"""

from __future__ import annotations

import collections
import logging
import math
import random
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from fractions import Fraction
from typing import Annotated, Literal, get_args

import numpy as np

from onboard.core.errors import InputError
from onboard.core.schema import Bool, Integer, Invalid, Number, Text, config_dataclass
from onboard.io.foxglove_messages import drawn_box
from onboard.io.rtp_h264 import DEFAULT_MAX_PACKET_BYTES, DEFAULT_PAYLOAD_TYPE, RtpH264Packetizer
from onboard.io.worker_queue import items_until_stopped, stop_and_join

__all__ = [
    "agc_limits",
    "agc_u8",
    "AgcState",
    "draw_overlay",
    "draw_objects",
    "OBJECT_GREY",
    "H264TsEncoder",
    "H264RtpEncoder",
    "VideoConfig",
    "VideoStreamer",
    "TS_DATAGRAM_BYTES",
    "TRANSPORTS",
]

log = logging.getLogger(__name__)

TS_PACKET_BYTES = 188
TS_DATAGRAM_BYTES = 7 * TS_PACKET_BYTES  # 1316
#: MPEG-TS time stamps (PTS, PCR) count a 90 kHz clock
TS_CLOCK_HZ = 90_000
#: the capture times the camera's rate is measured over (about 2 s at 30 Hz), and the fewest that measure it
RATE_FRAMES = 64
RATE_MIN_FRAMES = 16
#: FFmpeg's AVColorRange for limited ("TV", "MPEG") range: written into the stream's VUI
AVCOL_RANGE_MPEG = 1
AGC_LOW_PCT, AGC_HIGH_PCT = 1.0, 99.0
AGC_SMOOTHING = 0.1  # weight of the newest frame's limits (exponential smoothing)
AGC_MIN_SPAN = 8.0  # grey levels: a flat frame is not stretched into noise
AGC_SAMPLE_STEP = 4  # percentiles over every 4th pixel in each direction (1/16 of the frame)
Transport = Literal["rtp", "mpegts"]  # RTP/UDP (RFC 6184) or MPEG-TS/UDP (module docstring)
TRANSPORTS: tuple[str, ...] = get_args(Transport)
#: a step of the capture clock is logged at most this often (each one counted: ``clock_resets``)
CLOCK_STEP_LOG_INTERVAL_S = 10.0
SEND_BUFFER_BYTES = 1 << 20  # an IDR (~40-110 kB at 640 x 512) leaves in one burst of datagrams
RESOLVE_INTERVAL_S = 1.0  # a destination name not resolved yet is looked up at most this often (the encoder waits)
#: datagrams sent this long without a refusal: someone listens at the destination again.  Linux sends an ICMP port
#: unreachable about once a second per destination (icmp_ratelimit), so a shorter quiet time would say "again"
#: between two refusals of a destination still closed
REFUSED_QUIET_S = 5.0


def agc_limits(
    pixels: np.ndarray, low_pct: float = AGC_LOW_PCT, high_pct: float = AGC_HIGH_PCT, step: int = AGC_SAMPLE_STEP
) -> tuple[float, float]:
    """(low, high) input levels of one frame: its ``low_pct`` / ``high_pct`` percentiles (sub-sampled)."""
    if pixels.ndim != 2 or pixels.dtype not in (np.uint8, np.uint16):
        raise InputError(f"video frame must be a 2-D uint8/uint16 array, got {pixels.dtype} {pixels.shape}")
    sample = pixels[::step, ::step].ravel()
    n = sample.size
    # numpy's default (linear) percentile, from one partition at the two ranks: 0.09 ms instead of 0.21
    ranks = [((n - 1) * pct / 100.0) for pct in (low_pct, high_pct)]
    kth = sorted({min(int(r) + d, n - 1) for r in ranks for d in (0, 1)})
    part = np.partition(sample, kth)

    def at(r: float) -> float:
        k = int(r)
        lo_v, hi_v = float(part[k]), float(part[min(k + 1, n - 1)])
        return lo_v + (hi_v - lo_v) * (r - k)

    return at(ranks[0]), at(ranks[1])


@dataclass
class AgcState:
    """The smoothed limits (None before the first frame)."""

    low: float | None = None
    high: float | None = None

    def update(self, pixels: np.ndarray, smoothing: float = AGC_SMOOTHING) -> tuple[float, float]:
        lo, hi = agc_limits(pixels)
        if self.low is None or self.high is None:
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
    out = pixels.astype(np.float32)  # the same float32 operations as out-of-place, without the temporaries
    out -= np.float32(lo)
    out *= np.float32(scale)
    np.clip(out, 0.0, 255.0, out=out)
    return out.astype(np.uint8)


#: grey levels of the objects drawn: the selected target, the other confirmed objects, coasting ones
OBJECT_GREY = {"primary": 255, "confirmed": 200, "coasting": 130}


def draw_objects(out: np.ndarray, objects) -> None:
    """Every object of an ``irtrack.objects/1`` message drawn on ``out`` (in place): its box (at least
    :data:`~onboard.io.foxglove_messages.MIN_DRAWN_BOX_PX` a side about its centre, so a point target is framed,
    not covered) and its id above it; the selected target white and 2 px thick, others 1 px and greyer."""
    import cv2

    for o in objects.get("objects", ()):
        kind = "primary" if o.get("primary") else ("coasting" if o.get("state") == "coasting" else "confirmed")
        grey = OBJECT_GREY[kind]
        x, y, w, h = drawn_box(*o["box_px"])
        p0 = (int(round(x)), int(round(y)))
        p1 = (int(round(x + w)), int(round(y + h)))
        cv2.rectangle(out, p0, p1, grey, 2 if kind == "primary" else 1)
        cv2.putText(out, str(o["id"]), (p0[0], max(p0[1] - 3, 8)), cv2.FONT_HERSHEY_PLAIN, 0.7, grey, 1)


def draw_overlay(img_u8: np.ndarray, track, objects=None) -> np.ndarray:
    """The track's box (white, 1 px) and, with a 3-D position, ``range m +- sigma`` beside it; ``objects`` (an
    ``irtrack.objects/1`` dict, the objects image chain's) each object's box and id (:func:`draw_objects`); a copy."""
    import cv2

    out = img_u8.copy()
    if objects is not None:
        draw_objects(out, objects)
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


def _x264_options(gop_frames: int, bitrate_bps: int) -> dict[str, str]:
    """libx264's low-latency settings: ultrafast, zerolatency, no B-frames, an IDR at most every ``gop_frames``
    (no scene-cut IDRs; :class:`_GreyFrames` forces one sooner by capture time) with SPS/PPS repeated in band,
    ABR with a VBV of one second, the picture signalled as limited ("TV") range, which is what it holds."""
    g, kbps = int(gop_frames), int(bitrate_bps) // 1000
    return {
        "preset": "ultrafast",
        "tune": "zerolatency",
        "bf": "0",
        "g": str(g),
        "forced-idr": "1",  # a keyframe asked for by the frame's picture type is an IDR (a viewer can join at it)
        "x264-params": (
            f"keyint={g}:min-keyint={g}:scenecut=0:repeat-headers=1:vbv-maxrate={kbps}:vbv-bufsize={kbps}:range=tv"
            # x264 writes the range into the VUI only beside a colour description: BT.709's (grey has no colour)
            ":colorprim=bt709:transfer=bt709:colormatrix=bt709"
        ),
    }


#: grey 0..255 -> luma 16..235: decoders and ground stations (GStreamer's, FFmpeg's) read H.264 luma as
#: limited range unless told otherwise; full-range luma in a limited-range stream clips the sky's darkest and a
#: warm target's brightest tenth to black and white
_LIMITED_RANGE = np.round(16.0 + np.arange(256) * (219.0 / 255.0)).astype(np.uint8)


def _yuv420p_frame(img_u8: np.ndarray, chroma: np.ndarray):
    """A grey picture as a yuv420p frame: luma ``img_u8``, flat chroma; a fresh buffer per frame, which the
    frame wraps without a copy (``from_numpy_buffer``: 0.24 ms a frame less than ``from_ndarray``'s copy)."""
    import av

    return av.VideoFrame.from_numpy_buffer(np.vstack([img_u8, chroma]), format="yuv420p")


def _check_size(width_px: int, height_px: int) -> None:
    if width_px % 2 or height_px % 2:
        raise InputError(f"H.264 4:2:0 needs even frame sizes, got {width_px} x {height_px}")


class _GreyFrames:
    """The encoders' input: grey pictures of one (even) size, each checked and made the next yuv420p frame, its
    grey levels mapped to limited-range luma (:data:`_LIMITED_RANGE`); ``pts`` 0, 1, 2 ... unless the caller
    stamps it.  An IDR is asked for when ``gop_us`` of capture time passed since the last keyframe (a camera
    slower than ``video.fps``, or frames dropped, would otherwise stretch the frame-counted interval)."""

    def __init__(self, width_px: int, height_px: int, gop_us: int) -> None:
        import av
        import cv2

        self._cv2 = cv2
        _check_size(width_px, height_px)
        self.width_px, self.height_px = int(width_px), int(height_px)
        self._chroma = np.full((self.height_px // 2, self.width_px), 128, np.uint8)  # U and V planes, flat
        self._n = 0
        self._gop_us = int(gop_us)
        self._key_us: int | None = None  # capture time of the last keyframe
        self._picture_i = av.video.frame.PictureType.I

    def next(self, img_u8: np.ndarray, capture_time_us: int):
        if img_u8.shape != (self.height_px, self.width_px) or img_u8.dtype != np.uint8:
            raise InputError(
                f"encoder frame must be uint8 {self.height_px} x {self.width_px}, got {img_u8.dtype} {img_u8.shape}"
            )
        frame = _yuv420p_frame(self._cv2.LUT(img_u8, _LIMITED_RANGE), self._chroma)  # numpy's take: 7x slower
        frame.pts = self._n
        self._n += 1
        key = self._key_us
        if key is None or not 0 <= capture_time_us - key < self._gop_us:
            frame.pict_type = self._picture_i
            self._key_us = capture_time_us
        return frame

    def keyframe(self, capture_time_us: int) -> None:
        """The encoder made a keyframe of its own accord (its frame-counted interval)."""
        self._key_us = capture_time_us


class _StreamClock:
    """Capture times (us, the camera's clock) -> the stream's 90 kHz clock (MPEG-TS PTS, RTP timestamp), which must
    always move forward: ``(capture - origin) * 90 kHz`` plus a base that only changes when the capture clock steps.

    A capture time before the previous frame's (the camera or the autopilot rebooted, a time sync stepped the clock)
    re-bases the clock: that frame is stamped one frame period after the previous one and the following frames are
    spaced by their capture times from it.  A step forward is kept as it is, however long: a camera silent for a
    minute is a minute of the stream's time too (a receiver sees the gap it was), and stamps moving forward are
    always valid.  Without it, the stamps of every frame
    after a step back were pinned one tick apart until the capture clock passed its old maximum again, and an RTP
    receiver saw the timestamps of one SSRC jump back.  ``origin_us``: the capture time of stamp 0 (None: the first
    frame's).  ``resets``: the steps seen."""

    def __init__(self, fps: float, origin_us: int | None = None) -> None:
        self.period_ticks = max(1, round(TS_CLOCK_HZ / float(fps)))
        self._origin_us = origin_us
        self._base_ticks = 0
        self._last_us: int | None = None
        self._last_ticks = -1
        self.resets = 0
        self._logged_s = -math.inf

    def ticks(self, capture_time_us: int) -> int:
        c = int(capture_time_us)
        last_us = self._last_us
        if last_us is not None and c < last_us:
            self._origin_us, self._base_ticks = c, self._last_ticks + self.period_ticks
            self.resets += 1
            now_s = time.monotonic()
            if now_s - self._logged_s >= CLOCK_STEP_LOG_INTERVAL_S:
                self._logged_s = now_s
                log.info(
                    "video: the capture clock stepped %+.3f s between frames (a camera or autopilot restart?); the "
                    "stream's timestamps go on one frame period after the last (counted in video.clock_resets)",
                    (c - last_us) / 1e6,
                )
        elif self._origin_us is None:
            self._origin_us = c
        assert self._origin_us is not None
        # two frames with the same capture time: the second just after the first, since stamps must grow
        t = max(self._base_ticks + (c - self._origin_us) * TS_CLOCK_HZ // 1_000_000, self._last_ticks + 1)
        self._last_us, self._last_ticks = c, t
        return t


class H264TsEncoder:
    """Grey frames -> H.264 in MPEG-TS written to ``sink`` (anything with ``write(bytes)``).

    ``gop_frames``: frames between IDRs (x264 ``keyint`` = ``min-keyint``, no scene-cut IDRs);
    ``bitrate_bps``: target (ABR with a VBV of one second).  The chroma planes are flat (grey video).
    """

    def __init__(
        self,
        sink,
        width_px: int,
        height_px: int,
        fps: float = 30.0,
        bitrate_bps: int = 2_000_000,
        gop_frames: int = 30,
        gop_s: float = 1.0,
    ) -> None:
        import av

        self._frames = _GreyFrames(width_px, height_px, int(round(gop_s * 1e6)))
        self.width_px, self.height_px = self._frames.width_px, self._frames.height_px
        self.fps = float(fps)
        self._container = av.open(sink, mode="w", format="mpegts", options={"flush_packets": "1"})
        s = self._container.add_stream("libx264", rate=int(round(fps)))
        s.width, s.height, s.pix_fmt = self.width_px, self.height_px, "yuv420p"
        s.bit_rate = int(bitrate_bps)
        s.options = dict(_x264_options(gop_frames, bitrate_bps))  # av types it dict[str, object]
        s.codec_context.thread_count = 1
        s.codec_context.color_range = AVCOL_RANGE_MPEG
        # stamps in MPEG-TS's own 90 kHz units from each frame's capture time: a camera gap stays a gap in a
        # recording of the stream, and a camera off video.fps plays at its own speed
        s.codec_context.time_base = Fraction(1, TS_CLOCK_HZ)
        s.time_base = Fraction(1, TS_CLOCK_HZ)
        self._stream = s
        self.clock = _StreamClock(fps)
        self.closed = False

    def encode(self, img_u8: np.ndarray, capture_time_us: int | None = None) -> int:
        """Encode and mux one frame captured at ``capture_time_us`` (any monotonic microsecond clock; None: now),
        stamped with it; returns the number of packets written."""
        if capture_time_us is None:
            capture_time_us = time.monotonic_ns() // 1000
        frame = self._frames.next(img_u8, capture_time_us)
        frame.pts = self.clock.ticks(capture_time_us)
        frame.time_base = self._stream.codec_context.time_base
        packets = self._stream.encode(frame)
        if any(p.is_keyframe for p in packets):
            self._frames.keyframe(capture_time_us)
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


class H264RtpEncoder:
    """Grey frames -> H.264 access units -> RTP packets handed to ``send(datagram: bytes)``.

    The encoder is libx264 with the settings of :class:`H264TsEncoder` (no container: its Annex B
    output, SPS/PPS in band before every IDR); each access unit goes through an
    :class:`~onboard.io.rtp_h264.RtpH264Packetizer` (random SSRC and first sequence number) with the
    RTP timestamp of the frame's capture time (:func:`~onboard.io.rtp_h264.rtp_timestamp`, random
    offset).  ``ssrc`` / ``rng`` make a stream reproducible in tests.
    """

    def __init__(
        self,
        send,
        width_px: int,
        height_px: int,
        fps: float = 30.0,
        bitrate_bps: int = 2_000_000,
        gop_frames: int = 30,
        payload_type: int = DEFAULT_PAYLOAD_TYPE,
        max_packet_bytes: int = DEFAULT_MAX_PACKET_BYTES,
        rng: random.Random | None = None,
        gop_s: float = 1.0,
    ) -> None:
        import av

        self._frames = _GreyFrames(width_px, height_px, int(round(gop_s * 1e6)))
        self.width_px, self.height_px = self._frames.width_px, self._frames.height_px
        self.fps = float(fps)
        rng = rng or random.SystemRandom()
        self.packetizer = RtpH264Packetizer(
            rng.getrandbits(32), payload_type, max_packet_bytes, first_sequence=rng.getrandbits(16)
        )
        self._ts_offset = rng.getrandbits(32)
        # origin 0: the timestamps are rtp_timestamp(capture time, offset) until the capture clock steps
        self.clock = _StreamClock(fps, origin_us=0)
        self._send = send
        ctx = av.CodecContext.create("libx264", "w")
        ctx.width, ctx.height, ctx.pix_fmt = self.width_px, self.height_px, "yuv420p"
        rate = Fraction(int(round(fps)), 1)
        ctx.framerate, ctx.time_base = rate, 1 / rate
        ctx.bit_rate = int(bitrate_bps)
        ctx.options = _x264_options(gop_frames, bitrate_bps)
        ctx.thread_count = 1
        ctx.color_range = AVCOL_RANGE_MPEG
        ctx.open()
        self._ctx = ctx
        self.packets = 0
        self.closed = False

    def encode(self, img_u8: np.ndarray, capture_time_us: int | None = None) -> int:
        """Encode one frame captured at ``capture_time_us`` (any monotonic microsecond clock; None: now)
        and send its RTP packets; returns their number."""

        if capture_time_us is None:
            capture_time_us = time.monotonic_ns() // 1000
        packets = self._ctx.encode(self._frames.next(img_u8, capture_time_us))
        if any(p.is_keyframe for p in packets):
            self._frames.keyframe(capture_time_us)
        return self._send_units(packets, (self.clock.ticks(capture_time_us) + self._ts_offset) % (1 << 32))

    def _send_units(self, packets, timestamp: int) -> int:
        n = 0
        for packet in packets:  # zerolatency, no B-frames: one access unit out per frame in
            for datagram in self.packetizer.packetize(bytes(packet), timestamp):
                self._send(datagram)
                n += 1
        self.packets += n
        return n

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        # nothing is held back (zerolatency: no lookahead), so there is nothing to flush onto the wire


class _UdpSink:
    """One UDP socket connected to ``host:port``: the kernel delivers it datagrams from that address only (it
    never reads; unconnected, it would queue anyone's), and it learns when nobody listens there.

    Each datagram is sent on its own and counted (``datagrams``); one that does not leave is counted in
    ``errors`` and dropped, the next one goes on (a full buffer, no route yet: a destination that is not
    reachable when the daemon starts is connected again at the next send).  Nobody listening: the ICMP port
    unreachable of an earlier datagram comes back as ECONNREFUSED on a later send, which Linux then does not
    send; counted in ``refused`` and that datagram sent once more, so that a ground station that has just
    opened its port gets whole pictures.

    Said once per outage, not per datagram: one WARNING at the first refusal and one INFO once datagrams have gone
    :data:`REFUSED_QUIET_S` (on ``clock``) without one; one WARNING per kind of send error (errno) and one INFO at
    the next datagram that leaves."""

    send_buffer_bytes: int | None = None  # SO_SNDBUF of the socket, None: the system's

    def __init__(self, host: str, port: int, clock: Callable[[], float] = time.monotonic) -> None:
        self.host, self.port = host, port
        self._clock = clock
        self._refused_s: float | None = None  # the latest refusal while nobody is said to listen (None: listened)
        self._refused_at_warning = 0
        self._failing: dict[int | None, int] = {}  # errno of each send error said -> datagrams lost to it
        self.addr: tuple | None = None  # resolved at the first connect that can: DNS may come up after the daemon
        self.sock: socket.socket | None = None
        self.datagrams = 0
        self.errors = 0
        self.refused = 0
        self.connected = False
        self._warned = False
        self._next_resolve_s = -math.inf
        self._connect()

    def _connect(self) -> bool:
        try:
            sock, addr = self.sock, self.addr
            if sock is None or addr is None:
                now_s = time.monotonic()
                if now_s < self._next_resolve_s:
                    return False  # a name is looked up again once a second, not for every datagram
                self._next_resolve_s = now_s + RESOLVE_INTERVAL_S
                family, _, _, _, addr = socket.getaddrinfo(self.host, self.port, 0, socket.SOCK_DGRAM)[0]
                sock = socket.socket(family, socket.SOCK_DGRAM)
                if self.send_buffer_bytes is not None:
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.send_buffer_bytes)
                self.sock, self.addr = sock, addr
            sock.connect(addr)
        # a name not resolved yet (socket.gaierror) too: a companion may boot before its DNS; a malformed one
        # (UnicodeError from the IDNA codec) is counted the same, never raised out of the daemon's start
        except (OSError, UnicodeError) as exc:
            if not self._warned:
                self._warned = True
                log.warning("video: cannot reach %s:%s yet (%s); retried as datagrams come", self.host, self.port, exc)
            return False
        self.connected = True
        return True

    def send(self, datagram: bytes) -> None:
        if not self.connected and not self._connect():
            self.errors += 1
            return
        sock = self.sock
        assert sock is not None  # connected: made by _connect
        for _ in range(2):
            try:
                sock.send(datagram)
            except ConnectionRefusedError:
                self.refused += 1
                self._on_refused()
                continue
            except OSError as exc:
                self.errors += 1
                self._on_error(exc)
                return
            self.datagrams += 1
            if self._refused_s is not None or self._failing:
                self._on_sent()
            return
        self.errors += 1  # refused twice: a new ICMP error came back in between

    def _on_refused(self) -> None:
        if self._refused_s is None:
            self._refused_at_warning = self.refused - 1
            log.warning("video: nobody listening at %s:%s; counted in video.refused", self.host, self.port)
        self._refused_s = self._clock()

    def _on_error(self, exc: OSError) -> None:
        n = self._failing.get(exc.errno)
        self._failing[exc.errno] = 1 if n is None else n + 1
        if n is None:
            log.warning(
                "video: cannot send to %s:%s (%s); counted in video.send_errors",
                self.host,
                self.port,
                exc.strerror or exc,
            )

    def _on_sent(self) -> None:
        if self._failing:
            lost = sum(self._failing.values())
            self._failing.clear()
            log.info("video: datagrams leave for %s:%s again (%d not sent meanwhile)", self.host, self.port, lost)
        if self._refused_s is not None and self._clock() - self._refused_s >= REFUSED_QUIET_S:
            self._refused_s = None
            log.info(
                "video: datagrams get through to %s:%s again (%d refused meanwhile)",
                self.host,
                self.port,
                self.refused - self._refused_at_warning,
            )

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()


class _UdpRtpSink(_UdpSink):
    """RTP packets -> one UDP datagram each."""

    send_buffer_bytes = SEND_BUFFER_BYTES

    def flush(self) -> None:
        """Nothing buffered: each packet left as it was made."""


class _UdpTsSink(_UdpSink):
    """MPEG-TS bytes -> UDP datagrams of 1316 bytes (whole TS packets)."""

    def __init__(self, host: str, port: int, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(host, port, clock)
        self._buf = bytearray()

    def write(self, data) -> int:
        self._buf += data
        while len(self._buf) >= TS_DATAGRAM_BYTES:
            self.send(bytes(self._buf[:TS_DATAGRAM_BYTES]))
            del self._buf[:TS_DATAGRAM_BYTES]
        return len(data)

    def flush(self) -> None:
        """Send what is left of whole TS packets (end of a frame: do not hold it for the next)."""
        n = len(self._buf) - len(self._buf) % TS_PACKET_BYTES
        if n:
            self.send(bytes(self._buf[:n]))
            del self._buf[:n]


def parse_destination(text: str, field: str = "video.destination") -> tuple[str, int]:
    """``HOST:PORT`` -> (host, port); InputError naming ``field``."""
    host, sep, port = str(text).rpartition(":")
    if not sep or not host or not (port.isascii() and port.isdigit()) or not 1 <= int(port) <= 65535:
        raise InputError(f"{field}: expected HOST:PORT with PORT in 1..65535, got {text!r}")
    return host, int(port)


@config_dataclass
class VideoConfig:
    """``video``: the IR video for ground stations (the daemon's section, composed by
    :class:`onboard.app.config.OnboardConfig`; no ``destination``, no video).  ``queue_length``: frames
    :class:`VideoStreamer` holds while the encoder is behind."""

    destination: Annotated[str | None, Text(pattern=r"^[^\s:]+:\d{1,5}$", what="HOST:PORT")] = None
    transport: Annotated[Transport, Text()] = "rtp"
    fps: Annotated[float, Number(1.0, 120.0)] = 30.0
    bitrate_bps: Annotated[int, Integer(100_000, 50_000_000)] = 2_000_000
    gop_s: Annotated[float, Number(0.1, 1.0)] = 1.0
    overlay: Bool = True
    queue_length: Annotated[int, Integer(1, 30)] = 2

    def __post_init__(self) -> None:
        # the pattern takes up to five digits; the port's range is checked here, so that --check refuses it
        if self.destination is not None and not 1 <= int(self.destination.rsplit(":", 1)[1]) <= 65535:
            raise Invalid("destination", "HOST:PORT with PORT in 1..65535", self.destination)


class VideoStreamer:
    """The encoder thread (module docstring) sending ``width_px`` x ``height_px`` frames as ``settings`` says (its
    destination required).  ``submit`` from the pipeline thread; ``close`` to stop."""

    def __init__(self, settings: VideoConfig, width_px: int, height_px: int) -> None:
        if not isinstance(settings, VideoConfig):
            raise InputError(f"VideoStreamer needs a VideoConfig, got {type(settings).__name__}")
        if settings.destination is None:
            raise InputError("video.destination: a VideoStreamer needs a destination (host:port)")
        host, port = parse_destination(settings.destination)
        self.settings = settings
        self.destination = settings.destination
        self.port = port
        self.transport = settings.transport
        self.overlay = settings.overlay
        fps, bitrate_bps = settings.fps, settings.bitrate_bps
        gop_frames = max(1, int(round(settings.gop_s * fps)))
        self._sink: _UdpRtpSink | _UdpTsSink
        self._encoder: H264RtpEncoder | H264TsEncoder
        if self.transport == "rtp":
            self._sink = _UdpRtpSink(host, port)
            self._encoder = H264RtpEncoder(
                self._sink.send, width_px, height_px, fps, bitrate_bps, gop_frames, gop_s=settings.gop_s
            )
        else:
            self._sink = _UdpTsSink(host, port)
            self._encoder = H264TsEncoder(
                self._sink, width_px, height_px, fps, bitrate_bps, gop_frames, gop_s=settings.gop_s
            )
        self._agc = AgcState()
        self._q: collections.deque = collections.deque()
        self._maxlen = settings.queue_length
        self._cond = threading.Condition(threading.Lock())
        self._stop = threading.Event()
        self.frames_in = 0
        self.frames_encoded = 0
        self.frames_dropped = 0
        self.errors = 0
        self.encode_ms: collections.deque = collections.deque(maxlen=1000)
        self._capture_us: collections.deque[int] = collections.deque(maxlen=RATE_FRAMES)
        self._thread = threading.Thread(target=self._run, name="irtrack-video", daemon=True)
        self._thread.start()

    def submit(self, pixels: np.ndarray, track=None, capture_time_us: int | None = None, objects=None) -> None:
        """Queue a frame (and its track and objects -- an ``irtrack.objects/1`` dict --, for the overlay) captured
        at ``capture_time_us`` (the frame's ``time_boot_us``; None: the time of this call), never blocks; drops the
        oldest when full."""
        if capture_time_us is None:
            capture_time_us = time.monotonic_ns() // 1000
        with self._cond:
            self.frames_in += 1
            self._capture_us.append(int(capture_time_us))
            while len(self._q) >= self._maxlen:
                self._q.popleft()
                self.frames_dropped += 1
            self._q.append((pixels, track, int(capture_time_us), objects))
            self._cond.notify()

    def _run(self) -> None:
        for pixels, track, capture_time_us, objects in items_until_stopped(self._cond, self._q, self._stop.is_set):
            t0 = time.perf_counter()
            try:
                lo, hi = self._agc.update(pixels)
                img = agc_u8(pixels, lo, hi)
                if self.overlay:
                    img = draw_overlay(img, track, objects)
                self._encoder.encode(img, capture_time_us)
                self._sink.flush()
                self.frames_encoded += 1
            except Exception as exc:  # noqa: BLE001 - video must never take the daemon down
                self.errors += 1
                if self.errors == 1:
                    log.warning("video encoding failed: %s: %s", type(exc).__name__, exc)
            self.encode_ms.append((time.perf_counter() - t0) * 1000.0)

    @property
    def camera_rate_hz(self) -> float | None:
        """The rate of the frames submitted, from their capture times: one over the median interval of the last
        :data:`RATE_FRAMES` (a gap of refused or dropped frames does not lower it); None before
        :data:`RATE_MIN_FRAMES` or without forward intervals.  x264 spreads ``video.bitrate_bps`` over
        ``video.fps`` frames a second, so a camera at another rate sends that fraction of it."""
        with self._cond:
            t = np.asarray(self._capture_us, dtype=float)
        if t.size < RATE_MIN_FRAMES:
            return None
        dt = np.diff(t)
        dt = dt[dt > 0]
        return None if dt.size == 0 else 1e6 / float(np.median(dt))

    def status(self) -> dict:
        ms = np.asarray(self.encode_ms, dtype=float)
        rate = self.camera_rate_hz
        return {
            "destination": self.destination,
            "transport": self.transport,
            "frames_in": self.frames_in,
            "encoded": self.frames_encoded,
            "dropped": self.frames_dropped,
            "errors": self.errors,
            "datagrams": self._sink.datagrams,
            "send_errors": self._sink.errors,
            "refused": self._sink.refused,
            "clock_resets": self._encoder.clock.resets,
            "encode_ms_p50": float(np.percentile(ms, 50)) if ms.size else None,
            "encode_ms_p99": float(np.percentile(ms, 99)) if ms.size else None,
            "camera_rate_hz": None if rate is None else round(rate, 2),
        }

    def close(self, timeout_s: float = 1.0) -> None:
        stop_and_join(self._cond, self._stop, self._thread, timeout_s)
        try:
            self._encoder.close()
            self._sink.flush()
        except Exception as exc:  # noqa: BLE001
            log.debug("video close: %s", exc)
        self._sink.close()
