"""IR rendering of the ground simulator: Planck band radiometry and the numpy/OpenCV rasteriser.

Public API::

    IrRenderer(intrinsics, settings, seed=0).render(p_cam_ned_m, R_ned_from_cam, p_target_ned_m,
                                                    R_ned_from_target_body, altitude_ground_d_m=0.0)
    truth_pixel(intrinsics, p_cam_ned_m, R_ned_from_cam, p_target_ned_m) -> (u_px, v_px)
    band_radiance(T_k, band_um) -> W m^-2 sr^-1;  grey_from_radiance(L, settings) -> uint8 | uint16

Scene content and the camera model (``docs/scenes.md``): ``scene_config`` (SceneConfig),
``scene.SceneContent``, ``sensor.Sensor``, imported from their modules (textures take a second to build,
so nothing of them is built at import).
"""

from groundsim.world.render.planck import (
    band_exitance,
    band_radiance,
    band_radiance_derivative,
    grey_float_from_radiance,
    grey_from_radiance,
    noise_sigma_grey,
)
from groundsim.world.render.raster import IrRenderer, PartRaster, RenderTiming, SceneBackground, truth_pixel
from groundsim.world.render.settings import IrSettings, TargetPart, default_target_parts

__all__ = [
    "IrRenderer",
    "PartRaster",
    "RenderTiming",
    "SceneBackground",
    "truth_pixel",
    "band_exitance",
    "band_radiance",
    "band_radiance_derivative",
    "grey_float_from_radiance",
    "grey_from_radiance",
    "noise_sigma_grey",
    "IrSettings",
    "TargetPart",
    "default_target_parts",
]
