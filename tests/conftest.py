"""Shared fixtures: every test runs on loopback and leaves no task behind."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# Virtual clock, no leftover tasks: the project's own test helpers.
pytest_plugins = ["supervisor.testing.plugin", "influxrig"]


@pytest.fixture
def root() -> Path:
    return ROOT
