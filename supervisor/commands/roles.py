"""Who may do what: the role hook of the command path.

docs/design.md "Safety" asks the one command path to check the role of whoever sends a command;
there are no users yet (the HTTP API answers on loopback, OPC UA user/password roles come
later), so the default lets everyone operate. A real policy implements ``Roles`` — e.g.
from the OPC UA session's user or an HTTP login — and is given to ``CommandPath``.
"""

from __future__ import annotations

from typing import Protocol

from supervisor.commands.model import Command
from supervisor.tags import Access


class Roles(Protocol):
    def access_of(self, actor: str) -> Access:
        """The highest tag access level ``actor`` has (tags declare what a write needs)."""
        ...

    def refuses(self, command: Command) -> str:
        """Why ``command.actor`` may not give ``command`` ("" when it may)."""
        ...


class EveryoneOperates:
    """No users yet: everyone has operator access and may give every command."""

    def access_of(self, actor: str) -> Access:
        return Access.OPERATOR

    def refuses(self, command: Command) -> str:
        return ""
