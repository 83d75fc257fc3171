"""The proxy in the middle without a socket: a ``Controller`` and its cores
driven on a fake clock, as the proxy's connections and shells drive them
(tests/test_middle_outputs.py, test_middle_memory.py, test_middle_close.py).

``Drive`` plays what the proxy does: for each connection it tells the
consumers ``Opened`` and ``UpstreamConnected``, hands the core what each side
sends (``received``), its FIN (``sender_ended``), a side gone (``lost``) and
the close (``Closed``, then ``Controller.closed``), and carries out the core's
commands as ``MiddleShell`` does: a ``Tell`` is a traffic event for the
consumers (``events``), a ``Deliver`` bytes a side got, ``PassEof`` a FIN
passed on, ``EndConnection`` both sides gone, ``WakeAt`` the one timer.  A
write after the FIN it follows is refused as a real transport refuses it
(``Cannot call write() after write_eof()``), so a core that asks for one
fails the test.  Control requests go through the control API's own
``answer`` (every route, no HTTP), so what they answer is what a person gets.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field

from whiztap.analyzer.mitm.commands import Command, Deliver, EndConnection, PassEof, Tell, WakeAt
from whiztap.analyzer.mitm.core import MiddleCore
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.traffic import Closed, HalfClosed, Opened, UpstreamConnected
from whiztap.sniffer.mitm import http_api
from whiztap.sniffer.mitm.controller import Controller

C2S, S2C = Direction.C2S, Direction.S2C
T0 = 1_700_000_000_000_000_000
MS = 1_000_000


KERNEL = 4 << 20  # what a receiver that never reads still takes: its socket buffers
TRANSPORT_HIGH_WATER = 256 << 10  # the proxy's transports (sniffer/record/proxy.py)


class WriteAfterEof(AssertionError):
    """The core asked to write toward a side after passing that side its FIN."""


@dataclass
class FakeShell:
    """One connection's shell: carries out the core's commands on fake sockets."""

    drive: Drive
    conn: int
    client_addr: str = "127.0.0.1:40000"
    got: dict[Direction, bytearray] = field(default_factory=lambda: {C2S: bytearray(), S2C: bytearray()})
    eof: set[Direction] = field(default_factory=set)  # FIN passed toward that direction's receiver
    wake_at: int | None = None
    ended: str | None = None  # reset or close, by the core
    core: MiddleCore | None = None

    def run(self, commands: list[Command]) -> None:
        drive = self.drive
        for command in commands:
            kind = type(command)
            if kind is Tell:
                drive.events.append(command.event)
            elif kind is Deliver:
                if self.conn in drive.gone:
                    continue  # the shell writes to no closed transport
                if command.direction in self.eof:
                    raise WriteAfterEof(f"#{self.conn}: a write {command.direction} after its FIN was passed on")
                self.got[command.direction] += command.data
            elif kind is PassEof:
                self.eof.add(command.direction)
            elif kind is WakeAt:
                self.wake_at = command.t_ns
            elif kind is EndConnection:
                self.ended = command.how.value
                drive.pending_ends.append(self.conn)
        self._takes_more()

    def _takes_more(self) -> None:
        """As the proxy's transport does: a lane that wrote its burst is told its
        receiver takes more while that receiver's (modeled) transport is under its mark."""
        core, drive = self.core, self.drive
        if core is None or self.conn in drive.gone:
            return
        for direction in (C2S, S2C):
            if core.blocked(direction) and drive.buffered(self.conn, direction) <= TRANSPORT_HIGH_WATER:
                self.run(core.writable(direction, drive.t))


class Drive:
    """A controller, its connections and a fake clock (nanoseconds from ``T0``)."""

    def __init__(self, controller: Controller | None = None, **options: object) -> None:
        self.t = T0
        self.reports: list[str] = []
        self.controller = controller or Controller(seed=1, report=self.reports.append, **options)
        self.events: list[object] = []
        self.controller.attach(lambda: self.t, self.events.append)
        self.shells: dict[int, FakeShell] = {}
        self.gone: set[int] = set()  # closed: both sides lost
        self.lost: dict[int, set[Direction]] = {}
        self.pending_ends: list[int] = []
        self.answers: list[tuple[str, str, int, object]] = []  # (method, path, status, answer) of every request
        self.never_reads: set[tuple[int, Direction]] = set()  # (conn, direction) whose receiver reads nothing

    # -- connections -----------------------------------------------------------------------

    def open(self, conn: int, connected: bool = True) -> MiddleCore:
        """A client connects (and, if ``connected``, its upstream at once)."""
        self.events.append(Opened(conn, self.t, "127.0.0.1:40000", "127.0.0.1:5000"))
        shell = self.shells[conn] = FakeShell(self, conn)
        self.lost[conn] = set()
        opened = self.controller.open(conn, shell)  # the core, and what it asks for first
        shell.core, commands = opened if isinstance(opened, tuple) else (opened, [])
        shell.run(commands)
        if connected:
            self.connect(conn)
        return shell.core

    def connect(self, conn: int) -> None:
        shell = self.shells[conn]
        shell.run(shell.core.ready(S2C, self.t))
        self.events.append(UpstreamConnected(conn, self.t, "from 127.0.0.1:50000"))
        shell.run(shell.core.ready(C2S, self.t))
        self._ends()

    def core(self, conn: int) -> MiddleCore:
        return self.shells[conn].core

    def send(self, conn: int, direction: Direction, data: bytes) -> None:
        """The sender of ``direction`` sent ``data`` (one read), now."""
        if conn in self.gone or direction in self.lost[conn]:
            return
        shell = self.shells[conn]
        shell.run(shell.core.received(direction, data, self.t))
        self._ends()

    def fin(self, conn: int, direction: Direction) -> None:
        if conn in self.gone or direction in self.lost[conn]:
            return
        self.events.append(HalfClosed(conn, self.t, direction))
        shell = self.shells[conn]
        shell.run(shell.core.sender_ended(direction, self.t))
        self._ends()

    def lose(self, conn: int, sender: Direction) -> None:
        """The socket that sends ``sender`` is gone (reset, or closed); once both are, the connection closed."""
        if conn in self.gone or sender in self.lost[conn]:
            return
        self.lost[conn].add(sender)
        shell = self.shells[conn]
        shell.run(shell.core.lost(sender, self.t))
        if len(self.lost[conn]) == 2:
            self.close(conn)
        self._ends()

    def close(self, conn: int, by: str = "client") -> None:
        """Both sides are gone: ``Closed``, then the controller forgets the connection (as the proxy does)."""
        if conn in self.gone:
            return
        self.gone.add(conn)
        self.events.append(Closed(conn, self.t, by, "closed"))
        self.controller.closed(conn)

    def _ends(self) -> None:
        """A reset or close the core asked for: both sockets go."""
        while self.pending_ends:
            conn = self.pending_ends.pop(0)
            for sender in (C2S, S2C):
                self.lose(conn, sender)

    # -- time ------------------------------------------------------------------------------------

    def advance(self, ns: int) -> None:
        """The clock moves on ``ns``; every timer due on the way fires at its time."""
        end = self.t + ns
        while True:
            due = [(s.wake_at, conn) for conn, s in self.shells.items()
                   if s.wake_at is not None and s.wake_at <= end and conn not in self.gone]
            if not due:
                break
            at, conn = min(due)
            self.t = max(self.t, at)
            shell = self.shells[conn]
            shell.wake_at = None
            shell.run(shell.core.wake(self.t))
            self._ends()
        self.t = end

    def settle(self, limit_ns: int = 120_000 * MS) -> None:
        """Let every timer fire (held frames time out, delays end), up to ``limit_ns``."""
        self.advance(limit_ns)

    # -- control ---------------------------------------------------------------------------------

    def api(self, method: str, path: str, body: dict | None = None) -> tuple[int, object]:
        """One control request through the API's own handler; never a 500."""
        request = http_api.Request(method, path, b"" if body is None else json.dumps(body).encode())
        status, answer, _ = http_api.answer(self.controller, request)
        assert status != 500, (method, path, answer, self.reports)
        self.answers.append((method, path, status, answer))
        self._ends()  # a reset or close the request's commands asked for
        return status, answer

    def every_get(self) -> None:
        """Every GET route of the API, answered now."""
        for method, pattern, _ in http_api.ROUTES:
            if method == "GET" and "(" not in pattern.pattern:
                self.api("GET", pattern.pattern.strip("^$"))

    def delivered(self, conn: int, direction: Direction) -> bytes:
        return bytes(self.shells[conn].got[direction])

    def buffered(self, conn: int, direction: Direction) -> int:
        """What the proxy's transport toward the receiver of ``direction`` holds:
        nothing for a receiver that reads; for one that never reads, what was
        delivered to it less what its kernel took."""
        if (conn, direction) not in self.never_reads:
            return 0
        return max(0, len(self.shells[conn].got[direction]) - KERNEL)


def interventions(events: Iterable[object]) -> list:
    from whiztap.analyzer.traffic import Intervention

    return [e for e in events if isinstance(e, Intervention)]
