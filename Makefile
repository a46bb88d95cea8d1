# The two README commands: `make demo` and `make test`. Both create .venv/ when missing.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.irtrack-installed

.PHONY: demo test lint bench venv clean bytecode kernels

# The pipeline is single-threaded by design; multi-threaded BLAS on small matrices only fights the
# other processes for the two cores (a MAP solve went from 0.9 s to 8.5 s under load with threads).
export OPENBLAS_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1

# Development and CI: the onboard runtime plus the simulator (sim) and the test tools (dev); the
# Dockerfile installs the onboard runtime alone (scripts/install.sh /opt/venv).
$(STAMP): pyproject.toml scripts/install.sh
	bash scripts/install.sh $(VENV) sim,dev
	@touch $(STAMP)

venv: $(STAMP)

# Our own modules compiled once, before the many processes the demo and the tests start: where the environment
# sets PYTHONDONTWRITEBYTECODE (this machine's does) no import writes a .pyc, so every daemon, simulator and CLI
# child compiled onboard/ and groundsim/ again (~0.5 s of CPU each; the subprocess-heavy tests took ~15 % less
# CPU with them compiled). A stale .pyc is never used: Python checks each against its source.
bytecode: $(STAMP)
	$(PY) -m compileall -q -j 0 onboard groundsim bench

# The numba kernels (the daemon's and the simulator's) compiled once into their cache, after an install and when a
# kernel's source changes (groundsim/app/warm.py says why): ~25 s on two cores the first time, so that the demo's
# daemon serves at once and its simulator flies from its first second. A process that finds them uncached compiles
# them itself: the tests need no such step.
KERNELS := $(VENV)/.irtrack-kernels
$(KERNELS): $(STAMP) $(wildcard onboard/*/kernels.py groundsim/world/render/*kernels.py)
	$(PY) -m groundsim.app.warm
	@touch $(KERNELS)

kernels: $(KERNELS)

# make demo LIVE_VIEW=8765: Foxglove's live view of the daemon on ws://127.0.0.1:8765
demo: $(STAMP) bytecode $(KERNELS)
	$(PY) -m groundsim demo $(if $(LIVE_VIEW),--live-view $(LIVE_VIEW))

# Lint and types first (seconds): ruff over the tree (lint + format check), mypy over onboard.
lint: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(PY) -m mypy

# pytest exit 5 means "no tests were collected": say so plainly, neither a failure nor a pass.  IRTRACK_NO_SKIPS: a
# skipped test fails the run (tests/conftest.py): a check against an independent reader must run, not pass unseen.
# Two pytest-xdist workers, one per core: the tests that start processes run on one of them, one at a time as in a
# serial run, while the other runs the in-process tests (tests/conftest.py says why; docs/performance.md the times).
# The 15 slowest tests are listed at the end, to keep the whole suite within 8 minutes on a fresh clone in sight.
# pytest rewrites the asserts of each test module it imports (~14 s of CPU for the whole suite) and caches the result
# beside the module, unless PYTHONDONTWRITEBYTECODE is set, as this machine's environment sets it: then each worker
# rewrote every module on every run (20 s before the first test; 7 s from the cache). So the suite runs with it unset
# (the processes the tests start then write the bytecode they compile too), and a collection pass fills the cache on
# one core while mypy checks on the other. That pass's output is dropped: the run after it collects the same modules
# and reports whatever failed there.
test: bytecode
	@PYTHONDONTWRITEBYTECODE= $(PY) -m pytest --collect-only -q -p no:cacheprovider >/dev/null 2>&1 & \
	$(MAKE) --no-print-directory lint; lint=$$?; wait; [ $$lint -eq 0 ] || exit $$lint; \
	PYTHONDONTWRITEBYTECODE= IRTRACK_NO_SKIPS=1 $(PY) -m pytest -n 2 --dist loadgroup --durations=15; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make test: NO TESTS RAN (pytest exit 5)"; exit 0; fi; \
	exit $$rc

bench: $(STAMP)
	$(PY) -m bench

clean:
	rm -rf out .pytest_cache
