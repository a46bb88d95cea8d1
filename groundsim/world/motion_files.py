"""The motion models of a scenario file (``model:`` of ``observer``, ``target``, ``other_targets``; schema in
``docs/scenarios.md``): one strict model per ``model`` name, each building its
:mod:`groundsim.world.motion` path with :meth:`motion`.

Kept apart from :mod:`groundsim.world.scenario` so that module stays a readable size; their errors are
:class:`~onboard.core.schema.SchemaError`, which the scenario loader turns into ``ScenarioError``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Annotated, Any, Literal

from pydantic import PlainValidator

from groundsim.world.motion import Circular, Cubic, FigureEight, Motion, Waypoints
from onboard.core.schema import Invalid, Number, Numbers, SchemaError, Text, check_value, config_dataclass

__all__ = [
    "MOTION_MODELS",
    "MotionFile",
    "UniformLinearFile",
    "UniformAccelerationFile",
    "CubicFile",
    "CircularFile",
    "FigureEightFile",
    "WaypointsFile",
]

#: a position (or a length of a path) at most this far from the origin, m: far beyond any encounter a camera sees,
#: and far below the magnitudes whose differences and squares overflow
MAX_POSITION_M = 1e6
#: a speed at most, m/s (Mach 3: above any aircraft or drone a scenario flies)
MAX_SPEED_MPS = 1000.0
#: an acceleration at most, m/s^2 (~100 g), and a jerk, m/s^3
MAX_ACCELERATION_MPS2 = 1000.0
MAX_JERK_MPS3 = 10_000.0

_VEC3 = Annotated[tuple[float, ...], Numbers(3, -MAX_POSITION_M, hi=MAX_POSITION_M, unit="m")]
_VEC3_MPS = Annotated[tuple[float, ...], Numbers(3, -MAX_SPEED_MPS, hi=MAX_SPEED_MPS, unit="m/s")]
_VEC3_MPS2 = Annotated[tuple[float, ...], Numbers(3, -MAX_ACCELERATION_MPS2, hi=MAX_ACCELERATION_MPS2, unit="m/s^2")]
_VEC3_MPS3 = Annotated[tuple[float, ...], Numbers(3, -MAX_JERK_MPS3, hi=MAX_JERK_MPS3, unit="m/s^3")]
_ZERO3 = (0.0, 0.0, 0.0)


@config_dataclass(kw_only=True)
class UniformLinearFile:
    model: Annotated[Literal["uniform_linear"], Text()] = "uniform_linear"
    p0_ned_m: _VEC3
    v0_ned_mps: _VEC3_MPS = _ZERO3

    def motion(self) -> Motion:
        return Cubic(self.p0_ned_m, self.v0_ned_mps, _ZERO3, _ZERO3)


@config_dataclass(kw_only=True)
class UniformAccelerationFile:
    model: Annotated[Literal["uniform_acceleration"], Text()] = "uniform_acceleration"
    p0_ned_m: _VEC3
    v0_ned_mps: _VEC3_MPS = _ZERO3
    a0_ned_mps2: _VEC3_MPS2 = _ZERO3

    def motion(self) -> Motion:
        return Cubic(self.p0_ned_m, self.v0_ned_mps, self.a0_ned_mps2, _ZERO3)


@config_dataclass(kw_only=True)
class CubicFile:
    model: Annotated[Literal["cubic"], Text()] = "cubic"
    p0_ned_m: _VEC3
    v0_ned_mps: _VEC3_MPS = _ZERO3
    a0_ned_mps2: _VEC3_MPS2 = _ZERO3
    j_ned_mps3: _VEC3_MPS3 = _ZERO3

    def motion(self) -> Motion:
        return Cubic(self.p0_ned_m, self.v0_ned_mps, self.a0_ned_mps2, self.j_ned_mps3)


@config_dataclass(kw_only=True)
class CircularFile:
    model: Annotated[Literal["circular"], Text()] = "circular"
    center_ned_m: _VEC3
    radius_m: Annotated[float, Number(0.0, MAX_POSITION_M, lo_open=True, unit="m")]
    azimuth0_deg: Annotated[float, Number(-360.0, 360.0, unit="deg")] = 0.0
    rate_degps: Annotated[float, Number(-360.0, 360.0, unit="deg/s (signed: > 0 clockwise from above)")]

    def motion(self) -> Motion:
        return Circular(
            self.center_ned_m, self.radius_m, math.radians(self.azimuth0_deg), math.radians(self.rate_degps)
        )


@config_dataclass(kw_only=True)
class FigureEightFile:
    model: Annotated[Literal["figure_eight"], Text()] = "figure_eight"
    center_ned_m: _VEC3
    amp1_ned_m: _VEC3
    amp2_ned_m: _VEC3 = _ZERO3
    period_s: Annotated[float, Number(0.0, lo_open=True)]

    def motion(self) -> Motion:
        return FigureEight(self.center_ned_m, self.amp1_ned_m, self.amp2_ned_m, self.period_s)


def _points(value: Any) -> tuple[tuple[float, ...], ...]:
    if not isinstance(value, (list, tuple)) or len(value) < 2:
        raise Invalid("", "a list of at least 2 points [n, e, d]", value)
    out = []
    for i, q in enumerate(value):
        try:
            out.append(check_value(_VEC3, q, f"[{i}]", "<points>"))
        except SchemaError as exc:
            raise Invalid(exc.field, exc.expected, got_text=exc.got) from None
    return tuple(out)


@config_dataclass(kw_only=True)
class WaypointsFile:
    model: Annotated[Literal["waypoints"], Text()] = "waypoints"
    points_ned_m: Annotated[tuple, PlainValidator(_points)]
    speed_mps: Annotated[float, Number(0.0, MAX_SPEED_MPS, lo_open=True, unit="m/s")]

    def motion(self) -> Motion:
        return Waypoints(self.points_ned_m, self.speed_mps)


_MOTION_FILES = (UniformLinearFile, UniformAccelerationFile, CubicFile, CircularFile, FigureEightFile, WaypointsFile)
MOTION_MODELS: tuple[str, ...] = tuple(dataclasses.fields(m)[0].default for m in _MOTION_FILES)
MotionFile = UniformLinearFile | UniformAccelerationFile | CubicFile | CircularFile | FigureEightFile | WaypointsFile
