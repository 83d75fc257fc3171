"""The pytest plugin's ``whiztap_proxy`` fixture, run by pytest itself
(``pytester``) on a small project whose client is tested against the
simulator through the proxy in the middle: a dropped answer, a reset, an
injected frame, each for the length of a ``with`` block."""

from __future__ import annotations

import pytest

pytest_plugins = ["pytester"]

INI = "[pytest]\nasyncio_default_fixture_loop_scope = function\n"

CONFTEST = '''
import pytest

from whiztap.sniffer.pytest_plugin import BackgroundLoop
from whiztap.sniffer.sim.simulator import Simulator


@pytest.fixture
def whiztap_target():
    with BackgroundLoop() as background:
        sim = Simulator(password="pw", seed=1)
        background.run(sim.start())
        yield f"127.0.0.1:{sim.port}"
        background.run(sim.close())
'''

TESTS = r'''
import asyncio
import os

import pytest

from whiztap.analyzer.recording.scan import RecordingScan
from whiztap.sniffer.mitm.controller import ControlError
from whiztap.sniffer.sim.client import Client, ConnectionClosed, ResponseTimeout


async def connect(address):
    host, port = address.rsplit(":", 1)
    return await Client.connect(host, int(port), password="pw", timeout=0.5)


async def sensor_with_retry(address, channel):
    """The client under test: a sensor read that asks again once when the
    answer does not come in time.  (attempts, value)."""
    async with await connect(address) as client:
        for attempt in (1, 2):
            try:
                return attempt, await client.sensor(channel)
            except ResponseTimeout:
                pass
        return attempt, None


async def sensor_with_reconnect(address, channel):
    """The client under test: a sensor read that connects again once when
    the connection is lost.  (connections used, value)."""
    for attempt in (1, 2):
        try:
            async with await connect(address) as client:
                return attempt, await client.sensor(channel)
        except ConnectionClosed:
            pass
    return attempt, None


def test_survives_a_dropped_answer(whiztap_proxy):
    with whiztap_proxy.fault("drop dir:s2c kind:response ch:12 nth:1") as fault:
        assert [f["spec"] for f in whiztap_proxy.state()["faults"]] == [fault.spec]
        attempts, value = asyncio.run(sensor_with_retry(whiztap_proxy.address, 12))
        assert attempts == 2 and 0 <= value <= 1024  # the timeout path, then the answer
        assert fault.hits == 1
    assert whiztap_proxy.state()["faults"] == []  # gone with the block
    assert asyncio.run(sensor_with_retry(whiztap_proxy.address, 12))[0] == 1
    [drop] = whiztap_proxy.interventions("drop")
    assert (drop.conn, drop.direction.value, drop.kind, drop.after) == (1, "s2c", "response", b"")
    assert drop.before.startswith(b"cr1-12--") and str(drop.cause) == f"fault {fault.name}: {fault.spec}"


def test_survives_a_reset(whiztap_proxy):
    with whiztap_proxy.fault("reset dir:c2s kind:command ch:13 conn:1"):
        connections, value = asyncio.run(sensor_with_reconnect(whiztap_proxy.address, 13))
    assert connections == 2 and 0 <= value <= 1024
    assert {(i.conn, i.action) for i in whiztap_proxy.interventions()} == {(1, "reset")}


def test_an_injected_answer_is_not_taken_for_the_next(whiztap_proxy):
    async def client_sees_an_unsolicited_answer():
        async with await connect(whiztap_proxy.address) as client:
            sent = whiztap_proxy.inject("s2c", "cr1-12--999--0-ss1")
            while not client.stray:
                await asyncio.sleep(0.01)
            return sent, client.stray[0].raw, await client.sensor(12)

    sent, stray, value = asyncio.run(client_sees_an_unsolicited_answer())
    assert sent == stray == b"cr1-12--999--0-ss1" and value != 999
    [inject] = whiztap_proxy.interventions("inject")
    assert (inject.conn, inject.direction.value, inject.before, inject.after) == (1, "s2c", b"", sent)


def test_inject_checks_the_frame_and_the_connection(whiztap_proxy):
    whiztap_proxy.connection_wait = 0.1  # no client will come: no need to wait the default 2 s
    with pytest.raises(ControlError, match="no connection is open through the proxy"):
        whiztap_proxy.inject("c2s", "sensor 12")

    async def two_clients():
        async with await connect(whiztap_proxy.address), await connect(whiztap_proxy.address):
            with pytest.raises(ControlError, match=r"2 connections are open through the proxy \(#1, #2\)"):
                whiztap_proxy.inject("c2s", "sensor 12")
            with pytest.raises(ControlError, match="breaks a rule"):
                whiztap_proxy.inject(2, "c2s", "sensor 99")
            return whiztap_proxy.inject(2, "c2s", "sensor 99", force=True)

    assert asyncio.run(two_clients()) == b"rr1-99--0--0-ss1"


def test_the_recording_keeps_what_the_proxy_did(whiztap_proxy):
    with whiztap_proxy.fault("delay:50ms dir:s2c kind:response", name="slow"):
        assert asyncio.run(sensor_with_retry(whiztap_proxy.address, 14))[0] == 1
    path = whiztap_proxy.stop()
    assert path == whiztap_proxy.recording and path.exists()
    with open(path, "rb") as f:
        scan = RecordingScan(f, ("/interventions", "/tcp/delivered"))
        messages = list(scan.messages())
    changes = [m for topic, _, m in messages if topic == "/interventions"]
    assert [(m["action"], m["cause"]) for m in changes] == [("delay", "fault slow: delay:50ms dir:s2c kind:response")]
    assert any(topic == "/tcp/delivered" for topic, _, _ in messages)


def test_whiztap_ctl_drives_the_fixtures_proxy(whiztap_proxy):
    from tests.cli_support import run_cli

    def ctl(*args):
        result = run_cli("ctl", "--control", whiztap_proxy.control, *args)
        assert result.returncode == 0, result.stderr
        return result.stdout

    assert ctl("fault", "add", "drop dir:s2c kind:response ch:12 nth:1", "--name", "once").startswith("added fault #1")
    assert [f["name"] for f in whiztap_proxy.state()["faults"]] == ["once"]
    attempts, _ = asyncio.run(sensor_with_retry(whiztap_proxy.address, 12))
    assert attempts == 2 and "once  on  matched 2  hits 1" in ctl("fault", "list")
    socket_path = whiztap_proxy.control
    whiztap_proxy.stop()
    assert not os.path.exists(socket_path)
'''


def run(pytester: pytest.Pytester, *args: str) -> pytest.RunResult:
    # as in test_pytest_plugin.py: plugins a nested session does not need
    return pytester.runpytest("-p", "no:cacheprovider", "-p", "no:textual-snapshot", "-p", "no:hypothesispytest",
                              *args)


@pytest.mark.slow
def test_a_client_tested_through_the_proxy_in_the_middle(pytester: pytest.Pytester) -> None:
    pytester.makeini(INI)
    pytester.makeconftest(CONFTEST)
    pytester.makepyfile(test_client=TESTS)
    result = run(pytester, "-v")
    result.assert_outcomes(passed=6)


def test_without_a_target_the_fixture_says_how_to_give_one(pytester: pytest.Pytester) -> None:
    pytester.makeini(INI)
    pytester.makepyfile(test_alone="def test_it(whiztap_proxy):\n    pass\n")
    result = run(pytester)
    result.assert_outcomes(errors=1)
    result.stdout.fnmatch_lines(["*whiztap: whiztap_proxy needs a live server: give the marker target=HOST:PORT,*"])
