"""What a fuzz session is, and sessions generated from the protocol's tables.

A session is the client's side of one connection: a tuple of ``Frame``s, each
sent whole or cut into separate writes (``cuts``), after the answers the frames
before it await or right behind them (``pipelined``).  The password is never
held as bytes in a session: a frame that carries it says how (``secret``), and
the runner puts the real one in only as it writes, so findings, test files and
logs can show a session without the password (docs/fuzz.md).

Generation walks the tables: the handshake the server revealed (Winsock: the
password first), Fetch Configuration Settings, then requests built from the
client messages of ``messages.py`` with fields drawn from the codec's ranges and
channels of the unit each command needs (``codec.UNIT_OF_COMMAND``) in the
configuration the server announced.
"""

from __future__ import annotations

import dataclasses
import itertools
import random
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.codec import (
    EXTERNAL_SCRIPTS,
    INTERNAL_SCRIPTS,
    MAX_CHANNEL,
    MAX_SEND_VALUE,
    UNIT_OF_COMMAND,
    encode,
)
from whiztap.analyzer.protocol.handshake import Mode
from whiztap.analyzer.protocol.text import escape

MAX_FRAMES = 64  # frames in one session: generated, mutated or taken from a recording
MAX_FRAME_BYTES = 4096  # bytes in one frame (a seed's larger items are cut)

# How a frame carries the password: the real one, or spoiled in a way that
# shows nothing of it (a stand-in of the same length, one byte short of it).
SECRETS = ("password", "stand-in", "short", "empty-line")


@dataclass(frozen=True, slots=True)
class Frame:
    """One frame of a session.  ``cuts``: offsets inside ``data`` where it is
    sent as separate writes (split across the server's reads); ``pipelined``:
    sent without first waiting for the answers due; ``secret``: this frame is
    the password in one of the ``SECRETS`` forms (``data`` is then empty)."""

    data: bytes = b""
    cuts: tuple[int, ...] = ()
    pipelined: bool = False
    secret: str = ""

    def wire(self, password: bytes) -> bytes:
        """The bytes written, with the real password put in."""
        if not self.secret:
            return self.data
        return {"password": password, "stand-in": b"x" * len(password), "short": password[:-1],
                "empty-line": b"\r\n"}[self.secret]

    def pieces(self, password: bytes) -> list[bytes]:
        """The writes this frame is sent in."""
        data = self.wire(password)
        edges = [0, *(c for c in self.cuts if 0 < c < len(data)), len(data)]
        return [data[a:b] for a, b in itertools.pairwise(edges) if b > a]

    def shown(self) -> str:
        """The frame as escaped text, the password by name only."""
        text = f"<{self.secret}>" if self.secret else escape(self.data)
        if self.cuts:
            text += f" cut at {','.join(map(str, self.cuts))}"
        return ("(pipelined) " if self.pipelined else "") + text

    def replace(self, **changes: object) -> Frame:
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]  # Frame's own fields only


Session = tuple[Frame, ...]


@dataclass(frozen=True, slots=True)
class Knowledge:
    """What the fuzzer learned of the server before fuzzing: its handshake
    mode and the channels its Configuration Settings announced."""

    mode: Mode = Mode.VPN
    channels: tuple[m.ChannelConfig, ...] = ()
    units: dict[m.UnitType, tuple[int, ...]] = field(default_factory=dict)

    @classmethod
    def of(cls, mode: Mode, channels: Iterable[m.ChannelConfig]) -> Knowledge:
        chs = tuple(channels)
        units = {u: tuple(i for i, c in enumerate(chs) if c.unit_type == u) for u in m.UnitType}
        return cls(mode, chs, units)

    def channel(self, rng: random.Random, unit: m.UnitType | None) -> int:
        """A channel of ``unit`` the server configured, else any channel."""
        choices = self.units.get(unit, ()) if unit is not None else ()
        return rng.choice(choices) if choices else rng.randint(0, MAX_CHANNEL)


def _script(cls: type[m.Message]) -> range:
    return INTERNAL_SCRIPTS if cls is m.PlayInternalScript else EXTERNAL_SCRIPTS


# Each field a client message has, and where its values come from.
FIELD_DOMAINS: dict[str, Callable[[random.Random, Knowledge, type[m.Message]], int]] = {
    "channel": lambda rng, k, cls: k.channel(rng, UNIT_OF_COMMAND.get(cls)),
    "value": lambda rng, k, cls: rng.randint(0, MAX_SEND_VALUE),
    "script": lambda rng, k, cls: rng.choice(_script(cls)),
}
# The client's requests a session draws from: every rr1 message of the table.
# Set Configuration is left out: it changes the robot for every later
# connection, so one execution would change what the next one meets.
REQUESTS: tuple[type[m.Message], ...] = tuple(
    cls for cls in vars(m).values()
    if isinstance(cls, type) and issubclass(cls, m.Message) and cls.sender == "client"
    and cls not in (m.Password, m.SetConfiguration, m.UnknownCommand))
# Requests that have an answer come three times as often: what a server
# computes and sends back is where it goes wrong most.
REQUEST_WEIGHTS = tuple(3 if cls in (m.SensorRequest, m.ServoPositionRequest, m.FetchConfiguration,
                                     m.FetchCameraImage) else 1 for cls in REQUESTS)
SYNC_FRAME = Frame(encode(m.FetchConfiguration()))
"""The request that ends every execution: its answer says the server got through everything before it."""


def request(rng: random.Random, knowledge: Knowledge) -> Frame:
    """One well-formed request, its fields drawn from their domains."""
    cls = rng.choices(REQUESTS, REQUEST_WEIGHTS)[0]
    values = {f.name: FIELD_DOMAINS[f.name](rng, knowledge, cls) for f in dataclasses.fields(cls)}
    return Frame(encode(cls(**values)))


def prelude(knowledge: Knowledge) -> Session:
    """The handshake the mode asks for, then the configuration a client asks first."""
    password = (Frame(secret="password"),) if knowledge.mode is Mode.WINSOCK else ()
    return (*password, SYNC_FRAME)


def generate(rng: random.Random, knowledge: Knowledge) -> Session:
    """A well-formed session: the prelude and one to six requests."""
    return prelude(knowledge) + tuple(request(rng, knowledge) for _ in range(rng.randint(1, 6)))


def normalise(session: Session) -> Session:
    """A session as it may be sent: at most ``MAX_FRAMES`` frames, and the real
    password in the first frame only (a recording masks the client's first
    line and nothing after it, so a later one becomes a stand-in)."""
    out = []
    for i, frame in enumerate(session[:MAX_FRAMES]):
        if i and frame.secret in ("password", "short"):
            frame = frame.replace(secret="stand-in")
        out.append(frame)
    return tuple(out)


def from_recording(items: Iterable[tuple[str, bytes]], knowledge: Knowledge) -> Session:
    """A seed session from a recorded connection's client items, given as
    (kind, bytes): the recorded password (masked in recordings) becomes the
    password frame, line breaks go, and the handshake is the server's."""
    frames = [Frame(raw[:MAX_FRAME_BYTES]) for kind, raw in items if kind not in ("password", "eol") and raw]
    return normalise(prelude(knowledge)[:-1] + tuple(frames))
