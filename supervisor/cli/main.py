"""``supervisor`` command line.

Exit codes: 0 success, 1 runtime failure, 2 usage or configuration error. A user
mistake gets one clear message naming file:line:col, never a traceback.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

from supervisor.core.errors import ConfigError, ConfigErrors, SupervisorError

log = logging.getLogger("supervisor")

DEFAULT_IO_MAP = Path("io_maps/sim.yaml")
EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2


def _err(msg: str) -> None:
    sys.stderr.write(msg.rstrip("\n") + "\n")


def _out(msg: str) -> None:
    sys.stdout.write(msg.rstrip("\n") + "\n")
    sys.stdout.flush()


def _setup_logging(level: str) -> None:
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
        stream=sys.stderr,
    )


# --- run -----------------------------------------------------------------------------
async def _run(args: argparse.Namespace) -> int:
    from supervisor.app import build_bench
    from supervisor.config.bench import load_bench
    from supervisor.core.clock import RealClock
    from supervisor.hmi import HttpApi

    cfg = load_bench(args.io_map)
    clock = RealClock()
    bench = build_bench(cfg, clock)
    port = cfg.hmi.port if args.http_port is None else args.http_port
    api = HttpApi(bench.db, clock, cfg.hmi.host, port)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await api.start()
    except OSError as exc:
        _err(f"supervisor: cannot listen on {cfg.hmi.host}:{port}: {exc.strerror or exc}")
        await bench.shutdown()
        return EXIT_USAGE
    _out(
        f"bench {cfg.bench!r}: {len(bench.db)} tags, {len(bench.channels)} channels,"
        f" scan period {cfg.scan.period_s * 1000:g} ms"
    )
    _out(f"HTTP API listening on {api.url}/tags")
    _out("Ctrl-C or SIGTERM stops the bench; every output goes to its safe state.")
    try:
        await bench.run(stop)
    finally:
        await bench.shutdown()
        await api.stop()
    _out("stopped: all outputs safe")
    return EXIT_OK


def cmd_run(args: argparse.Namespace) -> int:
    _setup_logging(args.log_level)
    if not Path(args.io_map).exists():
        _err(f"{args.io_map}: no such I/O map (give a path, e.g. io_maps/sim.yaml)")
        return EXIT_USAGE
    return asyncio.run(_run(args))


# --- check ---------------------------------------------------------------------------
def _check_one(path: Path) -> list[ConfigError]:
    from supervisor.config.bench import load_bench

    try:
        load_bench(path)
    except ConfigErrors as exc:
        return exc.errors
    except ConfigError as exc:
        return [exc]
    return []


def cmd_check(args: argparse.Namespace) -> int:
    bad = 0
    for f in args.files:
        errors = _check_one(Path(f))
        for e in errors:
            _err(e.location_message())
        if errors:
            bad += 1
        else:
            _out(f"{f}: OK")
    return EXIT_USAGE if bad else EXIT_OK


# --- schema --------------------------------------------------------------------------
def cmd_schema(args: argparse.Namespace) -> int:
    from supervisor.config.schema import write_schemas

    for path in write_schemas(Path(args.out)):
        _out(f"wrote {path}")
    return EXIT_OK


# --- bench ---------------------------------------------------------------------------
def cmd_bench(args: argparse.Namespace) -> int:
    from supervisor.app import benchmarks

    _setup_logging("warning")
    if args.what == "scan":
        return asyncio.run(
            benchmarks.scan_benchmark(args.tags, args.period_ms / 1000, args.seconds)
        )
    return asyncio.run(benchmarks.manual_charge_benchmark(args.hours))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="supervisor", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run a bench until Ctrl-C/SIGTERM")
    r.add_argument("io_map", nargs="?", default=str(DEFAULT_IO_MAP))
    r.add_argument("--http-port", type=int, default=None, help="override hmi.port (0 = any)")
    r.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    r.set_defaults(func=cmd_run)

    c = sub.add_parser("check", help="validate I/O maps; exit 2 on error")
    c.add_argument("files", nargs="+")
    c.set_defaults(func=cmd_check)

    s = sub.add_parser("schema", help="write the JSON Schemas editors use")
    s.add_argument("--out", default="io_maps", help="folder to write bench.schema.json into")
    s.set_defaults(func=cmd_schema)

    b = sub.add_parser("bench", help="benchmarks that print figures")
    b.add_argument("what", choices=["scan", "manual"])
    b.add_argument("--tags", type=int, default=1000, help="scan: number of tags")
    b.add_argument("--period-ms", type=float, default=10.0, help="scan: period in ms")
    b.add_argument("--seconds", type=float, default=10.0, help="scan: wall seconds to run")
    b.add_argument("--hours", type=float, default=10.0, help="manual: simulated hours")
    b.set_defaults(func=cmd_bench)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code: int = args.func(args)
    except ConfigErrors as exc:
        for e in exc.errors:
            _err(e.location_message())
        return EXIT_USAGE
    except ConfigError as exc:
        _err(exc.location_message())
        return EXIT_USAGE
    except SupervisorError as exc:
        _err(f"supervisor: {exc}")
        return EXIT_FAIL
    except KeyboardInterrupt:
        return EXIT_OK
    return code


if __name__ == "__main__":
    sys.exit(main())
