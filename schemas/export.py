"""Export every message model as JSON Schema, so a stage can be rewritten in any language."""

from __future__ import annotations

import json
from pathlib import Path

from schemas.messages import MESSAGE_MODELS, Message

JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"


def schema_file_name(model: type[Message]) -> str:
    """``cvxnav.<Model>.v<version>.schema.json``."""
    return f"{model.SCHEMA}.v{model.VERSION}.schema.json"


def json_schema(model: type[Message]) -> dict:
    """The model's JSON Schema with its name and version in ``$id`` and ``title``.

    Two constraints are not expressible in JSON Schema and are enforced by the pydantic model only:
    floats must be finite, and an ellipsoid's ``A`` must be symmetric positive definite.
    """
    schema = model.model_json_schema(mode="validation")
    return {
        "$schema": JSON_SCHEMA_DIALECT,
        "$id": f"urn:cvxnav:schema:{model.schema_id()}",
        **schema,
        "title": model.schema_id(),
        "x-zenoh-encoding": model.encoding(),
    }


def export_json_schemas(out_dir: Path) -> list[Path]:
    """Write one schema file per message model into ``out_dir`` (created if missing)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for model in MESSAGE_MODELS:
        path = out_dir / schema_file_name(model)
        path.write_text(json.dumps(json_schema(model), indent=2, sort_keys=True) + "\n")
        written.append(path)
    return written
