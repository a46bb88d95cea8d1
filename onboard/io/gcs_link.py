"""Thin pymavlink adapter for the ground-station endpoints of the camera component.

The camera's protocol lives in :mod:`onboard.io.camera_protocol` (pure); this module only moves bytes:

* ``GcsLink(endpoints, component_id)`` opens one connection per endpoint (``udpout:HOST:PORT`` --
  send to a ground station listening there, QGC's default is UDP 14550 --, ``udpin:HOST:PORT``,
  ``tcp:HOST:PORT`` (dialled without blocking: a ground station not up yet, or one that does not answer within
  :data:`TCP_CONNECT_TIMEOUT_S`, is counted ``gcs_open_failed`` and dialled again every :data:`TCP_REDIAL_S`),
  ``tcpin:HOST:PORT``; parsed by :func:`onboard.io.mavlink_endpoint.parse_endpoint`),
  MAVLink 2, common dialect, with ``srcComponent = component_id`` and ``srcSystem`` the autopilot's
  system id once known (:meth:`GcsLink.set_system_id`; nothing is sent before).  ``udpout`` and TCP
  are pymavlink connections (:func:`onboard.io.mavlink_wire.connect`; a ``tcp:`` one over a socket connected
  here, :class:`onboard.io.mavlink_transport.TcpDial`); ``udpin`` is our own socket (below).
* A ``udpout`` endpoint takes datagrams from its ground station's address only: its socket is connected there at
  its first send (when pymavlink has looked the address up; before, it has no port to send to).  pymavlink's
  ``udpout`` socket is unconnected, open on every interface, and it read whatever reached the port our heartbeats
  come from as the ground station's: anyone who saw one could stop the tracking.  As the autopilot link's ``udpout``
  (:class:`onboard.io.mavlink_transport.UdpTransport`); a ground station answers from the port it listens on.  Not
  to a multicast group, whose members answer from addresses of their own.
* :meth:`GcsLink.poll` reads every endpoint without blocking and returns the COMMAND_LONG /
  COMMAND_INT addressed to us (target system 0 or ours, target component 0 or ours) as
  :class:`~onboard.io.camera_protocol.CameraCommand` (with COMMAND_LONG's ``confirmation``, which tells a
  retransmission from a new command), whose ``via`` is where it came from: ``(endpoint index, source address)``,
  the address on ``udpin``, None on the other kinds (one peer each).  Ground stations share ids (QGC is
  255/190 on every copy): the protocol keys requesters by ``via`` too, and a reply carries it back.  It also
  remembers on which endpoint and address each (system, component) spoke last.
* :meth:`GcsLink.send` sends an :class:`~onboard.io.camera_protocol.Outgoing` as the message of that
  name (:func:`onboard.io.mavlink_wire.message_from_fields`): to its ``via`` (a reply's: the endpoint and address
  of its request; a periodic #275 / #276's: the link whose schedule it is on), or without one a reply to where
  its ``reply_to`` spoke last; everything else (the heartbeat, an IDLE status) to every endpoint.  Send
  errors are counted (``gcs_tx_error``), never raised.
* :meth:`GcsLink.links` names the links there are now, each a ``via``: ``(index, None)`` for each connected
  ``udpout`` / TCP / serial endpoint, ``(index, address)`` for each ``udpin`` peer.  The camera keeps the
  tracking statuses' intervals per link (MAVLink: SET_MESSAGE_INTERVAL applies to the link it came on;
  :class:`~onboard.io.status_schedule.StatusSchedules` says why a ``udpin`` peer is a link of its own).
* ``signing_key`` (the autopilot link's, ``mavlink.signing_key_file``): everything sent is signed and only
  verified packets are taken, on every endpoint; refusals are counted ``gcs_unsigned``, ``gcs_v1_refused``,
  ``gcs_signature_bad|replay|stale`` (:func:`onboard.io.mavlink_transport.signature_refusal`).  A refused
  packet makes no ``udpin`` peer.

``udpin`` (anyone may send to the port, so who gets our output is decided here, not by pymavlink's
``mavudp``, which answers every address a datagram ever came from):

* Each datagram is parsed alone by a fresh parser (the autopilot link's, :mod:`onboard.io.mavlink_link`),
  so a truncated or garbage datagram costs only itself (``gcs_truncated``, ``gcs_bad_data``) and never
  swallows the next one, whoever sent it; datagrams too large for MAVLink traffic are dropped unparsed
  (``gcs_datagram_too_large``).
* A source address becomes a *peer* with its first valid message: a known message id with a good
  CRC, of any type.  Not only a HEARTBEAT: a forged heartbeat costs a sender no more than any other
  message, and a router forwards whatever it gets; garbage, a cut packet or an unknown id never makes
  a peer.
* Replies (COMMAND_ACK, the requested message, STATUSTEXT) go to the address the command came from.
  Periodic messages (HEARTBEAT, and #275 / #276 each on its peer's schedule) go to the peers heard within
  ``peer_timeout_s`` (default :data:`PEER_TIMEOUT_S`); a silent peer is dropped, and with it its intervals.
  At most ``max_peers`` (:data:`MAX_PEERS`) peers: messages from further addresses are still answered but make
  no peer (``gcs_peer_refused``; a warning once while the table is full).
* Each peer has its own packet sequence numbers: a ground station counts a gap in the sequence of a component
  as lost packets (QGC's link-loss figure), and the messages each peer alone gets (its replies, its statuses)
  would leave gaps in every other peer's.

Why a separate component and separate endpoints, not the autopilot link's component 191: QGC handles
camera messages only from components 100..105 or the autopilot, and the autopilot link should carry
only what the autopilot needs (heartbeat, rate requests, TIMESYNC: :mod:`onboard.io.mavlink_link` keeps
191 for those).  A ground station that reaches the vehicle only through the autopilot's telemetry
radio gets the camera through a router (``deploy/README.md``: mavlink-router).
"""

from __future__ import annotations

import ipaddress
import logging
import math
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from onboard.core.errors import ConfigError, IrtrackError
from onboard.io.camera_protocol import CameraCommand, Outgoing
from onboard.io.mavlink_endpoint import parse_endpoint
from onboard.io.mavlink_transport import (
    MAX_DATAGRAM_PARSE_BYTES,
    TCP_CONNECT_TIMEOUT_S,
    DialFailed,
    TcpDial,
    UdpTransport,
    new_parser,
    new_signing,
    signature_refusal,
)
from onboard.io.mavlink_wire import connect, message_from_fields

__all__ = ["GcsLink", "GcsLinkError", "PEER_TIMEOUT_S", "MAX_PEERS", "TCP_CONNECT_TIMEOUT_S"]

log = logging.getLogger(__name__)

#: a udpin peer silent this long (s) gets no more periodic messages: QGC heartbeats at 1 Hz and gives up
#: on a camera after 5 s of silence, the same patience the other way round
PEER_TIMEOUT_S = 5.0
#: udpin peers receiving the periodic messages at once (a GCS or two, a router, a tool)
MAX_PEERS = 4
#: requesters remembered for routing replies; the least recently heard is forgotten (ids are sender-chosen)
_MAX_ROUTES = 64
#: a ``tcp:`` ground station that refused the connection is dialled again this often (s), as the autopilot link is
#: reopened (``mavlink.reopen_interval_s``)
TCP_REDIAL_S = 2.0

Address = tuple[str, int]


class _UdpInEndpoint:
    """A ``udpin`` endpoint (module docstring): the autopilot link's UDP socket, a fresh parser per
    datagram, a bounded table of peers.  ``mav`` packs what :meth:`send_to` writes."""

    def __init__(
        self,
        device: str,
        component_id: int,
        count: Callable[..., None],
        peer_timeout_s: float,
        max_peers: int,
        signing: mavlink2.MAVLinkSigning,
    ) -> None:
        _, host, port = device.split(":")
        self.device = device
        self._udp = UdpTransport("udpin", host, int(port), ())
        self.fd = self._udp.fileno()
        self._count = count
        self._signing = signing
        self.mav = new_parser(self._signing, self, 1, component_id)
        self.source_system = 1
        self.peer_timeout_s = peer_timeout_s
        self.max_peers = max_peers
        #: address -> time of its latest valid message, least recently heard first
        self.peers: OrderedDict[Address, float] = OrderedDict()
        self._full_warned = False
        self._dest: Sequence[Address] = ()
        #: peer -> the sequence number of its next packet (module docstring); kept for peers only (bounded), any
        #: other address (answered, not a peer) shares ``_other_seq``
        self._seq: dict[Address, int] = {}
        self._other_seq = 0

    def receive(self, now_s: float, max_datagrams: int) -> list[tuple[Any, Address, str]]:
        """Every message parsed from up to ``max_datagrams`` waiting datagrams, with its source address and why a
        signed one was refused (BAD_DATA included, for the caller to count); valid ones make or refresh a peer."""
        out: list[tuple[Any, Address, str]] = []
        for _ in range(max_datagrams):
            try:
                got = self._udp.read()
            except OSError as exc:
                self._count("gcs_rx_error", f"{type(exc).__name__}: {exc}")
                break
            if got is None:
                break
            data, addr = got
            if not data or not isinstance(addr, tuple):
                continue
            if len(data) > MAX_DATAGRAM_PARSE_BYTES:
                self._count("gcs_datagram_too_large", f"{len(data)} bytes from {addr}")
                continue
            parser = new_parser(self._signing)
            try:
                msg = parser.parse_char(data)
                while msg is not None:
                    mtype = msg.get_type()
                    if mtype != "BAD_DATA" and not mtype.startswith("UNKNOWN_"):
                        self._heard(addr, now_s)
                    out.append((msg, addr, parser.sig_reject))
                    parser.sig_reject = ""
                    msg = parser.parse_char(b"")
            except Exception as exc:  # noqa: BLE001 - pymavlink raises on some garbage
                self._count("gcs_rx_error", f"{type(exc).__name__}: {exc} (from {addr})")
            if parser.buf_len() > 0:
                self._count("gcs_truncated", f"{parser.buf_len()} bytes left over in a datagram from {addr}")
        return out

    def _heard(self, addr: Address, now_s: float) -> None:
        if addr in self.peers:
            self.peers[addr] = now_s
            self.peers.move_to_end(addr)
            return
        self.prune(now_s)
        if len(self.peers) >= self.max_peers:
            self._count("gcs_peer_refused", f"{addr[0]}:{addr[1]} on {self.device}", logging.DEBUG)
            if not self._full_warned:
                self._full_warned = True
                log.warning(
                    "%s: %d ground-station peers already (%s); %s:%d gets replies only",
                    self.device,
                    len(self.peers),
                    ", ".join(f"{a}:{p}" for a, p in self.peers),
                    *addr,
                )
            return
        self.peers[addr] = now_s
        log.info("%s: ground-station peer %s:%d", self.device, *addr)

    def prune(self, now_s: float) -> None:
        """Forget the peers silent for longer than ``peer_timeout_s``."""
        while self.peers:
            addr, last_s = next(iter(self.peers.items()))
            if now_s - last_s <= self.peer_timeout_s:
                break
            del self.peers[addr]
            self._seq.pop(addr, None)
            log.info("%s: ground-station peer %s:%d silent for %.1f s, dropped", self.device, *addr, now_s - last_s)
        if len(self.peers) < self.max_peers:
            self._full_warned = False

    def send_to(self, msg, dest: Sequence[Address]) -> None:
        """Pack ``msg`` for each address in ``dest``, with that address's next sequence number (module docstring), and
        send it there; every address is tried, the first failure raised after."""
        failed: OSError | None = None
        for addr in dest:
            peer = addr in self.peers
            self.mav.seq = self._seq.get(addr, 0) if peer else self._other_seq
            self._dest = (addr,)
            try:
                self.mav.send(msg)
            except OSError as exc:
                failed = failed or exc
            finally:
                self._dest = ()
                if peer:
                    self._seq[addr] = self.mav.seq
                else:
                    self._other_seq = self.mav.seq
        if failed is not None:
            raise failed

    def write(self, buf) -> None:
        """The sending parser's ``file``: ``buf`` to the address :meth:`send_to` is sending to."""
        for addr in self._dest:
            self._udp.sock.sendto(bytes(buf), addr)

    def close(self) -> None:
        self._udp.close()


class GcsLinkError(IrtrackError):
    """A ground-station endpoint could not be opened (port in use ...)."""


class GcsLink:
    """The camera component's sockets (see the module docstring).  Single-threaded."""

    def __init__(
        self,
        endpoints: Sequence[str],
        component_id: int = 100,
        counter=None,
        *,
        clock: Callable[[], float] = time.monotonic,
        peer_timeout_s: float = PEER_TIMEOUT_S,
        max_peers: int = MAX_PEERS,
        signing_key: bytes | None = None,
        signing_link_id: int = 0,
    ) -> None:
        if signing_key is not None and (not isinstance(signing_key, bytes) or len(signing_key) != 32):
            raise ConfigError(f"GcsLink.signing_key: expected 32 bytes, got {type(signing_key).__name__}")
        if isinstance(signing_link_id, bool) or not isinstance(signing_link_id, int) or not 0 <= signing_link_id <= 255:
            raise ConfigError(f"GcsLink.signing_link_id: expected an integer in [0, 255], got {signing_link_id!r}")
        if isinstance(component_id, bool) or not isinstance(component_id, int) or not 1 <= component_id <= 255:
            raise ConfigError(f"gcs.component_id: expected an integer in 1..255, got {component_id!r}")
        if isinstance(peer_timeout_s, bool) or not isinstance(peer_timeout_s, int | float) or not peer_timeout_s > 0:
            raise ConfigError(f"GcsLink.peer_timeout_s: expected seconds > 0, got {peer_timeout_s!r}")
        if isinstance(max_peers, bool) or not isinstance(max_peers, int) or max_peers < 1:
            raise ConfigError(f"GcsLink.max_peers: expected an integer >= 1, got {max_peers!r}")
        self.endpoints = tuple(endpoints)
        parsed = [parse_endpoint(ep, "gcs.endpoints") for ep in self.endpoints]
        self.component_id = component_id
        self.system_id: int | None = None
        self._counter = counter
        self._clock = clock
        self._peer_timeout_s = float(peer_timeout_s)
        self._max_peers = max_peers
        # one signing state for every endpoint: our packets' signing timestamps stay increasing across them
        self._signing = new_signing(signing_key, signing_link_id)
        #: requester (system, component) -> (endpoint index, source address on udpin else None)
        self._route: OrderedDict[tuple[int, int], tuple[int, Address | None]] = OrderedDict()
        self.messages_rx = 0
        self.messages_tx = 0
        self._parsed = parsed
        # None: a tcp: endpoint not connected (yet, or again), dialled at _redial_s[index]
        self._conns: list[Any] = [None] * len(parsed)
        self._redial_s: dict[int, float] = {}
        self._dialling: dict[int, TcpDial] = {}  # tcp: connections under way
        #: udpout endpoints whose socket is not connected to their ground station yet (module docstring)
        self._unpinned = {idx for idx, ep in enumerate(parsed) if ep.kind == "udpout"}
        try:
            for idx in range(len(parsed)):
                self._dial(idx, self._clock(), first=True)
        except Exception:
            self.close()
            raise

    def _dial(self, idx: int, now_s: float, first: bool = False) -> None:
        """Open endpoint ``idx``.  A ``tcp:`` ground station may not be up yet (it starts after the vehicle): its
        refusal is counted (``gcs_open_failed``) and it is dialled again every :data:`TCP_REDIAL_S`; any other
        endpoint that cannot be opened (a port in use) raises :class:`GcsLinkError`, an operator's error."""
        ep = self._parsed[idx]
        self._redial_s.pop(idx, None)
        if ep.kind == "tcp":
            self._start_tcp(idx, now_s, first)
            return
        self._connected(idx, self._open(ep), first)

    def _connected(self, idx: int, conn, first: bool) -> None:
        if self.system_id is not None:
            conn.mav.srcSystem = conn.source_system = self.system_id
        self._conns[idx] = conn
        if not first:
            log.info("gcs: connected to %s", self._parsed[idx].device)

    def _dial_failed(self, idx: int, now_s: float, why: str) -> None:
        self._redial_s[idx] = now_s + TCP_REDIAL_S
        self._count(
            "gcs_open_failed",
            f"gcs.endpoints: cannot open {self._parsed[idx].device!r}: {why}; dialled again every {TCP_REDIAL_S:g} s",
            logging.WARNING,
        )

    def _start_tcp(self, idx: int, now_s: float, first: bool) -> None:
        """Begin connecting ``tcp:`` endpoint ``idx`` without blocking; :meth:`_settle` finishes it."""
        try:
            self._dialling[idx] = TcpDial(self._parsed[idx], now_s)
        except DialFailed as exc:
            self._dial_failed(idx, now_s, str(exc))
            return
        self._settle(now_s, first)  # on loopback the answer (accepted or refused) is already in

    def _settle(self, now_s: float, first: bool = False) -> None:
        """Finish the ``tcp:`` connections under way that have an answer; give up those past their time."""
        for idx, dial in list(self._dialling.items()):
            try:
                conn = dial.settle(now_s, 1, self.component_id)
            except DialFailed as exc:
                del self._dialling[idx]
                self._dial_failed(idx, now_s, str(exc))
                continue
            if conn is not None:
                del self._dialling[idx]
                self._connected(idx, self._with_our_parser(conn), first)

    def _redial(self, now_s: float) -> None:
        for idx, conn in enumerate(self._conns):
            if conn is not None and getattr(conn, "irtrack_lost", False):  # the ground station closed or reset it
                self._count("gcs_link_lost", f"{self.endpoints[idx]}: closed by the ground station; dialled again")
                self._close_one(conn)
                self._conns[idx] = None
                self._redial_s[idx] = now_s + TCP_REDIAL_S
        for idx, at_s in list(self._redial_s.items()):
            if now_s >= at_s:
                self._dial(idx, now_s)
        self._settle(now_s)

    @staticmethod
    def _close_one(conn) -> None:
        try:
            conn.close()
        except Exception:  # noqa: BLE001 - a socket already gone
            pass

    def _with_our_parser(self, conn):
        """``conn`` (a pymavlink connection) with our parser, the autopilot link's: signed output with a key, and only
        verified packets taken in."""
        conn.mav = new_parser(self._signing, conn, 1, self.component_id)
        return conn

    def _open(self, ep):
        try:
            if ep.kind == "udpin":
                return _UdpInEndpoint(
                    ep.device, self.component_id, self._count, self._peer_timeout_s, self._max_peers, self._signing
                )
            options = {} if ep.kind == "serial" else {"autoreconnect": True}
            return self._with_our_parser(connect(ep, 1, self.component_id, **options))
        except Exception as exc:  # noqa: BLE001 - socket and serial errors of every kind
            raise GcsLinkError(
                f"gcs.endpoints: cannot open {ep.device!r}: {getattr(exc, 'strerror', None) or exc}"
            ) from None

    def set_system_id(self, sysid: int) -> None:
        """Speak as ``sysid`` (the autopilot's system id) from now on."""
        if sysid == self.system_id:
            return
        self.system_id = int(sysid)
        for conn in self._conns:
            if conn is None:
                continue
            conn.mav.srcSystem = self.system_id
            conn.source_system = self.system_id
        log.info("camera component %d/%d on %s", self.system_id, self.component_id, ", ".join(self.endpoints))

    def _count(self, key: str, detail: str, level: int = logging.WARNING) -> None:
        if self._counter is not None:
            self._counter.count(key, detail, level=level)

    def peers(self) -> list[list[Address]]:
        """Per endpoint, the udpin peers that receive the periodic messages now ([] for other kinds)."""
        now_s = self._clock()
        out: list[list[Address]] = []
        for conn in self._conns:
            if isinstance(conn, _UdpInEndpoint):
                conn.prune(now_s)
                out.append(list(conn.peers))
            else:
                out.append([])
        return out

    def links(self) -> list[tuple[int, Address | None]]:
        """The links there are now, each as the ``via`` :meth:`poll` gives a command from it (module docstring):
        ``(index, None)`` per connected endpoint of one peer, ``(index, address)`` per ``udpin`` peer."""
        out: list[tuple[int, Address | None]] = []
        for idx, peers in enumerate(self.peers()):
            conn = self._conns[idx]
            if isinstance(conn, _UdpInEndpoint):
                out += [(idx, addr) for addr in peers]
            elif conn is not None and not getattr(conn, "irtrack_lost", False):
                out.append((idx, None))
        return out

    def link_name(self, via) -> str:
        """A link (a ``via``) in words, for the status: its endpoint, and on ``udpin`` the peer's address."""
        checked = self._via(via)
        if checked is None:
            return str(via)
        idx, addr = checked
        return self.endpoints[idx] if addr is None else f"{self.endpoints[idx]} from {addr[0]}:{addr[1]}"

    def _receive(self, conn, now_s: float, max_messages: int) -> list[tuple[Any, Address | None, str]]:
        """The messages waiting on one endpoint, each with its source address (udpin) or None, and why a signed
        one was refused."""
        if isinstance(conn, _UdpInEndpoint):
            return list(conn.receive(now_s, max_messages))
        out: list[tuple[Any, Address | None, str]] = []
        for _ in range(max_messages):
            try:
                msg = conn.recv_msg()
            except Exception as exc:  # noqa: BLE001 - nothing from the wire may stop the loop
                self._count("gcs_rx_error", f"{type(exc).__name__}: {exc}")
                break
            if msg is None:
                break
            out.append((msg, None, conn.mav.sig_reject))
            conn.mav.sig_reject = ""
        return out

    def filenos(self) -> list[int]:
        """The endpoints' input file descriptors (for select; a serial port without one is left out)."""
        return [fd for fd in (getattr(c, "fd", None) for c in self._conns) if isinstance(fd, int) and fd >= 0]

    def poll(self, max_messages: int = 100) -> list[CameraCommand]:
        """Commands addressed to us, from every endpoint (never blocks, never raises)."""
        out: list[CameraCommand] = []
        now_s = self._clock()
        self._redial(now_s)
        for idx, conn in enumerate(self._conns):
            if conn is None:
                continue
            for msg, addr, sig_reject in self._receive(conn, now_s, max_messages):
                self.messages_rx += 1
                mtype = msg.get_type()
                if mtype == "BAD_DATA":
                    refused = signature_refusal(msg, sig_reject, "gcs")
                    if refused is not None:
                        sender = f" (from {addr[0]}:{addr[1]})" if addr is not None else f" (on {self.endpoints[idx]})"
                        self._count(refused, f"packet refused: MAVLink 2 signing is on{sender}")
                    else:
                        self._count("gcs_bad_data", str(getattr(msg, "reason", "")))
                    continue
                if mtype not in ("COMMAND_LONG", "COMMAND_INT"):
                    continue
                src = (msg.get_srcSystem(), msg.get_srcComponent())
                if msg.target_component not in (0, self.component_id):
                    continue
                if msg.target_system != 0 and (self.system_id is None or msg.target_system != self.system_id):
                    continue
                self._route[src] = (idx, addr)
                self._route.move_to_end(src)
                if len(self._route) > _MAX_ROUTES:
                    self._route.popitem(last=False)
                confirmation = 0  # COMMAND_INT has no confirmation field: each one is a first transmission
                if mtype == "COMMAND_LONG":
                    raw = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
                    confirmation = int(msg.confirmation)
                else:
                    raw = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
                p1, p2, p3, p4, p5, p6, p7 = (float(p) if p is not None else math.nan for p in raw)
                params = (p1, p2, p3, p4, p5, p6, p7)
                out.append(CameraCommand(int(msg.command), params, src[0], src[1], confirmation, via=(idx, addr)))
        return out

    def send(self, out: Outgoing) -> int:
        """Send one message; returns on how many endpoints it was written."""
        if self.system_id is None:
            return 0
        if self._dialling:
            self._settle(self._clock())
        targets: list[tuple[int, Address | None]] = [(idx, None) for idx in range(len(self._conns))]
        via = self._via(out.via)
        if via is not None:
            targets = [via]
        elif out.reply_to is not None and out.reply_to in self._route:
            targets = [self._route[out.reply_to]]
        now_s = self._clock()
        n = 0
        for idx, addr in targets:
            conn = self._conns[idx]
            if conn is None or getattr(conn, "irtrack_lost", False):
                continue  # a tcp: ground station not connected (yet, or again): nobody to send to
            try:
                if isinstance(conn, _UdpInEndpoint):
                    if addr is None:
                        conn.prune(now_s)
                    dest = [addr] if addr is not None else list(conn.peers)
                    if not dest:
                        continue  # nobody to send to: not an error, and no sequence number spent
                    conn.send_to(message_from_fields(out.msg, out.fields), dest)
                else:
                    conn.mav.send(message_from_fields(out.msg, out.fields))
                    if idx in self._unpinned:
                        self._pin(idx, conn)
                n += 1
            except Exception as exc:  # noqa: BLE001 - a send failure costs this message only
                self._count("gcs_tx_error", f"{out.msg} on {self.endpoints[idx]}: {type(exc).__name__}: {exc}")
        self.messages_tx += n
        return n

    def _pin(self, idx: int, conn) -> None:
        """Connect ``udpout`` endpoint ``idx``'s socket to its ground station (module docstring), once pymavlink has
        looked the address up: from then on the kernel drops datagrams from any other address."""
        if getattr(conn, "resolved_destination_addr", None) is None:
            return  # pymavlink's send failed before it looked the address up: pinned at a later send
        try:  # pymavlink puts the address in place of a host name once the name resolves
            address = ipaddress.ip_address(conn.destination_addr[0])
        except ValueError:
            # a name that did not resolve at the first send: pymavlink drops that error and sends to the name from
            # then on without putting an address in its place, so this endpoint stays unconnected, as before
            self._unpinned.discard(idx)
            return
        if address.is_multicast:
            # a group's members answer from their own addresses: connected to the group, the socket would drop them all
            self._unpinned.discard(idx)
            return
        try:
            conn.port.connect(conn.destination_addr)
        except OSError:
            # no route there now: the send just made failed the same way (pymavlink drops that error), and the
            # socket has sent nothing anyone could answer; tried again at the next send
            return
        self._unpinned.discard(idx)

    def _via(self, via) -> tuple[int, Address | None] | None:
        """``via`` when it is one :meth:`poll` made (an endpoint's index, a source address or None), else None."""
        if not isinstance(via, tuple) or len(via) != 2:
            return None
        idx, addr = via
        if isinstance(idx, int) and 0 <= idx < len(self._conns) and (addr is None or isinstance(addr, tuple)):
            return idx, addr
        return None

    def close(self) -> None:
        for conn in self._conns:
            if conn is not None:
                self._close_one(conn)
        self._conns = []
        self._redial_s.clear()
        for dial in self._dialling.values():
            dial.close()
        self._dialling.clear()
