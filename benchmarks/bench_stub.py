"""`whiztap stub`, with and without ``--upstream``: round-trip latency per request.

Each server runs as a user runs it, a process of its own (``whiztap sim``,
``whiztap stub``), and one lockstep client in this process (a blocking
socket, no event loop: the least overhead of its own) logs in, fetches the
configuration, then sends ``N`` Sensor Requests, each after the last one's
answer, timing each round trip with ``perf_counter_ns``.  Four servers, side
by side in one run, so the machine's drift hits them alike:

- the simulator directly (what a real server costs here);
- the stub without ``--upstream``, every request answered from the recording
  (the matched path of plain replay);
- the stub with ``--upstream``, every request still answered from the
  recording (what the new-episodes machinery adds to the matched path:
  nothing is forwarded, no upstream connection is opened);
- the stub with ``--upstream``, every request one the recording lacks (the
  miss path: forwarded on the client's upstream connection, the answer
  recorded, then sent back), beside the simulator directly.

The recording holds Sensor Requests on channels 12-15 once each; the matched
rows ask those (repeats of the last recorded answer), the miss row asks
channels 16-19, which it never has, so each one is forwarded (forwarded
answers are appended at the end, not served within the run).
"""

from __future__ import annotations

import asyncio
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

N = int(os.environ.get("WHIZTAP_BENCH_STUB_N", 3000))
ROUNDS = 3
MATCHED = (12, 13, 14, 15)  # the recording's channels
MISSED = (16, 17, 18, 19)  # never recorded: each request is forwarded
LISTEN = ("--listen", "127.0.0.1:0", "-q")
WHIZTAP = str(Path(sys.executable).with_name("whiztap"))
PASSWORD = "bench-pw"
_PORT = re.compile(r" on 127\.0\.0\.1:(\d+)")
_END = b"-ss1"


async def _record(path: Path, sim_port: int) -> None:
    from whiztap.sniffer.record.record_run import Recording, RecordSettings
    from whiztap.sniffer.sim.client import Client

    recording = Recording(RecordSettings(("127.0.0.1", 0), ("127.0.0.1", sim_port), str(path), quiet=True))
    await recording.start()
    try:
        async with await Client.connect("127.0.0.1", recording.proxy.port, password=PASSWORD) as client:
            await client.fetch_configuration()
            for channel in (12, 13, 14, 15):
                await client.sensor(channel)
        await asyncio.sleep(0.2)
    finally:
        await recording.stop()


@contextmanager
def _server(*args: str) -> Iterator[int]:
    """A whiztap process serving on a free port: its port, until the block ends (SIGINT then)."""
    proc = subprocess.Popen([WHIZTAP, *args], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        found = _PORT.search(proc.stdout.readline())
        if found is None:
            raise SystemExit(f"bench_stub: `whiztap {args[0]}` did not start")
        yield int(found.group(1))
    finally:
        proc.send_signal(2)
        proc.communicate(timeout=30)


def _read_frame(sock: socket.socket, pending: bytearray) -> bytes:
    """Bytes up to and including the next frame end (or a handshake word)."""
    while True:
        end = pending.find(_END)
        if end >= 0:
            frame = bytes(pending[:end + len(_END)])
            del pending[:end + len(_END)]
            return frame
        data = sock.recv(65536)
        if not data:
            raise SystemExit("bench_stub: the server closed the connection")
        pending += data


def _read_word(sock: socket.socket, pending: bytearray, word: bytes) -> None:
    while word not in pending:
        data = sock.recv(65536)
        if not data:
            raise SystemExit("bench_stub: the server closed the connection during the handshake")
        pending += data
    del pending[:pending.index(word) + len(word)]


def _round_trips(port: int, channels: tuple[int, ...]) -> list[int]:
    """Log in, fetch the configuration, then N lockstep Sensor Requests: each round trip in ns."""
    times: list[int] = []
    with socket.create_connection(("127.0.0.1", port)) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        pending = bytearray()
        _read_word(sock, pending, b"sendchkpass")
        sock.sendall(PASSWORD.encode())
        _read_word(sock, pending, b"readytogo")
        sock.sendall(b"rr1-24--0--0-ss1")
        _read_frame(sock, pending)
        requests = [b"rr1-%d--0--0-ss1" % channels[i % len(channels)] for i in range(N)]
        for request in requests:
            began = time.perf_counter_ns()
            sock.sendall(request)
            _read_frame(sock, pending)
            times.append(time.perf_counter_ns() - began)
    return times


def _percentiles(times: list[int]) -> tuple[float, float]:
    ordered = sorted(times)
    return ordered[len(ordered) // 2] / 1000, ordered[min(len(ordered) - 1, int(len(ordered) * 0.99))] / 1000


def main() -> None:
    print(f"== stub: round trip per Sensor Request, lockstep, {N:,} requests a row, best of {ROUNDS} rounds "
          "taken in turns (p50 / p99, microseconds)")
    with tempfile.TemporaryDirectory() as folder, ExitStack() as servers:
        sim = servers.enter_context(_server("sim", "--port", "0", "--password", PASSWORD, "-q"))
        recorded = Path(folder) / "recorded.mcap"
        asyncio.run(_record(recorded, sim))
        copies = [Path(folder) / f"{i}.mcap" for i in (1, 2)]
        for copy in copies:
            shutil.copyfile(recorded, copy)
        upstream = ("--upstream", f"127.0.0.1:{sim}")
        rows = [("simulator directly", sim, MATCHED),
                ("stub, matched", servers.enter_context(_server("stub", str(recorded), *LISTEN)), MATCHED),
                ("stub --upstream, matched", servers.enter_context(_server("stub", str(copies[0]), *LISTEN, *upstream)),
                 MATCHED),
                ("stub --upstream, miss (forwarded)",
                 servers.enter_context(_server("stub", str(copies[1]), *LISTEN, *upstream)), MISSED)]
        best: dict[str, tuple[float, float]] = {}
        for _ in range(ROUNDS):
            for name, port, channels in rows:
                p50, p99 = _percentiles(_round_trips(port, channels))
                was = best.get(name, (float("inf"), float("inf")))
                best[name] = (min(was[0], p50), min(was[1], p99))
    direct, plain = best["simulator directly"], best["stub, matched"]
    for name, _, _ in rows:
        p50, p99 = best[name]
        base, against = (plain, "plain stub") if name == "stub --upstream, matched" else (direct, "the simulator")
        added = "" if name == "simulator directly" else \
            f"   added vs {against}: {p50 - base[0]:+7.1f} / {p99 - base[1]:+7.1f}"
        print(f"  {name:34} {p50:7.1f} / {p99:7.1f}{added}")


if __name__ == "__main__":
    main()
