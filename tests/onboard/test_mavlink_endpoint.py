"""The MAVLink connection-string grammar (onboard.io.mavlink_endpoint): every form the daemon, the camera's
ground-station endpoints and the simulator take, and what it refuses, naming the field."""

from __future__ import annotations

import pytest

from onboard.core.errors import ConfigError
from onboard.io.mavlink_endpoint import MavlinkEndpoint, parse_endpoint


@pytest.mark.parametrize(
    "text, expected",
    [
        ("udpin:0.0.0.0:14540", MavlinkEndpoint("udpin", "udpin:0.0.0.0:14540")),
        ("udp:127.0.0.1:14550", MavlinkEndpoint("udpin", "udpin:127.0.0.1:14550")),
        ("udpout:10.0.0.2:14555", MavlinkEndpoint("udpout", "udpout:10.0.0.2:14555")),
        ("tcp:127.0.0.1:5760", MavlinkEndpoint("tcp", "tcp:127.0.0.1:5760")),
        ("tcpin:0.0.0.0:5760", MavlinkEndpoint("tcpin", "tcpin:0.0.0.0:5760")),
        ("serial:/dev/ttyS1:921600", MavlinkEndpoint("serial", "/dev/ttyS1", 921600)),
        ("serial:///dev/ttyACM0:57600", MavlinkEndpoint("serial", "/dev/ttyACM0", 57600)),
        ("/dev/ttyUSB0,115200", MavlinkEndpoint("serial", "/dev/ttyUSB0", 115200)),
        ("/dev/ttyTHS1", MavlinkEndpoint("serial", "/dev/ttyTHS1", 115200)),
    ],
)
def test_parse_endpoint_forms(text, expected):
    assert parse_endpoint(text) == expected


@pytest.mark.parametrize(
    "text",
    [
        "",
        "udpin:14540",
        "udpin:host:0",
        "udpin:host:70000",
        "tcp:host",
        "ftp:x:1",
        "serial:/dev/ttyS1:fast",
        "serial:",
        "serial:/dev/ttyS1:5\u00b2",  # a superscript two: str.isdigit holds, int() raised ValueError
    ],
)
def test_parse_endpoint_rejects_with_field_name(text):
    with pytest.raises(ConfigError, match="--mavlink"):
        parse_endpoint(text)


@pytest.mark.parametrize("text", ["udpbcast:1.2.3.4:14550", "udpin:host:0", "udpout:a:b:1", "ftp:x:1", ""])
def test_one_grammar_refuses_what_neither_side_uses(text):
    with pytest.raises(ConfigError, match="--mavlink"):
        parse_endpoint(text)
