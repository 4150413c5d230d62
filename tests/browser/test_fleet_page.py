"""Must show (issue 35): the fleet page in Chromium with real ``supervisor run`` benches and
a real ``supervisor fleet`` (login with the HMI's users file): one tile per bench, online;
one bench SIGKILLed → its tile goes offline. axe-core finds no serious or critical
violation on the page, online and with a bench offline, in English and in French."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
import yaml
from axe import audit, blocking
from browserrig import screenshot
from integration.test_fleet_mosquitto import Child, run_bench, run_fleet
from mqttrig import Mosquitto

from supervisor.config.users import hash_password

BENCHES = ("bench-a", "bench-b")
PASSWORD = "fleet-pw"


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, dict[str, Child]]]:
    tmp = tmp_path_factory.mktemp("fleet-page")
    broker = Mosquitto(tmp / "mosquitto")
    broker.start()
    users = tmp / "users.yaml"
    entry = {"role": "viewer", "password": hash_password(PASSWORD)}
    users.write_text(yaml.safe_dump({"users": {"vera": entry}}), encoding="utf-8")
    fleet, base = run_fleet(tmp, broker, "--users", str(users))
    benches = {edge: run_bench(tmp, broker, edge) for edge in BENCHES}
    try:
        yield base, benches
    finally:
        for child in (*benches.values(), fleet):
            child.stop()
        broker.stop()


def no_blocking_violation(page: Any) -> None:
    found = blocking(audit(page))
    assert not found, "\n".join(f"{v}\n{v.detail()}" for v in found)


def test_the_fleet_page_shows_each_bench_and_a_killed_one_goes_offline(
    page: Any, lab: tuple[str, dict[str, Child]]
) -> None:
    base, benches = lab
    page.goto(base)
    page.wait_for_function("() => location.hash.startsWith('#/login')")
    page.fill("#login-user", "vera")
    page.fill("#login-password", PASSWORD)
    page.click("#login-submit")
    page.wait_for_selector("#top:not([hidden])")
    for edge in BENCHES:
        page.wait_for_selector(
            f'[data-bench="{edge}"][data-online="true"] [data-channel="ch1"]', timeout=60_000
        )
    assert "vera" in page.inner_text("#who")
    assert "2" in page.inner_text("#fleet-counts")
    no_blocking_violation(page)

    benches["bench-b"].kill()
    page.wait_for_selector('[data-bench="bench-b"][data-online="false"]', timeout=30_000)
    tile = page.inner_text('[data-bench="bench-b"]')
    assert "OFFLINE" in tile
    assert page.get_attribute('[data-bench="bench-a"]', "data-online") == "true"
    no_blocking_violation(page)

    page.click("#lang")  # French: the same page, its own words
    page.wait_for_function("() => document.documentElement.lang === 'fr'")
    page.wait_for_selector('[data-bench="bench-b"]:has-text("HORS LIGNE")')
    no_blocking_violation(page)
    screenshot(page, "fleet-page-fr")
