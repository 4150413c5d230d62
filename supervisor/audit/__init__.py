"""The audit trail: who did what to the bench, in a log that cannot be edited silently
(issue 34, docs/adr/0047-audit-log.md, docs/audit.md).

``AuditLog(path).open()`` then ``append(actor, kind, target, details)`` from any thread:
queued, written by its own thread, each entry chained to the one before it by its hash.
``verify_file`` checks a chain and names the first broken entry; ``read_entries`` selects
entries (``Query``) for the export and the HTTP API.

Kinds recorded (``KINDS``): ``command.<verb>`` (every command of the command path,
accepted or refused), ``login``, ``login.failed``, ``login.refused``, ``logout``,
``recipe.save``, ``io_map.load``, ``calibration.write``, ``user.add``, ``user.remove``,
``notify.test``.
"""

from supervisor.audit.chain import GENESIS, Broken, Entry, canonical_json, utc_of_iso, utc_text
from supervisor.audit.changes import sha256_bytes, sha256_text, text_change
from supervisor.audit.store import (
    AUDIT_NAME,
    AuditFileError,
    AuditLog,
    Query,
    Verification,
    append_now,
    audit_path,
    read_entries,
    verify_file,
)

KINDS = (
    "command",
    "login",
    "login.failed",
    "login.refused",
    "logout",
    "recipe.save",
    "io_map.load",
    "calibration.write",
    "user.add",
    "user.remove",
    "notify.test",
)
"""The kinds (and kind families: ``command`` is ``command.<verb>``) the product records."""

__all__ = [
    "AUDIT_NAME",
    "GENESIS",
    "KINDS",
    "AuditFileError",
    "AuditLog",
    "Broken",
    "Entry",
    "Query",
    "Verification",
    "append_now",
    "audit_path",
    "canonical_json",
    "read_entries",
    "sha256_bytes",
    "sha256_text",
    "text_change",
    "utc_of_iso",
    "utc_text",
    "verify_file",
]
