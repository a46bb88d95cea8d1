"""The newest items of a stream in order, with a constant-time ``in`` (pure): frame admission and the fleet
fusion's stream check both tell a repeated ``(seq, time)`` from a new one among a stream's last few seconds."""

from __future__ import annotations

from collections import deque
from collections.abc import Hashable

__all__ = ["Recent"]


class Recent:
    """The newest ``maxlen`` items, oldest first (``recent[0]``, ``recent[-1]``, ``len``), and ``item in recent`` in
    constant time (a count per item: an item may be in it more than once)."""

    __slots__ = ("_items", "_counts")

    def __init__(self, maxlen: int) -> None:
        self._items: deque = deque(maxlen=maxlen)
        self._counts: dict[Hashable, int] = {}

    def add(self, item: Hashable) -> None:
        items, counts = self._items, self._counts
        if len(items) == items.maxlen:  # the oldest leaves as this one comes
            old = items[0]
            n = counts[old] - 1
            if n:
                counts[old] = n
            else:
                del counts[old]
        items.append(item)
        counts[item] = counts.get(item, 0) + 1

    def clear(self) -> None:
        self._items.clear()
        self._counts.clear()

    def __contains__(self, item: object) -> bool:
        return item in self._counts

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i: int):
        return self._items[i]
