"""Settings of the IR rasteriser: the band, the grey map, the sensor, the scene and the target model.

Temperatures in kelvin, lengths in metres, target parts placed in the target's body FRD frame
(see ``onboard.core.frames``).  The scenario loader (``groundsim.world.scenario``) builds these from the
``ir:`` section of a scenario file; defaults are the FLIR Vue Pro 640's band and NETD.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from onboard.core.checks import is_positive_int, require_each
from onboard.core.errors import ConfigError

__all__ = ["TargetPart", "IrSettings", "default_target_parts", "TARGET_SHAPES", "ENCODINGS"]

TARGET_SHAPES = ("ellipsoid", "box")
ENCODINGS = ("mono8", "mono16")


def _finite_tuple(obj, name: str, n: int) -> tuple[float, ...]:
    value = getattr(obj, name)
    try:
        t = tuple(float(v) for v in value)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{type(obj).__name__}.{name}: expected {n} numbers, got {value!r}") from exc
    if len(t) != n or not all(math.isfinite(v) for v in t):
        raise ConfigError(f"{type(obj).__name__}.{name}: expected {n} finite numbers, got {value!r}")
    object.__setattr__(obj, name, t)
    return t


def _finite(obj, name: str, lo: float | None = None, lo_open: bool = False, hi: float | None = None) -> float:
    value = getattr(obj, name)
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{type(obj).__name__}.{name}: expected a number, got {value!r}") from exc
    bad = not math.isfinite(v) or (lo is not None and (v <= lo if lo_open else v < lo)) or (hi is not None and v > hi)
    if bad:
        rng = f"{'(' if lo_open else '['}{lo if lo is not None else '-inf'}, {hi if hi is not None else 'inf'}]"
        raise ConfigError(f"{type(obj).__name__}.{name}: expected a finite number in {rng}, got {value!r}")
    object.__setattr__(obj, name, v)
    return v


@dataclass(frozen=True)
class TargetPart:
    """One part of the target: an ellipsoid or a box, centred at ``center_frd_m`` in the target body.

    ``half_extent_m`` are the semi-axes (ellipsoid) or half side lengths (box) along body F, R, D.
    """

    name: str
    shape: str  # "ellipsoid" | "box"
    center_frd_m: tuple[float, float, float]
    half_extent_m: tuple[float, float, float]
    temperature_k: float
    emissivity: float

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ConfigError(f"TargetPart.name: expected a non-empty string, got {self.name!r}")
        if self.shape not in TARGET_SHAPES:
            raise ConfigError(f"TargetPart({self.name!r}).shape: expected one of {TARGET_SHAPES}, got {self.shape!r}")
        _finite_tuple(self, "center_frd_m", 3)
        if min(_finite_tuple(self, "half_extent_m", 3)) <= 0.0:
            raise ConfigError(
                f"TargetPart({self.name!r}).half_extent_m: every semi-axis must be > 0 m, got {self.half_extent_m!r}"
            )
        _finite(self, "temperature_k", 0.0, lo_open=True)
        _finite(self, "emissivity", 0.0, hi=1.0)


def default_target_parts() -> tuple[TargetPart, ...]:
    """A small F450-class quad-rotor, symmetric about its centre in plan view.

    Body plate and arms at 305 K, four motors at 330 K on the diagonals (450 mm apart), a battery on the
    centre at 312 K (all painted/plastic, emissivity 0.9; motors anodised metal, 0.8).  The parts are boxes
    and ellipsoids along the body axes, so the arms are a "+" of 0.32 m along them rather than the diagonals
    reaching the motors: their plan area 0.015 m^2 against 0.022 m^2 for diagonal arms (the target a little
    dimmer in plan view than a real F450), its shape at a few pixels alike.
    """
    arm = 0.225 / 2**0.5  # 450 mm motor-to-motor diagonal
    parts = [
        TargetPart("body", "box", (0.0, 0.0, 0.0), (0.075, 0.075, 0.02), 305.0, 0.9),
        TargetPart("arm_fr_bl", "box", (0.0, 0.0, 0.0), (0.16, 0.012, 0.008), 303.0, 0.9),
        TargetPart("arm_fl_br", "box", (0.0, 0.0, 0.0), (0.012, 0.16, 0.008), 303.0, 0.9),
        TargetPart("battery", "box", (0.0, 0.0, -0.035), (0.05, 0.02, 0.015), 312.0, 0.9),
    ]
    for i, (sf, sr) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1))):
        parts.append(
            TargetPart(f"motor{i}", "ellipsoid", (sf * arm, sr * arm, -0.01), (0.014, 0.014, 0.016), 330.0, 0.8)
        )
    return tuple(parts)


@dataclass(frozen=True)
class IrSettings:
    """Radiometry and sensor model of the simulated thermal camera.

    Band radiance by Planck's law over ``band_um``; grey value by the paper's linear map between
    E(t_min_k) and E(t_max_k) to 8 bits (or 16 with ``encoding='mono16'``).

    Renderer knobs (added with the rasteriser, ``groundsim.world.render.raster``):
    ``netd_reference_k`` the scene temperature at which ``netd_k`` is quoted (Vue Pro: 30 C);
    ``supersample`` sub-samples per pixel side over the target (8 -> 64 rays per pixel; reduced
    automatically for a target larger than ``max_target_rays`` allows);
    ``background_reuse_tol_rad`` the background image is reused while the camera's tilt (the
    third row of ``R_ned_from_cam``) moved less than this (1e-5 rad ~ 0.008 px at fx = 765 px);
    ``noise_bank_frames`` how many frames of Gaussian noise are drawn once (per-frame noise is a
    random window into that bank).
    """

    band_um: tuple[float, float] = (7.5, 13.5)
    t_min_k: float = 243.15
    t_max_k: float = 323.15
    encoding: str = "mono8"  # "mono8" | "mono16"
    netd_k: float = 0.040  # noise-equivalent temperature difference, 1 sigma, at ~300 K
    blur_sigma_px: float = 0.6  # Gaussian optics PSF
    extinction_per_km: float = 0.15  # atmospheric transmission tau = exp(-extinction * range_km)
    air_temperature_k: float = 288.15  # path radiance temperature
    sky_zenith_k: float = 230.0  # effective sky brightness temperature straight up
    sky_horizon_k: float = 275.0  # ... and at the horizon
    ground_temperature_k: float = 290.0
    ground_emissivity: float = 0.95
    target_parts: tuple[TargetPart, ...] = field(default_factory=default_target_parts)
    netd_reference_k: float = 303.15
    supersample: int = 16
    max_target_rays: int = 8192
    background_reuse_tol_rad: float = 1e-5
    noise_bank_frames: int = 2

    def __post_init__(self) -> None:
        band = _finite_tuple(self, "band_um", 2)
        if not 0.0 < band[0] < band[1]:
            raise ConfigError(f"IrSettings.band_um: expected 0 < lambda1 < lambda2 micrometres, got {self.band_um!r}")
        for name in (
            "t_min_k",
            "t_max_k",
            "air_temperature_k",
            "sky_zenith_k",
            "sky_horizon_k",
            "ground_temperature_k",
            "netd_reference_k",
        ):
            _finite(self, name, 0.0, lo_open=True)
        if not self.t_min_k < self.t_max_k:
            raise ConfigError(f"IrSettings.t_max_k: expected > t_min_k = {self.t_min_k}, got {self.t_max_k}")
        if self.encoding not in ENCODINGS:
            raise ConfigError(f"IrSettings.encoding: expected one of {ENCODINGS}, got {self.encoding!r}")
        for name in ("netd_k", "blur_sigma_px", "extinction_per_km", "background_reuse_tol_rad"):
            _finite(self, name, 0.0)
        _finite(self, "ground_emissivity", 0.0, hi=1.0)
        require_each(
            self,
            ("supersample", "max_target_rays", "noise_bank_frames"),
            is_positive_int,
            ConfigError,
            "IrSettings.{name}: expected an integer >= 1, got {value!r}",
        )
        parts = tuple(self.target_parts)
        if not parts or not all(isinstance(p, TargetPart) for p in parts):
            raise ConfigError("IrSettings.target_parts: expected a non-empty sequence of TargetPart")
        object.__setattr__(self, "target_parts", parts)
