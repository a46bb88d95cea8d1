"""The independent video receiver (groundsim.io.video_rx): the daemon's encoder thread and UDP sink
(onboard.io.video.VideoStreamer) on 127.0.0.1 -> FFmpeg's decoder through PyAV; every frame comes back,
in order, with its index readable from the picture (bench.video's stamp)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from bench.video import H, W, read_index, stamp_index
from groundsim.io.video_rx import RtpMarkerDecoder, SdpRtpDecoder, UdpTsDecoder
from onboard.io.video import VideoConfig, VideoStreamer

FRAMES = 45  # one and a half GOPs at 30 Hz
WAIT_S = 10.0


def test_index_stamp_round_trips_in_both_depths():
    for dtype in (np.uint8, np.uint16):
        img = np.full((H, W), 7, dtype)
        for k in (0, 1, 0x5A5A, 0xFFFF):
            stamp_index(img, k)
            luma = (img.astype(np.float64) / np.iinfo(dtype).max * 255).astype(np.uint8)
            assert read_index(luma) == k


# transport -> the receiver that decodes it, and how many of the last frames it may still hold at the end
RECEIVERS = {
    "mpegts": (UdpTsDecoder, 2),  # the demuxer and the H.264 parser each hold one frame until the next starts
    "rtp-sdp": (SdpRtpDecoder, 2),  # FFmpeg's own RTP demuxer through an SDP file; its parser waits one frame
    "rtp-marker": (RtpMarkerDecoder, 0),  # decodes a picture at its last packet's marker bit
}


@pytest.mark.integration
@pytest.mark.parametrize("receiver", sorted(RECEIVERS))
def test_every_frame_is_decoded_in_order_from_the_first_idr(receiver):
    cls, held = RECEIVERS[receiver]
    transport = "mpegts" if receiver == "mpegts" else "rtp"
    got: list[int] = []
    done = threading.Event()

    def on_frame(f):
        got.append(read_index(f.luma))
        if len(got) >= FRAMES - held:
            done.set()

    rx = cls(on_frame)
    video = VideoConfig(destination=f"127.0.0.1:{rx.port}", transport=transport, overlay=False, queue_length=30)
    streamer = VideoStreamer(video, W, H)
    rng = np.random.default_rng(3)
    try:
        for k in range(FRAMES):
            img = (3000 + rng.normal(0, 10, (H, W))).astype(np.uint16)
            img[250:255, 300:305] = 4500
            stamp_index(img, k)
            # once the queue has room (the one in the encoder counted too): no drop however slow the encoder
            while streamer.frames_in - streamer.frames_encoded - streamer.errors >= video.queue_length:
                threading.Event().wait(0.005)
            streamer.submit(img)
            time.sleep(1 / 30)
        assert done.wait(WAIT_S), f"decoded {len(got)} of {FRAMES} frames; receiver error {rx.error}"
    finally:
        streamer.close()
        rx.stop()
    assert streamer.frames_dropped == 0
    assert got[: FRAMES - held] == list(range(FRAMES - held))
    assert rx.error is None and rx.decode_errors == 0
