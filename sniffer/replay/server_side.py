"""What the target sent, before the faults, against what the recorded server sent.

A replay through the proxy in the middle (``faults.py``) judges the answers
the replay *receives*, after the faults; a replay that reproduces a recording
made under the same faults judges them against what the recorded client
received (``ReplayOptions.reproduce``), and passes when the client's
experience is the same.  Whether the target itself behaved as the recorded
server did is another question, answered here and reported apart: the
proxy's own reads (what the replay sent, what the target sent, before any
fault acted) go through one session per connection, as a recording's
``/tcp/reads`` do, and each answer the target sent is judged against the
answer the recorded server sent to the same request.  These judgements have
their own counts and differences and do not change the replay's exit status.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from whiztap.analyzer.analysis.compare import answer_key
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import ChannelConfig
from whiztap.analyzer.protocol.observations import Direction, Event, Observation
from whiztap.analyzer.protocol.session import Session
from whiztap.analyzer.traffic import Closed, Data, Gap, HalfClosed, Opened, Traffic, TrafficEvent, UpstreamFailed
from whiztap.sniffer.replay.connection import ReplayedConnection, Slot
from whiztap.sniffer.replay.events import ServerResult
from whiztap.sniffer.replay.tally import Tally

_ANSWER_KINDS = frozenset({ItemKind.RESPONSE, ItemKind.CONFIG, ItemKind.IMAGE})
_ENDS = (HalfClosed, Closed, Gap, UpstreamFailed)


@dataclass(slots=True)
class _Proxied:
    """One of the proxy's connections: the replayed one it carries, once known."""

    local: str
    replayed: ReplayedConnection | None = None
    commands: int = 0  # commands the replay sent on it so far
    slots: dict[int, Slot] = field(default_factory=dict)  # by the request's index in this session
    answered: set[int] = field(default_factory=set)  # ids of the slots the target answered
    handshake: list[Observation] = field(default_factory=list)
    early: list[Event] = field(default_factory=list)  # the session's events before the replay said who it is


class ServerSide:
    """The proxy's reads of a replay, judged against the recorded server's answers."""

    def __init__(self, tally: Tally, checksum_rule: str, timeout_ns: int,
                 assumed_channels: tuple[ChannelConfig, ...] = ()) -> None:
        self.tally = tally
        self._traffic = Traffic(lambda: Session(checksum_rule, answer_timeout_ns=timeout_ns,
                                                assumed_channels=assumed_channels))
        self._conns: dict[int, _Proxied] = {}
        self._replayed: dict[str, ReplayedConnection] = {}

    def attach(self, local: str, replayed: ReplayedConnection) -> None:
        """The replayed connection that connected to the proxy from ``local``."""
        self._replayed[local] = replayed

    def receive(self, event: TrafficEvent) -> None:
        """One of the proxy's traffic events (what crossed it before the faults)."""
        kind = type(event)
        if isinstance(event, Opened):
            self._conns[event.conn] = _Proxied(event.client)
            return
        proxied = self._conns.get(event.conn)
        if proxied is None or kind not in (Data, *_ENDS):
            return  # what each side was delivered, and the changes, are the client side's business
        events = self._traffic.receive(event)
        if proxied.replayed is None:
            proxied.replayed = self._replayed.pop(proxied.local, None)
            if proxied.replayed is None:  # the target speaks first (its sendchkpass), before the replay knows
                proxied.early += events
                return
            events, proxied.early = proxied.early + events, []
        self._observe(proxied, proxied.replayed, events)

    def _observe(self, proxied: _Proxied, c: ReplayedConnection, events: list[Event]) -> None:
        for obs in events:
            if not isinstance(obs, Observation):
                continue
            kind = obs.item.kind
            if obs.direction is Direction.C2S:
                if kind is ItemKind.COMMAND:
                    if proxied.commands < len(c.order):
                        proxied.slots[obs.index] = c.order[proxied.commands]
                    proxied.commands += 1
            elif kind is ItemKind.HANDSHAKE:
                proxied.handshake.append(obs)
                self._judge_handshake(c, proxied, len(proxied.handshake) - 1)
            elif obs.answers is not None and obs.answers.index in proxied.slots:
                slot = proxied.slots.pop(obs.answers.index)
                proxied.answered.add(id(slot))
                self.tally.judge(c.conn, slot.item.answer, obs, slot.item, slot.item.at_rest)
            elif kind in _ANSWER_KINDS:
                self.tally.judge(c.conn, None, obs, None, False)

    def _judge_handshake(self, c: ReplayedConnection, proxied: _Proxied, i: int) -> None:
        recorded = c.plan.recorded.handshake
        mine = recorded[i] if i < len(recorded) else None
        theirs = proxied.handshake[i] if i < len(proxied.handshake) else None
        self.tally.judge(c.conn, mine, theirs, None, False, "the connection" if i == 0 else "the password")

    def finish(self, c: ReplayedConnection) -> None:
        """The replayed connection is over: what the target never sent is judged."""
        found = [(conn, p) for conn, p in self._conns.items()
                 if p.replayed is c or (p.replayed is None and self._replayed.get(p.local) is c)]
        if not found:
            return
        [(conn, proxied)] = found
        del self._conns[conn]  # judged: what the proxy says of it later is no concern of ours
        if proxied.replayed is None:  # nothing but the target's first words crossed it
            proxied.replayed = self._replayed.pop(proxied.local)
            self._observe(proxied, c, proxied.early)
        for i in range(len(proxied.handshake), len(c.plan.recorded.handshake)):
            self._judge_handshake(c, proxied, i)
        for slot in c.order[:proxied.commands]:
            key = answer_key(slot.item.obs)
            if id(slot) not in proxied.answered and (slot.item.answer is not None or (key is not None and key[1])):
                self.tally.judge(c.conn, slot.item.answer, None, slot.item, False)

    def result(self) -> ServerResult:
        return ServerResult(dict(self.tally.counts), tuple(self.tally.differences))
