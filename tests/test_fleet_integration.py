"""Two drones end to end on 127.0.0.1: a zenoh router, two onboard daemons (config/fleet/uav1.yaml,
uav2.yaml), the fusion node and ``groundsim run`` flying F1's first seconds, as ``python -m bench.fleet
--flight F1`` runs them (:mod:`bench.fleet_flight`).  The fleet track must name both vehicles, sit on the
true target and be called observable where neither vehicle alone is; every child is gone afterwards.
No timing is asserted (the latency is the bench's number)."""

from __future__ import annotations

import math
import os

import pytest

from bench.fleet_flight import VEHICLES, FlightRecord, plan_flight, run_flight, score_flight
from tests.process_helpers import descendants, kill_all, wait_gone

pytestmark = pytest.mark.integration

FLIGHT_S = 3.0  # F1's first seconds: both vehicles track from their chains' confirmation, ~0.4 s in
FUSED_MAX_ERR_RATIO = 0.02  # 2 % of range: ~4x the median goal, 30x below a lone vehicle's guess
EXIT_TIMEOUT_S = 10.0


def test_two_daemons_and_the_fusion_triangulate_f1(tmp_path):
    rec = FlightRecord(truth={})
    try:
        run_flight(plan_flight("F1", 0, tmp_path, duration_s=FLIGHT_S), drain_s=1.0, record=rec)
    finally:
        kill_all(rec.pids)
    assert rec.pids and wait_gone(set(rec.pids), EXIT_TIMEOUT_S) == []
    assert not (descendants(os.getpid()) & set(rec.pids))

    both = [m for _, m in rec.fleet if {c["vehicle"] for c in m["vehicles"]} == set(VEHICLES)]
    assert both, f"no fleet track with both vehicles among {len(rec.fleet)}"
    for m in both:
        assert m["schema"] == "irtrack.fleet_track/1"
        assert all(c["rays"] >= 1 and c["range_m"] > 0 for c in m["vehicles"])
    # what `onboard.watch --vehicle fleet` prints of them: the fusion's own payloads, read as a watcher reads them
    import json

    from onboard.app.watch import _fleet_track, format_fleet_track

    line = format_fleet_track(_fleet_track(json.dumps(both[-1]).encode()))
    assert f"target {both[-1]['target_id']}" in line and " UTC " in line, line
    assert sorted(line.split("  from ")[1].split("  ")[0].split(", ")) == sorted(VEHICLES), line
    for v in VEHICLES:  # the daemons' own tracks came through the same router
        assert any(obj.get("los_ned") is not None for _, obj in rec.tracks.get(v, []))

    score = score_flight(rec)
    assert score["fleet_tracks_both"] >= 1
    assert score["median_err_ratio"] <= FUSED_MAX_ERR_RATIO, score
    assert score["observable_share"] > 0.5, score
    for v in VEHICLES:  # straight and level: no vehicle ranges the target alone
        share = score[f"{v}_alone_observable_share"]
        assert math.isnan(share) or share == 0.0, score
