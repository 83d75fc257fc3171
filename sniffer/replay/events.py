"""What a replay tells its front end as it goes (``on_event``), and its result.

These are the replay's own progress events, one per step a person watching
wants to see (a connection opened, a write left, an answer judged, a
connection closed, the end); not traffic events (``whiztap.analyzer.traffic``),
which say what crossed the wire and go to the output recording.
"""

from __future__ import annotations

from dataclasses import dataclass

from whiztap.analyzer.analysis.compare import Status
from whiztap.analyzer.protocol.text import escape, plural


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
        text = (f"drift from schedule over {plural(self.count, 'write')}: p50 {self.p50_ns / 1e6:.3f} ms, "
                f"p99 {self.p99_ns / 1e6:.3f} ms, max {self.max_ns / 1e6:.3f} ms")
        if self.shift_ns:
            text += f" (schedule moved up to {self.shift_ns / 1e6:.3f} ms later by the server's handshake)"
        return text


@dataclass(frozen=True)
class ServerResult:
    """A replay through faults, judged on the target's side: what it sent
    before the faults acted, against what the recorded server sent
    (``server_side.py``).  Reported apart; the exit status is the client's."""

    counts: dict[Status, int]
    differences: tuple[ResponseCompared, ...]

    @property
    def ok(self) -> bool:
        return not self.differences

    def summary(self) -> str:
        return ("the target's own answers, before the faults, against the recorded server's: "
                + _judged(self.counts))

    def as_dict(self) -> dict:
        return {"answers": {str(s): self.counts.get(s, 0) for s in Status}, "ok": self.ok,
                "differences": [_difference(d) for d in self.differences]}


def _judged(counts: dict[Status, int]) -> str:
    return ", ".join(f"{counts.get(s, 0)} {s}" for s in (Status.MATCH, Status.MISMATCH, Status.MISSING,
                                                         Status.EXTRA, Status.UNANSWERED, Status.IGNORED))


def _text(data: bytes | None) -> str | None:
    return escape(data) if data is not None else None


def _difference(d: ResponseCompared) -> dict:
    return {"conn": d.conn, "at_s": d.at_s, "recorded_s": d.recorded_s, "request": _text(d.request),
            "request_text": d.request_text, "recorded": _text(d.recorded), "replayed": _text(d.replayed),
            "status": str(d.status), "diff": d.diff}


@dataclass(frozen=True)
class ReplayResult:
    connections: int
    writes: int
    counts: dict[Status, int]
    differences: tuple[ResponseCompared, ...]
    drift: Drift | None
    stopped: bool = False
    error: str | None = None
    server: ServerResult | None = None  # through faults: the target's side, reported apart

    @property
    def ok(self) -> bool:
        """The whole replay ran and every answer matched."""
        return self.error is None and not self.stopped and not self.differences

    @property
    def exit_status(self) -> int:
        """0 all matched, 1 a difference, 2 an error or stopped (Ctrl-C: 'interrupted')."""
        return 2 if self.error is not None or self.stopped else 0 if self.ok else 1

    def as_dict(self) -> dict:
        """The result as plain data (``whiztap replay --format json``); bytes as
        escaped text; ``server`` only for a replay through faults."""
        out = {
            "connections": self.connections, "writes": self.writes,
            "answers": {str(s): self.counts.get(s, 0) for s in Status},
            "ok": self.ok, "exit_status": self.exit_status, "stopped": self.stopped, "error": self.error,
            "differences": [_difference(d) for d in self.differences],
            "drift": None if self.drift is None else {
                "count": self.drift.count, "p50_ns": self.drift.p50_ns, "p99_ns": self.drift.p99_ns,
                "max_ns": self.drift.max_ns, "shift_ns": self.drift.shift_ns},
        }
        if self.server is not None:
            out["server"] = self.server.as_dict()
        return out

    def summary(self) -> str:
        return (f"replayed {plural(self.connections, 'connection')}, {plural(self.writes, 'write')}; "
                f"answers: {_judged(self.counts)}")


@dataclass(frozen=True, slots=True)
class Finished:
    result: ReplayResult


Event = ConnectionOpened | RequestSent | ResponseCompared | ConnectionClosed | Finished
