"""The two transports a driver's contract tests run on: one test body, both transports.

STYLE.md "Contract tests rerunnable on hardware" (python-can): what the driver does is the
same whatever carries its requests, so it is written once and run on each transport:

- ``in-process``: the driver's transport calls the simulated unit directly, on the virtual
  clock (time only moves when the code under test or the test moves it);
- ``tcp``: the same simulated unit served on a loopback port the OS picks, the driver's real
  TCP transport, the real clock (a socket answers in wall time). Marked ``integration``:
  real protocols over loopback.

Tests marked :data:`on_both_transports` run once per transport; every other test that takes
a rig gets the in-process one (the ``transport`` fixture of tests/unit/conftest.py).
"""

from __future__ import annotations

from typing import Final

import pytest

from supervisor.core.clock import Clock, RealClock, VirtualClock

IN_PROCESS: Final = "in-process"
TCP: Final = "tcp"

on_both_transports = pytest.mark.parametrize(
    "transport", [IN_PROCESS, pytest.param(TCP, marks=pytest.mark.integration)], indirect=True
)
"""Run the marked test (or class) on the in-process transport and over loopback TCP."""


def clock_for(transport: str, virtual_clock: VirtualClock) -> Clock:
    """The virtual clock in process; the real clock over TCP (nothing on the virtual clock
    may wait for a socket: time would not move while it waits)."""
    if transport == IN_PROCESS:
        return virtual_clock
    if transport == TCP:
        return RealClock()
    raise ValueError(f"unknown transport {transport!r}: {IN_PROCESS!r} or {TCP!r}")
