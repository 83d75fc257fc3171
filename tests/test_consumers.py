"""The proxy's traffic events reach every consumer, and a consumer that raises
is cut off and reported once, never stopping traffic, the recording or the
other consumers (as mitmproxy's addon manager isolates addons)."""

from __future__ import annotations

import asyncio

from tests.record_support import LOCAL, WAIT, EchoServer, both_ways, read_all
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.traffic import Closed, Data, Opened, TrafficEvent
from whiztap.sniffer.record.consumers import Consumers
from whiztap.sniffer.record.record_run import Recording, RecordSettings


class Keeper:
    """Keeps every event it is given."""

    def __init__(self) -> None:
        self.events: list[TrafficEvent] = []

    def receive(self, event: TrafficEvent) -> None:
        self.events.append(event)


class Breaks(Keeper):
    """Raises at its ``at``-th event (counting from 1), after keeping it."""

    def __init__(self, at: int) -> None:
        super().__init__()
        self.at = at

    def receive(self, event: TrafficEvent) -> None:
        super().receive(event)
        if len(self.events) == self.at:
            raise RuntimeError("a bug in a consumer")


def test_a_consumer_that_raises_is_dropped_once_and_the_others_get_every_event() -> None:
    failures: list[tuple[object, str]] = []
    fan_out = Consumers(lambda consumer, error: failures.append((consumer, str(error))))
    first, broken, last = Keeper(), Breaks(at=2), Keeper()
    for consumer in (first, broken, last):
        fan_out.add(consumer)
    sent = [Opened(1, 1), Data(1, Direction.C2S, 2, b"rr1-12--0--0-ss1"),
            Data(1, Direction.S2C, 3, b"cr1-12--7--0-ss1"), Closed(1, 4, "client")]
    for event in sent:
        fan_out.receive(event)
    assert first.events == sent and last.events == sent
    assert broken.events == sent[:2]
    assert failures == [(broken, "a bug in a consumer")]


async def test_a_failing_consumer_never_stops_the_proxy_the_file_or_the_other_consumers(tmp_path) -> None:
    path = tmp_path / "isolated.mcap"
    lines: list[str] = []
    broken, kept = Breaks(at=2), Keeper()
    async with EchoServer() as server:
        settings = RecordSettings((LOCAL, 0), (LOCAL, server.port), str(path))
        recording = Recording(settings, lines.append, consumers=[broken, kept])
        await recording.start()
        try:
            reader, writer = await asyncio.open_connection(LOCAL, recording.proxy.port)
            answers = b""
            for n in range(5):
                frame = b"rr1-%d--0--0-ss1" % (n + 1)
                writer.write(frame)
                answers += await asyncio.wait_for(reader.readexactly(len(frame)), WAIT)
            writer.close()
            await writer.wait_closed()
            for _ in range(int(WAIT / 0.01)):  # the proxy tells of the close once both sides are done
                if any(type(e) is Closed for e in kept.events):
                    break
                await asyncio.sleep(0.01)
        finally:
            await recording.stop()
    sent = b"".join(b"rr1-%d--0--0-ss1" % (n + 1) for n in range(5))
    assert answers == sent  # the proxy forwarded everything after the failure
    assert both_ways(str(path)) == {(1, "c2s"): sent, (1, "s2c"): sent}  # and recorded it
    assert len(broken.events) == 2  # cut off at its failure
    assert b"".join(e.data for e in kept.events if type(e) is Data and e.direction is Direction.C2S) == sent
    assert any(type(e) is Closed for e in kept.events)
    failed = [line for line in lines if "stopped receiving traffic" in line]
    assert failed == ["Breaks stopped receiving traffic: RuntimeError: a bug in a consumer"]
    assert read_all(str(path))["/tcp/events"][-1]["event"] == "recording_stopped"
