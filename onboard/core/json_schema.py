"""The JSON Schema of a message whose keys one table declares beside its builder (track, status, guidance): the
recording stores it with the message's channel (:mod:`onboard.io.record`), so that a viewer knows every key."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

__all__ = ["object_schema"]


def object_schema(
    title: str, description: str, keys: Iterable[tuple[str, dict[str, Any]]], required: Iterable[str] | None = None
) -> dict[str, Any]:
    """An object with ``keys`` (name, schema), in order, of which ``required`` (default: all) are always present;
    each key's schema is copied (the tables stay untouched by whoever edits the result)."""
    keys = list(keys)
    return {
        "title": title,
        "description": description,
        "type": "object",
        "properties": {key: dict(schema) for key, schema in keys},
        "required": [key for key, _ in keys] if required is None else list(required),
    }
