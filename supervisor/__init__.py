"""Bench supervisor: a PLC-style runtime for battery cycling test benches."""

__version__ = "0.1.0"
