"""`whiztap analyze --dask`: files per second with 1 and 2 Dask workers.

A fleet of ``FILES`` (default 16) recordings of ``FRAMES`` items each
(default 100,000: the pipelined session bench_analyze writes, cached in the
temp folder and copied under the fleet's names) is analysed by ``analyze``'s
own code path for a cluster (``_analyse_all`` with a scheduler address: the
client's connection, the worker check, one task per file, the in-order
merge) on a LocalCluster of 1 and one of 2 worker processes (one thread
each) on 127.0.0.1.  Both clusters are up at once (an idle one costs
nothing), so that runs on 1 and 2 workers can take turns and see the same
machine; starting them is not timed (a fleet's cluster is up before the
run), and each first analyses one file per worker, so every worker has
imported whiztap.  Wall-clock time (time.perf_counter) of a whole run, best
of ``ROUNDS`` (5) turns; files/s is FILES over it, and the ratio is 2
workers' files/s over 1 worker's.  For reference, the same files through
``analyze -j 1`` and ``-j 2`` (local processes, no cluster), also taking
turns.  The machine has as many cores as ``os.cpu_count()`` says; a ratio
near 2 needs two of them idle, and the process that merges the results
shares them.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from pathlib import Path

from benchmarks.bench_analyze import READ, recording

FILES = int(os.environ.get("WHIZTAP_BENCH_FLEET_FILES", 16))
FRAMES = int(os.environ.get("WHIZTAP_BENCH_FLEET_FRAMES", 100_000))
ROUNDS = 5


def _fleet(folder: Path) -> list:
    """FILES copies of one recording, as ``analyze`` finds them."""
    from whiztap.analyzer.recording.sets import find_recordings

    source = recording("pipelined", FRAMES, READ)
    for i in range(FILES):
        shutil.copy(source, folder / f"robot-{i:03d}.mcap")
    return find_recordings([str(folder)])


def _seconds(found: list, jobs: int | None, dask: str | None) -> tuple[float, int]:
    """Wall-clock seconds of one run, and the items it judged."""
    from whiztap.analyzer.cli.analyze import _analyse_all
    from whiztap.analyzer.cli.progress import ByteProgress
    from whiztap.analyzer.protocol.session import Limits

    start = time.perf_counter()
    with ByteProgress([], enabled=False) as progress:
        analysis, unreadable = _analyse_all(found, "dev-sum", Limits(), jobs, progress, dask)
    seconds = time.perf_counter() - start
    assert not unreadable and analysis is not None
    return seconds, analysis.frames


def _clusters(found: list) -> dict[int, float]:
    """Best seconds on a LocalCluster of 1 and one of 2 worker processes, both
    up at once and warmed up, taking turns ROUNDS times (so that both see the
    same machine: its speed drifts from one minute to the next)."""
    from distributed import LocalCluster

    # a scheduler serves HTTP even without a dashboard: on any free port, not on 8787 twice
    clusters = {n: LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                                dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR) for n in (1, 2)}
    try:
        for n, cluster in clusters.items():
            _seconds(found[:n], None, cluster.scheduler_address)
        best = {n: float("inf") for n in clusters}
        for _ in range(ROUNDS):
            for n, cluster in clusters.items():
                best[n] = min(best[n], _seconds(found, None, cluster.scheduler_address)[0])
        return best
    finally:
        for cluster in clusters.values():
            cluster.close()


def main() -> None:
    from whiztap.analyzer.analysis.throughput import tune_gc

    tune_gc()  # as the command does, for the -j 1 reference run in this process
    print(f"== fleet: {FILES} recordings of {FRAMES:,} items, {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory(prefix="whiztap-bench-fleet-") as folder:
        found = _fleet(Path(folder))
        frames = _seconds(found[:1], 1, None)[1] * FILES
        best = _clusters(found)
        for workers, seconds in best.items():
            print(f"--dask, {workers} worker{'s' * (workers != 1)}: {seconds:6.2f} s, {FILES / seconds:6.2f} files/s "
                  f"({frames / seconds:,.0f} items/s)")
        print(f"ratio 2 workers / 1 worker: {best[1] / best[2]:.2f}x")
        local = {jobs: float("inf") for jobs in (1, 2)}
        for _ in range(ROUNDS):
            for jobs in local:
                local[jobs] = min(local[jobs], _seconds(found, jobs, None)[0])
        for jobs, seconds in local.items():
            print(f"-j {jobs} (local processes, reference): {seconds:6.2f} s, {FILES / seconds:6.2f} files/s")
        print(f"ratio -j 2 / -j 1: {local[1] / local[2]:.2f}x")


if __name__ == "__main__":
    main()
