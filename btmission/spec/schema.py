"""JSON Schemas of the file formats, generated from the pydantic models (for editors)."""

from __future__ import annotations

from typing import Any

from btmission._version import __version__


def json_schema(kind: str) -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of a ``library`` or ``mission`` file."""
    if kind == "library":
        from btmission.spec.library import LibrarySpec as model
    elif kind == "mission":
        from btmission.spec.mission import MissionSpec as model  # type: ignore[assignment]
    else:
        raise ValueError(f"unknown schema kind '{kind}' (expected library or mission)")
    schema = model.model_json_schema()
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": f"https://btmission.dev/schema/{kind}-1.json",
        **schema,
        "title": f"btmission {kind} file, version 1 (btmission {__version__})",
    }
