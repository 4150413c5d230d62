"""Must show (issue 35), the fleet overview: a real Mosquitto on loopback, two real
``supervisor run`` benches (io_maps/sim.yaml as edge nodes ``bench-a`` and ``bench-b``) and
a real ``supervisor fleet``: both online with their channels; one SIGKILLed → offline
within the keep-alive (its NDEATH, the MQTT will); restarted → online again with the next
bdSeq. Then the fleet's login: the HMI's users file and rules."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from http.cookiejar import CookieJar
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
import pytest
import yaml
from mqttrig import GROUP, KEEPALIVE_S, Child, Mosquitto, running_broker, sim_map

from supervisor.config.users import hash_password

pytestmark = pytest.mark.integration
log = logging.getLogger(__name__)
ROOT = Path(__file__).resolve().parents[2]
LIMIT_S = 60.0  # a bound for a loaded machine, not a timing claim


def run_bench(tmp: Path, broker: Mosquitto, edge: str) -> Child:
    io_map = sim_map(tmp, broker, edge)
    return Child(["run", str(io_map)], tmp / f"{edge}.log", "Ctrl-C")


def run_fleet(tmp: Path, broker: Mosquitto, *extra: str) -> tuple[Child, str]:
    fleet = Child(
        ["fleet", "--broker", broker.url, "--group", GROUP, "--listen", "127.0.0.1:0", *extra],
        tmp / "fleet.log",
        "fleet: ",
    )
    return fleet, fleet.lines[-1].split(" ", 1)[1].strip()


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Mosquitto]:
    with running_broker(tmp_path / "mosquitto") as server:
        yield server


def get_json(url: str, opener: urllib.request.OpenerDirector | None = None) -> Any:
    with (opener or urllib.request.build_opener()).open(url, timeout=10) as resp:
        return json.loads(resp.read())


def nodes(base: str) -> dict[str, dict[str, Any]]:
    return {n["id"]: n for n in get_json(base + "api/fleet")["nodes"]}


def wait_until(check: Callable[[], bool], what: str, timeout_s: float = LIMIT_S) -> float:
    """Seconds it took (a figure for the log, not asserted)."""
    t0 = time.monotonic()
    while not check():
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError(f"no {what} within {timeout_s:g} s")
        time.sleep(0.1)
    return time.monotonic() - t0


def online_with_channels(base: str, edge: str) -> Callable[[], bool]:
    def check() -> bool:
        n = nodes(base).get(edge)
        return bool(n and n["online"] and {c["id"] for c in n["channels"]} >= {"ch0", "ch1"})

    return check


def test_two_benches_online_one_killed_goes_offline_and_comes_back_with_a_new_bdseq(
    tmp_path: Path, broker: Mosquitto
) -> None:
    fleet, base = run_fleet(tmp_path, broker)
    a = run_bench(tmp_path, broker, "bench-a")
    b = run_bench(tmp_path, broker, "bench-b")
    try:
        for edge in ("bench-a", "bench-b"):
            wait_until(online_with_channels(base, edge), f"{edge} online with its channels")
        body = get_json(base + "api/fleet")
        assert body["group"] == GROUP and body["broker_connected"] is True
        assert (body["online"], body["offline"]) == (2, 0)
        ch0 = next(c for c in nodes(base)["bench-a"]["channels"] if c["id"] == "ch0")
        assert ch0["state"] == "Idle" and isinstance(ch0["voltage_v"], float)
        assert isinstance(ch0["current_a"], float) and ch0["progress"] is not None
        assert nodes(base)["bench-a"]["url"].startswith("http://127.0.0.1:")  # its hmi.url
        first_bd_seq = nodes(base)["bench-b"]["bd_seq"]

        b.kill()
        took_s = wait_until(
            lambda: not nodes(base)["bench-b"]["online"],
            "bench-b offline",
            timeout_s=2.5 * KEEPALIVE_S,  # the broker publishes the will within 1.5-2.2 x
        )
        log.info("bench-b offline on the fleet %.2f s after its SIGKILL", took_s)
        assert nodes(base)["bench-a"]["online"] is True
        assert not any(c["online"] for c in nodes(base)["bench-b"]["channels"])

        b = run_bench(tmp_path, broker, "bench-b")
        wait_until(online_with_channels(base, "bench-b"), "bench-b online again")
        assert nodes(base)["bench-b"]["bd_seq"] == (first_bd_seq + 1) % 256
        assert nodes(base)["bench-b"]["in_sync"] is True
    finally:
        for child in (a, b, fleet):
            child.stop()


def test_a_fleet_started_after_the_bench_asks_its_rebirth_and_sees_it(
    tmp_path: Path, broker: Mosquitto
) -> None:
    """The bench's births went out before the fleet subscribed: its next data (seq without
    a birth) makes the fleet ask a rebirth, whose births carry every value."""
    a = run_bench(tmp_path, broker, "bench-a")
    fleet, base = run_fleet(tmp_path, broker)
    try:
        wait_until(online_with_channels(base, "bench-a"), "bench-a online after a rebirth")
        assert nodes(base)["bench-a"]["rebirths_asked"] >= 1
    finally:
        for child in (a, fleet):
            child.stop()


def test_the_fleet_page_and_api_follow_the_hmis_login_rules(
    tmp_path: Path, broker: Mosquitto
) -> None:
    users = tmp_path / "users.yaml"
    entry = {"role": "viewer", "password": hash_password("fleet-pw")}
    users.write_text(yaml.safe_dump({"users": {"vera": entry}}), encoding="utf-8")
    fleet, base = run_fleet(tmp_path, broker, "--users", str(users))
    try:
        with pytest.raises(urllib.error.HTTPError) as refused:
            get_json(base + "api/fleet")
        assert refused.value.code == 401
        refused.value.close()  # its socket (an unclosed one is a ResourceWarning)
        with urllib.request.urlopen(base, timeout=10) as page:  # the page itself loads
            assert b"fleet.js" in page.read()
        opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(CookieJar()))
        login = urllib.request.Request(
            base + "api/login",
            data=json.dumps({"user": "vera", "password": "fleet-pw"}).encode(),
            headers={"Content-Type": "application/json"},
            method="POST",
        )
        with opener.open(login, timeout=10) as resp:
            assert json.loads(resp.read())["role"] == "viewer"
        assert get_json(base + "api/fleet", opener)["group"] == GROUP
    finally:
        fleet.stop()


def test_with_a_host_id_the_fleet_publishes_its_state_and_its_death_as_the_will(
    tmp_path: Path, broker: Mosquitto
) -> None:
    """Sparkplug 3.0 host application: STATE online (retained) after its CONNECT; the will
    says offline with the same timestamp when the fleet is SIGKILLed."""
    fleet, _ = run_fleet(tmp_path, broker, "--host-id", "fleet1")
    states: list[dict[str, Any]] = []
    got = threading.Condition()

    def on_message(client: Any, userdata: Any, msg: Any) -> None:
        with got:
            states.append(json.loads(msg.payload))
            got.notify_all()

    watcher = paho.Client(client_id="state-watcher")
    watcher.on_message = on_message
    watcher.connect("127.0.0.1", broker.port, keepalive=10)
    watcher.subscribe("spBv1.0/STATE/fleet1", qos=1)
    watcher.loop_start()
    try:
        with got:
            assert got.wait_for(lambda: any(s["online"] for s in states), LIMIT_S)
        birth = next(s for s in states if s["online"])
        fleet.kill()
        with got:
            assert got.wait_for(lambda: not states[-1]["online"], LIMIT_S)
        assert states[-1] == {"online": False, "timestamp": birth["timestamp"]}
    finally:
        watcher.disconnect()
        watcher.loop_stop()
        fleet.stop()


def test_a_fleet_on_another_address_without_users_is_refused(tmp_path: Path) -> None:
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "supervisor.cli.main",
            "fleet",
            "--broker",
            "mqtt://127.0.0.1:1",
            "--group",
            GROUP,
            "--listen",
            "0.0.0.0:0",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2 and "without --users" in out.stderr
