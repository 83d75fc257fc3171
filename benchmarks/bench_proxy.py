"""The recording proxy: round trips, pipelined frames recorded, memory over time.

Everything runs as separate processes on this machine, as a user would run
them: the simulator (``whiztap sim --mode vpn``), ``socat`` as a plain relay
when it is installed, ``mitmdump`` in raw TCP reverse mode writing its flows
(the peer a user would otherwise pick; ``make bench`` installs mitmproxy into
``.venv-peers``), ``whiztap record -q``, and a blocking-socket client in this
process.

* Round trips: one Sensor Request, wait for its response, repeat, for
  ``WHIZTAP_BENCH_RT_S`` seconds (default 3) per path; direct, socat, mitmdump,
  a bare relay and whiztap record take turns ``ROUNDS`` times and the median
  counts.  The targets are ratios in the same run: whiztap record / socat at
  least 1.0; whiztap record / mitmdump is printed beside it.
  The bare relay forwards the way whiztap record does (uvloop, asyncio
  protocols, TCP_NODELAY, each read written on at once) and records nothing:
  it is what a relay in Python costs before recording costs anything.
  ``whiztap record --control 0`` is the proxy in the middle with no fault
  (every frame decided, written on and recorded on /tcp/delivered too): its
  row and its ratio to plain ``whiztap record`` are what the middle costs.
* Pipelined: a Fetch Configuration, its answer, then ``WHIZTAP_BENCH_PIPELINE_FRAMES``
  requests (default 200k; a realistic mix: Sensor Requests on channels 12-23
  and, one in ``BAD_EVERY``, a request for channel 99, which breaks two rules, and
  its answer one, so the violation path is measured too) written as fast as the socket takes them
  through whiztap record to a responder that answers each at C speed (the
  simulator answers too slowly to be what is measured), read back in
  parallel; then Ctrl-C, and the clock stops when the file is finished.
  Requests and responses both count as frames.  The recording is read back
  and must hold every byte and every frame.
* Pipelined, one way: ``WHIZTAP_BENCH_ONE_WAY_FRAMES`` Normal Sends (default
  500k; commands that get no answer, as a client that only drives outputs
  sends them) through whiztap record to a server that reads them and never
  says a thing; then Ctrl-C.  Every frame must be in the file, as sent: with
  no server to say whether a password is asked, only the client's first line
  could be one, and a client that begins with a frame has none.
* Pipelined in the middle: the same requests through ``whiztap record
  --control 0`` (no fault) to a server that reads and discards them; frames/s
  from the first byte sent to the last byte the server received (the
  forwarding rate of the middle, requests only, one way).
* Memory: resident size of the proxy and its writer process sampled every
  second while the request/response client runs through it to the simulator
  without a pause, for ``WHIZTAP_BENCH_SOAK_S`` seconds (default 60, to keep
  ``make bench`` short; the 10-minute run is ``WHIZTAP_BENCH_SOAK_S=600 make bench``).
"""

from __future__ import annotations

import os
import platform
import re
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

RT_S = float(os.environ.get("WHIZTAP_BENCH_RT_S", "3"))
ROUNDS = 3
PIPELINE_FRAMES = int(os.environ.get("WHIZTAP_BENCH_PIPELINE_FRAMES", "200000"))
ONE_WAY_FRAMES = int(os.environ.get("WHIZTAP_BENCH_ONE_WAY_FRAMES", "500000"))
SOAK_S = float(os.environ.get("WHIZTAP_BENCH_SOAK_S", "60"))
WHIZTAP = str(Path(sys.executable).with_name("whiztap"))
PEERS = Path(__file__).resolve().parent.parent / ".venv-peers" / "bin"
# one pipelined request in this many asks channel 99: rules broken
BAD_EVERY = int(os.environ.get("WHIZTAP_BENCH_BAD_EVERY", "10"))
TARGET_PIPELINED_FPS = 250_000
TARGET_SOCAT_RATIO = 1.0
MIDDLE = "record --control 0"  # the proxy in the middle, no fault
REQUEST = b"rr1-12--0--0-ss1"
FETCH_CONFIG = b"rr1-24--0--0-ss1"
RESPONDER = """
import asyncio, sys, uvloop
CONFIG = b"sr1-\\x18" + b"200" * 24 + b"-ss1"
class Responder(asyncio.Protocol):  # every Sensor Request answered with data 0, at C speed
    def connection_made(self, t): self.t = t
    def data_received(self, d):
        if d.startswith(b"rr1-24--0--0-ss1"):
            self.t.write(CONFIG)
            d = d[16:]
        self.t.write(d.replace(b"rr1-", b"cr1-"))
async def main():
    s = await asyncio.get_running_loop().create_server(Responder, "127.0.0.1", int(sys.argv[1]))
    await s.serve_forever()
uvloop.run(main())
"""
BARE_RELAY = """
import asyncio, socket, sys, uvloop
class Leg(asyncio.Protocol):  # forwards each read at once; records nothing
    peer = None
    def connection_made(self, t):
        self.t, self.early = t, []
        t.get_extra_info("socket").setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    def data_received(self, d):
        if self.peer is None: self.early.append(d)  # read before the upstream was connected
        else: self.peer.t.write(d)
    def eof_received(self):
        if self.peer is not None: self.peer.t.write_eof()
        return True
    def connection_lost(self, e):
        if self.peer is not None: self.peer.t.close()
class Client(Leg):
    def connection_made(self, t):
        super().connection_made(t)
        asyncio.get_running_loop().create_task(self.connect())
    async def connect(self):
        _, up = await asyncio.get_running_loop().create_connection(Leg, "127.0.0.1", int(sys.argv[2]))
        up.t.write(b"".join(self.early))
        self.peer, up.peer = up, self
        if self.t.is_closing(): up.t.close()
async def main():
    s = await asyncio.get_running_loop().create_server(Client, "127.0.0.1", int(sys.argv[1]))
    await s.serve_forever()
uvloop.run(main())
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_port(port: int, proc: subprocess.Popen | None = None) -> None:
    """Until ``port`` accepts; if ``proc`` (what should listen there) exits
    first, its own error message is the one to see."""
    for _ in range(500):
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return
        except OSError:
            if proc is not None and proc.poll() is not None:
                err = proc.stderr.read().decode().strip() if proc.stderr else ""
                raise RuntimeError(f"{proc.args[1]} exited with status {proc.returncode}: {err}") from None
            time.sleep(0.02)
    raise RuntimeError(f"nothing listens on {port}")


def _spawn(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _stop(proc: subprocess.Popen) -> str:
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=600)
    return out.decode()


def pipelined_requests() -> bytes:
    """The pipelined load: PIPELINE_FRAMES Sensor Requests, one in BAD_EVERY
    for channel 99 (which breaks rules), the rest over channels 12-23."""
    return b"".join(b"rr1-%d--0--0-ss1" % (99 if i % BAD_EVERY == BAD_EVERY - 1 else 12 + i % 12)
                    for i in range(PIPELINE_FRAMES))


def _recv_frame(sock: socket.socket) -> None:
    buf = b""
    while not buf.endswith(b"-ss1"):
        data = sock.recv(65536)
        if not data:
            raise ConnectionError("closed")
        buf += data


def _round_trips(port: int, seconds: float) -> float:
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        s.sendall(FETCH_CONFIG)
        _recv_frame(s)
        n = 0
        start = time.perf_counter()
        end = start + seconds
        while time.perf_counter() < end:
            for _ in range(100):
                s.sendall(REQUEST)
                _recv_frame(s)
            n += 100
        return n / (time.perf_counter() - start)


def _rss_kib(pid: int) -> int:
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0
    m = re.search(r"VmRSS:\s+(\d+)", text)
    return int(m.group(1)) if m else 0


def _tree_rss(pid: int) -> tuple[int, int]:
    """(proxy, writer) resident KiB: the writer is the proxy's child."""
    children = Path(f"/proc/{pid}/task/{pid}/children")
    kids = [int(c) for c in children.read_text().split()] if children.exists() else []
    return _rss_kib(pid), sum(_rss_kib(k) for k in kids)


def _mitmdump() -> str | None:
    """mitmproxy's command-line proxy: ``make bench`` installs it in .venv-peers."""
    found = PEERS / "mitmdump"
    return str(found) if found.exists() else shutil.which("mitmdump")


def _relay_round_trips(args: list[str], port: int) -> float:
    relay = _spawn(args)
    try:
        _wait_port(port, relay)
        return _round_trips(port, RT_S)
    finally:
        relay.terminate()
        relay.wait()


def round_trip_comparison(sim_port: int, tmp: Path) -> dict[str, float]:
    paths: dict[str, list[float]] = {"direct": [], "socat": [], "mitmdump": [], "bare relay": [],
                                     "whiztap record": [], MIDDLE: []}
    socat, mitmdump = shutil.which("socat"), _mitmdump()
    if socat is None:
        del paths["socat"]
    if mitmdump is None:
        del paths["mitmdump"]
    for _ in range(ROUNDS):
        paths["direct"].append(_round_trips(sim_port, RT_S))
        if socat is not None:
            port = _free_port()
            paths["socat"].append(_relay_round_trips(
                [socat, f"TCP-LISTEN:{port},reuseaddr,fork,nodelay,bind=127.0.0.1",
                 f"TCP:127.0.0.1:{sim_port},nodelay"], port))
        if mitmdump is not None:
            port = _free_port()
            paths["mitmdump"].append(_relay_round_trips(
                [mitmdump, "-q", "--mode", f"reverse:tcp://127.0.0.1:{sim_port}@{port}",
                 "-w", str(tmp / "rt.flows")], port))
        port = _free_port()
        relay = subprocess.Popen([sys.executable, "-c", BARE_RELAY, str(port), str(sim_port)])
        _wait_port(port)
        paths["bare relay"].append(_round_trips(port, RT_S))
        relay.terminate()
        relay.wait()
        port = _free_port()
        rec = _spawn([WHIZTAP, "record", "-q", "--listen", str(port), "--upstream", f"127.0.0.1:{sim_port}",
                      "-o", str(tmp / "rt.mcap"), "--force"])
        _wait_port(port, rec)
        paths["whiztap record"].append(_round_trips(port, RT_S))
        _stop(rec)
        port = _free_port()
        rec = _spawn([WHIZTAP, "record", "-q", "--listen", str(port), "--upstream", f"127.0.0.1:{sim_port}",
                      "-o", str(tmp / "rt-middle.mcap"), "--force", "--control", "0"])
        _wait_port(port, rec)
        paths[MIDDLE].append(_round_trips(port, RT_S))
        _stop(rec)
    return {name: statistics.median(rates) for name, rates in paths.items()}


def _streams(path: Path) -> dict[tuple[int, str], bytes]:
    """Each (connection, direction) byte stream the recording's reads hold."""
    from whiztap.analyzer.recording.format import TOPIC_READS
    from whiztap.analyzer.recording.scan import RecordingScan

    streams: dict[tuple[int, str], bytearray] = {}
    with open(path, "rb") as f:
        for event in RecordingScan(f, (TOPIC_READS,)).traffic():
            streams.setdefault((event.conn, event.direction.value), bytearray()).extend(event.data)
    return {key: bytes(data) for key, data in streams.items()}


def pipelined(tmp: Path) -> dict[str, float]:
    upstream_port, port = _free_port(), _free_port()
    upstream = subprocess.Popen([sys.executable, "-c", RESPONDER, str(upstream_port)])
    _wait_port(upstream_port)
    out = tmp / "pipelined.mcap"
    rec = _spawn([WHIZTAP, "record", "--listen", str(port), "--upstream", f"127.0.0.1:{upstream_port}",
                  "-o", str(out)])
    _wait_port(port, rec)
    payload = pipelined_requests()
    got = bytearray()
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        start = time.perf_counter()
        s.sendall(FETCH_CONFIG)  # as a client does: the channel map first, then the requests
        _recv_frame(s)

        def read() -> None:
            while len(got) < len(payload):  # each response is as long as its request
                got.extend(s.recv(1 << 20))

        reader = threading.Thread(target=read)
        reader.start()
        s.sendall(payload)
        reader.join()
        forwarded = time.perf_counter()
    payload = FETCH_CONFIG + payload
    got[:0] = b"sr1-\x18" + b"200" * 24 + b"-ss1"
    stdout = _stop(rec)
    finished = time.perf_counter()
    upstream.terminate()
    upstream.wait()
    streams = _streams(out)
    conn = max(c for c, _ in streams)  # the benchmark's connection (the port probe is #1)
    lost = streams.get((conn, "c2s")) != payload or streams.get((conn, "s2c")) != bytes(got)
    m = re.search(r"c2s ([\d,]+) frames .*; s2c ([\d,]+) frames", stdout)  # counts as said: 200,001
    recorded = _count(m.group(1)) + _count(m.group(2)) if m else 0
    frames = 2 * (PIPELINE_FRAMES + 1)
    return {"frames": frames, "recorded_frames": recorded, "lost": float(lost or recorded != frames),
            "forwarding_fps": frames / (forwarded - start), "recorded_fps": frames / (finished - start),
            "size": out.stat().st_size}


def _count(said: str) -> int:
    """A count as the closing summary says it ('200,001')."""
    return int(said.replace(",", ""))


class _Sink:
    """A server that reads and discards, and notes when the last of ``size`` bytes came."""

    def __init__(self, size: int) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.size = size
        self.received = 0
        self.last = 0.0
        self._thread = threading.Thread(target=self._discard, daemon=True)
        self._thread.start()

    def _discard(self) -> None:
        while self.received < self.size:  # the port probe first, then the benchmark's connection
            conn, _ = self.server.accept()
            with conn:
                while data := conn.recv(1 << 20):
                    self.received += len(data)
                    if self.received >= self.size:
                        self.last = time.perf_counter()
                        return

    def wait(self) -> None:
        self._thread.join(600)
        self.server.close()


def _one_way_run(tmp: Path, name: str, payload: bytes, *options: str) -> tuple[_Sink, float, float, str, bytes | None]:
    """``payload`` sent through ``whiztap record OPTIONS`` to a discarding server:
    the sink, when the first byte was sent and the file finished, what record
    printed, and the client stream the recording holds."""
    sink = _Sink(len(payload))
    port = _free_port()
    out = tmp / name
    rec = _spawn([WHIZTAP, "record", "--listen", str(port), "--upstream", f"127.0.0.1:{sink.port}", "-o", str(out),
                  *options])
    try:
        _wait_port(port, rec)
        with socket.create_connection(("127.0.0.1", port)) as s:
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            start = time.perf_counter()
            s.sendall(payload)
            sink.wait()
    finally:
        stdout = _stop(rec)
        finished = time.perf_counter()
        sink.server.close()
    streams = _streams(out)
    conn = max(c for c, _ in streams)
    return sink, start, finished, stdout, streams.get((conn, "c2s"))


def one_way(tmp: Path) -> dict[str, float]:
    """The one-way mix: Normal Sends through ``whiztap record`` to a server that
    never speaks; frames/s from the first byte sent to the finished file, and
    whether the file holds every frame, unmasked."""
    payload = b"".join(b"rr1-%d--%d--0-ss1" % (i % 24, 2 + i % 1999) for i in range(ONE_WAY_FRAMES))
    sink, start, finished, stdout, recorded_stream = _one_way_run(tmp, "one-way.mcap", payload)
    m = re.search(r"c2s ([\d,]+) frames", stdout)
    recorded = _count(m.group(1)) if m else 0
    lost = sink.received != len(payload) or recorded_stream != payload or recorded != ONE_WAY_FRAMES
    return {"frames": ONE_WAY_FRAMES, "recorded_frames": recorded, "lost": float(lost),
            "recorded_fps": ONE_WAY_FRAMES / (finished - start)}


def middle_blast(tmp: Path) -> dict[str, float]:
    """The pipelined requests through the proxy in the middle (``--control 0``,
    no fault) to a server that discards them: frames/s to the last byte received."""
    payload = pipelined_requests()
    sink, start, _, _, recorded_stream = _one_way_run(tmp, "middle.mcap", payload, "-q", "--control", "0",
                                                      "--keep-secrets")  # no login: nothing to mask
    return {"frames": PIPELINE_FRAMES, "fps": PIPELINE_FRAMES / (sink.last - start) if sink.last else 0.0,
            "lost": float(sink.received != len(payload) or recorded_stream != payload)}


def soak(sim_port: int, tmp: Path) -> dict[str, object]:
    port = _free_port()
    rec = _spawn([WHIZTAP, "record", "-q", "--listen", str(port), "--upstream", f"127.0.0.1:{sim_port}",
                  "-o", str(tmp / "soak.mcap")])
    _wait_port(port, rec)
    stop = threading.Event()
    done = [0]

    def client() -> None:  # the same request/response client as the round trips
        with socket.create_connection(("127.0.0.1", port)) as s:
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            s.sendall(FETCH_CONFIG)
            _recv_frame(s)
            while not stop.is_set():
                s.sendall(REQUEST)
                _recv_frame(s)
                done[0] += 1

    thread = threading.Thread(target=client)
    thread.start()
    samples: list[tuple[float, int, int]] = []
    start = time.monotonic()
    while time.monotonic() - start < SOAK_S:
        time.sleep(1)
        samples.append((time.monotonic() - start, *_tree_rss(rec.pid)))
    stop.set()
    thread.join()
    _stop(rec)
    second_half = samples[len(samples) // 2:]
    xs = [s[0] for s in second_half]
    totals = [s[1] + s[2] for s in second_half]
    slope = statistics.linear_regression(xs, totals).slope * 60 if len(second_half) > 2 else 0.0
    return {"seconds": SOAK_S, "round_trips": done[0], "proxy_kib": (samples[0][1], samples[-1][1]),
            "writer_kib": (samples[0][2], samples[-1][2]), "max_total_kib": max(s[1] + s[2] for s in samples),
            "slope_kib_per_min": slope}


def main() -> None:
    print("== recording proxy (bench_proxy) ==")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"{platform.platform()}")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        sim_port = _free_port()
        sim = _spawn([WHIZTAP, "sim", "--mode", "vpn", "--port", str(sim_port), "-q", "--camera", "none"])
        _wait_port(sim_port, sim)
        try:
            rates = round_trip_comparison(sim_port, tmp)
            direct = rates["direct"]
            for name, rate in rates.items():
                print(f"round trips/s {name:18} {rate:9,.0f}   {rate / direct:.2f} x direct")
            record = rates["whiztap record"]
            print(f"RATIO round trips {MIDDLE} / whiztap record: {rates[MIDDLE] / record:.2f} "
                  f"(what the middle costs with no fault)")
            peers = (("socat", f"target >= {TARGET_SOCAT_RATIO}"), ("mitmdump", "the peer a user would pick"))
            for peer, target in peers:
                if peer in rates:
                    print(f"RATIO round trips whiztap record / {peer}: {record / rates[peer]:.2f} ({target})")
                else:
                    print(f"RATIO round trips whiztap record / {peer}: not measured ({peer} is not installed)")
            p = pipelined(tmp)
            print(f"pipelined: {p['frames']:,} frames (requests and responses; 1 request in {BAD_EVERY} breaks "
                  f"rules, as its answer does) through whiztap record: forwarded at {p['forwarding_fps']:,.0f} "
                  f"frames/s; {p['recorded_frames']:,} frames in the recording, "
                  f"{'SOME LOST' if p['lost'] else 'nothing lost'}; {p['size'] / 1e6:.1f} MB")
            print(f"FRAMES/S pipelined recording, first byte to finished file: {p['recorded_fps']:,.0f} "
                  f"(target >= {TARGET_PIPELINED_FPS:,})")
            w = one_way(tmp)
            print(f"pipelined, one way: {w['frames']:,} Normal Sends through whiztap record to a server that never "
                  f"speaks: {w['recorded_frames']:,} frames in the recording, "
                  f"{'SOME LOST OR MASKED' if w['lost'] else 'every one, as sent'}; "
                  f"{w['recorded_fps']:,.0f} frames/s first byte to finished file")
            b = middle_blast(tmp)
            print(f"FRAMES/S pipelined in the middle: {b['frames']:,} requests through {MIDDLE} (no fault) to "
                  f"a discarding server, first byte sent to last byte received: {b['fps']:,.0f}; "
                  f"{'SOME LOST' if b['lost'] else 'nothing lost, every byte recorded'}")
            s = soak(sim_port, tmp)
            print(f"memory over {s['seconds']:.0f} s of round trips ({s['round_trips']:,}): resident size after 1 s "
                  f"-> at the end: proxy {s['proxy_kib'][0]:,} -> {s['proxy_kib'][1]:,} KiB, writer "
                  f"{s['writer_kib'][0]:,} -> {s['writer_kib'][1]:,} KiB; both at most {s['max_total_kib']:,} KiB; "
                  f"trend over the second half {s['slope_kib_per_min']:+,.0f} KiB/min")
        finally:
            _stop(sim)


if __name__ == "__main__":
    main()
