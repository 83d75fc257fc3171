"""One replayed connection: its socket, what the server answers, and the pairing of answers with requests.

What crosses the socket becomes traffic events, told to the output
recording and to the replay's table of sessions (one ``Session`` per
connection, ``whiztap.analyzer.traffic.Traffic``); the session's observations
pair each answer with the request it answers, and the tally judges it
against the recorded answer as it arrives: what the recorded server sent, or,
when the replay reproduces a recording made in the middle under its own
faults (``ReplayOptions.reproduce``), what the recorded client received.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from whiztap.analyzer.analysis.compare import answer_key
from whiztap.analyzer.analysis.exchanges import ClientItem
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.observations import Direction, Event, Observation
from whiztap.analyzer.traffic import Closed, Data, HalfClosed, Traffic, TrafficEvent
from whiztap.sniffer.replay.options import Pace, ReplayOptions
from whiztap.sniffer.replay.output import OutputRecording
from whiztap.sniffer.replay.pacing import Pacer
from whiztap.sniffer.replay.plan import ConnectionPlan, Send
from whiztap.sniffer.replay.tally import Tally

READ_SIZE = 65536
C2S, S2C = Direction.C2S, Direction.S2C
_ANSWER_KINDS = frozenset({ItemKind.RESPONSE, ItemKind.CONFIG, ItemKind.IMAGE})


@dataclass(slots=True)
class Slot:
    """A request sent: the recorded item and, once it came, the replayed answer."""

    item: ClientItem
    request: Observation
    replayed: Observation | None = None


class ReplayedConnection:
    """The socket, the replayed session and the pairing for one connection."""

    def __init__(self, p: ConnectionPlan, conn: int, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                 *, options: ReplayOptions, pacer: Pacer, tally: Tally, sessions: Traffic,
                 output: OutputRecording) -> None:
        self.plan = p
        self.conn = conn
        self.reader, self.writer = reader, writer
        self.options, self.pacer, self.tally = options, pacer, tally
        self.sessions, self.output = sessions, output
        self.expected: deque[ClientItem] = deque()  # commands written, not yet observed
        self.slots: dict[int, Slot] = {}  # by the replayed request's index
        self.order: list[Slot] = []
        self.handshake: list[Observation] = []
        self.eof = False
        self.closed_by = ""
        self.sent_items: set[int] = set()
        self.lag_ns = 0  # how much later than recorded the server let this connection go on
        self._wake = asyncio.Event()
        self._reader_task = asyncio.create_task(self._read())

    def waited_for_server(self, step: int) -> None:
        """The client had to wait for the server's ``step``-th handshake item:
        when it came later than recorded, the writes after it keep their
        recorded gaps from it rather than their clock times."""
        recorded = self.plan.recorded.handshake
        if step < len(recorded) and self.options.pace is Pace.RECORDED:
            self.lag_ns = max(self.lag_ns, self.pacer.late_by(recorded[step].item.t_end_ns))
            self.tally.shift_ns = max(self.tally.shift_ns, self.lag_ns)

    def _tell(self, event: TrafficEvent) -> None:
        """A traffic event of this connection: to the output recording, and to
        its session, whose observations are paired and judged."""
        self.output.receive(event)
        self._observe(self.sessions.receive(event))

    # -- input ---------------------------------------------------------------------------

    async def _read(self) -> None:
        clock = self.output.clock
        try:
            while data := await self.reader.read(READ_SIZE):
                self._tell(Data(self.conn, S2C, clock(), data))
                self._wake.set()
        except (ConnectionError, OSError):
            pass
        finally:
            self.eof = True
            self.closed_by = self.closed_by or "server"
            self._tell(HalfClosed(self.conn, clock(), S2C))
            self._wake.set()

    def _observe(self, events: list[Event]) -> None:
        for obs in events:
            if not isinstance(obs, Observation):
                continue  # late violations: unanswered requests are judged at the end
            kind = obs.item.kind
            if obs.direction is C2S:
                if kind is ItemKind.COMMAND and self.expected:
                    slot = Slot(self.expected.popleft(), obs)
                    self.slots[obs.index] = slot
                    self.order.append(slot)
            elif kind is ItemKind.HANDSHAKE:
                self.handshake.append(obs)
                self._judge_handshake(len(self.handshake) - 1)
            elif obs.answers is not None and obs.answers.index in self.slots:
                slot = self.slots[obs.answers.index]
                slot.replayed = obs
                self.tally.judge(self.conn, self.recorded(slot.item), obs, slot.item, slot.item.at_rest)
            elif kind in _ANSWER_KINDS:
                self.tally.judge(self.conn, None, obs, None, False)

    def recorded(self, item: ClientItem) -> Observation | None:
        """The recorded answer the replay's is judged against."""
        return item.received if self.options.reproduce else item.answer

    def _judge_handshake(self, i: int) -> None:
        recorded = self.plan.recorded.received_handshake if self.options.reproduce else self.plan.recorded.handshake
        mine = recorded[i] if i < len(recorded) else None
        theirs = self.handshake[i] if i < len(self.handshake) else None
        self.tally.judge(self.conn, mine, theirs, None, False, "the connection" if i == 0 else "the password")

    async def wait(self, ready: Callable[[], bool], timeout: float) -> bool:
        """Until ``ready()`` or the timeout or the server's close."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while not ready():
            remaining = deadline - loop.time()
            if self.eof or remaining <= 0:
                return ready()
            self._wake.clear()
            try:
                await asyncio.wait_for(self._wake.wait(), remaining)
            except TimeoutError:
                pass
        return True

    # -- output --------------------------------------------------------------------------

    async def write(self, data: bytes, items: tuple[ClientItem, ...], recorded_ns: int,
                    due: int | None) -> None:
        self.writer.write(data)
        now = time.perf_counter_ns()
        drift = None if due is None else max(0, now - due)
        self.expected.extend(i for i in items if i.obs.item.kind is ItemKind.COMMAND)
        self.sent_items.update(id(i) for i in items)
        event = Data(self.conn, C2S, self.output.clock(), data)
        self.output.receive(event)
        self.tally.sent(self.conn, data, items, recorded_ns, drift)
        self._observe(self.sessions.receive(event))
        await self.writer.drain()

    def answered(self, slots: list[Slot]) -> Callable[[], bool]:
        return lambda: all(s.replayed is not None for s in slots)

    def waiting_for(self, send: Send | None = None, lockstep: bool = False) -> list[Slot]:
        """Slots still waiting for an answer worth waiting for: one recorded (the
        server's, even when the recorded client never got it: it waited for it
        too), or (in lockstep) one the request certainly asks for."""
        wanted = {id(i) for i in send.items} if send is not None else None
        out = []
        for slot in self.order:
            if slot.replayed is not None or (wanted is not None and id(slot.item) not in wanted):
                continue
            key = answer_key(slot.item.obs)
            asked = slot.item.answer is not None or self.recorded(slot.item) is not None  # the server answered it
            if asked or (lockstep and key is not None and key[1]):
                out.append(slot)
        return out

    async def finish(self, judge: bool) -> None:
        """Half-close and let the server finish (or, stopping, just drop the
        connection); then judge every answer that never came.

        The client's half-close goes to the output recording only: the replay
        half-closes just to let the server finish, and the session keeps the
        client's side open until the connection closes, as the recorded
        client's did."""
        if judge and not self.eof and not self.writer.is_closing():
            try:
                self.writer.write_eof()
                self.closed_by = self.closed_by or "client"
                self.output.receive(HalfClosed(self.conn, self.output.clock(), C2S))
            except (ConnectionError, OSError):
                pass
            await self.wait(lambda: self.eof, self.options.timeout)
        self._reader_task.cancel()
        await asyncio.gather(self._reader_task, return_exceptions=True)
        closed = Closed(self.conn, self.output.clock(), self.closed_by or "client")
        if not judge:
            self.writer.transport.abort()
            self.output.receive(closed)
            self.sessions.end(self.conn, closed.t_ns)  # its answers are not judged: it was stopped
            return
        self.writer.close()
        self._tell(closed)
        self._judge_unanswered()

    def _judge_unanswered(self) -> None:
        """Judge what never came: the rest of the handshake, the answers, and the requests never sent."""
        recorded = self.plan.recorded
        for i in range(len(self.handshake), len(recorded.received_handshake if self.options.reproduce
                                                else recorded.handshake)):
            self._judge_handshake(i)
        for slot in self.order:
            key = answer_key(slot.item.obs)
            expected = self.recorded(slot.item)
            asked = slot.item.answer is not None or expected is not None
            if slot.replayed is None and (asked or (key is not None and key[1])):
                self.tally.judge(self.conn, expected, None, slot.item, False)
        for send in self.plan.sends:
            for item in send.items:
                if id(item) not in self.sent_items and item.obs.item.kind is ItemKind.COMMAND:
                    self.tally.judge(self.conn, self.recorded(item), None, item, False, note="not sent")
