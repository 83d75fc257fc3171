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

Faults (``options.faults``, parsed SPECs as ``whiztap record --fault`` takes
them): the replay connects through a proxy in the middle
(``whiztap.sniffer.replay.faults``) that applies them between it and the
target, seeded with ``options.fault_seed``; answers are judged as the replay
receives them, after the faults, against the recorded answers: what the
recorded server sent, or, with ``options.reproduce``, what the recorded
client received (a recording made in the middle, replayed under its own
faults, passes when it reproduces what its client went through).  The
target's own answers, before the faults, are judged against the recorded
server's apart (``server_side.py``, ``ReplayResult.server``).

The options and the error are in ``whiztap.sniffer.replay.options``, the
events and the result in ``whiztap.sniffer.replay.events``.
"""

from __future__ import annotations

import asyncio
import dataclasses
import socket
from collections.abc import Callable, Coroutine

from whiztap.analyzer.analysis.exchanges import RecordedSessions
from whiztap.analyzer.protocol.messages import FailedValidation, SendCheckPassword
from whiztap.analyzer.protocol.session import Session
from whiztap.analyzer.recording.format import MASK_BYTE
from whiztap.analyzer.traffic import Opened, Traffic, UpstreamConnected
from whiztap.sniffer.nettext import reason, show_address
from whiztap.sniffer.replay.connection import ReplayedConnection
from whiztap.sniffer.replay.faults import FaultProxy
from whiztap.sniffer.replay.events import ConnectionClosed, ConnectionOpened, Event, Finished, ReplayResult
from whiztap.sniffer.replay.options import Pace, ReplayError, ReplayOptions
from whiztap.sniffer.replay.output import OutputRecording
from whiztap.sniffer.replay.pacing import Pacer, Stopped
from whiztap.sniffer.replay.plan import NS, ConnectionPlan, plan
from whiztap.sniffer.replay.server_side import ServerSide
from whiztap.sniffer.replay.tally import Tally


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
        self._pacer = Pacer(options.rate)
        self._tally = Tally(recording.start_ns, options.rules, on_event)
        timeout_ns = int(options.timeout * NS)
        self._sessions = Traffic(lambda: Session(options.checksum_rule, answer_timeout_ns=timeout_ns,
                                                 assumed_channels=options.assumed_channels))
        self._output = OutputRecording(options, recording.path, on_error=self.stop)
        self._next_conn = 1
        self._tasks: set[asyncio.Task] = set()
        self._middle: FaultProxy | None = None  # with faults, while running
        self._server: ServerSide | None = None  # with faults: the target's own side, judged apart
        self._connect_to = options.target

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
        self._tally.begin()
        error = None
        ticker = None
        try:
            await self._start_middle()
            if self.options.output is not None:
                self._output.open(self.options.output)
                ticker = asyncio.create_task(self._output.tick())
            for loop in range(1, self.options.loop + 1):
                if self._pacer.stopped:
                    break
                await self._run_once(loop)
        except ReplayError as e:
            error = str(e)
        finally:
            if self._middle is not None:
                await self._middle.close()  # its last events, before the output is finished
            if ticker is not None:
                ticker.cancel()
            try:
                self._output.close(discard_if_empty=error is not None)
            except ReplayError as e:
                error = error or str(e)
        result = self._tally.result(self.options.pace is Pace.RECORDED, self._pacer.stopped, error)
        if self._server is not None:
            result = dataclasses.replace(result, server=self._server.result())
        self._tally.emit(Finished(result))
        return result

    async def _start_middle(self) -> None:
        """With faults: the proxy that applies them, where connections go instead
        of the target; its events are what an output records, on its clock."""
        if not self.options.faults:
            return
        output = self._output
        options = self.options
        self._server = ServerSide(Tally(self.recording.start_ns, options.rules, None), options.checksum_rule,
                                  int(options.timeout * NS), options.assumed_channels)
        self._middle = FaultProxy(options, output.record if options.output is not None else None,
                                  self._server.receive)
        output.clock = self._middle.clock
        self._connect_to = await self._middle.start()

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

    async def _together(self, coros: list[Coroutine[None, None, None]]) -> None:
        """Run connections until all are done; the first ReplayError ends them all."""
        tasks = [asyncio.create_task(c) for c in coros]
        self._tasks.update(tasks)
        try:
            done, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_EXCEPTION)
            for task in pending:
                task.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
            for task in done:
                error = None if task.cancelled() else task.exception()
                if error is not None:
                    raise error
        finally:
            for task in tasks:  # when run() itself is cancelled
                task.cancel()
            self._tasks.difference_update(tasks)

    async def _connection(self, p: ConnectionPlan, loop: int) -> None:
        recorded = self.options.pace is Pace.RECORDED
        try:
            await self._pacer.turn(p.recorded.opened_ns, recorded, write=False)
        except Stopped:
            return
        c = await self._open(p, loop)
        judge = False
        try:
            if not p.winsock or await self._handshake(c, recorded):
                await self._send(c, recorded)
            await c.wait(c.answered(c.waiting_for()), self.options.timeout)
            judge = True
        except Stopped:
            pass
        except (ConnectionError, OSError):
            judge = True  # the server went away: what it did not answer is missing
        finally:
            await c.finish(judge)
            if judge and self._server is not None:
                self._server.finish(c)
            self._tally.emit(ConnectionClosed(c.conn, self._tally.at(), c.closed_by or "client",
                                              "judged" if judge else "stopped"))

    async def _open(self, p: ConnectionPlan, loop: int) -> ReplayedConnection:
        """Connect to the target for the next replayed connection, and say so."""
        reader, writer = await self._connect()
        conn = self._next_conn
        self._next_conn += 1
        self._tally.connections += 1
        local = show_address(*writer.get_extra_info("sockname")[:2])
        t = self._output.clock()
        self._output.receive(Opened(conn, t, local, show_address(*self.options.address)))
        self._output.receive(UpstreamConnected(conn, t))
        self._tally.emit(ConnectionOpened(conn, p.recorded.conn, loop, self._tally.at(), local))
        c = ReplayedConnection(p, conn, reader, writer, options=self.options, pacer=self._pacer,
                               tally=self._tally, sessions=self._sessions, output=self._output)
        if self._server is not None:
            self._server.attach(local, c)
        return c

    async def _send(self, c: ReplayedConnection, recorded: bool) -> None:
        """The connection's planned writes, each at its turn (in lockstep, each
        after the answers it expects)."""
        for send in c.plan.sends:
            if c.eof:
                break
            due = await self._pacer.turn(send.t_ns, recorded, write=True, lag_ns=c.lag_ns)
            await c.write(send.data, send.items, send.t_ns, due)
            if self.options.pace is Pace.LOCKSTEP:
                await c.wait(c.answered(c.waiting_for(send, lockstep=True)), self.options.timeout)

    async def _connect(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        """A connection to the target (with faults, through the proxy, once it
        has reached the target: one that cannot be reached fails here alike)."""
        host, port = self._connect_to or self.options.address
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
        if self._middle is not None:
            try:
                await self._middle.reached(show_address(*writer.get_extra_info("sockname")[:2]))
            except ReplayError:
                writer.transport.abort()
                raise
        return reader, writer

    async def _handshake(self, c: ReplayedConnection, recorded: bool) -> bool:
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
