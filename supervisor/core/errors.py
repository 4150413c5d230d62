"""Typed exceptions by lifecycle: configuration, device I/O, protocol, operator."""

from __future__ import annotations

from pathlib import Path


class SupervisorError(Exception):
    """Base of every error the supervisor raises on purpose."""


class ConfigError(SupervisorError):
    """A configuration or recipe file is wrong; names file, line and column (1-based)."""

    def __init__(
        self,
        message: str,
        file: str | Path | None = None,
        line: int | None = None,
        col: int | None = None,
    ) -> None:
        self.message = message
        self.file = str(file) if file is not None else None
        self.line = line
        self.col = col
        super().__init__(self.location_message())

    def location_message(self) -> str:
        where = self.file or "<config>"
        if self.line is not None:
            where += f":{self.line}"
            if self.col is not None:
                where += f":{self.col}"
        return f"{where}: {self.message}"


class ConfigErrors(SupervisorError):
    """Several configuration errors found in one pass (report them all at once)."""

    def __init__(self, errors: list[ConfigError]) -> None:
        self.errors = errors
        super().__init__("\n".join(e.location_message() for e in errors))


class DeviceIOError(SupervisorError):
    """A device could not be reached or a transfer failed."""

    def __init__(self, device: str, message: str) -> None:
        self.device = device
        super().__init__(f"{device}: {message}")


class DeviceTimeout(DeviceIOError):
    """A device did not answer in time."""


class ProtocolError(SupervisorError):
    """A device answered something that does not parse; keeps the raw bytes."""

    def __init__(self, device: str, message: str, raw: bytes = b"") -> None:
        self.device = device
        self.raw = raw
        super().__init__(f"{device}: {message} (received {raw!r})")


class OperatorError(SupervisorError):
    """A command that is not allowed now (wrong state, access level, unknown tag)."""
