"""The Recipes screen's endpoints against the real aiohttp server on loopback (issue 12):
list, view, validate with ``supervisor check``'s messages at their line and column, a
dry-run preview with its timeline, capacity per cycle and trace, and a save that is
all-or-nothing, engineers only, never over an existing recipe unless asked.

The bench of the command-path tests (four Chadèche channels, virtual clock) gives the
channels; the last test runs the simulated bench on a real clock, because a held event
loop is what it looks for: a dry run of the 25 h recipe never costs the scan a deadline.
"""

from __future__ import annotations

import asyncio
import io
import json
import shutil
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import pytest
import yaml
from commandrig import started_bench
from yarl import URL

from supervisor.app import Bench, build_bench
from supervisor.app.preview import preview_in_child
from supervisor.cli.main import main
from supervisor.config.limits import MAX_YAML_BYTES
from supervisor.core.clock import RealClock
from supervisor.devices import base
from supervisor.devices.registry import load_bench
from supervisor.hmi import HttpApi
from supervisor.hmi.recipes_api import MAX_BODY_BYTES, MAX_TRACE_POINTS, RecipesConfig
from supervisor.testing import free_tcp_port, wait_until

JSON = {"Content-Type": "application/json"}
"""What every command declares, a body or not (supervisor.hmi.csrf)."""

ROOT = Path(__file__).resolve().parents[2]
# It asserts the scan kept its timing (no stall, no overrun) under load it makes itself:
# it runs alone, after the tests that run in parallel (Makefile: the "quiet" marker).
pytestmark = [pytest.mark.integration, pytest.mark.quiet]

SLOW = "nimh-25h-slow-cycle"
CONTROL_SCANS = 100
"""Scans (10 s at sim.yaml's 0.1 s, about the dry run's time) watched with no dry run."""
ANSWER_LIMIT_S = 120.0
"""Upper bound for an answer on a slow machine (not a timing claim)."""

BROKEN = """recipe: broken
capacity: 2000 mAh
steps:
  - id: charge
    charge: 0.1 C
    duration: 14 h
  - id: rest
    rest: 1 hour
  - {id: back, discharge: 200 bananas, duration: 1 h}
"""


@dataclass
class Client:
    api: HttpApi
    session: aiohttp.ClientSession
    recipes: Path
    role: str | None = "engineer"

    async def call(self, method: str, path: str, body: Any = None, **kw: Any) -> tuple[int, Any]:
        if body is not None:
            kw["json"] = body
        url = URL(self.api.url + path, encoded=True)  # as sent: ..%2F stays encoded
        headers = {"X-Test-Role": self.role} if self.role is not None else {}
        headers.update(JSON)  # every command declares JSON (supervisor.hmi.csrf)
        async with self.session.request(method, url, headers=headers, **kw) as resp:
            return resp.status, await resp.json()

    def files(self) -> list[str]:
        return sorted(p.name for p in self.recipes.iterdir())


def header_role(request: Any) -> str | None:
    """The session's role as the HMI's login would give it (a header stands in for it)."""
    role: str | None = request.headers.get("X-Test-Role")
    return role


@pytest.fixture
async def client(tmp_path: Path) -> AsyncIterator[Client]:
    bench = await started_bench(tmp_path)
    recipes = tmp_path / "recipes"
    recipes.mkdir()
    for name in (SLOW, "capacity-test", "nimh-fast-charge-dv"):
        shutil.copy(ROOT / "recipes" / f"{name}.yaml", recipes)
    config = RecipesConfig(
        recipes,
        preview_in_child,
        target_of=bench.target,
        channels=bench.runners,
        role_of=header_role,
    )
    api = HttpApi(bench.db, bench.clock, "127.0.0.1", 0, commands=bench.commands, recipes=config)
    await api.start()
    try:
        timeout = aiohttp.ClientTimeout(total=ANSWER_LIMIT_S)
        async with aiohttp.ClientSession(timeout=timeout) as session:
            yield Client(api, session, recipes)
    finally:
        await api.stop()
        await bench.shutdown()


def as_json(text: str) -> io.BytesIO:
    """A large body as a stream (aiohttp warns of a large body sent at once)."""
    return io.BytesIO(json.dumps({"text": text}).encode("utf-8"))


def check_lines(path: Path, capsys: pytest.CaptureFixture[str]) -> list[str]:
    capsys.readouterr()
    main(["check", str(path)])
    return capsys.readouterr().err.splitlines()


# --- list and view --------------------------------------------------------------------------
async def test_the_list_names_each_recipe_with_its_file_and_title(client: Client) -> None:
    status, body = await client.call("GET", "/recipes")
    assert status == 200
    by_name = {r["name"]: r for r in body["recipes"]}
    assert sorted(by_name) == ["capacity-test", "nimh-25h-slow-cycle", "nimh-fast-charge-dv"]
    slow = by_name[SLOW]
    assert slow["file"] == str(client.recipes / f"{SLOW}.yaml")
    assert slow["title"] == "0.1 C charge 14 h, rest, 0.2 C discharge to 1.0 V, rest"
    assert slow["modified"] == pytest.approx((client.recipes / f"{SLOW}.yaml").stat().st_mtime)


async def test_a_recipe_is_viewed_as_its_text(client: Client) -> None:
    status, body = await client.call("GET", f"/recipes/{SLOW}")
    assert status == 200
    assert body["name"] == SLOW
    assert body["text"] == (client.recipes / f"{SLOW}.yaml").read_text(encoding="utf-8")


async def test_an_unknown_recipe_is_404(client: Client) -> None:
    status, body = await client.call("GET", "/recipes/no-such-recipe")
    assert status == 404
    assert body["reason"] == f"no recipe 'no-such-recipe' in {client.recipes}"


@pytest.mark.parametrize("name", ["..%2F..%2Fetc%2Fpasswd", "..", ".hidden", "a..b", "%2Fetc"])
async def test_a_name_outside_the_folder_is_refused_before_any_file_is_touched(
    client: Client, name: str
) -> None:
    status, body = await client.call("GET", f"/recipes/{name}")
    assert status in (400, 404), body  # aiohttp itself answers 404 for a bare ".."
    if status == 400:
        assert "refused" in body["reason"]
    status, body = await client.call("PUT", f"/recipes/{name}", {"text": "recipe: x\n"})
    assert status in (400, 404, 405), body
    assert client.files() == ["capacity-test.yaml", f"{SLOW}.yaml", "nimh-fast-charge-dv.yaml"]


# --- validate -----------------------------------------------------------------------------
async def test_a_good_text_validates_with_its_steps_and_parameters(client: Client) -> None:
    text = (ROOT / "recipes" / f"{SLOW}.yaml").read_text(encoding="utf-8")
    status, body = await client.call("POST", "/recipes/validate", {"text": text, "name": SLOW})
    assert status == 200, body
    assert body["ok"] is True and body["steps"] == 4 and body["recipe"] == SLOW
    assert [p["name"] for p in body["parameters"]] == ["v_end", "dv_stop"]


async def test_a_broken_text_is_refused_at_its_lines_as_supervisor_check_says(
    client: Client, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    status, body = await client.call("POST", "/recipes/validate", {"text": BROKEN, "name": "b"})
    assert status == 422
    assert body["ok"] is False
    # The same file given to `supervisor check`: the same lines, word for word.
    same_file = client.recipes / "b.yaml"
    same_file.write_text(BROKEN, encoding="utf-8")
    expected = check_lines(same_file, capsys)
    assert [e["text"] for e in body["errors"]] == expected
    where = {(e["line"], e["column"]) for e in body["errors"]}
    assert (8, 11) in where  # "1 hour": the rest's value
    assert any(e["line"] == 9 and "bananas" in e["message"] for e in body["errors"])
    for e in body["errors"]:
        assert e["text"] == f"{same_file}:{e['line']}:{e['column']}: {e['message']}"


async def test_a_text_against_a_channel_is_refused_by_its_limits(client: Client) -> None:
    text = "recipe: hot\nsteps:\n  - {id: c, charge: 5 A, duration: 1 h}\n"
    status, body = await client.call("POST", "/recipes/validate", {"text": text, "channel": "ch0"})
    assert status == 422
    assert body["errors"][0]["line"] == 3 and "ch0" in body["errors"][0]["message"]
    status, body = await client.call("POST", "/recipes/validate", {"text": text, "channel": "ch9"})
    assert status == 404 and "unknown channel 'ch9'" in body["reason"]


async def test_a_text_over_the_size_limit_is_413_with_supervisor_checks_message(
    client: Client,
) -> None:
    text = "recipe: big\nsteps:\n" + "  - {id: s, rest: 1 s}\n" * (MAX_YAML_BYTES // 20)
    size = len(text.encode())
    assert size > MAX_YAML_BYTES
    for path in ("/recipes/validate", "/recipes/dryrun"):
        status, body = await client.call("POST", path, data=as_json(text))
        assert status == 413, path
        assert body["errors"][0]["message"] == (
            f"file is too large: {size:,} bytes; a recipe or an I/O map may have at most 1 MiB"
            " (README: Input limits)"
        )
    status, body = await client.call("PUT", "/recipes/big", data=as_json(text))
    assert status == 413
    assert "big.yaml" not in client.files()


async def test_a_body_too_large_to_hold_a_recipe_is_413_unread(client: Client) -> None:
    data = io.BytesIO(b'{"text": "' + b"x" * (MAX_BODY_BYTES + 1) + b'"}')
    async with aiohttp.ClientSession() as session:  # its own connection, closed here
        url = client.api.url + "/recipes/huge"
        async with session.put(url, data=data, headers={"X-Test-Role": "engineer", **JSON}) as resp:
            status, body = resp.status, await resp.json()
    assert status == 413
    assert body["reason"].startswith("request body is too large")
    assert "huge.yaml" not in client.files()
    # The server stops reading the rest when the connection closes.
    await wait_until(lambda: not handlers(), "the server's handler of that request ended")


def handlers() -> list[asyncio.Task[Any]]:
    return [t for t in asyncio.all_tasks() if "RequestHandler.start" in repr(t) and not t.done()]


# --- dry run ------------------------------------------------------------------------------
async def test_a_dry_run_of_the_25_h_nimh_recipe_gives_its_timeline_cycles_and_trace(
    client: Client,
) -> None:
    text = (ROOT / "recipes" / f"{SLOW}.yaml").read_text(encoding="utf-8")
    status, body = await client.call("POST", "/recipes/dryrun", {"text": text, "name": SLOW})
    assert status == 200, body
    assert body["ok"] is True and body["finished"] is True and body["state"] == "Complete"
    assert 20 * 3600 < body["duration_s"] < 25 * 3600  # 14 h + 1 h + ≤ 6 h + 4 h
    assert body["end_reason"].startswith("complete after step rest2 of cycle 1")
    starts = [e for e in body["timeline"] if e["text"].startswith("starting step")]
    assert [e["step"] for e in starts] == ["charge", "rest1", "discharge", "rest2"]
    assert [e["t_s"] for e in starts][:3] == [0.0, 14 * 3600.0, 15 * 3600.0]
    (cycle,) = body["cycles"]
    # 0.1 C of 2000 mAh for 14 h in; 0.2 C out to 1.0 V: at most what the cell holds.
    assert cycle["cycle"] == 1
    assert cycle["charge_ah"] == pytest.approx(2.8, rel=0.01)
    assert 1.5 < cycle["discharge_ah"] < 2.4
    assert 0.5 < cycle["efficiency"] < 1.0
    assert cycle["efficiency"] == pytest.approx(cycle["discharge_ah"] / cycle["charge_ah"])
    trace = body["trace"]
    n = len(trace["t_s"])
    assert 100 < n <= MAX_TRACE_POINTS
    assert len(trace["voltage_v"]) == len(trace["current_a"]) == n
    assert trace["t_s"] == sorted(trace["t_s"]) and trace["t_s"][-1] <= body["duration_s"]
    volts = [v for v in trace["voltage_v"] if v is not None]
    assert min(volts) > 0.8 and max(volts) < 1.9  # the recipe's own voltage window
    amps = [a for a in trace["current_a"] if a is not None]
    assert max(amps) == pytest.approx(0.2, abs=0.02)
    assert min(amps) == pytest.approx(-0.4, abs=0.02)


async def test_a_dry_run_of_a_broken_text_is_refused_before_anything_runs(
    client: Client,
) -> None:
    status, body = await client.call("POST", "/recipes/dryrun", {"text": BROKEN})
    assert status == 422
    assert {e["line"] for e in body["errors"]} >= {8, 9}


async def test_a_dry_run_takes_the_recipe_parameters_given(client: Client) -> None:
    text = (ROOT / "recipes" / "capacity-test.yaml").read_text(encoding="utf-8")
    status, base_run = await client.call("POST", "/recipes/dryrun", {"text": text})
    assert status == 200, base_run
    status, body = await client.call(
        "POST", "/recipes/dryrun", {"text": text, "parameters": {"bogus": "1 V"}}
    )
    assert status == 422 and "bogus" in body["reason"]


# --- save ---------------------------------------------------------------------------------
async def test_a_broken_recipe_is_not_saved_and_nothing_is_written(client: Client) -> None:
    before = client.files()
    status, body = await client.call("PUT", "/recipes/new", {"text": BROKEN})
    assert status == 422 and body["errors"]
    assert client.files() == before  # no file, no temporary


async def test_a_good_recipe_is_saved_then_listed(client: Client) -> None:
    text = "recipe: new\ndescription: a new one\nsteps:\n  - {id: r, rest: 1 min}\n"
    status, body = await client.call("PUT", "/recipes/new", {"text": text})
    assert status == 200, body
    assert body["saved"] is True and body["created"] is True
    assert (client.recipes / "new.yaml").read_text(encoding="utf-8") == text
    _, listing = await client.call("GET", "/recipes")
    assert {"name": "new", "title": "a new one"}.items() <= next(
        r for r in listing["recipes"] if r["name"] == "new"
    ).items()


async def test_an_existing_recipe_is_replaced_only_when_overwrite_is_asked(
    client: Client,
) -> None:
    path = client.recipes / f"{SLOW}.yaml"
    old = path.read_text(encoding="utf-8")
    text = f"recipe: {SLOW}\nsteps:\n  - {{id: r, rest: 1 min}}\n"
    status, body = await client.call("PUT", f"/recipes/{SLOW}", {"text": text})
    assert status == 409 and body["exists"] is True
    assert "overwrite" in body["reason"]
    assert path.read_text(encoding="utf-8") == old
    status, body = await client.call("PUT", f"/recipes/{SLOW}", {"text": text, "overwrite": True})
    assert status == 200 and body["created"] is False
    assert path.read_text(encoding="utf-8") == text


@pytest.mark.parametrize(("role", "status"), [("viewer", 403), ("operator", 403), (None, 401)])
async def test_only_an_engineer_saves_a_recipe(
    client: Client, role: str | None, status: int
) -> None:
    client.role = role
    text = "recipe: mine\nsteps:\n  - {id: r, rest: 1 min}\n"
    got, body = await client.call("PUT", "/recipes/mine", {"text": text})
    assert got == status
    if role is not None:
        assert body["reason"] == f"{role} may not save recipes (engineers only)"
    assert "mine.yaml" not in client.files()


# --- the scan goes on ---------------------------------------------------------------------
def sim_map(tmp_path: Path) -> Path:
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    for name in ("adam", "ea", "bms"):
        data["devices"][name]["port"] = free_tcp_port()
    data["hmi"]["port"] = 0
    data.pop("opcua", None)
    data.pop("modbus_server", None)  # nor Modbus (1502 may be taken)
    data["state_dir"] = str(tmp_path / "state")
    path = tmp_path / "sim.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


@pytest.fixture
async def real_bench(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> AsyncIterator[Bench]:
    monkeypatch.setattr(base, "BACKOFF_START_S", 0.2)
    monkeypatch.setattr(base, "BACKOFF_MAX_S", 1.0)
    b = build_bench(load_bench(sim_map(tmp_path)), RealClock())
    stop = asyncio.Event()
    await b.start()
    task = asyncio.create_task(b.run(stop))
    try:
        db = b.db
        await wait_until(
            lambda: (
                all(db[f"{d}.connected"].value is True for d in ("adam", "ea", "bms"))
                and db["ch0.voltage"].good
            ),
            "every device connected",
        )
        yield b
    finally:
        stop.set()
        await task
        await b.shutdown()


async def test_a_dry_run_of_the_25_h_recipe_never_costs_the_scan_a_deadline(
    real_bench: Bench, tmp_path: Path
) -> None:
    config = RecipesConfig(ROOT / "recipes", preview_in_child)
    api = HttpApi(real_bench.db, real_bench.clock, "127.0.0.1", 0, recipes=config)
    stats = real_bench.engine.stats
    # The control: the same bench without a dry run. A machine that makes the scan miss
    # deadlines on its own (other processes on every core) cannot tell whether the dry run
    # costs one; the test then says so instead of passing or failing by chance.
    skipped, stalls, scans = stats.skipped, stats.stalls, stats.count
    await wait_until(lambda: stats.count >= scans + CONTROL_SCANS, "the control scans", 60.0)
    if stats.skipped > skipped or stats.stalls > stalls:
        pytest.skip(
            f"this machine is too busy to measure: the scan missed {stats.skipped - skipped}"
            f" deadlines in {CONTROL_SCANS} scans with no dry run"
        )
    await api.start()
    try:
        skipped, overruns, scans = stats.skipped, stats.overruns, stats.count
        text = (ROOT / "recipes" / f"{SLOW}.yaml").read_text(encoding="utf-8")
        timeout = aiohttp.ClientTimeout(total=ANSWER_LIMIT_S)
        async with (
            aiohttp.ClientSession(timeout=timeout) as session,
            session.post(api.url + "/recipes/dryrun", json={"text": text, "name": SLOW}) as r,
        ):
            status, body = r.status, await r.json()
    finally:
        await api.stop()
    assert status == 200 and body["finished"] is True, body
    assert stats.count > scans  # the scan ran meanwhile...
    assert stats.skipped == skipped  # ...and missed no deadline
    assert stats.overruns == overruns
    assert stats.stalls == stalls, f"worst stall {stats.stall_max_s} s"
