"""Per-file analyses merged into one, the one way every run does it.

``whiztap analyze`` analyses each recording on its own (in this process, in
local worker processes, or as tasks on a Dask cluster) and merges the
results.  Results may come back in any order, but the merge is not
order-free: the report lists the first 10,000 violations in file order, and
the plotted series are down-sampled as points arrive.  So results are merged
strictly in input order, each as soon as all before it are in, and the report
of a run is the same whoever did the work and whenever each file finished.
Everything else merges exactly: counts add, and latency percentiles come from
summed histogram buckets (``LatencyStats.merge``), never from averages.

A runner that shares the files out elsewhere (``analyze --dask``: the
``whiztap.runners`` entry points, ``whiztap.sniffer.fleet.cluster``) raises
``RunnerError`` when it cannot do the work and hands back ``Lost`` for a file
it gave up on; both are here so that the analyzer never imports a runner.
"""

from __future__ import annotations

from dataclasses import dataclass

from whiztap.analyzer.analysis.facts import Analysis
from whiztap.analyzer.errors import WhiztapError


class RunnerError(WhiztapError):
    """A runner cannot do the work (a cluster unreachable, no workers...); one line."""


@dataclass(frozen=True)
class Lost:
    """A file's task the runner gave up on (its workers kept dying): why."""

    reason: str


class DuplicateResult(RuntimeError):
    """A file's result came twice: a retried task must not count it again."""


class Merger:
    """Results by input index (an ``Analysis``, or the line saying why that
    file could not be read), merged in input order as they arrive."""

    def __init__(self, names: list[str]) -> None:
        self.names = names
        self.merged: Analysis | None = None
        self.unreadable: list[dict[str, str]] = []
        self._pending: dict[int, Analysis | str] = {}
        self._next = 0

    def add(self, index: int, result: Analysis | str) -> None:
        """One file's result; raises DuplicateResult for a file already in."""
        if index < self._next or index in self._pending or not 0 <= index < len(self.names):
            raise DuplicateResult(f"a second result for {self.names[index]}" if 0 <= index < len(self.names)
                                  else f"a result for no input (#{index})")
        self._pending[index] = result
        while self._next in self._pending:
            self._take(self._next, self._pending.pop(self._next))
            self._next += 1

    def _take(self, index: int, result: Analysis | str) -> None:
        if isinstance(result, str):
            self.unreadable.append({"file": self.names[index], "error": result})
        elif self.merged is None:
            self.merged = result
        else:
            self.merged.merge(result)

    @property
    def complete(self) -> bool:
        return self._next == len(self.names)

    def finish(self) -> tuple[Analysis | None, list[dict[str, str]]]:
        """(the merged analysis of the files that could be read, or None if none
        could; {"file", "error"} of those that could not, in input order)."""
        if not self.complete:
            missing = [self.names[i] for i in range(self._next, len(self.names)) if i not in self._pending]
            raise RuntimeError(f"no result for {', '.join(missing[:3])}")
        return self.merged, self.unreadable
