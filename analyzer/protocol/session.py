"""The session model: both directions of one connection, turned into meaning.

Everything that needs context lives here: where the handshake stands
(``handshake``), the channel map the server announced (``channels``), which
request a response answers (``pairing``) and how long it took.  Recorder,
reports, replayer and TUI all read traffic through it.
"""

from __future__ import annotations

from collections import Counter, defaultdict, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

from whiztap.analyzer.protocol.channels import ChannelMap, command_meaning, data_violation
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE, checksum_violation, get_rule
from whiztap.analyzer.protocol.codec import MAX_SENSOR_DATA, MAX_SERVO_DATA, decode, decode_cache
from whiztap.analyzer.protocol.framing import DEFAULT_MAX_IMAGE, DEFAULT_MAX_ITEM, Framer, Item, ItemKind, unasked
from whiztap.analyzer.protocol.handshake import SENDCHKPASS, SERVER_STEPS, HandshakeState, Mode, Step, advance, outcome
from whiztap.analyzer.protocol.messages import (
    ChannelConfig,
    ChannelResponse,
    ConfigurationSettings,
    FetchConfiguration,
    Message,
    ServoPositionRequest,
    SetConfiguration,
)
from whiztap.analyzer.protocol.observations import (
    Direction, Event, Observation, direction_violation, line_break_violation)
from whiztap.analyzer.protocol.pairing import Awaited, Book, Pending, answer_spec
from whiztap.analyzer.protocol.rules import Violation
from whiztap.analyzer.protocol.stats import LatencyStats

_S, _St = HandshakeState, Step
_SERVER_KINDS = frozenset({ItemKind.RESPONSE, ItemKind.CONFIG, ItemKind.IMAGE})
_FRAME_KINDS = frozenset({ItemKind.COMMAND, ItemKind.SET_CONFIG, ItemKind.RESPONSE, ItemKind.CONFIG, ItemKind.IMAGE})


@dataclass(frozen=True, slots=True)
class Limits:
    """How long a request may wait for its answer, and how large an item may
    grow, for every command that judges traffic (``--answer-timeout``,
    ``--max-frame``, ``--max-image``; docs/protocol.md)."""

    answer_timeout_ns: int = 5_000_000_000
    max_frame: int = DEFAULT_MAX_ITEM
    max_image: int = DEFAULT_MAX_IMAGE
    # ``--channels``/``--assume-config``: the map a session starts with, for
    # clients that never fetch the configuration (docs/analyze.md)
    assumed_channels: tuple[ChannelConfig, ...] = ()

    def session(self, checksum_rule: str = DEFAULT_CHECKSUM_RULE, clean_commands: bool = True) -> Session:
        return Session(checksum_rule, self.answer_timeout_ns, self.max_frame, clean_commands, self.max_image,
                       self.assumed_channels)

    def as_dict(self) -> dict[str, int | list[list[int]]]:
        """For the writer process's configuration (JSON); ``from_dict`` reads it back."""
        return {"answer_timeout_ns": self.answer_timeout_ns, "max_frame": self.max_frame,
                "max_image": self.max_image,
                "assumed_channels": [[c.unit_type, c.unused, c.switch_type] for c in self.assumed_channels]}

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> Limits:
        channels = tuple(ChannelConfig(*c) for c in values.get("assumed_channels", ()))
        return cls(**{k: v for k, v in values.items() if k != "assumed_channels"}, assumed_channels=channels)


EARLY_KEPT = 64  # client items held while they may be a password sent before 'sendchkpass'


class _Plan(NamedTuple):
    """What a command's bytes mean in the current channel map, once worked out."""

    message: Message | None
    candidates: tuple[Message, ...]
    violations: tuple[Violation, ...]
    answer_kind: ItemKind | None
    channel: int | None
    certain: bool


_new = tuple.__new__  # NamedTuples without their Python-level __new__, on the hot path
_FastLocals = tuple[list[Event], Callable[[Event], None], Awaited, Book, deque[Pending], int, bool, int]


class Session:
    """Feed it both directions of one connection; it yields events.

    ``receive()`` takes a chunk as it arrived on one direction; ``end()`` says one
    direction closed; ``close()`` ends the session and reports requests left
    unanswered.
    """

    def __init__(
        self,
        checksum_rule: str = DEFAULT_CHECKSUM_RULE,
        answer_timeout_ns: int = 5_000_000_000,
        max_item: int = DEFAULT_MAX_ITEM,
        clean_commands: bool = True,
        max_image: int = DEFAULT_MAX_IMAGE,
        assumed_channels: tuple[ChannelConfig, ...] = (),
    ) -> None:
        """``clean_commands=False`` leaves out of the events the commands of
        established traffic that broke no rule: they are counted and paired all
        the same (a response's ``answers`` still names them).  For consumers
        that only aggregate, like ``whiztap analyze``: most frames are such
        commands, and not handing them over saves a pass over them.
        ``assumed_channels``: the map stated by the user, used until the server
        announces its own (``assumed`` says whether it still stands)."""
        self.checksum_rule = get_rule(checksum_rule)
        self.clean_commands = clean_commands
        self.framers = {Direction.C2S: Framer(max_item, max_image), Direction.S2C: Framer(max_item, max_image)}
        self.framers[Direction.C2S].expect_password()  # the client's first line may be its password
        self.state = HandshakeState.START
        self.mode = Mode.UNKNOWN
        self.channel_map: ChannelMap = dict(enumerate(assumed_channels))
        self.assumed = bool(assumed_channels)
        self.counts: Counter[tuple[Direction, ItemKind]] = Counter()
        self.violation_counts: Counter[str] = Counter()
        self.latencies: defaultdict[str, LatencyStats] = defaultdict(LatencyStats)  # by request title
        self.first_t_ns: int | None = None
        self.last_t_ns: int | None = None
        self.awaited = Awaited(answer_timeout_ns, self.violation_counts)  # requests and their deadlines
        # The client's first line (a password item) and what follows it, when they
        # come before the server's first item, which says whether it is a password.
        self._early: list[Item] | None = None
        self._may_hold_early = True  # until the server speaks or the handshake moves on
        self._asks_password = False  # the server began with 'sendchkpass': the first line is the password
        self._asked_t_ns: int | None = None  # when 'sendchkpass' arrived
        self._plans: dict[bytes, _Plan] = {}  # valid for the current channel map only
        self._index = 0
        self._commands = 0
        self._last_kind: dict[Direction, ItemKind | None] = {Direction.C2S: None, Direction.S2C: None}
        self._ended: set[Direction] = set()
        self._closed = False

    # -- input ------------------------------------------------------------------------

    def receive(self, direction: Direction, data: bytes, t_ns: int) -> list[Event]:
        return self._observe_all(direction, self.framers[direction].feed(data, t_ns), t_ns)

    def end(self, direction: Direction, t_ns: int) -> list[Event]:
        if direction in self._ended and not self.framers[direction].buffered:
            return []  # (bytes fed after the end are flushed by another: the close's)
        self._ended.add(direction)
        events = self._observe_all(direction, self.framers[direction].end(t_ns), t_ns)
        if direction is Direction.C2S:
            self._release_early(events, None)
        return events

    def server_unreachable(self, detail: str) -> None:
        """The proxy could not reach the server (``detail`` says why): requests
        left unanswered at close are still reported, as no server reached."""
        self.awaited.ended_why = f"the server was never reached ({detail})"

    def close(self, t_ns: int) -> list[Event]:
        if self._closed:
            return []
        events = self.end(Direction.S2C, t_ns) + self.end(Direction.C2S, t_ns)
        self._release_early(events, None)
        self._closed = True
        self.awaited.close(t_ns, events)
        return events

    # -- state ------------------------------------------------------------------------

    @property
    def handshake_outcome(self) -> str:
        return outcome(self.state, self.mode)

    # -- internals ----------------------------------------------------------------------

    def _observe_all(self, direction: Direction, items: list[Item], t_ns: int) -> list[Event]:
        """Observe items in order.

        Established traffic takes a fast path that builds the same observations
        with far less work: commands whose meaning in the current channel map was
        already worked out (a plan), and responses that answer the oldest request.
        Anything else, or anything with a violation, goes through ``_observe``.
        The loops keep counters in locals and hand them back to ``self`` before
        every slow step, which reads them.
        """
        if direction is Direction.C2S:
            return self._observe_commands(items)
        return self._observe_responses(items)

    def _fast_start(self) -> _FastLocals:
        """The locals both fast paths start from: a new events list and its append,
        the requests awaited, their book and its order, the answer timeout, readiness, the index."""
        events: list[Event] = []
        awaited = self.awaited
        book = awaited.pending
        return (events, events.append, awaited, book, book.order, awaited.timeout_ns, self.state is _S.READY,
                self._index)

    def _observe_commands(self, items: list[Item]) -> list[Event]:
        events, append, awaited, book, pending, timeout, ready, index = self._fast_start()
        plans = self._plans
        command = ItemKind.COMMAND
        direction = Direction.C2S
        every = self.clean_commands
        fast = 0
        t = None
        for item in items:
            kind, raw, _, t, _ = item
            plan = plans.get(raw) if ready and kind is command else None
            if plan is None:
                index, ready = self._slow_step(direction, command, item, events, index, fast)
                fast = 0
                continue
            if pending and t - pending[0][4] > timeout:
                awaited.expire(t, events)
            message, candidates, violations, answer_kind, channel, certain = plan
            index += 1
            fast += 1
            if violations:
                for v in violations:
                    self.violation_counts[v.rule_id] += 1
            elif answer_kind is None and not every:
                continue  # nobody will see it
            obs = _new(Observation, (index - 1, direction, item, message, candidates, violations, None, None))
            if answer_kind is not None:
                if book.live >= awaited.pending_kept:
                    awaited.give_up_oldest(t, events)
                book.add(_new(Pending, (obs, answer_kind, channel, certain, t)))
            if every or violations:
                append(obs)
        self._end_fast(direction, command, index, fast, t)
        return events

    def _observe_responses(self, items: list[Item]) -> list[Event]:
        events, append, _, book, pending, timeout, ready, index = self._fast_start()
        response = ItemKind.RESPONSE
        direction = Direction.S2C
        waited: dict[str, list[int]] = {}  # latencies by request title, added in bulk at the end
        known = decode_cache(response)
        fast = 0
        t = None
        message: ChannelResponse  # read below only once it broke no rule, which makes it a ChannelResponse
        for item in items:
            kind, raw, _, t, _ = item
            if ready and kind is response and pending:
                decoded = known.get(raw) or decode(response, raw)
                message, candidates, violations = decoded  # type: ignore[assignment]  # if read, a ChannelResponse
                head = pending[0]
                request, answer_kind, channel, certain, t_request = head
                if (answer_kind is response and certain and not violations
                        and channel == message.channel and t - t_request <= timeout):
                    asked = request.message  # a request certainly asked: it has its message
                    if asked is not None and message.data <= (
                            MAX_SERVO_DATA if type(asked) is ServoPositionRequest else MAX_SENSOR_DATA):
                        book.pop_oldest()
                        title = asked.title
                        batch = waited.get(title)
                        if batch is None:
                            batch = waited[title] = []
                        batch.append(t - t_request)
                        append(_new(Observation, (index, direction, item, message, candidates, (),
                                                  request, t - t_request)))
                        index += 1
                        fast += 1
                        continue
            index, ready = self._slow_step(direction, response, item, events, index, fast)
            fast = 0
        self._end_fast(direction, response, index, fast, t)
        for title, batch in waited.items():
            self.latencies[title].add_many(batch)
        return events

    def _hand_back(self, direction: Direction, kind: ItemKind, index: int, fast: int) -> None:
        """Give ``self`` the counters a fast path keeps in locals: the index and the ``fast`` items it took."""
        self._index = index
        self.counts[(direction, kind)] += fast
        if kind is ItemKind.COMMAND:
            self._commands += fast

    def _slow_step(self, direction: Direction, kind: ItemKind, item: Item, events: list[Event], index: int,
                   fast: int) -> tuple[int, bool]:
        """A fast path hands ``item`` to ``_observe``: the index and readiness after it."""
        self._hand_back(direction, kind, index, fast)
        self._observe(direction, item, events)
        return self._index, self.state is _S.READY

    def _end_fast(self, direction: Direction, kind: ItemKind, index: int, fast: int, t: int | None) -> None:
        if fast:  # the fast path took the last items: its counters, their kind and time
            self._hand_back(direction, kind, index, fast)
            self._last_kind[direction] = kind
            self.last_t_ns = t

    def _observe(self, direction: Direction, item: Item, events: list[Event]) -> None:
        """The general path: one item of any kind, in any state (the fast paths
        hand over every item they do not take)."""
        if self._may_hold_early:
            if direction is Direction.C2S:
                if self._hold_early(item, events):
                    return
            elif item.kind is not ItemKind.EOL:
                self._release_early(events, item)
        if item.kind is ItemKind.PASSWORD and not self._asks_password:  # no password asked: bytes like any others
            framer = self.framers[Direction.C2S]
            for piece in unasked(item, framer.max_item, framer.max_image):
                self._observe(direction, piece, events)
            return
        kind = item.kind
        t = item.t_end_ns
        if self.first_t_ns is None:
            self.first_t_ns = item.t_start_ns
        self.last_t_ns = t
        self.awaited.expire(t, events)
        decoded = decode(kind, item.raw, item.reason)
        message = decoded.message
        violations = list(decoded.violations)
        candidates = decoded.candidates
        was_ready = self.state is _S.READY
        if kind is ItemKind.HANDSHAKE and message is not None and direction is Direction.S2C:
            self._server_handshake(item, violations, events)
        elif kind in _FRAME_KINDS or kind is ItemKind.PASSWORD or kind is ItemKind.HANDSHAKE:
            message = self._frame(direction, item, message, candidates, violations)
        elif kind is ItemKind.EOL and (broken := line_break_violation(item.raw, self._last_kind[direction])):
            violations.append(broken)
        answers = latency = None
        if direction is Direction.S2C and kind in _SERVER_KINDS:
            answers, latency = self._answer(kind, message, t, violations)
        observation = Observation(self._index, direction, item, message, candidates,
                                  tuple(violations), answers, latency)
        self._index += 1
        self.counts[(direction, kind)] += 1
        self._last_kind[direction] = kind
        for v in violations:
            self.violation_counts[v.rule_id] += 1
        if direction is Direction.C2S and kind is ItemKind.COMMAND:
            self._await_answer(observation, was_ready, t, events)
        events.append(observation)

    def _server_handshake(self, item: Item, violations: list[Violation], events: list[Event]) -> None:
        """A handshake word from the server (SERVER_STEPS)."""
        step = SERVER_STEPS[item.raw]
        t = item.t_end_ns
        if step is not _St.SENDCHKPASS and self._asks_password:
            # a verdict before the password's end: what came of it is observed first
            password_items = self.framers[Direction.C2S].close_password(t)
            events.extend(self._observe_all(Direction.C2S, password_items, t))
        early = self.state is _S.EARLY_PASSWORD
        self._step(step, violations)
        if step is _St.SENDCHKPASS and (self.state is _S.AWAIT_PASSWORD or early):
            self._asked_t_ns = item.t_start_ns

    def _frame(self, direction: Direction, item: Item, message: Message | None,
               candidates: tuple[Message, ...], violations: list[Violation]) -> Message | None:
        """A frame or a password: from the side that sends such items, in its
        place in the handshake; a command's meaning in the channel map."""
        kind = item.kind
        wrong_way = direction_violation(kind, direction)
        if wrong_way is not None:
            violations.append(wrong_way)
            return message
        if direction is Direction.S2C:
            step = _St.SERVER_FRAME
        else:
            step = _St.PASSWORD if kind is ItemKind.PASSWORD else _St.CLIENT_FRAME
        if (step is _St.PASSWORD and self._asked_t_ns is not None
                and item.t_start_ns < self._asked_t_ns and self.state is _S.AWAIT_PASSWORD):
            violations.append(Violation(
                "PW-HS-ORDER", "the password began before the server's 'sendchkpass' arrived"))
        self._step(step, violations)
        if direction is Direction.C2S and kind is not ItemKind.PASSWORD:
            message = self._client_frame(message, candidates, violations)
        return message

    def _await_answer(self, observation: Observation, was_ready: bool, t: int, events: list[Event]) -> None:
        """Book the answer a command waits for; once the traffic is established,
        keep what its bytes mean as a plan for the fast path."""
        answer_kind, channel, certain = answer_spec(observation.message, observation.candidates)
        if answer_kind is not None:
            self.awaited.add(Pending(observation, answer_kind, channel, certain, t), events)
        if was_ready and self.state is _S.READY and self._commands > 1:
            # from now on these bytes mean the same until the channel map changes
            self._plans[observation.item.raw] = _Plan(observation.message, observation.candidates,
                                                      observation.violations, answer_kind, channel, certain)

    def _hold_early(self, item: Item, events: list[Event]) -> bool:
        """Hold the client's first line (a password item) and what follows it
        until the server's first item says whether it is a password; False
        when the item is to be observed now."""
        if self._early is None:
            if self.state is not _S.START:
                self._may_hold_early = False
                return False
            if item.kind is not ItemKind.PASSWORD:
                return False
            self._early = []
        self._early.append(item)
        if len(self._early) > EARLY_KEPT:
            self._release_early(events, None)  # no server in sight: judge them as they are
        return True

    def _release_early(self, events: list[Event], server_first: Item | None) -> None:
        """The server's first item (None: none will come in time) says whether
        the client's first line is a password ('sendchkpass': it is, sent early);
        the held client items are observed before it."""
        if not self._may_hold_early:
            return
        self._may_hold_early = False
        self._asks_password = server_first is not None and server_first.raw == SENDCHKPASS
        early, self._early = self._early, None
        for held in early or ():
            self._observe(Direction.C2S, held, events)

    def _step(self, step: Step, violations: list[Violation]) -> None:
        self.state, mode, broken = advance(self.state, step)
        if mode is not None:
            self.mode = mode
        if broken is not None:
            violations.append(broken)

    def _client_frame(self, message: Message | None, candidates: tuple[Message, ...],
                      violations: list[Violation]) -> Message | None:
        """Resolve a command's meaning from the channel map and check it fits."""
        self._commands += 1
        message, broken = command_meaning(message, candidates, self.channel_map)
        if broken is not None:
            violations.append(broken)
        if isinstance(message, SetConfiguration):
            self._apply_set_config(message, violations)
        if self._commands == 1 and self.state is _S.READY and not isinstance(message, FetchConfiguration):
            what = message.title if message else "an ambiguous frame" if candidates else "an undecodable frame"
            rule = "PW-VPN-CONFIG-FIRST" if self.mode is Mode.VPN else "PW-WINSOCK-CONFIG-FIRST"
            violations.append(Violation(rule, f"first command was {what}"))
        return message

    def _apply_set_config(self, message: SetConfiguration, violations: list[Violation]) -> None:
        wrong_sum = checksum_violation(message, self.checksum_rule)
        if wrong_sum is not None:
            violations.append(wrong_sum)
            return
        if any(v.rule.severity >= 3 for v in violations):
            return  # a server would not apply a configuration it cannot read
        for entry in message.entries:
            self.channel_map[entry.port] = ChannelConfig(entry.unit_type)
        self._plans.clear()

    def _answer(self, kind: ItemKind, message: Message | None, t: int,
                violations: list[Violation]) -> tuple[Observation | None, int | None]:
        channel = message.channel if isinstance(message, ChannelResponse) else None
        found = self.awaited.take(kind, channel)
        request = None if found is None else found.request
        if found is None:
            violations.append(Violation("PW-PAIR-UNSOLICITED", f"no outstanding request is answered by {kind.words}"))
        if isinstance(message, ConfigurationSettings):
            self.channel_map = dict(enumerate(message.channels))
            self.assumed = False
            self._plans.clear()
        if isinstance(message, ChannelResponse):
            broken = data_violation(message, request, self.channel_map)
            if broken is not None:
                violations.append(broken)
        if found is None or request is None:
            return None, None
        latency = t - found.t_ns
        title = request.message.title if request.message is not None else "Sensor Request"
        self.latencies[title].add(latency)
        return request, latency
