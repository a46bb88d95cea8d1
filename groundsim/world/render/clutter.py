"""A plain point detector, to measure how much point-like clutter a rendered scene holds.

Pixels above their ``window x window`` local mean by ``k_sigma`` times the temporal noise sigma,
grouped into 8-connected blobs; blobs of at most ``max_blob_px`` pixels count as point-like
detections.  This is the single-frame detector the scenes are meant to defeat (clouds' sun-lit edges,
roofs and roads on the terrain), not a tracker component.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["point_detections", "WINDOW_PX", "K_SIGMA", "MAX_BLOB_PX"]

WINDOW_PX = 15
K_SIGMA = 5.0
MAX_BLOB_PX = 50


def point_detections(
    image, noise_sigma: float, window_px: int = WINDOW_PX, k_sigma: float = K_SIGMA, max_blob_px: int = MAX_BLOB_PX
) -> np.ndarray:
    """Centroids (u_px, v_px), shape (n, 2), of the point-like blobs of ``image`` (any numeric type).

    ``noise_sigma``: the temporal noise, 1 sigma, in the image's units.
    """
    img = np.asarray(image, dtype=np.float32)
    local = cv2.blur(img, (window_px, window_px), borderType=cv2.BORDER_REFLECT)
    mask = ((img - local) > np.float32(k_sigma * noise_sigma)).astype(np.uint8)
    n, _, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    keep = stats[1:, cv2.CC_STAT_AREA] <= max_blob_px
    return centroids[1:][keep] + 0.5  # pixel (i, j) is centred at (j + 0.5, i + 0.5)
