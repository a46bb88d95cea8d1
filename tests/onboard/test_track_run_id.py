"""The track's ``run_id``: the daemon's run, on the wire and back."""

from __future__ import annotations

import json

import pytest
from hypothesis import given
from hypothesis import strategies as st

from onboard.core.errors import InputError
from onboard.core.track import RUN_ID_HEX_DIGITS, Track, is_run_id, new_run_id, track_from_json, track_to_bytes


def _track(**kw) -> Track:
    return Track(vehicle="uav1", seq=1, time_boot_us=1_000_000, state="searching", pose_valid=False, **kw)


def test_a_new_run_id_is_16_hex_digits_and_another_each_time():
    ids = {new_run_id() for _ in range(100)}
    assert len(ids) == 100 and all(is_run_id(i) and len(i) == RUN_ID_HEX_DIGITS for i in ids)


@given(st.text(max_size=20) | st.integers() | st.none() | st.binary(max_size=8) | st.lists(st.integers(), max_size=2))
def test_a_run_id_is_refused_unless_it_is_16_lower_case_hex_digits(value):
    if value is None or is_run_id(value):
        assert _track(run_id=value).run_id == value
    else:
        with pytest.raises(InputError, match="run_id"):
            _track(run_id=value)


def test_run_id_goes_out_and_comes_back_and_an_older_track_without_it_reads_as_none():
    run = new_run_id()
    obj = json.loads(track_to_bytes(_track(run_id=run)))
    assert obj["run_id"] == run and track_from_json(obj).run_id == run
    del obj["run_id"]
    assert track_from_json(obj).run_id is None
    with pytest.raises(InputError, match="run_id"):  # upper case is not how a daemon writes it
        track_from_json({**obj, "run_id": "00000000000000AB"})
