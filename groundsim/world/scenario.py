"""Scenario files: their schema, their validation, and the typed objects everybody else uses.

A scenario is a YAML file in ``config/scenarios/`` (schema and examples: ``docs/scenarios.md``).
:func:`load_scenario` reads one into a frozen :class:`Scenario`; :func:`scenario_from_dict` does
the same for an already-parsed mapping.  Geometry is in local NED about ``origin`` (see
``onboard.core.frames``), angles in degrees in the file and radians inside, a unit in every key.

Validation is complete at load: unknown keys (with a "did you mean"), wrong types, wrong vector
lengths, non-finite numbers, out-of-range values, unknown model names, inconsistent pairs
(``t_min_k >= t_max_k``), bad YAML syntax and unreadable files all raise :class:`ScenarioError`,
whose message is one line::

    <file>: <field.path>: expected <what>, got <value>

Entry points print that line and exit with :attr:`ScenarioError.exit_code` (2); ``python -m
groundsim.world.scenario [FILE ...]`` does exactly that (no argument: every shipped scenario).

Randomness is data until it is realised: a target's ``disturbance`` is a
:class:`SingerDisturbance` spec; ``scenario.target_motion(run_seed)`` realises it with a generator
drawn from ``scenario.rng("target.disturbance", run_seed)``, which depends only on the scenario's
``seed``, the run seed and the stream name.  ``scenario.target.motion`` is run 0's realisation.
"""

from __future__ import annotations

import difflib
import logging
import math
import re
import sys
import zlib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from groundsim.world.motion import Circular, Cubic, FigureEight, Motion, Perturbed, SingerPerturbation, Waypoints
from groundsim.world.render.settings import IrSettings, TargetPart
from onboard.core.errors import ConfigError, IrtrackError
from onboard.core.frames import CameraMount, GeodeticOrigin, PinholeIntrinsics

__all__ = [
    "ScenarioError",
    "SingerDisturbance",
    "VehicleSpec",
    "GimbalSpec",
    "CameraSpec",
    "Scenario",
    "NoiseCase",
    "MOTION_MODELS",
    "REFERENCE_GIMBAL",
    "DEFAULT_ORIGIN",
    "load_scenario",
    "scenario_from_dict",
    "reference_scenario_paths",
    "scenarios_dir",
    "load_noise_cases",
    "noise_cases_from_dict",
    "main",
]

log = logging.getLogger(__name__)

MAX_DURATION_S = 3600.0  # one hour: longer runs are not scenarios but campaigns
MAX_FRAME_RATE_HZ = 1000.0
MAX_SINGER_SIGMA_MPS2 = 100.0  # ~10 g: beyond it a "disturbance" is not one
MIN_SEPARATION_M = 1.0  # observer and target (commanded paths) must stay this far apart at every frame
SINGER_MARGIN_S = 1.0  # a disturbance is realised this long past duration_s (no clamping at the end)
FRAME_COUNT_EPS = 1e-9  # k < duration * rate, robust to 0.1 * 30 = 3.0000000000000004
NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")

DEFAULT_ORIGIN = GeodeticOrigin(32.0, 118.8, 0.0)  # Nanjing, see REFERENCE_SCENARIOS.md
DEFAULT_DURATION_S = 10.0
DEFAULT_FRAME_RATE_HZ = 30.0
DEFAULT_SEED = 0
DEFAULT_NAV_NOISE = "RTK"  # navigation errors of the telemetry when nothing else is asked (groundsim.world.nav_errors)

_CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"
_REFERENCE_ORDER = ("P1", "P2", "P3", "P1g", "P2g", "P3g", "H1", "H2", "H3")


# --------------------------------------------------------------------------- the error


class _Missing:
    def __repr__(self) -> str:  # pragma: no cover - never shown
        return "<missing>"


_MISSING: Any = _Missing()


def _show(value: Any, limit: int = 60) -> str:
    """A value as one short line for an error message."""
    if isinstance(value, _Missing):
        return "nothing (the key is missing)"
    text = " ".join(repr(value).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


class ScenarioError(ConfigError):
    """A scenario or noise-case file (or dict) is invalid.

    ``str(err)`` is one line: ``"<source>: <field>: expected <expected>, got <got>[; <hint>]"``.
    Attributes: ``source`` (file or ``"<dict>"``), ``field`` (dotted path, ``"(document)"`` for the
    whole file, ``"line L, column C"`` for YAML syntax), ``expected``, ``got`` (the offending
    value or ``None``), ``hint`` (e.g. a "did you mean"), ``line`` (1-based, YAML errors only).
    """

    exit_code = 2

    def __init__(self, source, field_path: str, expected: str, got: Any = _MISSING, hint: str | None = None,
                 *, got_text: str | None = None, line: int | None = None):
        self.source = str(source)
        self.field = field_path or "(document)"
        self.expected = expected
        self.got = None if isinstance(got, _Missing) else got
        self.hint = hint
        self.line = line
        got_part = got_text if got_text is not None else _show(got)
        msg = f"{self.source}: {self.field}: expected {expected}, got {got_part}"
        if hint:
            msg += f"; {hint}"
        super().__init__(" ".join(msg.split()))


class _Fail:
    """Raises ScenarioError for one source: ``fail(path, expected, got, hint)``; ``fail.text(...)``
    when the 'got' part is a description rather than a value."""

    def __init__(self, source) -> None:
        self.source = source

    def __call__(self, path: str, expected: str, got: Any = _MISSING, hint: str | None = None):
        raise ScenarioError(self.source, path, expected, got, hint)

    def text(self, path: str, expected: str, got_text: str, hint: str | None = None):
        raise ScenarioError(self.source, path, expected, got_text=got_text, hint=hint)


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


# --------------------------------------------------------------------------- value checkers
# Each takes (value, path, fail, ...) and returns the clean value or calls fail().  They are shared
# by the loader (paths like "target.motion.p0_ned_m") and the dataclasses' __post_init__.


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _bounds_text(lo, lo_open, hi, hi_open) -> str:
    if lo is not None and hi is not None:
        return f" in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f" {'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f" {'<' if hi_open else '<='} {hi:g}"
    return ""


def _number(v, path, fail: _Fail, *, lo=None, lo_open=False, hi=None, hi_open=False, unit="") -> float:
    what = f"a finite number{_bounds_text(lo, lo_open, hi, hi_open)}{(' ' + unit) if unit else ''}"
    if not _is_number(v):
        fail(path, what, v)
    try:
        x = float(v)
    except OverflowError:
        fail(path, what, v)
    if not math.isfinite(x):
        fail(path, what, v)
    if lo is not None and (x < lo or (lo_open and x == lo)):
        fail(path, what, v)
    if hi is not None and (x > hi or (hi_open and x == hi)):
        fail(path, what, v)
    return x


def _integer(v, path, fail: _Fail, *, lo=None, hi=None) -> int:
    what = f"an integer{_bounds_text(lo, False, hi, False)}"
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
        fail(path, what, v)
    i = int(v)
    if (lo is not None and i < lo) or (hi is not None and i > hi):
        fail(path, what, v)
    return i


def _string(v, path, fail: _Fail, *, choices=None, pattern: re.Pattern | None = None, what="a string") -> str:
    if choices is not None:
        what = "one of " + ", ".join(choices)
    if not isinstance(v, str):
        fail(path, what, v)
    if choices is not None and v not in choices:
        fail(path, what, v, _did_you_mean(v, choices))
    if pattern is not None and not pattern.match(v):
        fail(path, what, v)
    return v


def _vector(v, path, fail: _Fail, n: int = 3, *, lo=None, lo_open=False, unit="", what=None) -> tuple[float, ...]:
    what = what or f"a list of {n} finite numbers{_bounds_text(lo, lo_open, None, False)}{(' ' + unit) if unit else ''}"
    if not isinstance(v, (list, tuple)) or len(v) != n:
        fail(path, what, v)
    for i, x in enumerate(v):
        if not _is_number(x):
            fail(path, what, v)
        _number(x, f"{path}[{i}]", fail, lo=lo, lo_open=lo_open, unit=unit)
    return tuple(float(x) for x in v)


def _did_you_mean(word: str, options) -> str | None:
    close = difflib.get_close_matches(word, list(options), n=1, cutoff=0.6)
    return f"did you mean '{close[0]}'?" if close else None


def _mapping(v, path, fail: _Fail, allowed, required=()) -> dict:
    """A dict with string keys, all in ``allowed``, all of ``required`` present."""
    allowed = tuple(allowed)
    if not isinstance(v, dict):
        fail(path, f"a mapping with keys {', '.join(allowed)}", v)
    for k in v:
        if not isinstance(k, str):
            fail(path, f"string keys (one of {', '.join(allowed)})", k)
    for k in v:
        if k not in allowed:
            fail.text(_join(path, k), f"a key of {path or 'the document'} ({', '.join(allowed)})",
                      f"unknown key {k!r}", _did_you_mean(k, allowed))
    for k in required:
        if k not in v:
            fail(_join(path, k), "a value (required)")
    return v


# --------------------------------------------------------------------------- typed objects


@dataclass(frozen=True)
class SingerDisturbance:
    """Random (Singer) target acceleration, as data: 1-sigma per horizontal axis (N, E) and for D,
    correlation time ``tau_s``.  :meth:`realise` turns it into a ``SingerPerturbation`` path."""

    sigma_horizontal_mps2: float
    sigma_vertical_mps2: float
    tau_s: float

    def __post_init__(self) -> None:
        fail = _Fail("<SingerDisturbance>")
        _number(self.sigma_horizontal_mps2, "sigma_horizontal_mps2", fail, lo=0.0, hi=MAX_SINGER_SIGMA_MPS2)
        _number(self.sigma_vertical_mps2, "sigma_vertical_mps2", fail, lo=0.0, hi=MAX_SINGER_SIGMA_MPS2)
        _number(self.tau_s, "tau_s", fail, lo=0.0, lo_open=True)

    @property
    def sigma_ned_mps2(self) -> tuple[float, float, float]:
        h = float(self.sigma_horizontal_mps2)
        return (h, h, float(self.sigma_vertical_mps2))

    def realise(self, duration_s: float, rng: np.random.Generator) -> SingerPerturbation:
        """One realisation over ``[0, duration_s]``: position and velocity offsets start at zero."""
        return SingerPerturbation(duration_s, self.sigma_ned_mps2, float(self.tau_s), rng)


@dataclass(frozen=True)
class VehicleSpec:
    """One vehicle's path.

    ``motion``: what it flies (a ``groundsim.world.motion`` model with ``state(t_s)``); for a target with
    a ``disturbance`` this is already ``Perturbed(base_motion, <run 0 realisation>)``.
    ``base_motion``: the deterministic model (defaults to ``motion``).  ``disturbance``: the spec
    of the random part, or ``None``.  Other realisations: :meth:`realise`.
    """

    motion: Motion
    base_motion: Motion | None = None
    disturbance: SingerDisturbance | None = None

    def __post_init__(self) -> None:
        fail = _Fail("<VehicleSpec>")
        for name in ("motion", "base_motion"):
            m = getattr(self, name)
            if m is not None and not callable(getattr(m, "state", None)):
                fail(name, "a motion model with a state(t_s) method", m)
        if self.disturbance is not None and not isinstance(self.disturbance, SingerDisturbance):
            fail("disturbance", "a SingerDisturbance or None", self.disturbance)
        if self.base_motion is None:
            if self.disturbance is not None:
                fail("base_motion", "the unperturbed model when a disturbance is given")
            object.__setattr__(self, "base_motion", self.motion)

    def realise(self, duration_s: float, rng: np.random.Generator) -> Motion:
        """``base_motion`` plus a fresh realisation of ``disturbance`` drawn from ``rng``."""
        if self.disturbance is None:
            return self.base_motion
        return Perturbed(self.base_motion, self.disturbance.realise(duration_s, rng))


@dataclass(frozen=True)
class GimbalSpec:
    """A gimbal that keeps the target near the image centre with a slowly varying pointing error:
    per NED axis a sinusoid of amplitude ``pointing_error_frac_of_range[i] * range`` and period
    ``pointing_error_period_s[i]`` (phase: the pointing model's choice)."""

    pointing_error_frac_of_range: tuple[float, float, float]
    pointing_error_period_s: tuple[float, float, float]

    def __post_init__(self) -> None:
        fail = _Fail("<GimbalSpec>")
        _vector(self.pointing_error_frac_of_range, "pointing_error_frac_of_range", fail, lo=0.0)
        _vector(self.pointing_error_period_s, "pointing_error_period_s", fail, lo=0.0, lo_open=True, unit="s")


#: The reference study's pointing: 3 %, 2 %, 1.5 % of the range, periods 7 s, 5 s, 3 s.
REFERENCE_GIMBAL = GimbalSpec((0.03, 0.02, 0.015), (7.0, 5.0, 3.0))


@dataclass(frozen=True)
class CameraSpec:
    """The camera: intrinsics, its pod mount on the observer, and an optional gimbal (``None`` = a
    fixed pod; the observer then yaws toward the target)."""

    intrinsics: PinholeIntrinsics = field(default_factory=PinholeIntrinsics.vue_pro_640)
    mount: CameraMount = field(default_factory=CameraMount)
    gimbal: GimbalSpec | None = REFERENCE_GIMBAL

    def __post_init__(self) -> None:
        fail = _Fail("<CameraSpec>")
        if not isinstance(self.intrinsics, PinholeIntrinsics):
            fail("intrinsics", "a PinholeIntrinsics", self.intrinsics)
        if not isinstance(self.mount, CameraMount):
            fail("mount", "a CameraMount", self.mount)
        if self.gimbal is not None and not isinstance(self.gimbal, GimbalSpec):
            fail("gimbal", "a GimbalSpec or None", self.gimbal)


def _frame_count(duration_s: float, frame_rate_hz: float) -> int:
    return max(1, math.ceil(duration_s * frame_rate_hz - FRAME_COUNT_EPS))


def _stream_rng(seed: int, stream: str, run_seed: int) -> np.random.Generator:
    key = zlib.crc32(stream.encode("utf-8"))
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(run_seed), key]))


@dataclass(frozen=True, kw_only=True)
class Scenario:
    """One simulated encounter (see the module docstring and ``docs/scenarios.md``).

    ``observer``/``target``: :class:`VehicleSpec` in local NED about ``origin``; ``camera``: on the
    observer; ``ir``: the renderer's settings; ``wind_ned_mps``: (n, e, d) m/s; ``seed``: the root
    of every random stream of the scenario (see :meth:`rng`); ``source_path``: the file it came
    from, or ``None``.
    """

    name: str
    description: str = ""
    origin: GeodeticOrigin = DEFAULT_ORIGIN
    duration_s: float = DEFAULT_DURATION_S
    frame_rate_hz: float = DEFAULT_FRAME_RATE_HZ
    seed: int = DEFAULT_SEED
    observer: VehicleSpec
    target: VehicleSpec
    camera: CameraSpec = field(default_factory=CameraSpec)
    ir: IrSettings = field(default_factory=IrSettings)
    wind_ned_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    nav_noise: str = DEFAULT_NAV_NOISE
    source_path: Path | None = None

    def __post_init__(self) -> None:
        fail = _Fail(self.source_path if self.source_path is not None else "<Scenario>")
        _string(self.name, "name", fail, pattern=NAME_PATTERN, what="a name of letters, digits, '_', '.', '-'")
        _string(self.description, "description", fail)
        if not isinstance(self.origin, GeodeticOrigin):
            fail("origin", "a GeodeticOrigin", self.origin)
        _number(self.duration_s, "duration_s", fail, lo=0.0, lo_open=True, hi=MAX_DURATION_S)
        _number(self.frame_rate_hz, "frame_rate_hz", fail, lo=0.0, lo_open=True, hi=MAX_FRAME_RATE_HZ)
        _integer(self.seed, "seed", fail, lo=0)
        for name in ("observer", "target"):
            if not isinstance(getattr(self, name), VehicleSpec):
                fail(name, "a VehicleSpec", getattr(self, name))
        if not isinstance(self.camera, CameraSpec):
            fail("camera", "a CameraSpec", self.camera)
        if not isinstance(self.ir, IrSettings):
            fail("ir", "an IrSettings", self.ir)
        object.__setattr__(self, "wind_ned_mps", _vector(self.wind_ned_mps, "wind_ned_mps", fail, unit="m/s"))
        _string(self.nav_noise, "nav_noise", fail, pattern=NAME_PATTERN, what="a noise-case name of config/noise_cases.yaml")

    @property
    def frame_count(self) -> int:
        """Number of frames: every k >= 0 with k < duration_s * frame_rate_hz."""
        return _frame_count(self.duration_s, self.frame_rate_hz)

    def frame_times_s(self) -> np.ndarray:
        """Frame times ``k / frame_rate_hz`` (s since start) for k < duration_s * frame_rate_hz, shape (F,)."""
        return np.arange(self.frame_count) / self.frame_rate_hz

    def rng(self, stream: str, run_seed: int = 0) -> np.random.Generator:
        """An independent generator per (scenario seed, run seed, stream name); deterministic.

        Streams used here: ``"target.disturbance"``.  Other components pick their own names
        (e.g. ``"noise.pixel"``) so adding a stream never shifts another.
        """
        run_seed = _integer(run_seed, "run_seed", _Fail(f"<Scenario {self.name}>"), lo=0)
        return _stream_rng(self.seed, stream, run_seed)

    def target_motion(self, run_seed: int = 0) -> Motion:
        """The target's path for run ``run_seed``: its base model plus that run's disturbance
        realisation (the base model alone when it has none).  ``target_motion(0) is target.motion``."""
        run_seed = _integer(run_seed, "run_seed", _Fail(f"<Scenario {self.name}>"), lo=0)
        if run_seed == 0 or self.target.disturbance is None:
            return self.target.motion
        return self.target.realise(self.duration_s + SINGER_MARGIN_S, self.rng("target.disturbance", run_seed))

    def observer_motion(self, run_seed: int = 0) -> Motion:
        """The observer's path (deterministic: observers carry no disturbance)."""
        return self.observer.motion


@dataclass(frozen=True)
class NoiseCase:
    """Measurement noise of one evaluation case (``config/noise_cases.yaml``).

    ``pixel_sigma_px``: 1-sigma per image axis; ``attitude_white_sigma_rad`` / ``attitude_bias_sigma_rad``:
    per-axis 1-sigma of white attitude noise and of a constant bias drawn once per run;
    ``camera_position_white_sigma_m``: per-axis white noise on the camera position;
    ``camera_position_offset_m``: size of a constant position offset; ``camera_position_drift_mps``:
    size of a constant position drift rate (the noise model draws their directions per run).
    """

    name: str
    pixel_sigma_px: float
    attitude_white_sigma_rad: float = 0.0
    attitude_bias_sigma_rad: float = 0.0
    camera_position_white_sigma_m: float = 0.0
    camera_position_offset_m: float = 0.0
    camera_position_drift_mps: float = 0.0
    description: str = ""

    def __post_init__(self) -> None:
        fail = _Fail("<NoiseCase>")
        _string(self.name, "name", fail, pattern=NAME_PATTERN, what="a name of letters, digits, '_', '.', '-'")
        _string(self.description, "description", fail)
        for f in fields(self):
            if f.name not in ("name", "description"):
                _number(getattr(self, f.name), f.name, fail, lo=0.0)


# --------------------------------------------------------------------------- motion from YAML

_VEC0 = (0.0, 0.0, 0.0)

# model -> {key: (kind, required)}; kinds: "vec3", "pos", "ang", "rate", "period", "speed", "points"
_MOTION_KEYS: dict[str, dict[str, tuple[str, bool]]] = {
    "uniform_linear": {"p0_ned_m": ("vec3", True), "v0_ned_mps": ("vec3", False)},
    "uniform_acceleration": {"p0_ned_m": ("vec3", True), "v0_ned_mps": ("vec3", False),
                             "a0_ned_mps2": ("vec3", False)},
    "cubic": {"p0_ned_m": ("vec3", True), "v0_ned_mps": ("vec3", False), "a0_ned_mps2": ("vec3", False),
              "j_ned_mps3": ("vec3", False)},
    "circular": {"center_ned_m": ("vec3", True), "radius_m": ("pos", True), "azimuth0_deg": ("ang", False),
                 "rate_degps": ("rate", True)},
    "figure_eight": {"center_ned_m": ("vec3", True), "amp1_ned_m": ("vec3", True), "amp2_ned_m": ("vec3", False),
                     "period_s": ("pos", True)},
    "waypoints": {"points_ned_m": ("points", True), "speed_mps": ("pos", True)},
}
MOTION_MODELS: tuple[str, ...] = tuple(_MOTION_KEYS)


def _motion_from_dict(d, path: str, fail: _Fail) -> Motion:
    if not isinstance(d, dict):
        fail(path, f"a mapping with 'model' (one of {', '.join(MOTION_MODELS)}) and its parameters", d)
    if "model" not in d:
        fail(_join(path, "model"), f"one of {', '.join(MOTION_MODELS)} (required)")
    model = _string(d["model"], _join(path, "model"), fail, choices=MOTION_MODELS)
    spec = _MOTION_KEYS[model]
    _mapping(d, path, fail, ("model",) + tuple(spec), [k for k, (_, req) in spec.items() if req])
    v: dict[str, Any] = {}
    for key, (kind, _) in spec.items():
        p = _join(path, key)
        if key not in d:
            v[key] = _VEC0 if kind == "vec3" else 0.0
        elif kind == "vec3":
            v[key] = _vector(d[key], p, fail)
        elif kind == "pos":
            v[key] = _number(d[key], p, fail, lo=0.0, lo_open=True)
        elif kind == "ang":
            v[key] = _number(d[key], p, fail, lo=-360.0, hi=360.0, unit="deg")
        elif kind == "rate":
            v[key] = _number(d[key], p, fail, lo=-360.0, hi=360.0, unit="deg/s (signed: > 0 clockwise from above)")
        elif kind == "points":
            pts = d[key]
            if not isinstance(pts, list) or len(pts) < 2:
                fail(p, "a list of at least 2 points [n, e, d]", pts)
            v[key] = tuple(_vector(q, f"{p}[{i}]", fail) for i, q in enumerate(pts))
    if model in ("uniform_linear", "uniform_acceleration", "cubic"):
        return Cubic(v["p0_ned_m"], v["v0_ned_mps"], v.get("a0_ned_mps2", _VEC0), v.get("j_ned_mps3", _VEC0))
    if model == "circular":
        return Circular(v["center_ned_m"], v["radius_m"], math.radians(v["azimuth0_deg"]), math.radians(v["rate_degps"]))
    if model == "figure_eight":
        return FigureEight(v["center_ned_m"], v["amp1_ned_m"], v["amp2_ned_m"], v["period_s"])
    return Waypoints(v["points_ned_m"], v["speed_mps"])


def _disturbance_from_dict(d, path: str, fail: _Fail) -> SingerDisturbance | None:
    if d is None:
        return None
    keys = ("model", "sigma_horizontal_mps2", "sigma_vertical_mps2", "tau_s")
    _mapping(d, path, fail, keys, keys)
    _string(d["model"], _join(path, "model"), fail, choices=("singer",))
    return SingerDisturbance(
        _number(d["sigma_horizontal_mps2"], _join(path, "sigma_horizontal_mps2"), fail, lo=0.0,
                hi=MAX_SINGER_SIGMA_MPS2, unit="m/s^2"),
        _number(d["sigma_vertical_mps2"], _join(path, "sigma_vertical_mps2"), fail, lo=0.0,
                hi=MAX_SINGER_SIGMA_MPS2, unit="m/s^2"),
        _number(d["tau_s"], _join(path, "tau_s"), fail, lo=0.0, lo_open=True, unit="s"),
    )


# --------------------------------------------------------------------------- camera, IR, origin


def _intrinsics_from_dict(d, path: str, fail: _Fail) -> PinholeIntrinsics:
    vue = PinholeIntrinsics.vue_pro_640()
    if d is None:
        return vue
    keys = ("fx_px", "fy_px", "cx_px", "cy_px", "width_px", "height_px", "distortion")
    _mapping(d, path, fail, keys)
    w = _integer(d.get("width_px", vue.width_px), _join(path, "width_px"), fail, lo=1, hi=100_000)
    h = _integer(d.get("height_px", vue.height_px), _join(path, "height_px"), fail, lo=1, hi=100_000)
    fx = _number(d.get("fx_px", vue.fx_px), _join(path, "fx_px"), fail, lo=0.0, lo_open=True)
    fy = _number(d.get("fy_px", vue.fy_px), _join(path, "fy_px"), fail, lo=0.0, lo_open=True)
    cx = _number(d.get("cx_px", w / 2), _join(path, "cx_px"), fail, lo=0.0, hi=float(w))
    cy = _number(d.get("cy_px", h / 2), _join(path, "cy_px"), fail, lo=0.0, hi=float(h))
    dist = _vector(d.get("distortion", vue.distortion), _join(path, "distortion"), fail, 5,
                   what="a list of 5 finite numbers (k1, k2, p1, p2, k3)")
    return PinholeIntrinsics(fx, fy, cx, cy, w, h, dist)


def _mount_from_dict(d, path: str, fail: _Fail, gimballed: bool) -> CameraMount:
    if d is None:
        d = {}
    keys = ("lever_arm_frd_m", "roll_deg", "pitch_deg", "yaw_deg")
    _mapping(d, path, fail, keys)
    arm = _vector(d.get("lever_arm_frd_m", _VEC0), _join(path, "lever_arm_frd_m"), fail, unit="m")
    ang = [_number(d.get(k, 0.0), _join(path, k), fail, lo=-360.0, hi=360.0, unit="deg") for k in keys[1:]]
    return CameraMount.from_euler_deg(arm, *ang, gimballed=gimballed)


def _gimbal_from_dict(d, path: str, fail: _Fail) -> GimbalSpec | None:
    if d is None:
        return None
    keys = ("pointing_error_frac_of_range", "pointing_error_period_s")
    _mapping(d, path, fail, keys)
    frac = d.get("pointing_error_frac_of_range", REFERENCE_GIMBAL.pointing_error_frac_of_range)
    per = d.get("pointing_error_period_s", REFERENCE_GIMBAL.pointing_error_period_s)
    return GimbalSpec(
        _vector(frac, _join(path, "pointing_error_frac_of_range"), fail, lo=0.0),
        _vector(per, _join(path, "pointing_error_period_s"), fail, lo=0.0, lo_open=True, unit="s"),
    )


def _camera_from_dict(d, path: str, fail: _Fail) -> CameraSpec:
    if d is None:
        d = {}
    _mapping(d, path, fail, ("intrinsics", "mount", "gimbal"))
    # absent gimbal -> the reference pointing; explicit null -> a fixed pod
    gimbal = _gimbal_from_dict(d["gimbal"], _join(path, "gimbal"), fail) if "gimbal" in d else REFERENCE_GIMBAL
    return CameraSpec(
        _intrinsics_from_dict(d.get("intrinsics"), _join(path, "intrinsics"), fail),
        _mount_from_dict(d.get("mount"), _join(path, "mount"), fail, gimballed=gimbal is not None),
        gimbal,
    )


_PART_KEYS = ("name", "shape", "center_frd_m", "half_extent_m", "temperature_k", "emissivity")


def _parts_from_list(v, path: str, fail: _Fail) -> tuple[TargetPart, ...]:
    if not isinstance(v, list) or not v:
        fail(path, "a non-empty list of parts (mappings with " + ", ".join(_PART_KEYS) + ")", v)
    parts, names = [], set()
    for i, d in enumerate(v):
        p = f"{path}[{i}]"
        _mapping(d, p, fail, _PART_KEYS, _PART_KEYS)
        name = _string(d["name"], _join(p, "name"), fail)
        if name in names:
            fail(_join(p, "name"), "a part name not used before in the list", name)
        names.add(name)
        parts.append(TargetPart(
            name,
            _string(d["shape"], _join(p, "shape"), fail, choices=("ellipsoid", "box")),
            _vector(d["center_frd_m"], _join(p, "center_frd_m"), fail, unit="m"),
            _vector(d["half_extent_m"], _join(p, "half_extent_m"), fail, lo=0.0, lo_open=True, unit="m"),
            _number(d["temperature_k"], _join(p, "temperature_k"), fail, lo=0.0, lo_open=True, unit="K"),
            _number(d["emissivity"], _join(p, "emissivity"), fail, lo=0.0, lo_open=True, hi=1.0),
        ))
    return tuple(parts)


def _ir_from_dict(d, path: str, fail: _Fail) -> IrSettings:
    if d is None:
        return IrSettings()
    names = tuple(f.name for f in fields(IrSettings))
    _mapping(d, path, fail, names)
    base = IrSettings()
    kw: dict[str, Any] = {}
    temps = ("t_min_k", "t_max_k", "air_temperature_k", "sky_zenith_k", "sky_horizon_k", "ground_temperature_k",
             "netd_reference_k")
    for k in temps:
        if k in d:
            kw[k] = _number(d[k], _join(path, k), fail, lo=0.0, lo_open=True, unit="K")
    for k in ("netd_k", "blur_sigma_px", "extinction_per_km", "background_reuse_tol_rad"):
        if k in d:
            kw[k] = _number(d[k], _join(path, k), fail, lo=0.0)
    # the renderer's tuning knobs (groundsim.world.render.settings.IrSettings)
    for k in ("supersample", "max_target_rays", "noise_bank_frames"):
        if k in d:
            kw[k] = _integer(d[k], _join(path, k), fail, lo=1, hi=1_000_000)
    if "ground_emissivity" in d:
        kw["ground_emissivity"] = _number(d["ground_emissivity"], _join(path, "ground_emissivity"), fail,
                                          lo=0.0, lo_open=True, hi=1.0)
    if "encoding" in d:
        kw["encoding"] = _string(d["encoding"], _join(path, "encoding"), fail, choices=("mono8", "mono16"))
    if "band_um" in d:
        band = _vector(d["band_um"], _join(path, "band_um"), fail, 2, lo=0.0, lo_open=True, unit="um")
        if band[1] <= band[0]:
            fail(_join(path, "band_um"), "[lower, upper] with lower < upper (micrometres)", d["band_um"])
        kw["band_um"] = band
    if "target_parts" in d:
        kw["target_parts"] = _parts_from_list(d["target_parts"], _join(path, "target_parts"), fail)
    t_min = kw.get("t_min_k", base.t_min_k)
    t_max = kw.get("t_max_k", base.t_max_k)
    if t_min >= t_max:
        key = "t_max_k" if "t_max_k" in d else "t_min_k"
        other = "t_min_k" if key == "t_max_k" else "t_max_k"
        rel = ">" if key == "t_max_k" else "<"
        fail(_join(path, key), f"a temperature {rel} {path}.{other} ({kw.get(other, getattr(base, other)):g} K)",
             d[key])
    return IrSettings(**kw)


def _origin_from_dict(d, path: str, fail: _Fail) -> GeodeticOrigin:
    if d is None:
        return DEFAULT_ORIGIN
    _mapping(d, path, fail, ("lat_deg", "lon_deg", "alt_m"))
    return GeodeticOrigin(
        _number(d.get("lat_deg", DEFAULT_ORIGIN.lat_deg), _join(path, "lat_deg"), fail, lo=-90.0, hi=90.0, unit="deg"),
        _number(d.get("lon_deg", DEFAULT_ORIGIN.lon_deg), _join(path, "lon_deg"), fail, lo=-180.0, hi=180.0, unit="deg"),
        _number(d.get("alt_m", DEFAULT_ORIGIN.alt_m), _join(path, "alt_m"), fail, lo=-1000.0, hi=100_000.0, unit="m"),
    )


def _wind_from_dict(d, path: str, fail: _Fail) -> tuple[float, float, float]:
    if d is None:
        return _VEC0
    keys = ("n_mps", "e_mps", "d_mps")
    _mapping(d, path, fail, keys)
    return tuple(_number(d.get(k, 0.0), _join(path, k), fail, lo=-100.0, hi=100.0, unit="m/s") for k in keys)


# --------------------------------------------------------------------------- scenario

_TOP_KEYS = ("name", "description", "origin", "duration_s", "frame_rate_hz", "seed",
             "observer", "target", "camera", "ir", "wind", "nav_noise")


def _check_paths(observer: Motion, target: Motion, t_s: np.ndarray, fail: _Fail) -> None:
    """The commanded paths stay finite and apart at every frame."""
    with np.errstate(all="ignore"):
        p_obs = observer.state(t_s).p_ned_m
        p_tgt = target.state(t_s).p_ned_m
        if not np.all(np.isfinite(p_obs)):
            fail("observer.motion", "a path that stays finite over duration_s", "overflow")
        if not np.all(np.isfinite(p_tgt)):
            fail("target.motion", "a path that stays finite over duration_s", "overflow")
        r = np.linalg.norm(p_tgt - p_obs, axis=-1)
    k = int(np.argmin(r))
    if not r[k] >= MIN_SEPARATION_M:
        fail.text("target.motion", f"a path at least {MIN_SEPARATION_M:g} m from the observer at every frame",
                  f"{r[k]:.3g} m at t = {t_s[k]:.3f} s")


def scenario_from_dict(d, source="<dict>") -> Scenario:
    """Validate a parsed scenario mapping and build the :class:`Scenario`; raises :class:`ScenarioError`.

    ``source`` names the origin in error messages (a file path, or ``"<dict>"``); a ``Path``
    becomes ``Scenario.source_path``.  ``d`` is not modified.
    """
    fail = _Fail(source)
    _mapping(d, "", fail, _TOP_KEYS, ("name", "observer", "target"))
    name = _string(d["name"], "name", fail, pattern=NAME_PATTERN, what="a name of letters, digits, '_', '.', '-'")
    description = _string(d.get("description", ""), "description", fail)
    origin = _origin_from_dict(d.get("origin"), "origin", fail)
    duration_s = _number(d.get("duration_s", DEFAULT_DURATION_S), "duration_s", fail,
                         lo=0.0, lo_open=True, hi=MAX_DURATION_S, unit="s")
    rate_hz = _number(d.get("frame_rate_hz", DEFAULT_FRAME_RATE_HZ), "frame_rate_hz", fail,
                      lo=0.0, lo_open=True, hi=MAX_FRAME_RATE_HZ, unit="Hz")
    seed = _integer(d.get("seed", DEFAULT_SEED), "seed", fail, lo=0, hi=2**63 - 1)

    _mapping(d["observer"], "observer", fail, ("motion",), ("motion",))
    obs_motion = _motion_from_dict(d["observer"]["motion"], "observer.motion", fail)
    _mapping(d["target"], "target", fail, ("motion", "disturbance"), ("motion",))
    tgt_base = _motion_from_dict(d["target"]["motion"], "target.motion", fail)
    disturbance = _disturbance_from_dict(d["target"].get("disturbance"), "target.disturbance", fail)

    camera = _camera_from_dict(d.get("camera"), "camera", fail)
    ir = _ir_from_dict(d.get("ir"), "ir", fail)
    wind = _wind_from_dict(d.get("wind"), "wind", fail)
    nav_noise = DEFAULT_NAV_NOISE
    if "nav_noise" in d:  # a case of config/noise_cases.yaml: the telemetry's navigation errors (groundsim.world.nav_errors)
        nav_noise = _string(d["nav_noise"], "nav_noise", fail, choices=tuple(load_noise_cases()))

    t_s = np.arange(_frame_count(duration_s, rate_hz)) / rate_hz
    _check_paths(obs_motion, tgt_base, t_s, fail)
    if disturbance is None:
        target = VehicleSpec(tgt_base)
    else:
        rng = _stream_rng(seed, "target.disturbance", 0)
        target = VehicleSpec(Perturbed(tgt_base, disturbance.realise(duration_s + SINGER_MARGIN_S, rng)),
                             tgt_base, disturbance)
    sc = Scenario(name=name, description=description, origin=origin, duration_s=duration_s,
                  frame_rate_hz=rate_hz, seed=seed, observer=VehicleSpec(obs_motion), target=target,
                  camera=camera, ir=ir, wind_ned_mps=wind, nav_noise=nav_noise,
                  source_path=Path(source) if isinstance(source, Path) else None)
    log.debug("scenario %s from %s: %d frames", name, source, sc.frame_count)
    return sc


# --------------------------------------------------------------------------- YAML files


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that rejects duplicate keys and reads ``1e-3`` as a float (YAML 1.2 style)."""


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode, deep: bool = False):
    loader.flatten_mapping(node)
    seen: set = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=True)
        try:
            dup = key in seen
        except TypeError:  # unhashable key: let the base constructor report it
            break
        if dup:
            raise yaml.constructor.ConstructorError("while constructing a mapping", node.start_mark,
                                                    f"found duplicate key {key!r}", key_node.start_mark)
        seen.add(key)
    return yaml.SafeLoader.construct_mapping(loader, node, deep)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def _read_yaml(path) -> Any:
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ScenarioError(path, "(file)", "an existing file", got_text="no such file") from None
    except IsADirectoryError:
        raise ScenarioError(path, "(file)", "a file", got_text="a directory") from None
    except UnicodeDecodeError as e:
        raise ScenarioError(path, "(file)", "UTF-8 text", got_text=f"undecodable byte at offset {e.start}") from None
    except OSError as e:
        raise ScenarioError(path, "(file)", "a readable file", got_text=e.strerror or type(e).__name__) from None
    try:
        return yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "(file)"
        problem = " ".join(f"{e.context or ''} {e.problem or ''}".split())
        raise ScenarioError(path, where, "valid YAML", got_text=problem or "a syntax error",
                            line=mark.line + 1 if mark else None) from None
    except yaml.YAMLError as e:
        raise ScenarioError(path, "(file)", "valid YAML", got_text=" ".join(str(e).split())) from None


def load_scenario(path) -> Scenario:
    """Read and validate one scenario file; raises :class:`ScenarioError` (one line) on any problem."""
    return scenario_from_dict(_read_yaml(path), source=Path(path))


def scenarios_dir() -> Path:
    """The repository's ``config/scenarios`` directory (found relative to this file)."""
    return _CONFIG_DIR / "scenarios"


def reference_scenario_paths() -> dict[str, Path]:
    """Shipped scenarios, name (file stem) -> path: P1, P2, P3, P1g, P2g, P3g, H1, H2, H3 first,
    then any others alphabetically."""
    d = scenarios_dir()
    if not d.is_dir():
        raise ScenarioError(d, "(directory)", "the shipped config/scenarios directory", got_text="missing")
    found = {p.stem: p for p in d.glob("*.yaml")}
    order = [k for k in _REFERENCE_ORDER if k in found] + sorted(k for k in found if k not in _REFERENCE_ORDER)
    return {k: found[k] for k in order}


# --------------------------------------------------------------------------- noise cases

_NOISE_KEYS = ("description", "pixel_sigma_px", "attitude_white_sigma_deg", "attitude_bias_sigma_deg",
               "camera_position_white_sigma_m", "camera_position_offset_m", "camera_position_drift_mps")


def noise_cases_from_dict(d, source="<dict>") -> dict[str, NoiseCase]:
    """Validate a parsed noise-case mapping ``{name: {fields}}`` (angles in degrees) into NoiseCases."""
    fail = _Fail(source)
    if not isinstance(d, dict) or not d:
        fail("", "a non-empty mapping of case name -> fields", d)
    out: dict[str, NoiseCase] = {}
    for name, c in d.items():
        if not isinstance(name, str) or not NAME_PATTERN.match(name):
            fail("", "case names of letters, digits, '_', '.', '-'", name)
        _mapping(c, name, fail, _NOISE_KEYS, ("pixel_sigma_px",))
        num = {k: _number(c.get(k, 0.0), _join(name, k), fail, lo=0.0) for k in _NOISE_KEYS[1:]}
        out[name] = NoiseCase(
            name=name,
            pixel_sigma_px=num["pixel_sigma_px"],
            attitude_white_sigma_rad=math.radians(num["attitude_white_sigma_deg"]),
            attitude_bias_sigma_rad=math.radians(num["attitude_bias_sigma_deg"]),
            camera_position_white_sigma_m=num["camera_position_white_sigma_m"],
            camera_position_offset_m=num["camera_position_offset_m"],
            camera_position_drift_mps=num["camera_position_drift_mps"],
            description=_string(c.get("description", ""), _join(name, "description"), fail),
        )
    return out


def load_noise_cases(path=None) -> dict[str, NoiseCase]:
    """Read ``config/noise_cases.yaml`` (or ``path``): case name -> :class:`NoiseCase`."""
    p = Path(path) if path is not None else _CONFIG_DIR / "noise_cases.yaml"
    return noise_cases_from_dict(_read_yaml(p), source=p)


# --------------------------------------------------------------------------- entry point


def main(argv=None) -> int:
    """``python -m groundsim.world.scenario [FILE ...]``: validate scenario files (default: the shipped
    ones); print one line per file; exit 0 if all are valid, else 2."""
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        paths = [Path(a) for a in args] or list(reference_scenario_paths().values())
    except IrtrackError as e:
        print(f"error: {e}", file=sys.stderr)
        return ScenarioError.exit_code
    rc = 0
    for p in paths:
        try:
            sc = load_scenario(p)
        except ScenarioError as e:
            print(f"error: {e}", file=sys.stderr)
            rc = ScenarioError.exit_code
        else:
            print(f"ok: {p}: {sc.name}, {sc.frame_count} frames at {sc.frame_rate_hz:g} Hz")
    return rc


if __name__ == "__main__":
    sys.exit(main())
