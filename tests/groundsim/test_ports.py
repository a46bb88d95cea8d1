"""groundsim.io.ports: the one free-port helper of the demo, the benches and the tests."""

from __future__ import annotations

import socket

import pytest

from groundsim.io.ports import free_rtp_port, free_tcp_port, free_udp_port

pytestmark = pytest.mark.integration  # opens sockets on 127.0.0.1


@pytest.mark.parametrize("free, kind", [(free_tcp_port, socket.SOCK_STREAM), (free_udp_port, socket.SOCK_DGRAM)])
def test_a_free_port_is_bindable_on_loopback_with_its_kind(free, kind):
    port = free()
    assert 1024 <= port <= 65535  # an ephemeral port, never a privileged one
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", port))
        assert s.getsockname() == ("127.0.0.1", port)


def test_a_tcp_port_in_use_is_not_handed_out():
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        taken = held.getsockname()[1]
        assert all(free_tcp_port() != taken for _ in range(20))


def test_an_rtp_port_is_even_and_its_rtcp_neighbour_is_free_too():
    port = free_rtp_port()
    assert port % 2 == 0 and 1024 <= port < 65535  # RFC 3550 section 11: RTP even, RTCP the next odd
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rtp,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rtcp,
    ):
        rtp.bind(("127.0.0.1", port))
        rtcp.bind(("127.0.0.1", port + 1))
