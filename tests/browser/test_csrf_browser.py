"""Cross-site request forgery in Chromium (issue 27, finding 2): a page of another origin,
served on another loopback port of the same host, makes the operator's browser send a
command to the supervisor, a form (``text/plain``, a body that parses as JSON) or a
``fetch(..., {mode: "no-cors"})``. With login off (everyone on the API operates) and with
login on (the operator logged in in the same browser: SameSite=Strict sends the cookie to
another port of the same site), the supervisor refuses it (403/415) and the tag keeps its
value. Before the fix both changed ``ch1.manual_current`` (recorded ``hmi:operator``)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import pytest
from browserrig import Supervisor, login, supervisor_fixture, wait_for

ATTACK_A = 0.17
"""The current the attacker's page asks for (within ch1's limits, never set otherwise)."""
COMMAND = "/api/channels/ch1/commands/manual_current"


def form_page(base: str) -> str:
    # text/plain encodes name=value: this name and value make the body
    # {"value": "=", "value": 0.17}, JSON whose last "value" wins.
    name = '{"value": "'
    value = f'", "value": {ATTACK_A}}}'
    return f"""<!doctype html><title>cat pictures</title>
<iframe name="sink"></iframe>
<form method="POST" action="{base}{COMMAND}" enctype="text/plain" target="sink">
<input name='{name}' value='{value}'></form>
<script>document.forms[0].submit()</script>"""


def fetch_page(base: str) -> str:
    return f"""<!doctype html><title>cat pictures</title>
<script>
fetch("{base}{COMMAND}", {{method: "POST", mode: "no-cors", credentials: "include",
  headers: {{"Content-Type": "text/plain"}}, body: '{{"value": {ATTACK_A}}}'}})
</script>"""


PAGES = {"form": form_page, "fetch": fetch_page}


class Attacker:
    """Another origin: a tiny HTTP server on another loopback port serving the pages."""

    def __init__(self) -> None:
        self.pages: dict[str, str] = {}
        pages = self.pages

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                text = pages.get(self.path)
                body = (text or "not found").encode()
                self.send_response(200 if text else 404)
                self.send_header("Content-Type", "text/html; charset=utf-8")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, format: str, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.base = f"http://127.0.0.1:{self.server.server_address[1]}"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(5)


@pytest.fixture(scope="module")
def attacker() -> Iterator[Attacker]:
    a = Attacker()
    try:
        yield a
    finally:
        a.close()


@pytest.fixture(scope="module")
def open_bench(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Supervisor]:
    """The same simulated bench with ``hmi.login: false`` (the default of an I/O map)."""
    yield from supervisor_fixture(tmp_path_factory.mktemp("open-bench"), login=False)


def manual(bench: Supervisor) -> float:
    """ch1 in manual mode (where a manual_current write is taken), its setpoint now."""
    status, body = bench.call("POST", "/api/channels/ch1/commands/mode", {"value": "manual"})
    assert status == 200, body
    status, body = bench.call("POST", COMMAND, {"value": 0.0})
    assert status == 200, body
    return float(bench.tag("ch1.manual_current"))


# The form posts into a hidden frame of the attacker's page; the HMI's answer may not be
# framed by another origin (frame-ancestors 'none'), and Chromium says so on the console.
@pytest.mark.csp_refusal("frame-ancestors")
@pytest.mark.parametrize("how", list(PAGES))
@pytest.mark.parametrize("login_on", [False, True], ids=["login-off", "login-on"])
def test_a_page_of_another_origin_cannot_command_the_bench_through_the_browser(
    page: Any,
    bench: Supervisor,
    open_bench: Supervisor,
    attacker: Attacker,
    how: str,
    login_on: bool,
) -> None:
    target = bench if login_on else open_bench
    before = manual(target)
    if login_on:
        login(page, target, "operator")  # the operator's session, in this browser
    attacker.pages[f"/{how}.html"] = PAGES[how](target.base)
    with page.expect_response(lambda r: r.url == target.base + COMMAND) as answer:
        page.goto(f"{attacker.base}/{how}.html")
    status = answer.value.status
    assert status in (403, 415), f"the forged {how} command was answered {status}"
    # Answered after the command path would have taken it: the setpoint stayed.
    assert target.tag("ch1.manual_current") == before
    wait_for("the bench still answering", lambda: target.tag("adam.connected") is True)


def test_the_hmi_s_own_page_still_commands(page: Any, bench: Supervisor) -> None:
    # The same fetch from the HMI's own origin, as its scripts send it (JSON).
    manual(bench)
    login(page, bench, "operator")
    status = page.evaluate(
        """async ([url, a]) => (await fetch(url, {method: "POST", credentials: "same-origin",
             headers: {"Content-Type": "application/json"},
             body: JSON.stringify({value: a})})).status""",
        [bench.base + COMMAND, ATTACK_A],
    )
    assert status == 200
    assert bench.tag("ch1.manual_current") == pytest.approx(ATTACK_A)
    bench.call("POST", COMMAND, {"value": 0.0})
