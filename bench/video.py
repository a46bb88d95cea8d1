"""Video: ``python -m bench.video`` prints the encoder's ms per frame and the loopback latency.

1. Encoding cost at 640 x 512, 30 Hz: AGC mapping (mono16 -> 8 bit) + overlay + H.264 (PyAV libx264,
   ultrafast / zerolatency, no B-frames, IDR every 30 frames) + MPEG-TS muxing into memory, and the
   same with RTP packetisation (RFC 6184) instead of MPEG-TS, one thread, on frames of a 14-bit sky
   with sensor noise and a moving warm object (noise is the hard case for an encoder).  CPU time of
   the thread (``time.thread_time``: other programs on a loaded machine do not count), p50 / p99
   over ``--frames``; the issue's budget is <= 3 ms per frame.
2. Latency on loopback, the daemon's own video path, per transport (``--transport``): frames handed
   to :class:`onboard.io.video.VideoStreamer` (encoder thread, UDP to 127.0.0.1) at 30 Hz in real
   time, stamped with their capture time (the moment of the hand-off), received and decoded in this
   process (:mod:`groundsim.io.video_rx`, FFmpeg's H.264 decoder through PyAV) by:

   - ``rtp / ffmpeg-sdp``: FFmpeg's own RTP demuxer through a session description (independent of our
     packetiser); its H.264 parser ignores the marker bit and completes a picture when the next one
     starts, one frame period (33 ms) of the figure;
   - ``rtp / marker``: access units assembled at the RTP marker bit, as QGroundControl's GStreamer
     ``rtph264depay`` does, then decoded: what a QGC user sees, less QGC's display;
   - ``mpegts``: FFmpeg's MPEG-TS demuxer; video PES packets carry no length, so a picture is complete
     only when the next one starts, and the parser waits once more: about two frame periods (~70 ms).

   Each frame carries its index as 16 black/white blocks in its top row, read back from the decoded
   picture, so a dropped frame cannot shift the pairing.  Printed: capture -> decoded p50 / p99 / max
   after the first second (a receiver joins at the first IDR; printed apart) and frames decoded /
   submitted.  Wall time (a latency is wall time), so the machine's load is printed beside it.
   "Capture" here is the hand-off to the encoder: in the daemon the pipeline's own capture -> track
   latency (``python -m bench.onboard``, p99 ~15 ms) comes before it, since the frame is handed over
   with its track for the overlay.  The issue's budget for capture -> decoded frame is p99 <= 100 ms.

Prints numbers and the machine's load; asserts nothing.
"""

from __future__ import annotations

import io
import os
import sys
import threading
import time

import numpy as np

from bench import run_benchmark
from bench.options import BenchParser, nonnegative_int

W, H = 640, 512
CODE_BITS = 16
CODE_BLOCK_PX = 16  # each bit a 16 x 16 block in the top row (0 or full scale before AGC)
CODE_Y0 = 8


def _scene(rng):
    base = (3000 + 200 * np.linspace(0, 1, H)[:, None]).astype(np.float32)
    noise = [rng.normal(0, 10, (H, W)).astype(np.float32) for _ in range(8)]
    return base, noise


def _frame(base, noise, k: int) -> tuple[np.ndarray, tuple[int, int]]:
    img = (base + noise[k % 8]).astype(np.uint16)
    u, v = 100 + k % 400, 250
    img[v - 2 : v + 3, u - 2 : u + 3] = 4500
    return img, (u, v)


def _track(k: int, u: int, v: int):
    from onboard.core.track import Track

    return Track(
        vehicle="uav1",
        seq=k,
        time_boot_us=k,
        state="tracking",
        track_id=1,
        u_px=float(u),
        v_px=float(v),
        bbox=(u - 8.0, v - 8.0, 16.0, 16.0),
    )


def stamp_index(img: np.ndarray, k: int) -> None:
    """Write ``k`` (mod 2^16) into the top row as black (0) / white (full scale) blocks, in place."""
    full = np.iinfo(img.dtype).max
    for b in range(CODE_BITS):
        x0 = 8 + b * CODE_BLOCK_PX
        img[CODE_Y0 : CODE_Y0 + CODE_BLOCK_PX, x0 : x0 + CODE_BLOCK_PX] = full if (k >> b) & 1 else 0


def read_index(luma: np.ndarray) -> int:
    """The index written by :func:`stamp_index`, from a decoded (AGC-mapped) picture."""
    k = 0
    q = CODE_BLOCK_PX // 4
    for b in range(CODE_BITS):
        x0 = 8 + b * CODE_BLOCK_PX
        centre = luma[CODE_Y0 + q : CODE_Y0 + CODE_BLOCK_PX - q, x0 + q : x0 + CODE_BLOCK_PX - q]
        if float(centre.mean()) > 128.0:
            k |= 1 << b
    return k


def encode_cost(frames: int) -> None:
    from onboard.io.video import AgcState, H264RtpEncoder, H264TsEncoder, agc_u8, draw_overlay

    print(f"video 640x512 @30 Hz, {frames} frames, thread CPU time, load {os.getloadavg()[0]:.2f}")
    for transport in ("mpegts", "rtp"):
        base, noise = _scene(np.random.default_rng(0))
        sink = io.BytesIO()
        if transport == "mpegts":
            enc = H264TsEncoder(sink, W, H, 30.0, 2_000_000, 30)
        else:
            enc = H264RtpEncoder(sink.write, W, H, 30.0, 2_000_000, 30)
        agc = AgcState()
        ms_all, ms_enc = [], []
        for k in range(frames):
            img, (u, v) = _frame(base, noise, k)
            tr = _track(k, u, v)
            t0 = time.thread_time()
            out = draw_overlay(agc_u8(img, *agc.update(img)), tr)
            t1 = time.thread_time()
            enc.encode(out, k * 33_333)
            t2 = time.thread_time()
            ms_all.append((t2 - t0) * 1e3)
            ms_enc.append((t2 - t1) * 1e3)
        enc.close()
        a, e = np.asarray(ms_all), np.asarray(ms_enc)
        mbps = sink.tell() * 8 / (frames / 30.0) / 1e6
        name = {"mpegts": "TS", "rtp": "RTP"}[transport]
        print(
            f"  AGC + overlay + H.264 + {name}: p50 {np.percentile(a, 50):.2f} ms, p99 {np.percentile(a, 99):.2f} ms "
            f"per frame; H.264 + {name} alone: p50 {np.percentile(e, 50):.2f} ms, p99 {np.percentile(e, 99):.2f} ms; "
            f"{mbps:.2f} Mbit/s on the wire (target 2.0)"
        )


RECEIVERS = {"rtp": ("ffmpeg-sdp", "marker"), "mpegts": ("ffmpeg-ts",)}


def _receiver(transport: str, kind: str, on_frame):
    from groundsim.io.video_rx import RtpMarkerDecoder, SdpRtpDecoder, UdpTsDecoder

    if transport == "mpegts":
        return UdpTsDecoder(on_frame)
    return SdpRtpDecoder(on_frame) if kind == "ffmpeg-sdp" else RtpMarkerDecoder(on_frame)


def loopback_latency(frames: int, fps: float = 30.0, transport: str = "rtp", kind: str = "ffmpeg-sdp") -> None:
    from onboard.io.video import VideoConfig, VideoStreamer

    base, noise = _scene(np.random.default_rng(1))
    submit_ns: dict[int, int] = {}
    lat_ms: dict[int, float] = {}
    unknown = [0]
    lock = threading.Lock()

    def on_frame(f) -> None:
        k = read_index(f.luma)
        with lock:
            t = submit_ns.get(k)
            if t is None:
                unknown[0] += 1
            else:
                lat_ms[k] = (f.decoded_ns - t) / 1e6

    rx = _receiver(transport, kind, on_frame)
    streamer = VideoStreamer(
        VideoConfig(destination=f"127.0.0.1:{rx.port}", transport=transport, fps=fps, queue_length=2), W, H
    )
    period_ns = int(1e9 / fps)
    t_next = time.monotonic_ns()
    try:
        for k in range(frames):
            img, (u, v) = _frame(base, noise, k)
            stamp_index(img, k)
            now = time.monotonic_ns()
            if t_next > now:
                time.sleep((t_next - now) / 1e9)
            with lock:
                submit_ns[k] = t_capture = time.monotonic_ns()
            streamer.submit(img, _track(k, u, v), capture_time_us=t_capture // 1000)
            t_next += period_ns
        time.sleep(0.5)  # the last frames through encoder, socket and decoder
    finally:
        st = streamer.status()
        streamer.close()
        rx.stop()
    join = int(round(fps))  # the first second: a receiver joins at an IDR (and a demuxer probes the stream)
    # the last two frames wait for the end of the stream (a frame is complete when the next one starts)
    a = np.asarray([ms for k, ms in lat_ms.items() if join <= k < frames - 2])
    print(
        f"video loopback latency, {transport} / {kind} (VideoStreamer -> UDP 127.0.0.1 -> PyAV/FFmpeg decode), "
        f"{frames} frames at {fps:g} Hz, load {os.getloadavg()[0]:.2f}"
    )
    if a.size == 0:
        print(f"  no frame decoded (receiver: {rx.error or 'no data'})")
        return
    first = [lat_ms[k] for k in sorted(lat_ms) if k < join]
    if first:
        print(f"  joining: first frame decoded after {first[0]:.0f} ms; steady state from frame {join}:")
    print(
        f"  capture -> decoded: p50 {np.percentile(a, 50):.1f} ms, p99 {np.percentile(a, 99):.1f} ms, "
        f"max {a.max():.1f} ms (budget: p99 <= 100 ms)"
    )
    print(
        f"  frames decoded {len(lat_ms)}/{frames} ({100.0 * len(lat_ms) / frames:.1f} %), unreadable index {unknown[0]}, "
        f"encoder dropped {st['dropped']}, datagrams sent {st['datagrams']}"
    )


def main(argv=None) -> int:
    ap = BenchParser(prog="python -m bench.video")
    ap.add_argument(
        "--frames",
        type=nonnegative_int,
        default=300,
        help="frames for the encoding cost (default: %(default)s; 0 = skip)",
    )
    ap.add_argument(
        "--latency-frames",
        type=nonnegative_int,
        default=300,
        help="frames for the loopback latency, sent in real time at 30 Hz (default: %(default)s; 0 = skip)",
    )
    ap.add_argument(
        "--transport",
        choices=("rtp", "mpegts", "both"),
        default="both",
        help="the latency's transport(s) (default: %(default)s)",
    )
    args = ap.parse_args(argv)
    if args.frames == 0 and args.latency_frames == 0:
        ap.error("argument --frames: 0 with --latency-frames 0 measures nothing")
    if args.frames > 0:
        encode_cost(args.frames)
    if args.latency_frames > 0:
        for transport in ("rtp", "mpegts") if args.transport == "both" else (args.transport,):
            for kind in RECEIVERS[transport]:
                loopback_latency(args.latency_frames, transport=transport, kind=kind)
    return 0


if __name__ == "__main__":
    sys.exit(run_benchmark("video", main))
