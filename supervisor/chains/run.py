"""What one test run has to remember between scans (and to resume after a hold or a
restart).

``RunState`` holds times on the running process's monotonic axis (``Clock.now()``); a
``ChainSnapshot`` holds the same state with every time relative to the moment it was
taken, plus that moment's Unix time, so that another process (after a crash or a
restart, docs/design.md "Safety", seed 001's context save) can put it back on its own axis.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any

from supervisor.chains.states import State
from supervisor.tags.spec import shown

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
        fmt = data.get("format")
        if type(fmt) is not int or fmt != SNAPSHOT_FORMAT:  # first: other fields, other meaning
            raise ValueError(
                f"chain snapshot field format: format {shown(fmt)}, expected {SNAPSHOT_FORMAT}"
            )
        # Every field checked before any is used (issue 26, finding 5: a state edited to
        # "Xunning" was taken for an ended test and closed it as complete, silently): a
        # field unknown, missing or not what ``freeze`` writes refuses the whole snapshot,
        # naming the field and what was received.
        unknown = sorted(set(data) - set(_SNAPSHOT_FIELDS))
        if unknown:
            raise ValueError(f"chain snapshot fields: unknown {', '.join(map(repr, unknown))}")
        missing = [name for name in _SNAPSHOT_FIELDS if name not in data]
        if missing:
            raise ValueError(f"chain snapshot fields: {', '.join(missing)} missing")
        for name, (ok, expected) in _SNAPSHOT_CHECKS.items():
            value = data[name]
            if not ok(value):
                raise ValueError(f"chain snapshot field {name}: {shown(value)} is not {expected}")
        return cls(**data)


_SNAPSHOT_FIELDS = tuple(f.name for f in fields(ChainSnapshot))
_SNAPSHOT_DICTS = ("group_time_s", "test0", "cycle0")
"""The fields of a snapshot that are dicts (copied by ``as_dict``, as ``asdict`` does)."""

STATES = tuple(s.value for s in State)
COUNTER_NAMES = ("charged_ah", "discharged_ah", "charged_wh", "discharged_wh")
"""The keys of ``test0`` / ``cycle0`` (``ChannelPort.counters``)."""
TEXT_MAX_CHARS = 4096
"""A saved text longer than this was not written by ``freeze`` (names, reasons, alarms)."""


def _int(x: object, low: int) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and x >= low


def _number(x: object, low: float = -math.inf) -> bool:
    """A finite number (a boolean is not one), at least ``low``."""
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) and x >= low


def _text(x: object) -> bool:
    return isinstance(x, str) and len(x) <= TEXT_MAX_CHARS and "\x00" not in x


def _name(x: object) -> bool:
    """One line of text (a test id names a folder, a step id a step)."""
    return _text(x) and isinstance(x, str) and x.isprintable()


def _counters(x: object) -> bool:
    return (
        isinstance(x, dict)
        and set(x) <= set(COUNTER_NAMES)
        and all(_number(v, 0.0) for v in x.values())
    )


def _group_times(x: object) -> bool:
    return isinstance(x, dict) and all(
        isinstance(k, str) and k.isdigit() and len(k) <= 6 and _number(v, 0.0) for k, v in x.items()
    )


_SNAPSHOT_CHECKS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "format": (lambda x: type(x) is int and x == SNAPSHOT_FORMAT, f"format {SNAPSHOT_FORMAT}"),
    "state": (lambda x: x in STATES, f"an ISA-88 state ({', '.join(STATES)})"),
    "recipe": (_name, "a recipe name (one line of text)"),
    "test_id": (_name, "a test id (one line of text)"),
    "step": (lambda x: _int(x, 0), "a step index (an integer >= 0)"),
    "step_id": (_name, "a step id (one line of text)"),
    "cycle": (lambda x: _int(x, 1), "a cycle number (an integer >= 1)"),
    "step_count": (lambda x: _int(x, 0), "a count of steps started (an integer >= 0)"),
    "test_time_s": (lambda x: _number(x, 0.0), "a time in s (a finite number >= 0)"),
    "cycle_time_s": (lambda x: _number(x, 0.0), "a time in s (a finite number >= 0)"),
    "step_time_s": (lambda x: _number(x, 0.0), "a time in s (a finite number >= 0)"),
    "group_time_s": (_group_times, "group index -> time in s (finite numbers >= 0)"),
    "sleep_until_wall": (
        lambda x: x is None or _number(x, 0.0),
        "null or a Unix time (a finite number >= 0)",
    ),
    "sleep_then": (lambda x: x is None or _int(x, 0), "null or a step index (an integer >= 0)"),
    "q0_ah": (_number, "a charge in Ah (a finite number)"),
    "step_q0_ah": (_number, "a charge in Ah (a finite number)"),
    "step_e0_wh": (_number, "an energy in Wh (a finite number)"),
    "test0": (_counters, f"counters ({', '.join(COUNTER_NAMES)}: finite numbers >= 0)"),
    "cycle0": (_counters, f"counters ({', '.join(COUNTER_NAMES)}: finite numbers >= 0)"),
    "since_record_s": (
        lambda x: x is None or _number(x, 0.0),
        "null or a time in s (a finite number >= 0)",
    ),
    "last_rec_v": (lambda x: x is None or _number(x), "null or a voltage (a finite number)"),
    "last_rec_i": (lambda x: x is None or _number(x), "null or a current (a finite number)"),
    "end_reason": (_text, "a text"),
    "max_time_acked": (lambda x: isinstance(x, bool), "true or false"),
    "alarm": (_text, "a text"),
    "peak_v": (lambda x: x is None or _number(x), "null or a voltage (a finite number)"),
    "wall": (lambda x: _number(x, 0.0), "a Unix time (a finite number >= 0)"),
}
"""What each field of a saved snapshot must be (``freeze`` writes nothing else)."""
assert set(_SNAPSHOT_CHECKS) == set(_SNAPSHOT_FIELDS), "every snapshot field has its check"
