"""The suite's own IRTRACK_* switches survive the start, where every config override of the shell is dropped."""

from __future__ import annotations

import pytest

from tests.conftest import KEPT_ENV


@pytest.mark.parametrize(
    "name",
    [
        "IRTRACK_NO_SKIPS",  # tests/conftest.py
        "IRTRACK_WRITE_GOLDEN",  # tests/onboard/test_mavlink_wire_bytes.py rewrites its golden bytes
        "IRTRACK_FUZZ_EXAMPLES",  # tests/fuzz_budget.py
    ],
)
def test_a_switch_of_the_suite_is_kept(name):
    assert name in KEPT_ENV
