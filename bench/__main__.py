"""`make bench`: every benchmark in turn, each in its own process (they pin threads and CPUs).

    python -m bench [NAME ...]      NAME in: estimator render imaging flight simrate onboard video (default: all)

Prints numbers; asserts nothing; exit code 1 if a benchmark crashed.  Ctrl-C (or SIGTERM) stops the running
benchmark through its own clean-up and skips the rest: one line ``interrupted: finished: ...; stopped part-way:
...; not run: ...; the figures printed above are kept``; exit 130 (143 for SIGTERM).

Each benchmark runs in a session of its own, started with SIGINT ignored: a terminal's Ctrl-C reaches this
process alone, which passes it on once a second until the benchmark has exited.  A benchmark starts
listening when its ``main`` starts (:func:`bench.run_benchmark`), so a Ctrl-C during its imports waits for
them instead of ending it in a traceback, and its daemons and pool workers are stopped by it, never by the
terminal behind its back.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

from bench import EXIT_SIGNALLED, SUITE_ENV
from groundsim.io.stop_signals import install_stop_signals, print_interrupted
from onboard.core.blas import single_thread_blas_env

BENCHES = ("estimator", "render", "imaging", "flight", "simrate", "onboard", "video")
POLL_S = 0.1  # how soon a Ctrl-C is passed on
FORWARD_EVERY_S = 1.0  # SIGINT again while the benchmark still imports (it ignores SIGINT until main)
CHILD_STOP_S = 60.0  # from the first SIGINT to SIGKILL: a benchmark's clean-up stops a daemon in 10 s at most


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _run_child(name: str, env: dict, stop: threading.Event) -> int:
    """``python -m bench.<name>``'s exit code; once ``stop`` is set, SIGINT to it every FORWARD_EVERY_S,
    SIGKILL after CHILD_STOP_S."""
    proc = subprocess.Popen(
        [sys.executable, "-m", f"bench.{name}"], env=env, start_new_session=True, preexec_fn=_ignore_sigint
    )
    t_stop = next_forward = None
    while proc.poll() is None:
        if not stop.wait(POLL_S):
            continue
        now = time.monotonic()
        if t_stop is None:
            t_stop = next_forward = now
        if now - t_stop > CHILD_STOP_S:
            print(f"bench.{name} (pid {proc.pid}) still running {CHILD_STOP_S:g} s after SIGINT: SIGKILL", flush=True)
            proc.kill()
            break
        if now >= next_forward:
            proc.send_signal(signal.SIGINT)
            next_forward = now + FORWARD_EVERY_S
        time.sleep(POLL_S)  # stop.wait no longer waits once set
    return proc.wait()


def main(argv=None) -> int:
    names = list(argv if argv is not None else sys.argv[1:]) or list(BENCHES)
    if any(n in ("-h", "--help") for n in names):
        print((__doc__ or "").split("\n\n")[0] + "\n\n" + (__doc__ or "").split("\n\n")[1].strip())
        return 0
    unknown = [n for n in names if n not in BENCHES]
    if unknown:
        print(f"bench: unknown benchmark(s) {', '.join(unknown)}; choose from {', '.join(BENCHES)}", file=sys.stderr)
        return 2
    env = single_thread_blas_env({**os.environ, SUITE_ENV: "1"})
    stop, received = threading.Event(), []
    restore = install_stop_signals(stop, received, on_first=lambda _name: None)  # the one line comes at the end
    finished, failed = [], []
    try:
        for name in names:
            print(f"\n===== bench.{name} =====", flush=True)
            t0 = time.perf_counter()
            rc = _run_child(name, env, stop)
            print(f"----- bench.{name}: {time.perf_counter() - t0:.0f} s, exit {rc}", flush=True)
            if stop.is_set() or rc in EXIT_SIGNALLED.values():
                return _interrupted(names, finished, name, received)
            finished.append(name if rc == 0 else f"{name} (exit {rc})")
            if rc != 0:
                failed.append(name)
    finally:
        restore()
    if failed:
        print(f"bench: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


def _interrupted(names: list[str], finished: list[str], stopped: str, received: list[int]) -> int:
    """The suite's one line (what finished, what stopped part-way, what did not run) and its exit code."""
    rest = names[names.index(stopped) + 1 :]
    parts = [f"finished: {', '.join(finished)}"] if finished else []
    parts.append(f"stopped part-way: {stopped}")
    if rest:
        parts.append(f"not run: {', '.join(rest)}")
    rc = print_interrupted("; ".join(parts) + "; the figures printed above are kept")
    return EXIT_SIGNALLED.get(received[0], rc) if received else rc


if __name__ == "__main__":
    sys.exit(main())
