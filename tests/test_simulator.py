"""The simulator over real sockets on 127.0.0.1: examples, handshake, faults, load, robustness."""

from __future__ import annotations

import asyncio
import logging
import random

import pytest

from whiztap.analyzer.protocol.codec import encode
from whiztap.analyzer.protocol.framing import Framer, Item, ItemKind
from whiztap.analyzer.protocol.messages import FetchConfiguration
from whiztap.sniffer.sim.client import Client
from whiztap.sniffer.sim.faults import GARBAGE_ALPHABET, FaultConfig, FaultPlanner
from whiztap.sniffer.sim.simulator import Simulator
from tests.test_robot import EXAMPLES, check_effect, example_robot

SEC = 1_000_000_000
FROZEN = 42 * SEC  # a stopped clock: sensor values and servo positions are known in advance
PASSWORD = b"progwhiz"
FETCH_CONFIG = b"rr1-24--0--0-ss1"


def frozen() -> int:
    return FROZEN


async def until(condition, timeout: float = 10.0) -> None:
    async with asyncio.timeout(timeout):
        while not condition():
            await asyncio.sleep(0.001)


async def read_to_eof(reader: asyncio.StreamReader) -> bytes:
    async with asyncio.timeout(10):
        return await reader.read()


async def read_items(reader: asyncio.StreamReader, framer: Framer, done) -> list[Item]:
    """Read and frame until ``done(items)``."""
    items: list[Item] = []
    async with asyncio.timeout(10):
        while not done(items):
            data = await reader.read(65536)
            assert data, f"connection closed after {items}"
            items += framer.feed(data, 0)
    return items


async def send_in_two(sim: Simulator, writer: asyncio.StreamWriter, data: bytes, cut: int) -> None:
    """Two writes, the second only once the server has read the first: two reads for sure."""
    before = sim.stats.bytes_in
    if cut:
        writer.write(data[:cut])
        await writer.drain()
        await until(lambda: sim.stats.bytes_in == before + cut)
    writer.write(data[cut:])
    await writer.drain()


# -- basics ---------------------------------------------------------------------------------------


async def test_binds_loopback_by_default():
    async with Simulator() as sim:
        assert sim.host == "127.0.0.1"
        assert sim._server.sockets[0].getsockname() == ("127.0.0.1", sim.port)
        assert sim.port > 0


@pytest.mark.parametrize("frame, message", EXAMPLES, ids=[f"{f.decode('latin-1')}={type(m).__name__}"
                                                         for f, m in EXAMPLES])
async def test_spec_example_split_at_every_offset_over_tcp(frame, message):
    async with Simulator(mode="vpn", clock=frozen) as sim:
        for cut in range(len(frame)):
            sim.robot = robot = example_robot(message)  # fresh state for every connection
            reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
            await send_in_two(sim, writer, frame, cut)
            writer.write(FETCH_CONFIG)  # no reply for many commands: a known answer shows it was done
            configs = 2 if isinstance(message, FetchConfiguration) else 1
            items = await read_items(reader, Framer(),
                                     lambda its, n=configs: sum(i.kind == "config" for i in its) == n)
            assert items[-1].raw == encode(robot.configuration())
            check_effect(message, robot, [i.raw for i in items[:-1]], FROZEN)
            writer.close()
            await writer.wait_closed()
        assert sim.stats.errors == 0


# -- handshake ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [b"", b"\r\n"])
async def test_password_split_at_every_offset_over_tcp(suffix):
    stream = PASSWORD + suffix
    async with Simulator(clock=frozen) as sim:
        for cut in range(len(stream)):
            reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
            assert await reader.readexactly(11) == b"sendchkpass"
            await send_in_two(sim, writer, stream, cut)
            assert await reader.readexactly(9) == b"readytogo"
            writer.write(b"rr1-0--0--2-ss1")
            assert await reader.readexactly(18) == b"cr1-0--4000--0-ss1"
            writer.close()


async def test_wrong_password_gets_failed_validation_and_the_connection_closes():
    async with Simulator() as sim:
        reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
        assert await reader.readexactly(11) == b"sendchkpass"
        writer.write(b"progwhix" + FETCH_CONFIG)
        assert await read_to_eof(reader) == b"Failed Validation"  # then EOF
        writer.close()


async def test_no_command_is_served_before_readytogo():
    async with Simulator() as sim:
        reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
        assert await reader.readexactly(11) == b"sendchkpass"
        writer.write(FETCH_CONFIG)
        assert await read_to_eof(reader) == b"Failed Validation"


async def test_vpn_mode_serves_at_once():
    async with Simulator(mode="vpn") as sim:
        reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
        writer.write(FETCH_CONFIG)
        assert await reader.readexactly(81) == encode(sim.robot.configuration())
        writer.close()


# -- robustness ----------------------------------------------------------------------------------------


async def test_malformed_commands_are_logged_with_rule_ids_and_the_connection_stays(caplog):
    caplog.set_level(logging.INFO, logger="whiztap.sim")
    async with Simulator(mode="vpn") as sim:
        reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
        writer.write(b"rr1-99--0--0-ss1junk\x00\xffrr1-5--9999--0-ss1rr1-0--0--2-ss1")
        assert await reader.readexactly(18) == b"cr1-0--4000--0-ss1"
        writer.close()
    for rule in ("PW-RANGE-CHANNEL", "PW-FRAME-GARBAGE", "PW-RANGE-SEND-VALUE"):
        assert rule in caplog.text


async def test_random_bytes_from_many_connections_never_stop_the_server():
    rng = random.Random(1)
    async with Simulator(mode="vpn") as sim:
        async def spray() -> None:
            _, writer = await asyncio.open_connection("127.0.0.1", sim.port)
            for _ in range(16):
                pieces = [rng.randbytes(rng.randint(1, 2000)), b"rr1-", b"sr1-", b"\xff\xd8\xff", b"sr1-25--"]
                writer.write(b"".join(rng.sample(pieces, len(pieces))))
            await writer.drain()
            writer.close()
        await asyncio.gather(*(spray() for _ in range(20)))
        await until(lambda: sim.stats.open_connections == 0)
        async with await Client.connect("127.0.0.1", sim.port) as client:
            assert len((await client.fetch_configuration()).channels) == 24
        assert sim.stats.errors == 0


async def test_an_error_in_one_connection_leaves_the_others_running():
    async with Simulator(mode="vpn") as sim:
        real = sim.robot.command

        def faulty(decoded, raw, t_ns, notes):
            if raw == b"rr1-23--0--0-ss1":
                raise RuntimeError("simulated bug")
            return real(decoded, raw, t_ns, notes)

        sim.robot.command = faulty
        async with await Client.connect("127.0.0.1", sim.port) as good:
            bad_reader, bad_writer = await asyncio.open_connection("127.0.0.1", sim.port)
            bad_writer.write(b"rr1-23--0--0-ss1")
            assert await read_to_eof(bad_reader) == b""  # that connection is closed
            assert sim.stats.errors == 1
            assert await good.servo_position(2) == 1000
        async with await Client.connect("127.0.0.1", sim.port) as late:
            assert await late.servo_position(2) == 1000


async def test_client_leaving_mid_reply_does_no_harm():
    async with Simulator(mode="vpn") as sim:
        for _ in range(5):
            reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
            writer.write(b"rr1-29--0--0-ss1" * 50)
            await reader.read(10)
            writer.transport.abort()
        await until(lambda: sim.stats.open_connections == 0)
        async with await Client.connect("127.0.0.1", sim.port) as client:
            assert (await client.fetch_camera_image()).startswith(b"\xff\xd8")
        assert sim.stats.errors == 0


# -- faults: the planner ----------------------------------------------------------------------------------


def plans(config: FaultConfig, seed, n: int = 200, answer: bool = True):
    planner = FaultPlanner(config, seed)
    return [planner.plan(b"cr1-%d--512--0-ss1" % (i % 24), answer) for i in range(n)]


def test_fault_plans_are_reproducible_per_seed():
    config = FaultConfig(latency_ms=5, jitter_ms=3, drop_rate=0.3, split=True, garbage_rate=0.4)
    assert plans(config, "7:1") == plans(config, "7:1")
    assert plans(config, "7:1") != plans(config, "8:1")


def test_drop_rate_drops_that_share_of_answers_but_never_handshake_text():
    dropped = sum(p is None for p in plans(FaultConfig(drop_rate=0.25), 1, n=2000))
    assert 400 <= dropped <= 600
    assert all(p is not None for p in plans(FaultConfig(drop_rate=1.0), 1, answer=False))
    assert all(p is None for p in plans(FaultConfig(drop_rate=1.0), 1))


def test_latency_and_jitter_bound_every_delay():
    delays = [p.delay_s for p in plans(FaultConfig(latency_ms=20, jitter_ms=5), 3)]
    assert all(0.015 <= d <= 0.025 for d in delays)
    assert len(set(delays)) > 100
    assert {p.delay_s for p in plans(FaultConfig(latency_ms=20), 3)} == {0.02}
    assert min(p.delay_s for p in plans(FaultConfig(latency_ms=1, jitter_ms=5), 3)) == 0.0


def test_split_cuts_replies_into_small_pieces_that_join_up():
    reply = b"cr1-12--512--0-ss1"
    planner = FaultPlanner(FaultConfig(split=True), 5)
    cuts = [planner.plan(reply, True).pieces for _ in range(100)]
    assert all(b"".join(p) == reply and all(1 <= len(x) <= 16 for x in p) for p in cuts)
    assert sum(len(p) > 1 for p in cuts) > 90
    image = bytes(range(256)) * 40
    pieces = planner.plan(image, True).pieces
    assert b"".join(pieces) == image and max(map(len, pieces)) <= len(image) // 32


def test_garbage_is_stray_bytes_the_framer_keeps_apart_from_the_reply():
    reply = b"cr1-12--512--0-ss1"
    planned = [p.pieces[0] for p in plans(FaultConfig(garbage_rate=0.5), 9) if p]
    garbled = [d for d in planned if d != b"cr1-%d--512--0-ss1" % int(d.split(b"-")[1])]
    assert 60 <= len(garbled) <= 140
    for data in garbled:
        prefix = data[:data.index(b"cr1-")]
        assert 1 <= len(prefix) <= 8 and set(prefix) <= set(GARBAGE_ALPHABET)
        framer = Framer()
        items = framer.feed(data + reply, 0) + framer.end(0)
        assert [i.kind for i in items] == [ItemKind.UNFRAMED, ItemKind.RESPONSE, ItemKind.RESPONSE]


@pytest.mark.parametrize("bad", [dict(drop_rate=1.5), dict(garbage_rate=-0.1), dict(latency_ms=-1)])
def test_fault_config_rejects_nonsense(bad):
    with pytest.raises(ValueError):
        FaultConfig(**bad)


# -- faults: on the wire ---------------------------------------------------------------------------------------


async def answered_channels(seed: int, **faults) -> tuple[list[bytes], bytes]:
    """Which of 24 pipelined sensor requests were answered, and the exact bytes received."""
    async with Simulator(mode="vpn", channels="sensor:0-23", seed=seed, clock=frozen,
                         faults=FaultConfig(**faults)) as sim:
        reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
        writer.write(b"".join(b"rr1-%d--0--0-ss1" % ch for ch in range(24)))
        await until(lambda: sim.stats.answers_sent + sim.stats.answers_dropped == 24)
        received = bytearray()
        items = await read_items(reader, Framer(), lambda its: sum(
            i.kind == "response" for i in its) == sim.stats.answers_sent)
        for item in items:
            received += item.raw
        writer.close()
        return [i.raw.split(b"--")[0] for i in items if i.kind == "response"], bytes(received)


async def test_drop_rate_on_the_wire_is_reproducible_per_seed():
    first, _ = await answered_channels(seed=3, drop_rate=0.5)
    again, _ = await answered_channels(seed=3, drop_rate=0.5)
    other, _ = await answered_channels(seed=4, drop_rate=0.5)
    assert first == again != other
    assert 0 < len(first) < 24


async def test_garbage_and_split_on_the_wire_are_reproducible_and_every_answer_survives():
    faults = dict(garbage_rate=0.5, split=True)
    answered, received = await answered_channels(seed=11, **faults)
    _, again = await answered_channels(seed=11, **faults)
    _, other = await answered_channels(seed=12, **faults)
    assert received == again != other
    assert answered == [b"cr1-%d" % ch for ch in range(24)]
    framer = Framer()
    kinds = [i.kind for i in framer.feed(received, 0) + framer.end(0)]
    assert kinds.count(ItemKind.RESPONSE) == 24 and ItemKind.UNFRAMED in kinds


async def test_latency_delays_answers_and_jitter_keeps_their_order():
    async with Simulator(mode="vpn", faults=FaultConfig(latency_ms=150)) as sim:
        async with await Client.connect("127.0.0.1", sim.port) as client:
            loop = asyncio.get_running_loop()
            start = loop.time()
            await client.servo_position(0)
            assert loop.time() - start >= 0.15  # a lower bound: a loaded machine only adds to it
    _, received = await answered_channels(seed=2, latency_ms=2, jitter_ms=2)
    framer = Framer()
    order = [i.raw.split(b"--")[0] for i in framer.feed(received, 0)]
    assert order == [b"cr1-%d" % ch for ch in range(24)]


async def test_a_flood_under_latency_is_answered_whole_and_in_order():
    requests = b"".join(b"rr1-%d--0--2-ss1" % (i % 6) for i in range(3000))
    async with Simulator(mode="vpn", faults=FaultConfig(latency_ms=20)) as sim:
        reader, writer = await asyncio.open_connection("127.0.0.1", sim.port)
        writer.write(requests)
        items = await read_items(reader, Framer(), lambda its: len(its) >= 3000)
        assert [i.raw for i in items] == [b"cr1-%d--4000--0-ss1" % (i % 6) for i in range(3000)]
        writer.close()


# -- load ---------------------------------------------------------------------------------------------------


@pytest.mark.slow
async def test_200_clients_with_100_requests_each():
    async with Simulator(clock=frozen) as sim:
        robot = sim.robot
        config = robot.configuration()

        async def one(n: int) -> int:
            async with await Client.connect("127.0.0.1", sim.port, PASSWORD, timeout=30) as client:
                for i in range(100):
                    match (n + i) % 3:
                        case 0:
                            ch = 12 + (n + i) % 12
                            assert await client.sensor(ch) == robot.sensor_value(ch, FROZEN)
                        case 1:
                            assert await client.servo_position((n + i) % 6) == 1000
                        case 2:
                            assert await client.fetch_configuration() == config
                return 100

        results = await asyncio.gather(*(one(n) for n in range(200)))
        assert sum(results) == 20_000
        assert sim.stats.connections == 200 and sim.stats.answers_sent == 20_000
        assert sim.stats.errors == 0
