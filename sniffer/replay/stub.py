"""Serve a recording's server side: a stand-in server for a client under test.

Each client connection is answered from one recorded connection: by default
the k-th client from the k-th recorded connection that completed its handshake
(a VPN one, or a Winsock one the server let in; later clients from the last
such), or every client from ``conn``: the same handshake, then for each
request the recorded answer to a request of the same kind and channel, in
recorded order, byte for byte (``match`` chooses the fields: near_miss.Match).
When a kind's answers are used up the last one is repeated, or
(``exhausted="fail"``) none is sent.

A request the stub cannot answer (the recording has no answer for it, or its
recorded answer never came) is logged, kept in ``unanswered`` and met at once
as ``unmatched`` says: ``close`` the connection (the default), ``ignore`` it
(send nothing, as the recording did), or send a given frame: never a silent
wait until the client's own timeout.  Each miss carries the closest recorded
requests and the fields that differ (``near``), and ``unused()`` lists the
recorded exchanges no client asked for, so a recording that rots shows.

The client's bytes go through the analyzer's session model, so requests are
recognised however the client cuts its writes, and the channel map the stub
itself sent resolves ambiguous frames as it did in the recording.

With ``episodes`` (``--upstream``, the plugin's ``new_episodes``) a miss is
not met but forwarded to the real server on the client's own upstream
connection (``upstream.UpstreamLink``), its answer sent back and recorded,
to be appended to the recording when the run ends (``episodes.Episodes``).
Connections appended so serve the recorded connection they were made for:
their exchanges come after its own (``_Script.extend``).
"""

from __future__ import annotations

import asyncio
import itertools
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum

from whiztap.analyzer.analysis.compare import answer_key
from whiztap.analyzer.protocol.describe import meaning
from whiztap.analyzer.analysis.exchanges import RecordedConnection, RecordedSessions
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import ChannelConfig, FailedValidation, FetchConfiguration, ReadyToGo
from whiztap.analyzer.protocol.handshake import Mode
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.session import Session
from whiztap.analyzer.protocol.text import escape
from whiztap.sniffer.replay.episodes import Episodes, episodes_of
from whiztap.sniffer.replay.near_miss import Match, NearMiss, Recorded, closest
from whiztap.sniffer.replay.options import Pace
from whiztap.sniffer.replay.upstream import UpstreamError, UpstreamLink
from whiztap.sniffer.sim.tcp_server import READ_SIZE, TcpServer

NS = 1_000_000_000
_PASSWORD_END = (b"\r", b"\n", b"rr1-", b"sr1-")
_FAILED = FailedValidation().title.encode()


class Unmatched(StrEnum):
    CLOSE = "close"  # close the client's connection at once
    IGNORE = "ignore"  # send nothing and go on


class Exhausted(StrEnum):
    REPEAT = "repeat"  # answer with the last recorded answer again
    FAIL = "fail"  # answer nothing, and log the request as unanswered


@dataclass(frozen=True, slots=True)
class Unanswered:
    """A request the stub had no recorded answer for."""

    conn: int
    request: bytes
    text: str
    why: str = "no recorded answer"
    near: tuple[NearMiss, ...] = ()  # the closest recorded requests, closest first

    def line(self) -> str:
        return f"#{self.conn}: {self.why} for {escape(self.request)} ({self.text})"

    def near_lines(self) -> list[str]:
        """One line per close recorded request: which, and what differs."""
        return [f"closest recorded: {n.line()}" for n in self.near]

    def as_dict(self) -> dict:
        return {"conn": self.conn, "request": escape(self.request), "text": self.text, "why": self.why,
                "closest": [n.as_dict() for n in self.near]}


@dataclass(frozen=True, slots=True)
class _Answer:
    raw: bytes
    delay_ns: int


class _Script:
    """What one recorded connection's server said, arranged for serving."""

    def __init__(self, rec: RecordedConnection, match: Match) -> None:
        self.conn = rec.conn
        self.winsock = rec.mode is Mode.WINSOCK
        shake = rec.handshake
        self.let_in = rec.mode is Mode.VPN or (len(shake) > 1 and isinstance(shake[1].message, ReadyToGo))
        password = rec.password
        self.greeting = shake[0].item.raw if shake else b""
        self.greeting_delay = max(0, shake[0].item.t_end_ns - rec.opened_ns) if shake else 0
        self.verdict = shake[1].item.raw if len(shake) > 1 else ReadyToGo().title.encode()
        after = password.t_ns if password is not None else rec.opened_ns
        self.verdict_delay = max(0, shake[1].item.t_end_ns - after) if len(shake) > 1 else 0
        self.requests: list[Recorded] = []  # every request served from, for near misses and unused
        self.answers: dict[tuple, list[tuple[Recorded, _Answer | None]]] = {}
        self.match = match
        self.extend(rec)

    def extend(self, rec: RecordedConnection, appended: bool = False) -> None:
        """Serve ``rec``'s exchanges too, after those already here: its own at
        first, then those of each connection appended with new episodes of it
        (``appended``; the channel map such a connection fetched first for a
        client that had it already is no episode, and is not served)."""
        position = 0
        match = self.match
        for item in rec.requests:
            key = answer_key(item.obs)
            if key is None:
                continue
            position += 1
            if item.answer is None and not key[1]:
                continue
            answer = item.answer
            entry = None if answer is None else _Answer(answer.item.raw, max(0, answer.item.t_end_ns - item.t_ns))
            recorded = Recorded(rec.conn, position, *key[0], item.obs.item.raw, meaning(item.obs))
            group = match.key(*key[0], recorded.value)
            if appended and position == 1 and isinstance(item.obs.message, FetchConfiguration) \
                    and group in self.answers:
                continue
            self.requests.append(recorded)
            self.answers.setdefault(group, []).append((recorded, entry))


def _scripts(recording: RecordedSessions, match: Match) -> list[_Script]:
    """A script per recorded connection; one appended with new episodes of
    another extends that one's script instead."""
    scripts: dict[int, _Script] = {}
    for rec in recording.connections:
        base = episodes_of(rec.client)
        if base in scripts:
            scripts[base].extend(rec, appended=True)
        else:
            scripts[rec.conn] = _Script(rec, match)
    return list(scripts.values())


class Stub(TcpServer):
    """Serves ``recording`` on ``host:port``; ``start()``/``close()`` or ``async with``.

    ``on_log(line)`` gets a line per client connection and per request with no
    recorded answer."""

    def __init__(self, recording: RecordedSessions, host: str = "127.0.0.1", port: int = 0, *,
                 password: bytes | None = None, pace: Pace | str = Pace.MAX, rate: float = 1.0,
                 exhausted: Exhausted | str = Exhausted.REPEAT, conn: int | None = None,
                 unmatched: Unmatched | str | bytes = Unmatched.CLOSE, match: Match | None = None,
                 on_log: Callable[[str], None] | None = None,
                 assumed_channels: tuple[ChannelConfig, ...] = (), episodes: Episodes | None = None) -> None:
        """``unmatched``: ``"close"``, ``"ignore"``, or the bytes of a frame to send.
        ``assumed_channels``: the map ``--channels`` states, for clients that never fetch it.
        ``episodes``: forward misses to the real server and record them (opened
        and finished by the caller)."""
        self.episodes = episodes
        self.forwarded = 0  # misses the upstream answered
        self.assumed_channels = assumed_channels
        self.match = match or Match()
        self.pace = Pace(pace)
        if self.pace is Pace.LOCKSTEP:
            raise ValueError("a stub answers at the recorded delay (recorded) or at once (max)")
        if rate <= 0:
            raise ValueError("--rate must be above 0")
        scripts = _scripts(recording, self.match)
        if conn is not None:
            scripts = [s for s in scripts if s.conn == conn]
            if not scripts:
                raise ValueError(f"the recording has no connection {conn}")
        elif any(s.let_in for s in scripts):
            scripts = [s for s in scripts if s.let_in]  # a failed login is served only on request (conn)
        if not scripts:
            raise ValueError("the recording has no connection to serve")
        self.unmatched = unmatched if isinstance(unmatched, bytes) else Unmatched(unmatched)
        self.recording = recording
        super().__init__(host, port)
        self.password = password
        self.rate = rate
        self.exhausted = Exhausted(exhausted)
        self.on_log = on_log or (lambda line: None)
        self.unanswered: list[Unanswered] = []
        self.connections = 0
        self.answers = 0
        self.finished = asyncio.Event()  # set each time a client connection ends
        self._scripts = scripts
        self._numbers = itertools.count(1)
        self._used: set[tuple[int, int]] = set()  # (recorded conn, position) of each answer given

    def unused(self) -> list[Recorded]:
        """Recorded requests no client's request was answered from, in recorded order."""
        return [r for s in self._scripts for r in s.requests if (r.conn, r.position) not in self._used]

    # -- one client ---------------------------------------------------------------------------

    async def _serve_connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        number = next(self._numbers)
        self.connections += 1
        script = self._scripts[min(number, len(self._scripts)) - 1]
        peer = writer.get_extra_info("peername")
        self.on_log(f"#{number} opened from {peer[0]}:{peer[1]}, answered from recorded connection {script.conn}")
        served = _Served(self, script, number, writer)
        try:
            await served.run(reader)
            await served.close()
        except (ConnectionError, OSError):
            served.abort()
        except asyncio.CancelledError:  # the stub is closing; not re-raised, as
            served.abort()  # asyncio's server would log a cancelled handler
        finally:
            self.on_log(f"#{number} closed")
            self.finished.set()


class _Served:
    """One client connection: handshake, then answers in order, each at its time."""

    def __init__(self, stub: Stub, script: _Script, number: int, writer: asyncio.StreamWriter) -> None:
        self.stub, self.script, self.number, self.writer = stub, script, number, writer
        self.session = Session(stub.recording.checksum_rule, assumed_channels=stub.assumed_channels)
        self.cursors: Counter[tuple] = Counter()
        self.login: bytes | None = None  # the password the client gave, for its upstream connection
        self.link: UpstreamLink | None = None
        self.config: bytes | None = None  # the client's Fetch Configuration, once answered
        self.position = 0  # answerable requests so far, as Recorded.position counts them
        self.recorded_pace = stub.pace is Pace.RECORDED
        self._due = 0.0  # answers leave in order, each no earlier than its delay
        self._queue: asyncio.Queue[tuple[float, bytes] | None] = asyncio.Queue()
        self._sender = asyncio.create_task(self._send_loop())

    async def run(self, reader: asyncio.StreamReader) -> None:
        pending: bytes | None = b""
        if self.script.winsock:
            self.send(self.script.greeting, self.script.greeting_delay)
            pending = await self._password(reader)
            if pending is None:
                return
        if pending and not await self._receive(pending):
            return
        while data := await reader.read(READ_SIZE):
            if not await self._receive(data):
                return  # an unmatched request closes the connection
        self.session.end(Direction.C2S, time.perf_counter_ns())

    async def _password(self, reader: asyncio.StreamReader) -> bytes | None:
        """Read the password and answer it; the bytes after it, or None when the
        connection is over (refused, or the client left)."""
        expected = self.stub.password
        got = b""
        while True:
            data = await reader.read(READ_SIZE)
            if not data:
                return None
            got += data
            if expected is not None:
                if not expected.startswith(got[:len(expected)]):
                    self._feed(got)
                    self.send(_FAILED, self.script.verdict_delay)
                    return None
                if len(got) < len(expected):
                    continue
                cut = len(expected)
            else:
                ends = [i for i in (got.find(t) for t in _PASSWORD_END) if i > 0]
                cut = min(ends, default=len(got))
            self._feed(got[:cut])
            self.login = got[:cut]
            self.send(self.script.verdict, self.script.verdict_delay)
            return None if self.script.verdict == _FAILED else got[cut:]

    def _feed(self, data: bytes) -> list:
        return self.session.receive(Direction.C2S, data, time.perf_counter_ns())

    async def _receive(self, data: bytes) -> bool:
        """Answer the requests in ``data``; False once the connection is to close."""
        for obs in self._feed(data):
            if (isinstance(obs, Observation) and obs.direction is Direction.C2S
                    and obs.item.kind is ItemKind.COMMAND):
                if not await self._answer(obs):
                    return False
                if isinstance(obs.message, FetchConfiguration):
                    self.config = obs.item.raw
        return True

    async def _answer(self, request: Observation) -> bool:
        key = answer_key(request)
        if key is None:
            return True
        self.position += 1
        group = self.stub.match.key(*key[0], request.item.raw)
        recorded = self.script.answers.get(group, [])
        i = self.cursors[group] if self.stub.match.order else 0
        if i < len(recorded):
            self.cursors[group] += 1
            used, answer = recorded[i]
        elif recorded and self.stub.exhausted is Exhausted.REPEAT:
            used, answer = recorded[-1]
        elif key[1] or recorded:  # a frame that only may ask is new only if it never did
            if self.stub.episodes is not None:
                return await self._forward(request)
            return self._unmatched(request, "no recorded answer")
        else:
            return True
        self.stub._used.add((used.conn, used.position))
        if answer is None:
            return self._unmatched(request, "no answer in the recording either")
        self.stub.answers += 1
        self.send(answer.raw, answer.delay_ns)
        return True

    async def _forward(self, request: Observation) -> bool:
        """Ask the real server what the recording cannot answer; a failed
        upstream leaves the request unmatched, and the run appends nothing."""
        episodes = self.stub.episodes
        assert episodes is not None
        raw = request.item.raw
        if episodes.failure is not None:
            return self._unmatched(request, "no recorded answer (the upstream failed earlier)")
        if self.link is None:
            self.link = UpstreamLink(episodes, self.script.conn, self.login if self.script.winsock else None,
                                     self.config)
        try:
            answer = await self.link.ask(raw)
        except UpstreamError as e:
            episodes.fail(str(e))
            self.stub.on_log(f"! upstream failed: {e}; nothing will be appended to {episodes.path}")
            return self._unmatched(request, "no recorded answer (the upstream failed)")
        episodes.exchanges += 1
        self.stub.forwarded += 1
        self.stub.on_log(f"#{self.number}: no recorded answer for {escape(raw)} ({meaning(request)}): "
                         f"forwarded to {episodes.upstream_text}, new episode")
        self.send(answer, 0)
        return True

    def _unmatched(self, request: Observation, why: str) -> bool:
        """Log and count a request the stub cannot answer, and meet it at once."""
        key = answer_key(request)
        text = meaning(request)
        asked = Recorded(self.number, self.position, *(key[0] if key else (text, None)), request.item.raw, text)
        miss = Unanswered(self.number, request.item.raw, text, why, tuple(closest(asked, self.script.requests)))
        self.stub.unanswered.append(miss)
        reaction = self.stub.unmatched
        if isinstance(reaction, bytes):
            self.stub.on_log(f"! {miss.line()}: sent {escape(reaction)}")
        else:
            self.stub.on_log(f"! {miss.line()}" + ("; connection closed" if reaction is Unmatched.CLOSE else ""))
        for line in miss.near_lines():
            self.stub.on_log(f"!   {line}")
        if isinstance(reaction, bytes):
            self.send(reaction, 0)
            return True
        return reaction is not Unmatched.CLOSE

    def send(self, data: bytes, delay_ns: int) -> None:
        """Queue bytes to leave after the recorded delay (recorded pace) or at once."""
        loop = asyncio.get_running_loop()
        delay = delay_ns / NS / self.stub.rate if self.recorded_pace else 0.0
        self._due = max(self._due, loop.time() + delay)
        self._queue.put_nowait((self._due, data))
        # the session sees the answer now, so the next request is read in its light
        self.session.receive(Direction.S2C, data, time.perf_counter_ns())

    async def _send_loop(self) -> None:
        loop = asyncio.get_running_loop()
        while (entry := await self._queue.get()) is not None:
            due, data = entry
            if due > loop.time():
                await asyncio.sleep(due - loop.time())
            self.writer.write(data)
            await self.writer.drain()

    async def close(self) -> None:
        """Send what is queued, then close."""
        self._queue.put_nowait(None)
        await self._sender
        self.writer.close()
        if self.link is not None:
            await self.link.close()

    def abort(self) -> None:
        self._sender.cancel()
        self.writer.transport.abort()
        if self.link is not None:
            self.link.abort()
