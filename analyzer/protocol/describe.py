"""Observations in words and in plain fields, for every view of the traffic.

Kept apart from the session so that the hot path builds no strings: these run
only for what is actually shown or written.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import ChannelResponse, Password, ServoPositionRequest
from whiztap.analyzer.protocol.observations import Observation


def response_meaning(observation: Observation) -> str | None:
    """'sensor' or 'servo' for a Sensor/Servo Response whose request is known."""
    if not isinstance(observation.message, ChannelResponse) or observation.answers is None:
        return None
    return "servo" if isinstance(observation.answers.message, ServoPositionRequest) else "sensor"


def meaning(observation: Observation) -> str:
    """One line: what the item means, e.g. 'Sensor value ch 12 = 431'."""
    message = observation.message
    kind = observation.item.kind
    if isinstance(message, ChannelResponse):
        as_ = response_meaning(observation)
        if as_ == "servo":
            return f"Servo {message.channel} position {message.data / 4:g}"
        if as_ == "sensor":
            return f"Sensor value ch {message.channel} = {message.data}"
        return message.describe()
    if message is not None:
        return message.describe()
    if observation.candidates:
        names = " / ".join(c.describe() for c in observation.candidates)
        return f"{names} (ambiguous)"
    if kind is ItemKind.UNFRAMED:
        return f"unframed bytes ({observation.item.reason})"
    if kind is ItemKind.EOL:
        return "line break"
    return f"malformed {kind}"


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    return value


def fields(observation: Observation) -> dict[str, Any]:
    """The decoded fields as JSON-ready values.  Passwords give only their length;
    image bytes only their size (the raw bytes are recorded beside them)."""
    message = observation.message
    if message is None:
        if observation.candidates:
            return {"candidates": [c.title for c in observation.candidates],
                    **_plain(observation.candidates[0])}
        return {}
    if isinstance(message, Password):
        return {"message": message.title, "length": len(message.secret)}
    out: dict[str, Any] = {"message": message.title}
    for f in dataclasses.fields(message):
        value = getattr(message, f.name)
        out[f.name] = len(value) if isinstance(value, bytes) else _plain(value)
    as_ = response_meaning(observation)
    if isinstance(message, ChannelResponse) and as_ == "servo":
        out["servo_position"] = message.data / 4
    elif isinstance(message, ChannelResponse) and as_ == "sensor":
        out["sensor_value"] = message.data
    if observation.latency_ns is not None:
        out["latency_ns"] = observation.latency_ns
    return out
