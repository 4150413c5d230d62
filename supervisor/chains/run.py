"""What one test run has to remember between scans (and to resume after a hold)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field


@dataclass
class RunState:
    """Everything that matters to resume a test (persisted by the safety layer later)."""

    test_id: str = ""
    step: int = 0
    cycle: int = 1
    step_count: int = 0
    t_test0: float = 0.0
    t_cycle0: float = 0.0
    t_step0: float = 0.0
    held_since: float | None = None
    q0_ah: float = 0.0  # channel counters at test start
    step_q0: float = 0.0
    step_e0: float = 0.0
    test0: dict[str, float] = field(default_factory=dict)  # counters at test start
    cycle0: dict[str, float] = field(default_factory=dict)  # counters at cycle start
    sleep_until_t: float | None = None
    sleep_then: int | None = None  # step index after a sleep action
    group_t0: dict[int, float] = field(default_factory=dict)
    last_rec_t: float = -math.inf
    last_rec_v: float | None = None
    last_rec_i: float | None = None
    end_reason: str = ""
    # The step activation (its step count) whose step-time supervision was acknowledged.
    max_time_acked: int = -1
