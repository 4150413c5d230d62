"""``GET /api/tags`` served from the sliced snapshots (docs/adr/0019-http-off-the-scan.md)
answers what it answered before: the JSON text of every ``tag_json`` (or those of a
prefix), as ``application/json; charset=utf-8``, and a write shows in the next answer.
The bench runs on the virtual clock; requests are made between scans."""

from __future__ import annotations

from pathlib import Path

import aiohttp
import pytest
from commandrig import started_bench

from supervisor.hmi import HttpApi
from supervisor.hmi.server import json_dumps, tag_json
from supervisor.testing import run_scans

pytestmark = pytest.mark.integration


async def test_get_tags_answers_the_text_of_every_tag_json_and_changes_show_at_once(
    tmp_path: Path,
) -> None:
    bench = await started_bench(tmp_path)
    api = HttpApi(bench.db, bench.clock, "127.0.0.1", 0, commands=bench.commands)
    await api.start()
    try:
        async with aiohttp.ClientSession() as s:
            await run_scans(bench.engine, 2)
            for path, prefix in (("/tags", ""), ("/tags?prefix=ch1.", "ch1.")):
                expected = json_dumps(
                    [tag_json(t, bench.clock) for t in bench.db if t.name.startswith(prefix)]
                )
                async with s.get(api.url + path) as resp:
                    assert resp.status == 200
                    assert resp.headers["Content-Type"] == "application/json; charset=utf-8"
                    assert await resp.text() == expected
            name = next(t.name for t in bench.db if t.name.endswith(".manual_current"))
            # Within every channel's hard limits (a setpoint beyond them is refused).
            async with s.put(api.url + f"/tags/{name}", json={"value": 0.1}) as resp:
                assert resp.status == 200
            async with s.get(api.url + "/tags") as resp:
                tags = {t["name"]: t for t in await resp.json()}
            assert tags[name]["value"] == bench.db[name].value == 0.1
    finally:
        await api.stop()
        await bench.shutdown()
