r"""The objects chain's whole-frame passes compiled (numba), bit for bit the OpenCV and numpy formulations.

:func:`contrast_and_cells` is the detector's main pass (below).  Four smaller ones: :func:`area_mean`, the background
motion's 4x smaller frames summed in integers from the kept frame (no float32 copy), and :func:`cell_extremes`, the
two-level cap's cell maxima and minima in the frame's own dtype, both exact by construction (integer arithmetic);
:func:`defect_rate`, the defect map's update (eight-neighbour extremes, float32 arithmetic as numpy's); and
:func:`minus_columns`, the frame as float32 less its column offsets.

What it computes, for the usual detector (3 x 3 surround cells): the frame's 3 x 3 box mean, its point contrast
(:func:`onboard.imaging.clutter.point_contrast`) and the noise estimate's cells
(:func:`onboard.imaging.clutter.noise_cells`).  In OpenCV those were nine full-frame passes (the box mean, two
sparse dilations and their maximum, a 2 x 2 box mean and its dilation, the subtraction, the absolute deviation and
its area resize), each writing a frame-sized float32 array that the next pass read back: a third of the chain's
CPU (docs/perception.md, "The whole-frame statistics in one compiled pass").  Here one loop over the rows computes each row's box mean, the surrounds'
row maxima and the centre's 2 x 2 means into a few rows of ring buffers, and the contrast of a row as soon as the
rows it reads exist, while they are still in the cache.

Why bit for bit: the contrast is compared with a threshold, and a candidate, a track and a score that moved by a
rounding would make every measured figure of the chain suspect.  The arithmetic is OpenCV's: its float box filters
sum in float64 (exact here: nine float32 grey values) and round the product by the scale to float32; its area
resize by an integer factor, as the x86-64 wheels run it (on Intel's IPP), sums the cell's float32 deviations in
row order in float32 and multiplies by ``1 / factor**2``; maxima and the final float32 subtraction are exact.  (OpenCV
built without IPP, as on ARM, sums each cell row's deviations before adding them: its cells differ from these by a
rounding, in either direction; the kernel's are the same on every machine.)  ``tests/onboard/test_imaging_kernels.py``
checks the box mean and the contrast against the OpenCV path, and the cells against that arithmetic (and OpenCV's
own at the detector's frame size on x86-64), for random frames, fractional and integer, in every geometry the kernel
takes.  No ``fastmath`` (numba's comparisons vectorise without it here).

The kernel compiles on first use or loads from numba's cache (``cache=True``; ``NUMBA_CACHE_DIR`` when set, as in
the container, whose image seeds it: :mod:`onboard.app.numba_seed`); :func:`warm` does that once per process.
"""

from __future__ import annotations

import numpy as np

from onboard.core.jit import njit

__all__ = [
    "area_mean",
    "cell_extremes",
    "contrast_and_cells",
    "cubic_patch",
    "defect_rate",
    "fits",
    "minus_columns",
    "warm",
]

_WARM = False


def fits(shape: tuple[int, ...], cell_px: int, guard_px: int, sharp_guard_px: int, factor: int) -> bool:
    """Whether :func:`contrast_and_cells` computes what the OpenCV path does for this frame ``shape`` and geometry:
    3 x 3 cells, a sharp surround within the cells' reach (``1 <= sharp_guard_px <= guard_px + 1``), a frame whose
    sides are multiples of ``factor`` (OpenCV's area resize takes another path otherwise) and larger than the
    contrast's blank border on both sides.  Anything else takes the OpenCV path, which is the reference."""
    if len(shape) != 2 or cell_px != 3 or guard_px < 1 or not 1 <= sharp_guard_px <= guard_px + 1 or factor < 1:
        return False
    h, w = shape
    border = guard_px + 1
    return h % factor == 0 and w % factor == 0 and min(h, w) > 2 * border


@njit(cache=True, nogil=True)
def _box3_row(img, i, v, out):
    """Row ``i`` of the 3 x 3 box mean (edges replicated) into ``out``; ``v`` (w + 2,) float64 work."""
    h, w = img.shape
    r0 = img[max(i - 1, 0)]
    r1 = img[i]
    r2 = img[min(i + 1, h - 1)]
    for j in range(w):
        v[j + 1] = np.float64(r0[j]) + np.float64(r1[j]) + np.float64(r2[j])
    v[0] = v[1]
    v[w + 1] = v[w]
    left = v[0:w]
    mid = v[1 : w + 1]
    right = v[2 : w + 2]
    ninth = 1.0 / 9.0
    for j in range(w):
        out[j] = np.float32((left[j] + mid[j] + right[j]) * ninth)


@njit(cache=True, nogil=True)
def _sparse_row_max(row, g, out):
    """``out[j] = max(row[j - g], row[j], row[j + g])`` for ``g <= j < w - g`` (the rest untouched)."""
    n = row.shape[0] - 2 * g
    left = row[0:n]
    mid = row[g : g + n]
    right = row[2 * g : 2 * g + n]
    o = out[g : g + n]
    for j in range(n):
        o[j] = max(max(left[j], mid[j]), right[j])


@njit(cache=True, nogil=True)
def _centre_row(upper, lower, means, out):
    """The larger of the two 2 x 2 box means anchored at (row, j - 1) and (row, j), for ``1 <= j < w - 1``, of the
    rows ``upper`` and ``lower`` (the row below it); ``means`` (w,) float32 work."""
    w = upper.shape[0]
    upper_r = upper[1:]
    lower_r = lower[1:]
    for j in range(w - 1):
        s = np.float64(upper[j]) + np.float64(upper_r[j]) + np.float64(lower[j]) + np.float64(lower_r[j])
        means[j] = np.float32(s * 0.25)
    o = out[1 : w - 1]
    left = means[0 : w - 2]
    right = means[1 : w - 1]
    for j in range(w - 2):
        o[j] = max(left[j], right[j])


@njit(cache=True, nogil=True)
def _contrast_row(centre_above, centre, box_above, box_below, box_row, sharp_above, sharp_below, row, g, s, out):
    """One row of the point contrast: the centre (the larger of the two rows' 2 x 2 maxima) minus the largest of the
    eight cell means ``g`` away and the eight pixels ``s`` away; its first and last ``g + 1`` columns 0."""
    w = row.shape[0]
    b = g + 1
    n = w - 2 * b
    out[:b] = 0.0
    out[w - b :] = 0.0
    o = out[b : w - b]
    c0 = centre_above[b : w - b]
    c1 = centre[b : w - b]
    ba = box_above[b : w - b]
    bb = box_below[b : w - b]
    bl = box_row[b - g : w - b - g]
    br = box_row[b + g : w - b + g]
    sa = sharp_above[b : w - b]
    sb = sharp_below[b : w - b]
    sl = row[b - s : w - b - s]
    sr = row[b + s : w - b + s]
    for j in range(n):
        c = max(c0[j], c1[j])
        m = max(max(ba[j], bb[j]), max(bl[j], br[j]))
        m = max(m, max(max(sa[j], sb[j]), max(sl[j], sr[j])))
        o[j] = c - m


@njit(cache=True, nogil=True)
def _cells_row(row, box_row, work, out, factor):
    """Add one pixel row's ``|g - mean3x3(g)|`` to its cells' sums, column by column within each cell."""
    wc = out.shape[0]
    w = wc * factor
    for j in range(w):
        work[j] = abs(row[j] - box_row[j])
    if factor == 4:  # written out: the same additions in the same order, in one pass over the cells
        for c in range(wc):
            out[c] = (((out[c] + work[4 * c]) + work[4 * c + 1]) + work[4 * c + 2]) + work[4 * c + 3]
        return
    by_cell = work[:w].reshape((wc, factor))
    for k in range(factor):
        col = by_cell[:, k]
        for c in range(wc):
            out[c] += col[c]


@njit(cache=True, nogil=True)
def _contrast_and_cells(img, g, s, factor, box3, contrast, cells, box_max, sharp_max, centre, v, work):
    h, w = img.shape
    b = g + 1
    lag = max(g, s)  # contrast row k is computed once rows k + g (the cells) and k + s (the pixels) are in
    ring = box_max.shape[0]  # at least 2 * lag + 1: the rows from k - lag to k + lag
    hc = cells.shape[0]
    cells[:, :] = 0.0
    for i in range(h):
        _box3_row(img, i, v, box3[i])
        _sparse_row_max(box3[i], g, box_max[i % ring])
        _sparse_row_max(img[i], s, sharp_max[i % ring])
        if i >= 1:
            _centre_row(img[i - 1], img[i], work, centre[(i - 1) % ring])
        if i // factor < hc:
            _cells_row(img[i], box3[i], work, cells[i // factor], factor)
        k = i - lag
        if b <= k < h - b:
            _contrast_row(
                centre[(k - 1) % ring],
                centre[k % ring],
                box_max[(k - g) % ring],
                box_max[(k + g) % ring],
                box3[k],
                sharp_max[(k - s) % ring],
                sharp_max[(k + s) % ring],
                img[k],
                g,
                s,
                contrast[k],
            )
    for k in range(b):
        contrast[k, :] = 0.0
        contrast[h - 1 - k, :] = 0.0
    scale = np.float32(1.0 / (factor * factor))
    for ci in range(hc):
        row = cells[ci]
        for c in range(cells.shape[1]):
            row[c] = row[c] * scale


def contrast_and_cells(
    img: np.ndarray,
    guard_px: int,
    sharp_guard_px: int,
    factor: int,
    box3: np.ndarray,
    contrast: np.ndarray,
    cells: np.ndarray,
    work: dict[str, np.ndarray] | None = None,
) -> None:
    """Write ``img``'s 3 x 3 box mean into ``box3``, its point contrast (cells ``guard_px`` away, pixels
    ``sharp_guard_px`` away) into ``contrast`` and its noise cells (``factor`` px) into ``cells``: bit for bit
    ``cv2.blur(img, (3, 3), borderType=cv2.BORDER_REPLICATE)``, :func:`~onboard.imaging.clutter.point_contrast` and
    :func:`~onboard.imaging.clutter.noise_cells` for a geometry :func:`fits` accepts.  ``img`` float32, C-ordered;
    ``box3``, ``contrast`` its shape, ``cells`` ``(h // factor, w // factor)``, all float32 and C-ordered; ``work``: a
    dict the small row buffers are kept in between calls (None: new ones)."""
    h, w = img.shape
    if not fits(img.shape, 3, guard_px, sharp_guard_px, factor):
        raise ValueError(
            f"contrast_and_cells takes 3 x 3 cells, 1 <= sharp_guard_px <= guard_px + 1 and a frame whose sides are "
            f"multiples of factor and over twice guard_px + 1: got a {h} x {w} frame, guard_px {guard_px}, "
            f"sharp_guard_px {sharp_guard_px}, factor {factor}"
        )
    for name, a, shape in (
        ("box3", box3, (h, w)),
        ("contrast", contrast, (h, w)),
        ("cells", cells, (h // factor, w // factor)),
    ):
        if a.shape != shape or a.dtype != np.float32 or not a.flags.c_contiguous:
            raise ValueError(
                f"contrast_and_cells: {name} must be C-ordered float32 of shape {shape}, got {a.dtype} {a.shape}"
            )
    if img.dtype != np.float32 or not img.flags.c_contiguous:
        raise ValueError(f"contrast_and_cells: img must be C-ordered float32, got {img.dtype}")
    ring = 2 * max(guard_px, sharp_guard_px) + 2
    buffers = {} if work is None else work
    kept = buffers.get("box_max")
    if kept is None or kept.shape != (ring, w):
        buffers.update(
            box_max=np.empty((ring, w), np.float32),
            sharp_max=np.empty((ring, w), np.float32),
            centre=np.empty((ring, w), np.float32),
            v=np.empty(w + 2, np.float64),
            work=np.empty(w, np.float32),
        )
    _contrast_and_cells(
        img,
        guard_px,
        sharp_guard_px,
        factor,
        box3,
        contrast,
        cells,
        buffers["box_max"],
        buffers["sharp_max"],
        buffers["centre"],
        buffers["v"],
        buffers["work"],
    )


@njit(cache=True, nogil=True)
def _area_mean(img, factor, out, column_sums):
    """Each ``factor`` x ``factor`` cell's mean of the integer frame ``img`` into ``out`` (float32): the cell's sum in
    integers (exact), then scaled.  ``column_sums`` (w,) int32 work: each column's sum over the cell's rows first."""
    hc, wc = out.shape
    w = wc * factor
    scale = np.float32(1.0 / (factor * factor))
    for ci in range(hc):
        column_sums[:] = 0
        for a in range(factor):
            row = img[ci * factor + a]
            for j in range(w):
                column_sums[j] += np.int32(row[j])
        o = out[ci]
        if factor == 4:  # written out: the loop over the cells then vectorises
            for c in range(wc):
                total = column_sums[4 * c] + column_sums[4 * c + 1] + column_sums[4 * c + 2] + column_sums[4 * c + 3]
                o[c] = np.float32(total) * scale
        else:
            for c in range(wc):
                total = column_sums[c * factor]
                for k in range(1, factor):
                    total += column_sums[c * factor + k]
                o[c] = np.float32(total) * scale


def area_mean(img: np.ndarray, factor: int) -> np.ndarray | None:
    """``cv2.resize(img.astype(np.float32), (w // factor, h // factor), interpolation=cv2.INTER_AREA)``, bit for bit,
    for a uint8 or uint16 frame whose sides are multiples of ``factor`` (1, 2 or 4), without the frame-sized float32
    copy: each cell's sum is exact (at most 16 x 65535 < 2**24) and so is its scaling by a power of two, so OpenCV's
    float sums, in whatever order, give the same value.  None otherwise: the caller takes OpenCV's resize."""
    if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16) or not img.flags.c_contiguous:
        return None
    h, w = img.shape
    if factor not in (1, 2, 4) or h % factor or w % factor or h < factor or w < factor:
        return None
    out = np.empty((h // factor, w // factor), np.float32)
    _area_mean(img, factor, out, np.empty(w, np.int32))
    return out


@njit(cache=True, nogil=True)
def _cell_extremes(img, factor, hi, lo, top, bottom):
    """Each cell's largest and least pixel into ``hi``, ``lo``; ``top``, ``bottom`` (w,) of ``img``'s dtype, work:
    each column's extremes over the cell's rows first (contiguous, vectorised in the frame's own type)."""
    hc, wc = hi.shape
    w = wc * factor
    for ci in range(hc):
        first = img[ci * factor]
        for j in range(w):
            top[j] = first[j]
            bottom[j] = first[j]
        for a in range(1, factor):
            row = img[ci * factor + a]
            for j in range(w):
                top[j] = max(top[j], row[j])
                bottom[j] = min(bottom[j], row[j])
        up = hi[ci]
        down = lo[ci]
        if factor == 4:  # written out: the loop over the cells then vectorises
            for c in range(wc):
                up[c] = max(max(top[4 * c], top[4 * c + 1]), max(top[4 * c + 2], top[4 * c + 3]))
                down[c] = min(min(bottom[4 * c], bottom[4 * c + 1]), min(bottom[4 * c + 2], bottom[4 * c + 3]))
        else:
            for c in range(wc):
                t = top[c * factor]
                b = bottom[c * factor]
                for k in range(1, factor):
                    t = max(t, top[c * factor + k])
                    b = min(b, bottom[c * factor + k])
                up[c] = t
                down[c] = b


def cell_extremes(img: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The largest and the least pixel of each ``factor`` x ``factor`` cell of a uint8 or uint16 frame (its dtype,
    ``(h // factor, w // factor)``; the last rows and columns that fill no cell left out), in one pass; None for
    another dtype or layout (the caller's numpy and OpenCV formulation)."""
    if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16) or not img.flags.c_contiguous or factor < 1:
        return None
    h, w = img.shape
    hc, wc = h // factor, w // factor
    if hc < 1 or wc < 1:
        return None
    hi = np.empty((hc, wc), img.dtype)
    lo = np.empty((hc, wc), img.dtype)
    _cell_extremes(img, factor, hi, lo, np.empty(w, img.dtype), np.empty(w, img.dtype))
    return hi, lo


@njit(cache=True, nogil=True)
def _outlier_extremes(img, i, j):
    """The largest and the least of pixel (i, j)'s eight neighbours, edges replicated (a neighbour beyond the frame
    is the nearest pixel inside it, the pixel itself included)."""
    h, w = img.shape
    hi = -np.inf
    lo = np.inf
    for di in (-1, 0, 1):
        r = img[min(max(i + di, 0), h - 1)]
        for dj in (-1, 0, 1):
            if di == 0 and dj == 0:
                continue
            x = r[min(max(j + dj, 0), w - 1)]
            hi = max(hi, x)
            lo = min(lo, x)
    return np.float32(hi), np.float32(lo)


@njit(cache=True, nogil=True)
def _defect_rate(img, s, decay, gain, level, rate, mask):
    h, w = img.shape
    for i in range(h):
        up = img[max(i - 1, 0)]
        row = img[i]
        down = img[min(i + 1, h - 1)]
        r = rate[i]
        m = mask[i]
        for j in range(0, w, max(w - 1, 1)):  # the edge columns (one when w is 1), their neighbours replicated
            hi, lo = _outlier_extremes(img, i, j)
            x = row[j]
            v = r[j] * decay
            if x > hi + s or x < lo - s:
                v = v + gain
            r[j] = v
            m[j] = v >= level
        for j in range(1, w - 1):
            hi = max(
                max(max(up[j - 1], up[j]), max(up[j + 1], row[j - 1])),
                max(max(row[j + 1], down[j - 1]), max(down[j], down[j + 1])),
            )
            lo = min(
                min(min(up[j - 1], up[j]), min(up[j + 1], row[j - 1])),
                min(min(row[j + 1], down[j - 1]), min(down[j], down[j + 1])),
            )
            x = row[j]
            outlier = (x > hi + s) | (x < lo - s)
            v = r[j] * decay
            v = v + gain if outlier else v
            r[j] = v
            m[j] = v >= level


def defect_rate(
    img: np.ndarray,
    sigma: np.floating,
    decay: np.floating,
    gain: np.floating,
    level: np.floating,
    rate: np.ndarray,
    mask: np.ndarray,
) -> bool:
    """One defect-map update in one pass, bit for bit :class:`onboard.imaging.clutter.DefectMap`'s numpy and OpenCV
    formulation: a pixel is an outlier when it lies more than ``sigma`` above the largest or below the least of its
    eight neighbours (edges replicated, float32 arithmetic as ``img > nmax + sigma``); ``rate`` (float32) becomes
    ``rate * decay``, plus ``gain`` where the pixel is an outlier; ``mask`` (bool) ``rate >= level``.  The scalars
    float32.  False, with nothing written, for arrays it does not take (the caller's formulation then runs)."""
    if (
        img.ndim != 2
        or img.dtype != np.float32
        or rate.dtype != np.float32
        or mask.dtype != np.bool_
        or rate.shape != img.shape
        or mask.shape != img.shape
        or not (img.flags.c_contiguous and rate.flags.c_contiguous and mask.flags.c_contiguous)
        or min(img.shape) < 1
    ):
        return False
    _defect_rate(img, np.float32(sigma), np.float32(decay), np.float32(gain), np.float32(level), rate, mask)
    return True


@njit(cache=True, nogil=True)
def _minus_columns(image, offsets, out):
    h, w = image.shape
    for i in range(h):
        row = image[i]
        o = out[i]
        for j in range(w):
            o[j] = np.float32(row[j]) - offsets[j]


def minus_columns(image: np.ndarray, offsets: np.ndarray, out: np.ndarray) -> bool:
    """``out[:] = image.astype(np.float32) - offsets[None, :]`` in one pass (numpy's cast, then its subtraction in
    place, read and write the float32 frame twice), the same values: the cast of a uint8, uint16 or float32 grey is
    exact and the subtraction one float32 rounding either way.  False, with nothing written, for arrays it does not
    take (the caller's numpy then runs)."""
    h, w = image.shape if image.ndim == 2 else (0, 0)
    if (
        image.ndim != 2
        or image.dtype not in (np.uint8, np.uint16, np.float32)
        or offsets.dtype != np.float32
        or offsets.shape != (w,)
        or out.dtype != np.float32
        or out.shape != image.shape
        or not (image.flags.c_contiguous and offsets.flags.c_contiguous and out.flags.c_contiguous)
    ):
        return False
    _minus_columns(image, offsets, out)
    return True


@njit(cache=True, nogil=True)
def _cubic_patch(big, wx, wy, out):
    side = out.shape[0]
    rows = np.empty((side, side + 3), np.float32)
    for i in range(side):
        for j in range(side + 3):
            r = wy[0] * big[i, j]
            r = r + wy[1] * big[i + 1, j]
            r = r + wy[2] * big[i + 2, j]
            r = r + wy[3] * big[i + 3, j]
            rows[i, j] = r
    for i in range(side):
        for j in range(side):
            o = wx[0] * rows[i, j]
            o = o + wx[1] * rows[i, j + 1]
            o = o + wx[2] * rows[i, j + 2]
            o = o + wx[3] * rows[i, j + 3]
            a, b = big[i + 1, j + 1], big[i + 1, j + 2]
            c, d = big[i + 2, j + 1], big[i + 2, j + 2]
            out[i, j] = min(max(o, min(min(a, b), min(c, d))), max(max(a, b), max(c, d)))


def cubic_patch(big: np.ndarray, wx: np.ndarray, wy: np.ndarray) -> np.ndarray:
    """The ``side`` x ``side`` cubic resampling of a float32 ``(side + 3)`` square patch by the four Keys weights
    ``wx`` (along rows) and ``wy`` (along columns), float32, each value held within the four patch pixels about it:
    :func:`onboard.imaging.background_difference.cubic_square`'s arithmetic (its numpy formulation: eight float32
    products and sums over the whole square, each a rounding, then the clip), in one pass and the same values, bit
    for bit: float32 products and sums in the same order, no fused multiply-add (no ``fastmath``).  Called four times
    for each difference square (its registration's refinement), where numpy's sixteen small-array operations cost
    ~60 us each time (``tests/onboard/test_imaging_kernels.py`` compares the two)."""
    side = big.shape[0] - 3
    out = np.empty((side, side), np.float32)
    _cubic_patch(big, wx, wy, out)
    return out


def warm() -> None:
    """Compile (or load from the cache) the kernel for the float32 frames the detector passes: once per process,
    so that no frame pays it (the detector calls it at construction)."""
    global _WARM
    if _WARM:
        return

    img = np.zeros((16, 16), np.float32)  # the detector's own float32 frame: always a writable array
    contrast_and_cells(img, 4, 2, 4, np.empty_like(img), np.empty_like(img), np.empty((4, 4), np.float32))
    one = np.float32(1.0)
    defect_rate(img, one, one, one, one, np.zeros_like(img), np.zeros(img.shape, np.bool_))

    def frames(dtype):
        # the received frame itself, writable and read-only: numba compiles each kind apart, and the daemon's
        # frames are read-only views of the received bytes (onboard.core.irframe), the lockstep's writable arrays;
        # neither must compile on a first frame (0.5 s, several times that on a companion's core)
        writable = np.zeros((16, 16), dtype)
        read_only = writable.copy()
        read_only.setflags(write=False)
        return writable, read_only

    for dtype in (np.uint8, np.uint16):
        for frame in frames(dtype):
            area_mean(frame, 4)
            cell_extremes(frame, 4)
    for kind in (np.uint8, np.uint16, np.float32):
        for frame in frames(kind):
            minus_columns(frame, np.zeros(16, np.float32), np.empty((16, 16), np.float32))
    cubic_patch(img, np.zeros(4, np.float32), np.zeros(4, np.float32))  # getRectSubPix's float32 patch
    _WARM = True
