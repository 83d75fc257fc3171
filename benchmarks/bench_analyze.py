"""`whiztap analyze` end to end on a recording of a million frames.

The recording is written once (cached in the system's temp folder, named after
a digest of the code that writes recordings) by the real
Recorder and RecordingFile, from the same mixed session bench_core frames: a
pipelined client whose reads hold many frames.  A second, lockstep-shaped file
has one frame per read, the worst case for the per-read cost.  Throughput is
CPU time of one process (time.process_time), best of three.  Since this
machine's speed drifts by up to 2x from one minute to the next, mcap's own
Python reader takes turns with the analysis on a file of small messages (what
the issue's reference figure of 110,000 messages/s was quoted for), and the
ratio of the two is printed too.  Memory is the peak resident size of a fresh
process analysing half the file and the whole file.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import click

from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.traffic import Closed, Data, Opened

from benchmarks.bench_core import mixed_session

FRAMES = int(os.environ.get("WHIZTAP_BENCH_FRAMES", 1_000_000))
READ = 16 * 1024  # bytes per read in the pipelined recording


def _write(path: Path, blocks: list[tuple[bytes, bytes]], read_size: int | None) -> None:
    from whiztap.analyzer.recording.format import metadata_record
    from whiztap.sniffer.record.recorder import Recorder
    from whiztap.sniffer.record.writer import RecordingFile

    part = Path(str(path) + ".tmp")
    recording = RecordingFile(str(part), metadata_record(source="benchmark"))
    recorder = Recorder(recording)
    t = 1_700_000_000_000_000_000
    recorder.start(t)
    recorder.receive(Opened(1, t, "127.0.0.1:40000", "127.0.0.1:5000"))
    for client, server in blocks:
        for direction, data in ((Direction.C2S, client), (Direction.S2C, server)):
            if read_size is None:  # one frame per read
                pieces = [p + b"-ss1" for p in data.split(b"-ss1")[:-1]]
            else:
                pieces = [data[i:i + read_size] for i in range(0, len(data), read_size)]
            for piece in pieces:
                t += 20_000
                recorder.receive(Data(1, direction, t, piece))
        recorder.tick(t)
    recorder.receive(Closed(1, t, "client"))
    recorder.stop(t)
    for written in recording.finished:
        os.replace(written, path)


def _writer_digest() -> str:
    """Changes whenever the code that lays out a recording does."""
    import hashlib

    import whiztap.analyzer.recording.encode
    import whiztap.analyzer.recording.format
    import whiztap.analyzer.recording.mcap
    import whiztap.sniffer.record.recorder
    import whiztap.sniffer.record.writer

    digest = hashlib.sha256()
    for module in (whiztap.analyzer.recording.format, whiztap.analyzer.recording.encode,
                   whiztap.analyzer.recording.mcap, whiztap.sniffer.record.recorder, whiztap.sniffer.record.writer):
        digest.update(Path(module.__file__).read_bytes())
    return digest.hexdigest()[:10]


def least_cpu(command: click.Command, args: list[str], out: Path, rounds: int) -> float:
    """The least CPU time of ``rounds`` runs of a whiztap click ``command`` in
    this process, ``out`` (what it writes) removed before each run."""
    best = float("inf")
    for _ in range(rounds):
        out.unlink(missing_ok=True)
        began = time.process_time()
        try:
            command.main(args, standalone_mode=False)
        finally:
            best = min(best, time.process_time() - began)
    return best


def recording(name: str, frames: int, read_size: int | None) -> Path:
    path = Path(tempfile.gettempdir()) / f"whiztap-bench-{name}-{frames}-{_writer_digest()}.mcap"
    if not path.exists():
        _write(path, mixed_session(frames // 6), read_size)
    return path


REFERENCE_MESSAGES = 200_000
REFERENCE_RATE = 110_000  # what the issue measured the mcap reader at, messages/s


def _reference_file() -> Path:
    """Small messages (16-byte frames, one message each) written by mcap's own
    writer: what the mcap reader's speed was quoted for."""
    path = Path(tempfile.gettempdir()) / f"whiztap-bench-mcap-reference-{REFERENCE_MESSAGES}.mcap"
    if not path.exists():
        from mcap.writer import Writer

        part = Path(str(path) + ".tmp")
        with open(part, "wb") as f:
            writer = Writer(f)
            writer.start()
            schema = writer.register_schema("frame", "jsonschema", b"{}")
            channel = writer.register_channel("/frames", "json", schema)
            for i in range(REFERENCE_MESSAGES):
                writer.add_message(channel, i, b"rr1-%02d--0--0-ss1" % (i % 24), i)
            writer.finish()
        os.replace(part, path)
    return path


def _analyse_seconds(path: Path) -> tuple[float, int]:
    from whiztap.analyzer.cli.analyze import analyse_file

    start = time.process_time()
    analysis = analyse_file(path, "dev-sum")
    return time.process_time() - start, analysis.frames


def _reader_seconds(path: Path) -> float:
    from mcap.reader import make_reader

    start = time.process_time()
    with open(path, "rb") as f:
        count = sum(1 for _ in make_reader(f).iter_messages())
    assert count == REFERENCE_MESSAGES
    return time.process_time() - start


def _side_by_side(path: Path) -> tuple[float, int, float]:
    """Best of three, analysis and the mcap reader taking turns, so both see the
    same machine (its speed drifts by up to 2x here)."""
    from whiztap.analyzer.analysis.throughput import tune_gc

    tune_gc()
    reference = _reference_file()
    analyse = reader = float("inf")
    frames = 0
    for _ in range(3):
        seconds, frames = _analyse_seconds(path)
        analyse = min(analyse, seconds)
        reader = min(reader, _reader_seconds(reference))
    return analyse, frames, REFERENCE_MESSAGES / reader


def _peak_rss_mib(path: Path) -> float:
    code = ("import resource,sys; from pathlib import Path; from whiztap.analyzer.cli.analyze import analyse_file;"
            "analyse_file(Path(sys.argv[1]), 'dev-sum');"
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
    out = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, check=True)
    return int(out.stdout) / 1024


def main() -> None:
    print("== analyze")
    for name, read_size, frames in (("pipelined", READ, FRAMES), ("lockstep", None, FRAMES // 5)):
        path = recording(name, frames, read_size)
        seconds, observed, reader_rate = _side_by_side(path)
        rate = observed / seconds
        print(f"{name:10} {observed:>10,} items, {path.stat().st_size / 1e6:6.1f} MB: {rate:>10,.0f} items/s; "
              f"mcap's reader meanwhile {reader_rate:,.0f} messages/s: {rate / reader_rate:.2f}x it "
              f"(= {rate / reader_rate * REFERENCE_RATE:,.0f}/s where it reads {REFERENCE_RATE:,})")
    half = recording("pipelined", FRAMES // 2, READ)
    whole = recording("pipelined", FRAMES, READ)
    print(f"peak memory analysing {FRAMES // 2:,} frames: {_peak_rss_mib(half):.0f} MiB; "
          f"{FRAMES:,} frames: {_peak_rss_mib(whole):.0f} MiB")


if __name__ == "__main__":
    main()
