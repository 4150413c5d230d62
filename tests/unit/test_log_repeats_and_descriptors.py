"""Issue 27, finding 3: repeated log lines collapsed (on a virtual clock) and the file
descriptors the connection caps may take checked against the process's limit."""

from __future__ import annotations

import logging

import pytest

from supervisor.core.clock import VirtualClock
from supervisor.core.descriptors import DescriptorBudget, NofileLimit
from supervisor.core.logrepeat import RepeatFilter


def _record(msg: str, *args: object, name: str = "asyncio") -> logging.LogRecord:
    return logging.LogRecord(name, logging.ERROR, __file__, 1, msg, args, None)


def test_one_identical_line_passes_per_window_and_the_next_says_how_many_were_suppressed() -> None:
    clock = VirtualClock()
    f = RepeatFilter(clock.now, window_s=10.0)
    passed = []
    for _ in range(71_567):  # the flood's "Too many open files" lines
        rec = _record(
            "socket.accept() out of system resource: %s", "[Errno 24] Too many open files"
        )
        if f.filter(rec):
            passed.append(rec.getMessage())
        clock.advance(0.0001)  # 7 s of virtual time in all: one window
    assert len(passed) == 1
    clock.advance(10.0)
    rec = _record("socket.accept() out of system resource: %s", "[Errno 24] Too many open files")
    assert f.filter(rec)
    assert rec.getMessage().endswith("[71566 similar lines suppressed in the last 10 s]")
    assert f.suppressed == 71_566


def test_lines_of_one_template_pass_up_to_the_burst_and_different_templates_all_pass() -> None:
    clock = VirtualClock()
    f = RepeatFilter(clock.now, window_s=10.0, burst=10)
    peers = [f.filter(_record("refusing %s", f"127.0.0.1:{p}")) for p in range(1000)]
    assert sum(peers) == 10
    # Five channels tripping at once: five texts of one template, all written.
    trips = [f.filter(_record("%s tripped", ch, name="supervisor")) for ch in "01234"]
    assert all(trips)
    # A message whose text has a percent sign and no arguments is still written as it is.
    rec = _record("100% done", name="other")
    assert f.filter(rec) and rec.getMessage() == "100% done"


def test_the_budget_names_every_owner_and_refuses_caps_over_the_soft_limit() -> None:
    budget = DescriptorBudget(listeners={"HTTP": 416, "OPC UA": 164}, devices=16)
    assert budget.needed == 416 + 164 + 16 + 64 + 64
    assert budget.problem(NofileLimit(1024, 1024, 1024)) is None
    big = DescriptorBudget(listeners={"HTTP": 4000}, devices=16)
    problem = big.problem(NofileLimit(1024, 1024, 1024))
    assert problem is not None
    assert "soft limit RLIMIT_NOFILE is 1024" in problem
    assert "HTTP 4000" in problem and "LimitNOFILE=8192" in problem


def test_a_listener_in_a_process_of_its_own_counts_against_that_process_not_the_benchs() -> None:
    """ADR 0029: OPC UA's connections are the server process's descriptors; the line
    ``supervisor run`` prints says so, and its cap alone must still fit the soft limit."""
    budget = DescriptorBudget(listeners={"HTTP": 416}, devices=16, apart={"OPC UA": 164})
    assert budget.needed == 416 + 16 + 64 + 64
    assert budget.describe() == (
        "560 (HTTP 416 + devices 16 + files 64 + margin 64); OPC UA 164 in its own process"
    )
    assert budget.problem(NofileLimit(1024, 1024, 1024)) is None
    huge = DescriptorBudget(listeners={"HTTP": 416}, apart={"OPC UA": 2000})
    assert huge.problem(NofileLimit(1024, 1024, 1024)) is not None


@pytest.mark.parametrize(("max_connections", "ok"), [(256, True), (2000, False)])
def test_supervisor_run_s_configuration_fits_under_1024_descriptors_with_the_default_caps(
    max_connections: int, ok: bool
) -> None:
    from pathlib import Path

    from supervisor.app.descriptors import descriptor_budget
    from supervisor.devices.registry import load_bench

    cfg = load_bench(Path(__file__).resolve().parents[2] / "io_maps" / "sim.yaml")
    cfg = cfg.model_copy(
        update={"hmi": cfg.hmi.model_copy(update={"max_connections": max_connections})}
    )
    assert (descriptor_budget(cfg).problem(NofileLimit(1024, 1024, 1024)) is None) is ok
