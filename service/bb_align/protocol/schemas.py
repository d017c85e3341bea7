"""JSON Schema files of the wire models (proto_schemas/, checked in sync by a test)."""

from __future__ import annotations

import json

from .models import SCHEMA_VERSION, WIRE_MODELS


def json_schemas() -> dict[str, dict]:
    """Each wire model's JSON Schema (file name stem -> schema), as committed in proto_schemas/."""
    out = {}
    for name, cls in WIRE_MODELS.items():
        schema = cls.model_json_schema()
        out[name] = {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "$id": f"bb-align/wire/v{SCHEMA_VERSION}/{name}.schema.json",
            **schema,
        }
    return out


def write_json_schemas(directory) -> list:
    """Write ``<name>.schema.json`` files; returns their paths."""
    from pathlib import Path

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, schema in json_schemas().items():
        p = directory / f"{name}.schema.json"
        p.write_text(json.dumps(schema, indent=2, sort_keys=True) + "\n")
        paths.append(p)
    return paths
