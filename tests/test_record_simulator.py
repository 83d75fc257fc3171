"""The simulator behind the recording proxy, with and without its fault switches."""

from __future__ import annotations

import base64

import pytest

from whiztap.sniffer.sim.client import Client, ResponseTimeout
from whiztap.sniffer.sim.faults import FaultConfig
from whiztap.sniffer.sim.simulator import Simulator
from tests.replay_support import until_closed
from tests.record_support import LOCAL, both_ways, events, frame_items, on_channels, read_all, recording

PASSWORD = "s3cret-pw"


async def test_a_winsock_session_through_the_proxy_is_recorded_whole(tmp_path):
    path = tmp_path / "sim.mcap"
    async with Simulator(port=0, mode="winsock", password=PASSWORD, seed=7) as sim, \
            recording(sim.port, path) as rec:
        async with await Client.connect(LOCAL, rec.proxy.port, password=PASSWORD) as client:
            config = await client.fetch_configuration()
            sensor = await client.sensor(12)
            position = await client.servo_position(3)
            await client.normal_send(2, 1500)
            await client.activate_switch(7)
            await client.deactivate_switch(7)
            image = await client.fetch_camera_image()
        await until_closed(sim)  # the simulator has seen its clients go
        summary = await rec.stop()
        stats = sim.stats
    assert len(config.channels) == 24
    recorded = both_ways(str(path))
    assert len(recorded[(1, "s2c")]) == stats.bytes_out
    assert len(recorded[(1, "c2s")]) == stats.bytes_in
    assert recorded[(1, "c2s")].startswith(b"*" * len(PASSWORD))  # redacted
    by_topic = read_all(str(path))
    assert [s["value"] for s in on_channels(by_topic, "/sensors")] == [sensor]
    assert [s["value"] for s in by_topic["/sensors/12"]] == [sensor]  # a topic per channel
    assert [(s["channel"], s["position"]) for s in on_channels(by_topic, "/servos")] == [(3, position)]
    assert all(isinstance(s["latency_ns"], int) and s["latency_ns"] >= 0 for s in by_topic["/servos/3"])
    assert [(s["channel"], s["value"]) for s in on_channels(by_topic, "/sends")] == [(2, 1500)]
    assert [(s["channel"], s["state"]) for s in on_channels(by_topic, "/switches")] == [(7, 1), (7, 0)]
    [camera] = by_topic["/camera"]
    assert camera["format"] == "jpeg" and base64.b64decode(camera["data"]) == image
    assert camera["frame_id"] == "conn-1" and set(camera["timestamp"]) == {"sec", "nsec"}
    kinds = [k for k, _ in frame_items(by_topic["/frames"], 1, "s2c")]
    assert kinds[:3] == ["handshake", "handshake", "config"] and "image" in kinds
    assert next(k for k, _ in frame_items(by_topic["/frames"], 1, "c2s")) == "password"
    assert not [v for v in by_topic["/violations"] if v["severity"] == "error"]
    assert summary["frames"]["c2s"] == 8 and summary["violations"].get("error", 0) == 0
    assert events(by_topic, 1) == ["opened", "upstream_connected", "half_closed", "closed"] or \
        events(by_topic, 1)[-1] == "closed"


@pytest.mark.slow
@pytest.mark.parametrize("faults", [
    FaultConfig(split=True),
    FaultConfig(garbage_rate=0.5, split=True),
    FaultConfig(drop_rate=0.3),
    FaultConfig(latency_ms=5, jitter_ms=4),
], ids=["split", "garbage", "drop", "latency"])
async def test_simulator_faults_are_forwarded_and_recorded_exactly(tmp_path, faults):
    path = tmp_path / "faults.mcap"
    async with Simulator(port=0, mode="vpn", seed=3, faults=faults, camera=False) as sim, \
            recording(sim.port, path) as rec:
        async with await Client.connect(LOCAL, rec.proxy.port, timeout=0.3) as client:
            for _ in range(20):  # the channel map makes Sensor Requests unambiguous
                try:
                    await client.fetch_configuration()
                    break
                except ResponseTimeout:
                    pass  # that answer was dropped
            answered = 0
            for channel in range(12, 24):
                try:
                    await client.sensor(channel)
                    answered += 1
                except ResponseTimeout:
                    pass  # a dropped answer
        await until_closed(sim)  # the simulator has seen its clients go
        await rec.stop()
    recorded = both_ways(str(path))
    assert len(recorded[(1, "s2c")]) == sim.stats.bytes_out
    by_topic = read_all(str(path))
    assert len(on_channels(by_topic, "/sensors")) >= answered
    rules = {v["rule_id"] for v in by_topic["/violations"]}
    if faults.garbage_rate:
        assert "PW-FRAME-GARBAGE" in rules
    if faults.drop_rate:
        assert sim.stats.answers_dropped > 0 and "PW-PAIR-UNANSWERED" in rules
    if faults.split:  # replies cut into many writes still make whole frames
        responses = [raw for kind, raw in frame_items(by_topic["/frames"], 1, "s2c") if kind == "response"]
        assert len(responses) == len(on_channels(by_topic, "/sensors")) == answered
