"""The stub as a cassette tool: near misses, unused recorded requests, --match."""

from __future__ import annotations

import asyncio
import json
import re

import pytest
from hypothesis import given
from hypothesis import strategies as st

from whiztap.analyzer.analysis.exchanges import load_exchanges
from whiztap.analyzer.protocol.observations import Direction
from whiztap.sniffer.replay.near_miss import Match, Recorded, closest
from whiztap.sniffer.replay.stub import Stub
from whiztap.sniffer.sim.client import Client, ConnectionClosed, ResponseTimeout
from whiztap.sniffer.sim.dialogue import Dialogue
from tests.cli_support import run_cli, start_process
from tests.record_support import LOCAL, WAIT, recording

C2S, S2C = Direction.C2S, Direction.S2C
CONFIG = [(C2S, b"rr1-24--0--0-ss1"), (S2C, b"sr1-\x0d" + b"000" * 12 + b"200-ss1")]


@pytest.fixture(scope="module")
def asked_twice(tmp_path_factory):
    """One connection: configuration, sensor 12 (answered 100, then 200), servo 2."""
    path = tmp_path_factory.mktemp("match") / "twice.mcap"
    steps = [*CONFIG, (C2S, b"rr1-12--0--0-ss1"), (S2C, b"cr1-12--100--0-ss1"),
             (C2S, b"rr1-12--0--0-ss1"), (S2C, b"cr1-12--200--0-ss1"),
             (C2S, b"rr1-2--0--2-ss1"), (S2C, b"cr1-2--6000--0-ss1")]

    async def make() -> None:
        async with Dialogue() as peer, recording(peer.port, path) as rec:
            await peer.play(steps, (LOCAL, rec.proxy.port))
            await asyncio.sleep(0.1)
            await rec.stop()

    asyncio.run(make())
    return path


async def sensors(stub: Stub, channels: list[int]) -> list[int]:
    async with await Client.connect(LOCAL, stub.port, timeout=0.3) as client:
        await client.fetch_configuration()
        return [await client.sensor(ch) for ch in channels]


async def test_a_miss_names_the_closest_recorded_requests_and_what_differs(asked_twice):
    lines: list[str] = []
    async with Stub(load_exchanges(str(asked_twice)), unmatched="ignore", on_log=lines.append) as stub:
        async with await Client.connect(LOCAL, stub.port, timeout=0.3) as client:
            await client.fetch_configuration()
            with pytest.raises(ResponseTimeout):
                await client.servo_position(5)
    (miss,) = stub.unanswered
    near = [(n.recorded.text, n.differs) for n in miss.near]
    assert near == [("Servo Position Request ch 2", {"channel": (5, 2), "position": (2, 4)}),
                    ("Sensor Request ch 12", {"kind": ("Servo Position Request", "Sensor Request"),
                                              "channel": (5, 12)}),
                    ("Fetch Configuration Settings", {"kind": ("Servo Position Request",
                                                               "Fetch Configuration Settings"),
                                                      "channel": (5, None), "position": (2, 1)})]
    assert ("!   closest recorded: #1 request 4 Servo Position Request ch 2: channel 5 here, 2 recorded; "
            "position 2 here, 4 recorded") in lines


async def test_match_chooses_the_fields_and_order(asked_twice):
    exchanges = load_exchanges(str(asked_twice))
    async with Stub(exchanges) as stub:  # the default: kind, channel, in recorded order
        assert await sensors(stub, [12, 12, 12]) == [100, 200, 200]
    async with Stub(exchanges, match=Match.parse("kind,channel")) as stub:  # no order: the first, always
        assert await sensors(stub, [12, 12]) == [100, 100]
    no_channel = await raw(Stub(exchanges, match=Match.parse("kind,order")), b"rr1-2--0--2-ss1rr1-5--0--2-ss1")
    assert no_channel.endswith(b"cr1-2--6000--0-ss1cr1-2--6000--0-ss1")  # servo 5 gets servo 2's answer
    stub = Stub(exchanges, match=Match.parse("kind,channel,value,order"), unmatched="ignore")
    got = await raw(stub, b"rr1-2--0--2-ss1rr1-02--0--2-ss1")  # the same request, written another way
    assert got.endswith(b"cr1-2--6000--0-ss1")
    assert stub.unanswered[0].near[0].differs == {
        "value": (b"rr1-02--0--2-ss1", b"rr1-2--0--2-ss1"), "position": (3, 4)}


async def raw(stub: Stub, requests: bytes) -> bytes:
    """What the stub sends a raw client that fetches the configuration, then writes ``requests``."""
    async with stub:
        reader, writer = await asyncio.open_connection(LOCAL, stub.port)
        writer.write(b"rr1-24--0--0-ss1" + requests)
        writer.write_eof()
        got = await asyncio.wait_for(reader.read(-1), WAIT)
        writer.close()
    return got


def test_match_words_are_checked():
    assert Match.parse("kind,channel,order") == Match() and Match().text() == "kind,channel,order"
    with pytest.raises(ValueError, match="unknown field 'chanel'"):
        Match.parse("kind,chanel")
    with pytest.raises(ValueError, match="must include kind"):
        Match.parse("channel,order")
    ran = run_cli("stub", "x.mcap", "--match", "kind,size")
    assert ran.returncode == 2 and ran.stderr.startswith("whiztap: --match: unknown field 'size'")
    assert ran.stderr.count("\n") == 1


async def test_unused_and_the_json_summary(asked_twice):
    proc = await start_process("stub", asked_twice, "--listen", "127.0.0.1:0", "--once", "--fail-unused",
                               "--format", "json")
    port = int(re.search(rb":(\d+) \(", await asyncio.wait_for(proc.stdout.readline(), WAIT)).group(1))
    async with await Client.connect(LOCAL, port, timeout=WAIT) as client:
        await client.fetch_configuration()
        assert await client.sensor(12) == 100
        with pytest.raises(ConnectionClosed):
            await client.servo_position(5)  # not recorded: closed at once
    out, err = await asyncio.wait_for(proc.communicate(), WAIT)
    assert (proc.returncode, err) == (1, b"")
    summary = json.loads(out.decode().splitlines()[-1])
    assert [u["text"] for u in summary["unused"]] == ["Sensor Request ch 12", "Servo Position Request ch 2"]
    assert summary["match"] == "kind,channel,order" and summary["answers"] == 2
    (miss,) = summary["unanswered"]
    assert miss["text"] == "Servo Position Request ch 5"
    assert miss["closest"][0]["differs"] == {"channel": {"here": 5, "recorded": 2},
                                             "position": {"here": 3, "recorded": 4}}


requests = st.builds(Recorded, st.integers(1, 3), st.integers(1, 20),
                     st.sampled_from(["Sensor Request", "Servo Position Request", "Fetch Camera Image"]),
                     st.none() | st.integers(0, 30), st.binary(max_size=20), st.just(""))


@given(requests, st.lists(requests, max_size=12))
def test_closest_is_ranked_and_names_only_real_differences(asked, recorded):
    near = closest(asked, recorded)
    assert len(near) == min(3, len({(r.kind, r.channel, r.value) for r in recorded}))
    for n in near:
        for field, (here, there) in n.differs.items():
            assert here != there and field in ("kind", "channel", "value", "position")
    kinds = [n.recorded.kind != asked.kind for n in near]
    assert kinds == sorted(kinds)  # a request of the same kind always comes before one of another
    if recorded and any(r.kind == asked.kind for r in recorded):
        assert "kind" not in near[0].differs
