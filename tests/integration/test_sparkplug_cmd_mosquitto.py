"""Commands over Sparkplug (issue 35), end to end: a real Mosquitto on loopback, a real
``supervisor run`` with a recipe loaded on ch0 and ``sparkplug.commands`` enabled for the
primary host ``scada``, and a host application that is not the project's code (paho-mqtt
and pysparkplug: its retained STATE, its DCMD).

The edge node waits for the host's STATE online before its NBIRTH; a DCMD
``Command/start`` = true on ch0 starts the chain (its DDATA says Running), answered by
``Command/last_result``; the NBIRTH carries ``hmi.url`` (the screens' address) and
``alarms.active`` for the fleet; the audit trail has the command with the actor
``sparkplug:scada``. The host's STATE offline: the node publishes its NDEATH and
reconnects, and a DCMD is refused (logged with the reason).

Wall time: a real process on the real clock (bounded waits, never a timing claim).
"""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
import pysparkplug as ps
import pytest
import yaml
from commandrig import DISCHARGE, chadeche_map, recipe
from mqttrig import Mosquitto, Received, SparkplugConsumer, running_broker

pytestmark = pytest.mark.integration
GROUP = "Lab"
HOST = "scada"
LIMIT_S = 60.0  # a bound for a loaded machine, not a timing claim


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Mosquitto]:
    with running_broker(tmp_path / "mosquitto") as server:
        yield server


class HostApplication:
    """The primary host application's side: its retained STATE and its DCMDs."""

    def __init__(self, port: int) -> None:
        self.client = paho.Client(client_id=f"test-host-{os.getpid()}", clean_session=True)
        self.client.connect("127.0.0.1", port, keepalive=10)
        self.client.loop_start()

    def state(self, online: bool) -> None:
        doc = {"online": online, "timestamp": ps.get_current_timestamp()}
        info = self.client.publish(
            f"spBv1.0/STATE/{HOST}", json.dumps(doc).encode(), qos=1, retain=True
        )
        info.wait_for_publish(timeout=10)

    def command(self, channel: str, verb: str) -> None:
        now = ps.get_current_timestamp()
        metric = ps.Metric(now, f"Command/{verb}", ps.DataType.BOOLEAN, value=True)
        payload = ps.DCmd(timestamp=now, metrics=(metric,)).encode(include_dtypes=True)
        info = self.client.publish(f"spBv1.0/{GROUP}/DCMD/chadeche/{channel}", payload, qos=1)
        info.wait_for_publish(timeout=10)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def bench_map(tmp: Path, broker: Mosquitto) -> str:
    path = Path(chadeche_map(tmp))
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    data["bench"] = "chadeche"
    data["hmi"]["port"] = 0
    data["sparkplug"] = {
        "broker": broker.url,
        "group": GROUP,
        "keepalive_s": 5,
        "commands": {"enabled": True, "primary_host": HOST},
    }
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return str(path)


def last_result(channel: str, text: str) -> Any:
    def check(messages: list[Received]) -> bool:
        return any(
            m.verb == "DDATA"
            and m.device == channel
            and m.metrics().get("Command/last_result") is not None
            and m.metrics()["Command/last_result"].value == text
            for m in messages
        )

    return check


def chain_state(channel: str, state: str) -> Any:
    def check(messages: list[Received]) -> bool:
        return any(
            m.verb in ("DDATA", "DBIRTH")
            and m.device == channel
            and "chain.state" in m.metrics()
            and m.metrics()["chain.state"].value == state
            for m in messages
        )

    return check


def count(verb: str) -> Any:
    return lambda n: lambda ms: len([m for m in ms if m.verb == verb]) >= n


@pytest.mark.timeout(300)
def test_a_dcmd_of_the_primary_host_starts_a_channel_and_is_audited_offline_is_refused(
    tmp_path: Path, broker: Mosquitto
) -> None:
    consumer = SparkplugConsumer(broker.port, GROUP)
    host = HostApplication(broker.port)
    log_path = tmp_path / "supervisor.log"
    proc = None
    try:
        proc, screens = run_supervisor(tmp_path, broker, log_path)
        time.sleep(1.0)  # not a timing claim: a margin for a birth that should not come
        assert consumer.of("NBIRTH") == []  # the host's STATE is not online yet

        host.state(True)
        consumer.wait_for(count("DBIRTH")(2), "births after the STATE online", LIMIT_S)
        (nbirth,) = consumer.of("NBIRTH")
        assert screens.startswith("http://127.0.0.1:")  # what the fleet links to
        assert nbirth.metrics()["hmi.url"].value == screens
        assert nbirth.metrics()["alarms.active"].value >= 0
        (ch0_birth,) = consumer.of("DBIRTH", "ch0")
        assert ch0_birth.metrics()["Command/start"].value is False
        assert ch0_birth.metrics()["chain.state"].value == "Idle"

        host.command("ch0", "start")
        consumer.wait_for(last_result("ch0", "start: accepted"), "the answer", LIMIT_S)
        consumer.wait_for(chain_state("ch0", "Running"), "ch0 running", LIMIT_S)

        host.state(False)  # the host goes away: the node ends its session
        consumer.wait_for(count("NDEATH")(1), "the NDEATH", LIMIT_S)
        # Sent again until the node, reconnecting, has subscribed (a DCMD that reaches the
        # broker in between is for no one: clean sessions).
        refused = "Sparkplug DCMD hold on ch0 refused: the primary host application scada is"
        deadline = time.monotonic() + LIMIT_S
        while refused not in log_path.read_text(encoding="utf-8"):
            assert time.monotonic() < deadline, f"no {refused!r} in {log_path}"
            host.command("ch0", "hold")
            time.sleep(0.5)
        assert len(consumer.of("NBIRTH")) == 1  # no births until it is online again
    finally:
        if proc is not None and proc.poll() is None:
            proc.terminate()
            proc.wait(60)
        if proc is not None and proc.stdout is not None:
            proc.stdout.close()
        host.close()
        consumer.close()

    entries = audit_entries(tmp_path / "state" / "audit.sqlite")
    started = [e for e in entries if e["actor"] == f"sparkplug:{HOST}"]
    assert [(e["target"], "start" in e["details"]) for e in started] == [("ch0", True)]
    assert not any("hold" in e["details"] for e in started)  # refused before the path


def run_supervisor(
    tmp: Path, broker: Mosquitto, log_path: Path
) -> tuple[subprocess.Popen[str], str]:
    """``supervisor run`` with the recipe loaded on ch0, up: its process and the URL of its
    screens (from its banner)."""
    file = recipe(tmp, DISCHARGE)
    cli = [sys.executable, "-m", "supervisor.cli.main", "run", bench_map(tmp, broker)]
    with log_path.open("w", encoding="utf-8") as log_file:
        proc = subprocess.Popen(
            [*cli, "--recipe", f"ch0={file}"],
            cwd=tmp,
            stdout=subprocess.PIPE,
            stderr=log_file,
            text=True,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
    assert proc.stdout is not None
    screens = ""
    for line in proc.stdout:
        screens = line.split()[2] if line.startswith("operator screens:") else screens
        if line.startswith("Ctrl-C"):
            break
    return proc, screens


def audit_entries(path: Path) -> list[dict[str, Any]]:
    with sqlite3.connect(path) as db:
        db.row_factory = sqlite3.Row
        return [dict(r) for r in db.execute("SELECT actor, kind, target, details FROM entries")]
