"""The autopilot link's transports and parser: one UDP socket of our own (each datagram parsed alone), serial or
TCP through pymavlink's port classes (bytes only), a ``tcp:`` connection made without blocking (:class:`TcpDial`)
and a pymavlink TCP connection over its socket (:func:`tcp_connected`), and pymavlink's parser with the signature
checked before its replay table is touched.  :mod:`onboard.io.mavlink_link` (the autopilot) and :mod:`onboard.io.gcs_link` (ground
stations) use them."""

from __future__ import annotations

import errno
import hashlib
import ipaddress
import os
import select
import socket
import threading
import time
from concurrent.futures import Future

from pymavlink.dialects.v20 import common as mavlink2

from onboard.io.mavlink_endpoint import MavlinkEndpoint
from onboard.io.mavlink_wire import use_mavlink2

__all__ = [
    "MAX_DATAGRAM_PARSE_BYTES",
    "TCP_CONNECT_TIMEOUT_S",
    "DialFailed",
    "StreamTransport",
    "TcpDial",
    "UdpTransport",
    "new_parser",
    "new_signing",
    "signature_refusal",
    "tcp_connected",
]

#: a new signed stream may lag our signing clock by this much (pymavlink's rule), 10 us units
_SIGNING_NEW_STREAM_LAG = 6_000_000
#: MAVLink 2 signing timestamps count 10 us units since 2015-01-01 00:00:00 UTC
_SIGNING_EPOCH_S = 1420070400
_MAX_DATAGRAM_BYTES = 65535
_STREAM_READ_BYTES = 4096
#: larger UDP datagrams are dropped unparsed: 16 of the largest MAVLink 2 packets (280 bytes)
MAX_DATAGRAM_PARSE_BYTES = 16 * 280
#: a ``tcp:`` peer that neither takes nor refuses the connection in this long (s; an address whose host drops the
#: packets) is given up, and its owner dials again later: the connection is made without blocking, so the daemon's
#: main loop (the autopilot's telemetry, the ground stations, the status) never waits for it
TCP_CONNECT_TIMEOUT_S = 5.0


class _Parser(mavlink2.MAVLink):
    """pymavlink's parser with the signature checked before the replay table is touched.

    pymavlink's own ``check_signature`` records a packet's timestamp before it compares the
    signature, so one packet with a wrong key and a far-future timestamp would make every genuine
    packet of that stream look replayed.  Here an entry is only made for a verified packet, which
    also bounds ``stream_timestamps`` to the genuine (link id, system, component) streams.
    ``sig_reject`` names why the last signed packet was refused.
    """

    sig_reject = ""

    def check_signature(self, msgbuf, srcSystem, srcComponent):  # noqa: N803 - pymavlink's signature
        signing = self.signing
        digest = hashlib.sha256(signing.secret_key + bytes(msgbuf[:-6])).digest()[:6]
        if digest != bytes(msgbuf[-6:]):
            self.sig_reject = "signature_bad"
            return False
        link_id = msgbuf[-13]
        tlow, thigh = self.mav_sign_unpacker.unpack(msgbuf[-12:-6])
        timestamp = tlow + (thigh << 32)
        key = (link_id, srcSystem, srcComponent)
        last = signing.stream_timestamps.get(key)
        if last is not None and timestamp <= last:
            self.sig_reject = "signature_replay"
            return False
        if last is None and timestamp + _SIGNING_NEW_STREAM_LAG < signing.timestamp:
            self.sig_reject = "signature_stale"
            return False
        signing.stream_timestamps[key] = timestamp
        signing.timestamp = max(signing.timestamp, timestamp)
        return True


def new_signing(key: bytes | None, link_id: int = 0) -> mavlink2.MAVLinkSigning:
    """The signing state of one link: with ``key`` (32 bytes) everything sent is signed with ``link_id`` and only
    verified packets are accepted (:class:`_Parser`); None: unsigned, as MAVLink without signing."""
    signing = mavlink2.MAVLinkSigning()
    if key is not None:
        signing.secret_key = key
        signing.sign_outgoing = True
        signing.link_id = link_id
        # 10 us units since 2015-01-01 (MAVLink 2 signing): the wall clock, as the protocol asks
        signing.timestamp = int(max(time.time() - _SIGNING_EPOCH_S, 0.0) * 100_000)
    return signing


def signature_refusal(msg, sig_reject: str, prefix: str) -> str | None:
    """The counter name of a packet refused for its signature (``msg`` a BAD_DATA "Invalid signature"), else None:
    ``<prefix>_`` + the parser's ``sig_reject`` (``signature_bad|replay|stale``), ``v1_refused`` for MAVLink 1,
    ``unsigned`` for an unsigned MAVLink 2 packet."""
    if msg.get_type() != "BAD_DATA" or str(getattr(msg, "reason", "")) != "Invalid signature":
        return None
    if sig_reject:
        return f"{prefix}_{sig_reject}"
    raw = bytes(getattr(msg, "data", b"")[:1])
    return f"{prefix}_v1_refused" if raw == b"\xfe" else f"{prefix}_unsigned"


def new_parser(signing, file=None, src_system: int = 0, src_component: int = 0) -> _Parser:
    p = _Parser(file, src_system, src_component)
    p.robust_parsing = True
    p.signing = signing
    return p


class UdpTransport:
    """One UDP socket of our own.  ``udpin`` binds HOST:PORT and answers only the locked autopilot's
    address (``peer``); ``udpout`` sends to its fixed HOST:PORT and takes datagrams from there only (a connected
    socket: the kernel picks the source address of the route to it, 127.0.0.1 for a router on loopback, and drops
    what other addresses send; unconnected, its ephemeral port was open on every interface and anyone reaching it
    was read as the autopilot).  Each datagram is parsed alone."""

    datagrams = True

    def __init__(self, kind: str, host: str, port: int, extra: tuple[tuple[str, int], ...]) -> None:
        self.kind = kind
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.fixed: tuple[str, int] | None = None
        try:
            if kind == "udpin":
                # a plain bind, no SO_REUSEADDR: with it a second daemon on the same port bound silently and the
                # kernel handed each datagram to one of the two; without it the second one's open fails (counted
                # mavlink_open_failed, retried; no_mavlink warns) while the first holds the port
                self.sock.bind((host, port))
            else:
                self.fixed = (socket.gethostbyname(host), port)
                self.sock.connect(self.fixed)
        except Exception:
            self.sock.close()
            raise
        self.peer: tuple[str, int] | None = None
        self.extra = extra

    def fileno(self) -> int:
        return self.sock.fileno()

    def read(self) -> tuple[bytes, object] | None:
        try:
            data, addr = self.sock.recvfrom(_MAX_DATAGRAM_BYTES)
        except (BlockingIOError, InterruptedError):
            return None
        except ConnectionRefusedError:  # ICMP port unreachable from an earlier send: not our input
            return b"", None
        return data, addr

    def write(self, buf: bytes) -> None:
        if self.fixed is not None:
            try:
                self.sock.send(buf)
            except ConnectionRefusedError:
                pass  # ICMP port unreachable from an earlier send: nobody listens there yet (a router restarting)
        elif self.peer is not None:
            self.sock.sendto(buf, self.peer)
        for addr in self.extra:
            try:
                self.sock.sendto(buf, addr)
            except ConnectionRefusedError:
                pass  # (connected udpout) an earlier send's ICMP port unreachable, reported on this one

    def close(self) -> None:
        self.sock.close()


class StreamTransport:
    """Serial or TCP through pymavlink's port classes, used only for bytes (its message store is never
    fed); one parser per stream, kept across reads."""

    datagrams = False

    def __init__(self, conn) -> None:
        self.conn = conn

    def fileno(self) -> int | None:
        fd = getattr(self.conn, "fd", None)
        return fd

    def read(self) -> tuple[bytes, object] | None:
        fd = self.fileno()
        if fd is not None:
            r, _, _ = select.select([fd], [], [], 0)
            if not r:
                return None
        data = self.conn.recv(_STREAM_READ_BYTES)
        if not data:
            return None
        return bytes(data), None

    def write(self, buf: bytes) -> None:
        self.conn.write(buf)

    @property
    def lost(self) -> bool:
        """Whether the peer closed or reset a ``tcp:`` connection (:func:`tcp_connected`): its owner closes it and
        dials again.  Never for serial."""
        return bool(getattr(self.conn, "irtrack_lost", False))

    def close(self) -> None:
        self.conn.close()


class DialFailed(Exception):
    """A ``tcp:`` connection that could not be made; the text says why (refused, no answer, out of descriptors)."""


_resolving: dict[str, Future] = {}  # host name -> its lookup under way (one per name, however often it is dialled)
_resolver_lock = threading.Lock()


def _resolve(host: str) -> Future:
    """The IPv4 address of ``host`` looked up on a daemon thread of its own, one per name: ``getaddrinfo`` blocks
    for the resolver's timeouts (seconds a try) where no name server answers, as on a vehicle off the network; a
    pool's threads would be joined at exit (a stopping daemon held for them) and queue one name behind another."""
    with _resolver_lock:
        pending = _resolving.get(host)
        if pending is not None and not pending.done():
            return pending
        future: Future = Future()

        def lookup() -> None:
            try:
                future.set_result(socket.getaddrinfo(host, None, socket.AF_INET, socket.SOCK_STREAM))
            except BaseException as exc:  # noqa: BLE001 - handed to the dial, which names it
                future.set_exception(exc)

        threading.Thread(target=lookup, name="irtrack-resolve", daemon=True).start()
        _resolving[host] = future
        return future


class TcpDial:
    """A ``tcp:`` connection to ``endpoint`` under way, begun at ``now_s`` without blocking: pymavlink's ``mavtcp``
    connects in its constructor, blocking until the peer answers or the kernel gives up (two minutes against an
    address that drops the packets), and reconnects inside ``recv`` and ``write`` in a loop of its own that prints to
    stdout.  :meth:`settle` finishes it.  A host name is looked up on a thread of its own first (:func:`_resolve`).
    Raises :class:`DialFailed` when the connection cannot even be begun."""

    def __init__(self, endpoint: MavlinkEndpoint, now_s: float) -> None:
        host, port = endpoint.device.split(":")[1:]
        self.endpoint = endpoint
        self.since_s = now_s
        self.port = int(port)
        self.sock: socket.socket | None = None
        self._lookup: Future | None = None
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            self._lookup = _resolve(host)
            self.host = host
            return
        self._connect(host)

    def _connect(self, address: str) -> None:
        sock = None
        try:
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)  # (out of descriptors: DialFailed)
            sock.setblocking(False)
            err = sock.connect_ex((address, self.port))
        except OSError as exc:
            if sock is not None:
                sock.close()
            raise DialFailed(exc.strerror or str(exc)) from exc
        if err not in (0, errno.EINPROGRESS, errno.EWOULDBLOCK):
            sock.close()
            raise DialFailed(os.strerror(err))
        self.sock = sock

    def settle(self, now_s: float, src_system: int, src_component: int):
        """The pymavlink connection (:func:`tcp_connected`) once the peer has taken it, None while it has not
        answered; :class:`DialFailed` (the socket closed) when its name has no address, when it refused, or when
        it gave no answer within :data:`TCP_CONNECT_TIMEOUT_S` of the start."""
        if self._lookup is not None:
            if not self._lookup.done():
                if now_s - self.since_s < TCP_CONNECT_TIMEOUT_S:
                    return None
                raise DialFailed(f"no address for {self.host!r} within {TCP_CONNECT_TIMEOUT_S:g} s")
            lookup, self._lookup = self._lookup, None
            try:
                address = lookup.result()[0][4][0]
            except Exception as exc:  # noqa: BLE001 - OSError, and a name the codec refuses (a label over 63 chars)
                raise DialFailed(f"no address for {self.host!r}: {getattr(exc, 'strerror', None) or exc}") from exc
            self._connect(address)
        sock = self.sock
        if sock is None:
            raise DialFailed("the connection was given up")
        try:
            poller = select.poll()  # not select.select: it refuses descriptors past 1024
            poller.register(sock, select.POLLOUT)
            if not poller.poll(0):
                if now_s - self.since_s < TCP_CONNECT_TIMEOUT_S:
                    return None  # no answer yet
                why: str | None = f"no answer within {TCP_CONNECT_TIMEOUT_S:g} s"
            else:
                err = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
                why = os.strerror(err) if err else None
            if why is None:
                conn = tcp_connected(sock, self.endpoint, src_system, src_component)
                self.sock = None  # the connection's now
                return conn
        except Exception as exc:  # noqa: BLE001 - socket errors of every kind
            why = getattr(exc, "strerror", None) or str(exc)
        self.close()
        raise DialFailed(why)

    def close(self) -> None:
        self._lookup = None  # a lookup under way finishes on its thread; its answer is not used
        if self.sock is not None:
            self.sock.close()
            self.sock = None


def tcp_connected(sock, endpoint: MavlinkEndpoint, src_system: int, src_component: int):
    """A pymavlink TCP connection (MAVLink 2, :func:`use_mavlink2`) over ``sock``, a socket its owner has already
    connected to ``endpoint``: pymavlink's own ``mavtcp`` connects in its constructor, blocking until the peer
    answers or the kernel gives up (minutes against an address that drops the packets).  It never reconnects by
    itself and prints nothing: the peer's close or reset marks it ``irtrack_lost`` (:attr:`StreamTransport.lost`),
    for its owner to close and dial again."""
    from pymavlink import mavutil

    class _Connected(mavutil.mavtcp):
        def do_connect(self) -> None:
            self.port = sock
            self.port.setblocking(False)
            mavutil.set_close_on_exec(self.port.fileno())
            self.port.setsockopt(socket.SOL_TCP, socket.TCP_NODELAY, 1)

    device = endpoint.device.split(":", 1)[1]  # "tcp:HOST:PORT" -> "HOST:PORT", as mavtcp takes it
    conn = _Connected(device, autoreconnect=False, source_system=src_system, source_component=src_component, retries=0)
    conn.handle_eof = conn.handle_disconnect = lambda: setattr(conn, "irtrack_lost", True)
    return use_mavlink2(conn, src_system, src_component)
