"""onboard.core.recent.Recent against a plain deque: the same newest items, and ``in`` says what the deque holds."""

from __future__ import annotations

from collections import deque

from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.core.recent import Recent


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 6), st.lists(st.one_of(st.integers(0, 8), st.none()), max_size=60))
def test_recent_holds_the_newest_items_and_knows_them_in_constant_time(maxlen, ops):
    recent, model = Recent(maxlen), deque(maxlen=maxlen)
    for op in ops:
        if op is None:  # a clear
            recent.clear()
            model.clear()
        else:
            recent.add(op)
            model.append(op)
        assert len(recent) == len(model) and [recent[i] for i in range(len(model))] == list(model)
        assert all((k in recent) == (k in model) for k in range(9))
