"""The fleet's side of ``supervisor bench fleet``: the fleet's state code (``Fleet`` and its
MQTT client ``FleetHost``, as ``supervisor fleet`` runs them) in a process of its own,
subscribed to the group, measuring each sample's latency on the way.

``python -m supervisor.bench.fleetsink --port P --group G --status FILE --out FILE``:
writes ``--status`` (JSON: connected, nodes born) every half second; SIGUSR1 starts the
measured window (counters from zero), SIGUSR2 ends it and writes ``--out``; SIGTERM stops.

A sample's latency is its arrival (Unix ms, when the fleet's MQTT thread hands the message
over) minus its metric timestamp (the bench's acquisition time): the benches and the fleet
share this machine's clock.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

from supervisor.fleet.host import FleetHost
from supervisor.fleet.state import Fleet

__all__ = ["MeasuredFleet", "main", "percentile_ms"]

DATA_VERBS = frozenset(("NDATA", "DDATA"))


class MeasuredFleet(Fleet):
    """``Fleet`` that counts, in its measured window, messages, samples and each data
    sample's latency (a histogram by whole ms: a hundred benches' samples for a minute in
    a few hundred counters)."""

    def __init__(self, group: str) -> None:
        super().__init__(group)
        self.measuring = False
        self.messages = 0
        self.samples = 0
        self.latency_ms: Counter[int] = Counter()
        self.window = (math.nan, math.nan)  # monotonic begin, end

    def _apply(self, verb: str, edge: str, device: str | None, p: Any, now_ms: int) -> bool:
        if self.measuring:
            self.messages += 1
            if verb in DATA_VERBS:
                hist = self.latency_ms
                for m in p.metrics:
                    hist[now_ms - m.timestamp] += 1
                self.samples += len(p.metrics)
        return super()._apply(verb, edge, device, p, now_ms)

    def begin(self) -> None:
        with self.lock:
            self.messages = self.samples = 0
            self.latency_ms.clear()
            self.measuring = True
            self.window = (time.monotonic(), math.nan)

    def end(self) -> None:
        """The window ends now (a signal handler: no lock, one assignment each)."""
        self.measuring = False
        self.window = (self.window[0], time.monotonic())

    def result(self) -> dict[str, Any]:
        with self.lock:
            self.measuring = False
            return {
                "window_s": self.window[1] - self.window[0],
                "messages": self.messages,
                "samples": self.samples,
                "latency_ms": sorted(self.latency_ms.items()),
                "online": sum(1 for n in self.nodes.values() if n.online),
                "rebirths": sum(n.rebirths for n in self.nodes.values()),
                "seq_gaps": sum(n.seq_gaps for n in self.nodes.values()),
            }

    def born(self) -> int:
        with self.lock:
            return sum(1 for n in self.nodes.values() if n.online and n.next_seq is not None)


def percentile_ms(hist: list[tuple[int, int]], q: float) -> float:
    """The ``q`` quantile (0–1) of a histogram [(ms, count)] sorted by ms (nearest rank)."""
    total = sum(c for _, c in hist)
    if total == 0:
        return float("nan")
    rank = max(1, round(q * total + 0.5 - 1e-9))
    seen = 0
    for ms, count in hist:
        seen += count
        if seen >= rank:
            return float(ms)
    return float(hist[-1][0])


def _write_json(path: Path, doc: dict[str, Any]) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(doc), encoding="utf-8")
    tmp.replace(path)  # the reader never sees half a file


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m supervisor.bench.fleetsink")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--group", required=True)
    p.add_argument("--status", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    fleet = MeasuredFleet(args.group)
    host = FleetHost(fleet, args.host, args.port, host_id=None)
    stop = threading.Event()
    ended = threading.Event()
    signal.signal(signal.SIGUSR1, lambda *_: fleet.begin())

    def end_window(*_: object) -> None:
        fleet.end()
        ended.set()

    signal.signal(signal.SIGUSR2, end_window)
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    host.start()
    while not stop.is_set():
        _write_json(args.status, {"connected": host.connected, "born": fleet.born()})
        if ended.is_set():
            ended.clear()
            _write_json(args.out, fleet.result())
        stop.wait(0.5)
    host.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
