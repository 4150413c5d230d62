"""Driving a scan engine on the virtual clock, one scan at a time."""

from __future__ import annotations

from supervisor.scan import ScanEngine


async def run_scans(engine: ScanEngine, count: int = 1) -> None:
    """Exactly ``count`` scans (on a virtual clock: as fast as the CPU allows)."""
    if not engine.clock.virtual:
        raise ValueError("run_scans needs an engine on a virtual clock")
    await engine.run_for(count * engine.period_s)
