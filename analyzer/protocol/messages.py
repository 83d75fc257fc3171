"""Typed, immutable messages: what a frame means, as opposed to its bytes."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from whiztap.analyzer.protocol.handshake import FAILED_VALIDATION, READYTOGO, SENDCHKPASS
from whiztap.analyzer.protocol.text import LowerNamed, plural


class UnitType(LowerNamed):
    SERVO = 0
    SWITCH = 1
    SENSOR = 2


@dataclass(frozen=True, slots=True)
class Message:
    """Base of all messages.  ``title`` is the spec's name for the message.
    A dataclass like every message, so that what reads one reads its fields."""

    title: ClassVar[str] = ""
    sender: ClassVar[str] = ""  # "client" or "server"

    def describe(self) -> str:
        return self.title


# -- client to server: the rr1 commands ------------------------------------------


@dataclass(frozen=True, slots=True)
class FetchConfiguration(Message):
    title: ClassVar[str] = "Fetch Configuration Settings"
    sender: ClassVar[str] = "client"


@dataclass(frozen=True, slots=True)
class FetchCameraImage(Message):
    title: ClassVar[str] = "Fetch Camera Image"
    sender: ClassVar[str] = "client"


@dataclass(frozen=True, slots=True)
class NormalSend(Message):
    channel: int
    value: int
    title: ClassVar[str] = "Normal Send to Channel/Port"
    sender: ClassVar[str] = "client"

    def describe(self) -> str:
        return f"Normal Send ch {self.channel} = {self.value}"


@dataclass(frozen=True, slots=True)
class ActivateSwitch(Message):
    channel: int
    title: ClassVar[str] = "Activate/Close Switch"
    sender: ClassVar[str] = "client"

    def describe(self) -> str:
        return f"Switch ch {self.channel} on"


@dataclass(frozen=True, slots=True)
class DeactivateSwitch(Message):
    channel: int
    title: ClassVar[str] = "De-Activate/Open Switch"
    sender: ClassVar[str] = "client"

    def describe(self) -> str:
        return f"Switch ch {self.channel} off"


@dataclass(frozen=True, slots=True)
class PlayInternalScript(Message):
    script: int
    title: ClassVar[str] = "Play Internal Script"
    sender: ClassVar[str] = "client"

    def describe(self) -> str:
        return f"Play internal script {self.script}"


@dataclass(frozen=True, slots=True)
class StopInternalScript(Message):
    title: ClassVar[str] = "Stop Internal Script"
    sender: ClassVar[str] = "client"


@dataclass(frozen=True, slots=True)
class PlayExternalScript(Message):
    script: int
    title: ClassVar[str] = "Play External Script"
    sender: ClassVar[str] = "client"

    def describe(self) -> str:
        return f"Play external script {self.script}"


@dataclass(frozen=True, slots=True)
class StopExternalScript(Message):
    title: ClassVar[str] = "Stop External Script"
    sender: ClassVar[str] = "client"


@dataclass(frozen=True, slots=True)
class SensorRequest(Message):
    channel: int
    title: ClassVar[str] = "Sensor Request"
    sender: ClassVar[str] = "client"

    def describe(self) -> str:
        return f"Sensor Request ch {self.channel}"


@dataclass(frozen=True, slots=True)
class ServoPositionRequest(Message):
    channel: int
    title: ClassVar[str] = "Servo Position Request"
    sender: ClassVar[str] = "client"

    def describe(self) -> str:
        return f"Servo Position Request ch {self.channel}"


@dataclass(frozen=True, slots=True)
class UnknownCommand(Message):
    """An rr1 frame whose codes match none of the spec's commands."""

    data1: int
    data2: int
    data3: int
    title: ClassVar[str] = "Unknown command"
    sender: ClassVar[str] = "client"

    def describe(self) -> str:
        return f"Unknown command {self.data1}/{self.data2}/{self.data3}"


# -- server to client --------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ChannelResponse(Message):
    """Sensor/Servo Response: whether ``data`` is a sensor value or servo data
    depends on the request it answers, which the session knows."""

    channel: int
    data: int
    title: ClassVar[str] = "Sensor/Servo Response"
    sender: ClassVar[str] = "server"

    @property
    def servo_position(self) -> float:
        return self.data / 4

    def describe(self) -> str:
        return f"Response ch {self.channel} data {self.data}"


@dataclass(frozen=True, slots=True)
class ChannelConfig:
    unit_type: int
    unused: int = 0
    switch_type: int = 0


@dataclass(frozen=True, slots=True)
class ConfigurationSettings(Message):
    channels: tuple[ChannelConfig, ...]
    title: ClassVar[str] = "Configuration Settings"
    sender: ClassVar[str] = "server"

    def describe(self) -> str:
        counts = {u: sum(1 for c in self.channels if c.unit_type == u) for u in UnitType}
        parts = ", ".join(f"{n} {u}" for u, n in counts.items() if n)
        return f"Configuration Settings: {plural(len(self.channels), 'channel')}" + (f" ({parts})" if parts else "")


@dataclass(frozen=True, slots=True)
class SetConfigEntry:
    device: int
    port: int
    unit_type: int


@dataclass(frozen=True, slots=True)
class SetConfiguration(Message):
    entries: tuple[SetConfigEntry, ...]
    checksum: int
    title: ClassVar[str] = "Set Configuration Settings"
    sender: ClassVar[str] = "client"

    def describe(self) -> str:
        return f"Set Configuration: {plural(len(self.entries), 'entry', 'entries')}, checksum {self.checksum}"


# -- handshake and images -----------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SendCheckPassword(Message):
    title: ClassVar[str] = SENDCHKPASS.decode()
    sender: ClassVar[str] = "server"


@dataclass(frozen=True, slots=True)
class ReadyToGo(Message):
    title: ClassVar[str] = READYTOGO.decode()
    sender: ClassVar[str] = "server"


@dataclass(frozen=True, slots=True)
class FailedValidation(Message):
    title: ClassVar[str] = FAILED_VALIDATION.decode()
    sender: ClassVar[str] = "server"


@dataclass(frozen=True, slots=True)
class Password(Message):
    secret: bytes
    title: ClassVar[str] = "Password"
    sender: ClassVar[str] = "client"

    def describe(self) -> str:
        return f"Password ({plural(len(self.secret), 'byte')})"


@dataclass(frozen=True, slots=True)
class CameraImage(Message):
    format: str  # "jpeg" or "png"
    data: bytes
    title: ClassVar[str] = "Camera Image"
    sender: ClassVar[str] = "server"

    def describe(self) -> str:
        return f"Camera image ({self.format}, {plural(len(self.data), 'byte')})"
