"""What an entry says of a changed file: its content's SHA-256 and a unified diff against
the version it replaced (a recipe saved from the screens, an I/O map calibrated)."""

from __future__ import annotations

import difflib
import hashlib
from typing import Any, Final

MAX_DIFF_CHARS: Final = 64 * 1024
"""A diff longer than this is cut (``diff_truncated``): the hashes still name both versions
(a recipe is at most a few hundred lines; a whole file replaced by a generated one is not
worth a megabyte of log)."""


def sha256_text(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest()


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def text_change(previous: str | None, text: str, name: str) -> dict[str, Any]:
    """``sha256``, ``previous_sha256`` (None: the file is new) and ``diff`` (unified,
    ``a/name`` → ``b/name``). Computes a diff: call it off the event loop for large texts."""
    before = previous if previous is not None else ""
    lines = difflib.unified_diff(
        before.splitlines(keepends=True),
        text.splitlines(keepends=True),
        fromfile=f"a/{name}" if previous is not None else "/dev/null",
        tofile=f"b/{name}",
    )
    diff = "".join(
        line if line.endswith("\n") else line + "\n\\ No newline at end of file\n" for line in lines
    )
    out: dict[str, Any] = {
        "sha256": sha256_text(text),
        "previous_sha256": sha256_text(previous) if previous is not None else None,
        "diff": diff[:MAX_DIFF_CHARS],
    }
    if len(diff) > MAX_DIFF_CHARS:
        out["diff_truncated"] = True
    return out
