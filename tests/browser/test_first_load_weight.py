"""Issue 33, "What to build": the first load's weight before and after compression (it was
198 KB, none of it compressed). A fresh Chromium (nothing cached) logs in and opens the
Overview; every text answer of more than a kilobyte came gzip; then each GET of that load is
fetched again by a raw HTTP client, once without gzip (what the page cost before) and once
with it. The figures are printed (``-s``) and written to tests/artifacts/hmi-figures.json
(``first_load``)."""

from __future__ import annotations

import urllib.request
from typing import Any

from browserrig import USERS, VIEWPORT, Supervisor, save_figures, wait_for

from supervisor.hmi.compress import GZIP_MIN_BYTES, compressible


def _body_bytes(bench: Supervisor, url: str, encoding: str) -> tuple[int, str]:
    """The size of ``url``'s body as sent (not decompressed), and its Content-Encoding."""
    req = urllib.request.Request(url, headers={"Accept-Encoding": encoding})
    with bench.opener("operator").open(req, timeout=10) as res:
        return len(res.read()), res.headers.get("Content-Encoding", "")


Loaded = list[tuple[str, str, int, dict[str, str]]]
"""Each request of a load: method, URL, bytes transferred (body and headers), answer's headers."""


def first_load(browser: Any, bench: Supervisor) -> Loaded:
    """What a fresh Chromium (nothing cached) loads to log in and show the Overview."""
    ctx = browser.new_context(viewport=VIEWPORT)
    page = ctx.new_page()
    loaded: Loaded = []

    def finished(req: Any) -> None:
        sizes = req.sizes()
        response = req.response()
        headers = response.headers if response is not None else {}
        size_b = sizes["responseBodySize"] + sizes["responseHeadersSize"]
        loaded.append((req.method, req.url, size_b, headers))

    page.on("requestfinished", finished)
    try:
        page.goto(f"{bench.base}/")
        if bench.login:
            page.wait_for_selector("#login-form")
            page.fill("#login-user", "operator")
            page.fill("#login-password", USERS["operator"])
            page.click("#login-submit")
        page.wait_for_selector("#tile-ch4")
        wait_for("live values", lambda: page.text_content("#tile-ch0 .big") not in ("", "—"))
        page.wait_for_load_state("networkidle")
    finally:
        ctx.close()
    return loaded


def test_the_first_load_is_less_than_half_its_uncompressed_weight(
    browser: Any, bench: Supervisor
) -> None:
    loaded = first_load(browser, bench)
    gets = [(url, headers) for method, url, _, headers in loaded if method == "GET"]
    assert any(u.endswith("/api/tags") for u, _ in gets), gets
    # Every text answer worth it came gzip to the browser.
    plain_text = [
        u.removeprefix(bench.base)
        for u, h in gets
        if compressible(h.get("content-type"))
        and int(h.get("content-length") or GZIP_MIN_BYTES) >= GZIP_MIN_BYTES
        and h.get("content-encoding") != "gzip"
    ]
    assert not plain_text, plain_text
    browser_b = sum(b for _, _, b, _ in loaded)
    rows = []
    for url, _ in gets:
        plain, _ = _body_bytes(bench, url, "identity")
        packed, encoding = _body_bytes(bench, url, "gzip")
        rows.append((url.removeprefix(bench.base), plain, packed, encoding))
    before_b, after_b = sum(r[1] for r in rows), sum(r[2] for r in rows)
    print(
        f"first load (login + overview), {len(loaded)} requests: bodies {before_b / 1024:.1f} KB"
        f" plain, {after_b / 1024:.1f} KB gzip; Chromium transferred {browser_b / 1024:.1f} KB"
        " (headers included)"
    )
    for path, plain, packed, encoding in sorted(rows, key=lambda r: -r[1])[:8]:
        print(f"  {plain / 1024:7.1f} KB -> {packed / 1024:6.1f} KB {encoding or '-':5} {path}")
    save_figures(
        {
            "first_load": {
                "requests": len(loaded),
                "bodies_plain_kb": round(before_b / 1024, 1),
                "bodies_gzip_kb": round(after_b / 1024, 1),
                "browser_transferred_kb": round(browser_b / 1024, 1),
            }
        }
    )
    assert after_b < before_b / 2, (after_b, before_b)
    assert browser_b < before_b / 2, (browser_b, before_b)
