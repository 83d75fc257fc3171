"""What a replay tells its front end, and the count it adds up to.

Every progress event of a replay leaves through ``Tally.emit``, so the clock
of its ``at_s`` (seconds since the run began) and the counts of its result
are kept in one place: ``sent`` renders a write for people (the meaning of
the items it carries, a password masked), ``judge`` compares an answer with
the recorded one and renders the difference, and ``result`` sums it all up.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable

from whiztap.analyzer.analysis.compare import CompareRules, Status, compare, headline, side_by_side
from whiztap.analyzer.analysis.exchanges import ClientItem
from whiztap.analyzer.protocol.describe import meaning
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.observations import Observation
from whiztap.analyzer.protocol.stats import LatencyStats
from whiztap.sniffer.replay.events import Drift, Event, ReplayResult, RequestSent, ResponseCompared
from whiztap.sniffer.replay.plan import NS


class Tally:
    """The writes, connections and judged answers of one replay, told as they happen."""

    def __init__(self, start_ns: int, rules: CompareRules, on_event: Callable[[Event], None] | None) -> None:
        self.start_ns = start_ns  # the recording's first read: recorded_s counts from it
        self.rules = rules
        self.on_event = on_event
        self.counts: Counter[Status] = Counter()
        self.differences: list[ResponseCompared] = []
        self.drift = LatencyStats()
        self.shift_ns = 0  # the most a slow handshake moved a connection's schedule
        self.writes = 0
        self.connections = 0
        self._t0 = time.perf_counter_ns()

    def begin(self) -> None:
        """The run begins: ``at_s`` counts from now."""
        self._t0 = time.perf_counter_ns()

    def at(self) -> float:
        return (time.perf_counter_ns() - self._t0) / NS

    def recorded_s(self, t_ns: int) -> float:
        return (t_ns - self.start_ns) / NS

    def emit(self, event: Event) -> None:
        if self.on_event is not None:
            self.on_event(event)

    def sent(self, conn: int, data: bytes, items: tuple[ClientItem, ...], recorded_ns: int,
             drift: int | None) -> None:
        self.writes += 1
        if drift is not None:
            self.drift.add(drift)
        shown = [meaning(i.obs) for i in items if i.obs.item.kind is not ItemKind.EOL]
        text = "; ".join(shown) if shown else f"{len(data)} bytes"
        if any(i.obs.item.kind is ItemKind.PASSWORD for i in items):
            data, text = b"*" * len(data), "Password"
        self.emit(RequestSent(conn, self.at(), self.recorded_s(recorded_ns), data, text, drift))

    def judge(self, conn: int, recorded: Observation | None, replayed: Observation | None,
              item: ClientItem | None, at_rest: bool, what: str = "", note: str = "") -> None:
        verdict = compare(recorded, replayed, self.rules, at_rest)
        self.counts[verdict.status] += 1
        if verdict.status is Status.UNANSWERED:
            return
        request = item.obs if item is not None else None
        if recorded is not None:
            t_rec = recorded.item.t_end_ns
        else:
            t_rec = item.t_ns if item is not None else self.start_ns
        recorded_s = self.recorded_s(t_rec)
        diff = ""
        if not verdict.match:
            head = headline(verdict, conn, recorded_s, request, what)
            if note or not (request or what):
                head += f" ({note or 'it answers no request'})"
            lines = [head] + side_by_side(recorded, replayed, verdict)
            diff = "\n".join(lines)
        event = ResponseCompared(
            conn, self.at(), recorded_s, request.item.raw if request is not None else None,
            meaning(request) if request is not None else what, recorded.item.raw if recorded else None,
            replayed.item.raw if replayed else None, verdict.status, verdict.match, diff)
        if not verdict.match:
            self.differences.append(event)
        self.emit(event)

    def result(self, with_drift: bool, stopped: bool, error: str | None) -> ReplayResult:
        """The result so far; ``with_drift``: say how late writes left (recorded pacing)."""
        drift = None
        if with_drift and self.drift.count:
            d = self.drift
            drift = Drift(d.count, d.percentile(50), d.percentile(99), d.max, self.shift_ns)
        return ReplayResult(self.connections, self.writes, dict(self.counts), tuple(self.differences), drift,
                            stopped, error)
