"""``python -m groundsim <command>``: the ground simulator's entry point (commands in groundsim.app.cli)."""

from onboard.core.blas import single_thread_blas_env

# the simulator is single-threaded by design (it shares a small machine with the onboard daemon):
# one BLAS thread, set before numpy is imported
single_thread_blas_env()

import sys  # noqa: E402

from groundsim.app.cli import entry  # noqa: E402

if __name__ == "__main__":
    sys.exit(entry())
