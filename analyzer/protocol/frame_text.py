"""Frames as people type them, to inject or edit, and a frame judged alone.

Two ways to write a frame:

- escaped text, as ``whiztap decode`` takes it: ``rr1-12--0--0-ss1``,
  ``cr1-12--999--0-ss1\\r\\n``, ``sr1-\\x01000-ss1`` (``\\r``, ``\\n``, ``\\t``,
  ``\\\\`` and ``\\xNN``; see analyzer/protocol/text.py), optionally in quotes;
- the words of the client console (``whiztap client``): ``sensor 12``,
  ``servo 3``, ``servo 3 1500``, ``send 5 100``, ``switch 4 on``, ``script 20``,
  ``script stop internal``, ``config``, ``camera``,
  ``setconfig servo:0-5,sensor:6-23 [CHECKSUM]``.

The console's words live here, not in the console, so that the console, the TUI
and anything else that turns them into a frame make the same bytes.  Words build
the frame they name even when its values break the spec (``sensor 99``): a frame
typed to be injected may be wrong on purpose, and ``check_frame`` says how.

A frame judged alone (``item_alone``, ``frame_alone``, ``check_frame``) is
judged here once for all of whiztap: the proxy in the middle judges each frame
it decides on this way, the Controller a frame typed to inject or edit, the
TUI's dialog the frame as it is typed, ``whiztap decode`` each frame given.
What only a session can tell (the handshake, the channel map, pairing) is left
to ``session.py``.
"""

from __future__ import annotations

from collections.abc import Callable

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.channels import ChannelSpecError, parse_channels
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE, checksum_violation, get_rule
from whiztap.analyzer.protocol.codec import EXTERNAL_SCRIPTS, decode, encode
from whiztap.analyzer.protocol.framing import (
    DEFAULT_MAX_IMAGE, DEFAULT_MAX_ITEM, FRAME_HEADERS, Framer, Item, ItemKind)
from whiztap.analyzer.protocol.messages import (
    ActivateSwitch,
    DeactivateSwitch,
    FetchCameraImage,
    FetchConfiguration,
    Message,
    NormalSend,
    PlayExternalScript,
    PlayInternalScript,
    SensorRequest,
    ServoPositionRequest,
    SetConfigEntry,
    SetConfiguration,
    StopExternalScript,
    StopInternalScript,
)
from whiztap.analyzer.protocol.observations import Direction, Observation, direction_violation
from whiztap.analyzer.protocol.rules import Violation
from whiztap.analyzer.protocol.text import plural, unescape

DEFAULT_DEVICE = 12  # the spec's default Dev#, which setconfig puts in every entry
HEADERS = tuple(header.decode() for header in FRAME_HEADERS)  # typed text that is escaped frame text
SWITCH_ON = ("on", "1", "close")
SWITCH_OFF = ("off", "0", "open")

# Each console word and how it is written (for error messages and completion).
CONSOLE_WORDS: dict[str, str] = {
    "config": "config",
    "camera": "camera",
    "sensor": "sensor CH",
    "servo": "servo CH [VALUE]",
    "send": "send CH VALUE",
    "switch": "switch CH on|off",
    "script": "script N | script stop internal|external",
    "setconfig": "setconfig SPEC [CHECKSUM]",
}


class FrameTextError(WhiztapError, ValueError):
    """The text is no frame; the message says why, in one line."""


def _int(word: str, what: str) -> int:
    try:
        value = int(word)
    except ValueError:
        raise FrameTextError(f"{what} must be a whole number, got {word!r}") from None
    if value < 0:
        raise FrameTextError(f"{what} must not be negative, got {value}")
    return value


def _arity(name: str, args: list[str], *counts: int) -> None:
    if len(args) not in counts:
        raise FrameTextError(f"wrong arguments for {name!r}: {CONSOLE_WORDS[name]}")


def _config(args: list[str]) -> Message:
    _arity("config", args, 0)
    return FetchConfiguration()


def _camera(args: list[str]) -> Message:
    _arity("camera", args, 0)
    return FetchCameraImage()


def _sensor(args: list[str]) -> Message:
    _arity("sensor", args, 1)
    return SensorRequest(_int(args[0], "channel"))


def _servo(args: list[str]) -> Message:
    _arity("servo", args, 1, 2)
    if len(args) == 1:
        return ServoPositionRequest(_int(args[0], "channel"))
    return NormalSend(_int(args[0], "channel"), _int(args[1], "value"))


def _send(args: list[str]) -> Message:
    _arity("send", args, 2)
    return NormalSend(_int(args[0], "channel"), _int(args[1], "value"))


def _switch(args: list[str]) -> Message:
    _arity("switch", args, 2)
    channel = _int(args[0], "channel")
    state = args[1].lower()
    if state in SWITCH_ON:
        return ActivateSwitch(channel)
    if state in SWITCH_OFF:
        return DeactivateSwitch(channel)
    raise FrameTextError(f"switch state must be on or off, got {args[1]!r}")


def _script(args: list[str]) -> Message:
    if args and args[0].lower() == "stop":
        which = args[1].lower() if len(args) == 2 else ""
        if which == "internal":
            return StopInternalScript()
        if which == "external":
            return StopExternalScript()
        raise FrameTextError("usage: script stop internal|external")
    _arity("script", args, 1)
    number = _int(args[0], "script number")
    return PlayExternalScript(number) if number in EXTERNAL_SCRIPTS else PlayInternalScript(number)


def _setconfig(args: list[str]) -> Message:
    """Set Configuration Settings for the channels SPEC names, Dev# 12 on each;
    the checksum the default rule computes unless given."""
    _arity("setconfig", args, 1, 2)
    try:
        channels = parse_channels(args[0])
    except ChannelSpecError as e:
        raise FrameTextError(str(e)) from None
    entries = tuple(SetConfigEntry(DEFAULT_DEVICE, port, c.unit_type) for port, c in enumerate(channels))
    if len(args) == 1:
        return SetConfiguration(entries, get_rule(DEFAULT_CHECKSUM_RULE).compute(entries))
    checksum = _int(args[1], "checksum")
    if checksum > 255:
        raise FrameTextError(f"checksum is one byte (0-255), got {checksum}")
    return SetConfiguration(entries, checksum)


_BUILDERS: dict[str, Callable[[list[str]], Message]] = {
    "config": _config, "camera": _camera, "sensor": _sensor, "servo": _servo, "send": _send,
    "switch": _switch, "script": _script, "setconfig": _setconfig,
}


def message_from_words(words: list[str]) -> Message:
    """The message the console's words stand for (the word in any case).
    FrameTextError names what is wrong: an unknown word, the wrong number of
    arguments, a value that is not a whole number 0 or more."""
    if not words:
        raise FrameTextError("no words")
    build = _BUILDERS.get(words[0].lower())
    if build is None:
        raise FrameTextError(f"unknown word {words[0]!r}: expected {', '.join(CONSOLE_WORDS)} "
                             "or escaped frame text (rr1-..., \\r, \\xNN)")
    return build(words[1:])


def _is_escaped(text: str) -> bool:
    return text.startswith(HEADERS) or text[:1] in ("'", '"') or "\\" in text


def frame_from_text(text: str) -> bytes:
    """The bytes ``text`` stands for: escaped text when it starts with a header
    (rr1-, sr1-, cr1-) or a quote or holds a backslash, else console words.
    Surrounding whitespace is not part of the frame (quote the text, or write
    ``\\x20``, to send a space at an end)."""
    text = text.strip()
    if not text:
        raise FrameTextError("no frame given: expected escaped text (rr1-...) or console words (sensor 12)")
    if not _is_escaped(text):
        return encode(message_from_words(text.split()))
    if text[0] in ("'", '"'):
        if len(text) < 2 or text[-1] != text[0]:
            raise FrameTextError(f"no closing quote in {text!r}")
        text = text[1:-1]
    try:
        data = unescape(text)
    except UnicodeEncodeError:
        raise FrameTextError(f"{text!r} holds a character that is no byte (a lone surrogate)") from None
    if not data:
        raise FrameTextError("an empty frame: nothing between the quotes")
    return data


def item_alone(item: Item, direction: Direction, index: int = 0,
               checksum_rule: str = DEFAULT_CHECKSUM_RULE) -> Observation:
    """An item sent in ``direction``, judged as a session judges it where
    that needs no context: its meaning and the rules it breaks (the codec's,
    the direction its kind travels in, the Set Configuration checksum under
    ``checksum_rule``; ValueError for an unknown rule).  What needs the
    session (the handshake, the channel map, pairing) is not judged: one
    frame is no session.  ``index`` numbers it among its sender's items."""
    rule = get_rule(checksum_rule)
    decoded = decode(item.kind, item.raw, item.reason)
    violations = list(decoded.violations)
    wrong_way = direction_violation(item.kind, direction)
    if wrong_way is not None:
        violations.append(wrong_way)
    if isinstance(decoded.message, SetConfiguration):
        wrong_sum = checksum_violation(decoded.message, rule)
        if wrong_sum is not None:
            violations.append(wrong_sum)
    return Observation(index, direction, item, decoded.message, decoded.candidates, tuple(violations))


def frame_alone(data: bytes, direction: Direction, checksum_rule: str = DEFAULT_CHECKSUM_RULE,
                max_item: int = DEFAULT_MAX_ITEM, max_image: int = DEFAULT_MAX_IMAGE,
                ) -> tuple[list[Observation], list[Violation]]:
    """``data`` sent on its own in ``direction``: each item it frames as,
    judged alone (``item_alone``); and PW-FRAME-GARBAGE for the bytes as a
    whole unless they are exactly one complete item.  The first observation
    is what the bytes mean, where something wants one meaning (the held
    frame an edit made, a dropped or injected frame's row)."""
    direction = Direction(direction)
    get_rule(checksum_rule)  # an unknown rule fails whatever the bytes
    framer = Framer(max_item, max_image)
    items = framer.feed(data, 0) + framer.end(0)
    observations = [item_alone(item, direction, index, checksum_rule) for index, item in enumerate(items)]
    kinds = [item.kind for item in items]
    whole = len(kinds) == 1 and kinds[0] not in (ItemKind.UNFRAMED, ItemKind.EOL)
    if whole or any(v.rule_id == "PW-FRAME-GARBAGE" for o in observations for v in o.violations):
        return observations, []
    what = ", ".join(kind.words for kind in kinds) if kinds else "nothing"
    return observations, [Violation("PW-FRAME-GARBAGE", f"not exactly one complete frame: "
                                                        f"{plural(len(data), 'byte')} framed as {what}")]


def check_frame(data: bytes, direction: Direction, checksum_rule: str = DEFAULT_CHECKSUM_RULE) -> list[Violation]:
    """What is wrong with ``data`` sent on its own in ``direction``: every
    rule ``frame_alone`` finds broken, by its items or as a whole."""
    observations, whole = frame_alone(data, direction, checksum_rule)
    return [v for o in observations for v in o.violations] + whole
