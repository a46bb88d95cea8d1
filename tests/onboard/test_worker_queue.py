"""onboard.io.worker_queue: a worker's loop takes the items oldest first, each outside the lock, and ends on stop
with what is still queued left there."""

from __future__ import annotations

import threading
from collections import deque

from onboard.io.worker_queue import items_until_stopped, stop_and_join

WAIT_S = 10.0  # a hang guard only


def test_items_come_oldest_first_outside_the_lock_and_the_loop_ends_on_stop():
    cond = threading.Condition(threading.Lock())
    q: deque = deque([1, 2])
    state = {"stop": False}
    taken: list[int] = []
    for item in items_until_stopped(cond, q, lambda: state["stop"]):
        assert cond.acquire(blocking=False)  # the caller works on an item without the queue's lock held
        cond.release()
        taken.append(item)
        if item == 2:
            with cond:
                q.extend([3, 4])
                state["stop"] = True
    assert taken == [1, 2] and list(q) == [3, 4]


def test_a_waiting_worker_wakes_for_an_item_and_for_the_stop():
    cond = threading.Condition(threading.Lock())
    q: deque = deque()
    state = {"stop": False}
    taken: list[str] = []
    got_one = threading.Event()

    def worker() -> None:
        for item in items_until_stopped(cond, q, lambda: state["stop"]):
            taken.append(item)
            got_one.set()

    th = threading.Thread(target=worker)
    th.start()
    with cond:
        q.append("frame")
        cond.notify_all()
    assert got_one.wait(WAIT_S)
    with cond:
        state["stop"] = True
        cond.notify_all()
    th.join(WAIT_S)
    assert not th.is_alive() and taken == ["frame"]


def test_stop_and_join_wakes_a_waiting_worker_and_says_it_ended():
    """The worker waits with an hour's timeout: it ends only because the stop woke it (the join is a hang guard)."""
    cond = threading.Condition(threading.Lock())
    stop = threading.Event()
    waiting = threading.Event()

    def worker() -> None:
        with cond:
            while not stop.is_set():
                waiting.set()
                cond.wait(3600.0)

    th = threading.Thread(target=worker)
    th.start()
    assert waiting.wait(WAIT_S)
    assert stop_and_join(cond, stop, th, WAIT_S) is True
    assert stop.is_set() and not th.is_alive()


def test_stop_and_join_says_when_the_worker_is_still_running():
    cond = threading.Condition(threading.Lock())
    stop, release = threading.Event(), threading.Event()
    th = threading.Thread(target=lambda: release.wait(WAIT_S))  # busy with an item: deaf to the stop
    th.start()
    try:
        assert stop_and_join(cond, stop, th, 0.01) is False
        assert stop.is_set() and th.is_alive()
    finally:
        release.set()
        th.join(WAIT_S)


def test_stop_and_join_of_a_worker_never_started_only_sets_the_stop():
    cond, stop = threading.Condition(threading.Lock()), threading.Event()
    assert stop_and_join(cond, stop, None, WAIT_S) is True and stop.is_set()
