"""`make bench`: every benchmark in turn, each in its own process (they pin threads and CPUs).

    python -m bench [NAME ...]      NAME in: estimator render imaging flight simrate onboard video (default: all)

Prints numbers; asserts nothing; exit code 1 if a benchmark crashed.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

from onboard.core.blas import single_thread_blas_env

BENCHES = ("estimator", "render", "imaging", "flight", "simrate", "onboard", "video")


def main(argv=None) -> int:
    names = list(argv if argv is not None else sys.argv[1:]) or list(BENCHES)
    unknown = [n for n in names if n not in BENCHES]
    if unknown:
        print(f"bench: unknown benchmark(s) {', '.join(unknown)}; choose from {', '.join(BENCHES)}", file=sys.stderr)
        return 2
    env = single_thread_blas_env(dict(os.environ))
    failed = []
    for name in names:
        print(f"\n===== bench.{name} =====", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call([sys.executable, "-m", f"bench.{name}"], env=env)
        print(f"----- bench.{name}: {time.perf_counter() - t0:.0f} s, exit {rc}", flush=True)
        if rc != 0:
            failed.append(name)
    if failed:
        print(f"bench: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
