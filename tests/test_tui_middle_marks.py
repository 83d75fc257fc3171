"""The TUI's marks find their frame by the facts an intervention carries
(offsets, the held id), never by its bytes: the middle's real core on a fake
clock, its traffic events straight into the TUI's model, no socket."""

from __future__ import annotations

from whiztap.analyzer.mitm.commands import Command, Tell, WakeAt
from whiztap.analyzer.protocol.codec import encode
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import FetchConfiguration
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.traffic import Action, Closed, Opened
from whiztap.sniffer.mitm.controller import Controller
from whiztap.tui.widgets.detail import describe_frame
from whiztap.tui.data.model import TrafficModel

from tests.middle_support import sensor
from tests.test_tui_middle import plain

C2S, S2C = Direction.C2S, Direction.S2C
T0 = 1_700_000_000_000_000_000
MS = 1_000_000
ANSWER_12 = b"cr1-12--431--0-ss1"
CONFIG = b"sr1-\x04000000101200-ss1"  # channel 12 a sensor


class Rig:
    """One connection through the middle's core, its events into a TUI model."""

    client_addr = "127.0.0.1:40000"

    def __init__(self, *faults: str, intercept: str | None = None) -> None:
        self.now = T0
        self.wake_at: int | None = None
        self.model = TrafficModel()
        self.model.in_the_middle(redact=False)
        self.controller = Controller(seed=0)
        self.controller.attach(lambda: self.now, lambda event: None)
        for spec in faults:
            self.controller.add_fault(spec)
        if intercept:
            self.controller.set_intercept(intercept)
        self.model.receive(Opened(1, T0, self.client_addr, "127.0.0.1:5000"))
        self.core, commands = self.controller.open(1, self)
        self.run(commands)
        self.run(self.core.ready(C2S, T0))
        self.run(self.core.ready(S2C, T0))

    def run(self, commands: list[Command]) -> None:
        for command in commands:
            if isinstance(command, Tell):
                self.model.receive(command.event)
            elif isinstance(command, WakeAt):
                self.wake_at = command.t_ns

    def client(self, *frames: bytes) -> None:
        self.run(self.core.received(C2S, b"".join(frames), self.now))

    def server(self, *frames: bytes) -> None:
        self.run(self.core.received(S2C, b"".join(frames), self.now))

    def later(self, ns: int) -> None:
        """The fake clock moves on; the core's timer fires if it is due."""
        self.now += ns
        if self.wake_at is not None and self.wake_at <= self.now:
            self.wake_at = None
            self.run(self.core.wake(self.now))

    @property
    def store(self):
        return self.model.store

    def rows(self, direction: Direction) -> list[int]:
        return [n for n in range(self.store.count) if self.store.direction(n) is direction]

    def actions(self, n: int) -> list[Action]:
        return [m.action for m in self.store.marks.get(n, ())]


def unanswered(store, n: int) -> bool:
    return any(v.rule_id == "PW-PAIR-UNANSWERED" for v in store.violations.get(n, ()))


def test_of_two_identical_answers_the_dropped_one_is_marked_not_the_latest():
    """Both answers come in one read, so both rows are stored before the
    proxy tells that it dropped the first: matching the mark by its bytes
    took the latest row with them (the one the client did get)."""
    rig = Rig("drop dir:s2c kind:response nth:1")
    rig.client(sensor(12), sensor(12))
    rig.server(ANSWER_12, ANSWER_12)
    first, second = rig.rows(S2C)
    assert rig.store.raw(first) == rig.store.raw(second) == ANSWER_12
    assert rig.actions(first) == [Action.DROP] and rig.actions(second) == []
    request_1, request_2 = rig.rows(C2S)
    assert rig.store.pair[first] == request_1 and unanswered(rig.store, request_1)
    assert rig.store.pair[second] == request_2 and not unanswered(rig.store, request_2)


def test_of_two_identical_answers_the_delayed_one_is_marked_when_it_goes():
    rig = Rig("delay:50ms dir:s2c kind:response nth:1")
    rig.client(sensor(12), sensor(12))
    rig.server(ANSWER_12, ANSWER_12)
    first, second = rig.rows(S2C)
    assert rig.actions(first) == rig.actions(second) == []  # told once delivered
    rig.later(50 * MS)
    assert rig.actions(first) == [Action.DELAY] and rig.actions(second) == []


def test_a_request_held_twice_goes_with_its_own_release_by_the_held_id():
    """Two identical requests are held; the first is dropped by hand and the
    second let go: the drop is a row of its own with its hold, the delivered
    request has the other hold and its release."""
    rig = Rig(intercept="kind:command")
    rig.client(sensor(12), sensor(12))
    first, second = sorted(rig.controller.held.frames)
    assert rig.rows(C2S) == []  # nothing delivered yet
    rig.controller.drop(first)
    rig.controller.release(second)
    [dropped] = [n for n in rig.rows(C2S) if Action.DROP in rig.actions(n)]
    [delivered] = [n for n in rig.rows(C2S) if n != dropped]
    assert rig.actions(dropped) == [Action.HOLD, Action.DROP]
    assert [m.held for m in rig.store.marks[dropped]] == [first, first]
    assert rig.actions(delivered) == [Action.HOLD, Action.RELEASE]
    assert [m.held for m in rig.store.marks[delivered]] == [second, second]
    assert rig.store.raw(dropped) == rig.store.raw(delivered) == sensor(12)


def test_every_copy_of_a_duplicated_request_is_marked_and_the_next_one_is_not():
    rig = Rig("dup dir:c2s nth:1")
    rig.client(sensor(12), sensor(12))
    rows = rig.rows(C2S)
    assert len(rows) == 3 and {rig.store.raw(n) for n in rows} == {sensor(12)}
    assert [rig.actions(n) for n in rows] == [[Action.DUP], [Action.DUP], []]


def test_an_injected_request_is_marked_where_it_was_delivered_and_pairs_with_its_answer():
    rig = Rig()
    rig.client(sensor(12))
    rig.controller.inject(1, "c2s", "sensor 12")
    rig.server(ANSWER_12, ANSWER_12)
    requests = rig.rows(C2S)
    assert [rig.actions(n) for n in requests] == [[], [Action.INJECT]]
    answers = rig.rows(S2C)
    assert [rig.store.pair[n] for n in answers] == requests
    assert rig.store.kind(answers[1]) is ItemKind.RESPONSE


def test_a_request_dropped_by_a_fault_is_a_row_with_the_marks_told_on_it_before():
    rig = Rig("corrupt dir:c2s nth:1", "drop dir:c2s nth:1")
    rig.client(sensor(12), sensor(12))
    dropped, delivered = rig.rows(C2S)
    assert rig.actions(dropped) == [Action.CORRUPT, Action.DROP] and rig.actions(delivered) == []
    assert rig.store.raw(delivered) == sensor(12) and rig.store.raw(dropped) != sensor(12)  # as it was dropped


def test_a_delayed_answer_shows_the_servers_latency_and_the_clients():
    """The server answered in 1 ms; the proxy held the answer 300 ms more:
    the detail pane and the statistics say both, each labelled."""
    rig = Rig("delay:300ms dir:s2c kind:response")
    rig.client(encode(FetchConfiguration()))
    rig.later(MS)
    rig.server(CONFIG)
    rig.later(300 * MS)
    rig.client(sensor(12))
    rig.later(MS)
    rig.server(ANSWER_12)
    rig.later(300 * MS)
    [_, answer] = rig.rows(S2C)
    assert rig.actions(answer) == [Action.DELAY]
    shown = plain(describe_frame(rig.store, answer))
    assert "latency for the server 1.00 ms, for the client 301.00 ms" in shown, shown
    rig.run(rig.core.closed(rig.now))
    rig.model.receive(Closed(1, rig.now, "client"))
    server, client = rig.model.both_latencies()
    assert server["Sensor Request"].max == MS and client["Sensor Request"].max == 301 * MS


def test_a_request_a_reset_took_away_is_one_row_with_its_marks_once():
    rig = Rig("reset dir:c2s nth:2")
    rig.client(sensor(12), sensor(13))
    [delivered] = [n for n in rig.rows(C2S) if rig.store.raw(n) == sensor(12)]
    [reset] = [n for n in rig.rows(C2S) if rig.store.raw(n) == sensor(13)]
    assert len(rig.rows(C2S)) == 2 and rig.actions(delivered) == []
    marks = rig.store.marks[reset]
    assert {m.action for m in marks} == {Action.RESET} and len(marks) == len(set(marks))
