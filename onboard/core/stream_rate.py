"""Measured rates of the telemetry streams, beside the rates requested (the status's ``link.streams``).

An autopilot may ACCEPT a SET_MESSAGE_INTERVAL and still send slower: ArduPilot caps a stream at its scheduler's
rate (and a link's bandwidth) without a word, and so does the simulator at its tick.  :class:`StreamRates` counts
the messages of each requested stream as they are taken (one integer per message id, the receive path's only
cost) and works the rates out when asked: messages over the time between the newest look and the oldest one within
:data:`RATE_WINDOW_S`, so a status every second gives the last few seconds' rate.

Rates in Hz (messages per second), times in seconds on the caller's monotonic clock.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

__all__ = ["CLEAR_FRACTION", "RATE_WINDOW_S", "MIN_SPAN_S", "REASK_S", "SLOW_FRACTION", "StreamRate", "StreamRates"]

#: the rate is measured over the last this many seconds (at least :data:`MIN_SPAN_S` of looks)
RATE_WINDOW_S = 5.0
MIN_SPAN_S = 1.0
#: a stream below this fraction of its requested rate for :data:`SLOW_PERSIST_S` after its rate was confirmed is
#: slow (what a capped autopilot looks like)
SLOW_FRACTION = 0.5
#: a slow stream is slow until it is above this fraction of its requested rate: an autopilot capping a stream at
#: half its request measures on both sides of SLOW_FRACTION from one look to the next, and the warning came and went
#: every second
CLEAR_FRACTION = 0.55
SLOW_PERSIST_S = 3.0
#: a slow stream's rate is asked again at most this often (:mod:`onboard.io.mavlink_rates`; here, where the
#: watchdog's advice that says so reads it too)
REASK_S = 10.0


@dataclass(frozen=True)
class StreamRate:
    """One stream: its message id and name, ``requested_hz``, ``measured_hz`` (None until :data:`MIN_SPAN_S` of
    looks), ``confirmed_s`` (when its rate request was ACCEPTED; None: not confirmed)."""

    msg_id: int
    name: str
    requested_hz: float
    measured_hz: float | None
    confirmed_s: float | None

    def as_dict(self) -> dict:
        m = self.measured_hz
        return {
            "msg_id": self.msg_id,
            "requested_hz": round(self.requested_hz, 2),
            "measured_hz": None if m is None else round(m, 2),
        }


class StreamRates:
    """Counts per message id (:meth:`count`); :meth:`rates` at status time.  ``requested``: ``{msg_id: (name,
    requested Hz)}``."""

    def __init__(self, requested: dict[int, tuple[str, float]]) -> None:
        self.requested = dict(requested)
        self.counts: dict[int, int] = {mid: 0 for mid in self.requested}
        self._confirmed_s: dict[int, float] = {}
        self._looks: deque[tuple[float, dict[int, int]]] = deque()
        self._slow: set[int] = set()  # the streams the last slow() found slow (they clear at CLEAR_FRACTION)

    def count(self, msg_id: int) -> None:
        """One message of a requested stream taken (others are ignored)."""
        if msg_id in self.counts:
            self.counts[msg_id] += 1

    def confirmed(self, msg_id: int, now_s: float) -> None:
        """Its rate request was ACCEPTED at ``now_s``: the measurement judged from here."""
        self._confirmed_s[msg_id] = float(now_s)
        self._looks.clear()  # the rate before the request is not the rate asked for
        self._slow.discard(msg_id)

    def reset(self) -> None:
        """The requests are sent again (link lost, autopilot rebooted): nothing confirmed, nothing measured."""
        self._confirmed_s.clear()
        self._looks.clear()
        self._slow.clear()

    def rates(self, now_s: float) -> list[StreamRate]:
        """Each requested stream's rate over the last :data:`RATE_WINDOW_S` (this call is a look)."""
        now_s = float(now_s)
        looks = self._looks
        if not looks or now_s > looks[-1][0]:
            looks.append((now_s, dict(self.counts)))
        while len(looks) > 2 and now_s - looks[1][0] >= RATE_WINDOW_S:
            looks.popleft()
        t0, c0 = looks[0]
        span_s = now_s - t0
        out = []
        for mid, (name, hz) in self.requested.items():
            measured = (self.counts[mid] - c0.get(mid, 0)) / span_s if span_s >= MIN_SPAN_S else None
            out.append(StreamRate(mid, name, hz, measured, self._confirmed_s.get(mid)))
        return out

    def slow(self, now_s: float, rates: list[StreamRate]) -> list[StreamRate]:
        """The streams of ``rates`` (just measured) below :data:`SLOW_FRACTION` of their requested rate (one found slow
        the time before: below :data:`CLEAR_FRACTION`), over a window
        that began after their rate was confirmed, :data:`SLOW_PERSIST_S` or more ago.  None while no requested stream
        brought a message over the last :data:`MIN_SPAN_S` (since the newest look at least that old): the telemetry
        stopped, which the link's own warnings say (its rates over the window, the silence included, had read as an
        autopilot capping every stream once a simulator ended); a stream that stays silent while the others arrive is
        slow (0 Hz).  Not since the look just before: the daemon looks twice in a row (its link status, then this),
        on the thread that takes the messages, so nothing can arrive between the two."""
        t0 = self._looks[0][0] if self._looks else now_s
        before = next((counts for t_s, counts in reversed(self._looks) if now_s - t_s >= MIN_SPAN_S), None)
        if before is not None and all(self.counts[mid] == before.get(mid) for mid in self.counts):
            return []
        slow = [
            r
            for r in rates
            if r.measured_hz is not None
            and r.confirmed_s is not None
            and t0 >= r.confirmed_s
            and now_s - r.confirmed_s >= SLOW_PERSIST_S
            and r.measured_hz < (CLEAR_FRACTION if r.msg_id in self._slow else SLOW_FRACTION) * r.requested_hz
        ]
        self._slow = {r.msg_id for r in slow}
        return slow
