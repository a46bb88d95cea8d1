"""IR rasteriser of the ground simulator: one thermal frame from the observer's camera pose and the target's pose.

Frames and pixel conventions are those of ``onboard.core.frames`` (local NED, body FRD, OpenCV camera,
pixel (i, j) centred at (j + 0.5, i + 0.5)).  Radiance in W m^-2 sr^-1 (``planck.band_radiance``);
the image is the paper's linear grey map of radiance (see ``planck``), mono8 or mono16.

Scene model
-----------
Sky (ray elevation ``el > 0``, ``s = sin(el)``): brightness temperature
``T_sky(s) = sky_horizon_k + (sky_zenith_k - sky_horizon_k) * s``, radiance ``L(T_sky)`` (an
effective sky temperature already includes the atmosphere along the ray).
Ground (``s < 0``): flat, at NED down = ``altitude_ground_d_m``, at ``ground_temperature_k`` with
``ground_emissivity``, reflecting the sky specularly, seen through the atmosphere::

    L = tau * (eps_g L(T_g) + (1 - eps_g) L_sky(-s)) + (1 - tau) L(T_air),
    tau = exp(-extinction_per_km * range_km),  range_m = h / (-s),  h = camera height above ground.

Target: the parts of ``settings.target_parts`` (boxes and ellipsoids in the target's body FRD),
intersected exactly per ray (slab test, scaled-sphere quadratic), the nearest part wins::

    L = tau * (eps L(T) + (1 - eps) L_env) + (1 - tau) L(T_air),   tau from the camera-target range,

``L_env`` a crude constant surround: half sky (at the mean of zenith and horizon temperatures),
half ground.

Sensor
------
Pixel aperture (box) and a Gaussian optics PSF (``blur_sigma_px``), then temporal NETD noise
(``planck.noise_sigma_grey``), then one rounding/saturation to the output integer type.

How it is fast (the issue asks >= 125 frames/s of 640 x 512 on one core; ``python -m bench.render``)
----------------------------------------------------------------------------------------------------
* The background depends only on ``s`` of each pixel's ray, ``s = -(row 3 of R_ned_from_cam) . d_cam``,
  through a 1-D table of grey values over ``s`` (``LUT_SIZE`` entries, nearest entry: <= 0.025 px
  at the horizon).  The pixel aperture and the PSF act on the horizon's step through the table:
  ``Phi(el / sigma_el)`` blends the sky and ground sides, ``sigma_el = sqrt(blur_sigma_px^2 + 1/12)
  / sqrt(fx fy)`` rad (a Gaussian stand-in for box x PSF, exact in angle at the image centre; at
  the corners of a 45 deg lens pixels subtend ~20 % less angle, so the edge is that much wider in
  pixels there).  Smooth parts of sky and ground are not smoothed (they change by far less than a
  grey level across a pixel).  The table is rebuilt only when the camera height changed by more
  than ``ALT_REUSE_ABS_M + ALT_REUSE_REL * h``.
* Per frame, the table is looked up on a 4 x 4 px coarse grid (plus a ring outside the image),
  upsampled bilinearly (cv2.resize), and looked up per pixel only in the blocks whose interpolation
  could err by more than ``COARSE_TOL_FS`` of full scale (flags precomputed over the table from
  its curvature: the horizon band, a few px wide).  Max difference to a per-pixel look-up:
  0.03 grey in mono8 (``tests/groundsim/test_raster.py``).  The background image is reused while
  the third row of ``R_ned_from_cam`` moved less than ``background_reuse_tol_rad`` (a pure yaw
  change is an exact reuse).
* The target is cast only in the bounding box of its projected body-frame bounding box, with
  ``supersample x supersample`` stratified rays per pixel (16 x 16 unless the box needs more than
  ``max_target_rays``; only those within one sub-sample of the projected box are cast, the rest of the
  whole-pixel box cannot meet it), as a *difference* to the background.  PSF and pixel aperture act on the
  sub-samples in one separable linear map (two small matrix products with ``K = box * Gaussian``
  weights), so the sub-pixel position of a target thinner than a pixel survives; the result,
  over the box padded by 3 sigma, is added to the background, which is never blurred per frame.
* Noise: one bank of standard-normal samples (``noise_bank_frames`` frames long, scaled to grey
  levels) drawn once; each frame reads a contiguous window at a random offset (deterministic from
  ``seed``): no per-frame normal draw.  ``cv2.add(..., dtype=CV_8U/16U)`` fuses the noise addition,
  rounding and saturation in one pass.

Results depend only on the call sequence and ``seed`` (the reuse tolerances are far below a pixel).

Hook for scene content (``groundsim.world.render.scene``, ``docs/scenes.md``)
----------------------------------------------------------------------------
:meth:`IrRenderer.base_radiance` gives the background above as radiance (no noise);
:class:`SceneBackground` is a background with clouds and terrain composited over it, per pixel with the
range to the nearest surface and the opacity of a cloud there; :meth:`IrRenderer.render_radiance`
draws the target over one (behind a nearer cloud it is seen through ``1 - alpha``), and
:meth:`IrRenderer.quantise` turns radiance into :meth:`render`'s output (grey map, NETD noise,
rounding).  :class:`PartRaster` is the target's ray caster as a class of its own, so that other
objects (distractors) are drawn the same way.  :meth:`render` itself is unchanged.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.special import ndtr

from groundsim.world.render.planck import band_radiance, grey_full_scale, noise_sigma_grey
from groundsim.world.render.settings import IrSettings
from onboard.core.errors import InputError
from onboard.core.frames import PinholeIntrinsics

__all__ = [
    "IrRenderer",
    "RenderTiming",
    "PartRaster",
    "PyrUpImage",
    "project_in_front",
    "SceneBackground",
    "truth_pixel",
    "LUT_SIZE",
]

log = logging.getLogger(__name__)

LUT_SIZE = 32768  # entries of the background table over s = sin(elevation) in [-1, 1]
_LUT_PAD = 2  # guard entries at each end (float rounding of |s| slightly above 1)
ALT_REUSE_ABS_M = 0.5  # the background table is rebuilt when the camera height changed by more than
ALT_REUSE_REL = 0.01  # ALT_REUSE_ABS_M + ALT_REUSE_REL * height
COARSE_STEP = 4  # background computed on a 4 x 4 px coarse grid, bilinear upsampling, exact near the horizon
MAX_EXACT_STRIPS = 16  # ... in at most this many block strips, else the whole image exactly
COARSE_TOL_FS = 4e-4  # ... where the interpolation error could exceed this fraction of full scale (0.1 grey)
ROT_TOL = 5e-3  # max |R^T R - I| accepted (a quaternion off unit norm by frames.QUAT_NORM_TOL gives ~2e-3)
NEAR_M = 1e-3  # target bounding-box corners closer than this (camera z) -> whole-image ROI
APERTURE_KEPT = 256  # aperture weight matrices kept per object raster (by region size and offset)


@dataclass(frozen=True)
class RenderTiming:
    """Where the last :meth:`IrRenderer.render` spent its time (milliseconds) and what it reused."""

    background_ms: float
    target_ms: float
    noise_quantise_ms: float
    total_ms: float
    background_reused: bool
    table_rebuilt: bool
    target_roi_px: int  # pixels of the (padded) target ROI, 0 when the target is not in view
    supersample: int  # sub-samples per pixel side used on the target, 0 when not in view


def truth_pixel(intrinsics: PinholeIntrinsics, p_cam_ned_m, R_ned_from_cam, p_target_ned_m) -> tuple[float, float]:
    """The pixel (u_px, v_px) of the target body centre: ``intrinsics.project(R_ned_from_cam^T (p_t - p_cam))``.

    NaN when the target is behind the camera.  Same convention as the renderer and ``onboard.core.frames``.
    """
    p_c = _vec3(p_cam_ned_m, "p_cam_ned_m")
    p_t = _vec3(p_target_ned_m, "p_target_ned_m")
    R = _rotation(R_ned_from_cam, "R_ned_from_cam")
    uv = intrinsics.project(R.T @ (p_t - p_c))
    return float(uv[0]), float(uv[1])


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


def _vec3(v, name: str) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected 3 finite numbers, got {v!r}") from exc
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InputError(f"{name}: expected 3 finite numbers, got shape {a.shape}")
    return a


def _rotation(R, name: str) -> np.ndarray:
    try:
        a = np.asarray(R, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected a 3x3 rotation matrix") from exc
    if a.shape != (3, 3) or not np.all(np.isfinite(a)):
        raise InputError(f"{name}: expected a finite 3x3 rotation matrix, got shape {a.shape}")
    if np.max(np.abs(a.T @ a - np.eye(3))) > ROT_TOL or np.linalg.det(a) < 0.0:
        raise InputError(f"{name}: not a proper rotation (R^T R != I within {ROT_TOL} or det < 0)")
    return a


class PyrUpImage:
    """An (H, W) float32 image held as the coarse image two ``cv2.pyrUp`` steps below it (one sample per
    4 x 4 px): :meth:`full` takes it up once and keeps it; :meth:`window` takes up only the coarse samples
    around a window, with the same values as the full image there (a pixel of two pyrUp steps depends on
    the coarse samples within 2 of its own; at the image's border the window reaches the same border).
    The scene's depth and cloud opacity are read per object and per label, rarely whole.

    A window is taken up with one more coarse sample around it than it needs and kept: later windows
    inside the region it holds exactly (an object's label pixel inside its region, a spot's centre next to
    its label's) are read from it without another two ``pyrUp`` calls, whose fixed cost is most of a small
    window's.  Windows are read-only views (the kept images are shared)."""

    MARGIN = 2  # coarse samples a pixel depends on, each way
    SPARE = 1  # ... and this many more taken up around each window, for the windows that follow
    MAX_KEPT = 32  # windows kept per image (an image lives one frame; a frame reads a few per object)

    def __init__(self, coarse: np.ndarray, shape: tuple[int, int]):
        self.coarse = coarse
        self.shape = (int(shape[0]), int(shape[1]))
        self._full: np.ndarray | None = None
        # (first row, end row, first col, end col) of the pixels a kept window holds exactly, and its image
        self._kept: list[tuple[int, int, int, int, np.ndarray]] = []

    def full(self) -> np.ndarray:
        if self._full is None:
            H, W = self.shape
            self._full = np.ascontiguousarray(cv2.pyrUp(cv2.pyrUp(self.coarse))[:H, :W])
        return self._full

    def window(self, rows: slice, cols: slice) -> np.ndarray:
        if self._full is not None:
            return self._full[rows, cols]
        H, W = self.shape
        i0, i1, _ = rows.indices(H)
        j0, j1, _ = cols.indices(W)
        for r0, r1, c0, c1, img in self._kept:
            if r0 <= i0 and i1 <= r1 and c0 <= j0 and j1 <= c1:
                return img[i0 - r0 : i1 - r0, j0 - c0 : j1 - c0]
        hc, wc = self.coarse.shape
        m = self.MARGIN
        # the coarse samples of the window's own pixels, grown by SPARE (within the image) ...
        k0, k1 = max(i0 // 4 - self.SPARE, 0), min(-(-i1 // 4) + self.SPARE, hc)
        l0, l1 = max(j0 // 4 - self.SPARE, 0), min(-(-j1 // 4) + self.SPARE, wc)
        # ... and the MARGIN samples they depend on
        a, b = max(k0 - m, 0), min(k1 + m, hc)
        c, d = max(l0 - m, 0), min(l1 + m, wc)
        up = cv2.pyrUp(cv2.pyrUp(np.ascontiguousarray(self.coarse[a:b, c:d])))
        up.flags.writeable = False
        r0, r1 = 4 * k0, min(4 * k1, H)
        c0, c1 = 4 * l0, min(4 * l1, W)
        held = up[r0 - 4 * a : r1 - 4 * a, c0 - 4 * c : c1 - 4 * c]
        if len(self._kept) < self.MAX_KEPT:
            self._kept.append((r0, r1, c0, c1, held))
        return held[i0 - r0 : i1 - r0, j0 - c0 : j1 - c0]


class SceneBackground:
    """A background with scene content, per pixel, (H, W) float32 each, as the renderer's hook takes it.

    ``radiance``: W m^-2 sr^-1 at the aperture (sky or terrain, clouds composited over it);
    ``base_radiance``: the same without clouds (what a cloud hides); ``depth_m``: range along the
    ray to the nearest surface (the cloud layer where the ray meets it, else the ground, else a far
    value); ``cloud_alpha``: opacity of the cloud there (0 where the layer is clear or absent).  An object at range ``R`` behind
    ``depth_m`` is seen through ``1 - cloud_alpha`` of the cloud.  ``depth_m`` and ``cloud_alpha`` may be
    given as :class:`PyrUpImage`: taken up whole when read whole, by window through :meth:`depth_window`
    and :meth:`alpha_window` (the objects' regions).
    """

    __slots__ = ("radiance", "base_radiance", "_depth", "_alpha")

    def __init__(self, radiance, base_radiance, depth_m, cloud_alpha):
        self.radiance = radiance
        self.base_radiance = base_radiance
        self._depth = depth_m
        self._alpha = cloud_alpha
        shape = np.shape(radiance)
        for name, v in (("base_radiance", base_radiance), ("depth_m", depth_m), ("cloud_alpha", cloud_alpha)):
            v_shape = v.shape if isinstance(v, PyrUpImage) else np.shape(v)
            if tuple(v_shape) != shape or len(shape) != 2:
                raise InputError(f"SceneBackground.{name}: expected shape {shape} like radiance")

    @property
    def depth_m(self) -> np.ndarray:
        return self._depth.full() if isinstance(self._depth, PyrUpImage) else self._depth

    @property
    def cloud_alpha(self) -> np.ndarray:
        return self._alpha.full() if isinstance(self._alpha, PyrUpImage) else self._alpha

    def depth_window(self, rows: slice, cols: slice) -> np.ndarray:
        return self._depth.window(rows, cols) if isinstance(self._depth, PyrUpImage) else self._depth[rows, cols]

    def alpha_window(self, rows: slice, cols: slice) -> np.ndarray:
        return self._alpha.window(rows, cols) if isinstance(self._alpha, PyrUpImage) else self._alpha[rows, cols]


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
    ):
        s = settings
        # objects whose projected bounding box spans at most this many pixels each way are drawn as an
        # analytic splat (:meth:`_splat`) instead of the ray cast; 0: always the ray cast
        self.splat_max_px = int(splat_max_px)
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
        self._splat_parts = [
            (tuple(c), tuple(h), bool(b), float(L))
            for c, h, b, L in zip(centre.tolist(), half.tolist(), is_box, self._part_L_emit)
        ]
        self._box_idx = np.flatnonzero(is_box)
        self._ell_idx = np.flatnonzero(~is_box)
        self._part_order = np.concatenate([self._box_idx, self._ell_idx])  # the rows of intersect's t_all
        self._box_c, self._box_h = centre[is_box].astype(np.float32), half[is_box].astype(np.float32)
        self._ell_c, self._ell_h = centre[~is_box], half[~is_box].astype(np.float32)
        lo = (centre - half).min(axis=0)
        hi = (centre + half).max(axis=0)
        self._radius_b = float(np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi))))  # bounding sphere, body origin
        self._f_max_px = max(intrinsics.fx_px, intrinsics.fy_px)
        self.bbox_corners_b = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        self._parts = tuple(parts)
        self._splat_table: tuple[np.ndarray, np.ndarray] | None = None  # built at the first splat (~0.1 s)
        self._aperture_kept: dict[tuple[int, int, int, int], np.ndarray] = {}  # see _aperture

    def _visible_fractions(self, parts, n_dirs: int = 256, n_grid: int = 48) -> tuple[np.ndarray, np.ndarray]:
        """For the splat: the fraction of each part's silhouette that is in front of the other parts (the ray
        cast's nearest-part rule), seen from ``n_dirs`` directions (a Fibonacci sphere, body frame), by
        casting a ``n_grid`` x ``n_grid`` grid of nearly parallel rays (from 200 bounding radii) at the
        object and at each part alone.  ``(dirs (n_dirs, 3), fractions (n_dirs, parts))``."""
        k = np.arange(n_dirs) + 0.5
        zc = 1.0 - 2.0 * k / n_dirs
        phi = math.pi * (1.0 + math.sqrt(5.0)) * k
        r = np.sqrt(1.0 - zc * zc)
        dirs = np.stack([r * np.cos(phi), r * np.sin(phi), zc], axis=1)
        frac = np.ones((n_dirs, len(parts)))
        if len(parts) < 2:
            return dirs, frac
        alone = [PartRaster(self.intrinsics, self.settings, (p,), 0.0, 0.0, 1.0) for p in parts]
        R = self._radius_b
        g = ((np.arange(n_grid) + 0.5) / n_grid * 2.0 - 1.0) * R
        for n, d in enumerate(dirs):
            e1 = np.cross(d, (0.0, 0.0, 1.0) if abs(d[2]) < 0.9 else (1.0, 0.0, 0.0))
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(d, e1)
            o = (-200.0 * R * d).astype(np.float32)
            aim = (g[:, None, None] * e1 + g[None, :, None] * e2).reshape(-1, 3)
            d_b = (aim - o).T.astype(np.float32)
            t, part = self.intersect(o, d_b)
            hit = np.isfinite(t)
            seen = np.bincount(part[hit], minlength=len(parts))
            for p, single in enumerate(alone):
                n_alone = int(np.isfinite(single.intersect(o, d_b)[0]).sum())
                frac[n, p] = seen[p] / n_alone if n_alone else 1.0
        return dirs, frac

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
        z = corners_cam[:, 2]
        if z.max() <= NEAR_M:
            return None
        box_uv = None  # the projected bounding box (u0, u1, v0, v1), px, when the ROI is drawn around it
        if z.min() <= NEAR_M:
            i0, i1, j0, j1 = 0, H, 0, W
        else:
            cu, cv = project_in_front(intr, corners_cam, distorted)
            if not distorted:
                box_uv = (float(cu.min()), float(cu.max()), float(cv.min()), float(cv.max()))
            pad = 1 if distorted else 0
            j0 = max(int(math.floor(cu.min())) - pad, 0)
            j1 = min(int(math.ceil(cu.max())) + pad, W)
            i0 = max(int(math.floor(cv.min())) - pad, 0)
            i1 = min(int(math.ceil(cv.max())) + pad, H)
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
        o_b = R_nt.T @ (p_cam - p_t)
        if distorted:
            uu, vv = np.meshgrid(u[c0:c1], v[r0:r1])
            xy = intr.normalized_from_pixel(np.stack([uu, vv], axis=-1)).reshape(-1, 2)
            d_b = R_bc[:, :2] @ xy.T + R_bc[:, 2:3]  # (3, n)
        else:
            x = (u[c0:c1] - intr.cx_px) / intr.fx_px
            y = (v[r0:r1] - intr.cy_px) / intr.fy_px
            d_b = (
                R_bc[:, 0, None, None] * x[None, None, :]
                + (R_bc[:, 1, None] * y[None, :] + R_bc[:, 2, None])[:, :, None]
            )
            d_b = d_b.reshape(3, -1)  # (3, n), row-major over (sub-row, sub-column)
        # float32 ray casting: ~3e-5 m resolution at 300 m, far below the 16 mm thinnest part
        d_b = d_b.astype(np.float32)
        o_b = o_b.astype(np.float32)
        t_near, nearest = self.intersect(o_b, d_b)
        covered = np.isfinite(t_near)
        d_m = p_t - p_cam
        range_km = math.sqrt(d_m.dot(d_m)) * 1e-3  # np.linalg.norm's own sqrt(x . x), without its checks
        tau = math.exp(-s.extinction_per_km * range_km)
        part_grey = ((tau * self._part_L_emit + (1.0 - tau) * self._L_air) - self._L_min) * self._grey_per_L
        if not np.any(covered):
            return None
        # difference to the background per sub-sample (the background of the sub-sample's pixel)
        ref = bg[i0:i1, j0:j1]
        pad = int(math.ceil(3.0 * s.blur_sigma_px + 0.5))  # K reaches half a pixel + 3 sigma
        pi0, pi1 = max(i0 - pad, 0), min(i1 + pad, H)
        pj0, pj1 = max(j0 - pad, 0), min(j1 + pad, W)
        behind = None  # where a surface (a cloud) is nearer than the object, when anywhere in its region
        if occluder is not None:
            range_m = range_km * 1e3
            behind = occluder.depth_window(slice(pi0, pi1), slice(pj0, pj1)) < range_m
            if behind.any():
                ref = np.where(
                    behind[i0 - pi0 : i1 - pi0, j0 - pj0 : j1 - pj0], occluder.base_radiance[i0:i1, j0:j1], ref
                )
            else:
                behind = None  # the usual case: nothing in front, no opacity to read
        # each cast sub-sample minus its pixel's background, 0 where it meets nothing (float64)
        obj = part_grey[nearest].reshape(r1 - r0, c1 - c0)
        obj -= ref.repeat(ss, axis=0)[r0:r1].repeat(ss, axis=1)[:, c0:c1]
        delta = np.zeros((ny * ss, nx * ss))
        np.copyto(delta[r0:r1, c0:c1], obj, where=covered.reshape(r1 - r0, c1 - c0))
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

    def _splat(self, bg, t_c: list[float], R_nc, R_nt, occluder: SceneBackground | None):
        """:meth:`delta` of an object a few pixels across, without the ray cast: its radiance integral and
        its first and second moments on the image, drawn as a separable box x Gaussian spot.

        Each part is projected through the pinhole's Jacobian at its centre (the object is small against
        its range): generators ``A = J R_cam_from_body diag(half)``; the silhouette's area (px^2) is
        ``4 sum |det(a_i, a_j)|`` for a box (the hexagon of a projected cube), ``pi |det(A A^T)|^1/2`` for an
        ellipsoid, its covariance ``A A^T / 3`` or ``/ 4``.  The integral is ``sum_p area_p (L_p - L_bg)``
        (``L_bg`` the background at the centroid's pixel), ``area_p`` times the fraction of it in front of the
        other parts from the nearest tabulated view direction (:meth:`_visible_fractions`: the ray cast's
        nearest-part rule, e.g. a bird's body over its wings).
        Centroid and spread are the ``|area contrast|``-weighted mixture of the parts'; the spread adds
        to the PSF's, the pixel box is kept, so the pixels sum to the integral (within the 3 sigma cut)
        and the intensity centroid is the parts' centroid.  A cloud in front (``occluder``) is read at the
        centroid's pixel only.  Written in scalar arithmetic over the few parts: numpy's per-call cost on
        arrays of 2-4 parts is larger than the arithmetic."""
        intr = self.intrinsics
        s = self.settings
        H, W = self._H, self._W
        R_cb = (R_nc.T @ R_nt).tolist()
        r0, r1, r2 = R_cb
        fx, fy, cx, cy = intr.fx_px, intr.fy_px, intr.cx_px, intr.cy_px
        range_m = math.sqrt(t_c[0] ** 2 + t_c[1] ** 2 + t_c[2] ** 2)
        tau = math.exp(-s.extinction_per_km * range_m * 1e-3)
        # the view direction in the body frame picks the parts' visible fractions (nearest tabulated one)
        if self._splat_table is None:
            self._splat_table = self._visible_fractions(self._parts)
        dirs, fractions = self._splat_table
        view_b = np.dot(R_nt.T, R_nc @ np.array(t_c))
        visible = fractions[int(np.argmax(dirs @ view_b))].tolist()
        parts = []  # (area px^2, contrast-free radiance, u, v, var_u, var_v) per part
        for ((bx, by, bz), (hx, hy, hz), is_box, L_emit), seen in zip(self._splat_parts, visible):
            x = t_c[0] + r0[0] * bx + r0[1] * by + r0[2] * bz
            y = t_c[1] + r1[0] * bx + r1[1] * by + r1[2] * bz
            z = t_c[2] + r2[0] * bx + r2[1] * by + r2[2] * bz
            if z <= NEAR_M:
                return None
            xz, yz = x / z, y / z
            ju = [fx / z * (r0[k] - xz * r2[k]) * h for k, h in enumerate((hx, hy, hz))]
            jv = [fy / z * (r1[k] - yz * r2[k]) * h for k, h in enumerate((hx, hy, hz))]
            c0 = ju[1] * jv[2] - ju[2] * jv[1]
            c1 = ju[2] * jv[0] - ju[0] * jv[2]
            c2 = ju[0] * jv[1] - ju[1] * jv[0]
            if is_box:
                area, mk = 4.0 * (abs(c0) + abs(c1) + abs(c2)), 1.0 / 3.0
            else:
                area, mk = math.pi * math.sqrt(c0 * c0 + c1 * c1 + c2 * c2), 0.25
            area *= seen
            L = ((tau * L_emit + (1.0 - tau) * self._L_air) - self._L_min) * self._grey_per_L
            var_u = mk * (ju[0] ** 2 + ju[1] ** 2 + ju[2] ** 2)
            var_v = mk * (jv[0] ** 2 + jv[1] ** 2 + jv[2] ** 2)
            parts.append((area, L, fx * xz + cx, fy * yz + cy, var_u, var_v))
        # the spot's centre: the parts weighted by |area x contrast| against the background near the
        # object's projected centre (one background read; the weights only place and shape the spot)
        u0 = min(max(int(parts[0][2]), 0), W - 1)
        v0 = min(max(int(parts[0][3]), 0), H - 1)
        ref = float(bg[v0, u0])
        w = [abs(a * (L - ref)) + 1e-30 for a, L, *_ in parts]
        w_sum = sum(w)
        u_c = sum(wk * p[2] for wk, p in zip(w, parts)) / w_sum
        v_c = sum(wk * p[3] for wk, p in zip(w, parts)) / w_sum
        var_u = sum(wk * (p[4] + (p[2] - u_c) ** 2) for wk, p in zip(w, parts)) / w_sum
        var_v = sum(wk * (p[5] + (p[3] - v_c) ** 2) for wk, p in zip(w, parts)) / w_sum
        sig_u = max(math.sqrt(s.blur_sigma_px**2 + var_u), 1e-3)
        sig_v = max(math.sqrt(s.blur_sigma_px**2 + var_v), 1e-3)
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
            if occluder.depth_window(*px)[0, 0] < range_m:
                ref = float(occluder.base_radiance[ic, jc])
                gain = 1.0 - float(occluder.alpha_window(*px)[0, 0])
        energy = gain * sum(a * (L - ref) for a, L, *_ in parts)
        # pixel j spans [j, j + 1]: box x Gaussian weights Phi((j + 1 - u_c) / sig) - Phi((j - u_c) / sig)
        cu = [0.5 * math.erfc((u_c - j) / (math.sqrt(2.0) * sig_u)) for j in range(j0, j1 + 1)]
        cv = [0.5 * math.erfc((v_c - i) / (math.sqrt(2.0) * sig_v)) for i in range(i0, i1 + 1)]
        ku = np.diff(np.array(cu))
        kv = np.diff(np.array(cv)) * energy
        delta = np.multiply.outer(kv, ku).astype(np.float32)
        return slice(i0, i1), slice(j0, j1), delta, 1

    def intersect(self, o_b: np.ndarray, d_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit of rays ``o_b + t d_b`` (body FRD; ``d_b`` shape (3, n)) with the parts.

        Boxes: slab test (Kay & Kajiya 1986): ``t_near = max_k min(t1_k, t2_k)``,
        ``t_far = min_k max(t1_k, t2_k)``, hit when ``t_near <= t_far`` and ``t_far > 0``.
        Ellipsoids: scale to the unit sphere, ``a t^2 + 2 b t + c = 0``, hit when ``b^2 - a c >= 0``
        and the far root is > 0.  A camera inside a part sees it at t = 0.
        Returns ``(t, part)``: the nearest ``t`` per ray (inf: no hit) and that part's index (any part's
        where there is no hit).  Ties go to the boxes before the ellipsoids, each in index order.
        """
        n = d_b.shape[1]
        nb = self._box_idx.size
        # every part's hit distance in one (parts, n) array, boxes first, reduced once at the end (one
        # argmin instead of three calls per part: the arrays are small and the call count per frame high)
        t_all = np.empty((nb + self._ell_idx.size, n), dtype=np.float32)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            if self._box_idx.size:
                inv = np.float32(1.0) / np.where(d_b == 0.0, np.float32(1e-30), d_b)  # (3, n)
                oc = o_b - self._box_c  # (Pb, 3)
                lo = (-self._box_h - oc)[:, :, None] * inv[None]  # (Pb, 3, n)
                hi = (self._box_h - oc)[:, :, None] * inv[None]
                t1 = np.minimum(lo, hi)
                t2 = np.maximum(lo, hi, out=lo)
                t_in = t1.max(axis=1)  # (Pb, n)
                t_out = t2.min(axis=1)
                hit = t_in <= t_out
                hit &= t_out > 0.0
                t = t_all[:nb]
                t.fill(np.inf)
                np.copyto(t, np.maximum(t_in, 0.0, out=t_in), where=hit)
            if self._ell_idx.size:
                oe = ((o_b.astype(float) - self._ell_c) / self._ell_h).astype(np.float32)  # (Pe, 3)
                de = d_b[None] / self._ell_h[:, :, None]  # (Pe, 3, n)
                d0, d1, d2 = de[:, 0], de[:, 1], de[:, 2]
                a = d0 * d0
                a += d1 * d1
                a += d2 * d2
                o0, o1, o2 = oe[:, 0, None], oe[:, 1, None], oe[:, 2, None]
                b = d0 * o0
                b += d1 * o1
                b += d2 * o2
                # b^2 - a c = a - |oe x de|^2 (Lagrange's identity): no cancellation of two ~1e12 terms
                # in float32 when the target is hundreds of metres away (|oe| ~ 2e4 motor radii)
                cx = o1 * d2
                cx -= o2 * d1
                cy = o2 * d0
                cy -= o0 * d2
                cz = o0 * d1
                cz -= o1 * d0
                cx *= cx
                cy *= cy
                cz *= cz
                cx += cy
                cx += cz
                disc = np.subtract(a, cx, out=cx)
                sq = np.sqrt(np.maximum(disc, 0.0, out=cy), out=cy)
                t_out = np.subtract(sq, b, out=cz)
                t_out /= a
                hit = disc >= 0.0
                hit &= t_out > 0.0
                near = np.add(b, sq, out=b)
                np.negative(near, out=near)
                near /= a
                t = t_all[nb:]
                t.fill(np.inf)
                np.copyto(t, np.maximum(near, 0.0, out=near), where=hit)
        # argmin: the first of equal minima, i.e. the order above
        return t_all.min(axis=0), self._part_order.take(t_all.argmin(axis=0))


class IrRenderer:
    """Renders (H, W) thermal frames; see the module docstring for the model and the speed-ups.

    ``render(p_cam_ned_m, R_ned_from_cam, p_target_ned_m, R_ned_from_target_body, altitude_ground_d_m)``
    returns uint8 (mono8) or uint16 (mono16).  ``p_target_ned_m=None`` renders the background only.
    The renderer keeps caches (table, background, noise window); it is not thread-safe.
    """

    def __init__(self, intrinsics: PinholeIntrinsics, settings: IrSettings, seed: int = 0):
        if not isinstance(intrinsics, PinholeIntrinsics):
            raise InputError(f"intrinsics: expected PinholeIntrinsics, got {type(intrinsics).__name__}")
        if not isinstance(settings, IrSettings):
            raise InputError(f"settings: expected IrSettings, got {type(settings).__name__}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise InputError(f"seed: expected an integer, got {seed!r}")
        self.intrinsics = intrinsics
        self.settings = settings
        s = settings
        self._H, self._W = int(intrinsics.height_px), int(intrinsics.width_px)
        self._fs = grey_full_scale(s.encoding)
        self._dtype = cv2.CV_8U if self._fs == 255 else cv2.CV_16U
        L_min = float(band_radiance(s.t_min_k, s.band_um))
        L_max = float(band_radiance(s.t_max_k, s.band_um))
        self._L_min = L_min
        self._grey_per_L = self._fs / (L_max - L_min)
        self._L_air = float(band_radiance(s.air_temperature_k, s.band_um))
        self._rng = np.random.default_rng(int(seed))

        self._init_rays()
        self._init_sky()
        self._init_target()
        self._init_noise()
        self._lut_h_m: float | None = None
        self._lut: np.ndarray | None = None
        self._exact_flags: np.ndarray | None = None
        self._bg: np.ndarray | None = None
        self._bg_row: np.ndarray | None = None
        self._mx = np.empty((self._H, self._W), dtype=np.float32)
        self.last_timing: RenderTiming | None = None

    # ------------------------------------------------------------------ setup

    def _init_rays(self) -> None:
        """Camera-frame rays (x, y, 1) through every pixel centre and their inverse norms (float32)."""
        intr = self.intrinsics
        u = np.arange(self._W) + 0.5
        v = np.arange(self._H) + 0.5
        if intr.has_distortion:
            uu, vv = np.meshgrid(u, v)
            xy = intr.normalized_from_pixel(np.stack([uu, vv], axis=-1))
            self._ray_x = xy[..., 0].astype(np.float32)
            self._ray_y = xy[..., 1].astype(np.float32)
            x2 = xy[..., 0] ** 2
            y2 = xy[..., 1] ** 2
        else:
            x = (u - intr.cx_px) / intr.fx_px
            y = (v - intr.cy_px) / intr.fy_px
            self._ray_x = x.astype(np.float32)  # (W,)
            self._ray_y = y.astype(np.float32)  # (H,)
            x2 = (x**2)[None, :]
            y2 = (y**2)[:, None]
        self._ray_invn = (1.0 / np.sqrt(x2 + y2 + 1.0)).astype(np.float32)
        # coarse grid for the background: one sample per COARSE_STEP x COARSE_STEP block, at the
        # block centre, plus a ring of blocks outside the image, so that cv2.resize(INTER_LINEAR) by
        # COARSE_STEP interpolates (never extrapolates) at every pixel centre
        st = COARSE_STEP
        self._Hc, self._Wc = -(-self._H // st) + 2, -(-self._W // st) + 2
        xc = (st * (np.arange(self._Wc) - 1) + 0.5 * st - intr.cx_px) / intr.fx_px
        yc = (st * (np.arange(self._Hc) - 1) + 0.5 * st - intr.cy_px) / intr.fy_px
        self._coarse_x = xc.astype(np.float32)
        self._coarse_y = yc.astype(np.float32)
        self._coarse_invn = (1.0 / np.sqrt(xc[None, :] ** 2 + yc[:, None] ** 2 + 1.0)).astype(np.float32)
        self._block_di, self._block_dj = (a.astype(np.intp) for a in np.divmod(np.arange(st * st), st))
        self._ray_invn_flat = self._ray_invn.ravel()
        self._coarse_ds = st / min(intr.fx_px, intr.fy_px)  # upper bound of the change of s between samples

    def _init_sky(self) -> None:
        """Static parts of the background table: sky radiance at the table's s and the horizon's edge profile."""
        s = self.settings
        s_k = np.linspace(-1.0, 1.0, LUT_SIZE)
        self._lut_s = s_k
        T_sky = s.sky_horizon_k + (s.sky_zenith_k - s.sky_horizon_k) * np.abs(s_k)
        # L_sky(|s|): sky above, mirrored sky below; Planck on 257 temperatures, then linear in T
        # (0.18 K steps for the default 45 K span: interpolation error ~ L'' dT^2 / 8 < 1e-3 grey)
        T_lo = min(s.sky_horizon_k, s.sky_zenith_k)
        T_grid = np.linspace(T_lo, max(s.sky_horizon_k, s.sky_zenith_k, T_lo + 1.0), 257)
        self._L_sky_abs = np.interp(T_sky, T_grid, band_radiance(T_grid, s.band_um))
        self._L_sky_horizon = float(band_radiance(s.sky_horizon_k, s.band_um))
        self._ground = (
            s.ground_emissivity * float(band_radiance(s.ground_temperature_k, s.band_um)),
            1.0 - s.ground_emissivity,
        )
        # the horizon seen through the pixel aperture and the PSF: a Gaussian of sigma_eff px in
        # elevation applied to the sky/ground step -> weight Phi(el / sigma_el) of the sky side
        sigma_px = math.sqrt(s.blur_sigma_px**2 + 1.0 / 12.0)
        sigma_el = sigma_px / math.sqrt(self.intrinsics.fx_px * self.intrinsics.fy_px)
        self._sky_weight = ndtr(np.arcsin(s_k) / sigma_el)

    def _init_target(self) -> None:
        s = self.settings
        L_env = 0.5 * float(band_radiance(0.5 * (s.sky_zenith_k + s.sky_horizon_k), s.band_um)) + 0.5 * (
            self._ground[0] + self._ground[1] * float(band_radiance(s.sky_horizon_k, s.band_um))
        )
        self.environment_radiance = L_env
        self._target = PartRaster(self.intrinsics, s, s.target_parts, L_env, self._L_min, self._grey_per_L)
        self._target_radiance = PartRaster(self.intrinsics, s, s.target_parts, L_env, 0.0, 1.0)

    def _init_noise(self) -> None:
        s = self.settings
        n = self._H * self._W
        self.noise_sigma_grey = noise_sigma_grey(s)
        if self.noise_sigma_grey > 0.0:
            bank = self._rng.standard_normal(n * s.noise_bank_frames, dtype=np.float32)
            bank *= np.float32(self.noise_sigma_grey)
            self._noise_bank = bank
            self._noise_offsets = n * (s.noise_bank_frames - 1) + 1
        else:
            self._noise_bank = np.zeros(n, dtype=np.float32)
            self._noise_offsets = 1

    # ------------------------------------------------------------------ background

    def background_table(self, height_m: float) -> np.ndarray:
        """Grey values (float32, ``LUT_SIZE`` + guards) over s = sin(elevation) for a camera ``height_m`` above ground.

        ``Phi(el / sigma_el) L_sky(s) + (1 - Phi) L_ground(s)``, each side continued across the
        horizon by its value there: the step smoothed exactly, the smooth parts (which change by
        far less than a grey level over a pixel) unsmoothed.
        """
        s = self.settings
        s_k = self._lut_s
        h = max(float(height_m), 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            range_km = np.where(s_k < 0.0, h / np.maximum(-s_k, 1e-300), 0.0) * 1e-3
        tau = np.exp(-s.extinction_per_km * range_km)
        L_ground = tau * (self._ground[0] + self._ground[1] * self._L_sky_abs) + (1.0 - tau) * self._L_air
        # ground just below the horizon: all air unless the camera is on the ground (h = 0: no air)
        edge = (
            self._L_air
            if (h > 0.0 and s.extinction_per_km > 0.0)
            else self._ground[0] + self._ground[1] * self._L_sky_horizon
        )
        L_ground = np.where(s_k < 0.0, L_ground, edge)
        L_sky = np.where(s_k >= 0.0, self._L_sky_abs, self._L_sky_horizon)
        w = self._sky_weight
        table = ((w * L_sky + (1.0 - w) * L_ground - self._L_min) * self._grey_per_L).astype(np.float32)
        return np.concatenate([np.full(_LUT_PAD, table[0]), table, np.full(_LUT_PAD, table[-1])]).astype(np.float32)

    def _background(self, R_nc: np.ndarray, height_m: float) -> tuple[np.ndarray, bool, bool]:
        rebuilt = False
        h = max(height_m, 0.0)
        if self._lut is None or abs(h - self._lut_h_m) > ALT_REUSE_ABS_M + ALT_REUSE_REL * h:
            self._lut = self.background_table(h)
            self._lut_h_m = h
            self._exact_flags = self._exact_table(self._lut)
            self._bg = None
            rebuilt = True
        row = R_nc[2]
        if self._bg is not None and np.max(np.abs(row - self._bg_row)) <= self.settings.background_reuse_tol_rad:
            return self._bg, True, rebuilt
        if self._ray_x.ndim == 1:
            self._bg = self._background_coarse(row)
        else:
            self._bg = self._background_exact(row)
        self._bg_row = row.copy()
        return self._bg, False, rebuilt

    def _exact_table(self, lut: np.ndarray) -> np.ndarray:
        """uint8 flags over the table: 1 where bilinear interpolation over one coarse step could err by
        more than ``COARSE_TOL_FS`` of full scale, ``|f''(s)| ds(s)^2 / 8`` with ``ds(s)`` the change
        of s over ``COARSE_STEP`` px (``st/f cos(el) + (st/f)^2 / 2``), grown by one coarse step so
        that any coarse cell reaching into a flagged s has a flagged corner."""
        d = 8  # second difference over 8 table entries (0.4 px at the horizon)
        h_s = 2.0 / (LUT_SIZE - 1)
        t = lut.astype(float)
        s_t = (np.arange(t.size) - _LUT_PAD) * h_s - 1.0
        f2 = np.zeros_like(t)
        f2[d:-d] = np.abs(t[2 * d :] - 2.0 * t[d:-d] + t[: -2 * d]) / (d * h_s) ** 2
        step = self._coarse_ds
        ds = step * np.sqrt(np.clip(1.0 - s_t**2, 0.0, 1.0)) + 0.5 * step**2
        bad = (f2 * ds**2 / 8.0 > COARSE_TOL_FS * self._fs).astype(np.uint8)
        grow = int(math.ceil((step + d * h_s) / h_s))
        return cv2.dilate(bad[None, :], np.ones((1, 2 * grow + 1), np.uint8))[0]

    def _background_exact(self, row: np.ndarray) -> np.ndarray:
        """Table look-up at every pixel: index = (s + 1) (N - 1) / 2 + 0.5 + pad, s = -(row . d) / |d|."""
        k = np.float32(-0.5 * (LUT_SIZE - 1))
        off = np.float32(0.5 * (LUT_SIZE - 1) + 0.5 + _LUT_PAD)
        r0, r1, r2 = (np.float32(v) for v in row)
        mx = self._mx
        if self._ray_x.ndim == 1:
            np.add((k * r0 * self._ray_x)[None, :], (k * r1 * self._ray_y + k * r2)[:, None], out=mx)
        else:
            np.multiply(self._ray_x, k * r0, out=mx)
            mx += (k * r1) * self._ray_y
            mx += k * r2
        np.multiply(mx, self._ray_invn, out=mx)
        mx += off
        return self._lut.take(mx.astype(np.int32))

    def _background_coarse(self, row: np.ndarray) -> np.ndarray:
        """Table look-up on the coarse grid, bilinear upsampling, exact look-up in the blocks next to
        coarse samples flagged by ``_exact_table`` (the horizon and the fast-changing ground near it)."""
        k = np.float32(-0.5 * (LUT_SIZE - 1))
        off = np.float32(0.5 * (LUT_SIZE - 1) + 0.5 + _LUT_PAD)
        r0, r1, r2 = (np.float32(v) for v in row)
        idx_c = ((k * r0 * self._coarse_x)[None, :] + (k * r1 * self._coarse_y + k * r2)[:, None]) * self._coarse_invn
        idx_c = (idx_c + off).astype(np.int32)
        grey_c = self._lut.take(idx_c)
        st = COARSE_STEP
        big = cv2.resize(grey_c, (self._Wc * st, self._Hc * st), interpolation=cv2.INTER_LINEAR)
        bg = big[st : st + self._H, st : st + self._W]
        near = self._exact_flags.take(idx_c)
        if not near.any():
            return bg
        near = cv2.dilate(near, np.ones((3, 3), np.uint8))[1:-1, 1:-1]  # image blocks only
        bi, bj = np.nonzero(near)
        ii = (st * bi[:, None] + self._block_di[None, :]).ravel()  # pixel rows and columns of the blocks
        jj = (st * bj[:, None] + self._block_dj[None, :]).ravel()
        if self._H % st or self._W % st:
            keep = (ii < self._H) & (jj < self._W)
            ii, jj = ii[keep], jj[keep]
        m = (k * r0) * self._ray_x.take(jj) + ((k * r1) * self._ray_y.take(ii) + k * r2)
        m *= self._ray_invn_flat.take(ii * self._W + jj)
        m += off
        big.ravel()[(ii + st) * (self._Wc * st) + (jj + st)] = self._lut.take(m.astype(np.int32))
        return bg

    # ------------------------------------------------------------------ frame

    def render(
        self, p_cam_ned_m, R_ned_from_cam, p_target_ned_m, R_ned_from_target_body, altitude_ground_d_m: float = 0.0
    ) -> np.ndarray:
        """One frame, (H, W) uint8 (mono8) or uint16 (mono16).

        ``p_cam_ned_m`` camera optical centre and ``R_ned_from_cam`` its attitude (use
        ``onboard.core.frames.camera_pose_ned`` for the pod mount); ``p_target_ned_m`` the target body
        centre (``None``: no target) and ``R_ned_from_target_body`` its attitude (FRD);
        ``altitude_ground_d_m`` the NED down coordinate of the flat ground.  A camera at or below
        the ground is rendered as if at ground level.  Bad inputs raise InputError naming the field.
        """
        t0 = time.perf_counter()
        p_cam = _vec3(p_cam_ned_m, "p_cam_ned_m")
        R_nc = _rotation(R_ned_from_cam, "R_ned_from_cam")
        try:
            ground_d = float(altitude_ground_d_m)
        except (TypeError, ValueError) as exc:
            raise InputError(f"altitude_ground_d_m: expected a number, got {altitude_ground_d_m!r}") from exc
        if not math.isfinite(ground_d):
            raise InputError(f"altitude_ground_d_m: expected a finite number, got {altitude_ground_d_m!r}")
        if p_target_ned_m is not None:
            p_t = _vec3(p_target_ned_m, "p_target_ned_m")
            R_nt = _rotation(R_ned_from_target_body, "R_ned_from_target_body")
        height_m = ground_d - float(p_cam[2])
        if height_m < 0.0:
            log.debug("camera %.2f m below the ground plane; rendered as at ground level", -height_m)

        bg, reused, rebuilt = self._background(R_nc, height_m)
        t1 = time.perf_counter()
        roi = None
        if p_target_ned_m is not None:
            roi = self._target.delta(bg, p_cam, R_nc, p_t, R_nt)
        t2 = time.perf_counter()

        n = self._H * self._W
        off = int(self._rng.integers(self._noise_offsets))
        noise = self._noise_bank[off : off + n].reshape(self._H, self._W)
        out = cv2.add(bg, noise, dtype=self._dtype)
        if roi is not None:
            rows, cols, delta, ss = roi
            out[rows, cols] = cv2.add(bg[rows, cols] + delta, noise[rows, cols], dtype=self._dtype)
        t3 = time.perf_counter()
        self.last_timing = RenderTiming(
            background_ms=(t1 - t0) * 1e3,
            target_ms=(t2 - t1) * 1e3,
            noise_quantise_ms=(t3 - t2) * 1e3,
            total_ms=(t3 - t0) * 1e3,
            background_reused=reused,
            table_rebuilt=rebuilt,
            target_roi_px=0 if roi is None else int(roi[2].size),
            supersample=0 if roi is None else int(roi[3]),
        )
        return out

    # ------------------------------------------------------------------ scene hook

    def base_radiance(self, p_cam_ned_m, R_ned_from_cam, altitude_ground_d_m: float = 0.0) -> np.ndarray:
        """Today's background (sky gradient, flat ground, horizon through the PSF) as radiance, (H, W) float32.

        The scene content (``groundsim.world.render.scene``) composites clouds and terrain over it.
        Shares the background cache of :meth:`render`.
        """
        p_cam = _vec3(p_cam_ned_m, "p_cam_ned_m")
        R_nc = _rotation(R_ned_from_cam, "R_ned_from_cam")
        bg, _, _ = self._background(R_nc, float(altitude_ground_d_m) - float(p_cam[2]))
        L = bg * np.float32(1.0 / self._grey_per_L)
        L += np.float32(self._L_min)
        return L

    def render_radiance(
        self, p_cam_ned_m, R_ned_from_cam, p_target_ned_m, R_ned_from_target_body, background: SceneBackground
    ) -> tuple[np.ndarray, tuple | None]:
        """The target drawn over ``background`` (a :class:`SceneBackground`), in radiance, no noise.

        Returns ``(radiance (H, W) float32, roi)``; ``roi`` is ``(rows, cols, delta, supersample)`` of the
        target (``delta`` in W m^-2 sr^-1 after PSF and cloud occlusion) or None when it is not in view.
        ``background`` is not modified.
        """
        if not isinstance(background, SceneBackground):
            raise InputError(f"background: expected a SceneBackground, got {type(background).__name__}")
        p_cam = _vec3(p_cam_ned_m, "p_cam_ned_m")
        R_nc = _rotation(R_ned_from_cam, "R_ned_from_cam")
        out = background.radiance.copy()
        roi = None
        if p_target_ned_m is not None:
            p_t = _vec3(p_target_ned_m, "p_target_ned_m")
            R_nt = _rotation(R_ned_from_target_body, "R_ned_from_target_body")
            roi = self._target_radiance.delta(background.radiance, p_cam, R_nc, p_t, R_nt, occluder=background)
            if roi is not None:
                out[roi[0], roi[1]] += roi[2]
        return out, roi

    def quantise(self, radiance) -> np.ndarray:
        """A radiance image through the grey map, NETD noise and rounding: what :meth:`render` outputs.

        Draws the noise window from the same generator as :meth:`render` (one draw per call).
        """
        L = np.asarray(radiance, dtype=np.float32)
        if L.shape != (self._H, self._W):
            raise InputError(f"radiance: expected shape {(self._H, self._W)}, got {L.shape}")
        grey = np.subtract(L, np.float32(self._L_min), out=self._mx)  # scratch: cv2.add below makes the output
        grey *= np.float32(self._grey_per_L)
        n = self._H * self._W
        off = int(self._rng.integers(self._noise_offsets))
        noise = self._noise_bank[off : off + n].reshape(self._H, self._W)
        return cv2.add(grey, noise, dtype=self._dtype)
