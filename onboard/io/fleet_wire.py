"""The fleet fusion's wire: vehicles' ``irtrack.track/2`` in, ``irtrack.fleet_track/1`` out (thin adapter).

Keys::

    irtrack/<vehicle>/track        in: each vehicle's track (schema irtrack.track/2, onboard.core.track)
    irtrack/fleet/track            out: one message per fused target and update (schema below)
    irtrack/<vehicle>/fleet/track  out: the same, with ned_m / origin / cov_ned_m2 in that vehicle's own frame

``fleet`` is therefore not a vehicle name.  Schema ``irtrack.fleet_track/1`` (UTF-8 JSON, encoding
``application/json;irtrack.fleet_track/1``): ``schema``, ``seq`` (the fusion's message counter),
``target_id``, ``time_unix_us`` (the estimate's time, UTC microseconds: the newest line of sight in it),
``lat_deg``, ``lon_deg``, ``alt_m`` (WGS84, as ``irtrack.track/2``), ``ned_m`` with its ``origin``
``{lat_deg, lon_deg, alt_m}``, ``vel_ned_mps``, ``sigma_ned_m``, ``sigma_vel_ned_mps`` (1 sigma),
``cov_ned_m2`` (3 x 3), ``range_sigma_ratio`` (the worst contributing vehicle's range sigma over range, of the
covariance published: the range floor included when unobservable),
``observable`` (the verdict of :mod:`onboard.estimation.fleet`), ``vehicles``: one object per contributing
vehicle ``{vehicle, time_unix_us (its newest line of sight), rays, range_m, range_sigma_ratio,
time_source}``; the per-vehicle key adds ``vehicle`` (the addressee) and ``range_m`` (from its newest
camera position, null before it sent one; for a vehicle that did not contribute to this target that position
can be older than the estimate).

Time: every line of sight is put on one clock, UTC seconds (:class:`CommonClock`): the track's ``time_unix_us`` when
it carries one (``time_source: vehicle``; a stamp whose ``UTC - boot`` offset jumps from the vehicle's is held back
until the next stamps say whether it was a glitch or the vehicle's UTC stepped), else its ``time_boot_us`` plus a
configured per-vehicle offset (``configured``), else plus the ``UTC - boot`` offset of the vehicle's latest stamped
track (``remembered``: a daemon restarted on a running autopilot publishes its first seconds unstamped, on the same
boot clock; the memory ends when the boot clock goes backwards, a reboot, or when the clock check refuses the stamps it
came from: :meth:`CommonClock.forget_stamps`), else plus an offset estimated from
arrival times, the minimum of ``arrival - time_boot`` over the last ``window_s`` (``arrival``: the fusion's clock,
biased by the vehicle's shortest capture-to-arrival latency, typically a few ms on one machine; it drifts with the
vehicle's clock and resets when the boot clock goes backwards).

Clock check (:class:`ClockConsistency`): a vehicle whose ``time_unix_us`` is off the others' (a wrong UTC mapping,
an injected 20 ms) is found from arrival times.  For each vehicle the fusion keeps the shortest ``arrival -
time_unix`` over ``window_s``: the floor of its capture-to-arrival latency.  Vehicles that run the same daemon over
the same kind of link share that floor within a few ms (the processing's fastest frame plus the link's shortest
delay), so a vehicle whose floor is ``tolerance_s`` (10 ms) off the median of the vehicles' floors is named: its
clock says its frames were taken later (floor lower) or earlier (higher) than they were.  The fusion's own clock
error is common to every vehicle and cancels.  With two vehicles the median is their midpoint and cannot say which
is off: then the one whose floor is farther from zero is named when they disagree by more than the tolerance, which
takes the fusion's clock as a third reference (a floor is small and positive on a clock that agrees with theirs: one
machine, or GNSS/PTP-disciplined clocks; a fusion clock off by more than the vehicle's error can name the wrong
one).  A vehicle whose floor genuinely differs (a slower computer, a longer radio hop) is named too: the status
gives the floors and the deviations so an operator can tell.  A vehicle whose UTC stepped (:class:`CommonClock`) is
forgotten and judged again from its new stamps: its old ones' floor would hide a step back (a higher floor) for the
whole window.  Why not the geometry: 20 ms of a 20 m/s target is 0.4 m, 0.8 mrad at 500 m, no more than one ray's
bearing noise, and as long as the target's angular rate is steady that error is a constant angle, which the solve's
per-vehicle attitude-bias nuisance absorbs; it would take a manoeuvring target and many seconds, where the latency
floor shows 20 ms within its first window.

A ray's time sigma: a stamped track's ``time_unix_sigma_us`` (the vehicle's UTC mapping) becomes the ray's
``time_sigma_s`` (:class:`~onboard.estimation.fleet.Ray`); a time from a configured, remembered or arrival offset
carries none and is taken as exact: a configured offset is the operator's, a remembered one the vehicle's own
earlier mapping, and the arrival estimate's error is the vehicle's shortest capture-to-arrival latency, a few ms
on one machine or a wired link (a constant lag, which the clock check reports; a radio link's longer floor belongs
in ``--clock-offset``).

One vehicle per name (:class:`StreamCheck`): a daemon publishes one track per frame, its ``seq`` and
``time_boot_us`` increasing and its camera moving no faster than an aircraft.  Two vehicles configured with the same
name interleave two such streams on one key: ``seq`` or ``time_boot_us`` go back and forth, the camera jumps
hundreds of metres between consecutive tracks.  Each such step is an anomaly; ``clash_anomalies`` (4) within
``window_s`` (5 s) name the vehicle a name clash until ``clear_after_s`` (5 s) pass without one.  A daemon restart
(``seq`` from 0) or a reboot (``time_boot_us`` from 0) is one anomaly; a message the link delivered late, which
falls between two of the stream's recent messages in both ``seq`` and ``time_boot_us``, is none (a reorder: the
tracker refuses its ray, older than its object's newest, as ``ray_out_of_order``); a message heard again (a
redelivery, a replay) is refused as ``duplicate`` and is none, unless its camera is more than ``slack_m`` from
where that message's was: then it is a second vehicle's on the same counts (``camera_jump``, an anomaly); a new
local origin two (the first track there is refused as a jump, the next one, consistent with it, is the stream's new
place).  A single camera jump (a glitch, a track placed against another origin) is refused alone (``camera_jump``), and a camera farther than
``MAX_CAMERA_DISTANCE_M`` from the fleet's origin is refused outright (``camera_far``).  A daemon states its run
(the track's ``run_id``): a new one is a restart, said (``restarted``) and no anomaly -- the stream's state starts
again, its camera at a new origin included -- and a message of an earlier run after a newer one is two daemons
taking turns under the name (``run_returned``, refused, an anomaly each time).

Frames: each vehicle's ``camera_ned_m`` / ``los_ned`` are in its own local NED frame (its track's
``origin``); both are mapped into the fleet's frame (the first origin seen, or a configured one) by the exact
affine map between the two tangent frames (:func:`ned_transform`, through ECEF).
"""

from __future__ import annotations

import functools
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from onboard.core.errors import InputError
from onboard.core.frames import GeodeticOrigin, geodetic_from_ned, ned_from_geodetic
from onboard.core.recent import Recent
from onboard.core.track import Track, json_number, track_from_json
from onboard.estimation.fleet import FleetEstimate, Ray
from onboard.io.zenoh_session import check_vehicle_name

__all__ = [
    "FLEET_TRACK_SCHEMA",
    "FLEET_TRACK_ENCODING",
    "FLEET_NAME",
    "TRACKS_KEY_EXPR",
    "fleet_track_key",
    "vehicle_fleet_track_key",
    "vehicle_from_track_key",
    "ned_transform",
    "ClockReading",
    "CommonClock",
    "ClockConsistency",
    "StreamCheck",
    "MAX_CAMERA_DISTANCE_M",
    "TimedTrack",
    "parse_track",
    "ray_from_track",
    "fleet_track_json",
]

FLEET_TRACK_SCHEMA = "irtrack.fleet_track/1"
FLEET_TRACK_ENCODING = f"application/json;{FLEET_TRACK_SCHEMA}"
FLEET_NAME = "fleet"  # irtrack/fleet/... is the fusion's, not a vehicle's
TRACKS_KEY_EXPR = "irtrack/*/track"


def fleet_track_key() -> str:
    """``irtrack/fleet/track``: the fused targets."""
    return f"irtrack/{FLEET_NAME}/track"


def vehicle_fleet_track_key(vehicle: str) -> str:
    """``irtrack/<vehicle>/fleet/track``: the fused targets in ``vehicle``'s own frame."""
    return f"irtrack/{check_vehicle_name(vehicle)}/fleet/track"


def vehicle_from_track_key(key: str) -> str | None:
    """The ``<vehicle>`` of ``irtrack/<vehicle>/track``; None for any other key and for the fleet's own."""
    parts = str(key).split("/")
    if len(parts) != 3 or parts[0] != "irtrack" or parts[2] != "track" or parts[1] == FLEET_NAME or not parts[1]:
        return None
    return parts[1]


@functools.lru_cache(maxsize=256)
def ned_transform(origin_from: GeodeticOrigin, origin_to: GeodeticOrigin) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` with ``p_to = R p_from + t`` between two local NED frames: both are rigid maps of ECEF, so
    the map is affine and exact (computed from the images of the origin and of three 1 km axis points)."""
    pts = np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0], [0.0, 1000.0, 0.0], [0.0, 0.0, 1000.0]])
    lat, lon, alt = geodetic_from_ned(pts, origin_from)
    img = ned_from_geodetic(lat, lon, alt, origin_to)
    t = img[0]
    R = (img[1:] - t).T / 1000.0
    u, _, vt = np.linalg.svd(R)  # remove the round-off: the nearest rotation
    R = u @ vt
    R.setflags(write=False)
    t.setflags(write=False)
    return R, t


@dataclass(frozen=True)
class TimedTrack:
    """A vehicle's track with its time on the common clock: ``t_s`` (UTC seconds), where it came from
    (``vehicle`` | ``configured`` | ``remembered`` | ``arrival``) and its 1-sigma ``time_sigma_s`` (module
    docstring, "A ray's time sigma")."""

    track: Track
    t_s: float
    time_source: str
    time_sigma_s: float = 0.0


#: farther than this from the fleet's origin a camera is not one of the fleet's (a garbage position, a track
#: placed against a wrong origin): the fleet works within a radio link's range
MAX_CAMERA_DISTANCE_M = 200_000.0


#: how many of a stream's newest messages a repeat is recognised among (a few seconds at 30 Hz)
RECENT_MESSAGES = 128
#: how many of a stream's daemon runs are remembered: a run back from among them is a second daemon's
RECENT_RUNS = 8


@dataclass
class _Stream:
    seq: int
    boot_us: int
    anchor: tuple[float, np.ndarray] | None = None  # (t_s, camera) of the newest accepted camera
    candidate: tuple[float, np.ndarray] | None = None  # the newest refused one: the stream may have moved there
    anomalies: deque = field(default_factory=deque)  # arrival times, s
    # the newest (seq, time_boot_us) pairs heard: one heard again is a repeat of that message, not a second stream
    seen: Recent = field(default_factory=lambda: Recent(RECENT_MESSAGES))
    # the camera each of those carried: a repeat is the same message, at the same place
    cameras: dict = field(default_factory=dict)
    # the daemon runs (run_id) stated, newest last: a new one is a restart, an earlier one back is a second daemon
    runs: deque = field(default_factory=lambda: deque(maxlen=RECENT_RUNS))


class StreamCheck:
    """Whether each vehicle name carries one vehicle's tracks (module docstring, "One vehicle per name").

    Step method :meth:`add` (one track's ``seq``, ``time_boot_us``, common time, camera in the fleet frame or
    None, arrival time on the fusion's clock) returns ``camera_far`` / ``camera_jump`` for a track whose camera
    is not believable (refuse its ray), ``duplicate`` for a message heard already (one of the stream's last
    :data:`RECENT_MESSAGES`: a redelivery or a replay, refused without counting against the name; one whose camera
    is more than ``slack_m`` from where that message's was is another vehicle's on the same counts, ``camera_jump``
    and an anomaly), or None (also for a late message that slots into the stream's recent ``seq`` and
    ``time_boot_us`` order: the link delivered it after newer ones, no anomaly; the tracker refuses its ray as out of
    order); :meth:`clashing` names the vehicles
    whose recent anomalies say two vehicles share the name.  ``max_speed_mps``: the fastest vehicle, ``slack_m``: a
    navigation fix's jump allowed on top of it."""

    def __init__(
        self,
        max_speed_mps: float = 100.0,
        slack_m: float = 20.0,
        window_s: float = 5.0,
        clash_anomalies: int = 4,
        clear_after_s: float = 5.0,
    ) -> None:
        self.max_speed_mps = float(max_speed_mps)
        self.slack_m = float(slack_m)
        self.window_s = float(window_s)
        self.clash_anomalies = int(clash_anomalies)
        self.clear_after_s = float(clear_after_s)
        self._streams: dict[str, _Stream] = {}
        self._clashing: set[str] = set()  # named a clash, until it clears

    def _near(self, a: tuple[float, np.ndarray], t_s: float, p: np.ndarray) -> bool:
        return float(np.linalg.norm(p - a[1])) <= self.max_speed_mps * abs(t_s - a[0]) + self.slack_m

    def forget(self, vehicle: str) -> None:
        """Drop what is kept of ``vehicle``'s stream (a vehicle long silent)."""
        self._streams.pop(vehicle, None)
        self._clashing.discard(vehicle)

    @staticmethod
    def _slots_in(st: _Stream, seq: int, time_boot_us: int) -> bool:
        """Whether a late ``(seq, time_boot_us)`` falls between two of the stream's recent messages in both orders:
        one message of this stream the link delivered after newer ones.  A second vehicle's stream, on its own
        ``seq`` count and boot clock, does not slot into the first's (nor does a message older than all those kept:
        nothing says which stream it is of)."""
        older = False
        for i in range(len(st.seen)):
            s_seen, b_seen = st.seen[i]
            if s_seen == seq or b_seen == time_boot_us or (s_seen < seq) != (b_seen < time_boot_us):
                return False
            older = older or s_seen < seq
        return older

    def add(
        self,
        vehicle: str,
        seq: int,
        time_boot_us: int,
        t_s: float,
        p_cam_ned_m,
        arrival_unix_s: float,
        run_id: str | None = None,
    ) -> str | None:
        """One track of ``vehicle`` (the class docstring); ``run_id``: its daemon's run, None when not stated.
        ``restarted`` for the first track of a run after another (the stream starts again from it, no anomaly: take
        its ray), ``run_returned`` for one of an earlier run after a newer one (refuse it; an anomaly)."""
        p = None if p_cam_ned_m is None else np.asarray(p_cam_ned_m, dtype=float)
        if p is not None and not float(np.linalg.norm(p)) <= MAX_CAMERA_DISTANCE_M:
            return "camera_far"
        st = self._streams.get(vehicle)
        restarted = False
        if st is not None and run_id is not None and st.runs and run_id != st.runs[-1]:
            if run_id in st.runs:  # an earlier run back after a newer one: two daemons take turns under the name
                return self._judge(vehicle, st, True, arrival_unix_s, "run_returned")
            restarted = True
        if st is None or restarted:  # the vehicle's first track, or its daemon's new run: the stream starts here
            # (a restart keeps the runs it has seen and its anomalies: a clash in progress is not forgotten)
            st = self._streams[vehicle] = (
                _Stream(seq, time_boot_us)
                if st is None
                else _Stream(seq, time_boot_us, runs=st.runs, anomalies=st.anomalies)
            )
            self._note(st, seq, time_boot_us, p)
            if run_id is not None:
                st.runs.append(run_id)
            if p is not None:
                st.anchor = (t_s, p)
            return "restarted" if restarted else None
        if run_id is not None and not st.runs:
            st.runs.append(run_id)
        if (seq, time_boot_us) in st.seen:
            first = st.cameras.get((seq, time_boot_us))
            if p is None or first is None or float(np.linalg.norm(p - first)) <= self.slack_m:
                return "duplicate"
            # the same seq and time_boot_us from a camera elsewhere: no repeat of that message but a second vehicle's
            # on the same counts (two daemons of one name started together, on one simulated boot clock)
            return self._judge(vehicle, st, True, arrival_unix_s, "camera_jump")
        late = seq <= st.seq or time_boot_us < st.boot_us
        if (
            late
            and self._slots_in(st, seq, time_boot_us)
            and (p is None or st.anchor is None or self._near(st.anchor, t_s, p))
        ):
            self._note(st, seq, time_boot_us, p)
            return None
        self._note(st, seq, time_boot_us, p)
        anomaly = late
        st.seq, st.boot_us = seq, time_boot_us
        verdict = None
        if p is not None:
            if st.anchor is None or self._near(st.anchor, t_s, p):
                st.anchor, st.candidate = (t_s, p), None
            elif st.candidate is not None and self._near(st.candidate, t_s, p):
                st.anchor, st.candidate = (t_s, p), None  # two in a row agree: the stream moved (a new origin)
            else:
                st.candidate = (t_s, p)
                anomaly, verdict = True, "camera_jump"
        return self._judge(vehicle, st, anomaly, arrival_unix_s, verdict)

    @staticmethod
    def _note(st: _Stream, seq: int, time_boot_us: int, p: np.ndarray | None) -> None:
        st.seen.add((seq, time_boot_us))
        if p is not None:
            st.cameras[(seq, time_boot_us)] = p
            if len(st.cameras) > 2 * RECENT_MESSAGES:  # keep those of the messages still among the recent ones
                st.cameras = {k: c for k, c in st.cameras.items() if k in st.seen}

    def _judge(
        self, vehicle: str, st: _Stream, anomaly: bool, arrival_unix_s: float, verdict: str | None
    ) -> str | None:
        """Note an ``anomaly`` (or none) of ``vehicle``'s stream, name the clash once they are enough; ``verdict``."""
        if anomaly:
            st.anomalies.append(arrival_unix_s)
        while st.anomalies and st.anomalies[0] < arrival_unix_s - self.window_s:
            st.anomalies.popleft()
        if len(st.anomalies) >= self.clash_anomalies:
            self._clashing.add(vehicle)
        return verdict

    def clashing(self, now_unix_s: float) -> list[str]:
        """The vehicles named a name clash now: enough anomalies in a window, the newest less than
        ``clear_after_s`` ago."""
        for v in list(self._clashing):
            st = self._streams[v]
            if not st.anomalies or st.anomalies[-1] < now_unix_s - self.clear_after_s:
                self._clashing.discard(v)
        return sorted(self._clashing)


#: how fast an autopilot's boot clock may drift against UTC (a crystal's tolerance, with margin)
CLOCK_DRIFT_PPM = 50.0
#: a vehicle's ``UTC - boot`` offset that moves more than this (plus its drift) from one stamp to the next jumped: the
#: daemon's UTC fit (:mod:`onboard.core.utc_clock`) moves it by well under a millisecond between frames
STAMP_JUMP_S = 0.005
#: stamps in a row that agree on a new offset before it is the vehicle's (its UTC stepped); fewer are a glitch
STEP_STAMPS = 3


@dataclass(frozen=True)
class ClockReading:
    """A frame placed on the common clock (:meth:`CommonClock.place`): ``t_s`` (UTC s) and its ``source``;
    ``held_jump_s``: its stamp's ``UTC - boot`` offset minus the vehicle's, when that is a jump the clock holds back
    (a glitch, or the first stamps of a step: which one, the next stamps say), else None; ``step_s``: the step of the
    vehicle's offset this stamp confirmed (the new offset minus the old), else None."""

    t_s: float
    source: str
    held_jump_s: float | None = None
    step_s: float | None = None


class CommonClock:
    """Puts each vehicle's frames on one clock, UTC seconds (module docstring, "Time").

    ``offsets_s``: configured ``UTC - boot`` offsets per vehicle, seconds.  ``window_s``: the arrival-time
    estimate's memory.  Step method :meth:`place`; :meth:`time_s` is its time and source alone.

    A stamped track's ``UTC - boot`` offset is the vehicle's once it agrees with the one before (within
    :data:`STAMP_JUMP_S` plus the boot clock's drift since): one stamp that jumps from it is held (not the vehicle's,
    :attr:`ClockReading.held_jump_s`) until a stamp agrees with the vehicle's offset again (a glitch) or
    :data:`STEP_STAMPS` newer stamps in a row agree with each other on the new one (the vehicle's UTC stepped,
    :attr:`ClockReading.step_s`: the new offset is the vehicle's from then on)."""

    def __init__(self, offsets_s: Mapping[str, float] | None = None, window_s: float = 10.0) -> None:
        self.offsets_s = dict(offsets_s or {})
        self.window_s = float(window_s)
        self._arrivals: dict[str, deque[tuple[float, float]]] = {}
        self._last_boot_s: dict[str, float] = {}
        # (UTC - boot, boot time) of each vehicle's latest stamped track whose offset is the vehicle's
        self._stamped: dict[str, tuple[float, float]] = {}
        # (UTC - boot, boot time, stamps in a row) of the newest held stamps that agree with each other
        self._held: dict[str, tuple[float, float, int]] = {}

    def forget(self, vehicle: str) -> None:
        """Drop what is kept of ``vehicle``'s clock (a vehicle long silent; a configured offset stays)."""
        for kept in (self._arrivals, self._last_boot_s, self._stamped, self._held):
            kept.pop(vehicle, None)

    def forget_stamps(self, vehicle: str) -> None:
        """Drop the ``UTC - boot`` offset kept from ``vehicle``'s stamps (the clock check found them off): its unstamped
        frames are ``arrival``-timed from then on, not ``remembered`` by that offset (a configured one still wins)."""
        self._stamped.pop(vehicle, None)
        self._held.pop(vehicle, None)

    @staticmethod
    def _agree(offset_s: float, kept: tuple[float, ...], boot_s: float) -> bool:
        return abs(offset_s - kept[0]) <= STAMP_JUMP_S + abs(boot_s - kept[1]) * CLOCK_DRIFT_PPM * 1e-6

    def _stamp(self, vehicle: str, offset_s: float, boot_s: float) -> tuple[float | None, float | None]:
        """(held jump, confirmed step) of a stamp whose ``UTC - boot`` is ``offset_s`` (class docstring)."""
        kept = self._stamped.get(vehicle)
        if kept is None or self._agree(offset_s, kept, boot_s):
            self._stamped[vehicle] = (offset_s, boot_s)
            self._held.pop(vehicle, None)
            return None, None
        held = self._held.get(vehicle)
        n = 1
        if held is not None and self._agree(offset_s, held, boot_s):
            if boot_s <= held[1]:  # a copy (or a late one) of a held message: not another stamp of the new offset
                return offset_s - kept[0], None
            n = held[2] + 1
        if n >= STEP_STAMPS:
            self._stamped[vehicle] = (offset_s, boot_s)
            self._held.pop(vehicle, None)
            return None, offset_s - kept[0]
        self._held[vehicle] = (offset_s, boot_s, n)
        return offset_s - kept[0], None

    def remembered_sigma_s(self, vehicle: str, time_boot_us: int) -> float:
        """The 1-sigma of a ``remembered`` time: the vehicle's boot clock drifts against UTC since its last stamped
        track (:data:`CLOCK_DRIFT_PPM`); 0 when there is none."""
        stamped = self._stamped.get(vehicle)
        return 0.0 if stamped is None else abs(time_boot_us / 1e6 - stamped[1]) * CLOCK_DRIFT_PPM * 1e-6

    def time_s(
        self, vehicle: str, time_boot_us: int, time_unix_us: int | None, arrival_unix_s: float
    ) -> tuple[float, str]:
        """(common time s, its source) of a frame of ``vehicle`` (:meth:`place`)."""
        reading = self.place(vehicle, time_boot_us, time_unix_us, arrival_unix_s)
        return reading.t_s, reading.source

    def place(self, vehicle: str, time_boot_us: int, time_unix_us: int | None, arrival_unix_s: float) -> ClockReading:
        """A frame of ``vehicle`` on the common clock, with what its stamp says of the vehicle's UTC (class
        docstring)."""
        boot_s = time_boot_us / 1e6
        hist = self._arrivals.setdefault(vehicle, deque())
        if boot_s < self._last_boot_s.get(vehicle, -math.inf) - 1.0:  # the boot clock went back: a reboot
            hist.clear()
            self._stamped.pop(vehicle, None)
            self._held.pop(vehicle, None)
        self._last_boot_s[vehicle] = boot_s
        if time_unix_us is not None:
            held_s, step_s = self._stamp(vehicle, time_unix_us / 1e6 - boot_s, boot_s)
            return ClockReading(time_unix_us / 1e6, "vehicle", held_s, step_s)
        if vehicle in self.offsets_s:
            return ClockReading(boot_s + self.offsets_s[vehicle], "configured")
        if vehicle in self._stamped:
            return ClockReading(boot_s + self._stamped[vehicle][0], "remembered")
        hist.append((arrival_unix_s, arrival_unix_s - boot_s))
        while hist and hist[0][0] < arrival_unix_s - self.window_s:
            hist.popleft()
        return ClockReading(boot_s + min(o for _, o in hist), "arrival")


class ClockConsistency:
    """Which vehicles' UTC stamps disagree with the others' (module docstring, "Clock check").

    Step methods: :meth:`add` (one frame with a ``time_unix_us``: its common time and arrival, UTC seconds
    on the fusion's clock) and :meth:`deviations_s` (each judged vehicle's latency floor minus the median
    floor, s; a vehicle is judged once it has ``min_samples`` frames in the last ``window_s``).
    :meth:`inconsistent` names the vehicles off the others by more than ``tolerance_s`` (with two judged, the one
    farther from the fusion's own clock); :meth:`errors_s` says by how much each named one is off."""

    def __init__(
        self, window_s: float = 10.0, tolerance_s: float = 0.010, min_samples: int = 20, judging_max_s: float = 1.5
    ) -> None:
        self.window_s = float(window_s)
        self.tolerance_s = float(tolerance_s)
        self.min_samples = int(min_samples)
        self.judging_max_s = float(judging_max_s)  # how long a vehicle's rays wait for its verdict at most (judging)
        self._floor: dict[str, deque[tuple[float, float]]] = {}  # (arrival, lag), lags increasing: sliding min
        self._arrivals: dict[str, deque[float]] = {}

    def add(self, vehicle: str, t_s: float, arrival_unix_s: float) -> None:
        lag = arrival_unix_s - t_s
        floor = self._floor.setdefault(vehicle, deque())
        while floor and floor[-1][1] >= lag:
            floor.pop()
        floor.append((arrival_unix_s, lag))
        self._arrivals.setdefault(vehicle, deque()).append(arrival_unix_s)
        self._trim(vehicle, arrival_unix_s)

    def forget(self, vehicle: str) -> None:
        """Drop ``vehicle``'s frames (a vehicle long silent)."""
        self._floor.pop(vehicle, None)
        self._arrivals.pop(vehicle, None)

    def judging(self, vehicle: str, now_unix_s: float) -> bool:
        """Whether ``vehicle``'s stamps are still too few to judge (fewer than ``min_samples`` in the window) and the
        first of those in the window came less than ``judging_max_s`` before ``now_unix_s``: a vehicle that starts,
        returns after a window's silence, or stepped.  Until it is judged a clock that is off is named by nothing, and
        its rays paired at the wrong place with a time sigma of a fraction of a millisecond (a vehicle 0.3 s ahead from
        its start: 6 fleet points up to NEES 111 in its first 20 frames), so the fusion holds them; ``judging_max_s``
        bounds the wait for a vehicle that publishes too slowly ever to have ``min_samples`` in the window, which
        stays unjudged as before."""
        arrivals = self._arrivals.get(vehicle)
        if not arrivals:
            return False
        self._trim(vehicle, now_unix_s)
        return bool(arrivals) and len(arrivals) < self.min_samples and now_unix_s - arrivals[0] < self.judging_max_s

    def judged(self, vehicle: str, now_unix_s: float) -> bool:
        """Whether ``vehicle`` has ``min_samples`` stamps in the window ending at ``now_unix_s`` (:meth:`floors_s`
        names it), without a pass over the other vehicles."""
        if not self._arrivals.get(vehicle):
            return False
        self._trim(vehicle, now_unix_s)
        return len(self._arrivals[vehicle]) >= self.min_samples and bool(self._floor[vehicle])

    def _trim(self, vehicle: str, now_unix_s: float) -> None:
        cutoff = now_unix_s - self.window_s
        floor, arrivals = self._floor[vehicle], self._arrivals[vehicle]
        while floor and floor[0][0] < cutoff:
            floor.popleft()
        while arrivals and arrivals[0] < cutoff:
            arrivals.popleft()

    def floors_s(self, now_unix_s: float) -> dict[str, float]:
        """Each judged vehicle's shortest ``arrival - time_unix`` in the window ending at ``now_unix_s``."""
        out = {}
        for v in sorted(self._floor):
            self._trim(v, now_unix_s)
            if len(self._arrivals[v]) >= self.min_samples and self._floor[v]:
                out[v] = self._floor[v][0][1]
        return out

    def deviations_s(self, now_unix_s: float) -> dict[str, float]:
        """Each judged vehicle's floor minus the median of the judged vehicles' floors, s (negative: its
        stamps are late, its clock ahead)."""
        floors = self.floors_s(now_unix_s)
        if len(floors) < 2:
            return {}
        med = float(np.median(list(floors.values())))
        return {v: f - med for v, f in floors.items()}

    def errors_s(self, now_unix_s: float) -> dict[str, float]:
        """How far the UTC of each vehicle :meth:`inconsistent` names is off the others', s: the median of the other
        judged vehicles' floors minus its own (positive: its stamps say its frames were taken later than they were,
        its clock is ahead).  Not :meth:`deviations_s`: with two judged the median is their midpoint, which splits
        their disagreement between them, while the vehicle named is blamed for all of it."""
        floors = self.floors_s(now_unix_s)
        out = {}
        for v in self.inconsistent(now_unix_s):
            others = [f for o, f in floors.items() if o != v]
            out[v] = float(np.median(others)) - floors[v]
        return out

    def inconsistent(self, now_unix_s: float) -> list[str]:
        """The judged vehicles whose floor is more than ``tolerance_s`` off the median floor (three or more
        judged); with two judged that disagree by more than ``tolerance_s``, the one whose floor is farther from
        zero (module docstring, "Clock check"); none with fewer."""
        floors = self.floors_s(now_unix_s)
        if len(floors) >= 3:
            med = float(np.median(list(floors.values())))
            return sorted(v for v, f in floors.items() if abs(f - med) > self.tolerance_s)
        if len(floors) == 2:
            (a, fa), (b, fb) = floors.items()
            if abs(fa - fb) > self.tolerance_s:
                return [a if abs(fa) > abs(fb) else b]
        return []


def parse_track(obj: Mapping) -> tuple[Track, int | None]:
    """(the track, its ``time_unix_us`` or None) of an ``irtrack.track/2`` dict; :class:`InputError` naming
    the key otherwise (the reader checks ``time_unix_us``: an integer in [0, 2**63))."""
    track = track_from_json(obj)
    return track, track.time_unix_us


def ray_from_track(timed: TimedTrack, fleet_origin: GeodeticOrigin) -> Ray:
    """The :class:`Ray` of a track with a line of sight and an origin, in the fleet's frame; raises
    :class:`InputError` (naming what is missing) otherwise."""
    track = timed.track
    los = track.los
    if los is None:
        raise InputError("track has no line of sight (los_ned)")
    if track.origin is None:
        raise InputError("track has no origin: its camera_ned_m cannot be placed")
    R, t = ned_transform(track.origin, fleet_origin)
    u = R @ np.asarray(los.u_ned)
    own_p = own_cov = None
    # the vehicle's own position of its object, where it ranged it itself: what tells two objects on crossing
    # lines of sight apart (onboard.estimation.fleet_tracker)
    if track.observable and track.p_ned_m is not None and track.cov_p_ned_m2 is not None:
        p = np.asarray(track.p_ned_m, dtype=float)
        cov = np.asarray(track.cov_p_ned_m2, dtype=float)
        if p.shape == (3,) and cov.shape == (3, 3) and np.all(np.isfinite(p)) and np.all(np.isfinite(cov)):
            own_p, own_cov = R @ p + t, R @ cov @ R.T
    return Ray(
        vehicle=track.vehicle,
        object_id=track.track_id or 0,
        t_s=timed.t_s,
        p_cam_ned_m=R @ np.asarray(los.p_cam_ned_m) + t,
        los_ned=u / np.linalg.norm(u),
        sigma_az_rad=math.radians(los.sigma_azimuth_deg),
        sigma_el_rad=math.radians(los.sigma_elevation_deg),
        time_sigma_s=timed.time_sigma_s,
        own_p_ned_m=own_p,
        own_cov_ned_m2=own_cov,
    )


def _vec(v) -> list:
    return [json_number(x) for x in np.asarray(v, dtype=float).ravel()]


def _sigmas(cov: np.ndarray) -> list:
    return _vec(np.sqrt(np.maximum(np.diag(cov), 0.0)))


def fleet_track_json(
    est: FleetEstimate,
    fleet_origin: GeodeticOrigin,
    seq: int,
    time_sources: Mapping[str, str],
    vehicle: str | None = None,
    vehicle_origin: GeodeticOrigin | None = None,
    vehicle_camera_ned_m=None,
) -> dict:
    """The ``irtrack.fleet_track/1`` dict of ``est`` (module docstring); with ``vehicle`` and its origin,
    the per-vehicle variant in that vehicle's frame (``vehicle_camera_ned_m``: its newest camera position,
    in its own frame, for ``range_m``)."""
    p, P, V = est.p_ned_m, est.cov_p_ned_m2, est.cov_v_ned_m2ps2
    v = est.v_ned_mps
    origin = fleet_origin
    if vehicle is not None and vehicle_origin is not None:
        R, t = ned_transform(fleet_origin, vehicle_origin)
        p, P, V, v = R @ p + t, R @ P @ R.T, R @ V @ R.T, R @ v
        origin = vehicle_origin
    lat, lon, alt = (float(x) for x in geodetic_from_ned(est.p_ned_m, fleet_origin))
    out = {
        "schema": FLEET_TRACK_SCHEMA,
        "seq": int(seq),
        "target_id": int(est.target_id),
        "time_unix_us": int(round(est.t_s * 1e6)),
        "lat_deg": json_number(lat),
        "lon_deg": json_number((lon + 180.0) % 360.0 - 180.0),
        "alt_m": json_number(alt),
        "ned_m": _vec(p),
        "origin": {"lat_deg": origin.lat_deg, "lon_deg": origin.lon_deg, "alt_m": origin.alt_m},
        "vel_ned_mps": _vec(v),
        "sigma_ned_m": _sigmas(P),
        "sigma_vel_ned_mps": _sigmas(V),
        "cov_ned_m2": [_vec(row) for row in P],
        "range_sigma_ratio": json_number(est.range_sigma_ratio),
        "observable": bool(est.observable),
        "vehicles": [
            {
                "vehicle": c.vehicle,
                "time_unix_us": int(round(c.t_s * 1e6)),
                "rays": c.rays,
                "range_m": json_number(c.range_m),
                "range_sigma_ratio": json_number(c.range_sigma_ratio),
                "time_source": time_sources.get(c.vehicle),
            }
            for c in est.contributions
        ],
    }
    if vehicle is not None:
        out["vehicle"] = vehicle
        rng = None
        if vehicle_camera_ned_m is not None:
            rng = json_number(float(np.linalg.norm(p - np.asarray(vehicle_camera_ned_m, dtype=float))))
        out["range_m"] = rng
    return out
