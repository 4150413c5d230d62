"""The alarm journal over HTTP (issue 34, supervisor/hmi/journal_api.py, ADR 0048) from
the alarm model's in-memory log (a bench without the embedded historian): filters, the
newest ``limit``, CSV with a header row and formula cells escaped, a viewer may read,
a bad parameter is a 400 naming it."""

from __future__ import annotations

import csv
import io
from collections.abc import AsyncIterator, Awaitable, Callable

import pytest
from aiohttp import web
from aiohttp.test_utils import TestClient, TestServer

from supervisor.core.clock import VirtualClock
from supervisor.hmi.auth import PRINCIPAL_KEY, Principal
from supervisor.hmi.journal_api import add_journal_routes
from supervisor.safety import AlarmManager, Severity

EPOCH = 1_767_225_600.0  # the virtual clock's 2026-01-01T00:00:00Z
Client = TestClient[web.Request, web.Application]


@pytest.fixture
def alarms() -> AlarmManager:
    """ch0.overtemp (a channel's) raised at t = 10, acknowledged by hmi:alice at t = 20,
    cleared at t = 30; the bench's estop raised at t = 40 with a formula-like message."""
    clock = VirtualClock()
    m = AlarmManager(clock)
    hot = m.declare("ch0.overtemp", group="ch0", severity=Severity.HIGH)
    estop = m.declare("estop", severity=Severity.CRITICAL, latched=True)
    clock.advance(10)
    m.set(hot, True, "ch0 too hot")
    clock.advance(10)
    m.acknowledge("ch0.overtemp", "hmi:alice")
    clock.advance(10)
    m.set(hot, False)
    clock.advance(10)
    m.set(estop, True, "=HYPERLINK(1)")
    clock.advance(10)
    return m


@pytest.fixture
async def client(alarms: AlarmManager) -> AsyncIterator[Client]:
    @web.middleware
    async def viewer(
        request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        request[PRINCIPAL_KEY] = Principal("anonymous", "viewer", "viewer")
        return await handler(request)

    app = web.Application(middlewares=[viewer])
    add_journal_routes(app, alarms, lambda: None, lambda group: group)
    async with TestClient(TestServer(app)) as c:
        yield c


async def journal(client: Client, **params: str) -> list[dict[str, object]]:
    resp = await client.get("/api/alarms/journal", params=params)
    assert resp.status == 200, await resp.text()
    body = await resp.json()
    assert body["source"] == "memory"
    entries: list[dict[str, object]] = body["entries"]
    return entries


async def test_a_viewer_reads_every_transition_oldest_first(client: Client) -> None:
    entries = await journal(client)
    assert [(e["alarm"], e["transition"], e["actor"]) for e in entries] == [
        ("ch0.overtemp", "activated", "safety"),
        ("ch0.overtemp", "acknowledged", "hmi:alice"),
        ("ch0.overtemp", "cleared", "safety"),
        ("estop", "activated", "safety"),
    ]
    assert entries[0]["time"] == EPOCH + 10
    assert entries[0]["time_iso"] == "2026-01-01T00:00:10.000Z"
    assert (entries[0]["channel"], entries[0]["priority"]) == ("ch0", "high")


async def test_the_filters_select_by_channel_alarm_actor_transition_and_time(
    client: Client,
) -> None:
    assert [e["alarm"] for e in await journal(client, channel="")] == ["estop"]
    assert len(await journal(client, channel="ch0")) == 3
    assert len(await journal(client, alarm="ch0.overtemp", transition="cleared")) == 1
    assert [e["transition"] for e in await journal(client, actor="hmi:alice")] == ["acknowledged"]
    since, until = str(EPOCH + 15), "2026-01-01T00:00:35Z"
    assert [e["transition"] for e in await journal(client, since=since, until=until)] == [
        "acknowledged",
        "cleared",
    ]


async def test_limit_keeps_the_newest_and_says_so(client: Client) -> None:
    resp = await client.get("/api/alarms/journal", params={"limit": "2"})
    body = await resp.json()
    assert body["truncated"] is True
    assert [e["transition"] for e in body["entries"]] == ["cleared", "activated"]


async def test_csv_has_a_header_row_and_no_cell_a_spreadsheet_would_run(client: Client) -> None:
    resp = await client.get("/api/alarms/journal", params={"format": "csv"})
    assert resp.status == 200 and resp.content_type == "text/csv"
    rows = list(csv.reader(io.StringIO(await resp.text())))
    assert rows[0] == [
        "time", "time_iso", "alarm", "channel", "transition", "priority", "message", "actor",
    ]  # fmt: skip
    assert len(rows) == 5
    assert rows[4][2:] == ["estop", "", "activated", "critical", "'=HYPERLINK(1)", "safety"]


@pytest.mark.parametrize(
    ("params", "named"),
    [
        ({"transition": "exploded"}, "transition"),
        ({"limit": "0"}, "limit"),
        ({"limit": "many"}, "limit"),
        ({"since": "yesterday"}, "since"),
        ({"since": "2026-01-02T00:00:00Z", "until": "2026-01-01T00:00:00Z"}, "since"),
        ({"format": "xlsx"}, "format"),
        ({"alarm": "x" * 300}, "alarm"),
    ],
)
async def test_a_bad_parameter_is_a_400_that_names_it(
    client: Client, params: dict[str, str], named: str
) -> None:
    resp = await client.get("/api/alarms/journal", params=params)
    assert resp.status == 400
    assert named in (await resp.json())["reason"]
