"""What counts as a number or a count in the hand-written validation of parameters (``__post_init__``, constructors,
command-line values): the one rule, so that every parameter refuses the same values.

A bool is never a number here (``True`` would pass ``isinstance(v, int)`` and read as 1), NaN and infinities are never
numbers, and only Python's ``int`` and ``float`` (a ``numpy.float64`` is a ``float``) are accepted: a parameter comes
from a configuration file, a command line or code, not from an array.  The callers raise their own error, in their own
words, naming the parameter; the predicates only answer whether the value is acceptable, and :func:`require_each`
applies one of them to several attributes of a parameter object.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import TypeGuard

__all__ = ["is_finite_number", "is_nonnegative_number", "is_positive_int", "is_positive_number", "require_each"]


def is_finite_number(v: object) -> TypeGuard[float]:
    """An ``int`` or ``float``, not a bool, finite."""
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)


def is_positive_number(v: object) -> TypeGuard[float]:
    """A finite number (:func:`is_finite_number`) > 0."""
    return is_finite_number(v) and v > 0


def is_nonnegative_number(v: object) -> TypeGuard[float]:
    """A finite number (:func:`is_finite_number`) >= 0."""
    return is_finite_number(v) and v >= 0


def is_positive_int(v: object) -> TypeGuard[int]:
    """An ``int``, not a bool, >= 1."""
    return not isinstance(v, bool) and isinstance(v, int) and v >= 1


def require_each(
    obj: object, names: Iterable[str], ok: Callable[[object], bool], error: Callable[[str], Exception], message: str
) -> None:
    """Raise ``error(message.format(name=name, value=value))`` for the first of ``names`` whose attribute ``value`` of
    ``obj`` is not ``ok``; ``message`` names the owner and what was expected, e.g.
    ``"PaperConfig.{name} must be a positive number, got {value!r}"``."""
    for name in names:
        value = getattr(obj, name)
        if not ok(value):
            raise error(message.format(name=name, value=value))
