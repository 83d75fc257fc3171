"""Planted server bugs: defects a conformance suite or a fuzzer must catch.

``whiztap probe`` and ``whiztap fuzz`` (issue 28) are only as good as what they
are shown to find, so the simulator can be told to misbehave on purpose:
``Simulator(bugs=("drop-nth",))`` or ``whiztap sim --bug drop-nth``.  Each bug
is one small class with one concern, changing one hook of a connection
(``robot.Hooks``): what is sent on connect, the password check, the answer to
one item, or the replies of one read.  Its docstring says by which rule or
check a suite must catch it; ``CAUGHT_BY`` says it in a word for the table in
docs/simulator.md.

Every bug is deterministic (counters, no randomness) and counts per
connection, so a probe case on its own connection sees the same thing every
run.  A clean simulator creates none of this: its connections have no hooks.
"""

from __future__ import annotations

import re
from typing import ClassVar

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.codec import MAX_CHANNEL, decode, encode
from whiztap.analyzer.protocol.framing import CONFIG_HEADER, FRAME_HEADERS, JPEG_SOI, RESPONSE_HEADER, TRAILER
from whiztap.analyzer.protocol.items import Item, ItemKind
from whiztap.sniffer.sim.robot import Output, Robot, ServerMode

MAX_SENSOR = 1024  # the top of a sensor's range (PW-RANGE-SENSOR)


class Bug:
    """One planted defect, one instance per connection (its counters are that
    connection's).  The hooks do nothing unless a bug overrides them."""

    name: ClassVar[str]
    summary: ClassVar[str]  # what it does wrong, one line
    caught_by: ClassVar[str]  # the rule id or check that must catch it
    needs: ClassVar[ServerMode | None] = None  # the mode it can show in, if only one
    any_password: ClassVar[bool] = False

    def __init__(self, robot: Robot) -> None:
        self.robot = robot

    def greet(self, out: Output) -> None:
        """Change what goes out on connect."""

    def item(self, item: Item, reply: bytes | None, out: Output) -> bytes | None:
        """The answer to send for ``item`` instead of ``reply``."""
        return reply

    def read(self, data: bytes, buffered: int, out: Output) -> None:
        """Change the replies of one read, or crash on it."""

    def crash(self, out: Output) -> None:
        out.crash = self.name


def _response(reply: bytes | None) -> m.ChannelResponse | None:
    """The channel response ``reply`` is, if it is one."""
    if reply is None or not reply.startswith(RESPONSE_HEADER):
        return None
    message = decode(ItemKind.RESPONSE, reply).message
    return message if isinstance(message, m.ChannelResponse) else None


class OutOfRange(Bug):
    """Every Sensor Response reports its reading plus 1025, past the top of
    the sensor range: a suite checking answers' ranges catches it by
    PW-RANGE-SENSOR."""

    name = "out-of-range"
    summary = "every sensor answer's value is past 1024 (the reading plus 1025)"
    caught_by = "PW-RANGE-SENSOR"

    def item(self, item: Item, reply: bytes | None, out: Output) -> bytes | None:
        response = _response(reply)
        if response is None or self.robot.unit_of(response.channel) is not m.UnitType.SENSOR:
            return reply
        return encode(m.ChannelResponse(response.channel, response.data + MAX_SENSOR + 1))


class WrongChannel(Bug):
    """Every Sensor/Servo Response names the next channel (23 wraps to 0), not
    the one asked about: the answer fits no waiting request, caught by
    PW-PAIR-UNSOLICITED (and the request by PW-PAIR-UNANSWERED)."""

    name = "wrong-channel"
    summary = "sensor and servo answers echo the next channel, not the one asked"
    caught_by = "PW-PAIR-UNSOLICITED"

    def item(self, item: Item, reply: bytes | None, out: Output) -> bytes | None:
        response = _response(reply)
        if response is None:
            return reply
        return encode(m.ChannelResponse((response.channel + 1) % (MAX_CHANNEL + 1), response.data))


class BadConfig(Bug):
    """Configuration Settings with a '?' for the last channel's unit type, a
    frame that still ends where its count says: caught by PW-CFG-DIGIT."""

    name = "bad-config"
    summary = "Fetch Configuration is answered with a '?' where a unit-type digit belongs"
    caught_by = "PW-CFG-DIGIT"

    def item(self, item: Item, reply: bytes | None, out: Output) -> bytes | None:
        if reply is None or not reply.startswith(CONFIG_HEADER) or len(reply) < len(CONFIG_HEADER) + 8:
            return reply
        unit = len(reply) - len(TRAILER) - 3  # the last group: unit type, unused, switch type
        return reply[:unit] + b"?" + reply[unit + 1:]


class OutOfOrder(Bug):
    """Answers made in one read (pipelined requests) go out swapped in pairs:
    the second before the first.  No analyzer rule pairs by order (answers pair
    by kind and channel), so a suite catches it by checking that pipelined
    answers come in the order of their requests."""

    name = "out-of-order"
    summary = "pipelined answers go out swapped in pairs (2, 1, 4, 3, ...)"
    caught_by = "answers in request order (probe: pipelining)"

    def read(self, data: bytes, buffered: int, out: Output) -> None:
        answers = [i for i, reply in enumerate(out.replies) if reply.answer]
        replies = out.replies
        for first, second in zip(answers[::2], answers[1::2], strict=False):
            replies[first], replies[second] = replies[second], replies[first]


class DropNth(Bug):
    """Every 5th request that has an answer (on one connection) gets none:
    caught by PW-PAIR-UNANSWERED."""

    name = "drop-nth"
    summary = "every 5th request that has an answer gets none"
    caught_by = "PW-PAIR-UNANSWERED"
    EVERY: ClassVar[int] = 5

    def __init__(self, robot: Robot) -> None:
        super().__init__(robot)
        self.answered = 0

    def item(self, item: Item, reply: bytes | None, out: Output) -> bytes | None:
        if reply is None:
            return None
        self.answered += 1
        return None if self.answered % self.EVERY == 0 else reply


class SplitCrash(Bug):
    """The server crashes when a read ends inside a frame (a frame header or
    part of one is left waiting for the rest): a client whose frames reach the
    server split across TCP reads kills it.  Caught by a suite that splits
    frames (one byte at a time, at field boundaries): the connection and the
    server die."""

    name = "split-crash"
    summary = "the server crashes when a frame reaches it split across TCP reads"
    caught_by = "crash (probe: split frames)"

    def __init__(self, robot: Robot) -> None:
        super().__init__(robot)
        self._held = b""  # the stream's last bytes the framer holds: a suffix of what came

    def read(self, data: bytes, buffered: int, out: Output) -> None:
        self._held = (self._held + data)[-buffered:] if buffered else b""
        head = self._held[:len(RESPONSE_HEADER)]
        if head and any(header.startswith(head) for header in FRAME_HEADERS):
            self.crash(out)


class AnyPassword(Bug):
    """Winsock: whatever the client sends as its password is accepted once it
    is as long as the real one (a shorter one waits for more): a suite sending
    a wrong password catches it by the `readytogo` where `Failed Validation`
    is due."""

    name = "any-password"
    summary = "winsock: any password is accepted (readytogo for a wrong one)"
    caught_by = "Failed Validation for a wrong password (probe: handshake)"
    needs = ServerMode.WINSOCK
    any_password = True


class NoSendchkpass(Bug):
    """Winsock: the server does not send `sendchkpass` on connect, yet still
    waits for the password and answers `readytogo`: caught by PW-HS-ORDER."""

    name = "no-sendchkpass"
    summary = "winsock: no sendchkpass on connect, readytogo all the same"
    caught_by = "PW-HS-ORDER"
    needs = ServerMode.WINSOCK

    def greet(self, out: Output) -> None:
        out.replies.clear()


class BadTrailer(Bug):
    """Every 7th answer that ends in a trailer ends in `-ss2` instead of `-ss1`
    (images have none and are not counted): the client's framer never sees the
    frame end, caught by PW-FRAME-TRUNCATED."""

    name = "bad-trailer"
    summary = "every 7th framed answer ends in -ss2 instead of -ss1"
    caught_by = "PW-FRAME-TRUNCATED"
    EVERY: ClassVar[int] = 7

    def __init__(self, robot: Robot) -> None:
        super().__init__(robot)
        self.framed = 0

    def item(self, item: Item, reply: bytes | None, out: Output) -> bytes | None:
        if reply is None or not reply.endswith(TRAILER):
            return reply
        self.framed += 1
        return reply[:-1] + b"2" if self.framed % self.EVERY == 0 else reply


class CameraLength(Bug):
    """Every camera image's first JPEG segment (APP0, after SOI) has a length
    field one more than its bytes, so whoever walks the segments loses step:
    caught by PW-FRAME-GARBAGE (the image is no image)."""

    name = "camera-length"
    summary = "every camera image's first JPEG segment length is one more than its bytes"
    caught_by = "PW-FRAME-GARBAGE"

    def item(self, item: Item, reply: bytes | None, out: Output) -> bytes | None:
        if reply is None or not reply.startswith(JPEG_SOI) or len(reply) < 6:
            return reply
        length = int.from_bytes(reply[4:6], "big") + 1
        return reply[:4] + length.to_bytes(2, "big") + reply[6:]


class SilentAfterGarbage(Bug):
    """After any bytes that form no frame (garbage, a truncated frame) the
    connection gets no answer again, though it stays open: a suite sending a
    good request after garbage catches it by PW-PAIR-UNANSWERED."""

    name = "silent-after-garbage"
    summary = "after a garbage byte the connection never gets an answer again"
    caught_by = "PW-PAIR-UNANSWERED"

    def __init__(self, robot: Robot) -> None:
        super().__init__(robot)
        self.silent = False

    def item(self, item: Item, reply: bytes | None, out: Output) -> bytes | None:
        if item.kind is ItemKind.UNFRAMED:
            self.silent = True
        return None if self.silent else reply


_THREE_DIGIT_ZERO = re.compile(rb"rr1-([0-9]{1,5})--000--0-ss1")


class CrashOnFrame(Bug):
    """The server crashes on a Sensor Request whose value field is written
    with 3 digits (`rr1-12--000--0-ss1`: only PW-SYNTAX-LEADING-ZERO, a
    warning, which a server must survive).  A fuzzer that mutates digit counts
    reaches it; caught as a crash."""

    name = "crash-on-frame"
    summary = "the server crashes on a Sensor Request whose value field has 3 digits (rr1-12--000--0-ss1)"
    caught_by = "crash (fuzz: digit counts)"

    def item(self, item: Item, reply: bytes | None, out: Output) -> bytes | None:
        match = _THREE_DIGIT_ZERO.fullmatch(item.raw) if item.kind is ItemKind.COMMAND else None
        if match is not None and int(match[1]) <= MAX_CHANNEL \
                and self.robot.unit_of(int(match[1])) is m.UnitType.SENSOR:
            self.crash(out)
        return reply


BUGS: dict[str, type[Bug]] = {bug.name: bug for bug in (
    OutOfRange, WrongChannel, BadConfig, OutOfOrder, DropNth, SplitCrash, AnyPassword, NoSendchkpass,
    BadTrailer, CameraLength, SilentAfterGarbage, CrashOnFrame)}


class BugError(WhiztapError, ValueError):
    """A bug name nobody knows, or one the server's mode cannot show (a
    ValueError too, as every other bad Simulator argument)."""


def check_bugs(names: tuple[str, ...] | list[str], mode: ServerMode) -> tuple[str, ...]:
    """The names, each once, in the order given; BugError names what is wrong."""
    unknown = [name for name in names if name not in BUGS]
    if unknown:
        raise BugError(f"no planted bug {unknown[0]!r}; known: {', '.join(BUGS)}")
    for name in names:
        needs = BUGS[name].needs
        if needs is not None and needs is not mode:
            raise BugError(f"planted bug {name} needs --mode {needs} (the server is in {mode} mode)")
    return tuple(dict.fromkeys(names))


class Planted:
    """A connection's bugs, one instance each, called in the order planted
    (``robot.Hooks``)."""

    def __init__(self, names: tuple[str, ...], robot: Robot) -> None:
        self.bugs = [BUGS[name](robot) for name in names]
        self.any_password = any(bug.any_password for bug in self.bugs)

    def greet(self, out: Output) -> None:
        for bug in self.bugs:
            bug.greet(out)

    def item(self, item: Item, reply: bytes | None, out: Output) -> bytes | None:
        for bug in self.bugs:
            reply = bug.item(item, reply, out)
            if out.crash is not None:
                return None
        return reply

    def read(self, data: bytes, buffered: int, out: Output) -> None:
        for bug in self.bugs:
            bug.read(data, buffered, out)
            if out.crash is not None:
                return


def listing() -> str:
    """``whiztap sim --bugs``: a line per bug, its name and what it does wrong."""
    width = max(map(len, BUGS))
    return "\n".join(f"{name:<{width}}  {bug.summary}" for name, bug in BUGS.items())


def table() -> str:
    """The Markdown table of docs/simulator.md's "Planted bugs" (a test holds the doc to it)."""
    rows = ["| bug | what it does wrong | caught by |", "| --- | --- | --- |"]
    rows += [f"| `{name}` | {bug.summary} | {bug.caught_by} |" for name, bug in BUGS.items()]
    return "\n".join(rows)
