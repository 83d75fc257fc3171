"""The simulated robot's default channel map, in the ``--channels`` notation.

The notation itself (parsing, formatting, its errors) lives in the analyzer,
analyzer/protocol/channels.py, so that turning the console's ``setconfig`` words
into a frame (analyzer/protocol/frame_text.py) reads it too; its names are
available from here as before.
"""

from __future__ import annotations

from whiztap.analyzer.protocol.channels import ChannelSpecError, format_channels, parse_channels

__all__ = ["DEFAULT_CHANNELS", "ChannelSpecError", "format_channels", "parse_channels"]

DEFAULT_CHANNELS = "servo:0-5,switch:6-8,switch1:9-11,sensor:12-23"
