"""``supervisor ctl`` against a real OPC UA server on loopback (opcuarig: the bench in
process on the virtual clock, scanning when the test says so). The command line runs on
its own thread, as a separate process would, so the server and the bench keep serving.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from commandrig import recipe
from opcuarig import PASSWORDS, Rig, opcua_rig

from supervisor.cli.main import main
from supervisor.testing import free_tcp_port, wait_until

pytestmark = pytest.mark.integration


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    async with opcua_rig(tmp_path) as r:
        yield r


async def ctl(
    rig: Rig | None, capsys: pytest.CaptureFixture[str], *argv: str, user: str | None = None
) -> tuple[int, list[str], list[str]]:
    """``supervisor ctl --url <the rig's server> [--user …] argv``: (exit code, out, err)."""
    url = rig.server.endpoint if rig is not None else "opc.tcp://127.0.0.1:1/supervisor"
    login = ["--user", user, "--password", PASSWORDS[user]] if user else []
    code = await asyncio.to_thread(main, ["ctl", "--url", url, *login, *argv])
    out, err = capsys.readouterr()
    return code, out.splitlines(), err.splitlines()


async def test_status_shows_every_channel(rig: Rig, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = await ctl(rig, capsys, "status")
    assert (code, err) == (0, [])
    assert out[0].split() == ["channel", "state", "mode", "recipe", "step", "V", "I", "(A)", "Ah"]
    channels = [c.name for c in rig.bench.cfg.channels]
    assert [line.split()[0] for line in out[1:]] == channels
    ch0 = out[1].split()
    assert ch0[1:3] == ["Idle", "manual"]
    assert ch0[-3] == f"{rig.bench.db['ch0.voltage'].value:.3f}"


async def test_start_runs_the_recipe_and_status_shows_its_step(
    rig: Rig, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    code, out, err = await ctl(rig, capsys, "start", "ch0", recipe(tmp_path), user="alice")
    assert (code, err) == (0, [])
    assert "recipe d loaded" in out[0] and "started" in out[0]
    await rig.scans(3)
    code, out, _ = await ctl(rig, capsys, "status")
    assert code == 0
    ch0 = out[1].split()
    assert ch0[:5] == ["ch0", "Running", "auto", "d", "1"] and ch0[5] == "d"
    assert float(ch0[-2]) == pytest.approx(-0.2, abs=0.01)  # discharging 200 mA
    command = rig.bench.commands.log[-1]
    assert (command.actor, command.accepted) == ("opcua:alice", True)


async def test_start_passes_its_parameters(
    rig: Rig, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    text = (
        "recipe: p\nparameters: {v_min: 1.0 V}\nsteps:\n  - id: d\n    discharge: 200 mA\n"
        "    duration: 1 h\n    until: [{voltage <= v_min: next}]\n  - {id: r, rest: 1 h}\n"
    )
    code, _, err = await ctl(
        rig, capsys, "start", "ch0", recipe(tmp_path, text), "-p", "v_min=5 V", user="alice"
    )
    assert (code, err) == (0, [])
    await rig.scans(3)
    assert rig.bench.db["ch0.chain.step"].value == "r"  # above the cell: the step ended at once


async def test_a_refused_command_exits_2_with_the_server_s_reason(
    rig: Rig, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = await ctl(rig, capsys, "start", "ch0", "no-such-recipe", user="alice")
    assert (code, out) == (2, [])
    assert err == [
        "supervisor ctl: ch0: start refused (BadNotFound): no-such-recipe: no such recipe"
    ]
    code, _, err = await ctl(rig, capsys, "hold", "ch0")  # anonymous: read only
    assert code == 2
    assert err == [
        "supervisor ctl: ch0: hold refused (BadUserAccessDenied): an anonymous session may"
        " only read (role viewer): log in as an operator"
    ]
    code, _, err = await ctl(rig, capsys, "abort", "ch9", user="alice")
    assert code == 2
    assert err[0].startswith("supervisor ctl: ch9: no such channel (channels: ch0, ")


async def test_the_isa88_commands_and_ack_reach_the_command_path(
    rig: Rig, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    assert (await ctl(rig, capsys, "start", "ch1", recipe(tmp_path), user="alice"))[0] == 0
    await rig.scans(2)
    for verb in ("hold", "resume", "advance", "stop"):
        code, _, err = await ctl(rig, capsys, verb, "ch1", user="alice")
        assert (code, err) == (0, []), verb
        await rig.scans(3)
    assert (await ctl(rig, capsys, "reset", "ch1", user="alice"))[0] == 0
    code, _, err = await ctl(rig, capsys, "ack", "ch1", user="alice")
    assert code in (0, 2) and all("Traceback" not in e for e in err)
    kinds = [e.command.split()[0] for e in rig.bench.commands.log if e.actor == "opcua:alice"]
    assert kinds[:6] == ["start", "hold", "resume", "advance", "stop", "reset"]


async def test_alarms_lists_the_active_ones(rig: Rig, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = await ctl(rig, capsys, "alarms")
    assert (code, err) == (0, [])
    assert rig.bench.alarms is not None
    active = [a for a in rig.bench.alarms if a.active or not a.acked]
    assert active, "the rig's room is above its H limit"
    assert sorted(line.split()[0] for line in out) == sorted(a.id for a in active)


async def test_watch_prints_a_line_at_each_state_or_step_change(
    rig: Rig, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    url = rig.server.endpoint
    watching = asyncio.create_task(
        asyncio.to_thread(
            main, ["ctl", "--url", url, "watch", "ch0", "--every", "600", "--lines", "2"]
        )
    )
    seen: list[str] = []

    def lines() -> int:
        seen.extend(capsys.readouterr().out.splitlines())
        return len(seen)

    await wait_until(lambda: lines() >= 1, "the first line (the subscription's initial values)")
    assert seen[0].startswith("ch0 C/00/00 mA=  0 ") and " Idle " in seen[0]
    assert (await ctl(rig, capsys, "start", "ch0", recipe(tmp_path), user="alice"))[0] == 0
    await rig.scans(3)
    assert await watching == 0
    lines()
    assert seen[1].startswith("ch0 D/") and " Running d, " in seen[1]


async def test_an_unreachable_server_exits_1_with_one_line(
    capsys: pytest.CaptureFixture[str],
) -> None:
    url = f"opc.tcp://127.0.0.1:{free_tcp_port()}/supervisor"
    code = await asyncio.to_thread(main, ["ctl", "--url", url, "status"])
    out, err = capsys.readouterr()
    assert (code, out) == (1, "")
    assert err.splitlines() == [err.strip()] and err.startswith(
        f"supervisor ctl: cannot reach {url}: "
    )


async def test_a_wrong_password_exits_2_with_one_line(
    rig: Rig, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["ctl", "--url", rig.server.endpoint, "--user", "alice", "--password", "nope", "status"]
    code = await asyncio.to_thread(main, argv)
    out, err = capsys.readouterr()
    assert (code, out) == (2, "")
    assert err.splitlines() == [
        f"supervisor ctl: {rig.server.endpoint}: the server refused the login of user 'alice'"
        " (BadUserAccessDenied): check --user and the password"
    ]


async def test_the_password_may_come_from_the_environment(
    rig: Rig, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("SUPERVISOR_OPCUA_PASSWORD", PASSWORDS["alice"])
    argv = [
        "ctl",
        "--url",
        rig.server.endpoint,
        "--user",
        "alice",
        "start",
        "ch0",
        recipe(tmp_path),
    ]
    assert await asyncio.to_thread(main, argv) == 0
    assert rig.bench.commands.log[-1].actor == "opcua:alice"


def test_usage_errors_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ctl", "bogus"]) == 2
    assert main(["ctl", "start", "ch0"]) == 2  # no recipe
    assert main(["ctl", "watch", "--every", "0"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 3 and all(e.startswith("supervisor ctl") for e in err)
