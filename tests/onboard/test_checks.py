"""onboard.core.checks: the one rule for what a parameter may be (the callers' messages are tested with them)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onboard.core.checks import is_finite_number, is_nonnegative_number, is_positive_int, is_positive_number

NOT_NUMBERS = [True, False, None, "1", b"1", [1.0], math.nan, math.inf, -math.inf, np.int64(3), 1 + 0j]


@pytest.mark.parametrize("v", NOT_NUMBERS)
def test_bools_text_non_finite_and_numpy_integers_are_no_numbers(v):
    assert not is_finite_number(v) and not is_positive_number(v) and not is_nonnegative_number(v)


@pytest.mark.parametrize(
    "v, finite, positive, nonnegative",
    [(1, True, True, True), (0.5, True, True, True), (np.float64(2.0), True, True, True), (0, True, False, True),
     (0.0, True, False, True), (-0.0, True, False, True), (-1e-300, True, False, False), (-3, True, False, False)],
)  # fmt: skip
def test_the_sign_rules(v, finite, positive, nonnegative):
    assert (is_finite_number(v), is_positive_number(v), is_nonnegative_number(v)) == (finite, positive, nonnegative)


@pytest.mark.parametrize("v, ok", [(1, True), (2**70, True), (0, False), (-1, False), (True, False), (1.0, False),
                                   (np.int64(1), False), ("1", False), (None, False)])  # fmt: skip
def test_a_positive_int_is_a_python_int_from_one(v, ok):
    assert is_positive_int(v) is ok
