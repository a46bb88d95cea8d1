"""IR frame wire format: layout, round trip, every rejection reason, fuzz."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from onboard.core.errors import InputError
from onboard.core.irframe import (
    DEFAULT_MAX_BYTES,
    ENCODING_MONO8,
    ENCODING_MONO16,
    HEADER,
    MAGIC,
    REJECT_REASONS,
    IrFrame,
    IrFrameError,
    check_payload_size,
    decode_irframe,
    encode_irframe,
    zoom_off_calibration,
)

HEADER_BYTES = 32


def _frame(h=4, w=5, dtype=np.uint16, seq=7, t_us=1_234_567):
    px = (np.arange(h * w, dtype=np.uint32) * 997 % (np.iinfo(dtype).max + 1)).astype(dtype).reshape(h, w)
    return IrFrame(seq=seq, time_boot_us=t_us, pixels=px)


def _header(magic=MAGIC, version=1, encoding=2, width=5, height=4, seq=7, t_us=1_234_567, zoom=0.0):
    return HEADER.pack(magic, version, encoding, width, height, seq, t_us, zoom)


def _reencodes_to(f: IrFrame, payload: bytes) -> bool:
    """``encode_irframe(f)`` is ``payload``, but for a NaN zoom's payload bits (a float32 NaN through a Python
    float may come back quieted: still a NaN, still not stated)."""
    again = encode_irframe(f)
    if math.isnan(f.zoom):
        return again[:28] == payload[:28] and again[32:] == payload[32:] and math.isnan(decode_irframe(again).zoom)
    return again == payload


def test_header_is_32_bytes_little_endian_at_the_documented_offsets():
    assert HEADER.size == HEADER_BYTES
    payload = encode_irframe(_frame(h=3, w=2, dtype=np.uint16, seq=0x01020304, t_us=0x1122334455667788))
    assert payload[0:4] == b"IRF1"
    assert payload[4:6] == b"\x01\x00"  # version 1
    assert payload[6:8] == b"\x02\x00"  # mono16
    assert payload[8:12] == (2).to_bytes(4, "little")  # width
    assert payload[12:16] == (3).to_bytes(4, "little")  # height
    assert payload[16:20] == bytes([4, 3, 2, 1])  # seq, LE
    assert payload[20:28] == bytes([0x88, 0x77, 0x66, 0x55, 0x44, 0x33, 0x22, 0x11])
    assert payload[28:32] == b"\x00" * 4
    assert len(payload) == HEADER_BYTES + 3 * 2 * 2


def test_pixels_are_row_major_little_endian():
    px = np.array([[0x0102, 0x0304], [0x0506, 0x0708]], dtype=np.uint16)
    payload = encode_irframe(IrFrame(seq=1, time_boot_us=2, pixels=px))
    assert payload[HEADER_BYTES:] == bytes([2, 1, 4, 3, 6, 5, 8, 7])


@pytest.mark.parametrize("dtype, encoding", [(np.uint8, ENCODING_MONO8), (np.uint16, ENCODING_MONO16)])
def test_round_trip_both_encodings(dtype, encoding):
    f = _frame(h=6, w=9, dtype=dtype)
    assert f.encoding == encoding
    g = decode_irframe(encode_irframe(f))
    assert g.encoding == encoding
    assert (g.seq, g.time_boot_us) == (f.seq, f.time_boot_us)
    assert g.pixels.dtype == dtype and g.pixels.shape == (6, 9)
    np.testing.assert_array_equal(g.pixels, f.pixels)


def test_decode_of_bytes_is_zero_copy_and_read_only():
    payload = encode_irframe(_frame(h=8, w=8))
    g = decode_irframe(payload)
    assert not g.pixels.flags.writeable
    assert np.shares_memory(g.pixels, np.frombuffer(payload, dtype=np.uint8))


def test_decode_of_writable_buffer_copies_so_reuse_cannot_corrupt_it():
    buf = bytearray(encode_irframe(_frame(h=2, w=2, dtype=np.uint8)))
    g = decode_irframe(buf)
    before = g.pixels.copy()
    buf[HEADER_BYTES:] = b"\xff" * 4
    np.testing.assert_array_equal(g.pixels, before)


def test_frame_does_not_mutate_or_alias_writably_the_callers_array():
    px = np.zeros((2, 3), dtype=np.uint8)
    f = IrFrame(seq=0, time_boot_us=0, pixels=px)
    assert px.flags.writeable  # caller's array untouched
    assert not f.pixels.flags.writeable


def test_non_contiguous_and_big_endian_inputs_encode_correctly():
    base = np.arange(40, dtype=np.uint16).reshape(4, 10)
    f = IrFrame(seq=1, time_boot_us=1, pixels=base[:, ::2])
    np.testing.assert_array_equal(decode_irframe(encode_irframe(f)).pixels, base[:, ::2])
    with pytest.raises(IrFrameError) as e:
        IrFrame(seq=1, time_boot_us=1, pixels=base.astype(">u2"))
    assert e.value.reason == "encoding"


# ----------------------------------------------------------------------------- rejections


def _reason(payload, **kw) -> str:
    with pytest.raises(IrFrameError) as e:
        decode_irframe(payload, **kw)
    assert isinstance(e.value, InputError)
    assert e.value.reason in REJECT_REASONS
    return e.value.reason


@pytest.mark.parametrize(
    "payload, reason",
    [
        (b"", "short"),
        (b"IRF1" + b"\x00" * 27, "short"),
        (_header(magic=b"IRF2") + b"\x00" * 40, "magic"),
        (_header(version=2) + b"\x00" * 40, "version"),
        (_header(version=0) + b"\x00" * 40, "version"),
        (_header(encoding=0) + b"\x00" * 40, "encoding"),
        (_header(encoding=3) + b"\x00" * 40, "encoding"),
        (_header(width=0) + b"", "dims"),
        (_header(height=0) + b"", "dims"),
        (_header() + b"\x00" * 39, "size"),  # 4 x 5 x 2 = 40 expected
        (_header() + b"\x00" * 41, "size"),
        (_header(encoding=1) + b"\x00" * 40, "size"),  # mono8 wants 20
        (_header(width=2**32 - 1, height=2**32 - 1) + b"\x00" * 40, "too_large"),
    ],
)
def test_each_bad_payload_is_rejected_with_its_reason(payload, reason):
    assert _reason(payload) == reason


def test_a_frame_cut_short_names_its_sequence_number_and_a_bad_header_none():
    """A receiver counting frames lost by the gaps in their numbers needs the number of one that arrived broken."""
    with pytest.raises(IrFrameError) as e:
        decode_irframe(_header(seq=42) + b"\x00" * 39)
    assert (e.value.reason, e.value.seq) == ("size", 42)
    with pytest.raises(IrFrameError) as e:
        decode_irframe(_header(magic=b"IRF2", seq=42) + b"\x00" * 40)
    assert e.value.seq is None


def test_exact_size_boundaries_pass():
    f = decode_irframe(_header() + b"\x01" * 40)
    assert f.pixels.shape == (4, 5) and int(f.pixels[0, 0]) == 0x0101


def test_oversize_payload_is_rejected_on_length_before_parsing():
    """A frame 100x too large: refused on len() alone (even its header is garbage)."""
    payload = b"\x00" * (100 * (HEADER_BYTES + 640 * 512 * 2))
    assert len(payload) > DEFAULT_MAX_BYTES
    assert _reason(payload) == "too_large"
    assert _reason(encode_irframe(_frame(h=64, w=64)), max_bytes=HEADER_BYTES + 64 * 64 * 2 - 1) == "too_large"


def test_length_precheck_for_non_buffer_payloads():
    check_payload_size(HEADER_BYTES)
    for n, reason in ((HEADER_BYTES - 1, "short"), (DEFAULT_MAX_BYTES + 1, "too_large")):
        with pytest.raises(IrFrameError) as e:
            check_payload_size(n)
        assert e.value.reason == reason


def test_memoryview_input_is_accepted():
    payload = encode_irframe(_frame())
    g = decode_irframe(memoryview(payload))
    np.testing.assert_array_equal(g.pixels, _frame().pixels)


@pytest.mark.parametrize(
    "field, kwargs",
    [
        ("seq", dict(seq=-1, time_boot_us=0)),
        ("seq", dict(seq=2**32, time_boot_us=0)),
        ("time_boot_us", dict(seq=0, time_boot_us=-5)),
        ("time_boot_us", dict(seq=0, time_boot_us=2**64)),
        ("seq", dict(seq=1.5, time_boot_us=0)),
        ("seq", dict(seq=True, time_boot_us=0)),
    ],
)
def test_constructor_rejects_out_of_range_fields_naming_them(field, kwargs):
    with pytest.raises(IrFrameError) as e:
        IrFrame(pixels=np.zeros((2, 2), np.uint8), **kwargs)
    assert e.value.reason == "field"
    assert f"IrFrame.{field}" in str(e.value)


@pytest.mark.parametrize(
    "pixels, reason",
    [
        (np.zeros((2, 2), np.float32), "encoding"),
        (np.zeros((2, 2), np.int16), "encoding"),
        (np.zeros((2, 2, 3), np.uint8), "dims"),
        (np.zeros((0, 4), np.uint8), "dims"),
        (np.zeros(4, np.uint8), "dims"),
    ],
)
def test_constructor_rejects_bad_pixels(pixels, reason):
    with pytest.raises(IrFrameError) as e:
        IrFrame(seq=0, time_boot_us=0, pixels=pixels)
    assert e.value.reason == reason


# ----------------------------------------------------------------------------- properties

_frames = st.builds(
    IrFrame,
    seq=st.integers(0, 2**32 - 1),
    time_boot_us=st.integers(0, 2**64 - 1),
    pixels=st.sampled_from([np.uint8, np.uint16]).flatmap(
        lambda dt: hnp.arrays(dt, hnp.array_shapes(min_dims=2, max_dims=2, min_side=1, max_side=24))
    ),
    # any float32 a sender may write there: not stated, zooms, and the invalid ones a sloppy sender's padding makes
    zoom=st.one_of(st.just(0.0), st.floats(width=32), st.sampled_from([1.0, 2.0, -1.0, math.inf, math.nan])),
)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_frames)
def test_round_trip_property(f):
    payload = encode_irframe(f)
    assert len(payload) == HEADER_BYTES + f.pixels.size * f.pixels.itemsize
    g = decode_irframe(payload)
    assert (g.seq, g.time_boot_us, g.encoding) == (f.seq, f.time_boot_us, f.encoding)
    assert g.zoom == f.zoom or (math.isnan(g.zoom) and math.isnan(f.zoom))
    assert g.stated_zoom == f.stated_zoom and g.zoom_invalid == f.zoom_invalid
    assert g.stated_zoom is None or (math.isfinite(g.stated_zoom) and g.stated_zoom > 0)
    assert g.pixels.dtype == f.pixels.dtype
    np.testing.assert_array_equal(g.pixels, f.pixels)
    assert _reencodes_to(g, payload)


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=256))
def test_random_bytes_raise_only_irframe_error(data):
    try:
        f = decode_irframe(data)
    except IrFrameError as e:
        assert e.reason in REJECT_REASONS
    else:  # random bytes that happen to be a valid frame must round-trip exactly, their zoom field with them
        assert _reencodes_to(f, data)


@settings(max_examples=300, deadline=None)
@given(
    version=st.integers(0, 3),
    encoding=st.integers(0, 3),
    width=st.integers(0, 2**32 - 1),
    height=st.integers(0, 2**32 - 1),
    extra=st.integers(-3, 3),
)
def test_fuzzed_headers_are_accepted_only_when_consistent(version, encoding, width, height, extra):
    depth = {1: 1, 2: 2}.get(encoding, 1)
    want = width * height * depth
    body_len = max(0, min(want, 4096) + extra)
    payload = HEADER.pack(MAGIC, version, encoding, width, height, 1, 2, 0.0) + b"\x07" * body_len
    try:
        f = decode_irframe(payload, max_bytes=HEADER_BYTES + 4096)
    except IrFrameError as e:
        assert e.reason in REJECT_REASONS
    else:
        assert version == 1 and encoding in (1, 2) and width * height >= 1 and body_len == want
        assert f.pixels.shape == (height, width)


def test_header_struct_matches_issue_format():
    assert HEADER.format in ("<4sHHIIIQf", b"<4sHHIIIQf")
    assert struct.calcsize("<4sHHIIIQf") == HEADER_BYTES


# ----------------------------------------------------------------------------- the zoom field


@pytest.mark.parametrize("zoom", [1.0, 2.0, 0.5, 1.25])
def test_a_stated_zoom_is_a_little_endian_float32_at_offset_28_and_round_trips(zoom):
    payload = encode_irframe(IrFrame(seq=1, time_boot_us=2, pixels=np.zeros((2, 3), np.uint8), zoom=zoom))
    assert payload[28:32] == struct.pack("<f", zoom)
    g = decode_irframe(payload)
    assert g.zoom == zoom and g.stated_zoom == zoom and not g.zoom_invalid


def test_a_zoom_is_kept_as_its_float32_so_a_decoded_frame_equals_the_one_sent():
    f = IrFrame(seq=1, time_boot_us=2, pixels=np.zeros((2, 2), np.uint8), zoom=1.1)
    assert f.zoom == struct.unpack("<f", struct.pack("<f", 1.1))[0]
    assert decode_irframe(encode_irframe(f)).zoom == f.zoom


def test_an_old_senders_zero_padding_decodes_as_zoom_not_stated():
    """Every sender before the field wrote zeros there (struct '<4sHHIIIQ4x'): read as before."""
    old = struct.pack("<4sHHIIIQ4x", MAGIC, 1, ENCODING_MONO16, 5, 4, 7, 1_234_567) + b"\x00" * 40
    g = decode_irframe(old)
    assert g.zoom == 0.0 and g.stated_zoom is None and not g.zoom_invalid
    assert encode_irframe(_frame())[28:32] == b"\x00" * 4  # and a frame that states none still sends zeros


@pytest.mark.parametrize("zoom", [math.nan, -math.nan, -1.0, math.inf, -math.inf, -1e-30])
def test_a_zoom_no_zoom_can_be_is_not_refused_and_reads_as_not_stated(zoom):
    g = decode_irframe(_header(zoom=zoom) + b"\x00" * 40)
    assert g.pixels.shape == (4, 5)  # the frame is taken
    assert g.zoom_invalid and g.stated_zoom is None


def test_a_zoom_that_does_not_fit_a_float32_or_is_no_number_is_refused_by_the_constructor():
    for zoom in (1e39, "2", True, None):
        with pytest.raises(IrFrameError) as e:
            IrFrame(seq=0, time_boot_us=0, pixels=np.zeros((2, 2), np.uint8), zoom=zoom)
        assert e.value.reason == "field" and "IrFrame.zoom" in str(e.value)


@pytest.mark.parametrize(
    "stated, off",
    [(None, False), (1.0, False), (1.004, False), (0.996, False), (1.006, True), (0.99, True), (2.0, True)],
)
def test_zoom_off_calibration_beyond_half_a_percent(stated, off):
    assert zoom_off_calibration(stated) is off


@pytest.mark.parametrize(
    "stated, off", [(1.004, True), (1.003, True), (1.002, False), (0.997, True), (1.0, False), (None, False)]
)
def test_once_off_a_zoom_clears_only_within_half_the_tolerance(stated, off):
    """A lens read at the tolerance's edge (1.005 +- its last digit) would withhold every other frame and restart the
    estimator at each: once off, a zoom stays off until within a quarter of a percent."""
    assert zoom_off_calibration(stated, was_off=True) is off


@pytest.mark.parametrize("zoom", [1e-45, 1e-3, 1e3, 3.0e38])
def test_a_zoom_outside_the_plausible_range_is_stray_bytes_read_as_not_stated(zoom):
    """The old padding left uninitialised reads mostly as a subnormal or a huge float32: not a zoom, so it must not
    withhold every line of sight."""
    g = decode_irframe(_header(zoom=zoom) + b"\x00" * 40)
    assert g.zoom_invalid and g.stated_zoom is None


@pytest.mark.parametrize("zoom", [0.0, 0.01, 0.5, 30.0, 100.0])
def test_zooms_a_camera_states_are_taken(zoom):
    g = decode_irframe(_header(zoom=zoom) + b"\x00" * 40)
    assert not g.zoom_invalid and g.stated_zoom == (None if zoom == 0.0 else pytest.approx(zoom))


@pytest.mark.parametrize(
    ("header", "reason"),
    [
        (_header(encoding=9, seq=42), "encoding"),
        (_header(width=0, seq=42), "dims"),
        (_header(width=60_000, height=60_000, seq=42), "too_large"),
    ],
    ids=["encoding", "dims", "too_large"],
)
def test_a_frame_refused_after_its_header_was_read_names_its_sequence_number(header, reason):
    """Magic and version checked, the header's seq is the sender's: the frame arrived (refused and counted), and a
    receiver counting frames lost by the gaps in their numbers must not count it missing as well (it did for these
    three reasons, as it had for a frame cut short)."""
    with pytest.raises(IrFrameError) as e:
        decode_irframe(header + b"\x00" * 40)
    assert (e.value.reason, e.value.seq) == (reason, 42)
