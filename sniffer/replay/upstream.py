"""One served client's connection to the real server, for the requests its recording cannot answer.

The protocol is stateful: a request means something only after the
connection's handshake, on a connection the server let in.  So each client
connection the stub serves gets at most one upstream connection, opened at
its first miss (a client the recording answers in full needs no server at
all): the handshake the recorded connection had (Winsock: the server's
``sendchkpass``, then the password *this client gave*, then ``readytogo``;
VPN: none), the client's Fetch Configuration if it made one (so the server,
and every reader of the new connection, knows the channel map the client
knew), then each missed request in turn, its answer awaited before the next
is read, so the client gets every answer in the order it asked.

Every event of the upstream connection goes to ``Episodes``, which records
it (the password masked, as the recorder masks it).  A server that cannot be
reached, refuses the password, closes, or does not answer within the timeout
raises ``UpstreamError``: the run then appends nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import ReadyToGo, SendCheckPassword
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.session import Session
from whiztap.analyzer.protocol.text import escape
from whiztap.analyzer.traffic import Closed, Data, HalfClosed, Opened, TrafficEvent, UpstreamConnected
from whiztap.sniffer.replay.episodes import EPISODES_OF, Episodes
from whiztap.sniffer.sim.tcp_server import READ_SIZE

C2S, S2C = Direction.C2S, Direction.S2C


class UpstreamError(WhiztapError):
    """The upstream let a forwarded request down; the message says how, in one line."""


class UpstreamLink:
    """The upstream connection of one served client (recorded connection ``base``)."""

    def __init__(self, episodes: Episodes, base: int, login: bytes | None, config: bytes | None) -> None:
        """``login``: the password the client gave (None: a VPN connection, no handshake);
        ``config``: the client's Fetch Configuration frame, if it sent one."""
        self.episodes, self.base, self.login, self.config = episodes, base, login, config
        self.conn = 0
        self._writer: asyncio.StreamWriter | None = None
        self._reader_task: asyncio.Task[None] | None = None
        self._session = Session(episodes.checksum_rule)
        self._handshake: list[Observation] = []
        self._waiting = -1  # the index of the request whose answer is awaited
        self._answer: bytes | None = None
        self._eof = False
        self._wake = asyncio.Event()

    async def ask(self, request: bytes) -> bytes:
        """Send one request frame; the server's answer (its raw bytes)."""
        if self._writer is None:
            await self._open()
            if self.config is not None:
                await self._exchange(self.config)
        return await self._exchange(request)

    async def _exchange(self, request: bytes) -> bytes:
        t = self.episodes.clock()
        self._tell(Data(self.conn, C2S, t, request))
        commands = [o for o in self._session.receive(C2S, request, t)
                    if isinstance(o, Observation) and o.item.kind is ItemKind.COMMAND]
        self._waiting, self._answer = (commands[-1].index if commands else -1), None
        await self._write(request)
        await self._until(lambda: self._answer is not None, f"no answer to {escape(request)}")
        answer, self._answer, self._waiting = self._answer, None, -1
        assert answer is not None
        return answer

    async def _open(self) -> None:
        episodes = self.episodes
        self.conn = episodes.new_conn()
        self._tell(Opened(self.conn, episodes.clock(), EPISODES_OF.format(self.base), episodes.upstream_text))
        try:
            reader, self._writer = await asyncio.wait_for(asyncio.open_connection(*episodes.upstream),
                                                          episodes.timeout_s)
        except (OSError, TimeoutError) as e:
            self._tell(Closed(self.conn, episodes.clock(), "server", "upstream unreachable"))
            raise UpstreamError(f"cannot connect to {episodes.upstream_text} "
                                f"({getattr(e, 'strerror', None) or e or 'timed out'})") from None
        self._tell(UpstreamConnected(self.conn, episodes.clock()))
        self._reader_task = asyncio.create_task(self._read(reader))
        if self.login is None:
            return
        await self._until(lambda: bool(self._handshake), "no sendchkpass")
        if not isinstance(self._handshake[0].message, SendCheckPassword):
            raise UpstreamError(f"the server began with {escape(self._handshake[0].item.raw)}, not sendchkpass")
        self._tell(Data(self.conn, C2S, episodes.clock(), self.login))
        self._session.receive(C2S, self.login, episodes.clock())
        await self._write(self.login)
        await self._until(lambda: len(self._handshake) > 1, "no answer to the password")
        if not isinstance(self._handshake[1].message, ReadyToGo):
            raise UpstreamError("the server refused the password the client gave")

    async def _write(self, data: bytes) -> None:
        assert self._writer is not None
        try:
            self._writer.write(data)
            await self._writer.drain()
        except (ConnectionError, OSError) as e:
            raise UpstreamError(f"{self.episodes.upstream_text} closed the connection ({e})") from None

    async def _until(self, done: Callable[[], bool], what: str) -> None:
        """Wait for ``done()``; UpstreamError on the server's close or the timeout.
        (``asyncio.timeout``, not ``wait_for``: no task per wait on the forwarding path.)"""
        upstream = self.episodes.upstream_text
        try:
            async with asyncio.timeout(self.episodes.timeout_s):
                while not done():
                    if self._eof:
                        raise UpstreamError(f"{upstream} closed the connection ({what})")
                    if self._handshake and self.login is None:
                        raise UpstreamError(f"{upstream} asks for a password (Winsock), but the recorded "
                                            "connection had none (VPN)")
                    self._wake.clear()
                    await self._wake.wait()
        except TimeoutError:
            raise UpstreamError(f"{what} from {upstream} within {self.episodes.timeout_s:g} s") from None

    async def _read(self, reader: asyncio.StreamReader) -> None:
        try:
            while data := await reader.read(READ_SIZE):
                t = self.episodes.clock()
                self._tell(Data(self.conn, S2C, t, data))
                for obs in self._session.receive(S2C, data, t):
                    if not isinstance(obs, Observation):
                        continue
                    if obs.item.kind is ItemKind.HANDSHAKE:
                        if len(self._handshake) < 2:  # greeting and verdict: a server's repeats are not kept
                            self._handshake.append(obs)
                    elif obs.answers is not None and obs.answers.index == self._waiting:
                        self._answer = obs.item.raw
                self._wake.set()
        except (ConnectionError, OSError):
            pass
        finally:
            self._eof = True
            self._tell(HalfClosed(self.conn, self.episodes.clock(), S2C))
            self._wake.set()

    def _tell(self, event: TrafficEvent) -> None:
        self.episodes.tell(event)

    async def close(self) -> None:
        """The served client left: close the upstream connection too."""
        if self._writer is None:
            return
        writer, self._writer = self._writer, None
        writer.close()
        with contextlib.suppress(ConnectionError, OSError):
            await writer.wait_closed()
        if self._reader_task is not None:
            self._reader_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._reader_task
        self._tell(Closed(self.conn, self.episodes.clock(), "client", "the stub's client left"))

    def abort(self) -> None:
        """Close at once (the stub is closing).  A request still waiting for
        its answer would be appended without one: the run appends nothing."""
        if self._waiting >= 0:
            self.episodes.fail("the stub stopped while a forwarded request waited for its answer")
        if self._writer is not None:
            self._writer.transport.abort()
            self._writer = None
        if self._reader_task is not None:
            self._reader_task.cancel()
