"""Frame admission, pure: is this frame's (sequence number, capture time) the next one of the stream?

No pixels, no clocks, no I/O: :class:`FrameAdmission` keeps the stream's state and answers each
frame with an :class:`Admission`; :class:`~onboard.pipeline.frame_pipeline.FramePipeline` counts
and acts on it.  Times are ``time_boot_us`` (the autopilot's boot clock), ``threshold_us`` is
``input.time_reset_threshold_s``.

With ``L`` the last accepted capture time and ``t`` the frame's, each refused frame is named by
what is wrong with it, so that a status reader can tell a sender problem from a clock problem:

* ``duplicate``: the sequence number and capture time of a recently accepted frame (sent twice,
  however late);
* ``out_of_order``: before ``L`` with the sequence number going back too (an old frame delivered
  late);
* ``time_ahead``: within ``threshold_us`` after ``L`` but more than ``AHEAD_OF_RATE_US`` past where the
  stream's rate puts it and more than ``AHEAD_OF_TELEMETRY_US`` past the telemetry's newest time (one odd stamp:
  taken, it would have the good frames after it refused until a run of them restarted the estimator); or more
  than ``threshold_us`` after ``L`` (a stamp far in the future), unless the
  sequence number moved on with it: a frame within ``threshold_us`` of where the stream's own rate
  (its frames accepted since the last event, at least ``RATE_FRAMES``) puts its number is the next
  one after a gap, frames missing in between (dropped by the sender, the network, or the daemon's
  bounded queue while its pipeline was starved of CPU): a stall is not a clock step; nor is a frame
  within ``threshold_us`` of the telemetry's newest time (``reference_us``) with its sequence number
  moving on by any amount: the camera paused (numbering its frames on from where it stopped) while
  the clocks ran on together, and the stream goes on from it with the same estimate;
* ``time_behind``: before ``L`` with the sequence number moving forward (a bad stamp, such as one
  taken just after boot).

Accepted, and named by the event: ``""`` (the next frame), ``sequence_reset`` (time forward,
sequence back: the sender restarted), ``sequence_repeated`` (time forward, the last frame's sequence number
again: the sender did not number the frame anew), ``time_reset`` (``TIME_CONFIRM_FRAMES`` mutually consistent
frames far from ``L``: a clock step or an autopilot reboot; the estimator restarts),
``stream_restart`` (``restart_count`` mutually consistent frames at most ``threshold_us`` before
``L``: the sender restarted its clock; the estimator restarts).  A run is consistent when each
frame of it is after the previous one by at most ``threshold_us`` with a sequence number moving
forward: duplicates and scattered odd frames never add up to a run, so one odd frame (or a few
unrelated ones) never restarts the estimator, and a real step never locks the stream out.

A far run that stands apart from the telemetry too (its newest frame more than ``threshold_us`` from
``reference_us``) confirms only once it also spans ``APART_CONFIRM_US`` of its own stamps: its frames
find no pose at their stamps, so taking them at once gains nothing, while a short burst of bogus stamps
(a sender's glitch an hour ahead) taken as the new clock would restart the estimator twice, once for the
burst and once for the good frames after it, and lose its window each time.  A step the telemetry shares
(an autopilot reboot once its new telemetry is in) is confirmed by ``TIME_CONFIRM_FRAMES`` as before.

Once such a step is taken the stream's clock stands apart from the telemetry's (:attr:`FrameAdmission.apart_us`):
a frame stamped within the pose window of the telemetry (a camera clock stepped back 2 s) does find a pose at its
stamp, the wrong one, seconds old, so the pipeline gives the frames no pose while the stream stands apart.  Every
frame is held against the telemetry's newest time then; the first within ``threshold_us`` of it (the telemetry
caught up: an autopilot reboot, or a camera clock set right) ends it.

The first frame is accepted unless a telemetry time is known (``reference_us``, the pose buffer's
newest sample) and the frame is more than ``threshold_us`` from it: a stream that starts with a
stamp an hour ahead, or one at boot, would otherwise become the clock the good frames are judged
by.  Such a frame waits for a consistent run, as a clock step does.
"""

from __future__ import annotations

from dataclasses import dataclass

from onboard.core.recent import Recent

__all__ = [
    "SEQ_MOD",
    "TIME_CONFIRM_FRAMES",
    "APART_CONFIRM_US",
    "RECENT_FRAMES",
    "RATE_FRAMES",
    "Admission",
    "FrameAdmission",
    "ArrivalGaps",
    "MAX_NUMBERINGS",
]

SEQ_MOD = 2**32
#: consecutive, mutually consistent frames far from the running clock that confirm a clock step
TIME_CONFIRM_FRAMES = 3
#: the span of its own stamps a far run standing apart from the telemetry needs before it confirms a clock step
APART_CONFIRM_US = 500_000
#: accepted (seq, time) pairs remembered to recognise a duplicate sent late (4 s at 30 Hz)
RECENT_FRAMES = 128
#: accepted frames (since the last event) the stream's rate is learnt from before a gap is told from a clock step
RATE_FRAMES = 8
#: a frame within the threshold of the last one but this far past where the stream's rate puts it ...
AHEAD_OF_RATE_US = 100_000
#: ... and this far past the telemetry's newest time is an odd stamp, not the next frame: taken as the stream's
#: newest it would have the good frames after it refused as behind it, until a run of them restarts the estimator
AHEAD_OF_TELEMETRY_US = 250_000
#: sequence numberings :class:`ArrivalGaps` follows at once (two senders on the key, a restart's old one)
MAX_NUMBERINGS = 4


@dataclass(frozen=True)
class Admission:
    """The decision on one frame.

    ``accepted``; ``reason``: the refusal reason (``duplicate``, ``out_of_order``, ``time_ahead``,
    ``time_behind``) or the accepted event (``""``, ``sequence_reset``, ``sequence_repeated``, ``time_reset``,
    ``stream_restart``); ``restart``: the estimator must restart (accepted steps only);
    ``message``: one line for the log, naming the frame and the stream's last accepted one.
    """

    accepted: bool
    reason: str
    message: str = ""
    restart: bool = False


_ACCEPTED = Admission(True, "")  # the usual verdict (immutable: one for every frame)


def _forward(seq: int, after: int) -> bool:
    """``seq`` comes after ``after`` in the wrapping uint32 sequence."""
    return 0 < (seq - after) % SEQ_MOD < SEQ_MOD // 2


class FrameAdmission:
    """Stateful admission of (seq, time_boot_us) pairs; see the module docstring.  Not thread-safe."""

    def __init__(self, threshold_us: int, restart_count: int) -> None:
        if threshold_us <= 0 or restart_count < 1:
            raise ValueError(f"threshold_us must be > 0 and restart_count >= 1, got {threshold_us}, {restart_count}")
        self.threshold_us = int(threshold_us)
        self.restart_count = int(restart_count)
        self.last_seq: int | None = None
        self.last_t_us: int | None = None
        self._recent = Recent(RECENT_FRAMES)  # accepted (seq, t) pairs since the last event
        self._run: list[tuple[int, int]] = []  # (seq, t) of refused, mutually consistent frames
        self._run_far = False  # the run is far from the running clock (else: shortly before it)
        #: how far (us, frame stamp minus the telemetry's newest time) the stream's clock stands from the telemetry's
        #: since a step the telemetry did not share (module docstring); None: they agree
        self.apart_us: int | None = None

    def reset(self) -> None:
        """Forget the stream."""
        self.last_seq = self.last_t_us = None
        self.apart_us = None
        self._recent.clear()
        self._run.clear()

    def wants_reference(self, seq: int, t_us: int) -> bool:
        """Whether :meth:`admit` reads the telemetry's newest time for this frame (the first, one more than
        ``threshold_us`` from the last accepted, or one past where the stream's rate puts it): the caller looks it
        up for those only."""
        last_t = self.last_t_us
        return (
            last_t is None
            or self.apart_us is not None
            or abs(t_us - last_t) > self.threshold_us
            or self._ahead_of_rate(seq, t_us)
        )

    def admit(self, seq: int, t_us: int, reference_us: int | None = None) -> Admission:
        """Decide on the frame ``seq`` captured at ``t_us``; ``reference_us``: the newest telemetry time, if any
        (read when :meth:`wants_reference` says so)."""
        verdict = self._admit(seq, t_us, reference_us)
        if verdict.accepted and self.apart_us is not None and reference_us is not None:
            apart_us = t_us - reference_us
            self.apart_us = apart_us if abs(apart_us) > self.threshold_us else None
        return verdict

    def _admit(self, seq: int, t_us: int, reference_us: int | None) -> Admission:
        last_seq, last_t = self.last_seq, self.last_t_us
        thr = self.threshold_us
        if last_t is None or last_seq is None:  # the first frame (both are set together)
            if reference_us is None or abs(t_us - reference_us) <= thr:
                return self._accept(seq, t_us, "")
            step = (t_us - reference_us) / 1e6
            return self._candidate(
                seq,
                t_us,
                far=True,
                apart=True,
                reference_us=reference_us,
                reason="time_ahead" if step > 0 else "time_behind",
                message=f"first frame seq {seq} at time_boot_us {t_us} is {step:+.3f} s from the telemetry",
            )
        if (seq, t_us) in self._recent:
            return Admission(False, "duplicate", f"frame seq {seq} (time_boot_us {t_us}) again")
        seq_forward = _forward(seq, last_seq)
        if last_t < t_us <= last_t + thr:  # the usual frame: no message made for it
            if seq_forward:
                if (
                    reference_us is not None
                    and t_us > reference_us + AHEAD_OF_TELEMETRY_US
                    and self._ahead_of_rate(seq, t_us)
                ):
                    ahead = f"{(t_us - reference_us) / 1e6:+.3f} s from the telemetry"
                    return self._candidate(
                        seq, t_us, far=False, reason="time_ahead",
                        message=f"frame seq {seq} at time_boot_us {t_us} is past the stream's rate and {ahead}",
                    )  # fmt: skip
                return self._accept(seq, t_us, "")
            if seq == last_seq:  # not a sender numbering anew: one that did not move its counter on
                return self._accept(
                    seq,
                    t_us,
                    "sequence_repeated",
                    f"seq {seq} again with a capture time {(t_us - last_t) / 1e6:+.3f} s later: the sender numbered "
                    "two frames alike (or a second sender on the key)",
                )
            return self._accept(
                seq, t_us, "sequence_reset", f"seq {last_seq} -> {seq} while time moved forward: the sender restarted"
            )
        step = (t_us - last_t) / 1e6
        where = f"seq {seq} at time_boot_us {t_us} is {step:+.3f} s from the last accepted one (seq {last_seq})"
        if t_us > last_t + thr:
            if seq_forward and (
                self._on_the_streams_rate(seq, t_us) or (reference_us is not None and abs(t_us - reference_us) <= thr)
            ):
                return self._accept(seq, t_us, "")
            apart = reference_us is not None and abs(t_us - reference_us) > thr
            return self._candidate(
                seq,
                t_us,
                far=True,
                apart=apart,
                reference_us=reference_us,
                reason="time_ahead",
                message=f"frame {where}",
            )
        far = t_us < last_t - thr
        apart = far and reference_us is not None and abs(t_us - reference_us) > thr
        if seq_forward:
            return self._candidate(
                seq,
                t_us,
                far=far,
                apart=apart,
                reference_us=reference_us,
                reason="time_behind",
                message=f"frame {where}",
            )
        return self._candidate(seq, t_us, far=False, reason="out_of_order", message=f"frame {where}")

    # ------------------------------------------------------------------ internals

    def _ahead_of_rate(self, seq: int, t_us: int) -> bool:
        """``t_us`` is more than ``AHEAD_OF_RATE_US`` past where the stream's rate (``RATE_FRAMES`` accepted since
        the last event at least) puts frame ``seq``."""
        expected_us = self._expected_us(seq)
        return expected_us is not None and t_us - expected_us > AHEAD_OF_RATE_US

    def _expected_us(self, seq: int) -> float | None:
        if len(self._recent) < RATE_FRAMES:
            return None
        seq0, t0 = self._recent[0]
        seq1, t1 = self._recent[-1]
        n = (seq1 - seq0) % SEQ_MOD
        if n == 0 or t1 <= t0:
            return None
        return t1 + (t1 - t0) / n * ((seq - seq1) % SEQ_MOD)

    def _on_the_streams_rate(self, seq: int, t_us: int) -> bool:
        """``t_us`` is within ``threshold_us`` of where the rate of the frames accepted since the last event puts
        frame ``seq`` (from the oldest remembered one to the newest: their jitter averages out over the span)."""
        expected_us = self._expected_us(seq)
        return expected_us is not None and abs(t_us - expected_us) <= self.threshold_us

    def _candidate(
        self,
        seq: int,
        t_us: int,
        *,
        far: bool,
        reason: str,
        message: str,
        apart: bool = False,
        reference_us: int | None = None,
    ) -> Admission:
        """Refuse, unless this frame completes a consistent run (module docstring); ``apart``: the frame is far from
        ``reference_us``, the telemetry's newest time, as well."""
        run = self._run
        if run and far == self._run_far and run[-1][1] < t_us <= run[-1][1] + self.threshold_us:
            if _forward(seq, run[-1][0]):
                run.append((seq, t_us))
            else:
                run[:] = [(seq, t_us)]
        else:
            run[:] = [(seq, t_us)]
            self._run_far = far
        need = TIME_CONFIRM_FRAMES if far else self.restart_count
        if len(run) < need or (apart and run[-1][1] - run[0][1] < APART_CONFIRM_US):
            return Admission(False, reason, message)
        first_seq = run[0][0]
        last_t = self.last_t_us
        if last_t is None:
            what = f"{len(run)} consistent frames from seq {first_seq} stand apart from the telemetry"
        else:
            what = f"capture time stepped {(t_us - last_t) / 1e6:+.3f} s (seq {self.last_seq} -> {seq})"
            what += f", confirmed by {len(run)} consistent frames from seq {first_seq}"
            if apart:
                what += " (apart from the telemetry's clock too)"
        event = "time_reset" if far else "stream_restart"
        verdict = self._accept(seq, t_us, event, what, restart=True)
        if apart and reference_us is not None:  # admit follows it from here, frame by frame
            self.apart_us = t_us - reference_us
        return verdict

    def _accept(self, seq: int, t_us: int, event: str, message: str = "", restart: bool = False) -> Admission:
        """Take the frame as the stream's newest; ``event`` names a step (module docstring), ``""`` none."""
        if event:  # a new clock or a new sequence: the old numbers say nothing about the new ones
            self._recent.clear()
        self._recent.add((seq, t_us))
        self.last_seq, self.last_t_us = seq, t_us
        if self._run:
            self._run.clear()
        if not event and not message and not restart:
            return _ACCEPTED
        return Admission(True, event, message, restart)


class _Numbering:
    """One sender's sequence numbering as :class:`ArrivalGaps` follows it."""

    __slots__ = ("newest", "arrived", "seen_at")

    def __init__(self, seq: int, seen_at: int) -> None:
        self.newest = seq
        self.arrived = 1  # bit k: frame newest - k arrived (k = 0 .. reorder)
        self.seen_at = seen_at  # ArrivalGaps.arrivals when its last frame came


class ArrivalGaps:
    """Frames the sender numbered that never arrived, from the gaps in the sequence numbers of the frames as they
    arrive (before the daemon's queue, whose own drops are counted apart): lost by the camera's sender, the network,
    or zenoh's congestion control, which drops rather than delays a camera's frames.  Pure, not thread-safe.

    A forward step of ``d`` frames counts ``d - 1`` missing, unless ``d`` is over ``max_gap`` (a sender numbering
    anew, not frames lost: counted as nothing).  A frame up to ``reorder`` behind the newest that had not arrived
    came late: one of those counted missing came after all.  One that had arrived (the last ``reorder`` are
    remembered), like any frame sent twice, changes nothing.  Further behind, the sender restarted its numbering:
    taken as the new newest.

    Several numberings are followed at once (up to ``MAX_NUMBERINGS``, each forgotten ``forget_after`` arrivals
    after its last frame): a frame belongs to the one it is the nearest step of (forward up to ``max_gap``, back up
    to ``reorder``), the most recent on a tie, and starts a new one when it is none's.  Two senders on one key (two
    cameras, each numbering its frames) interleave two numberings: each counts its own gaps, and a jump from one to
    the other is not frames lost (one numbering 300 ahead of the other counted 300 missing at every other frame).
    A frame of a numbering seen before, other than the previous frame's, is counted in
    ``returns``: a sender that restarted leaves its old numbering for good (none, or the odd late frame), two
    senders come back to theirs with every frame.  A numbering dropped to make room while its sender may still
    publish (not yet forgotten) is counted in ``returns`` too: more senders than ``MAX_NUMBERINGS`` start a numbering
    anew with every frame, and their frames come back to none.  Numberings closer than ``reorder`` to each other
    cannot be told apart (their frames read as late or repeated ones).

    A payload that arrived with no readable number (:meth:`unnumbered`: refused on its length before its header
    was read, as a 100x frame the daemon will not copy, or for a header that is not IRF1's) may be a frame that
    did not get lost: it explains one missing number of the gap the next readable frame closes, and none if that
    frame follows in order.  It is counted where it was refused; here it only keeps a frame that arrived out of
    the frames lost on the way."""

    def __init__(self, max_gap: int = 1000, reorder: int = 8, forget_after: int = 300) -> None:
        self.max_gap = int(max_gap)
        self.reorder = int(reorder)
        self.forget_after = int(forget_after)
        self.missing = 0
        #: frames that came back to a numbering seen before, other than the previous frame's (class docstring)
        self.returns = 0
        self.arrivals = 0
        self._numberings: list[_Numbering] = []  # the previous frame's first
        self._window = (1 << (self.reorder + 1)) - 1
        # the last forward step that counted frames missing: (the newest before it, the newest it made, missing
        # counted, arrivals then), undone when a new numbering starts within it soon after (the step
        # was onto another sender's numbering, not past frames lost)
        self._jump: tuple[int, int, int, int] | None = None
        self._unnumbered = 0  # payloads with no readable number since the last frame (see unnumbered)

    @property
    def newest(self) -> int | None:
        """The newest sequence number of the previous frame's numbering (None before any frame)."""
        return self._numberings[0].newest if self._numberings else None

    def unnumbered(self) -> None:
        """One payload arrived whose sequence number could not be read (class docstring)."""
        self._unnumbered += 1

    def see(self, seq: int) -> None:
        self.arrivals += 1
        unnumbered, self._unnumbered = self._unnumbered, 0
        best: _Numbering | None = None
        best_d = SEQ_MOD
        for num in self._numberings:  # the most recent first: it keeps a tie
            step = (seq - num.newest) % SEQ_MOD
            d = step if step < SEQ_MOD // 2 else SEQ_MOD - step
            if d < best_d and (d <= self.reorder or (step < SEQ_MOD // 2 and step <= self.max_gap)):
                best, best_d = num, d
        if best is None:
            jump = self._jump
            if jump is not None and self.arrivals - jump[3] <= self.reorder + 1:
                before, after, counted, _ = jump
                if 0 < (seq - before) % SEQ_MOD < (after - before) % SEQ_MOD:
                    self.missing = max(0, self.missing - counted)
                    self._jump = None
            live = [n for n in self._numberings if self.arrivals - n.seen_at <= self.forget_after]
            if len(live) >= MAX_NUMBERINGS:
                # one is dropped whose sender may still publish: with more senders than numberings followed, each
                # frame's numbering was dropped for the one before, and their frames would never be returns
                self.returns += 1
            self._numberings = live[: MAX_NUMBERINGS - 1]
            self._numberings.insert(0, _Numbering(seq, self.arrivals))
            return
        if best is not self._numberings[0]:
            self.returns += 1
            self._numberings.remove(best)
            self._numberings.insert(0, best)
        best.seen_at = self.arrivals
        step = (seq - best.newest) % SEQ_MOD
        if step == 0:
            return
        if step < SEQ_MOD // 2:
            if step > 1 and (lost := step - 1 - min(unnumbered, step - 1)):
                self.missing += lost
                self._jump = (best.newest, seq, lost, self.arrivals)
            best.newest = seq
            best.arrived = ((best.arrived << min(step, self.reorder + 1)) | 1) & self._window
            return
        back = SEQ_MOD - step
        if not best.arrived >> back & 1:
            best.arrived |= 1 << back
            self.missing = max(0, self.missing - 1)
