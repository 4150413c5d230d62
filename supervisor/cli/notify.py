"""``supervisor notify test [--io-map FILE]``: one test message through every notification
route of a bench (issue 34; docs/notifications.md).

Prints one line per route, ``<route>: OK`` or ``<route>: FAILED <why>``; exit 0 when every
route delivered, 1 when one did not, 2 for a configuration error (the I/O map refused, with
file:line:col, or no ``notifications:`` section). The test is recorded in the bench's
audit trail (``notify.test``, with each route's outcome).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from pathlib import Path
from typing import Any

EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2


def add_parser(sub: Any, default_io_map: Path) -> None:
    """Register ``supervisor notify`` on the main parser's subcommands."""
    p = sub.add_parser(
        "notify",
        help="notifications: send a test message through every route",
        description="A bench's notification routes (the I/O map's notifications: section).",
        epilog="exit codes: 0 every route delivered; 1 one did not; 2 a configuration error.",
    )
    what = p.add_subparsers(dest="action", required=True)
    t = what.add_parser("test", help="send a test message through every route")
    t.add_argument("--io-map", default=str(default_io_map), help="the bench's I/O map")
    t.set_defaults(func=cmd_notify)


def cmd_notify(args: argparse.Namespace) -> int:
    from supervisor.cli.audit import record
    from supervisor.devices.registry import load_bench
    from supervisor.notify import send_test

    if not Path(args.io_map).exists():
        _err(f"{args.io_map}: no such I/O map (give a path, e.g. io_maps/sim.yaml)")
        return EXIT_USAGE
    cfg = load_bench(args.io_map)  # ConfigErrors: main says them (exit 2)
    if cfg.notifications is None:
        _err(f"{args.io_map}: no notifications: section (docs/notifications.md)")
        return EXIT_USAGE
    results = asyncio.run(send_test(cfg.notifications, cfg.bench, time.time()))
    for route, why in results.items():
        _out(f"{route}: OK" if why is None else f"{route}: FAILED {why}")
    record(
        cfg.state_dir,
        "notify.test",
        cfg.bench,
        {"routes": {r: "ok" if why is None else why for r, why in results.items()}},
    )
    return EXIT_OK if all(why is None for why in results.values()) else EXIT_FAIL


def _err(msg: str) -> None:
    sys.stderr.write(msg + "\n")


def _out(msg: str) -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()
