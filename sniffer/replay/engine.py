"""Replay a recording's client side against a live server and judge its answers.

The engine behind ``whiztap replay``, the pytest plugin and the TUI.  Use it
from a running asyncio event loop, and call its control methods from that
loop's thread (from another thread, through ``loop.call_soon_threadsafe``)::

    recording = load_exchanges("session.mcap")
    replay = Replay(recording, ReplayOptions(target=("127.0.0.1", 5000), password=b"progwhiz"),
                    on_event=print)
    replay.check()                     # ReplayError: no target, nothing selected, no password
    result = await replay.run()        # returns when done, stopped or failed
    result.exit_status                 # 0 all matched, 1 any difference, 2 unreachable / write error

``run()`` raises ``ReplayError`` only for what ``check()`` finds; a target
that cannot be reached or an output that cannot be written ends the run with
``result.error`` set (and a ``Finished`` event), like any other end.

Control, at any time while ``run()`` is awaited:

- ``pause()``: no further write leaves until ``resume()`` or ``step()``;
  answers still arrive and are judged, and the recorded schedule waits too.
- ``resume()``: carry on; the schedule is shifted by the time spent paused.
- ``step()``: let exactly one write (one frame, or one recorded read with
  ``segments="exact"``) go now, then pause again.  Called while running, it
  pauses after the next write.
- ``stop()``: end the replay; ``run()`` returns a result with ``stopped`` set
  and does not judge answers still outstanding.
- ``paused`` says whether writes are held.

``on_event(event)`` is called on the loop's thread with small frozen objects,
in the order things happen; it must return quickly and not raise:

- ``ConnectionOpened(conn, recorded_conn, loop, at_s, local)``
- ``RequestSent(conn, at_s, recorded_s, data, text, drift_ns)``: a write left;
  ``drift_ns`` is how late against the schedule (recorded pacing only).
- ``ResponseCompared(conn, at_s, recorded_s, request, request_text, recorded,
  replayed, status, match, diff)``: an answer was judged, as it arrived, or
  at the end of its connection for one that never came (``replayed`` None,
  status ``missing``).  ``status`` is an ``whiztap.analyzer.analysis.compare.Status``;
  ``diff`` is the readable side-by-side text ("" for a match).  The server's
  handshake words are judged the same way, with ``request`` None and
  ``request_text`` "the connection" or "the password"; so is a server frame
  that answers nothing (status ``extra``, ``request_text`` "").
- ``ConnectionClosed(conn, at_s, by, detail)``
- ``Finished(result)``: always last, also after ``stop()`` or an error.

``at_s`` is seconds since ``run()`` began; ``recorded_s`` is the recorded
time, in seconds from the recording's first read (``whiztap cat``'s clock).

Pacing: ``recorded`` keeps the original gaps divided by ``rate``; connections
open at their recorded times and run side by side.  ``lockstep`` sends a write,
then waits for the answers it expects (or ``timeout``); ``max`` writes as fast
as the server reads.  In both, connections run one after another.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum

from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE
from whiztap.analyzer.analysis.compare import CompareRules, Status, answer_key, compare, headline, side_by_side
from whiztap.analyzer.protocol.describe import meaning
from whiztap.analyzer.analysis.exchanges import ClientItem, RecordedSessions
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import FailedValidation, SendCheckPassword
from whiztap.analyzer.recording.format import MASK_BYTE
from whiztap.analyzer.protocol.session import Direction, Observation, Session
from whiztap.analyzer.protocol.stats import LatencyStats
from whiztap.analyzer.protocol.text import escape
from whiztap.sniffer.nettext import reason, show_address
from whiztap.sniffer.replay.plan import ConnectionPlan, Selection, Send, plan

NS = 1_000_000_000
SPIN_NS = 2_000_000  # the last stretch before a due time is waited out without a timer
READ_SIZE = 65536
TICK_S = 0.2  # how often the output recording is flushed
C2S, S2C = Direction.C2S, Direction.S2C
_ANSWER_KINDS = frozenset({ItemKind.RESPONSE, ItemKind.CONFIG, ItemKind.IMAGE})


class Pace(StrEnum):
    RECORDED = "recorded"
    LOCKSTEP = "lockstep"
    MAX = "max"


class ReplayError(Exception):
    """The replay cannot start or go on (one line for the user).

    ``missing`` names a setting the replay needs and was not given ("target",
    "password"): each front end says how to give it in its own terms
    (``explained``); the command line and the TUI check the target themselves
    before a replay exists, so only the password reaches them this way.
    """

    def __init__(self, message: str, missing: str | None = None) -> None:
        super().__init__(message)
        self.missing = missing

    def explained(self, how: dict[str, str]) -> str:
        """The message, with ``how[missing]`` saying how to give what is missing."""
        hint = how.get(self.missing or "")
        return f"{self}: {hint}" if hint else str(self)


@dataclass(frozen=True, slots=True)
class ReplayOptions:
    target: tuple[str, int] | None = None
    password: bytes | None = None  # None: the recorded one if it was kept
    pace: Pace = Pace.RECORDED
    rate: float = 1.0
    segments: bool = False  # re-send the recorded TCP reads instead of whole frames
    rules: CompareRules = CompareRules()
    timeout: float = 2.0  # for each expected answer and the handshake
    connect_timeout: float = 5.0
    loop: int = 1
    selection: Selection = Selection()
    output: str | None = None  # write the replayed session here as a recording
    checksum_rule: str = DEFAULT_CHECKSUM_RULE


# -- events -------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ConnectionOpened:
    conn: int
    recorded_conn: int
    loop: int
    at_s: float
    local: str


@dataclass(frozen=True, slots=True)
class RequestSent:
    conn: int
    at_s: float
    recorded_s: float
    data: bytes
    text: str
    drift_ns: int | None


@dataclass(frozen=True, slots=True)
class ResponseCompared:
    conn: int
    at_s: float
    recorded_s: float
    request: bytes | None
    request_text: str
    recorded: bytes | None
    replayed: bytes | None
    status: Status
    match: bool
    diff: str


@dataclass(frozen=True, slots=True)
class ConnectionClosed:
    conn: int
    at_s: float
    by: str
    detail: str


@dataclass(frozen=True, slots=True)
class Drift:
    """How late writes left against the recorded schedule."""

    count: int
    p50_ns: int
    p99_ns: int
    max_ns: int
    shift_ns: int = 0  # the most a slow handshake moved a connection's schedule

    def text(self) -> str:
        text = (f"drift from schedule over {self.count} writes: p50 {self.p50_ns / 1e6:.3f} ms, "
                f"p99 {self.p99_ns / 1e6:.3f} ms, max {self.max_ns / 1e6:.3f} ms")
        if self.shift_ns:
            text += f" (schedule moved up to {self.shift_ns / 1e6:.3f} ms later by the server's handshake)"
        return text


@dataclass(frozen=True)
class ReplayResult:
    connections: int
    writes: int
    counts: dict[Status, int]
    differences: tuple[ResponseCompared, ...]
    drift: Drift | None
    stopped: bool = False
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None and not self.differences

    @property
    def exit_status(self) -> int:
        return 2 if self.error is not None else 0 if self.ok else 1

    def as_dict(self) -> dict:
        """The result as plain data (``whiztap replay --format json``); bytes as escaped text."""

        def text(data: bytes | None) -> str | None:
            return escape(data) if data is not None else None

        return {
            "connections": self.connections, "writes": self.writes,
            "answers": {str(s): self.counts.get(s, 0) for s in Status},
            "ok": self.ok, "exit_status": self.exit_status, "stopped": self.stopped, "error": self.error,
            "differences": [{
                "conn": d.conn, "at_s": d.at_s, "recorded_s": d.recorded_s, "request": text(d.request),
                "request_text": d.request_text, "recorded": text(d.recorded), "replayed": text(d.replayed),
                "status": str(d.status), "diff": d.diff,
            } for d in self.differences],
            "drift": None if self.drift is None else {
                "count": self.drift.count, "p50_ns": self.drift.p50_ns, "p99_ns": self.drift.p99_ns,
                "max_ns": self.drift.max_ns, "shift_ns": self.drift.shift_ns},
        }

    def summary(self) -> str:
        c = self.counts
        judged = ", ".join(f"{c.get(s, 0)} {s}" for s in (Status.MATCH, Status.MISMATCH, Status.MISSING,
                                                           Status.EXTRA, Status.UNANSWERED, Status.IGNORED))
        return f"replayed {self.connections} connection(s), {self.writes} writes; answers: {judged}"


@dataclass(frozen=True, slots=True)
class Finished:
    result: ReplayResult


Event = ConnectionOpened | RequestSent | ResponseCompared | ConnectionClosed | Finished


# -- pacing and control ---------------------------------------------------------------------


class _Stopped(Exception):
    pass


class _Pacer:
    """When each write may leave: the schedule, and pause / resume / step.

    The schedule maps recorded times to ``perf_counter_ns``; time spent paused
    shifts it, and a stepped write re-anchors it so the write is due now."""

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.paused = False
        self.stopped = False
        self._tokens = 0
        self._pause_after_next = False
        self._changed = asyncio.Event()
        self._origin = 0
        self._base = time.perf_counter_ns()
        self._paused_at = 0

    def anchor(self, origin_ns: int) -> None:
        self._origin = origin_ns
        self._base = time.perf_counter_ns()
        self._paused_at = self._base

    def due(self, t_rec: int) -> int:
        return self._base + int((t_rec - self._origin) / self.rate)

    def _notify(self) -> None:
        self._changed.set()
        self._changed = asyncio.Event()

    def pause(self) -> None:
        if not self.paused:
            self.paused = True
            self._paused_at = time.perf_counter_ns()
            self._notify()

    def resume(self) -> None:
        self._tokens = 0
        self._pause_after_next = False
        if self.paused:
            self.paused = False
            self._base += time.perf_counter_ns() - self._paused_at
            self._notify()

    def step(self) -> None:
        if self.paused:
            self._tokens += 1
        else:
            self._pause_after_next = True
        self._notify()

    def stop(self) -> None:
        self.stopped = True
        self._notify()

    async def changed(self, timeout: float | None = None) -> None:
        try:
            await asyncio.wait_for(self._changed.wait(), timeout)
        except TimeoutError:
            pass

    def late_by(self, t_rec: int) -> int:
        """How far now is past the time ``t_rec`` is due (0 when not yet due)."""
        return max(0, time.perf_counter_ns() - self.due(t_rec))

    async def turn(self, t_rec: int, recorded: bool, write: bool, lag_ns: int = 0) -> int | None:
        """Wait until something recorded at ``t_rec`` may happen; the due time.

        ``lag_ns`` shifts the due time (a connection whose server answered its
        handshake later than recorded keeps its gaps, not its clock times).
        Only writes take a step; opening a connection waits out a pause unless
        a step is pending (the step's write needs the connection)."""
        while True:
            if self.stopped:
                raise _Stopped
            if self.paused:
                if self._tokens and not write:
                    return None
                if self._tokens:
                    self._tokens -= 1
                    now = time.perf_counter_ns()
                    self._base = now - int((t_rec - self._origin) / self.rate)
                    self._paused_at = now
                    return now if recorded else None
                await self.changed()
                continue
            if not recorded:
                self._after_write(write)
                return None
            due = self.due(t_rec) + lag_ns
            remaining = due - time.perf_counter_ns()
            if remaining > SPIN_NS:
                await self.changed((remaining - SPIN_NS) / NS)
                continue
            while time.perf_counter_ns() < due and not (self.paused or self.stopped):
                await asyncio.sleep(0)
            if self.paused or self.stopped:
                continue
            self._after_write(write)
            return due

    def _after_write(self, write: bool) -> None:
        if write and self._pause_after_next:
            self._pause_after_next = False
            self.pause()


# -- one replayed connection ----------------------------------------------------------------------


@dataclass(slots=True)
class _Slot:
    """A request sent: the recorded item and, once it came, the replayed answer."""

    item: ClientItem
    request: Observation
    replayed: Observation | None = None


@dataclass(slots=True)
class _Tally:
    counts: Counter = field(default_factory=Counter)
    differences: list[ResponseCompared] = field(default_factory=list)
    drift: LatencyStats = field(default_factory=LatencyStats)
    shift_ns: int = 0
    writes: int = 0
    connections: int = 0


class _Connection:
    """The socket, the replayed session and the pairing for one connection."""

    def __init__(self, replay: Replay, p: ConnectionPlan, conn: int,
                 reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.replay = replay
        self.plan = p
        self.conn = conn
        self.reader, self.writer = reader, writer
        timeout_ns = int(replay.options.timeout * NS)
        self.session = Session(replay.options.checksum_rule, answer_timeout_ns=timeout_ns)
        self.expected: deque[ClientItem] = deque()  # commands written, not yet observed
        self.slots: dict[int, _Slot] = {}  # by the replayed request's index
        self.order: list[_Slot] = []
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
        if step < len(recorded) and self.replay.options.pace is Pace.RECORDED:
            self.lag_ns = max(self.lag_ns, self.replay._pacer.late_by(recorded[step].item.t_end_ns))
            tally = self.replay._tally
            tally.shift_ns = max(tally.shift_ns, self.lag_ns)

    # -- input ---------------------------------------------------------------------------

    async def _read(self) -> None:
        replay = self.replay
        try:
            while data := await self.reader.read(READ_SIZE):
                replay._record("data", self.conn, S2C, data)
                self._observe(self.session.receive(S2C, data, time.perf_counter_ns()))
                self._wake.set()
        except (ConnectionError, OSError):
            pass
        finally:
            self.eof = True
            self.closed_by = self.closed_by or "server"
            replay._record("half_closed", self.conn, S2C)
            self._observe(self.session.end(S2C, time.perf_counter_ns()))
            self._wake.set()

    def _observe(self, events: list) -> None:
        for obs in events:
            if not isinstance(obs, Observation):
                continue  # late violations: unanswered requests are judged at the end
            kind = obs.item.kind
            if obs.direction is C2S:
                if kind is ItemKind.COMMAND and self.expected:
                    slot = _Slot(self.expected.popleft(), obs)
                    self.slots[obs.index] = slot
                    self.order.append(slot)
            elif kind is ItemKind.HANDSHAKE:
                self.handshake.append(obs)
                self._judge_handshake(len(self.handshake) - 1)
            elif obs.answers is not None and obs.answers.index in self.slots:
                slot = self.slots[obs.answers.index]
                slot.replayed = obs
                self.replay._judge(self.conn, slot.item.answer, obs, slot.item, slot.item.at_rest)
            elif kind in _ANSWER_KINDS:
                self.replay._judge(self.conn, None, obs, None, False)

    def _judge_handshake(self, i: int) -> None:
        recorded = self.plan.recorded.handshake
        mine = recorded[i] if i < len(recorded) else None
        theirs = self.handshake[i] if i < len(self.handshake) else None
        self.replay._judge(self.conn, mine, theirs, None, False, "the connection" if i == 0 else "the password")

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
        replay = self.replay
        self.writer.write(data)
        now = time.perf_counter_ns()
        drift = None if due is None else max(0, now - due)
        self.expected.extend(i for i in items if i.obs.item.kind is ItemKind.COMMAND)
        self.sent_items.update(id(i) for i in items)
        replay._record("data", self.conn, C2S, data)
        replay._sent(self.conn, data, items, recorded_ns, drift)
        self._observe(self.session.receive(C2S, data, now))
        await self.writer.drain()

    def answered(self, slots: list[_Slot]) -> Callable[[], bool]:
        return lambda: all(s.replayed is not None for s in slots)

    def waiting_for(self, send: Send | None = None, lockstep: bool = False) -> list[_Slot]:
        """Slots still waiting for an answer worth waiting for: one recorded, or
        (in lockstep) one the request certainly asks for."""
        wanted = {id(i) for i in send.items} if send is not None else None
        out = []
        for slot in self.order:
            if slot.replayed is not None or (wanted is not None and id(slot.item) not in wanted):
                continue
            key = answer_key(slot.item.obs)
            if slot.item.answer is not None or (lockstep and key is not None and key[1]):
                out.append(slot)
        return out

    async def finish(self, judge: bool) -> None:
        """Half-close and let the server finish (or, stopping, just drop the
        connection); then judge every answer that never came."""
        if judge and not self.eof and not self.writer.is_closing():
            try:
                self.writer.write_eof()
                self.closed_by = self.closed_by or "client"
                self.replay._record("half_closed", self.conn, C2S)
            except (ConnectionError, OSError):
                pass
            await self.wait(lambda: self.eof, self.replay.options.timeout)
        self._reader_task.cancel()
        await asyncio.gather(self._reader_task, return_exceptions=True)
        if not judge:
            self.writer.transport.abort()
            return
        self.writer.close()
        self._observe(self.session.close(time.perf_counter_ns()))
        replay = self.replay
        for i in range(len(self.handshake), len(self.plan.recorded.handshake)):
            self._judge_handshake(i)
        for slot in self.order:
            key = answer_key(slot.item.obs)
            if slot.replayed is None and (slot.item.answer is not None or (key is not None and key[1])):
                replay._judge(self.conn, slot.item.answer, None, slot.item, False)
        for send in self.plan.sends:
            for item in send.items:
                if id(item) not in self.sent_items and item.obs.item.kind is ItemKind.COMMAND:
                    replay._judge(self.conn, item.answer, None, item, False, note="not sent")


# -- the engine ------------------------------------------------------------------------------------


class Replay:
    """One replay of a recording; see the module docstring for the API."""

    def __init__(self, recording: RecordedSessions, options: ReplayOptions,
                 on_event: Callable[[Event], None] | None = None) -> None:
        if options.rate <= 0:
            raise ReplayError("--rate must be above 0")
        if options.loop < 1:
            raise ReplayError("--loop must be at least 1")
        self.recording = recording
        self.options = options
        self.on_event = on_event
        self.plans = plan(recording, options.selection, options.segments)
        self._pacer = _Pacer(options.rate)
        self._tally = _Tally()
        self._t0 = time.perf_counter_ns()
        self._recorder = None
        self._wall = None
        self._output_error: str | None = None
        self._next_conn = 1
        self._tasks: set[asyncio.Task] = set()

    def check(self) -> None:
        """Raise ReplayError for what would stop a replay before it starts."""
        if self.options.target is None:
            raise ReplayError("no target", missing="target")
        if not self.plans:
            raise ReplayError("nothing to replay: no connection is selected")
        if any(p.winsock and p.recorded.password is not None and self.password_for(p) is None for p in self.plans):
            raise ReplayError("the recording's password is redacted", missing="password")

    def password_for(self, p: ConnectionPlan) -> bytes | None:
        """What a connection sends as its password (None: it needs --password).

        A connection the server refused is replayed refused: with the password it
        recorded if secrets were kept, else with one sure to differ from
        --password; so is one whose client left before the server's verdict
        (a password perhaps never finished).  An accepted one sends --password,
        or the one it recorded if secrets were kept.
        """
        recorded = p.recorded.password
        kept = recorded.obs.item.raw if recorded is not None and self.recording.secrets_kept else None
        if p.recorded.refused or len(p.recorded.handshake) < 2:
            if kept is not None:
                return kept
            wrong = MASK_BYTE * (len(recorded.obs.item.raw) if recorded is not None else 1)
            return wrong + MASK_BYTE if wrong == self.options.password else wrong
        return self.options.password if self.options.password is not None else kept

    # -- control -------------------------------------------------------------------------------

    @property
    def paused(self) -> bool:
        return self._pacer.paused

    def pause(self) -> None:
        self._pacer.pause()

    def resume(self) -> None:
        self._pacer.resume()

    def step(self) -> None:
        self._pacer.step()

    def stop(self) -> None:
        self._pacer.stop()
        for task in list(self._tasks):
            task.cancel()

    # -- running ---------------------------------------------------------------------------------

    async def run(self) -> ReplayResult:
        """Replay; the result (also sent as the ``Finished`` event)."""
        self.check()
        self._t0 = time.perf_counter_ns()
        error = None
        ticker = None
        try:
            if self.options.output is not None:
                self._open_output()
                ticker = asyncio.create_task(self._tick())
            for loop in range(1, self.options.loop + 1):
                if self._pacer.stopped:
                    break
                await self._run_once(loop)
        except ReplayError as e:
            error = str(e)
        finally:
            if ticker is not None:
                ticker.cancel()
            try:
                self._close_output(discard_if_empty=error is not None)
            except ReplayError as e:
                error = error or str(e)
        t = self._tally
        drift = None
        if self.options.pace is Pace.RECORDED and t.drift.count:
            d = t.drift
            drift = Drift(d.count, d.percentile(50), d.percentile(99), d.max, t.shift_ns)
        result = ReplayResult(t.connections, t.writes, dict(t.counts), tuple(t.differences), drift,
                              self._pacer.stopped, error)
        self._emit(Finished(result))
        return result

    async def _run_once(self, loop: int) -> None:
        """One pass over the plans: side by side on the recorded schedule, or
        one connection after another."""
        start_s = self.options.selection.start_s
        origin = min(p.recorded.opened_ns for p in self.plans)
        if start_s is not None:
            origin = max(origin, self.recording.start_ns + int(start_s * NS))
        self._pacer.anchor(origin)
        if self.options.pace is Pace.RECORDED:
            await self._together([self._connection(p, loop) for p in self.plans])
        else:
            for p in self.plans:
                await self._together([self._connection(p, loop)])

    async def _together(self, coros: list) -> None:
        """Run connections until all are done; the first ReplayError ends them all."""
        tasks = [asyncio.create_task(c) for c in coros]
        self._tasks.update(tasks)
        try:
            done, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_EXCEPTION)
            for task in pending:
                task.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
            for task in done:
                if not task.cancelled() and task.exception() is not None:
                    raise task.exception()  # type: ignore[misc]
        finally:
            for task in tasks:  # when run() itself is cancelled
                task.cancel()
            self._tasks.difference_update(tasks)

    async def _connection(self, p: ConnectionPlan, loop: int) -> None:
        pacer = self._pacer
        options = self.options
        recorded = options.pace is Pace.RECORDED
        try:
            await pacer.turn(p.recorded.opened_ns, recorded, write=False)
        except _Stopped:
            return
        reader, writer = await self._open()
        conn = self._next_conn
        self._next_conn += 1
        self._tally.connections += 1
        local = show_address(*writer.get_extra_info("sockname")[:2])
        self._record("opened", conn, local=local)
        self._emit(ConnectionOpened(conn, p.recorded.conn, loop, self._at(), local))
        c = _Connection(self, p, conn, reader, writer)
        judge = False
        try:
            if not p.winsock or await self._handshake(c, recorded):
                for send in p.sends:
                    if c.eof:
                        break
                    due = await pacer.turn(send.t_ns, recorded, write=True, lag_ns=c.lag_ns)
                    await c.write(send.data, send.items, send.t_ns, due)
                    if options.pace is Pace.LOCKSTEP:
                        await c.wait(c.answered(c.waiting_for(send, lockstep=True)), options.timeout)
            await c.wait(c.answered(c.waiting_for()), options.timeout)
            judge = True
        except _Stopped:
            pass
        except (ConnectionError, OSError):
            judge = True  # the server went away: what it did not answer is missing
        finally:
            await c.finish(judge)
            by = c.closed_by or "client"
            self._record("closed", conn, by=by)
            self._emit(ConnectionClosed(conn, self._at(), by, "judged" if judge else "stopped"))

    async def _open(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        host, port = self.options.target  # type: ignore[misc]
        try:
            reader, writer = await asyncio.wait_for(asyncio.open_connection(host, port),
                                                    self.options.connect_timeout)
        except TimeoutError:
            raise ReplayError(f"cannot connect to {show_address(host, port)}: timed out") from None
        except OSError as e:
            raise ReplayError(f"cannot connect to {show_address(host, port)}: {reason(e)}") from None
        sock = writer.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return reader, writer

    async def _handshake(self, c: _Connection, recorded: bool) -> bool:
        """Wait for sendchkpass, send the password, wait for the verdict; False
        when the server refused it (the rest of the connection is not sent)."""
        timeout = self.options.timeout
        if not await c.wait(lambda: bool(c.handshake), timeout):
            return True  # no sendchkpass: send the commands anyway, the difference is reported
        if not isinstance(c.handshake[0].message, SendCheckPassword):
            return True
        c.waited_for_server(0)
        password = c.plan.recorded.password
        if password is None:
            return True  # the client never answered (a probe, a health check): neither does the replay
        due = await self._pacer.turn(c.plan.password_t_ns, recorded, write=True, lag_ns=c.lag_ns)
        items = (password,) if password is not None else ()
        await c.write((self.password_for(c.plan) or b"") + c.plan.password_tail, items, c.plan.password_t_ns, due)
        await c.wait(lambda: len(c.handshake) >= 2, timeout)
        c.waited_for_server(1)
        return not (len(c.handshake) >= 2 and isinstance(c.handshake[1].message, FailedValidation))

    # -- bookkeeping ---------------------------------------------------------------------------

    def _at(self) -> float:
        return (time.perf_counter_ns() - self._t0) / NS

    def _emit(self, event: Event) -> None:
        if self.on_event is not None:
            self.on_event(event)

    def _sent(self, conn: int, data: bytes, items: tuple[ClientItem, ...], recorded_ns: int,
              drift: int | None) -> None:
        self._tally.writes += 1
        if drift is not None:
            self._tally.drift.add(drift)
        shown = [meaning(i.obs) for i in items if i.obs.item.kind is not ItemKind.EOL]
        text = "; ".join(shown) if shown else f"{len(data)} bytes"
        if any(i.obs.item.kind is ItemKind.PASSWORD for i in items):
            data, text = b"*" * len(data), "Password"
        self._emit(RequestSent(conn, self._at(), self._recorded_s(recorded_ns), data, text, drift))

    def _recorded_s(self, t_ns: int) -> float:
        return (t_ns - self.recording.start_ns) / NS

    def _judge(self, conn: int, recorded: Observation | None, replayed: Observation | None,
               item: ClientItem | None, at_rest: bool, what: str = "", note: str = "") -> None:
        verdict = compare(recorded, replayed, self.options.rules, at_rest)
        self._tally.counts[verdict.status] += 1
        if verdict.status is Status.UNANSWERED:
            return
        request = item.obs if item is not None else None
        if recorded is not None:
            t_rec = recorded.item.t_end_ns
        else:
            t_rec = item.t_ns if item is not None else self.recording.start_ns
        recorded_s = self._recorded_s(t_rec)
        diff = ""
        if not verdict.match:
            head = headline(verdict, conn, recorded_s, request, what)
            if note or not (request or what):
                head += f" ({note or 'it answers no request'})"
            lines = [head] + side_by_side(recorded, replayed, verdict)
            diff = "\n".join(lines)
        event = ResponseCompared(
            conn, self._at(), recorded_s, request.item.raw if request is not None else None,
            meaning(request) if request is not None else what, recorded.item.raw if recorded else None,
            replayed.item.raw if replayed else None, verdict.status, verdict.match, diff)
        if not verdict.match:
            self._tally.differences.append(event)
        self._emit(event)

    # -- the output recording ------------------------------------------------------------------------

    def _open_output(self) -> None:
        from whiztap.sniffer.record.proxy import Clock
        from whiztap.sniffer.cli.record import base_metadata
        from whiztap.sniffer.record.recorder import Recorder
        from whiztap.sniffer.record.writer import RecordingFile, RecordingWriteError

        options = self.options
        self._wall = Clock()
        start = self._wall()
        target = show_address(*options.target)  # type: ignore[misc]
        metadata = base_metadata("replay", False, options.checksum_rule, start, replay_of=self.recording.path,
                                 target=target, pace=str(options.pace), rate=options.rate)
        self._recorder = Recorder(RecordingFile(options.output, metadata),  # type: ignore[arg-type]
                                  checksum_rule=options.checksum_rule)
        try:
            self._recorder.start(start, detail=f"replay of {self.recording.path} against {target}")
        except RecordingWriteError as e:
            self._recorder = None
            raise ReplayError(str(e)) from None

    def _record(self, what: str, conn: int, direction: Direction | None = None, data: bytes = b"",
                **details: str) -> None:
        recorder = self._recorder
        if recorder is None:
            return
        from whiztap.sniffer.record.writer import RecordingWriteError

        t = self._wall()  # type: ignore[misc]
        try:
            if what == "data":
                recorder.data(conn, direction, t, data)
            elif what == "opened":
                recorder.opened(conn, t, details["local"], show_address(*self.options.target))  # type: ignore[misc]
                recorder.upstream_connected(conn, t)
            elif what == "half_closed":
                recorder.half_closed(conn, direction, t)
            elif what == "closed":
                recorder.closed(conn, t, details["by"])
        except RecordingWriteError as e:
            self._recorder = None
            self.stop()
            self._output_error = str(e)

    async def _tick(self) -> None:
        """Flush the output recording now and then, as the recorder expects."""
        from whiztap.sniffer.record.writer import RecordingWriteError

        while self._recorder is not None:
            await asyncio.sleep(TICK_S)
            try:
                self._recorder.tick(self._wall())  # type: ignore[misc]
            except RecordingWriteError as e:
                self._recorder = None
                self._output_error = str(e)
                self.stop()

    def _close_output(self, discard_if_empty: bool = False) -> None:
        """Finish the output recording.  A replay that failed before any
        connection (the target unreachable) leaves no file: an empty recording
        would only make the next try refuse to overwrite it."""
        from whiztap.sniffer.record.writer import RecordingWriteError

        error = self._output_error
        if self._recorder is not None:
            recorder, self._recorder = self._recorder, None
            try:
                summary = recorder.stop(self._wall(), "replay finished")  # type: ignore[misc]
            except RecordingWriteError as e:
                error = str(e)
            else:
                if discard_if_empty and summary.connections == 0:
                    for path in summary.files:
                        with contextlib.suppress(OSError):
                            os.unlink(path)
        if error:
            raise ReplayError(error)

