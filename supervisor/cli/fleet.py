"""``supervisor fleet --broker mqtt://HOST:PORT --group NAME [--listen HOST:PORT]
[--users FILE] [--host-id ID]``: the fleet overview, a Sparkplug B host application over a
lab's benches (issue 35; docs/fleet.md).

Prints ``fleet: http://HOST:PORT/`` once it listens (port 0: the one the system chose),
then runs until Ctrl-C or SIGTERM. Exit 2 for a usage error (a broker URL or group that is
not one, a users file refused, an address other than loopback without ``--users``).
"""

from __future__ import annotations

import argparse
import asyncio
import ipaddress
import re
import signal
import sys
from pathlib import Path
from typing import Any

EXIT_OK, EXIT_USAGE = 0, 2
DEFAULT_LISTEN = "127.0.0.1:8090"


def add_parser(sub: Any) -> None:
    """Register ``supervisor fleet`` on the main parser's subcommands."""
    p = sub.add_parser(
        "fleet",
        help="the fleet overview: every bench of a Sparkplug group, one page",
        description="A Sparkplug B host application: subscribes to spBv1.0/GROUP/# and"
        " serves the fleet page and GET /api/fleet (docs/fleet.md).",
    )
    p.add_argument("--broker", required=True, help="MQTT broker, mqtt://HOST:PORT")
    p.add_argument("--group", required=True, help="Sparkplug group id")
    p.add_argument(
        "--listen", default=DEFAULT_LISTEN, help=f"HTTP address (default {DEFAULT_LISTEN})"
    )
    p.add_argument(
        "--users",
        help="users file (a bench's: supervisor opcua add-user); without: loopback, no login",
    )
    p.add_argument("--keepalive-s", type=int, default=30, help="the fleet's MQTT keep-alive")
    p.add_argument(
        "--host-id",
        help="publish the Sparkplug host application STATE as this host id (spBv1.0/STATE/ID)",
    )
    p.add_argument("--log-level", default="INFO")
    p.set_defaults(func=cmd_fleet)


def _listen(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535 or not host:
        raise ValueError(f"--listen {text!r}: expected HOST:PORT")
    return host.strip("[]"), int(port)


def _loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def cmd_fleet(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from supervisor.cli.main import _setup_logging
    from supervisor.config.models import SPARKPLUG_ID_PATTERN, SparkplugConfig
    from supervisor.config.users import UserStore

    try:
        if args.host_id is not None and not re.match(SPARKPLUG_ID_PATTERN, args.host_id):
            raise ValueError(f"--host-id {args.host_id!r}: one topic level, no '/', '+', '#'")
        cfg = SparkplugConfig(broker=args.broker, group=args.group, edge_node=args.host_id)
        host, port = _listen(args.listen)
    except (ValidationError, ValueError) as exc:
        _err(f"supervisor fleet: {exc}")
        return EXIT_USAGE
    users = None
    if args.users:
        users = UserStore(Path(args.users))  # ConfigError: main says it (exit 2)
    elif not _loopback(host):
        _err(
            f"supervisor fleet: --listen {args.listen} without --users: anyone there would see"
            " the fleet; give the users file (login) or listen on loopback"
        )
        return EXIT_USAGE
    _setup_logging(args.log_level)
    mqtt = (cfg.host, cfg.port, cfg.group, args.keepalive_s, cfg.edge_node)
    return asyncio.run(_serve(mqtt, host, port, users))


async def _serve(
    broker: tuple[str, int, str, int, str | None], host: str, port: int, users: Any
) -> int:
    from supervisor.fleet import Fleet, FleetHost, FleetServer

    broker_host, broker_port, group, keepalive_s, host_id = broker
    fleet = Fleet(group)
    mqtt = FleetHost(fleet, broker_host, broker_port, keepalive_s=keepalive_s, host_id=host_id)
    server = FleetServer(fleet, lambda: mqtt.connected, users=users, host=host, port=port)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    await server.start()
    mqtt.start()
    _out(f"fleet: {server.url}")
    _out("Ctrl-C to stop")
    try:
        await stop.wait()
    finally:
        mqtt.stop()
        await server.stop()
    return EXIT_OK


def _out(msg: str) -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()


def _err(msg: str) -> None:
    sys.stderr.write(msg + "\n")
    sys.stderr.flush()
