"""The pytest plugin, run by pytest itself (``pytester``) on a small project that
tests a client against the simulator: record once, then replay from the stub."""

from __future__ import annotations

import pytest

from whiztap.analyzer.analysis.exchanges import load_exchanges
from whiztap.analyzer.recording.scan import read_metadata

pytest_plugins = ["pytester"]

INI = "[pytest]\nasyncio_default_fixture_loop_scope = function\n"

CONFTEST = '''
import os

import pytest

from whiztap.sniffer.pytest_plugin import BackgroundLoop
from whiztap.sniffer.sim.simulator import Simulator


@pytest.fixture
def whiztap_target():
    """The live server: a frozen-clock simulator, so a seed fixes every answer."""
    if os.environ.get("NO_TARGET"):
        pytest.fail("the live server was used")
    if os.environ.get("DEAD_TARGET"):  # nothing listens on port 1
        yield "127.0.0.1:1"
        return
    with BackgroundLoop() as background:
        sim = Simulator(password="pw", seed=int(os.environ.get("SIM_SEED", "1")), clock=lambda: 5_000_000_000)
        background.run(sim.start())
        yield f"127.0.0.1:{sim.port}"
        background.run(sim.close())
'''

TESTS = '''
import asyncio
import os

import pytest

from whiztap.sniffer.sim.client import Client


async def read_sensors(address):
    """The client under test: configuration, then a few sensors."""
    host, port = address.rsplit(":", 1)
    channels = [12, 13] + ([14] if os.environ.get("NEW_REQUEST") else [])
    async with await Client.connect(host, int(port), password="pw", timeout=0.5) as client:
        config = await client.fetch_configuration()
        return len(config.channels), [await client.sensor(ch) for ch in channels]


@pytest.mark.whiztap("recordings/sensors.mcap", password="pw")
def test_sensors(whiztap_server):
    count, values = asyncio.run(read_sensors(whiztap_server.address))
    assert count == 24 and all(0 <= v <= 1024 for v in values)


@pytest.mark.whiztap
def test_default_name(whiztap_server, whiztap_recording):
    assert whiztap_recording == whiztap_server.path
    assert whiztap_recording.parts[-3:] == ("recordings", "test_client", "test_default_name.mcap")
    assert asyncio.run(read_sensors(whiztap_server.address))[0] == 24


@pytest.mark.asyncio
@pytest.mark.whiztap("recordings/sensors.mcap")
async def test_from_asyncio(whiztap_server):
    assert (await read_sensors(whiztap_server.address))[0] == 24


@pytest.mark.whiztap("recordings/sensors.mcap", password="pw")
def test_replay_matches(whiztap_replay):
    result = whiztap_replay(compare="exact", pace="lockstep", timeout=0.5)
    assert result.ok
'''


@pytest.fixture
def project(pytester: pytest.Pytester) -> pytest.Pytester:
    pytester.makeini(INI)
    pytester.makeconftest(CONFTEST)
    pytester.makepyfile(test_client=TESTS)
    return pytester


def run(pytester: pytest.Pytester, *args: str) -> pytest.RunResult:
    # textual's snapshot plugin keeps a per-process temporary folder that a
    # second pytest session in the same process finds removed; hypothesis's
    # costs seconds per session and is not needed here
    return pytester.runpytest("-p", "no:cacheprovider", "-p", "no:textual-snapshot", "-p", "no:hypothesispytest",
                              *args)


@pytest.mark.slow
def test_record_once_then_serve_from_the_recording(project, monkeypatch):
    recording = project.path / "recordings" / "sensors.mcap"
    default = project.path / "recordings" / "test_client" / "test_default_name.mcap"
    first = run(project, "-k", "not replay")  # record mode none: nothing recorded yet
    first.assert_outcomes(errors=3)
    first.stdout.fnmatch_lines([f"*whiztap: no recording {recording}; run pytest with --whiztap-record=once*"])

    run(project, "--whiztap-record=once", "-k", "not replay").assert_outcomes(passed=3)
    assert recording.exists() and default.exists()
    session = read_metadata(str(recording))["session_id"]

    monkeypatch.setenv("NO_TARGET", "1")  # from now on only the recordings answer
    run(project, "-k", "not replay").assert_outcomes(passed=3)
    run(project, "--whiztap-record=once", "-k", "not replay").assert_outcomes(passed=3)
    assert read_metadata(str(recording))["session_id"] == session  # once: kept as it was

    monkeypatch.setenv("NEW_REQUEST", "1")  # the client asks for something new
    new = run(project, "-k", "test_sensors")
    new.assert_outcomes(failed=1)
    new.stdout.fnmatch_lines([f"*whiztap: 1 request not in {recording} (record mode none):*",
                              "*#1: no recorded answer for rr1-14--0--0-ss1 (Sensor Request ch 14)*",
                              "*closest recorded: #1 request 3 Sensor Request ch 13: channel 14 here, 13 recorded; "
                              "position 4 here, 3 recorded*"])

    monkeypatch.delenv("NO_TARGET")
    run(project, "--whiztap-record=all", "-k", "test_sensors").assert_outcomes(passed=1)
    assert read_metadata(str(recording))["session_id"] != session  # all: made again
    monkeypatch.setenv("NO_TARGET", "1")
    run(project, "-k", "test_sensors").assert_outcomes(passed=1)  # and it has the new request

    monkeypatch.delenv("NEW_REQUEST")  # the client no longer asks for channel 14: the recording has rotted
    run(project, "-k", "test_sensors").assert_outcomes(passed=1)
    rotten = run(project, "-k", "test_sensors", "--whiztap-fail-unused")
    rotten.assert_outcomes(failed=1)
    rotten.stdout.fnmatch_lines([
        f"*whiztap: 1 recorded request never asked for in {recording} (--whiztap-fail-unused):*",
        "*#1 request 4 Sensor Request ch 14*"])


@pytest.mark.slow
def test_new_episodes_records_only_what_is_missing(project, monkeypatch):
    """vcrpy's new_episodes: what is recorded is served, the one new request is
    asked of the target and appended; a target that fails appends nothing."""
    recording = project.path / "recordings" / "sensors.mcap"
    run(project, "--whiztap-record=new_episodes", "-k", "test_sensors").assert_outcomes(passed=1)  # made whole
    session, before = read_metadata(str(recording))["session_id"], recording.read_bytes()

    monkeypatch.setenv("NEW_REQUEST", "1")  # the client now also asks for channel 14
    monkeypatch.setenv("DEAD_TARGET", "1")
    dead = run(project, "--whiztap-record=new_episodes", "-k", "test_sensors")
    dead.assert_outcomes(failed=1)
    dead.stdout.fnmatch_lines(["*whiztap: new_episodes: the target 127.0.0.1:1 failed: cannot connect to "
                               f"127.0.0.1:1 (*); nothing will be appended to {recording}*"])
    assert recording.read_bytes() == before

    monkeypatch.delenv("DEAD_TARGET")
    run(project, "--whiztap-record=new_episodes", "-k", "test_sensors").assert_outcomes(passed=1)
    assert read_metadata(str(recording))["session_id"] == session  # appended to, not made again
    first, new = load_exchanges(str(recording)).connections
    assert [i.obs.item.raw for i in new.requests] == [b"rr1-24--0--0-ss1", b"rr1-14--0--0-ss1"]
    assert recording.read_bytes() != before and len(first.requests) == 3

    monkeypatch.setenv("NO_TARGET", "1")  # the recording now answers everything the client asks
    run(project, "-k", "test_sensors", "--whiztap-fail-unused").assert_outcomes(passed=1)


@pytest.mark.slow
def test_replay_fixture_passes_on_the_same_server_and_fails_with_the_diff(project, monkeypatch):
    run(project, "--whiztap-record=once", "-k", "test_sensors").assert_outcomes(passed=1)
    run(project, "-k", "replay").assert_outcomes(passed=1)
    monkeypatch.setenv("SIM_SEED", "2")
    other = run(project, "-k", "replay")
    other.assert_outcomes(failed=1)
    other.stdout.fnmatch_lines([
        "*whiztap: replay of *sensors.mcap against 127.0.0.1:* differs*",
        "MISMATCH c1 at * s after rr1-12--0--0-ss1 (Sensor Request ch 12)",
        "  sensor_value: * | sensor_value: *",
    ])


def test_setup_problems_are_one_clear_line(pytester):
    pytester.makeini(INI)
    (pytester.path / "damaged.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 40)
    pytester.makepyfile(test_alone='''
        import pytest

        @pytest.mark.whiztap("r.mcap")
        def test_recording_without_a_target(whiztap_server):
            pass

        @pytest.mark.whiztap("damaged.mcap")
        def test_a_damaged_recording(whiztap_server):
            pass
    ''')
    result = run(pytester, "--whiztap-record=once")
    result.assert_outcomes(errors=2)
    result.stdout.fnmatch_lines(["*whiztap: recording needs a live server: give the marker target=HOST:PORT,*",
                                 "*whiztap: cannot read *damaged.mcap: *"])
