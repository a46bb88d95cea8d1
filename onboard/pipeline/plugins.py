"""Plug-in algorithms: the protocols a detector, a tracker and a trajectory estimator implement, and their discovery.

Anyone's algorithm runs in irtrack's lockstep evaluation (``groundsim eval --estimator NAME``, ``--tracker NAME``)
and campaigns without a change to irtrack: write a class against the protocol below and either

* register it as an entry point of your own package (``pyproject.toml``)::

      [project.entry-points."irtrack.estimators"]
      my_ekf = "my_package.filters:MyEkf"

  groups :data:`GROUPS`: ``irtrack.detectors``, ``irtrack.trackers``, ``irtrack.estimators``; or
* name it on the command line as ``module:Attribute`` (the module importable from ``sys.path``).

:func:`load_factory` resolves a name (an entry point first, then ``module:Attribute``) to a
*factory* ``factory(config) -> instance`` where ``config`` is the daemon's
:class:`onboard.app.config.OnboardConfig` (camera, noise model, estimator settings): a class with a
``from_config(config)`` classmethod is built with it, any other class or function is called with
``config`` if it takes one argument, with nothing otherwise.  irtrack's own algorithms are registered
the same way in its ``pyproject.toml`` (estimators ``map``: the sliding-window MAP estimator; ``paper``: the
paper's closed form over the same window; ``rpekf``: a range-parameterised EKF bank in
:mod:`groundsim.evaluation.baselines.rpekf`, written only against this module; trackers ``objects`` and
``single``: the daemon's two image chains, whatever the configuration's ``imaging.chain`` says).

Protocols (structural: no base class to inherit; ``isinstance`` checks work for the method names):

:class:`TrajectoryEstimator` -- the step interface :class:`onboard.pipeline.frame_pipeline.FramePipeline` drives,
one call per frame, in time order:

* ``add(t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam) -> estimate | None``: a measured target
  centroid ``uv_px`` (2,) in the pixel convention of :mod:`onboard.core.frames` (pixel (i, j) centred at
  (j + 0.5, i + 0.5)), the frame's :class:`~onboard.core.frames.PinholeIntrinsics`, the camera centre
  ``p_cam_ned_m`` (3,) in local NED metres and ``q_ned_from_cam`` (4,) (w, x, y, z; OpenCV camera) at
  capture time ``t_s`` (seconds, monotonic);
* ``predict(t_s, p_cam_ned_m=None) -> estimate | None``: no measurement this frame (coasting);
* ``reset()``: forget everything (new track, clock reset).

An *estimate* is any object with the attributes of :class:`EstimateFields` (the reference is
:class:`onboard.estimation.sliding.TrackEstimate`): ``t_s``, ``p_ned_m`` (3,), ``v_ned_mps`` (3,),
``cov_p_ned_m2`` (3, 3), ``cov_v_ned_m2ps2`` (3, 3), ``observable`` (bool: the range is known well
enough to publish), ``range_m``, ``range_sigma_ratio``, ``window_frames``, ``model`` (str).  An
estimate with a field missing or of another type or shape, a non-finite position, velocity, position covariance
or range, or a covariance that is not symmetric positive semi-definite is not published (counted
``estimator_output_invalid``).  ``None`` = no estimate yet.  An estimator that raises is logged and the frame goes
on without 3-D.

:class:`Tracker` -- ``update(pixels) -> TrackUpdate`` (:class:`onboard.imaging.TrackUpdate`): one IR
frame (H, W) uint8/uint16 in, the target's centre, box and track state out.  Only a ``TrackUpdate`` with
``measurement_valid`` (a :class:`onboard.imaging.Detection` and its centre) reaches the estimator: the centre of a
coasting box has no bearing worth reconstructing, and a measured centre must lie on the frame (0 <= u <= W,
0 <= v <= H; off it, the frame is refused as ``tracker_output_invalid``, as is any answer the pipeline cannot read:
:func:`onboard.pipeline.answer_checks.tracker_problem`).  A tracker whose class says ``uses_pose = True`` is called
``update(pixels, rotation, time_boot_us)`` instead, ``rotation()`` returning the frame's ``R_ned_from_cam`` (3, 3)
(or None without a pose): the objects chain registers frames with it.  ``reset()``, when it has one, is called when
the pipeline restarts (a clock reset).  ``groundsim eval --tracker NAME`` runs it in the daemon's pipeline in
place of the configuration's chain; its track is scored as the selected target's (Pd, HOTA and the 3-D tables).

:class:`Detector` -- ``detect(pixels) -> sequence of Detection`` (:class:`onboard.imaging.Detection`
or any object with ``u_px``, ``v_px``, ``bbox``): candidate targets in one frame, no memory.
Detectors are discovered and loaded by the same functions; the lockstep evaluation plugs in estimators
(``--estimator``) and trackers (``--tracker``); a detector alone has no track to score, and is not wired into it.
"""

from __future__ import annotations

import importlib
import inspect
import logging
from collections.abc import Callable, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

from onboard.core.errors import ConfigError

__all__ = [
    "GROUPS",
    "ESTIMATORS",
    "DETECTORS",
    "TRACKERS",
    "EstimateFields",
    "TrajectoryEstimator",
    "Tracker",
    "Detector",
    "available",
    "load_factory",
    "build",
    "make_map_estimator",
    "make_objects_tracker",
    "make_single_tracker",
]

log = logging.getLogger(__name__)

ESTIMATORS = "irtrack.estimators"
TRACKERS = "irtrack.trackers"
DETECTORS = "irtrack.detectors"
GROUPS = (DETECTORS, TRACKERS, ESTIMATORS)


class EstimateFields(Protocol):
    """What an estimate returned by :meth:`TrajectoryEstimator.add` / ``predict`` carries (NED about the local origin)."""

    t_s: float
    p_ned_m: np.ndarray  # (3,)
    v_ned_mps: np.ndarray  # (3,)
    cov_p_ned_m2: np.ndarray  # (3, 3)
    cov_v_ned_m2ps2: np.ndarray  # (3, 3)
    observable: bool
    range_m: float
    range_sigma_ratio: float
    window_frames: int
    model: str


@runtime_checkable
class TrajectoryEstimator(Protocol):
    """One target's 3-D trajectory from bearings and camera poses (see the module docstring)."""

    def add(self, t_s: float, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam) -> EstimateFields | None: ...

    def predict(self, t_s: float, p_cam_ned_m=None) -> EstimateFields | None: ...

    def reset(self) -> None: ...


@runtime_checkable
class Tracker(Protocol):
    """Image chain: one IR frame -> the target's centre and box (``onboard.imaging.TrackUpdate``)."""

    def update(self, pixels: np.ndarray) -> Any: ...


@runtime_checkable
class Detector(Protocol):
    """Single-frame detector: candidates with ``u_px``, ``v_px``, ``bbox``."""

    def detect(self, pixels: np.ndarray) -> Sequence[Any]: ...


_PROTOCOL = {ESTIMATORS: TrajectoryEstimator, TRACKERS: Tracker, DETECTORS: Detector}


def _entry_points(group: str):
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group=group)}


def available(group: str = ESTIMATORS) -> list[str]:
    """Names registered under ``group`` (installed distributions' entry points), sorted."""
    if group not in GROUPS:
        raise ConfigError(f"plug-in group: expected one of {', '.join(GROUPS)}, got {group!r}")
    return sorted(_entry_points(group))


def _as_factory(obj: Any, name: str) -> Callable[[Any], Any]:
    if inspect.isclass(obj) and hasattr(obj, "from_config"):
        return obj.from_config
    if not callable(obj):
        raise ConfigError(f"plug-in {name!r}: expected a class or a function, got {type(obj).__name__}")
    try:
        required = sum(
            1
            for p in inspect.signature(obj).parameters.values()
            if p.default is inspect.Parameter.empty and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
        )
    except (TypeError, ValueError):  # builtins without a signature: called with the config
        required = 1
    if required == 0:
        return lambda _config: obj()
    return obj


def load_factory(name: str, group: str = ESTIMATORS, option: str = "--estimator") -> Callable[[Any], Any]:
    """``name`` -> ``factory(config) -> instance``: an entry point of ``group``, else ``module:Attribute``.

    Unknown names, modules that do not import and missing attributes are a :class:`ConfigError`
    naming ``option`` and what is registered."""
    if group not in GROUPS:
        raise ConfigError(f"plug-in group: expected one of {', '.join(GROUPS)}, got {group!r}")
    eps = _entry_points(group)
    if name in eps:
        try:
            obj = eps[name].load()
        except Exception as exc:  # noqa: BLE001 - a broken plug-in is a configuration error, one line
            raise ConfigError(
                f"{option} {name}: entry point {eps[name].value} of {group} does not load: {type(exc).__name__}: {exc}"
            ) from None
        return _as_factory(obj, name)
    if ":" not in name:
        known = ", ".join(sorted(eps)) or "none installed"
        raise ConfigError(
            f"{option}: expected a name registered under {group} ({known}) or module:Attribute, got {name!r}"
        )
    module_name, _, attr = name.partition(":")
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # noqa: BLE001
        raise ConfigError(
            f"{option} {name}: module {module_name!r} does not import: {type(exc).__name__}: {exc}"
        ) from None
    target: Any = module
    for part in attr.split("."):
        if not hasattr(target, part):
            raise ConfigError(f"{option} {name}: {module_name} has no attribute {attr!r}")
        target = getattr(target, part)
    return _as_factory(target, name)


def build(name: str, config, group: str = ESTIMATORS, option: str = "--estimator"):
    """The instance ``load_factory(name, group)(config)``, checked against the group's protocol.  A factory that
    raises (a plug-in's ``__init__``, an import inside it) is a :class:`ConfigError` naming ``option`` and ``name``."""
    factory = load_factory(name, group, option)
    try:
        inst = factory(config)
    except ConfigError:
        raise
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - a plug-in that cannot be built is a configuration error
        # in one line; a sys.exit() in its __init__ too, which would otherwise end the command without a word
        raise ConfigError(f"{option} {name}: {type(exc).__name__}: {exc}") from None
    proto = _PROTOCOL[group]
    if not isinstance(inst, proto):
        missing = [
            m
            for m in ("add", "predict", "reset", "update", "detect")
            if hasattr(proto, m) and not callable(getattr(inst, m, None))
        ]
        raise ConfigError(
            f"{option} {name}: {type(inst).__name__} does not implement {proto.__name__} (missing {', '.join(missing)})"
        )
    return inst


# --------------------------------------------------------------------------- irtrack's own, registered in pyproject.toml


def make_map_estimator(config):
    """``map``: the sliding-window MAP estimator of ``config.estimator`` (what the daemon runs)."""
    from onboard.pipeline.frame_pipeline import make_estimator

    est = make_estimator(config)
    if est is None:
        raise ConfigError("--estimator map: the configuration's estimator.enabled is false")
    return est


def _tracker_of_chain(config, chain: str):
    import dataclasses

    from onboard.pipeline.frame_pipeline import make_tracker

    return make_tracker(dataclasses.replace(config, imaging=dataclasses.replace(config.imaging, chain=chain)))


def make_objects_tracker(config):
    """``objects``: the daemon's default image chain (every object tracked, the primary selected by its rule)."""
    return _tracker_of_chain(config, "objects")


def make_single_tracker(config):
    """``single``: the one-blob chain (top-hat, double threshold, KCF), for a clear sky."""
    return _tracker_of_chain(config, "single")
