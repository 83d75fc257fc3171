"""`whiztap probe server`: the whole catalogue against the simulator, in both modes.

The command as a user runs it, a process of its own against a `whiztap sim`
process (each in Winsock and in VPN mode), ``ROUNDS`` times, with and
without ``--record``: wall time of the whole run (the interpreter's start,
the discovery, every case, the report) and cases per second.  The issue's
target is under 30 s for the whole catalogue.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROUNDS = 3
WHIZTAP = str(Path(sys.executable).with_name("whiztap"))
PASSWORD = "bench-pw"
_LISTENING = re.compile(rb"listening on 127\.0\.0\.1:(\d+)")


def _sim(mode: str) -> tuple[subprocess.Popen, int]:
    proc = subprocess.Popen([WHIZTAP, "sim", "--port", "0", "--mode", mode, "--password", PASSWORD, "-q"],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    assert proc.stdout is not None
    found = _LISTENING.search(proc.stdout.readline())
    if found is None:
        proc.kill()
        raise RuntimeError("whiztap sim did not say where it listens")
    return proc, int(found[1])


def _probe(port: int, record: str | None) -> tuple[float, dict]:
    args = [WHIZTAP, "probe", "server", f"127.0.0.1:{port}", "-p", PASSWORD, "--format", "json", "-q"]
    if record is not None:
        args += ["--record", record]
    start = time.perf_counter()
    done = subprocess.run(args, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"probe server exited {done.returncode}: {done.stderr.strip()}")
    return seconds, json.loads(done.stdout)


def main() -> None:
    print("probe server: the whole catalogue against whiztap sim (wall time of the command, median of "
          f"{ROUNDS}; target < 30 s)")
    for mode in ("winsock", "vpn"):
        sim, port = _sim(mode)
        try:
            for recorded in (False, True):
                times, report = [], {}
                for _ in range(ROUNDS):
                    with tempfile.TemporaryDirectory() as tmp:
                        seconds, report = _probe(port, str(Path(tmp) / "rec") if recorded else None)
                    times.append(seconds)
                median = sorted(times)[len(times) // 2]
                ran = report["passed"] + report["failed"]
                print(f"  {mode:7} {'--record' if recorded else 'no record':9}  {median:5.2f} s  "
                      f"{len(report['cases'])} cases ({ran} run, {report['skipped']} skipped, "
                      f"{report['failed']} failed)  {len(report['cases']) / median:5.1f} cases/s")
        finally:
            sim.terminate()
            sim.wait()


if __name__ == "__main__":
    main()
