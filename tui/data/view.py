"""Which frames the list shows: all of them, or those the filter accepts.

The filter is ``whiztap.analyzer.analysis.item_filter.ItemFilter``, the one ``whiztap cat`` uses,
written in the filter bar as words (``conn:2 dir:c2s kind:response ch:12
since:1.5 until:9 violations`` and free text).  A filtered view is an index:
the sorted ids of accepted frames, built by a worker thread in slices so the
screen stays live, and extended as frames arrive.
"""

from __future__ import annotations

from array import array
from bisect import bisect_left, insort
from collections.abc import Callable
from dataclasses import replace

from whiztap.analyzer.analysis.item_filter import ItemFilter
from whiztap.tui.data.marks import mark_kind
from whiztap.tui.data.store import FrameStore

SLICE = 4096  # frames judged between looks at whether the filter was replaced

def with_connection(item_filter: ItemFilter, conn: int | None) -> ItemFilter:
    """The filter narrowed to the connection chosen in the connections pane."""
    return item_filter if conn is None else replace(item_filter, conns=frozenset({conn}))


def _marked(store: FrameStore, n: int, kinds: frozenset[str]) -> bool:
    """Frame ``n`` has a mark of one of ``kinds`` (``held``, ``injected``, ...)."""
    return any(mark_kind(mark) in kinds for mark in store.marks.get(n, ()))


class FrameView:
    """Rows of the frame list: row -> frame id."""

    def __init__(self, store: FrameStore, item_filter: ItemFilter = ItemFilter()) -> None:
        self.store = store
        self.filter = item_filter
        self.all = item_filter == ItemFilter()
        self.rows = array("q")
        self.judged = 0  # frames below this id have been judged
        self._late_seen = 0  # store.late_marked entries looked at

    def __len__(self) -> int:
        return self.store.count if self.all else len(self.rows)

    def __getitem__(self, row: int) -> int:
        return row if self.all else self.rows[row]

    @property
    def complete(self) -> bool:
        """Every frame stored so far has been judged."""
        return self.all or self.judged >= self.store.count

    def row_of(self, frame: int) -> int:
        """The row showing ``frame``, or the row of the first frame after it."""
        if self.all:
            return frame
        return bisect_left(self.rows, frame)

    def judge(self, cancelled: Callable[[], bool] = lambda: False) -> None:
        """Judge the frames not judged yet (in a worker thread), in slices."""
        store = self.store
        accepts = self.filter.accepts
        rows = self.rows
        while not cancelled():
            end = min(store.count, self.judged + SLICE)
            if self.judged >= end:
                break
            start_ns = store.start_ns or 0
            observation, conn = store.observation, store.conn
            wanted = self.filter.interventions
            for n in range(self.judged, end):
                if accepts(conn[n], observation(n), start_ns) and (not wanted or _marked(store, n, wanted)):
                    rows.append(n)
            self.judged = end
        self._rejudge_late_marks()

    def _rejudge_late_marks(self) -> None:
        """A violation found later (an unanswered request) can let in a frame
        already judged, under ``violations``."""
        marked = self.store.late_marked
        new, self._late_seen = marked[self._late_seen:], len(marked)
        if not self.filter.violations_only:
            return
        start_ns = self.store.start_ns or 0
        for n in new:
            if n < self.judged:
                at = bisect_left(self.rows, n)
                if (at == len(self.rows) or self.rows[at] != n) and \
                        self.filter.accepts(self.store.conn[n], self.store.observation(n), start_ns):
                    insort(self.rows, n)
