"""Suite-wide fixtures."""

from __future__ import annotations

import signal

import pytest

try:  # BLAS threads contend badly on small shared machines (a MAP solve ran ~9x slower with them)
    from threadpoolctl import threadpool_limits
except ImportError:  # a dev dependency; without it the tests only run slower
    threadpool_limits = None


# A shell that starts a job in the background (`make test &`, `nohup`) passes it SIGINT ignored, and an
# ignored signal stays ignored across exec: every child the tests start would then shrug off the Ctrl-C that
# the interrupt tests send it (five of them failed so in a background CI dry run). Tests own their children's
# signals: SIGINT is caught here, so that the children start with its default action, as from a terminal.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session", autouse=True)
def _one_blas_thread():
    """Every test in-process on one BLAS thread, as the daemon and the benchmarks run."""
    if threadpool_limits is None:
        yield
        return
    with threadpool_limits(limits=1):
        yield


@pytest.fixture(scope="session")
def recorded_p1_flight(tmp_path_factory):
    """One closed-loop P1 flight, recorded: the daemon (inline estimator, ``--record``) and the simulator
    (``--record``, real time, 10 s) on 127.0.0.1 (:func:`tests.onboard.test_record_daemon.record_pair`).

    Shared by the recording and the replay tests, which only read it: a recording costs 15-20 s of real
    time, and one flight serves both as well as two would.  (The flight report's test records a shorter
    flight of its own: the report replays the whole recording twice, so 10 s would cost it about what the
    recording saves.)"""
    from tests.onboard.test_record_daemon import record_pair

    return record_pair(tmp_path_factory.mktemp("recorded_p1_flight"))
