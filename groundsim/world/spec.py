"""What every spec file shares: its error, its name pattern, its YAML loader and its field-by-field checks.

Scenario files (:mod:`groundsim.world.scenario`), the noise cases (:mod:`groundsim.world.noise_cases`) and the
campaign spec (:mod:`groundsim.evaluation.campaign_spec`) all raise :class:`ScenarioError`, one line naming the
file, the field and what was expected; the checks here give the campaign spec, which validates its mapping field by
field, the same texts as the models.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Annotated, Any, Literal

from onboard.core.schema import (
    MISSING_TEXT,
    Integer,
    Number,
    SchemaError,
    Text,
    check_value,
    config_dataclass,
    did_you_mean,
    read_yaml,
    show,
)

__all__ = [
    "NAME",
    "NAME_PATTERN",
    "ScenarioError",
    "SpecFail",
    "check_integer",
    "check_mapping",
    "check_number",
    "check_string",
    "read_spec_yaml",
    "scenario_model",
]

NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


class ScenarioError(SchemaError):
    """A scenario or noise-case file (or dict) is invalid (the one config error, :class:`~onboard.core.schema.SchemaError`).

    ``str(err)`` is one line: ``"<source>: <field>: expected <expected>, got <got>[; <hint>]"``.
    Attributes: ``source`` (file or ``"<dict>"``), ``field`` (dotted path, ``"(document)"`` for the
    whole file, ``"line L, column C"`` for YAML syntax), ``expected``, ``got`` (the value as shown),
    ``hint`` (e.g. a "did you mean"), ``line`` (1-based, YAML errors only).
    """

    def __init__(
        self,
        source,
        field_path: str,
        expected: str,
        got: Any = dataclasses.MISSING,
        hint: str | None = None,
        *,
        got_text: str | None = None,
        line: int | None = None,
    ):
        if got_text is None:
            got_text = MISSING_TEXT if got is dataclasses.MISSING else show(got)
        super().__init__(source, field_path, expected, got_text, hint, line=line)


#: a scenario's, observer's or noise case's name
NAME = Annotated[str, Text(pattern=NAME_PATTERN.pattern, what="a name of letters, digits, '_', '.', '-'")]


def scenario_model(cls=None, /, **kw):
    """A model of the one config system whose errors are :class:`ScenarioError` (every spec file's)."""
    return config_dataclass(cls, error=ScenarioError, **kw)


def read_spec_yaml(path) -> Any:
    """The one YAML loader (:func:`onboard.core.schema.read_yaml`), errors as :class:`ScenarioError`."""
    return read_yaml(path, ScenarioError)


# --------------------------------------------------------------------------- value checks
# Public for the spec files that validate their mapping field by field (the campaign spec,
# groundsim.evaluation.campaign): they check through the one system's field types, so the texts are the
# same as the models', and they raise ScenarioError like the scenario files.


class SpecFail:
    """Raises ScenarioError for one source: ``fail(path, expected, got, hint)``; ``fail.text(...)``
    when the 'got' part is a description rather than a value."""

    def __init__(self, source) -> None:
        self.source = source

    def __call__(self, path: str, expected: str, got: Any = dataclasses.MISSING, hint: str | None = None):
        raise ScenarioError(self.source, path, expected, got, hint)

    def text(self, path: str, expected: str, got_text: str, hint: str | None = None):
        raise ScenarioError(self.source, path, expected, got_text=got_text, hint=hint)


def check_number(v, path, fail: SpecFail, *, lo=None, lo_open=False, hi=None, hi_open=False, unit="") -> float:
    return check_value(
        Annotated[float, Number(lo, hi, lo_open=lo_open, hi_open=hi_open, unit=unit)],
        v,
        path,
        fail.source,
        ScenarioError,
    )


def check_integer(v, path, fail: SpecFail, *, lo=None, hi=None) -> int:
    return check_value(Annotated[int, Integer(lo, hi)], v, path, fail.source, ScenarioError)


def check_string(v, path, fail: SpecFail, *, choices=None, pattern: re.Pattern | None = None, what="a string") -> str:
    text = Text(pattern=None if pattern is None else pattern.pattern, what=what, empty=True)
    tp = Annotated[Literal[tuple(choices)], text] if choices else Annotated[str, text]
    return check_value(tp, v, path, fail.source, ScenarioError)


def check_mapping(v, path, fail: SpecFail, allowed, required=()) -> dict:
    """A dict with string keys, all in ``allowed``, all of ``required`` present."""
    allowed = tuple(allowed)
    if not isinstance(v, dict):
        fail(path, f"a mapping with keys {', '.join(allowed)}", v)
    for k in v:
        if not isinstance(k, str):
            fail(path, f"string keys (one of {', '.join(allowed)})", k)
    for k in v:
        if k not in allowed:
            fail.text(
                f"{path}.{k}" if path else k,
                f"a key of {path or 'the document'} ({', '.join(allowed)})",
                f"unknown key {k!r}",
                did_you_mean(k, allowed),
            )
    for k in required:
        if k not in v:
            fail(f"{path}.{k}" if path else k, "a value (required)")
    return v
