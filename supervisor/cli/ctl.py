"""``supervisor ctl``: a command-line OPC UA client of a running supervisor, for headless
benches worked over SSH (issue 11; seed 000's user has no screen).

It reads the channel nodes (``ns=<bench>;s=<tag>``, ADR 0014) and calls the channel
methods; a refused command answers a Bad status code with the command path's reason as its
``Result`` output argument, which is printed (exit 2). The server unreachable: one line,
exit 1. A login the server refuses: one line, exit 2 (a user mistake, like a refused
command: fix the user or the password and run again).

Security (ADR 0014 "Security"): ``--security sign|sign_and_encrypt`` connects over
Basic256Sha256 with a client certificate, ``--cert/--key`` or one made on first use in
``$XDG_CONFIG_HOME/bench-supervisor/ctl-pki`` (``supervisor ctl cert`` prints its path). The
server accepts it only once an administrator copied it into the server's ``pki/trusted``:
until then ctl says so in one line and exits 1 (nothing to fix on this command line). A
server with the None policy switched off is told apart from a refusal: one line saying to
use ``--security``, exit 2.
"""

from __future__ import annotations

import argparse
import contextlib
import getpass
import logging
import os
import socket
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

if TYPE_CHECKING:
    from asyncua import Client

DEFAULT_URL: Final = "opc.tcp://127.0.0.1:4840/supervisor"
PASSWORD_ENV: Final = "SUPERVISOR_OPCUA_PASSWORD"
EXIT_OK, EXIT_FAIL, EXIT_REFUSED = 0, 1, 2
CONNECT_TIMEOUT_S: Final = 5.0
LIVENESS_S: Final = 1.0  # watch: how often an idle watch reads the server to see it is there
SECURITY: Final = ("none", "sign", "sign_and_encrypt")
# The server's trust list (supervisor/publish/opcua/security.py::Pki), for the messages.
SERVER_TRUSTED: Final = "<state_dir>/opcua/pki/trusted"
# A refusal of the client's certificate (OPC UA Part 4 §7.34 certificate status codes), as
# opposed to a refused login: the fix is on the server, not on this command line.
CERT_REFUSALS: Final = frozenset(
    {
        "BadCertificateUntrusted",
        "BadCertificateInvalid",
        "BadCertificateUriInvalid",
        "BadCertificateTimeInvalid",
        "BadCertificateIssuerTimeInvalid",
        "BadCertificateUseNotAllowed",
        "BadCertificateRevoked",
        "BadCertificateIssuerRevoked",
        "BadCertificateRevocationUnknown",
        "BadCertificateIssuerRevocationUnknown",
        "BadCertificateChainIncomplete",
        "BadCertificatePolicyCheckFailed",
        "BadSecurityChecksFailed",
    }
)

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
# The chain's state is read as its number (StateMachine/CurrentState/Number: CurrentState
# holds its PackML name) and shown by the name the operator knows (``Running``).
FIELDS: Final = (
    "chain.state_code",
    "mode",
    "chain.recipe",
    "chain.step_index",
    "chain.step",
    "chain.cycle",
    "chain.step_time",
    "chain.test_time",
    "voltage",
    "current",
    "chain.charge_ah",
    "state",
    "current_cmd",
)
ALARM_FIELDS: Final = ("State", "Active", "Acked", "Severity", "Message")
# `ctl estop [reset]` → the Bench object's method (methods.py::BENCH_METHODS).
ESTOP_METHODS: Final = {None: "EmergencyStop", "reset": "ResetEmergencyStop"}


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


def _add_session_options(p: argparse.ArgumentParser) -> None:
    """The server, the login and the message security of ctl's OPC UA session."""
    p.add_argument("--url", default=DEFAULT_URL, help=f"the server (default {DEFAULT_URL})")
    p.add_argument("--user", default=None, help="log in as this user (default: anonymous)")
    given = p.add_mutually_exclusive_group()
    given.add_argument("--password", default=None, help=f"the user's password (or ${PASSWORD_ENV})")
    given.add_argument(
        "--password-stdin",
        action="store_true",
        help="read the password from the first line of standard input (for scripts: a"
        " password on the command line shows in the process list)",
    )
    p.add_argument(
        "--security",
        choices=SECURITY,
        default="none",
        help="the message security (Basic256Sha256 for sign and sign_and_encrypt; default none)",
    )
    p.add_argument("--cert", type=Path, default=None, help="this client's certificate (DER/PEM)")
    p.add_argument("--key", type=Path, default=None, help="its private key (PEM)")


def add_parser(sub: Any) -> None:
    """Register ``supervisor ctl`` on the main parser's subcommands."""
    p = sub.add_parser(
        "ctl",
        help="command a running supervisor over OPC UA (status, start, hold, …)",
        description="A command-line OPC UA client of a running supervisor.",
        epilog="exit codes: 0 done; 1 the server cannot be reached, or it does not trust this"
        " client's certificate (copy it into the server's pki/trusted); 2 a usage error, a"
        " security mode the server does not offer, a login or a command the server refused"
        f" (its reason is printed). The password: --password-stdin (its first line),"
        f" ${PASSWORD_ENV} or --password (seen by anyone who lists processes: avoid it; asked"
        " for when none is given and --user is). The client certificate: --cert/--key, or"
        f" made on first use in {default_pki_hint()} (`supervisor ctl cert` prints it).",
    )
    _add_session_options(p)
    what = p.add_subparsers(dest="what", required=True)
    what.add_parser(
        "status",
        help="a table of the channels: what each does, its chain's state, step, V, I, charge",
    )
    st = what.add_parser("start", help="load a recipe and start its test")
    st.add_argument("channel")
    st.add_argument("recipe", help="a recipe file as the server sees it, or its name")
    st.add_argument(
        "-p", "--param", action="append", default=[], metavar="NAME=VALUE", help="a parameter"
    )
    # The test's metadata (docs/recipes.md "Test records"): the server checks them.
    st.add_argument("--cell", default="", metavar="ID", help="the cell or sample tested")
    st.add_argument("--chemistry", default="", help="the cell's chemistry (e.g. nimh)")
    st.add_argument("--capacity", default="", help="the cell's nominal capacity (e.g. 2.5 Ah)")
    st.add_argument("--comment", default="", help="a free comment")
    for verb in COMMANDS:
        if verb not in ("start", "ack"):
            what.add_parser(verb, help=f"{COMMANDS[verb]} a channel").add_argument("channel")
    what.add_parser(
        "ack", help="acknowledge what holds a channel, or one alarm (its id in `ctl alarms`)"
    ).add_argument("channel", metavar="CHANNEL|ALARM")
    _add_bench_parsers(what)
    w = what.add_parser(
        "watch", help="live lines until Ctrl-C (or --count): each step/state change"
    )
    w.add_argument("channel", nargs="?", default=None, help="one channel (default: all)")
    w.add_argument(
        "--every", type=_positive, default=10.0, metavar="S", help="a line every S s too"
    )
    w.add_argument(
        "--count",
        "--lines",
        dest="lines",
        type=_count,
        default=0,
        metavar="N",
        help="stop after N lines (default 0: until Ctrl-C)",
    )
    what.add_parser(
        "cert", help="print this client's certificate file (made if missing), to be trusted"
    )
    p.set_defaults(func=cmd_ctl)


def _add_bench_parsers(what: Any) -> None:
    """The commands about the whole bench: its alarms, its software e-stop."""
    what.add_parser("alarms", help="the alarms that are active or not acknowledged")
    what.add_parser(
        "estop",
        help="press the bench-wide software e-stop (every channel tripped, as by the button);"
        " `estop reset` releases it once its alarm is acknowledged (`ack estop`)",
    ).add_argument("action", nargs="?", choices=("reset",), default=None)


def default_pki() -> Path:
    """Where ctl keeps the client certificate it makes: per user (XDG base directories)."""
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "bench-supervisor" / "ctl-pki"


def default_pki_hint() -> str:
    return "$XDG_CONFIG_HOME/bench-supervisor/ctl-pki (~/.config/… by default)"


def _count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of lines") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: give 0 (no end) or a positive count")
    return value


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
    import asyncio  # here, not at the top: the parser (add_parser) needs no loop (issue 30)

    try:
        _check_security_options(args)
        if args.what == "cert":
            return asyncio.run(_cert(args))
        return asyncio.run(_run(args, _password(args)))
    except CtlError as exc:
        _err(f"supervisor ctl: {exc}")
        return exc.code
    except KeyboardInterrupt:
        return EXIT_OK


# --- security ------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class ClientCertificate:
    """This client's certificate and key, and the application URI it names (OPC UA Part 6
    §6.2.2: the client's ApplicationUri must be the certificate's subjectAltName URI)."""

    cert: Path
    key: Path
    uri: str


def _check_security_options(args: argparse.Namespace) -> None:
    if (args.cert is None) != (args.key is None):
        raise CtlError(
            "--cert and --key go together: give both, or neither for the certificate ctl"
            f" makes in {default_pki()}",
            EXIT_REFUSED,
        )
    if args.cert is not None and args.security == "none" and args.what != "cert":
        raise CtlError(
            "--cert/--key are used with --security sign or sign_and_encrypt", EXIT_REFUSED
        )
    for option, path in (("--cert", args.cert), ("--key", args.key)):
        if path is not None and not path.is_file():
            raise CtlError(f"{option} {path}: no such file", EXIT_REFUSED)


def app_uri() -> str:
    """The application URI of the certificate ctl makes: one per host."""
    return f"urn:{socket.gethostname()}:bench-supervisor:ctl"


async def client_certificate(args: argparse.Namespace) -> ClientCertificate:
    """``--cert/--key`` when given, else the one in ``default_pki()``, made on first use (or
    again when it expired or names another host): then its path is printed, to be copied
    into the server's trust list."""
    if args.cert is not None:
        return ClientCertificate(args.cert, args.key, _uri_of(args.cert))
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    folder = default_pki()
    cert, key = folder / "cert.der", folder / "key.pem"
    uri = app_uri()
    try:
        before = cert.read_bytes() if cert.is_file() else None
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        host = socket.gethostname()
        await setup_self_signed_certificate(
            key,
            cert,
            uri,
            host,
            [ExtendedKeyUsageOID.CLIENT_AUTH],
            {"organizationName": "bench-supervisor", "commonName": f"supervisor ctl {host}"},
        )
        key.chmod(0o600)  # the private key: this user's only
        made = cert.read_bytes() != before
    except OSError as exc:
        raise CtlError(
            f"cannot make the client certificate in {folder}: {exc}", EXIT_FAIL
        ) from None
    if made:
        _err(
            f"supervisor ctl: made this client's certificate {cert}: a server accepts it once"
            f" it is copied into its pki/trusted ({SERVER_TRUSTED})"
        )
    return ClientCertificate(cert, key, uri)


def _uri_of(path: Path) -> str:
    from cryptography import x509

    data = path.read_bytes()
    try:
        if data.lstrip().startswith(b"-----BEGIN"):
            cert = x509.load_pem_x509_certificate(data)
        else:
            cert = x509.load_der_x509_certificate(data)
    except ValueError as exc:
        raise CtlError(f"--cert {path}: not a certificate (DER or PEM): {exc}", 2) from None
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        uris = san.get_values_for_type(x509.UniformResourceIdentifier)
    except x509.ExtensionNotFound:
        uris = []
    if not uris:
        raise CtlError(
            f"--cert {path}: the certificate names no application URI (a subjectAltName URI,"
            " which OPC UA requires)",
            EXIT_REFUSED,
        )
    return str(uris[0])


async def _cert(args: argparse.Namespace) -> int:
    """``ctl cert``: the certificate's path on stdout, to copy into the server's trust list."""
    ident = await client_certificate(args)
    _out(str(ident.cert))
    return EXIT_OK


def _mode_of(security: str) -> Any:
    from asyncua import ua

    return {
        "none": ua.MessageSecurityMode.None_,
        "sign": ua.MessageSecurityMode.Sign,
        "sign_and_encrypt": ua.MessageSecurityMode.SignAndEncrypt,
    }[security]


def _offered(endpoints: Sequence[Any]) -> str:
    names = {"None_": "none", "Sign": "sign", "SignAndEncrypt": "sign_and_encrypt"}
    modes = dict.fromkeys(names.get(e.SecurityMode.name, e.SecurityMode.name) for e in endpoints)
    return ", ".join(modes) or "nothing"


def _endpoint(endpoints: Sequence[Any], security: str, url: str) -> Any:
    """The server's endpoint for ``--security``; a mode it does not offer is the user's to
    change: one line saying what it offers (exit 2)."""
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

    mode = _mode_of(security)
    policy = (
        "http://opcfoundation.org/UA/SecurityPolicy#None"
        if security == "none"
        else SecurityPolicyBasic256Sha256.URI
    )
    for e in endpoints:
        if e.SecurityMode == mode and e.SecurityPolicyUri == policy:
            return e
    if security == "none":
        raise CtlError(
            f"{url}: the server accepts no unsecured connection (its None policy is switched"
            f" off; it offers {_offered(endpoints)}): use --security sign_and_encrypt",
            EXIT_REFUSED,
        )
    raise CtlError(
        f"{url}: the server offers no Basic256Sha256 {security} endpoint (it offers"
        f" {_offered(endpoints)}): change --security",
        EXIT_REFUSED,
    )


def _first_certificate(der: bytes) -> bytes:
    """The server's own certificate (an endpoint may carry its chain, OPC UA Part 6 §6.2.3)."""
    from asyncua.crypto.uacrypto import x509_from_der
    from cryptography.hazmat.primitives.serialization import Encoding

    return bytes(x509_from_der(der).public_bytes(Encoding.DER))


def _password(args: argparse.Namespace) -> str | None:
    """The password from, in turn: standard input's first line, --password, the
    environment, a prompt (only with --user: anonymous needs none)."""
    if args.password_stdin:
        if not args.user:
            raise CtlError("--password-stdin needs --user (anonymous sessions have none)", 2)
        return sys.stdin.readline().rstrip("\r\n")
    password: str | None = args.password
    if password is None:
        password = os.environ.get(PASSWORD_ENV)
    if args.user and password is None:
        password = getpass.getpass(f"OPC UA password for {args.user}: ")
    return password


async def _run(args: argparse.Namespace, password: str | None) -> int:
    from asyncua import Client, ua
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

    ident = await client_certificate(args) if args.security != "none" else None
    c = Client(args.url, timeout=CONNECT_TIMEOUT_S)
    if ident is not None:
        c.application_uri = ident.uri
    if args.user:
        c.set_user(args.user)
        c.set_password(password or "")
    try:
        # The endpoints first: a security mode the server does not offer gets its own
        # message, not asyncua's "No matching endpoints".
        endpoint = _endpoint(await c.connect_and_get_server_endpoints(), args.security, args.url)
        if ident is not None:
            await c.set_security(
                SecurityPolicyBasic256Sha256,
                str(ident.cert),
                str(ident.key),
                server_certificate=_first_certificate(endpoint.ServerCertificate),
                mode=_mode_of(args.security),
            )
        await c.connect()
    except ua.UaStatusCodeError as exc:
        code = _code_name(exc.code)
        if code in CERT_REFUSALS and ident is not None:
            raise CtlError(
                f"{args.url}: the server refused this client's certificate ({code}): copy"
                f" {ident.cert} into the server's pki/trusted ({SERVER_TRUSTED}; it keeps the"
                " refused one in pki/rejected) and run again",
                EXIT_FAIL,
            ) from None
        who = f"user {args.user!r}" if args.user else "an anonymous session"
        raise CtlError(
            f"{args.url}: the server refused the login of {who} ({code}):"
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

    async def alarm_ids(self) -> list[str]:
        folder = self.client.get_node(self.node("/Bench/Alarms"))
        return [str((await n.read_browse_name()).Name) for n in await folder.get_children()]

    async def alive(self) -> None:
        """Read the server's state: raises when the connection is gone."""
        from asyncua import ua

        await self.client.get_node(ua.ObjectIds.Server_ServerStatus_State).read_value()

    async def channel_values(self, channel: str) -> dict[str, Any]:
        values = await self.read([f"{channel}.{f}" for f in FIELDS])
        return dict(zip(FIELDS, values, strict=True))

    async def call(self, channel: str, method: str, *args: Any) -> tuple[bool, str, str]:
        """(accepted, the server's Result text, the status code's name)."""
        return await self.call_on(f"/Bench/Channels/{channel}", method, *args)

    async def call_on(self, obj: str, method: str, *args: Any) -> tuple[bool, str, str]:
        """``method`` of the object ``obj`` (``/Bench``, a channel's), as :meth:`call`."""
        from asyncua import ua

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
    if args.what == "estop":
        return await _estop(bench, args.action)
    if args.what == "ack" and args.channel not in bench.channels:
        if args.channel in await bench.alarm_ids():
            return await _ack_alarm(bench, args.channel)
        raise CtlError(
            f"{args.channel}: no such channel or alarm (channels: {', '.join(bench.channels)};"
            " alarms: `supervisor ctl alarms`)",
            EXIT_REFUSED,
        )
    bench.check_channel(args.channel)
    call_args: list[Any] = []
    if args.what == "start":
        call_args = [
            ua.Variant(args.recipe, ua.VariantType.String),
            ua.Variant(list(args.param), ua.VariantType.String),
        ]
        metadata = (args.cell, args.chemistry, args.capacity, args.comment)
        if any(metadata):  # only then: a server older than the metadata takes two
            call_args += [ua.Variant(m, ua.VariantType.String) for m in metadata]
    ok, text, code = await bench.call(args.channel, COMMANDS[args.what], *call_args)
    if not ok:
        raise CtlError(f"{args.channel}: {args.what} refused ({code}): {text}", EXIT_REFUSED)
    _out(text)
    return EXIT_OK


def _num(value: Any, fmt: str) -> str:
    return "—" if value is None else format(value, fmt)


def _text(value: Any) -> str:
    return "—" if value is None or value == "" else str(value)


def chain_state(v: dict[str, Any]) -> Any:
    """The chain's state by the name the operator knows (``Running``), from its OPC UA
    number (``chain.state_code``); None when unknown."""
    from supervisor.chains.states import OPCUA_CODE

    code = v["chain.state_code"]
    names = {number: state.value for state, number in OPCUA_CODE.items()}
    return names.get(code, code) if code is not None else None


def status_table(channels: Sequence[str], rows: Sequence[dict[str, Any]]) -> list[str]:
    """One line per channel: what the channel does (``charging 20.000 A, manual``:
    supervisor/channels/activity.py), its chain's state, recipe, step (number and id), V, I,
    and the test's charge (``chN.chain.charge_ah``, the figure the display line and the
    screens show; the raw counters are not the test's charge)."""
    from supervisor.channels.activity import activity_label

    head = ("channel", "channel state", "chain", "recipe", "step", "V", "I (A)", "charge (Ah)")
    body = []
    for ch, v in zip(channels, rows, strict=True):
        index = v["chain.step_index"]
        name = v["chain.step"]
        step = "—" if not index or not name else f"{index} {name}"
        body.append(
            (
                ch,
                activity_label(v["state"], v["current_cmd"], v["mode"]),
                _text(chain_state(v)),
                _text(v["chain.recipe"]),
                step,
                _num(v["voltage"], ".3f"),
                _num(v["current"], "+.3f"),
                _num(v["chain.charge_ah"], ".4f"),
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
    what a remote client cannot see (step time left) is left out. ``mAh`` is the test's
    charge (``chN.chain.charge_ah``), the display line's figure."""
    amps = v["current"] or 0.0
    index = v["chain.step_index"]
    step = index or 0  # 1-based, 0 before the first step
    charge_ah = v["chain.charge_ah"]
    mah = "—" if charge_ah is None else f"{charge_ah * 1000:.1f}"
    date = time.strftime("%a %b %d %H:%M:%S %Y", time.localtime(wall))
    return (
        f"{channel} {'C' if amps >= 0 else 'D'}/{v['chain.cycle'] or 0:02d}/{step:02d}"
        f" mA={abs(amps) * 1000:3.0f} SET= {v['chain.step_time'] or 0:.0f}"
        f" TET= {v['chain.test_time'] or 0:.0f} V={_num(v['voltage'], '.3f')} mAh={mah}"
        f" {_text(chain_state(v))} {_text(v['chain.step'])}, {date}"
    )


async def _estop(bench: Bench, action: str | None) -> int:
    """Press (or reset) the software e-stop: the server's answer, or its refusal (exit 2)."""
    ok, text, code = await bench.call_on("/Bench", ESTOP_METHODS[action])
    if not ok:
        what = "estop reset" if action == "reset" else "estop"
        raise CtlError(f"{what} refused ({code}): {text}", EXIT_REFUSED)
    _out(text)
    return EXIT_OK


async def _ack_alarm(bench: Bench, alarm: str) -> int:
    """Acknowledge one alarm through its condition's Acknowledge (OPC UA Part 9 §5.7.3), as
    a SCADA alarm list does: the server acknowledges it in the alarm model, with this
    session's user as the actor."""
    from asyncua import ua

    obj = bench.node(f"/Bench/Alarms/{alarm}")
    # The EventId of the occurrence to acknowledge, as an alarm list has it: from the
    # condition's last event, replayed by a ConditionRefresh (Part 9 §5.5.7); the server
    # acknowledges only an occurrence it sent (issue 31, finding 3).
    event = await _last_event_id(bench, alarm)
    req = ua.CallMethodRequest()
    req.ObjectId = obj
    req.MethodId = ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge)
    req.InputArguments = [
        ua.Variant(event or b"", ua.VariantType.ByteString),
        ua.Variant(ua.LocalizedText("supervisor ctl"), ua.VariantType.LocalizedText),
    ]
    (res,) = await bench.client.uaclient.call([req])
    code = str(res.StatusCode.name)
    if code == "BadConditionBranchAlreadyAcked":
        raise CtlError(f"{alarm}: ack refused ({code}): nothing to acknowledge", EXIT_REFUSED)
    if not res.StatusCode.is_good():
        raise CtlError(f"{alarm}: ack refused ({code})", EXIT_REFUSED)
    (state,) = await bench.read([f"/Bench/Alarms/{alarm}/State"])
    _out(f"{alarm}: acknowledged ({_text(state)})")
    return EXIT_OK


async def _last_event_id(bench: Bench, alarm: str) -> bytes:
    """The EventId of the last event of ``alarm``'s condition (b"" when the server replays
    none: not retained, so nothing to acknowledge)."""
    import asyncio

    from asyncua import ua

    got: dict[str, bytes] = {}
    done = asyncio.Event()

    class Events:
        def event_notification(self, event: Any) -> None:
            fields = event.get_event_props_as_fields_dict()
            kind = fields.get("EventType")
            if kind is not None and kind.Value == ua.NodeId(ua.ObjectIds.RefreshEndEventType):
                done.set()
            name = fields.get("ConditionName")
            if name is not None and name.Value == alarm:
                got["id"] = fields["EventId"].Value

    sub = await bench.client.create_subscription(100, Events())
    try:
        await sub.subscribe_events(
            bench.client.nodes.server,
            [ua.ObjectIds.AlarmConditionType, ua.ObjectIds.RefreshEndEventType],
        )
        req = ua.CallMethodRequest()
        req.ObjectId = ua.NodeId(ua.ObjectIds.ConditionType)
        req.MethodId = ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh)
        req.InputArguments = [ua.Variant(sub.subscription_id, ua.VariantType.UInt32)]
        (res,) = await bench.client.uaclient.call([req])
        if res.StatusCode.is_good():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(done.wait(), CONNECT_TIMEOUT_S)
    finally:
        with contextlib.suppress(Exception):
            await sub.delete()
    return got.get("id", b"")


async def _alarms(bench: Bench) -> int:
    ids = await bench.alarm_ids()
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
    import asyncio

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
        for f in ("chain.state_code", "chain.step_index")
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
                key = (v["chain.state_code"], v["chain.step_index"])
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
