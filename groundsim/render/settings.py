"""Settings of the IR rasteriser: the band, the grey map, the sensor, the scene and the target model.

Temperatures in kelvin, lengths in metres, target parts placed in the target's body FRD frame
(see ``onboard.frames``).  The scenario loader (``groundsim.scenario``) builds these from the
``ir:`` section of a scenario file; defaults are the FLIR Vue Pro 640's band and NETD.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["TargetPart", "IrSettings", "default_target_parts"]


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


def default_target_parts() -> tuple[TargetPart, ...]:
    """A small F450-class quad-rotor, symmetric about its centre in plan view.

    Body plate and arms at 305 K, four motors at the arm tips at 330 K, a battery on the centre
    at 312 K (all painted/plastic, emissivity 0.9; motors anodised metal, 0.8).
    """
    arm = 0.225 / 2 ** 0.5  # 450 mm motor-to-motor diagonal
    parts = [
        TargetPart("body", "box", (0.0, 0.0, 0.0), (0.075, 0.075, 0.02), 305.0, 0.9),
        TargetPart("arm_fr_bl", "box", (0.0, 0.0, 0.0), (0.16, 0.012, 0.008), 303.0, 0.9),
        TargetPart("arm_fl_br", "box", (0.0, 0.0, 0.0), (0.012, 0.16, 0.008), 303.0, 0.9),
        TargetPart("battery", "box", (0.0, 0.0, -0.035), (0.05, 0.02, 0.015), 312.0, 0.9),
    ]
    for i, (sf, sr) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1))):
        parts.append(TargetPart(f"motor{i}", "ellipsoid", (sf * arm, sr * arm, -0.01), (0.014, 0.014, 0.016), 330.0, 0.8))
    return tuple(parts)


@dataclass(frozen=True)
class IrSettings:
    """Radiometry and sensor model of the simulated thermal camera.

    Band radiance by Planck's law over ``band_um``; grey value by the paper's linear map between
    E(t_min_k) and E(t_max_k) to 8 bits (or 16 with ``encoding='mono16'``).
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
