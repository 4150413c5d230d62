"""The HTTP API against the real aiohttp server on loopback: every write and command goes
through the command path and is answered ``{"accepted", "reason", ...}`` with its status
(200, 400, 403, 404, 409, 422). The bench runs on the virtual clock; requests are made
between scans, as a screen makes them between two scans of a real bench.

The findings users reported each have a test here (``test_finding_…``).
"""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import pytest
import yaml
from commandrig import CV_ON_CHADECHE, DISCHARGE, recipe, started_bench

from supervisor.app import Bench, build_bench
from supervisor.chains.states import State
from supervisor.core.clock import VirtualClock
from supervisor.core.quality import Quality, Reason
from supervisor.devices.registry import load_bench
from supervisor.hmi import HttpApi
from supervisor.tags import Access, TagSpec
from supervisor.testing import run_scans

JSON = {"Content-Type": "application/json"}
"""What every command declares, a body or not (supervisor.hmi.csrf)."""

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[2]


@dataclass
class Client:
    bench: Bench
    api: HttpApi
    session: aiohttp.ClientSession

    async def call(self, method: str, path: str, body: Any = None) -> tuple[int, Any]:
        kw: dict[str, Any] = {"headers": JSON} if body is None else {"json": body}
        async with self.session.request(method, self.api.url + path, **kw) as resp:
            return resp.status, await resp.json()

    async def put_tag(self, name: str, value: Any) -> tuple[int, Any]:
        return await self.call("PUT", f"/tags/{name}", {"value": value})

    async def command(self, channel: str, verb: str, **args: Any) -> tuple[int, Any]:
        return await self.call("POST", f"/channels/{channel}/commands/{verb}", args)

    async def scans(self, n: int) -> None:
        await run_scans(self.bench.engine, n)

    def value(self, tag: str) -> Any:
        return self.bench.db[tag].value


@pytest.fixture
async def client(tmp_path: Path) -> AsyncIterator[Client]:
    bench = await started_bench(tmp_path)
    api = HttpApi(bench.db, bench.clock, "127.0.0.1", 0, commands=bench.commands)
    await api.start()
    try:
        async with aiohttp.ClientSession() as session:
            yield Client(bench, api, session)
    finally:
        await api.stop()
        await bench.shutdown()


async def press_estop(c: Client, pressed: bool = True) -> None:
    assert c.bench.sim is not None
    c.bench.sim.press_estop(pressed)
    await c.scans(10)


async def start_discharge(c: Client, tmp_path: Path) -> None:
    status, body = await c.command("ch0", "start", recipe=recipe(tmp_path, DISCHARGE))
    assert status == 200 and body["accepted"] is True, body
    await c.scans(20)
    assert c.value("ch0.current_cmd") == pytest.approx(-0.2)


# --- the findings ----------------------------------------------------------------------------
async def test_finding_7_a_refused_command_tag_write_answers_409_with_the_reason(
    client: Client,
) -> None:
    status, body = await client.put_tag("ch0.command", "resume")
    assert status == 409
    assert body == {
        "accepted": False,
        "reason": "ch0: resume is not allowed while Idle (allowed: start)",
        "kind": "refused",
        "tag": body["tag"],
    }
    assert body["tag"]["name"] == "ch0.command" and body["tag"]["value"] == ""


async def test_finding_7_loading_leaves_manual_alone_and_is_refused_while_enabled(
    client: Client, tmp_path: Path
) -> None:
    assert (await client.put_tag("ch0.manual_current", 0.1))[0] == 200
    assert (await client.put_tag("ch0.enable", True))[0] == 200
    status, body = await client.call("PUT", "/channels/ch0/recipe", {"file": recipe(tmp_path)})
    assert status == 409
    assert body["reason"] == (
        "ch0: cannot load a recipe while the channel is driven in manual (enable on):"
        " turn enable off first"
    )
    await client.scans(3)
    assert (client.value("ch0.mode"), client.value("ch0.enable")) == ("manual", True)
    assert client.value("ch0.current_cmd") == pytest.approx(0.1)
    assert (await client.put_tag("ch0.enable", False))[0] == 200
    status, body = await client.call("PUT", "/channels/ch0/recipe", {"file": recipe(tmp_path)})
    assert status == 200 and body["channel"] == "ch0" and body["test_id"]
    assert (client.value("ch0.mode"), client.value("ch0.enable")) == ("manual", False)


async def test_finding_7_after_abort_and_reset_the_channel_is_manual_disabled_at_0_a(
    client: Client, tmp_path: Path
) -> None:
    await start_discharge(client, tmp_path)
    assert client.value("ch0.mode") == "auto"
    assert (await client.put_tag("ch0.command", "abort"))[0] == 200
    await client.scans(2)
    status, body = await client.put_tag("ch0.command", "reset")
    assert status == 200 and body["accepted"] is True
    assert "the channel is in manual, enable off, 0 A" in body["reason"]
    await client.scans(2)
    assert client.value("ch0.mode") == "manual"
    assert client.value("ch0.enable") is False
    assert client.value("ch0.manual_current") == 0.0
    assert client.value("ch0.current_cmd") == 0.0


async def test_finding_9_switching_to_manual_mid_recipe_is_bumpless(
    client: Client, tmp_path: Path
) -> None:
    assert (await client.put_tag("ch0.manual_current", 0.3))[0] == 200  # staged in Manual
    await start_discharge(client, tmp_path)
    for tag, value in (("ch0.manual_current", 0.3), ("ch0.enable", True)):
        status, body = await client.put_tag(tag, value)
        assert status == 409
        assert body["reason"] == "channel ch0 is in auto (step chain): switch to manual first"
    status, body = await client.put_tag("ch0.mode", "manual")
    assert status == 200
    assert body["reason"] == (
        "ch0: mode manual: chain held (was Running), manual setpoint 0 A, enable off"
    )
    seen = []
    for _ in range(5):
        await client.scans(1)
        seen.append(client.value("ch0.current_cmd"))
    assert seen == [0.0] * 5  # from −0.2 A to 0 A, never to the staged +0.3 A
    assert client.bench.runners["ch0"].state is State.HELD


async def test_finding_9_manual_from_the_present_setpoint_when_asked(
    client: Client, tmp_path: Path
) -> None:
    await start_discharge(client, tmp_path)
    status, body = await client.command("ch0", "mode", value="manual", keep_setpoint=True)
    assert status == 200 and "manual setpoint -0.2 A (kept), enable on" in body["reason"]
    await client.scans(5)
    assert client.value("ch0.current_cmd") == pytest.approx(-0.2)


async def test_finding_4_ack_while_the_estop_is_pressed_answers_409_with_the_reason(
    client: Client,
) -> None:
    await press_estop(client)
    status, body = await client.put_tag("ch0.ack", True)
    assert status == 409
    assert body["accepted"] is False
    assert body["reason"].startswith(
        "ch0: cannot reset estop: the cause is still present (Emergency stop pressed (e-stop"
    )
    await press_estop(client, False)
    status, body = await client.put_tag("ch0.ack", True)
    assert (status, body["reason"]) == (200, "ch0: reset: estop")


# --- status codes --------------------------------------------------------------------------------
async def test_an_accepted_write_answers_200_with_the_tag(client: Client) -> None:
    status, body = await client.put_tag("ch0.manual_current", 0.25)
    assert status == 200
    assert body["accepted"] is True and body["kind"] == "accepted"
    assert body["reason"] == "ch0: manual setpoint 0.25 A (enable is off: nothing flows yet)"
    assert body["tag"]["value"] == 0.25 and body["tag"]["unit"] == "A"


@pytest.mark.parametrize(
    ("method", "path", "body", "status", "reason"),
    [
        ("PUT", "/tags/ch0.manual_current", {"value": "abc"}, 400, "must be a number (A)"),
        ("PUT", "/tags/ch0.mode", {"value": "semi"}, 400, "mode is auto or manual"),
        ("PUT", "/tags/ch0.enable", {"value": 7}, 400, "must be true or false"),
        # Issue 28: an unknown member is refused by name (it was "body must be JSON ...").
        ("PUT", "/tags/ch0.manual_current", {"val": 1}, 400, "unknown member 'val'"),
        ("POST", "/channels/ch0/commands/hold", {"now": 1}, 400, "unknown argument now"),
        ("PUT", "/channels/ch0/recipe", {"recipe": "x"}, 400, 'body must be JSON {"file"'),
        ("PUT", "/tags/ch0.voltage", {"value": 3}, 403, "ch0.voltage is read-only"),
        ("PUT", "/tags/nope.tag", {"value": 3}, 404, "unknown tag 'nope.tag'"),
        ("POST", "/channels/ch9/commands/hold", None, 404, "unknown channel 'ch9'"),
        ("POST", "/channels/ch0/commands/jump", None, 404, "unknown command 'jump'"),
        ("POST", "/alarms/nope/acknowledge", None, 404, "unknown alarm 'nope'"),
        ("POST", "/alarms/estop/explode", None, 404, "unknown alarm command 'explode'"),
        ("PUT", "/channels/ch0/recipe", {"file": "nope.yaml"}, 404, "nope.yaml: no such recipe"),
        ("POST", "/channels/ch0/commands/start", None, 409, "ch0: no recipe loaded"),
        ("POST", "/alarms/estop/reset", None, 409, "estop is not a trip waiting for a reset"),
    ],
)
async def test_a_refusal_answers_its_status_and_the_reason(
    client: Client, method: str, path: str, body: Any, status: int, reason: str
) -> None:
    got, answer = await client.call(method, path, body)
    assert got == status, answer
    assert answer["accepted"] is False
    assert reason in answer["reason"]


async def test_a_body_that_is_not_json_is_a_bad_argument(client: Client) -> None:
    url = client.api.url + "/tags/ch0.enable"
    async with client.session.put(url, data=b"true please", headers=JSON) as resp:
        assert resp.status == 400
        assert (await resp.json())["accepted"] is False


async def test_a_refused_recipe_answers_422_with_every_error_located(
    client: Client, tmp_path: Path
) -> None:
    bad = recipe(tmp_path, CV_ON_CHADECHE, "cv.yaml")
    status, body = await client.call("PUT", "/channels/ch0/recipe", {"file": bad})
    assert status == 422 and body["accepted"] is False
    assert body["details"] and body["details"][0].startswith(f"{bad}:")


# --- channel commands, alarms ------------------------------------------------------------------
async def test_channel_commands_start_hold_resume_stop_reset_over_http(
    client: Client, tmp_path: Path
) -> None:
    status, body = await client.command(
        "ch0", "start", recipe=recipe(tmp_path), parameters={"unused": "1 V"}
    )
    assert status == 422 and "unused" in body["reason"]  # an unknown parameter is refused
    status, body = await client.command("ch0", "start", recipe=recipe(tmp_path))
    assert (status, body["state"]) == (200, "Running")
    assert body["test_id"] == client.bench.runners["ch0"].test_id
    assert (await client.command("ch0", "hold"))[0] == 200
    await client.scans(2)
    status, body = await client.command("ch0", "resume")
    assert (status, body["state"]) == (200, "Resuming")
    status, body = await client.command("ch0", "reset")
    assert status == 409 and "reset is not allowed while Resuming" in body["reason"]
    assert (await client.command("ch0", "stop"))[0] == 200
    await client.scans(2)
    status, body = await client.command("ch0", "reset")
    assert (status, body["state"]) == (200, "Idle")


async def test_alarms_are_listed_with_their_history_and_commanded_by_id(
    client: Client,
) -> None:
    await press_estop(client)
    status, body = await client.call("GET", "/alarms")
    assert status == 200 and body["accepted"] is True
    active = {a["id"]: a for a in body["active"]}
    estop = active["estop"]
    assert estop["state"] == "active, unacknowledged" and estop["tripped"] is True
    assert estop["severity_name"] == "critical" and estop["first_out"] is True
    assert "room.temp.H" in active  # a plain alarm: above its H limit
    assert ("estop", "activated") in [(e["alarm"], e["transition"]) for e in body["history"]]

    status, body = await client.call("POST", "/alarms/estop/acknowledge")
    assert (status, body["reason"]) == (200, "alarm estop acknowledge: now active, acknowledged")
    status, body = await client.call("POST", "/alarms/room.temp.H/shelve", {"duration_s": 600})
    assert status == 200 and body["alarm"] == "room.temp.H"
    status, body = await client.call("POST", "/alarms/estop/shelve", {"duration_s": 600})
    assert status == 409 and "cannot be shelved" in body["reason"]
    await press_estop(client, False)
    assert (await client.call("POST", "/alarms/estop/reset"))[0] == 200
    status, body = await client.call("GET", "/alarms?limit=2")
    assert [a["id"] for a in body["active"]] == ["room.temp.H"]
    assert body["active"][0]["shelved"] is True
    assert [(e["transition"], e["actor"]) for e in body["history"]] == [
        ("cleared", ""),
        ("reset", "operator"),
    ]


async def test_every_http_command_is_recorded_with_its_actor(client: Client) -> None:
    await client.put_tag("ch0.command", "hold")
    await client.put_tag("ch0.manual_current", 0.1)
    events = list(client.bench.commands.log)[-2:]
    assert [(e.actor, e.command, e.accepted) for e in events] == [
        ("operator", "hold", False),
        ("operator", "manual_current 0.1 A", True),
    ]


# --- strict values (issue 9) -----------------------------------------------------------------
def strict_json(text: str) -> Any:
    """Parse as a browser's JSON.parse does: NaN and Infinity are not JSON."""

    def refuse(name: str) -> Any:
        raise ValueError(f"{name} is not JSON")

    return json.loads(text, parse_constant=refuse)


async def put_raw(c: Client, name: str, body: str) -> tuple[int, Any]:
    url = f"{c.api.url}/tags/{name}"
    async with c.session.put(url, data=body.encode(), headers=JSON) as resp:
        return resp.status, strict_json(await resp.text())


@pytest.fixture
def lab_tags(client: Client) -> Client:
    """Operator tags that are no channel command: a write takes the tag's own coercion."""
    client.bench.db.add(TagSpec("lab.setpoint", access=Access.OPERATOR, initial=20.0))
    client.bench.db.add(TagSpec("lab.heater", dtype="bool", access=Access.OPERATOR, initial=False))
    return client


@pytest.mark.parametrize(
    ("tag", "body", "reason"),
    [
        ("lab.setpoint", '{"value": true}', "lab.setpoint: expected a number, got true"),
        ("lab.setpoint", '{"value": null}', "lab.setpoint: expected a number, got null"),
        ("lab.setpoint", '{"value": 1e999}', "expected a finite number, got Infinity"),
        (
            "lab.setpoint",
            '{"value": 1' + "0" * 400 + "}",
            "expected a finite number, got an integer of about 401 digits",
        ),
        ("lab.setpoint", '{"value": NaN}', 'body must be JSON {"value": ...}'),
        ("lab.heater", '{"value": 2}', "lab.heater: expected a boolean, got 2"),
        ("lab.heater", '{"value": [0]}', "lab.heater: expected a boolean, got a list of 1"),
        ("ch0.manual_current", '{"value": 1' + "0" * 400 + "}", "value must be a number (A)"),
        ("ch0.manual_current", '{"value": null}', "value must be a number (A), not None"),
        ("ch0.enable", '{"value": [0]}', "value must be true or false, not [0]"),
    ],
    ids=[
        "true-to-float",
        "null-to-float",
        "1e999",
        "1-and-400-zeros",
        "NaN",
        "2-to-bool",
        "list-to-bool",
        "manual-400-zeros",
        "manual-null",
        "enable-list",
    ],
)
async def test_a_value_of_the_wrong_kind_answers_400_with_a_clear_reason(
    lab_tags: Client, tag: str, body: str, reason: str
) -> None:
    before = lab_tags.value(tag)
    status, answer = await put_raw(lab_tags, tag, body)
    assert status == 400, answer
    assert answer["accepted"] is False
    assert reason in answer["reason"]
    assert "NoneType" not in answer["reason"] and "float()" not in answer["reason"]
    assert lab_tags.value(tag) == before


async def test_a_right_value_of_a_plain_operator_tag_is_written(lab_tags: Client) -> None:
    assert (await put_raw(lab_tags, "lab.setpoint", '{"value": 21}'))[0] == 200
    assert (await put_raw(lab_tags, "lab.heater", '{"value": true}'))[0] == 200
    assert (lab_tags.value("lab.setpoint"), lab_tags.value("lab.heater")) == (21.0, True)


async def test_a_non_finite_value_from_a_device_is_sent_as_null_with_quality_bad(
    lab_tags: Client,
) -> None:
    # A device can still produce one (a broken sensor, a bad scaling): the snapshot stays
    # JSON that a browser parses, and the value is not shown as if it were good.
    db = lab_tags.bench.db
    db.update(db["lab.setpoint"], float("nan"), Quality.GOOD, Reason.NONE)
    db.update(db["ch0.voltage"], float("inf"), Quality.GOOD, Reason.NONE)
    async with lab_tags.session.get(lab_tags.api.url + "/tags") as resp:
        assert resp.status == 200
        tags = {t["name"]: t for t in strict_json(await resp.text())}
    assert (tags["lab.setpoint"]["value"], tags["lab.setpoint"]["quality"]) == (None, "BAD")
    assert tags["lab.setpoint"]["reason"] == "not a finite number (nan)"
    assert (tags["ch0.voltage"]["value"], tags["ch0.voltage"]["quality"]) == (None, "BAD")
    async with lab_tags.session.get(lab_tags.api.url + "/tags/lab.setpoint") as resp:
        assert strict_json(await resp.text())["value"] is None


# --- issue 26, finding 4: a setpoint is answered with what will flow -------------------------
def seed002_in_process(tmp: Path) -> Path:
    """io_maps/sim.yaml whole (ch4: the seed 002 bench, ±20 A), its HTTP clients not logging
    in, its state in ``tmp``, no OPC UA server (its port is not this test's)."""
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["hmi"]["login"] = False
    data.pop("opcua", None)
    data.pop("modbus_server", None)  # nor Modbus (1502 may be taken)
    data["state_dir"] = str(tmp / "state")
    path = tmp / "sim.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


@pytest.fixture
async def sim_client(tmp_path: Path) -> AsyncIterator[Client]:
    bench = build_bench(load_bench(seed002_in_process(tmp_path)), VirtualClock(), in_process=True)
    await bench.start()
    await run_scans(bench.engine, 20)  # every device connected, first images in
    api = HttpApi(bench.db, bench.clock, "127.0.0.1", 0, commands=bench.commands)
    await api.start()
    try:
        async with aiohttp.ClientSession() as session:
            yield Client(bench, api, session)
    finally:
        await api.stop()
        await bench.shutdown()


async def test_issue26_finding_4_500_a_on_ch4_is_refused_409_naming_its_20_a_hard_limit(
    sim_client: Client,
) -> None:
    c = sim_client
    assert (await c.put_tag("ch4.enable", True))[0] == 200
    status, body = await c.put_tag("ch4.manual_current", 500)
    assert status == 409, body
    assert body["accepted"] is False and body["kind"] == "out of range"
    assert body["reason"] == (
        "ch4: manual setpoint 500 A is beyond the channel's hard limit of 20 A"
        " (range -20 … 20 A); refused"
    )
    assert body["tag"]["value"] == 0.0  # nothing staged: the screen shows what is asked
    status, body = await c.command("ch4", "manual_current", value=-25)
    assert status == 409 and "hard limit of -20 A" in body["reason"], body
    await c.scans(20)
    assert c.value("ch4.manual_current") == 0.0 and c.value("ch4.current_cmd") == 0.0
    # Inside the hard limits: accepted, and what flows is what was asked.
    status, body = await c.put_tag("ch4.manual_current", 2)
    assert (status, body["reason"]) == (200, "ch4: manual setpoint 2 A"), body
    await c.scans(20)
    assert c.value("ch4.current_cmd") == 2.0 and c.value("ch4.clamped") is False
