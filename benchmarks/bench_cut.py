"""`whiztap cut` on the million-frame benchmark recording (bench_analyze's
pipelined file, cached): items per second of the whole command, which reads
the recording twice (the session model to choose, then the copy).

The recording has one connection, so the cut keeps it all: the worst case,
every message copied.  CPU time of one process, best of three.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from benchmarks.bench_analyze import FRAMES, READ, least_cpu, recording


def _cut_seconds(path: Path, out: Path) -> float:
    from whiztap.sniffer.cli.cut import cut_command

    return least_cpu(cut_command, [str(path), "-o", str(out), "--conn", "1"], out, 3)


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
