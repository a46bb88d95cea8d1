"""The image chain and the 3-D estimator a configuration asks for, each built fresh: the daemon's pipeline, its
estimator worker process, replay, the lockstep evaluation and the benches build them the same way.  Apart from
:mod:`onboard.pipeline.frame_pipeline` (which re-exports both): building a component is not processing a frame."""

from __future__ import annotations

import math
from typing import Any

__all__ = ["make_estimator", "make_tracker"]


def make_tracker(config: Any):
    """The image chain of ``config``, fresh, in ``gcs.tracker_mode``: an
    :class:`~onboard.imaging.objects_chain.ObjectChain` (``imaging.chain: objects``, the default) or a
    :class:`~onboard.imaging.TargetTracker` (``single``)."""
    from onboard.imaging import TargetTracker

    if config.imaging.chain == "objects":
        from onboard.imaging.objects_chain import ObjectChain

        return ObjectChain(
            config.camera.pinhole(),
            config.imaging,
            mode=config.gcs.tracker_mode,
            attitude_white_sigma_rad=math.radians(config.estimator.attitude_white_sigma_deg),
        )
    return TargetTracker(config.imaging, mode=config.gcs.tracker_mode)


def make_estimator(config: Any):
    """The sliding-window estimator of ``config.estimator`` (None when disabled)."""
    if not config.estimator.enabled:
        return None
    from onboard.estimation.sliding import SlidingWindowEstimator

    return SlidingWindowEstimator(config.estimator.sliding_config(), noise=config.estimator.noise_model())
