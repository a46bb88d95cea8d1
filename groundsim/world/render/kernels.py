"""Compiled inner loops of the renderer (numba, compiled once and cached beside this file).

Why compiled: an object on the image is a few thousand sub-sample rays against a handful of parts, a
frame draws several objects, and in numpy each step of the ray cast was a call over a small array whose
fixed cost was most of its time (a crowded frame spent more on calls than on arithmetic).  One loop per
object does the same float operations per ray in the same order, so the results are bit-identical to the
numpy formulation they replace (``PartRaster.intersect``, kept as the reference and for batch use;
``tests/groundsim/test_raster.py`` checks the two against each other).

Rules the loops keep so that they stay bit-identical: every constant of a float32 expression is a
float32 (a float64 literal would promote the expression), sums are written in numpy's left-to-right
order, no ``fastmath`` (no reassociation, no fused multiply-add).
"""

from __future__ import annotations

import numpy as np
from numba import njit, types
from numba.extending import intrinsic

__all__ = ["cast_part_rays", "nearest_parts"]

_F32 = np.float32


@intrinsic
def _fma(typingctx, a, b, c):
    """``a b + c`` rounded once (LLVM's ``fma``: the CPU's fused multiply-add, else libm's ``fma``): the
    rounding of OpenCV's SIMD kernels on a CPU with fused multiply-adds."""
    if not (a == b == c and isinstance(a, types.Float)):
        return None

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return a(a, a, a), codegen


@njit(cache=True, nogil=True)
def _relative_origins(o_b, box_c, ell_c, ell_h):
    """The ray origin relative to each box's centre (float32), and to each ellipsoid's centre in its
    semi-axes (float64, then rounded to float32)."""
    oc = np.empty((box_c.shape[0], 3), np.float32)
    for p in range(box_c.shape[0]):
        for k in range(3):
            oc[p, k] = o_b[k] - box_c[p, k]
    oe = np.empty((ell_c.shape[0], 3), np.float32)
    for p in range(ell_c.shape[0]):
        for k in range(3):
            oe[p, k] = _F32((np.float64(o_b[k]) - ell_c[p, k]) / np.float64(ell_h[p, k]))
    return oc, oe


@njit(cache=True, nogil=True, inline="always")
def _nearest(d0, d1, d2, oc, box_h, oe, ell_h):
    """``(t, part)`` of the nearest part along float32 direction ``(d0, d1, d2)`` (``part`` -1, ``t`` inf:
    none), parts numbered boxes first, then ellipsoids."""
    zero = _F32(0.0)
    one = _F32(1.0)
    tiny = _F32(1e-30)
    nb = oc.shape[0]
    best = _F32(np.inf)
    part = -1
    if nb > 0:
        i0 = one / (d0 if d0 != zero else tiny)
        i1 = one / (d1 if d1 != zero else tiny)
        i2 = one / (d2 if d2 != zero else tiny)
        for p in range(nb):
            lo = (-box_h[p, 0] - oc[p, 0]) * i0
            hi = (box_h[p, 0] - oc[p, 0]) * i0
            t_in = min(lo, hi)
            t_out = max(lo, hi)
            lo = (-box_h[p, 1] - oc[p, 1]) * i1
            hi = (box_h[p, 1] - oc[p, 1]) * i1
            t_in = max(t_in, min(lo, hi))
            t_out = min(t_out, max(lo, hi))
            lo = (-box_h[p, 2] - oc[p, 2]) * i2
            hi = (box_h[p, 2] - oc[p, 2]) * i2
            t_in = max(t_in, min(lo, hi))
            t_out = min(t_out, max(lo, hi))
            if t_in <= t_out and t_out > zero:
                t = max(t_in, zero)
                if t < best:
                    best = t
                    part = p
    for p in range(oe.shape[0]):
        e0 = d0 / ell_h[p, 0]
        e1 = d1 / ell_h[p, 1]
        e2 = d2 / ell_h[p, 2]
        q0 = oe[p, 0]
        q1 = oe[p, 1]
        q2 = oe[p, 2]
        a = e0 * e0 + e1 * e1 + e2 * e2
        b = e0 * q0 + e1 * q1 + e2 * q2
        cx = q1 * e2 - q2 * e1
        cy = q2 * e0 - q0 * e2
        cz = q0 * e1 - q1 * e0
        disc = a - (cx * cx + cy * cy + cz * cz)
        sq = np.sqrt(max(disc, zero))
        if disc >= zero and (sq - b) / a > zero:
            t = max(-(b + sq) / a, zero)
            if t < best:
                best = t
                part = nb + p
    return best, part


@njit(cache=True, nogil=True)
def nearest_parts(o_b, d_b, box_c, box_h, ell_c, ell_h):
    """Nearest hit of rays ``o_b + t d_b[:, n]`` (float32, body frame) with the parts: ``(t (n,) float32,
    inf where none; part (n,) int64, -1 where none)``, parts numbered boxes first, then ellipsoids."""
    oc, oe = _relative_origins(o_b, box_c, ell_c, ell_h)
    n = d_b.shape[1]
    t = np.empty(n, np.float32)
    part = np.empty(n, np.int64)
    for k in range(n):
        t[k], part[k] = _nearest(d_b[0, k], d_b[1, k], d_b[2, k], oc, box_h, oe, ell_h)
    return t, part


@njit(cache=True, nogil=True)
def cast_part_rays(R_bc, o_b, x, y, box_c, box_h, ell_c, ell_h, L_emit, L_seen, ref, ss, r0, c0, shape):
    """Cast the rays of sub-sample rows ``r0 + i`` and columns ``c0 + j`` at the parts: ``(out, hits)``,
    ``out`` (``shape``, float64) ``part_value[nearest] - ref[(r0 + i) // ss, (c0 + j) // ss]`` where a ray
    meets a part and 0 elsewhere, ``hits`` how many rays met one.  ``part_value = ((tau L_emit + (1 - tau)
    L_air) - L_min) grey_per_L`` from ``L_seen = (tau, L_air, L_min, grey_per_L)`` (numpy's order), the
    part's radiance through the atmosphere in the units of ``ref``.

    Rays in the body frame from ``o_b`` (3, float32) along ``float32(R_bc[:, 0] x + (R_bc[:, 1] y +
    R_bc[:, 2]))``, ``x``, ``y`` the normalised image coordinates of the sub-samples (float64, (rows, cols);
    ``x`` may have one row and ``y`` one column when they are separable, a camera without distortion).
    Parts as in :func:`nearest_parts` (``part_value`` in that order).  ``ref`` (float32) is the background
    of each sub-sample's pixel."""
    oc, oe = _relative_origins(o_b, box_c, ell_c, ell_h)
    tau, L_air, L_min, grey_per_L = L_seen[0], L_seen[1], L_seen[2], L_seen[3]
    part_value = np.empty(L_emit.size)
    for p in range(L_emit.size):
        part_value[p] = ((tau * L_emit[p] + (1.0 - tau) * L_air) - L_min) * grey_per_L
    out = np.zeros((shape[0], shape[1]))
    n_rows = y.shape[0]
    n_cols = x.shape[1]
    x_rows = x.shape[0] > 1
    y_cols = y.shape[1] > 1
    n_hit = 0
    for i in range(n_rows):
        row = (r0 + i) // ss
        xi = i if x_rows else 0
        for j in range(n_cols):
            xv = x[xi, j]
            yv = y[i, j if y_cols else 0]
            d0 = _F32(R_bc[0, 0] * xv + (R_bc[0, 1] * yv + R_bc[0, 2]))
            d1 = _F32(R_bc[1, 0] * xv + (R_bc[1, 1] * yv + R_bc[1, 2]))
            d2 = _F32(R_bc[2, 0] * xv + (R_bc[2, 1] * yv + R_bc[2, 2]))
            _, part = _nearest(d0, d1, d2, oc, box_h, oe, ell_h)
            if part >= 0:
                out[r0 + i, c0 + j] = part_value[part] - np.float64(ref[row, (c0 + j) // ss])
                n_hit += 1
    return out, n_hit


@njit(cache=True, nogil=True, error_model="numpy")
def project_box(corners_cam, fx, fy, cx, cy, near_m):
    """Camera-frame points ``(n, 3)`` (an object's bounding-box corners) through the pinhole without
    distortion (``f x / z + c``, as ``parts.project_in_front``): ``(z_max, z_min, u_min, u_max, v_min,
    v_max)``; the image extents are NaN unless every point lies beyond ``near_m``."""
    z_max = -np.inf
    z_min = np.inf
    for k in range(corners_cam.shape[0]):
        z_max = max(z_max, corners_cam[k, 2])
        z_min = min(z_min, corners_cam[k, 2])
    if not z_min > near_m:
        return z_max, z_min, np.nan, np.nan, np.nan, np.nan
    u_min = np.inf
    u_max = -np.inf
    v_min = np.inf
    v_max = -np.inf
    for k in range(corners_cam.shape[0]):
        z = corners_cam[k, 2]
        u = fx * (corners_cam[k, 0] / z) + cx
        v = fy * (corners_cam[k, 1] / z) + cy
        u_min = min(u_min, u)
        u_max = max(u_max, u)
        v_min = min(v_min, v)
        v_max = max(v_max, v)
    return z_max, z_min, u_min, u_max, v_min, v_max


# ---------------------------------------------------------------------------- the sky and ground table


@njit(cache=True, nogil=True)
def table_lookup_coarse(kr0, kr1, kr2, off, xs, ys, invn, lut, flags):
    """The background table on the coarse grid: index ``int32(((kr0 xs[j] + (kr1 ys[i] + kr2)) invn[i, j])
    + off)`` (float32, numpy's order: ``IrRenderer._background_coarse``); returns ``(lut[index],
    flags[index], whether any flag is set)``."""
    h, w = invn.shape
    grey = np.empty((h, w), np.float32)
    near = np.empty((h, w), np.uint8)
    any_near = False
    for i in range(h):
        b = kr1 * ys[i] + kr2
        for j in range(w):
            k = np.int32((kr0 * xs[j] + b) * invn[i, j] + off)
            grey[i, j] = lut[k]
            near[i, j] = flags[k]
            any_near |= near[i, j] != 0
    return grey, near, any_near


@njit(cache=True, nogil=True)
def table_lookup_blocks(near, kr0, kr1, kr2, off, ray_x, ray_y, invn, lut, st, out):
    """The exact table look-up at every pixel of the ``st`` x ``st`` blocks next to a flagged coarse sample
    (``near`` on the coarse grid with its ring: block ``(bi, bj)`` is coarse sample ``(bi + 1, bj + 1)``,
    flagged when any of its 3 x 3 neighbours is, cv2.dilate's rule), written into ``out[i + st, j + st]``
    (the upsampled image with its ring); pixels beyond ``invn``'s shape are skipped."""
    h, w = invn.shape
    nb = near.shape[1] - 2
    flagged = np.zeros(nb + 1, np.bool_)  # one block row's flags, and a False past its end
    for bi in range(near.shape[0] - 2):
        for bj in range(nb):
            f = False
            for a in range(3):
                for c in range(3):
                    f |= near[bi + a, bj + c] != 0
            flagged[bj] = f
        # runs of flagged blocks side by side, each row of a run in one loop (the same values per pixel)
        bj = 0
        while bj < nb:
            if not flagged[bj]:
                bj += 1
                continue
            end = bj
            while flagged[end]:
                end += 1
            j0, j1 = st * bj, min(st * end, w)
            for i in range(st * bi, min(st * bi + st, h)):
                b = kr1 * ray_y[i] + kr2
                for j in range(j0, j1):
                    out[i + st, j + st] = lut[np.int32((kr0 * ray_x[j] + b) * invn[i, j] + off)]
            bj = end


@njit(cache=True, nogil=True)
def scale_offset(src, a, b):
    """``src a + b`` in float32, two roundings (numpy's ``src * a``, then ``+= b``), as a new array."""
    h, w = src.shape
    return scale_offset_window(src, 0, 0, h, w, a, b)


@njit(cache=True, nogil=True)
def scale_offset_window_twice(src, r0, c0, h, w, a, b):
    """:func:`scale_offset_window` written into two new arrays in the same pass (the image and a copy of it
    to draw on: one read of ``src`` fewer than a copy afterwards)."""
    out = np.empty((h, w), np.float32)
    copy = np.empty((h, w), np.float32)
    for i in range(h):
        row = src[r0 + i, c0 : c0 + w]
        o = out[i]
        c = copy[i]
        for j in range(w):
            v = row[j] * a + b
            o[j] = v
            c[j] = v
    return out, copy


@njit(cache=True, nogil=True)
def scale_offset_window(src, r0, c0, h, w, a, b):
    """:func:`scale_offset` of the window ``src[r0 : r0 + h, c0 : c0 + w]`` read in place: given the whole
    (C-ordered) image rather than a strided view of it, the loop knows its rows are contiguous and is
    vectorised (~4x faster on a 640 x 512 window)."""
    out = np.empty((h, w), np.float32)
    for i in range(h):
        row = src[r0 + i, c0 : c0 + w]  # contiguous rows, and indices the loop knows are not negative
        o = out[i]
        for j in range(w):
            o[j] = row[j] * a + b
    return out


# ---------------------------------------------------------------------------- compositing and output


@njit(cache=True, nogil=True)
def terrain_blend(near, far, f0, w_far, tau, out):
    """``out = tau (near + w_far (far - near))`` on the rows ``f0 .. f0 + len(far) - 1`` (``far``: the far mip
    level's look-up over those rows only), ``tau near`` elsewhere (where the far weight is 0): numpy's
    ``near += w_far * (far - near); out = tau * near`` over the whole frame in one pass, the same float32
    roundings (no fused multiply-add)."""
    h, w = near.shape
    f1 = f0 + far.shape[0]
    for i in range(h):
        if f0 <= i < f1:
            k = i - f0
            for j in range(w):
                x = near[i, j]
                x = x + w_far[i, j] * (far[k, j] - x)
                out[i, j] = tau[i, j] * x
        else:
            for j in range(w):
                out[i, j] = tau[i, j] * near[i, j]


@njit(cache=True, nogil=True)
def composite_band(below, a_up, lit_up, e0, e1, w0, out):
    """``out = below`` outside rows ``e0 .. e1 - 1``, and ``(below - a below) + lit`` there with ``a``, ``lit``
    the rows ``w0 ..`` of ``a_up``, ``lit_up`` (float32, numpy's three passes in one: a layer of opacity
    ``a`` seen over the background, radiating ``lit = a L_layer``)."""
    h, w = below.shape
    for i in range(h):
        if e0 <= i < e1:
            k = i - e0 + w0
            for j in range(w):
                x = below[i, j]
                out[i, j] = (x - a_up[k, j] * x) + lit_up[k, j]
        else:
            for j in range(w):
                out[i, j] = below[i, j]


@njit(cache=True, nogil=True)
def quantise_grey(radiance, L_min, grey_per_L, noise, full_scale, out):
    """``out = saturate(round(((radiance - L_min) grey_per_L) + noise))`` (float32, round half to even,
    0 .. ``full_scale``): numpy's subtract and multiply, then ``cv2.add(..., dtype=CV_8U/CV_16U)``'s
    rounding and saturation, in one pass (NaN gives full scale, as cv2's does)."""
    h, w = radiance.shape
    top = np.float32(full_scale)
    for i in range(h):
        for j in range(w):
            v = np.rint((radiance[i, j] - L_min) * grey_per_L + noise[i, j])
            if v != v:
                v = top
            out[i, j] = min(max(v, np.float32(0.0)), top)


# ---------------------------------------------------------------------------- the scene's planes (coarse grid)


@njit(cache=True, nogil=True, error_model="numpy")
def plane_rays(R, x, y, rnorm, h_g, far_m):
    """The rays of the coarse grid (``x``, ``y`` their image coordinates, ``rnorm`` their norms, float32)
    in NED and where they meet the ground ``h_g`` below the camera (``SceneContent.render_background``):
    ``(dn, de, dd, inv_dd, t_g, r_g, on_ground, rows)``; ``t_g`` -1 everywhere when the camera is not above
    the ground, ``r_g`` ``far_m`` off the ground; ``rows`` the first and last row with a ray pointing
    down (``dd > 0``) and up (``dd < 0``), -1 when none."""
    f32 = np.float32
    h, w = x.shape
    a0, a1, a2 = f32(R[0, 0]), f32(R[0, 1]), f32(R[0, 2])
    b0, b1, b2 = f32(R[1, 0]), f32(R[1, 1]), f32(R[1, 2])
    c0, c1, c2 = f32(R[2, 0]), f32(R[2, 1]), f32(R[2, 2])
    hg = f32(h_g)
    far = f32(far_m)
    dn = np.empty((h, w), np.float32)
    de = np.empty((h, w), np.float32)
    dd = np.empty((h, w), np.float32)
    inv_dd = np.empty((h, w), np.float32)
    t_g = np.empty((h, w), np.float32)
    r_g = np.empty((h, w), np.float32)
    on_ground = np.empty((h, w), np.bool_)
    rows = np.full(4, -1, np.int64)
    for i in range(h):
        down = False
        up = False
        for j in range(w):
            xv = x[i, j]
            yv = y[i, j]
            dn[i, j] = a0 * xv + a1 * yv + a2
            de[i, j] = b0 * xv + b1 * yv + b2
            d = c0 * xv + c1 * yv + c2
            dd[i, j] = d
            down |= d > f32(0.0)
            up |= d < f32(0.0)
            inv = f32(1.0) / d
            inv_dd[i, j] = inv
            t = hg * inv if h_g > 0.0 else f32(-1.0)
            t_g[i, j] = t
            on_ground[i, j] = t > f32(0.0)
            r_g[i, j] = t * rnorm[i, j] if t > f32(0.0) else far
        if down:
            if rows[0] < 0:
                rows[0] = i
            rows[1] = i
        if up:
            if rows[2] < 0:
                rows[2] = i
            rows[3] = i
    return dn, de, dd, inv_dd, t_g, r_g, on_ground, rows


@njit(cache=True, nogil=True, error_model="numpy")
def layer_rays(h_c, inv_dd, rnorm, r_g, r0, r1, max_range_m, foot_scale):
    """Where the rays of coarse rows ``r0 .. r1 - 1`` meet a layer ``h_c`` below the camera (the cloud
    layer, ``SceneContent._cloud_geometry``): ``(t, r_c, hit, foot_m, samples)`` over those rows, ``t`` the
    ray parameter where hit (0 elsewhere), ``r_c`` the range, ``hit`` in front (t > 0), within
    ``max_range_m`` and nearer than the ground ``r_g``, ``foot_m = r_c^2 / foot_scale``, ``samples`` the
    footprints of the hit rays in every third row and column (row-major; the mip level's quantile)."""
    f32 = np.float32
    n = r1 - r0
    w = inv_dd.shape[1]
    hc = f32(h_c)
    mr = f32(max_range_m)
    fs = f32(foot_scale)
    t = np.empty((n, w), np.float32)
    r_c = np.empty((n, w), np.float32)
    hit = np.empty((n, w), np.bool_)
    foot = np.empty((n, w), np.float32)
    samples = np.empty(((n + 2) // 3) * ((w + 2) // 3), np.float32)
    k = 0
    for i in range(n):
        for j in range(w):
            tc = hc * inv_dd[r0 + i, j]
            r = tc * rnorm[r0 + i, j]
            r_c[i, j] = r
            ok = tc > f32(0.0) and r < mr and r < r_g[r0 + i, j]
            hit[i, j] = ok
            t[i, j] = tc if ok else f32(0.0)
            foot[i, j] = r * r / fs
            if ok and i % 3 == 0 and j % 3 == 0:
                samples[k] = foot[i, j]
                k += 1
    return t, r_c, hit, foot, samples[:k]


@njit(cache=True, nogil=True, error_model="numpy")
def surface_maps(t, dn, de, r0, foot_m, off_e, off_n, inv_texel, texel, limit):
    """Texture coordinates of a tiled surface where the rays (``dn``, ``de`` from row ``r0``) meet it at
    ``t`` (``_mip_map``): ``x = clip((off_e + t de) inv_texel - 0.5, -limit, limit)``, ``y`` the same with
    north, and ``max(foot_m / texel, 1e-6)`` (float32; its log2 places the far level's weight)."""
    f32 = np.float32
    n, w = t.shape
    x = np.empty((n, w), np.float32)
    y = np.empty((n, w), np.float32)
    ratio = np.empty((n, w), np.float32)
    lo = f32(-limit)
    hi = f32(limit)
    for i in range(n):
        for j in range(w):
            tv = t[i, j]
            x[i, j] = min(max((off_e + tv * de[r0 + i, j]) * inv_texel - f32(0.5), lo), hi)
            y[i, j] = min(max((off_n + tv * dn[r0 + i, j]) * inv_texel - f32(0.5), lo), hi)
            ratio[i, j] = max(foot_m[i, j] / texel, f32(1e-6))
    return x, y, ratio


@njit(cache=True, nogil=True, error_model="numpy")
def layer_weights(hit, w_far_all, attenuation, r_c, r_g, rnorm, inv_dd, r0, tau_v, max_range_m, fade_m):
    """The cloud layer's compositing channels over its rows (``SceneContent._cloud_geometry``), where hit
    (0 elsewhere): ``w_far`` (from ``w_far_all``), ``optical = tau_v min(|r / d_down|, 1e3)``, ``seen =
    attenuation clip((max_range_m - r_c) / fade_m, 0, 1)``; ``depth`` (``r_c`` where hit, the ground's
    ``r_g`` elsewhere) and ``rows``: the first and last row where the near level is read (hit, w_far < 1)
    and where the far one is (w_far > 0), -1 when none.  ``rnorm``, ``inv_dd``, ``r_g`` from row ``r0``."""
    f32 = np.float32
    n, w = hit.shape
    w_far = np.empty((n, w), np.float32)
    optical = np.empty((n, w), np.float32)
    seen = np.empty((n, w), np.float32)
    depth = np.empty((n, w), np.float32)
    rows = np.full(4, -1, np.int64)
    mr = f32(max_range_m)
    fd = f32(fade_m)
    zero = f32(0.0)
    one = f32(1.0)
    for i in range(n):
        near_row = False
        far_row = False
        for j in range(w):
            if hit[i, j]:
                wf = w_far_all[i, j]
                optical[i, j] = tau_v * min(rnorm[r0 + i, j] * abs(inv_dd[r0 + i, j]), f32(1e3))
                fade = min(max((mr - r_c[i, j]) / fd, zero), one)
                seen[i, j] = attenuation[i, j] * fade
                depth[i, j] = r_c[i, j]
                near_row |= wf < one
            else:
                wf = zero
                optical[i, j] = zero
                seen[i, j] = zero
                depth[i, j] = r_g[r0 + i, j]
            w_far[i, j] = wf
            far_row |= wf > zero
        if near_row:
            if rows[0] < 0:
                rows[0] = i
            rows[1] = i
        if far_row:
            if rows[2] < 0:
                rows[2] = i
            rows[3] = i
    return w_far, optical, seen, depth, rows


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def fold_pair(a, b, scale, fn, inv):
    """One texture coordinate pair (times ``scale`` unless it is 0) folded into one period ``[0, fn)``:
    ``m - fn floor(m inv)`` (float32), and whether both lie in ``[0, fn]``."""
    if scale != 0.0:
        a = a * scale
        b = b * scale
    a = a - fn * np.floor(a * inv)
    b = b - fn * np.floor(b * inv)
    zero = np.float32(0.0)
    return a, b, a >= zero and a <= fn and b >= zero and b <= fn


@njit(cache=True, nogil=True, error_model="numpy")
def fold_maps(map_x, map_y, r0, r1, n, scale):
    """Texture coordinates of rows ``r0 .. r1 - 1`` (times ``scale`` unless it is 0) folded into one period
    ``[0, n)``: ``m - n floor(m (1 / n))`` (float32), and whether every folded
    coordinate lies in ``[0, n]``."""
    f32 = np.float32
    h = r1 - r0
    w = map_x.shape[1]
    fn = f32(n)
    inv = f32(1.0 / n)
    mx = np.empty((h, w), np.float32)
    my = np.empty((h, w), np.float32)
    inside = True
    for i in range(h):
        for j in range(w):
            a, b, ok = fold_pair(map_x[r0 + i, j], map_y[r0 + i, j], scale, fn, inv)
            mx[i, j] = a
            my[i, j] = b
            inside &= ok
    return mx, my, inside


@njit(cache=True, nogil=True, error_model="numpy")
def layer_blend(rho, L_c, rho_far, L_c_far, w_far, optical):
    """The far mip level blended into the near one in place (``x += w_far (x_far - x)``; ``rho_far``
    empty: no far level), and ``-(optical rho)`` returned (its exp is the layer's transmission)."""
    n, w = rho.shape
    out = np.empty((n, w), np.float32)
    blend = rho_far.size > 0
    for i in range(n):
        for j in range(w):
            if blend:
                wf = w_far[i, j]
                rho[i, j] += wf * (rho_far[i, j] - rho[i, j])
                L_c[i, j] += wf * (L_c_far[i, j] - L_c[i, j])
            out[i, j] = -(optical[i, j] * rho[i, j])
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def layer_light(transmission, seen, L_c):
    """In place: ``transmission`` becomes the opacity ``1 - transmission``, ``seen`` the opacity seen
    (``alpha seen``) and ``L_c`` the light the layer adds (``alpha seen L_c``)."""
    n, w = seen.shape
    for i in range(n):
        for j in range(w):
            a = np.float32(1.0) - transmission[i, j]
            transmission[i, j] = a
            s = a * seen[i, j]
            seen[i, j] = s
            L_c[i, j] = s * L_c[i, j]


@njit(cache=True, nogil=True, error_model="numpy")
def peak_box(delta, gain, fraction):
    """``(peak, i0, i1, j0, j1, warm)`` of ``|delta gain|`` (float32, ``gain`` rounded to float32 as numpy's
    in-place multiply rounds it): its maximum and the rows ``i0 .. i1 - 1``, columns ``j0 .. j1 - 1`` of the
    values at least ``fraction`` of it (the threshold rounded to float32 as numpy's comparison rounds it);
    ``warm``: ``delta gain`` is > 0 at the first pixel (row by row) where the maximum is reached; the box is
    -1s and ``warm`` False when the peak is not > 0 (``SceneContent._label``)."""
    g = np.float32(abs(gain))
    scale = gain != 1.0
    h, w = delta.shape
    peak = np.float32(0.0)
    warm = False
    for i in range(h):
        for j in range(w):
            m = abs(delta[i, j])
            if scale:
                m = m * g
            if m > peak:  # max(peak, m), and the sign where it was reached
                peak = m
                warm = (delta[i, j] > 0.0) == (gain > 0.0)
    if not peak > np.float32(0.0):
        return np.float64(peak), -1, -1, -1, -1, False
    thr = np.float32(fraction * np.float64(peak))
    i0, i1, j0, j1 = h, -1, w, -1
    for i in range(h):
        for j in range(w):
            m = abs(delta[i, j])
            if scale:
                m = m * g
            if m >= thr:
                i0 = min(i0, i)
                i1 = max(i1, i)
                j0 = min(j0, j)
                j1 = max(j1, j)
    return np.float64(peak), i0, i1 + 1, j0, j1 + 1, warm


# ---------------------------------------------------------------------------- the camera model (sensor)


@njit(cache=True, nogil=True)
def sensor_counts(radiance, gain, offset, noise, full_scale, out):
    """``out = min(saturate(round((radiance gain + offset) + noise)), full_scale)`` (float32, round half to
    even): ``cv2.multiply``, ``+=``, ``cv2.add(..., dtype=CV_16U)``'s rounding and saturation (NaN and +inf
    to 65535, -inf to 0) and numpy's ``minimum`` with the full scale, in one pass (``Sensor.counts``)."""
    h, w = radiance.shape
    top = np.float32(min(full_scale, 65535))
    for i in range(h):
        for j in range(w):
            x = radiance[i, j] * gain[i, j]
            x = x + offset[i, j]
            v = np.rint(x + noise[i, j])
            if v != v:
                v = top
            out[i, j] = min(max(v, np.float32(0.0)), top)


@njit(cache=True, nogil=True)
def _block_sum(a, i0, n):
    """numpy's pairwise summation of a block ``a[i0 : i0 + n]``, ``n <= 128`` (float64): below 8 in order,
    else in eight interleaved partial sums combined as a tree, then the rest in order."""
    if n < 8:
        res = 0.0
        for i in range(i0, i0 + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[i0], a[i0 + 1], a[i0 + 2], a[i0 + 3]
    r4, r5, r6, r7 = a[i0 + 4], a[i0 + 5], a[i0 + 6], a[i0 + 7]
    m = n - n % 8
    for i in range(i0 + 8, i0 + m, 8):
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    for i in range(i0 + m, i0 + n):
        res += a[i]
    return res


@njit(cache=True, nogil=True)
def pairwise_sum_pow2(a):
    """``a.sum()`` rounded as numpy rounds it (float64, ``len(a)`` a power of two): numpy's pairwise
    summation halves the array down to blocks of 128 (:func:`_block_sum`) and adds the halves' sums, which
    for a power of two is a perfect binary tree over the blocks (written as a loop: numba's cache does not
    keep recursive functions)."""
    n = a.shape[0]
    if n & (n - 1) != 0:
        raise ValueError("pairwise_sum_pow2: the length must be a power of two")
    if n <= 128:
        return _block_sum(a, 0, n)
    m = n // 128
    s = np.empty(m, np.float64)
    for k in range(m):
        s[k] = _block_sum(a, 128 * k, 128)
    while m > 1:
        m //= 2
        for k in range(m):
            s[k] = s[2 * k] + s[2 * k + 1]
    return s[0]


@njit(cache=True, nogil=True)
def agc_map(counts, n_bins, plateau_fraction, max_gain, linear_fraction, tail):
    """The AGC map (float64, ``n_bins`` entries, a power of two, 0..255) of ``counts[::2, ::2]`` (``Sensor.agc_map``, whose
    docstring has the model): the histogram, its plateau-clipped cumulative sum and the linear map between
    the ``tail`` and ``1 - tail`` points, with numpy's float64 operations in numpy's order (pairwise sums,
    sequential cumulative sums, ``searchsorted``'s left side)."""
    h, w = counts.shape
    # four partial histograms, one per column modulo 8: a sky's samples fall in a few bins, and one
    # histogram's increments of the same bin would wait on each other
    part = np.zeros((4, n_bins), np.int32)
    for i in range(0, h, 2):
        j = 0
        while j + 6 < w:
            part[0, counts[i, j]] += 1
            part[1, counts[i, j + 2]] += 1
            part[2, counts[i, j + 4]] += 1
            part[3, counts[i, j + 6]] += 1
            j += 8
        while j < w:
            part[0, counts[i, j]] += 1
            j += 2
    hist = np.empty(n_bins, np.float64)
    for k in range(n_bins):
        hist[k] = np.float64((part[0, k] + part[1, k]) + (part[2, k] + part[3, k]))
    total = 0.0  # integers: exact in any order
    for k in range(n_bins):
        total += hist[k]
    cap = plateau_fraction * total
    clipped = np.empty(n_bins, np.float64)
    for _ in range(2):  # as Sensor.agc_map: the slope cap depends on the clipped total
        for k in range(n_bins):
            clipped[k] = min(hist[k], cap)
        s = max_gain * pairwise_sum_pow2(clipped) / 255.0
        a = plateau_fraction * total
        cap = s if s < a else a
    # both cumulative sums in one loop (two independent chains of additions)
    cdf = np.empty(n_bins, np.float64)
    raw = np.empty(n_bins, np.float64)
    c = 0.0
    r = 0.0
    for k in range(n_bins):
        c += min(hist[k], cap)
        r += hist[k]
        cdf[k] = c
        raw[k] = r
    eq_den = max(c, 1.0)
    raw_den = max(total, 1.0)
    lo_t = tail
    hi_t = 1.0 - tail
    lo = n_bins
    hi = n_bins
    for k in range(n_bins):
        q = raw[k] / raw_den
        if lo == n_bins and q >= lo_t:
            lo = k
        if q >= hi_t:
            hi = k
            break
    lo_f = np.float64(lo)
    hi_f = np.float64(hi)
    span = max(hi_f - lo_f, 255.0 / max_gain)
    start = 0.5 * (lo_f + hi_f) - span / 2
    slope = 255.0 / span
    out = np.empty(n_bins, np.float64)
    for k in range(n_bins):
        eq = 255.0 * cdf[k] / eq_den
        lin = min(max((np.float64(k) - start) * slope, 0.0), 255.0)
        out[k] = (1.0 - linear_fraction) * eq + linear_fraction * lin
    return out


@njit(cache=True, nogil=True)
def lut_take(lut, counts, out):
    """``out = rint(lut).astype(uint8)[counts]`` (``lut`` float64 in 0..255, ``counts`` indices into it)."""
    n = lut.shape[0]
    lut8 = np.empty(n, np.uint8)
    for k in range(n):
        lut8[k] = np.uint8(np.rint(lut[k]))
    h, w = counts.shape
    for i in range(h):
        for j in range(w):
            out[i, j] = lut8[counts[i, j]]


@njit(cache=True, nogil=True)
def min_max(a, i0, i1, j0, j1):
    """``(a[i0:i1, j0:j1].min(), .max())`` as float64 (``a`` float32; NaN, NaN if one is NaN): exact, one call
    where numpy's two on a few dozen samples cost ~5 us each (``PyrUpImage.lower_bound``, ~14 a frame)."""
    if i1 <= i0 or j1 <= j0:
        raise ValueError("min_max: empty window")
    lo = a[i0, j0]
    hi = lo
    for i in range(i0, i1):
        for j in range(j0, j1):
            v = a[i, j]
            if v != v:  # numpy's min and max propagate NaN
                return np.nan, np.nan
            lo = min(lo, v)
            hi = max(hi, v)
    return np.float64(lo), np.float64(hi)


@njit(cache=True, nogil=True)
def remap_pair(pair, mx, my, r0, out0, out1):
    """``cv2.remap(level, mx, my, INTER_LINEAR)`` of two textures held interleaved, into rows ``r0 ..`` of
    ``out0``, ``out1``: ``pair`` (n + 2, n + 2, 2) float32 (``scene._wrap_padded_pair``: one look-up reads
    both channels from the same cache lines), ``mx``, ``my`` folded into ``[0, n]`` by :func:`fold_maps`
    (which says whether they are).  OpenCV's arithmetic on a CPU with fused multiply-adds (its SIMD path):
    ``a = x - floor(x)``, ``b = y - floor(y)``, ``top = fma(a, s01 - s00, s00)``, ``bottom = fma(a, s11 -
    s10, s10)``, ``fma(b, bottom - top, top)``."""
    flat = pair.reshape(-1)
    stride = np.uint64(2 * pair.shape[1])
    h, w = mx.shape
    u1, u2, u3 = np.uint64(1), np.uint64(2), np.uint64(3)
    for i in range(h):
        o0 = out0[r0 + i]
        o1 = out1[r0 + i]
        for j in range(w):
            x = mx[i, j]
            y = my[i, j]
            fx = np.floor(x)
            fy = np.floor(y)
            k = np.uint64(np.int64(fy)) * stride + np.uint64(np.int64(fx)) * u2
            ax = x - fx
            ay = y - fy
            s00, s01, s10, s11 = flat[k], flat[k + u2], flat[k + stride], flat[k + stride + u2]
            top = _fma(ax, s01 - s00, s00)
            bottom = _fma(ax, s11 - s10, s10)
            o0[j] = _fma(ay, bottom - top, top)
            s00, s01, s10, s11 = flat[k + u1], flat[k + u3], flat[k + stride + u1], flat[k + stride + u3]
            top = _fma(ax, s01 - s00, s00)
            bottom = _fma(ax, s11 - s10, s10)
            o1[j] = _fma(ay, bottom - top, top)
