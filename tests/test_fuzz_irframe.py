"""Fuzz target: the IRF1 decoder and the daemon's frame receive path (untrusted input), with hypothesis.

Subjects: :func:`onboard.core.irframe.decode_irframe` on any bytes-like payload (random bytes and valid
frames mutated: header fields flipped, truncated, extended, spliced; as ``bytes``, ``bytearray`` or
``memoryview``; any ``max_bytes``), and :meth:`onboard.app.service.OnboardService._on_frame`, the zenoh
subscriber callback (length check before any copy, decode, count by reason, queue), fed with a
stand-in for zenoh's sample whose payload has ``len`` and ``to_bytes`` as ``ZBytes`` has.

Properties:

* the decoder raises nothing but :class:`~onboard.core.irframe.IrFrameError` with a documented
  ``reason``; what it accepts re-encodes to the same bytes (its zoom field with them, any float32 it holds)
  and obeys ``max_bytes``;
* the callback never raises; each payload is either queued or counted exactly once, as
  ``frame_<reason>`` (never the catch-all ``frame_receive_error``);
* valid frames between garbage payloads all reach the queue, in order, with their pixels.

Budget: ``tests/fuzz_budget.py`` (``IRTRACK_FUZZ_EXAMPLES`` runs it longer).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from onboard.app.config import build_config
from onboard.app.service import OnboardService
from onboard.core.irframe import REJECT_REASONS, IrFrame, IrFrameError, decode_irframe, encode_irframe
from tests.fuzz_budget import fuzz_settings, timeout_s

pytestmark = pytest.mark.timeout(timeout_s(120))

CATCH_ALL = "frame_receive_error"
MAX_SIDE_PX = 16  # small frames: many examples per second; the size checks scale with the header fields

frames = st.builds(
    IrFrame,
    seq=st.integers(0, 2**32 - 1),
    time_boot_us=st.integers(0, 2**64 - 1),
    pixels=st.sampled_from([np.uint8, np.uint16]).flatmap(
        lambda dt: hnp.arrays(dt, hnp.array_shapes(min_dims=2, max_dims=2, min_side=1, max_side=MAX_SIDE_PX))
    ),
    zoom=st.one_of(st.just(0.0), st.floats(width=32)),  # not stated, any zoom, and what no zoom can be (NaN, -1)
)


@st.composite
def mutated_payload(draw):
    """A valid frame's bytes, then 0-3 of: a header field set to any value (all zeros and all ones as often as
    the rest), a byte flipped, truncated, extended, spliced with another frame.

    No change, and the edge values, keep the decoder's accept path and its dimensions check (a width or height of 0)
    reached: with at least one change of random value, nearly every case was refused for its magic or its size."""
    data = bytearray(encode_irframe(draw(frames)))
    for _ in range(draw(st.integers(0, 3))):
        op = draw(st.sampled_from(["field", "flip", "truncate", "extend", "splice"]))
        if op == "field":
            offset, fmt = draw(
                st.sampled_from(
                    [(0, "4s"), (4, "<H"), (6, "<H"), (8, "<I"), (12, "<I"), (16, "<I"), (20, "<Q"), (28, "<f")]
                )
            )
            size = {"4s": 4, "<H": 2, "<I": 4, "<Q": 8, "<f": 4}[fmt]
            if len(data) >= offset + size:
                data[offset : offset + size] = draw(
                    st.one_of(
                        st.binary(min_size=size, max_size=size), st.sampled_from([b"\x00" * size, b"\xff" * size])
                    )
                )
        elif op == "flip" and data:
            i = draw(st.integers(0, len(data) - 1))
            data[i] ^= draw(st.integers(1, 255))
        elif op == "truncate" and data:
            del data[draw(st.integers(0, len(data) - 1)) :]
        elif op == "extend":
            data += draw(st.binary(min_size=1, max_size=64))
        elif op == "splice":
            other = encode_irframe(draw(frames))
            i = draw(st.integers(0, len(data)))
            data[i:] = other[draw(st.integers(0, len(other) - 1)) :]
    return bytes(data)


payloads = st.one_of(st.binary(max_size=200), mutated_payload())
as_buffer = st.sampled_from([bytes, bytearray, lambda b: memoryview(b), lambda b: memoryview(bytearray(b))])


def _same_frame(a: IrFrame, b: IrFrame) -> bool:
    same_zoom = a.zoom == b.zoom or (math.isnan(a.zoom) and math.isnan(b.zoom))
    return (
        (a.seq, a.time_boot_us, a.pixels.dtype) == (b.seq, b.time_boot_us, b.pixels.dtype)
        and same_zoom
        and np.array_equal(a.pixels, b.pixels)
    )


# --------------------------------------------------------------------------- the decoder


@fuzz_settings(ci_default=400)
@given(payload=payloads, wrap=as_buffer, max_bytes=st.one_of(st.none(), st.integers(0, 2048)))
def test_decoder_raises_only_its_rejection_and_what_it_accepts_round_trips(payload, wrap, max_bytes):
    kwargs = {} if max_bytes is None else {"max_bytes": max_bytes}
    try:
        f = decode_irframe(wrap(payload), **kwargs)
    except IrFrameError as exc:
        assert exc.reason in REJECT_REASONS
        return
    assert max_bytes is None or len(payload) <= max_bytes
    again = encode_irframe(f)
    assert again[:28] == payload[:28] and again[32:] == payload[32:]
    # the zoom field: the same float32, but a NaN, whose payload bits a Python float may quiet (still not stated)
    assert again[28:32] == payload[28:32] or (math.isnan(f.zoom) and math.isnan(decode_irframe(again).zoom))
    assert f.stated_zoom is None or (math.isfinite(f.stated_zoom) and f.stated_zoom > 0)
    assert not f.pixels.flags.writeable


# --------------------------------------------------------------------------- the daemon's callback


class FakeZBytes(bytes):
    """What the callback uses of zenoh's ``ZBytes``: ``len()`` and ``to_bytes()``."""

    def to_bytes(self) -> bytes:
        return bytes(self)


class FakeSample:
    def __init__(self, payload: bytes) -> None:
        self.payload = FakeZBytes(payload)


@pytest.fixture(scope="module")
def service():
    """The daemon's object, never started (no zenoh, no MAVLink, no estimator worker): only its callback runs."""
    cfg = build_config(
        {
            "estimator": {"enabled": False},
            "input": {"max_frame_bytes": 4096, "queue_length": 1000},
            "output": {"health_file": None},
        }
    )
    svc = OnboardService(cfg)
    yield svc
    svc.close()


def _receive(svc: OnboardService, payload: bytes):
    """One payload through the callback; returns (queued frame or None, counts added)."""
    before = svc.counter.counts
    n_before = len(svc.queue)
    svc._on_frame(FakeSample(payload))  # must not raise
    added = {k: v - before.get(k, 0) for k, v in svc.counter.counts.items() if v != before.get(k, 0)}
    queued = None
    if len(svc.queue) > n_before:
        queued, _received_ns = svc.queue.pop(0.0)
    return queued, added


@fuzz_settings(ci_default=250)
@given(batch=st.lists(payloads, min_size=1, max_size=10))
def test_the_receive_callback_queues_or_counts_each_payload_once(service, batch):
    for payload in batch:
        queued, added = _receive(service, payload)
        assert CATCH_ALL not in added, added
        if queued is None:
            assert sum(added.values()) == 1, added
            (reason,) = added
            assert reason.startswith("frame_") and reason[len("frame_") :] in REJECT_REASONS, reason
        else:
            assert added == {}, added
            assert len(payload) <= service.config.input.max_frame_bytes


@fuzz_settings(ci_default=150)
@given(
    genuine=st.lists(frames, min_size=1, max_size=4),
    garbage=st.lists(st.lists(payloads, max_size=4), min_size=5, max_size=5),
)
def test_valid_frames_between_garbage_all_reach_the_queue_in_order(service, genuine, garbage):
    got = []
    for i, frame in enumerate(genuine):
        for g in garbage[i]:
            queued, _ = _receive(service, g)
            if queued is not None:  # garbage that is a well-formed frame is a frame (the pipeline judges seq/time)
                continue
        queued, added = _receive(service, encode_irframe(frame))
        assert queued is not None and added == {}, added
        got.append(queued)
    for g in garbage[-1]:
        _receive(service, g)
    assert len(got) == len(genuine) and all(_same_frame(a, b) for a, b in zip(got, genuine))


def test_a_frame_refused_on_its_length_alone_is_refused_not_lost_on_the_way():
    """Frame 2 of 1, 2, 3 is too large: refused on its length before its header (and number) is read, so the gap
    from 1 to 3 must not count it lost on the way as well; frame 5 of 3, 5 never came (one missing)."""
    cfg = build_config(
        {"estimator": {"enabled": False}, "input": {"max_frame_bytes": 4096}, "output": {"health_file": None}}
    )
    svc = OnboardService(cfg)
    try:
        pixels = np.zeros((8, 8), np.uint8)
        too_large = encode_irframe(IrFrame(seq=2, time_boot_us=2_000, pixels=np.zeros((64, 64), np.uint8)))
        for payload in (
            encode_irframe(IrFrame(seq=1, time_boot_us=1_000, pixels=pixels)),
            too_large,
            encode_irframe(IrFrame(seq=3, time_boot_us=3_000, pixels=pixels)),
            encode_irframe(IrFrame(seq=5, time_boot_us=5_000, pixels=pixels)),
        ):
            _receive(svc, payload)
        assert svc.counter.counts.get("frame_too_large") == 1
        assert svc.arrival_gaps.missing == 1
    finally:
        svc.close()
