"""Free loopback ports for the demo, the benches and the tests (one helper instead of one per file):
a TCP port, a UDP port, an even UDP port pair for RTP + RTCP.

The port is free when the function returns: the kernel picked it for a socket bound to
``127.0.0.1:0``, which is then closed.  Another process may take it before the caller binds it; the
callers are short-lived children started at once, the usual trade-off (the OS offers no "reserve").
"""

from __future__ import annotations

import socket

__all__ = ["free_tcp_port", "free_udp_port", "free_rtp_port"]

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


def free_rtp_port(host: str = "127.0.0.1", tries: int = 50) -> int:
    """An even UDP port on ``host`` with the next one free too (RTP and RTCP, RFC 3550 section 11), as
    found now: a receiver that opens it later races other programs for it (fine on a test machine)."""
    for _ in range(tries):
        a = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            a.bind((host, 0))
            port = a.getsockname()[1]
            if port % 2 or port >= 65535:
                continue
            b.bind((host, port + 1))
            return port
        except OSError:
            continue
        finally:
            a.close()
            b.close()
    raise OSError(f"no free even UDP port pair on {host} after {tries} tries")
