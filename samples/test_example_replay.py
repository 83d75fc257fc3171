"""An example of whiztap's pytest plugin (docs/pytest-plugin.md explains it).

Run it with ``pytest samples/test_example_replay.py``; it is not part of
whiztap's own test suite, which collects only ``tests/``.  The client code
under test is ``sensor_report``.  Its recording, ``recordings/sensor_report.mcap``,
was made with ``--whiztap-record=once`` against the simulator below; delete it
(or run with ``--whiztap-record=all``) to record it again.
"""

from __future__ import annotations

import asyncio

import pytest

from whiztap.analyzer.protocol.messages import UnitType
from whiztap.sniffer.sim.client import Client
from whiztap.sniffer.pytest_plugin import BackgroundLoop
from whiztap.sniffer.sim.simulator import Simulator

PASSWORD = "progwhiz"  # the samples' password


async def sensor_report(address: str) -> dict[int, int]:
    """The client under test: the first four sensors the server configures, read once."""
    host, port = address.rsplit(":", 1)
    async with await Client.connect(host, int(port), password=PASSWORD) as client:
        config = await client.fetch_configuration()
        sensors = [ch for ch, c in enumerate(config.channels) if c.unit_type == UnitType.SENSOR][:4]
        return {ch: await client.sensor(ch) for ch in sensors}


@pytest.fixture
def whiztap_target():
    """The live server, used to record and to replay against: the simulator
    with the seed the samples were made with.  Point at a real robot instead
    with ``--whiztap-target HOST:PORT`` and no such fixture."""
    with BackgroundLoop() as background:
        sim = Simulator(password=PASSWORD, seed=1)
        background.run(sim.start())
        yield f"127.0.0.1:{sim.port}"
        background.run(sim.close())


@pytest.mark.whiztap("recordings/sensor_report.mcap")
def test_sensor_report_reads_the_first_four_sensors(whiztap_server):
    """Runs against a stub serving the recording: no server needed, and a
    request the recording does not have fails the test."""
    report = asyncio.run(sensor_report(whiztap_server.address))
    assert list(report) == [12, 13, 14, 15]
    assert all(0 <= value <= 1024 for value in report.values())


@pytest.mark.whiztap("clean-winsock.mcap", password=PASSWORD)
def test_the_server_still_answers_like_the_recording(whiztap_replay):
    """Replays a recorded client against the live server; a differing answer
    fails the test with the side-by-side diff."""
    result = whiztap_replay(pace="max", compare="structure")
    assert result.counts["match"] > 0
