"""Simulated benches for ``supervisor bench fleet``: one process hosting several edge nodes,
each the real ``SparkplugPublisher`` (its thread, its paho connection) over a synthetic tag
database whose every tag changes once a second.

``python -m supervisor.bench.fleetnodes --port P --group G --first K --count N --tags T
--seconds S``: benches ``bench-K`` … ``bench-(K+N-1)``; their tags spread over
``CHANNELS`` channels (one DDATA per channel and second). The benches' seconds are spread
over the second (bench ``k`` at ``k / N`` of it): a lab's benches do not scan in step, and
all of them at once would measure a burst no lab makes.
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
import time
from dataclasses import dataclass
from typing import Final

from supervisor.core.clock import RealClock
from supervisor.publish.sparkplug.publisher import SparkplugPublisher, SparkplugSettings
from supervisor.tags import Tag, TagDB, TagSpec

__all__ = ["CHANNELS", "SimBench", "main", "sim_bench"]

CHANNELS: Final = 4


@dataclass
class SimBench:
    db: TagDB
    tags: list[Tag]
    publisher: SparkplugPublisher

    def tick(self, clock: RealClock, k: int) -> None:
        """Every tag a new value, sampled now; the scan's end (``on_scan``)."""
        t = clock.now()
        db = self.db
        db.set_scan_time(t)
        for n, tag in enumerate(self.tags):
            db.update(tag, math.sin(k * 0.1 + n) * 4.0 + k * 1e-6)
        self.publisher.on_scan(db, t)


def sim_bench(name: str, tags: int, host: str, port: int, group: str, clock: RealClock) -> SimBench:
    """A bench of ``tags`` float tags over ``CHANNELS`` channels, its edge node built."""
    db = TagDB()
    channels = [f"ch{c + 1}" for c in range(CHANNELS)]
    made = [
        db.add(TagSpec(f"{channels[n % CHANNELS]}.m{n:03d}", "float", unit="V"))
        for n in range(tags)
    ]
    settings = SparkplugSettings(host, port, group, name, spool_max_bytes=0)
    publisher = SparkplugPublisher(db, clock, settings, channels=channels, devices=[])
    return SimBench(db, made, publisher)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m supervisor.bench.fleetnodes")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--group", required=True)
    p.add_argument("--first", type=int, default=0)
    p.add_argument("--count", type=int, required=True)
    p.add_argument("--total", type=int, default=0, help="benches of the whole run (phases)")
    p.add_argument("--tags", type=int, default=100)
    p.add_argument("--seconds", type=float, required=True)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    stopping = False

    def stop(*_: object) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGTERM, stop)
    clock = RealClock()
    benches = [
        sim_bench(f"bench-{args.first + j:03d}", args.tags, args.host, args.port, args.group, clock)
        for j in range(args.count)
    ]
    for b in benches:
        b.publisher.start()
    total = max(args.total, args.first + args.count)
    # (next time, bench) in phase order: bench k at k/total of each second.
    start = time.monotonic() + 1.0
    due = [start + (args.first + j) / total for j in range(args.count)]
    k = 0
    end = start + args.seconds
    while not stopping and time.monotonic() < end:
        j = min(range(len(due)), key=due.__getitem__)
        delay = due[j] - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        benches[j].tick(clock, k)
        due[j] += 1.0
        k += 1
    for b in benches:
        b.publisher.close(timeout_s=2.0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
