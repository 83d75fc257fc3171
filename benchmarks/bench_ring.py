"""``record --ring``: the flight recorder beside plain recording, in one run.

The load is bench_proxy's pipelined one: a Fetch Configuration, then
``WHIZTAP_BENCH_PIPELINE_FRAMES`` requests (default 200k; one in
``BAD_EVERY`` for channel 99, which breaks rules) written as fast as the
socket takes them through ``whiztap record`` to a responder that answers at
C speed, read back in parallel; then Ctrl-C, and the clock stops when the
command has exited (its files finished).  Requests and responses both count
as frames.

Two configurations take turns ``ROUNDS`` times and the median counts:

* plain: ``whiztap record -o F`` (every message compressed and written);
* ring: ``whiztap record -o F --ring RING --trigger PW-PAIR-UNSOLICITED``, a
  trigger this load never fires, so the window is all that is kept: the
  flight recorder's steady state.  ``RING`` is ``WHIZTAP_BENCH_RING``
  (default 64MB, less than the load's messages, so the ring fills and
  evicts);
* tiny: the same with the smallest ring (64kB): the writer's working memory
  without a ring to speak of, so ring - tiny is what the ring itself holds.

For each: frames/s (the target: ring / plain >= 0.95), and the most resident
memory of the proxy and of its writer process, sampled every 50 ms.  Then
one ring run whose trigger fires (``severity:error``, every tenth request)
shows what writing incidents costs: one long merged incident.
"""

from __future__ import annotations

import os
import re
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from benchmarks.bench_proxy import (
    FETCH_CONFIG,
    PIPELINE_FRAMES,
    RESPONDER,
    WHIZTAP,
    _free_port,
    _recv_frame,
    _spawn,
    _stop,
    _tree_rss,
    _wait_port,
    pipelined_requests,
)

RING = os.environ.get("WHIZTAP_BENCH_RING", "64MB")
ROUNDS = 3
TARGET_RATIO = 0.95
SAMPLE_S = 0.05
CONFIGS = {"plain": (), "ring": ("--ring", RING, "--trigger", "PW-PAIR-UNSOLICITED"),
           "tiny": ("--ring", "64kB", "--trigger", "PW-PAIR-UNSOLICITED")}
FIRING = ("--ring", RING, "--trigger", "severity:error", "--after", "1s")


def _run(tmp: Path, upstream_port: int, name: str, options: tuple[str, ...]) -> dict[str, float]:
    """One pipelined run through ``whiztap record OPTIONS``: frames/s, peak memory, what was recorded."""
    port = _free_port()
    out = tmp / f"{name}.mcap"
    rec = _spawn([WHIZTAP, "record", "--listen", str(port), "--upstream", f"127.0.0.1:{upstream_port}",
                  "-o", str(out), *options])
    _wait_port(port, rec)
    peak = [0, 0]
    sampling = threading.Event()

    def sample() -> None:
        while not sampling.wait(SAMPLE_S):
            proxy, writer = _tree_rss(rec.pid)
            peak[0], peak[1] = max(peak[0], proxy), max(peak[1], writer)

    sampler = threading.Thread(target=sample)
    sampler.start()
    payload = pipelined_requests()
    got = bytearray()
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        start = time.perf_counter()
        s.sendall(FETCH_CONFIG)
        _recv_frame(s)

        def read() -> None:
            while len(got) < len(payload):
                got.extend(s.recv(1 << 20))

        reader = threading.Thread(target=read)
        reader.start()
        s.sendall(payload)
        reader.join()
    stdout = _stop(rec)
    finished = time.perf_counter()
    sampling.set()
    sampler.join()
    m = re.search(r"c2s ([\d,]+) frames? .*; s2c ([\d,]+) frames?", stdout)
    seen = int(m.group(1).replace(",", "")) + int(m.group(2).replace(",", "")) if m else 0
    frames = 2 * (PIPELINE_FRAMES + 1)
    files = sorted(tmp.glob(f"{name}*.mcap"))
    size = sum(f.stat().st_size for f in files)
    for f in files:
        f.unlink()
    return {"fps": frames / (finished - start), "proxy_kib": peak[0], "writer_kib": peak[1],
            "seen": seen, "frames": frames, "files": len(files),
            "size": size, "forwarded": float(bytes(got) == payload.replace(b"rr1-", b"cr1-"))}


def main() -> None:
    print("== flight recorder (bench_ring) ==")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        upstream_port = _free_port()
        upstream = subprocess.Popen([sys.executable, "-c", RESPONDER, str(upstream_port)])
        _wait_port(upstream_port)
        try:
            runs: dict[str, list[dict[str, float]]] = {name: [] for name in CONFIGS}
            for _ in range(ROUNDS):
                for name, options in CONFIGS.items():
                    runs[name].append(_run(tmp, upstream_port, name, options))
            med = {name: {k: statistics.median(r[k] for r in rs) for k in rs[0]} for name, rs in runs.items()}
            for name, options in CONFIGS.items():
                r = med[name]
                print(f"{name:6} whiztap record {' '.join(options)}: {r['fps']:,.0f} frames/s first byte to exit; "
                      f"peak resident proxy {r['proxy_kib']:,.0f} KiB, writer {r['writer_kib']:,.0f} KiB; "
                      f"{r['seen']:,.0f} of {r['frames']:,.0f} frames seen by the recorder; "
                      f"{r['files']:.0f} file(s), {r['size'] / 1e6:.1f} MB; "
                      f"{'every answer forwarded' if r['forwarded'] else 'ANSWERS LOST'}")
            held = med["ring"]["writer_kib"] - med["tiny"]["writer_kib"]
            print(f"MEMORY the ring itself (writer with {RING} - writer with 64kB): {held:,.0f} KiB")
            ratio = med["ring"]["fps"] / med["plain"]["fps"]
            print(f"RATIO frames/s ring / plain: {ratio:.2f} (target >= {TARGET_RATIO}); medians of {ROUNDS} rounds")
            f = _run(tmp, upstream_port, "firing", FIRING)
            print(f"firing whiztap record {' '.join(FIRING)}: {f['fps']:,.0f} frames/s; peak resident proxy "
                  f"{f['proxy_kib']:,.0f} KiB, writer {f['writer_kib']:,.0f} KiB; {f['files']:.0f} incident file(s), "
                  f"{f['size'] / 1e6:.1f} MB")
        finally:
            upstream.terminate()
            upstream.wait()


if __name__ == "__main__":
    main()
