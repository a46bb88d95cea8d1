"""The background an object is drawn over, per pixel: radiance, the range to the nearest surface and a
cloud's opacity there (:class:`SceneBackground`), the last two possibly held on a coarse grid
(:class:`PyrUpImage`).  Built by the renderer (``raster.IrRenderer.base_radiance``) and the scene content
(``scene.SceneContent.render_background``); read by the ray caster (``parts.PartRaster``)."""

from __future__ import annotations

import cv2
import numpy as np

from groundsim.world.render.kernels import min_max
from onboard.core.errors import InputError

__all__ = ["PyrUpImage", "SceneBackground"]


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
    ROUNDING = 1e-5  # lower_bound's margin, of the largest magnitude: far above float32 rounding of the sums

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

    def lower_bound(self, rows: slice, cols: slice) -> float:
        """A value no pixel of the window falls below, without taking it up: the least coarse sample it
        depends on (within MARGIN of its own), less ``ROUNDING`` of the largest magnitude there (each
        ``pyrUp`` step's weights are non-negative and sum to 1, so a pixel is a convex combination of those
        samples up to float32 rounding of a few sums).  Exact (the window's minimum) once taken up whole."""
        if self._full is not None:
            return float(self._full[rows, cols].min())
        H, W = self.shape
        i0, i1, _ = rows.indices(H)
        j0, j1, _ = cols.indices(W)
        hc, wc = self.coarse.shape
        m = self.MARGIN
        lo, hi = min_max(
            self.coarse, max(i0 // 4 - m, 0), min(-(-i1 // 4) + m, hc), max(j0 // 4 - m, 0), min(-(-j1 // 4) + m, wc)
        )
        return lo - self.ROUNDING * max(abs(lo), abs(hi))


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

    def nothing_nearer(self, rows: slice, cols: slice, range_m: float) -> bool:
        """True when certainly no pixel of the window has ``depth_m < range_m`` (decided on the coarse grid
        by :meth:`PyrUpImage.lower_bound`, no ``pyrUp``); False when one may have (read the window)."""
        return isinstance(self._depth, PyrUpImage) and self._depth.lower_bound(rows, cols) >= range_m
