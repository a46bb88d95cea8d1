"""IR video: AGC mapping, overlay, H.264/MPEG-TS round trip decoded by an independent decoder (PyAV's
FFmpeg decoder), the RTP stream's packets (RFC 6184 on the wire), the UDP streamer on 127.0.0.1 for both
transports (RTP received by FFmpeg's own RTP demuxer through an SDP file written here, MPEG-TS by its
MPEG-TS demuxer: >= 95 % of frames, of the right size, the target visible where it is), the
receivers a ground station would use, drop-oldest without blocking, and the stream advertised by the
camera component with the type of its transport."""

from __future__ import annotations

import errno
import io
import math
import os
import socket
import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

av = pytest.importorskip("av")

from onboard.core.errors import ConfigError, InputError  # noqa: E402
from onboard.io.rtp_h264 import depacketize, parse_rtp, rtp_timestamp  # noqa: E402
from onboard.io.video import (  # noqa: E402
    AgcState,
    H264RtpEncoder,
    H264TsEncoder,
    VideoConfig,
    VideoStreamer,
    _UdpRtpSink,
    _UdpTsSink,
    agc_limits,
    agc_u8,
    draw_overlay,
)
from tests.fakes import tracking_track  # noqa: E402
from tests.udp_capture import UdpCapture  # noqa: E402

W, H = 640, 512
N_FRAMES = 90  # 3 s at 30 Hz: three IDR periods
TARGET_MIN_GREY = 200  # the target's centre in the decoded frame (AGC maps it near the top)
SKY_MAX_GREY = 200
WAIT_S = 20.0
TS_HELD_BACK_FRAMES = 2  # UdpTsDecoder: a PES ends only when the next one starts, and the decoder keeps one more
FRAME_US = 33_333  # 30 Hz
RTP_TICKS_PER_FRAME = 3000  # 90 kHz / 30 Hz (33 333 us -> 2999.97, floored per frame: 2999 or 3000)
MAX_DATAGRAM = 1400


def _mono16(k: int) -> tuple[np.ndarray, tuple[int, int]]:
    """A 14-bit sky with a warm 5 x 5 object moving right by 2 px per frame; (frame, (u, v) of its centre)."""
    rng = np.random.default_rng(k)
    img = (3000 + 200 * np.linspace(0, 1, H)[:, None] + rng.normal(0, 10, (H, W))).astype(np.uint16)
    u, v = 100 + 2 * k, 250
    img[v - 2 : v + 3, u - 2 : u + 3] = 4500
    return img, (u, v)


def test_agc_maps_percentiles_onto_the_display_range_and_keeps_flat_frames_dark_grey():
    img, _ = _mono16(0)
    lo, hi = agc_limits(img)
    out = agc_u8(img, lo, hi)
    assert out.dtype == np.uint8 and out.shape == img.shape
    assert 1.0 <= np.mean(out == 0) * 100 <= 3.0 and np.mean(out == 255) * 100 <= 3.0
    flat = np.full((H, W), 3000, np.uint16)
    assert np.all(agc_u8(flat, *agc_limits(flat)) == 127)  # no stretch of nothing into noise
    state = AgcState()
    state.update(img)
    bright = img + np.uint16(1000)
    lo2, _ = state.update(bright)
    assert lo < lo2 < lo + 1000  # smoothed: one frame moves the limits part of the way only
    with pytest.raises(Exception, match="2-D uint8/uint16"):
        agc_limits(np.zeros((4, 4, 3), np.uint8))


def test_overlay_draws_the_box_only_while_tracking():
    from onboard.core.track import Track

    img = np.zeros((H, W), np.uint8)
    tr = tracking_track(u_px=110.0, v_px=110.0, bbox=(100.0, 100.0, 20.0, 20.0))  # the overlay reads the box
    out = draw_overlay(img, tr)
    assert out[100, 100:121].min() == 255 and out[110, 110] == 0 and img.max() == 0  # input untouched
    lost = Track(vehicle="uav1", seq=1, time_boot_us=1, state="lost")
    assert draw_overlay(img, lost).max() == 0


def _decode(data: bytes) -> list[np.ndarray]:
    c = av.open(io.BytesIO(data), format="mpegts")
    try:
        return [f.to_ndarray(format="gray") for f in c.decode(video=0)]
    finally:
        c.close()


def test_encoder_round_trip_every_frame_with_an_idr_each_second():
    buf = io.BytesIO()
    enc = H264TsEncoder(buf, W, H, fps=30.0, gop_frames=30)
    agc = AgcState()
    for k in range(N_FRAMES):
        img, _ = _mono16(k)
        enc.encode(agc_u8(img, *agc.update(img)), capture_time_us=1_000_000 + k * FRAME_US)
    enc.close()
    c = av.open(io.BytesIO(buf.getvalue()), format="mpegts")
    keys, n, bframes = [], 0, 0
    for pkt in c.demux(video=0):
        if pkt.size:
            if pkt.is_keyframe:
                keys.append(n)
            n += 1
            bframes += pkt.pts is not None and pkt.dts is not None and pkt.pts != pkt.dts
    c.close()
    assert n == N_FRAMES and keys == [0, 30, 60]  # an IDR every second, nothing else
    assert bframes == 0  # no reordering: no B-frames
    frames = _decode(buf.getvalue())
    assert len(frames) == N_FRAMES


@pytest.mark.parametrize("transport", ["rtp", "mpegts"])
def test_an_idr_comes_each_second_of_capture_time_whatever_the_cameras_rate_and_gaps(transport):
    """video.fps says 30 but the camera gives 10 frames a second, then stops for 2 s: an IDR every second of
    capture time all the same (a ground station joins within it), the first frame after the gap one; MPEG-TS's
    time stamps are the capture times (the gap stays a gap)."""
    import random

    t_us = [1_000_000 + k * 100_000 for k in range(25)] + [5_500_000 + k * 100_000 for k in range(15)]
    img, _ = _mono16(0)
    grey = agc_u8(img, *AgcState().update(img))
    keys: list[int] = []
    if transport == "rtp":
        datagrams: list[bytes] = []
        enc = H264RtpEncoder(datagrams.append, W, H, fps=30.0, gop_frames=30, gop_s=1.0, rng=random.Random(1))
        for k, t in enumerate(t_us):
            n0 = len(datagrams)
            enc.encode(grey, capture_time_us=t)
            types = [n[0] & 0x1F for n in depacketize([parse_rtp(d).payload for d in datagrams[n0:]])]
            if 5 in types:
                keys.append(k)
    else:
        buf = io.BytesIO()
        enc_ts = H264TsEncoder(buf, W, H, fps=30.0, gop_frames=30, gop_s=1.0)
        for t in t_us:
            enc_ts.encode(grey, capture_time_us=t)
        enc_ts.close()
        c = av.open(io.BytesIO(buf.getvalue()), format="mpegts")
        pts = []
        for pkt in c.demux(video=0):
            if pkt.size:
                keys += [len(pts)] if pkt.is_keyframe else []
                pts.append(float(pkt.pts * pkt.time_base))
        c.close()
        assert np.allclose(np.diff(pts), np.diff(t_us) / 1e6, atol=2e-5)
    assert keys == [0, 10, 20, 25, 35]


@pytest.mark.parametrize("transport", ["rtp", "mpegts"])
def test_the_streams_stamps_go_on_one_frame_period_after_the_capture_clock_steps_back_and_keep_a_gap(transport, caplog):
    """The capture clock (the frames' time_boot_us) steps back 39.8 s (an autopilot reboot), then the camera is
    silent for 60 s: the stream's 90 kHz stamps (MPEG-TS PTS as PyAV's demuxer reads them; RTP timestamps of one
    SSRC) advance by one frame period at the step back, as between any two frames, and by the 60 s across the gap.
    Before, the PTS after the step back went up one tick a frame (until the capture clock passed its old maximum)
    and the RTP timestamps jumped back 39.8 s; a gap of over five GOPs was taken for a step and lost its time."""
    import logging
    import random

    before = [40_000_000 + k * FRAME_US for k in range(40)]
    after_reboot = [before[-1] - 39_800_000 + k * FRAME_US for k in range(40)]
    later = [after_reboot[-1] + 60_000_000 + k * FRAME_US for k in range(20)]
    t_us = before + after_reboot + later
    grey = agc_u8(_mono16(0)[0], *AgcState().update(_mono16(0)[0]))
    with caplog.at_level(logging.INFO, logger="onboard.io.video"):
        if transport == "rtp":
            datagrams: list[bytes] = []
            enc: H264RtpEncoder | H264TsEncoder
            enc = H264RtpEncoder(datagrams.append, W, H, fps=30.0, gop_frames=30, rng=random.Random(5))
            stamps = []
            for t in t_us:
                n0 = len(datagrams)
                enc.encode(grey, capture_time_us=t)
                packets = [parse_rtp(d) for d in datagrams[n0:]]
                assert {p.ssrc for p in packets} == {enc.packetizer.ssrc}
                stamps.append(packets[0].timestamp)
            steps = [(b - a) % 2**32 for a, b in zip(stamps, stamps[1:])]
        else:
            buf = io.BytesIO()
            enc = H264TsEncoder(buf, W, H, fps=30.0, gop_frames=30)
            for t in t_us:
                enc.encode(grey, capture_time_us=t)
            enc.close()
            c = av.open(io.BytesIO(buf.getvalue()), format="mpegts")
            stamps = [pkt.pts for pkt in c.demux(video=0) if pkt.size]
            c.close()
            assert len(stamps) == len(t_us)
            steps = [b - a for a, b in zip(stamps, stamps[1:])]
    gap = len(before) + len(after_reboot) - 1  # the step from the last frame before the gap to the first after it
    assert abs(steps[gap] - 60_000_000 * 90_000 // 1_000_000) <= 1, steps[gap]
    del steps[gap]
    assert all(abs(d - RTP_TICKS_PER_FRAME) <= 1 for d in steps), sorted(set(steps))
    assert enc.clock.resets == 1
    said = [r.getMessage() for r in caplog.records if "capture clock stepped" in r.getMessage()]
    assert len(said) == 1 and "-39.800" in said[0]


@pytest.mark.parametrize("transport", ["rtp", "mpegts"])
def test_decoded_grey_levels_are_the_pictures_and_the_stream_says_limited_range(transport):
    """A ramp over every grey level, through the encoder and PyAV's decoder (as a ground station converts it):
    the levels come back within 2 (a full-range picture in a stream read as limited range clipped ~11 % of a
    sky frame and stretched the rest by 1.16)."""
    import random

    ramp = np.tile(np.round(np.linspace(0, 255, W)).astype(np.uint8), (H, 1))
    if transport == "rtp":
        datagrams: list[bytes] = []
        enc = H264RtpEncoder(datagrams.append, W, H, rng=random.Random(2))
        enc.encode(ramp, capture_time_us=1_000_000)
        ctx = av.CodecContext.create("h264", "r")
        unit = b"".join(b"\x00\x00\x00\x01" + n for n in depacketize([parse_rtp(x).payload for x in datagrams]))
        frames = list(ctx.decode(av.Packet(unit))) + list(ctx.decode(None))
    else:
        buf = io.BytesIO()
        enc_ts = H264TsEncoder(buf, W, H)
        enc_ts.encode(ramp, capture_time_us=1_000_000)
        enc_ts.close()
        c = av.open(io.BytesIO(buf.getvalue()), format="mpegts")
        frames = list(c.decode(video=0))
        c.close()
    assert len(frames) == 1 and frames[0].color_range == 1  # AVCOL_RANGE_MPEG: limited, said in the stream
    grey = frames[0].to_ndarray(format="gray").astype(int)
    assert np.abs(grey - ramp).max() <= 2 and grey.min() <= 1 and grey.max() >= 254


def test_rtp_packets_are_rfc6184_with_capture_timestamps_markers_and_headers_before_each_idr():
    import random

    datagrams: list[bytes] = []
    enc = H264RtpEncoder(datagrams.append, W, H, fps=30.0, gop_frames=30, rng=random.Random(3))
    agc = AgcState()
    units: list[list] = []
    for k in range(N_FRAMES):
        img, _ = _mono16(k)
        n0 = len(datagrams)
        enc.encode(agc_u8(img, *agc.update(img)), capture_time_us=1_000_000 + k * FRAME_US)
        units.append([parse_rtp(d) for d in datagrams[n0:]])
    enc.close()
    assert all(len(d) <= MAX_DATAGRAM for d in datagrams)
    seqs = [p.sequence for unit in units for p in unit]
    assert all((b - a) % 65536 == 1 for a, b in zip(seqs, seqs[1:]))  # consecutive across frames
    ts = [unit[0].timestamp for unit in units]
    assert all({p.timestamp for p in unit} == {t} for unit, t in zip(units, ts))  # one timestamp per frame
    assert [(b - a) % 2**32 for a, b in zip(ts, ts[1:])] == [
        rtp_timestamp(1_000_000 + (k + 1) * FRAME_US) - rtp_timestamp(1_000_000 + k * FRAME_US)
        for k in range(N_FRAMES - 1)
    ]
    assert all(abs(d - RTP_TICKS_PER_FRAME) <= 1 for d in (b - a for a, b in zip(ts, ts[1:])))
    assert all([p.marker for p in unit] == [False] * (len(unit) - 1) + [True] for unit in units)
    for k, unit in enumerate(units):
        types = [n[0] & 0x1F for n in depacketize([p.payload for p in unit])]
        if k % 30 == 0:
            assert types[:2] == [7, 8] and 5 in types, f"frame {k}: NAL types {types}"  # SPS, PPS, IDR
        else:
            assert 5 not in types and 7 not in types, f"frame {k}: NAL types {types}"
    assert max(len(unit) for unit in units) > 1 and any(p.payload[0] & 0x1F == 28 for u in units for p in u)  # FU-A


def _udp_bound(port: int) -> bool:
    """Someone has bound UDP ``port`` on this machine (Linux: /proc/net/udp); no bind of ours to race it."""
    for name in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            with open(name) as f:
                rows = f.read().splitlines()[1:]  # "sl local_address rem_address st ...", address = HEXIP:HEXPORT
        except OSError:
            continue
        if any(int(row.split()[1].rpartition(":")[2], 16) == port for row in rows if len(row.split()) > 1):
            return True
    return False


def _submit_without_drop(streamer: VideoStreamer, img: np.ndarray, capture_time_us: int) -> None:
    """Submit once the streamer's queue has room (frames in, less those encoded or failed, counts the one in the
    encoder too): however far a loaded machine's encoder falls behind, no frame is dropped."""
    while streamer.frames_in - streamer.frames_encoded - streamer.errors >= streamer.settings.queue_length:
        threading.Event().wait(0.005)
    streamer.submit(img, capture_time_us=capture_time_us)


def _stream(destination: str, transport: str) -> tuple[dict, list]:
    """N_FRAMES through a VideoStreamer, submitted at up to twice the camera's rate (each once the queue has
    room); (status, truth (u, v) per frame).  Paced, not all at once: 90 frames encoded back to back leave as one
    burst of ~1 MB of datagrams, more than a loopback receive buffer holds when the receiving thread is
    slow on a loaded machine (a CI run lost a third of the MPEG-TS packets that way); a camera never bursts."""
    video = VideoConfig(destination=destination, transport=transport, fps=30.0, overlay=False, queue_length=30)
    streamer = VideoStreamer(video, W, H)
    truth = []
    try:
        for k in range(N_FRAMES):
            img, uv = _mono16(k)
            truth.append(uv)
            _submit_without_drop(streamer, img, k * FRAME_US)
            time.sleep(FRAME_US / 2e6)
        deadline = time.monotonic() + WAIT_S
        while streamer.frames_encoded < N_FRAMES and time.monotonic() < deadline:
            threading.Event().wait(0.05)
        st = streamer.status()
    finally:
        streamer.close()
    assert st["encoded"] == N_FRAMES and st["dropped"] == 0 and st["errors"] == 0, st
    assert st["transport"] == transport
    return st, truth


def _assert_target_seen(frames: list[np.ndarray], truth: list) -> None:
    assert len(frames) >= math.ceil(0.95 * N_FRAMES), f"decoded {len(frames)} of {N_FRAMES}"
    assert all(img.shape == (H, W) for img in frames)
    seen = sum(
        img[v, u] >= TARGET_MIN_GREY and np.percentile(img, 50) < SKY_MAX_GREY for img, (u, v) in zip(frames, truth)
    )
    assert seen >= math.ceil(0.95 * N_FRAMES)


@pytest.mark.integration
@pytest.mark.timeout(60)
def test_rtp_stream_is_decoded_by_ffmpegs_rtp_demuxer_from_an_sdp_file(tmp_path):
    from groundsim.io.ports import free_rtp_port

    port = free_rtp_port()
    sdp_path = tmp_path / "stream.sdp"
    # written here, by hand, not by onboard.io.rtp_h264.sdp: what a user would type for ffplay / VLC
    sdp_path.write_text(
        "v=0\no=- 0 0 IN IP4 127.0.0.1\ns=test\nc=IN IP4 127.0.0.1\nt=0 0\n"
        f"m=video {port} RTP/AVP 96\na=rtpmap:96 H264/90000\na=fmtp:96 packetization-mode=1\n"
    )
    frames: list[np.ndarray] = []
    result: dict = {}
    opened = threading.Event()

    def receive():
        try:
            c = av.open(
                str(sdp_path), format="sdp", options={"protocol_whitelist": "file,udp,rtp"}, timeout=(WAIT_S, 2.0)
            )
        except Exception as exc:  # noqa: BLE001 - reported below
            result["error"] = repr(exc)
            return
        try:
            opened.set()
            result["size"] = (c.streams.video[0].codec_context.width, c.streams.video[0].codec_context.height)
            for pkt in c.demux(video=0):
                frames.extend(f.to_ndarray(format="gray") for f in pkt.decode())
                if len(frames) == N_FRAMES:
                    # every frame sent is decoded: nothing more can come.  The demuxer gives the last frame only
                    # after a read timeout (it ends an access unit when the next one starts), and then waited
                    # out a second one before it ended (2 s of the test's 6)
                    break
        except av.error.ExitError:
            pass  # 2 s without a packet: the stream is over
        finally:
            c.close()

    th = threading.Thread(target=receive, daemon=True)
    th.start()
    deadline = time.monotonic() + WAIT_S
    while not _udp_bound(port):  # FFmpeg listens before the first IDR leaves
        assert time.monotonic() < deadline and th.is_alive(), f"FFmpeg never bound port {port}: {result}"
        threading.Event().wait(0.01)
    _, truth = _stream(f"127.0.0.1:{port}", "rtp")
    th.join(WAIT_S)
    assert not th.is_alive() and "error" not in result, result
    assert result["size"] == (W, H)
    _assert_target_seen(frames, truth)


@pytest.mark.integration
@pytest.mark.timeout(60)
def test_mpegts_stream_is_decoded_with_the_target_where_it_is():
    rx = UdpCapture()
    try:
        _, truth = _stream(f"127.0.0.1:{rx.port}", "mpegts")
    finally:
        rx.close()  # after the last datagrams
    chunks = rx.chunks
    assert all(len(c) % 188 == 0 and c[0] == 0x47 for c in chunks)  # whole TS packets per datagram
    _assert_target_seen(_decode(b"".join(chunks)), truth)


@pytest.mark.integration
@pytest.mark.timeout(60)
@pytest.mark.parametrize("receiver", ["SdpRtpDecoder", "RtpMarkerDecoder", "UdpTsDecoder"])
def test_ground_station_receivers_decode_their_transport(receiver):
    import groundsim.io.video_rx as video_rx

    transport = "mpegts" if receiver == "UdpTsDecoder" else "rtp"
    frames: list[np.ndarray] = []
    got_all = threading.Event()
    # the frames a receiver can deliver while the stream is still open: MPEG-TS holds the newest frames back
    # until more data (or the end) comes, so waiting for all N_FRAMES there only ever ran into the timeout
    before_end = N_FRAMES - TS_HELD_BACK_FRAMES if transport == "mpegts" else N_FRAMES

    def on_frame(f):
        frames.append(f.luma)
        if len(frames) >= before_end:
            got_all.set()

    rx = getattr(video_rx, receiver)(on_frame)
    try:
        if receiver == "SdpRtpDecoder":
            deadline = time.monotonic() + WAIT_S
            while not _udp_bound(rx.port):
                assert time.monotonic() < deadline, f"the receiver never bound port {rx.port}: {rx.error}"
                threading.Event().wait(0.01)
        _, truth = _stream(f"127.0.0.1:{rx.port}", transport)
        got_all.wait(5.0)  # bounded: MPEG-TS's held-back frames come, if at all, when stop() ends the stream
    finally:
        rx.stop()
    assert rx.error is None, rx.error
    if receiver == "RtpMarkerDecoder":
        assert rx.lost_units == 0 and len(frames) == N_FRAMES  # every access unit, at its marker
    _assert_target_seen(frames, truth)


def test_submit_never_blocks_and_drops_the_oldest(monkeypatch):
    gate = threading.Event()

    class SlowEncoder:
        def __init__(self, *a, **k) -> None:
            pass

        def encode(self, img) -> int:
            gate.wait(WAIT_S)  # an encoder stuck far behind the frames
            return 0

        def close(self) -> None:
            pass

    monkeypatch.setattr("onboard.io.video.H264TsEncoder", SlowEncoder)
    streamer = VideoStreamer(VideoConfig(destination="127.0.0.1:9", queue_length=2), W, H)
    try:
        img, _ = _mono16(0)
        t0 = time.perf_counter()
        for _ in range(50):
            streamer.submit(img)
        took_s = time.perf_counter() - t0
        assert streamer.frames_in == 50 and streamer.frames_dropped >= 47  # 1 in the encoder, 2 queued
        assert took_s < WAIT_S  # it returned while the encoder is stuck (no timing claim beyond that)
    finally:
        gate.set()
        streamer.close()


def _closed_port() -> int:
    """A port on 127.0.0.1 that nobody listens on (bound, then let go)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _recv_all(sock: socket.socket, n: int) -> list[bytes]:
    sock.settimeout(WAIT_S)
    return [sock.recv(65536) for _ in range(n)]


@pytest.mark.parametrize("sink_cls", [_UdpRtpSink, _UdpTsSink], ids=["rtp", "mpegts"])
def test_the_video_socket_is_connected_to_its_destination_and_takes_nothing_from_others(sink_cls):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as x:
        rx.bind(("127.0.0.1", 0))
        sink = sink_cls("127.0.0.1", rx.getsockname()[1])
        try:
            assert sink.sock.getpeername() == rx.getsockname()
            sink.send(b"picture")
            assert _recv_all(rx, 1) == [b"picture"] and sink.datagrams == 1
            x.sendto(b"from anyone", sink.sock.getsockname())  # a stranger writing to the sender's port
            rx.sendto(b"from the destination", sink.sock.getsockname())
            sink.sock.settimeout(WAIT_S)
            assert sink.sock.recv(100) == b"from the destination"  # the kernel dropped the stranger's
        finally:
            sink.close()


def test_nobody_listening_is_counted_not_raised_and_a_receiver_that_opens_gets_every_datagram():
    port = _closed_port()
    sink = _UdpRtpSink("127.0.0.1", port)
    try:
        sent = 0
        while sink.refused == 0 and sent < 1000:  # the ICMP port unreachable of one comes back on a later send
            sink.send(b"nobody")
            sent += 1
        assert sink.refused >= 1 and sink.errors == 0 and sink.datagrams == sent
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
            rx.bind(("127.0.0.1", port))  # the ground station opens its port
            for k in range(3):
                sink.send(b"unit %d" % k)
            assert _recv_all(rx, 3) == [b"unit 0", b"unit 1", b"unit 2"]  # none lost to an earlier refusal
    finally:
        sink.close()


def test_nobody_listening_is_said_once_and_that_datagrams_get_through_again_once(caplog):
    """Refusals were counted and never logged (tens of thousands over minutes, nothing in the log): one WARNING at
    the first, one INFO once datagrams went REFUSED_QUIET_S without one."""
    import logging

    from onboard.io.video import REFUSED_QUIET_S

    now_s = [100.0]
    port = _closed_port()
    sink = _UdpRtpSink("127.0.0.1", port, clock=lambda: now_s[0])
    try:
        with caplog.at_level(logging.INFO, logger="onboard.io.video"):
            sent = 0
            while sink.refused < 3 and sent < 3000:
                sink.send(b"nobody")
                sent += 1
            assert sink.refused >= 3
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
                rx.bind(("127.0.0.1", port))  # the ground station opens its port
                sink.send(b"first")
                now_s[0] += REFUSED_QUIET_S / 2
                sink.send(b"not yet")
                now_s[0] += REFUSED_QUIET_S / 2
                sink.send(b"quiet long enough")
                sink.send(b"and on")
                assert _recv_all(rx, 4) == [b"first", b"not yet", b"quiet long enough", b"and on"]
    finally:
        sink.close()
    said = [(r.levelno, r.getMessage()) for r in caplog.records if r.name == "onboard.io.video"]
    assert said == [
        (logging.WARNING, f"video: nobody listening at 127.0.0.1:{port}; counted in video.refused"),
        (logging.INFO, f"video: datagrams get through to 127.0.0.1:{port} again ({sink.refused} refused meanwhile)"),
    ]


def test_a_send_error_is_said_once_per_errno_until_a_datagram_leaves(caplog):
    import logging

    class Failing:
        errnos: list[int | None] = []

        def send(self, data: bytes) -> int:
            if self.errnos:
                e = self.errnos.pop(0)
                if e is not None:
                    raise OSError(e, os.strerror(e))
            return len(data)

        def close(self) -> None:
            pass

    sink = _UdpTsSink("127.0.0.1", _closed_port())
    sink.sock.close()
    sink.sock = Failing()  # type: ignore[assignment]
    sink.connected = True
    Failing.errnos = [errno.ENOBUFS] * 5 + [errno.EHOSTUNREACH] * 3 + [None] + [errno.ENOBUFS] * 2 + [None]
    with caplog.at_level(logging.INFO, logger="onboard.io.video"):
        for _ in range(13):
            sink.send(b"\x47" * 188)
    assert sink.errors == 10 and sink.datagrams == 3
    said = [(r.levelno, r.getMessage().split(" (")[0]) for r in caplog.records if r.name == "onboard.io.video"]
    assert said == [
        (logging.WARNING, "video: cannot send to 127.0.0.1:" + str(sink.port)),
        (logging.WARNING, "video: cannot send to 127.0.0.1:" + str(sink.port)),
        (logging.INFO, f"video: datagrams leave for 127.0.0.1:{sink.port} again"),
        (logging.WARNING, "video: cannot send to 127.0.0.1:" + str(sink.port)),
        (logging.INFO, f"video: datagrams leave for 127.0.0.1:{sink.port} again"),
    ]
    assert "(8 not sent meanwhile)" in caplog.records[2].getMessage()


def test_a_destination_unreachable_at_start_fails_nothing_and_is_connected_at_a_later_send(monkeypatch):
    """No route yet when the daemon starts (the data link comes up later): the datagram is counted and dropped,
    the next one connects and goes."""

    class NoRouteOnce(socket.socket):
        fails = 2  # the constructor's connect and the first send's

        def connect(self, address) -> None:
            if NoRouteOnce.fails:
                NoRouteOnce.fails -= 1
                raise OSError(errno.ENETUNREACH, "Network is unreachable")
            super().connect(address)

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", 0))
        monkeypatch.setattr(socket, "socket", NoRouteOnce)
        sink = _UdpRtpSink("127.0.0.1", rx.getsockname()[1])
        monkeypatch.undo()
        try:
            sink.send(b"lost")
            assert (sink.errors, sink.datagrams, sink.connected) == (1, 0, False)
            sink.send(b"goes")
            assert (sink.errors, sink.datagrams, sink.connected) == (1, 1, True)
            assert _recv_all(rx, 1) == [b"goes"]
        finally:
            sink.close()


def test_a_name_not_resolvable_at_start_fails_nothing_and_is_resolved_at_a_later_send(monkeypatch):
    """A companion booting before its DNS: the destination's name cannot be resolved when the daemon starts (this
    raised socket.gaierror out of the daemon's start, a traceback); the datagram is counted and dropped, and a later
    send resolves and connects."""
    real = socket.getaddrinfo
    fails = {"n": 2}  # the constructor's and the first send's

    def not_yet(host, *args, **kw):
        if host == "gcs.example" and fails["n"]:
            fails["n"] -= 1
            raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")
        return real("127.0.0.1" if host == "gcs.example" else host, *args, **kw)

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", 0))
        monkeypatch.setattr(socket, "getaddrinfo", not_yet)
        sink = _UdpRtpSink("gcs.example", rx.getsockname()[1])
        try:
            sink._next_resolve_s = -math.inf  # a second later
            sink.send(b"lost")
            assert (sink.errors, sink.datagrams, sink.connected) == (1, 0, False)
            for _ in range(50):  # within the second: dropped, counted, the name not looked up again
                sink.send(b"lost too")
            assert fails["n"] == 0 and sink.errors == 51
            sink._next_resolve_s = -math.inf  # a second later
            sink.send(b"goes")
            assert (sink.errors, sink.datagrams, sink.connected) == (51, 1, True)
            assert _recv_all(rx, 1) == [b"goes"]
        finally:
            sink.close()


def test_a_malformed_destination_name_is_counted_not_raised():
    """'x..y' passes the HOST:PORT check and makes the IDNA codec raise UnicodeError, which stopped the start."""
    sink = _UdpTsSink("x..y", 5600)
    try:
        sink.send(b"\x47" * 188)
        assert (sink.errors, sink.datagrams, sink.connected) == (1, 0, False)
    finally:
        sink.close()


def test_the_streamer_to_nobody_encodes_every_frame_and_counts_the_refusals():
    streamer = VideoStreamer(VideoConfig(destination=f"127.0.0.1:{_closed_port()}", queue_length=30), W, H)
    try:
        for k in range(5):
            _submit_without_drop(streamer, _mono16(k)[0], k * FRAME_US)
        deadline = time.monotonic() + WAIT_S
        while streamer.frames_encoded < 5 and time.monotonic() < deadline:
            threading.Event().wait(0.05)
        st = streamer.status()
    finally:
        streamer.close()
    assert st["encoded"] == 5 and st["errors"] == 0 and st["send_errors"] == 0
    assert st["refused"] >= 1 and st["datagrams"] > 0
    assert st["clock_resets"] == 0


def test_camera_advertises_the_stream_on_the_destination_port():
    from onboard.app.components import make_camera_protocol
    from onboard.app.config import build_config

    cfg = build_config({"gcs": {"endpoints": ["udpout:127.0.0.1:14550"]}, "video": {"destination": "10.0.0.5:5600"}})
    K = cfg.camera.pinhole()
    proto = make_camera_protocol(cfg, K)
    s = proto.stream
    # RTP/UDP by default: VIDEO_STREAM_TYPE_RTPUDP (1), QGC opens udp://0.0.0.0:5600 as RTP H.264
    # not flagged THERMAL: QGroundControl opens its main video only from a stream without the flag
    assert s.uri == "5600" and s.stream_type == 1 and not s.thermal and (s.resolution_h_px, s.resolution_v_px) == (W, H)
    ts = make_camera_protocol(
        build_config(
            {
                "gcs": {"endpoints": ["udpout:127.0.0.1:14550"]},
                "video": {"destination": "10.0.0.5:5600", "transport": "mpegts"},
            }
        ),
        K,
    )
    assert ts.stream.stream_type == 3 and ts.stream.uri == "5600"  # MPEG_TS: QGC opens mpegts://0.0.0.0:5600
    assert s.hfov_deg == pytest.approx(math.degrees(2 * math.atan(W / (2 * K.fx_px))))
    assert make_camera_protocol(build_config({"gcs": {"endpoints": ["udpout:127.0.0.1:14550"]}}), K).stream is None


def test_transport_is_checked_by_name():
    from onboard.app.config import build_config
    from onboard.io.camera_description import video_stream_type

    with pytest.raises(Exception, match="video.transport"):
        build_config({"video": {"destination": "10.0.0.5:5600", "transport": "rtsp"}})
    with pytest.raises(Exception, match="transport: expected one of rtp, mpegts, got 'srt'"):
        VideoConfig(destination="127.0.0.1:9", transport="srt")
    with pytest.raises(Exception, match="video.transport"):
        video_stream_type("webrtc")


def test_the_streamer_needs_the_sections_destination():
    with pytest.raises(InputError, match="video.destination"):
        VideoStreamer(VideoConfig(), W, H)  # the section's default: no video
    with pytest.raises(
        ConfigError, match=r"destination: expected HOST:PORT with PORT in 1..65535, got '127.0.0.1:70000'"
    ):
        VideoConfig(destination="127.0.0.1:70000")  # the section checks the port's range too (--check refuses it)
    with pytest.raises(ConfigError, match="destination: expected HOST:PORT"):
        VideoConfig(destination="127.0.0.1:560\u00b2")  # a superscript two: str.isdigit holds, int() raised ValueError


@settings(max_examples=200, deadline=None)
@given(
    h=st.integers(1, 70),
    w=st.integers(1, 70),
    wide=st.booleans(),
    pcts=st.tuples(st.floats(0.0, 100.0), st.floats(0.0, 100.0)).map(sorted),
    seed=st.integers(0, 2**32 - 1),
)
def test_agc_limits_are_numpys_linear_percentiles_of_the_subsample(h, w, wide, pcts, seed):
    """agc_limits computes its two percentiles from one partition; they are np.percentile's (linear) values."""
    dtype = np.uint16 if wide else np.uint8
    px = np.random.default_rng(seed).integers(0, np.iinfo(dtype).max + 1, (h, w)).astype(dtype)
    got = agc_limits(px, pcts[0], pcts[1], 4)
    want = np.percentile(px[::4, ::4], pcts)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)


def test_the_streamer_measures_the_cameras_rate_from_capture_times_through_gaps():
    """10 Hz capture stamps with every fifth frame missing (refused upstream) and jitter: 10 Hz, not the rate of
    the frames that came; None before it has enough frames."""
    streamer = VideoStreamer(VideoConfig(destination="127.0.0.1:9", queue_length=2), W, H)
    try:
        img = np.zeros((H, W), np.uint16)
        rng = np.random.default_rng(3)
        for k in range(10):
            streamer.submit(img, capture_time_us=k * 100_000)
        assert streamer.camera_rate_hz is None and streamer.status()["camera_rate_hz"] is None
        for k in range(10, 80):
            if k % 5:
                streamer.submit(img, capture_time_us=k * 100_000 + int(rng.integers(-2000, 2000)))
        assert streamer.camera_rate_hz == pytest.approx(10.0, rel=0.03)
        assert streamer.status()["camera_rate_hz"] == pytest.approx(10.0, rel=0.03)
    finally:
        streamer.close()
