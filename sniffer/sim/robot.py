"""A sans-IO model of a Progwhiz Robotics Server: the robot and its connections.

``Robot`` is the shared hardware (channel map, servos, switches, scripts, sensors,
camera); ``RobotConnection`` is one client's view of it (handshake, framing).  No
sockets and no clock: bytes and a time in nanoseconds go in, reply bytes and log
notes come out, so every behaviour is testable exactly and the asyncio server
around it stays thin.

Commands are read with the analyzer's framer and codec, so the simulator accepts
and rejects exactly what the analyzer calls valid, and names the same rule ids.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Protocol

from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE, get_rule
from whiztap.analyzer.protocol.codec import MAX_CHANNEL, MAX_SEND_VALUE, Decoded, decode, encode, resolve
from whiztap.analyzer.protocol.framing import DEFAULT_MAX_ITEM, Framer, Item, ItemKind
from whiztap.analyzer.protocol.rules import Severity
from whiztap.analyzer.protocol.text import escape
from whiztap.sniffer.sim.waveforms import Signal, make_signal

DEFAULT_PASSWORD = "progwhiz"
SERVO_START = 1000  # every servo starts centred
DEFAULT_SERVO_SPEED = 500.0  # position units per second: a full 0-2000 sweep takes 4 s
_SWEEP_CYCLE = 2 * MAX_SEND_VALUE  # up and back down again
_SHOWN = 60  # characters of a frame quoted in a log note

Camera = Callable[[int, float], bytes]  # (frame number, seconds since start) -> image bytes


class ServerMode(StrEnum):
    WINSOCK = "winsock"  # sendchkpass / password / readytogo before any command
    VPN = "vpn"  # commands are served at once


@dataclass(frozen=True, slots=True)
class Note:
    """Something the server would log: ``level`` is a ``logging`` level."""

    level: int
    text: str
    rule_id: str | None = None

    def __str__(self) -> str:
        return f"{self.rule_id}: {self.text}" if self.rule_id else self.text


@dataclass(frozen=True, slots=True)
class Reply:
    data: bytes
    answer: bool  # answers a request (fault injection may drop it); False for handshake text


@dataclass(slots=True)
class Output:
    replies: list[Reply] = field(default_factory=list)
    notes: list[Note] = field(default_factory=list)
    close: bool = False  # send the replies, then close the connection
    crash: str | None = None  # a planted bug (its name) crashes the whole server: nothing more is sent


class Hooks(Protocol):
    """What planted bugs may change in one connection (``sniffer/sim/bugs.py``).

    A clean connection has none (``RobotConnection.hooks is None``), so it pays
    one test per read and per item, nothing more.
    """

    any_password: bool  # every password is right

    def greet(self, out: Output) -> None:
        """Change what the server sends on connect."""

    def item(self, item: Item, reply: bytes | None, out: Output) -> bytes | None:
        """See each item the client sent with the server's answer to it (None:
        none); return the answer to send instead.  Setting ``out.crash`` stops
        the connection's work at once."""

    def read(self, data: bytes, buffered: int, out: Output) -> None:
        """See each read once its items are served: its bytes, how many of the
        stream's last bytes the framer still holds, and the replies about to go."""


@dataclass(slots=True)
class _Servo:
    """Straight-line travel from ``start`` (at ``t0_ns``) towards ``target``."""

    start: float
    t0_ns: int
    target: float

    def position(self, t_ns: int, speed: float) -> float:
        travel = speed * max(0, t_ns - self.t0_ns) / 1e9
        if abs(self.target - self.start) <= travel:
            return self.target
        return self.start + travel if self.target > self.start else self.start - travel


def _sweep(origin: float, travel: float) -> float:
    """Position on a 0..2000..0 triangle, starting upwards from ``origin``."""
    s = (origin + travel) % _SWEEP_CYCLE
    return s if s <= MAX_SEND_VALUE else _SWEEP_CYCLE - s


def _quote(raw: bytes) -> str:
    text = escape(raw)
    return text if len(text) <= _SHOWN else text[:_SHOWN] + f"... ({len(raw)} bytes)"


class Robot:
    """The state one server shares between all its connections, as one robot would.

    While an internal script plays, every servo sweeps 0-2000 and back at the servo
    speed, starting from where it was; when it stops, servos head back to their
    last commanded position.  External scripts change only the script state.
    """

    def __init__(
        self,
        channels: tuple[m.ChannelConfig, ...],
        *,
        seed: int = 0,
        servo_speed: float = DEFAULT_SERVO_SPEED,
        camera: Camera | None = None,
        checksum_rule: str = DEFAULT_CHECKSUM_RULE,
        start_ns: int = 0,
    ) -> None:
        if servo_speed <= 0:
            raise ValueError("servo speed must be positive")
        self.channels = channels
        self.servo_speed = servo_speed
        self.camera = camera
        self.checksum_rule = get_rule(checksum_rule)
        self.start_ns = start_ns
        self.frames = 0  # camera frames taken
        self.switches = [False] * (MAX_CHANNEL + 1)
        self.internal_script: int | None = None
        self.external_script: int | None = None
        self._servos = [_Servo(SERVO_START, start_ns, SERVO_START) for _ in range(MAX_CHANNEL + 1)]
        self._sensors: list[Signal] = [make_signal(seed, ch) for ch in range(MAX_CHANNEL + 1)]
        self._sweep: tuple[int, list[float]] | None = None  # (start time, each servo's origin)

    def connect(self, mode: ServerMode, password: bytes = b"", max_item: int = DEFAULT_MAX_ITEM,
                hooks: Hooks | None = None) -> RobotConnection:
        return RobotConnection(self, mode, password, max_item, hooks)

    # -- what a client can read ------------------------------------------------------------

    def unit_of(self, channel: int) -> m.UnitType | None:
        if channel >= len(self.channels) or self.channels[channel].unit_type not in (0, 1, 2):
            return None
        return m.UnitType(self.channels[channel].unit_type)

    def configuration(self) -> m.ConfigurationSettings:
        return m.ConfigurationSettings(self.channels)

    def sensor_value(self, channel: int, t_ns: int) -> int:
        return self._sensors[channel].value((t_ns - self.start_ns) / 1e9)

    def servo_position(self, channel: int, t_ns: int) -> float:
        if self._sweep is not None:
            t0, origins = self._sweep
            return _sweep(origins[channel], self.servo_speed * max(0, t_ns - t0) / 1e9)
        return self._servos[channel].position(t_ns, self.servo_speed)

    def servo_target(self, channel: int) -> float:
        return self._servos[channel].target

    # -- commands ------------------------------------------------------------------------

    def command(self, decoded: Decoded, raw: bytes, t_ns: int, notes: list[Note]) -> bytes | None:
        """Carry out one decoded command; the reply bytes, if the spec has a reply."""
        errors = [v for v in decoded.violations if v.severity >= Severity.ERROR]
        for v in decoded.violations:
            notes.append(Note(logging.WARNING if errors else logging.INFO,
                              f"{v.detail} in {_quote(raw)}" + (", ignored" if errors else ""), v.rule_id))
        if errors or not decoded.candidates:
            return None
        message = decoded.message
        channel = getattr(decoded.candidates[0], "channel", None)
        if channel is not None:
            unit = self.unit_of(channel)
            if unit is None:
                notes.append(Note(logging.WARNING, f"channel {channel} is not configured; "
                                  f"ignored {_quote(raw)}", "PW-CHANNEL-UNCONFIGURED"))
                return None
            message = resolve(decoded.candidates, unit)
            if message is None:
                names = " or ".join(c.title for c in decoded.candidates)
                notes.append(Note(logging.WARNING, f"channel {channel} is a {unit}, {_quote(raw)} "
                                  f"means {names}; ignored", "PW-UNIT-MISMATCH"))
                return None
        return None if message is None else self._execute(message, t_ns, notes)

    def _execute(self, message: m.Message, t_ns: int, notes: list[Note]) -> bytes | None:
        match message:
            case m.FetchConfiguration():
                return encode(self.configuration())
            case m.FetchCameraImage():
                if self.camera is None:
                    notes.append(Note(logging.INFO, "Fetch Camera Image: the camera is off, no reply"))
                    return None
                self.frames += 1
                return self.camera(self.frames, (t_ns - self.start_ns) / 1e9)
            case m.SensorRequest(channel=ch):
                return encode(m.ChannelResponse(ch, self.sensor_value(ch, t_ns)))
            case m.ServoPositionRequest(channel=ch):
                return encode(m.ChannelResponse(ch, round(self.servo_position(ch, t_ns) * 4)))
            case m.NormalSend(channel=ch, value=value):
                servo = self._servos[ch]
                if self._sweep is None:
                    servo.start, servo.t0_ns = servo.position(t_ns, self.servo_speed), t_ns
                servo.target = value  # under a script, taken up when the script stops
            case m.ActivateSwitch(channel=ch):
                self.switches[ch] = True
            case m.DeactivateSwitch(channel=ch):
                self.switches[ch] = False
            case m.PlayInternalScript(script=n):
                if self._sweep is None:
                    self._sweep = (t_ns, [self.servo_position(ch, t_ns) for ch in range(MAX_CHANNEL + 1)])
                self.internal_script = n
            case m.StopInternalScript():
                self._stop_sweep(t_ns)
                self.internal_script = None
            case m.PlayExternalScript(script=n):
                self.external_script = n
            case m.StopExternalScript():
                self.external_script = None
            case m.SetConfiguration():
                self._set_configuration(message, notes)
        return None

    def _stop_sweep(self, t_ns: int) -> None:
        if self._sweep is None:
            return
        for ch, servo in enumerate(self._servos):
            servo.start, servo.t0_ns = self.servo_position(ch, t_ns), t_ns
        self._sweep = None

    def _set_configuration(self, message: m.SetConfiguration, notes: list[Note]) -> None:
        """Change the units of the listed ports, as the analyzer's session does."""
        expected = self.checksum_rule.compute(message.entries)
        if expected != message.checksum:
            notes.append(Note(logging.WARNING, f"Set Configuration ignored: checksum {message.checksum}, "
                              f"expected {expected} ({self.checksum_rule.name})", "PW-SETCFG-CHECKSUM"))
            return
        channels = dict(enumerate(self.channels))
        for entry in message.entries:
            old = channels.get(entry.port)
            switch_type = old.switch_type if old is not None and old.unit_type == entry.unit_type else 0
            channels[entry.port] = m.ChannelConfig(entry.unit_type, 0, switch_type)
        gaps = [ch for ch in range(max(channels) + 1) if ch not in channels]
        if gaps:
            notes.append(Note(logging.WARNING, f"Set Configuration ignored: channel {gaps[0]} would have "
                              "no unit (channels run from 0 without gaps)"))
            return
        self.channels = tuple(channels[ch] for ch in range(len(channels)))
        notes.append(Note(logging.INFO, f"Set Configuration applied: {len(self.channels)} channels"))


class ConnectionState(StrEnum):
    AWAIT_PASSWORD = "await_password"
    READY = "ready"
    FAILED = "failed"


class RobotConnection:
    """One client connection: the winsock handshake, then framed commands.

    The password is compared byte by byte as it arrives, so it may come in any
    number of pieces; it is judged the moment it is complete or goes wrong.  A
    line break after it is an ``eol`` item like any other and is ignored.
    """

    def __init__(self, robot: Robot, mode: ServerMode, password: bytes, max_item: int,
                 hooks: Hooks | None = None) -> None:
        if mode is ServerMode.WINSOCK and not password:
            raise ValueError("winsock mode needs a non-empty password")
        self.robot = robot
        self.mode = mode
        self.password = password
        self.state = ConnectionState.AWAIT_PASSWORD if mode is ServerMode.WINSOCK else ConnectionState.READY
        self._matched = 0  # password bytes received so far
        self._framer = Framer(max_item)
        self.hooks = hooks  # planted bugs, if any

    def start(self, t_ns: int) -> Output:
        """What the server sends as soon as the client connects."""
        out = Output([Reply(encode(m.SendCheckPassword()), answer=False)] if self.mode is ServerMode.WINSOCK else [])
        if self.hooks is not None:
            self.hooks.greet(out)
        return out

    def receive(self, data: bytes, t_ns: int) -> Output:
        out = Output()
        if self.state is ConnectionState.AWAIT_PASSWORD:
            data = self._password(data, out)
        if self.state is ConnectionState.READY and data:
            self._serve(self._framer.feed(data, t_ns), t_ns, out)
            if self.hooks is not None and out.crash is None:
                self.hooks.read(data, self._framer.buffered, out)
        return out

    def end(self, t_ns: int) -> Output:
        """The client closed its side: what was left unfinished gets logged."""
        out = Output()
        if self.state is ConnectionState.READY:
            self._serve(self._framer.end(t_ns), t_ns, out)
        elif self.state is ConnectionState.AWAIT_PASSWORD:
            out.notes.append(Note(logging.INFO, "client left before completing the password"))
        return out

    def _password(self, data: bytes, out: Output) -> bytes:
        """Consume password bytes; return what follows a complete password."""
        expected = self.password[self._matched:]
        take = data[:len(expected)]
        if not expected.startswith(take) and not (self.hooks is not None and self.hooks.any_password):
            self.state = ConnectionState.FAILED
            out.replies.append(Reply(encode(m.FailedValidation()), answer=False))
            out.notes.append(Note(logging.WARNING, "wrong password: Failed Validation, closing"))
            out.close = True
            return b""
        self._matched += len(take)
        if self._matched < len(self.password):
            return b""
        self.state = ConnectionState.READY
        out.replies.append(Reply(encode(m.ReadyToGo()), answer=False))
        out.notes.append(Note(logging.INFO, "password accepted: readytogo"))
        return data[len(take):]

    def _serve(self, items: list[Item], t_ns: int, out: Output) -> None:
        robot, hooks = self.robot, self.hooks
        for item in items:
            kind = item.kind
            reply = None
            if kind is ItemKind.COMMAND or kind is ItemKind.SET_CONFIG:
                reply = robot.command(decode(kind, item.raw), item.raw, t_ns, out.notes)
            elif kind is ItemKind.EOL:
                out.notes.append(Note(logging.DEBUG, "line break ignored"))
            elif kind is ItemKind.UNFRAMED:
                for v in decode(kind, item.raw, item.reason).violations:
                    out.notes.append(Note(logging.WARNING, f"{v.detail}: {_quote(item.raw)}, ignored", v.rule_id))
            else:
                out.notes.append(Note(logging.WARNING, f"a {kind} item came from the client: "
                                      f"{_quote(item.raw)}, ignored", "PW-DIRECTION"))
            if hooks is not None:
                reply = hooks.item(item, reply, out)
                if out.crash is not None:
                    return
            if reply is not None:
                out.replies.append(Reply(reply, answer=True))
