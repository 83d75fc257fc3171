"""Shadow traffic: round trips through ``whiztap record`` with ``--mirror`` and without, side by side.

Processes as a user runs them: the primary (``whiztap sim --mode vpn``),
``whiztap record -q`` with and without ``--mirror``, and a blocking-socket
client in this process doing one Sensor Request, waiting for its answer, and
again, for ``WHIZTAP_BENCH_RT_S`` seconds (default 3) per run.  The mirror is
bench_proxy's responder (every request answered at once, reading 0): a
second simulator would take a good part of one of this machine's two cores
for itself, which is the mirror's cost, not whiztap's; and its answers all
differ from the simulator's, so every exchange is a difference to pair, write
and report: the pairing's worst case.  The two runs take turns ``ROUNDS``
times against the same servers (the mirror runs in both, idle in the run
without it) and the medians count, with the CPU time the proxy and its writer
process spent per round trip.  The target is the ratio in the same run: with
a mirror at least 0.9 of without.
"""

from __future__ import annotations

import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.bench_proxy import RESPONDER, RT_S, WHIZTAP, _free_port, _round_trips, _spawn, _stop, _wait_port

ROUNDS = 5
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


def _through_record(sim_port: int, out: Path, *more: str) -> tuple[float, float, float]:
    """Round trips/s through one ``whiztap record`` run, and the CPU microseconds its proxy
    and its writer spent per round trip meanwhile."""
    port = _free_port()
    rec = _spawn([WHIZTAP, "record", "-q", "--listen", str(port), "--upstream", f"127.0.0.1:{sim_port}",
                  "-o", str(out), "--force", *more])
    _wait_port(port, rec)
    before = _cpu_s(rec.pid)
    start = time.perf_counter()
    rate = _round_trips(port, RT_S)
    trips = rate * (time.perf_counter() - start)
    after = _cpu_s(rec.pid)
    _stop(rec)
    return rate, (after[0] - before[0]) / trips * 1e6, (after[1] - before[1]) / trips * 1e6


def comparison(primary: int, mirror: int, tmp: Path) -> dict[str, tuple[float, float, float]]:
    """Per run: the median round trips/s, and the proxy's and the writer's CPU µs per round trip."""
    runs: dict[str, list[tuple[float, float, float]]] = {"without": [], "with": []}
    for _ in range(ROUNDS):
        runs["without"].append(_through_record(primary, tmp / "plain.mcap"))
        runs["with"].append(_through_record(primary, tmp / "mirror.mcap", "--mirror", f"127.0.0.1:{mirror}"))
    return {name: tuple(statistics.median(r[i] for r in values) for i in range(3))  # type: ignore[misc]
            for name, values in runs.items()}


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
