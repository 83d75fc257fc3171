"""The channel map: what the server's configuration makes of a command or an answer.

The bytes of 'rr1-3--0--0-ss1' may be a Sensor Request or a Servo Position
Request: the unit the server configured on channel 3 says which, and a command
for another unit than the channel's breaks a rule.  An answer's data range
depends on what was asked (sensor data 0-1024, servo data 0-8000).

And the notation people write a channel map in (``whiztap sim --channels``, the
console's ``setconfig``): a unit per range of channels,
``servo:0-5,switch:6-8,switch1:9-11,sensor:12-23``, ``switch`` being a switch
of type 0 and ``switch1`` one of type 1.  The Configuration Settings message
lists channels 0 to N-1 by position, so such a map is a gap-free tuple.
"""

from __future__ import annotations

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.codec import (
    MAX_CONFIG_CHANNELS,
    MAX_SENSOR_DATA,
    MAX_SERVO_DATA,
    UNIT_OF_COMMAND,
    resolve,
)
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
        return message, Violation("PW-UNIT-MISMATCH",
                                  f"{message.title} needs a {needed}; channel {channel} is a {unit}")
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


# -- the notation ---------------------------------------------------------------------

_UNITS = {
    "servo": ChannelConfig(UnitType.SERVO),
    "sensor": ChannelConfig(UnitType.SENSOR),
    "switch": ChannelConfig(UnitType.SWITCH, 0, 0),
    "switch0": ChannelConfig(UnitType.SWITCH, 0, 0),
    "switch1": ChannelConfig(UnitType.SWITCH, 0, 1),
}


class ChannelSpecError(WhiztapError, ValueError):
    """The notation is wrong; the message says where, in one line."""


def _range(text: str) -> range:
    low, sep, high = text.partition("-")
    try:
        first = int(low)
        last = int(high) if sep else first
    except ValueError:
        raise ChannelSpecError(f"bad channel range {text!r}: expected N or N-M") from None
    if first < 0 or last < first:
        raise ChannelSpecError(f"bad channel range {text!r}")
    if last >= MAX_CONFIG_CHANNELS:  # before walking it: 'servo:0-99999999999' would take forever
        raise ChannelSpecError(f"at most {MAX_CONFIG_CHANNELS} channels (0-{MAX_CONFIG_CHANNELS - 1})")
    return range(first, last + 1)


def parse_channels(spec: str) -> tuple[ChannelConfig, ...]:
    """Turn the notation into one ChannelConfig per channel, 0 upwards."""
    assigned: dict[int, ChannelConfig] = {}
    for group in filter(None, (g.strip() for g in spec.split(","))):
        unit, sep, ranges = group.partition(":")
        config = _UNITS.get(unit.strip().lower())
        if not sep or config is None:
            raise ChannelSpecError(
                f"bad channel group {group!r}: expected UNIT:RANGE with UNIT one of {', '.join(_UNITS)}")
        for channel in _range(ranges.strip()):
            if channel in assigned:
                raise ChannelSpecError(f"channel {channel} is given twice")
            assigned[channel] = config
    if not assigned:
        raise ChannelSpecError("no channels given")
    count = max(assigned) + 1
    missing = [c for c in range(count) if c not in assigned]
    if missing:
        raise ChannelSpecError(
            f"channel {missing[0]} has no unit: channels must run from 0 without gaps")
    return tuple(assigned[c] for c in range(count))


def _unit_name(config: ChannelConfig) -> str:
    if config.unit_type == UnitType.SWITCH:
        return "switch1" if config.switch_type == 1 else "switch"
    return str(UnitType(config.unit_type)) if config.unit_type in (0, 1, 2) else f"unit{config.unit_type}"


def format_channels(channels: tuple[ChannelConfig, ...]) -> str:
    """The notation for a channel map (runs of the same unit joined)."""
    groups: list[tuple[str, int, int]] = []
    for channel, config in enumerate(channels):
        name = _unit_name(config)
        if groups and groups[-1][0] == name and groups[-1][2] == channel - 1:
            groups[-1] = (name, groups[-1][1], channel)
        else:
            groups.append((name, channel, channel))
    return ",".join(f"{n}:{a}" if a == b else f"{n}:{a}-{b}" for n, a, b in groups)
