"""The scan engine: inputs → logic → outputs → publish, at a fixed period."""

from supervisor.scan.engine import (
    InputBinding,
    LogicPhase,
    OutputBinding,
    Publisher,
    ScanEngine,
    ScanStats,
)
from supervisor.scan.phases import ScanPhases

__all__ = [
    "InputBinding",
    "LogicPhase",
    "OutputBinding",
    "Publisher",
    "ScanEngine",
    "ScanPhases",
    "ScanStats",
]
