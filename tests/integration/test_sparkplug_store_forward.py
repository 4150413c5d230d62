"""Must show (issue 35): a 60 s broker stop with 0 points lost and the historical flag on
the replayed ones.

A real ``supervisor run`` (io_maps/sim.yaml with a ``sparkplug:`` section) publishes
through a real Mosquitto on loopback to a consumer that is not the project's code
(pysparkplug, tests/mqttrig.py). The broker is stopped for a real 60 s and started again
on the same port. ``scan.count`` changes every scan, each time to a new value: every value
it took is a sample, so "0 points lost" is "every value from the first birth to the end
was received", and the outage's are those received flagged ``is_historical``, each once,
oldest first, after the new births and before live data resumes.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import pytest
from mqttrig import Mosquitto, Received, SparkplugConsumer
from test_sparkplug_mosquitto import GROUP, LIMIT_S, Supervisor, births_done, sim_map

pytestmark = pytest.mark.integration
log = logging.getLogger(__name__)
OUTAGE_S = 60.0
RECONNECT_LIMIT_S = 60.0  # paho's back-off reaches 30 s between attempts: a bound, no claim
COUNTER = "scan.count"


def node_values(messages: list[Received]) -> list[tuple[str, int, bool]]:
    """(verb, scan.count value, historical) of every NBIRTH/NDATA metric, in order."""
    out: list[tuple[str, int, bool]] = []
    for m in messages:
        if m.verb in ("NBIRTH", "NDATA"):
            for metric in m.payload.metrics:
                if metric.name == COUNTER and metric.value is not None:  # None: before a scan
                    out.append((m.verb, int(metric.value), bool(metric.is_historical)))
    return out


def historical_metrics(messages: list[Received]) -> list[Any]:
    return [
        x
        for m in messages
        if m.verb in ("NDATA", "DDATA")
        for x in m.payload.metrics
        if x.is_historical
    ]


@pytest.mark.timeout(400)
def test_a_60_s_broker_stop_loses_no_point_and_flags_the_replayed_ones_historical(
    tmp_path: Path,
) -> None:
    broker = Mosquitto(tmp_path / "mosquitto")
    broker.start()
    before = SparkplugConsumer(broker.port, GROUP)
    after: SparkplugConsumer | None = None
    sup = Supervisor(sim_map(tmp_path, broker), tmp_path / "supervisor.log")
    try:
        before.wait_for(births_done("sim"), "births", LIMIT_S)
        before.wait_for(lambda ms: len([m for m in ms if m.verb == "NDATA"]) >= 20, "NDATA")

        broker.stop()
        stopped_at = time.monotonic()
        time.sleep(OUTAGE_S)
        before.close()  # else it reconnects to the new broker too
        broker.start()  # the same port
        after = SparkplugConsumer(broker.port, GROUP)
        restarted_at = time.monotonic()
        after.wait_for(births_done("sim"), "the new births", RECONNECT_LIMIT_S)
        # Live data after the replay: the node's NDATA that are not historical.
        after.wait_for(
            lambda ms: any(v[0] == "NDATA" and not v[2] for v in node_values(ms)),
            "live data after the replay",
            LIMIT_S,
        )
        time.sleep(1.0)  # a few live scans more
        reconnected_s = after.of("NBIRTH")[0].at - restarted_at
        away_s = after.of("NBIRTH")[0].at - stopped_at
    finally:
        assert sup.stop() == 0
        broker.stop()
        if after is not None:
            after.close()

    first = node_values(before.messages)
    second = node_values(after.messages)
    # The new session: its births first, then the replay (historical, oldest first),
    # then live data.
    assert second[0][0] == "NBIRTH"
    kinds = ["birth" if v == "NBIRTH" else "history" if h else "live" for v, _, h in second]
    first_live = kinds.index("live")
    assert set(kinds[1:first_live]) == {"history"}
    assert "history" not in kinds[first_live:]
    replayed = [value for _, value, h in second if h]
    assert replayed == sorted(replayed) and len(replayed) == len(set(replayed))  # once each

    # 0 points lost: every value scan.count took, from the first birth to the last
    # message, was received (live before the stop, historical, in the births, live after).
    received = {value for _, value, _ in first + second}
    lowest, highest = min(received), max(received)
    lost = sorted(set(range(lowest, highest + 1)) - received)
    assert lost == []
    # The outage's samples are the replayed ones: the broker was away OUTAGE_S and more
    # (until the node's reconnection), the scan is 10 Hz.
    live_before = max(value for _, value, h in first if not h)
    assert replayed[0] == live_before + 1  # the first sample the broker did not get
    outage_s = (second[0][1] - live_before) * 0.1
    assert len(replayed) >= 0.9 * OUTAGE_S * 10

    every = historical_metrics(after.messages)
    assert every and all(m.is_historical for m in every)
    per_message: dict[str, int] = {}
    for m in after.messages:
        n = sum(1 for x in getattr(m.payload, "metrics", ()) if x.is_historical)
        if n:
            key = m.verb if m.device is None else f"{m.verb}/{m.device}"
            per_message[key] = per_message.get(key, 0) + n
    summary = (
        f"broker stopped {OUTAGE_S:g} s; node reconnected {reconnected_s:.1f} s after the"
        f" restart (outage as the node saw it: {outage_s:.1f} s of scans);"
        f" {COUNTER}: {len(replayed)} samples replayed with is_historical, {len(lost)} lost,"
        f" {len(first)} live before, {len(second) - len(replayed)} in births/live after;"
        f" all tags: {len(every)} historical metrics replayed ({per_message})"
    )
    print(summary)
    log.info("%s", summary)
    assert away_s >= OUTAGE_S
