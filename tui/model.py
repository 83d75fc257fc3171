"""The traffic the TUI shows: the analyzer's sessions and the frame store, fed together.

Whatever the source (a recording, a growing file, the proxy inside the app),
reads and connection events come here.  The ``Analyzer`` runs one ``Session``
per connection over the raw bytes, exactly as ``whiztap analyze`` and ``cat``
do, and its events go into the ``FrameStore``.  The panes read summaries from
here (connections, latencies, values per channel), under the same lock the
feeder holds, so they never see half of a batch.
"""

from __future__ import annotations

from dataclasses import dataclass

from whiztap.analyzer.analysis.analyzer import Analyzer, Series
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE
from whiztap.analyzer.protocol.session import Limits
from whiztap.analyzer.protocol.stats import LatencyStats
from whiztap.analyzer.traffic import Delivered, Intervention, TrafficEvent
from whiztap.tui.middle import MiddleView
from whiztap.tui.store import FrameStore

_MIDDLE_ONLY = (Delivered, Intervention)


@dataclass(frozen=True, slots=True)
class ConnectionRow:
    """One line of the connections pane."""

    conn: int
    client: str
    upstream: str
    mode: str
    handshake: str
    frames: int
    violations: int
    state: str  # "open", or who closed it


class TrafficModel:
    def __init__(self, name: str = "", checksum_rule: str = DEFAULT_CHECKSUM_RULE,
                 redact_passwords: bool = False, limits: Limits = Limits()) -> None:
        self.analyzer = Analyzer(name, checksum_rule, limits)
        self.store = FrameStore(redact_passwords)
        self.lock = self.store.lock
        self.finished = False  # no more traffic will come (the file ended, the proxy stopped)
        self.middle: MiddleView | None = None  # the proxy stands in the middle: see middle.py

    def in_the_middle(self, redact: bool) -> None:
        """From now on, traffic is that of a proxy in the middle (a recording
        whose metadata says so, or the live proxy with its controller)."""
        self.middle = MiddleView(self.analyzer.receive, self.store, redact)

    # -- feeding (one worker thread) --------------------------------------------------------

    def receive(self, event: TrafficEvent) -> None:
        with self.lock:
            if self.middle is not None:
                self.middle.receive(event)
            elif type(event) not in _MIDDLE_ONLY:  # they mean something only in the middle
                self.store.add(event.conn, self.analyzer.receive(event))

    def finish(self) -> None:
        """End every open session: requests still unanswered become violations."""
        with self.lock:
            for conn, events in self.analyzer.close_all():
                self.store.add(conn, events)
            self.finished = True

    # -- summaries (the screen) ----------------------------------------------------------------

    def connections(self) -> list[ConnectionRow]:
        analyzer = self.analyzer
        rows = []
        with self.lock:
            for conn, summary in sorted(analyzer.summaries.items()):
                session = analyzer.sessions.get(conn)
                if session is not None:  # still open: the live session knows more than the summary
                    mode, handshake = str(session.mode), session.handshake_outcome
                    frames = sum(session.counts.values())
                    violations = sum(session.violation_counts.values())
                    state = "open"
                else:
                    mode, handshake = summary.mode, summary.handshake
                    frames = sum(summary.frames.values())
                    violations = sum(summary.violations.values())
                    state = f"closed by {summary.closed_by}" if summary.closed_by else "ended"
                rows.append(ConnectionRow(conn, summary.client, summary.upstream, mode, handshake,
                                          frames, violations, state))
        return rows

    def latencies(self) -> dict[str, LatencyStats]:
        """Latency by request title over every session, open or closed."""
        merged: dict[str, LatencyStats] = {}
        with self.lock:
            sources = [self.analyzer.result.latencies] + [s.latencies for s in self.analyzer.sessions.values()]
            for source in sources:
                for title, stats in source.items():
                    merged.setdefault(title, LatencyStats()).merge(stats)
        return dict(sorted(merged.items()))

    def channel_values(self) -> dict[tuple[str, int], list[tuple[int, float]]]:
        """("sensor" | "servo", channel) -> (t_ns, value) points, down-sampled."""
        with self.lock:
            values: dict[tuple[str, int], Series] = self.analyzer.result.values
            return {key: list(series.points) for key, series in sorted(values.items())}
