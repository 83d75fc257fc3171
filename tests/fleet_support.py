"""A small fleet of recordings for the fleet tests, a Dask cluster in
processes of its own, and a slow analysis task (so that a worker can be
killed in the middle of one).

The fleet's recordings are the samples' traffic, re-recorded by the real
Recorder on other days with the metadata ``whiztap record --meta`` writes
(robot, firmware); one of them was made with the proxy in the middle.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from whiztap.analyzer.cli.reading import scan_recording
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.traffic import (
    Action,
    Cause,
    Data,
    Delivered,
    Intervention,
    RecordingStarted,
    RecordingStopped,
    Source,
)
from whiztap.sniffer.record.metadata import base_metadata
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile

REPO = Path(__file__).resolve().parent.parent
SAMPLES = REPO / "samples"
DAY_NS = 86_400 * 1_000_000_000
MARCH_1 = 1_772_323_200 * 1_000_000_000  # 2026-03-01 00:00 UTC
HOUR_NS = 3_600 * 1_000_000_000

# (file, sample, day, robot, firmware, made in the middle); robot None: a recording without --meta
FLEET = [
    ("r1-d1.mcap", "clean-winsock", 0, "r1", "1.0", False),
    ("r1-d2.mcap", "violations", 1, "r1", "1.0", False),
    ("r2-d1.mcap", "vpn", 0, "r2", "1.1", False),
    ("r2-d2.mcap", "clean-winsock", 1, "r2", "1.1", True),
    ("r3-d3.mcap", "violations", 2, "r3", "1.1", False),
    ("bare-d3.mcap", "failed-password", 2, None, None, False),
]


def write_fleet(folder: Path) -> list[Path]:
    """The fleet's recordings in ``folder``, in FLEET's order."""
    paths = []
    for name, sample, day, robot, firmware, middle in FLEET:
        meta = {"robot": robot, "firmware": firmware} if robot else {}
        path = folder / name
        rerecord(SAMPLES / f"{sample}.mcap", path, MARCH_1 + day * DAY_NS + 9 * HOUR_NS, meta, middle)
        paths.append(path)
    return paths


def rerecord(sample: Path, path: Path, t0: int, meta: dict[str, str], middle: bool = False) -> None:
    """A sample's traffic recorded again from ``t0``, with ``meta`` in its
    metadata.  ``middle``: as the proxy in the middle would have recorded it,
    each read also delivered, but for one answer it dropped."""
    events = [e for e in scan_recording(sample) if type(e) not in (RecordingStarted, RecordingStopped)]
    shift = t0 - events[0].t_ns
    extra = {"middle": "yes", "faults": "[]", "seed": ""} if middle else {}
    metadata = base_metadata("proxy", False, "dev-sum", t0, user=meta, listen="127.0.0.1:6000",
                             upstream="127.0.0.1:5000", **extra)
    recording = RecordingFile(str(path) + ".tmp", metadata)
    recorder = Recorder(recording)
    recorder.start(t0)
    answers = 0
    for event in events:
        event = event._replace(t_ns=event.t_ns + shift) if isinstance(event, tuple) else _shifted(event, shift)
        recorder.receive(event)
        if middle and type(event) is Data:
            answers += event.direction is Direction.S2C
            if answers == 6 and event.direction is Direction.S2C:  # the proxy dropped this read of the server's
                recorder.receive(Intervention(event.conn, event.t_ns, Direction.S2C, Action.DROP,
                                              Cause(Source.FAULT, "f1", "drop dir:s2c every:6"), event.data, b""))
            else:
                recorder.receive(Delivered(event.conn, event.direction, event.t_ns, event.data))
        recorder.tick(event.t_ns)
    recorder.stop(events[-1].t_ns + shift + 1)
    for written in recording.finished:
        os.replace(written, path)


def _shifted(event, shift: int):
    from dataclasses import replace

    return replace(event, t_ns=event.t_ns + shift)


# -- a Dask cluster in processes of its own ------------------------------------------------------

CLUSTER_SCRIPT = """
import json, sys
from distributed import LocalCluster
if __name__ == "__main__":
    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address=None)
    print(json.dumps({"address": cluster.scheduler_address}), flush=True)
    sys.stdin.read()  # until the test closes it
    cluster.close()
"""


class DaskCluster:
    """A LocalCluster (scheduler and two worker processes on 127.0.0.1) run by
    a process of its own, so that neither the scheduler nor the workers live
    in the test's process or in the command under test."""

    def __init__(self) -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", CLUSTER_SCRIPT], cwd=REPO, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline()
        if not line:
            self.proc.kill()
            raise RuntimeError("the Dask cluster did not start")
        self.address = json.loads(line)["address"]

    def close(self) -> None:
        self.proc.stdin.close()
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


# -- a task slow enough to be killed in the middle of ---------------------------------------------

SLOW_S = 1.5  # each file's task sleeps this long before analysing it


def slow_analysis(args: tuple):
    """``analyze``'s own task, after a pause; each attempt leaves a file
    ``started-LABEL-PID`` beside the recording (and ``done-LABEL-PID`` when it
    returns), so a test sees which worker process is in the middle of which file."""
    from whiztap.analyzer.cli.analyze import _analyse_in_worker

    recording, label = args[0], args[-1]
    marks = Path(recording.parts[0]).parent / "attempts"
    marks.mkdir(exist_ok=True)
    (marks / f"started-{Path(label).name}-{os.getpid()}").touch()
    time.sleep(SLOW_S)
    result = _analyse_in_worker(args)
    (marks / f"done-{Path(label).name}-{os.getpid()}").touch()
    return result
