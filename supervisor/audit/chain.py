"""The audit log's entries and their hash chain (docs/adr/0047-audit-log.md).

An entry is: its sequence number (1, 2, 3… with no gap), its UTC time, the actor (as the
command path names them: ``hmi:alice``, ``opcua:bob``, ``command line``…), the kind of
action (``command.start``, ``login``, ``recipe.save``…), its target (a channel, a recipe
file, a user…), its details as canonical JSON, the hash of the entry before it and its
own hash: SHA-256 over a canonical encoding of every other field and the previous hash.

Changing any field of an entry changes its hash; rewriting that hash changes the next
entry's "previous hash"; deleting an entry leaves a gap in the sequence. What the chain
cannot see alone is a whole chain rewritten by someone who can write the file, or its
last entries cut off: an anchor kept elsewhere (the head hash exported or published,
``verify``'s ``anchor``) is what shows those.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

GENESIS: Final = "0" * 64
"""The "previous hash" of the first entry."""
ENCODING: Final = "audit/1"
"""Names the canonical encoding inside every hash: a later encoding cannot be mistaken for
this one."""


def canonical_json(value: Any) -> str:
    """``value`` as canonical JSON text: keys sorted, no white space, ASCII only (a lone
    surrogate written ``\\udXXX``, storable anywhere), a non-finite number as its text
    (``"nan"``: JSON has none) and anything else JSON does not know as its ``str``."""
    return json.dumps(
        _plain(value), sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False
    )


def _plain(value: Any) -> Any:
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        items = [_plain(v) for v in value]
        return sorted(items, key=canonical_json) if isinstance(value, set | frozenset) else items
    return str(value)


def utc_text(wall_s: float) -> str:
    """``2026-12-05T20:15:00.123456Z``: fixed width, so that texts sort as times."""
    whole = math.floor(wall_s)
    micros = min(999_999, round((wall_s - whole) * 1e6))
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(whole)) + f".{micros:06d}Z"


def entry_hash(
    seq: int, time_utc: str, actor: str, kind: str, target: str, details: str, prev_hash: str
) -> str:
    """SHA-256 (hex) of the entry's fields and the previous entry's hash, canonically
    encoded (a JSON array: each field delimited, none can run into the next)."""
    fields = [ENCODING, seq, time_utc, actor, kind, target, details, prev_hash]
    data = json.dumps(fields, separators=(",", ":"), ensure_ascii=True).encode("ascii")
    return hashlib.sha256(data).hexdigest()


@dataclass(frozen=True, slots=True)
class Entry:
    """One entry as stored."""

    seq: int
    time: str
    actor: str
    kind: str
    target: str
    details: str
    """Canonical JSON text (``canonical_json``): what the hash covers."""
    prev_hash: str
    hash: str

    @property
    def details_json(self) -> Any:
        """The details as data (the text itself if it is no JSON: a damaged entry)."""
        try:
            return json.loads(self.details)
        except ValueError:
            return self.details

    def computed_hash(self) -> str:
        return entry_hash(
            self.seq, self.time, self.actor, self.kind, self.target, self.details, self.prev_hash
        )

    def as_json(self) -> dict[str, Any]:
        return {
            "seq": self.seq,
            "time": self.time,
            "actor": self.actor,
            "kind": self.kind,
            "target": self.target,
            "details": self.details_json,
            "prev_hash": self.prev_hash,
            "hash": self.hash,
        }


@dataclass(frozen=True, slots=True)
class Broken:
    """The first entry where the chain breaks, and what is wrong there."""

    seq: int
    time: str
    problem: str

    def as_json(self) -> dict[str, Any]:
        return {"seq": self.seq, "time": self.time, "problem": self.problem}

    def line(self) -> str:
        when = f" ({self.time})" if self.time else ""
        return f"entry {self.seq}{when}: {self.problem}"


class ChainCheck:
    """Entries fed in sequence order; the first break is kept (``broken``)."""

    def __init__(self) -> None:
        self.entries = 0
        self.head = GENESIS
        self.last_seq = 0
        self.last_time = ""
        self.broken: Broken | None = None
        self.hashes_seen: set[str] | None = None

    def feed(self, e: Entry) -> bool:
        """Check one more entry; False once the chain is broken (stop feeding)."""
        problem = self._problem(e)
        if problem:
            seq = e.seq if isinstance(e.seq, int) else self.last_seq + 1
            self.broken = Broken(seq, e.time if isinstance(e.time, str) else "", problem)
            return False
        self.entries += 1
        self.head = e.hash
        self.last_seq = e.seq
        self.last_time = e.time
        if self.hashes_seen is not None:
            self.hashes_seen.add(e.hash)
        return True

    def _problem(self, e: Entry) -> str:
        if not isinstance(e.seq, int):
            return f"its sequence number is not a number ({e.seq!r})"
        expected = self.last_seq + 1
        if e.seq != expected:
            if self.last_seq == 0:
                return (
                    f"gap in sequence: the log begins at {e.seq} (entries 1..{e.seq - 1} missing)"
                )
            missing = (
                f"entry {expected} missing"
                if e.seq == expected + 1
                else f"entries {expected}..{e.seq - 1} missing"
            )
            return f"gap in sequence: follows entry {self.last_seq} ({missing})"
        texts = (e.time, e.actor, e.kind, e.target, e.details, e.prev_hash, e.hash)
        if not all(isinstance(x, str) for x in texts):
            return "content changed: a field is no longer text"
        if e.computed_hash() != e.hash:
            return "content changed: its fields do not give its hash"
        if e.prev_hash != self.head:
            return (
                "previous hash mismatch: it does not follow the entry before it"
                " (that entry, or this one, was rewritten)"
            )
        return ""

    def unreadable(self, why: str) -> None:
        """The file could not be read past the last entry fed."""
        self.broken = Broken(self.last_seq + 1, "", f"unreadable (damaged file: {why})")


def utc_of_iso(text: str) -> str:
    """An ISO 8601 time (``2026-12-05``, ``2026-12-05T20:15``, ``…Z``, ``…+01:00``) as
    ``utc_text``, for comparing with the entries' times; a time without a zone is UTC (the
    log's own). ``ValueError`` naming what is wrong."""
    from datetime import UTC, datetime

    given = text.strip()
    try:
        parsed = datetime.fromisoformat(given[:-1] + "+00:00" if given.endswith("Z") else given)
    except ValueError:
        raise ValueError(f"{text!r} is not an ISO 8601 time (e.g. 2026-12-05T20:15:00Z)") from None
    if parsed.tzinfo is None:
        parsed = parsed.replace(tzinfo=UTC)
    return utc_text(parsed.timestamp())
