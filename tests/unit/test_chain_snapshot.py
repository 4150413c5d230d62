"""A chain's run as a restart needs it: ``RunState.freeze`` / ``RunState.thaw`` and the
``ChainSnapshot`` document. Times on one process's monotonic axis mean nothing to the
next process: a snapshot keeps durations and the Unix time of the save."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest

from supervisor.app.retained import RecipeSource
from supervisor.chains.run import SNAPSHOT_FORMAT, ChainSnapshot, RunState

WALL = 1_767_254_400.0


def running(now: float = 1000.0) -> RunState:
    return RunState(
        test_id="t1",
        step=2,
        cycle=3,
        step_count=9,
        t_test0=now - 500.0,
        t_cycle0=now - 200.0,
        t_step0=now - 40.0,
        q0_ah=0.1,
        step_q0=0.4,
        step_e0=0.5,
        test0={"charged_ah": 0.1},
        cycle0={"charged_ah": 0.3},
        group_t0={1: now - 60.0},
        last_rec_t=now - 4.0,
        last_rec_v=1.3,
        end_reason="",
        max_time_acked=9,
    )


def freeze(r: RunState, now: float = 1000.0, **kw: object) -> ChainSnapshot:
    args: dict[str, object] = {
        "state": "Running",
        "recipe": "r",
        "step_id": "pulse",
        "alarm": "",
        "peak_v": 1.45,
        "now": now,
        "wall": WALL,
    }
    args.update(kw)
    return r.freeze(**args)  # type: ignore[arg-type]


def test_a_snapshot_keeps_durations_and_the_unix_time_of_the_save() -> None:
    s = freeze(running())
    assert (s.test_time_s, s.cycle_time_s, s.step_time_s) == (500.0, 200.0, 40.0)
    assert s.group_time_s == {"1": 60.0} and s.since_record_s == 4.0
    assert s.wall == WALL and s.max_time_acked is True and s.format == SNAPSHOT_FORMAT


def test_a_held_steps_time_is_the_time_it_had_when_held() -> None:
    r = running()
    r.held_since = 1000.0 - 15.0  # held 15 s ago
    s = freeze(r, state="Held")
    assert s.step_time_s == 25.0 and s.group_time_s == {"1": 45.0}
    assert s.test_time_s == 500.0  # test time runs on through a hold


def test_thawed_on_another_axis_the_time_away_is_test_time_but_not_step_time() -> None:
    s = freeze(running())
    r, away = RunState.thaw(s, now=7.0, wall=WALL + 120.0)
    assert away == 120.0
    assert 7.0 - r.t_test0 == 620.0 and 7.0 - r.t_cycle0 == 320.0
    assert 7.0 - r.t_step0 == 40.0 and r.held_since == 7.0  # held from the restart
    assert r.group_t0 == {1: 7.0 - 60.0}
    assert 7.0 - r.last_rec_t == 124.0
    assert (r.step, r.cycle, r.step_count, r.q0_ah, r.step_q0) == (2, 3, 9, 0.1, 0.4)
    assert r.test0 == {"charged_ah": 0.1} and r.cycle0 == {"charged_ah": 0.3}
    assert r.max_time_acked == 9


def test_a_pending_sleep_keeps_its_wall_clock_wake_up() -> None:
    s = freeze(running(), to_wall=WALL + 3600.0)
    r, _ = RunState.thaw(s, now=0.0, wall=WALL + 600.0)
    assert r.sleep_until_t == 3000.0


def test_a_clock_that_went_backwards_counts_no_time_away() -> None:
    _, away = RunState.thaw(freeze(running()), now=0.0, wall=WALL - 50.0)
    assert away == 0.0


def test_a_run_without_a_record_yet_has_none_to_restore() -> None:
    r = running()
    r.last_rec_t = -math.inf
    s = freeze(r)
    assert s.since_record_s is None
    assert RunState.thaw(s, 0.0, WALL)[0].last_rec_t == -math.inf


def test_the_document_goes_through_json_and_refuses_another_format() -> None:
    s = freeze(running())
    again = ChainSnapshot.from_dict(json.loads(json.dumps(s.as_dict())))
    assert again == s
    with pytest.raises(ValueError, match="format 0, expected 1"):
        ChainSnapshot.from_dict({**s.as_dict(), "format": 0})
    with pytest.raises(ValueError, match="fields"):
        ChainSnapshot.from_dict({"format": SNAPSHOT_FORMAT, "state": "Running"})


def test_the_document_is_the_snapshots_fields_with_dicts_of_its_own() -> None:
    s = freeze(running())
    doc = s.as_dict()
    assert doc == dataclasses.asdict(s)
    for name in ("group_time_s", "test0", "cycle0"):
        assert doc[name] == getattr(s, name) and doc[name] is not getattr(s, name)
    # Every dict-valued field is copied: a field added later must be named there too.
    assert {f.name for f in dataclasses.fields(s) if isinstance(getattr(s, f.name), dict)} == {
        "group_time_s",
        "test0",
        "cycle0",
    }


def test_the_recipe_source_document_is_its_fields() -> None:
    src = RecipeSource("recipes/x.yaml", "recipe: x\n", {"i": "1 A"}, "var/results/t1")
    doc = src.as_dict()
    assert doc == dataclasses.asdict(src) and doc["parameters"] is not src.parameters
    assert RecipeSource.from_dict(doc) == src
