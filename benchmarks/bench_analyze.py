"""`whiztap analyze` end to end on a recording of a million frames.

The recording is written once (cached in the system's temp folder, named after
a digest of the code that writes recordings) by the real
Recorder and RecordingFile, from the same mixed session bench_core frames: a
pipelined client whose reads hold many frames.  A second, lockstep-shaped file
has one frame per read, the worst case for the per-read cost.  Throughput is
CPU time of one process (time.process_time), best of three; memory is the peak
resident size of a fresh process analysing half the file and the whole file.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from analyzer.session import Direction
from benchmarks.bench_core import mixed_session

FRAMES = int(os.environ.get("WHIZTAP_BENCH_FRAMES", 1_000_000))
READ = 16 * 1024  # bytes per read in the pipelined recording


def _write(path: Path, blocks: list[tuple[bytes, bytes]], read_size: int | None) -> None:
    from analyzer.recording import metadata_record
    from sniffer.recorder import Recorder
    from sniffer.writer import RecordingFile

    part = Path(str(path) + ".tmp")
    recording = RecordingFile(str(part), metadata_record(source="benchmark"))
    recorder = Recorder(recording)
    t = 1_700_000_000_000_000_000
    recorder.start(t)
    recorder.opened(1, t, "127.0.0.1:40000", "127.0.0.1:5000")
    for client, server in blocks:
        for direction, data in ((Direction.C2S, client), (Direction.S2C, server)):
            if read_size is None:  # one frame per read
                pieces = [p + b"-ss1" for p in data.split(b"-ss1")[:-1]]
            else:
                pieces = [data[i:i + read_size] for i in range(0, len(data), read_size)]
            for piece in pieces:
                t += 20_000
                recorder.data(1, direction, t, piece)
        recorder.tick(t)
    recorder.closed(1, t, "client")
    recorder.stop(t)
    for written in recording.finished:
        os.replace(written, path)


def _writer_digest() -> str:
    """Changes whenever the code that lays out a recording does."""
    import hashlib

    import analyzer.recording
    import sniffer.mcapwriter
    import sniffer.recorder
    import sniffer.writer

    digest = hashlib.sha256()
    for module in (analyzer.recording, sniffer.mcapwriter, sniffer.recorder, sniffer.writer):
        digest.update(Path(module.__file__).read_bytes())
    return digest.hexdigest()[:10]


def recording(name: str, frames: int, read_size: int | None) -> Path:
    path = Path(tempfile.gettempdir()) / f"whiztap-bench-{name}-{frames}-{_writer_digest()}.mcap"
    if not path.exists():
        _write(path, mixed_session(frames // 6), read_size)
    return path


def _analyse_seconds(path: Path) -> tuple[float, int]:
    from analyzer.analyze_cli import analyse_file
    from analyzer.throughput import tune_gc

    tune_gc()
    best = float("inf")
    frames = 0
    for _ in range(3):
        start = time.process_time()
        analysis = analyse_file(path, "dev-sum")
        best = min(best, time.process_time() - start)
        frames = analysis.frames
    return best, frames


def _peak_rss_mib(path: Path) -> float:
    code = ("import resource,sys; from pathlib import Path; from analyzer.analyze_cli import analyse_file;"
            "analyse_file(Path(sys.argv[1]), 'dev-sum');"
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
    out = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, check=True)
    return int(out.stdout) / 1024


def main() -> None:
    print("== analyze")
    for name, read_size, frames in (("pipelined", READ, FRAMES), ("lockstep", None, FRAMES // 5)):
        path = recording(name, frames, read_size)
        seconds, observed = _analyse_seconds(path)
        print(f"{name:10} {observed:>10,} items, {path.stat().st_size / 1e6:6.1f} MB: "
              f"{observed / seconds:>10,.0f} items/s")
    half = recording("pipelined", FRAMES // 2, READ)
    whole = recording("pipelined", FRAMES, READ)
    print(f"peak memory analysing {FRAMES // 2:,} frames: {_peak_rss_mib(half):.0f} MiB; "
          f"{FRAMES:,} frames: {_peak_rss_mib(whole):.0f} MiB")


if __name__ == "__main__":
    main()
