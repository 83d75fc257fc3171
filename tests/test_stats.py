"""Latency statistics: exact counts and maxima, percentiles within 1%."""

import random

from hypothesis import given
from hypothesis import strategies as st

from whiztap.analyzer.protocol.stats import LatencyStats


def exact_percentile(values, p):
    ordered = sorted(values)
    return ordered[max(1, round(p / 100 * len(ordered))) - 1]


@given(st.lists(st.integers(0, 10**11), min_size=1, max_size=300), st.sampled_from([50, 95, 99, 100]),
       st.integers(1, 50))
def test_percentiles_within_one_percent(values, p, batch):
    """Added one by one or in batches (as the session adds a read's answers)."""
    singly, batched = LatencyStats(), LatencyStats()
    for v in values:
        singly.add(v)
    for i in range(0, len(values), batch):
        batched.add_many(values[i:i + batch])
    exact = exact_percentile(values, p)
    for stats in (singly, batched):
        assert abs(stats.percentile(p) - exact) <= max(1, exact // 100)
        assert (stats.count, stats.total, stats.min, stats.max) == (len(values), sum(values), min(values), max(values))
    assert batched.histogram() == singly.histogram()


def test_merge_equals_adding_everything():
    rng = random.Random(7)
    values = [rng.randrange(10**9) for _ in range(1000)]
    one, a, b = LatencyStats(), LatencyStats(), LatencyStats()
    for i, v in enumerate(values):
        one.add(v)
        (a if i % 2 else b).add(v)
    a.merge(b)
    assert (a.count, a.total, a.max, a.histogram()) == (one.count, one.total, one.max, one.histogram())


def test_memory_is_bounded_by_buckets_not_values():
    stats = LatencyStats()
    for v in range(1_000, 2_000_000, 7):
        stats.add(v)
    assert len(stats.histogram()) < 2000 < stats.count


def test_empty():
    assert LatencyStats().percentile(99) == 0
