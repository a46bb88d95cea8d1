"""Ray-cast rasteriser of rigid objects made of box and ellipsoid parts: the renderer's target and the
scene's distractors (model and sampling in the ``raster`` module docstring; the splat of small objects in
``docs/scenes.md``).  Frames and pixel conventions of ``onboard.core.frames``."""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtr

from groundsim.world.render.background import SceneBackground
from groundsim.world.render.kernels import cast_part_rays, nearest_parts, project_box
from groundsim.world.render.planck import band_radiance
from groundsim.world.render.settings import IrSettings
from groundsim.world.render.splat_kernels import splat_moments, splat_spot
from onboard.core.frames import PinholeIntrinsics

_SPLAT_WARM = False  # the splat's kernels compiled or loaded in this process (PartRaster._warm_splat)

__all__ = ["PartRaster", "project_in_front", "NEAR_M", "TARGET_SPLAT_MAX_PX"]

NEAR_M = 1e-3  # target bounding-box corners closer than this (camera z) -> whole-image ROI
APERTURE_KEPT = 256  # aperture weight matrices kept per object raster (by region size and offset)
# a target whose bounding sphere spans at most this many pixels is drawn by the splat, not the ray cast.  The
# ray cast samples a fixed grid of sub-samples per pixel: once one sub-sample is about as wide as the target's
# thinnest parts (16 mm arms: beyond ~100 m at 16 x 16), whole rows of sub-samples fall on or beside them as
# the target moves by a fraction of a pixel, and its radiance integral follows (by several times at 800 m);
# the splat's is exact in position and range.  Below 2 px the splat's image is also the nearer one to a
# fine ray cast's (rms 3 % against the 16 x 16 cast's 4 % at 200 m); above, the cast keeps the target's shape.
TARGET_SPLAT_MAX_PX = 2
# parallel rays per splat for its parts' visible fractions (splat_kernels.visible_fractions): ~40 us for the default
# target's 8 parts, its radiance integral within 1.6 % of the exact one over random views
SPLAT_VISIBILITY_RAYS = 2048


def project_in_front(
    intrinsics: PinholeIntrinsics, p_cam_m: np.ndarray, distorted: bool | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``intrinsics.project`` of camera-frame points ``(..., 3)`` with ``z > 0``, as ``(u_px, v_px)``.

    Without lens distortion the same float64 operations written out (``f (x / z) + c``): the same
    pixels, without the general path's NaN masking and stacking, which cost more than the arithmetic
    for the few points per object and frame (bounding-box corners, label centres).  ``distorted``:
    ``intrinsics.has_distortion`` if the caller holds it (that property loops over the coefficients)."""
    if intrinsics.has_distortion if distorted is None else distorted:
        uv = intrinsics.project(p_cam_m)
        return uv[..., 0], uv[..., 1]
    z = p_cam_m[..., 2]
    return (
        intrinsics.fx_px * (p_cam_m[..., 0] / z) + intrinsics.cx_px,
        intrinsics.fy_px * (p_cam_m[..., 1] / z) + intrinsics.cy_px,
    )


def _aperture_weights(centres_px: np.ndarray, samples_px: np.ndarray, sigma_px: float, ss: int) -> np.ndarray:
    """``W[i, k] = K(centres_i - samples_k) / ss``: 1-D pixel box (width 1) convolved with a Gaussian PSF.

    ``K(x) = Phi((x + 1/2) / sigma) - Phi((x - 1/2) / sigma)`` (Phi the standard normal CDF); with
    ``sigma = 0`` the box alone.  Each sub-sample stands for ``1 / ss`` of a pixel side.
    """
    x = centres_px[:, None] - samples_px[None, :]
    if sigma_px > 0.0:
        K = ndtr((x + 0.5) / sigma_px) - ndtr((x - 0.5) / sigma_px)
    else:
        K = ((x > -0.5) & (x <= 0.5)).astype(float)
    return K / ss


class PartRaster:
    """Ray-cast rasteriser of one rigid object made of box and ellipsoid parts (``TargetPart``).

    ``delta(bg, p_cam, R_ned_from_cam, p_obj, R_ned_from_body)`` returns the object's image minus the
    background ``bg`` over its region of interest, through the pixel aperture and the optics PSF, in the
    units of ``bg``: grey when built with the renderer's ``(L_min, grey_per_L)``, radiance with
    ``(0, 1)``.  Each part radiates ``eps L(T) + (1 - eps) L_env`` (``L_env`` the surround it
    reflects), seen through the atmosphere over the camera-object range.  The renderer's target and
    the scene's distractors are drawn by this one class.
    """

    def __init__(
        self,
        intrinsics: PinholeIntrinsics,
        settings: IrSettings,
        parts,
        L_env: float,
        L_min: float,
        grey_per_L: float,
        splat_max_px: int = 0,
        visibility_rays: int = SPLAT_VISIBILITY_RAYS,
    ):
        s = settings
        # objects whose projected bounding box spans at most this many pixels each way are drawn as an
        # analytic splat (:meth:`_splat`) instead of the ray cast; 0: always the ray cast
        self.splat_max_px = int(splat_max_px)
        self._visibility_rays = int(visibility_rays)  # the splat's rays for its parts' visible fractions
        self.intrinsics = intrinsics
        self._distorted = intrinsics.has_distortion  # read per call (the property loops over coefficients)
        self.settings = settings
        self._H, self._W = int(intrinsics.height_px), int(intrinsics.width_px)
        self._L_min = L_min
        self._grey_per_L = grey_per_L
        self._L_air = float(band_radiance(s.air_temperature_k, s.band_um))
        T = np.array([p.temperature_k for p in parts])
        eps = np.array([p.emissivity for p in parts])
        self._part_L_emit = eps * band_radiance(T, s.band_um) + (1.0 - eps) * L_env  # at the target
        centre = np.array([p.center_frd_m for p in parts], dtype=float)
        half = np.array([p.half_extent_m for p in parts], dtype=float)
        is_box = np.array([p.shape == "box" for p in parts])
        # for the splat (small objects): per part centre, half extents, box or ellipsoid, emitted radiance
        self._splat_parts = (centre, half, is_box, self._part_L_emit)
        self._intr_array = np.array([intrinsics.fx_px, intrinsics.fy_px, intrinsics.cx_px, intrinsics.cy_px])
        self._box_idx = np.flatnonzero(is_box)
        self._ell_idx = np.flatnonzero(~is_box)
        self._part_order = np.concatenate([self._box_idx, self._ell_idx])  # the kernels' part numbers
        self._part_L_emit_cast = self._part_L_emit[self._part_order]
        self._box_c, self._box_h = centre[is_box].astype(np.float32), half[is_box].astype(np.float32)
        self._ell_c, self._ell_h = centre[~is_box], half[~is_box].astype(np.float32)
        lo = (centre - half).min(axis=0)
        hi = (centre + half).max(axis=0)
        self._radius_b = float(np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi))))  # bounding sphere, body origin
        self._f_max_px = max(intrinsics.fx_px, intrinsics.fy_px)
        self.bbox_corners_b = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        self._aperture_kept: dict[tuple[int, int, int, int], np.ndarray] = {}  # see _aperture
        if self.splat_max_px > 0:
            self._warm_splat()

    def delta(self, bg, p_cam, R_nc, p_t, R_nt, occluder: SceneBackground | None = None):
        """Object minus background (through PSF and pixel aperture) over the object's ROI, or None.

        Returns ``(rows slice, cols slice, delta float32, supersample)``.  With ``occluder`` (a
        :class:`SceneBackground` in the units of ``bg``), pixels whose ``depth_m`` is nearer than the
        object show it through ``1 - cloud_alpha`` of the cloud, against the cloud-free background.
        """
        intr = self.intrinsics
        s = self.settings
        H, W = self._H, self._W
        distorted = self._distorted
        if self.splat_max_px and not distorted:
            t_c = ((p_t - p_cam) @ R_nc).tolist()
            z_near = t_c[2] - self._radius_b
            # the bounding sphere's diameter on the image, an upper bound of the object's footprint
            if z_near > NEAR_M and 2.0 * self._radius_b * self._f_max_px <= self.splat_max_px * z_near:
                return self._splat(bg, t_c, R_nc, R_nt, occluder)
        corners_cam = (p_t + self.bbox_corners_b @ R_nt.T - p_cam) @ R_nc
        if distorted:
            z = corners_cam[:, 2]
            z_max, z_min = float(z.max()), float(z.min())
            if z_min > NEAR_M:
                cu, cv = project_in_front(intr, corners_cam, distorted)
                uv = (float(cu.min()), float(cu.max()), float(cv.min()), float(cv.max()))
        else:  # one compiled pass: project_in_front's pixels and their extents
            z_max, z_min, *uv = project_box(corners_cam, intr.fx_px, intr.fy_px, intr.cx_px, intr.cy_px, NEAR_M)
        if z_max <= NEAR_M:
            return None
        box_uv = None  # the projected bounding box (u0, u1, v0, v1), px, when the ROI is drawn around it
        if z_min <= NEAR_M:
            i0, i1, j0, j1 = 0, H, 0, W
        else:
            if not distorted:
                box_uv = (uv[0], uv[1], uv[2], uv[3])
            pad = 1 if distorted else 0
            j0 = max(int(math.floor(uv[0])) - pad, 0)
            j1 = min(int(math.ceil(uv[1])) + pad, W)
            i0 = max(int(math.floor(uv[2])) - pad, 0)
            i1 = min(int(math.ceil(uv[3])) + pad, H)
            if j1 <= j0 or i1 <= i0:
                return None
        ny, nx = i1 - i0, j1 - j0
        ss = max(1, min(s.supersample, int(math.sqrt(s.max_target_rays / (ny * nx)))))
        u = j0 + (np.arange(nx * ss) + 0.5) / ss
        v = i0 + (np.arange(ny * ss) + 0.5) / ss
        # only the sub-sample rows and columns within one sub-sample of the projected bounding box are cast
        # (the ROI is that box rounded out to whole pixels: for a target 2 px across about half of it lies
        # outside); the others cannot meet the object and keep a delta of 0
        r0, r1, c0, c1 = 0, ny * ss, 0, nx * ss
        if box_uv is not None:
            c0 = max(math.floor((box_uv[0] - j0) * ss - 0.5) - 1, 0)
            c1 = min(math.ceil((box_uv[1] - j0) * ss - 0.5) + 2, nx * ss)
            r0 = max(math.floor((box_uv[2] - i0) * ss - 0.5) - 1, 0)
            r1 = min(math.ceil((box_uv[3] - i0) * ss - 0.5) + 2, ny * ss)
        R_bc = R_nt.T @ R_nc
        # float32 ray casting: ~3e-5 m resolution at 300 m, far below the 16 mm thinnest part
        o_b = (R_nt.T @ (p_cam - p_t)).astype(np.float32)
        if distorted:
            uu, vv = np.meshgrid(u[c0:c1], v[r0:r1])
            xy = intr.normalized_from_pixel(np.stack([uu, vv], axis=-1))
            x, y = np.ascontiguousarray(xy[..., 0]), np.ascontiguousarray(xy[..., 1])
        else:  # separable: one row of x, one column of y
            x = ((u[c0:c1] - intr.cx_px) / intr.fx_px)[None, :]
            y = ((v[r0:r1] - intr.cy_px) / intr.fy_px)[:, None]
        d_m = p_t - p_cam
        range_km = math.sqrt(d_m.dot(d_m)) * 1e-3  # np.linalg.norm's own sqrt(x . x), without its checks
        tau = math.exp(-s.extinction_per_km * range_km)
        # difference to the background per sub-sample (the background of the sub-sample's pixel)
        ref = bg[i0:i1, j0:j1]
        pad = int(math.ceil(3.0 * s.blur_sigma_px + 0.5))  # K reaches half a pixel + 3 sigma
        pi0, pi1 = max(i0 - pad, 0), min(i1 + pad, H)
        pj0, pj1 = max(j0 - pad, 0), min(j1 + pad, W)
        behind = None  # where a surface (a cloud) is nearer than the object, when anywhere in its region
        # (nothing_nearer: a coarse-grid bound that spares the window's two pyrUp steps when no cloud can be
        # nearer; otherwise the window decides, pixel by pixel)
        if occluder is not None and not occluder.nothing_nearer(slice(pi0, pi1), slice(pj0, pj1), range_km * 1e3):
            range_m = range_km * 1e3
            behind = occluder.depth_window(slice(pi0, pi1), slice(pj0, pj1)) < range_m
            if behind.any():
                ref = np.where(
                    behind[i0 - pi0 : i1 - pi0, j0 - pj0 : j1 - pj0], occluder.base_radiance[i0:i1, j0:j1], ref
                )
            else:
                behind = None  # the usual case: nothing in front, no opacity to read
        # each cast sub-sample minus its pixel's background, 0 where it meets nothing (float64); the rows
        # and columns outside [r0, r1) x [c0, c1) are not cast
        delta, n_hit = cast_part_rays(
            R_bc,
            o_b,
            x,
            y,
            self._box_c,
            self._box_h,
            self._ell_c,
            self._ell_h,
            self._part_L_emit_cast,
            np.array((tau, self._L_air, self._L_min, self._grey_per_L)),
            np.ascontiguousarray(ref),
            ss,
            r0,
            c0,
            (ny * ss, nx * ss),
        )  # fmt: skip  (one compiled signature: the background's window is a strided view)
        if n_hit == 0:
            return None
        # optics PSF and pixel aperture applied to the sub-samples in one separable linear map:
        # pixel = sum_k delta_k K(u_pix - u_k) K(v_pix - v_k) / ss^2, K = box(1 px) * Gaussian(sigma)
        # (blurring pixel values instead would lose the sub-pixel position of a sub-pixel target)
        A_rows = self._aperture(pi0, pi1, i0, v, ss)
        A_cols = self._aperture(pj0, pj1, j0, u, ss)
        delta = (A_rows @ delta) @ A_cols.T
        i0, i1, j0, j1 = pi0, pi1, pj0, pj1
        if behind is not None:
            delta = delta * np.where(behind, 1.0 - occluder.alpha_window(slice(i0, i1), slice(j0, j1)), 1.0)
        return slice(i0, i1), slice(j0, j1), delta.astype(np.float32, copy=False), ss

    def _aperture(self, p0: int, p1: int, k0: int, samples: np.ndarray, ss: int) -> np.ndarray:
        """``_aperture_weights`` of the output pixels ``p0 .. p1 - 1`` and the sub-samples ``samples`` (from
        pixel ``k0``, ``ss`` a pixel), kept per offset and size when ``ss`` is a power of two: then every
        offset between a pixel centre and a sample is a short binary fraction, exact wherever the region
        lies, so the kept weights are the very values a fresh computation gives (other ``ss``: computed)."""
        if ss & (ss - 1):
            return _aperture_weights(np.arange(p0, p1) + 0.5, samples, self.settings.blur_sigma_px, ss)
        key = (p0 - k0, p1 - k0, samples.size, ss)
        w = self._aperture_kept.get(key)
        if w is None:
            if len(self._aperture_kept) >= APERTURE_KEPT:
                self._aperture_kept.clear()
            rel = (np.arange(samples.size) + 0.5) / ss
            w = _aperture_weights(np.arange(p0 - k0, p1 - k0) + 0.5, rel, self.settings.blur_sigma_px, ss)
            w.flags.writeable = False
            self._aperture_kept[key] = w
        return w

    def _warm_splat(self) -> None:
        """Compile (or load from numba's cache) the splat's kernels now, once per process, for the backgrounds
        they are drawn on: the renderer's (float32, a window of a larger array) and a scene's image (float32, C
        order).  Compiled at their first use instead, a new install's simulator stalled 4 s in real time at the
        moment the target first shrank to a few pixels (P1, 18.6 s into the flight)."""
        global _SPLAT_WARM
        if _SPLAT_WARM:
            return
        larger = np.zeros((self._H + 2, self._W + 2), np.float32)
        for bg in (larger[1:-1, 1:-1], np.zeros((self._H, self._W), np.float32)):
            self._splat(bg, [0.0, 0.0, 1.0e4], np.eye(3), np.eye(3), None)  # the object 10 km along the axis
        _SPLAT_WARM = True

    def _splat(self, bg, t_c: list[float], R_nc, R_nt, occluder: SceneBackground | None):
        """:meth:`delta` of an object a few pixels across, without the ray cast: its radiance integral and
        its first and second moments on the image, drawn as a separable box x Gaussian spot.

        Each part is projected through the pinhole's Jacobian at its centre (the object is small against
        its range): generators ``A = J R_cam_from_body diag(half)``; the silhouette's area (px^2) is
        ``4 sum |det(a_i, a_j)|`` for a box (the hexagon of a projected cube), ``pi |det(A A^T)|^1/2`` for an
        ellipsoid, its covariance ``A A^T / 3`` or ``/ 4``.  The integral is ``sum_p area_p (L_p - L_bg)``
        (``L_bg`` the background at the centroid's pixel), ``area_p`` times the fraction of it in front of the
        other parts along this view (``splat_kernels.visible_fractions``, parallel rays: the ray cast's nearest-part
        rule, e.g. a bird's body over its wings).
        Centroid and spread are the ``|area contrast|``-weighted mixture of the parts'; the spread adds
        to the PSF's, the pixel box is kept, so the pixels sum to the integral (within the 3 sigma cut)
        and the intensity centroid is the parts' centroid.  A cloud in front (``occluder``) is read at the
        centroid's pixel only.  Compiled scalar arithmetic over the few parts (``splat_kernels.splat_moments``,
        ``splat_spot``): numpy's per-call cost on arrays of 2-4 parts is larger than the arithmetic."""
        s = self.settings
        H, W = self._H, self._W
        range_m = math.sqrt(t_c[0] ** 2 + t_c[1] ** 2 + t_c[2] ** 2)
        tau = math.exp(-s.extinction_per_km * range_m * 1e-3)
        # the parts' areas (times their visible fractions along this view), grey levels, positions and
        # spreads, and the spot's centre and spread: the parts weighted by |area x contrast| against the
        # background near the object's projected centre (one background read; the weights only place and
        # shape the spot)
        parts, u_c, v_c, sig_u, sig_v = splat_moments(
            np.array(t_c), R_nc.T @ R_nt, R_nc, R_nt, *self._splat_parts, self._visibility_rays,
            np.array((tau, self._L_air, self._L_min, self._grey_per_L)), self._intr_array, bg, s.blur_sigma_px,
        )  # fmt: skip
        if parts.shape[0] == 0:  # a part behind the camera
            return None
        ru, rv = int(math.ceil(3.0 * sig_u + 0.5)), int(math.ceil(3.0 * sig_v + 0.5))
        i0, i1 = max(math.floor(v_c) - rv, 0), min(math.floor(v_c) + rv + 1, H)
        j0, j1 = max(math.floor(u_c) - ru, 0), min(math.floor(u_c) + ru + 1, W)
        if i1 <= i0 or j1 <= j0:
            return None
        ic, jc = min(max(int(v_c), 0), H - 1), min(max(int(u_c), 0), W - 1)
        gain = 1.0
        ref = float(bg[ic, jc])
        if occluder is not None:
            px = slice(ic, ic + 1), slice(jc, jc + 1)
            if not occluder.nothing_nearer(*px, range_m) and occluder.depth_window(*px)[0, 0] < range_m:
                ref = float(occluder.base_radiance[ic, jc])
                gain = 1.0 - float(occluder.alpha_window(*px)[0, 0])
        # pixel j spans [j, j + 1]: box x Gaussian weights Phi((j + 1 - u_c) / sig) - Phi((j - u_c) / sig)
        delta = splat_spot(parts, ref, gain, u_c, v_c, sig_u, sig_v, i0, i1, j0, j1)
        return slice(i0, i1), slice(j0, j1), delta, 1

    def intersect(self, o_b: np.ndarray, d_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit of rays ``o_b + t d_b`` (body FRD, float32; ``d_b`` shape (3, n)) with the parts.

        Boxes: slab test (Kay & Kajiya 1986): ``t_near = max_k min(t1_k, t2_k)``,
        ``t_far = min_k max(t1_k, t2_k)``, hit when ``t_near <= t_far`` and ``t_far > 0``.
        Ellipsoids: scale to the unit sphere, ``a t^2 + 2 b t + c = 0``, hit when ``b^2 - a c >= 0``
        and the far root is > 0 (``b^2 - a c`` as ``a - |o x d|^2``, Lagrange's identity: no cancellation
        of two ~1e12 terms in float32 when the object is hundreds of metres away).  A camera inside a part
        sees it at t = 0.  Returns ``(t, part)``: the nearest ``t`` per ray (inf: no hit) and that part's
        index (-1: no hit).  Ties go to the boxes before the ellipsoids, each in index order.
        (``kernels.nearest_parts``; :meth:`delta` casts through ``kernels.cast_part_rays``, the same tests.)
        """
        t, part = nearest_parts(
            np.ascontiguousarray(o_b, np.float32), np.ascontiguousarray(d_b, np.float32),
            self._box_c, self._box_h, self._ell_c, self._ell_h,
        )  # fmt: skip
        return t, np.where(part >= 0, self._part_order[np.maximum(part, 0)], -1)
