"""Recorded JSON messages checked against the JSON Schema stored beside them, by the `jsonschema` package (an
independent validator), with one rule stricter than the schemas say: an object whose schema lists ``properties``
may hold no key it does not declare, so a schema that omits an emitted key fails (the stored schemas leave
``additionalProperties`` open for readers of older files; the tests hold the writer to the full list)."""

from __future__ import annotations

import copy
from typing import Any

import jsonschema


def _closed(schema: Any) -> Any:
    """``schema`` with ``additionalProperties: false`` on every object that lists its properties and sets none."""
    if isinstance(schema, dict):
        out = {k: _closed(v) for k, v in schema.items()}
        if "properties" in out and "additionalProperties" not in out:
            out["additionalProperties"] = False
        return out
    if isinstance(schema, list):
        return [_closed(v) for v in schema]
    return schema


def check(value: Any, schema: dict[str, Any]) -> list[str]:
    """Every way ``value`` breaks ``schema`` (closed: :func:`_closed`), one line each; empty: it conforms."""
    validator = jsonschema.Draft202012Validator(_closed(copy.deepcopy(schema)))
    return [
        f"{'/'.join(str(p) for p in e.absolute_path) or '$'}: {e.message}"
        for e in sorted(validator.iter_errors(value), key=lambda e: list(map(str, e.absolute_path)))
    ]
