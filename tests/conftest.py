"""Suite-wide fixtures."""

from __future__ import annotations

import logging
import os
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


# `make test` runs the suite on two pytest-xdist workers (``-n 2 --dist loadgroup``).  The tests that start
# processes (marked ``integration``: closed-loop flights paced in real time, daemons, Dask clusters; or
# ``multicore``: a process pool) all go to one worker, one after the other as in a serial run: two real-time
# flights at once on the two cores would test the machine rather than the code (the flights of
# tests/test_integration.py alone take 1.5 cores), and a session fixture they share (``recorded_p1_flight``) is
# made once.  The other worker meanwhile runs the in-process tests (``slow`` ones too: one core, no real time),
# which a serial run made wait while a flight slept through its real time, and the ``subprocess`` ones (short-lived
# children, no socket, no real time: one core like an in-process test; the process group is the suite's critical
# path, 363 of its 380 s, while the other worker idled for its last 150 s).
PROCESS_GROUP = "processes"
PROCESS_MARKERS = ("integration", "multicore")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items):
    for item in items:
        if any(item.get_closest_marker(m) for m in PROCESS_MARKERS):
            item.add_marker(pytest.mark.xdist_group(PROCESS_GROUP))
            # first of the test's fixtures (a usefixtures mark added after collection is not read): before the
            # module-scoped ones that start the processes.  Not for the subprocess tests: their short-lived children
            # wait on no deadline a compile could miss, and on the other worker the warm ran beside this one's,
            # compiling the same kernels a second time on a fresh clone (22 s of its CI run)
            item.fixturenames.insert(0, "_compiled_kernels")


@pytest.fixture(scope="session")
def _compiled_kernels():
    """The daemon's numba kernels and the simulator's clean-sky ones in numba's cache before a test starts
    processes (groundsim/app/warm.py; ``integration`` and ``multicore`` tests), once per worker.  On a fresh clone nothing is cached: four daemons
    started at once (tests/test_integration.py's flights) each compiled ~13 s of CPU on two cores and published
    no status within the tests' 30 s, so that module failed when run first or alone, and passed in the whole
    suite only because earlier tests had filled the cache.  Cached, this costs about a second."""
    from groundsim.app.warm import warm_onboard, warm_simulator

    warm_onboard()
    warm_simulator(("P1",))


#: the shell's IRTRACK_* variables the suite keeps (its own switches: no skips, the golden bytes' rewrite, the fuzz
#: budget, each read after this runs); every other one is a config override (IRTRACK_<SECTION>_<FIELD>,
#: IRTRACK_HEALTH_FILE: the container images set some) that would change what the tests and the daemons they start
#: run on, so a suite run inside the simulator's image failed where a clean shell passed
KEPT_ENV = frozenset({"IRTRACK_NO_SKIPS", "IRTRACK_WRITE_GOLDEN", "IRTRACK_FUZZ_EXAMPLES"})


def pytest_configure(config):
    """Drop the shell's config overrides (:data:`KEPT_ENV`).  Refuse ``--dist loadgroup`` where it would not group:
    pytest-xdist (3.8) groups by appending ``@group`` to each test's node id, which pytest 9.2 ignores (its node ids
    became structured): the process tests were then spread over both workers, silently, real-time flights beside
    each other (pyproject.toml pins pytest < 9.2)."""
    for name in [n for n in os.environ if n.startswith("IRTRACK_") and n not in KEPT_ENV]:
        del os.environ[name]
    if config.getoption("dist", "no") == "loadgroup" and _pytest_version() >= (9, 2):
        raise pytest.UsageError(
            f"--dist loadgroup does not group tests under pytest {pytest.__version__} (pytest-xdist appends the "
            "group to node ids, which pytest >= 9.2 ignores): install pyproject.toml's pytest (<9.2) or run without -n"
        )


def _pytest_version() -> tuple[int, int]:
    major, minor = pytest.__version__.split(".")[:2]
    return int(major), int(minor)


@pytest.fixture(autouse=True)
def _no_stray_log_handlers():
    """A handler a test leaves on the root logger (an entry point's ``logging.basicConfig``) holds the ``sys.stderr``
    of that test, which pytest's capture closes: every record logged in a later test then printed a 'Logging error'
    traceback into that test's stderr (a one-line-error test failed so in a whole run).  pytest's own handlers come
    and go by themselves.  The root's level is put back too: an entry point run in-process with ``--log-level error``
    left it at ERROR, and a later test's caplog then saw no warning (the dataset's 'coco.json removed' check failed
    after tests/groundsim/test_run.py)."""
    root = logging.getLogger()
    before = set(map(id, root.handlers))
    level = root.level
    yield
    root.setLevel(level)
    for handler in list(root.handlers):
        if id(handler) not in before and not type(handler).__module__.startswith("_pytest"):
            root.removeHandler(handler)


#: ``make test`` (and so CI) sets it: a skipped test is a check that did not run (a missing independent reader, a
#: command not installed), which must fail the run rather than pass unseen
NO_SKIPS_ENV = "IRTRACK_NO_SKIPS"


def pytest_sessionfinish(session, exitstatus):
    if not os.environ.get(NO_SKIPS_ENV) or hasattr(session.config, "workerinput"):
        return  # a developer's run may skip; xdist workers report to the controller, which decides
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    skipped = reporter.stats.get("skipped", []) if reporter is not None else []
    if skipped and session.exitstatus == 0:
        names = ", ".join(r.nodeid for r in skipped[:5]) + (" ..." if len(skipped) > 5 else "")
        reporter.ensure_newline()
        reporter.write_line(f"{NO_SKIPS_ENV}: {len(skipped)} test(s) skipped, which fails this run: {names}", red=True)
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


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

    Shared by the recording, the replay and the flight report's tests, which only read it: a recording costs
    15-20 s of real time, and one flight serves them all as well as three would.  (The report's own 4 s
    recording cost 11 s; each of its two replays of this 10 s flight costs about 1.5 s more than of that one.)"""
    from tests.onboard.test_record_daemon import record_pair

    return record_pair(tmp_path_factory.mktemp("recorded_p1_flight"))
