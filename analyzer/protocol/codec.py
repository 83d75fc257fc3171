"""Framed items to typed messages and back.

``decode`` looks at one item alone: it reports what the bytes can mean and every
rule the bytes break by themselves.  What needs context (the channel map, the
handshake, the pending request) is the session's job.
"""

from __future__ import annotations

from typing import NamedTuple

from whiztap.analyzer.protocol.framing import (
    CONFIG_HEADER,
    JPEG_SOI,
    SET_CONFIG_PREFIX,
    SET_CONFIG_TRAILER,
    TRAILER,
    ItemKind,
    Unframed,
)
from whiztap.analyzer.protocol.handshake import HANDSHAKE_WORDS
from whiztap.analyzer.protocol.messages import (
    ActivateSwitch,
    CameraImage,
    ChannelConfig,
    ChannelResponse,
    ConfigurationSettings,
    DeactivateSwitch,
    FailedValidation,
    FetchCameraImage,
    FetchConfiguration,
    Message,
    NormalSend,
    Password,
    PlayExternalScript,
    PlayInternalScript,
    ReadyToGo,
    SendCheckPassword,
    SensorRequest,
    ServoPositionRequest,
    SetConfigEntry,
    SetConfiguration,
    StopExternalScript,
    StopInternalScript,
    UnitType,
    UnknownCommand,
)
from whiztap.analyzer.protocol.rules import Violation
from whiztap.analyzer.protocol.text import plural

MAX_CHANNEL = 23
MAX_SEND_VALUE = 2000
MAX_SENSOR_DATA = 1024
MAX_SERVO_DATA = 8000
MAX_CONFIG_CHANNELS = 24
MAX_DEVICE = 127
FETCH_CONFIG_CODE = 24
FETCH_CAMERA_CODE = 29
SERVO_POSITION_CODE = 2
INTERNAL_SCRIPTS = range(11, 267)
EXTERNAL_SCRIPTS = range(270, 276)
STOP_INTERNAL = 267
STOP_EXTERNAL = 269
# Widest field the Layout lines allow, per position (Data1, Data2, Data3).
FIELD_WIDTHS = (2, 4, 3)

# The unit a channel must have for a command to make sense on it.
UNIT_OF_COMMAND: dict[type[Message], UnitType] = {
    NormalSend: UnitType.SERVO,
    ServoPositionRequest: UnitType.SERVO,
    ActivateSwitch: UnitType.SWITCH,
    DeactivateSwitch: UnitType.SWITCH,
    SensorRequest: UnitType.SENSOR,
}

_HANDSHAKE_MESSAGES: dict[bytes, Message] = dict(
    zip(HANDSHAKE_WORDS, (SendCheckPassword(), ReadyToGo(), FailedValidation()))
)
_UNFRAMED_RULES = {
    Unframed.GARBAGE: "PW-FRAME-GARBAGE",
    Unframed.TRUNCATED: "PW-FRAME-TRUNCATED",
    Unframed.OVERSIZE: "PW-FRAME-OVERSIZE",
}


class Decoded(NamedTuple):
    """What one item can mean.

    ``message`` is set when the bytes have exactly one meaning; ``candidates``
    lists every meaning (several for the frames the spec gives more than one).
    A NamedTuple: one is made per distinct frame on the hot path.
    """

    message: Message | None
    candidates: tuple[Message, ...]
    violations: tuple[Violation, ...]

    @property
    def ambiguous(self) -> bool:
        return len(self.candidates) > 1


_NOTHING = Decoded(None, (), ())


def _one(message: Message, violations: list[Violation]) -> Decoded:
    return Decoded(message, (message,), tuple(violations))


def _fixed(name: str, value: int, expected: int, what: str, out: list[Violation]) -> None:
    """PW-FIXED-FIELD, cited in the section of the message ``what`` names."""
    if value != expected:
        out.append(Violation("PW-FIXED-FIELD", f"{what}: {name} must be {expected}, got {value}", what))


def _channel(value: int, candidates: tuple[Message, ...], out: list[Violation]) -> None:
    """PW-RANGE-CHANNEL, cited in the section of the message the channel is
    in: every one it may be, for a frame with several meanings."""
    if value > MAX_CHANNEL:
        titles = [c.title for c in candidates]
        where = titles[0] if len(titles) == 1 else f"{', '.join(titles[:-1])} or {titles[-1]}"
        out.append(Violation("PW-RANGE-CHANNEL", f"channel must be 0-{MAX_CHANNEL}, got {value}", where))


def _parse_fields(raw: bytes, out: list[Violation]) -> tuple[int, int, int] | None:
    """The three decimal fields of an rr1/cr1 frame, noting every syntax slip."""
    body = raw[4:-4]
    fields = body.split(b"--")
    if len(fields) == 3:
        a, b, c = fields
        # the common case, inline for speed: canonical digits within the Layout widths
        if (a.isdigit() and b.isdigit() and c.isdigit() and len(a) <= 2 and len(b) <= 4 and len(c) <= 3
                and (len(a) == 1 or a[0] != 0x30) and (len(b) == 1 or b[0] != 0x30)
                and (len(c) == 1 or c[0] != 0x30)):
            return int(a), int(b), int(c)
    if b" " in body:
        out.append(Violation("PW-SYNTAX-SPACE", f"space at offset {raw.index(b' ')} of the frame"))
        fields = body.replace(b" ", b"").split(b"--")
    if len(fields) != 3 or not all(f.isdigit() for f in fields):  # bytes.isdigit is ASCII-only
        out.append(Violation("PW-SYNTAX-FIELDS",
                             f"expected three decimal fields separated by '--', got {body!r}"))
        return None
    for position, (field, width) in enumerate(zip(fields, FIELD_WIDTHS), start=1):
        if len(field) > 1 and field[0] == 0x30:
            out.append(Violation("PW-SYNTAX-LEADING-ZERO", f"Data{position} written as {field.decode()}"))
        if len(field) > width:
            out.append(Violation("PW-SYNTAX-WIDTH",
                                 f"Data{position} may be at most {width} digits, got {len(field)}"))
    return int(fields[0]), int(fields[1]), int(fields[2])


def _decode_command(raw: bytes) -> Decoded:
    out: list[Violation] = []
    fields = _parse_fields(raw, out)
    if fields is None:
        return Decoded(None, (), tuple(out))
    d1, d2, d3 = fields
    if d3 == SERVO_POSITION_CODE:
        _fixed("Data2", d2, 0, "Servo Position Request", out)
        message = ServoPositionRequest(d1)
        _channel(d1, (message,), out)
        return _one(message, out)
    script: Message | None = None
    if d3 in INTERNAL_SCRIPTS:
        script = PlayInternalScript(d3)
    elif d3 in EXTERNAL_SCRIPTS:
        script = PlayExternalScript(d3)
    elif d3 == STOP_INTERNAL:
        script = StopInternalScript()
    elif d3 == STOP_EXTERNAL:
        script = StopExternalScript()
    if script is not None:
        _fixed("Data1", d1, 0, script.title, out)
        _fixed("Data2", d2, 0, script.title, out)
        return _one(script, out)
    if d3 != 0:
        if d3 > STOP_INTERNAL:
            out.append(Violation("PW-RANGE-SCRIPT",
                                 f"script code must be 11-266, 267, 269 or 270-275, got {d3}"))
        else:
            out.append(Violation("PW-UNKNOWN-COMMAND",
                                 f"Data3 must be 0, 2, a script number or a stop code, got {d3}"))
        return _one(UnknownCommand(d1, d2, d3), out)
    if d1 == FETCH_CONFIG_CODE:
        _fixed("Data2", d2, 0, "Fetch Configuration Settings", out)
        return _one(FetchConfiguration(), out)
    if d1 == FETCH_CAMERA_CODE:
        _fixed("Data2", d2, 0, "Fetch Camera Image", out)
        return _one(FetchCameraImage(), out)
    candidates: tuple[Message, ...]
    if d2 == 0:
        candidates = (SensorRequest(d1), DeactivateSwitch(d1), NormalSend(d1, 0))
    elif d2 == 1:
        candidates = (ActivateSwitch(d1), NormalSend(d1, 1))
    else:
        candidates = (NormalSend(d1, d2),)
    _channel(d1, candidates, out)
    if len(candidates) > 1:
        return Decoded(None, candidates, tuple(out))
    if d2 > MAX_SEND_VALUE:
        out.append(Violation("PW-RANGE-SEND-VALUE", f"Normal Send value must be 0-{MAX_SEND_VALUE}, got {d2}"))
    return _one(candidates[0], out)


_new = tuple.__new__
_new_object = object.__new__
_set_response_channel = vars(ChannelResponse)["channel"].__set__  # the slots' own setters
_set_response_data = vars(ChannelResponse)["data"].__set__


def _decode_response(raw: bytes) -> Decoded:
    # Responses carry readings that rarely repeat, so this runs for most of them:
    # a canonical one is built without the general parser, and its frozen message
    # through the slot setters (the dataclass __init__ costs twice as much).
    fields = raw[4:-4].split(b"--")
    if len(fields) == 3:
        a, b, c = fields
        if (c == b"0" and a.isdigit() and b.isdigit() and len(a) <= 2 and len(b) <= 4
                and (len(a) == 1 or a[0] != 0x30) and (len(b) == 1 or b[0] != 0x30)):
            channel = int(a)
            if channel <= MAX_CHANNEL:
                message = _new_object(ChannelResponse)
                _set_response_channel(message, channel)
                _set_response_data(message, int(b))
                return _new(Decoded, (message, (message,), ()))
    out: list[Violation] = []
    parsed = _parse_fields(raw, out)
    if parsed is None:
        return Decoded(None, (), tuple(out))
    d1, d2, d3 = parsed
    message = ChannelResponse(d1, d2)
    _channel(d1, (message,), out)
    _fixed("Data3", d3, 0, message.title, out)
    return _one(message, out)


def _decode_config(raw: bytes) -> Decoded:
    out: list[Violation] = []
    count = raw[4]
    body = raw[5:-4]
    if count > MAX_CONFIG_CHANNELS:
        out.append(Violation("PW-CFG-COUNT", f"channel count must be at most {MAX_CONFIG_CHANNELS}, got {count}"))
    if not (body.isdigit() and body.isascii()) and body:
        bad = next(i for i, b in enumerate(body) if not 0x30 <= b <= 0x39)
        out.append(Violation("PW-CFG-DIGIT", f"channel {bad // 3}: expected a digit, got byte 0x{body[bad]:02x}"))
        return Decoded(None, (), tuple(out))
    channels = []
    for ch in range(count):
        unit, unused, switch = (body[3 * ch + k] - 0x30 for k in range(3))
        if unit > 2:
            out.append(Violation("PW-CFG-UNIT", f"channel {ch}: unit type must be 0, 1 or 2, got {unit}"))
        if unused != 0:
            out.append(Violation("PW-CFG-UNUSED", f"channel {ch}: unused field must be 0, got {unused}"))
        if switch > 1:
            out.append(Violation("PW-CFG-SWITCH-TYPE", f"channel {ch}: switch type must be 0 or 1, got {switch}"))
        channels.append(ChannelConfig(unit, unused, switch))
    return _one(ConfigurationSettings(tuple(channels)), out)


def _decode_set_config(raw: bytes) -> Decoded:
    out: list[Violation] = []
    if raw.startswith(SET_CONFIG_PREFIX):
        payload = raw[len(SET_CONFIG_PREFIX):-len(SET_CONFIG_TRAILER)]
    else:
        # the Layout line's reading: a raw Data1 byte and a pad byte before -ss1
        out.append(Violation("PW-SETCFG-FORM",
                             "Data1 sent as the raw byte 25 (the Layout line's reading); "
                             "expected the text '25--' as in the spec's example"))
        payload = raw[5:-len(TRAILER) - 1]
        if raw[-5:-4] != b"0":
            out.append(Violation("PW-SETCFG-TRAILER",
                                 f"expected '0' before -ss1, got {raw[-5:-4]!r}"))
    triples, checksum = payload[:-1], payload[-1]
    entries = []
    for i in range(0, len(triples), 3):
        dev, port, unit = triples[i], triples[i + 1], triples[i + 2]
        n = i // 3
        if dev > MAX_DEVICE:
            out.append(Violation("PW-SETCFG-DEV", f"entry {n}: Dev# must be 0-{MAX_DEVICE}, got {dev}"))
        if port > MAX_CHANNEL:
            out.append(Violation("PW-SETCFG-PORT", f"entry {n}: Port# must be 0-{MAX_CHANNEL}, got {port}"))
        if unit > 2:
            out.append(Violation("PW-SETCFG-UNIT", f"entry {n}: unit type must be 0, 1 or 2, got {unit}"))
        entries.append(SetConfigEntry(dev, port, unit))
    if not entries:
        out.append(Violation("PW-SETCFG-EMPTY", "no (Dev#, Port#, unit type) entries"))
    return _one(SetConfiguration(tuple(entries), checksum), out)


def checksum_offset(raw: bytes) -> int | None:
    """Where a Set Configuration frame's checksum byte is (either form), or
    None for any other frame: what a deliberately corrupted frame changes."""
    if raw.startswith(SET_CONFIG_PREFIX) and raw.endswith(SET_CONFIG_TRAILER):
        at = len(raw) - len(SET_CONFIG_TRAILER) - 1
    elif raw.startswith(CONFIG_HEADER + b"\x19") and raw.endswith(TRAILER):
        at = len(raw) - len(TRAILER) - 2
    else:
        return None
    return at if at >= 5 else None


def _decode_image(raw: bytes) -> Decoded:
    return _one(CameraImage("jpeg" if raw.startswith(JPEG_SOI) else "png", raw), [])


_DECODERS = {
    ItemKind.COMMAND: _decode_command,
    ItemKind.RESPONSE: _decode_response,
    ItemKind.CONFIG: _decode_config,
    ItemKind.SET_CONFIG: _decode_set_config,
    ItemKind.IMAGE: _decode_image,
}
# Decoded text frames by bytes: sessions repeat the same commands endlessly, and
# responses take at most 24 x 8001 well-formed values, all of which the response
# cache can hold (a smaller one, emptied when full, kept missing on long sessions
# of servo positions).  Only these small frames are cached; the limits bound
# memory (a few tens of MB at worst) on hostile input.
_CACHES: dict[ItemKind, dict[bytes, Decoded]] = {ItemKind.COMMAND: {}, ItemKind.RESPONSE: {}}
_CACHE_LIMITS = {ItemKind.COMMAND: 65536, ItemKind.RESPONSE: (MAX_CHANNEL + 1) * (MAX_SERVO_DATA + 1)}


def decode_cache(kind: ItemKind) -> dict[bytes, Decoded]:
    """The cache ``decode`` fills for a kind of text frame, for hot loops that look
    up known frames themselves before paying for a call."""
    return _CACHES[kind]


def decode(kind: ItemKind, raw: bytes, reason: Unframed | None = None) -> Decoded:
    """Everything the bytes of one item say on their own.  Never raises."""
    cache = _CACHES.get(kind)
    if cache is not None:
        hit = cache.get(raw)
        if hit is None:
            hit = _DECODERS[kind](raw)
            if len(cache) >= _CACHE_LIMITS[kind]:
                cache.clear()
            cache[raw] = hit
        return hit
    decoder = _DECODERS.get(kind)
    if decoder is not None:
        return decoder(raw)
    if kind is ItemKind.HANDSHAKE:
        return _one(_HANDSHAKE_MESSAGES[raw], [])
    if kind is ItemKind.PASSWORD:
        return _one(Password(raw), [])
    if kind is ItemKind.EOL:
        return _NOTHING
    rule = _UNFRAMED_RULES[reason or Unframed.GARBAGE]
    return Decoded(None, (), (Violation(rule, f"{plural(len(raw), 'byte')} forming no message"),))


def resolve(candidates: tuple[Message, ...], unit: UnitType | None) -> Message | None:
    """Pick the meaning that fits the channel's unit type, if exactly one does."""
    if unit is None:
        return None
    fitting = [c for c in candidates if UNIT_OF_COMMAND.get(type(c)) == unit]
    return fitting[0] if len(fitting) == 1 else None


# -- encoding ---------------------------------------------------------------------------


def _text(header: bytes, d1: int, d2: int, d3: int) -> bytes:
    return b"%s-%d--%d--%d-ss1" % (header, d1, d2, d3)


def encode(message: Message) -> bytes:
    """The exact wire bytes of a message."""
    match message:
        case FetchConfiguration():
            return _text(b"rr1", FETCH_CONFIG_CODE, 0, 0)
        case FetchCameraImage():
            return _text(b"rr1", FETCH_CAMERA_CODE, 0, 0)
        case NormalSend(channel=ch, value=v):
            return _text(b"rr1", ch, v, 0)
        case ActivateSwitch(channel=ch):
            return _text(b"rr1", ch, 1, 0)
        case DeactivateSwitch(channel=ch) | SensorRequest(channel=ch):
            return _text(b"rr1", ch, 0, 0)
        case ServoPositionRequest(channel=ch):
            return _text(b"rr1", ch, 0, SERVO_POSITION_CODE)
        case PlayInternalScript(script=s) | PlayExternalScript(script=s):
            return _text(b"rr1", 0, 0, s)
        case StopInternalScript():
            return _text(b"rr1", 0, 0, STOP_INTERNAL)
        case StopExternalScript():
            return _text(b"rr1", 0, 0, STOP_EXTERNAL)
        case UnknownCommand(data1=a, data2=b, data3=c):
            return _text(b"rr1", a, b, c)
        case ChannelResponse(channel=ch, data=d):
            return _text(b"cr1", ch, d, 0)
        case ConfigurationSettings(channels=chs):
            digits = b"".join(b"%d%d%d" % (c.unit_type, c.unused, c.switch_type) for c in chs)
            return CONFIG_HEADER + bytes([len(chs)]) + digits + TRAILER
        case SetConfiguration(entries=entries, checksum=checksum):
            triples = bytes(b for e in entries for b in (e.device, e.port, e.unit_type))
            return SET_CONFIG_PREFIX + triples + bytes([checksum]) + SET_CONFIG_TRAILER
        case SendCheckPassword() | ReadyToGo() | FailedValidation():
            return message.title.encode()
        case Password(secret=secret):
            return secret
        case CameraImage(data=data):
            return data
    raise TypeError(f"cannot encode {message!r}")

