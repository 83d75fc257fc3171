"""The asyncio client against the simulator: every command, both modes, passwords, errors."""

from __future__ import annotations

import asyncio
import socket

import pytest

from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import ChannelConfig, SetConfigEntry
from whiztap.sniffer.sim.camera import render_frame
from whiztap.sniffer.sim.client import Client, ConnectionClosed, HandshakeError, ResponseTimeout
from whiztap.sniffer.sim.faults import FaultConfig
from whiztap.sniffer.sim.simulator import Simulator

SEC = 1_000_000_000
PASSWORD = "progwhiz"


class Clock:
    """The simulator's clock, moved by the test: servo travel without waiting."""

    def __init__(self) -> None:
        self.now = 100 * SEC

    def __call__(self) -> int:
        return self.now


@pytest.fixture(params=["winsock", "vpn"])
async def connected(request):
    clock = Clock()
    async with Simulator(mode=request.param, clock=clock) as sim:
        password = PASSWORD if request.param == "winsock" else None
        async with await Client.connect("127.0.0.1", sim.port, password, timeout=5) as client:
            yield sim, client, clock


async def test_requests_with_answers(connected):
    sim, client, clock = connected
    robot = sim.robot
    assert await client.fetch_configuration() == robot.configuration()
    assert await client.sensor(12) == robot.sensor_value(12, clock.now)
    assert await client.servo_position(0) == 1000
    assert await client.fetch_camera_image() == render_frame(1, 0.0)
    assert await client.fetch_camera_image() == render_frame(2, 0.0)
    clock.now += 3 * SEC
    assert await client.sensor(20) == robot.sensor_value(20, clock.now)


async def test_normal_send_moves_a_servo_the_client_sees_travel(connected):
    _sim, client, clock = connected
    await client.normal_send(2, 1500)
    positions = []
    for _ in range(4):
        positions.append(await client.servo_position(2))
        clock.now += SEC // 2
    assert positions == [1000, 1250, 1500, 1500]


async def test_switches(connected):
    sim, client, _ = connected
    await client.activate_switch(7)
    await client.activate_switch(10)
    await client.deactivate_switch(10)
    await client.fetch_configuration()  # answered after the commands before it were done
    assert [ch for ch, on in enumerate(sim.robot.switches) if on] == [7]


async def test_scripts(connected):
    sim, client, clock = connected
    robot = sim.robot
    await client.play_internal_script(120)
    await client.play_external_script(272)
    await client.fetch_configuration()
    assert (robot.internal_script, robot.external_script) == (120, 272)
    clock.now += SEC
    assert await client.servo_position(5) == 1500  # the script sweeps the servos
    await client.stop_internal_script()
    await client.stop_external_script()
    await client.fetch_configuration()
    assert (robot.internal_script, robot.external_script) == (None, None)


async def test_set_configuration(connected):
    _, client, _ = connected
    await client.set_configuration((SetConfigEntry(12, 0, 2), SetConfigEntry(12, 1, 1)))
    channels = (await client.fetch_configuration()).channels
    assert channels[:3] == (ChannelConfig(2), ChannelConfig(1), ChannelConfig(0))
    await client.set_configuration((SetConfigEntry(12, 0, 0),), checksum=99)  # wrong: ignored
    assert (await client.fetch_configuration()).channels[0] == ChannelConfig(2)


async def test_concurrent_requests_on_one_connection_get_their_own_answers(connected):
    sim, client, clock = connected
    robot = sim.robot
    results = await asyncio.gather(*(client.sensor(ch) for ch in range(12, 24)),
                                   client.servo_position(3), client.fetch_configuration())
    assert results == [robot.sensor_value(ch, clock.now) for ch in range(12, 24)] + [1000, robot.configuration()]


async def test_raw_exchange(connected):
    _, client, _ = connected
    items = await client.exchange_raw(b"rr1-0--0--2-ss1rr1-1--0--2-ss1", 0.3)
    assert [i.raw for i in items] == [b"cr1-0--4000--0-ss1", b"cr1-1--4000--0-ss1"]
    assert client.stray == []


# -- passwords and modes ----------------------------------------------------------------------------


async def test_wrong_password_raises_handshake_error():
    async with Simulator() as sim:
        with pytest.raises(HandshakeError, match="Failed Validation"):
            await Client.connect("127.0.0.1", sim.port, "wrong")


async def test_password_as_bytes():
    async with Simulator(password=b"\x01pass") as sim:
        async with await Client.connect("127.0.0.1", sim.port, b"\x01pass") as client:
            assert await client.servo_position(0) == 1000


async def test_no_password_for_a_winsock_server_raises_handshake_error():
    async with Simulator() as sim:
        async with await Client.connect("127.0.0.1", sim.port) as client:
            with pytest.raises(HandshakeError, match="asks for a password"):
                await client.sensor(12)


async def test_password_for_a_vpn_server_times_out_waiting_for_sendchkpass():
    async with Simulator(mode="vpn") as sim:
        with pytest.raises(ResponseTimeout, match="sendchkpass"):
            await Client.connect("127.0.0.1", sim.port, PASSWORD, timeout=0.2)


# -- errors --------------------------------------------------------------------------------------------


async def test_unanswered_request_times_out_and_the_client_goes_on():
    async with Simulator(mode="vpn", camera=False) as sim:
        async with await Client.connect("127.0.0.1", sim.port) as client:
            with pytest.raises(ResponseTimeout, match="Fetch Camera Image"):
                await client.fetch_camera_image(timeout=0.2)
            assert await client.servo_position(1) == 1000


async def test_server_closing_fails_pending_requests():
    async def close_after_a_read(reader, writer):
        await reader.read(100)
        writer.close()

    server = await asyncio.start_server(close_after_a_read, "127.0.0.1", 0)
    async with server:
        port = server.sockets[0].getsockname()[1]
        async with await Client.connect("127.0.0.1", port) as client:
            with pytest.raises(ConnectionClosed):
                await client.sensor(12)
            with pytest.raises(ConnectionClosed):
                await client.sensor(12)


async def test_unreachable_server_raises_connection_refused():
    server = await asyncio.start_server(lambda r, w: None, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    server.close()
    await server.wait_closed()
    with pytest.raises(ConnectionRefusedError):
        await Client.connect("127.0.0.1", port)


async def test_answers_survive_split_replies_and_garbage():
    faults = FaultConfig(split=True, garbage_rate=1.0)
    async with Simulator(mode="vpn", faults=faults, seed=5) as sim:
        async with await Client.connect("127.0.0.1", sim.port) as client:
            for _ in range(5):
                assert await client.servo_position(4) == 1000
                assert await client.fetch_configuration() == sim.robot.configuration()
            image = await client.fetch_camera_image()
            assert image.startswith(b"\xff\xd8") and image.endswith(b"\xff\xd9")
            assert len(client.stray) == 11 and all(i.kind is ItemKind.UNFRAMED for i in client.stray)


async def test_a_dropped_answer_costs_one_timeout_only():
    async with Simulator(mode="vpn", faults=FaultConfig(drop_rate=0.5), seed=0) as sim:
        async with await Client.connect("127.0.0.1", sim.port, timeout=0.2) as client:
            outcomes = []
            for _ in range(12):
                try:
                    outcomes.append(await client.servo_position(0))
                except ResponseTimeout:
                    outcomes.append(None)
            assert None in outcomes and 1000 in outcomes
            assert set(outcomes) == {None, 1000}
            assert len(outcomes) - outcomes.count(None) == sim.stats.answers_sent


def test_connection_failures_are_told_in_the_system_s_words():
    from whiztap.sniffer.nettext import reason

    # asyncio's text names the call and the address, which the message already says
    assert reason(ConnectionRefusedError(111, "Connect call failed ('127.0.0.1', 1)")) == "Connection refused"
    # a name that does not resolve: a negative errno of its own numbering
    assert reason(socket.gaierror(-2, "Name or service not known")) == "Name or service not known"
    assert reason(OSError("Multiple exceptions: ...")) == "Multiple exceptions: ..."
