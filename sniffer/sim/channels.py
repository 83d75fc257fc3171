"""The ``--channels`` notation: which unit sits on each channel of the robot.

The Configuration Settings message lists channels 0 to N-1 by position, so a
channel map here is a gap-free tuple; the notation names a unit per range
(``servo:0-5,switch:6-8,switch1:9-11,sensor:12-23``).  ``switch`` is a switch of
type 0, ``switch1`` one of type 1.
"""

from __future__ import annotations

from whiztap.analyzer.protocol.codec import MAX_CONFIG_CHANNELS
from whiztap.analyzer.protocol.messages import ChannelConfig, UnitType

DEFAULT_CHANNELS = "servo:0-5,switch:6-8,switch1:9-11,sensor:12-23"

_UNITS = {
    "servo": ChannelConfig(UnitType.SERVO),
    "sensor": ChannelConfig(UnitType.SENSOR),
    "switch": ChannelConfig(UnitType.SWITCH, 0, 0),
    "switch0": ChannelConfig(UnitType.SWITCH, 0, 0),
    "switch1": ChannelConfig(UnitType.SWITCH, 0, 1),
}


class ChannelSpecError(ValueError):
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
    if count > MAX_CONFIG_CHANNELS:
        raise ChannelSpecError(f"at most {MAX_CONFIG_CHANNELS} channels (0-{MAX_CONFIG_CHANNELS - 1})")
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
