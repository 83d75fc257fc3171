"""The session model: both directions of one connection, turned into meaning.

Everything that needs context lives here: the handshake state machine, the
channel map the server announced, which request a response answers and how long
it took.  Recorder, reports, replayer and TUI all read traffic through it.
"""

from __future__ import annotations

from collections import Counter, deque
from enum import StrEnum
from typing import NamedTuple

from analyzer.checksum import DEFAULT_CHECKSUM_RULE, get_rule
from analyzer.codec import MAX_SENSOR_DATA, MAX_SERVO_DATA, UNIT_OF_COMMAND, decode, resolve
from analyzer.framing import DEFAULT_MAX_ITEM, Framer, Item, ItemKind
from analyzer.messages import (
    ChannelConfig,
    ChannelResponse,
    ConfigurationSettings,
    FailedValidation,
    FetchCameraImage,
    FetchConfiguration,
    Message,
    ReadyToGo,
    SendCheckPassword,
    SensorRequest,
    ServoPositionRequest,
    SetConfiguration,
    UnitType,
)
from analyzer.rules import Violation


class Direction(StrEnum):
    C2S = "c2s"  # client to server
    S2C = "s2c"  # server to client

    @property
    def sender(self) -> str:
        return "client" if self is Direction.C2S else "server"


class Mode(StrEnum):
    UNKNOWN = "unknown"
    WINSOCK = "winsock"  # password handshake
    VPN = "vpn"  # no handshake: the first command is Fetch Configuration Settings


class HandshakeState(StrEnum):
    START = "start"
    AWAIT_PASSWORD = "await_password"
    AWAIT_VERDICT = "await_verdict"
    READY = "ready"
    FAILED = "failed"


class Step(StrEnum):
    """What the handshake state machine is fed."""

    SENDCHKPASS = "sendchkpass"
    PASSWORD = "password"
    READYTOGO = "readytogo"
    FAILED = "failed_validation"
    CLIENT_FRAME = "client_frame"
    SERVER_FRAME = "server_frame"


_S, _St = HandshakeState, Step
# (state, step) -> (next state, rule broken or None).  Pairs not listed keep the
# state and break PW-HS-ORDER (or PW-HS-AFTER-FAILED once validation failed).
HANDSHAKE_TABLE: dict[tuple[HandshakeState, Step], tuple[HandshakeState, str | None]] = {
    (_S.START, _St.SENDCHKPASS): (_S.AWAIT_PASSWORD, None),
    (_S.START, _St.CLIENT_FRAME): (_S.READY, None),  # VPN: no handshake
    (_S.START, _St.SERVER_FRAME): (_S.START, None),  # unsolicited: pairing reports it
    (_S.AWAIT_PASSWORD, _St.PASSWORD): (_S.AWAIT_VERDICT, None),
    (_S.AWAIT_PASSWORD, _St.CLIENT_FRAME): (_S.AWAIT_PASSWORD, "PW-HS-COMMAND-BEFORE-READY"),
    (_S.AWAIT_PASSWORD, _St.READYTOGO): (_S.READY, "PW-HS-ORDER"),
    (_S.AWAIT_PASSWORD, _St.FAILED): (_S.FAILED, None),
    (_S.AWAIT_VERDICT, _St.READYTOGO): (_S.READY, None),
    (_S.AWAIT_VERDICT, _St.FAILED): (_S.FAILED, None),
    (_S.AWAIT_VERDICT, _St.CLIENT_FRAME): (_S.AWAIT_VERDICT, "PW-HS-COMMAND-BEFORE-READY"),
    (_S.READY, _St.CLIENT_FRAME): (_S.READY, None),
    (_S.READY, _St.SERVER_FRAME): (_S.READY, None),
}
EXPECTED_IN_STATE = {
    _S.START: "'sendchkpass' from the server or a first command from the client",
    _S.AWAIT_PASSWORD: "the client's password",
    _S.AWAIT_VERDICT: "'readytogo' or 'Failed Validation' from the server",
    _S.READY: "commands and responses",
    _S.FAILED: "the connection to close",
}
_HANDSHAKE_STEPS = {SendCheckPassword: _St.SENDCHKPASS, ReadyToGo: _St.READYTOGO, FailedValidation: _St.FAILED}
_CLIENT_KINDS = frozenset({ItemKind.COMMAND, ItemKind.SET_CONFIG, ItemKind.PASSWORD})
_SERVER_KINDS = frozenset({ItemKind.RESPONSE, ItemKind.CONFIG, ItemKind.IMAGE})
_FRAME_KINDS = frozenset({ItemKind.COMMAND, ItemKind.SET_CONFIG, ItemKind.RESPONSE, ItemKind.CONFIG, ItemKind.IMAGE})
# The item kind that answers each request.
_ANSWER_KIND = {
    FetchConfiguration: ItemKind.CONFIG,
    FetchCameraImage: ItemKind.IMAGE,
    SensorRequest: ItemKind.RESPONSE,
    ServoPositionRequest: ItemKind.RESPONSE,
}


class Observation(NamedTuple):
    """One item of the session with everything known about it when it arrived."""

    index: int  # position in the session, both directions together
    direction: Direction
    item: Item
    message: Message | None  # the meaning, when there is exactly one
    candidates: tuple[Message, ...]  # every meaning the bytes allow
    violations: tuple[Violation, ...]
    answers: Observation | None = None  # for a response: the request it answers
    latency_ns: int | None = None


class LateViolation(NamedTuple):
    """A violation found after the item it concerns (a request never answered)."""

    violation: Violation
    about: Observation
    t_ns: int


Event = Observation | LateViolation


class _Pending(NamedTuple):
    request: Observation
    answer_kind: ItemKind
    channel: int | None
    certain: bool  # False for an ambiguous frame that may be a Sensor Request


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
    ) -> None:
        self.checksum_rule = get_rule(checksum_rule)
        self.answer_timeout_ns = answer_timeout_ns
        self.framers = {Direction.C2S: Framer(max_item), Direction.S2C: Framer(max_item)}
        self.state = HandshakeState.START
        self.mode = Mode.UNKNOWN
        self.channel_map: dict[int, ChannelConfig] = {}
        self.counts: Counter[tuple[Direction, ItemKind]] = Counter()
        self.violation_counts: Counter[str] = Counter()
        self.latencies_ns: dict[str, list[int]] = {}
        self.first_t_ns: int | None = None
        self.last_t_ns: int | None = None
        self._pending: deque[_Pending] = deque()
        self._index = 0
        self._commands = 0
        self._last_kind = {Direction.C2S: None, Direction.S2C: None}
        self._ended: set[Direction] = set()
        self._closed = False

    # -- input ------------------------------------------------------------------------

    def receive(self, direction: Direction, data: bytes, t_ns: int) -> list[Event]:
        return self._observe_all(direction, self.framers[direction].feed(data, t_ns), t_ns)

    def end(self, direction: Direction, t_ns: int) -> list[Event]:
        if direction in self._ended:
            return []
        self._ended.add(direction)
        return self._observe_all(direction, self.framers[direction].end(t_ns), t_ns)

    def close(self, t_ns: int) -> list[Event]:
        if self._closed:
            return []
        events = self.end(Direction.S2C, t_ns) + self.end(Direction.C2S, t_ns)
        self._closed = True
        for pending in self._pending:
            if pending.certain:
                events.append(self._unanswered(pending, t_ns, "the session ended first"))
        self._pending.clear()
        return events

    # -- state ------------------------------------------------------------------------

    @property
    def handshake_outcome(self) -> str:
        if self.mode is Mode.VPN:
            return "none (vpn)"
        return {
            _S.START: "not started",
            _S.AWAIT_PASSWORD: "no password sent",
            _S.AWAIT_VERDICT: "no verdict",
            _S.READY: "readytogo",
            _S.FAILED: "failed validation",
        }[self.state]

    def unit_of(self, channel: int) -> UnitType | None:
        config = self.channel_map.get(channel)
        if config is None or config.unit_type not in (0, 1, 2):
            return None
        return UnitType(config.unit_type)

    # -- internals ----------------------------------------------------------------------

    def _observe_all(self, direction: Direction, items: list[Item], t_ns: int) -> list[Event]:
        events: list[Event] = []
        for item in items:
            self._observe(direction, item, events)
        return events

    def _observe(self, direction: Direction, item: Item, events: list[Event]) -> None:
        kind = item.kind
        t = item.t_end_ns
        if self.first_t_ns is None:
            self.first_t_ns = item.t_start_ns
        self.last_t_ns = t
        if self._pending and t - self._pending[0].request.item.t_end_ns > self.answer_timeout_ns:
            self._expire(t, events)
        decoded = decode(kind, item.raw, item.reason)
        message = decoded.message
        violations = list(decoded.violations)
        candidates = decoded.candidates

        if kind is ItemKind.HANDSHAKE and message is not None and direction is Direction.S2C:
            step = _HANDSHAKE_STEPS[type(message)]
            if step is not _St.SENDCHKPASS:
                # the verdict ends the password: observe the password first
                password_items = self.framers[Direction.C2S].close_password(t)
                events.extend(self._observe_all(Direction.C2S, password_items, t))
            self._step(step, violations)
            if step is _St.SENDCHKPASS and self.state is _S.AWAIT_PASSWORD:
                self.mode = Mode.WINSOCK
                self.framers[Direction.C2S].expect_password()
        elif kind in _FRAME_KINDS or kind is ItemKind.PASSWORD or kind is ItemKind.HANDSHAKE:
            own = _CLIENT_KINDS if direction is Direction.C2S else _SERVER_KINDS
            if kind not in own:
                violations.append(Violation(
                    "PW-DIRECTION", f"a {kind} item came from the {direction.sender}"))
            else:
                if direction is Direction.S2C:
                    step = _St.SERVER_FRAME
                else:
                    step = _St.PASSWORD if kind is ItemKind.PASSWORD else _St.CLIENT_FRAME
                self._step(step, violations)
                if direction is Direction.C2S and kind is not ItemKind.PASSWORD:
                    message = self._client_frame(message, candidates, violations)
        elif kind is ItemKind.EOL:
            if self._last_kind[direction] not in (ItemKind.HANDSHAKE, ItemKind.PASSWORD):
                violations.append(Violation("PW-FRAME-EOL", f"line break {item.raw!r} after a {self._last_kind[direction]}"))

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
            self._expect_answer(observation)
        events.append(observation)

    def _step(self, step: Step, violations: list[Violation]) -> None:
        state = self.state
        transition = HANDSHAKE_TABLE.get((state, step))
        if transition is None:
            rule = "PW-HS-AFTER-FAILED" if state is _S.FAILED else "PW-HS-ORDER"
            violations.append(Violation(rule, f"got {step}, expected {EXPECTED_IN_STATE[state]}"))
            return
        self.state, rule = transition
        if rule is not None:
            violations.append(Violation(rule, f"got {step}, expected {EXPECTED_IN_STATE[state]}"))
        if state is _S.START and step is _St.CLIENT_FRAME:
            self.mode = Mode.VPN

    def _client_frame(self, message: Message | None, candidates: tuple[Message, ...],
                      violations: list[Violation]) -> Message | None:
        """Resolve a command's meaning from the channel map and check it fits."""
        self._commands += 1
        channel = getattr(candidates[0], "channel", None) if candidates else None
        if channel is not None:
            unit = self.unit_of(channel)
            if message is None:
                message = resolve(candidates, unit)
                if message is None:
                    if unit is not None:
                        names = " or ".join(c.title for c in candidates)
                        violations.append(Violation(
                            "PW-UNIT-MISMATCH", f"channel {channel} is a {unit}; the frame means {names}"))
                    elif self.channel_map:
                        violations.append(Violation(
                            "PW-CHANNEL-UNCONFIGURED", f"channel {channel} is not in the server's configuration"))
                    else:
                        names = ", ".join(c.title for c in candidates)
                        violations.append(Violation("PW-AMBIGUOUS", f"may be {names}"))
            elif type(message) in UNIT_OF_COMMAND:
                needed = UNIT_OF_COMMAND[type(message)]
                if unit is not None and unit != needed:
                    violations.append(Violation(
                        "PW-UNIT-MISMATCH", f"{message.title} needs a {needed}; channel {channel} is a {unit}"))
                elif unit is None and self.channel_map:
                    violations.append(Violation(
                        "PW-CHANNEL-UNCONFIGURED", f"channel {channel} is not in the server's configuration"))
        if isinstance(message, SetConfiguration):
            self._apply_set_config(message, violations)
        if self._commands == 1 and self.state is _S.READY and not isinstance(message, FetchConfiguration):
            what = message.title if message else "an ambiguous frame" if candidates else "an undecodable frame"
            rule = "PW-VPN-CONFIG-FIRST" if self.mode is Mode.VPN else "PW-WINSOCK-CONFIG-FIRST"
            violations.append(Violation(rule, f"first command was {what}"))
        return message

    def _apply_set_config(self, message: SetConfiguration, violations: list[Violation]) -> None:
        expected = self.checksum_rule.compute(message.entries)
        if expected != message.checksum:
            violations.append(Violation(
                "PW-SETCFG-CHECKSUM",
                f"expected {expected} ({self.checksum_rule.name}), got {message.checksum}"))
            return
        if any(v.rule.severity >= 3 for v in violations):
            return  # a server would not apply a configuration it cannot read
        for entry in message.entries:
            self.channel_map[entry.port] = ChannelConfig(entry.unit_type)

    def _expect_answer(self, request: Observation) -> None:
        message = request.message
        if message is not None:
            answer_kind = _ANSWER_KIND.get(type(message))
            if answer_kind is not None:
                self._pending.append(_Pending(request, answer_kind, getattr(message, "channel", None), True))
        elif any(isinstance(c, SensorRequest) for c in request.candidates):
            self._pending.append(_Pending(request, ItemKind.RESPONSE, request.candidates[0].channel, False))

    def _answer(self, kind: ItemKind, message: Message | None, t: int,
                violations: list[Violation]) -> tuple[Observation | None, int | None]:
        channel = message.channel if isinstance(message, ChannelResponse) else None
        found = None
        for pending in self._pending:
            if pending.answer_kind is kind and (channel is None or pending.channel == channel):
                found = pending
                break
        if found is None:
            violations.append(Violation("PW-PAIR-UNSOLICITED", f"no outstanding request is answered by a {kind}"))
            request = None
        else:
            self._pending.remove(found)
            request = found.request
        if isinstance(message, ConfigurationSettings):
            self.channel_map = dict(enumerate(message.channels))
        if isinstance(message, ChannelResponse):
            self._check_data(message, request, violations)
        if request is None:
            return None, None
        latency = t - request.item.t_end_ns
        title = request.message.title if request.message is not None else "Sensor Request"
        self.latencies_ns.setdefault(title, []).append(latency)
        return request, latency

    def _check_data(self, message: ChannelResponse, request: Observation | None,
                    violations: list[Violation]) -> None:
        """Sensor data and servo data have different ranges: use what was asked."""
        if request is not None:
            servo: bool | None = isinstance(request.message, ServoPositionRequest)
        else:
            unit = self.unit_of(message.channel)
            servo = None if unit is None else unit is UnitType.SERVO
        if servo is False:
            limit, rule, what = MAX_SENSOR_DATA, "PW-RANGE-SENSOR", "sensor data"
        else:
            limit, rule, what = MAX_SERVO_DATA, "PW-RANGE-SERVO", "servo data" if servo else "sensor or servo data"
        if message.data > limit:
            violations.append(Violation(rule, f"{what} must be 0-{limit}, got {message.data}"))

    def _expire(self, t: int, events: list[Event]) -> None:
        while self._pending and t - self._pending[0].request.item.t_end_ns > self.answer_timeout_ns:
            pending = self._pending.popleft()
            if pending.certain:
                events.append(self._unanswered(pending, t, f"no answer within {self.answer_timeout_ns / 1e9:g} s"))

    def _unanswered(self, pending: _Pending, t: int, why: str) -> LateViolation:
        self.violation_counts["PW-PAIR-UNANSWERED"] += 1
        title = pending.request.message.title if pending.request.message else "request"
        return LateViolation(Violation("PW-PAIR-UNANSWERED", f"{title}: {why}"), pending.request, t)
