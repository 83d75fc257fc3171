"""The channel map: what the server's configuration makes of a command or an answer.

The bytes of 'rr1-3--0--0-ss1' may be a Sensor Request or a Servo Position
Request: the unit the server configured on channel 3 says which, and a command
for another unit than the channel's breaks a rule.  An answer's data range
depends on what was asked (sensor data 0-1024, servo data 0-8000).
"""

from __future__ import annotations

from whiztap.analyzer.protocol.codec import MAX_SENSOR_DATA, MAX_SERVO_DATA, UNIT_OF_COMMAND, resolve
from whiztap.analyzer.protocol.messages import ChannelConfig, ChannelResponse, Message, ServoPositionRequest, UnitType
from whiztap.analyzer.protocol.observations import Observation
from whiztap.analyzer.protocol.rules import Violation

ChannelMap = dict[int, ChannelConfig]


def unit_of(channel_map: ChannelMap, channel: int) -> UnitType | None:
    """The unit the server configured on ``channel``; None if it did not say."""
    config = channel_map.get(channel)
    if config is None or config.unit_type not in (0, 1, 2):
        return None
    return UnitType(config.unit_type)


def command_meaning(message: Message | None, candidates: tuple[Message, ...],
                    channel_map: ChannelMap) -> tuple[Message | None, Violation | None]:
    """A command's meaning on its channel (``message``: the one its bytes alone
    give, if they do), and the rule it breaks there (None: none)."""
    channel = getattr(candidates[0], "channel", None) if candidates else None
    if channel is None:
        return message, None
    unit = unit_of(channel_map, channel)
    if message is None:
        message = resolve(candidates, unit)
        if message is not None:
            return message, None
        if unit is not None:
            names = " or ".join(c.title for c in candidates)
            return None, Violation("PW-UNIT-MISMATCH", f"channel {channel} is a {unit}; the frame means {names}")
        if channel_map:
            return None, _unconfigured(channel)
        return None, Violation("PW-AMBIGUOUS", f"may be {', '.join(c.title for c in candidates)}")
    needed = UNIT_OF_COMMAND.get(type(message))
    if needed is not None and unit is not None and unit != needed:
        return message, Violation("PW-UNIT-MISMATCH", f"{message.title} needs a {needed}; channel {channel} is a {unit}")
    if needed is not None and unit is None and channel_map:
        return message, _unconfigured(channel)
    return message, None


def _unconfigured(channel: int) -> Violation:
    return Violation("PW-CHANNEL-UNCONFIGURED", f"channel {channel} is not in the server's configuration")


def data_violation(message: ChannelResponse, request: Observation | None, channel_map: ChannelMap) -> Violation | None:
    """Whether an answer's data is out of range.  Sensor data and servo data
    have different ranges: the request says which applies, else the channel's
    unit; with neither, the wider one."""
    if request is not None:
        servo: bool | None = isinstance(request.message, ServoPositionRequest)
    else:
        unit = unit_of(channel_map, message.channel)
        servo = None if unit is None else unit is UnitType.SERVO
    if servo is False:
        limit, rule, what = MAX_SENSOR_DATA, "PW-RANGE-SENSOR", "sensor data"
    else:
        limit, rule, what = MAX_SERVO_DATA, "PW-RANGE-SERVO", "servo data" if servo else "sensor or servo data"
    if message.data > limit:
        return Violation(rule, f"{what} must be 0-{limit}, got {message.data}")
    return None
