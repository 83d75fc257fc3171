"""What serving live costs the recording, and what the origin gate adds (docs/recorder.md).

A ``Recorder`` writing a ``LiveRecordingFile`` is fed pipelined Sensor
Requests and their answers, 64 frames a read, for ``SECONDS``; frames per
second are counted in three setups, turn by turn so a noisy machine disturbs
each alike: no viewer; a viewer in another process subscribed to every topic
and reading all of it through the gate (where ``--foxglove`` listens); the
same viewer straight to the SDK's own server behind the gate.  The
difference between the last two is the gate's cost.

Prints figures; asserts nothing (timings belong here, not in tests).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from statistics import median

from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.codec import encode
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.format import metadata_record
from whiztap.analyzer.traffic import Data, Opened

SECONDS = float(os.environ.get("WHIZTAP_BENCH_LIVE_SECONDS", 3))
TURNS = int(os.environ.get("WHIZTAP_BENCH_LIVE_TURNS", 3))
PAIRS_PER_READ = 32  # 64 frames a read pair
T0 = 1_700_000_000_000_000_000

# The viewer: what the Foxglove app does, as tests/test_foxglove_live.py's client does.
VIEWER = r'''
import asyncio, json, sys, websockets
async def main(url):
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
        await ws.recv()
        print("connected", flush=True)
        async for message in ws:
            if isinstance(message, str):
                message = json.loads(message)
                if message["op"] == "advertise":
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": c["id"], "channelId": c["id"]} for c in message["channels"]]}))
asyncio.run(main(sys.argv[1]))
'''


def _frames_per_second(folder: Path, viewer: str) -> float:
    """One turn: ``viewer`` is "none", "gate" or "sdk"."""
    from whiztap.sniffer.record.live import LiveRecordingFile, LiveServer
    from whiztap.sniffer.record.recorder import Recorder

    live = LiveServer("127.0.0.1", 0, warn=lambda line: None)
    path = folder / f"{viewer}.mcap"
    rec = Recorder(LiveRecordingFile(live, str(path), metadata_record(source="bench", session_id=viewer)))
    rec.start(T0)
    process = None
    if viewer != "none":
        host, port = live.gate.inner if viewer == "sdk" else ("127.0.0.1", live.port)
        process = subprocess.Popen([sys.executable, "-c", VIEWER, f"ws://{host}:{port}"], stdout=subprocess.PIPE)
        assert process.stdout is not None and process.stdout.readline()  # connected
        time.sleep(0.3)  # subscribed
    requests = b"".join(encode(m.SensorRequest(12 + i % 12)) for i in range(PAIRS_PER_READ))
    answers = b"".join(encode(m.ChannelResponse(12 + i % 12, i % 1025)) for i in range(PAIRS_PER_READ))
    rec.receive(Opened(1, T0, "127.0.0.1:40000", "127.0.0.1:5000"))
    rec.receive(Data(1, Direction.C2S, T0 + 1, encode(m.FetchConfiguration())))
    frames, t = 0, T0 + 2
    start = time.perf_counter()
    while time.perf_counter() - start < SECONDS:
        for _ in range(50):
            rec.receive(Data(1, Direction.C2S, t, requests))
            rec.receive(Data(1, Direction.S2C, t + 1, answers))
            t += 2
        frames += 100 * PAIRS_PER_READ
    rate = frames / (time.perf_counter() - start)
    if process is not None:
        process.kill()
        process.wait()
    rec.stop(t)
    return rate


def main() -> None:
    print(f"== Foxglove live: the writer's frames/s, {SECONDS:g} s a turn, {TURNS} turns each, interleaved ==")
    rates: dict[str, list[float]] = {"none": [], "gate": [], "sdk": []}
    with tempfile.TemporaryDirectory() as d:
        for _ in range(TURNS):
            for viewer in rates:
                rates[viewer].append(_frames_per_second(Path(d), viewer))
    words = {"none": "no viewer", "gate": "a viewer through the gate", "sdk": "a viewer straight to the SDK"}
    for viewer, got in rates.items():
        print(f"FRAMES/S live, {words[viewer]}: median {median(got):,.0f}, best {max(got):,.0f}")
    print(f"RATIO gate / straight to the SDK (medians): {median(rates['gate']) / median(rates['sdk']):.2f}")


if __name__ == "__main__":
    main()
