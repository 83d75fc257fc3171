"""Latency statistics in bounded memory.

A live proxy runs for days and a recording may hold millions of requests, so
latencies are not kept one by one: each goes into a log-scale bucket
(128 buckets per power of two, under 1% relative error; exact below 256 ns).
Count, mean, minimum and maximum are exact.
"""

from __future__ import annotations

from collections import Counter

_SUB_BITS = 8  # bucket keys keep the top 8 significant bits


def _bucket_bounds(key: int) -> tuple[int, int]:
    """The smallest and largest latency a bucket holds."""
    shift = key >> _SUB_BITS
    if shift == 0:
        return key, key
    mantissa = key & ((1 << _SUB_BITS) - 1)
    return mantissa << shift, ((mantissa + 1) << shift) - 1


class LatencyStats:
    """Count, mean, maximum and percentiles of a stream of latencies (ns)."""

    __slots__ = ("count", "total", "min", "max", "_buckets")

    def __init__(self) -> None:
        self.count = 0
        self.total = 0
        self.min = 0
        self.max = 0
        self._buckets: dict[int, int] = {}

    def add(self, ns: int) -> None:
        self.add_many([ns])

    def add_many(self, latencies: list[int]) -> None:
        """``add`` each of them.  Pipelined answers that arrive in one read share
        a few distinct latencies, so counting them first does most of the work
        at C speed."""
        if len(latencies) < 2:  # one answer per read, as in request/response traffic
            counts = dict.fromkeys(latencies, 1)
        else:
            counts = Counter(latencies)
        if not counts:
            return
        low, high = min(counts), max(counts)
        if not self.count or low < self.min:
            self.min = low
        if high > self.max:
            self.max = high
        self.count += len(latencies)
        self.total += sum(latencies)
        buckets = self._buckets
        for ns, n in counts.items():
            shift = ns.bit_length() - _SUB_BITS
            key = ns if shift <= 0 else (shift << _SUB_BITS) | (ns >> shift)
            buckets[key] = buckets.get(key, 0) + n

    def merge(self, other: LatencyStats) -> None:
        if not other.count:
            return
        self.min = other.min if not self.count else min(self.min, other.min)
        self.count += other.count
        self.total += other.total
        self.max = max(self.max, other.max)
        for key, n in other._buckets.items():
            self._buckets[key] = self._buckets.get(key, 0) + n

    @property
    def mean(self) -> float:
        return self.total / self.count if self.count else 0.0

    def percentile(self, p: float) -> int:
        """The p-th percentile (0 < p <= 100), to within 1%, within [min, max]."""
        if not self.count:
            return 0
        rank = max(1, round(p / 100 * self.count))
        seen = 0
        for key in sorted(self._buckets):
            seen += self._buckets[key]
            if seen >= rank:
                low, high = _bucket_bounds(key)
                return max(self.min, min((low + high) // 2, self.max))
        return self.max

    def histogram(self) -> list[tuple[int, int, int]]:
        """(low ns, high ns, count) per occupied bucket, in order."""
        return [(*_bucket_bounds(key), self._buckets[key]) for key in sorted(self._buckets)]
