"""JSON Schemas for editors (VS Code YAML extension: ``# yaml-language-server: $schema=``)."""

from __future__ import annotations

import json
from pathlib import Path

from supervisor.config.models import BenchConfig
from supervisor.config.recipe import Recipe


def bench_schema(model: type[BenchConfig]) -> dict[str, object]:
    """The schema of an I/O map (``model``: the registry's bench model)."""
    schema = model.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "Bench supervisor I/O map"
    return schema


def recipe_schema() -> dict[str, object]:
    schema = Recipe.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "Bench supervisor recipe"
    return schema


def write_schemas(root: Path, bench_model: type[BenchConfig]) -> list[Path]:
    out = []
    for folder, name, schema in (
        ("io_maps", "bench.schema.json", bench_schema(bench_model)),
        ("recipes", "recipe.schema.json", recipe_schema()),
    ):
        (root / folder).mkdir(parents=True, exist_ok=True)
        path = root / folder / name
        path.write_text(json.dumps(schema, indent=2, sort_keys=True) + "\n", encoding="utf-8")
        out.append(path)
    return out
