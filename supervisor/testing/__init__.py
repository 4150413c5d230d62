"""Test helpers shared by the project's tests (and by tests run against real hardware).

Runtime code never imports this package (an import-linter contract says so). The pytest
fixtures are in :mod:`supervisor.testing.plugin` (``pytest_plugins`` in tests/conftest.py).
"""

from supervisor.testing.drivers import RecordingDriver
from supervisor.testing.ports import free_tcp_port
from supervisor.testing.scans import run_scans
from supervisor.testing.waiting import wait_until

__all__ = ["RecordingDriver", "free_tcp_port", "run_scans", "wait_until"]
