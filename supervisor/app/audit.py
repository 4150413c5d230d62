"""A bench's audit trail, wired (``supervisor.audit``; docs/audit.md).

One log per bench, ``<state_dir>/audit.sqlite``, beside its retained state: the command
path records every command into it; the HMI its logins, logouts and recipe saves; the
command line its user and calibration changes. Opening it records the I/O map the bench
was started with (its path and the SHA-256 of the bytes loaded): a limit or a calibration
edited in the file shows as a new hash at the next start.
"""

from __future__ import annotations

import getpass
from typing import Final

from supervisor.app.bench import Bench
from supervisor.audit import AuditLog, audit_path

__all__ = ["START_ACTOR", "open_audit", "shell_actor"]

START_ACTOR: Final = "command line"
"""Who starts a bench (``supervisor run``; the actor of the recipes it is given too)."""


def shell_actor() -> str:
    """``cli:<login name>``: a command-line tool's actor (``cli`` when the name is unknown)."""
    try:
        return f"cli:{getpass.getuser()}"
    except (OSError, KeyError):  # no name for the uid (a container)
        return "cli"


def open_audit(bench: Bench) -> AuditLog:
    """The bench's audit log, open, given to its command path, its first entry the I/O
    map's load."""
    cfg = bench.cfg
    audit = AuditLog(audit_path(cfg.state_dir), wall=bench.clock.wall)
    audit.gate = bench.gate  # real clock: the writer keeps out of the scan's way
    audit.open()
    bench.commands.audit = audit
    audit.append(
        START_ACTOR,
        "io_map.load",
        cfg.source_file or cfg.bench,
        {"bench": cfg.bench, "path": cfg.source_file, "sha256": cfg.source_sha256},
    )
    return audit
