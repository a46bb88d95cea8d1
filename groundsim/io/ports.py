"""Free loopback ports for the demo, the benches and the tests (one helper instead of one per file).

The port is free when the function returns: the kernel picked it for a socket bound to
``127.0.0.1:0``, which is then closed.  Another process may take it before the caller binds it; the
callers are short-lived children started at once, the usual trade-off (the OS offers no "reserve").
"""

from __future__ import annotations

import socket

__all__ = ["free_tcp_port", "free_udp_port"]

LOOPBACK = "127.0.0.1"


def _free(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind((LOOPBACK, 0))
        return int(s.getsockname()[1])


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    return _free(socket.SOCK_STREAM)


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that was free a moment ago."""
    return _free(socket.SOCK_DGRAM)

