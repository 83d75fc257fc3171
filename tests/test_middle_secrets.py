"""With the proxy in the middle, a password stays out of the recording as it
does without: not in /tcp/delivered, not in /interventions (a bug: the
delivered copy of a password was written in clear)."""

from __future__ import annotations

import asyncio
import json

from whiztap.analyzer.mitm.spec import parse_fault
from whiztap.sniffer.record.record_run import MiddleSettings
from whiztap.sniffer.sim.client import Client
from whiztap.sniffer.sim.simulator import Simulator
from tests.record_support import LOCAL, read_all, recording

PASSWORD = "progwhiz"
MIDDLE = MiddleSettings(faults=(parse_fault("delay:5ms dir:s2c"), parse_fault("dup dir:c2s kind:password")))


def _everything(path) -> str:
    """Every message of the recording as text, base64 decoded where it is data."""
    import base64

    text = []
    for topic, messages in read_all(str(path)).items():
        for m in messages:
            text.append(json.dumps(m))
            for key in ("data", "raw"):
                if isinstance(m.get(key), str):
                    text.append(base64.b64decode(m[key]).decode("latin-1"))
    return "\n".join(text)


async def test_a_password_through_the_middle_is_masked_everywhere(tmp_path):
    path = tmp_path / "pw.mcap"
    async with Simulator(port=0, mode="winsock", password=PASSWORD, seed=7) as sim:
        async with recording(sim.port, path, middle=MIDDLE) as rec:
            async with await Client.connect(LOCAL, rec.proxy.port, password=PASSWORD) as client:
                assert 0 <= await client.sensor(12) <= 1024
    by_topic = read_all(str(path))
    delivered = [m for m in by_topic["/tcp/delivered"] if m["dir"] == "c2s"]
    assert any(m.get("redacted") for m in delivered)
    assert PASSWORD not in _everything(path)


async def test_a_password_sent_before_the_server_asks_is_masked_too(tmp_path):
    """The early password reaches the proxy before sendchkpass: it passes as
    raw bytes, which are secret until the login is over."""
    path = tmp_path / "early.mcap"
    async with Simulator(port=0, mode="winsock", password=PASSWORD, seed=7) as sim:
        async with recording(sim.port, path, middle=MIDDLE) as rec:
            reader, writer = await asyncio.open_connection(LOCAL, rec.proxy.port)
            writer.write(PASSWORD.encode())
            await writer.drain()
            got = b""
            while b"readytogo" not in got and b"Failed" not in got:
                chunk = await asyncio.wait_for(reader.read(100), 5)
                assert chunk, got
                got += chunk
            writer.close()
    assert PASSWORD not in _everything(path)


async def test_secrets_kept_are_kept_in_the_delivered_copy_too(tmp_path):
    path = tmp_path / "kept.mcap"
    async with Simulator(port=0, mode="winsock", password=PASSWORD, seed=7) as sim:
        async with recording(sim.port, path, middle=MIDDLE, keep_secrets=True) as rec:
            async with await Client.connect(LOCAL, rec.proxy.port, password=PASSWORD) as client:
                await client.sensor(12)
    assert PASSWORD in _everything(path)
