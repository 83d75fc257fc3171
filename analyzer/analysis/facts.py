"""The facts a conformance report states: what ``Analyzer`` gathers and the
report renders.

Kept apart from the analyzer so that the judging of each side when the proxy
stood in the middle (``sides``) and the analyzer can both build them without
importing each other.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass, field

from whiztap.analyzer.protocol.messages import ChannelConfig
from whiztap.analyzer.protocol.rules import RULES, Severity
from whiztap.analyzer.protocol.stats import LatencyStats

NS = 1_000_000_000
RAW_KEPT = 2048  # bytes of a violating item kept for the report: every frame whole; an image or garbage cut


@dataclass(slots=True)
class ViolationRecord:
    rule_id: str
    file: str
    conn: int
    direction: str | None
    t_ns: int
    raw: bytes  # the frame's bytes (first RAW_KEPT)
    detail: str
    late: bool = False
    cut: bool = False  # the item was longer than RAW_KEPT
    side: str = ""  # whose conduct it is about: "client" or "server"; for an intervention's effect, who saw it
    cause: str = ""  # for an intervention's effect: the intervention it follows from ('' when not known)
    section: str = ""  # the spec section it cites (Violation.section: the message's, or the rule's)
    index: int = -1  # the item's position in its session (the HTML report's frame view finds it by it)

    @property
    def severity(self) -> Severity:
        return RULES[self.rule_id].severity


@dataclass(slots=True)
class SetConfigCheck:
    file: str
    conn: int
    t_ns: int
    checksum: int
    expected: int  # under the rule in use
    satisfies: tuple[str, ...]  # every candidate rule the checksum fits


class Series:
    """A time series down-sampled to at most ``2 * limit`` points: when full,
    every other point goes and only every ``stride``-th new one is kept."""

    __slots__ = ("points", "limit", "stride", "_skip")

    def __init__(self, limit: int = 1000) -> None:
        self.points: list[tuple[int, float]] = []
        self.limit = limit
        self.stride = 1
        self._skip = 0

    def add(self, t_ns: int, value: float) -> None:
        self._skip += 1
        if self._skip < self.stride:
            return
        self._skip = 0
        self.points.append((t_ns, value))
        if len(self.points) >= 2 * self.limit:
            del self.points[1::2]
            self.stride *= 2


@dataclass(slots=True)
class ConnectionSummary:
    file: str
    conn: int
    client: str = ""
    upstream: str = ""
    first_ns: int | None = None
    last_ns: int | None = None
    mode: str = "unknown"
    handshake: str = "not started"
    frames: Counter = field(default_factory=Counter)  # (dir, kind) -> count
    violations: Counter = field(default_factory=Counter)  # rule id -> count
    channel_map: dict[int, ChannelConfig] = field(default_factory=dict)
    closed_by: str = ""
    notes: list[str] = field(default_factory=list)  # upstream failures, capture gaps
    middle: bool = False  # the proxy stood in the middle: each side was judged by what it did
    interventions: int = 0  # changes the proxy made to this connection's traffic


@dataclass
class Analysis:
    """Everything a report says, for one file or merged over several."""

    files: list[str]
    checksum_rule: str
    connections: list[ConnectionSummary] = field(default_factory=list)
    violations: list[ViolationRecord] = field(default_factory=list)
    violation_counts: Counter = field(default_factory=Counter)
    side_counts: Counter = field(default_factory=Counter)  # (rule id, "client" | "server") -> count
    latencies: dict[str, LatencyStats] = field(default_factory=lambda: defaultdict(LatencyStats))
    # the client's latencies (from the request it sent to the answer it received), for the
    # connections the proxy stood in the middle of; ``latencies`` are the server's there
    client_latencies: dict[str, LatencyStats] = field(default_factory=lambda: defaultdict(LatencyStats))
    unanswered: Counter = field(default_factory=Counter)  # request title -> count
    set_configs: list[SetConfigCheck] = field(default_factory=list)
    frames_per_second: dict[int, Counter] = field(default_factory=lambda: defaultdict(Counter))
    values: dict[tuple[str, int], Series] = field(default_factory=dict)  # ("sensor"|"servo", ch)
    first_ns: int | None = None
    last_ns: int | None = None
    frames: int = 0
    max_violations: int = 10_000
    interventions: Counter = field(default_factory=Counter)  # (cause group, action) -> count
    # what the proxy's changes made one side see that the other side did not do:
    # not a violation of either side (the first max_violations kept, all counted)
    effects: list[ViolationRecord] = field(default_factory=list)
    effect_counts: Counter = field(default_factory=Counter)  # rule id -> count
    # file -> its "whiztap" metadata record: what a fleet report groups by (robot, firmware, start time)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    # the channel map stated by --channels/--assume-config, when a connection judged by it
    # never heard the server's own ('' otherwise): the report says so
    assumed_channels: str = ""

    @property
    def duration_s(self) -> float:
        if self.first_ns is None or self.last_ns is None:
            return 0.0
        return (self.last_ns - self.first_ns) / NS

    def worst(self, ignore: frozenset[str] = frozenset()) -> Severity | None:
        levels = [RULES[r].severity for r, n in self.violation_counts.items() if n and r not in ignore]
        return max(levels, default=None)

    def merge(self, other: Analysis) -> None:
        self.files += other.files
        self.connections += other.connections
        room = self.max_violations - len(self.violations)
        self.violations += other.violations[:max(room, 0)]
        self.violation_counts.update(other.violation_counts)
        self.side_counts.update(other.side_counts)
        for title, stats in other.latencies.items():
            self.latencies[title].merge(stats)
        for title, stats in other.client_latencies.items():
            self.client_latencies[title].merge(stats)
        self.unanswered.update(other.unanswered)
        self.set_configs += other.set_configs
        for second, counts in other.frames_per_second.items():
            self.frames_per_second[second].update(counts)
        for key, series in other.values.items():
            mine = self.values.setdefault(key, Series(series.limit))
            for t, v in series.points:
                mine.add(t, v)
        self.frames += other.frames
        for when in (other.first_ns, other.last_ns):
            if when is not None:
                self.first_ns = when if self.first_ns is None else min(self.first_ns, when)
                self.last_ns = when if self.last_ns is None else max(self.last_ns, when)
        self.interventions.update(other.interventions)
        room = self.max_violations - len(self.effects)
        self.effects += other.effects[:max(room, 0)]
        self.effect_counts.update(other.effect_counts)
        self.metadata.update(other.metadata)
        self.assumed_channels = self.assumed_channels or other.assumed_channels
