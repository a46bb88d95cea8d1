"""The one exception base of the onboard package; entry points turn these into one line + exit code."""

from __future__ import annotations

from typing import Any


def _rebuild(cls: type[IrtrackError], args: tuple) -> IrtrackError:
    """An error of ``cls`` holding ``args``, made without its ``__init__`` (see :meth:`IrtrackError.__reduce__`)."""
    err = cls.__new__(cls, *args)
    err.args = args
    return err


class IrtrackError(Exception):
    """Base of every error irtrack raises on purpose (bad input, bad config, unobservable...)."""

    def __reduce__(self) -> tuple[Any, ...]:
        # Exception's own pickling calls the class with ``self.args`` (the message), which subclasses taking other
        # arguments (SchemaError: source, field, expected ...) refuse; an error a process-pool worker raises must
        # reach its parent as itself, not as a BrokenProcessPool.  So it is rebuilt without __init__: the same
        # message (args) and attributes (the instance dict, restored by BaseException.__setstate__).
        return _rebuild, (type(self), self.args), dict(vars(self)) or None


class InputError(IrtrackError, ValueError):
    """Input data (file, message, payload) is malformed; the message names where."""


def wrong_sizes(*expected: tuple[str, Any, int]) -> str:
    """``"<name> has N values, expected M"`` for each ``(name, value, M)`` whose value (a sequence or an array) does
    not hold M values, joined by ``"; "``: the text of the InputError a step method raises for arguments of the wrong
    size (numpy's own reshape error names none)."""
    import numpy as np  # here: the container's health probe imports this module and the standard library only

    return "; ".join(
        f"{name} has {np.size(value)} values, expected {size}"
        for name, value, size in expected
        if np.size(value) != size
    )


class ConfigError(IrtrackError, ValueError):
    """A configuration file or option is invalid; the message names file, field and expectation."""
