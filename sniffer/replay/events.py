"""What a replay tells its front end as it goes (``on_event``), and its result.

These are the replay's own progress events, one per step a person watching
wants to see (a connection opened, a write left, an answer judged, a
connection closed, the end); not traffic events (``whiztap.analyzer.traffic``),
which say what crossed the wire and go to the output recording.
"""

from __future__ import annotations

from dataclasses import dataclass

from whiztap.analyzer.analysis.compare import Status
from whiztap.analyzer.protocol.text import escape


@dataclass(frozen=True, slots=True)
class ConnectionOpened:
    conn: int
    recorded_conn: int
    loop: int
    at_s: float
    local: str


@dataclass(frozen=True, slots=True)
class RequestSent:
    conn: int
    at_s: float
    recorded_s: float
    data: bytes
    text: str
    drift_ns: int | None


@dataclass(frozen=True, slots=True)
class ResponseCompared:
    conn: int
    at_s: float
    recorded_s: float
    request: bytes | None
    request_text: str
    recorded: bytes | None
    replayed: bytes | None
    status: Status
    match: bool
    diff: str


@dataclass(frozen=True, slots=True)
class ConnectionClosed:
    conn: int
    at_s: float
    by: str
    detail: str


@dataclass(frozen=True, slots=True)
class Drift:
    """How late writes left against the recorded schedule."""

    count: int
    p50_ns: int
    p99_ns: int
    max_ns: int
    shift_ns: int = 0  # the most a slow handshake moved a connection's schedule

    def text(self) -> str:
        text = (f"drift from schedule over {self.count} writes: p50 {self.p50_ns / 1e6:.3f} ms, "
                f"p99 {self.p99_ns / 1e6:.3f} ms, max {self.max_ns / 1e6:.3f} ms")
        if self.shift_ns:
            text += f" (schedule moved up to {self.shift_ns / 1e6:.3f} ms later by the server's handshake)"
        return text


@dataclass(frozen=True)
class ReplayResult:
    connections: int
    writes: int
    counts: dict[Status, int]
    differences: tuple[ResponseCompared, ...]
    drift: Drift | None
    stopped: bool = False
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None and not self.differences

    @property
    def exit_status(self) -> int:
        return 2 if self.error is not None else 0 if self.ok else 1

    def as_dict(self) -> dict:
        """The result as plain data (``whiztap replay --format json``); bytes as escaped text."""

        def text(data: bytes | None) -> str | None:
            return escape(data) if data is not None else None

        return {
            "connections": self.connections, "writes": self.writes,
            "answers": {str(s): self.counts.get(s, 0) for s in Status},
            "ok": self.ok, "exit_status": self.exit_status, "stopped": self.stopped, "error": self.error,
            "differences": [{
                "conn": d.conn, "at_s": d.at_s, "recorded_s": d.recorded_s, "request": text(d.request),
                "request_text": d.request_text, "recorded": text(d.recorded), "replayed": text(d.replayed),
                "status": str(d.status), "diff": d.diff,
            } for d in self.differences],
            "drift": None if self.drift is None else {
                "count": self.drift.count, "p50_ns": self.drift.p50_ns, "p99_ns": self.drift.p99_ns,
                "max_ns": self.drift.max_ns, "shift_ns": self.drift.shift_ns},
        }

    def summary(self) -> str:
        c = self.counts
        judged = ", ".join(f"{c.get(s, 0)} {s}" for s in (Status.MATCH, Status.MISMATCH, Status.MISSING,
                                                           Status.EXTRA, Status.UNANSWERED, Status.IGNORED))
        return f"replayed {self.connections} connection(s), {self.writes} writes; answers: {judged}"


@dataclass(frozen=True, slots=True)
class Finished:
    result: ReplayResult


Event = ConnectionOpened | RequestSent | ResponseCompared | ConnectionClosed | Finished
