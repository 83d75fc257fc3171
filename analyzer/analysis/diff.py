"""Two recordings side by side: which exchanges differ, how, and who broke the spec.

Bytes are a poor basis for comparing two sessions: a server that answers the
same questions with one reading changed shifts every later byte.  So the two
recordings are paired through the session model instead: connections by
their order, and within a connection each request (with the answer the
session paired to it) by its kind, its channel and its position among the
requests of that kind and channel.  The third Sensor Request on channel 12 in
A meets the third one in B, whatever came between.

Each pair is then judged: the request's bytes, the answer's fields (the
replayer's vocabulary, ``compare``, field by field and exactly: two
recordings are facts, nothing is forgiven as "varying by nature"), and the
answer's latency beyond a tolerance.  A request only one side has is
missing in B or extra in B.  Each connection's handshake outcome (mode,
password accepted or refused) is compared too.

The violations the session's rules found in a request or its answer are
attached to the difference they concern, with the side of the conversation
that broke the rule: a difference then says whether A, B, both or neither is
at fault.

Sans-IO: the module takes ``RecordedSessions`` (``exchanges.load_exchanges``
builds them from files) or bare connections, so a live mirror can diff
connections as they finish.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING

from whiztap.analyzer.analysis.compare import (
    LATENCY_TOLERANCE_MS,
    CompareMode,
    CompareRules,
    Status,
    answer_key,
    compare,
)
from whiztap.analyzer.analysis.sides import side_of
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.observations import Observation
from whiztap.analyzer.protocol.text import escape

if TYPE_CHECKING:
    from whiztap.analyzer.analysis.exchanges import ClientItem, RecordedConnection

_EXACT = CompareRules(CompareMode.EXACT)
MAX_KEPT = 10_000  # differences kept in full; past that they are only counted


class Kind(StrEnum):
    VALUE = "value"  # the same exchange, different bytes or fields
    TIMING = "timing"  # the answer's latency differs beyond the tolerance
    MISSING = "missing"  # in A, not in B
    EXTRA = "extra"  # in B, not in A
    HANDSHAKE = "handshake"  # the connection's outcome differs


@dataclass(frozen=True, slots=True)
class Breach:
    """A rule one recording broke in the exchange a difference is about."""

    recording: str  # "A" or "B"
    side: str  # "client" or "server" (or "" when the rule does not say)
    rule_id: str
    detail: str


@dataclass(frozen=True, slots=True)
class Difference:
    kind: Kind
    connection: int  # the connection's position (1-based) in both recordings
    exchange: str  # "Sensor Request #2 on channel 12", or "handshake"
    what: str  # what differs, in words
    a: str = ""  # A's side of it ("" when A has none)
    b: str = ""
    breaches: tuple[Breach, ...] = ()

    @property
    def at_fault(self) -> str:
        """Which recording breaks the spec here: "A", "B", "both" or "neither"."""
        who = {b.recording for b in self.breaches}
        return "both" if len(who) == 2 else (who.pop() if who else "neither")


@dataclass(slots=True)
class DiffResult:
    """The differences found: the first ``max_kept`` in full, every one
    counted by kind (two long recordings that differ everywhere must not
    hold a second copy of themselves as differences)."""

    a: str
    b: str
    latency_tolerance_ms: float
    max_kept: int = MAX_KEPT
    exchanges: int = 0  # exchanges compared (pairs, and one-sided ones)
    differences: list[Difference] = field(default_factory=list)
    by_kind: Counter[str] = field(default_factory=Counter)

    @property
    def equal(self) -> bool:
        return not self.by_kind

    @property
    def total(self) -> int:
        return sum(self.by_kind.values())

    def counts(self) -> dict[str, int]:
        return dict(sorted(self.by_kind.items()))

    def add(self, differences: Iterable[Difference]) -> None:
        for d in differences:
            self.by_kind[d.kind.value] += 1
            if len(self.differences) < self.max_kept:
                self.differences.append(d)


# -- pairing ------------------------------------------------------------------------------------


def exchange_key(item: ClientItem) -> tuple[str, int | None]:
    """What a request is paired by: its message (or 'unparsed') and its channel."""
    message = item.obs.message
    if message is None:
        return ("unparsed frame", None)
    return (message.title, getattr(message, "channel", None))


def keyed(items: Iterable[ClientItem]) -> dict[tuple[str, int | None, int], ClientItem]:
    """Each command by (message, channel, position among its message and channel), in stream order."""
    seen: dict[tuple[str, int | None], int] = defaultdict(int)
    out: dict[tuple[str, int | None, int], ClientItem] = {}
    for item in items:
        if item.obs.item.kind is not ItemKind.COMMAND:
            continue
        title, channel = exchange_key(item)
        seen[(title, channel)] += 1
        out[(title, channel, seen[(title, channel)])] = item
    return out


def _name(key: tuple[str, int | None, int]) -> str:
    title, channel, n = key
    return f"{title} #{n}" + (f" on channel {channel}" if channel is not None else "")


# -- judging ------------------------------------------------------------------------------------


def _breaches(label: str, *observations: Observation | None) -> list[Breach]:
    return [Breach(label, side_of(v.rule_id, str(o.direction)), v.rule_id, v.detail)
            for o in observations if o is not None for v in o.violations]


def _unanswered(label: str, item: ClientItem) -> list[Breach]:
    """The session's verdict on a request that certainly asked and got no
    answer (PW-PAIR-UNANSWERED, which it reports after the item, so the item
    does not carry it)."""
    key = answer_key(item.obs)
    if item.answer is None and key is not None and key[1]:
        return [Breach(label, "server", "PW-PAIR-UNANSWERED", "the request got no answer")]
    return []


def _exchange_breaches(label: str, item: ClientItem) -> list[Breach]:
    return _breaches(label, item.obs, item.answer) + _unanswered(label, item)


def _answer_text(answer: Observation | None) -> str:
    if answer is None:
        return "no answer"
    return escape(answer.item.raw)


def _pair(conn: int, key: tuple[str, int | None, int], a: ClientItem, b: ClientItem,
          tolerance_ns: int) -> list[Difference]:
    name = _name(key)
    breaches = tuple(_exchange_breaches("A", a) + _exchange_breaches("B", b))
    out = []
    if a.obs.item.raw != b.obs.item.raw:
        out.append(Difference(Kind.VALUE, conn, name, "the request's bytes",
                              escape(a.obs.item.raw), escape(b.obs.item.raw), breaches))
    verdict = compare(a.answer, b.answer, _EXACT)
    if verdict.status is Status.MISSING:
        out.append(Difference(Kind.MISSING, conn, name, "the answer", _answer_text(a.answer), "no answer", breaches))
    elif verdict.status is Status.EXTRA:
        out.append(Difference(Kind.EXTRA, conn, name, "the answer", "no answer", _answer_text(b.answer), breaches))
    elif verdict.status is Status.MISMATCH:
        fields = ", ".join(f"{d.field} {d.recorded} -> {d.replayed}" for d in verdict.differences)
        out.append(Difference(Kind.VALUE, conn, name, f"the answer ({fields})",
                              _answer_text(a.answer), _answer_text(b.answer), breaches))
    lat_a = a.answer.latency_ns if a.answer is not None else None
    lat_b = b.answer.latency_ns if b.answer is not None else None
    if lat_a is not None and lat_b is not None and abs(lat_a - lat_b) > tolerance_ns:
        out.append(Difference(Kind.TIMING, conn, name,
                              f"the answer's latency differs by {abs(lat_a - lat_b) / 1e6:.3f} ms",
                              f"{lat_a / 1e6:.3f} ms", f"{lat_b / 1e6:.3f} ms", breaches))
    return out


def _handshake(conn: int, a: RecordedConnection, b: RecordedConnection) -> list[Difference]:
    def outcome(c: RecordedConnection) -> str:
        if not c.handshake:
            return f"{c.mode}, no handshake"
        return f"{c.mode}, password {'refused' if c.refused else 'accepted'}" \
            if c.password is not None else f"{c.mode}, no password sent"

    def titles(c: RecordedConnection) -> list[str]:
        return [h.message.title if h.message else escape(h.item.raw) for h in c.handshake]

    oa, ob = outcome(a), outcome(b)
    if oa == ob and titles(a) == titles(b):
        return []
    breaches = tuple(_breaches("A", *a.handshake) + _breaches("B", *b.handshake))
    what = "the handshake's outcome" if oa != ob else "the handshake's messages"
    if oa == ob:
        oa, ob = ", ".join(titles(a)), ", ".join(titles(b))
    return [Difference(Kind.HANDSHAKE, conn, "handshake", what, oa, ob, breaches)]


def diff_connection(position: int, a: RecordedConnection | None, b: RecordedConnection | None,
                    tolerance_ns: int) -> tuple[int, list[Difference]]:
    """One connection of each recording (None: that recording has no such
    connection): how many exchanges were compared, and their differences."""
    items_a = keyed(a.items) if a is not None else {}
    items_b = keyed(b.items) if b is not None else {}
    out: list[Difference] = []
    if a is not None and b is not None:
        out += _handshake(position, a, b)
    else:
        only = a or b
        if only is None:
            return 0, out
        kind, label = (Kind.MISSING, "A") if b is None else (Kind.EXTRA, "B")
        breaches = [x for i in only.items for x in _exchange_breaches(label, i)]
        out.append(Difference(kind, position, "connection", f"the whole connection ({len(items_a or items_b)} "
                              "requests)", "present" if a else "", "present" if b else "", tuple(breaches)))
        return len(items_a or items_b), out
    for key, item in items_a.items():
        other = items_b.get(key)
        if other is None:
            out.append(Difference(Kind.MISSING, position, _name(key), "the request",
                                  escape(item.obs.item.raw), "", tuple(_exchange_breaches("A", item))))
        else:
            out += _pair(position, key, item, other, tolerance_ns)
    for key, item in items_b.items():
        if key not in items_a:
            out.append(Difference(Kind.EXTRA, position, _name(key), "the request",
                                  "", escape(item.obs.item.raw), tuple(_exchange_breaches("B", item))))
    return len(items_a.keys() | items_b.keys()), out


def diff_sessions(a: Sequence[RecordedConnection], b: Sequence[RecordedConnection], name_a: str = "A",
                  name_b: str = "B", latency_tolerance_ms: float = LATENCY_TOLERANCE_MS,
                  max_kept: int = MAX_KEPT) -> DiffResult:
    """Every connection of ``a`` against ``b``'s in the same position (their
    recorded order)."""
    result = DiffResult(name_a, name_b, latency_tolerance_ms, max_kept)
    tolerance_ns = int(latency_tolerance_ms * 1e6)
    for i in range(max(len(a), len(b))):
        count, differences = diff_connection(i + 1, a[i] if i < len(a) else None,
                                             b[i] if i < len(b) else None, tolerance_ns)
        result.exchanges += count
        result.add(differences)
    return result
