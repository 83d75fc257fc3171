"""With the proxy in the middle, a password stays out of the recording as it
does without: not in /tcp/delivered, not in /interventions (a bug: the
delivered copy of a password was written in clear)."""

from __future__ import annotations

import json

import pytest

from whiztap.analyzer.mitm.spec import parse_fault
from whiztap.sniffer.record.record_run import MiddleSettings
from whiztap.sniffer.sim.client import Client
from whiztap.sniffer.sim.simulator import Simulator
from tests.record_support import LOCAL, StepServer, play_client, read_all, recording

PASSWORD = "progwhiz"
MIDDLE = MiddleSettings(faults=(parse_fault("delay:5ms dir:s2c"), parse_fault("dup dir:c2s kind:password")))


def _everything(path) -> str:
    """Every message of the recording as text, base64 decoded where it is data."""
    import base64

    text = []
    for messages in read_all(str(path)).values():
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


@pytest.mark.parametrize("early", [b"", b"rr1-12--0--0-ss1"], ids=["alone", "run-into-by-a-command"])
async def test_a_password_sent_before_the_server_asks_is_masked_too(tmp_path, early):
    """The server asks only once the client's bytes are in, so the proxy sees
    the password before sendchkpass: alone, it passes as raw bytes after a
    stall; followed by a command, it is an unframed item before it.  Either
    way it is secret, the login not being over."""
    sent = PASSWORD.encode() + early
    server = StepServer([("recv", len(sent)), ("send", b"sendchkpass"), ("send", b"readytogo")])
    path = tmp_path / "early.mcap"
    async with server:
        async with recording(server.port, path, middle=MIDDLE) as rec:
            got = await play_client(rec.proxy.port, [("send", sent), ("recv", len(b"sendchkpassreadytogo"))])
    assert got == b"sendchkpassreadytogo" and bytes(server.received).startswith(sent)
    assert PASSWORD not in _everything(path)


async def test_secrets_kept_are_kept_in_the_delivered_copy_too(tmp_path):
    path = tmp_path / "kept.mcap"
    async with Simulator(port=0, mode="winsock", password=PASSWORD, seed=7) as sim:
        async with recording(sim.port, path, middle=MIDDLE, keep_secrets=True) as rec:
            async with await Client.connect(LOCAL, rec.proxy.port, password=PASSWORD) as client:
                await client.sensor(12)
    assert PASSWORD in _everything(path)
