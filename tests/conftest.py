"""Shared fixtures: every test runs on loopback and leaves no task behind."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import settings

from supervisor.core.encoding import storable_text

ROOT = Path(__file__).resolve().parent.parent

# Virtual clock, no leftover tasks: the project's own test helpers.
pytest_plugins = ["supervisor.testing.plugin", "influxrig"]

# No wall-clock deadline for a hypothesis example: it is a timing assertion, and a loaded
# machine made one fail (976 ms against 200 ms, a line fit). A hang is pytest-timeout's.
settings.register_profile("bench-supervisor", deadline=None)
settings.load_profile("bench-supervisor")


@pytest.fixture
def root() -> Path:
    return ROOT


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> object:
    """A report that quotes a lone surrogate (issue 28's tests send them on purpose; the
    product logs its refusals) is made storable as the product stores such text
    (``\\udXXX``): the report goes to the terminal, a JUnit file or another process
    (pytest-xdist's workers), none of which can encode it."""
    report = yield
    sections = getattr(report, "sections", None)
    if sections:
        report.sections = [(title, storable_text(text)) for title, text in sections]
    longrepr = getattr(report, "longrepr", None)
    if longrepr is not None and storable_text(str(longrepr)) != str(longrepr):
        report.longrepr = storable_text(str(longrepr))
    return report
