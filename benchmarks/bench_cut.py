"""`whiztap cut` on the million-frame benchmark recording (bench_analyze's
pipelined file, cached): items per second of the whole command, which reads
the recording twice (the session model to choose, then the copy).

The recording has one connection, so the cut keeps it all: the worst case,
every message copied.  CPU time of one process, best of three.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from benchmarks.bench_analyze import FRAMES, READ, recording


def _cut_seconds(path: Path, out: Path) -> float:
    from whiztap.sniffer.cli.cut import cut_command

    best = float("inf")
    for _ in range(3):
        out.unlink(missing_ok=True)
        began = time.process_time()
        try:
            cut_command.main([str(path), "-o", str(out), "--conn", "1"], standalone_mode=False)
        finally:
            best = min(best, time.process_time() - began)
    return best


def main() -> None:
    path = recording("pipelined", FRAMES, READ)
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "cut.mcap"
        seconds = _cut_seconds(path, out)
        size = out.stat().st_size
    print(f"cut: {FRAMES:,} items ({path.stat().st_size / 2**20:.0f} MiB -> {size / 2**20:.0f} MiB) "
          f"in {seconds:.2f} s CPU: {FRAMES / seconds:,.0f} items/s")


if __name__ == "__main__":
    main()
