"""``python -m groundsim <command>``: the ground simulator's entry point (commands in groundsim.app.cli)."""

import os

# the simulator is single-threaded by design (it shares a small machine with the onboard daemon):
# one BLAS thread, set before numpy is imported
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import sys  # noqa: E402

from groundsim.app.cli import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
