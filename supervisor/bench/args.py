"""``supervisor bench``'s arguments (the command line's parser registers them; only
``argparse`` here, so that building the parser imports no benchmark)."""

from __future__ import annotations

import argparse
from typing import Any, Final

__all__ = ["WHAT", "add_parser"]

WHAT: Final = (
    "scan", "manual", "seed002", "dry-run", "faults", "estop", "kill-restart", "historian",
    "influx", "opcua", "http", "load", "memory", "pi-budget", "report", "flood",
    "validate-attack", "cli", "fleet",
)  # fmt: skip
"""The benchmarks, as ``supervisor bench WHAT`` names them."""

NUMBERS: Final[tuple[tuple[str, type, float | int | None, str], ...]] = (
    ("--tags", int, None, "scan, historian, http: number of tags (1000); fleet: a bench's (100)"),
    ("--benches", int, 100, "fleet: simulated benches (edge nodes)"),
    ("--period-ms", float, 10.0, "scan, estop, historian: period in ms"),
    ("--presses", int, 100, "estop: e-stop presses"),
    ("--seconds", float, 10.0, "scan, historian, fleet: wall seconds to run (measured)"),
    ("--hours", float, 10.0, "manual: simulated hours"),
    ("--iterations", int, 20, "kill-restart: kills"),
    ("--seed", int, 1, "kill-restart: seed of the kill times"),
    ("--points", int, 200_000, "influx: points per round"),
    ("--rounds", int, 3, "influx: rounds of each writer"),
    ("--clients", int, 10, "opcua: subscribed clients"),
    ("--opcua-tags", int, 100, "opcua: analog tags changing"),
    ("--http-clients", int, 4, "http: GET /api/tags loops"),
    ("--ws-clients", int, 3, "http: WebSocket pages"),
    ("--minutes", float, 30.0, "memory: minutes to run"),
    ("--flood-http", int, 2000, "flood: idle HTTP connections"),
    ("--flood-opcua", int, 200, "flood: idle OPC UA connections"),
    ("--login-rate", float, 100.0, "flood: wrong logins per second"),
    ("--login-seconds", float, 30.0, "flood: seconds of wrong logins"),
    ("--warmup", float, None, "load, memory: warm-up seconds"),
    ("--http-rate", float, 10.0, "load: GET /api/tags per s"),
)
"""The numeric options: (flag, type, default, help)."""

SWITCHES: Final = (
    (
        "--bytecodes",
        "dry-run: instead of the speed, one scan's Python bytecodes and calls by function"
        " (a figure the machine's load does not move; traced: slow)",
    ),
    ("--recipes", "scan: a step chain on every channel"),
    ("--no-settle", "scan: no gc collect+freeze after warm-up"),
    ("--virtual", "memory --trace: the bench in process on the virtual clock (minutes simulated)"),
    ("--sim-in-process", "load: simulators inside the supervisor (default: a sim process)"),
)  # fmt: skip
"""The options that switch something on: (flag, help)."""


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``supervisor bench`` on the main parser's subcommands; its parser."""
    b: argparse.ArgumentParser = sub.add_parser("bench", help="benchmarks that print figures")
    b.add_argument("what", choices=WHAT)
    b.add_argument("--recipe", default="recipes/nimh-25h-slow-cycle.yaml", help="dry-run: recipe")
    b.add_argument(
        "--runs",
        type=int,
        default=5,
        choices=range(1, 101),
        metavar="1..100",
        help="dry-run: runs in this process, the median ratio recorded; cli: runs of each"
        " command, a fresh process each, the median recorded",
    )
    for flag, kind, default, text in NUMBERS:
        b.add_argument(flag, type=kind, default=default, help=text)
    for flag, text in SWITCHES:
        b.add_argument(flag, action="store_true", help=text)
    b.add_argument(
        "--trace",
        default=None,
        metavar="DIR",
        help="memory: tracemalloc snapshots into DIR, what grew printed (not the figure)",
    )
    b.add_argument(
        "--clients-nice",
        type=int,
        default=10,
        choices=range(20),
        metavar="0..19",
        help="load: niceness of the clients and influxd (they stand for other machines)",
    )
    b.add_argument("--out", default="var/bench", help="report: folder of results.json|md")
    return b
