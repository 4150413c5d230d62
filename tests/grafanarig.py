"""The Grafana dashboards and provisioning of ``hmi/grafana/``, read as Grafana reads them.

No Grafana binary is reachable from this machine (no registry here serves one), so
the tests check the dashboards the two ways that catch what Grafana would reject or show
empty: the JSON model (uids, panel ids, grid, data sources, variables, units) and every
Flux query run against the tests' real InfluxDB with Grafana's macros substituted the way
Grafana's InfluxDB data source does it (plain text replacement before the query is sent:
``v.timeRangeStart``/``v.timeRangeStop`` become RFC 3339 times, ``v.windowPeriod`` a
duration, ``v.defaultBucket`` the bucket name as a string, template variables their value).
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[1]
GRAFANA = ROOT / "hmi" / "grafana"
DASHBOARDS = GRAFANA / "dashboards"
PROVISIONING = GRAFANA / "provisioning"

# ``${name}``, ``${name:format}`` or ``$name`` (Grafana's variable syntaxes; ``[[name]]`` is
# deprecated and not used). Built-ins start with ``__`` (``${__field.labels.channel}``).
VARIABLE = re.compile(
    r"\$\{(?P<braced>[A-Za-z_][\w.]*)(?::(?P<format>[\w]+))?\}|\$(?P<bare>[A-Za-z_]\w*)"
)


@dataclass(frozen=True)
class Query:
    """One Flux query of a dashboard: a panel's target, a variable or an annotation."""

    dashboard: str  # file name
    where: str  # "panel 'Voltage'", "variable 'bench'", "annotation 'Steps'"
    flux: str


def dashboard_files() -> list[Path]:
    return sorted(DASHBOARDS.rglob("*.json"))


def load(path: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    return data


def panels(dashboard: Mapping[str, Any]) -> Iterator[dict[str, Any]]:
    """Every panel, rows' collapsed panels included."""
    for panel in dashboard.get("panels", []):
        yield panel
        yield from panel.get("panels", [])


def variables(dashboard: Mapping[str, Any]) -> list[dict[str, Any]]:
    result: list[dict[str, Any]] = dashboard.get("templating", {}).get("list", [])
    return result


def annotations(dashboard: Mapping[str, Any]) -> list[dict[str, Any]]:
    result: list[dict[str, Any]] = dashboard.get("annotations", {}).get("list", [])
    return result


def queries(path: Path) -> list[Query]:
    """Every Flux query of the dashboard file, in display order."""
    d = load(path)
    out: list[Query] = []
    for v in variables(d):
        if v.get("type") == "query":
            out.append(Query(path.name, f"variable {v['name']!r}", _text(v.get("query"))))
    for a in annotations(d):
        target = a.get("target") or {}
        if target.get("query"):
            out.append(Query(path.name, f"annotation {a['name']!r}", target["query"]))
    for p in panels(d):
        for t in p.get("targets", []):
            out.append(Query(path.name, f"panel {p.get('title')!r} ({t.get('refId')})", t["query"]))
    return out


def _text(query: object) -> str:
    # A variable's query is a string for the InfluxDB data source (an object for others).
    if isinstance(query, dict):
        return str(query.get("query", ""))
    return str(query or "")


def used_variables(text: str) -> set[str]:
    """The template variables a query refers to (Grafana's built-ins excluded)."""
    names = set()
    for m in VARIABLE.finditer(text):
        name = m.group("braced") or m.group("bare")
        if not name.startswith("__"):
            names.add(name)
    return names


def provisioned_datasource_uids() -> set[str]:
    uids = set()
    for file in (PROVISIONING / "datasources").glob("*.yaml"):
        doc = yaml.safe_load(file.read_text(encoding="utf-8"))
        for ds in doc.get("datasources", []):
            uids.add(ds["uid"])
    return uids


def datasource_refs(dashboard: Mapping[str, Any]) -> Iterator[tuple[str, object]]:
    """(where, datasource) for every data source reference in the dashboard."""
    for v in variables(dashboard):
        if "datasource" in v:
            yield f"variable {v['name']!r}", v["datasource"]
    for a in annotations(dashboard):
        if "datasource" in a:
            yield f"annotation {a['name']!r}", a["datasource"]
    for p in panels(dashboard):
        if "datasource" in p:
            yield f"panel {p.get('title')!r}", p["datasource"]
        for t in p.get("targets", []):
            if "datasource" in t:
                yield f"panel {p.get('title')!r} target {t.get('refId')}", t["datasource"]


def flux_time(t: datetime) -> str:
    return t.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def substitute(
    text: str,
    *,
    start: datetime,
    stop: datetime,
    window_s: int,
    bucket: str,
    values: Mapping[str, Sequence[str]],
) -> str:
    """The query as Grafana sends it: macros and template variables replaced by text."""
    out = (
        text.replace("v.timeRangeStart", flux_time(start))
        .replace("v.timeRangeStop", flux_time(stop))
        .replace("v.windowPeriod", f"{window_s}s")
        .replace("v.defaultBucket", json.dumps(bucket))
    )

    def value(m: re.Match[str]) -> str:
        name = m.group("braced") or m.group("bare")
        if name.startswith("__"):
            return m.group(0)
        chosen = values[name]
        if m.group("format") == "regex":
            # Grafana's regex format: every value escaped, alternatives in a group.
            return "(" + "|".join(re.escape(v) for v in chosen) + ")"
        if m.group("format") not in (None, "raw"):
            raise ValueError(f"format {m.group('format')!r} not substituted by this rig")
        if len(chosen) != 1:
            raise ValueError(f"${name} has {len(chosen)} values; use ${{{name}:regex}}")
        return chosen[0]

    return VARIABLE.sub(value, out)
