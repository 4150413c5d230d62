"""What one test run has to remember between scans (and to resume after a hold or a
restart).

``RunState`` holds times on the running process's monotonic axis (``Clock.now()``); a
``ChainSnapshot`` holds the same state with every time relative to the moment it was
taken, plus that moment's Unix time, so that another process (after a crash or a
restart, DESIGN.md "Safety", seed 001's context save) can put it back on its own axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

SNAPSHOT_FORMAT = 1
"""Version of ``ChainSnapshot.as_dict``; a stored snapshot of another version is refused."""


@dataclass
class RunState:
    """Everything that matters to resume a test (``snapshot`` / ``restore``)."""

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

    def freeze(
        self,
        *,
        state: str,
        recipe: str,
        step_id: str,
        alarm: str,
        peak_v: float | None,
        now: float,
        wall: float,
        to_wall: float | None = None,
    ) -> ChainSnapshot:
        """This run at ``now`` (Unix time ``wall``); ``to_wall``: the Unix time of a
        pending sleep's wake-up (None when no sleep is pending)."""
        # A held step's time stands still (ADR 0004): it is the time it had when held.
        frozen = self.held_since if self.held_since is not None else now
        return ChainSnapshot(
            state=state,
            recipe=recipe,
            test_id=self.test_id,
            step=self.step,
            step_id=step_id,
            cycle=self.cycle,
            step_count=self.step_count,
            test_time_s=now - self.t_test0,
            cycle_time_s=now - self.t_cycle0,
            step_time_s=max(0.0, frozen - self.t_step0),
            group_time_s={str(g): max(0.0, frozen - t0) for g, t0 in self.group_t0.items()},
            sleep_until_wall=to_wall,
            sleep_then=self.sleep_then,
            q0_ah=self.q0_ah,
            step_q0_ah=self.step_q0,
            step_e0_wh=self.step_e0,
            test0=dict(self.test0),
            cycle0=dict(self.cycle0),
            since_record_s=(now - self.last_rec_t) if math.isfinite(self.last_rec_t) else None,
            last_rec_v=self.last_rec_v,
            last_rec_i=self.last_rec_i,
            end_reason=self.end_reason,
            max_time_acked=self.max_time_acked == self.step_count,
            alarm=alarm,
            peak_v=peak_v,
            wall=wall,
        )

    @classmethod
    def thaw(cls, snap: ChainSnapshot, now: float, wall: float) -> tuple[RunState, float]:
        """The run of ``snap`` on this process's axis at ``now`` (Unix time ``wall``),
        held from ``now``; and the time the test was away (s, from the Unix times).

        The time away counts as test and cycle time (a hold does too) but not as step
        time: the step resumes where it was saved, as after a hold.
        """
        away_s = max(0.0, wall - snap.wall)
        return (
            cls(
                test_id=snap.test_id,
                step=snap.step,
                cycle=snap.cycle,
                step_count=snap.step_count,
                t_test0=now - (snap.test_time_s + away_s),
                t_cycle0=now - (snap.cycle_time_s + away_s),
                t_step0=now - snap.step_time_s,
                held_since=now,
                q0_ah=snap.q0_ah,
                step_q0=snap.step_q0_ah,
                step_e0=snap.step_e0_wh,
                test0=dict(snap.test0),
                cycle0=dict(snap.cycle0),
                sleep_until_t=(
                    None if snap.sleep_until_wall is None else now + snap.sleep_until_wall - wall
                ),
                sleep_then=snap.sleep_then,
                group_t0={int(g): now - s for g, s in snap.group_time_s.items()},
                last_rec_t=(
                    -math.inf
                    if snap.since_record_s is None
                    else now - (snap.since_record_s + away_s)
                ),
                last_rec_v=snap.last_rec_v,
                last_rec_i=snap.last_rec_i,
                end_reason=snap.end_reason,
                max_time_acked=snap.step_count if snap.max_time_acked else -1,
            ),
            away_s,
        )


@dataclass(frozen=True)
class ChainSnapshot:
    """A chain's test as a restart needs it (plain data; ``as_dict`` is JSON-ready).

    Times are relative to the save (``wall``, Unix time): ``test_time_s`` and
    ``cycle_time_s`` run on through holds, ``step_time_s`` and ``group_time_s`` exclude
    them; a pending sleep keeps its wall-clock wake-up (``sleep_until_wall``).
    """

    state: str  # the chain's ISA-88 state (``State`` value)
    recipe: str  # the program's name (for messages)
    test_id: str
    step: int  # step index
    step_id: str
    cycle: int
    step_count: int
    test_time_s: float
    cycle_time_s: float
    step_time_s: float
    group_time_s: dict[str, float]  # group index (as text, JSON keys) -> time in it
    sleep_until_wall: float | None
    sleep_then: int | None
    q0_ah: float  # counter baselines: at test start, at step start
    step_q0_ah: float
    step_e0_wh: float
    test0: dict[str, float]  # charged/discharged Ah and Wh at test start
    cycle0: dict[str, float]  # the same at cycle start
    since_record_s: float | None  # since the last result record (None: none yet)
    last_rec_v: float | None
    last_rec_i: float | None
    end_reason: str
    max_time_acked: bool  # the step's time supervision was acknowledged
    alarm: str  # the chain's latched alarm ("" when none)
    peak_v: float | None  # voltage peak since the step started (−ΔV detection)
    wall: float  # Unix time of the save
    format: int = SNAPSHOT_FORMAT

    def as_dict(self) -> dict[str, Any]:
        """``dataclasses.asdict(self)`` without its recursion (every field is a plain value
        or a dict of plain values): the retained state saves it at each result record."""
        out = {name: getattr(self, name) for name in _SNAPSHOT_FIELDS}
        for name in _SNAPSHOT_DICTS:
            out[name] = dict(out[name])
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ChainSnapshot:
        """The snapshot of ``as_dict``; ValueError when the format or a field is wrong."""
        if not isinstance(data, dict):
            raise ValueError("a chain snapshot is a mapping")
        if data.get("format") != SNAPSHOT_FORMAT:
            raise ValueError(
                f"chain snapshot format {data.get('format')!r}, expected {SNAPSHOT_FORMAT}"
            )
        try:
            return cls(**data)
        except TypeError as exc:
            raise ValueError(f"chain snapshot fields: {exc}") from None


_SNAPSHOT_FIELDS = tuple(f.name for f in fields(ChainSnapshot))
_SNAPSHOT_DICTS = ("group_time_s", "test0", "cycle0")
"""The fields of a snapshot that are dicts (copied by ``as_dict``, as ``asdict`` does)."""
