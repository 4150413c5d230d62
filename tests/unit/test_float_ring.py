"""The scan's statistics windows hold the latest values like a bounded deque, in memory
allocated once (issue 13: the deques of Python floats grew for the first 17 minutes)."""

from __future__ import annotations

import sys
from collections import deque

import pytest
from hypothesis import given
from hypothesis import strategies as st

from supervisor.core.ring import FloatRing
from supervisor.scan.engine import ScanStats

floats = st.floats(allow_nan=False, allow_infinity=False, width=64)


@given(st.integers(min_value=1, max_value=50), st.lists(floats, max_size=200))
def test_a_ring_reads_as_a_bounded_deque_of_the_same_values(
    maxlen: int, values: list[float]
) -> None:
    ring, reference = FloatRing(maxlen), deque[float](maxlen=maxlen)
    for v in values:
        ring.append(v)
        reference.append(v)
    assert list(ring) == list(reference)
    assert len(ring) == len(reference)
    for i in range(-len(reference), len(reference)):
        assert ring[i] == reference[i]
    with pytest.raises(IndexError):
        ring[len(reference)]


def test_the_window_takes_its_memory_at_once_and_keeps_it() -> None:
    ring = FloatRing(10_000)
    before = sys.getsizeof(ring._data)
    for i in range(25_000):
        ring.append(i * 1e-6)
    assert sys.getsizeof(ring._data) == before
    assert ring[-1] == pytest.approx(24_999e-6) and len(ring) == 10_000


def test_the_percentiles_of_a_window() -> None:
    stats = ScanStats()
    assert ScanStats.percentile(stats.durations_s, 99) == 0.0
    for i in range(1, 101):
        stats.durations_s.append(i / 1000)
    assert ScanStats.percentile(stats.durations_s, 50) == pytest.approx(0.050, abs=0.001)
    assert ScanStats.percentile(stats.durations_s, 99) == pytest.approx(0.099)
