"""MAVLink connection strings, one grammar for the daemon's autopilot link (``--mavlink``), the camera's
ground-station endpoints (``gcs.endpoints``) and the simulator: :func:`parse_endpoint` makes the
:class:`MavlinkEndpoint` that :func:`onboard.io.mavlink_wire.connect` and :mod:`onboard.io.mavlink_transport`
open.

``udpin:HOST:PORT`` (listen), ``udp:HOST:PORT`` (= udpin), ``udpout:HOST:PORT`` (send),
``tcp:HOST:PORT`` (connect), ``tcpin:HOST:PORT`` (listen), ``serial:/dev/ttyX[:BAUD]`` (also
``serial:///dev/ttyX:BAUD``), ``/dev/ttyX[:BAUD]``, ``/dev/ttyX,BAUD`` and ``COMn``; PORT 1..65535.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from onboard.core.errors import ConfigError

__all__ = ["DEFAULT_SERIAL_BAUD", "MavlinkEndpoint", "parse_endpoint"]

DEFAULT_SERIAL_BAUD = 115200


@dataclass(frozen=True)
class MavlinkEndpoint:
    """A parsed connection string: ``kind`` (udpin, udpout, tcp, tcpin, serial), pymavlink ``device``, ``baud``."""

    kind: str
    device: str
    baud: int = DEFAULT_SERIAL_BAUD

    @property
    def host(self) -> str | None:
        """HOST of a network endpoint, None for serial."""
        return None if self.kind == "serial" else self.device.split(":")[1]

    @property
    def port(self) -> int | None:
        """PORT of a network endpoint, None for serial."""
        return None if self.kind == "serial" else int(self.device.split(":")[2])

    @property
    def listens(self) -> bool:
        return self.kind in ("udpin", "tcpin")


DEFAULT_CONNECTION_EXAMPLE = "udpin:0.0.0.0:14540"
_HOSTPORT = re.compile(r"^(?P<host>[^:\s]+):(?P<port>\d+)$")


def parse_endpoint(connection: str, field: str = "--mavlink") -> MavlinkEndpoint:
    """Validate a connection string (grammar in the module docstring).  Raises :class:`ConfigError` naming ``field``."""
    if not isinstance(connection, str) or not connection.strip():
        raise ConfigError(
            f"{field}: expected a MAVLink connection like {DEFAULT_CONNECTION_EXAMPLE!r}, got {connection!r}"
        )
    text = connection.strip()
    for prefix in ("udpin", "udpout", "udp", "tcpin", "tcp"):
        if text.startswith(prefix + ":"):
            m = _HOSTPORT.match(text[len(prefix) + 1 :])
            if not m or not 1 <= int(m["port"]) <= 65535:
                raise ConfigError(f"{field}: {prefix} needs HOST:PORT with PORT in 1..65535, got {connection!r}")
            kind = "udpin" if prefix == "udp" else prefix
            return MavlinkEndpoint(kind, f"{kind}:{m['host']}:{int(m['port'])}")
    if text.startswith("serial:"):
        rest = text[len("serial:") :]
        return _parse_serial(rest[2:] if rest.startswith("//") else rest, connection, field)
    if text.startswith("/dev/") or text.upper().startswith("COM"):
        return _parse_serial(text, connection, field)
    raise ConfigError(
        f"{field}: unknown MAVLink connection {connection!r}; expected udpin:HOST:PORT, udpout:HOST:PORT, "
        "tcp:HOST:PORT, tcpin:HOST:PORT or serial:/dev/ttyX[:BAUD]"
    )


def _parse_serial(rest: str, original: str, field: str) -> MavlinkEndpoint:
    m = re.match(r"^(?P<dev>[^,:]+)(?:[,:](?P<baud>[^,:]*))?$", rest)
    if not m or not m["dev"]:
        raise ConfigError(f"{field}: serial needs a device path like /dev/ttyS0[:BAUD], got {original!r}")
    baud = DEFAULT_SERIAL_BAUD
    if m["baud"] is not None:
        if not (m["baud"].isascii() and m["baud"].isdigit()) or int(m["baud"]) <= 0:
            raise ConfigError(f"{field}: serial baud must be a positive integer, got {m['baud']!r} in {original!r}")
        baud = int(m["baud"])
    return MavlinkEndpoint("serial", m["dev"], baud)
