"""Helpers for the replay, stub and plugin tests: a client session recorded
through the real proxy from the real simulator, and simulators to replay it to.

The simulator's clock is frozen, so every answer is a function of the seed and
the commands alone: a replay against the same seed must match byte for byte,
and one against another seed differs exactly in the sensor readings.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

from whiztap.sniffer.sim.client import Client
from whiztap.sniffer.sim.faults import FaultConfig
from whiztap.sniffer.sim.simulator import Simulator
from tests.record_support import LOCAL, WAIT, recording

PASSWORD = "replay-pw"
FROZEN_NS = 5_000_000_000
SENSORS = (12, 13, 14, 15, 16)


def simulator(seed: int = 1, faults: FaultConfig = FaultConfig()) -> Simulator:
    return Simulator(port=0, mode="winsock", password=PASSWORD, seed=seed, clock=lambda: FROZEN_NS,
                     faults=faults)


async def client_session(port: int) -> list:
    """Every kind of request, a few pauses; what the client got back."""
    got: list = []
    async with await Client.connect(LOCAL, port, password=PASSWORD) as client:
        got.append(await client.fetch_configuration())
        for channel in SENSORS[:4]:
            got.append(await client.sensor(channel))
        await client.normal_send(2, 1500)
        got.append(await client.servo_position(2))
        await client.activate_switch(7)
        await asyncio.sleep(0.03)
        await client.deactivate_switch(7)
        got.append(len(await client.fetch_camera_image()))
        await asyncio.sleep(0.03)
        for channel in (12, SENSORS[4]):
            got.append(await client.sensor(channel))
        got.append(await client.servo_position(2))
    return got


async def until_closed(sim: Simulator) -> None:
    for _ in range(int(WAIT * 100)):
        if sim.stats.open_connections == 0:
            return
        await asyncio.sleep(0.01)


async def record(path: Path, seed: int = 1, session=client_session) -> list:
    """Record ``session`` through the proxy against a frozen-clock simulator."""
    async with simulator(seed) as sim, recording(sim.port, path) as rec:
        got = await session(rec.proxy.port)
        await until_closed(sim)
        await rec.stop()
    return got


