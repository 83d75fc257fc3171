"""The middle's asyncio shell (sniffer/mitm/shell.py) carries out its core's
commands in order on the proxy's real Connection; here with transports that
note what was done to them, so an order that real sockets hit only now and
then is played every time."""

from __future__ import annotations

from whiztap.analyzer.protocol.observations import Direction
from whiztap.sniffer.mitm.controller import Controller
from whiztap.sniffer.mitm.shell import MiddleShell
from whiztap.sniffer.record.proxy import Connection, RecordingProxy

C2S, S2C = Direction.C2S, Direction.S2C


class NotingTransport:
    """A transport that keeps what it was asked to write, and when it was closed."""

    def __init__(self, log: list[tuple[str, object]], name: str) -> None:
        self.log, self.name, self.closing = log, name, False

    def write(self, data: bytes) -> None:
        self.log.append((self.name, data))

    def write_eof(self) -> None:
        self.log.append((self.name, "eof"))

    def can_write_eof(self) -> bool:
        return True

    def close(self) -> None:
        self.closing = True
        self.log.append((self.name, "close"))

    def is_closing(self) -> bool:
        return self.closing

    def get_write_buffer_size(self) -> int:
        return 0

    def pause_reading(self) -> None:
        pass

    def resume_reading(self) -> None:
        pass


class _Nowhere:
    def receive(self, event: object) -> None:
        pass


async def test_a_fin_passed_before_a_write_of_the_other_way_does_not_close_over_that_write():
    now = [1_700_000_000_000_000_000]
    controller = Controller(report=lambda line: None)
    proxy = RecordingProxy("127.0.0.1", 0, "127.0.0.1", 9, _Nowhere(), controller=controller)
    controller.attach(lambda: now[0], lambda event: None)
    controller.add_fault("delay:1ms dir:s2c")
    connection = Connection(proxy, 1)
    log: list[tuple[str, object]] = []
    connection.client.transport = NotingTransport(log, "client")
    connection.upstream.transport = NotingTransport(log, "server")
    shell = connection.middle = MiddleShell(controller, connection, lambda: now[0])
    shell.ready(C2S)
    shell.ready(S2C)
    shell.received(S2C, b"cr1-12--5--0-ss1", now[0])  # delayed by a millisecond
    connection.upstream.eof = True
    shell.sender_ended(S2C)  # the server's FIN waits behind it
    now[0] += 1_000_000
    connection.client.eof = True
    # the client's FIN, just as the answer is due: one core call passes the FIN on, then delivers the answer
    shell.sender_ended(C2S)
    assert log.index(("client", b"cr1-12--5--0-ss1")) < log.index(("client", "close"))
