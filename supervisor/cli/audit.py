"""``supervisor audit verify|export``: a bench's audit trail from the shell (issue 34;
docs/audit.md).

- ``verify [--io-map FILE] [--anchor HASH]``: the hash chain of the bench's
  ``<state_dir>/audit.sqlite`` checked whole. Exit 0 "audit log OK: N entries, head H";
  exit 1 naming the first broken entry (sequence, time, what is wrong: content changed,
  previous hash mismatch, gap in sequence), or the anchor (a head hash kept elsewhere)
  not found in the chain; exit 2 when the file is missing or no audit log, one line.
- ``export --since TIME [--until TIME] [--format csv|json] [-o FILE]``: the entries of
  that time span (ISO 8601; without a zone, UTC), oldest first, to stdout or ``FILE``;
  ``--actor``, ``--kind`` (a kind or a family: ``command``) and ``--channel`` select.

``--file`` reads a given audit file instead of a bench's (a copy kept elsewhere). Bad
arguments: exit 2, one line, no traceback.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
from pathlib import Path
from typing import Any, Final

EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2
FORMULA_STARTS: Final = ("=", "+", "-", "@", "\t", "\r")
CSV_COLUMNS: Final = ("seq", "time", "actor", "kind", "target", "details", "prev_hash", "hash")


def _iso_time(text: str) -> str:
    from supervisor.audit import utc_of_iso

    try:
        return utc_of_iso(text)
    except (ValueError, OverflowError, OSError) as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _anchor(text: str) -> str:
    value = text.strip().lower()
    if len(value) != 64 or any(c not in "0123456789abcdef" for c in value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a SHA-256 hash (64 hex digits)")
    return value


def add_parser(sub: Any, default_io_map: Path) -> None:
    """Register ``supervisor audit`` on the main parser's subcommands."""
    p = sub.add_parser(
        "audit",
        help="the audit trail: verify its hash chain, export its entries (CSV, JSON)",
        description="A bench's audit trail (<state_dir>/audit.sqlite): who did what, in a"
        " hash chain (docs/audit.md).",
        epilog="exit codes: 0 OK (verify) or exported; 1 the chain is broken (the first broken"
        " entry named); 2 a usage error, or the log is missing or unreadable.",
    )
    what = p.add_subparsers(dest="action", required=True)
    v = what.add_parser("verify", help="check the hash chain; name the first broken entry")
    e = what.add_parser("export", help="the entries of a time span as CSV or JSON")
    for q in (v, e):
        q.add_argument(
            "--io-map", default=str(default_io_map), help="the bench whose log (its state_dir)"
        )
        q.add_argument("--file", default=None, help="this audit file instead of the bench's")
    v.add_argument(
        "--anchor",
        type=_anchor,
        default=None,
        help="a head hash kept elsewhere: the log must still hold it (not cut short)",
    )
    e.add_argument("--since", type=_iso_time, required=True, help="ISO 8601 (no zone: UTC)")
    e.add_argument("--until", type=_iso_time, default=None, help="ISO 8601 (no zone: UTC)")
    e.add_argument("--format", choices=["csv", "json"], default="csv")
    e.add_argument("--actor", default="")
    e.add_argument("--kind", default="", help="a kind (command.start) or a family (command)")
    e.add_argument("--channel", default="")
    e.add_argument("-o", "--output", default=None, help="write here (default: stdout)")
    v.set_defaults(func=cmd_audit)
    e.set_defaults(func=cmd_audit)


def _log_path(args: argparse.Namespace) -> Path | None:
    """The audit file asked for (None: the I/O map is missing, said on stderr)."""
    from supervisor.audit import audit_path
    from supervisor.devices.registry import load_bench

    if args.file:
        return Path(args.file)
    if not Path(args.io_map).exists():
        _err(f"{args.io_map}: no such I/O map (give a path, e.g. io_maps/sim.yaml)")
        return None
    return audit_path(load_bench(args.io_map).state_dir)  # ConfigErrors: main says them


def cmd_audit(args: argparse.Namespace) -> int:
    from supervisor.audit import AuditFileError

    path = _log_path(args)
    if path is None:
        return EXIT_USAGE
    try:
        if args.action == "verify":
            return _verify(path, args.anchor)
        return _export(path, args)
    except AuditFileError as exc:
        _err(f"supervisor audit {args.action}: {exc}")
        return EXIT_USAGE


def _verify(path: Path, anchor: str | None) -> int:
    from supervisor.audit import verify_file

    v = verify_file(path, anchor)
    if v.broken is not None:
        _out(f"audit log BROKEN: {path}: {v.broken.line()}")
        _out(f"  {v.entries} entries before it verified (up to head {v.head})")
        return EXIT_FAIL
    if v.anchor_found is False:
        _out(
            f"audit log NOT verified: {path}: the anchor {anchor} is in none of its {v.entries}"
            f" entries (the log was cut short or rewritten since that head was kept)"
        )
        return EXIT_FAIL
    _out(f"audit log OK: {v.entries} entries, head {v.head}")
    return EXIT_OK


def _export(path: Path, args: argparse.Namespace) -> int:
    from supervisor.audit import Query, read_entries

    query = Query(
        since=args.since,
        until=args.until or "",
        actor=args.actor,
        kind=args.kind,
        channel=args.channel,
    )
    entries = read_entries(path, query)
    if args.format == "json":
        text = json.dumps({"entries": [e.as_json() for e in entries]}, indent=1) + "\n"
    else:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(CSV_COLUMNS)
        for e in entries:
            w.writerow([_cell(getattr(e, c)) for c in CSV_COLUMNS])
        text = buf.getvalue()
    if args.output:
        try:
            Path(args.output).write_text(text, "utf-8", "backslashreplace")
        except OSError as exc:
            _err(f"supervisor audit export: cannot write {args.output}: {exc.strerror or exc}")
            return EXIT_USAGE
        _err(f"{len(entries)} entries written to {args.output}")
    else:
        sys.stdout.write(text)
    return EXIT_OK


def _cell(value: object) -> object:
    """A text a spreadsheet would run as a formula (a user name tried at the login, a tag
    name: ``=HYPERLINK(…)``) written with a leading ``'`` (OWASP, CSV injection); the
    JSON export keeps every text exact."""
    if isinstance(value, str) and value[:1] in FORMULA_STARTS:
        return "'" + value
    return value


def _err(msg: str) -> None:
    sys.stderr.write(msg + "\n")


def _out(msg: str) -> None:
    sys.stdout.write(msg + "\n")


def record(state_dir: str | Path, kind: str, target: str, details: dict[str, Any]) -> None:
    """One action of a command-line tool into the bench's audit trail (actor
    ``cli:<login name>``), written before returning; a failure is said on stderr, the
    action stands (it is done)."""
    from supervisor.app.audit import shell_actor
    from supervisor.audit import append_now, audit_path

    path = audit_path(state_dir)
    why = append_now(path, shell_actor(), kind, target, details)
    if why is not None:
        _err(f"warning: {kind} {target} not recorded in the audit log {path}: {why}")
