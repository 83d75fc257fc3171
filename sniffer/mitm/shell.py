"""The asyncio shell around one connection's sans-IO core (``whiztap.analyzer.mitm.core``).

The proxy's ``Connection`` (sniffer/record/proxy.py) turns what its sockets do
into the core's events (``received``, ``ready``, ``sender_ended``, ``lost``)
and this shell carries out the commands the core answers with: a write to a
socket, a FIN passed on, a reset or close, a traffic event for the consumers,
one timer per connection.  Nothing is decided here.

A timer's call is isolated: whatever goes wrong in it is reported once, never
raised into the event loop (a traceback on the terminal) and never into
another connection.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

from whiztap.analyzer.mitm.commands import Command, Deliver, EndConnection, PassEof, Tell, WakeAt
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.traffic import Action
from whiztap.sniffer.nettext import arm_reset

if TYPE_CHECKING:
    from whiztap.sniffer.mitm.controller import Controller

C2S, S2C = Direction.C2S, Direction.S2C


class Leg(Protocol):
    """One socket of a proxied connection (the proxy's ``_Leg``)."""

    transport: asyncio.Transport | None
    lost: bool

    def sync(self) -> None: ...


class Mirrored(Protocol):
    """A mirror server's connection (sniffer/record/mirror.py's ``MirrorLeg``)."""

    def feed(self, data: bytes) -> None: ...


class ProxiedConnection(Protocol):
    """What the shell needs of the proxy's ``Connection`` (sniffer/record/proxy.py),
    which builds on this package, so this package does not import it."""

    id: int
    client_addr: str
    closed_by: str | None
    detail: str

    @property
    def mirror(self) -> Mirrored | None: ...  # record --mirror: what the server gets also goes there
    @property
    def client(self) -> Leg: ...
    @property
    def upstream(self) -> Leg: ...

    def pass_eof(self, leg: Any) -> None: ...  # one of its own legs
    def close_both(self, by: str | None = None, detail: str = "") -> None: ...
    def abort(self) -> None: ...


class MiddleShell:
    def __init__(self, controller: Controller, connection: ProxiedConnection, clock: Callable[[], int],
                 high_water: int = 256 << 10) -> None:
        """``high_water``: the mark of the proxy's transports, under which a receiver takes more."""
        self.controller = controller
        self.connection = connection
        self.clock = clock
        self.high_water = high_water
        self._draining: set[Direction] = set()
        self.emit = controller.emit
        self._timer: asyncio.TimerHandle | None = None
        self._failed = False
        self._may_read = {C2S: True, S2C: True}  # what the core said last: a leg is synced when it changes
        self._eof_passed: set[Direction] = set()
        self.core, commands = controller.open(connection.id, self)
        self.run(commands)

    @property
    def client_addr(self) -> str:
        return self.connection.client_addr

    # -- events from the proxy ----------------------------------------------------------------

    def received(self, direction: Direction, data: bytes, t_ns: int) -> None:
        self.run(self.core.received(direction, data, t_ns))

    def ready(self, direction: Direction) -> None:
        self.run(self.core.ready(direction, self.clock()))

    def sender_ended(self, direction: Direction) -> None:
        self.run(self.core.sender_ended(direction, self.clock()))

    def lost(self, sender: Direction) -> None:
        self.run(self.core.lost(sender, self.clock()))

    def may_read(self, direction: Direction) -> bool:
        return self.core.may_read(direction)

    def drained(self, direction: Direction) -> None:
        """The receiver of ``direction``'s transport is under its mark again (``resume_writing``)."""
        self.run(self.core.writable(direction, self.clock()))

    def _drained(self, direction: Direction) -> None:
        self._draining.discard(direction)
        try:
            self.drained(direction)
        except Exception as e:  # a callback never raises into the loop, nor takes another connection
            self._report_once(e)

    def eof_passed(self, direction: Direction) -> bool:
        """The FIN of ``direction``'s sender was passed on: by this shell, not
        as the core sees it (the core may be a few commands ahead: a close
        that believed it would cut off a write still to be carried out)."""
        return direction in self._eof_passed

    # -- the core's commands ------------------------------------------------------------------

    def run(self, commands: list[Command]) -> None:
        connection = self.connection
        for command in commands:
            match command:
                case Tell():
                    self.emit(command.event)
                case Deliver():
                    leg = connection.upstream if command.direction is C2S else connection.client
                    transport = leg.transport
                    if transport is not None and not transport.is_closing():
                        transport.write(command.data)
                        if command.direction is C2S and connection.mirror is not None:  # record --mirror
                            connection.mirror.feed(command.data)
                case WakeAt():
                    self._schedule(command.t_ns)
                case PassEof():
                    self._eof_passed.add(command.direction)
                    connection.pass_eof(connection.client if command.direction is C2S else connection.upstream)
                case EndConnection():
                    self._end(command.how)
        core = self.core
        for direction, leg in ((C2S, connection.client), (S2C, connection.upstream)):
            may = core.may_read(direction)
            if may is not self._may_read[direction]:  # the lane filled past its mark, or emptied below it
                self._may_read[direction] = may
                leg.sync()
            if core.blocked(direction) and direction not in self._draining:
                receiver = (connection.upstream if direction is C2S else connection.client).transport
                if receiver is not None and not receiver.is_closing() and \
                        receiver.get_write_buffer_size() <= self.high_water:
                    self._draining.add(direction)  # it takes more now: say so once this run is over
                    asyncio.get_running_loop().call_soon(self._drained, direction)
                # else the receiver's transport calls drained() when it is under its mark again

    def _schedule(self, t_ns: int | None) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if t_ns is not None:
            delay = max(0.0, (t_ns - self.clock()) / 1e9)
            self._timer = asyncio.get_running_loop().call_later(delay, self._wake)

    def _wake(self) -> None:
        self._timer = None
        try:
            self.run(self.core.wake(self.clock()))
        except Exception as e:  # a timer never raises into the loop, nor takes another connection
            self._report_once(e)

    def _report_once(self, e: Exception) -> None:
        if not self._failed:
            self._failed = True
            self.controller.report(f"connection {self.connection.id}: the middle's timer failed: "
                                   f"{type(e).__name__}: {e} (reported once)")

    def _end(self, how: Action) -> None:
        connection = self.connection
        if how is Action.CLOSE:
            connection.close_both("proxy", "closed by a fault")
            return
        for leg in (connection.client, connection.upstream):  # a reset: both sides get a TCP RST
            transport = leg.transport
            if transport is None or leg.lost:
                continue
            arm_reset(transport)
        if connection.closed_by is None:
            connection.closed_by, connection.detail = "proxy", "reset by a fault"
        connection.abort()
