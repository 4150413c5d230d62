"""The scan engine: inputs → logic → outputs → publish, at a fixed period."""

from supervisor.scan.engine import (
    InputBinding,
    LogicPhase,
    OutputBinding,
    Publisher,
    ScanEngine,
    ScanStats,
)

__all__ = ["InputBinding", "LogicPhase", "OutputBinding", "Publisher", "ScanEngine", "ScanStats"]
