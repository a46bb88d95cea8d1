"""FramePipeline in lockstep (no sockets, no threads): synthetic frames + poses -> Track, every refusal counted.

Also the pure pieces of onboard.core.track: the Track noun, irtrack.track/1 JSON, the MAVLink #275/#276
mapping and the status builder.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from bench.onboard import SyntheticScene
from onboard.app.config import OnboardConfig, build_config
from onboard.core.counters import RejectCounter
from onboard.core.errors import InputError
from onboard.core.frames import GeodeticOrigin, geodetic_from_ned, ned_from_geodetic
from onboard.core.irframe import HEADER, MAGIC, IrFrame, encode_irframe
from onboard.core.pose import PoseBuffer
from onboard.core.status import STATUS_SCHEMA, RollingStats
from onboard.core.track import (
    TRACK_SCHEMA,
    Track,
    track_from_json,
    track_to_bytes,
    track_to_json,
)
from onboard.estimation.sliding import TrackEstimate
from onboard.io.mavlink_wire import geo_status_fields, image_status_fields
from onboard.pipeline.admission import APART_CONFIRM_US
from onboard.pipeline.frame_pipeline import FramePipeline, FrameRejected, make_estimator, make_tracker
from tests.fakes import idle_status, positioned_track, single_chain

US = 1_000_000  # microseconds per second
CENTROID_TOL_PX = 0.15  # blob sigma 1.5 px, amplitude 60, noise 1 grey: measured error ~0.03 px
GEO_TOL_DEG = 1e-9  # ~0.1 mm: the same conversion both ways
NED_TOL_M = 1e-6
RECON_TOL_M = 3.0  # real estimator, 0.3 px pixel noise assumed, ~160 m range, a few seconds of orbit
REQUIRED_KEYS = {
    "schema",
    "vehicle",
    "track_id",
    "time_boot_us",
    "state",
    "u_px",
    "v_px",
    "bbox",
    "lat_deg",
    "lon_deg",
    "alt_m",
    "ned_m",
    "origin",
    "vel_ned_mps",
    "sigma_ned_m",
    "range_m",
    "observable",
    "window_frames",
}
POSITION_KEYS = ("lat_deg", "lon_deg", "alt_m", "ned_m", "vel_ned_mps", "sigma_ned_m", "range_m")


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(autouse=True, scope="module")
def _one_blas_thread():
    """The estimator's matrices are small: OpenBLAS threads only spin (20x slower on a loaded 2-core box)."""
    from groundsim.evaluation.parallel import limit_blas_threads

    limit_blas_threads(1)


class FakeEstimator:
    """Records calls; after ``ready_after`` adds returns the scene's true target with a fixed covariance."""

    def __init__(self, scene: SyntheticScene, ready_after: int = 10, observable: bool = True, fail: bool = False):
        self.scene = scene
        self.ready_after = ready_after
        self.observable = observable
        self.fail = fail
        self.calls: list[tuple[str, float]] = []
        self.n = 0

    def _estimate(self, t_s: float, p_cam=None):
        if self.n < self.ready_after:
            return None
        ts = t_s - self.scene.boot_us0 / 1e6
        p, v = self.scene.target(ts)
        cam = self.scene.observer(ts)[0] if p_cam is None else np.asarray(p_cam)
        P = np.diag([4.0, 9.0, 1.0])
        return TrackEstimate(
            t_s,
            p,
            v,
            P,
            np.diag([0.25, 0.25, 0.04]),
            self.observable,
            float(np.linalg.norm(p - cam)),
            0.01,
            self.n,
            "cv",
        )

    def add(self, t_s, uv_px, intrinsics, p_cam_ned_m, q_ned_from_cam):
        self.calls.append(("add", t_s))
        if self.fail:
            raise RuntimeError("boom")
        self.n += 1
        return self._estimate(t_s, p_cam_ned_m)

    def predict(self, t_s, p_cam_ned_m=None):
        self.calls.append(("predict", t_s))
        return self._estimate(t_s, p_cam_ned_m)

    def reset(self):
        self.calls.append(("reset", math.nan))
        self.n = 0


class Rig:
    """Scene + pose buffer fed just ahead of each frame + pipeline; without a ``config``, the built-in one with
    the single image chain (the tests here count frames from the first, :func:`tests.fakes.single_chain`)."""

    def __init__(self, estimator="fake", config: OnboardConfig | None = None, **fake_kw):
        self.scene = SyntheticScene()
        self.config = config if config is not None else single_chain()
        self.counter = RejectCounter(log_interval_s=60.0)
        self.pose = PoseBuffer(
            mount=self.scene.mount,
            config=self.config.pose,
            origin=self.scene.origin,
            counter=self.counter,
        )
        if estimator == "fake":
            self.est = FakeEstimator(self.scene, **fake_kw)
        elif estimator == "real":
            self.est = make_estimator(self.config)
        else:
            self.est = None
        self.pipe = FramePipeline(self.config, self.pose, make_tracker(self.config), self.est, counter=self.counter)
        self.fed_us = None

    def feed_until(self, t_us: int, skip=None, skip_position=None) -> None:
        start = self.scene.t_us(0) - 100_000 if self.fed_us is None else self.fed_us + 1
        if t_us < start:
            return
        for t, p, v, q in self.scene.telemetry(start, t_us, 50.0):
            if skip is None or not skip(t):
                self.pose.add_attitude(t, q)
                if (t // 20_000) % 2 == 0 and (skip_position is None or not skip_position(t)):  # position at 25 Hz
                    self.pose.add_position_ned(t, p, v)
        self.fed_us = t_us

    def step(self, k: int, lead_us: int = 45_000, **frame_kw) -> Track:
        self.feed_until(self.scene.t_us(k) + lead_us)
        return self.pipe.process(self.scene.frame(k, **frame_kw), 0)

    def run(self, n: int, start: int = 0) -> list[Track]:
        return [self.step(k) for k in range(start, start + n)]

    def truth_uv(self, k: int) -> np.ndarray:
        return self.scene.uv((self.scene.t_us(k) - self.scene.boot_us0) / 1e6)


# --------------------------------------------------------------------------- lockstep: fields, units, nulls


def test_lockstep_tracks_have_image_fields_and_nulls_before_an_estimate():
    rig = Rig(ready_after=10)
    tracks = rig.run(20)
    for k, tr in enumerate(tracks):
        j = track_to_json(tr)
        assert REQUIRED_KEYS <= set(j) and j["schema"] == TRACK_SCHEMA
        assert j["vehicle"] == "uav1" and j["seq"] == k and j["time_boot_us"] == rig.scene.t_us(k)
        assert j["state"] == "tracking" and j["track_id"] == 1 and j["measurement_valid"] and j["pose_valid"]
        assert np.hypot(j["u_px"] - rig.truth_uv(k)[0], j["v_px"] - rig.truth_uv(k)[1]) < CENTROID_TOL_PX
        x, y, w, h = j["bbox"]
        assert x <= j["u_px"] <= x + w and y <= j["v_px"] <= y + h
        assert j["origin"] == {"lat_deg": 32.0, "lon_deg": 118.8, "alt_m": 0.0}
        if k < 9:  # the fake needs 10 observations
            assert all(j[key] is None for key in POSITION_KEYS) and j["observable"] is False and j["window_frames"] == 0
        else:
            assert all(j[key] is not None for key in POSITION_KEYS)
    assert [c[0] for c in rig.est.calls] == ["add"] * 20
    assert rig.est.calls[3][1] == rig.scene.t_us(3) / 1e6  # estimator time = capture time on the boot clock, s
    assert rig.counter.total == 0


def test_position_fields_are_wgs84_of_the_ned_estimate_with_one_sigma():
    rig = Rig(ready_after=1)
    tr = rig.run(3)[-1]
    j = json.loads(track_to_bytes(tr))
    ts = (rig.scene.t_us(2) - rig.scene.boot_us0) / 1e6
    p, v = rig.scene.target(ts)
    lat, lon, alt = geodetic_from_ned(p, rig.scene.origin)
    assert abs(j["lat_deg"] - float(lat)) < GEO_TOL_DEG and abs(j["lon_deg"] - float(lon)) < GEO_TOL_DEG
    assert j["alt_m"] == pytest.approx(85.0, abs=0.01)  # 85 m up = NED d -85 about a 0 m origin
    assert np.allclose(j["ned_m"], p, atol=NED_TOL_M)
    back = ned_from_geodetic(j["lat_deg"], j["lon_deg"], j["alt_m"], rig.scene.origin)
    assert np.allclose(back, j["ned_m"], atol=1e-3)
    assert j["vel_ned_mps"] == [5.0, 0.0, 0.0]
    assert j["sigma_ned_m"] == [2.0, 3.0, 1.0]  # sqrt of the diagonal of diag(4, 9, 1)
    assert j["sigma_vel_ned_mps"] == [0.5, 0.5, 0.2]
    assert j["cov_ned_m2"] == [[4.0, 0.0, 0.0], [0.0, 9.0, 0.0], [0.0, 0.0, 1.0]]
    cam = rig.scene.camera(ts)[0]
    assert j["range_m"] == pytest.approx(np.linalg.norm(p - cam), rel=1e-9)
    assert j["observable"] is True and j["window_frames"] == 3 and j["model"] == "cv"


def test_unobservable_estimate_is_published_graded_unless_configured_off():
    rig = Rig(ready_after=1, observable=False)
    j = track_to_json(rig.run(3)[-1])
    assert all(j[k] is not None for k in POSITION_KEYS) and j["observable"] is False and j["window_frames"] == 3
    cfg = build_config({"output": {"unobservable_positions": False}})  # the irtrack.track/1 behaviour
    rig = Rig(config=single_chain(cfg), ready_after=1, observable=False)
    j = track_to_json(rig.run(3)[-1])
    assert all(j[k] is None for k in POSITION_KEYS) and j["observable"] is False and j["window_frames"] == 3


def test_an_unobservable_position_is_published_widened_across_its_line_of_sight_an_observable_one_as_solved():
    """The across-range covariance of an unobservable solution is its bearing's at its own range: published, it is
    widened by 1 + sigma_r^2 / r^2 (:func:`~onboard.estimation.map_estimator.across_range_widened`), from the
    frame's camera; an observable one goes out exactly as the estimator gave it."""
    for observable in (True, False):
        rig = Rig(ready_after=1, observable=observable)
        tr = rig.run(3)[-1]
        ts = (rig.scene.t_us(2) - rig.scene.boot_us0) / 1e6
        p = rig.scene.target(ts)[0]
        P = np.diag([4.0, 9.0, 1.0])  # the fake's
        if observable:
            np.testing.assert_array_equal(tr.cov_p_ned_m2, P)
            continue
        los = p - rig.scene.camera(ts)[0]
        r = np.linalg.norm(los)
        u = los / r
        Q = np.eye(3) - np.outer(u, u)
        W = np.asarray(tr.cov_p_ned_m2)
        assert u @ W @ u == pytest.approx(u @ P @ u, rel=1e-9)
        np.testing.assert_allclose(Q @ W @ Q, (1.0 + (u @ P @ u) / r**2) * (Q @ P @ Q), rtol=1e-9, atol=1e-12)
        assert not np.allclose(W, P)


def test_the_pose_origin_names_the_estimate_whatever_origin_was_configured():
    """The estimate is in the NED frame of the poses it was made from: a configured origin 111 m north of it (a
    replay's --set pose.origin) must neither move the published target nor name the track's frame."""
    rig = Rig(ready_after=1)
    rig.pipe.origin = GeodeticOrigin(32.001, 118.8, 10.0)
    j = track_to_json(rig.run(2)[-1])
    assert j["origin"] == {"lat_deg": 32.0, "lon_deg": 118.8, "alt_m": 0.0}
    lat, lon, alt = geodetic_from_ned(j["ned_m"], rig.scene.origin)
    assert abs(j["lat_deg"] - float(lat)) < GEO_TOL_DEG and j["alt_m"] == pytest.approx(float(alt), abs=1e-6)


@pytest.mark.timeout(120)
def test_real_estimator_reconstructs_the_target_in_lockstep():
    cfg = build_config({"estimator": {"sliding": {"reselect_period_s": 2.0}}})
    rig = Rig(estimator="real", config=cfg)
    # the window is called observable once its worst range sigma is small: about a full 10 s window here
    tracks = rig.run(320)
    with_pos = [t for t in tracks if t.has_position]
    assert with_pos, "no observable estimate in 10.7 s of a circling observer"
    last = tracks[-1]
    assert last.has_position and last.observable
    ts = (last.time_boot_us - rig.scene.boot_us0) / 1e6
    err = np.linalg.norm(np.asarray(last.p_ned_m) - rig.scene.target(ts)[0])
    assert err < RECON_TOL_M, f"3-D error {err:.2f} m"
    assert err < 5 * math.sqrt(np.trace(last.cov_p_ned_m2)) + 0.5  # the sigma is not absurdly optimistic
    assert last.window_frames > 100 and last.range_m == pytest.approx(
        np.linalg.norm(rig.scene.target(ts)[0] - rig.scene.camera(ts)[0]), rel=0.03
    )
    assert rig.counter.total == 0


# --------------------------------------------------------------------------- refused frames, each counted


def _good(rig: Rig, k: int) -> bytes:
    rig.feed_until(rig.scene.t_us(k) + 45_000)
    return rig.scene.payload(k)


def _with_header(payload: bytes, **changes) -> bytes:
    magic, version, enc, w, h, seq, t, zoom = HEADER.unpack_from(payload, 0)
    vals = dict(magic=magic, version=version, enc=enc, w=w, h=h, seq=seq, t=t, zoom=zoom)
    vals.update(changes)
    return HEADER.pack(*vals.values()) + payload[HEADER.size :]


BAD_PAYLOADS = {
    "random_bytes": (lambda p: np.random.default_rng(1).integers(0, 256, 5000, dtype=np.uint8).tobytes(), "magic"),
    "short": (lambda p: p[:20], "short"),
    "bad_magic": (lambda p: b"XXXX" + p[4:], "magic"),
    "bad_version": (lambda p: _with_header(p, version=2), "version"),
    "bad_encoding": (lambda p: _with_header(p, enc=9), "encoding"),
    "zero_width": (lambda p: _with_header(p, w=0), "dims"),
    "wrong_size_truncated": (lambda p: p[:-640], "size"),
    "wrong_size_header": (lambda p: _with_header(p, h=511), "size"),
    "too_large_100x": (lambda p: p + bytes(len(p) * 99), "too_large"),
}


@pytest.mark.parametrize("name", list(BAD_PAYLOADS))
def test_bad_payload_is_refused_counted_once_and_survived(name):
    make, reason = BAD_PAYLOADS[name]
    rig = Rig(ready_after=1)
    rig.pipe.process_payload(_good(rig, 0))
    with pytest.raises(FrameRejected) as ei:
        rig.pipe.process_payload(make(_good(rig, 1)))
    assert ei.value.reason == reason
    assert rig.counter.counts == {f"frame_{reason}": 1}
    tr = rig.pipe.process_payload(_good(rig, 2))  # the stream goes on
    assert tr.seq == 2 and tr.state == "tracking" and rig.pipe.frames_processed == 2 and rig.pipe.frames_rejected == 1


def test_frame_of_another_size_than_the_camera_is_refused():
    rig = Rig()
    small = IrFrame(seq=0, time_boot_us=rig.scene.t_us(0), pixels=np.zeros((256, 320), np.uint8))
    with pytest.raises(FrameRejected, match="320 x 256"):
        rig.pipe.process(small)
    assert rig.counter.counts == {"frame_dims_mismatch": 1}


def test_a_change_of_encoding_mid_stream_is_counted_once_per_change():
    """A camera switching modes, or a second publisher on the frame key: the image chain's statistics start again
    (an audit saw its flat-field correction restart twice), and nothing said so."""
    rig = Rig()
    rig.run(3)
    k = 3
    rig.feed_until(rig.scene.t_us(k) + 45_000)
    wide = rig.scene.frame(k)
    rig.pipe.process(IrFrame(seq=wide.seq, time_boot_us=wide.time_boot_us, pixels=wide.pixels.astype(np.uint16) * 257))
    rig.step(4)
    assert rig.counter.counts.get("frame_encoding_changed") == 2  # mono8 -> mono16 -> mono8
    # every frame was taken: none of the frame_* keys counted is a refusal (the status's frames.rejected counted
    # these changes as refused frames)
    from onboard.pipeline.frame_pipeline import ACCEPTED_FRAME_EVENTS

    assert {k for k in rig.counter.counts if k.startswith("frame_")} <= ACCEPTED_FRAME_EVENTS


def test_a_resent_frame_with_other_pixels_is_counted_apart_from_an_exact_duplicate():
    """A frame sent again with its seq and stamp but other pixels (a second sender on the key, or a corrupted resend)
    was refused as an ordinary duplicate, logged "frame seq N again": nothing said that two images claimed one
    capture, nor that the one taken may be the wrong one (a frame-stream audit)."""
    rig = Rig(ready_after=100)
    for k in (0, 1, 2):
        rig.step(k)
    taken = rig.scene.frame(2)
    other = IrFrame(seq=taken.seq, time_boot_us=taken.time_boot_us, pixels=np.roll(taken.pixels, 40, axis=1))
    with pytest.raises(FrameRejected) as ei:
        rig.pipe.process(other)
    assert ei.value.reason == "duplicate_conflict"
    with pytest.raises(FrameRejected) as ei:
        rig.pipe.process(taken)
    assert ei.value.reason == "duplicate"
    assert rig.counter.counts == {"frame_duplicate_conflict": 1, "frame_duplicate": 1}


def test_duplicate_and_out_of_order_frames_are_refused():
    rig = Rig(ready_after=100)
    for k in (0, 1, 3):
        rig.step(k)
    with pytest.raises(FrameRejected) as ei:
        rig.step(3)
    assert ei.value.reason == "duplicate"
    with pytest.raises(FrameRejected) as ei:
        rig.step(2)  # never seen, but after frame 3: out of order
    assert ei.value.reason == "out_of_order"
    assert rig.step(4).seq == 4
    assert rig.counter.counts == {"frame_duplicate": 1, "frame_out_of_order": 1}
    assert [c[0] for c in rig.est.calls] == ["add"] * 4  # refused frames never reach the estimator


def _feed_new_boot(rig: Rig, t0_us: int, t1_us: int) -> None:
    """The autopilot's telemetry after a reboot: the scene's samples restamped from ``t0_us`` on its new clock."""
    base = rig.scene.t_us(3)
    for t, p, v, q in rig.scene.telemetry(base, base + (t1_us - t0_us), 50.0):
        rig.pose.add_attitude(t - base + t0_us, q)
        if (t // 20_000) % 2 == 0:
            rig.pose.add_position_ned(t - base + t0_us, p, v)


def test_reboot_time_going_back_is_accepted_and_restarts_the_estimator():
    """The autopilot reboots: its telemetry and the frames' stamps go back together; three frames confirm it."""
    rig = Rig(ready_after=100)
    rig.run(3)
    rebooted = rig.scene.boot_us0 - 15_000_000  # 15 s earlier on the boot clock, seq moves on
    _feed_new_boot(rig, rebooted - 300_000, rebooted + 100_000)
    assert rig.pose.reboots == 1
    for k in range(2):  # the first frames of the new boot are outliers until three agree
        with pytest.raises(FrameRejected):
            rig.pipe.process(IrFrame(seq=3 + k, time_boot_us=rebooted + 33_333 * k, pixels=rig.scene.image(3)))
    assert rig.counter["frame_time_behind"] == 2
    tr = rig.pipe.process(IrFrame(seq=5, time_boot_us=rebooted + 66_666, pixels=rig.scene.image(3)))
    assert tr.time_boot_us == rebooted + 66_666 and tr.pose_valid  # posed on the new boot's telemetry
    assert rig.counter["frame_time_reset"] == 1
    assert ("reset", math.nan) in [(c[0], math.nan) for c in rig.est.calls]


def test_frames_stepped_away_from_the_telemetry_too_confirm_after_half_a_second_of_them():
    """The frames' stamps go back 15 s but the telemetry does not (none of a new boot yet): the frames find no pose
    at their stamps, and a clock step is believed only once they have run for APART_CONFIRM_US."""
    rig = Rig(ready_after=100)
    rig.run(3)
    stepped = rig.scene.boot_us0 - 15_000_000
    period = 33_333
    n_refused = -(-APART_CONFIRM_US // period)  # the run spans APART_CONFIRM_US with its next frame
    for k in range(n_refused):
        with pytest.raises(FrameRejected):
            rig.pipe.process(IrFrame(seq=3 + k, time_boot_us=stepped + period * k, pixels=rig.scene.image(3)))
    assert rig.counter["frame_time_behind"] == n_refused and rig.pipe.estimator_resets == 0
    k = n_refused
    tr = rig.pipe.process(IrFrame(seq=3 + k, time_boot_us=stepped + period * k, pixels=rig.scene.image(3)))
    assert tr.seq == 3 + k and not tr.pose_valid  # no telemetry at its stamp
    assert rig.counter["frame_time_reset"] == 1


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    n_bogus=st.integers(1, 14),
    offset_s=st.sampled_from([3600.0, -15.0, 5.0, -2.5, 1e5]),
    seq_jump=st.integers(1, 1000),
)
def test_a_burst_of_bogus_stamps_shorter_than_half_a_second_restarts_nothing(n_bogus, offset_s, seq_jump):
    """A sender's glitch: up to 14 consecutive frames (under APART_CONFIRM_US at 30 Hz) stamped far from both the
    stream and the telemetry, numbered on; each is refused and counted, the stream goes on with the same estimate."""
    rig = Rig(ready_after=3)
    rig.run(10)
    t_last = rig.pipe._admission.last_t_us
    offset_us = int(offset_s * US)
    # a stamp where the stream's rate puts its number is the next frame after a gap, not a glitch
    assume(abs(t_last + offset_us - rig.scene.t_us(9 + seq_jump)) > 2 * US)
    reason = "time_ahead" if offset_us > 0 else "time_behind"
    for i in range(n_bogus):
        bogus = IrFrame(seq=10 + seq_jump + i, time_boot_us=t_last + offset_us + 33_333 * i, pixels=rig.scene.image(10))
        with pytest.raises(FrameRejected) as ei:
            rig.pipe.process(bogus, 0)
        assert ei.value.reason == reason
    k = 10 + seq_jump + n_bogus
    rig.feed_until(rig.scene.t_us(10) + 45_000)
    tr = rig.pipe.process(rig.scene.frame(10, seq=k), 0)  # the next good frame, numbered on
    assert tr.seq == k and tr.pose_valid and tr.has_position
    assert rig.counter[f"frame_{reason}"] == n_bogus and rig.counter["frame_time_reset"] == 0
    assert rig.pipe.estimator_resets == 0


def test_sender_restart_with_sequence_going_back_is_accepted():
    rig = Rig(ready_after=100)
    rig.run(5)
    tr = rig.step(5, seq=0)
    assert tr.seq == 0 and rig.counter.counts == {"frame_sequence_reset": 1}


def test_a_stream_of_old_frames_is_taken_as_a_restart_after_n_in_a_row():
    """A sender restarted: its numbering from 0 again, its clock mapping 0.2 s behind (within the threshold)."""
    rig = Rig(ready_after=100)
    rig.run(10)
    n = rig.config.input.sequence_restart_count
    behind_us = 200_000
    for i in range(n - 1):
        with pytest.raises(FrameRejected) as ei:
            rig.pipe.process(rig.scene.frame(10 + i, seq=i, time_boot_us=rig.scene.t_us(10 + i) - behind_us))
        assert ei.value.reason == "out_of_order"
    tr = rig.pipe.process(rig.scene.frame(10 + n - 1, seq=n - 1, time_boot_us=rig.scene.t_us(10 + n - 1) - behind_us))
    assert tr.seq == n - 1
    assert rig.counter["frame_out_of_order"] == n - 1 and rig.counter["frame_stream_restart"] == 1
    with pytest.raises(FrameRejected) as ei:  # the original frames again: exact duplicates
        rig.pipe.process(rig.scene.frame(3))
    assert ei.value.reason in ("duplicate", "out_of_order")


def test_resent_old_frames_are_duplicates_and_never_restart_the_stream():
    rig = Rig(ready_after=100)
    rig.run(10)
    for i in range(10):
        with pytest.raises(FrameRejected) as ei:
            rig.pipe.process(rig.scene.frame(i))
        assert ei.value.reason == "duplicate"
    assert rig.step(10).seq == 10 and rig.counter["frame_stream_restart"] == 0


# --------------------------------------------------------------------------- bad telemetry: counted, frames survive


def test_nan_and_zero_quaternions_and_gps_dropout_are_counted_and_frames_keep_their_pose():
    rig = Rig(ready_after=100)
    rig.run(3)
    t = rig.fed_us
    assert not rig.pose.add_attitude(t + 1000, (math.nan, 0.0, 0.0, 1.0))
    assert not rig.pose.add_attitude(t + 2000, (0.0, 0.0, 0.0, 0.0))
    assert not rig.pose.add_position(t + 3000, 0.0, 0.0, 50.0)  # GNSS dropout sentinel
    tracks = rig.run(5, start=3)
    assert all(tr.pose_valid for tr in tracks)
    assert {k: v for k, v in rig.counter.counts.items()} == {
        "attitude_not_finite": 1,
        "attitude_zero": 1,
        "position_zero": 1,
    }


def test_telemetry_gap_gives_2d_tracks_and_predictions_then_recovers():
    rig = Rig(ready_after=2)
    rig.run(5)
    gap0, gap1 = rig.scene.t_us(5) - 50_000, rig.scene.t_us(20)
    rig.feed_until(rig.scene.t_us(25), skip=lambda t: gap0 <= t <= gap1)  # 0.55 s without telemetry
    tracks = [rig.pipe.process(rig.scene.frame(k), 0) for k in range(5, 20)]
    assert all(tr.state == "tracking" and tr.u_px is not None for tr in tracks)
    assert not any(tr.pose_valid for tr in tracks)
    assert rig.counter["pose_attitude_gap"] + rig.counter["pose_position_gap"] == 15
    kinds = [c[0] for c in rig.est.calls]
    assert kinds[:5] == ["add"] * 5 and kinds[5:20] == ["predict"] * 15  # no pose: predict, never add
    after = rig.run(3, start=25)
    assert all(tr.pose_valid for tr in after) and [c[0] for c in rig.est.calls][-3:] == ["add"] * 3


def test_a_coasting_centre_makes_no_line_of_sight():
    """A coasting tracker's centre is its prediction, whose error no pixel sigma bounds: a line of sight went out
    of it with the measurement's sigma (3-66 deg off after a gap in the telemetry or the frames, while it said
    0.11 deg).  The objects chain (the default) shows its prediction; the track keeps it, without a line of sight."""
    rig = Rig(config=OnboardConfig())
    measured = rig.run(12)
    assert measured[-1].measurement_valid and measured[-1].los is not None
    after = [rig.step(k, with_target=False) for k in range(12, 20)]
    coasting = [tr for tr in after if tr.state == "coasting"]
    assert coasting and all(tr.u_px is not None and tr.pose_valid for tr in coasting)
    assert all(tr.los is None and not tr.measurement_valid for tr in coasting)


def test_a_lost_target_resets_the_estimator_and_nulls_the_position():
    rig = Rig(ready_after=2)
    rig.run(5)
    lost = [rig.step(k, with_target=False) for k in range(5, 5 + rig.config.imaging.lost_frames + 1)]
    assert lost[0].state == "coasting" and lost[-1].state in ("lost", "searching")
    assert lost[-1].track_id is None and not lost[-1].has_position
    assert "reset" in [c[0] for c in rig.est.calls]
    back = rig.run(2, start=40)
    assert back[-1].track_id == 2 and back[-1].state == "tracking"  # a new association, a new id


def test_estimator_failure_is_counted_and_never_stops_the_frames():
    rig = Rig(fail=True)
    tracks = rig.run(4)
    assert all(tr.state == "tracking" and not tr.has_position for tr in tracks)
    assert rig.counter["estimator_error"] == 4


def test_pose_wait_hook_is_called_with_the_capture_time_after_imaging():
    order = []
    rig = Rig()
    update = rig.pipe.tracker.update
    rig.pipe.tracker.update = lambda px: (order.append("imaging"), update(px))[1]
    rig.pipe.pose_wait = lambda t_us: order.append(("wait", t_us))
    rig.step(0)
    assert order == ["imaging", ("wait", rig.scene.t_us(0))]
    assert len(rig.pipe.pose_wait_ms) == 1 and len(rig.pipe.processing_ms) == 1


@pytest.mark.parametrize("config, first_tracked", [(single_chain(), 0), (OnboardConfig(), 11)])
def test_without_estimator_or_pose_source_the_pipeline_gives_2d_tracks(config, first_tracked):
    """The single chain tracks from the first frame, the default objects chain once its object is confirmed
    (0.37 s at 30 Hz), pose or no pose."""
    scene = SyntheticScene()
    pipe = FramePipeline(config, None, make_tracker(config), None)
    tracks = [pipe.process(scene.frame(k)) for k in range(first_tracked + 5)]
    assert [tr.state for tr in tracks] == ["searching"] * first_tracked + ["tracking"] * 5
    tr, k = tracks[-1], len(tracks) - 1
    assert not tr.pose_valid and tr.origin is None and not tr.has_position
    u_px, v_px = scene.uv((scene.t_us(k) - scene.boot_us0) / 1e6)
    assert math.hypot(tr.u_px - u_px, tr.v_px - v_px) < 0.5


# --------------------------------------------------------------------------- Track noun and JSON


def _track(**kw) -> Track:
    """positioned_track (uav1, tracking, observable, origin (32, 118.8, 0), 80 m up) with this file's numbers."""
    image = dict(seq=7, time_boot_us=123, u_px=10.5, v_px=20.25, bbox=(5.0, 15.0, 16.0, 16.0))
    where = dict(lon_deg=118.801, p_ned_m=(110.0, 95.0, -80.0), v_ned_mps=(3.0, 4.0, 0.0), range_m=150.0)
    sigmas = dict(cov_p_ned_m2=np.diag([4.0, 9.0, 16.0]), cov_v_ned_m2ps2=np.diag([0.01, 0.04, 0.09]))
    estimator = dict(range_sigma_ratio=0.02, window_frames=90, model="cv")
    return positioned_track(**{**image, **where, **sigmas, **estimator, **kw})


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"state": "flying"}, "Track.state"),
        ({"u_px": None}, "both be set"),
        ({"u_px": math.nan}, "u_px must be a finite"),
        ({"track_id": 0}, "track_id"),
        ({"seq": -1}, "seq"),
        ({"time_boot_us": 1.5}, "time_boot_us"),
        ({"lat_deg": None}, "all set or all None"),
        ({"cov_p_ned_m2": np.eye(2)}, "3 x 3"),
        ({"cov_p_ned_m2": -np.eye(3)}, "negative variance"),
        ({"origin": None}, "needs its origin"),
        ({"bbox": (0, 0, -1, 3)}, "bbox width"),
        ({"lat_deg": 95.0}, "lat/lon out of range"),
    ],
)
def test_track_validation_names_the_field(kw, match):
    with pytest.raises(InputError, match=match):
        _track(**kw)


def test_json_has_no_nan_and_round_trips():
    tr = _track(range_sigma_ratio=math.inf)
    text = track_to_bytes(tr)
    j = json.loads(text)
    assert j["range_sigma_ratio"] is None  # inf is not JSON: null
    back = track_from_json(text)
    assert back.p_ned_m == tr.p_ned_m and np.allclose(back.cov_p_ned_m2, tr.cov_p_ned_m2)
    assert track_to_json(back)["sigma_vel_ned_mps"] == j["sigma_vel_ned_mps"]
    assert j["schema"] == "irtrack.track/2"
    assert track_from_json({**j, "schema": "irtrack.track/1"}).p_ned_m == tr.p_ned_m  # /1 still reads
    with pytest.raises(InputError, match="schema"):
        track_from_json({**j, "schema": "irtrack.track/3"})
    with pytest.raises(InputError, match="missing key 'state'"):
        track_from_json({k: v for k, v in j.items() if k != "state"})
    with pytest.raises(InputError, match="not JSON"):
        track_from_json(b"{nope")


finite = st.floats(-1e6, 1e6, allow_nan=False)


@settings(max_examples=80, deadline=None)
@given(
    u=finite,
    v=finite,
    n=finite,
    e=finite,
    d=finite,
    s=st.floats(0, 1e3),
    state=st.sampled_from(["tracking", "coasting"]),
    seq=st.integers(0, 2**32 - 1),
    t=st.integers(0, 2**63),
)
def test_json_round_trip_any_valid_track(u, v, n, e, d, s, state, seq, t):
    tr = _track(u_px=u, v_px=v, p_ned_m=(n, e, d), cov_p_ned_m2=np.eye(3) * s, state=state, seq=seq, time_boot_us=t)
    back = track_from_json(track_to_bytes(tr))
    j0, j1 = track_to_json(tr), track_to_json(back)
    assert j0 == j1


# --------------------------------------------------------------------------- MAVLink mapping


def test_image_status_is_normalised_and_flags_follow_the_state():
    tr = _track(u_px=320.0, v_px=128.0, bbox=(312.0, 120.0, 16.0, 16.0))
    f = image_status_fields(tr, 640, 512)
    assert (f["tracking_status"], f["tracking_mode"]) == (1, 2)  # ACTIVE, RECTANGLE
    assert math.isnan(f["point_x"]) and math.isnan(f["point_y"]) and math.isnan(f["radius"])  # not this mode's fields
    assert (f["rec_top_x"], f["rec_top_y"], f["rec_bottom_x"], f["rec_bottom_y"]) == (
        312 / 640,
        120 / 512,
        328 / 640,
        136 / 512,
    )
    pt = image_status_fields(tr, 640, 512, mode=1)  # POINT: point fields only, the object's radius
    assert (pt["tracking_mode"], pt["point_x"], pt["point_y"], pt["radius"]) == (1, 0.5, 0.25, 8 / 640)
    assert math.isnan(pt["rec_top_x"]) and math.isnan(pt["rec_bottom_y"])
    coast = image_status_fields(_track(state="coasting", measurement_valid=False, bbox=None), 640, 512)
    assert coast["tracking_status"] == 1 | 8 and coast["tracking_mode"] == 1  # ACTIVE|COASTING, POINT
    assert math.isnan(coast["radius"])  # no box: the radius is unknown
    edge = image_status_fields(_track(u_px=-3.0, bbox=(-10.0, 500.0, 20.0, 20.0)), 640, 512)
    assert edge["rec_top_x"] == 0.0 and edge["rec_bottom_y"] == 1.0  # clipped into [0, 1]
    assert image_status_fields(_track(u_px=-3.0, bbox=None), 640, 512)["point_x"] == 0.0
    idle = image_status_fields(None, 640, 512)
    assert idle["tracking_status"] == 0 and idle["tracking_mode"] == 0 and math.isnan(idle["point_x"])


def test_geo_status_accuracies_are_one_sigma_root_sum_squares():
    tr = _track()
    f = geo_status_fields(tr)
    assert f["h_acc_m"] == pytest.approx(math.sqrt(4 + 9)) and f["v_acc_m"] == pytest.approx(4.0)
    assert f["vel_acc_mps"] == pytest.approx(math.sqrt(0.01 + 0.04 + 0.09))
    assert (f["vel_n_mps"], f["vel_e_mps"], f["vel_d_mps"]) == (3.0, 4.0, 0.0)
    assert f["hdg_rad"] == pytest.approx(math.atan2(4.0, 3.0))
    # d(atan2(e, n)) = (-e dn + n de) / |v|^2: sigma^2 = (16 * 0.01 + 9 * 0.04) / 625
    assert f["hdg_acc_rad"] == pytest.approx(math.sqrt((16 * 0.01 + 9 * 0.04) / 625))
    assert f["dist_m"] == 150.0 and (f["lat_deg"], f["lon_deg"], f["alt_m"]) == (32.001, 118.801, 80.0)
    slow = geo_status_fields(_track(v_ned_mps=(0.05, 0.0, 0.0)))
    assert math.isnan(slow["hdg_rad"]) and math.isnan(slow["hdg_acc_rad"])  # speed below 2 sigma: no heading
    # the speed's sigma along north is 0.1 m/s: 0.15 m/s is within 2 sigma of standing still (no heading), 0.25 not
    assert math.isnan(geo_status_fields(_track(v_ned_mps=(0.15, 0.0, 0.0)))["hdg_rad"])
    north = geo_status_fields(_track(v_ned_mps=(0.25, 0.0, 0.0)))
    assert north["hdg_rad"] == 0.0 and north["hdg_acc_rad"] == pytest.approx(0.2 / 0.25)  # sigma_east / speed
    assert (
        geo_status_fields(
            _track(
                lat_deg=None,
                lon_deg=None,
                alt_m=None,
                p_ned_m=None,
                v_ned_mps=None,
                cov_p_ned_m2=None,
                cov_v_ned_m2ps2=None,
                range_m=None,
            )
        )
        is None
    )
    unobs = _track(observable=False)
    assert geo_status_fields(unobs) is None  # #276 only for observable positions by default
    assert geo_status_fields(unobs, observable_only=False)["h_acc_m"] == pytest.approx(math.sqrt(4 + 9))


# --------------------------------------------------------------------------- status


def test_rolling_stats_and_status_document():
    r = RollingStats(100)
    for x in range(1, 201):
        r.add(x)
    s = r.summary()
    assert (
        s["n"] == 100 and s["max"] == 200.0 and s["p50"] == pytest.approx(150.5) and s["p99"] == pytest.approx(199.01)
    )
    assert RollingStats().summary() == {"n": 0, "p50": None, "p99": None, "max": None}
    st_ = idle_status(
        uptime_s=3.0,
        frames_in=10,
        frames_processed=7,
        frames_dropped=1,
        frames_missing=3,
        frames_rejected=2,
        tracks_published=7,
        processing_ms=s,
        latency_ms=s,
        pose_wait_ms=s,
        rejected={"frame_magic": 2, "dropped_queue": 1},
        link={"state": "connected", "rates_confirmed": (31, 33), "heartbeat_age_s": math.nan},
        cpu_share=0.5,
        pipeline_cpu_share=0.25,
        last_track=_track(),
        estimator="x",
    )
    text = json.dumps(st_, allow_nan=False)
    back = json.loads(text)
    assert back["schema"] == STATUS_SCHEMA
    assert back["frames"] == {
        "in": 10,
        "missing": 3,
        "processed": 7,
        "dropped": 1,
        "rejected": 2,
        "published": 7,
        "queue_length": 0,
    }
    assert back["link"] == {"state": "connected", "rates_confirmed": [31, 33], "heartbeat_age_s": None}
    assert back["track"]["has_position"] is True and back["cpu"]["share"] == 0.5
    assert back["rejected"] == {"dropped_queue": 1, "frame_magic": 2}


def test_encode_of_scene_frames_is_irf1():
    scene = SyntheticScene()
    p = scene.payload(3)
    assert p[:4] == MAGIC and len(p) == 32 + 640 * 512
    assert encode_irframe(scene.frame(3)) == p


@pytest.mark.parametrize(
    ("offset_us", "reason"),
    [(3600 * 1_000_000, "time_ahead"), (-3600 * 1_000_000 // 1000, "time_behind"), (5_000_000, "time_ahead")],
    ids=["+1h", "-3.6s", "+5s"],
)
def test_a_single_far_frame_stamp_costs_one_frame(offset_us, reason):
    rig = Rig(ready_after=100)
    rig.run(5)
    n_resets = rig.pipe.estimator_resets
    t_last = rig.pipe._admission.last_t_us
    with pytest.raises(FrameRejected):
        rig.pipe.process(IrFrame(seq=5, time_boot_us=t_last + offset_us, pixels=rig.scene.image(5)))
    tr = rig.step(6)  # the next normal frame goes through, nothing restarted
    assert tr.seq == 6 and rig.pipe.estimator_resets == n_resets
    assert rig.counter[f"frame_{reason}"] == 1 and rig.counter["frame_time_reset"] == 0


def test_odd_frames_among_a_30hz_stream_are_each_counted_under_their_reason_and_restart_nothing():
    """Two duplicates (one sent late), two out of order, one stamped an hour ahead, one 1 ms after boot."""
    rig = Rig(ready_after=3)
    scene = rig.scene
    held = {14: scene.frame(14), 21: scene.frame(21)}  # delivered after their successors: out of order
    sent: list[tuple[str, IrFrame]] = []
    for k in range(40):
        if k in held:
            continue
        sent.append(("ok", scene.frame(k)))
        if k == 8:
            sent.append(("duplicate", scene.frame(8)))  # at once
        if k == 12:
            sent.append(("duplicate", scene.frame(5)))  # late
        if k == 16:
            sent.append(("out_of_order", held[14]))
        if k == 22:
            sent.append(("out_of_order", held[21]))
        if k == 27:  # seq 100 and 101: a sender's numbering moves on while its stamps are wrong
            sent.append(
                ("time_ahead", IrFrame(seq=100, time_boot_us=scene.t_us(27) + 3600 * US, pixels=scene.image(27)))
            )
        if k == 31:
            sent.append(("time_behind", IrFrame(seq=101, time_boot_us=1000, pixels=scene.image(31))))
    got = []
    for expected, frame in sent:
        rig.feed_until(frame.time_boot_us + 45_000 if expected == "ok" else rig.fed_us or 0)
        try:
            tr = rig.pipe.process(frame, 0)
            got.append(("ok", tr.seq))
        except FrameRejected as exc:
            got.append((exc.reason, frame.seq))
    assert [g[0] for g in got] == [e for e, _ in sent]
    assert {k: v for k, v in rig.counter.counts.items() if k.startswith("frame_")} == {
        "frame_duplicate": 2,
        "frame_out_of_order": 2,
        "frame_time_ahead": 1,
        "frame_time_behind": 1,
    }
    assert rig.pipe.estimator_resets == 0 and ("reset", math.nan) not in [(c[0], math.nan) for c in rig.est.calls]
    assert rig.pipe.frames_processed == 38 and rig.pipe.last_track.seq == 39


def test_a_stream_that_starts_with_a_far_stamp_is_judged_by_the_telemetry():
    rig = Rig(ready_after=100)
    rig.feed_until(rig.scene.t_us(0) + 45_000)
    for t_us, reason in ((rig.scene.t_us(0) + 3600 * US, "time_ahead"), (1000, "time_behind")):
        with pytest.raises(FrameRejected) as ei:
            rig.pipe.process(IrFrame(seq=0, time_boot_us=t_us, pixels=rig.scene.image(0)))
        assert ei.value.reason == reason
    assert [tr.seq for tr in rig.run(5)] == [0, 1, 2, 3, 4]
    assert rig.counter["frame_time_reset"] == 0 and rig.counter["frame_time_ahead"] == 1


def test_a_gnss_gap_keeps_the_line_of_sight_and_coasts_the_3d_estimate_without_feeding_the_window():
    rig = Rig(ready_after=5)
    rig.run(30)
    gap = (rig.scene.t_us(30), rig.scene.t_us(90))  # 2 s without position telemetry

    def in_gap(t):
        return gap[0] <= t < gap[1]

    adds_before = sum(1 for c in rig.est.calls if c[0] == "add")
    traces = []
    for k in range(30, 90):
        rig.feed_until(rig.scene.t_us(k) + 45_000, skip_position=in_gap)
        tr = rig.pipe.process(rig.scene.frame(k), 0)
        assert tr.los is not None and tr.has_position, k
        t_s = (rig.scene.t_us(k) - rig.scene.boot_us0) / 1e6
        err = np.asarray(tr.p_ned_m) - rig.scene.target(t_s)[0]
        C = np.asarray(tr.cov_p_ned_m2)
        assert err @ np.linalg.solve(C, err) < 3.0**2 * 3, k  # honest: well inside 3 sigma (3 dof)
        traces.append(np.trace(C))
    assert rig.pipe.last_position_age_s is not None and rig.pipe.last_position_age_s > 1.5
    assert rig.pipe.frames_coasted > 45  # all but the first few hundred ms, still within the assumed noise
    assert sum(1 for c in rig.est.calls if c[0] == "add") - adds_before < 15  # dead-reckoned poses never added
    assert traces[-1] > 2.0 * traces[10]  # the covariance grows with the gap
    rig.feed_until(rig.scene.t_us(91) + 45_000)  # position back
    n_add = sum(1 for c in rig.est.calls if c[0] == "add")
    tr = rig.step(91)
    assert rig.pipe.last_position_age_s < 0.1 and sum(1 for c in rig.est.calls if c[0] == "add") == n_add + 1


def test_a_frame_refused_before_the_withholding_step_records_the_codes_in_force():
    """What withheld a frame goes into its recording (irtrack.frame_input/1's withheld_because), which a replay sets
    before the frame: a frame refused before the withholding step had recorded none while the daemon withheld, so a
    replay that took it (a daemon-side failure it does not meet) published what the flight withheld."""
    rig = Rig()
    rig.pipe.withheld_because = ("camera_mismatch",)
    small = IrFrame(seq=0, time_boot_us=rig.scene.t_us(0), pixels=np.zeros((256, 320), np.uint8))
    with pytest.raises(FrameRejected):
        rig.pipe.process(small)
    assert rig.pipe.last_withheld == ("camera_mismatch",)
    rig.pipe.withheld_because = ()
    rig.pipe.process_payload(_good(rig, 1))
    assert rig.pipe.last_withheld == ()
