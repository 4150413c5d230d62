"""``supervisor bench memory``: resident memory of ``supervisor run`` on the simulated bench.

``supervisor run`` on a copy of io_maps/sim.yaml (free ports, a temporary state folder:
historian and OPC UA on as shipped) with benchmarks/load-cycle.yaml started on every
channel. ``VmRSS`` is read from ``/proc/<pid>/status`` every ``SAMPLE_S``; printed: the
value at start-up (the reference), after the run, and the growth per 10 minutes after the
warm-up (least-squares slope of the samples after it: a steady leak shows as a slope, the
start-up's allocations and the first full collections do not).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

from supervisor.app import benchreport
from supervisor.app.benchrun import Supervisor, prepare, recipe_args

SIM_MAP = Path("io_maps/sim.yaml")
RECIPE = Path("benchmarks/load-cycle.yaml")
SAMPLE_S = 10.0


def _say(msg: str) -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()


def slope_per_s(points: list[tuple[float, float]]) -> float:
    """Least-squares slope of (t, y); 0 for fewer than two points."""
    if len(points) < 2:
        return 0.0
    n = len(points)
    mt = sum(t for t, _ in points) / n
    my = sum(y for _, y in points) / n
    var = sum((t - mt) ** 2 for t, _ in points)
    if var == 0:
        return 0.0
    return sum((t - mt) * (y - my) for t, y in points) / var


def memory_benchmark(
    minutes: float = 30.0,
    warmup_s: float | None = None,
    sample_s: float = SAMPLE_S,
    io_map: Path = SIM_MAP,
    recipe: Path = RECIPE,
) -> int:
    from supervisor.devices.registry import load_bench

    total_s = minutes * 60.0
    warm = min(300.0, total_s / 3) if warmup_s is None else warmup_s
    cfg = load_bench(io_map)
    channels = [c.name for c in cfg.channels]
    samples: list[tuple[float, float]] = []  # (s since ready, MiB)
    with tempfile.TemporaryDirectory(prefix="bench-memory-") as tmp:
        root = Path(tmp)
        copy, http_port, _ = prepare(io_map, root)
        sup = Supervisor(copy, http_port, recipe_args(channels, recipe), root / "run.log")
        try:
            sup.wait_ready()
            t0 = time.monotonic()
            while True:
                t = time.monotonic() - t0
                samples.append((t, sup.rss_kib() / 1024))
                if t >= total_s:
                    break
                time.sleep(min(sample_s, max(0.0, total_s - t)))
        finally:
            code = sup.stop()
            if code != 0:
                _say(f"  supervisor run exited with {code}: {sup.tail()}")
    start_mib, end_mib = samples[0][1], samples[-1][1]
    after = [p for p in samples if p[0] >= warm]
    growth = slope_per_s(after) * 600.0
    cmd = f"supervisor bench memory --minutes {minutes:g}"
    _say(
        f"memory benchmark: supervisor run {io_map} ({len(channels)} channels, recipes on all),"
        f" VmRSS every {sample_s:g} s for {minutes:g} min, warm-up {warm:g} s"
    )
    _say(
        f"  at start-up {start_mib:.1f} MiB (reference), peak {max(y for _, y in samples):.1f} MiB"
    )
    _say(f"  after {minutes:g} min {end_mib:.1f} MiB (target ≤ 150 MB)")
    _say(
        f"  growth after the warm-up {growth:+.2f} MiB per 10 min over {len(after)} samples"
        f" (target ≤ 1 MB per 10 min)"
    )
    benchreport.record(
        f"RSS of supervisor run (sim bench, recipes) after {minutes:g} min",
        end_mib,
        "MiB",
        "<= 150",
        f"{start_mib:.1f} MiB at start-up",
        cmd,
    )
    benchreport.record(
        f"RSS growth per 10 min after {warm:g} s warm-up ({minutes:g} min run)",
        growth,
        "MiB",
        "<= 1",
        f"{len(after)} samples every {sample_s:g} s",
        cmd,
    )
    return 0
