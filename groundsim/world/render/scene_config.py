"""Configuration of the scene content and of the camera model: clouds, terrain, distractors, sensor.

One model per YAML mapping (``docs/scenes.md`` says what each knob does), all models of the one
config system (:mod:`onboard.core.schema`: frozen, strict, ``extra="forbid"``, errors naming the
field).  Every section is off by default, so a scenario without them renders as before, byte for byte.

:func:`scene_config_from_dict` builds a :class:`SceneConfig` from a parsed mapping (``None``: all off)::

    scene_config_from_dict({"clouds": {"enabled": True, "cover_fraction": 0.5}}, source="C1.yaml")

Temperatures in kelvin, lengths in metres, positions in local NED (``onboard.core.frames``), angles in
degrees (config only), rates in Hz.  A ``seed`` in a section is mixed with the run's seed
(:func:`groundsim.world.render.scene.section_rng`), so the same scenario seed gives the same scene.
"""

from __future__ import annotations

import dataclasses
from typing import Annotated, Any, Literal

from onboard.core.schema import (
    Bool,
    Integer,
    Invalid,
    Number,
    Numbers,
    SchemaError,
    Text,
    build,
    config_dataclass,
)

__all__ = [
    "CloudsConfig",
    "TerrainConfig",
    "BirdsConfig",
    "AircraftConfig",
    "GlintConfig",
    "DistractorsConfig",
    "CrossoverConfig",
    "AgcConfig",
    "FpnConfig",
    "FfcConfig",
    "VignettingConfig",
    "SensorConfig",
    "SceneConfig",
    "scene_config_from_dict",
]

# field types of the one config system (a bool is not a number, 640.0 is not an int; every error reads
# "expected <what>"); the bounds are what a real scene holds, far inside what the renderer's arithmetic survives
#: a length or distance at most, m: 1000 km, beyond any scene a camera sees (a cloud feature of 1e300 m made NaN)
MAX_SCENE_LENGTH_M = 1e6
#: a scene speed at most, m/s (Mach 3)
MAX_SCENE_SPEED_MPS = 1000.0
#: a temperature span or spread at most, K
MAX_TEMPERATURE_SPREAD_K = 100.0
NonNegative = Annotated[float, Number(0.0)]
Positive = Annotated[float, Number(0.0, lo_open=True)]
Length = Annotated[float, Number(0.0, MAX_SCENE_LENGTH_M, lo_open=True, unit="m")]
NonNegativeLength = Annotated[float, Number(0.0, MAX_SCENE_LENGTH_M, unit="m")]
#: a temperature of the scene (ground, water, cloud, a bird, an aircraft's skin), K: as the scenario's ir section's
SceneKelvin = Annotated[float, Number(150.0, 400.0, unit="K")]
#: a hot thing's temperature (an engine, a sun glint's brightness temperature), K
HotKelvin = Annotated[float, Number(150.0, 5000.0, unit="K")]
DeltaKelvin = Annotated[float, Number(0.0, MAX_TEMPERATURE_SPREAD_K, unit="K")]
Fraction = Annotated[float, Number(0.0, 1.0)]
Emissivity = Annotated[float, Number(0.0, 1.0, lo_open=True)]
Seed = Annotated[int, Integer(0, 2**63 - 1)]
Vec3 = Annotated[tuple[float, float, float], Numbers(3, -MAX_SCENE_LENGTH_M, hi=MAX_SCENE_LENGTH_M, unit="m")]
VelocityVec3 = Annotated[
    tuple[float, float, float], Numbers(3, -MAX_SCENE_SPEED_MPS, hi=MAX_SCENE_SPEED_MPS, unit="m/s")
]
TexturePx = Annotated[int, Integer(64, 4096)]


def _model(cls=None, /, **kw):
    return config_dataclass(cls, kw_only=True, **kw)


# --------------------------------------------------------------------------- clouds


@_model
class CloudsConfig:
    """A layer of broken cloud: fractal (fBm) density on a horizontal plane ``base_altitude_m`` above the
    ground, ``thickness_m`` thick.  ``cover_fraction`` of the layer has cloud; inside, the vertical
    optical depth is ``optical_depth_per_km * thickness_km`` times the density (0 at the edge, 1 deep
    inside, reached over ``edge_softness`` of the noise's spread), and a slant ray goes through
    ``1 / |sin el|`` times as much.  The cloud radiates at ``brightness_temperature_k``; edges facing the
    sun (``sun_azimuth_deg``, from north through east) are up to ``sun_edge_warming_k`` warmer, and the
    cloud's temperature varies on small scales by ``texture_k`` (1 sigma).
    ``feature_size_m`` is the largest cloud scale, ``texel_m`` the texture's resolution on the plane and
    ``texture_px`` its side (the pattern repeats every ``texel_m * texture_px`` metres)."""

    __off_unless_enabled__ = True  # settings without enabled: refused (onboard.core.schema.build)
    enabled: Bool = False
    base_altitude_m: Length = 1500.0
    thickness_m: Length = 300.0
    cover_fraction: Fraction = 0.5
    brightness_temperature_k: SceneKelvin = 268.0
    sun_edge_warming_k: DeltaKelvin = 6.0
    texture_k: DeltaKelvin = 0.03
    sun_azimuth_deg: Annotated[float, Number(-360.0, 360.0, unit="deg")] = 135.0
    optical_depth_per_km: NonNegative = 30.0
    edge_softness: Annotated[float, Number(0.0, 1.0, lo_open=True)] = 0.6
    feature_size_m: Length = 1500.0
    texel_m: Length = 15.0
    texture_px: TexturePx = 1024
    max_range_m: Length = 30000.0
    seed: Seed = 0

    def __post_init__(self) -> None:
        if self.feature_size_m < 2.0 * self.texel_m:
            raise Invalid("feature_size_m", f"at least two texels ({2.0 * self.texel_m:g} m)", self.feature_size_m)


# --------------------------------------------------------------------------- terrain


@_model
class TerrainConfig:
    """A textured ground plane replacing the flat uniform ground: fields (patches of
    ``field_size_m`` around ``field_temperature_k`` +- ``field_temperature_spread_k``, varying inside by
    ``field_texture_k``), a road grid
    (``road_spacing_m`` apart, ``road_width_m`` wide), ``building_count`` roofs of about
    ``building_size_m`` per tile, a lake of ``lake_radius_m`` (0: none).  Each material has its
    temperature and emissivity; roofs and roads are hot by day, water is cool.  The texture has
    ``texture_px`` texels of ``texel_m`` a side and repeats every ``texel_m * texture_px`` metres.

    ``full_resolution`` (default): the texture looked up at every pixel and blurred by the optics' PSF
    (``ir.blur_sigma_px``), as a camera samples its optical image; false: at every second pixel and taken up
    by ``cv2.pyrUp``, the background ~2.5x cheaper, but aliased (an edge rendered one pixel further on
    differs from the same edge moved by up to ~8 % of the local span, 0.1 % at full resolution, which a
    background difference reads as texture) and smoother at the finest scale than the optics leave it
    (docs/scenes.md, "Terrain sampling")."""

    __off_unless_enabled__ = True  # settings without enabled: refused (onboard.core.schema.build)
    enabled: Bool = False
    full_resolution: Bool = True
    texel_m: Length = 0.5
    texture_px: TexturePx = 2048
    field_temperature_k: SceneKelvin = 296.0
    field_temperature_spread_k: DeltaKelvin = 3.0
    field_size_m: Length = 80.0
    field_texture_k: DeltaKelvin = 0.05
    field_emissivity: Emissivity = 0.95
    road_temperature_k: SceneKelvin = 312.0
    road_width_m: Length = 7.0
    road_spacing_m: Length = 260.0
    road_emissivity: Emissivity = 0.93
    roof_temperature_k: SceneKelvin = 318.0
    building_size_m: Length = 12.0
    building_count: Annotated[int, Integer(0, 100_000)] = 150
    roof_emissivity: Emissivity = 0.90
    water_temperature_k: SceneKelvin = 286.0
    lake_radius_m: NonNegativeLength = 110.0
    water_emissivity: Emissivity = 0.98
    seed: Seed = 0

    def __post_init__(self) -> None:
        tile = self.texel_m * self.texture_px
        if self.field_size_m < 2.0 * self.texel_m:  # a field a texel across is no field; fewer fields bound the grid
            raise Invalid("field_size_m", f"at least two texels ({2.0 * self.texel_m:g} m)", self.field_size_m)
        if self.road_width_m >= self.road_spacing_m:
            raise Invalid("road_width_m", f"less than road_spacing_m ({self.road_spacing_m:g} m)", self.road_width_m)
        if 2.0 * self.lake_radius_m >= tile:
            raise Invalid("lake_radius_m", f"less than half the tile ({tile / 2:g} m)", self.lake_radius_m)


# --------------------------------------------------------------------------- distractors


@_model
class BirdsConfig:
    """``count`` birds: warm bodies (``body_temperature_k``) with wings of ``wingspan_m`` that flap at
    ``flap_hz`` (the wings' seen area goes from full to ``1 - flap_depth`` of it and back), each circling
    at ``speed_mps`` on a circle of 10-60 m radius whose centre is drawn within ``spread_m`` (horizontal)
    and ``spread_m / 4`` (vertical) of ``center_ned_m``."""

    count: Annotated[int, Integer(0, 1000)] = 0
    wingspan_m: Length = 0.6
    body_temperature_k: SceneKelvin = 311.0
    emissivity: Emissivity = 0.95
    flap_hz: NonNegative = 4.0
    flap_depth: Fraction = 0.7
    speed_mps: Annotated[float, Number(0.0, MAX_SCENE_SPEED_MPS, unit="m/s")] = 10.0
    center_ned_m: Vec3 = (150.0, 0.0, -100.0)
    spread_m: NonNegativeLength = 150.0
    seed: Seed = 0


@_model
class AircraftConfig:
    """A distant aircraft flying straight at ``v_ned_mps`` from ``p0_ned_m`` (heading along its
    velocity): a fuselage of ``length_m``, wings of ``span_m`` at ``skin_temperature_k``, engines at
    ``engine_temperature_k``."""

    p0_ned_m: Vec3
    v_ned_mps: VelocityVec3 = (0.0, 60.0, 0.0)
    length_m: Length = 30.0
    span_m: Length = 30.0
    skin_temperature_k: SceneKelvin = 262.0
    engine_temperature_k: HotKelvin = 480.0


@_model
class GlintConfig:
    """Sun glint off water or glass at ``p_ned_m`` (on the ground): a small spot of ``size_m`` at
    ``brightness_temperature_k`` whose intensity flickers at ``flicker_hz`` (waves), between
    ``1 - flicker_depth`` and 1 of its peak."""

    p_ned_m: Vec3
    size_m: Length = 1.5
    brightness_temperature_k: HotKelvin = 420.0
    flicker_hz: NonNegative = 3.0
    flicker_depth: Fraction = 0.8


@_model
class DistractorsConfig:
    """Objects that are not the target: birds, aircraft, glints (each with an object id and a class)."""

    birds: BirdsConfig = dataclasses.field(default_factory=BirdsConfig)
    aircraft: tuple[AircraftConfig, ...] = ()
    glints: tuple[GlintConfig, ...] = ()

    @property
    def count(self) -> int:
        return self.birds.count + len(self.aircraft) + len(self.glints)


# --------------------------------------------------------------------------- thermal crossover


@_model
class CrossoverConfig:
    """Thermal crossover of the target (object 0): its signal over the background it hides (object minus
    background, per pixel) is scaled by a gain that holds 1 until ``start_s``, goes linearly to 0 at
    ``start_s + ramp_s``, holds 0 for ``hold_s`` and goes on to ``end_gain`` (negative: colder than its
    background) over another ``ramp_s``: the target and its background have the same radiance for a
    while, as around dawn and dusk.  Scaling the difference is the same as moving every part's radiance
    towards the background's along the straight line between them."""

    __off_unless_enabled__ = True  # settings without enabled: refused (onboard.core.schema.build)
    enabled: Bool = False
    start_s: NonNegative = 2.0
    ramp_s: Positive = 2.0
    hold_s: NonNegative = 1.0
    end_gain: Annotated[float, Number(-1.0, 1.0)] = -0.5

    def gain(self, t_s: float) -> float:
        """The gain on the target's signal at ``t_s`` (1 when disabled)."""
        if not self.enabled:
            return 1.0
        t = float(t_s) - self.start_s
        if t <= 0.0:
            return 1.0
        if t < self.ramp_s:
            return 1.0 - t / self.ramp_s
        t -= self.ramp_s + self.hold_s
        if t <= 0.0:
            return 0.0
        return self.end_gain * min(t / self.ramp_s, 1.0)


# --------------------------------------------------------------------------- sensor


@_model
class AgcConfig:
    """Automatic gain to 8 bit by plateau equalisation: the histogram of the raw counts, each bin
    clipped at ``plateau_fraction`` of the pixels, accumulated into a map, mixed with a linear
    min-max map by ``linear_fraction``, the slope capped at ``max_gain`` 8-bit levels per count; the
    map follows the scene with time constant ``time_constant_s`` (its frame-to-frame gain changes)."""

    __off_unless_enabled__ = True  # settings without enabled: refused (onboard.core.schema.build)
    enabled: Bool = False
    plateau_fraction: Annotated[float, Number(0.0, 1.0, lo_open=True)] = 0.01
    linear_fraction: Fraction = 0.2
    max_gain: Positive = 2.0
    time_constant_s: NonNegative = 0.3


@_model
class FpnConfig:
    """Fixed-pattern noise in raw counts: per-column offsets (``column_sigma_counts``), per-pixel offsets
    and gains, ``dead_pixels`` stuck at 0 and ``hot_pixels`` stuck at full scale.  The offsets drift
    (the core warms): the pattern grows by ``drift_counts_per_s`` (1 sigma) per second since the last
    flat-field correction, which resets it to ``residual_fraction`` of the static pattern."""

    __off_unless_enabled__ = True  # settings without enabled: refused (onboard.core.schema.build)
    enabled: Bool = False
    column_sigma_counts: NonNegative = 6.0
    pixel_offset_sigma_counts: NonNegative = 4.0
    pixel_gain_sigma: Annotated[float, Number(0.0, 0.5)] = 0.02
    dead_pixels: Annotated[int, Integer(0, 100_000)] = 6
    hot_pixels: Annotated[int, Integer(0, 100_000)] = 6
    drift_counts_per_s: NonNegative = 0.5
    residual_fraction: Fraction = 1.0


@_model
class FfcConfig:
    """Flat-field correction every ``period_s`` (first at ``first_s``): the shutter closes for
    ``frames`` frames, which are ``frozen`` (the last image repeated) or ``dropped`` (no image); after
    it the drifted offsets step back (see :class:`FpnConfig`)."""

    __off_unless_enabled__ = True  # settings without enabled: refused (onboard.core.schema.build)
    enabled: Bool = False
    period_s: Positive = 20.0
    first_s: NonNegative = 20.0
    frames: Annotated[int, Integer(1, 1000)] = 6
    mode: Annotated[Literal["frozen", "dropped"], Text()] = "frozen"


@_model
class VignettingConfig:
    """Signal falling off towards the corners: gain ``1 - (1 - corner_gain) r^2`` with r the distance
    from the principal point over the distance to the farthest corner."""

    __off_unless_enabled__ = True  # settings without enabled: refused (onboard.core.schema.build)
    enabled: Bool = False
    corner_gain: Annotated[float, Number(0.0, 1.0, lo_open=True)] = 0.85


@_model
class SensorConfig:
    """The camera as it behaves: radiance -> raw ``raw_bits`` counts (``counts_at_t_min`` at the band
    radiance of the renderer's ``t_min_k``, ``counts_at_t_max`` at ``t_max_k``, linear in radiance), with
    NETD noise, then fixed-pattern noise, vignetting, flat-field events, and the AGC 8-bit output."""

    __off_unless_enabled__ = True  # settings without enabled: refused (onboard.core.schema.build)
    enabled: Bool = False
    raw_bits: Annotated[int, Integer(8, 16)] = 14
    counts_at_t_min: Annotated[int, Integer(0, 65535)] = 2000
    counts_at_t_max: Annotated[int, Integer(1, 65535)] = 14000
    agc: AgcConfig = dataclasses.field(default_factory=AgcConfig)
    fpn: FpnConfig = dataclasses.field(default_factory=FpnConfig)
    ffc: FfcConfig = dataclasses.field(default_factory=FfcConfig)
    vignetting: VignettingConfig = dataclasses.field(default_factory=VignettingConfig)
    seed: Seed = 0

    def __post_init__(self) -> None:
        full = 2**self.raw_bits - 1
        if self.counts_at_t_max > full:
            raise Invalid("counts_at_t_max", f"at most {full} ({self.raw_bits}-bit counts)", self.counts_at_t_max)
        if self.counts_at_t_min >= self.counts_at_t_max:
            raise Invalid(
                "counts_at_t_min", f"less than counts_at_t_max ({self.counts_at_t_max})", self.counts_at_t_min
            )


# --------------------------------------------------------------------------- the scene


@_model
class SceneConfig:
    """Everything the renderer adds to today's clean sky: ``clouds``, ``terrain``, ``distractors``,
    ``crossover`` (the target's), ``sensor``."""

    clouds: CloudsConfig = dataclasses.field(default_factory=CloudsConfig)
    terrain: TerrainConfig = dataclasses.field(default_factory=TerrainConfig)
    distractors: DistractorsConfig = dataclasses.field(default_factory=DistractorsConfig)
    crossover: CrossoverConfig = dataclasses.field(default_factory=CrossoverConfig)
    sensor: SensorConfig = dataclasses.field(default_factory=SensorConfig)

    @property
    def has_content(self) -> bool:
        """True when anything is drawn beyond today's sky, ground and target, or the target differently."""
        return self.clouds.enabled or self.terrain.enabled or self.distractors.count > 0 or self.crossover.enabled


def scene_config_from_dict(raw: Any, source: Any = "<dict>", error: type[SchemaError] = SchemaError) -> SceneConfig:
    """A :class:`SceneConfig` from a parsed mapping (``None``: all off); a bad value raises ``error``
    naming ``source`` and the dotted field path (``clouds.cover_fraction``)."""
    try:
        return build(SceneConfig, raw)
    except SchemaError as exc:
        raise exc.as_(error, source) from None
