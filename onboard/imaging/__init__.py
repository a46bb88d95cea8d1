"""Onboard image chain: pre-processing, warm-blob detection and KCF tracking (pure, no I/O).

``TargetTracker(ImagingParams()).update(frame) -> TrackUpdate`` is the whole chain for one
frame; :func:`detect_targets` is the detector on its own.  See the submodules' docstrings for the
maths (preprocess: mean filter, background, double threshold; detect: sub-pixel centroid;
tracker: states and KCF).
"""

from onboard.imaging.detect import Blob, Detection, detect_targets, find_blobs, measure_blob
from onboard.imaging.preprocess import ImagingParams, Preprocessed, Region, check_frame, preprocess_frame
from onboard.imaging.tracker import TargetTracker, TrackState, TrackUpdate

__all__ = [
    "ImagingParams",
    "Region",
    "Preprocessed",
    "check_frame",
    "preprocess_frame",
    "Blob",
    "Detection",
    "detect_targets",
    "find_blobs",
    "measure_blob",
    "TrackState",
    "TrackUpdate",
    "TargetTracker",
]
