"""Secrets read from a file or an environment variable (never written in an I/O map): the
InfluxDB token, a notification route's password, header or URL."""

from __future__ import annotations

import os
from typing import Final

__all__ = ["SECRET_CHARS", "read_secret_env", "read_secret_file"]

SECRET_CHARS: Final = 4096
"""A secret file longer than this is not a secret (a wrong file named)."""


def read_secret_file(path: str, what: str = "secret file") -> str:
    """The one line of text in ``path``, its surrounding white space dropped; ValueError
    naming ``what`` and the path when it is missing, empty, too long or not one line."""
    try:
        with open(path, "rb") as f:  # noqa: PTH123 - bounded read below
            data = f.read(SECRET_CHARS + 1)
    except FileNotFoundError:
        raise ValueError(f"{what} {path!r} not found") from None
    except OSError as exc:
        raise ValueError(f"{what} {path!r} cannot be read: {exc.strerror or exc}") from None
    if len(data) > SECRET_CHARS:
        raise ValueError(f"{what} {path!r} is longer than {SECRET_CHARS} bytes")
    try:
        text = data.decode("utf-8").strip()
    except UnicodeDecodeError:
        raise ValueError(f"{what} {path!r} is not UTF-8 text") from None
    if not text:
        raise ValueError(f"{what} {path!r} is empty")
    if any(c in text for c in "\r\n"):
        raise ValueError(f"{what} {path!r} holds more than one line")
    return text


def read_secret_env(name: str) -> str:
    """The environment variable ``name``'s text; ValueError when it is unset or empty."""
    text = os.environ.get(name, "").strip()
    if not text:
        raise ValueError(f"environment variable {name} is not set")
    return text
