"""The camera intrinsics section that the daemon's config (``camera.intrinsics``) and the scenario files
(``camera.intrinsics``) share: its checks that a given principal point lies inside the image and that the
lens model can be inverted over it, and its
:class:`~onboard.core.frames.PinholeIntrinsics` (a null ``cx_px`` / ``cy_px`` is the image centre).

A mixin of the two pydantic section classes, which declare the fields (their bounds and defaults differ)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from onboard.core.frames import PinholeIntrinsics
from onboard.core.schema import Invalid

__all__ = ["PinholeSection", "MAX_FOV_DEG", "MIN_PIXEL_ASPECT"]

MAX_FOV_DEG = 170.0
MIN_PIXEL_ASPECT = 0.5


class PinholeSection:
    """Needs the fields ``fx_px, fy_px, cx_px, cy_px, width_px, height_px, distortion``."""

    if TYPE_CHECKING:  # declared by each section class (for the type checker only: not dataclass fields here)
        fx_px: float
        fy_px: float
        cx_px: float | None
        cy_px: float | None
        width_px: int
        height_px: int
        distortion: tuple[float, float, float, float, float]

    #: appended to the "expected" text of a principal point outside the image
    CENTRE_EXPECT_SUFFIX = ""

    def __post_init__(self) -> None:
        # a pinhole sees less than 180 deg, and no thermal lens near it; a focal length that wide is a unit slip
        # (metres for pixels); pixels are square within a factor of two on any imager (fx/fy beyond: a typo)
        for name, f, size in (("fx_px", self.fx_px, self.width_px), ("fy_px", self.fy_px, self.height_px)):
            fov_deg = math.degrees(2.0 * math.atan(size / (2.0 * f)))
            if fov_deg > MAX_FOV_DEG:
                raise Invalid(
                    name,
                    f"a focal length giving a field of view under {MAX_FOV_DEG:g} deg (at least "
                    f"{size / (2.0 * math.tan(math.radians(MAX_FOV_DEG / 2.0))):.3g} px for {size} px)",
                    f,
                )
        if not MIN_PIXEL_ASPECT <= self.fx_px / self.fy_px <= 1.0 / MIN_PIXEL_ASPECT:
            raise Invalid(
                "fy_px",
                f"within a factor {1.0 / MIN_PIXEL_ASPECT:g} of fx_px ({self.fx_px:g}): pixels are nearly square",
                self.fy_px,
            )
        for name, size in (("cx_px", self.width_px), ("cy_px", self.height_px)):
            v = getattr(self, name)
            if v is not None and not 0.0 <= v <= size:
                raise Invalid(name, f"a number in [0, {size}] (inside the image){self.CENTRE_EXPECT_SUFFIX}", v)
        if (failure := self.pinhole().undistortion_failure()) is not None:
            raise Invalid(
                "distortion",
                "coefficients (k1, k2, p1, p2, k3) whose lens model can be inverted over the whole image",
                self.distortion,
                hint=f"{failure}: check the calibration's signs and scale (OpenCV's order, normalised coordinates)",
            )

    def pinhole(self) -> PinholeIntrinsics:
        cx = self.width_px / 2.0 if self.cx_px is None else self.cx_px
        cy = self.height_px / 2.0 if self.cy_px is None else self.cy_px
        return PinholeIntrinsics(self.fx_px, self.fy_px, cx, cy, self.width_px, self.height_px, self.distortion)
