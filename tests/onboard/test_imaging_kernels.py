"""The compiled whole-frame pass of the objects chain against the OpenCV formulation it replaces: bit for bit."""

from __future__ import annotations

import platform

import cv2
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from onboard.imaging import kernels
from onboard.imaging.clutter import ClutterParams, noise_cells, point_contrast, two_level_cap
from onboard.imaging.kernels import contrast_and_cells, fits


def _reference(img: np.ndarray, guard: int, sharp: int, factor: int):
    """OpenCV's box mean and point contrast; the cells as the kernel's docstring states them (each cell's
    deviations summed in float32 row by row, then scaled), which is OpenCV's area resize where it runs on IPP."""
    params = ClutterParams(cell_px=3, guard_px=guard, sharp_guard_px=sharp)
    box3 = cv2.blur(img, (3, 3), borderType=cv2.BORDER_REPLICATE)
    dev = np.abs(img - box3)
    cells = np.zeros((img.shape[0] // factor, img.shape[1] // factor), np.float32)
    for a in range(factor):
        for b in range(factor):
            cells += dev[a::factor, b::factor]
    cells *= np.float32(1.0 / factor**2)
    return box3, point_contrast(img, params, box3.copy()), cells


def _kernel(img: np.ndarray, guard: int, sharp: int, factor: int, work=None):
    h, w = img.shape
    box3, contrast = np.full_like(img, np.nan), np.full_like(img, np.nan)
    cells = np.full((h // factor, w // factor), np.nan, np.float32)
    contrast_and_cells(img, guard, sharp, factor, box3, contrast, cells, work)
    return box3, contrast, cells


def _frame(seed: int, h: int, w: int, kind: str) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.normal(100.0, 4.0, (h, w))
    img[rng.integers(0, h, 6), rng.integers(0, w, 6)] += rng.uniform(5, 60, 6)  # points and hot pixels
    img += np.linspace(0.0, 30.0, w)[None, :]  # a gradient: the surrounds differ from side to side
    if kind == "integer":  # an 8-bit frame with no column offsets
        return np.clip(np.round(img), 0, 255).astype(np.float32)
    if kind == "destriped":  # integer grey minus fractional column offsets: sums that float32 would round
        return (np.round(img) - rng.uniform(-0.9, 0.9, w)[None, :]).astype(np.float32)
    return (img * 3.7 + 1e-3).astype(np.float32)  # wide, fine-grained values (16-bit frames)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    hc=st.integers(3, 12),
    wc=st.integers(3, 12),
    guard=st.integers(1, 6),
    sharp_offset=st.integers(0, 6),
    factor=st.sampled_from([2, 4]),
    kind=st.sampled_from(["integer", "destriped", "wide"]),
)
@example(seed=0, hc=128, wc=160, guard=4, sharp_offset=2, factor=4, kind="destriped")  # the detector's own
@example(seed=1, hc=6, wc=7, guard=4, sharp_offset=5, factor=4, kind="integer")  # sharp surround beyond the cells
def test_bit_for_bit_the_opencv_path(seed, hc, wc, guard, sharp_offset, factor, kind):
    sharp = min(sharp_offset, guard + 1) or 1
    h, w = hc * factor, wc * factor
    if not fits((h, w), 3, guard, sharp, factor):
        return
    img = _frame(seed, h, w, kind)
    ref_box, ref_contrast, ref_cells = _reference(img, guard, sharp, factor)
    box, contrast, cells = _kernel(img, guard, sharp, factor)
    np.testing.assert_array_equal(box, ref_box)
    np.testing.assert_array_equal(contrast, ref_contrast)
    np.testing.assert_array_equal(cells, ref_cells)
    # OpenCV's own area resize: the same to the bit where IPP runs it (below), else to rounding (its generic code
    # sums each cell row's four deviations before adding them)
    np.testing.assert_allclose(cells, noise_cells(img, factor, ref_box.copy()), rtol=1e-6, atol=0)


@pytest.mark.skipif(
    platform.machine() not in ("x86_64", "AMD64"), reason="OpenCV's wheels run the resize on IPP on x86-64"
)
@pytest.mark.parametrize("kind", ["integer", "destriped", "wide"])
def test_the_detectors_frames_bit_for_bit_opencvs_noise_cells(kind):
    """At the detector's 640 x 512 frames the kernel's cells are OpenCV's own, so every score of the chain is."""
    img = _frame(7, 512, 640, kind)
    box, contrast, cells = _kernel(img, 4, 2, 4)
    ref_box = cv2.blur(img, (3, 3), borderType=cv2.BORDER_REPLICATE)
    np.testing.assert_array_equal(box, ref_box)
    np.testing.assert_array_equal(cells, noise_cells(img, 4, ref_box))


def test_buffers_kept_between_frames_and_geometries():
    """The row buffers a caller keeps serve the next frame, and are rebuilt when the geometry changes."""
    work: dict = {}
    for guard, sharp, seed in ((4, 2, 3), (4, 2, 4), (2, 3, 5), (4, 2, 6)):
        img = _frame(seed, 64, 80, "destriped")
        for got, want in zip(_kernel(img, guard, sharp, 4, work), _reference(img, guard, sharp, 4), strict=True):
            np.testing.assert_array_equal(got, want)


def test_a_point_stands_out_and_edges_are_blank():
    img = np.full((32, 40), 50.0, np.float32)
    img[15:17, 20:22] = 60.0  # a 2 x 2 target 10 grey over a flat sky
    _, contrast, cells = _kernel(img, 4, 2, 4)
    assert contrast[15:17, 20:22].max() == pytest.approx(10.0)
    assert np.unravel_index(np.argmax(contrast), contrast.shape) in {(15, 20), (15, 21), (16, 20), (16, 21)}
    assert (
        not contrast[:5].any() and not contrast[-5:].any() and not contrast[:, :5].any() and not contrast[:, -5:].any()
    )
    assert cells.max() > 0 and cells[0, 0] == 0.0


@pytest.mark.parametrize(
    "shape, guard, sharp, factor",
    [((30, 40), 4, 2, 4), ((32, 40), 4, 6, 4), ((32, 40), 0, 1, 4), ((10, 40), 4, 2, 2), ((32, 40, 1), 4, 2, 4)],
)
def test_geometries_it_does_not_take(shape, guard, sharp, factor):
    assert not fits(shape, 3, guard, sharp, factor)
    if len(shape) == 2:
        img = np.zeros(shape, np.float32)
        with pytest.raises(ValueError, match="contrast_and_cells"):
            _kernel(img, guard, sharp, factor)


def test_cells_other_than_three_are_not_its():
    assert not fits((32, 40), 5, 4, 2, 4)
    assert fits((32, 40), 3, 4, 2, 4)


def test_wrong_arrays_are_named():
    img = np.zeros((32, 40), np.float32)
    with pytest.raises(ValueError, match="cells must be"):
        contrast_and_cells(img, 4, 2, 4, np.empty_like(img), np.empty_like(img), np.empty((8, 9), np.float32))
    with pytest.raises(ValueError, match="img must be"):
        contrast_and_cells(
            img.astype(np.float64), 4, 2, 4, np.empty_like(img), np.empty_like(img), np.empty((8, 10), np.float32)
        )


def test_the_detector_calls_only_what_warm_compiled():
    """A frame through the objects chain, mono8 and mono16, compiles no kernel signature beyond warm()'s (none is
    compiled on a frame in flight)."""
    from onboard.core.frames import PinholeIntrinsics
    from onboard.imaging.objects import ObjectTracker

    kernels.warm()
    compiled = list(kernels._contrast_and_cells.signatures)
    assert len(compiled) == 1
    K = PinholeIntrinsics(fx_px=800.0, fy_px=800.0, cx_px=320.0, cy_px=256.0, width_px=640, height_px=512)
    for dtype, scale in ((np.uint8, 1), (np.uint16, 256)):
        tracker = ObjectTracker(K, frame_rate_hz=30.0)
        frame = _frame(11, 512, 640, "integer") * scale
        tracker.update(np.clip(frame, 0, np.iinfo(dtype).max).astype(dtype), np.eye(3))
        assert tracker.detector.contrast is not None and tracker.detector.contrast.any()
    assert list(kernels._contrast_and_cells.signatures) == compiled


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    hc=st.integers(1, 40),
    wc=st.integers(1, 40),
    factor=st.sampled_from([1, 2, 4]),
    dtype=st.sampled_from([np.uint8, np.uint16]),
)
@example(seed=0, hc=128, wc=160, factor=4, dtype=np.uint8)  # the detector's background frames
@example(seed=1, hc=128, wc=160, factor=4, dtype=np.uint16)
def test_area_mean_is_opencvs_area_resize(seed, hc, wc, factor, dtype):
    rng = np.random.default_rng(seed)
    top = 255 if dtype == np.uint8 else 65535
    img = rng.integers(0, top + 1, (hc * factor, wc * factor)).astype(dtype)
    want = cv2.resize(img.astype(np.float32), (wc, hc), interpolation=cv2.INTER_AREA)
    got = kernels.area_mean(img, factor)
    assert got is not None and got.dtype == np.float32
    np.testing.assert_array_equal(got, want)


def test_area_mean_leaves_what_it_cannot_promise_to_opencv():
    img = np.zeros((32, 40), np.float32)
    assert kernels.area_mean(img, 4) is None  # a float frame: OpenCV's summation order would matter
    assert kernels.area_mean(np.zeros((30, 40), np.uint8), 4) is None  # a side not a multiple of the factor
    assert kernels.area_mean(np.zeros((32, 40), np.int16), 4) is None
    assert kernels.area_mean(np.zeros((36, 36), np.uint8), 3) is None
    assert kernels.area_mean(np.zeros((32, 40), np.uint8), 4) is not None


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    h=st.integers(1, 70),
    w=st.integers(1, 90),
    factor=st.sampled_from([1, 2, 3, 4]),
    level=st.integers(0, 65000),
    spread=st.sampled_from([1, 2, 3, 40]),
    dtype=st.sampled_from([np.uint8, np.uint16]),
)
@example(seed=0, h=512, w=640, factor=4, level=143, spread=2, dtype=np.uint8)
def test_two_level_cap_the_same_with_the_compiled_cell_extremes(seed, h, w, factor, level, spread, dtype):
    """Flat ground on a few grey levels with warmer patches: the cap is the same array whichever computes the cells'
    extremes (the compiled pass, or numpy rows and OpenCV's dilation along them)."""
    rng = np.random.default_rng(seed)
    base = min(level, np.iinfo(dtype).max - 80)
    img = base + rng.integers(0, spread, (h, w))
    patches = rng.integers(0, max(h * w // 200, 1))
    img[rng.integers(0, h, patches), rng.integers(0, w, patches)] += rng.integers(2, 40, patches)
    img = img.astype(dtype)
    hc, wc = h // factor, w // factor
    extremes = kernels.cell_extremes(img, factor)
    if hc and wc:
        cells = img[: hc * factor, : wc * factor].reshape(hc, factor, wc, factor)
        assert extremes is not None and extremes[0].dtype == dtype
        np.testing.assert_array_equal(extremes[0], cells.max(axis=(1, 3)))
        np.testing.assert_array_equal(extremes[1], cells.min(axis=(1, 3)))
    else:
        assert extremes is None
    compiled = two_level_cap(img, 31, factor, 1.0, 0.9)
    original = kernels.cell_extremes
    try:
        kernels.cell_extremes = lambda *_: None  # two_level_cap's own numpy and OpenCV formulation
        formulated = two_level_cap(img, 31, factor, 1.0, 0.9)
    finally:
        kernels.cell_extremes = original
    if formulated is None:
        assert compiled is None
    else:
        np.testing.assert_array_equal(compiled, formulated)


def _formulated_defect_update(img, sigma, decay, gain, level, rate):
    """DefectMap's numpy and OpenCV formulation of one update, on copies."""
    from onboard.imaging.clutter import isolated_outliers

    rate = rate.copy()
    out = isolated_outliers(img, sigma)
    rate *= decay
    np.add(rate, gain, out=rate, where=out)
    return rate, rate >= level


@settings(max_examples=80, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    h=st.integers(1, 40),
    w=st.integers(1, 50),
    sigma=st.sampled_from([0.0, 0.5, 2.0, 6.0, 37.25]),
    frames=st.integers(2, 40),
    kind=st.sampled_from(["integer", "destriped", "wide"]),
)
@example(seed=0, h=512, w=640, sigma=6.0, frames=7, kind="destriped")  # the detector's frame
@example(seed=3, h=1, w=1, sigma=0.0, frames=2, kind="integer")
def test_defect_rate_is_the_formulation_bit_for_bit(seed, h, w, sigma, frames, kind):
    """Outliers above and below, at the frame's edges and corners, with rates already decayed: the compiled update
    writes the same rates and map as the eight-neighbour dilation and erosion and numpy's float32 arithmetic."""
    rng = np.random.default_rng(seed)
    img = _frame(seed, max(h, 1), max(w, 1), kind)[:h, :w].copy()
    spikes = max(h * w // 20, 1)
    img[rng.integers(0, h, spikes), rng.integers(0, w, spikes)] += rng.choice([-1, 1], spikes) * rng.uniform(
        1, 80, spikes
    ).astype(np.float32)
    img[0, 0] += 90.0  # a corner pixel: its replicated neighbours include itself
    img[-1, w // 2] -= 90.0
    decay = np.float32(1.0 - 1.0 / frames)
    gain = np.float32(1.0) - decay
    level = np.float32(0.6) * np.float32(1.0 - decay**3)
    rate = (rng.integers(0, 4, (h, w)) * gain).astype(np.float32)
    want_rate, want_mask = _formulated_defect_update(img, sigma, decay, gain, level, rate)
    mask = np.zeros((h, w), np.bool_)
    assert kernels.defect_rate(img, np.float32(sigma), decay, gain, level, rate, mask)
    np.testing.assert_array_equal(rate, want_rate)
    np.testing.assert_array_equal(mask, want_mask)


def test_defect_rate_leaves_what_it_does_not_take_untouched():
    img, rate, mask = np.zeros((8, 9), np.float32), np.ones((8, 9), np.float32), np.zeros((8, 9), np.bool_)
    one = np.float32(1.0)
    assert not kernels.defect_rate(img.astype(np.float64), one, one, one, one, rate, mask)
    assert not kernels.defect_rate(img, one, one, one, one, np.ones((8, 8), np.float32), mask)
    assert not kernels.defect_rate(img[:, ::2], one, one, one, one, rate[:, ::2], mask[:, ::2])
    assert not kernels.defect_rate(img, one, one, one, one, rate, mask.view(np.uint8))
    assert (rate == 1.0).all() and not mask.any()


def test_defect_map_the_same_with_the_compiled_update():
    """A sequence of frames with hot, dead and blinking pixels: the map, the rates and the repaired frames are the same
    whichever computes the update."""
    from onboard.imaging.clutter import DefectMap

    rng = np.random.default_rng(5)
    compiled, formulated = DefectMap((48, 64), 6, 0.6), DefectMap((48, 64), 6, 0.6)
    original = kernels.defect_rate
    for k in range(14):
        img = rng.normal(100.0, 2.0, (48, 64)).astype(np.float32)
        img[10, 20] += 40.0  # hot
        img[30, 40] -= 40.0  # dead
        img[20, 63] -= 40.0  # dead at the edge, where a replicated neighbour is the pixel itself: never an outlier
        if k % 3 == 0:
            img[5, 5] += 40.0  # blinking: an outlier on a third of the frames
        compiled.update(img, 6.0)
        try:
            kernels.defect_rate = lambda *_: False
            formulated.update(img, 6.0)
        finally:
            kernels.defect_rate = original
        np.testing.assert_array_equal(compiled._rate, formulated._rate)
        np.testing.assert_array_equal(compiled.mask, formulated.mask)
        np.testing.assert_array_equal(compiled.repair(img), formulated.repair(img))
    assert compiled.mask[10, 20] and compiled.mask[30, 40] and not compiled.mask[5, 5] and not compiled.mask[20, 63]


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    h=st.integers(1, 30),
    w=st.integers(1, 40),
    dtype=st.sampled_from([np.uint8, np.uint16, np.float32]),
)
@example(seed=0, h=512, w=640, dtype=np.uint8)
def test_minus_columns_is_numpys_cast_and_subtraction(seed, h, w, dtype):
    rng = np.random.default_rng(seed)
    if dtype == np.float32:
        image = rng.normal(1000.0, 300.0, (h, w)).astype(np.float32)
    else:
        image = rng.integers(0, np.iinfo(dtype).max + 1, (h, w)).astype(dtype)
    offsets = rng.uniform(-3.0, 3.0, w).astype(np.float32)
    want = image.astype(np.float32)
    np.subtract(want, offsets[None, :], out=want)
    out = np.full((h, w), np.nan, np.float32)
    assert kernels.minus_columns(image, offsets, out)
    np.testing.assert_array_equal(out, want)


def test_minus_columns_leaves_what_it_does_not_take():
    out = np.zeros((4, 6), np.float32)
    offsets = np.zeros(6, np.float32)
    assert not kernels.minus_columns(np.ones((4, 6), np.float64), offsets, out)
    assert not kernels.minus_columns(np.ones((4, 6), np.int16), offsets, out)
    assert not kernels.minus_columns(np.ones((4, 12), np.uint8)[:, ::2], offsets, out)
    assert not kernels.minus_columns(np.ones((4, 6), np.uint8), np.zeros(5, np.float32), out)
    assert not kernels.minus_columns(np.ones((4, 6), np.uint8), offsets.astype(np.float64), out)
    assert not (out != 0).any()


_NO_FIRST_FRAME_COMPILE = r"""
import numpy as np
from onboard.app.config import build_config
from onboard.core.irframe import IrFrame, decode_irframe, encode_irframe
from onboard.imaging import kernels
from onboard.pipeline.frame_pipeline import make_tracker

cfg = build_config({"imaging": {"chain": "objects"}})
K = cfg.camera.intrinsics
chain = make_tracker(cfg)  # warms the kernels, as the daemon's start does
dispatchers = [getattr(kernels, n) for n in dir(kernels) if hasattr(getattr(kernels, n), "signatures")]
before = {d.__name__: len(d.signatures) for d in dispatchers}
rng = np.random.default_rng(0)
for dtype in (np.uint8, np.uint16):
    for seq in range(3):
        pixels = rng.integers(10, 30, (K.height_px, K.width_px)).astype(dtype)
        frame = decode_irframe(encode_irframe(IrFrame(seq, 100_000 + 33_333 * seq, pixels)))
        assert not frame.pixels.flags.writeable  # as the daemon receives it
        chain.update(frame.pixels, None, frame.time_boot_us)
after = {d.__name__: len(d.signatures) for d in dispatchers}
print({n: (before[n], after[n]) for n in before if after[n] != before[n]})
"""


def test_no_kernel_compiles_on_the_daemons_first_frames():
    """warm() compiled the kernels for writable arrays only; the daemon's frames are read-only views of the bytes
    received, a type numba compiles apart: the first frames of a new install paid 0.46 s and 0.12 s of compiling
    (a newcomer's first make demo dropped frames over it)."""
    import subprocess
    import sys

    # a process of its own: no other test's frames compiled anything in it (a kernel loaded from numba's cache
    # adds its signature as a compiled one does)
    out = subprocess.run([sys.executable, "-c", _NO_FIRST_FRAME_COMPILE], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "{}", out.stdout


def _cubic_numpy(big: np.ndarray, wx: np.ndarray, wy: np.ndarray) -> np.ndarray:
    """The numpy formulation the cubic kernel replaced (background_difference.cubic_square's until it was compiled)."""
    side = big.shape[0] - 3
    rows = wy[0] * big[0:side] + wy[1] * big[1 : side + 1] + wy[2] * big[2 : side + 2] + wy[3] * big[3 : side + 3]
    out = (
        wx[0] * rows[:, 0:side]
        + wx[1] * rows[:, 1 : side + 1]
        + wx[2] * rows[:, 2 : side + 2]
        + wx[3] * rows[:, 3 : side + 3]
    )
    a, b, c, d = (
        big[1 : side + 1, 1 : side + 1],
        big[1 : side + 1, 2 : side + 2],
        big[2 : side + 2, 1 : side + 1],
        big[2 : side + 2, 2 : side + 2],
    )
    return np.clip(out, np.minimum(np.minimum(a, b), np.minimum(c, d)), np.maximum(np.maximum(a, b), np.maximum(c, d)))


@settings(max_examples=60, deadline=None)
@given(
    st.integers(0, 2**31 - 1),
    st.sampled_from([4, 33]),
    st.floats(0.0, 1.0, exclude_max=True),
    st.floats(0.0, 1.0, exclude_max=True),
    st.sampled_from(["grey8", "grey16", "float", "edge"]),
)
def test_cubic_patch_is_numpys_cubic_resampling_bit_for_bit(seed, side, tx, ty, kind):
    from onboard.imaging.background_difference import keys_weights

    rng = np.random.default_rng(seed)
    n = side + 3
    if kind == "grey8":
        big = rng.integers(0, 256, (n, n)).astype(np.float32)
    elif kind == "grey16":
        big = rng.integers(0, 65536, (n, n)).astype(np.float32)
    elif kind == "float":
        big = rng.normal(130.0, 40.0, (n, n)).astype(np.float32)
    else:  # a roof's edge on two-level ground: the clip holds values inside their four pixels
        big = np.where(np.arange(n)[None, :] > n // 2, 205.0, 131.0) + rng.integers(0, 2, (n, n))
        big = big.astype(np.float32)
    wx, wy = keys_weights(tx), keys_weights(ty)
    got = kernels.cubic_patch(big, wx, wy)
    assert got.dtype == np.float32 and got.shape == (side, side)
    assert np.array_equal(got, _cubic_numpy(big, wx, wy))
