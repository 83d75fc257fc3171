"""``probe server``'s cases, sans-IO: what whiztap, playing the client, sends a server and expects.

The catalogue is derived from the protocol's tables, not from frames written
out by hand: one answer case per message a client sends (``messages.py``,
``Message.sender``), the range cases from the codec's limits (``codec.py``)
with "one past" found by asking the codec which value it no longer takes,
the malformed frames from the frame headers, separator, trailer and field
widths (``framing.py``, ``codec.FIELD_WIDTHS``), the handshake cases from the
handshake's words (``handshake.py``), and the channels each case uses from the
Configuration Settings the server itself announces (``channels.py``).

Each case (``server_plan.ServerCase``) is steps per connection and what it
expects of the server.  The runner (``whiztap.sniffer.probe.server_run``) plays the steps over a socket
and hands the traffic to ``judging.judge``, which reads it with the analyzer's
own session.  Where the spec leaves the server's behaviour open (closing the
connection after a frame that breaks the spec, an idle client, a camera that
sends nothing), the case says so in ``may_close`` or is skipped with the
reason (docs/protocol.md, "What the probe expects where the spec is silent").
"""

from __future__ import annotations

import fnmatch
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

from whiztap.analyzer.probe.client_cases import Cut
from whiztap.analyzer.probe.server_plan import (
    CLOSE_AFTER_BAD_FRAME,
    DEFAULT_DEV,
    FETCH,
    IDLE_S,
    MANY,
    SECTION_API,
    SECTION_FLOW,
    SECTION_MESSAGES,
    SEPARATOR,
    SLOW_GAP_S,
    SPLIT_GAP_S,
    Mode,
    Pause,
    Send,
    ServerCase,
    Step,
    Target,
    Until,
    canary,
)
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.checksum import get_rule
from whiztap.analyzer.protocol.codec import (
    EXTERNAL_SCRIPTS,
    FIELD_WIDTHS,
    INTERNAL_SCRIPTS,
    MAX_CHANNEL,
    MAX_DEVICE,
    MAX_SEND_VALUE,
    UNIT_OF_COMMAND,
    decode,
    encode,
)
from whiztap.analyzer.protocol.framing import DEFAULT_MAX_ITEM, FRAME_HEADERS, TRAILER, ItemKind
from whiztap.analyzer.protocol.handshake import FAILED_VALIDATION, READYTOGO


def _fixed(*steps: Step) -> Callable[[Target], list[Step]]:
    return lambda target: list(steps)


# -- answers: one case per message a client sends ---------------------------------------------------

_CLIENT_MESSAGES = [c for c in vars(m).values()
                    if isinstance(c, type) and issubclass(c, m.Message) and c.sender == "client"
                    and c not in (m.UnknownCommand, m.Password)]


def _slug(title: str) -> str:
    return "-".join("".join(ch if ch.isalnum() else " " for ch in title.lower()).split())


_ON_CHANNEL: dict[type[m.Message], Callable[[int], m.Message]] = {
    m.NormalSend: lambda ch: m.NormalSend(ch, MAX_SEND_VALUE // 2),
    m.ActivateSwitch: m.ActivateSwitch,
    m.DeactivateSwitch: m.DeactivateSwitch,
    m.SensorRequest: m.SensorRequest,
    m.ServoPositionRequest: m.ServoPositionRequest,
}
"""How to write each command the codec ties to a unit (``UNIT_OF_COMMAND``) on a channel."""


def sample(cls: type[m.Message], target: Target) -> m.Message | str:
    """A valid message of ``cls`` for ``target`` (on the first channel of the
    right unit), or why there is none."""
    unit = UNIT_OF_COMMAND.get(cls)
    if unit is not None:
        channels = target.of_unit(unit)
        return _ON_CHANNEL[cls](channels[0]) if channels else f"the server's configuration has no {unit} channel"
    if cls is m.PlayInternalScript:
        return m.PlayInternalScript(INTERNAL_SCRIPTS[0])
    if cls is m.PlayExternalScript:
        return m.PlayExternalScript(EXTERNAL_SCRIPTS[0])
    if cls is m.SetConfiguration:
        return set_configuration(target, DEFAULT_DEV, 0)
    return cls()


def set_configuration(target: Target, dev: int, port: int) -> m.SetConfiguration:
    """One entry that gives ``port`` the unit it has already (the robot is left as it was), its checksum by the rule."""
    unit = target.channels[port].unit_type if port < len(target.channels) else m.UnitType.SERVO
    entries = (m.SetConfigEntry(dev, port, unit),)
    return m.SetConfiguration(entries, get_rule(target.checksum_rule).compute(entries) & 0xFF)


def _answer_case(cls: type[m.Message]) -> ServerCase:
    answered = cls in (m.FetchConfiguration, m.FetchCameraImage, m.SensorRequest, m.ServoPositionRequest)

    def build(target: Target) -> list[Step] | str:
        message = sample(cls, target)
        if isinstance(message, str):
            return message
        return [Send(encode(message)), Until.ANSWERED] if answered else canary(Send(encode(message)))

    what = "answered, the answer checked" if answered else "no reply, and the server serves on"
    silent = ("the server sent nothing for Fetch Camera Image; the spec does not say what it sends (docs/protocol.md, "
              "A12)") if cls is m.FetchCameraImage else ""
    return ServerCase(f"answer.{_slug(cls.title)}", f"{cls.title}: {what}", cls.title, build, silent_ok=silent)


# -- ranges: lowest, highest and one past of every field with a range --------------------------------


def _past(make: Callable[[int], bytes], meant: type[m.Message], start: int, step: int, limit: int = 8) -> int | None:
    """The first value from ``start`` (going by ``step``) whose frame the codec
    reads as ``meant`` (or as no command at all) breaking a rule: values in
    between are other commands (channel 24 is Fetch Configuration's code,
    script 267 stops the internal script)."""
    value = start
    for _ in range(limit):
        if value < 0:
            return None
        raw = make(value)
        decoded = decode(ItemKind.SET_CONFIG if raw.startswith(b"sr1-") else ItemKind.COMMAND, raw)
        if decoded.violations and (isinstance(decoded.message, m.UnknownCommand)
                                   or any(isinstance(c, meant) for c in decoded.candidates)):
            return value
        value += step
    return None


@dataclass(frozen=True, slots=True)
class _Field:
    """A ranged field of a client message: ``frame(target, value)`` writes it;
    ``bounds(target)``: its lowest and highest valid value there (None: the
    target has none)."""

    name: str
    message: type[m.Message]
    frame: Callable[[Target, int], bytes]
    bounds: Callable[[Target], tuple[int, int] | None]
    answered: bool
    below: bool = False  # the spec's range starts above 0, so a value below it can be written
    ceiling: int | None = None  # the spec's highest, where the target's highest is only what it configured

    @property
    def edges(self) -> tuple[str, ...]:
        return tuple(e for e in _EDGES if e != "below" or self.below)


def _channels(unit: m.UnitType) -> Callable[[Target], tuple[int, int] | None]:
    return lambda t: (min(t.of_unit(unit)), max(t.of_unit(unit))) if t.of_unit(unit) else None


def _first(unit: m.UnitType, t: Target) -> int:
    channels = t.of_unit(unit)
    return channels[0] if channels else 0


_S, _V, _W = m.UnitType.SENSOR, m.UnitType.SERVO, m.UnitType.SWITCH
FIELDS = (
    _Field("sensor-request.channel", m.SensorRequest,
           lambda t, v: encode(m.SensorRequest(v)), _channels(_S), True, ceiling=MAX_CHANNEL),
    _Field("servo-position-request.channel", m.ServoPositionRequest,
           lambda t, v: encode(m.ServoPositionRequest(v)), _channels(_V), True, ceiling=MAX_CHANNEL),
    _Field("normal-send.channel", m.NormalSend,
           lambda t, v: encode(m.NormalSend(v, MAX_SEND_VALUE // 2)), _channels(_V), False, ceiling=MAX_CHANNEL),
    _Field("normal-send.value", m.NormalSend,
           lambda t, v: encode(m.NormalSend(_first(_V, t), v)),
           lambda t: (0, MAX_SEND_VALUE) if t.of_unit(_V) else None, False),
    _Field("switch.channel", m.ActivateSwitch,
           lambda t, v: encode(m.ActivateSwitch(v)), _channels(_W), False, ceiling=MAX_CHANNEL),
    _Field("internal-script", m.PlayInternalScript,
           lambda t, v: encode(m.UnknownCommand(0, 0, v)),
           lambda t: (INTERNAL_SCRIPTS[0], INTERNAL_SCRIPTS[-1]), False, below=True),
    _Field("external-script", m.PlayExternalScript,
           lambda t, v: encode(m.UnknownCommand(0, 0, v)),
           lambda t: (EXTERNAL_SCRIPTS[0], EXTERNAL_SCRIPTS[-1]), False, below=True),
    _Field("set-configuration.dev", m.SetConfiguration,
           lambda t, v: encode(set_configuration(t, v, 0)), lambda t: (0, MAX_DEVICE), False),
    _Field("set-configuration.port", m.SetConfiguration,
           lambda t, v: encode(set_configuration(t, DEFAULT_DEV, v)),
           lambda t: (0, min(MAX_CHANNEL, len(t.channels) - 1)) if t.channels else None, False),
)
_EDGES = {"lowest": "the lowest valid value", "highest": "the highest valid value",
          "below": "one below the range", "above": "one past the range"}


def _range_case(f: _Field, edge: str) -> ServerCase:
    def build(target: Target) -> list[Step] | str:
        bounds = f.bounds(target)
        if bounds is None:
            return f"the server's configuration has nothing {f.name} can address"
        low, high = bounds
        value: int | None = {"lowest": low, "highest": high}.get(edge)
        if edge == "below":
            value = _past(lambda v: f.frame(target, v), f.message, low - 1, -1)
        elif edge == "above":
            value = _past(lambda v: f.frame(target, v), f.message, (high if f.ceiling is None else f.ceiling) + 1, 1)
        if value is None:
            return f"no value {_EDGES[edge]} can be written in {f.name}"
        send = Send(f.frame(target, value))
        if f.answered and edge in ("lowest", "highest"):
            return canary(send, Until.ANSWERED)
        return canary(send)

    valid = edge in ("lowest", "highest")
    return ServerCase(f"range.{f.name}.{edge}", f"{f.name} at {_EDGES[edge]}"
                      + (": served" if valid else ": the server ignores it or closes, and serves on"),
                      f.message.title, build, may_close="" if valid else CLOSE_AFTER_BAD_FRAME)


# -- malformed frames, each followed by the canary ----------------------------------------------------


def _sensor_frame(target: Target) -> bytes:
    """A Sensor Request on the target's first sensor channel: what the malformed,
    split and slow cases send (check ``_with_sensor`` first)."""
    return encode(m.SensorRequest(_first(_S, target)))


def _with_sensor(make: Callable[[Target], list[Step]]) -> Callable[[Target], list[Step] | str]:
    """``make``, on a target with a sensor channel: the frames these cases
    change are Sensor Requests, whose answer no other request takes."""
    return lambda t: make(t) if t.of_unit(_S) else "the server's configuration has no sensor channel"


def _fields(frame: bytes) -> list[bytes]:
    return frame[len(FRAME_HEADERS[0]):-len(TRAILER)].split(SEPARATOR)


def _with_fields(frame: bytes, fields: list[bytes]) -> bytes:
    return frame[:len(FRAME_HEADERS[0])] + SEPARATOR.join(fields) + frame[-len(TRAILER):]


def _widened(position: int, width: int) -> Callable[[Target], list[Step]]:
    def build(target: Target) -> list[Step]:
        frame = _sensor_frame(target)
        fields = _fields(frame)
        fields[position] = fields[position].rjust(width, b"0")
        return canary(Send(_with_fields(frame, fields)))
    return build


def _malformed(name: str, title: str, make: Callable[[bytes, Target], bytes]) -> ServerCase:
    return ServerCase(f"malformed.{name}", f"{title}; then a request the server must answer", SECTION_MESSAGES,
                      _with_sensor(lambda t: canary(Send(make(_sensor_frame(t), t)))), may_close=CLOSE_AFTER_BAD_FRAME)


def _malformed_cases() -> Iterator[ServerCase]:
    header = FRAME_HEADERS[0]
    yield _malformed("header", f"a frame whose header is not {header.decode()!r}", lambda f, t: b"x" + f[1:])
    yield _malformed("trailer", f"a frame whose trailer is not {TRAILER.decode()!r}", lambda f, t: f[:-1] + b"x")
    yield _malformed("separator", "a frame with '-' where '--' separates fields",
                     lambda f, t: f.replace(SEPARATOR, b"-", 1))
    yield _malformed("space", "a frame with a space in it", lambda f, t: f[:len(header)] + b" " + f[len(header):])
    yield _malformed("letter", "a frame with a letter where a digit is due",
                     lambda f, t: _with_fields(f, [b"x", *_fields(f)[1:]]))
    yield _malformed("fields", "a frame with two fields instead of three",
                     lambda f, t: _with_fields(f, _fields(f)[:2]))
    yield _malformed("truncated", "a frame cut short before its trailer", lambda f, t: f[:-len(TRAILER)])
    yield _malformed("garbage", "stray bytes that form no item", lambda f, t: t.garbage())
    yield _malformed("line-break", "a frame followed by CR LF", lambda f, t: f + b"\r\n")
    yield _malformed("oversize", f"a header followed by {DEFAULT_MAX_ITEM} bytes and no trailer",
                     lambda f, t: header + b"1" * DEFAULT_MAX_ITEM)
    yield _malformed("unknown-command", "a command whose codes match no command",
                     lambda f, t: encode(m.UnknownCommand(0, 0, 7)))
    yield _malformed("direction", "a Sensor/Servo Response sent to the server",
                     lambda f, t: encode(m.ChannelResponse(0, 0)))
    yield _malformed("checksum", "a Set Configuration with a wrong checksum",
                     lambda f, t: encode(m.SetConfiguration((m.SetConfigEntry(DEFAULT_DEV, 0, 0),), 0)))
    for position, width in enumerate(FIELD_WIDTHS, start=1):
        for digits in range(2, width + 2):
            wide = digits > width
            yield ServerCase(
                f"malformed.width.data{position}.{digits}-digits",
                f"a Sensor Request with Data{position} written in {digits} digits (leading zeros"
                + (f"; the Layout allows {width})" if wide else ")"),
                SECTION_MESSAGES, _with_sensor(_widened(position - 1, digits)), may_close=CLOSE_AFTER_BAD_FRAME)


# -- the handshake ----------------------------------------------------------------------------------


def _wrong(target: Target) -> bytes:
    """A password that is not the right one: the right one with its last byte changed."""
    pw = target.password or b"x"
    return pw[:-1] + bytes([pw[-1] ^ 0x01])


def _handshake_cases() -> list[ServerCase]:
    w = Mode.WINSOCK
    return [
        ServerCase("handshake.sendchkpass", "the server asks for the password ('sendchkpass') on connect",
                   SECTION_FLOW, _fixed(Until.ASKED), login=False, greeting=True, mode=w),
        ServerCase("handshake.right-password", "the right password: 'readytogo'", SECTION_FLOW,
                   lambda t: [Until.ASKED, Send(t.password), Until.VERDICT], login=False, verdict=READYTOGO, mode=w),
        ServerCase("handshake.wrong-password", "a wrong password: 'Failed Validation'", SECTION_FLOW,
                   lambda t: [Until.ASKED, Send(_wrong(t)), Until.VERDICT], login=False,
                   verdict=FAILED_VALIDATION, mode=w),
        ServerCase("handshake.failed-validation-then-command",
                   "a command after 'Failed Validation' gets no answer", SECTION_FLOW,
                   lambda t: [Until.ASKED, Send(_wrong(t)), Until.VERDICT, Send(FETCH), Pause(0.2)],
                   login=False, verdict=FAILED_VALIDATION, mode=w),
        ServerCase("handshake.command-before-readytogo",
                   "a command instead of the password: not served before 'readytogo'", SECTION_FLOW,
                   _fixed(Until.ASKED, Send(FETCH), Until.VERDICT), login=False, mode=w,
                   may_close="the server closed the connection on a command before 'readytogo' without a verdict"),
        ServerCase("handshake.password-split", "the password one byte at a time: 'readytogo'", SECTION_FLOW,
                   lambda t: [Until.ASKED, Send(t.password, Cut.BYTES, SPLIT_GAP_S), Until.VERDICT], login=False,
                   verdict=READYTOGO, mode=w),
        ServerCase("handshake.password-late", f"the password after {IDLE_S:g} s of silence: 'readytogo'",
                   SECTION_FLOW, lambda t: [Until.ASKED, Pause(IDLE_S), Send(t.password), Until.VERDICT],
                   login=False, verdict=READYTOGO, mode=w,
                   may_close="the server closed the connection while waiting for the password; "
                             "the spec sets no time limit either way"),
        ServerCase("handshake.vpn", "no handshake: the first command, Fetch Configuration, is answered",
                   SECTION_FLOW, _fixed(Send(FETCH), Until.ANSWERED), login=False, mode=Mode.VPN),
    ]


# -- pipelining, splitting, slow, idle and many clients ------------------------------------------------


def _requests(target: Target) -> list[bytes]:
    """Every request with an answer, on every channel that takes it, and Fetch Configuration."""
    frames = [encode(m.SensorRequest(ch)) for ch in target.of_unit(_S)]
    frames += [encode(m.ServoPositionRequest(ch)) for ch in target.of_unit(_V)]
    return frames + [FETCH]


def _mixed(target: Target) -> list[bytes]:
    """The requests with a command that has no reply between each two."""
    quiet = [encode(message) for cls in _CLIENT_MESSAGES
             if cls not in (m.FetchConfiguration, m.FetchCameraImage, m.SensorRequest, m.ServoPositionRequest,
                            m.SetConfiguration, m.PlayInternalScript)
             and not isinstance(message := sample(cls, target), str)]
    out: list[bytes] = []
    for i, frame in enumerate(_requests(target)):
        out += [frame, quiet[i % len(quiet)]] if quiet else [frame]
    return out


def _split_two(target: Target) -> list[Step]:
    first, second = _sensor_frame(target), FETCH
    pieces = (first[:-3], first[-3:] + second[:5], second[5:])
    return [Send(first + second, pieces=pieces, gap_s=SPLIT_GAP_S), Until.ANSWERED]


def _more_cases() -> list[ServerCase]:
    api = SECTION_API
    return [
        ServerCase("pipeline.requests", "every request with an answer, on every channel, in one write: "
                   "all answered, in order", api, lambda t: [Send(b"".join(_requests(t))), Until.ANSWERED]),
        ServerCase("pipeline.mixed", "requests and commands without a reply interleaved in one write",
                   api, lambda t: [Send(b"".join(_mixed(t))), Until.ANSWERED]),
        ServerCase("pipeline.same-channel", "eight requests on one channel in one write: eight answers",
                   api, _with_sensor(lambda t: [Send(_sensor_frame(t) * 8), Until.ANSWERED])),
        ServerCase("split.bytes", "a request written one byte at a time", api,
                   _with_sensor(lambda t: [Send(_sensor_frame(t), Cut.BYTES, SPLIT_GAP_S), Until.ANSWERED])),
        ServerCase("split.every-field", "a request cut at every field boundary (header, separators, trailer)",
                   api, _with_sensor(lambda t: [Send(_sensor_frame(t), Cut.FIELDS, SPLIT_GAP_S), Until.ANSWERED])),
        ServerCase("split.two-frames", "two requests in three writes, the middle one straddling both",
                   api, _with_sensor(_split_two)),
        ServerCase("split.set-configuration", "a Set Configuration (raw bytes) one byte at a time",
                   m.SetConfiguration.title,
                   lambda t: canary(Send(encode(set_configuration(t, DEFAULT_DEV, 0)), Cut.BYTES, SPLIT_GAP_S))),
        ServerCase("slow.client", f"a request one byte every {SLOW_GAP_S * 1000:g} ms", api,
                   _with_sensor(lambda t: [Send(_sensor_frame(t), Cut.BYTES, SLOW_GAP_S), Until.ANSWERED])),
        ServerCase("idle.client", f"{IDLE_S:g} s of silence after the configuration, then a request", api,
                   _fixed(Pause(IDLE_S), *canary()),
                   may_close="the server closed an idle connection; the spec sets no idle limit either way"),
        ServerCase("many.connections", f"{MANY} connections at once, each through the handshake and a request",
                   api, _with_sensor(lambda t: [Send(_sensor_frame(t)), Until.ANSWERED]), connections=MANY),
    ]


def catalogue() -> list[ServerCase]:
    """Every case, in the order they run (the scripts' stop cases after their play cases)."""
    answers = [_answer_case(cls) for cls in _CLIENT_MESSAGES]
    ranges = [_range_case(f, edge) for f in FIELDS for edge in f.edges]
    return [*_handshake_cases(), *answers, *ranges, *_malformed_cases(), *_more_cases()]


def select(cases: Iterable[ServerCase], patterns: Iterable[str]) -> list[ServerCase]:
    """The cases whose id matches one of the glob ``patterns`` (all of them for none)."""
    patterns = list(patterns)
    return [c for c in cases if not patterns or any(fnmatch.fnmatchcase(c.id, p) for p in patterns)]
