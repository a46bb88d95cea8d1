"""The message rates the autopilot link asks for: one SET_MESSAGE_INTERVAL at a time, retried until ACCEPTED.

``COMMAND_LONG(MAV_CMD_SET_MESSAGE_INTERVAL, param1 = message id, param2 = interval us)``, one at a
time (an ACK does not say which message it is for), retried every ``command_retry_s`` until
``COMMAND_ACK`` ACCEPTED; IN_PROGRESS restarts the retry timer, TEMPORARILY_REJECTED waits for it, any other result
is a refusal (counted ``rate_request_refused``, the status's ``rates_refused``).  :class:`RateRequests` is owned
by :class:`~onboard.io.mavlink_link.MavlinkLink`, which starts the requests on connecting, again after a link loss
or an autopilot reboot, and sends what they write.

A stream measured slow after its rate was ACCEPTED (:meth:`RateRequests.reask`, from the link's slow streams) is asked
again, at most every :data:`REASK_S`: on a link the daemon shares with a ground station through a router, the
station's REQUEST_DATA_STREAM or SET_MESSAGE_INTERVAL sets the same channel's rates (MAVProxy sends
REQUEST_DATA_STREAM every 15 s by default; ArduPilot lets it override an interval asked before), and nothing else
would bring the rate back.  An autopilot that caps the stream ACCEPTS again and nothing changes: the
``stream_rate_low`` warning stays, the re-asks cost one command every :data:`REASK_S`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from onboard.core.counters import RejectCounter
from onboard.core.stream_rate import REASK_S, StreamRates
from onboard.io.mavlink_config import MavlinkConfig
from onboard.io.mavlink_wire import set_message_interval_message

__all__ = ["REASK_S", "RateRequests"]

log = logging.getLogger(__name__)

_RESULT_NAMES = {
    v: k[len("MAV_RESULT_") :]
    for k, v in vars(mavlink2).items()
    if k.startswith("MAV_RESULT_") and k != "MAV_RESULT_ENUM_END"
}


@dataclass
class _Inflight:
    msg_id: int
    interval_us: int
    sent_s: float
    attempts: int


class RateRequests:
    """The SET_MESSAGE_INTERVAL requests of ``rate_plan`` (message id -> interval us) to the autopilot component.

    ``stream_rates``: the link's measure of the requested streams (confirmed on ACCEPTED, reset on a new round);
    ``send(what, message)``: the link's writer; ``config``: the link's (``component_id``, ``autopilot_compid``,
    ``command_retry_s``).  The autopilot's system id is passed to each call: it is the link's, locked or not."""

    def __init__(
        self,
        config: MavlinkConfig,
        rate_plan: dict[int, int],
        stream_rates: StreamRates,
        counters: RejectCounter,
        send: Callable[[str, Any], bool],
    ) -> None:
        self.config = config
        self.rate_plan = rate_plan
        self.stream_rates = stream_rates
        self._counters = counters
        self._send = send
        self._rate_queue: list[int] = []
        self._inflight: _Inflight | None = None
        self.rates_confirmed: set[int] = set()
        self.rates_refused: dict[int, int] = {}
        self._reasked_s: dict[int, float] = {}  # message id -> when its rate was last asked again (reask)

    def request(self) -> None:
        """Ask for every rate of the plan again (connected, or the autopilot rebooted): nothing confirmed any more."""
        self.rates_confirmed.clear()
        self.stream_rates.reset()
        self.rates_refused.clear()
        self._inflight = None
        self._rate_queue = list(self.rate_plan)

    def forget(self) -> None:
        """The link is lost: nothing in flight, nothing confirmed, nothing asked until :meth:`request`."""
        self._inflight = None
        self._rate_queue.clear()
        self.rates_confirmed.clear()
        self.stream_rates.reset()

    def reask(self, msg_ids, now: float) -> None:
        """Ask again for the rates of ``msg_ids``, streams measured slow after their rate was ACCEPTED (module
        docstring), each at most every :data:`REASK_S`; one already asked and not answered is left to its retries."""
        for mid in msg_ids:
            if mid not in self.rates_confirmed or mid in self.pending():
                continue
            last = self._reasked_s.get(mid)
            if last is not None and now - last < REASK_S:
                continue
            self._reasked_s[mid] = now
            self._rate_queue.append(mid)
            log.log(
                logging.DEBUG if last is not None else logging.INFO,
                "message %d arrives under half its rate: asked again (a ground station sharing the link may have "
                "lowered it; asked again while it stays slow, every %g s)",
                mid,
                REASK_S,
            )

    def pending(self) -> tuple[int, ...]:
        """The message ids not answered yet: the one in flight first."""
        return tuple(([self._inflight.msg_id] if self._inflight else []) + self._rate_queue)

    def due_s(self, now: float) -> list[float]:
        """When :meth:`service` next has something to send (the retry of the request in flight, or ``now`` for the
        next one); empty when nothing is left to ask."""
        if self._inflight is not None:
            return [self._inflight.sent_s + self.config.command_retry_s]
        return [now] if self._rate_queue else []

    def service(self, now: float, autopilot_sysid: int | None) -> None:
        """Send the next request, or the one in flight again once ``command_retry_s`` passed without an answer."""
        inf = self._inflight
        if inf is not None:
            if now - inf.sent_s < self.config.command_retry_s:
                return
            inf.attempts += 1
            inf.sent_s = now
            self._send_interval(inf, autopilot_sysid)
            return
        if not self._rate_queue:
            return
        mid = self._rate_queue.pop(0)
        self._inflight = _Inflight(mid, self.rate_plan[mid], now, 0)
        self._send_interval(self._inflight, autopilot_sysid)

    def _send_interval(self, inf: _Inflight, autopilot_sysid: int | None) -> None:
        if autopilot_sysid is None:  # commands are serviced only while connected, i.e. to a locked system
            return
        self._send(
            "SET_MESSAGE_INTERVAL",
            set_message_interval_message(
                autopilot_sysid, self.config.autopilot_compid, inf.msg_id, inf.interval_us, inf.attempts
            ),
        )

    def on_ack(self, msg, now: float, autopilot_sysid: int | None) -> None:
        """A COMMAND_ACK of the autopilot component: the answer to the request in flight, when it is one."""
        if msg.command != mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL or self._inflight is None:
            return
        tgt_sys = getattr(msg, "target_system", 0)
        tgt_comp = getattr(msg, "target_component", 0)
        if tgt_sys not in (0, autopilot_sysid) or tgt_comp not in (0, self.config.component_id):
            return  # an answer to somebody else's command
        inf = self._inflight
        result = msg.result
        if result == mavlink2.MAV_RESULT_ACCEPTED:
            again = inf.msg_id in self.rates_confirmed  # a slow stream asked again: its measure goes on
            self.rates_confirmed.add(inf.msg_id)
            if not again:
                self.stream_rates.confirmed(inf.msg_id, now)
            self._inflight = None
            log.log(
                logging.DEBUG if again else logging.INFO, "rate of message %d set to %d us", inf.msg_id, inf.interval_us
            )
        elif result == mavlink2.MAV_RESULT_IN_PROGRESS:
            inf.sent_s = now
        elif result == mavlink2.MAV_RESULT_TEMPORARILY_REJECTED:
            pass  # retried on the next timeout
        else:
            self.rates_refused[inf.msg_id] = result
            self._inflight = None
            self._counters.count("rate_request_refused", f"message {inf.msg_id}: {_RESULT_NAMES.get(result, result)}")
