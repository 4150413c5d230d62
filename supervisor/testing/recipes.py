"""What the tests check a shipped recipe against: a bench's tags, no channel.

A shipped recipe may name bench tags in its conditions (the seed 002 pack's recipes:
``bms.cell_max``); it is checked as ``supervisor check io_maps/sim.yaml RECIPE`` and the
Recipes screen check it: against the tags of the bench, without a channel's limits.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Final

from supervisor.app.bench import build_bench
from supervisor.chains.compiler import Target
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import load_bench

RECIPES_MAP: Final = Path(__file__).resolve().parents[2] / "io_maps" / "sim.yaml"
"""The bench whose tags the shipped recipes name (the simulated seed 002 bench)."""


@cache
def bench_tags(io_map: Path = RECIPES_MAP) -> Target:
    """A target with ``io_map``'s tags and nothing else (no channel, no limits)."""
    bench = build_bench(load_bench(io_map), VirtualClock(), simulate=False)
    return Target(tags=bench.tag_dims())
