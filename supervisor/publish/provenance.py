"""What a test's result folder says about itself: the test's metadata, what produced it, and
whether it is still what was written (issue 26, ADR 0025).

- **Metadata** (:class:`TestMetadata`): the cell (or sample) id, its chemistry and nominal
  capacity, the operator who started the test and a free comment — what a lab needs to find
  a result again. Given at load and/or start (HTTP, the screens, OPC UA, ``ctl start``),
  checked here (:func:`metadata_from_arguments`, README "Input limits").
- **Provenance** (``provenance.json``, :func:`provenance_document`): the recipe's text and
  SHA-256, the parameters as given and as resolved, the I/O map's path, SHA-256 and the
  channel's section of it, the software version, the host, the bench and the start time
  (UTC). Written once when the test's files are opened and never changed afterwards: what
  happens later (pauses, restarts, the end) is in the timeline file and the summary.
- **Manifest** (the final summary's ``manifest``, :func:`manifest`): the SHA-256 and size of
  every data file once the test is over, so that :func:`verify` (``supervisor results
  verify DIR``) says whether the folder is complete and unmodified.
"""

from __future__ import annotations

import functools
import hashlib
import json
import platform
import re
import unicodedata
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from supervisor.core.encoding import WRITE_ERRORS
from supervisor.core.units import Dim, UnitError, parse_quantity

PROVENANCE_NAME = "provenance.json"
PROVENANCE_FORMAT = 1
BDF_METADATA_SUFFIX = ".bdf.metadata.json"
"""The BDF metadata sidecar beside ``<id>.bdf.csv`` (BDF: ``x.bdf.metadata.json``)."""
SOFTWARE = "bench-supervisor"

# --- metadata -------------------------------------------------------------------------------
METADATA_ARGUMENTS = ("cell_id", "chemistry", "nominal_capacity", "comment")
"""The metadata a load or a start may give (the operator is the start's actor)."""
CELL_ID_MAX = 64
CHEMISTRY_MAX = 64
COMMENT_MAX = 500
NOMINAL_CAPACITY_MAX_AH = 1e6
# One line of plain characters: a cell id is typed on labels, file names and queries.
_ID_CHARS = re.compile(r"[A-Za-z0-9 ._:/+-]*")


class MetadataError(ValueError):
    """A metadata field refused: ``field`` names it, the message says what was received."""

    def __init__(self, field_name: str, message: str) -> None:
        super().__init__(message)
        self.field = field_name


@dataclass(frozen=True)
class TestMetadata:
    """What a lab needs to find a result again (the BDF metadata's names in ``bdf``)."""

    __test__ = False  # not a pytest class

    cell_id: str = ""
    chemistry: str = ""
    nominal_capacity_ah: float | None = None
    operator: str = ""
    comment: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {
            "cell_id": self.cell_id,
            "chemistry": self.chemistry,
            "nominal_capacity_ah": self.nominal_capacity_ah,
            "operator": self.operator,
            "comment": self.comment,
        }

    @classmethod
    def from_dict(cls, data: Any) -> TestMetadata:
        """Back from a summary (a resumed test); anything odd is dropped, not trusted."""
        if not isinstance(data, Mapping):
            return cls()
        cap = data.get("nominal_capacity_ah")
        return cls(
            str(data.get("cell_id") or ""),
            str(data.get("chemistry") or ""),
            float(cap) if isinstance(cap, int | float) and not isinstance(cap, bool) else None,
            str(data.get("operator") or ""),
            str(data.get("comment") or ""),
        )

    def updated(self, given: Mapping[str, Any]) -> TestMetadata:
        """These metadata with the fields ``given`` (checked) replacing theirs."""
        d = self.as_dict()
        d.update(given)
        return TestMetadata(**d)


def _printable_line(name: str, value: Any, limit: int) -> str:
    if not isinstance(value, str):
        raise MetadataError(name, f"{name} must be a text, not {_clip(value)}")
    if len(value) > limit:
        raise MetadataError(
            name, f"{name} is {len(value)} characters long, at most {limit}: {_clip(value)}"
        )
    if not _ID_CHARS.fullmatch(value):
        bad = next(c for c in value if not _ID_CHARS.fullmatch(c))
        raise MetadataError(
            name,
            f"{name} {_clip(value)} has {bad!r}: one line of letters, digits, spaces and"
            " . _ : / + - only",
        )
    return value


def _comment(value: Any) -> str:
    if not isinstance(value, str):
        raise MetadataError("comment", f"comment must be a text, not {_clip(value)}")
    if len(value) > COMMENT_MAX:
        raise MetadataError(
            "comment", f"comment is {len(value)} characters long, at most {COMMENT_MAX}"
        )
    for c in value:
        # Newlines are a comment's paragraphs; any other control or format character (a
        # terminal escape, a bidirectional override) would change how it reads elsewhere.
        if c != "\n" and unicodedata.category(c)[0] == "C":
            raise MetadataError(
                "comment",
                f"comment has the control character {c!r}: text and newlines only",
            )
    return value


def _capacity_ah(value: Any) -> float | None:
    if value is None or value == "":
        return None
    try:
        if isinstance(value, bool):
            raise UnitError("not a number")
        if isinstance(value, int | float):
            ah = float(value)  # a bare number is in Ah (the field's unit)
        elif isinstance(value, str):
            text = value.strip()
            q = parse_quantity(text) if _is_number(text) else parse_quantity(text, Dim.CHARGE)
            ah = q.value
        else:
            raise UnitError("not a quantity")
    except UnitError:
        raise MetadataError(
            "nominal_capacity",
            f"nominal_capacity must be a charge (e.g. '2.5 Ah', '1300 mAh', or a number of"
            f" Ah), not {_clip(value)}",
        ) from None
    if not 0 < ah <= NOMINAL_CAPACITY_MAX_AH:
        raise MetadataError(
            "nominal_capacity",
            f"nominal_capacity must be above 0 and at most {NOMINAL_CAPACITY_MAX_AH:g} Ah,"
            f" not {_clip(value)}",
        )
    return ah


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def metadata_from_arguments(args: Mapping[str, Any]) -> dict[str, Any]:
    """The metadata fields among a command's ``args``, checked (``MetadataError`` naming the
    field and what was received); as ``TestMetadata`` fields (``nominal_capacity`` in Ah).
    A field given empty clears it."""
    out: dict[str, Any] = {}
    if "cell_id" in args:
        out["cell_id"] = _printable_line("cell_id", args["cell_id"], CELL_ID_MAX).strip()
    if "chemistry" in args:
        out["chemistry"] = _printable_line("chemistry", args["chemistry"], CHEMISTRY_MAX).strip()
    if "nominal_capacity" in args:
        out["nominal_capacity_ah"] = _capacity_ah(args["nominal_capacity"])
    if "comment" in args:
        out["comment"] = _comment(args["comment"])
    return out


def check_cell_id(value: Any) -> str:
    """A cell id as a query gives it (``GET /api/tests?cell=``): the same rule."""
    return _printable_line("cell", value, CELL_ID_MAX).strip()


def _clip(value: Any, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 1] + "…"


# --- provenance -----------------------------------------------------------------------------
def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def utc_iso(unix_s: float) -> str:
    """``2026-05-01T12:00:00.000Z``."""
    t = datetime.fromtimestamp(unix_s, UTC)
    return t.strftime("%Y-%m-%dT%H:%M:%S.") + f"{t.microsecond // 1000:03d}Z"


def software_version() -> dict[str, str]:
    """The package's version as installed (``importlib.metadata``); no git commit: a
    deployed bench has no repository, and git is not a run-time dependency (ADR 0025)."""
    return dict(_software_version())


@functools.cache
def _software_version() -> tuple[tuple[str, str], ...]:
    # Looked up once a process: ``importlib.metadata`` leaves reference cycles behind at
    # each look-up, and a recipe load must leave none (commands/worker.py freezes the heap
    # after it: tests/unit/test_recipe_load_off_the_loop.py).
    from importlib import metadata

    try:
        version = metadata.version(SOFTWARE)
    except metadata.PackageNotFoundError:
        version = "unknown (not installed)"
    return (("name", SOFTWARE), ("version", version), ("python", platform.python_version()))


@dataclass(frozen=True)
class Provenance:
    """What produced a test, gathered when its collector is made (``Bench.new_collector``);
    ``document`` adds the start time when the files are opened."""

    bench: str
    channel: str
    test_id: str
    recipe_name: str
    recipe_file: str
    recipe_text: str
    parameters_given: Mapping[str, str]
    parameters_resolved: Mapping[str, float]
    io_map_file: str
    io_map_sha256: str
    io_map_channel: Mapping[str, Any]
    software: Mapping[str, str] = field(default_factory=software_version)
    host: str = field(default_factory=platform.node)

    def document(self, started_unix_s: float) -> dict[str, Any]:
        return {
            "format": PROVENANCE_FORMAT,
            "test_id": self.test_id,
            "bench": self.bench,
            "channel": self.channel,
            "host": self.host,
            "software": dict(self.software),
            "started_utc": utc_iso(started_unix_s),
            "recipe": {
                "name": self.recipe_name,
                "file": self.recipe_file,
                "sha256": sha256_bytes(self.recipe_text.encode("utf-8")),
                "parameters_given": dict(self.parameters_given),
                "parameters_resolved": dict(self.parameters_resolved),
                "text": self.recipe_text,
            },
            "io_map": {
                "file": self.io_map_file,
                "sha256": self.io_map_sha256,
                "channel": self.io_map_channel,
            },
        }


def write_once(path: Path, document: Mapping[str, Any]) -> bool:
    """Write ``document`` to ``path`` unless it exists (a resumed test's stays as written at
    its start); atomically. Returns whether it was written."""
    if path.exists():
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    text = json.dumps(document, indent=2, ensure_ascii=False) + "\n"
    tmp.write_text(text, encoding="utf-8", errors=WRITE_ERRORS)  # core/encoding.py
    tmp.replace(path)
    return True


def bdf_metadata(
    test_id: str, channel: str, bench: str, metadata: TestMetadata, started_unix_s: float
) -> dict[str, Any]:
    """The BDF metadata sidecar: schema.org Dataset names as the reference package writes
    them (``batterydf``'s ``bdf.metadata``), with the cell's fields beside."""
    return {
        "@type": "Dataset",
        "name": f"{bench} {channel} test {test_id}",
        "identifier": test_id,
        "description": metadata.comment,
        "dateCreated": utc_iso(started_unix_s),
        "creator": metadata.operator,
        "battery": {
            "identifier": metadata.cell_id,
            "chemistry": metadata.chemistry,
            "nominal_capacity_ah": metadata.nominal_capacity_ah,
        },
        "instrument": {"bench": bench, "channel": channel, "software": software_version()},
    }


# --- manifest and verification --------------------------------------------------------------
def manifest(folder: Path, names: list[str]) -> dict[str, dict[str, Any]]:
    """SHA-256 and size of each of ``names`` in ``folder`` that exists (a test that never
    recorded a row has no data files)."""
    out: dict[str, dict[str, Any]] = {}
    for name in names:
        path = folder / name
        if path.is_file():
            out[name] = {"sha256": sha256_file(path), "bytes": path.stat().st_size}
    return out


@dataclass
class Verification:
    """What ``verify`` found: ``problems`` empty when the folder is complete and unmodified."""

    folder: Path
    checked: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


class NotAResultFolder(ValueError):
    """The path is not a test's result folder at all (a usage error, not a failed check)."""


def _json(path: Path) -> Any:
    return json.loads(path.read_text(encoding="utf-8"))


def verify(folder: Path) -> Verification:
    """Recompute a finished test's hashes: complete (a final summary, its record count equal
    to the BDF rows, every file of its manifest present) and unmodified (every hash, the
    recipe text's too). ``NotAResultFolder`` when ``folder`` holds no test at all."""
    if not folder.is_dir():
        raise NotAResultFolder(f"{folder}: not a folder")
    summary_path, prov_path = folder / "summary.json", folder / PROVENANCE_NAME
    if not summary_path.exists() and not prov_path.exists():
        raise NotAResultFolder(f"{folder}: no summary.json nor {PROVENANCE_NAME}: not a test")
    v = Verification(folder)
    try:
        summary = _json(summary_path)
        if not isinstance(summary, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError) as exc:
        v.problems.append(f"summary.json unreadable: {exc}")
        summary = {}
    if summary and summary.get("complete") is not True:
        v.problems.append("summary.json is not final: the test has not ended")
    man = summary.get("manifest")
    if summary and not isinstance(man, dict):
        v.problems.append("summary.json has no manifest (written by an older version?)")
        man = {}
    for name, entry in sorted((man or {}).items()):
        path = folder / name
        if not path.is_file():
            v.problems.append(f"{name}: listed in the manifest, missing")
            continue
        want = entry.get("sha256") if isinstance(entry, dict) else None
        if sha256_file(path) != want:
            v.problems.append(f"{name}: modified (SHA-256 differs from the manifest)")
        else:
            v.checked.append(name)
    bdf = [n for n in (man or {}) if n.endswith(".bdf.csv")]
    if bdf and (folder / bdf[0]).is_file():
        with (folder / bdf[0]).open(encoding="utf-8") as f:
            rows = max(0, sum(1 for _ in f) - 1)
        if rows != summary.get("records"):
            v.problems.append(
                f"{bdf[0]}: {rows} rows, the summary counts {summary.get('records')} records"
            )
    try:
        prov = _json(prov_path)
        recipe = prov["recipe"]
        if sha256_bytes(str(recipe["text"]).encode("utf-8")) != recipe["sha256"]:
            v.problems.append(f"{PROVENANCE_NAME}: the recipe text does not match its SHA-256")
        else:
            v.checked.append(f"{PROVENANCE_NAME} recipe text")
    except FileNotFoundError:
        v.problems.append(f"{PROVENANCE_NAME}: missing")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        v.problems.append(f"{PROVENANCE_NAME} unreadable: {exc!r}")
    return v
