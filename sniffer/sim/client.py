"""An asyncio client for the Progwhiz Robotics Server API: one method per command.

The server's bytes go through the analyzer's framer and codec, so the client
copes with whatever the framer copes with (replies split anywhere, several in one
read, stray bytes between them).  Answers are matched to requests by kind and
channel rather than by order alone, so concurrent callers on one connection each
get their own answer, and a dropped answer costs one timeout, not every later one.
"""

from __future__ import annotations

import asyncio
import socket
import time
from collections import deque
from dataclasses import dataclass

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE, get_rule
from whiztap.analyzer.protocol.codec import decode, encode
from whiztap.analyzer.protocol.framing import Framer, Item, ItemKind
from whiztap.analyzer.protocol.text import escape

DEFAULT_TIMEOUT = 5.0
READ_SIZE = 65536


class ClientError(WhiztapError):
    """Base of everything the client raises about the server or the connection."""


class HandshakeError(ClientError):
    """The winsock handshake failed or did not go as the spec says."""


class ResponseTimeout(ClientError, TimeoutError):
    """No answer came within the timeout."""


class BreaksTheSpec(ClientError):
    """A command that would put a frame on the wire that breaks a rule of the
    spec (``validate`` on); the message names the rule."""


class ConnectionClosed(ClientError, ConnectionError):
    """The server closed the connection."""


@dataclass(slots=True)
class _Waiter:
    kind: ItemKind
    channel: int | None
    future: asyncio.Future


class Client:
    """A connection to a Progwhiz server.  Use ``await Client.connect(...)``."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, timeout: float,
                 handshake: bool) -> None:
        self.reader = reader
        self.writer = writer
        self.timeout = timeout
        self.handshaking = handshake  # True until readytogo: handshake text is then expected
        self.validate = False  # refuse commands whose frame breaks a rule (whiztap client sets it)
        self.stray: list[Item] = []  # items that answered nothing (garbage, unsolicited replies)
        self._framer = Framer()
        self._waiters: deque[_Waiter] = deque()
        self._handshake: asyncio.Queue[m.Message] = asyncio.Queue()
        self._taps: list[list[Item]] = []
        self._closed: ClientError | None = None
        self._reader_task = asyncio.create_task(self._read())

    @classmethod
    async def connect(cls, host: str, port: int, password: str | bytes | None = None,
                      timeout: float = DEFAULT_TIMEOUT) -> Client:
        """Connect and, given a password, do the winsock handshake.

        Without a password the server is taken to be in VPN mode; if it asks for
        a password anyway, the next request raises ``HandshakeError``.
        """
        try:
            reader, writer = await asyncio.wait_for(asyncio.open_connection(host, port), timeout)
        except TimeoutError:
            raise ResponseTimeout(f"no connection to {host}:{port} within {timeout:g} s") from None
        sock = writer.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client = cls(reader, writer, timeout, handshake=password is not None)
        if password is not None:
            try:
                await client._login(password.encode() if isinstance(password, str) else password)
            except BaseException:
                await client.close()
                raise
        return client

    async def _login(self, password: bytes) -> None:
        first = await self._handshake_message(m.SendCheckPassword.title)
        if not isinstance(first, m.SendCheckPassword):
            raise HandshakeError(f"expected sendchkpass, got {first.title!r}")
        await self.send_raw(password)
        verdict = await self._handshake_message("readytogo or Failed Validation")
        if isinstance(verdict, m.FailedValidation):
            raise HandshakeError("Failed Validation: the server rejected the password")
        if not isinstance(verdict, m.ReadyToGo):
            raise HandshakeError(f"expected readytogo, got {verdict.title!r}")
        self.handshaking = False

    async def _handshake_message(self, what: str) -> m.Message:
        # A verdict may come with the server's close: take what arrived before looking at the close.
        if self._handshake.empty() and not self._reader_task.done():
            getter = asyncio.ensure_future(self._handshake.get())
            await asyncio.wait({getter, self._reader_task}, timeout=self.timeout,
                               return_when=asyncio.FIRST_COMPLETED)
            if getter.done():
                return getter.result()
            getter.cancel()
        if not self._handshake.empty():
            return self._handshake.get_nowait()
        if self._reader_task.done():
            raise self._closed or ConnectionClosed("the server closed the connection")
        raise ResponseTimeout(f"no {what} from the server within {self.timeout:g} s")

    # -- the spec's commands -------------------------------------------------------------

    async def fetch_configuration(self, timeout: float | None = None) -> m.ConfigurationSettings:
        item = await self._request(m.FetchConfiguration(), ItemKind.CONFIG, None, timeout)
        decoded = decode(item.kind, item.raw)
        if not isinstance(decoded.message, m.ConfigurationSettings):
            raise ClientError(f"unreadable Configuration Settings: {decoded.violations[0].detail}")
        return decoded.message

    async def fetch_camera_image(self, timeout: float | None = None) -> bytes:
        """The image as the server sent it (the simulator sends a bare JPEG)."""
        return (await self._request(m.FetchCameraImage(), ItemKind.IMAGE, None, timeout)).raw

    async def sensor(self, channel: int, timeout: float | None = None) -> int:
        """Sensor Request: the sensor value (0-1024)."""
        return (await self._channel_request(m.SensorRequest(channel), channel, timeout)).data

    async def servo_position(self, channel: int, timeout: float | None = None) -> float:
        """Servo Position Request: the position (0-2000), i.e. the servo data / 4."""
        return (await self._channel_request(m.ServoPositionRequest(channel), channel, timeout)).servo_position

    async def normal_send(self, channel: int, value: int) -> None:
        await self.send(m.NormalSend(channel, value))

    async def activate_switch(self, channel: int) -> None:
        await self.send(m.ActivateSwitch(channel))

    async def deactivate_switch(self, channel: int) -> None:
        await self.send(m.DeactivateSwitch(channel))

    async def play_internal_script(self, script: int) -> None:
        await self.send(m.PlayInternalScript(script))

    async def stop_internal_script(self) -> None:
        await self.send(m.StopInternalScript())

    async def play_external_script(self, script: int) -> None:
        await self.send(m.PlayExternalScript(script))

    async def stop_external_script(self) -> None:
        await self.send(m.StopExternalScript())

    async def set_configuration(self, entries: tuple[m.SetConfigEntry, ...], checksum: int | None = None,
                                checksum_rule: str = DEFAULT_CHECKSUM_RULE) -> None:
        """Set Configuration Settings; the checksum is computed unless given."""
        if checksum is None:
            checksum = get_rule(checksum_rule).compute(entries)
        await self.send(m.SetConfiguration(entries, checksum))

    # -- raw access ------------------------------------------------------------------------

    async def send_raw(self, data: bytes) -> None:
        self._check_open()
        self.writer.write(data)
        await self.writer.drain()

    async def exchange_raw(self, data: bytes, wait: float) -> list[Item]:
        """Send bytes as they are; every item the server sends within ``wait`` seconds."""
        seen: list[Item] = []
        self._taps.append(seen)
        try:
            await self.send_raw(data)
            await asyncio.wait({self._reader_task}, timeout=wait)
        finally:
            self._taps.remove(seen)
        return seen

    # -- lifecycle --------------------------------------------------------------------------

    async def close(self) -> None:
        self._reader_task.cancel()
        await asyncio.gather(self._reader_task, return_exceptions=True)
        self.writer.close()
        try:
            await self.writer.wait_closed()
        except (ConnectionError, OSError):
            pass

    async def __aenter__(self) -> Client:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- internals ----------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed is not None:
            raise self._closed

    def _frame(self, message: m.Message) -> bytes:
        """The message's bytes; with ``validate`` on, refused if they break a rule
        on their own (a channel or value out of range), before anything is sent."""
        data = encode(message)
        if self.validate:
            decoded = decode(ItemKind.SET_CONFIG if data.startswith(b"sr1-") else ItemKind.COMMAND, data)
            broken = [v for v in decoded.violations if v.severity >= 3]
            if broken:
                rules = ", ".join(dict.fromkeys(v.rule_id for v in broken))
                raise BreaksTheSpec(f"{message.title} {escape(data)} breaks {rules}: {broken[-1].detail} "
                                    f"(not sent; --raw sends it anyway)")
        return data

    async def send(self, message: m.Message) -> None:
        """Send a command that awaits no answer (checked first, with ``validate`` on)."""
        await self.send_raw(self._frame(message))

    async def _channel_request(self, message: m.Message, channel: int, timeout: float | None) -> m.ChannelResponse:
        item = await self._request(message, ItemKind.RESPONSE, channel, timeout)
        decoded = decode(item.kind, item.raw)
        if not isinstance(decoded.message, m.ChannelResponse):
            raise ClientError(f"unreadable response: {decoded.violations[0].detail}")
        return decoded.message

    async def _request(self, message: m.Message, kind: ItemKind, channel: int | None,
                       timeout: float | None) -> Item:
        self._check_open()
        data = self._frame(message)
        waiter = _Waiter(kind, channel, asyncio.get_running_loop().create_future())
        self._waiters.append(waiter)
        try:
            await self.send_raw(data)
            return await asyncio.wait_for(waiter.future, self.timeout if timeout is None else timeout)
        except TimeoutError:
            raise ResponseTimeout(f"no answer to {message.title} within "
                                  f"{self.timeout if timeout is None else timeout:g} s") from None
        finally:
            if waiter in self._waiters:
                self._waiters.remove(waiter)

    async def _read(self) -> None:
        try:
            while data := await self.reader.read(READ_SIZE):
                for item in self._framer.feed(data, time.monotonic_ns()):
                    self._dispatch(item)
            for item in self._framer.end(time.monotonic_ns()):
                self._dispatch(item)
            self._fail(ConnectionClosed("the server closed the connection"))
        except (ConnectionError, OSError) as e:
            self._fail(ConnectionClosed(f"connection lost: {e}"))

    def _fail(self, error: ClientError) -> None:
        if self._closed is None:
            self._closed = error
        for waiter in self._waiters:
            if not waiter.future.done():
                waiter.future.set_exception(self._closed)

    def _dispatch(self, item: Item) -> None:
        for tap in self._taps:
            tap.append(item)
        kind = item.kind
        if kind is ItemKind.HANDSHAKE:
            message = decode(kind, item.raw).message
            if self.handshaking and message is not None:
                self._handshake.put_nowait(message)
            elif isinstance(message, m.SendCheckPassword):
                self._fail(HandshakeError("the server asks for a password (winsock mode): give one"))
            else:
                self.stray.append(item)
            return
        channel = None
        if kind is ItemKind.RESPONSE:
            message = decode(kind, item.raw).message
            channel = message.channel if isinstance(message, m.ChannelResponse) else None
        for waiter in self._waiters:
            if waiter.kind is kind and waiter.channel == channel and not waiter.future.done():
                waiter.future.set_result(item)
                return
        if not self._taps:  # what a raw exchange collects is its answer, not stray
            self.stray.append(item)
