"""JSON Schemas for editors (VS Code YAML extension: ``# yaml-language-server: $schema=``)."""

from __future__ import annotations

import json
from pathlib import Path

from supervisor.config.models import BenchConfig


def bench_schema() -> dict[str, object]:
    schema = BenchConfig.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "Bench supervisor I/O map"
    return schema


def write_schemas(out_dir: Path) -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "bench.schema.json"
    path.write_text(json.dumps(bench_schema(), indent=2, sort_keys=True) + "\n", encoding="utf-8")
    return [path]
