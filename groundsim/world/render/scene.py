"""Scene content over the renderer's sky: a cloud layer, textured terrain, distractor objects, their labels.

Public API (the renderer is :class:`~groundsim.world.render.raster.IrRenderer`; the camera model that
turns the radiance into counts is :class:`~groundsim.world.render.sensor.Sensor`)::

    scene = SceneContent.from_config(scene_config, renderer, seed)
    frame = scene.render(t_s, p_cam_ned_m, R_ned_from_cam, p_target_ned_m, R_ned_from_target_body,
                         altitude_ground_d_m)           # SceneFrame(radiance, background, labels)
    image = renderer.quantise(frame.radiance)           # today's grey output (noise, mono8/16) ...
    out = sensor.apply(frame.radiance, t_s, k)          # ... or the camera's counts / AGC mono8

    scene.render_background(p_cam_ned_m, R_ned_from_cam, altitude_ground_d_m)  # SceneBackground
    scene.objects(t_s)                                  # the distractors' poses at t_s (SceneObject)

Frames and units as in ``raster``: local NED, OpenCV camera, radiance in W m^-2 sr^-1.

Background model (per pixel, ray ``d`` from the camera at ``p``)
-----------------------------------------------------------------
``L_base``: the renderer's sky gradient and flat ground (:meth:`IrRenderer.base_radiance`, exact
horizon through the PSF).  Terrain: the ray meets the ground plane ``d = altitude_ground_d_m`` at
range ``r_g``; the texture there (:func:`textures.terrain_texture`, radiance relative to the flat
ground) is seen through the atmosphere: ``L_below = L_base + tau(r_g) dL_terrain``,
``tau(r) = exp(-extinction_per_km r_km)``.  Clouds: the ray meets the cloud plane
``base_altitude_m`` above the ground at range ``r_c`` (only if nearer than the ground and within
``max_range_m``); the cloud's opacity there is ``alpha = 1 - exp(-k h rho / |sin el|)`` (``k``
``optical_depth_per_km``, ``h`` thickness in km, ``rho`` the density texture) and it radiates ``L_c``
(its brightness temperature, sun-lit edges warmer).  The air in front of the cloud radiates like the
clear sky along the same ray (the sky model's effective temperature already holds the path), so::

    L = L_below + alpha s (L_c - L_below),     s = tau(r_c) fade(r_c)

(``fade`` from 1 to 0 over the last fifth of ``max_range_m``): distant clouds sink into the horizon
haze.  ``depth_m`` is ``r_c`` where the ray meets the layer, else ``r_g``, else ``FAR_M``; an object at
range ``R > depth_m`` is seen through ``1 - alpha`` of the cloud, against ``L_below``
(``PartRaster.delta(..., occluder=background)``; ``cloud_alpha`` is 0 where the layer is clear).

How it is fast: the plane intersections (ranges, texture coordinates, atmosphere, mip weights) are
computed on a grid of one ray per 4 x 4 pixels.  The terrain is taken to half resolution by ``cv2.pyrUp``,
its texture looked up there (``cv2.remap``, bilinear, periodic, only in the rows that see the surface)
and one more ``pyrUp`` applies it to the full-resolution ``L_base``.  The cloud layer is looked up and
composited on the 4 x 4 px grid itself and taken to the full resolution by two ``pyrUp`` steps: its
edges are soft over ~4 px (a cloud 0.5-3 km away is smooth over a few metres, and near the camera the
6 m texels are magnified to several pixels anyway), at a quarter of the half-resolution look-ups' cost.
The depth and the cloud opacity stay on the coarse grid (:class:`~groundsim.world.render.background.PyrUpImage`)
and are taken up only around the objects and label pixels that read them, or whole when read whole.
The horizon, the sharpest edge, keeps the renderer's exact treatment.  Mip-mapping: a near level from
the 10th percentile of the pixels' footprint on the surface along the ray (``r^2 / (f h)``), blended
into a level ``FAR_LEVELS`` coarser where the footprint reaches 2 to 8 texels, so that far ground and
far clouds do not alias.

Objects: the target (id 0, class ``target``) and the distractors (ids from 1: birds, aircraft,
glints), each a set of box and ellipsoid parts drawn by the renderer's
:class:`~groundsim.world.render.parts.PartRaster` far to near, each over what is already drawn (a distractor at
most ``SPLAT_MAX_PX`` across, a target at most ``parts.TARGET_SPLAT_MAX_PX``, as an analytic spot with its
radiance integral and moments, not ray cast).
Labels per object and frame: :class:`ObjectLabel`.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from dataclasses import dataclass

import cv2
import numpy as np

from groundsim.world.render.background import PyrUpImage, SceneBackground
from groundsim.world.render.kernels import (
    fold_maps,
    layer_blend,
    layer_light,
    layer_rays,
    layer_weights,
    peak_box,
    plane_rays,
    remap_pair,
    surface_maps,
    terrain_blend,
)
from groundsim.world.render.parts import TARGET_SPLAT_MAX_PX, PartRaster, project_in_front
from groundsim.world.render.planck import band_radiance, band_radiance_derivative
from groundsim.world.render.pyrup_kernels import composite_up, fold_maps_up, terrain_blend_up
from groundsim.world.render.raster import BOX_FRACTION, IrRenderer
from groundsim.world.render.scene_config import SceneConfig
from groundsim.world.render.settings import TargetPart
from groundsim.world.render.textures import cloud_texture, terrain_texture
from onboard.core.errors import InputError

__all__ = [
    "SceneContent",
    "SceneFrame",
    "SceneObject",
    "ObjectLabel",
    "VISIBILITY",
    "section_rng",
    "FAR_M",
]

FAR_M = 1.0e7  # depth of a ray that meets nothing (finite, so that upsampling stays finite)
OCCLUDED_ALPHA = 0.5  # an object whose centre is behind a cloud at least this opaque ...
# ... and whose contrast left through it is below this (NETD) is "occluded": a hot jet behind a thin cloud still
# shows tens of NETD, plainly in the image, and a tracker that follows it must not be scored as a false track
OCCLUDED_MAX_NETD = 3.0
FLAP_PHASES = 8  # a bird's wing span is drawn at one of this many pre-built spans
DISTRACTOR_SUPERSAMPLE = 4  # sub-samples per pixel side for ray-cast distractors (the target keeps the renderer's)
# rays for a splatted distractor's visible fractions, fewer than the target's parts.SPLAT_VISIBILITY_RAYS: a
# bird's radiance integral stays within 2 % of the exact one, its fractions cost ~7 us a frame instead of ~27
DISTRACTOR_VISIBILITY_RAYS = 512
# a distractor whose projected bounding box spans at most this many pixels each way is drawn as an analytic
# spot with its radiance integral and moments (PartRaster._splat), not ray cast: a bird or a distant
# aircraft is a blur-sized blob either way, and the ray cast's fixed cost was most of a crowded frame
SPLAT_MAX_PX = 4
COARSE_STEP = 4  # plane geometry and clouds on a 4 x 4 px grid, terrain at 2 x 2 px: fixed by the pyrUp steps
MAP_LIMIT = 30000.0  # texture coordinates are clamped to +-this many texels (remap holds them in 16 bits)
FAR_LEVELS = 3  # far ground and far clouds are read this many mip levels coarser
SEAM_PAD = 2  # texture look-ups read copies of the textures padded by this many wrapped texels
VISIBILITY = ("visible", "occluded", "out_of_frame")


def section_rng(seed: int, section: str, section_seed: int) -> np.random.Generator:
    """The generator of one scene section: depends on the run's ``seed``, the section's name and its own
    ``seed`` only (adding a section never changes another)."""
    return np.random.default_rng([int(seed), zlib.crc32(section.encode()), int(section_seed)])


@dataclass(frozen=True)
class SceneObject:
    """One object at one instant: ``object_id`` (0: the target), ``cls`` (``target``, ``bird``, ``aircraft``,
    ``glint``), its pose (``p_ned_m`` centre, ``R_ned_from_body`` FRD), the raster of its parts, and
    ``gain`` on its signal (a glint's flicker)."""

    object_id: int
    cls: str
    p_ned_m: np.ndarray
    R_ned_from_body: np.ndarray
    raster: PartRaster
    gain: float = 1.0


@dataclass(frozen=True)
class ObjectLabel:
    """Truth of one object in one frame.

    ``u_px, v_px``: sub-pixel projection of its centre (NaN behind the camera); ``box_px``: ``(x0, y0,
    x1, y1)`` of the pixels whose signal reaches ``BOX_FRACTION`` of its peak (None when not drawn);
    ``visibility``: ``visible``, ``occluded`` (its centre behind a cloud of opacity >= 0.5, or inside
    the box of a nearer object drawn over it) or ``out_of_frame``; ``contrast_netd``: peak |signal -
    local background| over the NETD in radiance (``netd_k * dL/dT(netd_reference_k)``), 0 when not
    drawn; ``range_m``: camera to centre; ``p_ned_m``: the centre in local NED (its 3-D truth); ``warm``:
    the signal at that peak is above the local background (False: below it, or not drawn).  ``contrast_netd``
    is a magnitude, so a target colder than the roof behind it counts as contrast too; a detector that
    looks for warm points sees only the ``warm`` ones.
    """

    object_id: int
    cls: str
    u_px: float
    v_px: float
    box_px: tuple[int, int, int, int] | None
    visibility: str
    contrast_netd: float
    range_m: float
    p_ned_m: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    warm: bool = False


@dataclass(frozen=True)
class SceneFrame:
    """One rendered frame before the sensor: ``radiance`` (H, W) float32 W m^-2 sr^-1 (no noise), the
    ``background`` it was drawn on, and the ``labels`` of every object (target first)."""

    radiance: np.ndarray
    background: SceneBackground
    labels: tuple[ObjectLabel, ...]


def _wrap_padded(levels: list[np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each (n, n) level with its first ``SEAM_PAD`` rows and columns repeated after its last, and the level
    itself as a view into that copy (so the texture is held once)."""
    padded = [np.ascontiguousarray(np.pad(lv, ((0, SEAM_PAD), (0, SEAM_PAD)), mode="wrap")) for lv in levels]
    return padded, [q[:-SEAM_PAD, :-SEAM_PAD] for q in padded]


def _lookup(textures, map_x: np.ndarray, map_y: np.ndarray, rows: slice, scale: np.float32 | None = None):
    """Bilinear, periodic look-ups of ``textures`` (from :func:`_wrap_padded`, equal sides) at (map_x, map_y)
    texels (texel centres at integers), times ``scale`` if given, in ``rows`` only (0 elsewhere: the rows
    that see the surface).  One list of images, one per texture: the coordinates are folded once for all.

    Folded coordinates lie in ``[0, n]``, where the bilinear taps reach texels ``n`` and ``n + 1``: in the
    padded copy those are the wrapped texels ``0`` and ``1``, the same values cv2.remap's BORDER_WRAP
    fetches, but read by its interior path (the per-pixel border path is 1.5-2x slower on the 5-25 % of
    the pixels next to the seam).  Coordinates outside ``[0, n]`` (not expected) take the border path."""
    n = textures[0].shape[0] - SEAM_PAD
    outs = [_zeroed_outside(map_x.shape, rows) for _ in textures]
    if rows.stop > rows.start:
        # scaled and folded into one period [0, n) in one compiled pass: cv2.remap reads texels outside the
        # image through a per-pixel border path several times slower than the inside
        mx, my, inside = fold_maps(map_x, map_y, rows.start, rows.stop, n, np.float32(0.0 if scale is None else scale))
        for texture, out in zip(textures, outs):
            _remap_folded(texture, mx, my, inside, out[rows])
    return outs


def _zeroed_outside(shape: tuple[int, int], rows: slice) -> np.ndarray:
    """A float32 image of ``shape``, 0 outside ``rows``; the look-up writes ``rows`` in place (a whole-frame
    zeros and a copy of the look-up into it cost ~0.1 ms a frame at 640 x 512)."""
    out = np.empty(shape, np.float32)
    out[: rows.start] = 0.0
    out[max(rows.stop, rows.start) :] = 0.0
    return out


def _remap_folded(texture: np.ndarray, mx: np.ndarray, my: np.ndarray, inside: bool, dst=None) -> np.ndarray:
    """``cv2.remap`` (bilinear) of a :func:`_wrap_padded` texture at coordinates folded into its period
    (``inside``: every one within ``[0, n]``, read by the interior path of the padded copy; else the
    unpadded texture through BORDER_WRAP), into ``dst`` if given."""
    n = texture.shape[0] - SEAM_PAD
    src = texture if inside else texture[:n, :n]
    return cv2.remap(src, mx, my, cv2.INTER_LINEAR, dst=dst, borderMode=cv2.BORDER_WRAP)


def _lookup_rows(texture, map_x: np.ndarray, map_y: np.ndarray, rows: slice, scale: np.float32) -> np.ndarray:
    """:func:`_lookup` of one texture over ``rows`` only (non-empty): an image of ``rows``' length, the same
    values as those rows of :func:`_lookup`'s."""
    mx, my, inside = fold_maps(map_x, map_y, rows.start, rows.stop, texture.shape[0] - SEAM_PAD, scale)
    return _remap_folded(texture, mx, my, inside)


def _lookup_up(texture, half_x, half_y, rows: slice, shape: tuple[int, int], scale=None, compact: bool = False):
    """:func:`_lookup` of one texture at the coordinates ``cv2.pyrUp(half_x)``, ``cv2.pyrUp(half_y)`` cropped
    to ``shape`` (half resolution, the last pyrUp step taken as they are folded: ``pyrup_kernels.fold_maps_up``): a
    ``shape`` image, 0 outside ``rows``; ``compact``: ``rows``' (non-empty) look-up alone, as
    :func:`_lookup_rows` gives it."""
    if compact:
        out = dst = np.empty((rows.stop - rows.start, shape[1]), np.float32)
    else:
        out = _zeroed_outside(shape, rows)
        dst = out[rows]
    if rows.stop > rows.start:
        f = np.float32(0.0 if scale is None else scale)
        n = texture.shape[0] - SEAM_PAD
        mx, my, inside = fold_maps_up(half_x, half_y, rows.start, rows.stop, shape[1], n, f)
        _remap_folded(texture, mx, my, inside, dst)
    return out


def _wrap_padded_pair(levels_a: list[np.ndarray], levels_b: list[np.ndarray]) -> tuple[list, list, list]:
    """:func:`_wrap_padded` of two textures looked up together (the cloud layer's density and radiance),
    held interleaved, (n + SEAM_PAD, n + SEAM_PAD, 2) per level, so that a look-up reads both from the same
    cache lines: ``(pairs, levels of a, levels of b)``, the levels views into the pairs."""
    pairs = [
        np.ascontiguousarray(np.stack([np.pad(x, ((0, SEAM_PAD), (0, SEAM_PAD)), mode="wrap") for x in ab], axis=-1))
        for ab in zip(levels_a, levels_b)
    ]
    return pairs, [q[:-SEAM_PAD, :-SEAM_PAD, 0] for q in pairs], [q[:-SEAM_PAD, :-SEAM_PAD, 1] for q in pairs]


def _lookup_pair(pair: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, rows: slice, scale: np.float32 | None = None):
    """:func:`_lookup` of the two textures of ``pair`` (from :func:`_wrap_padded_pair`), the same values:
    ``kernels.remap_pair``, cv2.remap's interior arithmetic on both at once (cv2.remap itself where a folded
    coordinate would leave ``[0, n]``, not expected)."""
    n = pair.shape[0] - SEAM_PAD
    if rows.stop > rows.start:
        mx, my, inside = fold_maps(map_x, map_y, rows.start, rows.stop, n, np.float32(0.0 if scale is None else scale))
        if inside:
            outs = [np.zeros(map_x.shape, np.float32), np.zeros(map_x.shape, np.float32)]
            remap_pair(pair, mx, my, rows.start, *outs)
            return outs
    return _lookup([np.ascontiguousarray(pair[..., c]) for c in (0, 1)], map_x, map_y, rows, scale)


def _half_rows(mask: np.ndarray, limit: int) -> slice:
    """Rows of the half-resolution image that a coarse-grid mask's true rows reach (one coarse row
    spreads over the half-resolution rows 2 k - 1 .. 2 k + 1 through pyrUp)."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return slice(0, 0)
    return slice(max(2 * int(rows[0]) - 2, 0), min(2 * int(rows[-1]) + 3, limit))


def _full_rows(mask: np.ndarray, limit: int) -> slice:
    """Rows of the full-resolution image that a coarse-grid mask's true rows reach through two pyrUp steps
    (:func:`_half_rows` twice: a coarse row ``k`` spreads over the full rows ``4 k - 3 .. 4 k + 3``)."""
    half = _half_rows(mask, 2 * mask.shape[0])
    if half.stop <= half.start:
        return half
    return slice(max(2 * half.start - 2, 0), min(2 * half.stop + 1, limit))


def _quantile(x: np.ndarray, q: float) -> float:
    """The ``q`` quantile (nearest rank) of a 1-D array, 0 when empty (np.partition: no sort)."""
    if x.size == 0:
        return 0.0
    k = min(int(q * x.size), x.size - 1)
    return float(np.partition(x, k)[k])


def _mip_map(foot_m, samples, t, p, dn, de, r0: int, texel_m: float, levels) -> tuple:
    """Where a tiled surface's mip pyramid ``levels`` (level 0's texel ``texel_m``) is read, for the terrain
    and the cloud layer alike: ``(x, y, far weight, near level, far level)``.

    The near level from the 10th percentile of the footprint ``foot_m`` (m) over ``samples`` (the footprints
    of the rays that meet the surface in every third pixel), the far level ``FAR_LEVELS`` coarser; ``x, y``
    the hits ``p + t (dn, de)`` (``dn``, ``de`` from row ``r0``) in texels of the near level, the camera
    placed in the tile (the textures repeat); the far weight 0 to 1 as the footprint goes from 2 to 8 texels
    of the near level (before any mask)."""
    f32 = np.float32
    lv = 0
    if samples.size:
        q = _quantile(samples, 0.1)
        lv = min(max(math.floor(math.log2(max(q / texel_m, 1.0))), 0), len(levels) - 1)  # (np.clip: ~10 us)
    lv_far = min(lv + FAR_LEVELS, len(levels) - 1)
    texel = texel_m * 2**lv
    period = texel * levels[lv].shape[0]
    off_n, off_e = (float(c) - period * math.floor(float(c) / period) for c in (p[0], p[1]))  # camera in the tile
    x, y, w_far = surface_maps(t, dn, de, r0, foot_m, f32(off_e), f32(off_n), f32(1.0 / texel), f32(texel), MAP_LIMIT)
    # w_far = clip((log2(max(foot / texel, 1e-6)) - 1) / 2, 0, 1), numpy's log2 (the compiled one rounds
    # differently), in place
    np.log2(w_far, out=w_far)
    w_far -= f32(1.0)
    w_far *= f32(0.5)
    np.clip(w_far, 0.0, 1.0, out=w_far)
    return x, y, w_far, lv, lv_far


def _rot_z(yaw_rad: float, pitch_rad: float = 0.0) -> np.ndarray:
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    if pitch_rad == 0.0:  # the birds, every frame: Rz @ I is Rz to the bit (each entry one product by 1)
        return Rz
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    return Rz @ Ry


class SceneContent:
    """Clouds, terrain and distractors of one scenario run, deterministic given ``config`` and ``seed``.

    Built once per run (textures take ~1 s); not thread-safe (scratch buffers are reused).
    """

    def __init__(self, config: SceneConfig, renderer: IrRenderer, seed: int = 0):
        if not isinstance(config, SceneConfig):
            raise InputError(f"config: expected a SceneConfig, got {type(config).__name__}")
        if not isinstance(renderer, IrRenderer):
            raise InputError(f"renderer: expected an IrRenderer, got {type(renderer).__name__}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise InputError(f"seed: expected an integer >= 0, got {seed!r}")
        self.config = config
        self.renderer = renderer
        self.seed = int(seed)
        s = renderer.settings
        self.settings = s
        intr = renderer.intrinsics
        self._H, self._W = int(intr.height_px), int(intr.width_px)
        self._distorted = intr.has_distortion  # read per label (the property loops over coefficients)
        self._psf_sigma_px = float(s.blur_sigma_px)  # the optics' PSF, on a full-resolution terrain
        self._L_air = float(band_radiance(s.air_temperature_k, s.band_um))
        self.netd_radiance = float(s.netd_k) * float(band_radiance_derivative(s.netd_reference_k, s.band_um))
        L_sky_mean = float(band_radiance(0.5 * (s.sky_zenith_k + s.sky_horizon_k), s.band_um))
        self._init_rays()
        # the depth of a frame without clouds and terrain, and the opacity of a frame without clouds: the
        # same every frame, so built once and shared read-only (a caller that wrote into them would raise)
        self._far_depth = np.full((self._H, self._W), FAR_M, np.float32)
        self._no_cloud = np.zeros((self._H, self._W), np.float32)
        self._far_depth.flags.writeable = False
        self._no_cloud.flags.writeable = False
        self._empty = np.empty((0, 0), np.float32)  # no far level (kernels.layer_blend)
        # pyrUp scratch of the opacity and the light at half resolution, see render_background
        self._up_half = np.empty((2, 2 * self._hc, 2 * self._wc), np.float32)
        c = config
        self.clouds = (
            cloud_texture(c.clouds, s.band_um, section_rng(seed, "clouds", c.clouds.seed)) if c.clouds.enabled else None
        )
        self.terrain = (
            terrain_texture(
                c.terrain,
                s.band_um,
                s.ground_temperature_k,
                s.ground_emissivity,
                L_sky_mean,
                section_rng(seed, "terrain", c.terrain.seed),
            )
            if c.terrain.enabled
            else None
        )
        # the look-ups read padded copies (see _lookup); the textures' level lists become views into them
        if self.clouds is not None:
            self._cloud_pair_pad, self.clouds.density_levels, self.clouds.radiance_levels = _wrap_padded_pair(
                self.clouds.density_levels, self.clouds.radiance_levels
            )
        if self.terrain is not None:
            self._terrain_pad, self.terrain.levels = _wrap_padded(self.terrain.levels)
        self._terrain_full = bool(c.terrain.full_resolution)
        env = renderer.environment_radiance
        self._target_raster = PartRaster(intr, s, s.target_parts, env, 0.0, 1.0, TARGET_SPLAT_MAX_PX)
        self._distractor_settings = dataclasses.replace(s, supersample=min(s.supersample, DISTRACTOR_SUPERSAMPLE))
        self._init_distractors(env)

    @classmethod
    def from_config(cls, config: SceneConfig, renderer: IrRenderer, seed: int = 0) -> SceneContent:
        return cls(config, renderer, seed)

    # ------------------------------------------------------------------ setup

    def _init_rays(self) -> None:
        """Camera rays (x, y, 1) through the centres of every fourth pixel (pixel ``(4 i, 4 j)``), (Hc, Wc)
        float32, and their norms: two ``cv2.pyrUp`` steps take this grid to the half and the full
        resolution (each puts source sample ``k`` on output sample ``2 k``)."""
        intr = self.renderer.intrinsics
        st = COARSE_STEP
        self._hc, self._wc = -(-self._H // st), -(-self._W // st)
        u = st * np.arange(self._wc) + 0.5
        v = st * np.arange(self._hc) + 0.5
        uu, vv = np.meshgrid(u, v)
        if intr.has_distortion:
            xy = intr.normalized_from_pixel(np.stack([uu, vv], axis=-1))
            x, y = xy[..., 0], xy[..., 1]
        else:
            x = (uu - intr.cx_px) / intr.fx_px
            y = (vv - intr.cy_px) / intr.fy_px
        self._rx = x.astype(np.float32)
        self._ry = y.astype(np.float32)
        self._rnorm = np.sqrt(x * x + y * y + 1.0).astype(np.float32)
        self._f_px = math.sqrt(intr.fx_px * intr.fy_px)

    def _init_distractors(self, env: float) -> None:
        cfg = self.config.distractors
        intr, s = self.renderer.intrinsics, self._distractor_settings
        self._birds: list[tuple] = []
        b = cfg.birds
        if b.count:
            rng = section_rng(self.seed, "birds", b.seed)
            k = b.wingspan_m / 0.6
            self._bird_rasters = []
            for i in range(FLAP_PHASES):
                span = 1.0 - b.flap_depth * i / max(FLAP_PHASES - 1, 1)
                parts = (
                    TargetPart(
                        "body",
                        "ellipsoid",
                        (0.0, 0.0, 0.0),
                        (0.12 * k, 0.035 * k, 0.035 * k),
                        b.body_temperature_k,
                        b.emissivity,
                    ),
                    TargetPart(
                        "wings",
                        "box",
                        (0.01 * k, 0.0, -0.01 * k),
                        (0.05 * k, 0.5 * b.wingspan_m * span, 0.006 * k),
                        b.body_temperature_k - 4.0,
                        b.emissivity,
                    ),
                )
                self._bird_rasters.append(
                    PartRaster(intr, s, parts, env, 0.0, 1.0, SPLAT_MAX_PX, DISTRACTOR_VISIBILITY_RAYS)
                )
            c0 = np.asarray(b.center_ned_m, dtype=float)
            for _ in range(b.count):
                centre = c0 + rng.uniform(-1.0, 1.0, 3) * np.array([b.spread_m, b.spread_m, 0.25 * b.spread_m])
                radius = rng.uniform(10.0, 60.0)
                self._birds.append(
                    (centre, radius, rng.uniform(0, 2 * math.pi), rng.choice((-1.0, 1.0)), rng.uniform(0, 2 * math.pi))
                )
        self._aircraft = []
        for a in cfg.aircraft:
            L = a.length_m
            parts = (
                TargetPart(
                    "fuselage", "ellipsoid", (0.0, 0.0, 0.0), (L / 2, L / 22, L / 22), a.skin_temperature_k, 0.85
                ),
                TargetPart(
                    "wings", "box", (0.0, 0.0, 0.0), (L / 10, a.span_m / 2, L / 120), a.skin_temperature_k, 0.85
                ),
                TargetPart(
                    "engine_l",
                    "ellipsoid",
                    (0.0, -a.span_m / 4, L / 30),
                    (L / 12, L / 40, L / 40),
                    a.engine_temperature_k,
                    0.9,
                ),
                TargetPart(
                    "engine_r",
                    "ellipsoid",
                    (0.0, a.span_m / 4, L / 30),
                    (L / 12, L / 40, L / 40),
                    a.engine_temperature_k,
                    0.9,
                ),
            )
            v = np.asarray(a.v_ned_mps, dtype=float)
            R = _rot_z(math.atan2(v[1], v[0]), math.atan2(-v[2], max(math.hypot(v[0], v[1]), 1e-9)))
            self._aircraft.append(
                (
                    np.asarray(a.p0_ned_m, dtype=float),
                    v,
                    R,
                    PartRaster(intr, s, parts, env, 0.0, 1.0, SPLAT_MAX_PX, DISTRACTOR_VISIBILITY_RAYS),
                )
            )
        self._glints = []
        for i, g in enumerate(cfg.glints):
            part = TargetPart(
                "glint",
                "ellipsoid",
                (0.0, 0.0, 0.0),
                (g.size_m / 2, g.size_m / 2, g.size_m / 20),
                g.brightness_temperature_k,
                1.0,
            )
            phase = section_rng(self.seed, "glints", i).uniform(0, 2 * math.pi)
            self._glints.append(
                (g, phase, PartRaster(intr, s, (part,), env, 0.0, 1.0, SPLAT_MAX_PX, DISTRACTOR_VISIBILITY_RAYS))
            )

    # ------------------------------------------------------------------ objects

    def objects(self, t_s: float, first_id: int = 1) -> tuple[SceneObject, ...]:
        """The distractors at ``t_s`` (ids ``first_id``.. in the order birds, aircraft, glints)."""
        t = float(t_s)
        out = []
        oid = int(first_id)
        b = self.config.distractors.birds
        for centre, radius, phase, direction, flap_phase in self._birds:
            theta = phase + direction * b.speed_mps / radius * t
            p = centre + np.array([radius * math.cos(theta), radius * math.sin(theta), 2.0 * math.sin(0.3 * t + phase)])
            R = _rot_z(theta + direction * math.pi / 2)
            flap = 0.5 * (1.0 - math.cos(2 * math.pi * b.flap_hz * t + flap_phase))  # 0 spread .. 1 folded
            raster = self._bird_rasters[min(int(round(flap * (FLAP_PHASES - 1))), FLAP_PHASES - 1)]
            out.append(SceneObject(oid, "bird", p, R, raster))
            oid += 1
        for p0, v, R, raster in self._aircraft:
            out.append(SceneObject(oid, "aircraft", p0 + v * t, R, raster))
            oid += 1
        for g, phase, raster in self._glints:
            gain = 1.0 - g.flicker_depth * 0.5 * (1.0 - math.cos(2 * math.pi * g.flicker_hz * t + phase))
            out.append(SceneObject(oid, "glint", np.asarray(g.p_ned_m, dtype=float), np.eye(3), raster, gain))
            oid += 1
        return tuple(out)

    def target_object(self, p_target_ned_m, R_ned_from_target_body, t_s: float = 0.0) -> SceneObject:
        """The renderer's target as scene object 0 (its signal scaled by the ``crossover`` gain at ``t_s``)."""
        return SceneObject(
            0,
            "target",
            np.asarray(p_target_ned_m, float),
            np.asarray(R_ned_from_target_body, float),
            self._target_raster,
            self.config.crossover.gain(t_s),
        )

    def target_raster(self, parts) -> PartRaster:
        """A ray caster of another target made of ``parts`` (``TargetPart``), drawn like the renderer's target
        (same supersampling, the splat when unresolved), for :meth:`render`'s ``others``."""
        return PartRaster(
            self.renderer.intrinsics,
            self.settings,
            tuple(parts),
            self.renderer.environment_radiance,
            0.0,
            1.0,
            TARGET_SPLAT_MAX_PX,
        )

    # ------------------------------------------------------------------ background

    def render_background(self, p_cam_ned_m, R_ned_from_cam, altitude_ground_d_m: float = 0.0) -> SceneBackground:
        """The background with clouds and terrain (see the module docstring); today's when both are off."""
        return self._background(p_cam_ned_m, R_ned_from_cam, altitude_ground_d_m, False)[0]

    def background_and_copy(
        self, p_cam_ned_m, R_ned_from_cam, altitude_ground_d_m: float = 0.0
    ) -> tuple[SceneBackground, np.ndarray]:
        """:meth:`render_background` and a copy of its radiance, written in the same pass where the last pass
        makes the radiance (the sky's or the cloud composite's): the image :meth:`draw_objects` draws on."""
        bg, copy = self._background(p_cam_ned_m, R_ned_from_cam, altitude_ground_d_m, True)
        return bg, copy if copy is not None else bg.radiance.copy()

    def _background(self, p_cam_ned_m, R_ned_from_cam, altitude_ground_d_m, want_copy: bool):
        """``(SceneBackground, a copy of its radiance or None)``: None when ``want_copy`` is False or when no
        pass of this frame makes one cheaply (the caller copies)."""
        if self.clouds is None and self.terrain is None:
            if want_copy:
                base, copy = self.renderer.base_radiance_and_copy(p_cam_ned_m, R_ned_from_cam, altitude_ground_d_m)
                return SceneBackground(base, base, self._far_depth, self._no_cloud), copy
            base = self.renderer.base_radiance(p_cam_ned_m, R_ned_from_cam, altitude_ground_d_m)
            return SceneBackground(base, base, self._far_depth, self._no_cloud), None
        base = self.renderer.base_radiance(p_cam_ned_m, R_ned_from_cam, altitude_ground_d_m)
        p = np.asarray(p_cam_ned_m, dtype=float)
        R = np.asarray(R_ned_from_cam, dtype=float)
        f32 = np.float32
        # ---- plane geometry on the coarse grid (one compiled pass: the numpy formulation's float32 operations)
        ext_per_m = self.settings.extinction_per_km * 1e-3
        ground_d = float(altitude_ground_d_m)
        h_g = ground_d - float(p[2])  # camera height above the ground
        dn, de, dd, inv_dd, t_g, r_g, on_ground, dir_rows = plane_rays(R, self._rx, self._ry, self._rnorm, h_g, FAR_M)
        chans = [r_g]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            terrain = self._terrain_geometry(p, dn, de, t_g, r_g, on_ground, h_g, ext_per_m) if self.terrain else None
            band = self._cloud_band(p, dir_rows, ground_d) if self.clouds else slice(0, 0)
            clouds = None
            if band.stop > band.start:
                clouds = self._cloud_geometry(p, dn, de, inv_dd, r_g, band, ground_d, ext_per_m)
        if clouds is not None:
            chans[0] = r_g.copy()  # depth: the cloud layer where the ray meets it
            chans[0][band] = clouds[2]
        up = cv2.pyrUp
        depth = PyrUpImage(chans[0], (self._H, self._W))
        # ---- textures and compositing weights at half resolution (the terrain at full, unless asked otherwise)
        b_t = None
        H, W = self._H, self._W
        full = self._terrain_full
        if terrain is not None:
            lv, lv_far = terrain[1], terrain[2]
            levels = self._terrain_pad
            if full:
                rows, far_rows = _full_rows(terrain[3], H), _full_rows(terrain[4], H)
            else:
                # rows wholly at the far level skip the near one
                rows, far_rows = _half_rows(terrain[3], 2 * self._hc), _half_rows(terrain[4], 2 * self._hc)
            blend = lv_far != lv and far_rows.stop > far_rows.start
            # the far weight is taken up only when a far level is blended in (~40 % of C2's frames have none)
            halves = [up(c) if k < 3 or blend else self._empty for k, c in enumerate(terrain[0])]
            far_scale = f32(2.0 ** (lv - lv_far))
            hx, hy, tau, w_far = halves  # w_far is read on the far rows only (empty: there are none)
            if full:
                # the second pyrUp step of the coordinates, the transmission and the far weight is taken where
                # they are read (pyrup_kernels.fold_maps_up, terrain_blend_up: the same values without four
                # full-resolution images written and read back)
                dL = _lookup_up(levels[lv], hx, hy, rows, (H, W))
                far = _lookup_up(levels[lv_far], hx, hy, far_rows, (H, W), far_scale, True) if blend else self._empty
                blend_into = terrain_blend_up
            else:
                (dL,) = _lookup((levels[lv],), hx, hy, rows)
                far = _lookup_rows(levels[lv_far], hx, hy, far_rows, far_scale) if blend else self._empty
                blend_into = terrain_blend
            b_t = np.empty_like(dL)
            blend_into(dL, far, far_rows.start if blend else 0, w_far, tau, b_t)
            if full and self._psf_sigma_px > 0.0:
                # the optics' PSF, as a camera's sampling of its optical image has it (see TerrainConfig)
                b_t = cv2.GaussianBlur(b_t, (0, 0), self._psf_sigma_px, borderType=cv2.BORDER_REPLICATE)
        below = base if b_t is None else base + (b_t if full else up(b_t)[:H, :W])
        if clouds is None:
            # no cloud layer, or none of its plane in view: a copy, as a composite would be
            return SceneBackground(below if self.clouds is None else below.copy(), below, depth, self._no_cloud), None
        # ---- the cloud layer on the coarse grid itself: its look-ups and compositing weights at one ray per
        # 4 x 4 px, two pyrUp steps to the full resolution (the layer is smooth over 4 px at the mip level
        # read there, see _cloud_geometry; near the camera the texture is magnified far more than that)
        cx, cy, optical, seen, w_far = clouds[0]
        lv, lv_far = clouds[3], clouds[4]
        rows = clouds[6]  # rows wholly at the far level skip the near one
        pairs = self._cloud_pair_pad
        rho, L_c = _lookup_pair(pairs[lv], cx, cy, rows)
        far_rows = clouds[5]
        rho_far = L_c_far = self._empty
        if lv_far != lv and far_rows.stop > far_rows.start:
            rho_far, L_c_far = _lookup_pair(pairs[lv_far], cx, cy, far_rows, f32(2.0 ** (lv - lv_far)))
        # rho, L_c += w_far (far - near); alpha = 1 - exp(-(optical rho)) (numpy's exp: the compiled one
        # rounds differently), a_seen = alpha seen, lit = a_seen L_c, written into the buffers they consume
        alpha = layer_blend(rho, L_c, rho_far, L_c_far, w_far, optical)
        np.exp(alpha, out=alpha)
        layer_light(alpha, seen, L_c)
        a_seen, lit = seen, L_c
        # L = L_below + a_seen (L_c - L_below) = L_below (1 - a_seen) + a_seen L_c, each weight upsampled
        # (the two weights go up to half resolution through scratch buffers: fresh images per frame cost
        # page faults), over the band's pixel rows only: the others depend only on coarse rows where the
        # weights are 0 (a pixel two pyrUp steps up depends on the coarse rows within 2 of its own), L =
        # L_below there
        n = band.stop - band.start
        e0 = 0 if band.start == 0 else 4 * (band.start + 2)
        e1 = H if band.stop == self._hc else min(4 * (band.stop - 2), H)
        w0 = e0 - 4 * band.start  # row e0 in the band's upsampled images
        radiance = np.empty_like(below)
        copy = np.empty_like(below) if want_copy else self._empty
        a_half = up(a_seen, dst=self._up_half[0, : 2 * n])
        lit_half = up(lit, dst=self._up_half[1, : 2 * n])
        # the second pyrUp step of both weights inside the composite, (below - a below) + lit, one pass
        composite_up(below, a_half, lit_half, e0, e1, w0, radiance, copy)
        alpha_whole = np.zeros((self._hc, self._wc), np.float32)
        alpha_whole[band] = alpha
        return SceneBackground(radiance, below, depth, PyrUpImage(alpha_whole, (H, W))), (copy if want_copy else None)

    def _cloud_band(self, p, dir_rows, ground_d: float) -> slice:
        """The coarse rows the cloud geometry is computed on: those whose rays can meet the layer (pointing
        up to a layer above the camera, down to one below: ``dir_rows`` from ``kernels.plane_rays``), grown
        by 4 rows each way (the two pyrUp steps read 2; the band's first row a multiple of 3, as _mip_map's
        every-third-sample quantile reads).  Outside them the layer is not hit: no opacity, depth to the
        ground, the same as computed whole."""
        h_c = ground_d - self.config.clouds.base_altitude_m - float(p[2])  # layer below the camera: > 0
        if h_c == 0.0:
            return slice(0, 0)
        first, last = (int(dir_rows[0]), int(dir_rows[1])) if h_c > 0.0 else (int(dir_rows[2]), int(dir_rows[3]))
        if first < 0:
            return slice(0, 0)
        start = max(first - 4, 0)
        return slice(start - start % 3, min(last + 5, self._hc))

    def _terrain_geometry(self, p, dn, de, t_g, r_g, on_ground, h_g, ext_per_m):
        """Coarse-grid channels ``[x, y (texels of the near level), tau(r_g), far weight]`` and the two mip levels.

        Near level from the 10th percentile of a ground pixel's footprint along the ray's azimuth,
        ``r / f / sin(grazing) = r^2 / (f h)``; the far level ``FAR_LEVELS`` coarser, blended in where the
        footprint is 2 to 8 texels of the near level."""
        f32 = np.float32
        tex = self.terrain
        foot_m = r_g * r_g / f32(self._f_px * max(h_g, 1e-3))
        t = np.where(on_ground, t_g, f32(0.0))
        samples = foot_m[::3, ::3][on_ground[::3, ::3]]
        gx, gy, w_far, lv, lv_far = _mip_map(foot_m, samples, t, p, dn, de, 0, tex.texel_m, tex.levels)
        tau = np.where(on_ground, np.exp(f32(-ext_per_m) * r_g), f32(0.0))
        return [gx, gy, tau, w_far], lv, lv_far, on_ground & (w_far < 1.0), w_far > 0.0

    def _cloud_geometry(self, p, dn, de, inv_dd, r_g, band, ground_d, ext_per_m):
        """Coarse-grid channels ``[x, y (texels of the near level), optical depth per unit density, how much
        is seen, far weight]`` over the coarse rows ``band``, the hit mask, the depth (the range to the layer
        where hit, else the ground's), the near and far mip levels (chosen as for the terrain), and the rows
        where the far level and the near level are read (slices of the band's rows).

        ``seen = tau(r_c) * fade``: the cloud's radiance replaces the background by ``alpha seen``, the
        atmosphere in front of it radiating like the clear sky along that ray (far clouds fade into the
        horizon haze); ``fade`` goes from 1 to 0 over the last fifth of ``max_range_m``.  Compiled passes
        (``kernels.layer_rays``, ``surface_maps``, ``layer_weights``) around numpy's log2 and exp."""
        f32 = np.float32
        cfg = self.config.clouds
        tex = self.clouds
        h_c = ground_d - cfg.base_altitude_m - float(p[2])  # layer below the camera: > 0
        # the footprint of one coarse-grid sample (COARSE_STEP px, the layer is looked up there): a pixel's
        # r^2 / (f h) times the samples' spacing in half-resolution pixels, where the mip thresholds hold
        foot_scale = self._f_px * max(abs(h_c), 1e-3)
        t, r_c, hit, foot_m, samples = layer_rays(
            h_c, inv_dd, self._rnorm, r_g, band.start, band.stop, cfg.max_range_m, foot_scale
        )
        cx, cy, w_far, lv, lv_far = _mip_map(foot_m, samples, t, p, dn, de, band.start, tex.texel_m, tex.density_levels)
        attenuation = np.exp(np.multiply(r_c, f32(-ext_per_m), out=t), out=t)  # t is spent
        tau_v = f32(cfg.optical_depth_per_km * cfg.thickness_m * 1e-3)
        w_far, optical, seen, depth, rows = layer_weights(
            hit, w_far, attenuation, r_c, r_g, self._rnorm, inv_dd, band.start, tau_v, cfg.max_range_m,
            0.2 * cfg.max_range_m,
        )  # fmt: skip
        near_rows = slice(int(rows[0]), int(rows[1]) + 1) if rows[0] >= 0 else slice(0, 0)
        far_rows = slice(int(rows[2]), int(rows[3]) + 1) if rows[2] >= 0 else slice(0, 0)
        return [cx, cy, optical, seen, w_far], hit, depth, lv, lv_far, far_rows, near_rows

    # ------------------------------------------------------------------ objects on the image

    def draw_objects(
        self,
        radiance: np.ndarray,
        background: SceneBackground,
        objects,
        p_cam_ned_m,
        R_ned_from_cam,
        out: np.ndarray | None = None,
    ) -> tuple[np.ndarray, tuple[ObjectLabel, ...]]:
        """``objects`` (SceneObject) drawn far to near on a copy of ``radiance`` (``out``: that copy, made by
        the caller, e.g. :meth:`background_and_copy`, and drawn on in place); labels in the given order."""
        p_cam = np.asarray(p_cam_ned_m, dtype=float)
        R_nc = np.asarray(R_ned_from_cam, dtype=float)
        if out is None:
            out = np.array(radiance, dtype=np.float32, copy=True)
        elif out.shape != np.shape(radiance) or out.dtype != np.float32:
            raise InputError(
                f"out: expected a float32 image of shape {np.shape(radiance)}, got {out.dtype} {out.shape}"
            )
        offsets = [o.p_ned_m - p_cam for o in objects]
        ranges = [math.sqrt(d.dot(d)) for d in offsets]  # np.linalg.norm's own sqrt(x . x), without its checks
        labels: dict[int, ObjectLabel] = {}
        for k in sorted(range(len(objects)), key=lambda i: -ranges[i]):
            o = objects[k]
            roi = o.raster.delta(out, p_cam, R_nc, o.p_ned_m, o.R_ned_from_body, occluder=background)
            if roi is not None:
                rows, cols, delta, _ = roi
                if o.gain != 1.0:
                    delta = delta * np.float32(o.gain)
                out[rows, cols] += delta
            labels[k] = self._label(o, roi, ranges[k], background, p_cam, R_nc)
        return out, _occluded_by_nearer(tuple(labels[k] for k in range(len(objects))))

    def _label(self, o: SceneObject, roi, range_m: float, background, p_cam, R_nc) -> ObjectLabel:
        intr = self.renderer.intrinsics
        p_ned = tuple(o.p_ned_m.tolist())
        p_c = R_nc.T @ (o.p_ned_m - p_cam)
        if p_c[2] <= 0.0:
            return ObjectLabel(o.object_id, o.cls, math.nan, math.nan, None, "out_of_frame", 0.0, range_m, p_ned)
        u, v = (float(c) for c in project_in_front(intr, p_c, self._distorted))
        box, contrast, warm = None, 0.0, False
        if roi is not None:
            rows, cols, delta, _ = roi
            # the peak of |delta gain|, its sign and the box of the values at least BOX_FRACTION of it, one
            # compiled pass
            peak, i0, i1, j0, j1, warm = peak_box(delta, float(o.gain), BOX_FRACTION)
            if peak > 0.0:
                box = (cols.start + j0, rows.start + i0, cols.start + j1, rows.start + i1)
                contrast = peak / self.netd_radiance if self.netd_radiance > 0.0 else math.inf
        if not (0.0 <= u < self._W and 0.0 <= v < self._H):
            return ObjectLabel(o.object_id, o.cls, u, v, box, "out_of_frame", contrast, range_m, p_ned, bool(warm))
        i, j = int(v), int(u)
        px = slice(i, i + 1), slice(j, j + 1)
        behind = (
            not background.nothing_nearer(*px, range_m)
            and background.depth_window(*px)[0, 0] < range_m
            and background.alpha_window(*px)[0, 0] >= OCCLUDED_ALPHA
            and contrast < OCCLUDED_MAX_NETD
        )
        vis = "occluded" if behind else "visible"
        return ObjectLabel(o.object_id, o.cls, u, v, box, vis, contrast, range_m, p_ned, bool(warm))

    # ------------------------------------------------------------------ a frame

    def render(
        self,
        t_s,
        p_cam_ned_m,
        R_ned_from_cam,
        p_target_ned_m,
        R_ned_from_target_body,
        altitude_ground_d_m=0.0,
        others=(),
    ) -> SceneFrame:
        """Background, target (``p_target_ned_m=None``: none), ``others`` (more targets: SceneObjects with
        ids 1..n, rasters from :meth:`target_raster`) and the distractors (ids after them) at ``t_s``."""
        bg, out = self.background_and_copy(p_cam_ned_m, R_ned_from_cam, altitude_ground_d_m)
        others = tuple(others)
        objs = self.objects(t_s, 1 + max((o.object_id for o in others), default=0))
        objs = (*others, *objs)
        if p_target_ned_m is not None:
            objs = (self.target_object(p_target_ned_m, R_ned_from_target_body, t_s), *objs)
        radiance, labels = self.draw_objects(bg.radiance, bg, objs, p_cam_ned_m, R_ned_from_cam, out)
        return SceneFrame(radiance, bg, labels)


def _occluded_by_nearer(labels: tuple[ObjectLabel, ...]) -> tuple[ObjectLabel, ...]:
    """Labels with ``visible`` turned ``occluded`` where the object's centre pixel lies in the box of a
    nearer object (drawn over it: the image shows the nearer one there)."""
    out = []
    for lab in labels:
        if lab.visibility == "visible":
            i, j = math.floor(lab.v_px), math.floor(lab.u_px)
            for o in labels:
                if o.box_px is not None and o.range_m < lab.range_m and o.contrast_netd > 0.0:
                    x0, y0, x1, y1 = o.box_px
                    if x0 <= j < x1 and y0 <= i < y1:
                        lab = dataclasses.replace(lab, visibility="occluded")
                        break
        out.append(lab)
    return tuple(out)
