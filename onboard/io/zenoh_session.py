"""Zenoh session plumbing shared by the simulator and the onboard daemon (thin adapter).

Key expressions (``vehicle`` defaults to ``uav1``)::

    irtrack/<vehicle>/ir/frame   IR frames, payload per onboard.core.irframe
    irtrack/<vehicle>/track      track / 3-D estimate (JSON)
    irtrack/<vehicle>/status     service status (JSON)

Payload encodings name their schema (zenoh ``Encoding`` with a schema suffix), so generic recorders and
bridges that keep only typed payloads keep ours: frames ``application/octet-stream;irtrack.irf1/1``
(:data:`FRAME_ENCODING`, the IRF1 layout of :mod:`onboard.core.irframe`), tracks
``application/json;irtrack.track/2``, status ``application/json;irtrack.status/1``.  Readers accept
untyped payloads too (:func:`encoding_schema` is None for them); the daemon refuses only a frame whose
encoding names another schema (``frame_schema``).

The settings, :class:`ZenohConfig` (also the daemon's ``zenoh`` section), map one to one onto the
command line (:func:`config_from_options`): ``--zenoh-connect ENDPOINT`` and
``--zenoh-listen ENDPOINT`` (repeatable, zenoh locators such as ``tcp/127.0.0.1:7447``),
``--zenoh-config FILE`` (a zenoh JSON5/JSON/YAML configuration).  Endpoints given on the command
line are appended to those of the file.  Multicast scouting is off unless asked for (by the
option, or by the file when the option is not given).  With no ``listen`` endpoint from either
source the session listens on nothing (zenoh's own peer default is every interface on a random
port), so a process that only connects opens no port.

Behaviour measured with eclipse-zenoh 1.10 (peer mode):

* A listen endpoint whose port is taken fails ``zenoh.open`` at once ("Address already in
  use"): :func:`open_session` raises :class:`ZenohSessionError`.
* A connect endpoint with nobody listening does NOT fail ``zenoh.open`` (it returns after
  about 0.5 s) and zenoh keeps retrying in the background, at most a second apart
  (:data:`CONNECT_RETRY`, unless a zenoh config file sets its own ``connect/retry``; zenoh's own
  backoff grows to 4 s): a peer that starts later is joined within about a second.  This is what the daemon wants (start before the simulator).
  With ``connect_timeout_s`` set, the session instead requires a peer within that time
  (zenoh ``connect/exit_on_failure`` + ``connect/timeout_ms``) and raises
  :class:`ZenohSessionError` otherwise.
* A malformed endpoint (``bogus``) is refused by :class:`ZenohConfig` (a
  :class:`~onboard.core.schema.SchemaError` naming the field or option); one that passes that check
  but not zenoh's is refused when inserted into the config: raises :class:`ZenohConfigError`.  A
  well-formed but unresolvable host is accepted and retried.
* A missing, unreadable, unknown-extension or invalid config file: :class:`ZenohConfigError`
  naming the file.  So is one whose top level is not an object: zenoh reads a JSON5 list as its
  configuration's fields in order (``[]`` as no setting at all, ``[1, 2]`` as a bad zenoh id), which
  says nothing a user would recognise.

All three errors are :class:`~onboard.core.errors.IrtrackError`; entry points print them on one line and
exit with code 2.
"""

from __future__ import annotations

import json
import logging
import os
import re
from typing import Annotated, Any

import zenoh

from onboard.core.errors import ConfigError, IrtrackError
from onboard.core.schema import Flag, Invalid, Number, SchemaError, Text, Texts, config_dataclass
from onboard.core.status import STATUS_SCHEMA
from onboard.core.track import TRACK_SCHEMA

__all__ = [
    "DEFAULT_VEHICLE",
    "ZenohConfig",
    "config_from_options",
    "ZenohConfigError",
    "ZenohSessionError",
    "build_config",
    "open_session",
    "frame_key",
    "track_key",
    "status_key",
    "guidance_key",
    "check_vehicle_name",
    "FRAME_SCHEMA",
    "FRAME_ENCODING",
    "TRACK_ENCODING",
    "STATUS_ENCODING",
    "GUIDANCE_ENCODING",
    "OBJECTS_ENCODING",
    "objects_key",
    "encoding_schema",
    "foreign_schema",
]

log = logging.getLogger(__name__)

DEFAULT_VEHICLE = "uav1"
FRAME_SCHEMA = "irtrack.irf1/1"  # the IRF1 frame, version 1 (onboard.core.irframe)
FRAME_ENCODING = f"application/octet-stream;{FRAME_SCHEMA}"
TRACK_ENCODING = f"application/json;{TRACK_SCHEMA}"
STATUS_ENCODING = f"application/json;{STATUS_SCHEMA}"
GUIDANCE_ENCODING = "application/json;irtrack.guidance/1"  # onboard.estimation.guidance.GUIDANCE_SCHEMA
OBJECTS_SCHEMA = "irtrack.objects/1"
OBJECTS_ENCODING = f"application/json;{OBJECTS_SCHEMA}"


def encoding_schema(encoding) -> str | None:
    """The schema a zenoh ``Encoding`` (or its text) names after ``;``; None for an untyped one."""
    if encoding is None:
        return None
    return str(encoding).partition(";")[2] or None


def foreign_schema(encoding, schema: str, usual=None) -> str | None:
    """The schema a typed sample names when it is not ``schema``; None when it is ``schema`` or the sample is
    untyped (octet-stream, accepted too).  ``usual``, zenoh's ``Encoding`` of the expected type made once, is
    matched first by zenoh's own equality: a fraction of the cost of formatting the encoding as text per frame."""
    if encoding is None or (usual is not None and encoding == usual):
        return None
    named = encoding_schema(encoding)
    return named if named is not None and named != schema else None


_VEHICLE_RE = re.compile(r"^[A-Za-z0-9_.-]+$")
_RUST_LOCATION_RE = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")


class ZenohConfigError(ConfigError):
    """A zenoh option or config file is invalid (the message names it)."""


class ZenohSessionError(IrtrackError):
    """The zenoh session could not be opened (port in use, no peer within the timeout, ...)."""


def _one_line(exc: BaseException) -> str:
    """zenoh errors are multi-line and carry Rust source locations: keep the useful words."""
    text = " ".join(part.strip() for part in str(exc).splitlines() if part.strip())
    text = _RUST_LOCATION_RE.sub("", text)
    return re.sub(r"\s+", " ", text).strip()


def check_vehicle_name(vehicle: str) -> str:
    """A vehicle name is one key-expression chunk: letters, digits, ``_ . -``; returns it."""
    if not isinstance(vehicle, str) or not _VEHICLE_RE.match(vehicle):
        raise ZenohConfigError(
            f"vehicle name must be non-empty letters, digits, '_', '.', '-' (one zenoh key chunk), got {vehicle!r}"
        )
    return vehicle


def frame_key(vehicle: str = DEFAULT_VEHICLE) -> str:
    """``irtrack/<vehicle>/ir/frame``: IR frames (onboard.core.irframe wire format)."""
    return f"irtrack/{check_vehicle_name(vehicle)}/ir/frame"


def track_key(vehicle: str = DEFAULT_VEHICLE) -> str:
    """``irtrack/<vehicle>/track``: tracks and 3-D estimates, JSON."""
    return f"irtrack/{check_vehicle_name(vehicle)}/track"


def guidance_key(vehicle: str = DEFAULT_VEHICLE) -> str:
    """``irtrack/<vehicle>/guidance``: observer guidance advice, JSON (only while a manoeuvre is advised)."""
    return f"irtrack/{check_vehicle_name(vehicle)}/guidance"


def objects_key(vehicle: str = DEFAULT_VEHICLE) -> str:
    """``irtrack/<vehicle>/objects``: every confirmed object of a frame (image chain ``objects``), JSON."""
    return f"irtrack/{check_vehicle_name(vehicle)}/objects"


def status_key(vehicle: str = DEFAULT_VEHICLE) -> str:
    """``irtrack/<vehicle>/status``: service status, JSON."""
    return f"irtrack/{check_vehicle_name(vehicle)}/status"


#: the link protocols of the eclipse-zenoh wheel (zenoh's default features): any other protocol passed every check
#: here and was refused only when the session opened ('Unicast not supported for ... protocol').  zenoh itself knows
#: serial, unixpipe and vsock too, behind features the wheel is not built with.
LINK_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream")


@config_dataclass
class ZenohConfig:
    """The session: the ``zenoh`` section of the daemon's configuration (``config/onboard.yaml``; composed
    by :class:`onboard.app.config.OnboardConfig`) and what the ``--zenoh-*`` options of every command say
    (:func:`config_from_options`).

    connect, listen
        Zenoh endpoints (``<protocol>/<address>[?<metadata>][#<config>]``), appended to the
        file's.
    config_file
        Path of a zenoh config (``.json5``, ``.json`` or ``.yaml``), or None.
    multicast_scouting
        True/False forces it; None means off unless the config file enables it.  The default, False, is
        the daemon's; the commands pass None when neither option is given.
    gossip_autoconnect
        Whether the session dials the peers and routers that its peers' and routers' gossip names
        (``scouting/gossip/autoconnect``): addresses nobody gave the vehicle, which a direct peer link also takes
        around a router's access control.  False (the daemon's default): only the configured endpoints are
        dialed; True: zenoh's own peer default (dial routers and peers); None: as the config file says, else
        zenoh's default (what the commands on the ground pass: the loopback fleet meets that way).  The sessions
        that gossip introduces still listen and answer; they only do not dial.
    connect_timeout_s
        None: opening never waits for a connect endpoint (zenoh retries in the background).
        A positive number: opening fails unless a connect endpoint answers within it.
    """

    connect: Annotated[tuple[str, ...], Texts()] = ()
    listen: Annotated[tuple[str, ...], Texts()] = ()
    config_file: Annotated[str | None, Text()] = None
    multicast_scouting: Annotated[bool | None, Flag()] = False
    gossip_autoconnect: Annotated[bool | None, Flag()] = False
    connect_timeout_s: Annotated[float | None, Number(0.0, 3600.0, lo_open=True)] = None

    def __post_init__(self) -> None:
        for name in ("connect", "listen"):
            for i, ep in enumerate(getattr(self, name)):
                if "/" not in ep or not ep.split("/", 1)[1]:
                    raise Invalid(f"{name}[{i}]", "a zenoh endpoint <protocol>/<address>, e.g. tcp/127.0.0.1:7447", ep)
                proto, addr = ep.split("/", 1)
                if proto not in LINK_PROTOCOLS:
                    raise Invalid(
                        f"{name}[{i}]",
                        f"a zenoh endpoint whose protocol is one this zenoh links ({', '.join(LINK_PROTOCOLS)})",
                        ep,
                    )
                if proto in ("tcp", "udp", "tls", "quic", "ws"):
                    hostport = addr.split("?", 1)[0].split("#", 1)[0]
                    # "tcp/a:1,tcp/b:2" passed the port check and never connected; a host has neither (a unix
                    # socket's path, or the metadata and config after '?' and '#', may)
                    if any(c in hostport for c in ", \t\n"):
                        raise Invalid(
                            f"{name}[{i}]",
                            "one zenoh endpoint, its host without commas or spaces (a list for several)",
                            ep,
                        )
                    port = hostport.rsplit(":", 1)[1] if ":" in hostport else ""
                    if not (port.isascii() and port.isdigit()) or int(port) > 65535:
                        raise Invalid(f"{name}[{i}]", f"a {proto} endpoint {proto}/HOST:PORT with PORT in 0..65535", ep)


#: the command-line option of each :class:`ZenohConfig` field, the same in every command that opens a session
_OPTION_OF_FIELD = {
    "connect": "--zenoh-connect",
    "listen": "--zenoh-listen",
    "config_file": "--zenoh-config",
    "multicast_scouting": "--zenoh-multicast-scouting",
    "gossip_autoconnect": "zenoh.gossip_autoconnect",
    "connect_timeout_s": "--zenoh-connect-timeout",
}


#: how often a connect endpoint nobody answers yet is dialed again (without a config file; one may set its own)
CONNECT_RETRY = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}

#: what the daemon's errors about its zenoh config file call it (its --zenoh-config option sets this field)
DAEMON_CONFIG_FILE_FIELD = "zenoh.config_file"
#: and its connect timeout (no option: a config key, as in the fleet's file)
DAEMON_CONNECT_TIMEOUT_FIELD = "zenoh.connect_timeout_s"


def config_from_options(**fields: Any) -> ZenohConfig:
    """:class:`ZenohConfig` from a command's ``--zenoh-*`` options (its fields by name); an invalid value's
    :class:`~onboard.core.schema.SchemaError` names the option it came from, as the daemon's does.  A command's
    session dials what gossip names unless its config file says otherwise (``gossip_autoconnect`` None)."""
    fields.setdefault("gossip_autoconnect", None)
    try:
        return ZenohConfig(**fields)
    except SchemaError as exc:
        name = re.split(r"[.\[]", exc.field, maxsplit=1)[0]
        raise exc.as_(SchemaError, _OPTION_OF_FIELD.get(name, exc.source)) from None


#: key expression, encoding and framing of one zenoh put around its payload, bytes (generous)
MESSAGE_OVERHEAD_BYTES = 4096


def _insert(config, key: str, value, what: str) -> None:
    try:
        config.insert_json5(key, json.dumps(value))
    except zenoh.ZError as exc:
        raise ZenohConfigError(f"{what}: {_one_line(exc)}") from None


def _file_list(config, key: str) -> list[str]:
    """The file's endpoint list at ``key``; zenoh's per-mode defaults (a dict) count as none."""
    try:
        value = json.loads(config.get_json(key))
    except Exception:  # noqa: BLE001 - absent key or odd JSON: treat as unset
        return []
    return [str(v) for v in value] if isinstance(value, list) else []


#: JSON5 whitespace and comments before the top-level value (JSON5 whitespace is Unicode's, plus the BOM)
_JSON5_LEADING_RE = re.compile(r"(?:[\s\ufeff]|//[^\n\r\u2028\u2029]*|/\*.*?\*/)*", re.DOTALL)
#: what a JSON5 top-level value is, by how it starts; anything else (``{``, a syntax error) is zenoh's to judge
_JSON5_STARTS = (
    (re.compile(r"\["), "a list"),
    (re.compile(r"[\"']"), "a string"),
    (re.compile(r"[-+.0-9]|Infinity\b|NaN\b"), "a number"),
    (re.compile(r"(?:true|false)\b"), "a boolean"),
    (re.compile(r"null\b"), "null"),
)


def _top_level_kind(path: str) -> str | None:
    """What the top level of the zenoh config file ``path`` is when it is plainly not an object (``"a list"`` ...),
    else None: an object, or a file zenoh's own reader should judge (unreadable, not UTF-8, a syntax error, no value
    at all, an extension it does not read)."""
    ext = os.path.splitext(path)[1]  # as zenoh picks its reader: by the exact extension
    if ext not in (".json", ".json5", ".yaml", ".yml"):
        return None
    try:
        with open(path, "rb") as f:
            text = f.read().decode("utf-8-sig")
    except (OSError, UnicodeDecodeError):
        return None
    if ext in (".json", ".json5"):
        leading = _JSON5_LEADING_RE.match(text)
        rest = text[leading.end() :] if leading else text
        return next((kind for start, kind in _JSON5_STARTS if start.match(rest)), None)
    import yaml

    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return None
    if value is None or isinstance(value, dict):
        return None
    if isinstance(value, list):
        return "a list"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, bool):
        return "a boolean"
    return "a number" if isinstance(value, int | float) else f"a {type(value).__name__}"


#: the file paths a zenoh 1.x configuration's ``transport/link/tls`` may name (the *_base64 forms carry the data)
TLS_FILE_KEYS = (
    "root_ca_certificate",
    "listen_certificate",
    "listen_private_key",
    "connect_certificate",
    "connect_private_key",
)


def _not_a_file(path: str) -> str | None:
    """Why ``path`` is not a file zenoh can read from, in words, or None when it is a file."""
    if os.path.isfile(path):
        return None
    return "a folder, not a file" if os.path.isdir(path) else "not a file" if os.path.exists(path) else "no such file"


def _check_tls_files(config, where: str) -> None:
    """Each TLS file the configuration names must be a readable file: zenoh reads them only when a TLS link opens,
    so a certificate missing from a mount passed ``--check`` and failed the session at start, or at the first
    dial."""
    for key in TLS_FILE_KEYS:
        name = f"transport/link/tls/{key}"
        try:
            value = json.loads(config.get_json(name) or "null")
        except (zenoh.ZError, ValueError):
            continue  # not a key this zenoh knows: nothing to check
        if value is None:
            continue
        path = os.fspath(value)
        what = _not_a_file(path)
        if what is not None:
            raise ZenohConfigError(f"{where}: {name} {path}: {what}")
        if not os.access(path, os.R_OK):
            raise ZenohConfigError(f"{where}: {name} {path}: not readable by this process (uid {os.getuid()})")


def _warn_plain_beside_file(config, settings: ZenohConfig, file_option: str) -> None:
    """Warn when the file's session is a client or links over TLS and the options add endpoints of their own: they
    are opened beside the file's, outside its TLS and a router's access control (deploy/README.md asks for
    ``zenoh.connect`` / ``zenoh.listen`` empty with such a file; a daemon left with the shipped config's loopback
    listener accepted any local peer past the router's rules)."""
    mode = json.loads(config.get_json("mode") or "null")
    file_eps = _file_list(config, "connect/endpoints") + _file_list(config, "listen/endpoints")
    tls = any(str(ep).startswith(("tls/", "quic/")) for ep in file_eps)
    if mode != "client" and not tls:
        return
    extra = [*settings.connect, *settings.listen]
    plain = [ep for ep in extra if not str(ep).startswith(("tls/", "quic/"))]
    if not plain:
        return
    log.warning(
        "%s %s is a %s session, and connect/listen add %s beside it: those links are outside the file's TLS and a "
        "router's access control; give zenoh.connect: [] and zenoh.listen: [] (--set) to keep to the file's",
        file_option,
        settings.config_file,
        "client" if mode == "client" else "TLS",
        ", ".join(map(str, plain)),
    )


def build_config(settings: ZenohConfig, *, max_payload_bytes: int | None = None, file_option: str = "--zenoh-config"):
    """A ``zenoh.Config`` from ``settings`` (file first, then options on top).  No I/O but the file, whose
    errors name it after ``file_option`` (the daemon's ``zenoh.config_file``, a command's ``--zenoh-config``).

    ``max_payload_bytes``: the largest payload the session must receive (the daemon passes
    ``input.max_frame_bytes``, a setting of another section); plus :data:`MESSAGE_OVERHEAD_BYTES` it
    becomes zenoh's own receive limit (``transport/link/rx/max_message_size``, default 1 GiB), so the
    transport drops a larger message before the application sees it.  None keeps the file's or zenoh's.
    """
    p = max_payload_bytes
    if p is not None and (isinstance(p, bool) or not isinstance(p, int) or p < 1):
        raise ZenohConfigError(f"max_payload_bytes must be None or a positive integer, got {p!r}")
    file_sets_listen = False
    if settings.config_file is not None:
        path = os.fspath(settings.config_file)
        what = _not_a_file(path)
        if what is not None:
            raise ZenohConfigError(f"{file_option} {path}: {what}")
        kind = _top_level_kind(path)
        if kind is not None:
            raise ZenohConfigError(
                f"{file_option} {path}: its top level is {kind}; expected an object of zenoh settings "
                "(mode, connect, listen ...)"
            )
        try:
            config = zenoh.Config.from_file(path)
        except zenoh.ZError as exc:
            raise ZenohConfigError(f"{file_option} {path}: {_one_line(exc)}") from None
        _check_tls_files(config, f"{file_option} {path}")
        file_sets_listen = config.get_json("listen/endpoints") != zenoh.Config().get_json("listen/endpoints")
        scouting_in_file = json.loads(config.get_json("scouting/multicast/enabled") or "null")
    else:
        config = zenoh.Config()
        scouting_in_file = None

    if settings.config_file is not None and (settings.connect or settings.listen):
        _warn_plain_beside_file(config, settings, file_option)
    for name in ("connect", "listen"):
        mine = list(getattr(settings, name))
        if mine:
            endpoints = _file_list(config, f"{name}/endpoints") + mine
            for ep in mine:  # one at a time, so the error names the bad one
                _insert(config, f"{name}/endpoints", [ep], f"--zenoh-{name} {ep!r}")
            _insert(config, f"{name}/endpoints", endpoints, f"--zenoh-{name}")
    if not settings.listen and not file_sets_listen:
        _insert(config, "listen/endpoints", [], "listen/endpoints")

    scouting = settings.multicast_scouting
    if scouting is None:
        scouting = bool(scouting_in_file)
    _insert(config, "scouting/multicast/enabled", scouting, "scouting/multicast/enabled")
    if settings.gossip_autoconnect is not None:
        key = "scouting/gossip/autoconnect"
        _insert(config, key, ["router", "peer"] if settings.gossip_autoconnect else [], key)
    if settings.config_file is None:
        # zenoh keeps the shared-memory segments of peers that have gone away mapped for good (an open zenoh bug):
        # every camera or simulator session that ended left the daemon its segments and their descriptors, a leak
        # for a vehicle whose camera reconnects.  Every payload is copied out at once anyway; a config file may
        # still turn it on
        _insert(config, "transport/shared_memory/enabled", False, "transport/shared_memory/enabled")
    if json.loads(config.get_json("connect/retry") or "null") is None:
        # zenoh's own backoff grows to 4 s between dials: a peer that came up after a slow start (a daemon importing
        # on a loaded companion, a router restarted) was joined up to 4 s late, and a ground station started first
        # missed its first tracks.  A dial a second is cheap; a config file that sets its own retry keeps it
        _insert(config, "connect/retry", CONNECT_RETRY, "connect/retry")

    if settings.connect_timeout_s is not None:
        _insert(config, "connect/exit_on_failure", True, "connect/exit_on_failure")
        _insert(config, "connect/timeout_ms", int(round(settings.connect_timeout_s * 1000)), "connect/timeout_ms")
    if p is not None:
        key = "transport/link/rx/max_message_size"
        _insert(config, key, p + MESSAGE_OVERHEAD_BYTES, key)
    return config


def open_session(
    settings: ZenohConfig,
    *,
    max_payload_bytes: int | None = None,
    file_option: str = "--zenoh-config",
    timeout_option: str = "--zenoh-connect-timeout",
):
    """Open a zenoh session for ``settings`` (``max_payload_bytes``, ``file_option`` as :func:`build_config`;
    ``timeout_option``: what sets ``connect_timeout_s`` in the caller, named when no peer came in time); typed,
    one-line errors (see the module docstring)."""
    config = build_config(settings, max_payload_bytes=max_payload_bytes, file_option=file_option)
    try:
        session = zenoh.open(config)
    except zenoh.ZError as exc:
        msg = _one_line(exc)
        low = msg.lower()
        if "address already in use" in low or "address in use" in low:
            where = ", ".join(settings.listen) or "the configured listen endpoint"
            raise ZenohSessionError(f"zenoh: cannot listen on {where}: port already in use") from None
        if "unable to connect" in low:
            raise ZenohSessionError(
                f"zenoh: no peer reachable at {', '.join(settings.connect) or 'the configured endpoints'}"
                f" within {settings.connect_timeout_s:g} s: start it first (the daemon's or a router's listener), or"
                f" wait longer ({timeout_option})"
            ) from None
        endpoints = [f"listen {e}" for e in settings.listen] + [f"connect {e}" for e in settings.connect]
        if settings.config_file is not None:
            endpoints.append(f"{file_option} {settings.config_file}")
        on = f" ({', '.join(endpoints)})" if endpoints else ""
        raise ZenohSessionError(f"zenoh: cannot open session{on}: {msg}") from None
    if settings.connect and settings.connect_timeout_s is None:
        try:
            peers = list(session.info.peers_zid()) + list(session.info.routers_zid())
        except Exception:  # noqa: BLE001 - informational only
            peers = []
        if not peers:
            log.info("zenoh: no peer at %s yet; zenoh keeps retrying in the background", ", ".join(settings.connect))
    return session
