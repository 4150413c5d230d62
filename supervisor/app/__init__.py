"""Composition root: the only place that wires concrete drivers, simulators and publishers."""

from supervisor.app.bench import Bench, build_bench

__all__ = ["Bench", "build_bench"]
