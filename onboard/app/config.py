"""The onboard daemon's configuration: YAML -> typed frozen pydantic dataclasses, strict, loaded once.

Layers, later ones winning: built-in defaults < the YAML file (``--config``) < environment
variables ``IRTRACK_<SECTION>_<FIELD>`` (e.g. ``IRTRACK_MAVLINK_CONNECTION``,
``IRTRACK_CAMERA_INTRINSICS_FX_PX``, ``IRTRACK_VEHICLE``; values are parsed as YAML scalars/flow
collections, so ``IRTRACK_ZENOH_CONNECT='[tcp/10.0.0.2:7447]'`` works) < command-line options.
``IRTRACK_HEALTH_FILE`` is an alias of ``IRTRACK_OUTPUT_HEALTH_FILE`` (the container's health check
reads it too; set with ``IRTRACK_OUTPUT_HEALTH_FILE``, both must agree, and so must a command-line
``output.health_file``).  An unknown ``IRTRACK_<SECTION>_...``
variable of a known section is an error, and so is one a letter or two off a field's variable (a misspelt section);
the tools' own ``IRTRACK_*`` variables are not ours.

The models are those of the one config system, :mod:`onboard.core.schema` (strict pydantic v2,
``extra="forbid"``, one YAML loader, one error format).  Sections are declared where they are consumed
and composed here, each the one declaration of its settings, which its component takes as is: ``pose``
:class:`onboard.core.pose_config.PoseConfig` (the pose buffer's), ``mavlink``
:class:`onboard.io.mavlink_config.MavlinkConfig` (the autopilot link's), ``zenoh``
:class:`onboard.io.zenoh_session.ZenohConfig` (the session's), ``imaging``
:class:`onboard.imaging.preprocess.ImagingParams`, ``record`` :class:`onboard.io.record.RecordConfig`,
``live_view`` :class:`onboard.io.live_view.LiveViewConfig`, ``video`` :class:`onboard.io.video.VideoConfig`; the
others are below.

Every problem raises :class:`OnboardConfigError` (a :class:`~onboard.core.schema.SchemaError`), one line::

    <source>: <field.path>: expected <what>, got <value>[; did you mean '<key>'?]

where ``<source>`` is the file, ``env IRTRACK_...`` or ``--option``; entry points print it and exit
with :attr:`OnboardConfigError.exit_code` (2).  Unknown keys, wrong types (a bool is not a number,
``640.0`` is not an integer), out-of-range values, duplicate YAML keys and bad YAML all fail; ``3e-1``
is a number (YAML 1.2), as in the scenario files.

The schema, with defaults and meaning, is ``config/onboard.yaml`` (every field commented) and the
dataclasses; angles are degrees and durations milliseconds/seconds as the names say, converted
into the radians/microseconds of the core objects where they are read (:meth:`CameraConfig.camera_mount`,
``PoseConfig.window_us``, :meth:`EstimatorConfig.noise_model` ...).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
from collections.abc import Mapping
from typing import Annotated, Any, Literal

import yaml
from pydantic import AfterValidator

from onboard.app.health import DEFAULT_MAX_AGE_S
from onboard.core.camera_section import PinholeSection
from onboard.core.errors import ConfigError
from onboard.core.frames import CameraMount, FrameError, PinholeIntrinsics
from onboard.core.pose_config import ExtrapolationHorizons, OriginConfig, PoseConfig
from onboard.core.schema import (
    Bool,
    Instance,
    Integer,
    Invalid,
    Number,
    Numbers,
    SchemaError,
    Text,
    Texts,
    build,
    config_dataclass,
    did_you_mean,
    is_config_dataclass,
    parse_yaml_text,
    read_yaml,
    show,
    to_plain,
)
from onboard.estimation.guidance import GuidanceConfig
from onboard.estimation.window_problem import (
    SHIPPED_ATTITUDE_BIAS_SIGMA_DEG,
    SHIPPED_ATTITUDE_WHITE_SIGMA_DEG,
    SHIPPED_CAMERA_POSITION_WHITE_SIGMA_M,
    SHIPPED_PIXEL_SIGMA_PX,
)
from onboard.imaging.preprocess import ImagingParams
from onboard.io.live_view import LiveViewConfig
from onboard.io.mavlink_config import MavlinkConfig, parse_connection
from onboard.io.record import RecordConfig
from onboard.io.video import VideoConfig
from onboard.io.zenoh_session import ZenohConfig

__all__ = [
    "OnboardConfigError",
    "MavlinkConfig",
    "ZenohConfig",
    "InputConfig",
    "IntrinsicsConfig",
    "MountConfig",
    "CameraConfig",
    "EstimatorConfig",
    "TimeOffsetConfig",
    "OriginConfig",
    "PoseConfig",
    "OutputConfig",
    "GcsConfig",
    "VideoConfig",
    "FollowConfig",
    "RecordConfig",
    "LiveViewConfig",
    "LoggingConfig",
    "OnboardConfig",
    "load_config",
    "build_config",
    "env_overrides",
    "parse_set_option",
    "config_to_dict",
    "ENV_PREFIX",
]

ENV_PREFIX = "IRTRACK_"
MAX_LEVER_ARM_M = 50.0  # camera.mount.lever_arm_frd_m: each offset at most this, m
ENV_ALIASES = {"IRTRACK_HEALTH_FILE": "output.health_file"}
#: an unknown IRTRACK_* variable at least this alike (difflib's ratio) to a field's variable is taken for a misspelling
ENV_MISSPELT_RATIO = 0.9
DEFAULT_SOURCE = "(defaults)"


class OnboardConfigError(SchemaError):
    """One-line configuration error naming source, field and expectation; ``exit_code`` 2."""

    def __init__(self, source: str, path: str, expected: str, got_text: str, hint: str | None = None):
        super().__init__(source, path, expected, got_text, hint)


# --------------------------------------------------------------------------- sections


@config_dataclass
class InputConfig:
    """``input``: IR frames in (key ``irtrack/<vehicle>/ir/frame``)."""

    max_frame_bytes: Annotated[int, Integer(64, 1 << 31)] = 16 * 1024 * 1024
    queue_length: Annotated[int, Integer(1, 1000)] = 4
    sequence_restart_count: Annotated[int, Integer(1, 1000)] = 5
    # 1 ms at least: the pipeline counts it in whole microseconds, and a jump of less than a frame period is no reset
    time_reset_threshold_s: Annotated[float, Number(0.001, 3600.0)] = 1.0


#: Brown-Conrady coefficients k1, k2, p1, p2, k3 (OpenCV's order)
Distortion = Annotated[
    tuple[float, float, float, float, float], Numbers(5, what="a list of 5 finite numbers (k1, k2, p1, p2, k3)")
]


@config_dataclass
class IntrinsicsConfig(PinholeSection):
    """``camera.intrinsics``: pinhole + Brown-Conrady, as the scenario schema (cx/cy null = centre)."""

    # at most 1e7 px (a 640 px wide image would then see 0.004 deg): a larger value is a typo, not a lens
    fx_px: Annotated[float, Number(0.0, 1e7, lo_open=True)] = 13e-3 / 17e-6
    fy_px: Annotated[float, Number(0.0, 1e7, lo_open=True)] = 13e-3 / 17e-6
    cx_px: Annotated[float | None, Number()] = None
    cy_px: Annotated[float | None, Number()] = None
    width_px: Annotated[int, Integer(16, 100000)] = 640
    height_px: Annotated[int, Integer(16, 100000)] = 512
    distortion: Distortion = (0.0, 0.0, 0.0, 0.0, 0.0)

    CENTRE_EXPECT_SUFFIX = " or null"


@config_dataclass
class MountConfig:
    """``camera.mount``: the pod on the airframe (``CameraMount.from_euler_deg``)."""

    lever_arm_frd_m: Annotated[tuple[float, float, float], Numbers(3)] = (0.0, 0.0, 0.0)
    roll_deg: Annotated[float, Number(-360.0, 360.0)] = 0.0
    pitch_deg: Annotated[float, Number(-360.0, 360.0)] = 0.0
    yaw_deg: Annotated[float, Number(-360.0, 360.0)] = 0.0
    gimballed: Bool = False

    def __post_init__(self) -> None:
        # the camera's offset from the autopilot's reference point on one airframe: metres at most, so a
        # value of kilometres is a unit or sign slip that would move every line of sight's origin
        if any(abs(x) > MAX_LEVER_ARM_M for x in self.lever_arm_frd_m):
            raise Invalid(
                "lever_arm_frd_m",
                f"offsets within +-{MAX_LEVER_ARM_M:g} m (the camera on the airframe)",
                list(self.lever_arm_frd_m),
            )

    def camera_mount(self) -> CameraMount:
        return CameraMount.from_euler_deg(
            self.lever_arm_frd_m, self.roll_deg, self.pitch_deg, self.yaw_deg, self.gimballed
        )


@config_dataclass
class CameraConfig:
    """``camera``: intrinsics and mount."""

    intrinsics: IntrinsicsConfig = dataclasses.field(default_factory=IntrinsicsConfig)
    mount: MountConfig = dataclasses.field(default_factory=MountConfig)

    def pinhole(self) -> PinholeIntrinsics:
        return self.intrinsics.pinhole()

    def camera_mount(self) -> CameraMount:
        return self.mount.camera_mount()


def _sliding_mapping(value: Any) -> bool:
    return isinstance(value, Mapping) and all(isinstance(k, str) for k in value)


@config_dataclass
class EstimatorConfig:
    """``estimator``: the sliding-window reconstruction and the noise it assumes."""

    enabled: Bool = True
    window_s: Annotated[float, Number(0.0, 600.0, lo_open=True)] = 20.0
    pixel_sigma_px: Annotated[float, Number(0.0, 100.0, lo_open=True)] = SHIPPED_PIXEL_SIGMA_PX
    attitude_white_sigma_deg: Annotated[float, Number(0.0, 30.0)] = SHIPPED_ATTITUDE_WHITE_SIGMA_DEG
    attitude_bias_sigma_deg: Annotated[float, Number(0.0, 30.0)] = SHIPPED_ATTITUDE_BIAS_SIGMA_DEG
    camera_position_white_sigma_m: Annotated[float, Number(0.0, 1000.0)] = SHIPPED_CAMERA_POSITION_WHITE_SIGMA_M
    camera_position_offset_sigma_m: Annotated[float, Number(0.0, 1000.0)] = 0.0
    camera_position_drift_sigma_mps: Annotated[float, Number(0.0, 100.0)] = 0.0
    reset_on_new_track: Bool = True
    worker: Annotated[Literal["process", "thread", "inline"], Text()] = "process"
    result_wait_ms: Annotated[float, Number(0.0, 1000.0)] = 2.0
    max_extrapolation_s: Annotated[float, Number(0.0, 60.0)] = 1.0
    coast_accel_sigma_mps2: Annotated[float, Number(0.0, 100.0)] = 1.0
    # SlidingConfig fields, checked against onboard.estimation.sliding.SlidingConfig when the config is built
    sliding: Annotated[
        dict[str, Any], Instance(dict, what="a mapping of SlidingConfig fields", check=_sliding_mapping)
    ] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "sliding", dict(self.sliding))
        self.sliding_config()  # its own checks, each naming its field under estimator.sliding

    def sliding_config(self):
        """The :class:`~onboard.estimation.sliding.SlidingConfig` of ``sliding``, with ``window_s`` (not a key of
        ``sliding``: configured once, here)."""
        from onboard.estimation.sliding import SlidingConfig

        try:
            return build(SlidingConfig, self.sliding, given={"window_s": self.window_s})
        except SchemaError as exc:
            expected = exc.expected
            if exc.keys is not None:
                expected = f"a key of estimator.sliding ({', '.join(exc.keys)})"
            if exc.field == "window_s":  # given from here
                expected = "the window's length set once, as estimator.window_s, not in estimator.sliding"
            raise Invalid(f"sliding.{exc.field}", expected, got_text=exc.got, hint=exc.hint) from None

    def noise_model(self):
        """The :class:`~onboard.estimation.map_estimator.NoiseModel` (degrees -> radians)."""
        from onboard.estimation.map_estimator import NoiseModel

        return NoiseModel(
            pixel_sigma_px=self.pixel_sigma_px,
            attitude_white_sigma_rad=math.radians(self.attitude_white_sigma_deg),
            attitude_bias_sigma_rad=math.radians(self.attitude_bias_sigma_deg),
            camera_position_white_sigma_m=self.camera_position_white_sigma_m,
            camera_position_offset_sigma_m=self.camera_position_offset_sigma_m,
            camera_position_drift_sigma_mps=self.camera_position_drift_sigma_mps,
        )


@config_dataclass
class OutputConfig:
    """``output``: what goes out and how often."""

    publish_track: Bool = True
    # a finite 3-D estimate is published with observable=false as its quality verdict (irtrack.track/2);
    # false: positions only when observable, as irtrack.track/1 did
    unobservable_positions: Bool = True
    # CAMERA_TRACKING_GEO_STATUS (#276) for unobservable positions too (a ground station shows #276 as
    # a fix and cannot read the verdict: off by default)
    geo_status_unobservable: Bool = False
    status_interval_s: Annotated[float, Number(0.05, 3600.0)] = 1.0
    tracking_image_status_hz: Annotated[float, Number(0.0, 100.0)] = 10.0
    tracking_geo_status_hz: Annotated[float, Number(0.0, 100.0)] = 5.0
    camera_device_id: Annotated[int, Integer(0, 6)] = 0
    track_stale_s: Annotated[float, Number(0.0, 60.0, lo_open=True)] = 1.0
    health_file: Annotated[str | None, Text()] = "/tmp/irtrack-alive"
    # at most half the health probe's age limit: a longer period would make the container's probe call a live
    # daemon stale between two touches
    health_interval_s: Annotated[float, Number(0.05, DEFAULT_MAX_AGE_S / 2)] = 1.0


@config_dataclass
class GcsConfig:
    """``gcs``: the MAVLink camera component for ground stations (see :mod:`onboard.io.camera_protocol`)."""

    endpoints: Annotated[tuple[str, ...], Texts()] = ()
    component_id: Annotated[int, Integer(100, 105)] = 100
    vendor_name: Annotated[str, Text()] = "irtrack"
    model_name: Annotated[str, Text()] = "IR tracker"
    pixel_pitch_um: Annotated[float, Number(0.0, 1000.0, lo_open=True)] = 17.0
    # QGC drops a camera silent for 5 s: a longer period would make it vanish between heartbeats
    heartbeat_interval_s: Annotated[float, Number(0.0, 4.0, lo_open=True)] = 1.0
    tracker_mode: Annotated[Literal["auto", "operator"], Text()] = "auto"
    track_request_timeout_s: Annotated[float, Number(0.0, 60.0, lo_open=True)] = 1.0
    # with mavlink.signing_key_file: the camera's endpoints signed too (false: unsigned, for a ground station
    # reached over a link left unsigned; anyone there can then select the tracked target)
    signed: Bool = True

    def __post_init__(self) -> None:
        for i, ep in enumerate(self.endpoints):
            try:
                parse_connection(ep, f"gcs.endpoints[{i}]")
            except ConfigError as exc:
                msg = str(exc).split(": ", 1)[-1]
                raise Invalid(
                    f"endpoints[{i}]",
                    "an endpoint like udpout:127.0.0.1:14550, udpin:0.0.0.0:14551 or tcp:HOST:PORT",
                    got_text=f"{ep!r} ({msg})",
                ) from None
        for name in ("vendor_name", "model_name"):
            if len(getattr(self, name).encode()) > 32:
                raise Invalid(name, "at most 32 bytes (CAMERA_INFORMATION)", getattr(self, name))


@config_dataclass
class FollowConfig:
    """``follow``: FOLLOW_TARGET (#144) to the autopilot from observable 3-D positions (see :mod:`onboard.io.follow`)."""

    __off_unless_enabled__ = True  # settings without enabled: refused (onboard.core.schema.build)
    enabled: Bool = False
    rate_hz: Annotated[float, Number(0.0, 50.0, lo_open=True)] = 5.0


@config_dataclass
class TimeOffsetConfig:
    """``time_offset``: the camera clock's offset against the autopilot's, estimated online from the target's line
    of sight against the reported attitude (:mod:`onboard.estimation.time_offset`), in the status
    (``camera_time_offset``), warned and compensated in the pose lookup (``compensate``) once beyond
    ``warn_threshold_ms`` by two sigmas that can be trusted (``TimeOffsetEstimate.significantly_beyond``)."""

    enabled: Bool = True
    compensate: Bool = True
    warn_threshold_ms: Annotated[float, Number(0.0, 10000.0, lo_open=True)] = 20.0
    confident_sigma_ms: Annotated[float, Number(0.0, 1000.0, lo_open=True)] = 8.0
    max_offset_ms: Annotated[float, Number(0.0, 10000.0, lo_open=True)] = 250.0
    window_s: Annotated[float, Number(1.0, 3600.0)] = 60.0

    def params(self):
        """The estimator's :class:`~onboard.estimation.time_offset.TimeOffsetParams`."""
        from onboard.estimation.time_offset import TimeOffsetParams

        return TimeOffsetParams(
            window_s=self.window_s,
            confident_sigma_ms=self.confident_sigma_ms,
            max_offset_ms=self.max_offset_ms,
            compensate=self.compensate,
            min_compensated_ms=self.warn_threshold_ms,
        )


@config_dataclass
class LoggingConfig:
    """``logging``: level, line format, and how often a repeated rejection is logged."""

    level: Annotated[Literal["DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"], Text()] = "INFO"
    format: Annotated[Literal["text", "json"], Text()] = "text"
    reject_log_interval_s: Annotated[float, Number(0.0, 3600.0)] = 10.0


def _section(cls) -> Any:
    return dataclasses.field(default_factory=cls)


def _not_the_fleet(name: str) -> str:
    if name == "fleet":
        raise Invalid("", "a vehicle name other than 'fleet' (the fleet fusion's key chunk)", name)
    return name


@config_dataclass
class OnboardConfig:
    """The whole configuration.  ``OnboardConfig()`` is the built-in default, valid as is."""

    # "fleet" is the fleet fusion's key chunk (irtrack/fleet/track): a daemon of that name would publish on the
    # fusion's output and be ignored by it
    vehicle: Annotated[
        str,
        Text(pattern=r"^[A-Za-z0-9_.-]+$", what="a name of letters, digits, '_', '.', '-' (one zenoh key chunk)"),
        AfterValidator(_not_the_fleet),
    ] = "uav1"
    mavlink: MavlinkConfig = _section(MavlinkConfig)
    zenoh: ZenohConfig = _section(ZenohConfig)
    input: InputConfig = _section(InputConfig)
    camera: CameraConfig = _section(CameraConfig)
    imaging: ImagingParams = _section(ImagingParams)
    estimator: EstimatorConfig = _section(EstimatorConfig)
    pose: PoseConfig = _section(PoseConfig)
    output: OutputConfig = _section(OutputConfig)
    gcs: GcsConfig = _section(GcsConfig)
    video: VideoConfig = _section(VideoConfig)
    follow: FollowConfig = _section(FollowConfig)
    guidance: GuidanceConfig = _section(GuidanceConfig)
    record: RecordConfig = _section(RecordConfig)
    live_view: LiveViewConfig = _section(LiveViewConfig)
    time_offset: TimeOffsetConfig = _section(TimeOffsetConfig)
    logging: LoggingConfig = _section(LoggingConfig)

    def __post_init__(self) -> None:
        # both act on the estimator's 3-D track only: without it they would be on and never act, silently
        for section in ("follow", "guidance"):
            if getattr(self, section).enabled and not self.estimator.enabled:
                raise Invalid(
                    f"{section}.enabled", "false while estimator.enabled is false (it acts on the 3-D track)", True
                )

    def bearing_white_sigma_rad(self) -> float:
        """The white noise of one bearing the estimator assumes, 1 sigma per axis (rad):
        ``sqrt(attitude_white^2 + (pixel_sigma / f)^2)``, ``f = sqrt(fx fy)`` in pixels, the focal length the
        estimator's own bearing sigma takes (:func:`onboard.estimation.sliding.bearing_sigma_rad`)."""
        e, k = self.estimator, self.camera.intrinsics
        f_px = math.sqrt(k.fx_px * k.fy_px)
        return math.hypot(math.radians(e.attitude_white_sigma_deg), e.pixel_sigma_px / f_px)

    def extrapolation_horizons(self) -> ExtrapolationHorizons:
        """:meth:`PoseConfig.extrapolation_horizons` bounded by this configuration's bearing noise (those
        of the daemon's pose buffer)."""
        return self.pose.extrapolation_horizons(self.bearing_white_sigma_rad())


# --------------------------------------------------------------------------- building from mappings


_Sources = Mapping[str, str]


def _source_of(path: str, sources: _Sources, default: str) -> str:
    """The source of the most specific overridden prefix of ``path``; else ``default``, and with it the overrides of
    the same section (a cross-field rule refusing a field the file set may be broken by another one an override set)."""
    p = path
    while p:
        base = re.sub(r"\[\d+\]$", "", p)
        if base in sources:
            return sources[base]
        if "." not in base:
            break
        p = base.rsplit(".", 1)[0]
    section = re.sub(r"\[\d+\]$", "", path).rsplit(".", 1)[0] if "." in path else None
    beside = sorted({src for field, src in sources.items() if section and field.startswith(section + ".")})
    return f"{default} with {', '.join(beside)}" if beside else default


def build_config(
    raw: Mapping[str, Any] | None, source: str = DEFAULT_SOURCE, sources: _Sources | None = None
) -> OnboardConfig:
    """Validate a raw mapping (as read from YAML, with overrides merged) into :class:`OnboardConfig`.

    ``sources`` maps overridden field paths to where they came from (``env IRTRACK_X``,
    ``--option``) so an error names the right place; everything else is blamed on ``source``.
    """
    sources = sources or {}
    if raw is not None and not isinstance(raw, Mapping):
        raise OnboardConfigError(
            source, "(document)", "a mapping of sections (vehicle, mavlink, zenoh, ...)", show(raw)
        )
    try:
        return build(OnboardConfig, raw, "")
    except SchemaError as exc:
        raise exc.as_(OnboardConfigError, _source_of(exc.field, sources, source)) from None
    except (ConfigError, FrameError) as exc:  # a library's own check (e.g. CameraMount)
        raise OnboardConfigError(source, "(document)", "a consistent configuration", str(exc)) from None


# --------------------------------------------------------------------------- YAML, env, overrides


def _leaf_paths(cls=OnboardConfig, prefix: str = "") -> list[str]:
    """Every settable field path (sections descended; ``pose.origin``, nullable, is a leaf)."""
    out = []
    for f in dataclasses.fields(cls):
        p = f"{prefix}.{f.name}" if prefix else f.name
        if f.default is dataclasses.MISSING and is_config_dataclass(f.default_factory):
            out += _leaf_paths(f.default_factory, p)
        else:
            out.append(p)
    return out


def _sections() -> list[str]:
    return [f.name for f in dataclasses.fields(OnboardConfig) if f.default is dataclasses.MISSING]


def _env_name(path: str) -> str:
    return ENV_PREFIX + path.replace(".", "_").upper()


def _parse_value(text: str) -> Any:
    """An override's text as a YAML value by the one loader's rules (``""`` -> null; bad YAML -> the text)."""
    try:
        return parse_yaml_text(text) if text.strip() else None
    except yaml.YAMLError:
        return text


def env_overrides(environ: Mapping[str, str] | None = None) -> dict[str, tuple[Any, str]]:
    """``{field.path: (value, "env NAME")}`` from ``IRTRACK_*`` variables.

    Values are parsed as YAML (``"5"`` -> 5, ``"true"`` -> True, ``"[a, b]"`` -> list, ``""`` ->
    null).  An ``IRTRACK_<SECTION>_...`` name whose section exists but whose field does not, or one at least
    :data:`ENV_MISSPELT_RATIO` alike to a field's name, raises :class:`OnboardConfigError` with a "did you mean";
    other ``IRTRACK_*`` names are not ours.  ``IRTRACK_HEALTH_FILE`` may not be empty, nor differ from
    ``IRTRACK_OUTPUT_HEALTH_FILE`` when both are set.
    """
    environ = os.environ if environ is None else environ
    by_name = {_env_name(p): p for p in _leaf_paths()}
    by_name.update(ENV_ALIASES)
    sections = {_env_name(name) + "_" for name in _sections()}
    out: dict[str, tuple[Any, str]] = {}
    for name in sorted(environ):
        if not name.startswith(ENV_PREFIX):
            continue
        src = f"env {name}"
        path = by_name.get(name)
        if path is None:
            # a misspelt section too (IRTRACK_MAVLNK_CONNECTION): one letter off a field's variable, never one of
            # the other IRTRACK_* variables the tools read (IRTRACK_EXTRAS ...), which are < 0.75 alike
            near = difflib.get_close_matches(name, list(by_name), n=1, cutoff=ENV_MISSPELT_RATIO)
            if name + "_" in sections:  # a whole section in one variable: ignoring it would drop it silently
                raise OnboardConfigError(
                    src, "(name)", "one IRTRACK_<SECTION>_<FIELD> variable per field", repr(name), None
                )
            if any(name.startswith(s) for s in sections) or near:
                raise OnboardConfigError(
                    src, "(name)", "a known IRTRACK_<SECTION>_<FIELD> variable", repr(name), did_you_mean(name, by_name)
                )
            continue
        if path in out:  # an alias and its field's own name, both set
            first = out[path][1]
            if environ[name] != environ[first.removeprefix("env ")]:
                raise OnboardConfigError(
                    src, path, f"the value of {first.removeprefix('env ')} (the same field)", repr(environ[name])
                )
        if name in ENV_ALIASES and not environ[name].strip():
            # the health probe refuses an empty IRTRACK_HEALTH_FILE: the daemon must not read it as "no file"
            raise OnboardConfigError(src, path, "a file path (the health probe reads it too)", "an empty value")
        out[path] = (_parse_value(environ[name]), src)
    return out


def _set_path(raw: dict, path: str, value: Any, source: str) -> None:
    parts = path.split(".")
    node = raw
    for i, part in enumerate(parts[:-1]):
        nxt = node.get(part)
        if nxt is None:
            nxt = {}
        elif not isinstance(nxt, dict):
            raise OnboardConfigError(source, ".".join(parts[: i + 1]), "a mapping", show(nxt))
        else:
            nxt = dict(nxt)
        node[part] = nxt
        node = nxt
    node[parts[-1]] = value


def parse_set_option(text: str) -> tuple[str, Any]:
    """``--set section.field=value`` -> (path, YAML-parsed value); OnboardConfigError when malformed."""
    if "=" not in text:
        raise OnboardConfigError("--set", "(option)", "FIELD.PATH=VALUE", repr(text))
    path, _, value_text = text.partition("=")
    path = path.strip()
    leaves = _leaf_paths()
    if (
        path not in leaves
        and not any(p.startswith(path + ".") for p in leaves)
        and not path.startswith("estimator.sliding.")
    ):
        raise OnboardConfigError(
            "--set", path or "(option)", "a configuration field path", repr(text), did_you_mean(path, leaves)
        )
    return path, _parse_value(value_text)


def load_config(
    path: str | os.PathLike | None = None,
    overrides: Mapping[str, tuple[Any, str]] | None = None,
    environ: Mapping[str, str] | None = None,
) -> OnboardConfig:
    """Defaults < ``path`` (YAML) < environment < ``overrides`` (``{field.path: (value, source)}``).

    ``environ``: the variables to read (default ``os.environ``; pass ``{}`` to ignore them).
    """
    source = DEFAULT_SOURCE if path is None else os.fspath(path)
    raw: dict[str, Any] = {}
    if path is not None and not source.strip():  # an unset $CFG: Path("") would be read as the folder "."
        raise OnboardConfigError("(empty path)", "(file)", "a YAML file path", repr(source))
    if path is not None:
        data = read_yaml(source, OnboardConfigError)
        if data is None:
            # an empty or comment-only file is most likely the wrong one (a truncated copy, a placeholder mounted
            # over the real one): running on the built-in defaults would hide it; the defaults are --config left out
            raise OnboardConfigError(source, "(document)", "a mapping of config sections", "an empty document")
        if not isinstance(data, Mapping):
            raise OnboardConfigError(
                source, "(document)", "a mapping of sections (vehicle, mavlink, zenoh, ...)", show(data)
            )
        raw = dict(data)
    sources: dict[str, str] = {}
    merged = dict(env_overrides(environ))
    merged.update(overrides or {})
    for p, (value, src) in merged.items():
        _set_path(raw, p, value, src)
        sources[p] = src
    config = build_config(raw, source, sources)
    _check_health_file_agrees(config, os.environ if environ is None else environ, sources)
    return config


def _check_health_file_agrees(config: OnboardConfig, environ: Mapping[str, str], sources: Mapping[str, str]) -> None:
    """Refuse a command-line ``output.health_file`` other than ``IRTRACK_HEALTH_FILE``: the health probe reads the
    variable's path, so a daemon touching another file would be called dead by its own container."""
    (alias,) = (name for name, path in ENV_ALIASES.items() if path == "output.health_file")
    probe_path = environ.get(alias)
    if probe_path is None or config.output.health_file == probe_path:
        return
    raise OnboardConfigError(
        sources.get("output.health_file", alias),
        "output.health_file",
        f"the value of {alias} ({probe_path!r}: the health probe reads that file)",
        show(config.output.health_file),
    )


def config_to_dict(cfg) -> Any:
    """Plain YAML-able data of a config (tuples -> lists); ``load`` of it gives the same config."""
    return to_plain(cfg)
