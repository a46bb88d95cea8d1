"""When the camera's tracking statuses (#275 / #276) are due, pure: the rate limits and the schedule of each link
(:class:`StatusSchedules`: why per link, and what a link is, in its docstring).

No clocks: times (``now_s``) are passed in.  :mod:`onboard.io.camera_protocol` answers the commands that set and
read the intervals (SET_MESSAGE_INTERVAL, GET_MESSAGE_INTERVAL) and sends the statuses.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "MAX_TRACKING_STATUS_HZ",
    "MIN_TRACKING_STATUS_INTERVAL_S",
    "MAX_LINKS",
    "FOLLOW_DEFAULT",
    "StatusSchedules",
    "advance_due_s",
    "interval_of_rate_s",
]

#: the fastest a ground station may have #275 / #276 sent.  Each describes the newest track, which changes
#: once per IR frame at most (thermal cores deliver 9 to 60 frames/s, most 25 or 30): a faster stream repeats
#: the same track, and it shares a telemetry radio with the autopilot's.  SET_MESSAGE_INTERVAL has no upper
#: rate in common.xml, so a shorter interval is served at this rate, ACCEPTED, and MESSAGE_INTERVAL reports
#: the interval applied.  The configured defaults (``output.tracking_*_status_hz``) are the operator's and
#: are not clamped.
MAX_TRACKING_STATUS_HZ = 50.0
MIN_TRACKING_STATUS_INTERVAL_S = 1.0 / MAX_TRACKING_STATUS_HZ


def interval_of_rate_s(hz: float) -> float | None:
    return None if hz <= 0 else 1.0 / hz


def advance_due_s(due_s: float, every_s: float, now_s: float) -> float:
    """The next due time on the schedule; one that fell behind restarts from now instead of bursting."""
    nxt = due_s + every_s
    return nxt if nxt > now_s else now_s + every_s


#: links with a schedule at once.  :meth:`StatusSchedules.keep` cuts the table to the links the adapter has (its
#: endpoints, and on ``udpin`` its peers, bounded there) at every tick; this bounds what settings from other senders
#: (a flood of addresses, each setting an interval) can add in between, and those are forgotten first, the least
#: recently added of them first: a flood does not take the settings of the links there are
MAX_LINKS = 64


class _FollowDefault:
    """SET_MESSAGE_INTERVAL's 0: the link follows the configured default again (:meth:`StatusSchedules.set`)."""

    def __repr__(self) -> str:
        return "FOLLOW_DEFAULT"


FOLLOW_DEFAULT = _FollowDefault()


@dataclass
class _LinkSchedule:
    #: message id -> the link's own interval (s; None = off), set by SET_MESSAGE_INTERVAL; absent: the default
    interval_s: dict[int, float | None] = field(default_factory=dict)
    #: message id -> when it is next due on this link (s)
    next_due_s: dict[int, float] = field(default_factory=dict)


class StatusSchedules:
    """Per link, the interval of each tracking status (#275 / #276) and when it is next due.

    MAVLink's message-rate protocol (mavlink.io/en/guide/message_rates.html): "The interval set by this command only
    applies to the link (connection) the command was received on."  A *link* is the adapter's name of the connection
    a command came on (:attr:`~onboard.io.camera_protocol.CameraCommand.via`, opaque here).  For
    :class:`~onboard.io.gcs_link.GcsLink` that is each endpoint, and on a ``udpin`` endpoint each peer address:
    every peer gets its own copy of the statuses there, so it is a connection of its own, and ground stations cannot
    be told apart any other way (QGC is 255/190 on every copy).  ArduPilot keeps its rates per channel (serial port
    or network link); PX4 runs one MAVLink instance per port and a UDP instance answers one partner, the address it
    first heard, so it never has two ground stations on one port to keep apart.  Keyed so, one ground station's
    SET_MESSAGE_INTERVAL(275, -1) (QGC sends it on every stop) no longer silences #275 for every other one.

    A link that goes away (a ``udpin`` peer silent for the adapter's peer timeout, a TCP connection lost) forgets its
    settings: a ground station that comes back later starts at the defaults (``output.tracking_*_status_hz``), as it
    would on a camera it had never spoken to, and asks again the rates it wants (QGC asks #275 with each click).

    ``default_interval_s``: message id -> interval (s; None = off) of a link that set none, or set 0.
    """

    def __init__(self, default_interval_s: Mapping[int, float | None], max_links: int = MAX_LINKS) -> None:
        self.default_interval_s = dict(default_interval_s)
        self.max_links = max_links
        self._links: OrderedDict[Hashable, _LinkSchedule] = OrderedDict()
        self._alive: set[Hashable] = set()  # the links the last :meth:`keep` was given

    def __contains__(self, msg_id: object) -> bool:
        """Whether ``msg_id`` is a message scheduled here."""
        return msg_id in self.default_interval_s

    def interval_s(self, link: Hashable, msg_id: int) -> float | None:
        """``msg_id``'s interval on ``link`` (s; None = off): its own, else the default."""
        sched = self._links.get(link)
        if sched is not None and msg_id in sched.interval_s:
            return sched.interval_s[msg_id]
        return self.default_interval_s[msg_id]

    def set(self, link: Hashable, msg_id: int, interval_s: float | None | _FollowDefault, now_s: float) -> None:
        """``msg_id`` every ``interval_s`` on ``link`` from now (None: off; :data:`FOLLOW_DEFAULT`: the default's)."""
        sched = self._schedule(link)
        if isinstance(interval_s, _FollowDefault):
            sched.interval_s.pop(msg_id, None)
        else:
            sched.interval_s[msg_id] = interval_s
        sched.next_due_s[msg_id] = now_s

    def keep(self, links: Iterable[Hashable]) -> None:
        """Forget every link but ``links`` (the ones there are now), with its settings (class docstring)."""
        alive = self._alive = set(links)
        for link in [k for k in self._links if k not in alive]:
            del self._links[link]

    def due(self, now_s: float, links: Iterable[Hashable]) -> list[tuple[Hashable, int]]:
        """(link, message id) of each status due now on ``links``, each moved on to its next time; a link not seen
        before is due at once."""
        out: list[tuple[Hashable, int]] = []
        for link in dict.fromkeys(links):
            sched = self._schedule(link)
            for msg_id in self.default_interval_s:
                every = self.interval_s(link, msg_id)
                due_s = sched.next_due_s.get(msg_id, -math.inf)
                if every is None or now_s < due_s:
                    continue
                sched.next_due_s[msg_id] = advance_due_s(due_s, every, now_s)
                out.append((link, msg_id))
        return out

    def next_due_s(self) -> float:
        """The earliest time a status is due on a link known here (inf when none is)."""
        return min(
            (
                sched.next_due_s.get(msg_id, -math.inf)
                for link, sched in self._links.items()
                for msg_id in self.default_interval_s
                if self.interval_s(link, msg_id) is not None
            ),
            default=math.inf,
        )

    def own_settings(self, link_name: Callable[[Hashable], str], keys: Mapping[int, str]) -> list[dict[str, Any]]:
        """The links that set an interval of their own, for the status: each as ``{"link": link_name(link)}`` and,
        under ``keys[msg_id]``, every message's interval on it now (s; None = off), its own or the default."""
        return [
            {"link": link_name(link), **{keys[m]: self.interval_s(link, m) for m in self.default_interval_s}}
            for link, sched in self._links.items()
            if sched.interval_s
        ]

    def _schedule(self, link: Hashable) -> _LinkSchedule:
        sched = self._links.get(link)
        if sched is None:
            sched = self._links[link] = _LinkSchedule()
            while len(self._links) > self.max_links:
                gone = next((k for k in self._links if k not in self._alive), next(iter(self._links)))
                del self._links[gone]
        return sched
