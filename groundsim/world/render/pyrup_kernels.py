"""Compiled kernels that take ``cv2.pyrUp``'s last step inline, bit for bit (numba, cached beside this file).

The renderer computes its compositing weights and texture coordinates on a grid 2 or 4 times coarser and
takes them up to the frame with ``cv2.pyrUp``.  Where a full-resolution image would only be written to be
read once, these kernels take its last step row by row as they read it: OpenCV's horizontal pass
(:func:`_pyrup_row`) into a ring of three half-resolution rows, then its vertical pass and its 1/64 scale
in OpenCV's order (:func:`_pyrup_at`).  ``tests/groundsim/test_render_kernels.py`` holds each to
``cv2.pyrUp`` followed by the kernel it stands for.  The rules of :mod:`groundsim.world.render.kernels`
apply (float32 constants, numpy's order, no fastmath).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from groundsim.world.render.kernels import fold_pair

__all__ = ["composite_up", "fold_maps_up", "terrain_blend_up"]

_F32 = np.float32


@njit(cache=True, nogil=True)
def _pyrup_row(src, k, row):
    """``cv2.pyrUp``'s horizontal pass over row ``k`` of ``src`` into ``row`` (float32, 2 w values; the row
    index mapped as pyrUp maps it: -1 to 1, past the end to the last row; its first and last columns' rules)."""
    h, w = src.shape
    if k < 0:
        k = 1 if h > 1 else 0
    elif k >= h:
        k = h - 1
    six, two, four = _F32(6.0), _F32(2.0), _F32(4.0)
    row[0] = src[k, 0] * six + src[k, 1] * two
    row[1] = (src[k, 0] + src[k, 1]) * four
    for sx in range(1, w - 1):
        row[2 * sx] = (src[k, sx - 1] + src[k, sx] * six) + src[k, sx + 1]
        row[2 * sx + 1] = (src[k, sx] + src[k, sx + 1]) * four
    row[2 * w - 2] = src[k, w - 2] + src[k, w - 1] * _F32(7.0)
    row[2 * w - 1] = src[k, w - 1] * _F32(8.0)


@njit(cache=True, nogil=True, inline="always")
def _pyrup_ring(src, sy, have, ring, k):
    """Slot order ``k`` = (k0, k1, k2) of ``ring`` (3 rows) holding :func:`_pyrup_row` of ``src``'s rows
    ``sy - 1, sy, sy + 1``, given that it held those of ``have``: one new row when ``sy = have + 1``."""
    k0, k1, k2 = k
    if sy == have + 1:
        k0, k1, k2 = k1, k2, k0
    else:
        _pyrup_row(src, sy - 1, ring[k0])
        _pyrup_row(src, sy, ring[k1])
    _pyrup_row(src, sy + 1, ring[k2])
    return k0, k1, k2


@njit(cache=True, nogil=True, inline="always")
def _pyrup_at(ring, k, odd, j):
    """Column ``j`` of a full row of ``cv2.pyrUp`` from the three horizontal rows in ``ring`` (slot order
    ``k``): its vertical pass and the scale 1/64 in OpenCV's order, ``odd`` the full row's parity."""
    if odd:
        return ((ring[k[1], j] + ring[k[2], j]) * _F32(4.0)) * _F32(1.0 / 64.0)
    return ((ring[k[0], j] + ring[k[1], j] * _F32(6.0)) + ring[k[2], j]) * _F32(1.0 / 64.0)


@njit(cache=True, nogil=True, error_model="numpy")
def fold_maps_up(hx, hy, r0, r1, w, n, scale):
    """:func:`fold_maps` of ``cv2.pyrUp(hx)[:, :w]``, ``cv2.pyrUp(hy)[:, :w]`` (rows ``r0 .. r1 - 1``), the
    last pyrUp step taken row by row as the maps are folded: the same values without the two full-resolution
    maps in between (written, then read back)."""
    f32 = np.float32
    h = r1 - r0
    fn = f32(n)
    inv = f32(1.0 / n)
    mx = np.empty((h, w), np.float32)
    my = np.empty((h, w), np.float32)
    ring_x = np.empty((3, 2 * hx.shape[1]), np.float32)
    ring_y = np.empty((3, 2 * hx.shape[1]), np.float32)
    inside = True
    have = -10
    k = (0, 1, 2)
    for i in range(h):
        sy = (r0 + i) >> 1
        if sy != have:
            kx = _pyrup_ring(hx, sy, have, ring_x, k)
            _pyrup_ring(hy, sy, have, ring_y, k)
            k = kx
            have = sy
        odd = (r0 + i) & 1 == 1
        for j in range(w):
            a, b, ok = fold_pair(_pyrup_at(ring_x, k, odd, j), _pyrup_at(ring_y, k, odd, j), scale, fn, inv)
            mx[i, j] = a
            my[i, j] = b
            inside &= ok
    return mx, my, inside


@njit(cache=True, nogil=True)
def terrain_blend_up(near, far, f0, w_half, tau_half, out):
    """:func:`terrain_blend` with ``w_far = cv2.pyrUp(w_half)``, ``tau = cv2.pyrUp(tau_half)`` (cropped to
    ``near``'s shape) taken up row by row as they are read (``w_half`` read on the far rows only: any
    array when ``far`` has none)."""
    h, w = near.shape
    f1 = f0 + far.shape[0]
    ring_t = np.empty((3, 2 * tau_half.shape[1]), np.float32)
    ring_w = np.empty((3, 2 * tau_half.shape[1]), np.float32)
    have_t = have_w = -10
    kt = kw = (0, 1, 2)
    for i in range(h):
        sy = i >> 1
        odd = i & 1 == 1
        if sy != have_t:
            kt = _pyrup_ring(tau_half, sy, have_t, ring_t, kt)
            have_t = sy
        if f0 <= i < f1:
            if sy != have_w:
                kw = _pyrup_ring(w_half, sy, have_w, ring_w, kw)
                have_w = sy
            r = i - f0
            for j in range(w):
                x = near[i, j]
                x = x + _pyrup_at(ring_w, kw, odd, j) * (far[r, j] - x)
                out[i, j] = _pyrup_at(ring_t, kt, odd, j) * x
        else:
            for j in range(w):
                out[i, j] = _pyrup_at(ring_t, kt, odd, j) * near[i, j]


@njit(cache=True, nogil=True)
def composite_up(below, a_half, lit_half, e0, e1, w0, out, copy):
    """:func:`composite_band` with ``a_up = cv2.pyrUp(a_half)``, ``lit_up = cv2.pyrUp(lit_half)`` taken up
    row by row as they are read, with pyrUp's arithmetic (:func:`_pyrup_row`, then the vertical pass and the
    scale 1/64 in OpenCV's order), without the two full-resolution images in between (written, then read
    back: most of the cloud band's memory traffic).  ``out = below`` outside rows ``e0 .. e1 - 1``; the
    half images at least 2 x 2.  ``copy`` gets the same values in the same pass (an image to draw on: one
    read of ``out`` fewer than a copy afterwards), unless it is empty (0 x 0)."""
    h, w = below.shape
    wh = a_half.shape[1]
    twice = copy.shape[0] > 0
    ring = np.empty((2, 3, 2 * wh), np.float32)  # per image, the three half rows a full row pair reads
    six, four, scale = _F32(6.0), _F32(4.0), _F32(1.0 / 64.0)
    for i in range(0, e0):
        for j in range(w):
            out[i, j] = below[i, j]
        if twice:
            for j in range(w):
                copy[i, j] = below[i, j]
    have = -10  # the half row ``sy`` whose rows sy - 1, sy, sy + 1 the ring's slots k0, k1, k2 hold
    k0, k1, k2 = 0, 1, 2
    for i in range(e0, e1):
        r = i - e0 + w0
        sy = r >> 1
        if sy != have:  # one row on: the slots turn, one new row each
            turned = _pyrup_ring(a_half, sy, have, ring[0], (k0, k1, k2))
            _pyrup_ring(lit_half, sy, have, ring[1], (k0, k1, k2))
            k0, k1, k2 = turned
            have = sy
        a0, a1, a2 = ring[0, k0], ring[0, k1], ring[0, k2]
        l0, l1, l2 = ring[1, k0], ring[1, k1], ring[1, k2]
        b_row = below[i]
        o_row = out[i]
        c_row = copy[i] if twice else o_row
        if r & 1 == 0:
            for j in range(w):
                a = ((a0[j] + a1[j] * six) + a2[j]) * scale
                lit = ((l0[j] + l1[j] * six) + l2[j]) * scale
                x = b_row[j]
                v = (x - a * x) + lit
                o_row[j] = v
                c_row[j] = v
        else:
            for j in range(w):
                a = ((a1[j] + a2[j]) * four) * scale
                lit = ((l1[j] + l2[j]) * four) * scale
                x = b_row[j]
                v = (x - a * x) + lit
                o_row[j] = v
                c_row[j] = v
    for i in range(max(e1, e0), h):
        for j in range(w):
            out[i, j] = below[i, j]
        if twice:
            for j in range(w):
                copy[i, j] = below[i, j]
