"""The autopilot's address on a ``udpin`` link: the one followed, second senders of its identity refused.

One autopilot, one address (``udpin``): the autopilot is the first address its system/component heartbeats from.
A heartbeat of that system/component from another address while the followed one is alive (its newest heartbeat
within ``heartbeat_timeout_s``, the window the link calls it connected by) is a second sender: two vehicles with
one system id on the port (PX4 and ArduPilot both default to 1), or one autopilot over two routes.  Mixed, the
pose follows whichever spoke last (two clocks apart: every line of sight wrong) and the replies flip between them;
so everything from that address is refused instead: counted ``autopilot_duplicate`` (its
heartbeats; WARNING the first time, naming both addresses), ``autopilot_duplicate_refused`` (anything else, DEBUG),
and listed by :meth:`~onboard.io.mavlink_link.MavlinkLink.duplicate_senders` for the watchdog's
``autopilot_duplicate``.  The autopilot component's own messages from an address its heartbeats do not come from are not used either
(``autopilot_other_address``, DEBUG: a second sender before its first heartbeat, or a moved autopilot's first
second); other components of its system (a gimbal on a socket of its own) are taken from any address.  An
autopilot that moved (its old address silent for ``heartbeat_timeout_s``, so the link is lost, then heartbeats
from a new one) is followed there (``autopilot_address_changed``): a move costs up to ``heartbeat_timeout_s`` of
telemetry, a shorter window would hand the link to a second vehicle over a radio fade of the first.  A second
sender heartbeating after the first fell silent that long is followed the same way (nothing tells it from a moved
autopilot then; the count's log line says it was heard as a second sender).  A router (mavlink-router, MAVProxy)
that restarts sends from a new port: its first heartbeats come while the old address is silent but not yet timed
out, so they are refused as a second sender's for the rest of ``heartbeat_timeout_s``; the warning then says how
long the followed address has been silent (over :data:`SILENT_HINT_S`, a missed 1 Hz heartbeat), so that it does
not read as two vehicles only.

:class:`~onboard.io.mavlink_link.MavlinkLink` keeps one :class:`AutopilotAddress` and asks it about each autopilot
heartbeat and each message of the autopilot's system that comes from another address than the followed one.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass

from onboard.core.counters import RejectCounter
from onboard.io.mavlink_config import MavlinkConfig
from onboard.io.mavlink_transport import UdpTransport

__all__ = ["DuplicateSender", "AutopilotAddress", "MAX_DUPLICATE_SENDERS", "SILENT_HINT_S"]

log = logging.getLogger(__name__)

#: second senders of the autopilot's identity remembered (the newest ones): their messages are refused
MAX_DUPLICATE_SENDERS = 8
#: the followed address silent this long when a second sender heartbeats: said in the warning (PX4 and ArduPilot
#: heartbeat at 1 Hz, so past 1.5 s the followed one has missed a heartbeat: a restarted router's new port, or a
#: fade of the first vehicle)
SILENT_HINT_S = 1.5


@dataclass(frozen=True)
class DuplicateSender:
    """A second sender of the followed autopilot's identity on a ``udpin`` link (module docstring): ``other``
    heartbeats as system ``sysid`` component ``compid`` while ``followed`` (the address the link follows) is alive.
    ``heard_s``: its newest heartbeat, on the link's clock; ``followed_silent_s``: how long before it the followed
    address's newest heartbeat came."""

    sysid: int
    compid: int
    followed: tuple[str, int]
    other: tuple[str, int]
    heard_s: float
    followed_silent_s: float = 0.0

    def silence(self) -> str:
        """' (FOLLOWED silent for N s: ...)' when the followed address has missed a heartbeat (:data:`SILENT_HINT_S`),
        else ''."""
        if self.followed_silent_s <= SILENT_HINT_S:
            return ""
        return (
            f" ({self.followed[0]}:{self.followed[1]} silent for {self.followed_silent_s:.1f} s: a router restarted "
            "on a new port reads so, and is followed there once the old address has been silent for "
            "mavlink.heartbeat_timeout_s)"
        )


class AutopilotAddress:
    """Which address of a ``udpin`` link the followed autopilot is, and the second senders of its identity (module
    docstring).  ``config``: the link's (``autopilot_compid``, ``heartbeat_timeout_s``); ``counters`` counts what
    is refused."""

    def __init__(self, config: MavlinkConfig, counters: RejectCounter) -> None:
        self.config = config
        self._counters = counters
        #: udpin: addresses that heartbeat as the autopilot while the followed one is alive -> their newest one
        self._duplicates: OrderedDict[tuple[str, int], DuplicateSender] = OrderedDict()

    def heartbeat(
        self, t: UdpTransport, src_sys: int, src_comp: int, addr, now: float, alive: bool, followed_age_s: float = 0.0
    ) -> bool:
        """A heartbeat of the followed autopilot's system/component from ``addr``, not the address ``t`` (a ``udpin``
        link) follows: False (refused) when it is a second sender's (``alive``: the followed one's newest heartbeat
        within ``heartbeat_timeout_s``; ``followed_age_s``: how old it is), else True and ``t`` follows ``addr`` (the
        first address, or a moved one)."""
        if t.peer is not None and alive:
            self._duplicate(src_sys, src_comp, t.peer, addr, now, followed_age_s)
            return False
        was_second = self._duplicates.pop(addr, None) is not None
        if t.peer is not None:
            # a second sender followed once the first fell silent may be the other vehicle, not a move: said so
            self._counters.count(
                "autopilot_address_changed",
                f"system {src_sys}: {t.peer} -> {addr}"
                + (", which heartbeated as a second sender while the first was alive" if was_second else ""),
            )
        else:
            log.info("autopilot %d at %s:%d: our output goes there only", src_sys, *addr)
        t.peer = addr
        return True

    def refuses(self, t: object, mtype: str, src_comp: int, addr, autopilot_sysid: int | None) -> bool:
        """Count and return True for a message of the autopilot's system that a ``udpin`` link does not take from
        ``addr``: anything from a second sender of its identity, and the autopilot component's own messages from
        an address its heartbeats do not come from (another component, a gimbal on its own socket, may have one).
        ``t``: the link's transport (None while closed)."""
        if not isinstance(t, UdpTransport) or t.kind != "udpin" or t.peer is None or addr == t.peer:
            return False
        if addr in self._duplicates:
            self._counters.count(
                "autopilot_duplicate_refused",
                f"{mtype} from {addr[0]}:{addr[1]}, a second sender of autopilot {autopilot_sysid}'s identity",
                level=logging.DEBUG,
            )
            return True
        if src_comp != self.config.autopilot_compid:
            return False
        self._counters.count(
            "autopilot_other_address",
            f"{mtype} of autopilot {autopilot_sysid}/{src_comp} from {addr[0]}:{addr[1]}; its heartbeats come "
            f"from {t.peer[0]}:{t.peer[1]}",
            level=logging.DEBUG,
        )
        return True

    def _duplicate(self, sysid: int, compid: int, followed, other, now: float, followed_age_s: float) -> None:
        """A heartbeat of the followed identity from ``other`` while ``followed`` is alive: a second sender (module
        docstring), remembered so that all it sends is refused; counted, at WARNING the first time it is heard."""
        new = other not in self._duplicates
        dup = DuplicateSender(sysid, compid, followed, other, now, followed_age_s)
        self._duplicates[other] = dup
        self._duplicates.move_to_end(other)
        while len(self._duplicates) > MAX_DUPLICATE_SENDERS:
            self._duplicates.popitem(last=False)
        self._counters.count(
            "autopilot_duplicate",
            f"{other[0]}:{other[1]} heartbeats as autopilot {sysid}/{compid} too, which {followed[0]}:{followed[1]} "
            f"is{dup.silence()}: everything it sends is refused (autopilot_duplicate_refused); give each vehicle its "
            "own MAV_SYS_ID or its own port",
            level=logging.WARNING if new else logging.DEBUG,
        )

    def senders(self, now: float) -> list[DuplicateSender]:
        """The second senders of the autopilot's identity heard within ``heartbeat_timeout_s`` of ``now`` (the
        watchdog's ``autopilot_duplicate``); empty when none."""
        return [d for d in self._duplicates.values() if now - d.heard_s <= self.config.heartbeat_timeout_s]
