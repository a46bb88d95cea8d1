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
  A target whose bounding sphere spans at most ``parts.TARGET_SPLAT_MAX_PX`` (2 px) is not ray cast but drawn
  as the analytic splat (``PartRaster._splat``): on a fixed sub-sample grid the radiance integral of a target
  whose thinnest parts are narrower than a sub-sample follows its sub-pixel position, the splat's does not
  (its parts' projected areas, times the fractions of them in front of the others along the view).
* Noise: one bank of standard-normal samples (``noise_bank_frames`` frames long, scaled to grey
  levels) drawn once; each frame reads a contiguous window at a random offset (deterministic from
  ``seed``): no per-frame normal draw.  ``cv2.add(..., dtype=CV_8U/16U)`` fuses the noise addition,
  rounding and saturation in one pass.  The price: two frames' noise fields are one field shifted (by
  hundreds of pixels: the offsets' difference), not independent; a whole-frame registration of two flat-sky
  frames finds that shift (phase correlation's peak 0.34 against 0.03 for independent noise).  The image
  chain's local registrations (33 px squares within a few pixels) cannot see it; its background motion
  (phase correlation of 4x smaller whole frames, used over texture, whose own peak is far stronger than
  the averaged noise's) has not been measured against independent noise.

Results depend only on the call sequence and ``seed`` (the reuse tolerances are far below a pixel).

Hook for scene content (``groundsim.world.render.scene``, ``docs/scenes.md``)
----------------------------------------------------------------------------
:meth:`IrRenderer.base_radiance` gives the background above as radiance (no noise);
:class:`SceneBackground` is a background with clouds and terrain composited over it, per pixel with the
range to the nearest surface and the opacity of a cloud there; :meth:`IrRenderer.render_radiance`
draws the target over one (behind a nearer cloud it is seen through ``1 - alpha``), and
:meth:`IrRenderer.quantise` turns radiance into :meth:`render`'s output (grey map, NETD noise,
rounding).  :class:`~groundsim.world.render.parts.PartRaster` (module ``parts``) is the target's ray
caster as a class of its own, so that other objects (distractors) are drawn the same way;
:class:`~groundsim.world.render.background.SceneBackground` lives in ``background``.  :meth:`render` itself is unchanged.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.special import ndtr

from groundsim.world.render.background import PyrUpImage, SceneBackground
from groundsim.world.render.kernels import (
    peak_box,
    quantise_grey,
    scale_offset,
    scale_offset_window,
    scale_offset_window_twice,
    table_lookup_blocks,
    table_lookup_coarse,
)
from groundsim.world.render.parts import TARGET_SPLAT_MAX_PX, PartRaster, project_in_front
from groundsim.world.render.planck import band_radiance, grey_full_scale, noise_sigma_grey
from groundsim.world.render.settings import IrSettings
from onboard.core.errors import InputError
from onboard.core.frames import PinholeIntrinsics

BOX_FRACTION = 0.1  # an object's box: pixels whose |signal| is at least this fraction of its peak

__all__ = [
    "IrRenderer",
    "RenderTiming",
    # the ray caster and the background it draws over live in ``parts`` and ``background``; kept
    # importable from here, where the renderer's hook names them
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
    if a.shape != (3, 3):
        raise InputError(f"{name}: expected a finite 3x3 rotation matrix, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(
            f"{name}: expected a finite 3x3 rotation matrix, got {np.count_nonzero(~np.isfinite(a))} of 9 entries not finite"
        )
    if np.max(np.abs(a.T @ a - np.eye(3))) > ROT_TOL or np.linalg.det(a) < 0.0:
        raise InputError(f"{name}: not a proper rotation (R^T R != I within {ROT_TOL} or det < 0)")
    return a


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
        self._bg_big: np.ndarray | None = None  # the upsampled image _bg is the window (COARSE_STEP, COARSE_STEP) of
        self._bg_row: np.ndarray | None = None
        self._mx = np.empty((self._H, self._W), dtype=np.float32)
        self.last_timing: RenderTiming | None = None
        # the last frame's target as drawn: (x0, y0, x1, y1) of the pixels holding >= BOX_FRACTION of its peak
        # signal (ends exclusive; None when not drawn), the box a detector's can match (a far target's body
        # projects to under a pixel, its blur to a few)
        self.last_target_box_px: tuple[int, int, int, int] | None = None

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
        # ray cast when resolved, the splat (energy-exact) when at most TARGET_SPLAT_MAX_PX across
        self._target = PartRaster(
            self.intrinsics, s, s.target_parts, L_env, self._L_min, self._grey_per_L, TARGET_SPLAT_MAX_PX
        )
        self._target_radiance = PartRaster(self.intrinsics, s, s.target_parts, L_env, 0.0, 1.0, TARGET_SPLAT_MAX_PX)

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
            self._bg_big = self._background_upsampled(row)
            self._bg = self._bg_big[COARSE_STEP : COARSE_STEP + self._H, COARSE_STEP : COARSE_STEP + self._W]
        else:
            self._bg_big = None
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
        st = COARSE_STEP
        return self._background_upsampled(row)[st : st + self._H, st : st + self._W]

    def _background_upsampled(self, row: np.ndarray) -> np.ndarray:
        """:meth:`_background_coarse` with its ring of ``COARSE_STEP`` px: the image it is the window of."""
        k = np.float32(-0.5 * (LUT_SIZE - 1))
        off = np.float32(0.5 * (LUT_SIZE - 1) + 0.5 + _LUT_PAD)
        r0, r1, r2 = (np.float32(v) for v in row)
        # one compiled pass each (``kernels``): the same float32 operations as the numpy formulation
        # (``_background_exact``), without its index arrays over the horizon's blocks
        grey_c, near, any_near = table_lookup_coarse(
            k * r0, k * r1, k * r2, off, self._coarse_x, self._coarse_y, self._coarse_invn, self._lut, self._exact_flags
        )
        st = COARSE_STEP
        big = cv2.resize(grey_c, (self._Wc * st, self._Hc * st), interpolation=cv2.INTER_LINEAR)
        if any_near:
            table_lookup_blocks(
                near, k * r0, k * r1, k * r2, off, self._ray_x, self._ray_y, self._ray_invn, self._lut, st, big
            )
        return big

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
        self.last_target_box_px = None
        if p_target_ned_m is not None:
            roi = self._target.delta(bg, p_cam, R_nc, p_t, R_nt)
        if roi is not None:
            peak, i0, i1, j0, j1, _ = peak_box(roi[2], 1.0, BOX_FRACTION)
            if peak > 0.0:
                rows, cols = roi[0], roi[1]
                self.last_target_box_px = (cols.start + j0, rows.start + i0, cols.start + j1, rows.start + i1)
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
        a, b = np.float32(1.0 / self._grey_per_L), np.float32(self._L_min)
        if self._bg_big is not None:  # bg is a window of it: read in place, row-contiguous (see the kernel)
            return scale_offset_window(self._bg_big, COARSE_STEP, COARSE_STEP, self._H, self._W, a, b)
        return scale_offset(bg, a, b)

    def base_radiance_and_copy(
        self, p_cam_ned_m, R_ned_from_cam, altitude_ground_d_m: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`base_radiance` and a copy of it made in the same pass (an image to draw objects on)."""
        p_cam = _vec3(p_cam_ned_m, "p_cam_ned_m")
        R_nc = _rotation(R_ned_from_cam, "R_ned_from_cam")
        bg, _, _ = self._background(R_nc, float(altitude_ground_d_m) - float(p_cam[2]))
        a, b = np.float32(1.0 / self._grey_per_L), np.float32(self._L_min)
        if self._bg_big is not None:
            return scale_offset_window_twice(self._bg_big, COARSE_STEP, COARSE_STEP, self._H, self._W, a, b)
        radiance = scale_offset(bg, a, b)
        return radiance, radiance.copy()

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
        n = self._H * self._W
        off = int(self._rng.integers(self._noise_offsets))
        noise = self._noise_bank[off : off + n].reshape(self._H, self._W)
        out = np.empty((self._H, self._W), np.uint8 if self._fs == 255 else np.uint16)
        # one pass: the grey map, then cv2.add(grey, noise, dtype)'s rounding and saturation (render's)
        quantise_grey(
            np.ascontiguousarray(L), np.float32(self._L_min), np.float32(self._grey_per_L), noise, self._fs, out
        )
        return out
