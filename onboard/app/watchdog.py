"""Nothing fails silently: conditions an operator must fix, each warned once, naming what to check.

Pure: no clocks, no sockets.  The service feeds a :class:`Watchdog` with the time (monotonic
seconds, its own clock) and what it saw; tests feed it a fake clock.  Each condition has a code:

``no_frames``
    No IR frame received for ``input_timeout_s`` (5 s), from the start or since the last one.  The
    message names the zenoh key subscribed to and the session's endpoints, mode and scouting.
``no_mavlink``
    No MAVLink message for ``input_timeout_s``; the message names the connection string.
``zenoh_unconnected``
    The zenoh session dials endpoints (``zenoh.connect``) and has had no router and no peer for ``input_timeout_s``:
    what the daemon publishes reaches no one there (a router killed: the daemon went on tracking in silence while the
    ground saw nothing), and a camera behind it sends nothing.  Cleared by the first router or peer.
``frame_size``
    A frame whose size is not the configured camera's (refused as ``frame_dims_mismatch``); the
    message names both sizes.  Cleared by a frame of the right size once ``FRAME_SIZE_CLEAR_S`` (1 s)
    have passed without another: a second camera of another size publishing on the key between the
    configured one's frames keeps it raised, rather than raising and clearing it with every frame.
``frame_sources``
    Two (or more) senders publish frames on the frame key, each numbering its own: their sequence numbers interleave
    (:attr:`onboard.pipeline.admission.ArrivalGaps.returns`, frames that come back to a numbering seen before, at
    least ``FRAME_SOURCES_MIN_RETURNS`` (6) within ``FRAME_SOURCES_WINDOW_S`` (5 s)).  Frames of the same size and
    encoding are all taken, each as the next frame of one stream: the track alternates between the two views (each
    other frame counted ``frame_sequence_reset``), and none is known to be the configured camera's (its mount, its
    intrinsics), so the daemon withholds lines of sight and 3-D positions while it holds.  A sender that restarts
    its numbering once leaves its old one for
    good and is not warned.  Checked every 0.5 s, so raised within a second of the interleaving; cleared
    ``FRAME_SOURCES_CLEAR_S`` (5 s) after the last return.  A second sender slower than about one frame per
    1.7 s (each of its frames makes two returns, to its numbering and back: 6 in 5 s) is not warned, and one slower than one frame per
    ``forget_after`` frames of the other (``ArrivalGaps``: 10 s at 30 Hz) is forgotten between its frames: each of
    its frames then reads as a sender restart (``frame_sequence_reset``, counted).
``camera_mismatch``
    The residuals are persistently inconsistent with the configured camera: every estimate for at
    least ``residual_persist_s`` (5 s, at least ``residual_min_samples`` estimates, so about five
    model selections at the estimator's 1 Hz) has ``residual_rms_norm`` above
    ``residual_threshold`` (3: under the configured noise model the statistic is about 1 and
    stays below 3 with overwhelming probability).  Mount angles or intrinsics wrong are suspected.
    One estimate at or below the threshold starts the count again; estimates without the figure
    (None/NaN) neither count nor reset.
``zoom_mismatch``
    The IR frames state a zoom (IRF1's zoom field, relative to the zoom ``camera.intrinsics`` were calibrated at)
    more than :data:`~onboard.core.irframe.ZOOM_TOLERANCE` (0.5 %) from 1.0: every bearing made from the
    intrinsics is off by the zoom's ratio (a 2x zoom of P1's camera: lines of sight 1.5 deg off at a stated
    0.12 deg), which the residuals do not show.  The pipeline withholds each such frame's line of sight and 3-D
    position itself (:class:`~onboard.pipeline.frame_pipeline.FramePipeline`); this names it.  Fed with every frame
    taken, raised by the first such frame and cleared by the first frame at 1.0 or stating none.

``gimbal_mismatch``
    The configured mount and the vehicle disagree about a gimbal: GIMBAL_DEVICE_ATTITUDE_STATUS (#285)
    arrives although ``camera.mount.gimballed`` is false (the camera's attitude is then taken as the
    airframe's plus the fixed mount: 3-D positions off by the gimbal's angles, ~100 % of range in the
    reference scenarios), or none has arrived ``input_timeout_s`` after the first telemetry although it
    is true (no frame gets a pose).  The residuals cannot show a mount error (a constant pitch offset
    of the camera is explained exactly by a target higher up), so this is checked on the messages.
``overload``
    Frames were dropped because the pipeline was behind, or a frame's position was withheld because the
    newest estimate was older than ``estimator.max_extrapolation_s`` (``estimate_stale``; not the first frames
    after a gap in the frames themselves, ``estimate_after_gap``): the daemon does not get the CPU it needs.  Raised at the first check (every 0.5 s) that sees either count grow,
    cleared ``overload_clear_s`` (5 s) after the last; the message gives the counts, the CPU the daemon got
    and was refused, and what to do.

``no_attitude``
    The streams the camera's rotation is made of (ATTITUDE_QUATERNION #31, and GIMBAL_DEVICE_ATTITUDE_STATUS #285 on a
    gimballed mount) have brought no new sample for ``ROTATION_SILENT_S`` (2 s) while MAVLink messages and IR frames
    arrive (each within ``INPUTS_LIVE_S`` of the last; the silence counts from when both do): no frame gets a pose (each counted ``pose_attitude_*``), so no line of sight and no
    3-D.  An autopilot that heartbeats but stopped streaming (a stream rate reset, a refused SET_MESSAGE_INTERVAL)
    showed only in the counters.  When the pose buffer refused the stream's samples meanwhile (the status's
    ``rejected``: ``attitude_not_unit``, ``attitude_time_outlier`` ...), the message says they arrive and are refused,
    naming the counts, instead of pointing at the message rates.  Cleared by the next new sample.

``frames_without_pose``
    Every frame for ``FRAMES_WITHOUT_POSE_S`` (2 s) got no pose while the camera's rotation streams arrive (their
    newest sample moved within ``INPUTS_LIVE_S``) and no other warning says why (``no_mavlink``, ``no_attitude``,
    ``camera_clock_apart``, ``gimbal_mismatch``, ``gnss_dropout``: each names its own cause, and clears this one):
    no line of sight and no 3-D, with only the ``pose_*`` counters to say so.  Frames stamped a little ahead of the
    telemetry (200 ms: past what the pose buffer extrapolates, under the clock-step threshold
    ``input.time_reset_threshold_s``) did this silently.  The message gives how far the last frame's stamp stood
    ahead of or behind the telemetry's newest sample, and what to check: the camera's clock sync and capture
    latency, and ``time_offset``.  Cleared by the first frame with a pose.

``estimator_restarted``
    The estimator's worker process died or hung and was replaced (``estimator.worker: process``): its window is
    rebuilt from the parent's copy, and meanwhile 3-D is carried or withheld.  Raised at each replacement, cleared
    ``ESTIMATOR_RESTART_CLEAR_S`` (30 s) after the last; the message counts them.  The status's ``rejected`` says
    which (``estimator_restart``, ``estimator_hung``).

``autopilot_rebooted``
    The autopilot's boot clock went back (``time_boot_ms``, confirmed by consecutive samples: the pose buffer's
    ``reboot``): an autopilot that restarted in flight, or a simulator started again.  The pose buffers and the 3-D
    estimate start again, and the streams are asked again.  Counted and logged before, never in
    the status.  Raised at each reboot, cleared ``AUTOPILOT_REBOOT_CLEAR_S`` (30 s) after the last; the message counts
    them.

``record_stopped``, ``record_file_lost``
    The flight recording stopped (``record.stopped``: free space under ``record.min_free_mb``, a write the disk
    refused; the flight goes on, later messages dropped), or a recording file was deleted or replaced while it was
    written (``record.lost_files``: its messages are lost; the recording goes on in the next file).  Held while the
    recorder says so, which is the rest of the run: the flight's record is incomplete.  A stopped recording does not
    resume when space frees up; ``record_stopped`` names the file it ended in, its folder, and says so.

``health_file``
    The liveness file (``output.health_file``) cannot be touched: an orchestrator's health check (``python -m
    onboard.health``) then fails and may restart a daemon that works.  Cleared by the next touch that succeeds.

``gnss_dropout``
    The position stream (GLOBAL_POSITION_INT #33) has been silent for more than ``nav_gap_s``
    (0.3 s: seven missed samples at 25 Hz) at a frame's capture time while attitude and frames go on:
    the position is dead-reckoned with a growing sigma (``pose.dead_reckoning_max_s``) and the 3-D
    estimate coasts.  When the pose buffer refused #33's samples meanwhile (``position_alt_out_of_range``,
    ``position_jump`` ...), the message says they arrive and are refused, naming the counts, instead of pointing at
    the GNSS.  Checked on every processed frame, cleared by the first frame with fresh position.

``gnss_degraded``
    The autopilot's GNSS receiver has reported no 3-D fix (GPS_RAW_INT #24 ``fix_type`` below 3D_FIX: no GPS,
    no fix or 2-D) for more than ``GNSS_DEGRADED_S`` (1 s: five reports at the usual 5 Hz, so one glitch is
    not a warning): the autopilot's position (#33) is dead-reckoned by its estimator and its error grows, and
    so does the camera position behind every 3-D position.  Kept apart from ``gnss_dropout`` because either
    comes alone (an autopilot goes on sending #33 from its estimator without a fix; #33 can stop with a good
    fix): ``gnss_dropout`` says what the daemon does (its own dead reckoning), this one says why the position
    is poor; with both active, both are listed.  Cleared by the first report with a 3-D fix or better.  Also raised
    when the fix comes and goes, lost ``GNSS_FLAP_LOSSES`` (3) times within ``GNSS_FLAP_WINDOW_S`` (10 s) in runs each
    too short for the rule above (a receiver without a fix half of each second was never warned); cleared once the
    window holds fewer losses and the fix is there.

``camera_time_offset``
    The camera's clock is off the autopilot's: the estimate of :mod:`onboard.estimation.time_offset` is above
    ``time_offset.warn_threshold_ms`` (20 ms: at 0.1 rad/s of camera rotation, 2 mrad of line-of-sight error, twice
    the attitude noise) by more than two sigmas that can be trusted (a ``confident`` estimate's, or one pooled over
    three blocks: ``TimeOffsetEstimate.significantly_beyond``).  The message gives the offset,
    its sigma and whether the pose lookup compensates it.  While it holds and more than the threshold is left
    uncompensated (beyond ``time_offset.max_offset_ms``, compensation off, or an offset that moved from the
    compensation), the daemon withholds lines of sight and 3-D positions as for a mismatch
    (:func:`~onboard.pipeline.withholding.clock_offset_withholds`): made with the pose of another instant, their
    covariance does not hold.  Cleared by a confident estimate at or below the
    threshold; an estimate that is not confident (no target, a still camera) changes nothing.

``camera_clock_apart``
    The IR frames' stamps stand more than ``input.time_reset_threshold_s`` from the telemetry's newest sample since a
    step of the camera's clock the telemetry did not share (:attr:`onboard.pipeline.frame_pipeline.FramePipeline.
    clock_apart_s`): the frames get no pose, so no line of sight and no 3-D, until the two clocks agree again (the
    first frame within the threshold clears it).  A pose at such a stamp would be seconds old or missing.

``stream_rate_low``
    A requested telemetry stream (ATTITUDE_QUATERNION, GLOBAL_POSITION_INT, the followed gimbal's #285) arrives at
    under half the rate its SET_MESSAGE_INTERVAL asked for, averaged over the last 5 s and judged from 3 s after the
    request was ACCEPTED (:class:`onboard.core.stream_rate.StreamRates`): the autopilot caps it or the link loses
    messages.  Reset on a link loss or a new request; cleared when the stream is back over half its rate.

``utc_disputed``
    A SYSTEM_TIME disagrees with the boot clock -> UTC mapping and no step is confirmed yet
    (:class:`onboard.core.utc_clock.UtcClock`): ``time_unix_us`` carries a sigma that covers both readings until
    the next samples tell a wild sample from a UTC step; cleared when they do.

``autopilot_duplicate``
    On a ``udpin`` link, the followed autopilot's system and component id heartbeat from a second address while the
    followed one is alive (heard within ``mavlink.heartbeat_timeout_s``): two vehicles with one MAVLink system id on
    the daemon's port (both PX4 and ArduPilot default to 1), or one autopilot over two routes.  Everything from the
    second address is refused (:class:`onboard.io.mavlink_link.MavlinkLink`); mixed, the two had made every line of
    sight and 3-D position wrong.  The message names both addresses and the id, and how long the followed one has
    been silent once it has missed a heartbeat (a router restarted on a new port: it is followed there once the old
    address has been silent for ``mavlink.heartbeat_timeout_s``).  Cleared when the second one has not heartbeated
    for ``mavlink.heartbeat_timeout_s``.

``name_clash``
    Another daemon publishes under this daemon's vehicle name: a status (``irtrack/<vehicle>/status``) came from
    another zenoh session (the daemon's own are not delivered back to it).  Its tracks, objects and status then
    interleave with this daemon's on the same keys, and a consumer takes the two for one vehicle: the watcher prints
    both, a ground station follows both, the fleet fusion reads two cameras as one (it names the clash itself when
    their cameras stand apart, and drops the second copy when both daemons read one camera).  This daemon's own
    output is its own camera's and goes on.  The message names the key and what the other's status says (its
    uptime, frames received, MAVLink link state).  Raised by the first such status, cleared ``NAME_CLASH_CLEAR_S``
    (10 s) after the last.

``video_rate``
    The H.264 stream's camera runs at a rate other than ``video.fps`` by more than ``VIDEO_RATE_TOLERANCE``
    (20 %), measured from the frames' capture times (:attr:`onboard.io.video.VideoStreamer.camera_rate_hz`):
    x264 spreads ``video.bitrate_bps`` over ``video.fps`` frames a second, so a 10 Hz camera under the default 30
    sends under half the configured bit rate (a poorer picture) and a 60 Hz one about twice it (more than the
    radio link was sized for).  The message gives both rates and the bit rate that results; cleared when the
    two agree again.

Each code is logged at WARNING the first time only (``warned``); it is in :attr:`active` while the
condition holds (the status JSON lists them) and leaves it when the condition clears (logged at
INFO), coming back without a new WARNING.
"""

from __future__ import annotations

import collections
import logging
import math
import os
import threading
from dataclasses import dataclass

from onboard.app.overload import ESTIMATOR_SILENT_S, OVERLOAD_CLEAR_S, STALL_NAMED_S, Overload
from onboard.core.checks import is_positive_number
from onboard.core.errors import InputError
from onboard.core.stream_rate import REASK_S

__all__ = ["WatchdogWarning", "Watchdog", "INPUT_TIMEOUT_S", "NAV_GAP_S", "RESIDUAL_THRESHOLD"]
__all__ += ["OVERLOAD_CLEAR_S", "STALL_NAMED_S", "ESTIMATOR_SILENT_S"]  # onboard.app.overload's, importable as before

INPUT_TIMEOUT_S = 5.0
NAV_GAP_S = 0.3
GNSS_DEGRADED_S = 1.0
#: a fix lost this many times within the window, each run shorter than GNSS_DEGRADED_S, is degraded too
GNSS_FLAP_LOSSES = 3
GNSS_FLAP_WINDOW_S = 10.0
RESIDUAL_THRESHOLD = 3.0
RESIDUAL_PERSIST_S = 5.0
RESIDUAL_MIN_SAMPLES = 10
#: frame_size clears this long after the last frame of another size: two cameras alternating on the key raised and
#: cleared it with every frame (50 status messages and 50 log lines a second)
FRAME_SIZE_CLEAR_S = 1.0
#: frame_sources: this many returns to an earlier sequence numbering within the window are two senders interleaving (a
#: restart's old numbering comes back once or twice, as a late frame or two; a second camera at 1 Hz returns 10 times)
FRAME_SOURCES_MIN_RETURNS = 6
FRAME_SOURCES_WINDOW_S = 5.0
FRAME_SOURCES_CLEAR_S = 5.0
VIDEO_RATE_TOLERANCE = 0.2
ROTATION_SILENT_S = 2.0
ESTIMATOR_RESTART_CLEAR_S = 30.0
AUTOPILOT_REBOOT_CLEAR_S = 30.0
#: name_clash clears this long after the other daemon's last status (ten of the default 1 s status interval)
NAME_CLASH_CLEAR_S = 10.0
INPUTS_LIVE_S = 1.0  # frames and MAVLink messages within this long count as arriving, for no_attitude
FRAMES_WITHOUT_POSE_S = 2.0
#: the warnings that name why frames get no pose themselves: frames_without_pose would only repeat them
POSE_LOSS_NAMED = ("no_mavlink", "no_attitude", "camera_clock_apart", "gimbal_mismatch", "gnss_dropout")

#: the pose buffer's reasons that keep the sample they count (not a refusal), as ``<stream>_<reason>``
_SAMPLE_KEPT = frozenset({"resumed", "time_step", "reset", "rate_invalid", "velocity_invalid", "reference_changed"})

_log = logging.getLogger(__name__)


def _refused_since(counts: dict[str, int], since: dict[str, int], streams: tuple[str, ...]) -> str:
    """The pose buffer's refusals of ``streams``' samples (reasons ``<stream>_<why>``) counted in ``counts`` beyond
    ``since`` (an earlier copy), as "attitude_not_unit 387, ..."; "" when none."""
    grown = []
    for reason, n in sorted(counts.items()):
        stream, _, why = reason.partition("_")
        if stream in streams and why not in _SAMPLE_KEPT and n > since.get(reason, 0):
            grown.append(f"{reason} {n - since.get(reason, 0)}")
    return ", ".join(grown)


#: the inputs the timeouts watch: code -> (what did not come, where it was awaited and what to check)
_SILENT_INPUT = {
    "no_frames": (
        "IR frame",
        "zenoh key '{frame_key}' ({zenoh_where}): check that the camera or simulator publishes there, "
        "that a zenoh endpoint connects the two, and that its frames fit input.max_frame_bytes (zenoh's "
        "transport drops a larger one before the daemon can count it)",
    ),
    "no_mavlink": (
        "MAVLink message",
        "'{mavlink_connection}' (mavlink.connection / --mavlink): check the autopilot or mavlink-router sends "
        "there; without telemetry no frame gets a pose or a 3-D position",
    ),
}


class _CountGrowth:
    """A running count (replacements, reboots) whose growth raises a warning held ``hold_s`` after the last."""

    __slots__ = ("count", "grew_s", "hold_s")

    def __init__(self, hold_s: float) -> None:
        self.count = 0
        self.grew_s = -math.inf
        self.hold_s = hold_s

    def grew(self, now_s: float, count: int) -> bool:
        """``count`` is above the last one seen (taken as the new one)."""
        if count <= self.count:
            return False
        self.count, self.grew_s = count, float(now_s)
        return True

    def held(self, now_s: float) -> bool:
        return now_s - self.grew_s < self.hold_s


@dataclass(frozen=True)
class WatchdogWarning:
    """One active condition: ``code`` (module docstring) and a one-line ``message`` saying what to check."""

    code: str
    message: str

    def __post_init__(self) -> None:
        if not self.code or not isinstance(self.code, str) or not isinstance(self.message, str):
            raise InputError(f"WatchdogWarning needs a code and a message, got {self.code!r}, {self.message!r}")

    def as_dict(self) -> dict[str, str]:
        return {"code": self.code, "message": self.message}


class Watchdog:
    """See the module docstring.  ``started_s``: the time the inputs were opened (same clock as ``now_s``).

    ``frame_key``: the zenoh key of the frames; ``zenoh_where``: the session's endpoints/mode in
    words; ``mavlink_connection``: the connection string; ``camera_size_px``: ``(width, height)``
    configured.  ``logger``: where the warnings go.
    """

    def __init__(
        self,
        *,
        started_s: float,
        frame_key: str,
        zenoh_where: str,
        mavlink_connection: str,
        camera_size_px: tuple[int, int],
        input_timeout_s: float = INPUT_TIMEOUT_S,
        residual_threshold: float = RESIDUAL_THRESHOLD,
        residual_persist_s: float = RESIDUAL_PERSIST_S,
        residual_min_samples: int = RESIDUAL_MIN_SAMPLES,
        logger: logging.Logger | None = None,
    ) -> None:
        for name, v in (
            ("input_timeout_s", input_timeout_s),
            ("residual_threshold", residual_threshold),
            ("residual_persist_s", residual_persist_s),
        ):
            if not is_positive_number(v):
                raise InputError(f"Watchdog.{name} must be a positive number, got {v!r}")
        self.frame_key = frame_key
        self.zenoh_where = zenoh_where
        self.mavlink_connection = mavlink_connection
        self.camera_size_px = (int(camera_size_px[0]), int(camera_size_px[1]))
        self.input_timeout_s = float(input_timeout_s)
        self.residual_threshold = float(residual_threshold)
        self.residual_persist_s = float(residual_persist_s)
        self.residual_min_samples = int(residual_min_samples)
        self._log = logger or _log
        self._last_frame_s = float(started_s)
        self._last_mavlink_s = float(started_s)
        self._zenoh_alone_s: float | None = None  # since when the session has had no router or peer (zenoh_links)
        self._estimator_restarts = _CountGrowth(ESTIMATOR_RESTART_CLEAR_S)
        self._autopilot_reboots = _CountGrowth(AUTOPILOT_REBOOT_CLEAR_S)
        self._gnss_losses: collections.deque[tuple[float, int]] = collections.deque()  # (now_s, fix losses so far)
        self._rotation_newest_us: int | None = None
        self._rotation_since_s = float(started_s)
        self._rotation_moved_s = -math.inf  # when the rotation streams' newest sample last moved (frames_without_pose)
        self._rejected: dict[str, int] = {}  # the status's rejected counts, as of the last step
        self._rotation_rejected: dict[str, int] = {}  # ... when the rotation streams' newest sample last moved
        self._position_rejected: dict[str, int] = {}  # ... when a frame last had a newer position sample
        self._position_age_s = math.inf  # the last frame's position age (navigation)
        self._poseless_since_s: float | None = None  # the first frame of the run without a pose
        self._poseless_frames = 0
        self._frames_seen = 0
        self._mavlink_seen = 0
        self._mavlink_refused_seen = 0  # MAVLink messages signing refused, the running count
        self._high_since_s: float | None = None
        self._high_n = 0
        self._high_max = 0.0
        self._overload = Overload()
        self._size_mismatch_s = -math.inf  # the last frame of another size than the camera's
        self._source_returns: collections.deque[tuple[float, int]] = collections.deque()  # (now_s, returns so far)
        self._source_return_s = -math.inf  # when the returns last grew
        self._active: dict[str, WatchdogWarning] = {}
        self._lock = threading.Lock()  # the service feeds frames from one thread, the clock from another
        self.warned: set[str] = set()
        #: raised or cleared conditions so far (the service publishes a status at once when it moves)
        self.changes = 0

    def restart(self, now_s: float) -> None:
        """The inputs were (re)opened at ``now_s``: the input timeouts run from here."""
        self._last_frame_s = self._last_mavlink_s = self._rotation_since_s = float(now_s)

    # ------------------------------------------------------------------ inputs

    def step(
        self,
        now_s: float,
        *,
        frames_in: int | None = None,
        mavlink_rx: int | None = None,
        mavlink_open_error: str | None = None,
        rotation: tuple[int | None, bool] | None = None,
        mavlink_refused: int | None = None,
        rejected: dict[str, int] | None = None,
    ) -> None:
        """Update with the running counts of frames received and MAVLink messages, then check the timeouts.
        ``mavlink_open_error``: why the MAVLink connection could not be opened (None: it is open), which the
        ``no_mavlink`` warning then names instead of the far end.  ``rotation``: (the newest time the camera's
        rotation streams cover, the pose buffer's, None while there is none; whether the mount is gimballed), for
        ``no_attitude`` (None: not watched).  ``mavlink_refused``: the running count of MAVLink messages signing
        refused (not in ``mavlink_rx``): while they grow and nothing is taken, ``no_mavlink`` says the keys differ.
        ``rejected``: the running counts of rejected input by reason (the status's; a snapshot the caller does not
        change afterwards, as :attr:`~onboard.core.counters.RejectCounter.counts` is), for ``no_attitude`` and
        ``gnss_dropout`` to tell a stream that stopped from one whose samples are refused."""
        if rejected is not None:
            self._rejected = rejected  # a snapshot (RejectCounter.counts copies): kept as given
        # the attitude's silence counts from when frames and MAVLink both arrive again, not through their own
        if now_s - self._last_frame_s >= INPUTS_LIVE_S or now_s - self._last_mavlink_s >= INPUTS_LIVE_S:
            self._rotation_since_s = max(self._rotation_since_s, float(now_s))
        if frames_in is not None and frames_in > self._frames_seen:
            self._frames_seen = frames_in
            self.frame_received(now_s)
        if mavlink_rx is not None and mavlink_rx > self._mavlink_seen:
            self._mavlink_seen = mavlink_rx
            self._last_mavlink_s = float(now_s)
            self._clear("no_mavlink")
        refused_now = False
        if mavlink_refused is not None:
            refused_now = mavlink_refused > self._mavlink_refused_seen
            self._mavlink_refused_seen = mavlink_refused
        if rotation is not None:
            self._rotation(now_s, *rotation)
        t = self.input_timeout_s
        for code, last_s, seen in (
            ("no_frames", self._last_frame_s, self._frames_seen),
            ("no_mavlink", self._last_mavlink_s, self._mavlink_seen),
        ):
            if now_s - last_s >= t:
                what, where = _SILENT_INPUT[code]
                ever = "since the last one" if seen else "since start"
                if code == "no_mavlink" and refused_now and not mavlink_open_error:
                    # packets arrive and signing refuses every one: no silence far away, a key here or there
                    where = (
                        "'{mavlink_connection}': MAVLink arrives but signing refuses every packet (rejected: "
                        "mavlink_signature_bad, _replay or _stale): the sender's key differs from "
                        "mavlink.signing_key_file, or the sender does not sign"
                    )
                if code == "no_mavlink" and mavlink_open_error:
                    # nothing can arrive on a connection that is not open: say why it is not, not what to check far away
                    where = (
                        "'{mavlink_connection}' (mavlink.connection / --mavlink): it cannot be opened ("
                        + mavlink_open_error.replace("{", "{{").replace("}", "}}")
                        + "); for a port in use, another program (another daemon?) holds it; retried every "
                        "mavlink.reopen_interval_s"
                    )
                self._raise(
                    code,
                    f"no {what} for {now_s - last_s:.0f} s ({ever}) on "
                    + where.format(
                        frame_key=self.frame_key,
                        zenoh_where=self.zenoh_where,
                        mavlink_connection=self.mavlink_connection,
                    ),
                )

    def components(
        self, now_s: float, *, estimator_restarts: int = 0, record: dict | None = None, health_error: str | None = None
    ) -> None:
        """The daemon's own parts: the estimator worker's replacements so far, the recorder's stats (``record``, its
        ``stopped`` and ``lost_files``; None: not recording) and why the liveness file cannot be touched (None: it
        can), for ``estimator_restarted``, ``record_stopped``, ``record_file_lost`` and ``health_file``."""
        if self._estimator_restarts.grew(now_s, estimator_restarts):
            self._raise(
                "estimator_restarted",
                f"the estimator's worker process died or hung and was replaced ({estimator_restarts} since start; the "
                "status's rejected: estimator_restart, estimator_hung; the log has each exit): its window is rebuilt, "
                "3-D is carried or withheld meanwhile; if it repeats, check the companion's memory and the daemon's "
                "log",
            )
        elif not self._estimator_restarts.held(now_s):
            self._clear("estimator_restarted")
        record = record or {}
        stopped, lost = record.get("stopped"), list(record.get("lost_files") or [])
        # None: no file of the recording is left (its folder deleted, and the next file could not be made)
        ended = record.get("current_file")
        folder = os.path.dirname(str(ended or record.get("path") or "")) or "."
        self._hold(
            "record_stopped",
            stopped
            # the file it ended in and that it stays stopped: an operator who freed the space saw the same warning
            # and could not tell whether the recording had come back (it does not, by design: one flight, one file
            # set, no gap inside it)
            and f"the flight recording stopped: {stopped}; "
            + (
                f"{ended} ends there (readable)"
                if ended
                else "no file of it is left (record.lost_files)"
                if lost
                else "nothing of it was written"
            )
            + "; the flight goes on, later messages are dropped and counted (record.stopped); it does not resume in "
            f"this run: free space on (or make writable) {folder}, or set record.path on another disk, and restart "
            "the daemon to record again",
        )
        self._hold(
            "record_file_lost",
            lost
            and f"recording file(s) deleted while written, their messages lost: {', '.join(lost)}; "
            + ("the recording has stopped (record_stopped)" if stopped else f"the recording goes on in {ended}"),
        )
        self._hold(
            "health_file",
            health_error
            and f"cannot touch the liveness file: {health_error}; a health check (python -m onboard.health, the "
            "container's HEALTHCHECK) fails and may restart this daemon; check output.health_file's folder",
        )

    def autopilot_reboots(self, now_s: float, reboots: int) -> None:
        """The pose buffer's count of autopilot reboots so far (its boot clock going back), for
        ``autopilot_rebooted``."""
        if self._autopilot_reboots.grew(now_s, reboots):
            self._raise(
                "autopilot_rebooted",
                f"the autopilot's boot clock went back: it restarted ({reboots} since start; the log has each): the "
                "pose and the 3-D estimate started again and its streams were asked again; "
                "in flight, check the autopilot's power and its own log",
            )
        elif not self._autopilot_reboots.held(now_s):
            self._clear("autopilot_rebooted")

    def _rotation(self, now_s: float, newest_us: int | None, gimballed: bool) -> None:
        if newest_us is not None and newest_us != self._rotation_newest_us:
            self._rotation_newest_us = newest_us
            self._rotation_since_s = self._rotation_moved_s = float(now_s)
            self._rotation_rejected = self._rejected
            self._clear("no_attitude")
            return
        silent_s = now_s - self._rotation_since_s
        if silent_s < ROTATION_SILENT_S or not self._frames_seen or not self._mavlink_seen:
            return
        streams = (
            "ATTITUDE_QUATERNION (#31) or GIMBAL_DEVICE_ATTITUDE_STATUS (#285)"
            if gimballed
            else ("ATTITUDE_QUATERNION (#31)")
        )
        refused = _refused_since(self._rejected, self._rotation_rejected, ("attitude", "gimbal"))
        if refused:
            # the messages arrive: the rates are not the matter, what the autopilot puts in them is
            self._raise(
                "no_attitude",
                f"no {streams} sample accepted for {silent_s:.0f} s: they arrive but the pose buffer refuses them "
                f"(rejected: {refused}; the log says why): no frame gets a pose, so no line of sight and no 3-D; "
                "check what the autopilot sends (its quaternion's norm, its time_boot_ms)",
            )
            return
        self._raise(
            "no_attitude",
            f"no new {streams} for {silent_s:.0f} s ({'since the last one' if newest_us is not None else 'since start'})"
            " while MAVLink messages and IR frames arrive: no frame gets a pose, so no line of sight and no 3-D; check "
            "the autopilot's message rates (the daemon asks for them with SET_MESSAGE_INTERVAL: the status's "
            "link.rates_refused)",
        )

    def gimbal(self, now_s: float, *, gimballed: bool, gimbal_reports: int, telemetry_since_s: float | None) -> None:
        """Check the mount against the vehicle: ``gimbal_reports`` #285 messages received so far,
        ``telemetry_since_s`` when the first attitude/position arrived (None: none yet)."""
        if not gimballed and gimbal_reports > 0:
            self._raise(
                "gimbal_mismatch",
                f"the vehicle reports a gimbal ({gimbal_reports} GIMBAL_DEVICE_ATTITUDE_STATUS "
                f"messages) but camera.mount.gimballed is false: the camera attitude ignores the gimbal and "
                f"3-D positions will be wrong; set camera.mount (gimballed, roll/pitch/yaw_deg) to the pod (if that "
                f"gimbal carries another camera, set mavlink.gimbal_device_id to an id none of the vehicle's gimbals "
                f"uses: only that device's reports are then checked)",
            )
        elif (
            gimballed
            and gimbal_reports == 0
            and telemetry_since_s is not None
            and now_s - telemetry_since_s >= self.input_timeout_s
        ):
            self._raise(
                "gimbal_mismatch",
                f"camera.mount.gimballed is true but no GIMBAL_DEVICE_ATTITUDE_STATUS (#285) "
                f"arrived in {now_s - telemetry_since_s:.0f} s of telemetry: no frame gets a pose; check the "
                f"gimbal's MAVLink output or set camera.mount.gimballed false for a fixed pod",
            )
        elif gimballed and gimbal_reports > 0:
            self._clear("gimbal_mismatch")

    def frame_pose(self, now_s: float, has_pose: bool, stamp_from_telemetry_s: float | None) -> None:
        """One processed frame: whether it got a pose, and how far its stamp stood from the telemetry's newest sample
        when it was looked up (s; positive: ahead of it; None: no telemetry yet), for ``frames_without_pose``."""
        if has_pose:
            self._poseless_since_s, self._poseless_frames = None, 0
            self._clear("frames_without_pose")
            return
        if any(code in self._active for code in POSE_LOSS_NAMED):
            self._poseless_since_s, self._poseless_frames = None, 0  # its 2 s start when that one clears
            self._clear("frames_without_pose")  # that warning says why, and what to do
            return
        if stamp_from_telemetry_s is None or now_s - self._rotation_moved_s > INPUTS_LIVE_S:
            # no telemetry yet, or it stopped: no_attitude's or no_mavlink's to say, once their time has come; the
            # frames before it came do not count (a camera up before the autopilot's link is an ordinary start)
            if "frames_without_pose" not in self._active:
                self._poseless_since_s, self._poseless_frames = None, 0
            return
        if self._poseless_since_s is None:
            self._poseless_since_s = float(now_s)
        self._poseless_frames += 1
        lasted = now_s - self._poseless_since_s
        if lasted < FRAMES_WITHOUT_POSE_S:
            return
        ms = 1000.0 * stamp_from_telemetry_s
        if ms > 0:
            where = (
                f"{ms:.0f} ms ahead of the telemetry's newest sample, later than the pose buffer extrapolates (the "
                "clock-offset estimator needs a pose at the stamp, so it cannot measure this)"
            )
        else:
            where = f"{-ms:.0f} ms behind the telemetry's newest sample"
        self._raise(
            "frames_without_pose",
            f"no pose for the last {self._poseless_frames} frames ({lasted:.0f} s) while the telemetry arrives: the "
            f"last frame was stamped {where}; no line of sight and no 3-D (the status's rejected pose_* say which "
            "lookup failed); check the camera's clock sync (capture time on the autopilot's boot clock, through "
            "TIMESYNC) and its capture latency, and time_offset (an offset within time_offset.max_offset_ms is "
            "compensated once measured)",
        )

    def frame_received(self, now_s: float) -> None:
        self._last_frame_s = float(now_s)
        self._clear("no_frames")

    def frame_size(self, now_s: float, width_px: int, height_px: int) -> None:
        """A frame of ``width_px x height_px`` arrived (any, accepted or not)."""
        cw, ch = self.camera_size_px
        if (int(width_px), int(height_px)) == (cw, ch):
            if now_s - self._size_mismatch_s >= FRAME_SIZE_CLEAR_S:
                self._clear("frame_size")
            return
        self._size_mismatch_s = float(now_s)
        self._raise(
            "frame_size",
            f"frames are {int(width_px)} x {int(height_px)} px but the configured camera is "
            f"{cw} x {ch} px (camera.intrinsics.width_px / height_px): they are refused; configure the "
            f"camera that sends them",
        )

    def frame_sources(self, now_s: float, returns: int) -> None:
        """The running count of frames that came back to a sequence numbering seen before, other than the previous
        frame's (:attr:`onboard.pipeline.admission.ArrivalGaps.returns`), for ``frame_sources``."""
        samples = self._source_returns
        if samples and returns > samples[-1][1]:
            self._source_return_s = float(now_s)
        samples.append((float(now_s), int(returns)))
        while len(samples) > 1 and samples[1][0] <= now_s - FRAME_SOURCES_WINDOW_S:
            samples.popleft()  # the oldest kept is the count at the window's start
        t0_s, r0 = samples[0]
        n = int(returns) - r0
        if n >= FRAME_SOURCES_MIN_RETURNS:
            self._raise(
                "frame_sources",
                f"two or more senders publish frames on {self.frame_key}: their sequence numbers interleave ({n} "
                f"returns to another numbering in {now_s - t0_s:.1f} s); frames alike in size and clock are all taken "
                "as one stream's, so the track jumps between the views (rejected: frame_sequence_reset), and no frame is known "
                "to be the configured camera's: lines of sight and 3-D positions are withheld (the 2-D track goes "
                "on); configure one camera per key, or let only the camera publish there (the zenoh ACL in deploy/)",
            )
        elif now_s - self._source_return_s >= FRAME_SOURCES_CLEAR_S:
            self._clear("frame_sources")

    def zoom(self, now_s: float, stated_zoom: float | None, withheld: bool) -> None:
        """The zoom the last frame taken stated (relative to the one ``camera.intrinsics`` were calibrated at; None:
        not stated, taken as calibrated), and whether the pipeline withheld that frame's geometry for it (its
        decision, :func:`~onboard.core.irframe.zoom_off_calibration` with its hysteresis, taken as it is: a second
        decision here, from the frames this sees, could disagree with what was published)."""
        self._hold(
            "zoom_mismatch",
            withheld
            and stated_zoom is not None
            and f"IR frames state a zoom of {stated_zoom:g}x but camera.intrinsics are for 1.0x (the zoom they were "
            f"calibrated at): every line of sight made with them would be off by that ratio, so lines of sight and "
            f"3-D positions are withheld (the 2-D track goes on); set the camera's zoom back to 1.0, or calibrate "
            f"camera.intrinsics at this zoom and configure them (the camera then states its zoom relative to that)",
        )

    def video_rate(self, now_s: float, camera_rate_hz: float | None, video_fps: float, bitrate_bps: int) -> None:
        """The H.264 stream's camera rate as measured (None: not yet, or no stream) against ``video.fps``."""
        if camera_rate_hz is None or not math.isfinite(camera_rate_hz) or camera_rate_hz <= 0.0:
            return
        ratio = camera_rate_hz / video_fps
        if abs(ratio - 1.0) <= VIDEO_RATE_TOLERANCE:
            self._clear("video_rate")
            return
        self._raise(
            "video_rate",
            f"the camera delivers {camera_rate_hz:.1f} frames/s but video.fps is {video_fps:g}: the H.264 stream "
            f"gets about {ratio:.2f} x video.bitrate_bps ({ratio * bitrate_bps / 1e6:.2f} of "
            f"{bitrate_bps / 1e6:.2f} Mbit/s); set video.fps to the camera's rate",
        )

    def navigation(
        self,
        now_s: float,
        position_age_s: float | None,
        nav_gap_s: float = NAV_GAP_S,
        rejected: dict[str, int] | None = None,
    ) -> None:
        """One frame's age of the newest position sample at its capture time (None: no pose, ignored); ``rejected``:
        the running counts of rejected input by reason, as :meth:`step` takes them (the warning is raised within
        a frame of the gap, before the next step would bring them)."""
        if rejected is not None:
            self._rejected = rejected  # a snapshot (RejectCounter.counts copies): kept as given
        if position_age_s is None:
            return
        if position_age_s < self._position_age_s:
            # a newer position sample than the last frame's: refusals count from here, not from the last frame within
            # nav_gap_s (that put 1 of the 0.3 s's 7 refusals in the message)
            self._position_rejected = self._rejected
        self._position_age_s = position_age_s
        if position_age_s <= nav_gap_s:
            self._clear("gnss_dropout")
            return
        age = "over the dead-reckoning limit" if math.isinf(position_age_s) else f"for {position_age_s:.1f} s"
        refused = _refused_since(self._rejected, self._position_rejected, ("position",))
        if refused:
            # #33 arrives: the GNSS is not the matter, what the autopilot puts in the messages is
            self._raise(
                "gnss_dropout",
                f"no GLOBAL_POSITION_INT (#33) sample accepted {age}: they arrive but the pose buffer refuses them "
                f"(rejected: {refused}; the log says why) while attitude and frames go on: the position is "
                "dead-reckoned with a growing sigma (pose.dead_reckoning_max_s) and 3-D positions coast; check what "
                "the autopilot sends in #33 (its alt in mm, lat/lon in degE7)",
            )
            return
        self._raise(
            "gnss_dropout",
            f"no GLOBAL_POSITION_INT (#33) {age} while attitude and frames go on: the position is dead-reckoned "
            f"with a growing sigma (pose.dead_reckoning_max_s) and 3-D positions coast; check the GNSS (GPS_RAW_INT "
            f"fix type) and the #33 stream",
        )

    def gnss(self, now_s: float, state) -> None:
        """The latest GPS_RAW_INT (a :class:`~onboard.core.gnss.GnssState` on the same clock; None: none yet)."""
        if state is None:
            return
        losses = self._gnss_losses
        losses.append((float(now_s), int(state.fix_losses)))
        while len(losses) > 1 and losses[1][0] <= now_s - GNSS_FLAP_WINDOW_S:
            losses.popleft()  # the oldest kept is the count at the window's start
        lost = int(state.fix_losses) - losses[0][1]
        lasted = None if state.has_3d_fix else now_s - state.degraded_since_s
        if (lasted is None or lasted <= GNSS_DEGRADED_S) and lost >= GNSS_FLAP_LOSSES:
            self._raise(
                "gnss_degraded",
                f"the GNSS receiver's 3-D fix comes and goes (GPS_RAW_INT #24: lost {lost} times in the last "
                f"{now_s - losses[0][0]:.0f} s, each time for under {GNSS_DEGRADED_S:g} s): the autopilot's position "
                "(#33) is dead-reckoned between them and the camera position behind every 3-D position drifts; check "
                "the GNSS antenna, receiver and its view of the sky",
            )
            return
        if lasted is None:
            self._clear("gnss_degraded")
            return
        if lasted <= GNSS_DEGRADED_S:
            return
        sats = "unknown" if state.satellites is None else str(state.satellites)
        self._raise(
            "gnss_degraded",
            f"the GNSS receiver reports {state.fix} (GPS_RAW_INT #24, {sats} satellites) for {lasted:.1f} s: no "
            f"3-D fix, so the autopilot dead-reckons its position (#33, or stops it: gnss_dropout) and the camera "
            f"position behind every 3-D position drifts, its error growing with time; check the GNSS antenna, "
            f"receiver and its view of the sky",
        )

    def stream_rates(self, now_s: float, slow) -> None:
        """The requested telemetry streams arriving at under half their confirmed rate for a few seconds (a list of
        :class:`~onboard.core.stream_rate.StreamRate`, from the link; empty: none): warned once, naming each."""
        self._hold_each(
            "stream_rate_low",
            [
                f"{r.name} (#{r.msg_id}) arrives at {r.measured_hz:.1f} Hz, {r.requested_hz:g} Hz requested and "
                f"ACCEPTED"
                for r in slow
            ],
            "the autopilot caps the stream (its scheduler or the link's bandwidth: ArduPilot ACCEPTS and sends what it "
            "can), the link loses messages, or a ground station sharing the link lowered it (its rate is asked again "
            f"every {REASK_S:g} s while slow; MAVProxy: --streamrate=-1); poses are interpolated over wider gaps. Check the "
            "autopilot's stream rate limits and the link (status link.streams)",
        )

    def zenoh_links(self, now_s: float, connect: tuple[str, ...], linked: int | None) -> None:
        """``linked``: the zenoh session's routers and peers now (None: not known), ``connect`` the endpoints it
        dials: none linked for ``input_timeout_s`` is ``zenoh_unconnected``, naming them (module docstring)."""
        if not connect or linked is None or linked > 0:
            self._zenoh_alone_s = None
            return self._clear("zenoh_unconnected")
        since = self._zenoh_alone_s = now_s if self._zenoh_alone_s is None else self._zenoh_alone_s
        if now_s - since >= self.input_timeout_s:
            self._raise(
                "zenoh_unconnected",
                f"no zenoh router or peer for {now_s - since:.0f} s (connect {', '.join(connect)}): the tracks, objects "
                "and status published reach no one, and no frame comes through there; zenoh dials again by itself: "
                "check the router or peer at that endpoint (deploy/README.md)",
            )

    def autopilot_duplicate(self, now_s: float, senders) -> None:
        """The second senders of the autopilot's identity heard lately (a list of
        :class:`~onboard.io.mavlink_peer.DuplicateSender`, from the link; empty: none): warned once, naming each."""
        self._hold_each(
            "autopilot_duplicate",
            [
                f"{d.other[0]}:{d.other[1]} heartbeats as MAVLink system {d.sysid} component {d.compid}, which "
                f"{d.followed[0]}:{d.followed[1]} is and is followed{d.silence()}"
                for d in senders
            ],
            "two vehicles with one system id on this port (or one autopilot over two routes); everything from the "
            "second address is refused (rejected: autopilot_duplicate_refused). Give each vehicle its own MAV_SYS_ID "
            "(PX4 MAV_SYS_ID, ArduPilot SYSID_THISMAV) or its own port",
        )

    def name_clash(self, now_s: float, heard: tuple[float, str] | None, status_key: str) -> None:
        """``heard``: when the newest status of another daemon publishing as this vehicle arrived (``now_s``'s clock)
        and what it says in words, or None when none has; ``status_key``: the key it came on.  ``name_clash`` while
        one arrived within ``NAME_CLASH_CLEAR_S`` (module docstring)."""
        if heard is None or now_s - heard[0] > NAME_CLASH_CLEAR_S:
            return self._clear("name_clash")
        self._raise(
            "name_clash",
            f"another daemon publishes as this vehicle: its status arrives on {status_key} ({heard[1]}); its tracks, "
            "objects and status interleave with this daemon's on the same keys, and a consumer (onboard.watch, a "
            "ground station, the fleet fusion) takes the two for one vehicle. Give each daemon its own vehicle name "
            "(the 'vehicle' setting, --vehicle), or stop the other one",
        )

    def utc(self, now_s: float, mapping) -> None:
        """The UTC mapping frames are stamped with (an :class:`~onboard.core.utc_clock.UtcMapping`; None: none yet,
        ignored): warned while it is disputed, a SYSTEM_TIME disagreeing with it and no step confirmed."""
        if mapping is None or not mapping.disputed_us:
            self._clear("utc_disputed")
            return
        self._raise(
            "utc_disputed",
            f"a SYSTEM_TIME (#2) disagrees with the UTC mapping by {mapping.disputed_us / 1000:.0f} ms: a wild sample or "
            f"the first of a UTC step (or a leap second); until the next samples tell which, time_unix_us carries a "
            f"sigma that covers both readings (a fleet fusion refuses it above its time bound); if it persists, "
            f"check the autopilot's time source",
        )

    def camera_time_offset(self, now_s: float, estimate, threshold_ms: float, withheld: bool = False) -> None:
        """The camera clock's offset now (a :class:`~onboard.estimation.time_offset.TimeOffsetEstimate`, or None
        when the estimator is off: ignored) against ``threshold_ms``; ``withheld``: the daemon withholds lines of sight
        and 3-D positions for it (the message says so)."""
        if estimate is None or estimate.estimate_ms is None:
            return
        dt_ms, sigma_ms = float(estimate.estimate_ms), float(estimate.sigma_ms or 0.0)
        if abs(dt_ms) <= threshold_ms:
            if estimate.confident:
                self._clear("camera_time_offset")
            return
        if not estimate.significantly_beyond(threshold_ms):
            return  # above the threshold, but not by two trusted sigmas: neither raised nor cleared
        late = "late" if dt_ms > 0 else "early"
        comp = float(estimate.compensated_ms)
        done = (
            f"the pose lookup compensates {comp:.0f} ms (time_offset.compensate)"
            if comp
            else "not compensated (time_offset.compensate is false or the offset is beyond time_offset.max_offset_ms)"
        )
        if withheld:  # the daemon's decision (onboard/pipeline/withholding.py), said as it was taken
            done += ", so lines of sight and 3-D positions are withheld (the 2-D track goes on)"
        self._raise(
            "camera_time_offset",
            f"IR frames are stamped {abs(dt_ms):.0f} +- {sigma_ms:.0f} ms {late} against the autopilot's clock "
            f"(> {threshold_ms:g} ms): lines of sight and 3-D positions made with the pose at the stamp are off by "
            f"the camera's rotation over that time; {done}; fix the camera's time stamping (capture time on the "
            f"autopilot's boot clock, the capture-to-stamp latency), unless the camera zoomed: a zoom or lens "
            f"camera.intrinsics are not for reads as a clock offset too (a sender that fills IRF1's zoom field says it)",
        )

    def camera_clock(self, now_s: float, apart_s: float | None) -> None:
        """The frames' clock against the telemetry's: ``apart_s`` how far the last frame's stamp stood from the
        telemetry's newest sample while the two disagree, None when they agree (module docstring)."""
        self._hold(
            "camera_clock_apart",
            apart_s is not None
            and f"IR frames are stamped {apart_s:+.1f} s from the autopilot's telemetry since a step of the camera's "
            "clock the telemetry did not share: no line of sight and no 3-D until the two agree; check the camera's "
            "time stamping (capture time on the autopilot's boot clock, through TIMESYNC)",
        )

    def residual(self, now_s: float, residual_rms_norm: float | None) -> None:
        """One estimate's residual statistic (None or NaN: unknown, ignored)."""
        r = residual_rms_norm
        if r is None or (isinstance(r, float) and math.isnan(r)):
            return
        r = float(r)
        if r <= self.residual_threshold:
            self._high_since_s, self._high_n, self._high_max = None, 0, 0.0
            self._clear("camera_mismatch")
            return
        if self._high_since_s is None:
            self._high_since_s = float(now_s)
        self._high_n += 1
        self._high_max = max(self._high_max, r)
        lasted = now_s - self._high_since_s
        if lasted >= self.residual_persist_s and self._high_n >= self.residual_min_samples:
            self._raise(
                "camera_mismatch",
                f"image residuals inconsistent with the configured camera for {lasted:.0f} s "
                f"(residual_rms_norm up to {self._high_max:.1f}, > {self.residual_threshold:g} on all "
                f"{self._high_n} estimates; ~1 expected): a camera mount (camera.mount roll/pitch/yaw, "
                f"gimballed) or intrinsics (camera.intrinsics) mismatch is suspected, or the noise model "
                f"(estimator.*_sigma_*) is too optimistic; 3-D positions are not to be trusted",
            )

    def load(
        self,
        now_s: float,
        *,
        frames_dropped: int,
        estimates_stale: int,
        cpu_words: str = "",
        estimator_silent_s: float = 0.0,
        quota_bound: bool | None = None,
        stalled_s: float = 0.0,
        frames_dropped_bunched: int = 0,
    ) -> None:
        """Update ``overload`` with the running counts of frames dropped and positions withheld as too old, and what
        its message names as the cause: each argument as :meth:`onboard.app.overload.Overload.update` takes it."""
        message = self._overload.update(
            now_s,
            active="overload" in self._active,
            frames_dropped=frames_dropped,
            estimates_stale=estimates_stale,
            cpu_words=cpu_words,
            estimator_silent_s=estimator_silent_s,
            quota_bound=quota_bound,
            stalled_s=stalled_s,
            frames_dropped_bunched=frames_dropped_bunched,
        )
        if message is not None:
            self._raise("overload", message)
        elif not self._overload.held(now_s):
            self._clear("overload")

    # ------------------------------------------------------------------ state

    @property
    def active(self) -> tuple[WatchdogWarning, ...]:
        """The conditions holding now, in the order they were raised."""
        with self._lock:
            return tuple(self._active.values())

    def active_dicts(self) -> list[dict[str, str]]:
        return [w.as_dict() for w in self.active]

    def _raise(self, code: str, message: str) -> None:
        with self._lock:
            was_active = code in self._active
            self._active[code] = WatchdogWarning(code, message)
            first = code not in self.warned
            self.warned.add(code)
            if not was_active:
                self.changes += 1
        if was_active:
            return
        if first:
            self._log.warning("%s: %s", code, message)
        else:
            self._log.info("%s again (warned before): %s", code, message)

    def _hold_each(self, code: str, items: list[str], consequence: str) -> None:
        """:meth:`_hold` of one clause per item, then ``consequence`` after a colon; cleared with no item."""
        self._hold(code, "; ".join(items) + (f": {consequence}" if items else ""))

    def _hold(self, code: str, message: object) -> None:
        """Raise ``code`` with ``message`` while the condition holds (a message), clear it when not (a falsy one)."""
        if message:
            self._raise(code, str(message))
        else:
            self._clear(code)

    def _clear(self, code: str) -> None:
        if code not in self._active:  # the usual case, several times a frame: no lock for nothing to clear
            return
        with self._lock:
            gone = self._active.pop(code, None) is not None
            self.changes += gone
        if gone:
            self._log.info("%s cleared", code)
