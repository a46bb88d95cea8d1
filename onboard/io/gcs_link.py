"""Thin pymavlink adapter for the ground-station endpoints of the camera component.

The camera's protocol lives in :mod:`onboard.io.camera_protocol` (pure); this module only moves bytes:

* ``GcsLink(endpoints, component_id)`` opens one pymavlink connection per endpoint
  (``udpout:HOST:PORT`` -- send to a ground station listening there, QGC's default is UDP 14550 --,
  ``udpin:HOST:PORT``, ``tcp:HOST:PORT``, ``tcpin:HOST:PORT``; parsed by
  :func:`onboard.io.mavlink_wire.parse_endpoint`), MAVLink 2, common dialect
  (:func:`onboard.io.mavlink_wire.connect`), with
  ``srcComponent = component_id`` and ``srcSystem`` the autopilot's system id once known
  (:meth:`GcsLink.set_system_id`; nothing is sent before).
* :meth:`GcsLink.poll` reads every endpoint without blocking and returns the COMMAND_LONG /
  COMMAND_INT addressed to us (target system 0 or ours, target component 0 or ours) as
  :class:`~onboard.io.camera_protocol.CameraCommand`; it remembers on which endpoint each requester
  (system, component) spoke last, so replies go back there.
* :meth:`GcsLink.send` sends an :class:`~onboard.io.camera_protocol.Outgoing` as the message of that
  name (:func:`onboard.io.mavlink_wire.message_from_fields`): to the requester's endpoint when
  ``reply_to`` is set and known, else to
  every endpoint.  Send errors are counted (``gcs_tx_error``), never raised.

Why a separate component and separate endpoints, not the autopilot link's component 191: QGC handles
camera messages only from components 100..105 or the autopilot, and the autopilot link should carry
only what the autopilot needs (heartbeat, rate requests, TIMESYNC: :mod:`onboard.io.mavlink_link` keeps
191 for those).  A ground station that reaches the vehicle only through the autopilot's telemetry
radio gets the camera through a router (``deploy/README.md``: mavlink-router).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

from onboard.core.errors import ConfigError, IrtrackError
from onboard.io.camera_protocol import CameraCommand, Outgoing
from onboard.io.mavlink_wire import connect, message_from_fields, parse_endpoint

__all__ = ["GcsLink", "GcsLinkError"]

log = logging.getLogger(__name__)


class GcsLinkError(IrtrackError):
    """A ground-station endpoint could not be opened (port in use ...)."""


class GcsLink:
    """The camera component's sockets (see the module docstring).  Single-threaded."""

    def __init__(self, endpoints: Sequence[str], component_id: int = 100, counter=None) -> None:
        if isinstance(component_id, bool) or not isinstance(component_id, int) or not 1 <= component_id <= 255:
            raise ConfigError(f"gcs.component_id: expected an integer in 1..255, got {component_id!r}")
        self.endpoints = tuple(endpoints)
        parsed = [parse_endpoint(ep, "gcs.endpoints") for ep in self.endpoints]
        self.component_id = component_id
        self.system_id: int | None = None
        self._counter = counter
        self._route: dict[tuple[int, int], int] = {}
        self.messages_rx = 0
        self.messages_tx = 0
        self._conns = []
        try:
            for ep in parsed:
                self._conns.append(self._open(ep))
        except Exception:
            self.close()
            raise

    def _open(self, ep):
        try:
            return connect(ep, 1, self.component_id, **({} if ep.kind == "serial" else {"autoreconnect": True}))
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
            conn.mav.srcSystem = self.system_id
            conn.source_system = self.system_id
        log.info("camera component %d/%d on %s", self.system_id, self.component_id, ", ".join(self.endpoints))

    def _count(self, key: str, detail: str) -> None:
        if self._counter is not None:
            self._counter.count(key, detail)

    def filenos(self) -> list[int]:
        """The endpoints' input file descriptors (for select; a serial port without one is left out)."""
        return [fd for fd in (getattr(c, "fd", None) for c in self._conns) if isinstance(fd, int) and fd >= 0]

    def poll(self, max_messages: int = 100) -> list[CameraCommand]:
        """Commands addressed to us, from every endpoint (never blocks, never raises)."""
        out: list[CameraCommand] = []
        for idx, conn in enumerate(self._conns):
            for _ in range(max_messages):
                try:
                    msg = conn.recv_msg()
                except Exception as exc:  # noqa: BLE001 - nothing from the wire may stop the loop
                    self._count("gcs_rx_error", f"{type(exc).__name__}: {exc}")
                    break
                if msg is None:
                    break
                self.messages_rx += 1
                mtype = msg.get_type()
                if mtype == "BAD_DATA":
                    self._count("gcs_bad_data", str(getattr(msg, "reason", "")))
                    continue
                if mtype not in ("COMMAND_LONG", "COMMAND_INT"):
                    continue
                src = (msg.get_srcSystem(), msg.get_srcComponent())
                if msg.target_component not in (0, self.component_id):
                    continue
                if msg.target_system != 0 and (self.system_id is None or msg.target_system != self.system_id):
                    continue
                self._route[src] = idx
                if mtype == "COMMAND_LONG":
                    raw = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
                else:
                    raw = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
                p1, p2, p3, p4, p5, p6, p7 = (float(p) if p is not None else math.nan for p in raw)
                params = (p1, p2, p3, p4, p5, p6, p7)
                out.append(CameraCommand(int(msg.command), params, src[0], src[1]))
        return out

    def send(self, out: Outgoing) -> int:
        """Send one message; returns on how many endpoints it was written."""
        if self.system_id is None:
            return 0
        targets: Sequence[int] = range(len(self._conns))
        if out.reply_to is not None and out.reply_to in self._route:
            targets = [self._route[out.reply_to]]
        n = 0
        for idx in targets:
            conn = self._conns[idx]
            try:
                conn.mav.send(message_from_fields(out.msg, out.fields))
                n += 1
            except Exception as exc:  # noqa: BLE001 - a send failure costs this message only
                self._count("gcs_tx_error", f"{out.msg} on {self.endpoints[idx]}: {type(exc).__name__}: {exc}")
        self.messages_tx += n
        return n

    def close(self) -> None:
        for conn in self._conns:
            try:
                conn.close()
            except Exception:  # noqa: BLE001
                pass
        self._conns = []
