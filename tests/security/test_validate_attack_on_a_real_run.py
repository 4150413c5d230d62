"""Issue 28, finding 2: recipe texts a viewer posts to ``/api/recipes/validate`` that take
longer than the check's deadline are refused, and the checks are really stopped — against a
real ``supervisor run`` of the simulated bench (login on, a test running on ch0).

Before, each check ran in a thread of the supervisor: answered 503 at its time limit, it
ran on (CPU, memory, the scan's lock) and delayed the shutdown. Now each runs in a child
process with a deadline and a memory limit, killed when given up on.

The texts are slow without any trick (700 KB of valid recipe: seconds to check on any
machine) and the deadline is made short through the I/O map (``recipes.check_timeout_s``),
so the test holds whatever the loader learns about aliases. Wall time (real processes);
waits are bounded, nothing asserts a duration.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from supervisor.bench.flood import (
    CHANNEL,
    OPERATOR,
    Client,
    Supervisor,
    add_user,
    bench_run,
    start_test,
    tag,
    wait_ready,
)
from supervisor.bench.validate import (
    VIEWER,
    check_processes,
    gone,
    idle_check_processes,
    post_at_once,
    sigterm,
    slow_text,
    vm_rss_bytes,
)

# It asserts the scan kept its timing (no stall, no overrun) under load it makes itself:
# it runs alone, after the tests that run in parallel (Makefile: the "quiet" marker).
pytestmark = [pytest.mark.integration, pytest.mark.quiet]

WORKERS = 2
RSS_TOLERANCE_BYTES = 50 * 1024 * 1024
"""The issue's target: the supervisor's memory back within 50 MB."""


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Supervisor, Client]]:
    folder = tmp_path_factory.mktemp("validate-attack")
    # A deadline several times shorter than a check of slow_text() (2.8 s of CPU on the
    # development machine; once 3 s here, and a quiet machine answered 200 within it).
    recipes = {"check_timeout_s": 0.4, "check_workers": WORKERS}
    # A header timeout shorter than the checks: a connection whose request is being
    # answered is not cut off (its body's last bytes once started the timer).
    with bench_run(folder, {"header_timeout_s": 0.2}, recipes=recipes) as sup:
        add_user(folder / "flood.yaml", *VIEWER, role="viewer")
        op = Client(sup.host, sup.http_port)
        status, body = op.call("POST", "/api/login", {"user": OPERATOR[0], "password": OPERATOR[1]})
        assert status == 200, body
        wait_ready(op)
        start_test(op)
        yield sup, op
        op.close()


def test_slow_checks_by_a_viewer_are_refused_killed_and_cost_the_scan_nothing(
    run: tuple[Supervisor, Client],
) -> None:
    sup, op = run
    ready = idle_check_processes(sup.proc.pid, WORKERS)  # waiting for a job each
    stalls = tag(op, "scan.stalls")
    rss_before = vm_rss_bytes(sup.proc.pid)

    answers = post_at_once(sup, slow_text(), posts=3)

    # Each answered (none cut off), refused in words: 503 past the deadline (or 413 past
    # the memory limit).
    assert len(answers) == 3
    for a in answers:
        assert a.status in (413, 503) and "validating" in a.reason, a
        assert "took more than 0.4 s; stopped" in a.reason or "needs more than" in a.reason, a
    # The processes that took the checks are gone (killed), none is left computing, and
    # the ones now waiting are new.
    assert all(gone(p) for p in ready), check_processes(sup.proc.pid)
    now_ready = idle_check_processes(sup.proc.pid, WORKERS)
    assert not now_ready & ready
    # The scan never stalled; the supervisor's memory did not grow with the checks.
    assert tag(op, "scan.stalls") == stalls
    assert vm_rss_bytes(sup.proc.pid) - rss_before < RSS_TOLERANCE_BYTES
    assert tag(op, f"{CHANNEL}.chain.state") == "Running"


def test_sigterm_exits_with_every_output_safe_and_no_check_process_left(
    run: tuple[Supervisor, Client],
) -> None:
    sup, _ = run
    waiting = idle_check_processes(sup.proc.pid, WORKERS)
    _, code, out = sigterm(sup)
    assert code == 0, out
    assert "stopped: all outputs safe" in out
    assert all(gone(p) for p in waiting)  # the waiting checks end with it
