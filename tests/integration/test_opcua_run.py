"""``supervisor run`` serves OPC UA when the I/O map says so (``make run``: sim.yaml on
127.0.0.1:4840), and ``supervisor opcua add-user`` manages its users: here on a free port,
from another process, stopped by its pid.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from asyncua import Client, ua
from asyncua.common.node import Node
from commandrig import chadeche_map

from supervisor.testing import free_tcp_port

pytestmark = pytest.mark.integration


def opcua_map(tmp_path: Path) -> tuple[Path, int]:
    path = Path(chadeche_map(tmp_path))
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    port = free_tcp_port()
    data["opcua"] = {"enabled": True, "port": port, "security": ["none", "sign_and_encrypt"]}
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path, port


def supervisor(*args: str, cwd: Path, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "supervisor.cli.main", *args],
        cwd=cwd,
        input=stdin,
        capture_output=True,
        text=True,
        timeout=60,
    )


async def first_value(node: Node) -> ua.DataValue:
    """The banner is printed once the server listens, before the first scan: its first
    values are BadWaitingForInitialData until the scan's first hand-over reaches the
    server's process (ADR 0029)."""
    for _ in range(200):
        value = await node.read_data_value(raise_on_bad_status=False)
        if value.StatusCode.value != ua.StatusCodes.BadWaitingForInitialData:
            break
        await asyncio.sleep(0.05)
    return value


async def test_supervisor_run_serves_opc_ua_and_stops_safe_on_sigterm(tmp_path: Path) -> None:
    io_map, port = opcua_map(tmp_path)
    added = supervisor(
        "opcua", "add-user", "alice", "--role", "operator", "--io-map", str(io_map),
        "--password-stdin", cwd=tmp_path, stdin="s3cret\n",
    )  # fmt: skip
    assert added.returncode == 0, added.stderr
    assert added.stdout.endswith("user alice (operator) added\n")
    listed = supervisor("opcua", "list-users", "--io-map", str(io_map), cwd=tmp_path)
    assert listed.stdout == "alice\toperator\n"
    proc = subprocess.Popen(  # noqa: ASYNC220 - Popen only starts it; reads go to threads
        [sys.executable, "-m", "supervisor.cli.main", "run", str(io_map), "--http-port", "0"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )
    try:
        assert proc.stdout is not None
        banner = []
        while not banner or not banner[-1].startswith("Ctrl-C"):
            line = await asyncio.to_thread(proc.stdout.readline)
            assert line, f"supervisor exited: {banner}"
            banner.append(line)
        endpoint = f"opc.tcp://127.0.0.1:{port}/supervisor"
        assert (
            f"OPC UA server listening on {endpoint} (namespace urn:bench-supervisor:bench:sim)\n"
            in banner
        )
        client = Client(endpoint, timeout=10)
        client.set_user("alice")
        client.set_password("s3cret")
        async with client:
            ns = await client.get_namespace_index("urn:bench-supervisor:bench:sim")
            voltage = await first_value(client.get_node(ua.NodeId("ch0.voltage", ns)))
            assert voltage.StatusCode.is_good() and 0.5 < voltage.Value.Value < 2.0
            req = ua.CallMethodRequest()
            req.ObjectId = ua.NodeId("/Bench/Channels/ch0", ns)
            req.MethodId = ua.NodeId("/Bench/Channels/ch0/SetMode", ns)
            req.InputArguments = [ua.Variant("Auto", ua.VariantType.String)]
            (res,) = await client.uaclient.call([req])
            assert res.StatusCode.is_good(), res.OutputArguments
        proc.send_signal(signal.SIGTERM)
        rest = await asyncio.to_thread(proc.stdout.read)
        assert await asyncio.to_thread(proc.wait, 30) == 0
        assert "stopped: all outputs safe" in rest
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()


def test_a_password_in_clear_in_the_users_file_is_refused_with_its_line(tmp_path: Path) -> None:
    io_map, _ = opcua_map(tmp_path)
    users = tmp_path / "state" / "opcua" / "users.yaml"
    users.parent.mkdir(parents=True)
    users.write_text("users:\n  alice:\n    role: operator\n    password: hunter2\n", "utf-8")
    done = supervisor("run", str(io_map), "--http-port", "0", cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.splitlines()[-1] == (
        f"{users}:4:15: users.alice.password: must be a password hash written by"
        " `supervisor opcua add-user`, never the password itself"
    )
    assert "hunter2" not in done.stderr
    bad_role = supervisor(
        "opcua", "add-user", "bob", "--role", "admin", "--io-map", str(io_map), cwd=tmp_path
    )
    assert bad_role.returncode == 2 and "invalid choice: 'admin'" in bad_role.stderr


def test_an_opc_ua_port_already_taken_is_exit_2_with_the_reason(tmp_path: Path) -> None:
    import socket

    io_map, port = opcua_map(tmp_path)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", port))
        taken.listen()
        done = supervisor("run", str(io_map), "--http-port", "0", cwd=tmp_path)
    assert done.returncode == 2
    said = [line for line in done.stderr.splitlines() if line.startswith("supervisor:")]
    assert len(said) == 1 and said[0].startswith("supervisor: cannot listen:"), done.stderr
    assert str(port) in said[0] and "address already in use" in said[0]
    assert "Traceback" not in done.stderr
