"""JSON Schema documents (draft 2020-12) for every wire message, derived from its definition.

Run ``python -m schemas.jsonschema docs/messages`` to regenerate the committed docs; a test checks
that the committed files equal what this module derives, so the docs cannot drift from the code.
msgpack values are described by their JSON equivalents; array payloads are msgpack ``bin``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from schemas.messages import MESSAGE_TYPES
from schemas.wire import REASONS, Message


def message_schema(cls: type[Message]) -> dict:
    """The JSON Schema of one message type."""
    specs = cls.specs()
    description = " ".join((cls.__doc__ or "").split())
    if cls.RULES:
        description += " Also required: " + "; ".join(rule.text for rule in cls.RULES) + "."
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": f"https://posegrid.invalid/messages/{cls.TYPE}.json",
        "title": cls.TYPE,
        "description": description,
        "type": "object",
        "required": ["type", "v", *specs],
        "additionalProperties": False,
        "properties": {
            "type": {"const": cls.TYPE, "description": "message type"},
            "v": {"const": cls.VERSION, "description": "message version; other versions are rejected"},
            **{name: field_spec.json_schema() for name, field_spec in specs.items()},
        },
        "x-rejection-reasons": list(REASONS),
    }


def render_schemas() -> dict[str, str]:
    """File name -> JSON text for every message type (stable key order, trailing newline)."""
    return {
        f"{name}.json": json.dumps(message_schema(cls), indent=2) + "\n" for name, cls in sorted(MESSAGE_TYPES.items())
    }


def write_schemas(folder: str | Path) -> list[Path]:
    """Write every message's schema into ``folder``; returns the paths written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in render_schemas().items():
        (folder / name).write_text(text)
        written.append(folder / name)
    return written


if __name__ == "__main__":
    for path in write_schemas(sys.argv[1] if len(sys.argv) > 1 else "docs/messages"):
        print(path)
