"""What a replay will send: each recorded connection's client side, as timed writes.

Pure planning, apart from the sockets: which connections and items the
filters select (``--conn``, ``--start``/``--end``, ``--kind``), cut into writes
either one per frame or along the recorded TCP reads (``--segments exact``),
with the recorded time of each and the recorded items it completes, so the
replayer can pair what the server answers with what was recorded.  The
password is not among the writes: the replayer performs the handshake itself.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.describe import meaning
from whiztap.analyzer.analysis.exchanges import ClientItem, RecordedConnection, RecordedSessions
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.handshake import Mode
from whiztap.analyzer.protocol.text import escape, shorten

NS = 1_000_000_000

# --kind names: what a client item is, by message...
_MESSAGE_KINDS: dict[type[m.Message], str] = {
    m.FetchConfiguration: "config", m.FetchCameraImage: "camera", m.NormalSend: "send",
    m.ActivateSwitch: "switch", m.DeactivateSwitch: "switch", m.PlayInternalScript: "script",
    m.StopInternalScript: "script", m.PlayExternalScript: "script", m.StopExternalScript: "script",
    m.SensorRequest: "sensor", m.ServoPositionRequest: "servo", m.UnknownCommand: "unknown",
}
# ...or by item kind.
_ITEM_KINDS = ("command", "set_config", "eol", "unframed")
KINDS = tuple(sorted(set(_MESSAGE_KINDS.values()))) + _ITEM_KINDS


def kinds_of(item: ClientItem) -> set[str]:
    """Every --kind name that selects an item (an ambiguous frame answers to each
    of its meanings)."""
    obs = item.obs
    names = {obs.item.kind.value}
    for message in (obs.message,) if obs.message is not None else obs.candidates:
        if type(message) in _MESSAGE_KINDS:
            names.add(_MESSAGE_KINDS[type(message)])
    return names


@dataclass(frozen=True, slots=True)
class Selection:
    conns: frozenset[int] = frozenset()
    start_s: float | None = None  # seconds from the recording's first read
    end_s: float | None = None  # exclusive
    kinds: frozenset[str] = frozenset()

    @property
    def filtering(self) -> bool:
        return self.start_s is not None or self.end_s is not None or bool(self.kinds)

    def accepts(self, item: ClientItem, origin_ns: int) -> bool:
        rel = (item.t_ns - origin_ns) / NS
        if self.start_s is not None and rel < self.start_s:
            return False
        if self.end_s is not None and rel >= self.end_s:
            return False
        return not self.kinds or bool(self.kinds & kinds_of(item))


@dataclass(frozen=True, slots=True)
class Send:
    """One write: its recorded time, its bytes, and the recorded client items
    whose last byte it carries (the ones the server's answers pair with)."""

    t_ns: int
    data: bytes
    items: tuple[ClientItem, ...]

    def describe(self) -> str:
        shown = [i for i in self.items if i.obs.item.kind is not ItemKind.EOL]
        return "; ".join(meaning(i.obs) for i in shown) or f"{len(self.data)} bytes"


@dataclass(frozen=True, slots=True)
class ConnectionPlan:
    recorded: RecordedConnection
    sends: tuple[Send, ...]
    password_tail: bytes = b""  # sent right after the password (whole-frame writes only)

    @property
    def winsock(self) -> bool:
        return self.recorded.mode is Mode.WINSOCK

    @property
    def password_t_ns(self) -> int:
        password = self.recorded.password
        return password.t_ns if password is not None else self.recorded.opened_ns


def _password_tail(rec: RecordedConnection) -> bytes:
    """The line break the client sent right after its password, if any: a
    server may need it to see where the password ends."""
    password = rec.password
    if password is None:
        return b""
    tail = b""
    for item in rec.items[rec.items.index(password) + 1:]:
        if item.obs.item.kind is not ItemKind.EOL:
            break
        tail += item.obs.item.raw
    return tail


def _selected(rec: RecordedConnection, selection: Selection, origin_ns: int) -> list[ClientItem]:
    """The chosen items; a line break goes with the frame it follows (or with
    the password, which the replayer sends itself)."""
    chosen: list[ClientItem] = []
    previous_chosen = after_password = False
    for item in rec.items:
        kind = item.obs.item.kind
        if kind is ItemKind.PASSWORD or (kind is ItemKind.EOL and after_password):
            previous_chosen, after_password = False, True
            continue
        after_password = False
        if kind is ItemKind.EOL and not (selection.kinds and "eol" in selection.kinds):
            take = previous_chosen
        else:
            take = selection.accepts(item, origin_ns)
        if take:
            chosen.append(item)
        previous_chosen = take
    return chosen


def _frame_sends(chosen: list[ClientItem]) -> list[Send]:
    sends: list[Send] = []
    for item in chosen:
        raw = item.obs.item.raw
        last = sends[-1] if sends else None
        if item.obs.item.kind is ItemKind.EOL and last is not None and last.items[-1].end == item.offset:
            sends[-1] = Send(last.t_ns, last.data + raw, last.items + (item,))
        else:
            sends.append(Send(item.t_ns, raw, (item,)))
    return sends


def _segment_sends(rec: RecordedConnection, chosen: list[ClientItem]) -> list[Send]:
    """The recorded reads holding chosen bytes, whole, minus the password's bytes.

    An item is paired with the read holding its last byte, and only if every
    read it lies in is sent: only then does the server see it as recorded."""
    reads = rec.reads
    starts = [r.offset for r in reads]

    def overlapping(a: int, b: int) -> range:
        return range(max(bisect.bisect_right(starts, a) - 1, 0), bisect.bisect_left(starts, b))

    sent = [False] * len(reads)
    for item in chosen:
        for k in overlapping(item.offset, item.end):
            sent[k] = True
    ending: dict[int, list[ClientItem]] = {}
    for item in rec.items:
        spans = overlapping(item.offset, item.end)
        if item.obs.item.kind is not ItemKind.PASSWORD and spans and all(sent[k] for k in spans):
            ending.setdefault(spans[-1], []).append(item)
    password = rec.password
    hidden = (password.offset, password.end) if password is not None else (0, 0)
    sends = []
    for k, r in enumerate(reads):
        if not sent[k]:
            continue
        lo, hi = max(hidden[0], r.offset), min(hidden[1], r.offset + len(r.data))
        data = r.data[:lo - r.offset] + r.data[hi - r.offset:] if lo < hi else r.data
        if data:
            sends.append(Send(r.t_ns, data, tuple(ending.get(k, ()))))
    return sends


def plan(recording: RecordedSessions, selection: Selection, segments: bool) -> list[ConnectionPlan]:
    """Every connection to replay, in the order they were opened."""
    plans = []
    for rec in recording.connections:
        if selection.conns and rec.conn not in selection.conns:
            continue
        chosen = _selected(rec, selection, recording.start_ns)
        if selection.filtering and not chosen:
            continue
        if segments:  # the reads keep whatever followed the password
            plans.append(ConnectionPlan(rec, tuple(_segment_sends(rec, chosen))))
        else:
            plans.append(ConnectionPlan(rec, tuple(_frame_sends(chosen)), _password_tail(rec)))
    return sorted(plans, key=lambda p: p.recorded.opened_ns)


def dry_run_lines(plans: list[ConnectionPlan], origin_ns: int) -> list[str]:
    """What a replay would do, for ``--dry-run``."""
    lines = []
    for p in plans:
        rec = p.recorded
        lines.append(f"conn {rec.conn} ({rec.mode}, opened at {(rec.opened_ns - origin_ns) / NS:.6f} s, "
                     f"{len(p.sends)} writes)")
        if p.winsock:
            words = " -> ".join(escape(h.item.raw) for h in rec.handshake)
            lines.append(f"  {(p.password_t_ns - origin_ns) / NS:12.6f} handshake: {words} "
                         f"(the password is sent after sendchkpass)")
        for send in p.sends:
            at = (send.t_ns - origin_ns) / NS
            lines.append(f"  {at:12.6f} send {shorten(escape(send.data), 72)}  {send.describe()}")
            for item in send.items:
                if item.answer is not None:
                    answer = item.answer
                    lines.append(f"  {'':12} expect {shorten(escape(answer.item.raw), 64)}  {meaning(answer)}")
    return lines
