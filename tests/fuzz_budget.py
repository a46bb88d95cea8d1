"""How long the fuzz targets (``tests/test_fuzz_*.py``) run.

In CI each target runs a fixed number of hypothesis examples (a few seconds each on the 2-core
machine).  On demand, run them longer with ``IRTRACK_FUZZ_EXAMPLES``::

    IRTRACK_FUZZ_EXAMPLES=200000 .venv/bin/python -m pytest -q tests/test_fuzz_mavlink.py tests/test_fuzz_irframe.py

Every target then runs that many examples (the per-test timeout is lifted).  Examples that fail are
kept in hypothesis' example database (``.hypothesis/``) and replayed first on the next run.
"""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

ENV = "IRTRACK_FUZZ_EXAMPLES"
DEADLINE_MS = 2000  # one example (a handful of datagrams or payloads) far slower than this is a bug, not load


def examples(ci_default: int) -> int:
    """``IRTRACK_FUZZ_EXAMPLES`` when set (a positive integer), else ``ci_default``."""
    raw = os.environ.get(ENV, "").strip()
    if not raw:
        return ci_default
    n = int(raw)
    if n <= 0:
        raise ValueError(f"{ENV} must be a positive integer, got {raw!r}")
    return n


def on_demand() -> bool:
    return bool(os.environ.get(ENV, "").strip())


def fuzz_settings(ci_default: int) -> settings:
    return settings(
        max_examples=examples(ci_default),
        deadline=DEADLINE_MS,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.function_scoped_fixture],
    )


def timeout_s(ci_timeout_s: float) -> float:
    """The pytest-timeout of a fuzz test: bounded in CI, none on demand (0 = no timeout)."""
    return 0 if on_demand() else ci_timeout_s
