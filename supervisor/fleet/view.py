"""``GET /api/fleet``'s answer: the fleet's picture as the page shows it (docs/fleet.md).

Names are the bench's tags (docs/sparkplug.md): a channel is a Sparkplug device whose
metrics include its step chain's (``chain.state``); its state is the chain's (idle,
running, held…), falling back to the channel's own ``state``; V and I are ``voltage`` and
``current``, the step ``chain.step``, the progress ``chain.progress`` (0–1). A metric a
bench does not publish is null, never guessed.
"""

from __future__ import annotations

from typing import Any

from supervisor.fleet.state import ALARMS_METRIC, URL_METRIC, Device, Fleet, Node

__all__ = ["fleet_json"]


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value)


def _is_channel(dev: Device) -> bool:
    return "chain.state" in dev.metrics


def _channel_json(name: str, dev: Device) -> dict[str, Any]:
    m = dev.metrics
    state = m.get("chain.state")
    if not state:
        state = m.get("state")
    return {
        "id": name,
        "online": dev.online,
        "state": state if isinstance(state, str) else None,
        "step": m.get("chain.step") or None,
        "voltage_v": _number(m.get("voltage")),
        "current_a": _number(m.get("current")),
        "progress": _number(m.get("chain.progress")),
        "alarm": m.get("chain.alarm") or None,
    }


def _node_json(name: str, node: Node) -> dict[str, Any]:
    url = node.metrics.get(URL_METRIC)
    alarms = node.metrics.get(ALARMS_METRIC)
    channels = [_channel_json(d, dev) for d, dev in node.devices.items() if _is_channel(dev)]
    return {
        "id": name,
        "online": node.online,
        "since_ms": node.since_ms,
        "bd_seq": node.bd_seq,
        "in_sync": node.online and node.next_seq is not None,
        "born": node.born,
        "rebirths_asked": node.rebirths,
        "seq_gaps": node.seq_gaps,
        "url": url if isinstance(url, str) and url.startswith(("http://", "https://")) else None,
        "alarms_active": alarms
        if isinstance(alarms, int) and not isinstance(alarms, bool)
        else None,
        "channels": channels,
        "devices": [d for d, dev in node.devices.items() if not _is_channel(dev)],
    }


def fleet_json(fleet: Fleet, *, connected: bool, now_ms: int) -> dict[str, Any]:
    """The whole fleet, nodes by name; ``connected``: the fleet's own link to the broker
    (while it is down, what is shown is as it was, and the page says so)."""
    with fleet.lock:
        nodes = [_node_json(n, fleet.nodes[n]) for n in sorted(fleet.nodes)]
    online = sum(1 for n in nodes if n["online"])
    offline = sum(1 for n in nodes if n["born"] and not n["online"])
    return {
        "group": fleet.group,
        "broker_connected": connected,
        "now_ms": now_ms,
        "online": online,
        "offline": offline,
        "nodes": nodes,
    }
