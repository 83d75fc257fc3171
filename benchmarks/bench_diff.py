"""`whiztap diff` on the million-frame benchmark recording (bench_analyze's
pipelined file, cached) against a copy of itself: items per second of the
whole command, which reads both recordings through the session model and
pairs every exchange.

Equal recordings are the worst case for the pairing: every exchange is
compared, field by field, and none is skipped as missing.  CPU time of one
process, best of ``ROUNDS``; the peak resident size of the process is
printed too, since diff holds both recordings' exchanges at once.
"""

from __future__ import annotations

import os
import resource
import shutil
import tempfile
from pathlib import Path

from benchmarks.bench_analyze import FRAMES, READ, least_cpu, recording

ROUNDS = int(os.environ.get("WHIZTAP_BENCH_DIFF_ROUNDS", 2))


def _diff_seconds(a: Path, b: Path, out: Path) -> float:
    from whiztap.analyzer.cli.diff import diff_command

    return least_cpu(diff_command, [str(a), str(b), "-o", str(out)], out, ROUNDS)


def main() -> None:
    path = recording("pipelined", FRAMES, READ)
    with tempfile.TemporaryDirectory() as folder:
        copy = Path(folder) / "copy.mcap"
        shutil.copyfile(path, copy)
        out = Path(folder) / "diff.txt"
        seconds = _diff_seconds(path, copy, out)
        said = out.read_text().splitlines()[-1] if out.exists() else "(no report)"
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"diff: {FRAMES:,} items against a copy ({path.stat().st_size / 2**20:.0f} MiB each) in {seconds:.2f} s "
          f"CPU: {FRAMES / seconds:,.0f} items/s of A ({2 * FRAMES / seconds:,.0f} items/s read, both sides); "
          f"peak RSS {peak:,.0f} MiB; {said}")


if __name__ == "__main__":
    main()
