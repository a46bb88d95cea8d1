"""Procedural textures of the scene content: fractal noise, the cloud layer, the thermal terrain.

All textures are periodic (they tile the plane without seams) and deterministic given a
``numpy.random.Generator``.  Rows run north, columns east: texel ``(i, j)`` covers
``north in [i, i + 1) texel_m``, ``east in [j, j + 1) texel_m``.

Fractal noise (fBm) by spectral synthesis (Voss; Ebert et al., *Texturing and Modeling*, 3rd ed.,
ch. 16): white Gaussian noise filtered in the Fourier domain by an amplitude ``f^(-beta/2)`` for
frequencies above ``1 / feature_px`` and flat below, so that the largest structures are about
``feature_px`` texels; normalised to zero mean and unit variance.  ``beta = 3.6`` gives the
ragged, self-similar edges of cumulus fields (cloud fields' power spectra fall off with exponents
near 5/3 in one dimension, i.e. ~3.7 in two; Cahalan & Snider 1989).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from groundsim.world.render.planck import band_radiance
from groundsim.world.render.scene_config import CloudsConfig, TerrainConfig

__all__ = ["fbm", "mip_levels", "radiance_table", "CloudTexture", "cloud_texture", "TerrainTexture", "terrain_texture"]

T_TABLE_K = (150.0, 700.0)  # band radiance is tabulated over these temperatures (then linear interpolation)
T_TABLE_N = 2201  # 0.25 K steps: interpolation error < 1e-4 of the radiance
CLOUD_BETA = 3.6
MIP_LEVELS = 5  # terrain texture at texel_m * 2^k, k < MIP_LEVELS


def fbm(n: int, feature_px: float, rng: np.random.Generator, beta: float = CLOUD_BETA) -> np.ndarray:
    """Periodic fractal noise, (n, n) float32, zero mean, unit standard deviation."""
    white = rng.standard_normal((n, n))
    fy = np.fft.fftfreq(n)[:, None]
    fx = np.fft.rfftfreq(n)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f = np.maximum(f, 1.0 / max(feature_px, 1.0))
    field = np.fft.irfft2(np.fft.rfft2(white) * f ** (-beta / 2.0), s=(n, n))
    field -= field.mean()
    field /= field.std()
    return field.astype(np.float32)


def radiance_table(band_um) -> tuple[np.ndarray, np.ndarray]:
    """``(T_k, L)`` for :func:`numpy.interp`: band radiance on a fine temperature grid."""
    T = np.linspace(*T_TABLE_K, T_TABLE_N)
    return T, band_radiance(T, band_um)


def mip_levels(image: np.ndarray) -> list[np.ndarray]:
    """``image`` and its 2 x 2 averages down to 16 texels (at most ``MIP_LEVELS``), so far surfaces are not aliased."""
    levels = [image]
    while len(levels) < MIP_LEVELS and levels[-1].shape[0] >= 32:
        levels.append(cv2.resize(levels[-1], None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA))
    return levels


class CloudTexture:
    """The cloud layer's texture: ``density`` in [0, 1] and the cloud's band radiance ``radiance``
    (W m^-2 sr^-1, sun-lit edges warmer), both (n, n) float32, ``texel_m`` a side; ``density_levels``
    and ``radiance_levels`` their mip levels (level k at ``texel_m * 2^k``)."""

    def __init__(self, density: np.ndarray, radiance: np.ndarray, texel_m: float):
        self.density = density
        self.radiance = radiance
        self.texel_m = float(texel_m)
        self.density_levels = mip_levels(density)
        self.radiance_levels = mip_levels(radiance)


def cloud_texture(cfg: CloudsConfig, band_um, rng: np.random.Generator) -> CloudTexture:
    """Density: fBm thresholded at its ``1 - cover_fraction`` quantile, ramped to 1 over ``edge_softness``
    standard deviations (smoothstep).  Temperature: ``brightness_temperature_k`` plus, on edges whose
    density falls towards the sun, up to ``sun_edge_warming_k`` (scaled by the edge's steepness and its
    thinness), plus fine-scale variation of ``texture_k`` (1 sigma)."""
    n = cfg.texture_px
    noise = fbm(n, cfg.feature_size_m / cfg.texel_m, rng)
    if cfg.cover_fraction <= 0.0:
        density = np.zeros((n, n), np.float32)
    else:
        thr = float(np.quantile(noise, 1.0 - cfg.cover_fraction)) if cfg.cover_fraction < 1.0 else -np.inf
        x = np.clip((noise - thr) / cfg.edge_softness, 0.0, 1.0)
        density = (x * x * (3.0 - 2.0 * x)).astype(np.float32)
    # density gradient per texel (periodic central differences), sun direction in (north, east)
    g_n = 0.5 * (np.roll(density, -1, axis=0) - np.roll(density, 1, axis=0))
    g_e = 0.5 * (np.roll(density, -1, axis=1) - np.roll(density, 1, axis=1))
    az = math.radians(cfg.sun_azimuth_deg)
    toward_sun = -(g_n * math.cos(az) + g_e * math.sin(az))  # > 0 where density falls towards the sun
    scale = float(np.quantile(toward_sun[toward_sun > 0.0], 0.95)) if np.any(toward_sun > 0.0) else 1.0
    lit = np.clip(toward_sun / max(scale, 1e-12), 0.0, 1.0) * (1.0 - 0.5 * density)
    fine = fbm(n, 8.0, rng, beta=2.0)
    T = cfg.brightness_temperature_k + cfg.sun_edge_warming_k * lit + cfg.texture_k * fine
    T_tab, L_tab = radiance_table(band_um)
    radiance = np.interp(np.clip(T, *T_TABLE_K), T_tab, L_tab).astype(np.float32)
    return CloudTexture(density, radiance, cfg.texel_m)


class TerrainTexture:
    """The ground's texture as radiance *relative to today's flat ground* (W m^-2 sr^-1 at the ground,
    before the atmosphere), one (n / 2^k, n / 2^k) float32 image per mip level k at ``texel_m * 2^k``;
    ``material`` (n, n) uint8: 0 field, 1 road, 2 roof, 3 water (for tests and pictures)."""

    MATERIALS = ("field", "road", "roof", "water")

    def __init__(self, levels: list[np.ndarray], texel_m: float, material: np.ndarray, temperature_k: np.ndarray):
        self.levels = levels
        self.texel_m = float(texel_m)
        self.material = material
        self.temperature_k = temperature_k


def _periodic_distance(a: np.ndarray, b: float, period: float) -> np.ndarray:
    d = np.abs(a - b) % period
    return np.minimum(d, period - d)


def terrain_texture(
    cfg: TerrainConfig,
    band_um,
    ground_temperature_k: float,
    ground_emissivity: float,
    L_sky_reflected: float,
    rng: np.random.Generator,
) -> TerrainTexture:
    """Fields (a jittered grid of patches at random temperatures with fBm variation), a road grid, roofs
    near the roads and a lake, as the radiance difference to the flat ground of the renderer::

        dL = eps_m L(T_m) + (1 - eps_m) L_sky - (eps_g L(T_g) + (1 - eps_g) L_sky)

    ``L_sky`` the sky radiance the ground reflects (one value: the mean sky).  Mip levels by 2 x 2
    averaging (cv2.pyrDown), so far ground is not aliased."""
    n = cfg.texture_px
    tile = n * cfg.texel_m
    c = (np.arange(n) + 0.5) * cfg.texel_m  # texel centres, m
    north, east = c[:, None], c[None, :]
    # fields: columns of patches, each column shifted north by a random amount
    n_cols = max(1, round(tile / cfg.field_size_m))
    size = tile / n_cols
    col = np.floor(east / size).astype(int) % n_cols
    shift = rng.uniform(0.0, size, n_cols)
    aspect = rng.uniform(0.6, 1.6, n_cols)
    n_rows = np.maximum(1, np.round(tile / (size * aspect))).astype(int)
    row_len = tile / n_rows
    row = np.floor(((north + shift[col]) % tile) / row_len[col]).astype(int)
    field_T = rng.normal(0.0, cfg.field_temperature_spread_k, (n_cols, int(n_rows.max()) + 1))
    T = cfg.field_temperature_k + field_T[col, row] + cfg.field_texture_k * fbm(n, 32.0, rng, 3.5)
    material = np.zeros((n, n), np.uint8)
    # roads: a grid, spacing adjusted to divide the tile, each line offset at random
    n_roads = max(1, round(tile / cfg.road_spacing_m))
    spacing = tile / n_roads
    road_e = rng.uniform(0.0, spacing) + spacing * np.arange(n_roads)
    road_n = rng.uniform(0.0, spacing) + spacing * np.arange(n_roads)
    half_w = 0.5 * cfg.road_width_m
    on_road = np.zeros((n, n), bool)
    for x in road_e:
        on_road |= _periodic_distance(east, x, tile) <= half_w
    for y in road_n:
        on_road |= _periodic_distance(north, y, tile) <= half_w
    # roofs: rectangles beside the roads
    roof_mask = np.zeros((n, n), np.uint8)
    for _ in range(cfg.building_count):
        along = rng.uniform(0.0, tile)
        side = rng.choice((-1.0, 1.0)) * (half_w + rng.uniform(4.0, 30.0))
        a = cfg.building_size_m * rng.uniform(0.6, 1.5)
        b = cfg.building_size_m * rng.uniform(0.6, 1.5)
        if rng.random() < 0.5:  # along a north-south road
            cy, cx = along, road_e[rng.integers(n_roads)] + side + np.sign(side) * a / 2
        else:
            cy, cx = road_n[rng.integers(n_roads)] + side + np.sign(side) * b / 2, along
        j0, j1 = (int(round(v / cfg.texel_m)) for v in (cx - a / 2, cx + a / 2))
        i0, i1 = (int(round(v / cfg.texel_m)) for v in (cy - b / 2, cy + b / 2))
        for di in (-n, 0, n):  # periodic: the copies that reach into the tile
            for dj in (-n, 0, n):
                cv2.rectangle(roof_mask, (j0 + dj, i0 + di), (j1 - 1 + dj, i1 - 1 + di), 1, thickness=-1)
    on_roof = roof_mask.astype(bool)
    # lake: a disc with a fractal shore
    on_water = np.zeros((n, n), bool)
    if cfg.lake_radius_m > 0.0:
        ly, lx = rng.uniform(0.0, tile, 2)
        r = np.hypot(_periodic_distance(east, lx, tile), _periodic_distance(north, ly, tile))
        shore = cfg.lake_radius_m * (1.0 + 0.15 * fbm(n, cfg.lake_radius_m / cfg.texel_m, rng))
        on_water = r <= shore
    material[on_road] = 1
    material[on_roof & ~on_road] = 2
    material[on_water] = 3
    T = np.where(material == 1, cfg.road_temperature_k, T)
    T = np.where(material == 2, cfg.roof_temperature_k, T)
    T = np.where(material == 3, cfg.water_temperature_k, T)
    eps = np.array([cfg.field_emissivity, cfg.road_emissivity, cfg.roof_emissivity, cfg.water_emissivity])[material]
    T_tab, L_tab = radiance_table(band_um)
    L_mat = eps * np.interp(np.clip(T, *T_TABLE_K), T_tab, L_tab) + (1.0 - eps) * L_sky_reflected
    L_flat = (
        ground_emissivity * float(band_radiance(ground_temperature_k, band_um))
        + (1.0 - ground_emissivity) * L_sky_reflected
    )
    dL = np.pad((L_mat - L_flat).astype(np.float32), 3, mode="wrap")  # periodic anti-alias blur
    dL = np.ascontiguousarray(cv2.GaussianBlur(dL, (0, 0), 0.5)[3:-3, 3:-3])
    return TerrainTexture(mip_levels(dL), cfg.texel_m, material, T.astype(np.float32))
