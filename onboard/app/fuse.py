"""``python -m onboard.fuse``: fuse several vehicles' lines of sight into fleet tracks over zenoh.

    python -m onboard.fuse [--vehicles uav1 uav2 ...] [--origin LAT,LON,ALT] [--clock-offset NAME=SECONDS]...
                           [--seconds S] [--max-age-s 2] [--status-interval-s 1]
                           [--attitude-bias-deg 0.1] [--camera-white-m 0.02] [--camera-offset-m 0]
                           [--vehicle-noise NAME:attitude_bias_deg=..,camera_white_m=..,camera_offset_m=..]...
                           [--max-time-sigma-ms 50] [--silent-after-s 1] [--clock-tolerance-ms 10]
                           [--reject-log-interval-s 10] [--log-level INFO]
                           [--zenoh-connect ENDPOINT]... [--zenoh-listen ENDPOINT]... [--zenoh-config FILE]
                           [--zenoh-multicast-scouting | --no-zenoh-multicast-scouting] [--zenoh-gossip-autoconnect]

It subscribes ``irtrack/*/track`` (every vehicle; ``--vehicles`` keeps only those named), turns each track
with a line of sight into a ray in one frame and on one clock (:mod:`onboard.io.fleet_wire`), feeds the
:class:`~onboard.estimation.fleet_tracker.FleetTracker` and publishes each updated target on ``irtrack/fleet/track``
and, in each vehicle's own frame, on ``irtrack/<vehicle>/fleet/track``; ``irtrack/fleet/status`` (JSON,
``--status-interval-s``) carries the counts, ``silent`` (vehicles heard before but not for ``--silent-after-s``:
a daemon that stopped; the fleet track goes on with the others, unobservable when one is left, and the vehicle
rejoins with its next line of sight that gates), ``clocks`` (each vehicle's latency floor off the fleet's
median, ms; ``latency_floor_ms``: the floors themselves) and ``clock_inconsistent`` (the vehicles whose ``time_unix_us`` disagrees with the others' beyond
``--clock-tolerance-ms``: :class:`~onboard.io.fleet_wire.ClockConsistency`).  Counted on each change:
``vehicle_silent``, ``clock_inconsistent`` (WARNING, naming the vehicle), ``vehicle_back`` and, after
``FORGET_AFTER_S`` (10 min) of silence, ``vehicle_forgotten`` (INFO: out of the status and the per-vehicle outputs).
``clock_step`` (WARNING): a vehicle's ``UTC - boot`` offset stepped (:class:`~onboard.io.fleet_wire.CommonClock`);
the clock check starts judging it over from its new stamps, and until it has, its rays carry the step as their
time sigma.  ``clock_memory_dropped`` (WARNING): a vehicle whose stamps the clock check refuses (``clock_off``) sent
a track without one; the ``UTC - boot`` offset remembered from those stamps is dropped and its unstamped frames are
timed by their arrival (within the pairing window its remembered rays take the check's error as their time sigma).
A vehicle is one once a track of it parses; ``MAX_VEHICLES`` (64) are kept at most.  The zenoh options are
:mod:`onboard.app.watch`'s (the daemon's names), and so is their default, which is not the daemon's: with none given it
connects to ``tcp/127.0.0.1:7447``.  Like the daemon it dials no peer that gossip names (:func:`zenoh_settings`;
``--zenoh-gossip-autoconnect`` does): daemons that are peers of one router reach it only if it dials them, or if it
is that router, or a client of it.

Threads: zenoh's callback only queues ``(key, payload, arrival time)``; one loop drains the queue, adds
every ray, then solves each touched target that is due once and publishes: due when every live vehicle's
frame of the newest camera period is in, or a vehicle is ``max_defer_s`` (50 ms) late on the fleet clock
(:meth:`~onboard.estimation.fleet_tracker.FleetTracker.due`), or the queue has been idle for 0.1 s.  Eight vehicles
at 30 Hz then cost one solve per period instead of about two, at no latency from the later frame.
Bad input never stops it and never becomes a fused point: it is counted by reason and logged at most once per
``--reject-log-interval-s`` per reason: ``bad_vehicle_name`` (a key chunk that is no daemon's vehicle name: no
output key could carry it), ``track_too_large`` (a payload over ``MAX_TRACK_BYTES``, 64 KiB, refused unparsed),
``not_json``, ``bad_track`` (the schema's reader names the key; an origin's altitude
outside ``ORIGIN_ALT_RANGE_M`` too), ``vehicle_not_configured`` (a vehicle outside ``--vehicles``, a WARNING naming a close
configured name: a name mistyped there shows), ``too_many_vehicles`` (a new name while ``MAX_VEHICLES`` are heard and none is silent; a
silent one is forgotten to make room), ``bad_time_unix_us``, ``no_origin``, ``stale`` /
``future`` (common time more than ``--max-age-s`` before or after this machine's clock), ``stamp_jump`` (a stamp
whose ``UTC - boot`` offset jumped from its vehicle's: held until the next stamps say glitch or step,
:class:`~onboard.io.fleet_wire.CommonClock`), ``camera_far`` / ``camera_jump`` (a camera no vehicle of the fleet can
be at: :class:`~onboard.io.fleet_wire.StreamCheck`), ``run_returned`` (a track of an earlier daemon run than the
vehicle's newest ``run_id``: a second daemon under the name), ``time_sigma`` (a time sigma above ``--max-time-sigma-ms``: the
track's ``time_unix_sigma_us``, or what the clock check finds; the log line says which), ``sigma_below_floor`` (a
line-of-sight sigma below :data:`~onboard.estimation.fleet.MIN_BEARING_SIGMA_RAD`), ``clock_off`` (a vehicle the
clock check names, off the others by more than the pairing window: its rays could not pair and would move a target),
``ray_name_clash`` (DEBUG: a vehicle name two vehicles share, below), ``ray_clock_unjudged`` (DEBUG: a stamped
vehicle's ray before the clock check's verdict on it, at most ``ClockConsistency.judging_max_s``), ``ray_stale``, ``ray_out_of_order`` (a ray not
newer than its object's last, among them a message the link reordered), ``duplicate`` (a seq heard again:
redelivered or replayed; from a camera elsewhere it is a second vehicle's, ``camera_jump``), ``inbox_full`` (a flood
beyond ``INBOX_MAX``), ``receive_error`` (a message that failed in a way no check above names: counted, the loop goes
on); ``no_line_of_sight`` (a track without a target),
``ray_not_measured`` (a line of sight whose track says ``measurement_valid`` false: a coasting tracker's prediction,
not a measurement; a track without the key is read as false, as the schema's reader does), ``ray_of_ended_object``
(a late ray of an object its vehicle's track has left) and the tracker's events are counted at DEBUG level, but
``ray_unpaired`` (WARNING: a ray of an object that has been in no fleet target for ``FleetConfig.unpaired_after_s``,
1 s: its vehicle's lines of sight are taken and fused into nothing; the line names the vehicle and the nearest
miss) and ``attitude_bias_above_prior`` (a solve that found a vehicle's rays off by a constant beyond its attitude-bias
prior and fused them with the bias they suggest, counted per solve; WARNING once per vehicle, naming
``--vehicle-noise NAME:attitude_bias_deg=..`` with that value).  A frame refused as stale or future, or held as a stamp jump, is no evidence about its vehicle's clock: the
clock check (below) never sees it.  The status lists refusals under ``rejected`` and events (:data:`EVENTS`) under
``events``.

A vehicle whose tracks state a new ``run_id`` (its daemon restarted: object ids start again) is
``vehicle_restarted`` (INFO): its objects leave their targets at once rather than lend their old targets to the new
run's objects of the same ids.

Name clash: when the tracks under one name interleave two streams (``seq`` / ``time_boot_us`` back and forth,
the camera jumping farther than a vehicle flies, two ``run_id`` taking turns: :class:`~onboard.io.fleet_wire.StreamCheck`), ``name_clash`` is
counted and warned once naming the vehicle and the remedy, the vehicle's objects leave their targets and its rays
stay out until the clash clears (``name_clash_cleared``, INFO); the status lists it under ``name_clash``.

Noise: ``--attitude-bias-deg`` / ``--camera-white-m`` (> 0) / ``--camera-offset-m`` for every vehicle, and
``--vehicle-noise`` for one vehicle's keys where they differ (e.g. ``uav2:attitude_bias_deg=0.5``).  A vehicle's
attitude-bias prior (the share of each ray's published sigma the solve takes as a constant common to its rays, not
white noise) is, from its newest ray on: ``--vehicle-noise NAME:attitude_bias_deg=..`` where that names it (the
operator's word wins; a track stating a value more than :data:`~onboard.app.fuse_noise.BIAS_APART_FACTOR` (1.5) from it is warned of once,
naming both), else what its tracks state (``los_sigma_bias_deg``: its daemon's
``estimator.attitude_bias_sigma_deg``), else ``--attitude-bias-deg`` (a daemon before the key).  Said at INFO once per
vehicle and again if it changes; the status gives each vehicle's under ``attitude_bias_prior``: ``{deg, source,
stated_deg}`` with ``source`` ``vehicle_noise`` | ``track`` | ``attitude_bias_deg`` and ``stated_deg`` what its newest
track stated (null: nothing).  A vehicle whose rays showed an attitude bias beyond its prior
(``attitude_bias_above_prior``) is listed in the status under ``attitude_bias_deg`` with the bias its rays suggested
last, deg.

Exit codes: 0 after ``--seconds`` or on SIGTERM; 130 on Ctrl-C; 2 for invalid options or a session that
cannot open (one line on stderr).
"""

from __future__ import annotations

import contextlib
import difflib
import json
import logging
import math
import queue
import signal
import sys
import threading
import time
from collections.abc import Collection, Sequence

import numpy as np

from onboard.app.fuse_args import build_parser, check_names, zenoh_settings
from onboard.app.fuse_noise import BiasPriors, bias_named, noise_models
from onboard.app.logs import setup_logging
from onboard.core.counters import RejectCounter
from onboard.core.errors import InputError, IrtrackError
from onboard.core.frames import GeodeticOrigin
from onboard.estimation.fleet import (
    MIN_BEARING_SIGMA_RAD,
    FleetConfig,
    Ray,
    VehicleNoise,
    fleet_verdict,
    triangulate,
)
from onboard.estimation.fleet_tracker import FleetTracker
from onboard.estimation.map_estimator import NoiseModel
from onboard.io.fleet_wire import (
    FLEET_NAME,
    FLEET_TRACK_ENCODING,
    MAX_CAMERA_DISTANCE_M,
    TRACKS_KEY_EXPR,
    ClockConsistency,
    CommonClock,
    StreamCheck,
    TimedTrack,
    fleet_track_json,
    fleet_track_key,
    parse_track,
    ray_from_track,
    vehicle_fleet_track_key,
    vehicle_from_track_key,
)
from onboard.io.zenoh_session import check_vehicle_name, open_session

__all__ = ["FLEET_STATUS_SCHEMA", "EVENTS", "Fusion", "build_parser", "zenoh_settings", "main", "warm_up"]

log = logging.getLogger(__name__)

FLEET_STATUS_SCHEMA = "irtrack.fleet_status/1"
EXIT_OK, EXIT_CONFIG, EXIT_INTERRUPTED = 0, 2, 130
POLL_S = 0.1
#: track messages waiting for the main loop at most (a 3-vehicle fleet at 30 Hz sends ~90 a second): beyond, a flood,
#: the newest are dropped and counted (inbox_full) instead of growing memory without bound
INBOX_MAX = 3000
#: messages fused per turn of the main loop before it publishes what is due: a flood must not starve the output
MAX_PER_TURN = 300
#: a track message's size at most: a daemon's irtrack.track/2 is about 2 KB; parsing is paid per byte while zenoh's
#: thread waits for the interpreter, so one publisher of megabyte messages (5 MB at 10 Hz) stalled the whole fusion
MAX_TRACK_BYTES = 64 * 1024
#: a node that has received no track this long after its start says so, once
NOTHING_HEARD_S = 5.0
#: vehicles the fusion keeps state for at most: a new name beyond them takes the place of the longest silent one,
#: or is refused (too_many_vehicles) while none is silent, rather than growing the status, the per-vehicle outputs
#: and their publishers without bound
MAX_VEHICLES = 64
#: a vehicle silent this long is forgotten (vehicle_forgotten): out of the status and the per-vehicle outputs,
#: its place free for another
FORGET_AFTER_S = 600.0
#: a fleet frame set by the first vehicle heard (no --origin) and shared by no other yet is given up once another
#: vehicle's cameras have been refused as too far from it for this long (fleet_origin_moved) ...
REANCHOR_AFTER_S = 3.0
#: ... at most once in this long (and never back to a vehicle whose frame was given up): two vehicles that far apart
#: cannot be fused, and the frame must not flicker
REANCHOR_HOLD_S = 30.0


class Inbox:
    """The subscriber's track messages for the main loop (zenoh's threads put, the main loop takes): bounded at
    ``maxsize``; what does not fit is dropped and counted, for the main loop to report (:meth:`take_dropped`)."""

    def __init__(self, maxsize: int = INBOX_MAX) -> None:
        self._q: queue.Queue = queue.Queue(maxsize)
        self._lock = threading.Lock()
        self._dropped = 0

    def put(self, item: tuple) -> None:
        try:
            self._q.put_nowait(item)
        except queue.Full:
            with self._lock:
                self._dropped += 1

    def get(self, timeout_s: float | None = None) -> tuple | None:
        """The next message, waiting up to ``timeout_s`` (None: not at all); None when there is none."""
        try:
            return self._q.get(timeout=timeout_s) if timeout_s else self._q.get_nowait()
        except queue.Empty:
            return None

    def take_dropped(self) -> int:
        with self._lock:
            n, self._dropped = self._dropped, 0
        return n


def drain(inbox: Inbox, fusion: Fusion, first: tuple | None, limit: int = MAX_PER_TURN) -> int:
    """Fuse ``first`` and what else waits, ``limit`` messages at most; returns how many were fused."""
    n, item = 0, first
    while item is not None:
        try:
            fusion.receive(*item)
        except Exception as exc:  # noqa: BLE001 - one message the checks missed must not end the fusion
            fusion.counter.count("receive_error", f"{item[0]}: {type(exc).__name__}: {exc}")
        n += 1
        if n >= limit:
            break
        item = inbox.get()
    dropped = inbox.take_dropped()
    if dropped:
        fusion.counter.count(
            "inbox_full", f"{dropped} track messages dropped: more than the fusion keeps up with", n=dropped
        )
    return n


CLOCK_RECHECK_S = 0.1
#: the main loop judges silences (and forgets long-silent vehicles) this often, status messages or none
WATCH_INTERVAL_S = 1.0
#: counted reasons that are events, not refused input: the status lists them under ``events``, the rest under
#: ``rejected``
EVENTS = frozenset(
    {
        "vehicle_silent",
        "vehicle_back",
        "vehicle_forgotten",
        "vehicle_restarted",
        "fleet_origin_moved",
        "clock_inconsistent",
        "clock_step",
        "clock_memory_dropped",
        "name_clash",
        "name_clash_cleared",
        "target_created",
        "target_dropped",
        "object_left",
        "own_estimate_disagrees",
        "ray_unpaired",
        "attitude_bias_above_prior",
    }
)


class Fusion:
    """The fusion's step logic without sockets: :meth:`receive` takes one message (its key, payload and
    arrival time on this machine's UTC clock) and returns nothing; :meth:`flush` solves the targets touched
    since the last flush and returns the ``(key, payload dict)`` pairs to publish."""

    def __init__(
        self,
        tracker: FleetTracker,
        clock: CommonClock,
        vehicles: Sequence[str] | None = None,
        origin: GeodeticOrigin | None = None,
        max_age_s: float = 2.0,
        counter: RejectCounter | None = None,
        clock_check: ClockConsistency | None = None,
        silent_after_s: float = 1.0,
        stream_check: StreamCheck | None = None,
        max_time_sigma_s: float = 0.05,
        bias_named: Collection[str] = (),
    ) -> None:
        self.tracker = tracker
        self.clock = clock
        self.vehicles = None if not vehicles else frozenset(vehicles)
        self.origin = origin
        self.max_age_s = float(max_age_s)
        self.counter = counter or tracker.counter
        self.received = 0
        self.rays = 0
        self.published = 0
        self._touched: set[int] = set()
        self._seq = 0
        self._time_sources: dict[str, str] = {}
        self._origins: dict[str, GeodeticOrigin] = {}
        self._cameras: dict[str, np.ndarray] = {}
        self._objects: dict[str, tuple[int, float]] = {}  # each vehicle's newest object id and its newest ray time
        self.clock_check = clock_check if clock_check is not None else ClockConsistency()
        self.silent_after_s = float(silent_after_s)
        self._last_arrival: dict[str, float] = {}  # fusion clock, UTC s: the vehicle's newest track of any kind
        self._silent: set[str] = set()
        self._clock_flagged: set[str] = set()
        self.stream_check = stream_check if stream_check is not None else StreamCheck()
        self.max_time_sigma_s = float(max_time_sigma_s)
        self._clashing: set[str] = set()
        self._clock_refused: set[str] = set()
        self._clock_judged_at = -math.inf
        self._clock_far: dict[str, float] = {}
        self._clock_judged: frozenset[str] = frozenset()  # the vehicles the check had judged at that verdict
        self._stepped: dict[str, float] = {}  # vehicles whose UTC stepped (s, signed) and not judged since
        # the fleet frame's provenance: the vehicle whose ray set it (None: configured, or none yet), and whether
        # another vehicle's ray was accepted in it since (then it is the fleet's, and kept)
        self._origin_vehicle: str | None = None
        self._origin_shared = origin is not None
        self._far_since: dict[str, float] = {}  # vehicles refused camera_far since, while the frame is not shared
        self._frame_given_up: set[str] = set()  # vehicles whose frame was given up: they never move it again
        self._off_window: dict[str, int] = {}  # stamps in a row beyond --max-age-s of their arrival, by vehicle
        #: vehicles forgotten since the owner last looked (it drops what it keeps for them: their publishers)
        self.forgotten: list[str] = []
        self._reanchored_at = -math.inf
        #: each vehicle's attitude-bias prior (the operator's, its tracks', or the global option's)
        self.bias_priors = BiasPriors(tracker, bias_named)

    def _check_clashes(self, now_unix_s: float) -> list[str]:
        clashing = self.stream_check.clashing(now_unix_s)
        for v in clashing:
            if v not in self._clashing:
                self.counter.count(
                    "name_clash",
                    f"{v}: two vehicles publish as {v!r} (its tracks' seq / time_boot_us go back and forth, its "
                    "camera jumps farther than a vehicle flies, or two daemon runs take turns); its lines of sight are kept out of the fusion while "
                    "this lasts: give each vehicle its own name (the daemon's 'vehicle' setting)",
                    subject=v,
                )
                self.tracker.withdraw(v, "name clash")
        for v in sorted(self._clashing - set(clashing)):
            self.counter.count("name_clash_cleared", f"{v}: one stream again", level=logging.INFO, subject=v)
        self._clashing = set(clashing)
        return clashing

    def _clock_off(self, vehicle: str, now_unix_s: float) -> float | None:
        """How far ``vehicle``'s UTC is off the others' (s, positive: ahead; the whole disagreement, which with two
        vehicles the median's deviations split between them) when the clock check names it: its rays are timed wrong
        by that much while their time sigma says a fraction of a millisecond.  Beyond the pairing window they could
        not pair: kept out.  Within it they paired at the wrong place, confidently (docs/fleet.md gives the
        figures): their time sigma is widened to the deviation instead of shutting the vehicle out, since the check
        also names a vehicle whose link is slower by more than the tolerance (its latency floor, not its clock,
        differs), which would lose its rays for nothing."""
        # the verdict moves with the check's 10 s window: judged again every CLOCK_RECHECK_S, not on every ray
        # and at once for a vehicle judged since: its rays waited for this verdict (ClockConsistency.judging).  Not
        # for one the check cannot judge (too slow, or its stamps stopped and its offset is remembered): each of its
        # rays made the verdict over every vehicle again
        fresh = vehicle in self._clock_judged or not self.clock_check.judged(vehicle, now_unix_s)
        if not (now_unix_s - self._clock_judged_at < CLOCK_RECHECK_S and fresh):
            self._clock_judged_at = now_unix_s
            self._clock_far = self.clock_check.errors_s(now_unix_s)
            floors = self.clock_check.floors_s(now_unix_s)
            self._clock_judged = frozenset(floors)
            if len(floors) >= 2:  # judged again since its step: the check's verdict stands for it now
                for v in [v for v in self._stepped if v in floors]:
                    del self._stepped[v]
        return self._clock_far.get(vehicle)

    def _clock_stepped(self, key: str, vehicle: str, step_s: float) -> None:
        """``vehicle``'s UTC offset stepped by ``step_s``: which offset is right, the old or the new, only the clock
        check can say, from the new one's frames alone (the lowest arrival lag of the old ones would hide a step back
        for the check's whole window).  Until it has judged them, the vehicle's rays are as uncertain in time as the
        step."""
        self.counter.count(
            "clock_step",
            f"{key}: its time_unix_us stepped by {step_s * 1e3:+.1f} ms against its time_boot_us; its lines of sight "
            "carry that much time sigma until the clock check has judged its new UTC; check its UTC (SYSTEM_TIME)",
            subject=vehicle,
        )
        self.clock_check.forget(vehicle)
        self._stepped[vehicle] = step_s
        self._clock_far.pop(vehicle, None)
        self._clock_judged_at = -math.inf

    def receive(self, key: str, payload: bytes, arrival_unix_s: float) -> None:
        vehicle = vehicle_from_track_key(key)
        if vehicle is None:
            return  # the fusion's own output
        if self.vehicles is not None and vehicle not in self.vehicles:
            # not asked for: counted, not fused; a WARNING, since a name mistyped in --vehicles shows only here (its
            # vehicle then fuses nothing, and the others' rays read as unpaired)
            close = difflib.get_close_matches(vehicle, self.vehicles, n=1)
            hint = f" (did you mean {close[0]!r} in --vehicles? it is {vehicle!r} on the wire)" if close else ""
            self.counter.count(
                "vehicle_not_configured", f"{key}: not one of --vehicles {' '.join(self.vehicles)}{hint}"
            )
            return
        self.received += 1
        try:
            check_vehicle_name(vehicle)
        except IrtrackError as exc:  # zenoh keys take names no daemon sends and no output key can carry
            self.counter.count("bad_vehicle_name", f"{key}: {exc}")
            return
        if len(payload) > MAX_TRACK_BYTES:  # refused unparsed: its parse would be the cost
            self.counter.count("track_too_large", f"{key}: {len(payload)} bytes > {MAX_TRACK_BYTES}", subject=vehicle)
            return
        try:
            obj = json.loads(payload)
        except (ValueError, UnicodeDecodeError, RecursionError) as exc:  # (RecursionError: nested too deep)
            self.counter.count("not_json", f"{key}: {type(exc).__name__}: {exc}")
            return
        if not isinstance(obj, dict):
            self.counter.count("bad_track", f"{key}: expected a JSON object, got {type(obj).__name__}")
            return
        try:
            track, time_unix_us = parse_track(obj)
        except InputError as exc:
            reason = "bad_time_unix_us" if "time_unix_us" in str(exc) else "bad_track"
            self.counter.count(reason, f"{key}: {exc}")
            return
        if track.vehicle != vehicle:
            self.counter.count("bad_track", f"{key}: vehicle {track.vehicle!r} on another vehicle's key")
            return
        if not self._heard(vehicle, arrival_unix_s):
            return
        reading = self.clock.place(vehicle, track.time_boot_us, time_unix_us, arrival_unix_s)
        off_s = self._clock_off(vehicle, arrival_unix_s) if reading.source == "remembered" else None
        if off_s is not None and abs(off_s) > self.tracker.config.pair_max_dt_s:
            # the offset remembered is the one of the stamps the clock check refuses (clock_off): as far off as they
            # were, and fused, with no stamp left to refuse; the frame's arrival times it within the vehicle's latency
            # floor instead (within the pairing window its rays take the error as their time sigma, below)
            self.clock.forget_stamps(vehicle)
            self.counter.count(
                "clock_memory_dropped",
                f"{key}: no time_unix_us, and the UTC - boot offset remembered from its stamps is the one the clock "
                f"check finds {off_s * 1e3:+.0f} ms off the other vehicles': its frames are timed by their arrival",
                subject=vehicle,
            )
            reading = self.clock.place(vehicle, track.time_boot_us, time_unix_us, arrival_unix_s)
        if reading.step_s is not None:
            self._clock_stepped(key, vehicle, reading.step_s)
        # every frame times the vehicle's clock, with a target or not; but not a stamp whose UTC - boot offset jumped
        # from the vehicle's (a glitch, or the first of a step), which would set the vehicle's latency floor for the
        # check's whole window, nor one so far off that it is refused as stale or future below: such stamps count
        # from the second in a row, a clock that is off, which the check is there to name
        if time_unix_us is not None and reading.held_jump_s is None:
            off_window = abs(time_unix_us / 1e6 - arrival_unix_s) > self.max_age_s
            run = self._off_window[vehicle] = self._off_window.get(vehicle, 0) + 1 if off_window else 0
            if run != 1:
                self.clock_check.add(vehicle, time_unix_us / 1e6, arrival_unix_s)
        los = track.los
        if los is None or track.origin is None or not track.measurement_valid:
            self._restarted(key, track, self.stream_check.add(vehicle, track.seq, track.time_boot_us, 0.0, None,
                                                              arrival_unix_s, track.run_id))  # fmt: skip
            if los is None:
                self.counter.count("no_line_of_sight", key, level=logging.DEBUG)
            elif not track.measurement_valid:
                # a coasting tracker's line of sight is to where it predicts the object, not where it saw it: fused,
                # it holds the target to that prediction while it manoeuvres
                self.counter.count(
                    "ray_not_measured", f"{key}: {track.state}, measurement_valid false", level=logging.DEBUG
                )
            else:
                self.counter.count("no_origin", f"{key}: a line of sight without its origin cannot be placed")
            return
        # the instant its line of sight is of: the stamp minus the camera clock's compensated lateness (tens to
        # hundreds of ms, a ray that far off in time pairs with the others' at the wrong place)
        t_s, source = reading.t_s - track.compensated_us * 1e-6, reading.source
        if t_s < arrival_unix_s - self.max_age_s:
            self.counter.count(
                "stale", f"{key}: frame {arrival_unix_s - t_s:.3f} s old ({source} time)", subject=vehicle
            )
            return
        if t_s > arrival_unix_s + self.max_age_s:
            self.counter.count(
                "future", f"{key}: frame {t_s - arrival_unix_s:.3f} s ahead ({source} time)", subject=vehicle
            )
            return
        if reading.held_jump_s is not None:  # timed by a clock the vehicle may not have: a glitch timed it wrong
            self.counter.count(
                "stamp_jump",
                f"{key}: its time_unix_us puts UTC - boot {reading.held_jump_s * 1e3:+.1f} ms off the vehicle's "
                "recent stamps: held out until its next stamps say whether its clock stepped",
                subject=vehicle,
            )
            return
        # the fleet's frame is the first accepted ray's origin: a message refused below must not set it (a stray
        # origin far from the fleet would make every later camera 'far' for the life of the process)
        origin = self.origin if self.origin is not None else track.origin
        # the ray's time sigma and what it came from: a refusal names what happened, not a field never sent
        time_sigma_s, why = 0.0, "its time_unix_sigma_us"
        if source == "vehicle" and track.time_unix_sigma_us is not None:
            time_sigma_s = track.time_unix_sigma_us / 1e6
        elif source == "remembered":  # an old offset: its drift since (past --max-time-sigma-ms, refused)
            time_sigma_s = self.clock.remembered_sigma_s(vehicle, track.time_boot_us)
            why = "the drift of its boot clock since its last track with a time_unix_us"
        off = self._clock_off(vehicle, arrival_unix_s) if source in ("vehicle", "remembered") else None
        step = self._stepped.get(vehicle) if source == "vehicle" else None
        if step is not None and abs(step) > time_sigma_s:
            time_sigma_s = abs(step)
            why = f"its UTC stepped by {step * 1e3:+.0f} ms and the clock check has not judged it since"
        if off is not None and abs(off) <= self.tracker.config.pair_max_dt_s:
            if abs(off) > time_sigma_s:  # named, within the pairing window: as uncertain as it is off
                time_sigma_s = abs(off)
                why = f"the clock check finds its time_unix_us {off * 1e3:+.0f} ms off the other vehicles'"
            off = None
        if source == "vehicle" and self.clock_check.judging(vehicle, arrival_unix_s):  # (a clock off is named then)
            self.counter.count("ray_clock_unjudged", f"{key}: its clock not judged yet", level=logging.DEBUG)
            return
        try:
            ray = ray_from_track(TimedTrack(track, t_s, source, time_sigma_s), origin)
        except (InputError, ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:
            self.counter.count("bad_track", f"{key}: {type(exc).__name__}: {exc}")
            return
        implausible = self._restarted(
            key,
            track,
            self.stream_check.add(
                vehicle, track.seq, track.time_boot_us, t_s, ray.p_cam_ned_m, arrival_unix_s, track.run_id
            ),
        )
        if vehicle in self._check_clashes(arrival_unix_s):
            self.counter.count("ray_name_clash", f"{key}: its name is shared", level=logging.DEBUG)
            return
        if implausible is not None:
            where = np.round(ray.p_cam_ned_m, 1).tolist()
            self.counter.count(
                implausible,
                f"{key}: camera at {where} m in the fleet frame (seq {track.seq}, run_id {track.run_id})",
                subject=vehicle,
            )
            if implausible == "camera_far":
                self._reanchor_if_alone(vehicle, track.origin, arrival_unix_s)
            return
        if not self._ray_plausible(key, ray, why):
            return
        if time_unix_us is not None:
            if off is not None:
                self.counter.count(
                    "clock_off",
                    f"{key}: the clock check finds its time_unix_us {off * 1e3:+.0f} ms off the other vehicles', "
                    "beyond the pairing window",
                    subject=vehicle,
                )
                if vehicle not in self._clock_refused:  # what it sent before it was judged goes too
                    self._clock_refused.add(vehicle)
                    self.tracker.withdraw(vehicle, "its clock is off")
                return
            self._clock_refused.discard(vehicle)
        # a daemon's track is of one object at a time: a newer ray of a new id ends the last one's stay in its target
        # at once (else a flickering id kept the vehicle 'live' in its old target, and its new object made a second
        # one); a late ray of an object already ended is of no target any more
        last = self._objects.get(vehicle)
        if last is not None and last[0] != ray.object_id:
            if ray.t_s < last[1]:
                self.counter.count("ray_of_ended_object", f"{key}: object {ray.object_id}, late", level=logging.DEBUG)
                return
            self.tracker.retire(vehicle, last[0], f"its vehicle's track moved to object {ray.object_id}")
        self._objects[vehicle] = (ray.object_id, max(ray.t_s, last[1] if last is not None else ray.t_s))
        if self.origin is None:
            self.origin = origin
            self._origin_vehicle = vehicle
            log.info("fleet origin: %s's, %s", vehicle, origin)
        elif vehicle != self._origin_vehicle:
            self._origin_shared = True
        self._far_since.pop(vehicle, None)
        self._time_sources[vehicle] = source
        self._origins[vehicle] = track.origin
        self._cameras[vehicle] = np.asarray(los.p_cam_ned_m)
        self.bias_priors.take(vehicle, los.sigma_bias_deg)
        self.rays += 1
        tid = self.tracker.add(ray)
        if tid is not None:
            self._touched.add(tid)

    def _heard(self, vehicle: str, arrival_unix_s: float) -> bool:
        """Note a parsed track of ``vehicle`` (silent no more); False for a new vehicle beyond ``MAX_VEHICLES``
        while none of them is silent (a silent one, the longest silent, is forgotten to make room: names that
        sent once, a typo's or a flood's, must not lock the real vehicles out for ``FORGET_AFTER_S``)."""
        if vehicle not in self._last_arrival and len(self._last_arrival) >= MAX_VEHICLES:
            oldest = min(self._last_arrival, key=self._last_arrival.__getitem__)
            quiet_s = arrival_unix_s - self._last_arrival[oldest]
            if quiet_s <= self.silent_after_s:
                self.counter.count("too_many_vehicles", f"{vehicle}: {MAX_VEHICLES} vehicles are fused at most")
                return False
            self._forget_vehicle(oldest, f"silent for {quiet_s:.1f} s, its place given to {vehicle}")
        self._last_arrival[vehicle] = arrival_unix_s
        if vehicle in self._silent:
            self._silent.discard(vehicle)
            self.counter.count("vehicle_back", f"{vehicle}: tracks again", level=logging.INFO, subject=vehicle)
        return True

    def _restarted(self, key: str, track, verdict: str | None) -> str | None:
        """``verdict`` of :meth:`StreamCheck.add`, but None for ``restarted``: the vehicle's daemon restarted (a new
        ``run_id``), so its object ids start again and its old objects leave their targets now, said once."""
        if verdict != "restarted":
            return verdict
        self.tracker.withdraw(track.vehicle, "its daemon restarted")
        self.counter.count(
            "vehicle_restarted",
            f"{key}: a new daemon run (run_id {track.run_id}): its objects start again",
            level=logging.INFO,
            subject=track.vehicle,
        )
        return None

    def _reanchor_if_alone(self, vehicle: str, origin: GeodeticOrigin, now_unix_s: float) -> None:
        """Give up a fleet frame that only the vehicle which set it has been accepted in, once ``vehicle``'s cameras
        have been too far from it for ``REANCHOR_AFTER_S``: the first vehicle heard may be the stray one (a
        simulator on the fleet's network, a vehicle with a wrong position), and every real vehicle would then be
        refused for the life of the process.  ``vehicle``'s own ``origin`` becomes the frame, so the stray cannot
        take it back by being heard first again; nor can a vehicle whose frame was given up ask for it again
        (with one real vehicle and one stray, which is which cannot be told: the frame moves once, not back and
        forth)."""
        if self._origin_shared or self.origin is None or vehicle == self._origin_vehicle:
            return
        if vehicle in self._frame_given_up:
            return
        since = self._far_since.setdefault(vehicle, now_unix_s)
        if now_unix_s - since < REANCHOR_AFTER_S or now_unix_s - self._reanchored_at < REANCHOR_HOLD_S:
            return
        old = self._origin_vehicle
        self.counter.count(
            "fleet_origin_moved",
            f"the fleet frame was {old}'s origin {self.origin}, which no other vehicle has been placed near: {vehicle}'s "
            f"cameras were over {MAX_CAMERA_DISTANCE_M / 1e3:.0f} km from it for {now_unix_s - since:.1f} s; the frame "
            f"is {vehicle}'s origin now (pin it with --origin, or name the fleet's vehicles with --vehicles)",
        )
        if old is not None:
            self.tracker.withdraw(old, "the fleet frame moved")
            self._frame_given_up.add(old)
        for v in self._last_arrival:  # the streams' cameras are in the old frame
            self.stream_check.forget(v)
        self.origin, self._origin_vehicle = origin, vehicle
        self._far_since.clear()
        self._reanchored_at = now_unix_s

    def _forget(self, now_unix_s: float) -> None:
        """Drop what is kept for vehicles silent for ``FORGET_AFTER_S``."""
        for v in [v for v, t in self._last_arrival.items() if now_unix_s - t > FORGET_AFTER_S]:
            self._forget_vehicle(v, f"no track for {now_unix_s - self._last_arrival[v]:.0f} s")

    def _forget_vehicle(self, v: str, why: str) -> None:
        """Drop what is kept for vehicle ``v`` (``vehicle_forgotten``, saying ``why``)."""
        self.counter.count("vehicle_forgotten", f"{v}: {why}", level=logging.INFO, subject=v)
        for kept in (
            self._last_arrival,
            self._time_sources,
            self._origins,
            self._cameras,
            self._objects,
            self._far_since,
            self._clock_far,
            self._stepped,
            self._off_window,
        ):
            kept.pop(v, None)
        for named in (self._silent, self._clock_refused, self._clock_flagged):
            named.discard(v)
        self.bias_priors.forget(v)
        self.tracker.withdraw(v, "forgotten")
        self.stream_check.forget(v)
        self.clock_check.forget(v)
        self.clock.forget(v)
        self.forgotten.append(v)

    def _ray_plausible(self, key: str, ray: Ray, time_sigma_why: str) -> bool:
        """False (counted) for a ray the solve must not take; ``time_sigma_why``: what its time sigma came from."""
        if ray.time_sigma_s > self.max_time_sigma_s:
            self.counter.count(
                "time_sigma",
                f"{key}: a time sigma of {ray.time_sigma_s * 1e3:.1f} ms ({time_sigma_why}) > --max-time-sigma-ms "
                f"{self.max_time_sigma_s * 1e3:g}",
                subject=key,
            )
            return False
        if min(ray.sigma_az_rad, ray.sigma_el_rad) < MIN_BEARING_SIGMA_RAD:
            self.counter.count(
                "sigma_below_floor",
                f"{key}: line-of-sight sigma {min(ray.sigma_az_rad, ray.sigma_el_rad):.3g} rad "
                f"< {MIN_BEARING_SIGMA_RAD:g} rad: no camera measures that well",
                subject=key,
            )
            return False
        return True

    def flush(self, force: bool = False) -> list[tuple[str, dict]]:
        """Solve the touched targets that are due (:meth:`FleetTracker.due`; all of them with ``force``)."""
        out: list[tuple[str, dict]] = []
        if self.origin is None:
            return out
        due = {t for t in self._touched if force or self.tracker.due(t)}
        self._touched -= due
        for tid in sorted(due):
            est = self.tracker.solve(tid)
            if est is None:
                continue
            self._seq += 1
            out.append((fleet_track_key(), fleet_track_json(est, self.origin, self._seq, self._time_sources)))
            for vehicle, origin in self._origins.items():
                payload = fleet_track_json(
                    est,
                    self.origin,
                    self._seq,
                    self._time_sources,
                    vehicle=vehicle,
                    vehicle_origin=origin,
                    vehicle_camera_ned_m=self._cameras.get(vehicle),
                )
                out.append((vehicle_fleet_track_key(vehicle), payload))
        self.published += len(out)
        return out

    def watch(self, now_unix_s: float) -> tuple[list[str], dict[str, float], list[str]]:
        """(silent vehicles, clock deviations s, clock-inconsistent vehicles) now; each change is counted."""
        self._forget(now_unix_s)
        silent = {v for v, t in self._last_arrival.items() if now_unix_s - t > self.silent_after_s}
        for v in sorted(silent - self._silent):
            live = sorted(set(self._last_arrival) - silent)
            rest = f"fusing {', '.join(live)}" if live else "no vehicle left: nothing is fused until one is heard again"
            self.counter.count(
                "vehicle_silent", f"{v}: no track for {now_unix_s - self._last_arrival[v]:.1f} s; {rest}", subject=v
            )
        self._silent = silent
        devs = self.clock_check.deviations_s(now_unix_s)
        flagged = self.clock_check.inconsistent(now_unix_s)
        floors = self.clock_check.floors_s(now_unix_s)
        for v in flagged:
            if v not in self._clock_flagged:
                others = ", ".join(f"{o} {f * 1e3:.1f}" for o, f in floors.items() if o != v)
                self.counter.count(
                    "clock_inconsistent",
                    f"{v}: its frames' shortest arrival lag is {floors[v] * 1e3:.1f} ms (others: {others} ms): its "
                    "time_unix_us is off; check its UTC (SYSTEM_TIME) mapping",
                    subject=v,
                )
        self._clock_flagged = set(flagged)
        self._check_clashes(now_unix_s)
        return sorted(silent), devs, flagged

    def status(self, now_unix_s: float | None = None) -> dict:
        """The ``irtrack.fleet_status/1`` dict (module docstring); ``now_unix_s``: the fusion's clock (UTC s)."""
        now_s = time.time() if now_unix_s is None else now_unix_s
        silent, devs, flagged = self.watch(now_s)
        counts = self.counter.counts
        return {
            "schema": FLEET_STATUS_SCHEMA,
            "received": self.received,
            "rays": self.rays,
            "published": self.published,
            "targets": len(self.tracker.targets),
            "vehicles": dict(sorted(self._time_sources.items())),
            "silent": silent,
            "clocks": {v: round(d * 1e3, 2) for v, d in devs.items()},
            "latency_floor_ms": {v: round(f * 1e3, 2) for v, f in self.clock_check.floors_s(now_s).items()},
            "clock_inconsistent": flagged,
            "name_clash": sorted(self._clashing),
            "attitude_bias_deg": {
                v: round(math.degrees(b), 3) for v, b in sorted(self.tracker.biases_above_prior_rad.items())
            },
            "attitude_bias_prior": self.bias_priors.status(),
            "rejected": {k: n for k, n in counts.items() if k not in EVENTS},
            "events": {k: n for k, n in counts.items() if k in EVENTS},
        }


def warm_up(config: FleetConfig) -> None:
    """One solve and verdict of a synthetic pair before the first real one: the first call of each linear
    algebra and special function pays its dispatch set-up, which would land on the first fleet track's latency."""
    p = np.array([800.0, 0.0, -100.0])
    rays = []
    for i, y in enumerate((-100.0, 100.0)):
        c = np.array([0.0, y, -100.0])
        for k in range(2):
            rays.append(Ray(f"warm{i}", 1, k / 30, c, (p - c) / np.linalg.norm(p - c), 1e-3, 1e-3))
    fleet_verdict(triangulate(rays, VehicleNoise(NoiseModel()), p, config), rays, config)


def main(argv: Sequence[str] | None = None) -> int:
    try:
        return _main(argv)
    except KeyboardInterrupt:  # before the loop (the estimators' warm-up) or while closing the session
        print("interrupted: no fusion running yet, or its session closing", file=sys.stderr)
        return EXIT_INTERRUPTED


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    check_names(parser, args)
    setup_logging(args.log_level, "text")  # a service beside the daemons: their log lines, one parser for both
    noise = noise_models(args)
    config = FleetConfig()
    warm_up(config)
    counter = RejectCounter(log_interval_s=args.reject_log_interval_s, logger=log)
    fusion = Fusion(
        FleetTracker(config, noise, counter),
        CommonClock(dict(args.clock_offset)),
        vehicles=args.vehicles,
        origin=args.origin,
        max_age_s=args.max_age_s,
        clock_check=ClockConsistency(tolerance_s=args.clock_tolerance_ms / 1e3),
        silent_after_s=args.silent_after_s,
        max_time_sigma_s=args.max_time_sigma_ms / 1e3,
        bias_named=bias_named(args.vehicle_noise),
    )
    stop = threading.Event()
    session = None
    status_pub = None
    try:
        settings = zenoh_settings(args)
        session = open_session(settings)
        inbox = Inbox()
        session.declare_subscriber(
            TRACKS_KEY_EXPR, lambda s: inbox.put((str(s.key_expr), s.payload.to_bytes(), time.time()))
        )
        publishers: dict[str, object] = {}
        status_pub = session.declare_publisher(
            f"irtrack/{FLEET_NAME}/status", encoding=f"application/json;{FLEET_STATUS_SCHEMA}"
        )
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
        which = "all vehicles" if args.vehicles is None else " ".join(args.vehicles)
        where = list(settings.connect + settings.listen) + (
            [f"--zenoh-config {settings.config_file}"] if settings.config_file is not None else []
        )
        # where this node listens, said at start and again if it hears nothing
        endpoints = ", ".join(where) or "zenoh's defaults"
        where_text = f"{endpoints}, dialing gossiped peers {'on' if settings.gossip_autoconnect else 'off'}"
        log.info("fusing %s from %s on %s", which, TRACKS_KEY_EXPR, where_text)
        deadline = None if args.seconds == 0 else time.monotonic() + args.seconds
        next_status = time.monotonic() + args.status_interval_s
        next_watch = time.monotonic() + WATCH_INTERVAL_S
        # a node that hears nothing said nothing until its stop line's zeros: said once, with where it listens
        quiet_until: float | None = time.monotonic() + NOTHING_HEARD_S
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            item = inbox.get(POLL_S)
            idle = item is None
            if item is not None:
                quiet_until = None
            elif quiet_until is not None and time.monotonic() >= quiet_until:
                quiet_until = None
                log.warning(
                    "nothing received on %s for %.0f s (%s): check that the daemons run and publish, and that this "
                    "node reaches them (a peer that only dials a router hears the daemons behind it only with "
                    "--zenoh-gossip-autoconnect, or run this node as the router: docs/fleet.md)",
                    TRACKS_KEY_EXPR,
                    NOTHING_HEARD_S,
                    where_text,
                )
            drain(inbox, fusion, item)
            for key, payload in fusion.flush(force=idle):  # idle: whatever is pending, due or not
                pub = publishers.get(key)
                if pub is None:
                    pub = publishers[key] = session.declare_publisher(key, encoding=FLEET_TRACK_ENCODING)
                pub.put(json.dumps(payload, separators=(",", ":"), allow_nan=False))  # type: ignore[attr-defined]
            if time.monotonic() >= next_watch:  # silences and forgetting, whether or not a status is published
                next_watch += WATCH_INTERVAL_S
                fusion.watch(time.time())
            for vehicle in fusion.forgotten:
                pub = publishers.pop(vehicle_fleet_track_key(vehicle), None)
                if pub is not None:
                    with contextlib.suppress(Exception):  # a publisher already gone: nothing to release
                        pub.undeclare()  # type: ignore[attr-defined]
            fusion.forgotten.clear()
            if args.status_interval_s > 0 and time.monotonic() >= next_status:
                next_status += args.status_interval_s
                status_pub.put(json.dumps(fusion.status(), separators=(",", ":")))
        status_pub.put(json.dumps(fusion.status(), separators=(",", ":")))
        log.info("stopped: %s", json.dumps(fusion.status()))
        return EXIT_OK
    except IrtrackError as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_CONFIG
    except KeyboardInterrupt:  # the last status and the counts, as on SIGTERM, then 130
        if status_pub is None:  # the session was still opening
            print("interrupted while the zenoh session opened: nothing was fused", file=sys.stderr)
        else:
            with contextlib.suppress(Exception):  # a session already closing: the log line still says it
                status_pub.put(json.dumps(fusion.status(), separators=(",", ":")))
            log.info("stopped: %s", json.dumps(fusion.status()))
        return EXIT_INTERRUPTED
    finally:
        if session is not None:
            session.close()
