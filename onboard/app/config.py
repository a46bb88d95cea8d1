"""The onboard daemon's configuration: YAML -> typed frozen dataclasses, strict, loaded once.

Layers, later ones winning: built-in defaults < the YAML file (``--config``) < environment
variables ``IRTRACK_<SECTION>_<FIELD>`` (e.g. ``IRTRACK_MAVLINK_CONNECTION``,
``IRTRACK_CAMERA_INTRINSICS_FX_PX``, ``IRTRACK_VEHICLE``; values are parsed as YAML scalars/flow
collections, so ``IRTRACK_ZENOH_CONNECT='[tcp/10.0.0.2:7447]'`` works) < command-line options.
``IRTRACK_HEALTH_FILE`` is an alias of ``IRTRACK_OUTPUT_HEALTH_FILE`` (the container's health check
reads it too).  An unknown ``IRTRACK_<SECTION>_...`` variable of a known section is an error.

Every problem raises :class:`OnboardConfigError` (a :class:`~onboard.core.errors.ConfigError`), one line::

    <source>: <field.path>: expected <what>, got <value>[; did you mean '<key>'?]

where ``<source>`` is the file, ``env IRTRACK_...`` or ``--option``; entry points print it and exit
with :attr:`OnboardConfigError.exit_code` (2).  Unknown keys, wrong types (a bool is not a number,
``640.0`` is not an integer), out-of-range values, duplicate YAML keys and bad YAML all fail.

The schema, with defaults and meaning, is ``config/onboard.yaml`` (every field commented) and the
dataclasses below; angles are degrees and durations milliseconds/seconds as the names say, converted
once here into the radians/microseconds of the core objects (:meth:`CameraConfig.mount`,
:meth:`PoseConfig.buffer_config`, :meth:`EstimatorConfig.noise_model` ...).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, Mapping

import yaml

from onboard.core.errors import ConfigError
from onboard.core.frames import CameraMount, FrameError, GeodeticOrigin, PinholeIntrinsics
from onboard.imaging.preprocess import ImagingParams

__all__ = [
    "OnboardConfigError",
    "FieldError",
    "MavlinkConfig",
    "ZenohConfig",
    "InputConfig",
    "IntrinsicsConfig",
    "MountConfig",
    "CameraConfig",
    "EstimatorConfig",
    "PoseConfig",
    "OutputConfig",
    "GcsConfig",
    "VideoConfig",
    "LoggingConfig",
    "OnboardConfig",
    "load_config",
    "build_config",
    "env_overrides",
    "config_to_dict",
    "ENV_PREFIX",
]

ENV_PREFIX = "IRTRACK_"
ENV_ALIASES = {"IRTRACK_HEALTH_FILE": "output.health_file"}
DEFAULT_SOURCE = "(defaults)"


class FieldError(ConfigError):
    """A bad value of one field, before the source is known: ``<field.path>: expected <what>, got <value>``."""

    def __init__(self, path: str, expected: str, got: Any, hint: str | None = None, got_text: str | None = None):
        self.path = path
        self.expected = expected
        self.got_text = got_text if got_text is not None else _show(got)
        self.hint = hint
        super().__init__(f"{path}: expected {expected}, got {self.got_text}" + (f"; {hint}" if hint else ""))


class OnboardConfigError(ConfigError):
    """One-line configuration error naming source, field and expectation; ``exit_code`` 2."""

    exit_code = 2

    def __init__(self, source: str, path: str, expected: str, got_text: str, hint: str | None = None):
        self.source = source
        self.field = path or "(document)"
        self.expected = expected
        self.got = got_text
        self.hint = hint
        super().__init__(f"{source}: {self.field}: expected {expected}, got {got_text}" + (f"; {hint}" if hint else ""))


def _show(v: Any) -> str:
    text = repr(v) if isinstance(v, str) else str(v) if not isinstance(v, (dict, list, tuple)) else repr(v)
    if isinstance(v, bool):
        text = str(v).lower()
    if v is None:
        text = "null"
    text = " ".join(text.split())
    return text if len(text) <= 120 else text[:117] + "..."


def _did_you_mean(word: str, options) -> str | None:
    same_case = [o for o in options if str(o).lower() == str(word).lower()]
    if same_case:
        return f"did you mean '{same_case[0]}'?"
    close = difflib.get_close_matches(str(word), [str(o) for o in options], n=1, cutoff=0.6)
    return f"did you mean '{close[0]}'?" if close else None


# --------------------------------------------------------------------------- field specs


@dataclass(frozen=True)
class _Spec:
    """What one scalar/vector field accepts; ``check`` returns the normalised value or raises FieldError."""

    kind: str  # float | int | bool | str | str_list | floats
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    nullable: bool = False
    choices: tuple = ()
    n: int = 0
    pattern: str | None = None
    what: str | None = None  # overrides the generated description

    def expected(self) -> str:
        if self.what is not None:
            text = self.what
        elif self.kind == "bool":
            text = "true or false"
        elif self.kind == "str":
            text = f"one of {', '.join(map(str, self.choices))}" if self.choices else "a non-empty string"
        elif self.kind == "str_list":
            text = "a list of strings"
        elif self.kind == "floats":
            text = f"a list of {self.n} finite numbers"
        else:
            noun = "an integer" if self.kind == "int" else "a number"
            if self.lo is not None and self.hi is not None:
                text = f"{noun} in {'(' if self.lo_open else '['}{_g(self.lo)}, {_g(self.hi)}{')' if self.hi_open else ']'}"
            elif self.lo is not None:
                text = f"{noun} {'>' if self.lo_open else '>='} {_g(self.lo)}"
            elif self.hi is not None:
                text = f"{noun} {'<' if self.hi_open else '<='} {_g(self.hi)}"
            else:
                text = f"a finite {noun[2:] if noun.startswith('a ') else noun[3:]}"
        return text + (" or null" if self.nullable else "")

    def check(self, v: Any, path: str) -> Any:
        if v is None:
            if self.nullable:
                return None
            raise FieldError(path, self.expected(), v)
        bad = FieldError(path, self.expected(), v)
        if self.kind == "bool":
            if not isinstance(v, bool):
                raise bad
            return v
        if self.kind == "str":
            if not isinstance(v, str) or not v.strip():
                raise bad
            if self.choices and v not in self.choices:
                raise FieldError(path, self.expected(), v, _did_you_mean(v, self.choices))
            if self.pattern and not re.match(self.pattern, v):
                raise bad
            return v
        if self.kind == "str_list":
            if isinstance(v, str):
                v = [v]
            if not isinstance(v, (list, tuple)) or not all(isinstance(x, str) and x.strip() for x in v):
                raise bad
            return tuple(v)
        if self.kind == "floats":
            if not isinstance(v, (list, tuple)) or len(v) != self.n:
                raise bad
            out = []
            for i, x in enumerate(v):
                if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                    raise FieldError(f"{path}[{i}]", "a finite number", x)
                out.append(float(x))
            return tuple(out)
        if self.kind == "int":
            if isinstance(v, bool) or not isinstance(v, int):
                raise bad
        else:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise bad
            v = float(v)
        if self.lo is not None and (v < self.lo or (self.lo_open and v == self.lo)):
            raise bad
        if self.hi is not None and (v > self.hi or (self.hi_open and v == self.hi)):
            raise bad
        return v


def _g(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def F(default, kind: str, **kw) -> Any:
    """A dataclass field with a spec in its metadata."""
    return field(default=default, metadata={"spec": _Spec(kind, **kw)})


def _section(cls) -> Any:
    return field(default_factory=cls, metadata={"section": cls})


class _Section:
    """Base of the config sections: ``__post_init__`` validates every spec'd field (frozen-safe)."""

    _path: ClassVar[str] = ""

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            spec = f.metadata.get("spec")
            if spec is not None:
                object.__setattr__(self, f.name, spec.check(value, self._join(f.name)))
            elif "section" in f.metadata and not isinstance(value, f.metadata["section"]):
                raise FieldError(self._join(f.name), f"a {f.metadata['section'].__name__}", value)
        self._check()

    def _join(self, name: str) -> str:
        return f"{self._path}.{name}" if self._path else name

    def _check(self) -> None:  # cross-field checks of a section
        pass


# --------------------------------------------------------------------------- sections


@dataclass(frozen=True)
class MavlinkConfig(_Section):
    """``mavlink``: the autopilot link (see :mod:`onboard.io.mavlink_link`)."""

    _path: ClassVar[str] = "mavlink"
    connection: str = F("udpin:127.0.0.1:14540", "str")
    attitude_rate_hz: float = F(50.0, "float", lo=0.0, lo_open=True, hi=1000.0)
    position_rate_hz: float = F(25.0, "float", lo=0.0, lo_open=True, hi=1000.0)
    gimbal_rate_hz: float = F(50.0, "float", lo=0.0, lo_open=True, hi=1000.0)
    heartbeat_interval_s: float = F(1.0, "float", lo=0.0, lo_open=True, hi=60.0)
    heartbeat_timeout_s: float = F(5.0, "float", lo=0.0, lo_open=True, hi=600.0)
    command_retry_s: float = F(1.0, "float", lo=0.0, lo_open=True, hi=60.0)
    timesync_interval_s: float = F(1.0, "float", lo=0.0, lo_open=True, hi=60.0)
    reopen_interval_s: float = F(2.0, "float", lo=0.0, lo_open=True, hi=60.0)
    autopilot_sysid: int | None = F(1, "int", lo=1, hi=255, nullable=True)
    lock_settle_s: float = F(1.5, "float", lo=0.0, hi=60.0)
    signing_key_file: str | None = F(None, "str", nullable=True)
    signing_key_env: str | None = F(None, "str", nullable=True)
    autopilot_compid: int = F(1, "int", lo=1, hi=255)
    component_id: int = F(191, "int", lo=1, hi=255)
    poll_rate_hz: float = F(200.0, "float", lo=100.0, hi=10000.0)

    def _check(self) -> None:
        from onboard.io.mavlink_link import parse_connection

        try:
            parse_connection(self.connection, "mavlink.connection")
        except ConfigError as exc:
            msg = str(exc).split(": ", 1)[-1]
            raise FieldError("mavlink.connection", "a connection like udpin:0.0.0.0:14540, udpout:HOST:PORT, "
                             "tcp:HOST:PORT or serial:/dev/ttyX[:BAUD]", self.connection,
                             got_text=f"{self.connection!r} ({msg})") from None
        if self.heartbeat_timeout_s <= self.heartbeat_interval_s:
            raise FieldError("mavlink.heartbeat_timeout_s",
                             f"a timeout > mavlink.heartbeat_interval_s ({_g(self.heartbeat_interval_s)})",
                             self.heartbeat_timeout_s)
        self.signing_key()  # an unreadable or empty key fails at --check, naming its field

    def signing_key(self) -> bytes | None:
        """The MAVLink 2 signing key (reads ``signing_key_file`` or the ``signing_key_env`` variable), None = unsigned."""
        from onboard.io.mavlink_link import load_signing_key

        try:
            return load_signing_key(self.signing_key_file, self.signing_key_env)
        except ConfigError as exc:
            field, _, what = str(exc).partition(": ")
            raise FieldError(field, "a readable MAVLink 2 signing key (64 hex digits, 32 raw bytes or a passphrase)",
                             None, got_text=what) from None

    def link_config(self):
        """The :class:`~onboard.io.mavlink_link.MavlinkLinkConfig` of this section."""
        from onboard.io.mavlink_link import MavlinkLinkConfig

        return MavlinkLinkConfig(
            component_id=self.component_id,
            autopilot_sysid=self.autopilot_sysid,
            autopilot_compid=self.autopilot_compid,
            heartbeat_interval_s=self.heartbeat_interval_s,
            heartbeat_timeout_s=self.heartbeat_timeout_s,
            command_retry_s=self.command_retry_s,
            timesync_interval_s=self.timesync_interval_s,
            reopen_interval_s=self.reopen_interval_s,
            gimbal_rate_hz=self.gimbal_rate_hz,
            lock_settle_s=self.lock_settle_s,
            signing_key=self.signing_key(),
        )


@dataclass(frozen=True)
class ZenohConfig(_Section):
    """``zenoh``: the session (see :mod:`onboard.io.zenoh_session`)."""

    _path: ClassVar[str] = "zenoh"
    connect: tuple[str, ...] = F((), "str_list")
    listen: tuple[str, ...] = F((), "str_list")
    config_file: str | None = F(None, "str", nullable=True)
    multicast_scouting: bool | None = F(False, "bool", nullable=True)
    connect_timeout_s: float | None = F(None, "float", lo=0.0, lo_open=True, hi=3600.0, nullable=True)

    def _check(self) -> None:
        for name in ("connect", "listen"):
            for i, ep in enumerate(getattr(self, name)):
                if "/" not in ep or not ep.split("/", 1)[1]:
                    raise FieldError(f"zenoh.{name}[{i}]", "a zenoh endpoint <protocol>/<address>, e.g. tcp/127.0.0.1:7447", ep)
                proto, addr = ep.split("/", 1)
                if proto in ("tcp", "udp", "tls", "quic", "ws"):
                    hostport = addr.split("?", 1)[0].split("#", 1)[0]
                    port = hostport.rsplit(":", 1)[1] if ":" in hostport else ""
                    if not port.isdigit() or int(port) > 65535:
                        raise FieldError(f"zenoh.{name}[{i}]", f"a {proto} endpoint {proto}/HOST:PORT with PORT in 0..65535", ep)

    def settings(self, max_payload_bytes: int | None = None):
        """The :class:`~onboard.io.zenoh_session.ZenohSettings` of this section; ``max_payload_bytes`` (the
        daemon passes ``input.max_frame_bytes``) becomes zenoh's own receive limit, plus framing."""
        from onboard.io.zenoh_session import MESSAGE_OVERHEAD_BYTES, ZenohSettings

        return ZenohSettings(
            connect=self.connect,
            listen=self.listen,
            config_file=self.config_file,
            multicast_scouting=self.multicast_scouting,
            connect_timeout_s=self.connect_timeout_s,
            max_message_bytes=None if max_payload_bytes is None else int(max_payload_bytes) + MESSAGE_OVERHEAD_BYTES,
        )


@dataclass(frozen=True)
class InputConfig(_Section):
    """``input``: IR frames in (key ``irtrack/<vehicle>/ir/frame``)."""

    _path: ClassVar[str] = "input"
    max_frame_bytes: int = F(16 * 1024 * 1024, "int", lo=64, hi=1 << 31)
    queue_length: int = F(4, "int", lo=1, hi=1000)
    sequence_restart_count: int = F(5, "int", lo=1, hi=1000)
    time_reset_threshold_s: float = F(1.0, "float", lo=0.0, lo_open=True, hi=3600.0)


@dataclass(frozen=True)
class IntrinsicsConfig(_Section):
    """``camera.intrinsics``: pinhole + Brown-Conrady, as the scenario schema (cx/cy null = centre)."""

    _path: ClassVar[str] = "camera.intrinsics"
    fx_px: float = F(13e-3 / 17e-6, "float", lo=0.0, lo_open=True)
    fy_px: float = F(13e-3 / 17e-6, "float", lo=0.0, lo_open=True)
    cx_px: float | None = F(None, "float", nullable=True)
    cy_px: float | None = F(None, "float", nullable=True)
    width_px: int = F(640, "int", lo=16, hi=100000)
    height_px: int = F(512, "int", lo=16, hi=100000)
    distortion: tuple[float, ...] = F((0.0, 0.0, 0.0, 0.0, 0.0), "floats", n=5)

    def _check(self) -> None:
        for name, size in (("cx_px", self.width_px), ("cy_px", self.height_px)):
            v = getattr(self, name)
            if v is not None and not 0.0 <= v <= size:
                raise FieldError(f"camera.intrinsics.{name}", f"a number in [0, {size}] (inside the image) or null", v)

    def pinhole(self) -> PinholeIntrinsics:
        cx = self.width_px / 2.0 if self.cx_px is None else self.cx_px
        cy = self.height_px / 2.0 if self.cy_px is None else self.cy_px
        return PinholeIntrinsics(self.fx_px, self.fy_px, cx, cy, self.width_px, self.height_px, tuple(self.distortion))


@dataclass(frozen=True)
class MountConfig(_Section):
    """``camera.mount``: the pod on the airframe (``CameraMount.from_euler_deg``)."""

    _path: ClassVar[str] = "camera.mount"
    lever_arm_frd_m: tuple[float, float, float] = F((0.0, 0.0, 0.0), "floats", n=3)
    roll_deg: float = F(0.0, "float", lo=-360.0, hi=360.0)
    pitch_deg: float = F(0.0, "float", lo=-360.0, hi=360.0)
    yaw_deg: float = F(0.0, "float", lo=-360.0, hi=360.0)
    gimballed: bool = F(False, "bool")

    def camera_mount(self) -> CameraMount:
        return CameraMount.from_euler_deg(self.lever_arm_frd_m, self.roll_deg, self.pitch_deg, self.yaw_deg, self.gimballed)


@dataclass(frozen=True)
class CameraConfig(_Section):
    """``camera``: intrinsics and mount."""

    _path: ClassVar[str] = "camera"
    intrinsics: IntrinsicsConfig = _section(IntrinsicsConfig)
    mount: MountConfig = _section(MountConfig)

    def pinhole(self) -> PinholeIntrinsics:
        return self.intrinsics.pinhole()

    def camera_mount(self) -> CameraMount:
        return self.mount.camera_mount()


@dataclass(frozen=True)
class EstimatorConfig(_Section):
    """``estimator``: the sliding-window reconstruction and the noise it assumes."""

    _path: ClassVar[str] = "estimator"
    enabled: bool = F(True, "bool")
    window_s: float = F(20.0, "float", lo=0.0, lo_open=True, hi=600.0)
    pixel_sigma_px: float = F(0.3, "float", lo=0.0, lo_open=True, hi=100.0)
    attitude_white_sigma_deg: float = F(0.05, "float", lo=0.0, hi=30.0)
    attitude_bias_sigma_deg: float = F(0.1, "float", lo=0.0, hi=30.0)
    camera_position_white_sigma_m: float = F(0.02, "float", lo=0.0, hi=1000.0)
    camera_position_offset_sigma_m: float = F(0.0, "float", lo=0.0, hi=1000.0)
    camera_position_drift_sigma_mps: float = F(0.0, "float", lo=0.0, hi=100.0)
    reset_on_new_track: bool = F(True, "bool")
    worker: str = F("process", "str", choices=("process", "thread", "inline"))
    result_wait_ms: float = F(2.0, "float", lo=0.0, hi=1000.0)
    max_extrapolation_s: float = F(1.0, "float", lo=0.0, hi=60.0)
    sliding: Mapping[str, Any] = field(default_factory=dict, metadata={"free": True})

    def _check(self) -> None:
        if not isinstance(self.sliding, Mapping):
            raise FieldError("estimator.sliding", "a mapping of SlidingConfig fields", self.sliding)
        object.__setattr__(self, "sliding", dict(self.sliding))

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


@dataclass(frozen=True)
class OriginConfig(_Section):
    """``pose.origin``: a fixed local NED origin."""

    _path: ClassVar[str] = "pose.origin"
    lat_deg: float = F(0.0, "float", lo=-90.0, hi=90.0)
    lon_deg: float = F(0.0, "float", lo=-180.0, hi=180.0)
    alt_m: float = F(0.0, "float", lo=-1000.0, hi=100000.0)

    def geodetic(self) -> GeodeticOrigin:
        return GeodeticOrigin(self.lat_deg, self.lon_deg, self.alt_m)


@dataclass(frozen=True)
class PoseConfig(_Section):
    """``pose``: the pose buffer's tolerances (see :class:`~onboard.core.pose.PoseBufferConfig`)."""

    _path: ClassVar[str] = "pose"
    window_s: float = F(5.0, "float", lo=0.1, hi=600.0)
    attitude_max_gap_ms: float = F(100.0, "float", lo=0.0, lo_open=True, hi=10000.0)
    position_max_gap_ms: float = F(300.0, "float", lo=0.0, lo_open=True, hi=10000.0)
    gimbal_max_gap_ms: float = F(300.0, "float", lo=0.0, lo_open=True, hi=10000.0)
    reboot_threshold_s: float = F(1.0, "float", lo=0.0, lo_open=True, hi=3600.0)
    max_speed_mps: float = F(200.0, "float", lo=0.0, lo_open=True, hi=10000.0)
    jump_reset_count: int = F(5, "int", lo=1, hi=1000)
    keep_origin_on_reboot: bool = F(True, "bool")
    position_interp: str = F("hermite", "str", choices=("hermite", "linear"))
    wait_ms: float = F(5.0, "float", lo=0.0, hi=1000.0)
    max_extrapolation_ms: float = F(50.0, "float", lo=0.0, hi=10000.0)
    extrapolation_noise_fraction: float = F(0.25, "float", lo=0.0, hi=10.0)
    body_rate_sigma_dps: float = F(0.1, "float", lo=0.0, hi=1000.0)
    gimbal_rate_sigma_dps: float = F(0.5, "float", lo=0.0, hi=1000.0)
    angular_accel_sigma_dps2: float = F(20.0, "float", lo=0.0, hi=100000.0)
    velocity_sigma_mps: float = F(0.1, "float", lo=0.0, hi=1000.0)
    accel_sigma_mps2: float = F(2.0, "float", lo=0.0, hi=1000.0)
    origin: OriginConfig | None = field(default=None, metadata={"section": OriginConfig, "nullable": True})

    def __post_init__(self) -> None:  # origin may be None
        if self.origin is not None and not isinstance(self.origin, OriginConfig):
            raise FieldError("pose.origin", "a mapping {lat_deg, lon_deg, alt_m} or null", self.origin)
        for f in fields(self):
            spec = f.metadata.get("spec")
            if spec is not None:
                object.__setattr__(self, f.name, spec.check(getattr(self, f.name), self._join(f.name)))
        for name in ("attitude_max_gap_ms", "position_max_gap_ms", "gimbal_max_gap_ms"):
            if getattr(self, name) > self.window_s * 1000.0:
                raise FieldError(f"pose.{name}", f"a gap <= pose.window_s ({_g(self.window_s)} s)", getattr(self, name))

    def buffer_config(self, bearing_white_sigma_rad: float | None = None):
        """The :class:`~onboard.core.pose.PoseBufferConfig` (ms/s -> us, deg -> rad).

        Extrapolation horizons (each capped by its stream's max gap): position
        ``max_extrapolation_ms``; attitude and gimbal the same, shortened so that their added 1-sigma stays <= ``extrapolation_noise_fraction`` x
        ``bearing_white_sigma_rad`` (:func:`onboard.core.pose.attitude_horizon_us`; the service passes
        :meth:`OnboardConfig.bearing_white_sigma_rad`; None: not shortened).
        """
        from onboard.core.pose import PoseBufferConfig, attitude_horizon_us

        us = lambda ms: max(1, int(round(ms * 1000.0)))  # noqa: E731
        cap_us = int(round(self.max_extrapolation_ms * 1000.0))
        body_rps, gim_rps = math.radians(self.body_rate_sigma_dps), math.radians(self.gimbal_rate_sigma_dps)
        acc_rps2 = math.radians(self.angular_accel_sigma_dps2)
        if bearing_white_sigma_rad is None:
            att_us = gim_us = cap_us
        else:
            limit = self.extrapolation_noise_fraction * bearing_white_sigma_rad
            att_us = attitude_horizon_us(limit, body_rps, acc_rps2, cap_us)
            gim_us = attitude_horizon_us(limit, gim_rps, acc_rps2, cap_us)
        return PoseBufferConfig(
            att_max_extrapolation_us=min(att_us, us(self.attitude_max_gap_ms)),
            pos_max_extrapolation_us=min(cap_us, us(self.position_max_gap_ms)),
            gimbal_max_extrapolation_us=min(gim_us, us(self.gimbal_max_gap_ms)),
            body_rate_sigma_rps=body_rps,
            gimbal_rate_sigma_rps=gim_rps,
            angular_accel_sigma_rps2=acc_rps2,
            velocity_sigma_mps=self.velocity_sigma_mps,
            accel_sigma_mps2=self.accel_sigma_mps2,
            window_us=us(self.window_s * 1000.0),
            att_max_gap_us=us(self.attitude_max_gap_ms),
            pos_max_gap_us=us(self.position_max_gap_ms),
            gimbal_max_gap_us=us(self.gimbal_max_gap_ms),
            reboot_threshold_us=us(self.reboot_threshold_s * 1000.0),
            max_speed_mps=self.max_speed_mps,
            jump_reset_count=self.jump_reset_count,
            keep_origin_on_reboot=self.keep_origin_on_reboot,
            position_interp=self.position_interp,
        )

    def geodetic_origin(self) -> GeodeticOrigin | None:
        return None if self.origin is None else self.origin.geodetic()


@dataclass(frozen=True)
class OutputConfig(_Section):
    """``output``: what goes out and how often."""

    _path: ClassVar[str] = "output"
    publish_track: bool = F(True, "bool")
    # a finite 3-D estimate is published with observable=false as its quality verdict (irtrack.track/2);
    # false: positions only when observable, as irtrack.track/1 did
    unobservable_positions: bool = F(True, "bool")
    # CAMERA_TRACKING_GEO_STATUS (#276) for unobservable positions too (a ground station shows #276 as
    # a fix and cannot read the verdict: off by default)
    geo_status_unobservable: bool = F(False, "bool")
    status_interval_s: float = F(1.0, "float", lo=0.05, hi=3600.0)
    tracking_image_status_hz: float = F(10.0, "float", lo=0.0, hi=100.0)
    tracking_geo_status_hz: float = F(5.0, "float", lo=0.0, hi=100.0)
    camera_device_id: int = F(0, "int", lo=0, hi=6)
    track_stale_s: float = F(1.0, "float", lo=0.0, lo_open=True, hi=60.0)
    health_file: str | None = F("/tmp/irtrack-alive", "str", nullable=True)
    health_interval_s: float = F(1.0, "float", lo=0.05, hi=60.0)


@dataclass(frozen=True)
class GcsConfig(_Section):
    """``gcs``: the MAVLink camera component for ground stations (see :mod:`onboard.io.camera_protocol`)."""

    _path: ClassVar[str] = "gcs"
    endpoints: tuple[str, ...] = F((), "str_list")
    component_id: int = F(100, "int", lo=100, hi=105)
    vendor_name: str = F("irtrack", "str")
    model_name: str = F("IR tracker", "str")
    pixel_pitch_um: float = F(17.0, "float", lo=0.0, lo_open=True, hi=1000.0)
    heartbeat_interval_s: float = F(1.0, "float", lo=0.0, lo_open=True, hi=60.0)
    tracker_mode: str = F("auto", "str", choices=("auto", "operator"))
    track_request_timeout_s: float = F(1.0, "float", lo=0.0, lo_open=True, hi=60.0)

    def _check(self) -> None:
        from onboard.io.mavlink_link import parse_connection

        for i, ep in enumerate(self.endpoints):
            try:
                parse_connection(ep, f"gcs.endpoints[{i}]")
            except ConfigError as exc:
                msg = str(exc).split(": ", 1)[-1]
                raise FieldError(f"gcs.endpoints[{i}]", "an endpoint like udpout:127.0.0.1:14550, udpin:0.0.0.0:14551 "
                                 "or tcp:HOST:PORT", ep, got_text=f"{ep!r} ({msg})") from None
        for name in ("vendor_name", "model_name"):
            if len(getattr(self, name).encode()) > 32:
                raise FieldError(f"gcs.{name}", "at most 32 bytes (CAMERA_INFORMATION)", getattr(self, name))


@dataclass(frozen=True)
class VideoConfig(_Section):
    """``video``: the IR video for ground stations (see :mod:`onboard.io.video`)."""

    _path: ClassVar[str] = "video"
    destination: str | None = F(None, "str", nullable=True, pattern=r"^[^\s:]+:\d{1,5}$",
                                what="HOST:PORT")
    transport: str = F("rtp", "str", choices=("rtp", "mpegts"))  # RTP/UDP (RFC 6184) or MPEG-TS/UDP; onboard.io.video
    fps: float = F(30.0, "float", lo=1.0, hi=120.0)
    bitrate_bps: int = F(2_000_000, "int", lo=100_000, hi=50_000_000)
    gop_s: float = F(1.0, "float", lo=0.1, hi=1.0)
    overlay: bool = F(True, "bool")
    queue_length: int = F(2, "int", lo=1, hi=30)


@dataclass(frozen=True)
class FollowConfig(_Section):
    """``follow``: FOLLOW_TARGET (#144) to the autopilot from observable 3-D positions (see :mod:`onboard.io.follow`)."""

    _path: ClassVar[str] = "follow"
    enabled: bool = F(False, "bool")
    rate_hz: float = F(5.0, "float", lo=0.0, lo_open=True, hi=50.0)


@dataclass(frozen=True)
class RecordConfig(_Section):
    """``record``: the flight recording, an MCAP file of the daemon's inputs and outputs (see :mod:`onboard.io.record`)."""

    _path: ClassVar[str] = "record"
    path: str | None = F(None, "str", nullable=True, pattern=r"^.*\.mcap$", what="a file name ending in .mcap")
    frames: bool = F(True, "bool")
    max_file_mb: float = F(2000.0, "float", lo=1.0, hi=1_000_000.0)
    max_file_s: float = F(600.0, "float", lo=1.0, hi=86_400.0)
    max_files: int = F(0, "int", lo=0, hi=100_000)
    chunk_kb: int = F(1024, "int", lo=16, hi=65_536)
    flush_interval_s: float = F(1.0, "float", lo=0.05, hi=60.0)
    compression: str = F("none", "str", choices=("none", "lz4", "zstd"))
    queue_mb: float = F(64.0, "float", lo=1.0, hi=4096.0)
    sync_mb: float = F(8.0, "float", lo=0.0, hi=4096.0)


@dataclass(frozen=True)
class LiveViewConfig(_Section):
    """``live_view``: the Foxglove WebSocket server for watching live (see :mod:`onboard.io.live_view`)."""

    _path: ClassVar[str] = "live_view"
    port: int | None = F(None, "int", nullable=True, lo=1, hi=65535)
    host: str = F("127.0.0.1", "str")
    queue_length: int = F(32, "int", lo=1, hi=10_000)
    los_length_m: float = F(500.0, "float", lo=0.0, lo_open=True, hi=1_000_000.0)
    trail_points: int = F(600, "int", lo=2, hi=100_000)


@dataclass(frozen=True)
class LoggingConfig(_Section):
    """``logging``: level, line format, and how often a repeated rejection is logged."""

    _path: ClassVar[str] = "logging"
    level: str = F("INFO", "str", choices=("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"))
    format: str = F("text", "str", choices=("text", "json"))
    reject_log_interval_s: float = F(10.0, "float", lo=0.0, hi=3600.0)


@dataclass(frozen=True)
class OnboardConfig(_Section):
    """The whole configuration.  ``OnboardConfig()`` is the built-in default, valid as is."""

    _path: ClassVar[str] = ""
    vehicle: str = F("uav1", "str", pattern=r"^[A-Za-z0-9_.-]+$",
                     what="a name of letters, digits, '_', '.', '-' (one zenoh key chunk)")
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
    record: RecordConfig = _section(RecordConfig)
    live_view: LiveViewConfig = _section(LiveViewConfig)
    logging: LoggingConfig = _section(LoggingConfig)

    def bearing_white_sigma_rad(self) -> float:
        """The white noise of one bearing the estimator assumes, 1 sigma per axis (rad):
        ``sqrt(attitude_white^2 + (pixel_sigma / f)^2)``, ``f`` the mean focal length in pixels."""
        e, k = self.estimator, self.camera.intrinsics
        f_px = 0.5 * (k.fx_px + k.fy_px)
        return math.hypot(math.radians(e.attitude_white_sigma_deg), e.pixel_sigma_px / f_px)

    def pose_buffer_config(self):
        """:meth:`PoseConfig.buffer_config` with the horizons bounded by this configuration's bearing noise."""
        return self.pose.buffer_config(self.bearing_white_sigma_rad())


# --------------------------------------------------------------------------- building from mappings


_Sources = Mapping[str, str]


def _source_of(path: str, sources: _Sources, default: str) -> str:
    """The source of the most specific overridden prefix of ``path``."""
    p = path
    while p:
        base = re.sub(r"\[\d+\]$", "", p)
        if base in sources:
            return sources[base]
        if "." not in base:
            break
        p = base.rsplit(".", 1)[0]
    return default


def _fail(exc: FieldError, sources: _Sources, default: str) -> OnboardConfigError:
    return OnboardConfigError(_source_of(exc.path, sources, default), exc.path, exc.expected, exc.got_text, exc.hint)


def _build_imaging(raw: Any, path: str) -> ImagingParams:
    if raw is None:
        return ImagingParams()
    if not isinstance(raw, Mapping):
        raise FieldError(path, "a mapping of imaging parameters", raw)
    defaults = ImagingParams()
    known = [f.name for f in fields(ImagingParams)]
    kwargs = {}
    for key, value in raw.items():
        if key not in known:
            raise FieldError(f"{path}.{key}", f"a key of {path} ({', '.join(known[:4])}, ...)", None,
                             _did_you_mean(key, known), got_text=f"unknown key {key!r}")
        kind = "int" if isinstance(getattr(defaults, key), int) else "float"
        kwargs[key] = _Spec(kind).check(value, f"{path}.{key}")
    try:
        return ImagingParams(**kwargs)
    except ConfigError as exc:
        msg = str(exc)
        m = re.match(r"^imaging\.(\w+)(?: \(([^)]*)\))? must be (.*?)(?:, got (.*))?$", msg)
        if m:
            key = m.group(1)
            got = m.group(4) if m.group(4) is not None else (m.group(2) or _show(kwargs.get(key)))
            raise FieldError(f"{path}.{key}", m.group(3), None, got_text=got) from None
        m = re.match(r"^imaging\.(\w+)", msg)
        key = m.group(1) if m else ""
        raise FieldError(f"{path}.{key}" if key else path, "consistent imaging parameters", None, got_text=msg) from None


def _build(cls, raw: Any, path: str):
    """Build section ``cls`` from a raw mapping (None = defaults); FieldError on any problem."""
    if cls is ImagingParams:
        return _build_imaging(raw, path)
    if raw is None:
        return cls()
    if not isinstance(raw, Mapping):
        raise FieldError(path or "(document)", f"a mapping with keys {', '.join(_keys(cls))}", raw)
    known = _keys(cls)
    kwargs: dict[str, Any] = {}
    for key, value in raw.items():
        sub = f"{path}.{key}" if path else str(key)
        if key not in known:
            where = f"a key of {path}" if path else "a key of the document"
            raise FieldError(sub, f"{where} ({', '.join(known)})", None, _did_you_mean(key, known),
                             got_text=f"unknown key {key!r}")
        f = next(f for f in fields(cls) if f.name == key)
        if "section" in f.metadata:
            if value is None and f.metadata.get("nullable"):
                kwargs[key] = None
            else:
                kwargs[key] = _build(f.metadata["section"], value, sub)
        elif f.metadata.get("free"):
            if value is None:
                value = {}
            if not isinstance(value, Mapping):
                raise FieldError(sub, "a mapping", value)
            kwargs[key] = dict(value)
        else:
            kwargs[key] = value
    return cls(**kwargs)


def _keys(cls) -> list[str]:
    return [f.name for f in fields(cls)]


def _check_sliding(cfg: OnboardConfig) -> None:
    """``estimator.sliding`` keys must be SlidingConfig fields (when the estimator is installed)."""
    extra = cfg.estimator.sliding
    if not extra:
        return
    try:
        from onboard.estimation.sliding import SlidingConfig
    except ImportError:
        raise FieldError("estimator.sliding", "{} (onboard.estimation.sliding is not available)", extra) from None
    known = [f.name for f in fields(SlidingConfig)]
    for key in extra:
        if key not in known:
            raise FieldError(f"estimator.sliding.{key}", f"a SlidingConfig field ({', '.join(known)})", None,
                             _did_you_mean(key, known), got_text=f"unknown key {key!r}")
    try:
        SlidingConfig(**{"window_s": cfg.estimator.window_s, **extra})
    except Exception as exc:  # noqa: BLE001 - any refusal of the estimator's own validation
        raise FieldError("estimator.sliding", "valid SlidingConfig values", None, got_text=f"{extra!r} ({exc})") from None


def build_config(raw: Mapping[str, Any] | None, source: str = DEFAULT_SOURCE, sources: _Sources | None = None) -> OnboardConfig:
    """Validate a raw mapping (as read from YAML, with overrides merged) into :class:`OnboardConfig`.

    ``sources`` maps overridden field paths to where they came from (``env IRTRACK_X``,
    ``--option``) so an error names the right place; everything else is blamed on ``source``.
    """
    sources = sources or {}
    try:
        cfg = _build(OnboardConfig, raw, "")
        _check_sliding(cfg)
        return cfg
    except FieldError as exc:
        raise _fail(exc, sources, source) from None
    except (ConfigError, FrameError) as exc:  # a library's own check (e.g. CameraMount)
        raise OnboardConfigError(source, "(document)", "a consistent configuration", str(exc)) from None


# --------------------------------------------------------------------------- YAML, env, overrides


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate keys."""


def _construct_mapping(loader, node, deep=False):
    mapping = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in mapping:
            raise yaml.constructor.ConstructorError(
                "while constructing a mapping", node.start_mark, f"found duplicate key {key!r}", key_node.start_mark
            )
        mapping[key] = loader.construct_object(value_node, deep=deep)
    return mapping


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def _read_yaml(path: str) -> Any:
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except FileNotFoundError:
        raise OnboardConfigError(path, "(file)", "an existing file", "no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise OnboardConfigError(path, "(file)", "a readable UTF-8 file", f"{type(exc).__name__}: {exc}") from None
    try:
        data = yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark is not None else "(document)"
        problem = " ".join(str(getattr(exc, "problem", None) or exc).split())
        context = getattr(exc, "context", None)
        text = f"{context} {problem}" if context else problem
        raise OnboardConfigError(path, where, "valid YAML", " ".join(text.split())) from None
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise OnboardConfigError(path, "(document)", "a mapping of sections (vehicle, mavlink, zenoh, ...)", _show(data))
    return data


def _leaf_paths(cls=OnboardConfig, prefix: str = "") -> list[str]:
    out = []
    for f in fields(cls):
        p = f"{prefix}.{f.name}" if prefix else f.name
        sub = f.metadata.get("section")
        if sub is ImagingParams:
            out += [f"{p}.{g.name}" for g in fields(ImagingParams)]
        elif sub is not None and not f.metadata.get("nullable"):
            out += _leaf_paths(sub, p)
        else:
            out.append(p)
    return out


def _env_name(path: str) -> str:
    return ENV_PREFIX + path.replace(".", "_").upper()


def env_overrides(environ: Mapping[str, str] | None = None) -> dict[str, tuple[Any, str]]:
    """``{field.path: (value, "env NAME")}`` from ``IRTRACK_*`` variables.

    Values are parsed as YAML (``"5"`` -> 5, ``"true"`` -> True, ``"[a, b]"`` -> list, ``""`` ->
    null).  An ``IRTRACK_<SECTION>_...`` name whose section exists but whose field does not raises
    :class:`OnboardConfigError` with a "did you mean"; other ``IRTRACK_*`` names are not ours.
    """
    environ = os.environ if environ is None else environ
    by_name = {_env_name(p): p for p in _leaf_paths()}
    by_name.update(ENV_ALIASES)
    sections = {_env_name(f.name) + "_" for f in fields(OnboardConfig) if "section" in f.metadata}
    out: dict[str, tuple[Any, str]] = {}
    for name in sorted(environ):
        if not name.startswith(ENV_PREFIX):
            continue
        src = f"env {name}"
        path = by_name.get(name)
        if path is None:
            if any(name.startswith(s) for s in sections):
                raise OnboardConfigError(src, "(name)", "a known IRTRACK_<SECTION>_<FIELD> variable", repr(name),
                                         _did_you_mean(name, by_name))
            continue
        text = environ[name]
        try:
            value = yaml.safe_load(text) if text.strip() else None
        except yaml.YAMLError:
            value = text
        out[path] = (value, src)
    return out


def _set_path(raw: dict, path: str, value: Any, source: str) -> None:
    parts = path.split(".")
    node = raw
    for i, part in enumerate(parts[:-1]):
        nxt = node.get(part)
        if nxt is None:
            nxt = {}
        elif not isinstance(nxt, dict):
            raise OnboardConfigError(source, ".".join(parts[: i + 1]), "a mapping", _show(nxt))
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
    if path not in leaves and not any(p.startswith(path + ".") for p in leaves) and not path.startswith("estimator.sliding."):
        raise OnboardConfigError("--set", path or "(option)", "a configuration field path", repr(text),
                                 _did_you_mean(path, leaves))
    try:
        value = yaml.safe_load(value_text) if value_text.strip() else None
    except yaml.YAMLError:
        value = value_text
    return path, value


def load_config(
    path: str | os.PathLike | None = None,
    overrides: Mapping[str, tuple[Any, str]] | None = None,
    environ: Mapping[str, str] | None = None,
) -> OnboardConfig:
    """Defaults < ``path`` (YAML) < environment < ``overrides`` (``{field.path: (value, source)}``).

    ``environ``: the variables to read (default ``os.environ``; pass ``{}`` to ignore them).
    """
    source = DEFAULT_SOURCE if path is None else os.fspath(path)
    raw: dict[str, Any] = {} if path is None else dict(_read_yaml(source))
    sources: dict[str, str] = {}
    merged = dict(env_overrides(environ))
    merged.update(overrides or {})
    for p, (value, src) in merged.items():
        _set_path(raw, p, value, src)
        sources[p] = src
    return build_config(raw, source, sources)


def config_to_dict(cfg) -> Any:
    """Plain YAML-able data of a config (tuples -> lists); ``load`` of it gives the same config."""
    if dataclasses.is_dataclass(cfg):
        return {f.name: config_to_dict(getattr(cfg, f.name)) for f in fields(cfg)}
    if isinstance(cfg, (tuple, list)):
        return [config_to_dict(x) for x in cfg]
    if isinstance(cfg, Mapping):
        return {k: config_to_dict(v) for k, v in cfg.items()}
    return cfg

