"""``/api/bench``, ``/api/channels/{ch}/program``, ``/api/diagnostics`` and the page's files
over HTTP (real server on loopback, commandrig's bench on the virtual clock)."""

from __future__ import annotations

from pathlib import Path

import pytest
from commandrig import DISCHARGE, recipe
from hmirig import hmi_bench

# It asserts the scan kept its timing (no stall, no overrun) under load it makes itself:
# it runs alone, after the tests that run in parallel (Makefile: the "quiet" marker).
pytestmark = [pytest.mark.integration, pytest.mark.quiet]


async def test_the_bench_layout_over_http(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        s = await hmi.login("vera")
        status, body = await hmi.call(s, "GET", "/api/bench")
        assert status == 200
        assert set(body) == {"bench", "description", "period_s", "channels", "devices", "mimic"}
        assert [c["name"] for c in body["channels"]] == ["ch0", "ch1", "ch2", "ch3"]
        assert body["mimic"]["estop"] == "estop.ok"
        assert body["mimic"]["supply"] is None  # no supply on this bench
        for c in body["channels"]:
            for name in c["tags"].values():
                assert name is None or name in hmi.bench.db


async def test_a_channel_s_program_is_its_compiled_recipe(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        s = await hmi.login("otto")
        status, body = await hmi.call(s, "GET", "/api/channels/ch0/program")
        assert (status, body) == (
            404,
            {"error": "no recipe", "reason": "ch0: no recipe loaded"},
        )
        status, body = await hmi.call(s, "GET", "/api/channels/ch9/program")
        assert status == 404 and body["reason"] == "no channel 'ch9'"
        status, body = await hmi.call(
            s, "PUT", "/api/channels/ch0/recipe", {"file": recipe(tmp_path, DISCHARGE)}
        )
        assert status == 200, body
        await hmi.scans(2)
        status, body = await hmi.call(s, "GET", "/api/channels/ch0/program")
        assert status == 200
        assert body["recipe"] == "d"
        assert [(st["name"], st["kind"], st["index"]) for st in body["steps"]] == [
            ("d", "discharge", 0),
            ("r", "rest", 1),
        ]
        assert body["steps"][0]["transitions"] == [
            {"to": "r", "condition": "step time >= 3600 s", "action": "next"}
        ]
        assert body["steps"][1]["transitions"] == [
            {"to": "end", "condition": "step time >= 3600 s", "action": "next"}
        ]


async def test_diagnostics_report_devices_scan_and_publishers(tmp_path: Path) -> None:
    async with hmi_bench(tmp_path) as hmi:
        await hmi.scans(20)
        s = await hmi.login("vera")
        status, body = await hmi.call(s, "GET", "/api/diagnostics")
        assert status == 200
        assert set(body) == {"devices", "scan", "publishers", "spool"}
        devices = {d["name"]: d for d in body["devices"]}
        assert set(devices) == {"chadeche", "adam"}
        adam = devices["adam"]
        assert adam["kind"] == "adam5000tcp"
        assert adam["connected"] is True and adam["failures"] == 0 and adam["polls"] > 0
        assert adam["quality"] == "GOOD" and adam["last_error"] is None
        assert adam["inputs"]["GOOD"] > 0 and adam["inputs"]["BAD"] == 0
        scan = body["scan"]
        assert scan["period_s"] == 0.1 and scan["count"] >= 30
        assert scan["overruns"] == 0
        for key in ("duration_p99_s", "jitter_p99_s", "duration_max_s", "stalls"):
            assert isinstance(scan[key], int | float), key
        hmi_pub = next(p for p in body["publishers"] if p["name"] == "hmi")
        assert set(hmi_pub["tags"]) == {"ws_clients", "ws_dropped"}
        assert hmi_pub["tags"]["ws_dropped"]["value"] == 0
        assert body["spool"] is None  # no InfluxDB on this bench


# --- the page's files ----------------------------------------------------------------------
@pytest.fixture
def front(tmp_path: Path) -> Path:
    root = tmp_path / "hmi"
    (root / "js").mkdir(parents=True)
    (root / "index.html").write_text("<!doctype html><title>bench</title>", encoding="utf-8")
    (root / "js" / "app.js").write_text("console.log('hmi')", encoding="utf-8")
    dist = root / "node_modules" / "uplot" / "dist"
    dist.mkdir(parents=True)
    (dist / "uPlot.iife.min.js").write_text("var uPlot;", encoding="utf-8")
    (tmp_path / "secret.txt").write_text("not for the web", encoding="utf-8")
    return root


async def test_the_page_its_scripts_and_uplot_are_served(tmp_path: Path, front: Path) -> None:
    async with hmi_bench(tmp_path, root=front) as hmi:
        s = await hmi.client()  # not logged in: the login page must load
        for path, text, kind in (
            ("/", "<!doctype html><title>bench</title>", "text/html"),
            ("/static/js/app.js", "console.log('hmi')", "javascript"),
            ("/vendor/uplot/uPlot.iife.min.js", "var uPlot;", "javascript"),
        ):
            async with s.get(hmi.base + path) as resp:
                assert resp.status == 200, path
                assert await resp.text() == text
                assert kind in resp.headers["Content-Type"]
        for path in ("/static/missing.js", "/static/../secret.txt", "/static/%2e%2e/secret.txt"):
            async with s.get(hmi.base + path) as resp:
                assert resp.status == 404, path


async def test_without_the_front_end_installed_the_page_says_what_to_run(
    tmp_path: Path, front: Path
) -> None:
    async with hmi_bench(tmp_path, root=tmp_path / "nothing") as hmi:
        s = await hmi.client()
        for path in ("/", "/static/js/app.js", "/vendor/uplot/uPlot.iife.min.js"):
            async with s.get(hmi.base + path) as resp:
                assert resp.status == 503, path
                assert "make hmi" in await resp.text()
        status, _ = await hmi.call(s, "GET", "/api/tags/ch0.voltage")
        assert status == 200  # the API works without it


async def test_without_uplot_installed_its_route_answers_503(tmp_path: Path, front: Path) -> None:
    import shutil

    shutil.rmtree(front / "node_modules")
    async with hmi_bench(tmp_path, root=front) as hmi:
        s = await hmi.client()
        async with s.get(hmi.base + "/vendor/uplot/uPlot.iife.min.js") as resp:
            assert resp.status == 503
            assert "uPlot" in await resp.text() and "make hmi" in await resp.text()
        async with s.get(hmi.base + "/") as resp:
            assert resp.status == 200
