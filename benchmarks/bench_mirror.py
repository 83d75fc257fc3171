"""Shadow traffic: round trips through ``whiztap record`` with ``--mirror`` and without, side by side.

Processes as a user runs them: the primary (``whiztap sim --mode vpn``), the
mirror (a second ``whiztap sim --mode vpn`` with another seed, so its
readings differ and every answer is a difference to pair and record), ``whiztap
record -q`` with and without ``--mirror``, and a blocking-socket client in this
process doing one Sensor Request, waiting for its answer, and again, for
``WHIZTAP_BENCH_RT_S`` seconds (default 3) per run.  The two runs take turns
``ROUNDS`` times against the same two servers (the mirror runs in both, idle
in the run without it) and the medians count.  The target is the ratio in the
same run: with a mirror at least 0.9 of without.
"""

from __future__ import annotations

import os
import platform
import statistics
import tempfile
from pathlib import Path

from benchmarks.bench_proxy import RT_S, WHIZTAP, _free_port, _round_trips, _spawn, _stop, _wait_port

ROUNDS = 3
TARGET_RATIO = 0.9


def _through_record(sim_port: int, out: Path, *more: str) -> tuple[float, str]:
    """Round trips/s through one ``whiztap record`` run, and what it said at the end."""
    port = _free_port()
    rec = _spawn([WHIZTAP, "record", "-q", "--listen", str(port), "--upstream", f"127.0.0.1:{sim_port}",
                  "-o", str(out), "--force", *more])
    _wait_port(port, rec)
    rate = _round_trips(port, RT_S)
    return rate, _stop(rec)


def comparison(primary: int, mirror: int, tmp: Path) -> dict[str, float]:
    rates: dict[str, list[float]] = {"without": [], "with": []}
    for _ in range(ROUNDS):
        rates["without"].append(_through_record(primary, tmp / "plain.mcap")[0])
        rates["with"].append(_through_record(primary, tmp / "mirror.mcap", "--mirror", f"127.0.0.1:{mirror}")[0])
    return {name: statistics.median(values) for name, values in rates.items()}


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
        servers = [_spawn([WHIZTAP, "sim", "--mode", "vpn", "--port", str(port), "-q", "--camera", "none",
                           "--seed", str(seed)]) for port, seed in ((primary_port, 1), (mirror_port, 2))]
        try:
            for port, server in zip((primary_port, mirror_port), servers):
                _wait_port(port, server)
            rates = comparison(primary_port, mirror_port, tmp)
        finally:
            for server in servers:
                _stop(server)
        print(f"round trips/s through whiztap record, no mirror:   {rates['without']:9,.0f}")
        print(f"round trips/s through whiztap record, with mirror: {rates['with']:9,.0f}   "
              f"({_mirror_summary(tmp / 'mirror.mcap')})")
        print(f"RATIO round trips with --mirror / without: {rates['with'] / rates['without']:.2f} "
              f"(target >= {TARGET_RATIO})")


if __name__ == "__main__":
    main()
