"""Judging each side by what it did, when the proxy stood in the middle.

With faults, scripts, interception or injection the proxy changes what each
side receives, so what the client sent is not what the server got.  One
session over what both sides *sent* (/tcp/reads) would blame the server for an
answer the proxy dropped, or the client for a checksum the proxy broke.  So a
connection the proxy stood in the middle of (it has a /tcp/delivered or an
/interventions message) is judged in two more sessions:

- the server-side view: what the server received (delivered c2s) and what it
  sent (read s2c);
- the client-side view: what the client sent (read c2s) and what it received
  (delivered s2c).

Each view is kept for the violations about its own side: the server's view
for the server's frames and for the answering (a request never answered, an
answer to nothing: the server's duty), the client's view for the client's
frames.  What a view sees about the other side is matched against that side's
own view: a copy (the same rule on the same bytes) is the other side's
violation, reported once; what is left is the proxy's doing.  Left in the
client's view, an answering violation is the client's experience (the proxy
dropped, delayed or added an answer), reported on the client side; any other
is an intervention's effect, a violation of neither side, and so is an
answering violation that follows directly from a frame the proxy made or
changed (``consequences.py``): the answer to an injected request, the request
an edit replaced, an answer a ``dup`` copied.

Each view's sessions also time the answering: the server's view from the
request as the server received it to the answer it sent, the client's view
from the request as the client sent it to the answer as it received it.

The views begin only when they could differ from the one session of
``Analyzer``: until then the connection is in step (``instep.py``), the
traffic is the same for both sides, and the one session judges it for both
(each read is held here until its delivery shows it, then handed to the one
session).  At the first intervention, or the first delivery out of step
(other bytes, another time, a read still undelivered when anything else
happens, too much held), both views begin as copies of the one session as it
stands, before the reads still held, which then go to the views as they would
have; they are fed from there on.  What the one session found before is both
sides' own, in the order the views would have kept it.

A connection without any of those messages, or never out of step, is judged
by the one session as before: its violations are held here until it ends and
then handed back unchanged (in the middle, its latencies are both sides').
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Callable
from copy import deepcopy
from dataclasses import dataclass, field, replace
from typing import NamedTuple

from whiztap.analyzer.analysis.consequences import Consequences, Key, answer_key, request_key
from whiztap.analyzer.analysis.facts import ViolationRecord
from whiztap.analyzer.analysis.instep import InStep, OutOfStep
from whiztap.analyzer.protocol.observations import Direction, Event, LateViolation, Observation
from whiztap.analyzer.protocol.rules import Violation
from whiztap.analyzer.protocol.session import Session
from whiztap.analyzer.protocol.stats import LatencyStats
from whiztap.analyzer.traffic import (
    Action,
    Closed,
    Data,
    Delivered,
    Gap,
    HalfClosed,
    Intervention,
    Traffic,
    TrafficEvent,
    UpstreamFailed,
)

SERVER, CLIENT = "server", "client"
ANSWERING = frozenset({"PW-PAIR-UNANSWERED", "PW-PAIR-UNSOLICITED"})
ENDS = frozenset({Action.RESET, Action.CLOSE})  # the proxy ending a connection
"""The rules about the answering rather than about one frame: the server's duty."""
CAUSES_SHOWN = 3  # causes named in the detail of a violation only the client saw

Verdict = tuple[ViolationRecord, str | None]  # a violation, and the title of the request it says was never answered
_Held = tuple[ViolationRecord, str | None, Key | None]  # a verdict, and what pairs the request or answer it is about
MakeRecord = Callable[[int, Violation, Observation, int, bool], ViolationRecord]
_Key = tuple[str, str | None, int, int]  # rule, direction, frame length and hash: one violation in both views


def side_of(rule_id: str, direction: str | None) -> str:
    """Whose conduct a violation is about: the answering rules are the
    server's; every other rule is about the frame it was found on, so about
    the side that sent it (a rule that mostly concerns one side's frames, such
    as a malformed Set Configuration, still blames whoever sent that frame)."""
    return SERVER if rule_id in ANSWERING or direction == "s2c" else CLIENT


class Settled(NamedTuple):
    """A connection's judgement, once its sessions ended: the verdicts and,
    past the records kept, the rest counted by (rule, side, request title);
    the interventions' effects; and the server's and the client's latencies
    when they come from the two views (None: the one session's stand)."""

    verdicts: list[Verdict]
    more: Counter
    effects: list[ViolationRecord]
    latencies: dict[str, LatencyStats] | None
    client_latencies: dict[str, LatencyStats] | None = None


@dataclass(slots=True)
class _Connection:
    """One connection's bookkeeping until its sessions end."""

    middle: bool = False
    causes: dict[str, None] = field(default_factory=dict)  # what intervened, in order
    consequences: Consequences = field(default_factory=Consequences)
    ended: tuple[int, str] | None = None  # the proxy reset or closed it: when, and why
    views: bool = False  # out of step: the two views are fed (until then the one session judges)
    step: InStep = field(default_factory=InStep)  # in step: the reads not yet delivered
    held: int = 0  # verdicts held in full; past the cap only counted
    single: list[Verdict] = field(default_factory=list)  # the one session's
    batched: int = 0  # how many of them are in their place (``Sides.batch``)
    fresh: list[_Key] = field(default_factory=list)  # in step: the keys of those not yet in their place
    left: dict[str, dict[_Key, None]] = field(default_factory=lambda: {SERVER: {}, CLIENT: {}})  # see _diverge
    single_more: Counter = field(default_factory=Counter)
    before: int = 0  # how many of ``single`` were found before the views began: both sides'
    before_more: Counter = field(default_factory=Counter)  # and of ``single_more``
    kept: list[Verdict] = field(default_factory=list)  # each view's verdicts on its own side
    more: Counter = field(default_factory=Counter)  # past the cap: (rule, side, title) -> count
    published: dict[str, Counter] = field(default_factory=lambda: {SERVER: Counter(), CLIENT: Counter()})
    waiting: dict[str, dict[_Key, deque[_Held]]] = field(default_factory=lambda: {SERVER: {}, CLIENT: {}})
    latencies: dict[str, LatencyStats] = field(default_factory=dict)  # the server view's
    client_latencies: dict[str, LatencyStats] = field(default_factory=dict)  # the client view's


class Sides:
    """The two views of every connection of a recording made in the middle,
    begun when a connection goes out of step, and the reconciling of what
    they found.

    ``receive`` takes every traffic event but the connection's end (and
    hands the one session, through ``read``, each read once its delivery
    shows it: what it returns is what the one session made of them);
    ``flush`` comes before the one session takes a connection event and
    ``receive`` after; ``single`` takes the violations the analyzer's own
    session found; ``settle`` (when a connection's sessions ended: closed, or
    cut by a gap) and ``finish`` (at the end) say how each connection is
    judged.  Violations are held per connection until then, the first ``cap``
    in full, the rest counted (past the cap, what a view sees of the other
    side is no longer matched: it is left out).  ``lazy=False`` feeds the
    views of every connection from its first event (the way it was done
    before the views were begun lazily; what they find is the same)."""

    def __init__(self, new_session: Callable[[], Session], record: MakeRecord, cap: int, single: Traffic,
                 read: Callable[[Data], list[Event]], lazy: bool = True) -> None:
        """``single``: the analyzer's own sessions (copied when views begin);
        ``read``: hands the analyzer's own session a read."""
        self._record = record
        self._cap = cap
        self._single = single
        self._read = read
        self._lazy = lazy
        self._conns: dict[int, _Connection] = {}
        self.holder: int | None = None  # the one connection that holds reads, if any
        self._views = {SERVER: Traffic(new_session, self._server_ended),
                       CLIENT: Traffic(new_session, self._client_ended)}

    def is_middle(self, conn: int) -> bool:
        c = self._conns.get(conn)
        return c is not None and c.middle

    def judged_alone(self, conn: int) -> bool:
        """Whether the connection is judged by the one session (not in the
        middle, or never out of step so far)."""
        c = self._conns.get(conn)
        return c is None or not (c.middle and c.views)

    def receive(self, event: TrafficEvent) -> list[Event]:
        """One traffic event, into the views it belongs to; what the one
        session made of the reads it was handed meanwhile."""
        kind = type(event)
        if type(event) is Data:
            c = self._conns.get(event.conn) or self._conn(event.conn)
            if c.views:
                events = self._read(event)
                self._feed(SERVER if event.direction is Direction.S2C else CLIENT, event)
                return events
            if not c.step.hold(event):
                return self._diverge(event.conn, c) + self.receive(event)
            self.holder = event.conn
            return []
        if type(event) is Delivered:
            conn, direction, t_ns, data, _secret = event
            c = self._conns.get(conn) or self._conn(conn)
            c.middle = True
            events = []
            if not c.views:
                try:
                    read = c.step.deliver(direction, t_ns, data)
                except OutOfStep:
                    events = self._diverge(conn, c)
                else:
                    if read is None:
                        return events
                    if not c.step.reads:
                        self.holder = None
                    return self._read(read)
            self._feed(SERVER if direction is Direction.C2S else CLIENT, Data(conn, direction, t_ns, data))
            return events
        if type(event) is Intervention:
            c = self._conn(event.conn)
            c.middle = True
            events = [] if c.views else self._diverge(event.conn, c)
            c.causes[str(event.cause)] = None
            c.consequences.note(event)
            if event.action in ENDS and c.ended is None:
                c.ended = (event.t_ns, str(event.cause))
            return events
        if kind is HalfClosed or kind is UpstreamFailed or kind is Closed or kind is Gap:
            known = self._conns.get(event.conn)
            if known is not None and known.views:
                # a sender's FIN ends the stream in both views: the proxy passes it on once it has
                # delivered what it holds, and the recording has no time of its own for that
                self._feed(SERVER, event)
                self._feed(CLIENT, event)
        return []

    def flush(self, conn: int | None = None) -> list[Event]:
        """Before the one session takes a connection event (or the end of the
        traffic), or, with ``conn``, a read of that connection: the
        connection that holds reads (another one, with ``conn``) did not have
        them delivered in step before it, so it goes out of step.  Hence one
        connection at most holds reads, and the one session takes every read
        in the order they came.  What the one session made of them."""
        holder = self.holder
        if holder is None or holder == conn:
            return []
        return self._diverge(holder, self._conns[holder])

    def single(self, conn: int, verdict: Verdict, raw: bytes) -> None:
        """A violation the analyzer's one session found (``raw``: the frame it
        is about): held until the connection is settled, then handed back if
        it was judged alone."""
        c = self._conn(conn)
        if c.held < self._cap:
            c.held += 1
            c.single.append(verdict)
            if not c.views:
                record = verdict[0]
                c.fresh.append((record.rule_id, record.direction, len(raw), hash(raw)))
        else:
            record, title = verdict
            c.single_more[(record.rule_id, record.side, title)] += 1

    def batch(self, conn: int, first: str) -> None:
        """The one session's violations since the last call came from one
        event; in the middle they are put in the order the two views would have
        kept them: the side that took the event first (a read's sender, else
        the server) before the other, each in the order found."""
        c = self._conns.get(conn)
        if c is None or len(c.single) == c.batched:
            return
        single, done = c.single, c.batched
        found = single[done:]
        if c.fresh:  # in step: what the first view found of the other side's would have waited for it
            left = c.left[first]
            for (record, _title), key in zip(found, c.fresh):
                if record.side != first:
                    left.setdefault(key)
            c.fresh = []
        if len(found) > 1 and c.middle:
            single[done:] = [v for v in found if v[0].side == first] + [v for v in found if v[0].side != first]
        c.batched = len(single)

    def settle(self, conn: int, closed: bool) -> Settled:
        """How the connection's sessions that just ended are judged; ``closed``:
        the connection is over (else a gap cut its sessions, and it goes on,
        in step again until shown otherwise: every session begins anew)."""
        c = self._conns.pop(conn, None) if closed else self._conns.get(conn)
        if c is None:
            return Settled([], Counter(), [], None)
        if not closed:
            self._conns[conn] = _Connection(c.middle, c.causes, c.consequences, views=not self._lazy)
        return _judgement(c)

    def provisional(self) -> list[tuple[int, Settled]]:
        """How every connection not yet settled would be judged if its traffic
        ended now (a live verdict), changing nothing; latencies include what
        its open sessions timed so far (in step, the one session's are both sides')."""
        out = []
        for conn, c in self._conns.items():
            settled = _judgement(c)
            if settled.latencies is not None:
                server, client = (self._views[side].sessions.get(conn) for side in (SERVER, CLIENT))
                settled = settled._replace(latencies=_with_open(settled.latencies, server),
                                           client_latencies=_with_open(settled.client_latencies or {}, client))
            elif c.middle:
                single = self._single.sessions.get(conn)
                settled = settled._replace(latencies=_with_open({}, single), client_latencies=_with_open({}, single))
            out.append((conn, settled))
        return out

    def finish(self) -> list[tuple[int, Settled]]:
        """End every view still open (traffic cut short) and settle every connection."""
        for side, view in self._views.items():
            for conn, events in view.finish():
                self._judge(side, conn, events)
        return [(conn, self.settle(conn, closed=True)) for conn in list(self._conns)]

    # -- internals ---------------------------------------------------------------------

    def _conn(self, conn: int) -> _Connection:
        c = self._conns.get(conn)
        if c is None:
            c = self._conns[conn] = _Connection(views=not self._lazy)
        return c

    def _diverge(self, conn: int, c: _Connection) -> list[Event]:
        """The connection goes out of step: both views begin as copies of the
        one session as it stands (the held reads not in it yet), then the held
        reads go to the one session and the views as they would have gone
        (what was delivered of the first one, to its receiver's view);
        returns what the one session made of them."""
        c.views = True
        c.before, c.before_more = len(c.single), Counter(c.single_more)
        # what the views would have matched by now leaves its keys behind, in the order they came (the
        # order effects and the client's answering violations are listed and credited in, at one time)
        c.waiting = {side: {key: deque() for key in keys} for side, keys in c.left.items()}
        c.left = {SERVER: {}, CLIENT: {}}
        session = self._single.sessions.get(conn)
        if session is not None:
            for view in self._views.values():
                view.sessions[conn] = _copy(session)
        reads, delivered = c.step.take()
        if self.holder == conn:
            self.holder = None
        events: list[Event] = []
        for read in reads:
            events += self._read(read)
            direction = read.direction
            self._feed(SERVER if direction is Direction.S2C else CLIENT, read)
            if delivered:
                self._feed(CLIENT if direction is Direction.S2C else SERVER,
                           Data(conn, direction, read.t_ns, read.data[:delivered]))
                delivered = 0
        return events

    def _feed(self, side: str, event: TrafficEvent) -> None:
        events = self._views[side].receive(event)
        if events:
            self._judge(side, event.conn, events)

    def _server_ended(self, conn: int, session: Session) -> None:
        """The server's view ended: its latencies are the server's own (a
        delay the proxy added is not the server's)."""
        _merge(self._conn(conn).latencies, session.latencies)

    def _client_ended(self, conn: int, session: Session) -> None:
        """The client's view ended: its latencies are what the client waited."""
        _merge(self._conn(conn).client_latencies, session.latencies)

    def _judge(self, view: str, conn: int, events: list[Event]) -> None:
        for e in events:
            if type(e) is LateViolation:
                self._found(view, conn, e.violation, e.about, e.t_ns, True)
            elif type(e) is Observation:
                for v in e.violations:
                    self._found(view, conn, v, e, e.item.t_end_ns, False)

    def _found(self, view: str, conn: int, violation: Violation, about: Observation, t: int,
               late: bool) -> None:
        """A violation one view found: kept if it is about the view's own side
        (and noted, so that the other view's copy is known as one), else held
        until the other side's view shows whether that side did it too."""
        c = self._conn(conn)
        rule_id = violation.rule_id
        direction = str(about.direction)
        owner = side_of(rule_id, direction)
        raw = about.item.raw
        key = (rule_id, direction, len(raw), hash(raw))
        other = CLIENT if view == SERVER else SERVER
        title = _unanswered_title(rule_id, about)
        if owner == view:
            waiting = c.waiting[other].get(key)
            if waiting:
                waiting.popleft()  # the other view's copy: this side's violation, reported once
                c.held -= 1
            else:
                c.published[view][key] += 1
            if c.held < self._cap:
                c.held += 1
                record = self._record(conn, violation, about, t, late)
                record.side = owner
                c.kept.append((record, title))
            else:
                c.more[(rule_id, owner, title)] += 1
        elif c.published[other][key]:
            published = c.published[other]
            published[key] -= 1
            if not published[key]:
                del published[key]
        elif c.held < self._cap:
            c.held += 1
            record = self._record(conn, violation, about, t, late)
            record.side = view
            record.cause = c.consequences.cause_of(about.direction)
            pairs = None
            if rule_id == "PW-PAIR-UNSOLICITED":
                pairs = answer_key(about)
            elif rule_id == "PW-PAIR-UNANSWERED":
                pairs = request_key(about)
            c.waiting[view].setdefault(key, deque()).append((record, title, pairs))


def _judgement(c: _Connection) -> Settled:
    """A connection judged on what its views found so far (or by the one
    session alone: not in the middle, or never out of step); the records it
    hands back are copies, so a provisional judgement changes nothing."""
    if not (c.middle and c.views):
        return Settled(list(c.single), Counter(c.single_more), [], None)
    verdicts = c.single[:c.before] + _not_cut(c.kept, c.ended)  # before the views began: both sides'
    effects = [replace(record) for held in c.waiting[SERVER].values() for record, _, _ in held]
    effects += _cut(c.kept, c.ended)
    answering: list[_Held] = []
    for held in c.waiting[CLIENT].values():
        for record, title, pairs in held:
            if record.rule_id in ANSWERING:
                answering.append((record, title, pairs))
            else:
                effects.append(replace(record))
    causes = c.consequences.account([(r.t_ns, r.rule_id, pairs) for r, _, pairs in answering])
    for (record, title, _), cause in zip(answering, causes):
        if cause is None:
            verdicts.append((_experienced(record, c), title))
        else:  # what follows from a frame the proxy made or changed: not the client's experience
            effects.append(replace(record, cause=cause))
    effects.sort(key=lambda r: r.t_ns)
    return Settled(verdicts, c.before_more + c.more, effects, _copied(c.latencies), _copied(c.client_latencies))


def _cut_short(record: ViolationRecord, ended: tuple[int, str] | None) -> bool:
    """A request left unanswered because the proxy reset or closed the
    connection while it waited (found at or after that end): the server had
    no chance to answer, so it is the end's effect, not the server's doing."""
    return ended is not None and record.rule_id == "PW-PAIR-UNANSWERED" and record.t_ns >= ended[0]


def _not_cut(kept: list[Verdict], ended: tuple[int, str] | None) -> list[Verdict]:
    return [v for v in kept if not _cut_short(v[0], ended)]


def _cut(kept: list[Verdict], ended: tuple[int, str] | None) -> list[ViolationRecord]:
    if ended is None:
        return []
    return [replace(record, cause=ended[1]) for record, _ in kept if _cut_short(record, ended)]


def _experienced(record: ViolationRecord, c: _Connection) -> ViolationRecord:
    """An answering violation only the client's view has: what the client
    went through because the proxy intervened, never the server's doing."""
    causes = list(c.causes)
    named = "; ".join(causes[:CAUSES_SHOWN]) + (f"; and {len(causes) - CAUSES_SHOWN} more"
                                                if len(causes) > CAUSES_SHOWN else "")
    return replace(record, side=CLIENT, cause="", detail=(
        f"{record.detail} (the client's experience only: the proxy intervened on this "
        f"connection{': ' + named if named else ''}; the server's view has no such violation)"))


def _copy(session: Session) -> Session:
    """A view's session begun as a copy of the one session: all its state is
    its own (the checksum rule, a shared table, aside); like every view's
    session, it leaves clean commands out of its events."""
    rule = session.checksum_rule
    view = deepcopy(session, {id(rule): rule})
    view.clean_commands = False
    return view


def _merge(into: dict[str, LatencyStats], latencies: dict[str, LatencyStats]) -> None:
    for title, stats in latencies.items():
        into.setdefault(title, LatencyStats()).merge(stats)


def _copied(latencies: dict[str, LatencyStats]) -> dict[str, LatencyStats]:
    out: dict[str, LatencyStats] = {}
    _merge(out, latencies)
    return out


def _with_open(latencies: dict[str, LatencyStats], session: Session | None) -> dict[str, LatencyStats]:
    """``latencies`` and what an open session timed so far."""
    if session is not None:
        _merge(latencies, session.latencies)
    return latencies


def _unanswered_title(rule_id: str, about: Observation) -> str | None:
    """The request title a report counts as never answered (None: another rule)."""
    if rule_id != "PW-PAIR-UNANSWERED":
        return None
    return about.message.title if about.message is not None else "request"
