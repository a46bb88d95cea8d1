"""Frames, tracks and status go out with zenoh encodings that name their schema (seen by a plain
subscriber on 127.0.0.1), and the daemon's frame callback accepts untyped frames too but refuses one typed with
another schema."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from groundsim.io.ports import free_tcp_port
from onboard.app.config import build_config
from onboard.app.service import OnboardService
from onboard.core.irframe import IrFrame, encode_irframe
from onboard.io.zenoh_session import (
    FRAME_ENCODING,
    STATUS_ENCODING,
    TRACK_ENCODING,
    ZenohConfig,
    encoding_schema,
    foreign_schema,
    frame_key,
    open_session,
)

WAIT_S = 10.0


def test_encoding_schema_reads_typed_and_untyped():
    assert encoding_schema(FRAME_ENCODING) == "irtrack.irf1/1"
    assert encoding_schema(TRACK_ENCODING) == "irtrack.track/2"
    assert encoding_schema(STATUS_ENCODING) == "irtrack.status/1"
    assert encoding_schema("application/octet-stream") is None and encoding_schema(None) is None


def test_foreign_schema_names_only_another_schema():
    import zenoh

    schema = "irtrack.irf1/1"
    for untyped_or_same in (None, "application/octet-stream", FRAME_ENCODING):
        assert foreign_schema(untyped_or_same, schema) is None
    assert foreign_schema("application/octet-stream;irtrack.irf2/1", schema) == "irtrack.irf2/1"
    usual = zenoh.Encoding(FRAME_ENCODING)  # the daemon's fast path: zenoh's equality before any text
    assert foreign_schema(zenoh.Encoding(FRAME_ENCODING), schema, usual) is None
    assert foreign_schema(zenoh.Encoding("application/json;irtrack.track/2"), schema, usual) == "irtrack.track/2"


@pytest.mark.integration
def test_frame_publisher_sends_typed_frames_that_a_generic_subscriber_sees():
    import zenoh

    from groundsim.io.zenoh_video import FramePublisher

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    a = open_session(ZenohConfig(listen=(ep,)))
    b = open_session(ZenohConfig(connect=(ep,)))
    got, ev = [], threading.Event()
    try:
        sub = b.declare_subscriber(frame_key("uav1"), lambda s: (got.append(str(s.encoding)), ev.set()))
        pub = FramePublisher(a, "uav1")
        frame = IrFrame(1, 1000, np.zeros((4, 6), np.uint8))
        for _ in range(int(WAIT_S / 0.05)):  # until the subscription has propagated
            pub.publish(frame)
            if ev.wait(0.05):
                break
        assert got and got[0] == "application/octet-stream;irtrack.irf1/1"
        assert zenoh.Encoding(got[0]) == zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema("irtrack.irf1/1")
        pub.close()
        sub.undeclare()
    finally:
        b.close()
        a.close()


class _Payload:
    def __init__(self, data: bytes) -> None:
        self._d = data

    def __len__(self) -> int:
        return len(self._d)

    def to_bytes(self) -> bytes:
        return self._d


class _Sample:
    def __init__(self, data: bytes, encoding=None) -> None:
        self.payload = _Payload(data)
        if encoding is not None:
            self.encoding = encoding


def test_daemon_frame_callback_accepts_typed_and_untyped_refuses_foreign_schema():
    cfg = build_config({"estimator": {"enabled": False}, "output": {"health_file": None}})  # never started
    svc = OnboardService(cfg)
    try:
        data = encode_irframe(IrFrame(1, 1000, np.zeros((4, 6), np.uint8)))
        svc._on_frame(_Sample(data))  # untyped (a sample without an encoding)
        svc._on_frame(_Sample(data, "application/octet-stream"))  # untyped octet-stream
        svc._on_frame(_Sample(data, FRAME_ENCODING))  # typed
        svc._on_frame(_Sample(data, "application/octet-stream;irtrack.irf2/1"))  # another schema
        assert len(svc.queue) == 3
        assert svc.counter.counts.get("frame_schema") == 1
    finally:
        svc.close()


def test_daemon_counts_the_frames_that_never_arrived_in_its_status():
    """Frames 1, 2, 5, 4, 9 arrive (3, 6, 7, 8 lost on the way; 4 late): the status's frames.missing is 4 and
    frames.in 5."""
    cfg = build_config({"estimator": {"enabled": False}, "output": {"health_file": None}})  # never started
    svc = OnboardService(cfg)
    try:
        for seq in (1, 2, 5, 4, 9):
            svc._on_frame(_Sample(encode_irframe(IrFrame(seq, 1000 * seq, np.zeros((4, 6), np.uint8)))))
        frames = svc.status()["frames"]
        assert (frames["in"], frames["missing"]) == (5, 4)
    finally:
        svc.close()
