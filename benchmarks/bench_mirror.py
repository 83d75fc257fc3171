"""Shadow traffic: round trips through ``whiztap record`` with ``--mirror`` and without, side by side.

Processes as a user runs them: the primary (``whiztap sim --mode vpn``), two
``whiztap record -q`` in front of it, one with ``--mirror`` and one without,
and a blocking-socket client in this process doing one Sensor Request,
waiting for its answer, and again.  The mirror is bench_proxy's responder
(every request answered at once, reading 0): a second simulator would take a
good part of one of this machine's two cores for itself, which is the
mirror's cost, not whiztap's; and its answers all differ from the
simulator's, so every exchange is a difference to pair, write and report:
the pairing's worst case.

Both recorders run at once, and the client takes turns between them in
``SLICE_S`` slices (whichever goes first alternates; ``SETTLE_S`` between
slices, untimed, so that what a slice left its writer process to do is not
done in the other recorder's slice), ``WHIZTAP_BENCH_RT_S`` (default 3) times
``ROUNDS`` seconds each: on a machine others share, both see the same load
(runs one after the other each saw its own share of it, and gave ratios from
0.6 to 1.5).  Per recorder: round trips/s over its
slices, and the CPU time its proxy and its writer process spent per round
trip.  The target is the ratio: with a mirror at least 0.9 of without.
"""

from __future__ import annotations

import os
import platform
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.bench_proxy import (
    FETCH_CONFIG,
    REQUEST,
    RESPONDER,
    RT_S,
    WHIZTAP,
    _free_port,
    _recv_frame,
    _spawn,
    _stop,
    _wait_port,
)

ROUNDS = 5  # RT_S seconds of round trips per recorder, this many times over
SLICE_S = 0.5
SETTLE_S = 0.1
TARGET_RATIO = 0.9
TICKS = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> tuple[float, float]:
    """CPU seconds (user + system) the proxy and its writer process have used."""
    def one(p: int) -> float:
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return 0.0
        return (int(fields[11]) + int(fields[12])) / TICKS

    children = Path(f"/proc/{pid}/task/{pid}/children")
    kids = [int(c) for c in children.read_text().split()] if children.exists() else []
    return one(pid), sum(one(k) for k in kids)


def _start_record(sim_port: int, out: Path, *more: str) -> tuple[subprocess.Popen, socket.socket]:
    """A ``whiztap record`` run, and a client connection through it past its Fetch Configuration."""
    port = _free_port()
    rec = _spawn([WHIZTAP, "record", "-q", "--listen", str(port), "--upstream", f"127.0.0.1:{sim_port}",
                  "-o", str(out), "--force", *more])
    _wait_port(port, rec)
    sock = socket.create_connection(("127.0.0.1", port))
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.sendall(FETCH_CONFIG)
    _recv_frame(sock)
    return rec, sock


def _slice(sock: socket.socket, seconds: float) -> int:
    """Round trips for ``seconds`` on one connection: how many."""
    n = 0
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        for _ in range(20):
            sock.sendall(REQUEST)
            _recv_frame(sock)
        n += 20
    return n


def comparison(primary: int, mirror: int, tmp: Path) -> dict[str, tuple[float, float, float]]:
    """Both recorders run at once, the client taking turns between them in slices of ``SLICE_S``
    (whichever goes first alternates), so both see the same load from the rest of the machine;
    per recorder, round trips/s over its slices, and its proxy's and writer's CPU µs per round trip."""
    runs = {"without": _start_record(primary, tmp / "plain.mcap"),
            "with": _start_record(primary, tmp / "mirror.mcap", "--mirror", f"127.0.0.1:{mirror}")}
    trips = dict.fromkeys(runs, 0)
    spent = dict.fromkeys(runs, 0.0)
    before = {name: _cpu_s(rec.pid) for name, (rec, _) in runs.items()}
    order = list(runs)
    for i in range(int(RT_S * ROUNDS / SLICE_S)):
        for name in order if i % 2 else order[::-1]:
            start = time.perf_counter()
            trips[name] += _slice(runs[name][1], SLICE_S)
            spent[name] += time.perf_counter() - start
            time.sleep(SETTLE_S)  # what the slice left its writer to do is done in no other's slice
    after = {name: _cpu_s(rec.pid) for name, (rec, _) in runs.items()}
    for rec, sock in runs.values():
        sock.close()
        _stop(rec)
    return {name: (trips[name] / spent[name], (after[name][0] - before[name][0]) / trips[name] * 1e6,
                   (after[name][1] - before[name][1]) / trips[name] * 1e6) for name in runs}


def _mirror_summary(path: Path) -> str:
    """How many differences the last run with a mirror recorded (read back)."""
    from whiztap.analyzer.recording.format import TOPIC_MIRROR_DIFFERENCES, TOPIC_MIRROR_S2C
    from whiztap.analyzer.recording.scan import RecordingScan

    counts = {TOPIC_MIRROR_S2C: 0, TOPIC_MIRROR_DIFFERENCES: 0}
    with open(path, "rb") as f:
        for topic, _t, _record in RecordingScan(f, tuple(counts)).messages():
            counts[topic] += 1
    return (f"{counts[TOPIC_MIRROR_S2C]:,} mirror reads and {counts[TOPIC_MIRROR_DIFFERENCES]:,} differences "
            "in its recording")


def main() -> None:
    print("== shadow traffic: record --mirror (bench_mirror) ==")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        primary_port, mirror_port = _free_port(), _free_port()
        servers = [_spawn([WHIZTAP, "sim", "--mode", "vpn", "--port", str(primary_port), "-q", "--camera", "none"]),
                   _spawn([sys.executable, "-c", RESPONDER, str(mirror_port)])]
        try:
            for port, server in zip((primary_port, mirror_port), servers):
                _wait_port(port, server)
            rates = comparison(primary_port, mirror_port, tmp)
        finally:
            for server in servers:
                _stop(server)
        for name, label in (("without", "no mirror:  "), ("with", "with mirror:")):
            rate, proxy_us, writer_us = rates[name]
            print(f"round trips/s through whiztap record, {label} {rate:9,.0f}   CPU per round trip: proxy "
                  f"{proxy_us:5.1f} µs, writer {writer_us:5.1f} µs")
        print(f"  ({_mirror_summary(tmp / 'mirror.mcap')})")
        print(f"RATIO round trips with --mirror / without: {rates['with'][0] / rates['without'][0]:.2f} "
              f"(target >= {TARGET_RATIO})")


if __name__ == "__main__":
    main()
