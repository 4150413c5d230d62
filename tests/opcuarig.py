"""An OPC UA server on loopback for the tests: commandrig's bench (four Chadèche channels and
the ADAM, in process, virtual clock) served by ``supervisor.app.opcua.build_opcua`` on a
free port, with three users, and asyncua clients to talk to it.

The bench scans only when a test says so (``rig.scans(n)``); the server runs on its own
thread and serves between scans, as it does on a bench.
"""

from __future__ import annotations

import asyncio
import dataclasses
import threading
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from asyncua.server.address_space import NodeData
from asyncua.server.internal_server import InternalServer
from commandrig import io_map, started_bench
from cryptography.x509.oid import ExtendedKeyUsageOID

from supervisor.app import Bench, build_bench
from supervisor.app.opcua import build_opcua
from supervisor.config.users import hash_password
from supervisor.core.clock import RealClock, VirtualClock
from supervisor.devices.registry import load_bench
from supervisor.publish.opcua import OpcUaServer, OpcUaSettings, namespace_uri
from supervisor.publish.opcua.security import Pki
from supervisor.testing import free_tcp_port, run_scans, wait_until

# --- one standard address space per test session ---------------------------------------------
# asyncua builds OPC UA's standard address space (6174 nodes) for every server: 1 to 4 s on
# these machines, most of a test's set-up. It is built once here and copied for each server
# (0.2 to 0.7 s): fresh nodes and attribute holders, the same immutable values.
_TEMPLATE: dict[ua.NodeId, NodeData] | None = None
_TEMPLATE_LOCK = threading.Lock()
_BUILD = InternalServer.load_standard_address_space


def _copy_nodes(nodes: dict[ua.NodeId, NodeData]) -> dict[ua.NodeId, NodeData]:
    out = {}
    for nid, nd in nodes.items():
        n = NodeData(nid)
        n.attributes = {k: type(v)(v.value) for k, v in nd.attributes.items()}
        n.references = list(nd.references)
        n.call = nd.call
        out[nid] = n
    return out


async def _standard_space_once(self: InternalServer, shelf_file: Path | None = None) -> None:
    global _TEMPLATE
    if shelf_file is not None:
        # The server reads the space from its shelf (ADR 0020): as quick as a copy, and
        # what `supervisor run` does.
        await _BUILD(self, shelf_file)
        return
    if _TEMPLATE is None:
        await _BUILD(self, shelf_file)
        with _TEMPLATE_LOCK:
            _TEMPLATE = _copy_nodes(self.aspace._nodes)
        return
    with _TEMPLATE_LOCK:
        self.aspace._nodes = _copy_nodes(_TEMPLATE)


InternalServer.load_standard_address_space = _standard_space_once  # type: ignore[method-assign]

# The users' hashes (scrypt: tens of ms each) and the server's key pair (RSA 2048), made
# once per session too: every test bench is called "sim", so one certificate fits them all.
_HASHES: dict[str, str] = {}
_OWN: dict[str, bytes] = {}


def _users_file(path: Path) -> None:
    for name in ROLES:
        if name not in _HASHES:
            _HASHES[name] = hash_password(PASSWORDS[name])
    path.parent.mkdir(parents=True, exist_ok=True)
    users = {n: {"role": r, "password": _HASHES[n]} for n, r in ROLES.items()}
    path.write_text(yaml.safe_dump({"users": users}), encoding="utf-8")


async def _own_certificate(settings: OpcUaSettings) -> None:
    pki = Pki(settings.pki_dir)
    if not _OWN:
        await pki.ensure(namespace_uri(settings.bench), settings.bench)
        _OWN.update(cert=pki.cert.read_bytes(), key=pki.key.read_bytes())
        return
    pki.cert.parent.mkdir(parents=True, exist_ok=True)
    pki.cert.write_bytes(_OWN["cert"])
    pki.key.write_bytes(_OWN["key"])


PASSWORDS = {"alice": "alice-pw", "bob": "bob-pw", "carol": "carol-pw"}
ROLES = {"alice": "operator", "bob": "viewer", "carol": "engineer"}
CLIENT_URI = "urn:bench-supervisor:test-client"
VT = ua.VariantType
S = ua.StatusCodes


@dataclass
class Rig:
    bench: Bench
    server: OpcUaServer
    tmp: Path
    clients: list[Client] = field(default_factory=list)

    @property
    def settings(self) -> OpcUaSettings:
        return self.server.settings

    async def scans(self, n: int = 1, settle: bool = True) -> None:
        """``n`` scans, then (``settle``) wait until the server has written what they changed."""
        await run_scans(self.bench.engine, n)
        if settle:
            await self.settled()

    async def settled(self) -> None:
        await wait_until(lambda: self.server.idle, "the server wrote what the scans changed")

    @asynccontextmanager
    async def client(
        self,
        user: str | None = "alice",
        password: str | None = None,
        secure: ua.MessageSecurityMode | None = None,
        cert: tuple[Path, Path] | None = None,
    ) -> AsyncIterator[Client]:
        c = Client(self.server.endpoint, timeout=10)
        c.application_uri = CLIENT_URI
        if user is not None:
            c.set_user(user)
            c.set_password(password if password is not None else PASSWORDS[user])
        if secure is not None:
            cert_file, key_file = cert or await client_certificate(self.tmp)
            await c.set_security(
                SecurityPolicyBasic256Sha256, str(cert_file), str(key_file), mode=secure
            )
        async with c:
            yield c

    async def ns(self, c: Client) -> int:
        return int(await c.get_namespace_index(self.server.namespace))


async def client_certificate(tmp: Path, name: str = "client") -> tuple[Path, Path]:
    """A client certificate for ``CLIENT_URI`` (made once per folder): (cert.der, key.pem)."""
    cert, key = tmp / f"{name}-cert.der", tmp / f"{name}-key.pem"
    if not cert.exists():
        await setup_self_signed_certificate(
            key,
            cert,
            CLIENT_URI,
            "localhost",
            [ExtendedKeyUsageOID.CLIENT_AUTH],
            {"commonName": name},
        )
    return cert, key


def trust(rig: Rig, cert: Path) -> None:
    trusted = rig.settings.pki_dir / "trusted"
    trusted.mkdir(parents=True, exist_ok=True)
    (trusted / cert.name).write_bytes(cert.read_bytes())


@asynccontextmanager
async def opcua_rig(
    tmp: Path,
    change: Callable[[OpcUaSettings], OpcUaSettings] | None = None,
    prepare: Callable[[Bench], None] | None = None,
    real_clock: bool = False,
    history: bool = False,
    unhistorised: tuple[str, ...] = (),
    **kw: Any,
) -> AsyncIterator[Rig]:
    """The started bench and its started OPC UA server; both stopped on exit.

    ``real_clock``: the bench scans on its own at its period (wall time), from before the
    server starts until the end; else it scans only when the test says so. ``history``:
    the bench records its history (the embedded historian) from its start on, except the
    I/O map tags named in ``unhistorised`` (``history: {enabled: false}``)."""
    if history:
        path = io_map(tmp)
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
        for t in data["tags"]:
            if t["name"] in unhistorised:
                t["history"] = {"enabled": False}
        path.write_text(yaml.safe_dump(data), encoding="utf-8")
        bench = build_bench(load_bench(path), VirtualClock(), in_process=True)
        bench.record_history()
        await bench.start()
        await run_scans(bench.engine, 10)
    elif real_clock:
        bench = build_bench(load_bench(io_map(tmp)), RealClock(), in_process=True)
        await bench.start()
    else:
        bench = await started_bench(tmp)
    stop = asyncio.Event()
    running: asyncio.Task[None] | None = None
    if prepare is not None:
        prepare(bench)
    settings = dataclasses.replace(OpcUaSettings.of(bench.cfg), port=free_tcp_port())
    if change is not None:
        settings = change(settings)
    _users_file(settings.users_file)
    await _own_certificate(settings)
    server = build_opcua(bench, settings, **kw)
    try:
        await server.start()
        rig = Rig(bench, server, tmp)
        if real_clock:  # as `supervisor run` does: the server is up before the first scan
            running = asyncio.create_task(bench.run(stop))
            await wait_until(lambda: bench.engine.stats.count > 0, "the first scan")
        else:
            await rig.scans(1)
        yield rig
    finally:
        await server.stop()
        stop.set()
        if running is not None:
            await running
        await bench.shutdown()


async def call(
    c: Client, obj: ua.NodeId, method: ua.NodeId, *args: ua.Variant
) -> ua.CallMethodResult:
    """A method call as a SCADA client makes it: the result whatever its status."""
    req = ua.CallMethodRequest()
    req.ObjectId = obj
    req.MethodId = method
    req.InputArguments = list(args)
    (res,) = await c.uaclient.call([req])
    return res


def text(res: ua.CallMethodResult) -> str:
    return str(res.OutputArguments[0].Value) if res.OutputArguments else ""


class Collector:
    """An asyncua subscription handler that keeps what it gets."""

    def __init__(self) -> None:
        self.changes: list[tuple[str, Any, ua.DataValue]] = []
        self.events: list[Any] = []
        self.status: list[Any] = []

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.changes.append((node.nodeid.Identifier, val, data.monitored_item.Value))

    def event_notification(self, event: Any) -> None:
        self.events.append(event)

    def status_change_notification(self, status: Any) -> None:
        self.status.append(status)

    def values(self, tag: str) -> list[Any]:
        return [v for name, v, _ in self.changes if name == tag]

    def messages(self) -> list[str]:
        return [e.Message.Text for e in self.events if getattr(e, "Message", None) is not None]


async def eventually(cond: Callable[[], bool], what: str) -> None:
    await wait_until(cond, what)
    await asyncio.sleep(0)


# --- node-opcua, the independent client of the interoperability tests -------------------
INTEROP = Path(__file__).resolve().parent / "interop"


def node() -> str:
    """The ``node`` that runs tests/interop's scripts (with node-opcua-client installed)."""
    import shutil

    import pytest

    found = shutil.which("node")
    if found is None or not (INTEROP / "node_modules" / "node-opcua-client").is_dir():
        pytest.fail(
            "no node-opcua-client: run the tests with `make test` (it runs `make node_modules`,"
            " an npm install into tests/interop/node_modules)",
            pytrace=False,
        )
    return found


def pem_of(cert_der: Path, pem: Path) -> Path:
    """A client certificate (DER, as ``client_certificate`` makes it) as PEM, which
    node-opcua reads."""
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding

    pem.write_bytes(
        x509.load_der_x509_certificate(cert_der.read_bytes()).public_bytes(Encoding.PEM)
    )
    return pem
