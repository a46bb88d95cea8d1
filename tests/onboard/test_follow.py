"""FOLLOW_TARGET (#144) encoding (onboard.io.follow): only observable positions; degE7, m AMSL, NED
velocity, eph / epv from the covariance; packs with pymavlink and decodes to the same numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onboard.core.errors import InputError
from onboard.io.follow import FOLLOW_TARGET_CAP_POS, FOLLOW_TARGET_CAP_VEL, follow_target
from onboard.io.mavlink_wire import FollowTarget, wire_roundtrip
from tests.onboard.test_camera_protocol import _track

ATOL_DEGE7 = 1  # rounding of lat/lon to 1e-7 deg
ATOL_M = 1e-4  # float32 on the wire


def _with_velocity_cov(tr):
    return type(tr)(**{**{k: getattr(tr, k) for k in tr.__dataclass_fields__}, "cov_v_ned_m2ps2": np.eye(3) * 0.04})


def test_observable_track_encodes_position_velocity_and_accuracies():
    tr = _with_velocity_cov(_track(observable=True))  # cov diag(4, 4, 1) m^2, v (1, 0, 0) m/s, time_boot_us 10
    target = follow_target(tr)
    assert target.est_capabilities == FOLLOW_TARGET_CAP_POS | FOLLOW_TARGET_CAP_VEL == 3
    back = wire_roundtrip(target.to_message())  # packed and parsed by pymavlink
    assert back.get_type() == "FOLLOW_TARGET" and back.timestamp == tr.time_boot_us // 1000
    assert (
        abs(back.lat - round(tr.lat_deg * 1e7)) <= ATOL_DEGE7 and abs(back.lon - round(tr.lon_deg * 1e7)) <= ATOL_DEGE7
    )
    assert back.alt == pytest.approx(tr.alt_m, abs=ATOL_M)
    assert list(back.vel) == pytest.approx([1.0, 0.0, 0.0], abs=ATOL_M)
    assert list(back.position_cov) == pytest.approx([math.sqrt(8.0), 1.0, 0.0], abs=ATOL_M)  # eph = sqrt(4 + 4), epv
    # common.xml: attitude_q "(1 0 0 0 for unknown)", acc and rates "(0 0 0 for unknown)"; ACCEL, ATT + RATES clear
    assert list(back.attitude_q) == [1.0, 0.0, 0.0, 0.0] and list(back.acc) == list(back.rates) == [0.0, 0.0, 0.0]
    assert back.est_capabilities == 3
    decoded = FollowTarget.from_message(back)
    assert decoded.h_acc_m == pytest.approx(math.sqrt(8.0), abs=ATOL_M) and decoded.v_acc_m == pytest.approx(1.0)


def test_timestamp_is_the_capture_time_in_ms_on_the_boot_clock():
    tr = _track()
    tr2 = type(tr)(**{**{k: getattr(tr, k) for k in tr.__dataclass_fields__}, "time_boot_us": 123_456_789})
    assert follow_target(tr2).to_message().timestamp == 123_456


def test_timestamp_is_the_time_the_position_is_of_the_capture_less_the_compensation():
    """With a camera latency compensated, the track's 3-D is of its stamp less compensated_us: the autopilot's follow
    estimator had been told a time 40 ms later than the position's."""
    tr = _track(observable=True)
    fields = {k: getattr(tr, k) for k in tr.__dataclass_fields__}
    tr2 = type(tr)(**{**fields, "time_boot_us": 123_456_789, "compensated_us": 40_000})
    assert follow_target(tr2).to_message().timestamp == 123_416


def test_a_velocity_without_a_covariance_is_sent_as_unknown():
    """The pipeline drops a non-finite velocity covariance: that velocity is not vouched for, so no VEL bit and
    the velocity common.xml calls unknown, (0, 0, 0)."""
    tr = _track(observable=True)  # v (1, 0, 0) m/s, no velocity covariance
    assert tr.cov_v_ned_m2ps2 is None
    back = wire_roundtrip(follow_target(tr).to_message())
    assert back.est_capabilities == FOLLOW_TARGET_CAP_POS and list(back.vel) == [0.0, 0.0, 0.0]


@pytest.mark.parametrize(
    "caps, vel, field",
    [
        (FOLLOW_TARGET_CAP_POS | 1 << 2, (0.0, 0.0, 0.0), "est_capabilities"),  # ACCEL: never estimated
        (FOLLOW_TARGET_CAP_POS | 1 << 3, (0.0, 0.0, 0.0), "est_capabilities"),  # ATT + RATES: never estimated
        (FOLLOW_TARGET_CAP_POS, (1.0, 0.0, 0.0), "v_ned_mps"),  # a velocity without the VEL bit
    ],
)
def test_the_encoder_refuses_bits_for_what_is_not_sent(caps, vel, field):
    with pytest.raises(InputError, match=field):
        FollowTarget(0, 47.0, 8.0, 500.0, vel, 2.0, 1.0, caps).to_message()


@pytest.mark.parametrize("kw", [dict(observable=False), dict(position=False), dict(state="lost", position=False)])
def test_nothing_without_an_observable_position(kw):
    assert follow_target(_track(**kw)) is None
    assert follow_target(None) is None


class _FollowLink:
    def __init__(self) -> None:
        self.sent: list[FollowTarget] = []

    def send_follow_target(self, target: FollowTarget) -> bool:
        self.sent.append(target)
        return True


def _follow_service(enabled: bool):
    from onboard.app.config import build_config
    from onboard.app.service import OnboardService
    from tests.fakes import FakeClock

    cfg = build_config(
        {
            "estimator": {"worker": "inline"},  # follow acts on the 3-D track: never started here
            "output": {"health_file": None},
            "follow": {"enabled": enabled, "rate_hz": 2.0},
        }
    )
    clock = FakeClock()
    svc = OnboardService(cfg, clock=clock, clock_ns=clock.ns)
    svc.link = _FollowLink()
    return svc, clock


def test_the_service_sends_follow_target_paced_and_only_for_observable_fresh_tracks():
    svc, clock = _follow_service(True)
    t0 = clock()
    svc.newest.value = (_track(observable=False), t0)
    assert not svc.follow_step(t0)  # unobservable: nothing
    svc.newest.value = (_track(observable=True), t0)
    assert svc.follow_step(t0) and len(svc.link.sent) == 1
    assert not svc.follow_step(t0 + 0.2)  # 2 Hz: not before 0.5 s
    assert svc.follow_step(t0 + 0.5) and len(svc.link.sent) == 2
    assert not svc.follow_step(t0 + 5.0)  # the track is stale (output.track_stale_s, 1 s)
    assert svc.link.sent[0] == follow_target(_track(observable=True))


def test_follow_target_is_off_by_default():
    svc, clock = _follow_service(False)
    svc.newest.value = (_track(observable=True), clock())
    assert not svc.follow_step(clock()) and svc.link.sent == []
