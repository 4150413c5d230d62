"""``supervisor modbus map IOMAP``: the Modbus register map of an I/O map as CSV (issue 36,
ADR 0031), for a panel-HMI or SCADA tool to import. Nothing is opened or served: the
bench's tags are declared with stand-in drivers (``app/tagset.py``), so it runs on any
machine, and imports no server or field-bus package (tests/unit/test_cli_imports.py)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

EXIT_OK, EXIT_USAGE = 0, 2

__all__ = ["add_parser"]


def add_parser(sub: Any) -> None:
    """Register ``supervisor modbus`` on the main parser's subcommands."""
    p = sub.add_parser(
        "modbus",
        help="Modbus TCP server: map IOMAP prints its register map as CSV",
        description="The Modbus TCP server's register map (docs/integrator.md 'Modbus TCP').",
        epilog="exit codes: 0 printed; 2 the I/O map is refused (as by supervisor check).",
    )
    what = p.add_subparsers(dest="what", required=True)
    m = what.add_parser(
        "map",
        help="the register map as CSV: address, reference, function, type, word_order, tag,"
        " unit, scale, access, codes",
    )
    m.add_argument("io_map")
    m.add_argument("-o", "--output", default=None, help="write the CSV here (default: stdout)")
    m.set_defaults(func=cmd_modbus_map)


def cmd_modbus_map(args: argparse.Namespace) -> int:
    from supervisor.app.tagset import declared_tags
    from supervisor.core.errors import ConfigError, ConfigErrors
    from supervisor.devices.registry import load_bench
    from supervisor.publish.modbus.mapcsv import map_csv
    from supervisor.publish.modbus.regmap import plan

    try:
        cfg = load_bench(args.io_map)
    except ConfigErrors as exc:
        for e in exc.errors:
            sys.stderr.write(e.location_message() + "\n")
        return EXIT_USAGE
    except ConfigError as exc:
        sys.stderr.write(exc.location_message() + "\n")
        return EXIT_USAGE
    if cfg.modbus_server is None:
        sys.stderr.write(
            f"{args.io_map}: note: no modbus_server: section, the server is off; the map it"
            " would serve:\n"
        )
    writes = cfg.modbus_server is None or cfg.modbus_server.writes
    text = map_csv(plan(cfg, declared_tags(cfg)), writes)
    if args.output is None:
        sys.stdout.write(text)
        sys.stdout.flush()
    else:
        Path(args.output).write_text(text, encoding="utf-8")
    return EXIT_OK
