"""IR video: AGC mapping, overlay, H.264/MPEG-TS round trip decoded by an independent decoder (PyAV's
FFmpeg decoder), the UDP streamer on 127.0.0.1 (>= 95 % of frames, the target visible where it is),
drop-oldest without blocking, and the stream advertised by the camera component."""

from __future__ import annotations

import io
import math
import socket
import threading
import time

import numpy as np
import pytest

av = pytest.importorskip("av")

from onboard.io.video import AgcState, H264TsEncoder, VideoStreamer, agc_limits, agc_u8, draw_overlay  # noqa: E402

W, H = 640, 512
N_FRAMES = 90  # 3 s at 30 Hz: three IDR periods
TARGET_MIN_GREY = 200  # the target's centre in the decoded frame (AGC maps it near the top)
SKY_MAX_GREY = 200
WAIT_S = 20.0


def _mono16(k: int) -> tuple[np.ndarray, tuple[int, int]]:
    """A 14-bit sky with a warm 5 x 5 object moving right by 2 px per frame; (frame, (u, v) of its centre)."""
    rng = np.random.default_rng(k)
    img = (3000 + 200 * np.linspace(0, 1, H)[:, None] + rng.normal(0, 10, (H, W))).astype(np.uint16)
    u, v = 100 + 2 * k, 250
    img[v - 2:v + 3, u - 2:u + 3] = 4500
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
    tr = Track(vehicle="uav1", seq=1, time_boot_us=1, state="tracking", track_id=1, u_px=110.0, v_px=110.0,
               bbox=(100.0, 100.0, 20.0, 20.0))
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
        enc.encode(agc_u8(img, *agc.update(img)))
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


@pytest.mark.integration
@pytest.mark.timeout(60)
def test_udp_stream_is_decoded_with_the_target_where_it_is():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.2)
    port = rx.getsockname()[1]
    chunks: list[bytes] = []
    done = threading.Event()

    def receive():
        while not done.is_set():
            try:
                chunks.append(rx.recv(65536))
            except socket.timeout:
                continue

    th = threading.Thread(target=receive, daemon=True)
    th.start()
    streamer = VideoStreamer(f"127.0.0.1:{port}", W, H, fps=30.0, overlay=False, queue_length=N_FRAMES)
    truth = []
    try:
        for k in range(N_FRAMES):
            img, uv = _mono16(k)
            truth.append(uv)
            streamer.submit(img)
        deadline = time.monotonic() + WAIT_S
        while streamer.frames_encoded < N_FRAMES and time.monotonic() < deadline:
            done.wait(0.05)
        st = streamer.status()
    finally:
        streamer.close()
        done.wait(0.5)  # the last datagrams
        done.set()
        th.join(5)
        rx.close()
    assert st["encoded"] == N_FRAMES and st["dropped"] == 0 and st["errors"] == 0
    assert all(len(c) % 188 == 0 and c[0] == 0x47 for c in chunks)  # whole TS packets per datagram
    frames = _decode(b"".join(chunks))
    assert len(frames) >= math.ceil(0.95 * N_FRAMES)
    seen = 0
    for img, (u, v) in zip(frames, truth):
        if img[v, u] >= TARGET_MIN_GREY and np.percentile(img, 50) < SKY_MAX_GREY:
            seen += 1
    assert seen >= math.ceil(0.95 * N_FRAMES)


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
    streamer = VideoStreamer("127.0.0.1:9", W, H, queue_length=2)
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


def test_camera_advertises_the_stream_on_the_destination_port():
    from onboard.app.config import build_config
    from onboard.app.service import make_camera_protocol

    cfg = build_config({"gcs": {"endpoints": ["udpout:127.0.0.1:14550"]}, "video": {"destination": "10.0.0.5:5600"}})
    K = cfg.camera.pinhole()
    proto = make_camera_protocol(cfg, K)
    s = proto.stream
    assert s.uri == "5600" and s.stream_type == 3 and s.thermal and (s.resolution_h_px, s.resolution_v_px) == (W, H)
    assert s.hfov_deg == pytest.approx(math.degrees(2 * math.atan(W / (2 * K.fx_px))))
    assert make_camera_protocol(build_config({"gcs": {"endpoints": ["udpout:127.0.0.1:14550"]}}), K).stream is None
