"""Issue 28, finding 1, on one real ``supervisor run`` of the simulated bench (login on):
a viewer's tag write, an operator's command and a login, each carrying a lone surrogate
(``"\\ud800"``, a JSON escape), are refused with a JSON 400, and afterwards the historian
still writes: its row count grows, its queue drains, it never crashed, and each refusal's
event is in the history file. Before, the first refusal's event killed the historian's
writer thread for good, with nobody told. Wall time (a real process); waits are bounded,
nothing asserts a duration.
"""

from __future__ import annotations

import http.client
import json
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from supervisor.bench.flood import (
    OPERATOR,
    Client,
    Supervisor,
    add_user,
    bench_run,
    tag,
    wait_ready,
)

pytestmark = pytest.mark.integration

VIEWER = ("vera", "vera-pw")
WAIT_S = 30.0


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Supervisor, Path]]:
    folder = tmp_path_factory.mktemp("surrogates")
    with bench_run(folder) as sup:
        add_user(folder / "flood.yaml", *VIEWER, role="viewer")
        yield sup, folder


def raw(sup: Supervisor, cookie: str, method: str, path: str, data: bytes) -> tuple[int, Any]:
    """A request whose body is sent as written (a JSON escape stays an escape)."""
    c = http.client.HTTPConnection(sup.host, sup.http_port, timeout=10)
    try:
        headers = {"Content-Type": "application/json"}
        if cookie:
            headers["Cookie"] = cookie
        c.request(method, path, body=data, headers=headers)
        resp = c.getresponse()
        assert "application/json" in (resp.getheader("Content-Type") or ""), path
        return resp.status, json.loads(resp.read())
    finally:
        c.close()


def logged_in(sup: Supervisor, user: tuple[str, str]) -> Client:
    c = Client(sup.host, sup.http_port)
    status, body = c.call("POST", "/api/login", {"user": user[0], "password": user[1]})
    assert status == 200, body
    return c


def wait_for(what: str, ok: Any) -> None:
    deadline = time.monotonic() + WAIT_S
    while not ok():
        assert time.monotonic() < deadline, what
        time.sleep(0.2)


def test_a_lone_surrogate_from_a_viewer_an_operator_or_a_login_never_stops_the_historian(
    run: tuple[Supervisor, Path],
) -> None:
    sup, folder = run
    op = logged_in(sup, OPERATOR)
    viewer = logged_in(sup, VIEWER)
    wait_ready(op)
    wait_for("first rows written", lambda: tag(op, "historian.rows_written") > 0)
    status, body = raw(sup, viewer.cookie, "PUT", "/api/tags/ch1.command", b'{"value": "\\ud800"}')
    assert status in (400, 403), body  # refused at the edge, before the role
    assert "lone surrogate" in body["reason"], body
    status, body = raw(
        sup, op.cookie, "POST", "/api/channels/ch1/commands/mode", b'{"value": "\\ud800"}'
    )
    assert status == 400 and body["reason"].startswith("value:"), body
    status, body = raw(sup, "", "POST", "/api/login", b'{"user": "otto", "password": "\\ud800"}')
    assert status == 400 and body["reason"].startswith("password:"), body
    written = tag(op, "historian.rows_written")
    wait_for("rows written after the refusals", lambda: tag(op, "historian.rows_written") > written)
    assert tag(op, "historian.crashes") == 0
    assert tag(op, "historian.write_errors") == 0
    assert tag(op, "historian.last_error") == ""
    wait_for("queue drains", lambda: tag(op, "historian.queue_rows") < 5000)
    # Events are still stored: a later refusal's is in the file.
    status, body = op.call("POST", "/api/channels/ch1/commands/mode", {"value": "semi"})
    assert status == 400, body
    db = sqlite3.connect(folder / "state" / "history.sqlite")
    try:

        def stored() -> bool:
            rows = db.execute("SELECT text FROM events WHERE kind = 'command'").fetchall()
            return any("mode semi" in r[0] for r in rows)

        wait_for("the later refusal's event stored", stored)
    finally:
        db.close()
    op.close()
    viewer.close()
