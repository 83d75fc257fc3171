"""The live server: a recording served to the Foxglove app while it is written.

``whiztap record --foxglove [HOST:]PORT`` (and ``tui --upstream``, ``demo``)
run a Foxglove WebSocket server (the ``foxglove-sdk``'s, protocol
``foxglove.sdk.v1``) in the writer process.  Every message the file gets is
logged on a channel of the same topic and schema, with the same log time, so
a Foxglove layout made for a recording works live.

Where: ``LiveRecordingFile`` is the writer process's ``RecordingFile`` when
the option is given; its ``write_all`` (which ``write`` goes through) is where
every message on its way to the file passes.  Without the option the plain
``RecordingFile`` is used and this module is not even imported: recording
pays nothing for it.

Slow or absent clients cost the recording nothing it waits on: ``log`` hands
the message to the SDK's server (Rust, its own threads), which keeps at most
``message_backlog_size`` (1024) messages per client and drops the oldest when
a client does not keep up (its control messages overflowing disconnects it).

The server is never stopped: it ends with the writer process, right after the
file is finished, and clients see their connection close.  ``stop()`` would
wait for each client's close, and one that stopped reading holds it up (50 s,
measured here): the summary would wait for a viewer.
"""

from __future__ import annotations

import errno
import os
import re
import sys
from collections.abc import Callable

from whiztap.analyzer.recording.format import KNOWN_TOPICS, MESSAGE_ENCODING, SCHEMA_ENCODING, schema_bytes
from whiztap.sniffer.nettext import show_address
from whiztap.sniffer.record.writer import RecordingFile

SERVER_NAME = "whiztap"
_OS_ERROR = re.compile(r"\(os error (\d+)\)")

Log = Callable[..., None]


class LiveServerError(Exception):
    """The live server could not start; the message is one line for the user."""


def _bind_failure(host: str, port: int, error: Exception) -> str:
    """The SDK says 'FoxgloveError: Failed to bind port: Address already in
    use (os error 98)'; the user gets the address, the reason and what to do."""
    text = str(error).removeprefix("FoxgloveError: ").removeprefix("Failed to bind port: ")
    m = _OS_ERROR.search(text)
    code = int(m.group(1)) if m else None
    reason = os.strerror(code) if code else text
    todo = ("stop what listens there, or give another port with --foxglove [HOST:]PORT (0 picks a free one)"
            if code == errno.EADDRINUSE else "check the address given to --foxglove")
    return f"cannot serve Foxglove on {show_address(host, port)}: {reason}; {todo}"


class LiveServer:
    """A Foxglove WebSocket server with a channel per topic, each made when
    first asked for.  Raises LiveServerError when it cannot listen."""

    def __init__(self, host: str, port: int) -> None:
        import foxglove

        self._foxglove = foxglove
        self.context = foxglove.Context()
        try:
            self.server = foxglove.start_server(name=SERVER_NAME, host=host, port=port, context=self.context)
        except RuntimeError as e:
            raise LiveServerError(_bind_failure(host, port, e)) from None
        self.host = host
        self.port = self.server.port  # the bound one when 0 was asked
        self.channels: dict[str, object] = {}

    @property
    def url(self) -> str:
        """Where the Foxglove app connects."""
        return f"ws://{show_address(self.host, self.port)}"

    def log_function(self, topic: str) -> Log:
        """``log(data, t_ns)`` for ``topic``'s channel, made now if new: the
        format's schema, or plain JSON for a topic the format does not know.
        It is the channel's ``BaseChannel.log`` (bytes only), without
        ``Channel.log``'s checks of what it is given: that halves what serving
        live costs the writer (measured: 4% of its frames/s rather than 9%)."""
        channel = self.channels.get(topic)
        if channel is None:
            fg = self._foxglove
            name = KNOWN_TOPICS.get(topic)  # the format's look-up, per-channel plot topics (/sensors/12) too
            schema = fg.Schema(name=name, encoding=SCHEMA_ENCODING, data=schema_bytes(name)) if name else None
            channel = fg.Channel(topic, message_encoding=MESSAGE_ENCODING, schema=schema, context=self.context)
            self.channels[topic] = channel
        return channel.base.log  # type: ignore[attr-defined]


def _nowhere(data: bytes, log_time: int) -> None:
    """A message whose channel the file cannot name: not served."""


class LiveRecordingFile(RecordingFile):
    """A ``RecordingFile`` that also serves every message it is given on a
    ``LiveServer``.

    Messages come as (channel id, t_ns, data), ids from ``channel_ids``
    (topic -> id), fixed for the whole recording (every part uses the same
    ids) and only ever growing: when it has grown, the map back to topics is
    made again.  A live channel is made when the file has its topic, at the
    first message after: for the format's topics, when the recording starts;
    for one registered as it goes (``/sensors/12``), after its first message,
    which no client can have subscribed to yet and which is not served."""

    def __init__(self, live: LiveServer, *args, **kwargs) -> None:  # noqa: ANN002, ANN003 - RecordingFile's
        super().__init__(*args, **kwargs)
        self.live = live
        self._logs: dict[int, Log] = {}  # channel id -> its live channel's log
        self.serving = True  # False once the live server failed: the file goes on alone

    def write_all(self, messages: list[tuple[int, int, bytes]]) -> None:
        if self.serving:
            self._serve(messages)
        super().write_all(messages)

    def _serve(self, messages: list[tuple[int, int, bytes]]) -> None:
        """Hand each message to its live channel.  Serving must never cost the
        recording: if the SDK raises, say so once on stderr, serve nothing
        more, and record on."""
        ids = self.channel_ids
        try:
            if len(ids) != len(self._logs):
                self._remap(ids)
            logs = self._logs
            for channel_id, t_ns, data in messages:
                logs.get(channel_id, _nowhere)(data, t_ns)
        except Exception as e:  # noqa: BLE001 - whatever the live server does wrong, the file goes on
            self.serving = False
            sys.stderr.write(f"whiztap: the live Foxglove server stopped ({type(e).__name__}: {e}); "
                             "the recording goes on\n")

    def _remap(self, ids: dict[str, int]) -> None:
        """Channel ids back to topics, and a live channel for every topic the
        file has (so the app lists the file's topics, and a client subscribed
        early gets their first messages too)."""
        self._logs = {channel_id: self.live.log_function(topic) for topic, channel_id in ids.items()}
