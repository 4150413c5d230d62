"""One encoding policy for every writer (issue 28, finding 1).

A Python ``str`` may hold what no file can: a lone UTF-16 surrogate (U+D800..U+DFFF).
JSON lets a client send one (``"\\ud800"``), and ``json.loads`` hands it over as is. Every
writer encodes to UTF-8 (SQLite, the InfluxDB line protocol, result files, OPC UA
strings, log lines), and UTF-8 refuses it: ``UnicodeEncodeError ... surrogates not
allowed``. One viewer's refused tag write put the value in the refusal's event text, and
that event killed the historian's writer thread for good.

The policy, in two places:

- **At the edge, refused.** A value a client asks to write (an HTTP JSON body) with a
  lone surrogate is refused, 400, naming the member (``supervisor.hmi.body``): it is not
  text anybody typed, and nothing that cannot be stored should reach the bench.
- **At every writer, stored escaped.** Whatever still arrives (a refusal's text quoting
  the value, a name, a message built anywhere in the program) is stored with each
  character UTF-8 cannot encode written as its Python escape ``\\udXXX``
  (``backslashreplace``): the record keeps what was received, readable, and the writer
  lives. Refusing there instead would lose the very event that says what happened.
  Escaping only what cannot be encoded keeps every other text byte for byte. Log lines
  too (``StorableFormatter``).
"""

from __future__ import annotations

import logging
from typing import Final, TypeVar

WRITE_ERRORS: Final = "backslashreplace"
"""The ``errors=`` of every text file a writer opens (``open(..., errors=WRITE_ERRORS)``)."""

T = TypeVar("T")


def storable_text(text: str) -> str:
    """``text`` with every character UTF-8 cannot encode written as ``\\udXXX``; ``text``
    itself (no copy) when there is none, the usual case."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return text.encode("utf-8", WRITE_ERRORS).decode("utf-8")
    return text


def storable(value: T) -> T:
    """A value for a writer: a ``str`` made storable (``storable_text``), anything else as
    it is."""
    if isinstance(value, str):
        return storable_text(value)  # type: ignore[return-value]
    return value


def unencodable_at(text: str) -> int | None:
    """The index of the first character UTF-8 cannot encode (a lone surrogate), or None."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError as exc:
        return exc.start
    return None


class StorableFormatter(logging.Formatter):
    """Log lines made storable: a stream opened strict (``PYTHONIOENCODING=utf-8:strict``,
    a log file) would otherwise drop the line with a "--- Logging error ---" page."""

    def format(self, record: logging.LogRecord) -> str:
        return storable_text(super().format(record))
