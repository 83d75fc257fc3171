"""One recording made the way users make them (the proxy and its writer
process in front of the simulator) reads identically everywhere: the same
messages, byte for byte and at the same log times, through whiztap's own
scan, mcap's Python reader and the TypeScript @mcap/core reader (the one
Foxglove uses); and the same frames and violations in ``analyze``, ``cat``,
the TUI's frame store and replay's plan of the client side."""

from __future__ import annotations

import asyncio
import base64
import hashlib
import json
import shutil
import subprocess
import threading
from collections import Counter, defaultdict
from pathlib import Path

import pytest
from mcap.reader import make_reader

from tests.replay_support import until_closed
from tests.cli_support import run_cli
from tests.record_support import LOCAL, recording
from whiztap.analyzer.analysis.exchanges import load_exchanges
from whiztap.analyzer.recording.format import KNOWN_TOPICS
from whiztap.analyzer.recording.scan import RecordingScan
from whiztap.analyzer.recording.sets import find_one
from whiztap.sniffer.sim.client import Client
from whiztap.sniffer.sim.simulator import Simulator
from whiztap.tui.data.model import TrafficModel
from whiztap.tui.data.sources import FileSource

CHECK = Path(__file__).parent / "mcap_check"
PASSWORD = "reader-pw"


async def _record(path: Path) -> None:
    """A Winsock session with every kind of traffic, rules broken on purpose."""
    async with Simulator(port=0, mode="winsock", password=PASSWORD, seed=11) as sim, \
            recording(sim.port, path) as rec:
        async with await Client.connect(LOCAL, rec.proxy.port, password=PASSWORD) as client:
            await client.fetch_configuration()
            for channel in (12, 13, 14):
                await client.sensor(channel)
            await client.servo_position(3)
            await client.normal_send(2, 1500)
            await client.activate_switch(7)
            await client.fetch_camera_image()
            await client.exchange_raw(b"rr1-99--0--0-ss1", 0.2)  # an unconfigured channel: broken rules
            await client.send_raw(b"not a frame\r\n")
            await client.sensor(15)
        await until_closed(sim)  # the simulator has seen its clients go
        await rec.stop()


def _digest(messages: list[tuple[int, bytes]]) -> str:
    """As check.mjs hashes a topic: each log time in decimal and a newline, then the data."""
    h = hashlib.sha256()
    for t, data in messages:
        h.update(b"%d\n" % t)
        h.update(data)
    return h.hexdigest()


def _by_our_scan(path: Path) -> dict[str, list[tuple[int, bytes]]]:
    found: dict[str, list[tuple[int, bytes]]] = defaultdict(list)
    with open(path, "rb") as f:
        for t, topic, buf, start, stop in RecordingScan(f, tuple(KNOWN_TOPICS)).records():
            found[topic].append((t, bytes(buf[start:stop])))
    return found


def _by_mcap_python(path: Path) -> dict[str, list[tuple[int, bytes]]]:
    found: dict[str, list[tuple[int, bytes]]] = defaultdict(list)
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        for _, channel, message in reader.iter_messages(log_time_order=True):
            found[channel.topic].append((message.log_time, message.data))
    return found


@pytest.mark.slow
def test_the_same_recording_reads_identically_in_every_reader(tmp_path):
    path = tmp_path / "every.mcap"
    asyncio.run(_record(path))

    ours, theirs = _by_our_scan(path), _by_mcap_python(path)
    assert ours == theirs
    assert {"/tcp/reads", "/frames", "/violations", "/log", "/camera", "/sensors/12", "/servos/3"} <= set(ours)
    assert len(ours["/log"]) == len(ours["/violations"]) > 0

    if shutil.which("node") is None or not (CHECK / "node_modules" / "@mcap" / "core").is_dir():
        pytest.skip("node or @mcap/core is not installed (make test-deps installs them)")
    result = subprocess.run(["node", str(CHECK / "check.mjs"), str(path)], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["digests"] == {topic: _digest(found) for topic, found in ours.items()}


@pytest.mark.slow
def test_the_same_recording_means_the_same_in_analyze_cat_the_tui_and_replay(tmp_path):
    path = tmp_path / "every.mcap"
    asyncio.run(_record(path))

    report = json.loads(run_cli("analyze", path, "--format", "json").stdout)
    lines = [json.loads(line) for line in run_cli("cat", path, "--format", "jsonl").stdout.splitlines()]
    items = [line for line in lines if line["kind"] != "late_violation"]
    model = TrafficModel(str(path))
    source = FileSource(find_one([str(path)]))
    source.feed(model, threading.Event())
    sessions = load_exchanges(find_one([str(path)]))

    assert report["summary"]["frames"] == len(items) == model.store.count > 20
    assert Counter(report["rule_counts"]) == Counter(rule for line in lines for rule in line["violations"])
    assert "PW-CHANNEL-UNCONFIGURED" in report["rule_counts"]
    client_items = [line for line in items if line["dir"] == "c2s"]
    [connection] = sessions.connections
    assert len(connection.items) == len(client_items)
    assert [c.obs.item.raw for c in connection.items] == [base64.b64decode(line["raw_b64"]) for line in client_items]
