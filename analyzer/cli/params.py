"""Options and parameter types every command shares: sizes, the checksum rule,
--force and the limits of the session model.

Each converts and checks what the user typed once, here; a value that does not
fit is the usual one line and exit status 2.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import click

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE

if TYPE_CHECKING:
    from whiztap.analyzer.protocol.messages import ChannelConfig
    from whiztap.analyzer.protocol.session import Limits


class ByteSize(click.ParamType):
    """A byte count: 500000, 100k, 64M, 2G (powers of 1024)."""

    name = "BYTES"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> int:
        if isinstance(value, int):
            return value
        from whiztap.analyzer.protocol.text import parse_size

        try:
            return parse_size(str(value))
        except ValueError as e:
            self.fail(str(e), param, ctx)


class ChecksumRule(click.ParamType):
    """The name of a Set Configuration checksum rule ('whiztap rules',
    docs/protocol.md); an unknown one names the known ones."""

    name = "name"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> str:
        from whiztap.analyzer.protocol.checksum import get_rule

        try:
            return get_rule(value).name
        except ValueError as e:
            fail(str(e))


def checksum_rule_option(help: str, show_default: bool = False) -> Callable[[Callable], Callable]:
    """``--checksum-rule NAME`` (default dev-sum), checked before the command runs."""
    return click.option("--checksum-rule", type=ChecksumRule(), default=DEFAULT_CHECKSUM_RULE,
                        show_default=show_default, help=help)


force_option = click.option(
    "--force", is_flag=True,
    help="Write over an existing output file (never over an input of the command: that is refused even so).")


def limits_options(f: Callable) -> Callable:
    """``--answer-timeout``, ``--max-frame`` and ``--max-image``: the same three
    on every command that judges traffic."""
    f = click.option("--max-image", type=ByteSize(), default="32M", show_default=True,
                     help="Largest camera image taken as one item; longer ones are cut as oversize.")(f)
    f = click.option("--max-frame", type=ByteSize(), default="64k", show_default=True,
                     help="Largest item other than an image (at least 1k); bounds memory on garbage.")(f)
    return click.option("--answer-timeout", type=click.FloatRange(min=0, min_open=True), default=5.0,
                        show_default=True, metavar="SECONDS",
                        help="How long a request may wait for its answer before it is unanswered.")(f)


def limits_from(answer_timeout: float, max_frame: int, max_image: int) -> Limits:
    from whiztap.analyzer.protocol.framing import MIN_MAX_ITEM
    from whiztap.analyzer.protocol.session import Limits

    if max_frame < MIN_MAX_ITEM:
        fail(f"--max-frame must be at least {MIN_MAX_ITEM} bytes")
    return Limits(round(answer_timeout * 1e9), max_frame, max(max_image, max_frame))


def assumed_map_options(f: Callable) -> Callable:
    """``--channels MAP`` and ``--assume-config FRAME|FILE``: a channel map
    stated for clients that never fetch the configuration (docs/analyze.md);
    read with ``limits_assuming``."""
    f = click.option("--assume-config", default=None, metavar="FRAME|FILE",
                     help="Like --channels, as a Configuration Settings frame in escaped text "
                          "(sr1-\\x18000...-ss1) or a file holding one.")(f)
    return click.option("--channels", "channel_map", default=None, metavar="MAP",
                        help="The channel map to assume until the server announces one "
                             "(servo:0-5,switch:6-8,switch1:9-11,sensor:12-23): resolves ambiguous "
                             "requests, so unanswered ones are reported.")(f)


def limits_assuming(limits: Limits, channel_map: str | None, assume_config: str | None) -> Limits:
    """``limits`` with the map ``--channels`` or ``--assume-config`` states."""
    import dataclasses

    if channel_map is not None and assume_config is not None:
        fail("--channels and --assume-config both state the channel map: give one")
    if channel_map is not None:
        from whiztap.analyzer.protocol.channels import ChannelSpecError, parse_channels

        try:
            return dataclasses.replace(limits, assumed_channels=parse_channels(channel_map))
        except ChannelSpecError as e:
            fail(f"--channels: {e} (e.g. servo:0-5,switch:6-8,switch1:9-11,sensor:12-23)")
    if assume_config is not None:
        return dataclasses.replace(limits, assumed_channels=_config_channels(assume_config))
    return limits


def assumed_channels(channel_map: str | None, assume_config: str | None) -> tuple[ChannelConfig, ...]:
    """The map ``--channels`` or ``--assume-config`` states, for commands that
    build sessions without ``Limits`` (replay, stub); () when neither is given."""
    from whiztap.analyzer.protocol.session import Limits

    return limits_assuming(Limits(), channel_map, assume_config).assumed_channels


def _config_channels(text: str) -> tuple[ChannelConfig, ...]:
    """The channels of a Configuration Settings frame, given as escaped text or
    in a file; one line and exit 2 when it is none."""
    from pathlib import Path

    from whiztap.analyzer.protocol.frame_text import frame_alone
    from whiztap.analyzer.protocol.messages import ConfigurationSettings
    from whiztap.analyzer.protocol.observations import Direction
    from whiztap.analyzer.protocol.text import unescape

    path = Path(text)
    try:
        is_file = path.is_file()
    except (OSError, ValueError):  # a frame's text too long or odd for a file name
        is_file = False
    try:
        if is_file:  # the frame's own bytes, or its escaped text (a backslash: no config holds one)
            data = path.read_bytes().strip()
            data = unescape(data.decode("latin-1")) if b"\\" in data else data
        else:
            data = unescape(text.strip())
    except (OSError, UnicodeEncodeError) as e:
        fail(f"--assume-config: cannot read {text!r}: {e}")
    observations, whole = frame_alone(data, Direction.S2C)
    message = observations[0].message if observations else None
    broken = [v for o in observations for v in o.violations] + whole
    if not isinstance(message, ConfigurationSettings) or broken or not message.channels:
        why = broken[0].detail if broken else "it is no Configuration Settings frame"
        fail(f"--assume-config: {text[:60]!r} is not a usable configuration ({why}); "
             "give the frame as the server sends it (sr1-\\x18000...-ss1), or a file holding one")
    return message.channels
