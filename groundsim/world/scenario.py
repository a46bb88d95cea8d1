"""Scenario files: their schema, their validation, and the typed objects everybody else uses.

A scenario is a YAML file in ``config/scenarios/`` (schema and examples: ``docs/scenarios.md``).
:func:`load_scenario` reads one into a frozen :class:`Scenario`; :func:`scenario_from_dict` does
the same for an already-parsed mapping.  Geometry is in local NED about ``origin`` (see
``onboard.core.frames``), angles in degrees in the file and radians inside, a unit in every key.

The file schema is a set of models of the one config system (:mod:`onboard.core.schema`: strict
pydantic v2 dataclasses, ``extra="forbid"``, one YAML loader): :class:`ScenarioFile` and the models
it nests (one per YAML mapping, the motion models told apart by ``model``); they build the runtime
objects (:class:`Scenario` ...), which are models of the same system too.  A case of
``config/noise_cases.yaml`` is read straight into a :class:`~groundsim.world.noise_cases.NoiseCase`.  Validation is complete at load: unknown keys (with a
"did you mean"), wrong types, wrong vector lengths, non-finite numbers, out-of-range values, unknown
model names, inconsistent pairs (``t_min_k >= t_max_k``), bad YAML syntax and unreadable files all
raise :class:`ScenarioError` (a :class:`~onboard.core.schema.SchemaError`), whose message is one line::

    <file>: <field.path>: expected <what>, got <value>

Entry points print that line and exit with :attr:`ScenarioError.exit_code` (2); ``python -m
groundsim.world.scenario [FILE ...]`` does exactly that (no argument: every shipped scenario).

Randomness is data until it is realised: a target's ``disturbance`` is a
:class:`SingerDisturbance` spec; ``scenario.target_motion(run_seed)`` realises it with a generator
drawn from ``scenario.rng("target.disturbance", run_seed)``, which depends only on the scenario's
``seed``, the run seed and the stream name.  ``scenario.target.motion`` is run 0's realisation.

Several observers (``observers:`` instead of ``observer:``, a fleet): :class:`ObserverSpec` each, one shared
world; :meth:`Scenario.observer_views` gives one single-observer scenario per observer, with its own boot clock
and its own draws of the streams in :data:`OBSERVER_STREAMS`.  Every scenario has a simulated UTC of t = 0,
``start_time_utc`` (``Scenario.start_time_utc_us``).
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import logging
import math
import sys
import zlib
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BeforeValidator

from groundsim.world.motion import Motion, Perturbed, SingerPerturbation
from groundsim.world.motion_files import MOTION_MODELS, MotionFile
from groundsim.world.noise_cases import NoiseCase, load_noise_cases, noise_cases_from_dict, noise_cases_path
from groundsim.world.render.scene_config import SceneConfig
from groundsim.world.render.settings import IrSettings, TargetPart
from groundsim.world.spec import (
    NAME,
    NAME_PATTERN,
    ScenarioError,
    SpecFail,
    check_integer,
    check_mapping,
    check_number,
    check_string,
    read_spec_yaml,
    scenario_model,
)
from onboard.core.camera_section import PinholeSection
from onboard.core.errors import ConfigError, IrtrackError
from onboard.core.frames import CameraMount, GeodeticOrigin, PinholeIntrinsics
from onboard.core.schema import (
    Instance,
    Integer,
    Invalid,
    NonNegativeFloat,
    Number,
    Numbers,
    SchemaError,
    Text,
    build,
    check_value,
    did_you_mean,
)

__all__ = [
    "NAME_PATTERN",
    "ScenarioError",
    "SingerDisturbance",
    "VehicleSpec",
    "OtherTarget",
    "GimbalSpec",
    "CameraSpec",
    "ObserverSpec",
    "Scenario",
    "OBSERVER_STREAMS",
    "DEFAULT_START_TIME_UTC",
    "parse_utc_us",
    "NoiseCase",
    "MOTION_MODELS",
    "REFERENCE_GIMBAL",
    "DEFAULT_ORIGIN",
    "load_scenario",
    "scenario_digest",
    "scenario_from_dict",
    "reference_scenario_paths",
    "resolve_scenario_path",
    "refuse_duplicate_scenarios",
    "scenarios_dir",
    "noise_cases_path",
    "load_noise_cases",
    "noise_cases_from_dict",
    "read_spec_yaml",
    "SpecFail",
    "too_close",
    "check_apart",
    "check_number",
    "check_integer",
    "check_string",
    "check_mapping",
    "main",
]

log = logging.getLogger(__name__)

MAX_DURATION_S = 3600.0  # one hour: longer runs are not scenarios but campaigns
MAX_FRAME_RATE_HZ = 1000.0
#: the slowest camera at least, Hz: thermal cores run at 9 Hz or faster; below 1 Hz a run is not a video, and a rate
#: near 0 made the renderer size its buffers by 1 / rate
MIN_FRAME_RATE_HZ = 1.0
#: ``ir.band_um`` within this span, micrometres: from the near infrared to the far; a band in metres (7.5e-6) is
#: refused rather than rendered as no radiance at all
BAND_UM = (0.5, 100.0)
MAX_SINGER_SIGMA_MPS2 = 100.0  # ~10 g: beyond it a "disturbance" is not one
#: a scene temperature (air, sky, ground) lies in this span, kelvin: the coldest clear sky and the hottest ground on
#: Earth stay inside it, and a temperature in Celsius typed as kelvin (15 for 288.15) falls below it
SCENE_TEMPERATURE_K = (150.0, 400.0)
#: a hot thing's temperature (a target part, the camera's span, its NETD reference) at most, kelvin: an engine's
#: exhaust or a flare burns below it
HOT_TEMPERATURE_MAX_K = 3000.0
MIN_SEPARATION_M = 1.0  # observer and target (commanded paths) must stay this far apart at every frame
SINGER_MARGIN_S = 1.0  # a disturbance is realised this long past duration_s (no clamping at the end)
FRAME_COUNT_EPS = 1e-9  # k < duration * rate, robust to 0.1 * 30 = 3.0000000000000004

DEFAULT_ORIGIN = GeodeticOrigin(32.0, 118.8, 0.0)  # Nanjing, see REFERENCE_SCENARIOS.md
DEFAULT_DURATION_S = 10.0
DEFAULT_FRAME_RATE_HZ = 30.0
DEFAULT_SEED = 0
DEFAULT_NAV_NOISE = "RTK"  # navigation errors of the telemetry when nothing else is asked (groundsim.world.nav_errors)
#: the simulated UTC of t_s = 0 when a scenario names none: fixed, so a run at --rate max is reproducible
DEFAULT_START_TIME_UTC = "2026-01-01T12:00:00Z"
MAX_OBSERVERS = 16
#: ``camera.intrinsics.width_px`` / ``height_px`` at most: beyond the thermal cores a drone carries (640 x 512
#: here, 1280 x 1024 the largest uncooled ones), and one float32 image of the renderer stays at 64 MiB (it holds
#: several per camera)
MAX_IMAGE_SIDE_PX = 4096
#: ``ir.supersample`` at most: 64 sub-samples per pixel side are 1/64 px apart, far finer than the optics' blur
#: (0.6 px sigma); more only multiplies the rays, which ``ir.max_target_rays`` caps anyway
MAX_SUPERSAMPLE = 64
#: ``ir.max_target_rays`` at most: a million rays cost about 0.2 s of one core per frame (a few bytes each), so a
#: scenario at that budget still runs to its end; beyond it a close target would stall the simulation
MAX_TARGET_RAYS = 1_000_000
#: ``ir.noise_bank_frames`` at most: each frame reads the bank at a random offset, so two frames already give
#: width x height + 1 distinct windows; more frames only make two frames' windows overlap less
MAX_NOISE_BANK_FRAMES = 64
#: the noise banks' size at most (frames x width x height x 4 bytes of float32, summed over the observers' cameras):
#: each renderer holds its bank for the whole run, in every worker process of a campaign or an eval
MAX_NOISE_BANK_BYTES = 256 * 2**20
#: a fleet vehicle's boot clock reads between these at t_s = 0 unless the file says (powered on before take-off)
FLEET_BOOT_MIN_US, FLEET_BOOT_SPAN_MS = 1_000_000, 600_000
#: random streams that belong to one observer (its camera, gimbal and navigation) rather than to the shared world:
#: in a fleet, each observer's view draws them from its own stream (Scenario.rng)
OBSERVER_STREAMS = frozenset({"nav.errors", "gimbal.pointing_phase", "render.noise", "render.sensor"})

_CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"
_REFERENCE_ORDER = ("P1", "P2", "P3", "P1g", "P2g", "P3g", "H1", "H2", "H3")


_VEC3 = Annotated[tuple[float, ...], Numbers(3)]
_VEC3_M = Annotated[tuple[float, ...], Numbers(3, unit="m")]
_ZERO3 = (0.0, 0.0, 0.0)


# --------------------------------------------------------------------------- typed objects


@scenario_model
class SingerDisturbance:
    """Random (Singer) target acceleration, as data: 1-sigma per horizontal axis (N, E) and for D,
    correlation time ``tau_s``.  :meth:`realise` turns it into a ``SingerPerturbation`` path."""

    sigma_horizontal_mps2: Annotated[float, Number(0.0, MAX_SINGER_SIGMA_MPS2, unit="m/s^2")]
    sigma_vertical_mps2: Annotated[float, Number(0.0, MAX_SINGER_SIGMA_MPS2, unit="m/s^2")]
    tau_s: Annotated[float, Number(0.0, lo_open=True, unit="s")]

    @property
    def sigma_ned_mps2(self) -> tuple[float, float, float]:
        h = float(self.sigma_horizontal_mps2)
        return (h, h, float(self.sigma_vertical_mps2))

    def realise(self, duration_s: float, rng: np.random.Generator) -> SingerPerturbation:
        """One realisation over ``[0, duration_s]``: position and velocity offsets start at zero."""
        return SingerPerturbation(duration_s, self.sigma_ned_mps2, float(self.tau_s), rng)


def _is_motion(m: Any) -> bool:
    return callable(getattr(m, "state", None))


_MOTION_CHECK = Instance(object, what="a motion model with a state(t_s) method", check=_is_motion)
_MOTION = Annotated[Any, _MOTION_CHECK]


@scenario_model
class VehicleSpec:
    """One vehicle's path.

    ``motion``: what it flies (a ``groundsim.world.motion`` model with ``state(t_s)``); for a target with
    a ``disturbance`` this is already ``Perturbed(base_motion, <run 0 realisation>)``.
    ``base_motion``: the deterministic model (defaults to ``motion``).  ``disturbance``: the spec
    of the random part, or ``None``.  Other realisations: :meth:`realise`.
    """

    motion: _MOTION
    base_motion: Annotated[Any | None, _MOTION_CHECK] = None
    disturbance: Annotated[SingerDisturbance | None, Instance(SingerDisturbance, what="a SingerDisturbance")] = None

    def __post_init__(self) -> None:
        if self.base_motion is None:
            if self.disturbance is not None:
                raise Invalid("base_motion", "the unperturbed model when a disturbance is given")
            object.__setattr__(self, "base_motion", self.motion)

    def realise(self, duration_s: float, rng: np.random.Generator) -> Motion:
        """``base_motion`` plus a fresh realisation of ``disturbance`` drawn from ``rng``."""
        if self.disturbance is None:
            return self.base_motion
        return Perturbed(self.base_motion, self.disturbance.realise(duration_s, rng))


@scenario_model
class GimbalSpec:
    """A gimbal that keeps the target near the image centre with a slowly varying pointing error:
    per NED axis a sinusoid of amplitude ``pointing_error_frac_of_range[i] * range`` and period
    ``pointing_error_period_s[i]`` (phase: the pointing model's choice).  Defaults: the reference
    study's pointing, 3 %, 2 %, 1.5 % of the range, periods 7 s, 5 s, 3 s."""

    pointing_error_frac_of_range: Annotated[tuple[float, ...], Numbers(3, lo=0.0)] = (0.03, 0.02, 0.015)
    pointing_error_period_s: Annotated[tuple[float, ...], Numbers(3, lo=0.0, lo_open=True, unit="s")] = (7.0, 5.0, 3.0)


#: The reference study's pointing: 3 %, 2 %, 1.5 % of the range, periods 7 s, 5 s, 3 s.
REFERENCE_GIMBAL = GimbalSpec()


@scenario_model
class CameraSpec:
    """The camera: intrinsics, its pod mount on the observer, and an optional gimbal (``None`` = a
    fixed pod; the observer then yaws toward the target)."""

    intrinsics: Annotated[PinholeIntrinsics, Instance(PinholeIntrinsics, what="a PinholeIntrinsics")] = (
        dataclasses.field(default_factory=PinholeIntrinsics.vue_pro_640)
    )
    mount: Annotated[CameraMount, Instance(CameraMount, what="a CameraMount")] = dataclasses.field(
        default_factory=CameraMount
    )
    gimbal: Annotated[GimbalSpec | None, Instance(GimbalSpec, what="a GimbalSpec")] = REFERENCE_GIMBAL


@scenario_model(kw_only=True)
class ObserverSpec:
    """One observer of a fleet (``observers`` in the file): its ``name`` (the vehicle's name: frame key
    ``irtrack/<name>/ir/frame``, ``groundsim run --mavlink NAME=ENDPOINT``), its path (``vehicle``), its
    ``camera``, its navigation-error case ``nav_noise`` and ``boot_start_us``, what its boot clock reads at
    scenario time 0 (different per vehicle, as real autopilots powered on at different times)."""

    name: NAME
    vehicle: Annotated[VehicleSpec, Instance(VehicleSpec, what="a VehicleSpec")]
    camera: Annotated[CameraSpec, Instance(CameraSpec, what="a CameraSpec")]
    nav_noise: Annotated[str, Text(pattern=NAME_PATTERN.pattern, what="a noise-case name")] = DEFAULT_NAV_NOISE
    boot_start_us: Annotated[int, Integer(0, 2**40 - 1)] = FLEET_BOOT_MIN_US


def parse_utc_us(text: str) -> int:
    """``2026-01-01T12:00:00Z`` (ISO 8601 with a UTC offset) -> microseconds since the UNIX epoch; ValueError
    for a malformed text or one without an offset (a local time would make runs differ between machines)."""
    t = datetime.datetime.fromisoformat(str(text).strip().replace("Z", "+00:00").replace("z", "+00:00"))
    if t.tzinfo is None:
        raise ValueError(f"{text!r} has no UTC offset")
    delta = t - datetime.datetime(1970, 1, 1, tzinfo=datetime.UTC)
    return (delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds


def _frame_count(duration_s: float, frame_rate_hz: float) -> int:
    return max(1, math.ceil(duration_s * frame_rate_hz - FRAME_COUNT_EPS))


def _stream_rng(seed: int, stream: str, run_seed: int) -> np.random.Generator:
    key = zlib.crc32(stream.encode("utf-8"))
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(run_seed), key]))


@scenario_model(kw_only=True)
class Scenario:
    """One simulated encounter (see the module docstring and ``docs/scenarios.md``).

    ``observer``/``target``: :class:`VehicleSpec` in local NED about ``origin``; ``camera``: on the
    observer; ``ir``: the renderer's settings; ``wind_ned_mps``: (n, e, d) m/s; ``seed``: the root
    of every random stream of the scenario (see :meth:`rng`); ``source_path``: the file it came
    from, or ``None``; ``start_time_utc_us``: the simulated UTC of ``t_s = 0`` (us since the UNIX epoch).

    A fleet (``observers``, :class:`ObserverSpec`, one shared world and targets): ``observer``, ``camera`` and
    ``nav_noise`` are the first observer's, so code that knows one observer sees that one;
    :meth:`observer_views` gives one single-observer scenario per observer (``observer_name`` and
    ``boot_start_us`` set, its own streams of :data:`OBSERVER_STREAMS`).  ``boot_start_us`` None: the simulator's
    default boot clock.
    """

    name: NAME
    description: Annotated[str, Text(empty=True)] = ""
    origin: Annotated[GeodeticOrigin, Instance(GeodeticOrigin, what="a GeodeticOrigin")] = DEFAULT_ORIGIN
    duration_s: Annotated[float, Number(0.0, MAX_DURATION_S, lo_open=True, unit="s")] = DEFAULT_DURATION_S
    frame_rate_hz: Annotated[float, Number(MIN_FRAME_RATE_HZ, MAX_FRAME_RATE_HZ, unit="Hz")] = DEFAULT_FRAME_RATE_HZ
    seed: Annotated[int, Integer(0, 2**63 - 1)] = DEFAULT_SEED
    observer: Annotated[VehicleSpec, Instance(VehicleSpec, what="a VehicleSpec")]
    target: Annotated[VehicleSpec, Instance(VehicleSpec, what="a VehicleSpec")]
    camera: Annotated[CameraSpec, Instance(CameraSpec, what="a CameraSpec")] = dataclasses.field(
        default_factory=CameraSpec
    )
    ir: Annotated[IrSettings, Instance(IrSettings, what="an IrSettings")] = dataclasses.field(
        default_factory=IrSettings
    )
    wind_ned_mps: Annotated[tuple[float, ...], Numbers(3, unit="m/s")] = _ZERO3
    nav_noise: Annotated[
        str, Text(pattern=NAME_PATTERN.pattern, what="a noise-case name of config/noise_cases.yaml")
    ] = DEFAULT_NAV_NOISE
    source_path: Annotated[Path | None, Instance(Path, what="a path")] = None
    # clouds, terrain, distractors, the camera model (docs/scenes.md); all off: today's clean sky
    scene: Annotated[SceneConfig, Instance(SceneConfig, what="a SceneConfig")] = dataclasses.field(
        default_factory=SceneConfig
    )
    # more targets, flown like ``target`` and drawn as scene objects 1..n (OtherTarget)
    other_targets: Annotated[tuple, Instance(tuple, what="a tuple of OtherTarget")] = ()
    start_time_utc_us: Annotated[int, Integer(0, 2**62)] = dataclasses.field(
        default_factory=lambda: parse_utc_us(DEFAULT_START_TIME_UTC)
    )
    observers: Annotated[tuple, Instance(tuple, what="a tuple of ObserverSpec")] = ()
    observer_name: Annotated[str | None, Text(pattern=NAME_PATTERN.pattern, what="an observer name")] = None
    boot_start_us: Annotated[int | None, Integer(0, 2**40 - 1)] = None

    @property
    def is_fleet(self) -> bool:
        """True for a scenario with an ``observers`` list (even of one)."""
        return bool(self.observers)

    def refuse_fleet(self, why: str) -> None:
        """A ConfigError naming ``--scenario`` when this is a fleet scenario, which a command that flies one
        observer would fly as its first alone, without a word; ``why``: what needs one observer, and where to go."""
        if self.is_fleet:
            raise ConfigError(
                f"--scenario: {self.name} is a fleet scenario (its observers list: "
                f"{', '.join(o.name for o in self.observers)}); {why}"
            )

    def observer_views(self) -> tuple[Scenario, ...]:
        """One single-observer scenario per observer of a fleet, in file order (``(self,)`` otherwise): the
        shared world and targets, the observer's path, camera, navigation errors, name and boot clock."""
        if not self.observers:
            return (self,)
        return tuple(
            dataclasses.replace(
                self,
                observer=o.vehicle,
                camera=o.camera,
                nav_noise=o.nav_noise,
                observers=(),
                observer_name=o.name,
                boot_start_us=o.boot_start_us,
            )
            for o in self.observers
        )

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
        (e.g. ``"noise.pixel"``) so adding a stream never shifts another.  An observer's view of a fleet
        (``observer_name`` set) draws the streams of :data:`OBSERVER_STREAMS` from
        ``"observers.<name>.<stream>"``: each vehicle has its own navigation errors, render noise and gimbal
        phases, while the world's streams (targets, scene) stay shared.
        """
        run_seed = check_value(
            Annotated[int, Integer(lo=0)], run_seed, "run_seed", f"<Scenario {self.name}>", ScenarioError
        )
        if self.observer_name is not None and stream in OBSERVER_STREAMS:
            stream = f"observers.{self.observer_name}.{stream}"
        return _stream_rng(self.seed, stream, run_seed)

    def target_motion(self, run_seed: int = 0) -> Motion:
        """The target's path for run ``run_seed``: its base model plus that run's disturbance
        realisation (the base model alone when it has none).  ``target_motion(0) is target.motion``."""
        run_seed = check_value(
            Annotated[int, Integer(lo=0)], run_seed, "run_seed", f"<Scenario {self.name}>", ScenarioError
        )
        if run_seed == 0 or self.target.disturbance is None:
            return self.target.motion
        return self.target.realise(self.duration_s + SINGER_MARGIN_S, self.rng("target.disturbance", run_seed))

    def other_target_motion(self, index: int, run_seed: int = 0) -> Motion:
        """Path of ``other_targets[index]`` for run ``run_seed`` (its disturbance from the stream
        ``"other_targets[<index>].disturbance"``; run 0's is ``other_targets[index].vehicle.motion``)."""
        run_seed = check_value(
            Annotated[int, Integer(lo=0)], run_seed, "run_seed", f"<Scenario {self.name}>", ScenarioError
        )
        v = self.other_targets[index].vehicle
        if run_seed == 0 or v.disturbance is None:
            return v.motion
        return v.realise(self.duration_s + SINGER_MARGIN_S, self.rng(f"other_targets[{index}].disturbance", run_seed))

    def observer_motion(self, run_seed: int = 0) -> Motion:
        """The observer's path (deterministic: observers carry no disturbance)."""
        return self.observer.motion


# --------------------------------------------------------------------------- the file schema
# One model per YAML mapping (docs/scenarios.md); each builds the runtime object above.  Defaults are
# the runtime defaults: an absent key and its default value give the same scenario.

_VUE = PinholeIntrinsics.vue_pro_640()
_IR = IrSettings()
_SCENE_K = Annotated[float, Number(*SCENE_TEMPERATURE_K, unit="K")]
_HOT_K = Annotated[float, Number(SCENE_TEMPERATURE_K[0], HOT_TEMPERATURE_MAX_K, unit="K")]


@scenario_model(kw_only=True)
class DisturbanceFile:
    model: Annotated[Literal["singer"], Text()]
    sigma_horizontal_mps2: Annotated[float, Number(0.0, MAX_SINGER_SIGMA_MPS2, unit="m/s^2")]
    sigma_vertical_mps2: Annotated[float, Number(0.0, MAX_SINGER_SIGMA_MPS2, unit="m/s^2")]
    tau_s: Annotated[float, Number(0.0, lo_open=True, unit="s")]

    def spec(self) -> SingerDisturbance:
        return SingerDisturbance(self.sigma_horizontal_mps2, self.sigma_vertical_mps2, self.tau_s)


@scenario_model(kw_only=True)
class ObserverFile:
    motion: MotionFile


@scenario_model(kw_only=True)
class TargetFile:
    motion: MotionFile
    disturbance: DisturbanceFile | None = None


@scenario_model(kw_only=True)
class IntrinsicsFile(PinholeSection):
    fx_px: Annotated[float, Number(0.0, lo_open=True)] = _VUE.fx_px
    fy_px: Annotated[float, Number(0.0, lo_open=True)] = _VUE.fy_px
    cx_px: Annotated[float | None, Number()] = None
    cy_px: Annotated[float | None, Number()] = None
    width_px: Annotated[int, Integer(1, MAX_IMAGE_SIDE_PX)] = _VUE.width_px
    height_px: Annotated[int, Integer(1, MAX_IMAGE_SIDE_PX)] = _VUE.height_px
    distortion: Annotated[tuple[float, ...], Numbers(5, what="a list of 5 finite numbers (k1, k2, p1, p2, k3)")] = (
        tuple(_VUE.distortion)
    )


@scenario_model(kw_only=True)
class MountFile:
    lever_arm_frd_m: _VEC3_M = _ZERO3
    roll_deg: Annotated[float, Number(-360.0, 360.0, unit="deg")] = 0.0
    pitch_deg: Annotated[float, Number(-360.0, 360.0, unit="deg")] = 0.0
    yaw_deg: Annotated[float, Number(-360.0, 360.0, unit="deg")] = 0.0


@scenario_model(kw_only=True)
class CameraFile:
    intrinsics: IntrinsicsFile = dataclasses.field(default_factory=IntrinsicsFile)
    mount: MountFile = dataclasses.field(default_factory=MountFile)
    # absent: the reference pointing; explicit null: a fixed pod
    gimbal: GimbalSpec | None = REFERENCE_GIMBAL

    def spec(self) -> CameraSpec:
        m = self.mount
        mount = CameraMount.from_euler_deg(
            m.lever_arm_frd_m, m.roll_deg, m.pitch_deg, m.yaw_deg, gimballed=self.gimbal is not None
        )
        return CameraSpec(self.intrinsics.pinhole(), mount, self.gimbal)


@scenario_model(kw_only=True)
class TargetPartFile:
    name: Annotated[str, Text(empty=True, what="a string")]
    shape: Annotated[Literal["ellipsoid", "box"], Text()]
    center_frd_m: _VEC3_M
    half_extent_m: Annotated[tuple[float, ...], Numbers(3, lo=0.0, lo_open=True, unit="m")]
    temperature_k: _HOT_K
    emissivity: Annotated[float, Number(0.0, 1.0, lo_open=True)]

    def part(self) -> TargetPart:
        return TargetPart(
            self.name, self.shape, self.center_frd_m, self.half_extent_m, self.temperature_k, self.emissivity
        )


def _nonempty(value: Any) -> Any:
    if isinstance(value, (list, tuple)) and not value:
        raise Invalid(
            "",
            "a non-empty list of parts (mappings with name, shape, center_frd_m, half_extent_m, "
            "temperature_k, emissivity)",
            value,
        )
    return tuple(value) if isinstance(value, list) else value


@scenario_model(kw_only=True)
class OtherTarget:
    """One more target: its path (``vehicle``, flown by JSBSim like the scenario's target) and the parts it
    is drawn with (``parts``: ``TargetPart``s; the scenario's ``ir.target_parts`` when not given)."""

    vehicle: Annotated[VehicleSpec, Instance(VehicleSpec, what="a VehicleSpec")]
    parts: Annotated[tuple, Instance(tuple, what="a tuple of TargetPart")]


@scenario_model(kw_only=True)
class OtherTargetFile:
    """An entry of ``other_targets``: as ``target``, plus its own ``target_parts`` (default: ``ir``'s)."""

    motion: MotionFile
    disturbance: DisturbanceFile | None = None
    target_parts: Annotated[tuple[TargetPartFile, ...], BeforeValidator(_nonempty)] = ()


@scenario_model(kw_only=True)
class IrFile:
    """``ir``: the renderer's settings (:class:`~groundsim.world.render.settings.IrSettings`, which keeps its own
    consistency checks); target parts replace the default quadcopter."""

    band_um: Annotated[tuple[float, ...], Numbers(2, BAND_UM[0], hi=BAND_UM[1], unit="um")] = _IR.band_um
    t_min_k: _HOT_K = _IR.t_min_k
    t_max_k: _HOT_K = _IR.t_max_k
    encoding: Annotated[Literal["mono8", "mono16"], Text()] = _IR.encoding
    netd_k: NonNegativeFloat = _IR.netd_k
    blur_sigma_px: NonNegativeFloat = _IR.blur_sigma_px
    extinction_per_km: NonNegativeFloat = _IR.extinction_per_km
    air_temperature_k: _SCENE_K = _IR.air_temperature_k
    sky_zenith_k: _SCENE_K = _IR.sky_zenith_k
    sky_horizon_k: _SCENE_K = _IR.sky_horizon_k
    ground_temperature_k: _SCENE_K = _IR.ground_temperature_k
    ground_emissivity: Annotated[float, Number(0.0, 1.0, lo_open=True)] = _IR.ground_emissivity
    target_parts: Annotated[tuple[TargetPartFile, ...], BeforeValidator(_nonempty)] = ()
    netd_reference_k: _HOT_K = _IR.netd_reference_k
    supersample: Annotated[int, Integer(1, MAX_SUPERSAMPLE)] = _IR.supersample
    max_target_rays: Annotated[int, Integer(1, MAX_TARGET_RAYS)] = _IR.max_target_rays
    background_reuse_tol_rad: NonNegativeFloat = _IR.background_reuse_tol_rad
    noise_bank_frames: Annotated[int, Integer(1, MAX_NOISE_BANK_FRAMES)] = _IR.noise_bank_frames

    def __post_init__(self) -> None:
        if self.band_um[1] <= self.band_um[0]:
            raise Invalid("band_um", "[lower, upper] with lower < upper (micrometres)", list(self.band_um))
        if self.t_min_k >= self.t_max_k:
            if self.t_max_k != _IR.t_max_k:
                raise Invalid("t_max_k", f"a temperature > ir.t_min_k ({self.t_min_k:g} K)", self.t_max_k)
            raise Invalid("t_min_k", f"a temperature < ir.t_max_k ({self.t_max_k:g} K)", self.t_min_k)
        names = [p.name for p in self.target_parts]
        for i, name in enumerate(names):
            if name in names[:i]:
                raise Invalid(f"target_parts[{i}].name", "a part name not used before in the list", name)

    def settings(self) -> IrSettings:
        kw = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "target_parts"}
        if self.target_parts:
            kw["target_parts"] = tuple(p.part() for p in self.target_parts)
        return IrSettings(**kw)


@scenario_model(kw_only=True)
class OriginFile:
    lat_deg: Annotated[float, Number(-90.0, 90.0, unit="deg")] = DEFAULT_ORIGIN.lat_deg
    lon_deg: Annotated[float, Number(-180.0, 180.0, unit="deg")] = DEFAULT_ORIGIN.lon_deg
    alt_m: Annotated[float, Number(-1000.0, 100_000.0, unit="m")] = DEFAULT_ORIGIN.alt_m


@scenario_model(kw_only=True)
class WindFile:
    n_mps: Annotated[float, Number(-100.0, 100.0, unit="m/s")] = 0.0
    e_mps: Annotated[float, Number(-100.0, 100.0, unit="m/s")] = 0.0
    d_mps: Annotated[float, Number(-100.0, 100.0, unit="m/s")] = 0.0


@scenario_model(kw_only=True)
class FleetObserverFile:
    """An entry of ``observers``: a named observer with its own path; its camera and navigation errors default
    to the scenario's ``camera`` and ``nav_noise``, its boot clock at t = 0 to one drawn from the seed and name."""

    name: NAME
    motion: MotionFile
    camera: CameraFile | None = None
    nav_noise: Annotated[str | None, Text()] = None
    boot_time_s: Annotated[float | None, Number(0.0, 1e6, unit="s")] = None

    def boot_start_us(self, seed: int) -> int:
        if self.boot_time_s is not None:
            return round(self.boot_time_s * 1e6)
        # whole milliseconds: the boot time MAVLink carries (time_boot_ms) is then exact
        rng = _stream_rng(seed, f"observers.{self.name}.boot_clock", 0)
        return FLEET_BOOT_MIN_US + 1000 * int(rng.integers(0, FLEET_BOOT_SPAN_MS))


def _utc_text(value: Any) -> Any:
    if isinstance(value, datetime.datetime):  # YAML reads an unquoted timestamp as one
        value = value.isoformat()
    try:
        ok = parse_utc_us(value) >= 0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise Invalid("", "an ISO 8601 UTC time such as 2026-01-01T12:00:00Z, not before 1970", value)
    return value


@scenario_model(kw_only=True)
class ScenarioFile:
    """A scenario file's top level (``docs/scenarios.md``)."""

    name: NAME
    description: Annotated[str, Text(empty=True)] = ""
    origin: OriginFile = dataclasses.field(default_factory=OriginFile)
    duration_s: Annotated[float, Number(0.0, MAX_DURATION_S, lo_open=True, unit="s")] = DEFAULT_DURATION_S
    frame_rate_hz: Annotated[float, Number(MIN_FRAME_RATE_HZ, MAX_FRAME_RATE_HZ, unit="Hz")] = DEFAULT_FRAME_RATE_HZ
    seed: Annotated[int, Integer(0, 2**63 - 1)] = DEFAULT_SEED
    observer: ObserverFile | None = None
    # several observers (a fleet): one shared world and targets, each its own path, camera, errors, boot clock
    observers: tuple[FleetObserverFile, ...] = ()
    # the simulated UTC of t_s = 0 (SYSTEM_TIME, the truth's time_unix_us)
    start_time_utc: Annotated[str, BeforeValidator(_utc_text)] = DEFAULT_START_TIME_UTC
    target: TargetFile
    camera: CameraFile = dataclasses.field(default_factory=CameraFile)
    ir: IrFile = dataclasses.field(default_factory=IrFile)
    wind: WindFile = dataclasses.field(default_factory=WindFile)
    # a case of config/noise_cases.yaml: the telemetry's navigation errors (groundsim.world.nav_errors)
    nav_noise: Annotated[str, Text()] = DEFAULT_NAV_NOISE
    # clouds, terrain, distractors, the camera model (groundsim.world.render.scene_config, docs/scenes.md)
    scene: SceneConfig = dataclasses.field(default_factory=SceneConfig)
    # more targets, each with its own motion and thermal parts (drawn as scene objects 1..n)
    other_targets: tuple[OtherTargetFile, ...] = ()

    def __post_init__(self) -> None:
        if self.observer is None and not self.observers:
            raise Invalid("observer", "a value (required)", hint="or several named ones as a list `observers`")
        if self.observer is not None and self.observers:
            raise Invalid("observers", "either observer or observers, not both", got_text="both given")
        if len(self.observers) > MAX_OBSERVERS:
            raise Invalid("observers", f"at most {MAX_OBSERVERS} observers", got_text=f"{len(self.observers)}")
        names = [o.name for o in self.observers]
        for i, name in enumerate(names):
            if name in names[:i]:
                raise Invalid(f"observers[{i}].name", "a name not used by an earlier observer", name)
        # the default case too: a noise-case file without it would otherwise fail the first run, naming an option
        # nobody gave rather than this file
        named = [("nav_noise", self.nav_noise)]
        named += [(f"observers[{i}].nav_noise", o.nav_noise) for i, o in enumerate(self.observers)]
        cases = tuple(load_noise_cases())
        for field_path, case in named:
            if case is not None and case not in cases:
                hint = did_you_mean(case, cases)
                if case == DEFAULT_NAV_NOISE:
                    hint = f"the default case, which {noise_cases_path()} does not define" + (
                        f"; {hint}" if hint else ""
                    )
                raise Invalid(field_path, "one of " + ", ".join(cases), case, hint)
        self._check_noise_bank()

    def _check_noise_bank(self) -> None:
        """The renderers' noise banks (one per observer's camera) fit :data:`MAX_NOISE_BANK_BYTES`: the frame count
        alone is bounded, but a large camera, or many, multiply it."""
        cameras = [o.camera or self.camera for o in self.observers] or [self.camera]
        px = sum(c.intrinsics.width_px * c.intrinsics.height_px for c in cameras)
        frames = self.ir.noise_bank_frames
        if frames * px * 4 > MAX_NOISE_BANK_BYTES:
            most = MAX_NOISE_BANK_BYTES // (px * 4)
            over = f", summed over {len(cameras)} observers' cameras" if len(cameras) > 1 else ""
            raise Invalid(
                "ir.noise_bank_frames",
                f"a noise bank of at most {MAX_NOISE_BANK_BYTES >> 20} MiB (frames x width_px x height_px x 4 bytes"
                f"{over}): " + (f"at most {most} frames" if most else "a smaller camera"),
                got_text=f"{frames} ({frames * px * 4 / 2**20:.0f} MiB)",
            )


def too_close(p_a_ned_m: np.ndarray, p_b_ned_m: np.ndarray) -> tuple[int, float] | None:
    """(frame, distance m) of the closest approach of two paths ((N, 3) at the same frames) when under
    ``MIN_SEPARATION_M`` or not a number (an overflowed path); None while they stay apart: the one separation rule."""
    with np.errstate(all="ignore"):
        r = np.linalg.norm(np.asarray(p_b_ned_m) - np.asarray(p_a_ned_m), axis=-1)
    k = int(np.argmin(r)) if r.size else 0
    return (k, float(r[k])) if r.size and not r[k] >= MIN_SEPARATION_M else None


def check_apart(fail: SpecFail, field: str, expected: str, p_a_ned_m, p_b_ned_m, t_s, what: str = "") -> None:
    """``fail.text(field, expected, ...)`` naming the closest approach (after ``what``) of paths :func:`too_close`."""
    close = too_close(p_a_ned_m, p_b_ned_m)
    if close is not None:
        fail.text(field, expected, f"{what}{close[1]:.3g} m at t = {t_s[close[0]]:.3f} s")


def _check_paths(
    observer: Motion,
    target: Motion,
    t_s: np.ndarray,
    fail: SpecFail,
    field: str = "target.motion",
    observer_field: str = "observer.motion",
    what: str = "the observer",
) -> None:
    """The commanded paths stay finite and apart at every frame."""
    with np.errstate(all="ignore"):
        p_obs = observer.state(t_s).p_ned_m
        p_tgt = target.state(t_s).p_ned_m
        if not np.all(np.isfinite(p_obs)):
            fail(observer_field, "a path that stays finite over duration_s", "overflow")
        if not np.all(np.isfinite(p_tgt)):
            fail(field, "a path that stays finite over duration_s", "overflow")
    check_apart(fail, field, f"a path at least {MIN_SEPARATION_M:g} m from {what} at every frame", p_obs, p_tgt, t_s)


def _fleet(f: ScenarioFile, fail: SpecFail, t_s: np.ndarray) -> tuple[ObserverSpec, ...]:
    """The observers of a fleet file (empty for a single observer): each with the scenario's camera and
    navigation errors unless it has its own, its path checked against the target's and the earlier observers'."""
    out: list[ObserverSpec] = []
    tgt = f.target.motion.motion()
    for i, o in enumerate(f.observers):
        motion = o.motion.motion()
        field = f"observers[{i}].motion"
        _check_paths(motion, tgt, t_s, fail, observer_field=field, what=f"observers[{i}] ({o.name})")
        for j, earlier in enumerate(out):
            _check_paths(
                earlier.vehicle.motion,
                motion,
                t_s,
                fail,
                field,
                f"observers[{j}].motion",
                f"observers[{j}] ({earlier.name})",
            )
        out.append(
            ObserverSpec(
                name=o.name,
                vehicle=VehicleSpec(motion),
                camera=(o.camera or f.camera).spec(),
                nav_noise=o.nav_noise or f.nav_noise,
                boot_start_us=o.boot_start_us(f.seed),
            )
        )
    return tuple(out)


# --------------------------------------------------------------------------- scenario


def scenario_from_dict(d, source="<dict>") -> Scenario:
    """Validate a parsed scenario mapping and build the :class:`Scenario`; raises :class:`ScenarioError`.

    ``source`` names the origin in error messages (a file path, or ``"<dict>"``); a ``Path``
    becomes ``Scenario.source_path``.  ``d`` is not modified.
    """
    fail = SpecFail(source)
    try:
        f = build(ScenarioFile, d, none_is_default=False)
    except SchemaError as exc:
        raise exc.as_(ScenarioError, source) from None
    tgt_base = f.target.motion.motion()
    disturbance = None if f.target.disturbance is None else f.target.disturbance.spec()
    t_s = np.arange(_frame_count(f.duration_s, f.frame_rate_hz)) / f.frame_rate_hz
    fleet = _fleet(f, fail, t_s)
    obs_motion = fleet[0].vehicle.motion if fleet else f.observer.motion.motion()
    obs_field = "observers[0].motion" if fleet else "observer.motion"
    _check_paths(obs_motion, tgt_base, t_s, fail, observer_field=obs_field)
    others = []
    for i, o in enumerate(f.other_targets):
        base = o.motion.motion()
        _check_paths(obs_motion, base, t_s, fail, f"other_targets[{i}].motion", obs_field)
        for j, ob in enumerate(fleet[1:], start=1):
            _check_paths(ob.vehicle.motion, base, t_s, fail, f"other_targets[{i}].motion", f"observers[{j}].motion")
        parts = tuple(p.part() for p in (o.target_parts or f.ir.target_parts)) or _IR.target_parts
        if o.disturbance is None:
            vehicle = VehicleSpec(base)
        else:
            spec = o.disturbance.spec()
            rng = _stream_rng(f.seed, f"other_targets[{i}].disturbance", 0)
            vehicle = VehicleSpec(Perturbed(base, spec.realise(f.duration_s + SINGER_MARGIN_S, rng)), base, spec)
        others.append(OtherTarget(vehicle=vehicle, parts=parts))
    if disturbance is None:
        target = VehicleSpec(tgt_base)
    else:
        rng = _stream_rng(f.seed, "target.disturbance", 0)
        target = VehicleSpec(
            Perturbed(tgt_base, disturbance.realise(f.duration_s + SINGER_MARGIN_S, rng)), tgt_base, disturbance
        )
    try:
        sc = Scenario(
            name=f.name,
            description=f.description,
            origin=GeodeticOrigin(f.origin.lat_deg, f.origin.lon_deg, f.origin.alt_m),
            duration_s=f.duration_s,
            frame_rate_hz=f.frame_rate_hz,
            seed=f.seed,
            observer=VehicleSpec(obs_motion),
            target=target,
            camera=fleet[0].camera if fleet else f.camera.spec(),
            ir=f.ir.settings(),
            wind_ned_mps=(f.wind.n_mps, f.wind.e_mps, f.wind.d_mps),
            nav_noise=fleet[0].nav_noise if fleet else f.nav_noise,
            source_path=Path(source) if isinstance(source, Path) else None,
            scene=f.scene,
            other_targets=tuple(others),
            start_time_utc_us=parse_utc_us(f.start_time_utc),
            observers=fleet,
        )
    except ConfigError as exc:  # a library object's own consistency check (IrSettings, CameraMount ...)
        if isinstance(exc, SchemaError):
            raise exc.as_(ScenarioError, source) from None
        raise ScenarioError(
            source, "(document)", "a consistent scenario", got_text=" ".join(str(exc).split())
        ) from None
    log.debug("scenario %s from %s: %d frames", f.name, source, sc.frame_count)
    return sc


# --------------------------------------------------------------------------- YAML files


def load_scenario(path) -> Scenario:
    """Read and validate one scenario file; raises :class:`ScenarioError` (one line) on any problem."""
    return scenario_from_dict(read_spec_yaml(path), source=Path(path))


def scenario_digest(path) -> str:
    """12 hex digits naming what a scenario file says: SHA-256 of its validated model (:class:`ScenarioFile`, every
    default filled in) without its ``description``.  A comment, the layout, the key order, how a number is written
    or the description leave it as it is; any value a run reads changes it.  Raises :class:`ScenarioError` as
    :func:`load_scenario` does."""
    source = Path(path)
    try:
        f = build(ScenarioFile, read_spec_yaml(source), none_is_default=False)
    except SchemaError as exc:
        raise exc.as_(ScenarioError, source) from None
    # the model's repr lists every field, defaults included, with numbers as Python writes them: canonical text
    text = repr(dataclasses.replace(f, description=""))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:12]


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


def resolve_scenario_path(text: str | Path) -> Path:
    """``--scenario``: an existing file, or a shipped scenario's name (``P1``, ``h2``: case-insensitive).  A
    folder of the name in the current directory (a run's output called ``P1``, say) is no scenario file and does
    not hide the shipped one; a file of the name does, being what was named.

    Neither is a :class:`ScenarioError` naming the shipped scenarios."""
    p = Path(text)
    if p.exists() and not p.is_dir():
        return p
    shipped = reference_scenario_paths()
    by_lower = {name.lower(): path for name, path in shipped.items()}
    found = by_lower.get(str(text).lower())
    if found is not None:
        return found
    raise ScenarioError(
        str(text),
        "(file)",
        "an existing file or one of the shipped scenarios " + ", ".join(shipped),
        got_text="a folder, not a file" if p.is_dir() else "no such file",
    )


def refuse_duplicate_scenarios(
    names: list[str], paths: list[Path], scenario_names: list[str], shared: str = "one set of files"
) -> None:
    """A ConfigError naming --scenario when two entries are the same file or the same scenario name: a command's
    runs and files are keyed by the name, so a second entry would repeat the first's runs, or write a different
    scenario into the first's files (``shared``: what the two would share, for the message)."""
    by_file: dict[Path, str] = {}
    by_name: dict[str, str] = {}
    for given, path, name in zip(names, paths, scenario_names):
        key = Path(path).resolve()
        if key in by_file:
            raise ConfigError(f"--scenario: {by_file[key]} and {given} are the same file ({key}); give it once")
        if name in by_name:
            raise ConfigError(
                f"--scenario: {by_name[name]} and {given} are both scenario {name!r} (their runs would share"
                f" {shared}); give each scenario its own name"
            )
        by_file[key] = by_name[name] = given


# --------------------------------------------------------------------------- entry point


def main(argv=None) -> int:
    """``python -m groundsim.world.scenario [FILE ...]``: validate scenario files (default: the shipped
    ones); print one line per file; exit 0 if all are valid, else 2 (an unknown option too, in one line)."""
    import argparse

    class OneLineParser(argparse.ArgumentParser):  # a usage mistake is one line, as every command's (exit 2)
        def error(self, message: str):
            self.exit(2, f"{self.prog}: {message}\n")

    parser = OneLineParser(
        prog="python -m groundsim.world.scenario",
        description="Validate scenario files (docs/scenarios.md): one line per file, 'ok: ...' or 'error: ...'; "
        "exit 0 when every file is valid, else 2.",
    )
    parser.add_argument("files", nargs="*", metavar="FILE", help="scenario YAML files (default: the shipped ones)")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv).files
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
            fleet = (
                f", {len(sc.observers)} observers ({', '.join(o.name for o in sc.observers)})" if sc.is_fleet else ""
            )
            print(f"ok: {p}: {sc.name}, {sc.frame_count} frames at {sc.frame_rate_hz:g} Hz{fleet}")
    return rc


if __name__ == "__main__":
    sys.exit(main())
