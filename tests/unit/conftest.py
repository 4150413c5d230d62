"""Fixtures for the unit tests: which transport a driver rig is built on."""

from __future__ import annotations

import pytest
from rig_transports import IN_PROCESS


@pytest.fixture
def transport(request: pytest.FixtureRequest) -> str:
    """``in-process`` unless the test is marked ``on_both_transports`` (then each in turn)."""
    return str(getattr(request, "param", IN_PROCESS))
