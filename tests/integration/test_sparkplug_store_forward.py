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
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

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


def historical_per_message(messages: list[Received]) -> dict[str, int]:
    """Metrics flagged is_historical, per message kind ("NDATA", "DDATA/ch0"...)."""
    out: dict[str, int] = {}
    for m in messages:
        n = sum(1 for x in getattr(m.payload, "metrics", ()) if x.is_historical)
        if n:
            key = m.verb if m.device is None else f"{m.verb}/{m.device}"
            out[key] = out.get(key, 0) + n
    return out


@dataclass
class Outage:
    before: list[Received]  # what the consumer got before the broker stopped
    after: list[Received]  # and after it started again
    reconnected_s: float  # from the broker's restart to the new NBIRTH
    away_s: float  # from the broker's stop to the new NBIRTH


def broker_outage(tmp_path: Path) -> Outage:
    """``supervisor run`` publishing; the broker stopped OUTAGE_S and started again on
    the same port; a consumer before and one after, until live data has resumed."""
    broker = Mosquitto(tmp_path / "mosquitto", persistent=True)
    broker.start()
    before = SparkplugConsumer(broker.port, GROUP)
    after: SparkplugConsumer | None = None
    sup = Supervisor(sim_map(tmp_path, broker), tmp_path / "supervisor.log")
    try:
        before.wait_for(births_done("sim"), "births", LIMIT_S)
        before.wait_for(lambda ms: len([m for m in ms if m.verb == "NDATA"]) >= 20, "NDATA")
        # The consumer of after the outage has a session the broker keeps across its
        # restart: whatever the node sends once back waits for it, whichever of the two
        # reconnects first (paho's back-off picks the node's moment; it was a race).
        after = SparkplugConsumer(broker.port, GROUP, session=f"after-{tmp_path.name}")
        broker.stop()
        stopped_at = time.time()
        before.close()  # else it reconnects to the new broker too
        time.sleep(OUTAGE_S)
        broker.start()  # the same port, the same sessions
        restarted_at = time.time()
        after.wait_for(new_births_done("sim"), "the new births", RECONNECT_LIMIT_S)
        after.wait_for(
            lambda ms: any(v[0] == "NDATA" and not v[2] for v in node_values(new_session(ms))),
            "live data after the replay",
            LIMIT_S,
        )
        time.sleep(1.0)  # a few live scans more
        second = new_session(after.messages)
        born_at = second[0].payload.timestamp / 1000  # the node's own time of its birth
        return Outage(before.messages, second, born_at - restarted_at, born_at - stopped_at)
    finally:
        assert sup.stop() == 0
        broker.stop()
        if after is not None:
            after.close()


def new_session(messages: list[Received]) -> list[Received]:
    """The messages from the node's new birth on (the consumer of after the outage was
    subscribed a moment before it, and got the last live messages of the old session)."""
    births = [k for k, m in enumerate(messages) if m.verb == "NBIRTH"]
    return messages[births[0] :] if births else []


def new_births_done(node: str) -> Callable[[list[Received]], bool]:
    done = births_done(node)
    return lambda ms: done(new_session(ms))


def replayed_in_order(second: list[tuple[str, int, bool]]) -> list[int]:
    """The new session's births first, then the replay (historical, oldest first, each
    value once), then live data: the replayed values."""
    assert second[0][0] == "NBIRTH"
    kinds = ["birth" if v == "NBIRTH" else "history" if h else "live" for v, _, h in second]
    first_live = kinds.index("live")
    assert set(kinds[1:first_live]) == {"history"}
    assert "history" not in kinds[first_live:]
    replayed = [value for _, value, h in second if h]
    assert replayed == sorted(replayed) and len(replayed) == len(set(replayed))
    return replayed


@pytest.mark.timeout(400)
def test_a_60_s_broker_stop_loses_no_point_and_flags_the_replayed_ones_historical(
    tmp_path: Path,
) -> None:
    outage = broker_outage(tmp_path)
    first, second = node_values(outage.before), node_values(outage.after)
    replayed = replayed_in_order(second)

    # 0 points lost: every value scan.count took, from the first birth to the last
    # message, was received (live before the stop, historical, in the births, live after).
    received = {value for _, value, _ in first + second}
    lost = sorted(set(range(min(received), max(received) + 1)) - received)
    assert lost == []
    # The outage's samples are the replayed ones: the broker was away OUTAGE_S and more
    # (until the node's reconnection), the scan is 10 Hz.
    live_before = max(value for _, value, h in first if not h)
    # The replay starts at the first sample the broker did not get, or before it: what
    # was sent just before the loss was noticed comes again, as history (QoS 0).
    assert replayed[0] <= live_before + 1
    resent = len([v for v in replayed if v <= live_before])
    assert len(replayed) >= 0.9 * OUTAGE_S * 10
    assert outage.away_s >= OUTAGE_S
    per_message = historical_per_message(outage.after)
    summary = (
        f"broker stopped {OUTAGE_S:g} s; node reconnected {outage.reconnected_s:.1f} s after"
        f" the restart ({outage.away_s:.1f} s without the broker);"
        f" {COUNTER}: {len(replayed)} samples replayed with is_historical, each once"
        f" ({resent} of them also received live just before the loss),"
        f" {len(lost)} lost ({len(first)} received live before, {len(second) - len(replayed)}"
        f" in births and live after); all tags: {sum(per_message.values())} historical"
        f" metrics replayed {per_message}"
    )
    print(summary)
    log.info("%s", summary)
