"""Issue 27's attacks, one after the other, against one real ``supervisor run`` of the
simulated bench (login on, a test running on ch0), as someone on the lab network would
try them: each is refused, and afterwards the test still runs, every device is connected
and the scan never stalled. The finding-by-finding tests are beside this one (and in
tests/integration/); this one shows them together on the product as it is started.
Wall time (a real process); waits are bounded, nothing asserts a duration.
"""

from __future__ import annotations

import asyncio
import json
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client as UaClient
from asyncua import ua

from supervisor.bench.flood import (
    CHANNEL,
    OPERATOR,
    Client,
    Supervisor,
    add_user,
    bench_run,
    devices_connected,
    start_test,
    tag,
    wait_ready,
)

# It asserts the scan kept its timing (no stall, no overrun) under load it makes itself:
# it runs alone, after the tests that run in parallel (Makefile: the "quiet" marker).
pytestmark = [pytest.mark.integration, pytest.mark.quiet]

SECRET = "INFLUX_TOKEN=not-for-your-eyes-0123456789"
VIEWER = ("vera", "vera-pw")


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Supervisor, Client, Path]]:
    folder = tmp_path_factory.mktemp("attacks")
    (folder / "secret.env").write_text(SECRET + "\n", encoding="utf-8")
    # A recipe folder of the test's own, holding a link to the secret beside it.
    (folder / "recipes").mkdir()
    (folder / "recipes" / "link.yaml").symlink_to(folder / "secret.env")
    with bench_run(folder, recipe_folders=(folder / "recipes",)) as sup:
        add_user(folder / "flood.yaml", *VIEWER, role="viewer")
        op = Client(sup.host, sup.http_port)
        status, body = op.call("POST", "/api/login", {"user": OPERATOR[0], "password": OPERATOR[1]})
        assert status == 200, body
        wait_ready(op)
        start_test(op)
        stalls = tag(op, "scan.stalls")
        yield sup, op, folder
        # After every attack: the test runs, every device is connected, no stall.
        assert tag(op, f"{CHANNEL}.chain.state") == "Running"
        assert devices_connected(op) == dict.fromkeys(devices_connected(op), True)
        assert tag(op, "scan.stalls") == stalls
        assert tag(op, f"{CHANNEL}.fault") in ("", None)
        op.close()


def raw(
    sup: Supervisor,
    method: str,
    path: str,
    body: bytes | None,
    headers: dict[str, str],
) -> tuple[int, Any]:
    req = urllib.request.Request(
        f"http://{sup.host}:{sup.http_port}{path}", data=body, method=method, headers=headers
    )
    try:
        with urllib.request.urlopen(req, timeout=10) as resp:
            return resp.status, json.loads(resp.read() or b"null")
    except urllib.error.HTTPError as exc:
        with exc:
            return exc.code, json.loads(exc.read() or b"null")


def test_no_file_outside_the_recipe_folders_is_read_or_echoed(
    run: tuple[Supervisor, Client, Path],
) -> None:
    _, op, folder = run
    for path in (
        "/etc/passwd",
        "../../../../etc/passwd",
        str(folder / "secret.env"),
        str(folder / "recipes" / "link.yaml"),  # in a folder, a link to the secret
    ):
        status, body = op.call("PUT", "/api/channels/ch1/recipe", {"file": path})
        assert status == 403, (path, body)
        assert "outside the recipe folders" in body["reason"]
        assert "root:" not in json.dumps(body) and "INFLUX_TOKEN" not in json.dumps(body)
    # By its name the link is no recipe of the folders (not found): nothing of it either.
    status, body = op.call("PUT", "/api/channels/ch1/recipe", {"file": "link"})
    assert status == 404 and "INFLUX_TOKEN" not in json.dumps(body), body
    status, events = op.call("GET", "/api/events")
    assert status == 200 and "INFLUX_TOKEN" not in json.dumps(events)
    assert "INFLUX_TOKEN" not in str(tag(op, "ch1.chain.last_event"))


def test_a_page_of_another_origin_cannot_command(run: tuple[Supervisor, Client, Path]) -> None:
    sup, op, _ = run
    cookie = {"Cookie": op.cookie}
    body = b'{"value": 0.3}'
    form = {**cookie, "Content-Type": "text/plain"}
    status, _ = raw(sup, "PUT", "/api/tags/ch1.manual_current", body, form)
    assert status == 415
    foreign = {**cookie, "Content-Type": "application/json", "Origin": "http://127.0.0.1:1"}
    status, answer = raw(sup, "PUT", "/api/tags/ch1.manual_current", body, foreign)
    assert status == 403 and "http://127.0.0.1:1" in answer["reason"]
    assert tag(op, "ch1.manual_current") == 0.0


def test_wrong_passwords_are_throttled_and_a_viewer_cannot_press_the_estop(
    run: tuple[Supervisor, Client, Path],
) -> None:
    sup, op, _ = run
    answers = []
    for n in range(8):
        c = Client(sup.host, sup.http_port)
        answers.append(c.call("POST", "/api/login", {"user": VIEWER[0], "password": f"x{n}"})[0])
        c.close()
    assert answers[:5] == [401] * 5 and 429 in answers[5:], answers
    # The operator's session is untouched by a viewer's lockout.
    assert op.call("GET", "/api/session")[0] == 200
    viewer = Client(sup.host, sup.http_port)
    # Another address than the guesses' (127.0.0.2 is loopback too, and routes here).
    viewer.conn.source_address = ("127.0.0.2", 0)
    status, body = viewer.call("POST", "/api/login", {"user": VIEWER[0], "password": VIEWER[1]})
    assert status == 200, body
    status, body = viewer.call("PUT", "/api/sim/estop", {"pressed": True})
    assert status == 403, body
    viewer.close()
    assert tag(op, "estop.ok") is True


def test_opcua_asks_every_password_to_be_encrypted(
    run: tuple[Supervisor, Client, Path],
) -> None:
    sup, _, _ = run

    async def attempt() -> set[str]:
        url = f"opc.tcp://{sup.host}:{sup.opcua_port}/supervisor"
        c = UaClient(url, timeout=10)
        c.set_user(OPERATOR[0])
        c.set_password(OPERATOR[1])
        # The client library encrypts the password with the server's certificate when the
        # endpoint's token policy asks for it: the one offered must ask for it.
        await c.connect()
        try:
            endpoints = await c.get_endpoints()
            return {
                f"{e.SecurityMode.name} {p.SecurityPolicyUri or '(the channel)'}"
                for e in endpoints
                for p in e.UserIdentityTokens
                if p.TokenType == ua.UserTokenType.UserName
            }
        finally:
            await c.disconnect()

    # Where the channel does not encrypt (None, Sign) the UserName token names its own
    # encryption (an empty or None policy would send the password in clear); inside
    # SignAndEncrypt the channel encrypts it.
    policies = asyncio.run(attempt())
    assert policies, "no UserName token offered"
    for mode_and_token in policies:
        if not mode_and_token.startswith("SignAndEncrypt "):
            assert mode_and_token.endswith("#Basic256Sha256"), policies
