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

Who may connect: the SDK's server checks no ``Origin``, so it listens on a
loopback address of its own and ``live_gate.py`` listens where the user
asked, refusing web pages the user did not choose.  The SDK's log lines
(``Dropping client ...: handshake failed``) go to the writer's ``warn`` (the
proxy's stderr, or the TUI's notices), never raw onto the terminal.
"""

from __future__ import annotations

import errno
import logging
import secrets
import socket
from collections.abc import Callable
from types import ModuleType
from typing import TYPE_CHECKING, Any

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.text import printable, shorten
from whiztap.analyzer.recording.format import KNOWN_TOPICS, MESSAGE_ENCODING, SCHEMA_ENCODING, schema_bytes
from whiztap.sniffer.nettext import is_loopback, reason, show_address
from whiztap.sniffer.record.live_gate import MAX_CLIENTS, LiveGate
from whiztap.sniffer.record.writer import RecordingFile

if TYPE_CHECKING:
    from foxglove import Channel, Context

SERVER_NAME = "whiztap"
SDK_LINES = 20  # the SDK's log lines passed on; after them, one line says more were left out

Log = Callable[..., None]
Warn = Callable[[str], None]


class LiveServerError(WhiztapError):
    """The live server could not start; the message is one line for the user."""


def _listen(host: str, port: int) -> socket.socket:
    """The socket the gate serves on, bound and listening; LiveServerError
    names the address, the reason and what to do."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                                             flags=socket.AI_PASSIVE)[0]
        sock = socket.socket(family, kind, proto)
    except OSError as e:
        raise LiveServerError(f"cannot serve Foxglove on {show_address(host, port)}: {reason(e)}; "
                              "check the address given to --foxglove") from None
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(MAX_CLIENTS)
    except OSError as e:
        sock.close()
        todo = ("stop what listens there, or give another port with --foxglove [HOST:]PORT (0 picks a free one)"
                if e.errno == errno.EADDRINUSE else "check the address given to --foxglove")
        raise LiveServerError(f"cannot serve Foxglove on {show_address(host, port)}: {reason(e)}; {todo}") from None
    sock.setblocking(False)
    return sock


# A viewer that went away without a goodbye (a closed laptop, a killed app) is
# the life of a viewer, not news: the SDK logs it as an error, whiztap says nothing.
_VIEWER_GONE = ("without closing handshake", "Connection reset by peer")


class _SdkLog(logging.Handler):
    """The SDK's log records (Rust, forwarded to Python's logging) as warnings,
    at most ``SDK_LINES`` of them: a client failing its handshake over and
    over must not fill the screen."""

    def __init__(self, warn: Warn) -> None:
        super().__init__(logging.WARNING)
        self.warn = warn
        self.said = 0

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if any(words in message for words in _VIEWER_GONE):
            return
        self.said += 1
        if self.said <= SDK_LINES:
            self.warn(f"warning: foxglove server: {shorten(printable(message), 400)}")
        elif self.said == SDK_LINES + 1:
            self.warn("warning: foxglove server: more lines left out")


def _route_sdk_logs(foxglove: ModuleType, warn: Warn) -> None:
    """Before the server starts (the SDK takes its level once): warnings and
    errors go to ``warn``, nothing to stderr."""
    logger = logging.getLogger("foxglove")
    logger.handlers[:] = [_SdkLog(warn)]
    logger.propagate = False
    foxglove.set_log_level(logging.WARNING)


def _hidden_server(foxglove: ModuleType, context: Context) -> tuple[object, tuple[str, int]]:
    """The SDK's server on a loopback address no web page can guess
    (127.R.R.R; 127.0.0.1 where the system has no other), port chosen by the
    system; the server and where it listens."""
    hosts = (f"127.{secrets.randbelow(254) + 1}.{secrets.randbelow(254) + 1}.{secrets.randbelow(254) + 1}",
             "127.0.0.1")
    for host in hosts:
        try:
            server = foxglove.start_server(name=SERVER_NAME, host=host, port=0, context=context)
        except RuntimeError as e:
            failure = e
            continue
        return server, (host, server.port)
    raise LiveServerError(f"cannot start the Foxglove server on a loopback address: {failure}")


class LiveServer:
    """A Foxglove WebSocket server with a channel per topic, each made when
    first asked for, served at (``host``, ``port``) through the gate that
    lets only the web ``origins`` allowed in (``live_gate.py``).  ``warn``
    receives one line for each thing the user should know.  Raises
    LiveServerError when it cannot listen."""

    def __init__(self, host: str, port: int, origins: tuple[str, ...] = (), *, warn: Warn) -> None:
        import foxglove

        sock = _listen(host, port)  # first: a port in use is the user's error, before anything starts
        self._foxglove = foxglove
        _route_sdk_logs(foxglove, warn)
        self.context = foxglove.Context()
        try:
            self.server, inner = _hidden_server(foxglove, self.context)
        except LiveServerError:
            sock.close()
            raise
        self.gate = LiveGate(sock, inner, tuple(origins), warn)
        self.gate.start()
        self.host = host
        self.port = sock.getsockname()[1]  # the bound one when 0 was asked
        self.channels: dict[str, Channel] = {}
        if not is_loopback(host):
            warn(f"warning: foxglove: {self.url} can be reached from other machines: whoever reaches it reads "
                 "all the traffic (no password, no encryption); the origin check stops only web pages")

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
        return channel.base.log


def _nowhere(data: bytes, log_time: int) -> None:
    """A message whose channel the file cannot name: not served."""


class LiveRecordingFile(RecordingFile):
    """A ``RecordingFile`` that also serves every message it is given on a
    ``LiveServer``.

    Messages come as (channel id, t_ns, data), ids from ``channel_ids``
    (topic -> id), fixed for the whole recording (every part uses the same
    ids) and only ever growing.  A live channel is made as soon as the file
    knows its topic: the format's topics and, in the middle, the middle's
    (``Recorder``) before the recording says it is ready, so a viewer that
    connects then lists and subscribes to them before the first message; a
    plot topic (``/sensors/12``) when it joins, just before its first
    message, which no viewer can have subscribed to yet."""

    def __init__(self, live: LiveServer, *args: Any, **kwargs: Any) -> None:  # RecordingFile's
        super().__init__(*args, **kwargs)
        self.live = live
        self._logs: dict[int, Log] = {channel_id: live.log_function(topic)
                                      for topic, channel_id in self.channel_ids.items()}
        self.serving = True  # False once the live server failed: the file goes on alone

    def channel_id(self, topic: str) -> int:
        channel_id = super().channel_id(topic)
        if self.serving and channel_id not in self._logs:
            try:
                self._logs[channel_id] = self.live.log_function(topic)
            except Exception as e:  # whatever the live server does wrong, the file goes on
                self._stop_serving(e)
        return channel_id

    def write_all(self, messages: list[tuple[int, int, bytes]]) -> None:
        if self.serving:
            self._serve(messages)
        super().write_all(messages)

    def _serve(self, messages: list[tuple[int, int, bytes]]) -> None:
        """Hand each message to its live channel.  Serving must never cost the
        recording: if the SDK raises, say so once on stderr, serve nothing
        more, and record on."""
        logs = self._logs
        try:
            for channel_id, t_ns, data in messages:
                logs.get(channel_id, _nowhere)(data, t_ns)
        except Exception as e:  # whatever the live server does wrong, the file goes on
            self._stop_serving(e)

    def _stop_serving(self, e: Exception) -> None:
        self.serving = False
        self.warn(f"warning: the live Foxglove server stopped ({type(e).__name__}: {e}); the recording goes on")
