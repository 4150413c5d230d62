"""The audit trail of a scripted session (issue 34, "Must show": ``audit verify`` OK on a
log after a scripted session; a byte changed in the middle of the file: ``verify`` names
the entry). The supervisor as ``supervisor run`` assembles it (``build_supervisor``: the
command path, the HMI's logins and recipe editor, the audit log in the bench's state
folder), its HTTP API on loopback, the bench on the virtual clock; the checks through
the command line's own ``main``."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import aiohttp
import pytest
import yaml
from commandrig import DISCHARGE
from commandrig import io_map as command_map
from hmirig import USERS, HttpCalls, password

from supervisor.app.service import Supervisor, build_supervisor
from supervisor.audit import AUDIT_NAME, read_entries, sha256_text
from supervisor.cli.main import main
from supervisor.config.users import add_user
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import load_bench
from supervisor.publish.opcua import OpcUaSettings
from supervisor.testing import free_tcp_port, run_scans

pytestmark = pytest.mark.integration

SAVED = "recipe: saved\nsteps:\n  - {id: d, discharge: 100 mA, duration: 10 min}\n"
SAVED_AGAIN = "recipe: saved\nsteps:\n  - {id: d, discharge: 150 mA, duration: 10 min}\n"


def bench_map(tmp: Path) -> Path:
    """commandrig's bench (four Chadèche channels, the ADAM's e-stop and room alarm) with
    logins on, nothing else listening, and the demo users."""
    path = command_map(tmp)
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    data["hmi"]["login"] = True
    data["hmi"]["port"] = 0
    data.pop("opcua", None)
    data.pop("modbus_server", None)
    # The simulated ADAM serves Modbus TCP on the map's port (5020): a free one instead, so
    # that two of these benches (pytest -n 2) never meet on it.
    data["devices"]["adam"]["port"] = free_tcp_port()
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    users = OpcUaSettings.of(load_bench(path)).users_file
    for user, role in USERS.items():
        add_user(users, user, role, password(user))
    return path


@asynccontextmanager
async def supervisor(io_map: Path) -> AsyncIterator[Supervisor]:
    sup = build_supervisor(load_bench(io_map), VirtualClock(), lock=False)
    await sup.start()
    try:
        yield sup
    finally:
        await sup._stop()  # what ``run`` does once stopped: outputs safe, the log closed
        sup.release()


class Client(HttpCalls):
    def __init__(self, sup: Supervisor) -> None:
        self.base = f"http://127.0.0.1:{sup.api.port}"
        self.sessions = []

    async def login(self, user: str, pw: str | None = None) -> tuple[aiohttp.ClientSession, int]:
        s = await self.client()
        status, _ = await self.call(
            s, "POST", "/api/login", {"user": user, "password": pw or password(user)}
        )
        return s, status

    async def close(self) -> None:
        for s in self.sessions:
            await s.close()


async def scripted_session(sup: Supervisor, tmp: Path) -> None:
    """Login, a failed login, start, hold, an acknowledge, two recipe saves, a force (the
    engineer's change of a value the bench runs with; the product has no runtime limit to
    change: limits live in the I/O map, whose load is recorded), a refused command, logout."""
    http = Client(sup)
    engine = sup.bench.engine
    try:
        _, status = await http.login("erin", "not her password")
        assert status == 401
        otto, status = await http.login("otto")
        assert status == 200
        erin, status = await http.login("erin")
        assert status == 200
        vera, status = await http.login("vera")
        assert status == 200
        (tmp / "d.yaml").write_text(DISCHARGE, encoding="utf-8")
        status, body = await http.call(
            otto, "POST", "/api/channels/ch0/commands/start", {"recipe": "d.yaml"}
        )
        assert status == 200, body
        await run_scans(engine, 20)
        status, body = await http.call(otto, "POST", "/api/channels/ch0/commands/hold", {})
        assert status == 200, body
        status, alarms = await http.call(otto, "GET", "/api/alarms")
        room = next(a["id"] for a in alarms["active"] if a["id"].startswith("room.temp"))
        status, body = await http.call(otto, "POST", f"/api/alarms/{room}/acknowledge", {})
        assert status == 200, body
        for text in (SAVED, SAVED_AGAIN):
            status, body = await http.call(
                erin, "PUT", "/api/recipes/saved", {"text": text, "overwrite": True}
            )
            assert status == 200, body
        status, body = await http.call(erin, "PUT", "/api/tags/room.temp/force", {"value": 21.5})
        assert status == 200, body
        status, body = await http.call(vera, "POST", "/api/channels/ch1/commands/start", {})
        assert status == 403
        status, _ = await http.call(otto, "POST", "/api/logout")
        assert status == 200
        await run_scans(engine, 5)
        # Read back over HTTP (written by the log's own thread: waited for here): engineers
        # only, newest first.
        assert sup.bench.audit is not None and sup.bench.audit.flush()
        status, page = await http.call(erin, "GET", "/api/audit?limit=3")
        assert status == 200 and [e["kind"] for e in page["entries"]] == [
            "logout",
            "command.start",
            "command.force",
        ]
        assert page["next_before"] == page["entries"][-1]["seq"]
        status, body = await http.call(vera, "GET", "/api/audit")
        assert (status, body["reason"]) == (
            403,
            "viewer may not read the audit log: log in as an engineer",
        )
        status, body = await http.call(erin, "GET", "/api/audit/verify")
        assert status == 200 and body["ok"] is True and body["first_broken"] is None
    finally:
        await http.close()


async def test_a_scripted_session_verifies_exports_and_a_changed_byte_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    io_map = bench_map(tmp_path)
    async with supervisor(io_map) as sup:
        await run_scans(sup.bench.engine, 10)
        await scripted_session(sup, tmp_path)
    capsys.readouterr()

    assert main(["audit", "verify", "--io-map", str(io_map)]) == 0
    out = capsys.readouterr().out
    path = tmp_path / "state" / AUDIT_NAME
    entries = read_entries(path)
    assert out == f"audit log OK: {len(entries)} entries, head {entries[-1].hash}\n"

    assert (
        main(
            [
                "audit",
                "export",
                "--since",
                "2026-01-01",
                "--format",
                "json",
                "--io-map",
                str(io_map),
            ]
        )
        == 0
    )
    exported = json.loads(capsys.readouterr().out)["entries"]
    assert [(e["actor"], e["kind"], e["target"]) for e in exported] == [
        ("command line", "io_map.load", str(io_map.resolve())),
        ("hmi:erin", "login.failed", "erin"),
        ("hmi:otto", "login", "otto"),
        ("hmi:erin", "login", "erin"),
        ("hmi:vera", "login", "vera"),
        ("hmi:otto", "command.start", "ch0"),
        ("hmi:otto", "command.hold", "ch0"),
        ("hmi:otto", "command.acknowledge", f"alarm {room_alarm(exported)}"),
        ("hmi:erin", "recipe.save", str(tmp_path / "saved.yaml")),
        ("hmi:erin", "recipe.save", str(tmp_path / "saved.yaml")),
        ("hmi:erin", "command.force", "bench"),
        ("hmi:vera", "command.start", "ch1"),
        ("hmi:otto", "logout", "otto"),
    ]
    assert exported[0]["details"]["sha256"] == load_bench(io_map).source_sha256
    check_details([e["details"] for e in exported])

    # One byte changed in the middle of the file: the hold's entry ("hold" -> "hole").
    hold = exported[6]
    change_one_byte(path, b'"command":"hold"', b'"command":"hole"')
    assert main(["audit", "verify", "--io-map", str(io_map)]) == 1
    assert capsys.readouterr().out.splitlines()[0] == (
        f"audit log BROKEN: {path}: entry {hold['seq']} ({hold['time']}): content changed:"
        " its fields do not give its hash"
    )


def check_details(details: list[dict[str, Any]]) -> None:
    """What the session's entries say beyond who, what and on what."""
    start, refused, force = details[5], details[11], details[10]
    assert start["accepted"] is True and start["args"] == {"recipe": "d.yaml"}
    assert refused["accepted"] is False and refused["result"] == "forbidden"
    assert refused["reason"].startswith("viewer may not start ch1")
    first, second = details[8], details[9]
    assert first["created"] is True and first["previous_sha256"] is None
    assert second["previous_sha256"] == first["sha256"] and second["created"] is False
    assert "-  - {id: d, discharge: 100 mA" in second["diff"]
    assert "+  - {id: d, discharge: 150 mA" in second["diff"]
    assert force["args"] == {"tag": "room.temp", "value": 21.5} and force["accepted"] is True


def change_one_byte(path: Path, before: bytes, after: bytes) -> None:
    """``before`` (found once in the file) made ``after``, which differ by one byte."""
    assert sum(a != b for a, b in zip(before, after, strict=True)) == 1
    data = path.read_bytes()
    assert data.count(before) == 1
    path.write_bytes(data.replace(before, after))


def room_alarm(exported: list[dict[str, Any]]) -> str:
    ack = next(e for e in exported if e["kind"] == "command.acknowledge")
    return str(ack["target"]).removeprefix("alarm ")


async def test_verify_and_export_say_what_is_wrong_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    io_map = bench_map(tmp_path)
    assert main(["audit", "verify", "--io-map", str(io_map)]) == 2  # nothing recorded yet
    err = capsys.readouterr().err
    assert err == (
        f"supervisor audit verify: {tmp_path / 'state' / AUDIT_NAME}: no audit log there"
        " (no action recorded yet?)\n"
    )
    assert main(["audit", "verify", "--io-map", str(tmp_path / "none.yaml")]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    assert main(["audit", "export", "--io-map", str(io_map)]) == 2  # --since is needed
    assert "--since" in capsys.readouterr().err
    assert main(["audit", "export", "--since", "monday", "--io-map", str(io_map)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'monday' is not an ISO 8601 time" in err
    (tmp_path / "state").mkdir(exist_ok=True)
    (tmp_path / "state" / AUDIT_NAME).write_bytes(b"garbage" * 1000)
    assert main(["audit", "verify", "--io-map", str(io_map)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not an audit log" in err


PROFILE = "Time,Current\n0,0.1\n1,0.2\n2,0.3\n"


async def test_a_profile_loaded_from_the_screens_records_the_recipe_it_wrote(
    tmp_path: Path,
) -> None:
    """The Recipes screen's "Load profile" writes a recipe (``profiles/NAME.yaml``) and
    loads it: the write is a ``recipe.save`` with both hashes, the load a command."""
    io_map = bench_map(tmp_path)
    async with supervisor(io_map) as sup:
        await run_scans(sup.bench.engine, 10)
        http = Client(sup)
        try:
            otto, _ = await http.login("otto")
            status, body = await http.call(
                otto,
                "POST",
                "/api/profiles/load",
                {"csv": PROFILE, "name": "p.csv", "channel": "ch1"},
            )
            assert status == 200, body
        finally:
            await http.close()
        audit = sup.bench.audit
        assert audit is not None and audit.flush()
        entries = read_entries(audit.path)
    save, load = entries[-2:]
    assert (save.actor, save.kind, save.target) == ("hmi:otto", "recipe.save", "profiles/p.yaml")
    written = (tmp_path / "profiles" / "p.yaml").read_text(encoding="utf-8")
    assert save.details_json == {
        "sha256": sha256_text(written),
        "csv_sha256": sha256_text(PROFILE),
        "from_profile": True,
    }
    assert (load.kind, load.target, load.details_json["accepted"]) == ("command.load", "ch1", True)
