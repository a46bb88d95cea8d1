"""The watchdog's ``overload`` condition: the counts it follows and which cause its message names.

:class:`~onboard.app.watchdog.Watchdog` raises, holds and clears ``overload`` (its module docstring says when);
:class:`Overload` keeps what the condition needs between the service's checks (the running counts of frames dropped
and positions withheld as too old, what grew since it was raised, when it last grew) and words the message.  It
stands apart from the watchdog's other conditions because it alone tells causes apart: a process that stood still,
frames that arrived in bursts, an estimator worker that stopped answering, or too little CPU, each with its own
advice; and its thresholds are the service's too (:data:`STALL_NAMED_S`, :data:`OVERLOAD_CLEAR_S`).  Pure: no clocks.
"""

from __future__ import annotations

import math

__all__ = ["Overload", "OVERLOAD_CLEAR_S", "STALL_NAMED_S", "ESTIMATOR_SILENT_S"]

OVERLOAD_CLEAR_S = 5.0
#: a main-loop turn this much later than the previous one is a stall of the whole process, named as overload's cause
#: (the loop turns at least every 50 ms while it runs; a second is twenty times that)
STALL_NAMED_S = 1.0
ESTIMATOR_SILENT_S = 1.0  # a worker that has answered nothing this long is named as overload's cause


class Overload:
    """``overload``'s state between checks: :meth:`update` with the running counts gives the message to raise it with
    (None: neither count grew); :meth:`held` says whether it is still held (cleared ``OVERLOAD_CLEAR_S`` after the
    last growth).  :meth:`onboard.app.watchdog.Watchdog.load` feeds it."""

    def __init__(self) -> None:
        self._counts: tuple[int, int, int] | None = None  # dropped, stale, dropped as they arrived bunched
        self._since_s: float | None = None
        self._seen = (0, 0)  # dropped, stale since the overload was raised
        self._last_s = -math.inf

    def held(self, now_s: float) -> bool:
        """An overload grew within the last ``OVERLOAD_CLEAR_S``."""
        return not now_s - self._last_s >= OVERLOAD_CLEAR_S

    def update(
        self,
        now_s: float,
        *,
        active: bool,
        frames_dropped: int,
        estimates_stale: int,
        cpu_words: str = "",
        estimator_silent_s: float = 0.0,
        quota_bound: bool | None = None,
        stalled_s: float = 0.0,
        frames_dropped_bunched: int = 0,
    ) -> str | None:
        """The ``overload`` message when frames dropped or positions withheld grew since the last update, else None
        (the first update only takes the counts).  ``active``: ``overload`` is raised now (else its counts start
        again here).  ``frames_dropped``, ``estimates_stale``: the running counts of frames dropped and positions
        withheld as too old; ``cpu_words``: the CPU the daemon got, in words, for the message (see ``overload`` in
        :mod:`onboard.app.watchdog`);
        ``estimator_silent_s``: how long the estimator's worker process has answered nothing (the cause the message
        names instead of the CPU when frames are not being dropped); ``quota_bound``: whether its CPU quota ran out
        in the last interval (False: a quota that did not bind, so other work on the computer took the CPU; None:
        unknown), which decides the advice; ``stalled_s``: how long the daemon's main loop last stood still, when that
        was within :data:`OVERLOAD_CLEAR_S` (a stopped process, a paused or swapping computer; 0: none), named as the
        cause instead of the CPU share when it is at least :data:`STALL_NAMED_S`; ``frames_dropped_bunched``: of
        ``frames_dropped``, those dropped as the frames arrived bunched (:func:`onboard.app.frame_queue.arrived_bunched`:
        a link holding and releasing them), named as the cause when every frame dropped since the last update was."""
        counts = (int(frames_dropped), int(estimates_stale), int(frames_dropped_bunched))
        last, self._counts = self._counts, counts
        if last is None:
            return None
        grew = counts[0] > last[0] or counts[1] > last[1]
        if not grew:
            return None
        if not active:
            self._since_s, self._seen = now_s, (0, 0)
        self._last_s = now_s
        self._seen = (
            self._seen[0] + max(counts[0] - last[0], 0),
            self._seen[1] + max(counts[1] - last[1], 0),
        )
        since = now_s - (self._since_s if self._since_s is not None else now_s)
        seen = (
            f"{self._seen[0]} frames dropped and {self._seen[1]} positions withheld as too old since the "
            f"overload began {since:.1f} s ago"
        )
        if stalled_s >= STALL_NAMED_S:
            # every thread stood still (SIGSTOP, a VM paused, the machine swapping): no CPU share explains it,
            # and the CPU it got over the interval (a fraction of a core) would point at the wrong remedy
            return (
                f"{seen}: the daemon stood still for {stalled_s:.1f} s (its process stopped, or this computer "
                "paused or swapped), not a matter of its CPU share"
            )
        if (
            counts[1] == last[1]
            and counts[0] > last[0]
            and counts[2] - last[2] >= counts[0] - last[0]
            and quota_bound is not True
        ):
            # the queue overflowed with frames that came together, captured a camera period apart: a faster
            # pipeline would not have kept them all.  Where they were held is not known here: a CPU quota running
            # out stops the receiving thread too (then the CPU's words above), and so can a starved computer
            return (
                f"{seen}: the frames arrived in bursts, faster than they were captured, and the queue keeps the "
                f"newest only (input.queue_length){cpu_words}: something held them and released them together, "
                "the camera's link or sender, or this computer's scheduler while other work takes the CPU; check "
                "the link, or raise input.queue_length"
            )
        if counts[0] == last[0] and estimator_silent_s >= ESTIMATOR_SILENT_S:
            # the frames keep up and the worker does not answer: a stopped or stalled process, not the CPU
            return (
                f"{seen}: the estimator's worker process has answered nothing for {estimator_silent_s:.1f} s (a "
                f"stopped or stalled process; it is killed and replaced after 5 s){cpu_words}"
            )
        if quota_bound is False:
            advice = (
                "its CPU quota did not run out, so other work on this computer takes the CPU: move it off, "
                "give the daemon a higher priority, or lower the camera's frame rate"
            )
        else:
            advice = (
                "raise its CPU limit (compose deploy.resources.limits.cpus, sized in deploy/README.md), lower "
                "the camera's frame rate, or move other work off this computer"
            )
        return f"{seen}: the daemon does not get the CPU it needs{cpu_words}; {advice}"
