"""Input limits: how much a file, a recipe or a dry run may ask for, in one place.

Everything a user hands the supervisor (a recipe, an I/O map, a Chadèche sequence or
parameter file, a load profile) is read, parsed and compiled in full before it is used;
without a bound a valid but huge file (a 20 MB recipe, 700 000 sequence rows, 327 000
tags) takes minutes and gigabytes, and a device such as ``/dev/zero`` never ends. Each
limit is far above what a bench needs (the shipped files are a few kB; seed 000's
sequence files have tens of rows) and each refusal is one message naming the file, the
limit and what to do (README "Input limits"). The byte size is checked before a file is
read in full: a regular file by its size, anything else (a pipe, a device) by reading at
most one byte more than the limit.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Final

from supervisor.core.errors import ConfigError

__all__ = [
    "DRY_RUN_CYCLES_KEPT",
    "DRY_RUN_EVENTS_KEPT",
    "DRY_RUN_PREVIEW_TIMEOUT_S",
    "MAX_CYCLES",
    "MAX_INITIAL_CHARGE_AH",
    "MAX_IO_MAP_TAGS",
    "MAX_PROFILE_CSV_BYTES",
    "MAX_PROFILE_REPEAT",
    "MAX_PROFILE_ROWS",
    "MAX_RECIPE_GROUPS",
    "MAX_RECIPE_STEPS",
    "MAX_SCAN_PERIOD_S",
    "MAX_SEQUENCE_ROWS",
    "MAX_TEXT_BYTES",
    "MAX_TRANSITIONS_PER_SCAN",
    "MAX_YAML_BYTES",
    "MAX_YAML_TEXT_CHARS",
    "MAX_YAML_VALUES",
    "MIN_SCAN_PERIOD_S",
    "RECIPE_CHECK_MEMORY_BYTES",
    "RECIPE_CHECK_WORKERS",
    "RECIPE_COMPILE_TIMEOUT_S",
    "TooLarge",
    "read_limited",
    "size_text",
]

MIN_SCAN_PERIOD_S: Final = 0.001
MAX_SCAN_PERIOD_S: Final = 10.0
"""Scan period bounds (also those of ``supervisor dry-run --period-s``). Here, not beside
the I/O map's models, so that the command line's parser has them without the models."""

KIB: Final = 1024
MIB: Final = 1024 * KIB

# --- files ------------------------------------------------------------------------------
MAX_YAML_BYTES: Final = 1 * MIB
"""A recipe or an I/O map (the shipped ones are 1–10 kB). Parsing keeps every node's
position, in pure Python: a megabyte takes 5 to 9 s on a small two-core machine, which is
why a recipe is compiled in a worker thread, never on the scan's loop."""

MAX_YAML_VALUES: Final = 500_000
"""Values in one YAML document once aliases are expanded (``*a`` counts the whole anchored
node each time it is used): what the models validate. Bounds the "billion laughs"
document, a few hundred bytes that expand to 10⁹ values. Counted while the document is
built, merge keys included (``<<: *a`` counts every key of ``a`` each time): a merge bomb
is refused after building at most this many, not after gigabytes."""

MAX_YAML_TEXT_CHARS: Final = MAX_YAML_BYTES
"""Characters of text (keys and scalars) in one YAML document once aliases are expanded:
what the compiler reads. A file without aliases never holds more text than its size; a
100 kB condition anchored once and used as the ``until`` of 100 steps stands for 10 MB of
expressions to check (issue 28)."""

MAX_TEXT_BYTES: Final = 1 * MIB
"""A Chadèche sequence file (seed 000 §III.D) or its ``chadecheN.prm``."""

MAX_PROFILE_CSV_BYTES: Final = 8 * MIB
"""A load profile CSV (seed 002 §2.3): a day at one row a second with its V/I/T columns."""

# --- contents ---------------------------------------------------------------------------
MAX_RECIPE_STEPS: Final = 10_000
"""Steps of a recipe, counted once YAML aliases are expanded (a Chadèche sequence file at
its limit makes at most 4 000)."""
MAX_RECIPE_GROUPS: Final = 1_000
MAX_PROFILE_ROWS: Final = 100_000
"""Rows of one profile (inline ``rows:`` or its CSV, plus a header line): 27 h at one row
a second. Inline rows reach the 1 MiB file limit first (a row takes 20 bytes)."""
MAX_PROFILE_REPEAT: Final = 1_000_000
"""``repeat:`` of a profile: as many as a recipe's cycles. ``10**400`` was accepted and the
test aborted in its first scan (the profile's end time as a float overflowed; issue 28)."""
MAX_CYCLES: Final = 1_000_000
"""``cycles:`` of a recipe (and a Chadèche ``.prm``'s ``-n``)."""
MAX_INITIAL_CHARGE_AH: Final = 100_000.0
"""``initial_charge`` magnitude: no cell on a bench holds 100 kAh; ``1e300 Ah`` is a slip."""
MAX_SEQUENCE_ROWS: Final = 2_000
"""Rows of a Chadèche sequence file (each becomes at most two recipe steps)."""
MAX_IO_MAP_TAGS: Final = 10_000
"""``tags:`` of one I/O map (a bench has hundreds)."""

# --- running ------------------------------------------------------------------------------
RECIPE_COMPILE_TIMEOUT_S: Final = 30.0
"""Reading, parsing and compiling a recipe for a load (HTTP, ``--recipe``), in a worker
thread: past this the load is refused (HTTP 503) and the worker abandoned. A file at the
limits (1 MiB, 6 000 steps with their conditions) takes 5 to 10 s on a small two-core
machine; what takes longer is stuck (a named pipe nobody writes to, a hung network share)."""

RECIPE_CHECK_MEMORY_BYTES: Final = 1024 * MIB
"""Address space of the child process a recipe text posted to the HTTP API is checked in
(``RLIMIT_AS``; the interpreter and its modules take about 150 MiB of it): past it the
check is refused (HTTP 413) and the supervisor's own memory never grew."""
RECIPE_CHECK_WORKERS: Final = 2
"""Recipe texts checked at once for the HTTP API, each in its child process (as many more
wait; beyond that HTTP 503 with Retry-After)."""

MAX_TRANSITIONS_PER_SCAN: Final = 100
"""Steps a chain may enter in one scan (goto chains, ends of cycles): more is a loop that
lets no time pass; the chain is held with a supervision alarm instead of spinning."""

DRY_RUN_EVENTS_KEPT: Final = 1_000
"""Timeline events a dry run keeps (the first half and the last half; the count of the
ones between is reported)."""
DRY_RUN_CYCLES_KEPT: Final = 200
"""Cycles a dry run reports one by one (the first half and the last half)."""
DRY_RUN_PREVIEW_TIMEOUT_S: Final = 60.0
"""Computing time of the HMI's dry-run preview (``POST /api/recipes/dryrun``, in a worker
thread): the 25 h NiMH recipe takes about 6 s; past the limit the preview stops where it
is and says so (``supervisor dry-run`` runs a longer test to its end)."""


class TooLarge(ConfigError):
    """An input over one of the limits above (a ``ConfigError``: exit 2, no traceback)."""


def size_text(n_bytes: int) -> str:
    """``1 MiB``, ``8 MiB``, ``512 kiB``, ``900 bytes``."""
    if n_bytes >= MIB and n_bytes % MIB == 0:
        return f"{n_bytes // MIB} MiB"
    if n_bytes >= KIB and n_bytes % KIB == 0:
        return f"{n_bytes // KIB} kiB"
    return f"{n_bytes:,} bytes"


def read_limited(path: str | Path, limit_bytes: int, what: str) -> bytes:
    """The bytes of ``path``, refused with :class:`TooLarge` when over ``limit_bytes``.

    A regular file is refused by its size before anything is read; anything else (a pipe,
    a character device such as ``/dev/zero``) by reading at most ``limit_bytes + 1``
    bytes. ``what`` names the kind of file in the message ("a recipe"). ``OSError`` is
    left to the caller (each says "file not found" its own way).
    """
    file = str(path)
    with Path(path).open("rb") as f:
        st = os.fstat(f.fileno())
        if stat.S_ISREG(st.st_mode) and st.st_size > limit_bytes:
            raise TooLarge(too_large_message(what, f"{st.st_size:,} bytes", limit_bytes), file)
        data = f.read(limit_bytes + 1)
    if len(data) > limit_bytes:
        size = f"more than {size_text(limit_bytes)}"
        raise TooLarge(too_large_message(what, size, limit_bytes), file)
    return data


def too_large_message(what: str, size: str, limit_bytes: int) -> str:
    return (
        f"file is too large: {size}; {what} may have at most {size_text(limit_bytes)}"
        " (README: Input limits)"
    )
