"""Frames lost on the way to the daemon, counted from the gaps in their sequence numbers (ArrivalGaps)."""

from __future__ import annotations

from hypothesis import assume, given
from hypothesis import strategies as st

from onboard.pipeline.admission import SEQ_MOD, ArrivalGaps


def _count(seqs, **kw) -> int:
    gaps = ArrivalGaps(**kw)
    for s in seqs:
        gaps.see(s % SEQ_MOD)
    return gaps.missing


@given(
    start=st.integers(0, SEQ_MOD - 1),
    kept=st.lists(st.booleans(), min_size=2, max_size=300),
    swaps=st.lists(st.integers(1, 298), max_size=20),
    repeats=st.lists(st.integers(0, 298), max_size=10),
)
def test_the_frames_lost_between_the_first_and_the_newest_are_counted_through_wraps_and_reordering(
    start, kept, swaps, repeats
):
    """Frames start.. start+n, some lost, some neighbours swapped on the way, some sent twice (each late one within
    the reorder window of the newest before it; the numbering may wrap past 2**32): missing = the numbers between
    the first and the newest arrived that never came."""
    arrived = [start + i for i, k in enumerate(kept) if k]
    assume(len(arrived) >= 2)
    lost = arrived[-1] - arrived[0] + 1 - len(arrived)
    for i in swaps:
        if i + 1 < len(arrived):
            arrived[i], arrived[i + 1] = arrived[i + 1], arrived[i]
    for i in sorted(repeats, reverse=True):
        if i < len(arrived):
            arrived.insert(i + 1, arrived[i])
    newest = arrived[0]
    for s in arrived[1:]:
        assume(s > newest or newest - s <= ArrivalGaps().reorder)
        newest = max(newest, s)
    assert _count(arrived) == lost


def test_a_duplicate_changes_nothing_and_a_late_frame_is_found():
    assert _count([10, 11, 11, 12]) == 0
    assert _count([10, 13]) == 2
    assert _count([10, 13, 11]) == 1  # 11 came late
    assert _count([10, 13, 11, 12]) == 0
    assert _count([10, 11, 13, 11]) == 1  # 11 again: it had arrived, 12 is still missing
    assert _count([10, 13, 12, 12]) == 1


def test_a_sender_numbering_anew_is_not_frames_lost():
    """A jump forward beyond max_gap, or back beyond the reorder window, is a restart: nothing counted, and the
    frames after it count from the new numbers."""
    assert _count([5, 6, 7, 10_000_000, 10_000_001, 10_000_003]) == 1
    assert _count([500, 501, 0, 1, 3]) == 1
    assert _count([SEQ_MOD - 2, SEQ_MOD - 1, 1]) == 1  # 0 lost across the wrap
