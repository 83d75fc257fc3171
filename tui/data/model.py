"""The traffic the TUI shows: the analyzer's sessions and the frame store, fed together.

Whatever the source (a recording, a growing file, the proxy inside the app),
reads and connection events come here.  The ``Analyzer`` runs one ``Session``
per connection over the raw bytes, exactly as ``whiztap analyze`` and ``cat``
do, and its events go into the ``FrameStore``.  The panes read summaries from
here (connections, latencies, values per channel), under the same lock the
feeder holds, so they never see half of a batch.

The counts (violations, by connection and in all) are ``analyze``'s verdict
(``whiztap.analyzer.analysis.verdict``) on the same events, the one
``record``'s summary and the control API's ``/state`` give.  Without the
middle it is the store's own analyzer's.  In the middle the store shows the
conversation as the server had it (``middle_view.py``) while a ``Judge`` judges
each side by what it sent and received, as ``analyze`` does, fed the events
as the file has them.
"""

from __future__ import annotations

from dataclasses import dataclass

from whiztap.analyzer.analysis.analyzer import Analyzer, Series
from whiztap.analyzer.analysis.verdict import Judge, Verdict, both_latencies, verdict_of, violations_by_connection
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE
from whiztap.analyzer.protocol.session import Limits
from whiztap.analyzer.protocol.stats import LatencyStats
from whiztap.analyzer.traffic import Delivered, Intervention, TrafficEvent
from whiztap.tui.data.middle_view import MiddleView
from whiztap.tui.data.store import FrameStore

_MIDDLE_ONLY = (Delivered, Intervention)


@dataclass(frozen=True, slots=True)
class ConnectionRow:
    """One line of the connections pane."""

    conn: int
    client: str
    upstream: str
    mode: str
    handshake: str
    frames: int  # the list's rows of the connection (in the middle, with those the server never got)
    violations: int  # as analyze counts them (in the middle, an open one as if it ended now)
    state: str  # "open", or who closed it


def verdict_text(verdict: Verdict) -> str:
    """The status line's counts: the verdict so far, as ``analyze`` would give it."""
    return f"{'PASS' if verdict.passed else 'FAIL'}: {verdict.violations:,} violations ({verdict.words()})"


class TrafficModel:
    def __init__(self, name: str = "", checksum_rule: str = DEFAULT_CHECKSUM_RULE,
                 redact_passwords: bool = False, limits: Limits = Limits()) -> None:
        self.analyzer = Analyzer(name, checksum_rule, limits)
        self.store = FrameStore(redact_passwords)
        self.lock = self.store.lock
        self.finished = False  # no more traffic will come (the file ended, the proxy stopped)
        self.middle: MiddleView | None = None  # the proxy stands in the middle: see middle_view.py
        self.judge: Judge | None = None  # in the middle: analyze's judging (without it, the analyzer's)
        self._redact_delivered = False
        self._settings = (checksum_rule, limits, name)
        # the recording's time span: its first and last event (what 'whiztap info' gives as a file's span)
        self.first_ns: int | None = None
        self.last_ns: int | None = None

    def in_the_middle(self, redact: bool) -> None:
        """From now on, traffic is that of a proxy in the middle (a recording
        whose metadata says so, or the live proxy with its controller)."""
        self.middle = MiddleView(self.analyzer.receive, self.store, redact)
        checksum_rule, limits, name = self._settings
        self.judge = Judge(checksum_rule, limits, middle=True, name=name)
        self._redact_delivered = redact

    # -- feeding (one worker thread) --------------------------------------------------------

    def receive(self, event: TrafficEvent) -> None:
        with self.lock:
            t = event.t_ns
            if self.first_ns is None or t < self.first_ns:
                self.first_ns = t
            if self.last_ns is None or t > self.last_ns:
                self.last_ns = t
            middle, judge = self.middle, self.judge
            if middle is not None and judge is not None:  # both, from in_the_middle() on
                middle.receive(event)
                if self._redact_delivered and type(event) is Delivered and event.secret:
                    event = event._replace(data=b"*" * len(event.data))  # as the file has it
                judge.receive(event)
            elif type(event) not in _MIDDLE_ONLY:  # they mean something only in the middle
                self.store.add(event.conn, self.analyzer.receive(event))

    def finish(self) -> None:
        """End every open session: requests still unanswered become violations."""
        with self.lock:
            for conn, events in self.analyzer.close_all():
                self.store.add(conn, events)
            if self.judge is not None:
                self.judge.finish()
            self.finished = True

    # -- summaries (the screen) ----------------------------------------------------------------

    def connections(self) -> list[ConnectionRow]:
        analyzer = self.analyzer
        rows = []
        with self.lock:
            judged = self._judged_violations()
            for conn, summary in sorted(analyzer.summaries.items()):
                session = analyzer.sessions.get(conn)
                violations = judged.get(conn, 0)
                if session is not None:  # going on: the live session knows more than the summary
                    mode, handshake = str(session.mode), session.handshake_outcome
                    if self.judge is None:
                        violations = sum(session.violation_counts.values())
                else:
                    mode, handshake = summary.mode, summary.handshake
                if conn not in analyzer.closed:  # in the middle, open before its session begins
                    state = "open"
                else:
                    state = f"closed by {summary.closed_by}" if summary.closed_by else "ended"
                rows.append(ConnectionRow(conn, summary.client, summary.upstream, mode, handshake,
                                          self.store.conn_rows(conn), violations, state))
        return rows

    def _judged_violations(self) -> dict[int, int]:
        """Violations by connection as ``analyze`` counts them; in the middle,
        an open connection's as if its traffic ended now."""
        return violations_by_connection(self.judge.analyzer if self.judge is not None else self.analyzer)

    def verdict(self) -> Verdict:
        """What ``analyze`` would say of the traffic so far (open connections
        in the middle judged as if they ended now)."""
        with self.lock:
            if self.judge is not None:
                return self.judge.verdict()
            result = self.analyzer.result
            return verdict_of(result.side_counts, result.effect_counts, len(self.analyzer.summaries))

    @property
    def duration_s(self) -> float:
        """From the first event to the last: a recording's own span, whenever it is looked at."""
        with self.lock:
            if self.first_ns is None or self.last_ns is None:
                return 0.0
            return (self.last_ns - self.first_ns) / 1e9

    def latencies(self) -> dict[str, LatencyStats]:
        """Latency by request title over every session, open or closed (in
        the middle: the server's, from what it received to what it sent)."""
        return self.both_latencies()[0]

    def both_latencies(self) -> tuple[dict[str, LatencyStats], dict[str, LatencyStats]]:
        """The server's and the client's latency by request title, as
        ``analyze`` reports them; the client's only in the middle (else empty:
        they are the server's)."""
        with self.lock:
            if self.judge is not None:
                server, client = self.judge.latencies()
                return dict(sorted(server.items())), dict(sorted(client.items()))
            server, _ = both_latencies(self.analyzer)  # the client's are the server's here
        return dict(sorted(server.items())), {}

    def channel_values(self) -> dict[tuple[str, int], list[tuple[int, float]]]:
        """("sensor" | "servo", channel) -> (t_ns, value) points, down-sampled."""
        with self.lock:
            values: dict[tuple[str, int], Series] = self.analyzer.result.values
            return {key: list(series.points) for key, series in sorted(values.items())}
