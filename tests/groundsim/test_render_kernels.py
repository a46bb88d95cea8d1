"""The renderer's compiled loops (groundsim.world.render.kernels) against the numpy and OpenCV formulations
they replaced, bit for bit: the ray cast's nearest part (slab test and scaled-sphere quadratic in numpy
float32, written out here as the reference), the quantisation against cv2.add's rounding and saturation,
the cloud composite (with and without its last pyrUp step inside) and the grey-to-radiance map against
numpy's and OpenCV's passes; the camera model's counts, AGC
map and look-up against the numpy and OpenCV passes ``Sensor`` ran before them; and the coarse-grid bound that
spares the objects' depth windows (``PyrUpImage.lower_bound``) against the windows.  Byte identity of whole frames
is checked by the P1 goldens (tests/groundsim/test_scene.py) and the reference scenes' determinism tests."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from groundsim.world.render import IrSettings, PartRaster, TargetPart
from groundsim.world.render.background import PyrUpImage, SceneBackground
from groundsim.world.render.kernels import (
    agc_map,
    cast_part_rays,
    composite_band,
    fold_maps,
    lut_take,
    min_max,
    pairwise_sum_pow2,
    quantise_grey,
    remap_pair,
    scale_offset,
    scale_offset_window,
    scale_offset_window_twice,
    sensor_counts,
    table_lookup_blocks,
    terrain_blend,
)
from groundsim.world.render.pyrup_kernels import composite_up, fold_maps_up, terrain_blend_up
from groundsim.world.render.sensor import AGC_TAIL
from onboard.core.frames import PinholeIntrinsics

INTR = PinholeIntrinsics.vue_pro_640()
PARTS = (
    TargetPart("body", "box", (0.0, 0.0, 0.0), (0.075, 0.075, 0.02), 305.0, 0.9),
    TargetPart("arm", "box", (0.0, 0.0, 0.0), (0.16, 0.012, 0.008), 303.0, 0.9),
    TargetPart("motor", "ellipsoid", (0.11, 0.11, -0.01), (0.014, 0.014, 0.016), 330.0, 0.8),
    TargetPart("dome", "ellipsoid", (0.0, 0.0, -0.03), (0.05, 0.05, 0.03), 310.0, 0.9),
)


def numpy_nearest(raster: PartRaster, o_b: np.ndarray, d_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The numpy float32 formulation the kernel replaced: ``(t, part)`` per ray (inf, -1: none), parts
    numbered in ``PARTS`` order, ties to the boxes first, each in index order."""
    f32 = np.float32
    c = np.array([p.center_frd_m for p in PARTS])
    h = np.array([p.half_extent_m for p in PARTS])
    is_box = np.array([p.shape == "box" for p in PARTS])
    box_c, box_h = c[is_box].astype(f32), h[is_box].astype(f32)
    ell_c, ell_h = c[~is_box], h[~is_box].astype(f32)
    order = np.concatenate([np.flatnonzero(is_box), np.flatnonzero(~is_box)])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv = f32(1.0) / np.where(d_b == 0.0, f32(1e-30), d_b)
        oc = o_b - box_c
        lo = (-box_h - oc)[:, :, None] * inv[None]
        hi = (box_h - oc)[:, :, None] * inv[None]
        t_in = np.minimum(lo, hi).max(axis=1)
        t_out = np.maximum(lo, hi).min(axis=1)
        t_box = np.where((t_in <= t_out) & (t_out > 0.0), np.maximum(t_in, f32(0.0)), f32(np.inf))
        oe = ((o_b.astype(float) - ell_c) / ell_h).astype(f32)
        de = d_b[None] / ell_h[:, :, None]
        d0, d1, d2 = de[:, 0], de[:, 1], de[:, 2]
        o0, o1, o2 = oe[:, 0, None], oe[:, 1, None], oe[:, 2, None]
        a = d0 * d0 + d1 * d1 + d2 * d2
        b = d0 * o0 + d1 * o1 + d2 * o2
        cross = (o1 * d2 - o2 * d1) ** 2 + (o2 * d0 - o0 * d2) ** 2 + (o0 * d1 - o1 * d0) ** 2
        disc = a - cross
        sq = np.sqrt(np.maximum(disc, f32(0.0)))
        hit = (disc >= 0.0) & ((sq - b) / a > 0.0)
        t_ell = np.where(hit, np.maximum(-(b + sq) / a, f32(0.0)), f32(np.inf))
    t_all = np.concatenate([t_box, t_ell])
    t = t_all.min(axis=0)
    return t, np.where(np.isfinite(t), order[t_all.argmin(axis=0)], -1)


@settings(max_examples=40, deadline=None)
@given(
    origin=st.tuples(*[st.floats(-400.0, 400.0) for _ in range(3)]),
    aim=st.tuples(*[st.floats(-0.2, 0.2) for _ in range(3)]),
    seed=st.integers(0, 2**31),
)
def test_nearest_part_is_the_numpy_formulation_bit_for_bit(origin, aim, seed):
    raster = PartRaster(INTR, IrSettings(), PARTS, 0.0, 0.0, 1.0)
    o_b = np.array(origin, np.float32)
    # rays from the origin towards points scattered around `aim` (most meet a part, some graze or miss)
    rng = np.random.default_rng(seed)
    targets = np.array(aim) + rng.normal(0.0, 0.08, (400, 3))
    d_b = (targets - o_b).T.astype(np.float32)
    d_b[:, :4] = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]).T  # axis rays
    t, part = raster.intersect(o_b, d_b)
    t_ref, part_ref = numpy_nearest(raster, o_b, d_b)
    assert np.array_equal(t, t_ref)
    assert np.array_equal(part, part_ref)


def test_cast_part_rays_writes_part_minus_background_where_a_ray_meets_a_part():
    raster = PartRaster(INTR, IrSettings(), PARTS, 0.0, 0.0, 1.0)
    R_bc = np.eye(3)
    o_b = np.array([0.0, 0.0, -20.0], np.float32)  # 20 m in front of the object along its body z
    ss, r0, c0 = 4, 2, 3
    x = (np.linspace(-0.012, 0.012, 40))[None, :]
    y = (np.linspace(-0.012, 0.012, 36))[:, None]
    ref = np.arange(10 * 11, dtype=np.float32).reshape(10, 11)  # (38 // 4 + 1, 43 // 4 + 1) pixels
    L_emit = np.array([10.0, 20.0, 30.0, 40.0])  # in the kernels' part order: boxes, then ellipsoids
    out, hits = cast_part_rays(
        R_bc, o_b, x, y, raster._box_c, raster._box_h, raster._ell_c, raster._ell_h, L_emit,
        np.array([1.0, 0.0, 0.0, 1.0]), ref, ss, r0, c0, (40, 44),
    )  # fmt: skip
    d_b = np.stack(np.broadcast_arrays(x, y, np.ones_like(y) * np.ones_like(x))).reshape(3, -1).astype(np.float32)
    t_ref, part_ref = numpy_nearest(raster, o_b, d_b)
    part_ref = part_ref.reshape(36, 40)
    assert hits == int(np.count_nonzero(part_ref >= 0)) and 0 < hits < part_ref.size
    kernel_index = np.argsort(raster._part_order)  # PARTS index -> the kernels' part number
    for i, j in zip(*np.nonzero(part_ref >= 0)):
        want = L_emit[kernel_index[part_ref[i, j]]] - float(ref[(r0 + i) // ss, (c0 + j) // ss])
        assert out[r0 + i, c0 + j] == want
    untouched = np.ones_like(out, bool)
    untouched[r0 : r0 + 36, c0 : c0 + 40] = part_ref < 0
    assert not out[untouched].any()


def test_quantise_grey_is_cv2_adds_rounding_and_saturation():
    rng = np.random.default_rng(3)
    for full_scale, dtype, cv_type in ((255, np.uint8, cv2.CV_8U), (65535, np.uint16, cv2.CV_16U)):
        L_min, grey_per_L = np.float32(1.7), np.float32(37.3)
        L = (rng.uniform(-0.2, 1.2, (64, 80)) * full_scale / grey_per_L + L_min).astype(np.float32)
        L.ravel()[:500] = (np.round((L.ravel()[:500] - L_min) * grey_per_L) + 0.5) / grey_per_L + L_min  # ties
        L.ravel()[500:506] = [np.nan, np.inf, -np.inf, 3e9, -3e9, 1e30]
        noise = (rng.standard_normal((64, 80)) * 0.3).astype(np.float32)
        out = np.empty((64, 80), dtype)
        quantise_grey(L, L_min, grey_per_L, noise, full_scale, out)
        want = cv2.add((L - L_min) * grey_per_L, noise, dtype=cv_type)
        assert np.array_equal(out, want), full_scale


def test_composite_and_scale_offset_are_numpys_passes():
    rng = np.random.default_rng(4)
    below = rng.uniform(1.0, 50.0, (40, 30)).astype(np.float32)
    a_up = rng.uniform(0.0, 1.0, (60, 30)).astype(np.float32)
    lit_up = rng.uniform(0.0, 30.0, (60, 30)).astype(np.float32)
    out = np.empty_like(below)
    composite_band(below, a_up, lit_up, 8, 31, 5, out)
    want = below.copy()
    seg = a_up[5 : 5 + 23] * below[8:31]
    want[8:31] = (below[8:31] - seg) + lit_up[5 : 5 + 23]
    assert np.array_equal(out, want)
    grey = rng.uniform(0.0, 255.0, (40, 30)).astype(np.float32)
    want = grey * np.float32(0.0173)
    want += np.float32(2.5)
    assert np.array_equal(scale_offset(grey, np.float32(0.0173), np.float32(2.5)), want)
    ringed = np.pad(grey, 4, mode="edge")  # the window of a larger image, read in place
    assert np.array_equal(scale_offset_window(ringed, 4, 4, 40, 30, np.float32(0.0173), np.float32(2.5)), want)
    image, copy = scale_offset_window_twice(ringed, 4, 4, 40, 30, np.float32(0.0173), np.float32(2.5))
    assert np.array_equal(image, want) and np.array_equal(copy, want) and not np.shares_memory(image, copy)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    hh=st.integers(2, 40),
    wh=st.integers(2, 50),
    top=st.integers(0, 12),
    rows=st.integers(0, 90),
    w0=st.integers(0, 6),
)
def test_composite_up_is_cv2_pyrup_then_the_composite(seed, hh, wh, top, rows, w0):
    """The cloud composite with the weights' last pyrUp step inside: cv2.pyrUp's values (its first and last
    rows and columns included), then composite_band's, bit for bit."""
    rng = np.random.default_rng(seed)
    a_half = rng.uniform(0.0, 1.0, (hh, wh)).astype(np.float32)
    lit_half = rng.uniform(0.0, 30.0, (hh, wh)).astype(np.float32)
    a_half[rng.uniform(size=a_half.shape) < 0.3] = 0.0  # clear sky between clouds
    w0 = min(w0, 2 * hh - 1)
    rows = min(rows, 2 * hh - w0)  # the band's rows that the upsampled images hold
    below = rng.uniform(1.0, 50.0, (top + rows + 5, 2 * wh - seed % 2)).astype(np.float32)  # a cropped column
    out, copy, want = np.empty_like(below), np.empty_like(below), np.empty_like(below)
    composite_up(below, a_half, lit_half, top, top + rows, w0, out, copy)
    composite_band(below, cv2.pyrUp(a_half), cv2.pyrUp(lit_half), top, top + rows, w0, want)
    assert np.array_equal(out, want) and np.array_equal(copy, want)
    alone = np.empty_like(below)
    composite_up(below, a_half, lit_half, top, top + rows, w0, alone, np.empty((0, 0), np.float32))  # no copy
    assert np.array_equal(alone, want)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    far=st.booleans(),
    i0=st.integers(0, 60),
    j0=st.integers(0, 80),
    h=st.integers(1, 12),
    w=st.integers(1, 12),
)
def test_pyrup_lower_bound_is_below_every_pixel_of_the_window(seed, far, i0, j0, h, w):
    """The coarse-grid bound that spares the objects' depth windows: never above a pixel the window holds
    (ranges of 100 m - 5 km, and the far value 1e7 m beside them, as the cloud depth has)."""
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(100.0, 5000.0, (18, 22)).astype(np.float32)
    if far:
        coarse[rng.uniform(size=coarse.shape) < 0.3] = np.float32(1e7)
    img = PyrUpImage(coarse, (70, 86))
    rows, cols = slice(i0, min(i0 + h, 70)), slice(j0, min(j0 + w, 86))
    bound = img.lower_bound(rows, cols)
    window = img.window(rows, cols)
    assert bound <= float(window.min())
    assert np.array_equal(window, PyrUpImage(coarse, (70, 86)).full()[rows, cols])
    background = SceneBackground(np.zeros((70, 86), np.float32), np.zeros((70, 86), np.float32), img, img)
    assert background.nothing_nearer(rows, cols, bound)
    assert not background.nothing_nearer(rows, cols, float(window.min()) + 1.0)


def test_sensor_counts_are_cv2s_multiply_add_rounding_saturation_and_the_raw_full_scale():
    rng = np.random.default_rng(5)
    shape = (48, 72)
    gain = rng.uniform(150.0, 160.0, shape).astype(np.float32)
    offset = rng.uniform(-4000.0, -3000.0, shape).astype(np.float32)
    noise = (rng.standard_normal(shape) * 7.3).astype(np.float32)
    L = rng.uniform(-5.0, 140.0, shape).astype(np.float32)  # counts below 0 and above 14 and 16 bits
    # ties: radiances whose sum lands on k + 0.5 exactly in float32
    x = L.ravel()[:300] * gain.ravel()[:300] + offset.ravel()[:300]
    noise.ravel()[:300] = (np.floor(x) + np.float32(0.5)) - x
    L.ravel()[300:306] = [np.nan, np.inf, -np.inf, 3e9, -3e9, 1e30]
    for full_scale in (255, 16383, 65535):
        out = np.empty(shape, np.uint16)
        sensor_counts(L, gain, offset, noise, full_scale, out)
        want = cv2.multiply(L, gain)
        want += offset
        want = cv2.add(want, noise, dtype=cv2.CV_16U)
        np.minimum(want, full_scale, out=want)
        assert np.array_equal(out, want), full_scale


def numpy_agc_map(counts, n_bins, plateau_fraction, max_gain, linear_fraction):
    """The numpy formulation ``Sensor.agc_map`` ran before the kernel (the reference)."""
    h = np.bincount(counts[::2, ::2].ravel(), minlength=n_bins)[:n_bins].astype(np.float64)
    total = h.sum()
    cap = plateau_fraction * total
    for _ in range(2):
        clipped = np.minimum(h, cap)
        cap = min(plateau_fraction * total, max_gain * clipped.sum() / 255.0)
    clipped = np.minimum(h, cap)
    cdf = np.cumsum(clipped)
    eq = 255.0 * cdf / max(cdf[-1], 1.0)
    raw_cdf = np.cumsum(h) / max(total, 1.0)
    lo = float(np.searchsorted(raw_cdf, AGC_TAIL))
    hi = float(np.searchsorted(raw_cdf, 1.0 - AGC_TAIL))
    span = max(hi - lo, 255.0 / max_gain)
    mid = 0.5 * (lo + hi)
    lin = np.clip((np.arange(n_bins) - (mid - span / 2)) * (255.0 / span), 0.0, 255.0)
    return (1.0 - linear_fraction) * eq + linear_fraction * lin


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    raw_bits=st.sampled_from((8, 12, 14, 16)),
    spread=st.floats(0.5, 3000.0),
    plateau_fraction=st.floats(0.001, 1.0),
    max_gain=st.floats(0.05, 8.0),
    linear_fraction=st.floats(0.0, 1.0),
    odd_shape=st.booleans(),
)
def test_agc_map_is_the_numpy_formulation_bit_for_bit(
    seed, raw_bits, spread, plateau_fraction, max_gain, linear_fraction, odd_shape
):
    rng = np.random.default_rng(seed)
    n_bins = 2**raw_bits
    shape = (61, 83) if odd_shape else (64, 80)
    # a sky (one narrow mode), a warm patch (a second one) and a few saturated and dead pixels
    x = rng.normal(0.4 * n_bins, min(spread, n_bins / 8), shape)
    x[:10, :20] = rng.normal(0.7 * n_bins, min(spread, n_bins / 8) / 3, (10, 20))
    x.ravel()[rng.integers(0, x.size, 12)] = [0] * 6 + [n_bins - 1] * 6
    counts = np.clip(np.rint(x), 0, n_bins - 1).astype(np.uint16)
    got = agc_map(counts, n_bins, plateau_fraction, max_gain, linear_fraction, AGC_TAIL)
    want = numpy_agc_map(counts, n_bins, plateau_fraction, max_gain, linear_fraction)
    assert np.array_equal(got, want)
    mono8 = np.empty(shape, np.uint8)
    lut_take(got, counts, mono8)
    assert np.array_equal(mono8, np.rint(got).astype(np.uint8).take(counts))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), log2_n=st.integers(0, 16), scale=st.sampled_from((1.0, 1e-3, 1e12)))
def test_pairwise_sum_rounds_as_numpys_sum(seed, log2_n, scale):
    a = np.random.default_rng(seed).standard_normal(2**log2_n) * scale
    a[::7] *= 1e6  # magnitudes apart, so that the order of the additions shows in the last bits
    assert pairwise_sum_pow2(a) == a.sum()


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), i0=st.integers(0, 9), j0=st.integers(0, 9), h=st.integers(1, 9), w=st.integers(1, 9))
def test_min_max_is_numpys_min_and_max_nan_included(seed, i0, j0, h, w):
    rng = np.random.default_rng(seed)
    a = rng.uniform(-1e4, 1e7, (18, 18)).astype(np.float32)
    if seed % 3 == 0:
        a[rng.integers(0, 18), rng.integers(0, 18)] = np.nan
    window = a[i0 : i0 + h, j0 : j0 + w]
    got = min_max(a, i0, i0 + h, j0, j0 + w)
    want = (float(window.min()), float(window.max()))
    assert np.array_equal(got, want, equal_nan=True)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), hc=st.integers(3, 12), wc=st.integers(3, 14), crop=st.integers(0, 3))
def test_table_lookup_blocks_is_the_exact_lookup_in_the_dilated_blocks(seed, hc, wc, crop):
    """The sky's exact look-up near the horizon: in every 4 x 4 block next to a flagged coarse sample (3 x 3
    dilation), numpy's float32 index formula; elsewhere the image is untouched."""
    rng = np.random.default_rng(seed)
    st_px = 4
    near = (rng.uniform(size=(hc, wc)) < 0.15).astype(np.uint8)
    h, w = st_px * (hc - 2) - crop, st_px * (wc - 2) - crop
    ray_x = rng.uniform(-0.4, 0.4, w).astype(np.float32)
    ray_y = rng.uniform(-0.3, 0.3, h).astype(np.float32)
    invn = (1.0 / np.sqrt(ray_x[None, :] ** 2 + ray_y[:, None] ** 2 + 1.0)).astype(np.float32)
    lut = rng.uniform(0.0, 255.0, 4096).astype(np.float32)
    k = np.float32(-0.5 * 4000)
    kr0, kr1, kr2 = k * np.float32(0.3), k * np.float32(-0.5), k * np.float32(0.8)
    off = np.float32(2048.5)
    out = np.full((h + 2 * st_px, w + 2 * st_px), -1.0, np.float32)
    table_lookup_blocks(near, kr0, kr1, kr2, off, ray_x, ray_y, invn, lut, st_px, out)
    want = np.full_like(out, -1.0)
    grown = cv2.dilate(near, np.ones((3, 3), np.uint8))[1:-1, 1:-1]  # block (bi, bj) is sample (bi + 1, bj + 1)
    mask = np.kron(grown, np.ones((st_px, st_px), np.uint8))[:h, :w].astype(bool)
    index = (((kr0 * ray_x)[None, :] + (kr1 * ray_y + kr2)[:, None]) * invn + off).astype(np.int32)
    want[st_px : st_px + h, st_px : st_px + w][mask] = lut[index][mask]
    assert np.array_equal(out, want)


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    log2_n=st.integers(3, 10),
    h=st.integers(1, 40),
    w=st.integers(1, 90),
    scale=st.sampled_from((0.0, 0.125, 1.0)),
)
def test_remap_pair_is_cv2_remap_of_each_texture(seed, log2_n, h, w, scale):
    """The cloud layer's look-up of density and radiance held interleaved: cv2.remap's values (INTER_LINEAR,
    the folded coordinates inside the padded texture) for each, bit for bit, on this CPU (OpenCV's SIMD
    path rounds each of its three blends once: a fused multiply-add where the CPU has one)."""
    rng = np.random.default_rng(seed)
    n = 2**log2_n
    a = rng.uniform(0.0, 1.0, (n, n)).astype(np.float32)
    b = rng.uniform(0.0, 40.0, (n, n)).astype(np.float32)
    pa, pb = (np.ascontiguousarray(np.pad(t, ((0, 2), (0, 2)), mode="wrap")) for t in (a, b))
    pair = np.ascontiguousarray(np.stack([pa, pb], axis=-1))
    map_x = rng.normal(0.0, 3.0 * n, (h + 3, w)).astype(np.float32)
    map_y = rng.normal(0.0, 3.0 * n, (h + 3, w)).astype(np.float32)
    edges = [0.0, n, n - 1e-3, 1e-7, -1e-7, 2 * n + 0.5][:w]  # the seam and the period's ends
    map_x[2, : len(edges)] = edges
    mx, my, inside = fold_maps(map_x, map_y, 2, 2 + h, n, np.float32(scale))
    assert inside
    out0, out1 = np.zeros((h + 3, w), np.float32), np.zeros((h + 3, w), np.float32)
    remap_pair(pair, mx, my, 2, out0, out1)
    for texture, out in ((pa, out0), (pb, out1)):
        want = cv2.remap(texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        assert np.array_equal(out[2 : 2 + h], want)
        assert not out[:2].any() and not out[2 + h :].any()


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    h=st.integers(1, 30),
    w=st.integers(1, 40),
    f0=st.integers(0, 30),
    nf=st.integers(0, 30),
)
def test_terrain_blend_is_numpys_blend_then_extinction(seed, h, w, f0, nf):
    """The terrain's far mip level blended in and the extinction applied in one pass: numpy's ``near +=
    w_far * (far - near); tau * near`` over the whole frame (the far look-up zero outside its rows, where
    the far weight is 0), bit for bit; no far rows: ``tau * near``."""
    rng = np.random.default_rng(seed)
    f0, nf = min(f0, h), min(nf, h - min(f0, h))
    near = rng.uniform(-5.0, 40.0, (h, w)).astype(np.float32)
    tau = rng.uniform(0.0, 1.0, (h, w)).astype(np.float32)
    w_far = np.zeros((h, w), np.float32)
    w_far[f0 : f0 + nf] = rng.uniform(0.0, 1.0, (nf, w)).astype(np.float32)
    w_far[f0 : f0 + nf][rng.uniform(size=(nf, w)) < 0.2] = 1.0  # wholly the far level
    far = rng.uniform(-5.0, 40.0, (nf, w)).astype(np.float32)
    out = np.empty_like(near)
    terrain_blend(near, far, f0, w_far, tau, out)
    far_whole = np.zeros_like(near)
    far_whole[f0 : f0 + nf] = far
    want = near.copy()
    want += w_far * (far_whole - want)
    assert np.array_equal(out, tau * want)
    terrain_blend(near, np.empty((0, 0), np.float32), 0, w_far, tau, out)
    assert np.array_equal(out, tau * near)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    hh=st.integers(2, 20),
    wh=st.integers(2, 24),
    crop=st.tuples(st.integers(0, 1), st.integers(0, 1)),
    span=st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 1.0)),
    log2_n=st.integers(3, 10),
    scale=st.sampled_from((0.0, 0.25)),
)
def test_fold_maps_up_is_fold_maps_of_the_pyrup_maps(seed, hh, wh, crop, span, log2_n, scale):
    """The terrain's coordinates taken up their last pyrUp step while they are folded: fold_maps of
    cv2.pyrUp's maps (cropped as the renderer crops them; its first and last rows and columns included),
    bit for bit, over any run of rows."""
    rng = np.random.default_rng(seed)
    hx, hy = (rng.normal(0.0, 300.0, (hh, wh)).astype(np.float32) for _ in range(2))
    H, W = 2 * hh - crop[0], 2 * wh - crop[1]
    r0 = int(span[0] * H)
    r1 = r0 + int(span[1] * (H - r0))
    n = 2**log2_n
    fx, fy = (np.ascontiguousarray(cv2.pyrUp(x)[:H, :W]) for x in (hx, hy))
    want = fold_maps(fx, fy, r0, r1, n, np.float32(scale))
    got = fold_maps_up(hx, hy, r0, r1, W, n, np.float32(scale))
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]) and got[2] == want[2]


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    hh=st.integers(2, 16),
    wh=st.integers(2, 20),
    crop=st.tuples(st.integers(0, 1), st.integers(0, 1)),
    span=st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 1.0)),
)
def test_terrain_blend_up_is_terrain_blend_of_the_pyrup_weights(seed, hh, wh, crop, span):
    """The blend with the transmission's and the far weight's last pyrUp step inside: terrain_blend of
    cv2.pyrUp's images (cropped), bit for bit, with far rows anywhere or none."""
    rng = np.random.default_rng(seed)
    tau, w_far = (rng.uniform(0.0, 1.0, (hh, wh)).astype(np.float32) for _ in range(2))
    H, W = 2 * hh - crop[0], 2 * wh - crop[1]
    f0 = int(span[0] * H)
    far = rng.uniform(0.0, 40.0, (int(span[1] * (H - f0)), W)).astype(np.float32)
    near = rng.uniform(0.0, 40.0, (H, W)).astype(np.float32)
    want, got = np.empty_like(near), np.empty_like(near)
    terrain_blend(near, far, f0, *(np.ascontiguousarray(cv2.pyrUp(x)[:H, :W]) for x in (w_far, tau)), want)
    terrain_blend_up(near, far, f0, w_far, tau, got)
    assert np.array_equal(got, want)
