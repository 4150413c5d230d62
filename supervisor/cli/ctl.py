"""``supervisor ctl``: a command-line OPC UA client of a running supervisor, for headless
benches worked over SSH (issue 11; seed 000's user has no screen).

It reads the channel nodes (``ns=<bench>;s=<tag>``, ADR 0014) and calls the channel
methods; a refused command answers a Bad status code with the command path's reason as its
``Result`` output argument, which is printed (exit 2). The server unreachable: one line,
exit 1. A login the server refuses: one line, exit 2 (a user mistake, like a refused
command: fix the user or the password and run again).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import getpass
import logging
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

if TYPE_CHECKING:
    from asyncua import Client

DEFAULT_URL: Final = "opc.tcp://127.0.0.1:4840/supervisor"
PASSWORD_ENV: Final = "SUPERVISOR_OPCUA_PASSWORD"
EXIT_OK, EXIT_FAIL, EXIT_REFUSED = 0, 1, 2
CONNECT_TIMEOUT_S: Final = 5.0
LIVENESS_S: Final = 1.0  # watch: how often an idle watch reads the server to see it is there

# verb → the channel method (supervisor/publish/opcua/methods.py::METHODS)
COMMANDS: Final[dict[str, str]] = {
    "start": "Start",
    "hold": "Hold",
    "resume": "Resume",
    "advance": "Advance",
    "stop": "Stop",
    "abort": "Abort",
    "reset": "Reset",
    "ack": "AcknowledgeAlarms",
}
# What `status` and `watch` read of each channel (tag suffixes, layout.py::CHANNEL_NAMES).
FIELDS: Final = (
    "chain.state",
    "mode",
    "chain.recipe",
    "chain.step_index",
    "chain.step",
    "chain.cycle",
    "chain.step_time",
    "chain.test_time",
    "voltage",
    "current",
    "charge_ah",
)
ALARM_FIELDS: Final = ("State", "Active", "Acked", "Severity", "Message")


class CtlError(Exception):
    """One line for the operator, and the exit code."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


def _out(msg: str) -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()


def _err(msg: str) -> None:
    sys.stderr.write(msg + "\n")
    sys.stderr.flush()


def add_parser(sub: Any) -> None:
    """Register ``supervisor ctl`` on the main parser's subcommands."""
    p = sub.add_parser(
        "ctl",
        help="command a running supervisor over OPC UA (status, start, hold, …)",
        description="A command-line OPC UA client of a running supervisor.",
        epilog="exit codes: 0 done; 1 the server cannot be reached; 2 a usage error, a login"
        f" or a command the server refused (its reason is printed). The password: --password"
        f" or ${PASSWORD_ENV} (asked for when neither is given and --user is).",
    )
    p.add_argument("--url", default=DEFAULT_URL, help=f"the server (default {DEFAULT_URL})")
    p.add_argument("--user", default=None, help="log in as this user (default: anonymous)")
    p.add_argument("--password", default=None, help=f"the user's password (or ${PASSWORD_ENV})")
    what = p.add_subparsers(dest="what", required=True)
    what.add_parser("status", help="a table of the channels: state, step, V, I, Ah")
    st = what.add_parser("start", help="load a recipe and start its test")
    st.add_argument("channel")
    st.add_argument("recipe", help="a recipe file as the server sees it, or its name")
    st.add_argument(
        "-p", "--param", action="append", default=[], metavar="NAME=VALUE", help="a parameter"
    )
    for verb in COMMANDS:
        if verb != "start":
            what.add_parser(verb, help=f"{COMMANDS[verb]} a channel").add_argument("channel")
    what.add_parser("alarms", help="the alarms that are active or not acknowledged")
    w = what.add_parser("watch", help="live lines until Ctrl-C: each step/state change")
    w.add_argument("channel", nargs="?", default=None, help="one channel (default: all)")
    w.add_argument(
        "--every", type=_positive, default=10.0, metavar="S", help="a line every S s too"
    )
    w.add_argument("--lines", type=int, default=0, help="stop after this many lines (0: never)")
    p.set_defaults(func=cmd_ctl)


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"{text!r}: give a positive number of seconds")
    return value


def cmd_ctl(args: argparse.Namespace) -> int:
    # asyncua logs its connection failures and warnings itself; the operator gets one line.
    ua_log = logging.getLogger("asyncua")
    level = ua_log.level
    ua_log.setLevel(logging.CRITICAL)
    try:
        return _ctl(args)
    finally:
        ua_log.setLevel(level)


def _ctl(args: argparse.Namespace) -> int:
    password = args.password if args.password is not None else os.environ.get(PASSWORD_ENV)
    if args.user and password is None:
        password = getpass.getpass(f"OPC UA password for {args.user}: ")
    try:
        return asyncio.run(_run(args, password))
    except CtlError as exc:
        _err(f"supervisor ctl: {exc}")
        return exc.code
    except KeyboardInterrupt:
        return EXIT_OK


async def _run(args: argparse.Namespace, password: str | None) -> int:
    from asyncua import Client, ua

    c = Client(args.url, timeout=CONNECT_TIMEOUT_S)
    if args.user:
        c.set_user(args.user)
        c.set_password(password or "")
    try:
        await c.connect()
    except ua.UaStatusCodeError as exc:
        who = f"user {args.user!r}" if args.user else "an anonymous session"
        raise CtlError(
            f"{args.url}: the server refused the login of {who} ({_code_name(exc.code)}):"
            " check --user and the password",
            EXIT_REFUSED,
        ) from None
    except (OSError, TimeoutError, ua.UaError) as exc:
        reason = str(exc) or type(exc).__name__
        raise CtlError(f"cannot reach {args.url}: {reason}", EXIT_FAIL) from None
    try:
        bench = await Bench.of(c)
        return await _do(bench, args)
    except (OSError, TimeoutError, ua.UaError) as exc:
        raise CtlError(f"{args.url}: connection lost: {exc or type(exc).__name__}", 1) from None
    finally:
        with contextlib.suppress(Exception):  # the connection is already gone: nothing to tell
            await c.disconnect()


def _code_name(code: int) -> str:
    from asyncua import ua

    return str(ua.StatusCode(code).name)


@dataclass
class Bench:
    """The server's bench as ctl sees it: its namespace index and its channels."""

    client: Client
    ns: int
    channels: list[str]

    @classmethod
    async def of(cls, c: Client) -> Bench:
        from asyncua import ua

        from supervisor.publish.opcua.layout import URN_PREFIX

        namespaces = await c.get_namespace_array()
        ns = next((i for i, u in enumerate(namespaces) if u.startswith(URN_PREFIX)), None)
        if ns is None:
            raise CtlError(f"{c.server_url.geturl()}: not a supervisor (no {URN_PREFIX}…)", 1)
        folder = c.get_node(ua.NodeId("/Bench/Channels", ns))
        names = [str((await n.read_browse_name()).Name) for n in await folder.get_children()]
        return cls(c, ns, names)

    def node(self, ident: str) -> Any:
        from asyncua import ua

        return ua.NodeId(ident, self.ns)

    def check_channel(self, channel: str) -> None:
        if channel not in self.channels:
            raise CtlError(
                f"{channel}: no such channel (channels: {', '.join(self.channels)})",
                EXIT_REFUSED,
            )

    async def read(self, idents: Sequence[str]) -> list[Any]:
        """The values of these nodes; None where the value is Bad or the node is missing."""
        from asyncua import ua

        params = ua.ReadParameters()
        for ident in idents:
            rv = ua.ReadValueId()
            rv.NodeId = self.node(ident)
            rv.AttributeId = ua.AttributeIds.Value
            params.NodesToRead.append(rv)
        results = await self.client.uaclient.read(params)
        return [None if not r.StatusCode.is_good() else r.Value.Value for r in results]

    async def alive(self) -> None:
        """Read the server's state: raises when the connection is gone."""
        from asyncua import ua

        await self.client.get_node(ua.ObjectIds.Server_ServerStatus_State).read_value()

    async def channel_values(self, channel: str) -> dict[str, Any]:
        values = await self.read([f"{channel}.{f}" for f in FIELDS])
        return dict(zip(FIELDS, values, strict=True))

    async def call(self, channel: str, method: str, *args: Any) -> tuple[bool, str, str]:
        """(accepted, the server's Result text, the status code's name)."""
        from asyncua import ua

        obj = f"/Bench/Channels/{channel}"
        req = ua.CallMethodRequest()
        req.ObjectId = self.node(obj)
        req.MethodId = self.node(f"{obj}/{method}")
        req.InputArguments = list(args)
        (res,) = await self.client.uaclient.call([req])
        text = str(res.OutputArguments[0].Value) if res.OutputArguments else ""
        return res.StatusCode.is_good(), text, str(res.StatusCode.name)


async def _do(bench: Bench, args: argparse.Namespace) -> int:
    from asyncua import ua

    if args.what == "status":
        rows = [await bench.channel_values(ch) for ch in bench.channels]
        for line in status_table(bench.channels, rows):
            _out(line)
        return EXIT_OK
    if args.what == "alarms":
        return await _alarms(bench)
    if args.what == "watch":
        return await _watch(bench, args)
    bench.check_channel(args.channel)
    call_args: list[Any] = []
    if args.what == "start":
        call_args = [
            ua.Variant(args.recipe, ua.VariantType.String),
            ua.Variant(list(args.param), ua.VariantType.String),
        ]
    ok, text, code = await bench.call(args.channel, COMMANDS[args.what], *call_args)
    if not ok:
        raise CtlError(f"{args.channel}: {args.what} refused ({code}): {text}", EXIT_REFUSED)
    _out(text)
    return EXIT_OK


def _num(value: Any, fmt: str) -> str:
    return "—" if value is None else format(value, fmt)


def _text(value: Any) -> str:
    return "—" if value is None or value == "" else str(value)


def status_table(channels: Sequence[str], rows: Sequence[dict[str, Any]]) -> list[str]:
    """One line per channel: state, mode, recipe, step (number and id), V, I, Ah."""
    head = ("channel", "state", "mode", "recipe", "step", "V", "I (A)", "Ah")
    body = []
    for ch, v in zip(channels, rows, strict=True):
        index = v["chain.step_index"]
        name = v["chain.step"]
        step = "—" if not index or not name else f"{index} {name}"
        body.append(
            (
                ch,
                _text(v["chain.state"]),
                _text(v["mode"]),
                _text(v["chain.recipe"]),
                step,
                _num(v["voltage"], ".3f"),
                _num(v["current"], "+.3f"),
                _num(v["charge_ah"], ".4f"),
            )
        )
    widths = [max(len(r[i]) for r in (head, *body)) for i in range(len(head))]
    return [
        "  ".join(
            c.ljust(w) if i < 5 else c.rjust(w)
            for i, (c, w) in enumerate(zip(r, widths, strict=True))
        ).rstrip()
        for r in (head, *body)
    ]


def watch_line(channel: str, v: dict[str, Any], wall: float) -> str:
    """A channel's line in the Chadèche display's shape (supervisor/publish/display.py:
    C|D/cycle/step, mA, step and test time, V, mAh, the date), with its state and step id;
    what a remote client cannot see (the commanded current, step time left) is left out."""
    amps = v["current"] or 0.0
    index = v["chain.step_index"]
    step = index or 0  # 1-based, 0 before the first step
    mah = "—" if v["charge_ah"] is None else f"{v['charge_ah'] * 1000:.1f}"
    date = time.strftime("%a %b %d %H:%M:%S %Y", time.localtime(wall))
    return (
        f"{channel} {'C' if amps >= 0 else 'D'}/{v['chain.cycle'] or 0:02d}/{step:02d}"
        f" mA={abs(amps) * 1000:3.0f} SET= {v['chain.step_time'] or 0:.0f}"
        f" TET= {v['chain.test_time'] or 0:.0f} V={_num(v['voltage'], '.3f')} mAh={mah}"
        f" {_text(v['chain.state'])} {_text(v['chain.step'])}, {date}"
    )


async def _alarms(bench: Bench) -> int:
    folder = bench.client.get_node(bench.node("/Bench/Alarms"))
    ids = [str((await n.read_browse_name()).Name) for n in await folder.get_children()]
    shown = 0
    for alarm in ids:
        state, active, acked, severity, message = await bench.read(
            [f"/Bench/Alarms/{alarm}/{f}" for f in ALARM_FIELDS]
        )
        if active or acked is False:
            _out(f"{alarm}  {_text(state)}  severity {_text(severity)}  {_text(message)}")
            shown += 1
    if not shown:
        _out(f"no active alarm ({len(ids)} alarms)")
    return EXIT_OK


async def _watch(bench: Bench, args: argparse.Namespace) -> int:
    """A subscription on each channel's state and step: a line at each change, and every
    ``--every`` s a line per channel with its V, I and Ah."""
    channels = bench.channels
    if args.channel is not None:
        bench.check_channel(args.channel)
        channels = [args.channel]
    changed: asyncio.Queue[str] = asyncio.Queue()

    class Handler:
        def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
            changed.put_nowait(str(node.nodeid.Identifier).partition(".")[0])

    sub = await bench.client.create_subscription(200, Handler())
    nodes = [
        bench.client.get_node(bench.node(f"{ch}.{f}"))
        for ch in channels
        for f in ("chain.state", "chain.step_index")
    ]
    await sub.subscribe_data_change(nodes)
    printed = 0
    last: dict[str, tuple[Any, Any]] = {}
    loop = asyncio.get_running_loop()
    next_all = loop.time() + args.every
    try:
        while not args.lines or printed < args.lines:
            periodic = False
            wait_s = min(LIVENESS_S, max(0.0, next_all - loop.time()))
            try:
                due = [await asyncio.wait_for(changed.get(), wait_s)]
                while not changed.empty():
                    due.append(changed.get_nowait())
            except TimeoutError:
                if loop.time() < next_all:
                    await bench.alive()  # a server gone away ends the watch (exit 1)
                    continue
                due, periodic = list(channels), True
                next_all = loop.time() + args.every
            for ch in dict.fromkeys(due):
                v = await bench.channel_values(ch)
                key = (v["chain.state"], v["chain.step_index"])
                if not periodic and last.get(ch) == key:
                    continue  # a notification with nothing new to show
                last[ch] = key
                _out(watch_line(ch, v, time.time()))
                printed += 1
                if args.lines and printed >= args.lines:
                    break
    finally:
        with contextlib.suppress(Exception):  # the connection is going away anyway
            await sub.delete()
    return EXIT_OK
