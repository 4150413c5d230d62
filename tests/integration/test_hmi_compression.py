"""gzip of the screens' files and of ``GET /api/tags`` (issue 33, "What to build";
supervisor.hmi.compress, docs/adr/0041-compressed-first-load.md), over HTTP on loopback:
the compressed answer is the plain answer's bytes for every file the supervisor serves and
for a tag list of every kind of value, the browser's check at each load still gets a 304,
a changed file is compressed again, and a client that does not take gzip gets what it got
before."""

from __future__ import annotations

import asyncio
import gzip
import math
import os
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from aiohttp import web
from aiohttp.test_utils import BaseTestServer, TestServer, make_mocked_request

from supervisor.core.clock import VirtualClock
from supervisor.core.quality import Quality
from supervisor.hmi.compress import GZIP_MIN_BYTES, accepts_gzip, compressible
from supervisor.hmi.server import HttpApi
from supervisor.hmi.static import StaticFiles
from supervisor.tags import TagDB, TagSpec

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
HMI = ROOT / "hmi"
GZIP = {"Accept-Encoding": "gzip"}
PLAIN = {"Accept-Encoding": "identity"}


def served_files() -> Iterator[tuple[str, Path]]:
    """Every file the supervisor serves from this repository's hmi/: the page, each file
    under /static/ (scripts, styles, dashboards, notes) and uPlot's build under /vendor/."""
    yield "/", HMI / "index.html"
    for path in sorted(HMI.rglob("*")):
        if path.is_file() and "node_modules" not in path.relative_to(HMI).parts:
            yield f"/static/{path.relative_to(HMI).as_posix()}", path
    dist = HMI / "node_modules" / "uplot" / "dist"
    for path in sorted(dist.glob("*")) if dist.is_dir() else ():
        yield f"/vendor/uplot/{path.name}", path


@pytest.fixture
async def files_server() -> AsyncIterator[tuple[BaseTestServer, StaticFiles]]:
    app = web.Application()
    static = StaticFiles(HMI)
    static.install(app)
    async with TestServer(app, host="127.0.0.1") as server:
        yield server, static


async def _get(
    server: BaseTestServer, path: str, headers: dict[str, str]
) -> tuple[int, bytes, Any]:
    # Raw bytes (no decompression by the client), and no Accept-Encoding of its own.
    session = aiohttp.ClientSession(auto_decompress=False, skip_auto_headers=["Accept-Encoding"])
    async with session as s, s.get(server.make_url(path), headers=headers) as resp:
        return resp.status, await resp.read(), resp.headers


async def test_every_served_file_is_the_same_bytes_gzip_or_plain(
    files_server: tuple[BaseTestServer, StaticFiles],
) -> None:
    server, _ = files_server
    files = list(served_files())
    kinds = {p.suffix for _, p in files}
    assert {".html", ".js", ".css"} <= kinds, kinds  # the front end is there
    for url, path in files:
        status, plain, plain_headers = await _get(server, url, PLAIN)
        assert status == 200, url
        assert plain == path.read_bytes(), url
        assert "Content-Encoding" not in plain_headers, url
        status, packed, headers = await _get(server, url, GZIP)
        assert status == 200, url
        assert headers["Content-Type"] == plain_headers["Content-Type"], url
        assert headers["Cache-Control"] == "no-cache", url
        if compressible(headers["Content-Type"]):
            assert headers["Content-Encoding"] == "gzip", url
            assert headers["Vary"] == "Accept-Encoding", url
            assert gzip.decompress(packed) == plain, url
        else:
            assert packed == plain, url


async def test_the_first_load_s_text_files_shrink_by_more_than_half(
    files_server: tuple[BaseTestServer, StaticFiles],
) -> None:
    server, _ = files_server
    first_load = ["/", "/static/css/hmi.css", "/static/js/app.js", "/static/js/live.js"]
    if (HMI / "node_modules" / "uplot").is_dir():
        first_load += ["/vendor/uplot/uPlot.iife.min.js", "/vendor/uplot/uPlot.min.css"]
    plain = packed = 0
    for url in first_load:
        plain += len((await _get(server, url, PLAIN))[1])
        packed += len((await _get(server, url, GZIP))[1])
    assert packed < plain / 2, (packed, plain)


async def test_the_check_at_each_load_gets_a_304_for_the_gzip_it_has(
    files_server: tuple[BaseTestServer, StaticFiles],
) -> None:
    server, _ = files_server
    _, _, headers = await _get(server, "/static/js/app.js", GZIP)
    etag = headers["ETag"]
    _, _, plain_headers = await _get(server, "/static/js/app.js", PLAIN)
    assert etag != plain_headers["ETag"]  # other bytes, other tag
    status, body, again = await _get(server, "/static/js/app.js", {**GZIP, "If-None-Match": etag})
    assert (status, body) == (304, b"")
    assert again["ETag"] == etag
    status, _, _ = await _get(server, "/static/js/app.js", {**GZIP, "If-None-Match": '"other"'})
    assert status == 200


async def test_a_changed_file_is_compressed_again(tmp_path: Path) -> None:
    (tmp_path / "index.html").write_text("<!doctype html>", encoding="utf-8")
    script = tmp_path / "app.js"
    script.write_text("let a = 1;\n" * 400, encoding="utf-8")
    app = web.Application()
    static = StaticFiles(tmp_path)
    static.install(app)
    async with TestServer(app, host="127.0.0.1") as server:
        _, first, headers = await _get(server, "/static/app.js", GZIP)
        assert gzip.decompress(first) == script.read_bytes()
        script.write_text("let b = 2;\n" * 500, encoding="utf-8")
        later = script.stat().st_mtime_ns + 2_000_000_000
        os.utime(script, ns=(later, later))  # whatever the file system's time resolution
        status, second, new_headers = await _get(
            server, "/static/app.js", {**GZIP, "If-None-Match": headers["ETag"]}
        )
        assert status == 200
        assert gzip.decompress(second) == script.read_bytes()
        assert new_headers["ETag"] != headers["ETag"]


async def test_a_range_or_a_client_without_gzip_gets_the_file_as_it_is(
    files_server: tuple[BaseTestServer, StaticFiles],
) -> None:
    server, _ = files_server
    for headers in ({}, {"Accept-Encoding": "gzip;q=0"}, {**GZIP, "Range": "bytes=0-9"}):
        status, body, answer = await _get(server, "/static/js/app.js", headers)
        assert "Content-Encoding" not in answer, headers
        expected = (HMI / "js" / "app.js").read_bytes()
        assert body == (expected[:10] if "Range" in headers else expected), headers
        assert status == (206 if "Range" in headers else 200)


@pytest.mark.parametrize(
    ("header", "takes"),
    [
        ("gzip", True),
        ("gzip, deflate, br, zstd", True),  # Chromium's
        ("br;q=1.0, gzip;q=0.8, *;q=0.1", True),
        ("*", True),
        ("x-gzip", True),
        ("GZIP", True),
        ("gzip;q=0", False),
        ("gzip; q=0.0", False),
        ("deflate, br", False),
        ("identity", False),
        ("", False),
        ("gzip;q=nonsense", False),
    ],
)
def test_accept_encoding_is_read_as_rfc_9110_says(header: str, takes: bool) -> None:
    request = make_mocked_request("GET", "/", headers={"Accept-Encoding": header})
    assert accepts_gzip(request) is takes


# --- GET /api/tags --------------------------------------------------------------------------
def every_kind_db() -> TagDB:
    """A tag of every kind of value and quality the list writes, and enough of them that
    the list is compressed (more than GZIP_MIN_BYTES)."""
    db = TagDB()
    for k in range(40):
        db.update(db.add(TagSpec(f"ch{k % 5}.v{k:02d}", unit="V")), k * 0.125)
    db.update(db.add(TagSpec("flag", dtype="bool")), True)
    db.update(db.add(TagSpec("count", dtype="int")), -7)
    db.update(db.add(TagSpec("text", dtype="str")), 'a "quoted" text, ü, ✓, \\ and \n')
    db.update(db.add(TagSpec("lost", unit="A")), 1.0, Quality.BAD)
    db.update(db["ch1.v01"], math.nan)  # BAD, sent as null
    db.update(db["ch2.v02"], 3.0, Quality.UNCERTAIN)
    db.add(TagSpec("never", unit="degC"))  # no value yet
    db.force("ch3.v03", 7.0)
    return db


@pytest.fixture
async def api() -> AsyncIterator[tuple[BaseTestServer, HttpApi]]:
    http = HttpApi(every_kind_db(), VirtualClock())
    async with TestServer(http.app, host="127.0.0.1") as server:
        yield server, http


@pytest.mark.parametrize("query", ["", "?prefix=ch1", "?prefix=", "?prefix=nothing"])
async def test_the_tag_list_is_the_same_json_gzip_or_plain(
    api: tuple[BaseTestServer, HttpApi], query: str
) -> None:
    server, _ = api
    status, plain, plain_headers = await _get(server, f"/api/tags{query}", PLAIN)
    assert status == 200
    status, packed, headers = await _get(server, f"/api/tags{query}", GZIP)
    assert status == 200
    assert headers["Content-Type"] == plain_headers["Content-Type"]
    assert headers["Vary"] == plain_headers["Vary"] == "Accept-Encoding"
    if len(plain) < GZIP_MIN_BYTES:
        assert packed == plain and "Content-Encoding" not in headers
    else:
        assert headers["Content-Encoding"] == "gzip"
        assert gzip.decompress(packed) == plain
    assert query == "?prefix=nothing" or len(plain) >= GZIP_MIN_BYTES


async def test_one_compression_per_version_shared_by_every_request(
    api: tuple[BaseTestServer, HttpApi],
) -> None:
    server, http = api
    memo = http._tags_gzip
    answers = await asyncio.gather(*(_get(server, "/api/tags", GZIP) for _ in range(5)))
    assert len({body for _, body, _ in answers}) == 1
    assert memo.compressed == 1
    http.db.update(http.db["ch0.v00"], 99.0)  # a new version
    _, body, _ = await _get(server, "/api/tags", GZIP)
    assert memo.compressed == 2
    assert b"99.0" in gzip.decompress(body)


@pytest.mark.parametrize("path", ["/api/openapi.json", "/api/tags/text", "/api/nothing"])
async def test_the_api_s_other_json_answers_are_the_same_gzip_or_plain(
    api: tuple[BaseTestServer, HttpApi], path: str
) -> None:
    """The OpenAPI description (large), a tag (small), an error (JSON too)."""
    server, _ = api
    status, plain, plain_headers = await _get(server, path, PLAIN)
    status_gz, packed, headers = await _get(server, path, GZIP)
    assert status == status_gz
    assert headers["Content-Type"] == plain_headers["Content-Type"]
    if len(plain) < GZIP_MIN_BYTES:
        assert packed == plain and "Content-Encoding" not in headers
    else:
        assert headers["Content-Encoding"] == "gzip"
        assert headers["Vary"] == "Accept-Encoding"
        assert gzip.decompress(packed) == plain
    assert (path == "/api/openapi.json") == (len(plain) >= GZIP_MIN_BYTES)
