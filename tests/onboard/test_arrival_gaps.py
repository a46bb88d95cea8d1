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


def _interleaved(a0: int, b0: int, n: int) -> list[int]:
    """Two senders' frames alternating on the key, each numbering its own from ``a0`` and ``b0``."""
    return [s for i in range(n) for s in (a0 + i, b0 + i)]


def test_two_senders_interleaving_their_numberings_lose_no_frame_and_come_back_to_each_in_turn():
    """Two cameras on one key, one numbering 300 ahead of the other: each jump between them was counted as the
    frames in between lost (about 300 at every other frame); each counts its own gaps, and every frame after the
    first two goes back to a numbering seen before."""
    gaps = ArrivalGaps()
    for s in _interleaved(300, 0, 180):
        gaps.see(s)
    assert gaps.missing == 0
    assert gaps.returns == 2 * 180 - 2
    seqs = _interleaved(300, 0, 180)
    del seqs[101], seqs[50]  # one frame of each camera lost
    assert _count(seqs) == 2


def test_a_second_numbering_a_little_ahead_is_not_a_gap_of_the_first():
    """The second sender's first frame lies within max_gap ahead: taken as a step of the first numbering until the
    next frame, behind it, shows it was the other's."""
    assert _count(_interleaved(300, 600, 60)) == 0
    assert _count([*range(300, 310), *range(600, 602), *range(310, 320)]) == 0


def test_a_sender_restarting_is_no_return():
    """A restart leaves its old numbering for good: no return, whatever the jump; one late frame of the old
    numbering, as the new one starts, is one return (or two)."""
    gaps = ArrivalGaps()
    for s in [*range(4990, 5000), *range(0, 100)]:
        gaps.see(s)
    assert (gaps.returns, gaps.missing) == (0, 0)
    gaps = ArrivalGaps()
    for s in [*range(4990, 4999), 0, 4999, *range(1, 100)]:
        gaps.see(s)
    assert (gaps.returns, gaps.missing) == (2, 0)


def test_more_senders_than_the_numberings_followed_still_come_back_as_returns():
    """Five senders in turn on one key, more than MAX_NUMBERINGS: each frame's numbering had been dropped for the
    frame before, so every frame started one anew and none was a return (0 after 500 frames): frame_sources, which
    reads the returns, never said so and their frames' lines of sight went out.  A numbering dropped while its
    sender still publishes (within forget_after) is counted as a return; a sender restarting is still none."""
    from onboard.pipeline.admission import MAX_NUMBERINGS

    for senders in range(2, MAX_NUMBERINGS + 3):
        gaps = ArrivalGaps()
        for i in range(100):
            for j in range(senders):
                gaps.see(j * 100_000 + i)
        assert gaps.returns >= 100 * senders - 2 * senders, (senders, gaps.returns)
        assert gaps.missing == 0
    gaps = ArrivalGaps()
    for start in range(0, 10 * 100_000, 100_000):  # one sender restarting ten times, 100 frames each
        for i in range(100):
            gaps.see(start + 5_000 + i)
    assert gaps.returns == 0  # at most three of its old numberings within forget_after: none dropped


def _count_with_unreadable(events, **kw) -> int:
    """``events``: a sequence number, or None for a payload that arrived with no readable number (refused as too
    large by its length before its header was read, or shorter than the header)."""
    gaps = ArrivalGaps(**kw)
    for s in events:
        if s is None:
            gaps.unnumbered()
        else:
            gaps.see(s % SEQ_MOD)
    return gaps.missing


def test_a_frame_that_arrived_unreadable_in_a_gap_is_not_also_counted_missing():
    """A frame refused before its number could be read (counted as refused) arrived: the gap it leaves is one frame
    fewer lost on the way.  It explains a missing number only in the gap it arrived in: none in order after it, and
    never more than the gap."""
    assert _count_with_unreadable([10, None, 12]) == 0  # 11 arrived too large
    assert _count_with_unreadable([10, None, None, 13]) == 0
    assert _count_with_unreadable([10, None, 14]) == 2  # 3 gone, one of them arrived unreadable
    assert _count_with_unreadable([10, None, 11, 13]) == 1  # not 11's gap: the next one is a frame lost
    assert _count_with_unreadable([10, None, None, None, 12]) == 0  # never below what the gap holds
    assert _count_with_unreadable([10, 12, None, 11]) == 0  # a late frame is still found
    assert _count_with_unreadable([None, 10, 12]) == 1  # before the first frame: no gap to explain


@given(
    kept=st.lists(st.sampled_from(["ok", "lost", "unreadable"]), min_size=2, max_size=200),
)
def test_missing_counts_the_frames_that_never_arrived_whatever_arrived_unreadable(kept):
    """Frames 1..n, each arrived, lost, or arrived unreadable: missing = those lost between the first and the last
    frame that arrived readable."""
    readable = [i for i, k in enumerate(kept) if k == "ok"]
    assume(len(readable) >= 2)
    first, last = readable[0], readable[-1]
    lost = sum(1 for k in kept[first:last] if k == "lost")
    events = [i + 1 if k == "ok" else None for i, k in enumerate(kept) if k != "lost"]
    assert _count_with_unreadable(events) == lost
