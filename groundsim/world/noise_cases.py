"""Measurement-noise cases: ``config/noise_cases.yaml`` read into :class:`NoiseCase` objects.

A case names the navigation and pixel errors a run's telemetry and labels carry (``RTK``, ``GNSS``, ``exact`` ...);
scenario files, ``groundsim eval --nav-noise`` and the benchmarks name cases by their key in the file.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Annotated

from groundsim.world.spec import NAME, NAME_PATTERN, ScenarioError, read_spec_yaml, scenario_model
from onboard.core.schema import NOT_A_KEY, NonNegativeFloat, SchemaError, Text, build

__all__ = ["NoiseCase", "load_noise_cases", "noise_cases_from_dict", "noise_cases_path"]

_CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"
#: per-axis white camera-position noise up to which a case is an RTK fix (centimetre-level, as RTK receivers give)
RTK_WHITE_MAX_M = 0.05
#: the least position uncertainty a receiver reports (an RTK fix says ~1 cm, never 0)
GNSS_ACCURACY_FLOOR_M = 0.01


@scenario_model
class NoiseCase:
    """Measurement noise of one evaluation case: one case of ``config/noise_cases.yaml`` (angles in degrees
    there and here; ``*_rad`` in radians), ``name`` its key in the file.

    ``pixel_sigma_px``: 1-sigma per image axis; ``attitude_white_sigma_deg`` / ``attitude_bias_sigma_deg``:
    per-axis 1-sigma of white attitude noise and of a constant bias drawn once per run;
    ``camera_position_white_sigma_m``: per-axis white noise on the camera position;
    ``camera_position_offset_m``: size of a constant position offset; ``camera_position_drift_mps``:
    size of a constant position drift rate (the noise model draws their directions per run).
    """

    name: NAME = dataclasses.field(metadata=NOT_A_KEY)
    description: Annotated[str, Text(empty=True)] = dataclasses.field(default="", kw_only=True)
    pixel_sigma_px: NonNegativeFloat
    attitude_white_sigma_deg: NonNegativeFloat = 0.0
    attitude_bias_sigma_deg: NonNegativeFloat = 0.0
    camera_position_white_sigma_m: NonNegativeFloat = 0.0
    camera_position_offset_m: NonNegativeFloat = 0.0
    camera_position_drift_mps: NonNegativeFloat = 0.0

    def gnss_accuracy_m(self) -> tuple[bool, float, float]:
        """What the vehicle's GNSS receiver reports of this case's camera-position error (GPS_RAW_INT): whether
        it is an RTK fix (white noise of at most :data:`RTK_WHITE_MAX_M` per axis, no offset, no drift), and its
        horizontal and vertical 1-sigma uncertainty, m: the white noise (horizontal over two axes) plus the
        offset's size, at least :data:`GNSS_ACCURACY_FLOOR_M` (no receiver reports zero)."""
        white, offset = self.camera_position_white_sigma_m, self.camera_position_offset_m
        rtk = white <= RTK_WHITE_MAX_M and offset == 0.0 and self.camera_position_drift_mps == 0.0
        h = max(math.sqrt(2.0) * white + offset, GNSS_ACCURACY_FLOOR_M)
        v = max(white + offset, GNSS_ACCURACY_FLOOR_M)
        return rtk, h, v

    @property
    def attitude_white_sigma_rad(self) -> float:
        return math.radians(self.attitude_white_sigma_deg)

    @property
    def attitude_bias_sigma_rad(self) -> float:
        return math.radians(self.attitude_bias_sigma_deg)


def noise_cases_path() -> Path:
    """The repository's shipped ``config/noise_cases.yaml`` (found relative to this file)."""
    return _CONFIG_DIR / "noise_cases.yaml"


def noise_cases_from_dict(d, source="<dict>") -> dict[str, NoiseCase]:
    """Validate a parsed noise-case mapping ``{name: {fields}}`` (angles in degrees) into NoiseCases."""
    if not isinstance(d, dict) or not d:
        raise ScenarioError(source, "", "a non-empty mapping of case name -> fields", d)
    out: dict[str, NoiseCase] = {}
    for name, c in d.items():
        if not isinstance(name, str) or not NAME_PATTERN.match(name):
            raise ScenarioError(source, "", "case names of letters, digits, '_', '.', '-'", name)
        try:
            out[name] = build(NoiseCase, c, name, none_is_default=False, given={"name": name})
        except SchemaError as exc:
            raise exc.as_(ScenarioError, source) from None
    return out


def load_noise_cases(path=None) -> dict[str, NoiseCase]:
    """Read ``config/noise_cases.yaml`` (or ``path``): case name -> :class:`NoiseCase`."""
    p = Path(path) if path is not None else noise_cases_path()
    return noise_cases_from_dict(read_spec_yaml(p), source=p)
