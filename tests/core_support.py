"""The middle's sans-IO core on a fake clock: a Controller whose clock a test
moves, and a shell that only notes what the core asked for.  No socket, no
loop, no sleep: a second of fault time costs nothing."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from whiztap.analyzer.mitm.commands import Command, Deliver, EndConnection, PassEof, Tell, WakeAt
from whiztap.analyzer.mitm.core import MiddleCore
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.traffic import Action, Data, Delivered, Intervention
from whiztap.sniffer.mitm.controller import Controller

C2S, S2C = Direction.C2S, Direction.S2C
T0 = 1_700_000_000_000_000_000
MS = 1_000_000
S = 1_000_000_000


@dataclass
class NotingShell:
    """Carries out nothing; keeps every command, and the one wake-up asked for."""

    client_addr: str = "127.0.0.1:40000"
    commands: list[Command] = field(default_factory=list)
    wake_at: int | None = None

    core: MiddleCore | None = None
    now: Callable[[], int] = lambda: 0
    reads: bool = True  # the receivers take what is written (else a lane stops after its burst)

    def run(self, commands: list[Command]) -> None:
        for command in commands:
            self.commands.append(command)
            if type(command) is WakeAt:
                self.wake_at = command.t_ns
        core = self.core
        if core is not None and self.reads:
            for direction in (C2S, S2C):
                if core.blocked(direction):
                    self.run(core.writable(direction, self.now()))


class FakeClockMiddle:
    """One connection through a Controller with ``specs`` in force, both sides ready."""

    def __init__(self, *specs: str, intercept: str | None = None, hold_timeout: float = 60.0, seed: int = 0,
                 redact: bool = True, ready: bool = True, checksum_rule: str = "dev-sum") -> None:
        self.now = T0
        self.reports: list[str] = []
        self.controller = Controller(seed=seed, hold_timeout=hold_timeout, checksum_rule=checksum_rule, redact=redact,
                                     report=self.reports.append)
        self.controller.attach(lambda: self.now, lambda event: None)
        for spec in specs:
            self.controller.add_fault(spec)
        if intercept:
            self.controller.set_intercept(intercept)
        self.shell = NotingShell()
        self.core, commands = self.controller.open(1, self.shell)
        self.shell.core, self.shell.now = self.core, lambda: self.now
        self.shell.run(commands)
        if ready:
            for direction in (C2S, S2C):
                self.shell.run(self.core.ready(direction, self.now))

    def send(self, direction: Direction, data: bytes) -> None:
        self.shell.run(self.core.received(direction, data, self.now))

    def advance(self, ns: int) -> None:
        """Move the clock ``ns`` on, waking the core at each time it asked for on the way."""
        end = self.now + ns
        while self.shell.wake_at is not None and self.shell.wake_at <= end:
            self.now = max(self.now, self.shell.wake_at)
            self.shell.wake_at = None
            self.shell.run(self.core.wake(self.now))
        self.now = end

    # -- what came out ------------------------------------------------------------------------

    def writes(self, direction: Direction) -> list[bytes]:
        return [c.data for c in self.shell.commands if type(c) is Deliver and c.direction is direction]

    def got(self, direction: Direction) -> bytes:
        """Everything written toward the receiver of ``direction``."""
        return b"".join(self.writes(direction))

    def events(self) -> list[object]:
        return [c.event for c in self.shell.commands if type(c) is Tell]

    def interventions(self, action: Action | None = None) -> list[Intervention]:
        return [e for e in self.events() if type(e) is Intervention and (action is None or e.action is action)]

    def delivered_events(self, direction: Direction) -> list[Delivered]:
        return [e for e in self.events() if type(e) is Delivered and e.direction is direction]

    def reads(self, direction: Direction) -> bytes:
        return b"".join(e.data for e in self.events() if type(e) is Data and e.direction is direction)

    def write_times(self, direction: Direction) -> list[int]:
        """When each write toward ``direction``'s receiver happened (its Delivered event's time)."""
        return [e.t_ns for e in self.delivered_events(direction)]

    def ended(self) -> list[Action]:
        return [c.how for c in self.shell.commands if type(c) is EndConnection]

    def eofs(self) -> list[Direction]:
        return [c.direction for c in self.shell.commands if type(c) is PassEof]
