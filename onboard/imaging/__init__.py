"""Onboard image chains (pure, no I/O).

The default chain, ``imaging.chain: objects`` (:class:`onboard.imaging.objects_chain.ObjectChain`: clutter
suppression, local-contrast CFAR detection, track-before-detect, every object tracked with an id, the primary
reported as the track), is built by :func:`onboard.pipeline.frame_pipeline.make_tracker`.  The single chain,
``imaging.chain: single``: ``TargetTracker(ImagingParams()).update(frame) -> TrackUpdate`` (pre-processing,
warm-blob detection and KCF tracking of one target); :func:`detect_targets` is its detector on its own.  See the
submodules' docstrings for the maths (preprocess: mean filter, background, double threshold; detect: sub-pixel
centroid; tracker: states and KCF; clutter, objects*, tbd: the objects chain).
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
