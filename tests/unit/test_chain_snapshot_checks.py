"""A saved chain snapshot is taken back only as ``freeze`` writes it (issue 26, finding 5):
every field of every kind checked, and a wrong one refused with the field named and what it
held — never taken for another state, step or time."""

from __future__ import annotations

import math
from dataclasses import fields
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from snapshot_cases import BAD_VALUES

from supervisor.chains.run import ChainSnapshot, RunState
from supervisor.tags.spec import shown

FIELDS = tuple(f.name for f in fields(ChainSnapshot))


def saved() -> dict[str, Any]:
    """A snapshot as a running test saves it: 2nd step of its 2nd cycle, in a group."""
    r = RunState(
        test_id="t1",
        step=1,
        cycle=2,
        step_count=5,
        t_test0=10.0,
        t_cycle0=400.0,
        t_step0=500.0,
        q0_ah=0.01,
        step_q0=0.2,
        step_e0=0.3,
        test0={"charged_ah": 0.0, "discharged_ah": 0.0, "charged_wh": 0.0, "discharged_wh": 0.0},
        cycle0={"charged_ah": 0.1, "discharged_ah": 0.0, "charged_wh": 0.1, "discharged_wh": 0.0},
        group_t0={0: 450.0},
        last_rec_t=590.0,
        last_rec_v=1.3,
        last_rec_i=-0.2,
    )
    snap = r.freeze(
        state="Running",
        recipe="cycle",
        step_id="rest",
        alarm="",
        peak_v=1.42,
        now=600.0,
        wall=1_767_254_400.0,
    )
    return snap.as_dict()


def test_every_field_of_a_snapshot_has_wrong_values_to_try() -> None:
    assert set(BAD_VALUES) == set(FIELDS)


def test_a_snapshot_as_saved_comes_back_equal() -> None:
    data = saved()
    assert ChainSnapshot.from_dict(data).as_dict() == data


@pytest.mark.parametrize(
    ("name", "bad"),
    [(name, bad) for name, values in BAD_VALUES.items() for bad in values],
    ids=lambda x: repr(x)[:24],
)
def test_a_wrong_value_of_any_field_is_refused_naming_the_field_and_the_value(
    name: str, bad: object
) -> None:
    data = saved()
    data[name] = bad
    with pytest.raises(ValueError) as info:
        ChainSnapshot.from_dict(data)
    text = str(info.value)
    assert f"field {name}" in text, text
    assert shown(bad) in text, text


def test_a_missing_or_an_unknown_field_is_refused_naming_it() -> None:
    data = saved()
    del data["cycle0"]
    with pytest.raises(ValueError, match="fields: cycle0 missing"):
        ChainSnapshot.from_dict(data)
    data = saved()
    data["speed"] = 3
    with pytest.raises(ValueError, match="fields: unknown 'speed'"):
        ChainSnapshot.from_dict(data)


JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**20), 10**20)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner),
    max_leaves=6,
)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(FIELDS), JSON)
def test_any_value_of_any_field_is_refused_or_thaws_into_a_run_with_finite_times(
    name: str, value: object
) -> None:
    data = saved()
    data[name] = value
    try:
        snap = ChainSnapshot.from_dict(data)
    except ValueError as exc:
        assert f"field {name}" in str(exc)
        return
    run, away_s = RunState.thaw(snap, now=1000.0, wall=snap.wall + 60.0)
    times = [run.t_test0, run.t_cycle0, run.t_step0, away_s, *run.group_t0.values()]
    assert all(math.isfinite(t) for t in times)
    assert run.step >= 0 and run.cycle >= 1
