"""``analyze --dask`` on a real Dask cluster: a LocalCluster whose scheduler and
two workers are processes of their own on 127.0.0.1 (tests/fleet_support.py),
driven by the command as a user runs it.  The report is byte for byte the one
a run on this machine writes, in every format; a worker killed in the middle
of a file costs nothing: the task runs again elsewhere, and no file is counted
twice or lost."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from tests.cli_support import run_cli
from tests.fleet_support import SLOW_S, DaskCluster, slow_analysis, write_fleet
from whiztap.analyzer.analysis.report.content import build
from whiztap.analyzer.analysis.report.formats import FORMATS
from whiztap.analyzer.cli import analyze as analyze_cli
from whiztap.analyzer.cli.progress import ByteProgress
from whiztap.analyzer.protocol.session import Limits
from whiztap.analyzer.recording.sets import find_recordings
from whiztap.sniffer.fleet import cluster as cluster_module

pytestmark = pytest.mark.slow  # a Dask cluster of processes: not in make check

WAIT = 60.0  # a bound on waiting for the cluster; never a timing assertion


@pytest.fixture(scope="module")
def dask_cluster():
    cluster = DaskCluster()
    yield cluster
    cluster.close()


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return write_fleet(tmp_path_factory.mktemp("fleet"))


def test_the_cluster_writes_the_report_this_machine_writes_in_every_format(dask_cluster: DaskCluster,
                                                                           fleet: list[Path],
                                                                           tmp_path: Path) -> None:
    """Named relative to a folder the workers do not run in: they get them
    from the root, the report names them as given."""
    folder = fleet[0].parent
    names = [p.name for p in fleet]
    for fmt in FORMATS:
        here, there = tmp_path / f"here.{fmt}", tmp_path / f"there.{fmt}"
        local = run_cli("analyze", *names, "--group-by", "robot", "--group-by", "firmware", "--format", fmt,
                    "-j", "1", "-o", here, cwd=folder)
        remote = run_cli("analyze", *names, "--group-by", "robot", "--group-by", "firmware", "--format", fmt,
                     "--dask", dask_cluster.address, "-o", there, cwd=folder)
        assert local.returncode == remote.returncode == 1, (local.stderr, remote.stderr)
        assert f"Dask: 2 workers at {dask_cluster.address}" in remote.stderr
        assert here.read_bytes() == there.read_bytes(), fmt
    data = json.loads((tmp_path / "there.json").read_text())
    assert data["files"] == sorted(names) and len(data["fleet"]) == 2


def test_urls_on_the_cluster(dask_cluster: DaskCluster, fleet: list[Path]) -> None:
    url = f"file://{fleet[0].parent}"
    local = run_cli("analyze", url, "--format", "json", "--group-by", "robot")
    remote = run_cli("analyze", url, "--format", "json", "--group-by", "robot", "--dask", dask_cluster.address, "-q")
    assert local.stdout == remote.stdout and remote.stderr == ""
    assert json.loads(remote.stdout)["files"][0].startswith("file:///")


def test_an_unreadable_file_costs_only_itself_on_the_cluster(dask_cluster: DaskCluster, fleet: list[Path],
                                                             tmp_path: Path) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not a recording")
    local = run_cli("analyze", fleet[0], bad, "--format", "json", "-j", "1")
    remote = run_cli("analyze", fleet[0], bad, "--format", "json", "--dask", dask_cluster.address, "-q")
    assert remote.returncode == local.returncode == 2 and remote.stdout == local.stdout
    assert remote.stderr == local.stderr and "bad.mcap" in remote.stderr


def test_a_worker_killed_in_the_middle_of_a_file(dask_cluster: DaskCluster, fleet: list[Path], tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """Each task pauses before its file; the worker process in the middle of
    the first one is killed (SIGKILL).  Dask runs that task again on a
    worker that lives, and the merged report is the one-process report."""
    for path in fleet:
        shutil.copy(path, tmp_path / path.name)
    found = find_recordings([str(tmp_path)])
    with ByteProgress([], enabled=False) as progress:
        expected, _ = analyze_cli._analyse_all(found, "dev-sum", Limits(), 1, progress)
    monkeypatch.setattr(analyze_cli, "_analyse_in_worker", slow_analysis)
    marks = tmp_path / "attempts"
    with ThreadPoolExecutor(1) as pool, ByteProgress([], enabled=False) as progress:
        running = pool.submit(analyze_cli._analyse_all, found, "dev-sum", Limits(), None, progress,
                              dask_cluster.address)
        victim, killed = _kill_the_first_worker_to_start(marks)
        merged, unreadable = running.result(timeout=WAIT)
    assert unreadable == []
    assert json.dumps(build(merged, group_by=[("robot",)])) == json.dumps(build(expected, group_by=[("robot",)]))
    started = sorted(p.name for p in marks.glob("started-*"))
    done = sorted(p.name for p in marks.glob("done-*"))
    assert f"started-{victim}-{killed}" in started and not any(name.endswith(f"-{killed}") for name in done)
    assert sum(name.startswith(f"started-{victim}-") for name in started) == 2  # it ran again, elsewhere
    assert sorted(name.rsplit("-", 1)[0] for name in done) == sorted(f"done-{p.name}" for p in fleet)  # once each


def _kill_the_first_worker_to_start(marks: Path) -> tuple[str, int]:
    """(file, pid) of the first task to start, whose worker process is killed
    while the task sleeps (a third of the way into its pause)."""
    deadline = time.monotonic() + WAIT
    while time.monotonic() < deadline:
        started = sorted(marks.glob("started-*")) if marks.exists() else []
        if started:
            victim, pid = started[0].name.removeprefix("started-").rsplit("-", 1)
            time.sleep(SLOW_S / 3)
            os.kill(int(pid), signal.SIGKILL)
            return victim, int(pid)
        time.sleep(0.02)
    raise AssertionError("no task started on the cluster")


def test_dask_local_starts_a_cluster_on_this_machine(fleet: list[Path]) -> None:
    local = run_cli("analyze", *fleet, "--format", "json", "-j", "1")
    on_cluster = run_cli("analyze", *fleet, "--format", "json", "--dask", "local", "-j", "2")
    assert on_cluster.stdout == local.stdout
    [line] = on_cluster.stderr.splitlines()  # the cluster's one line, none of Dask's logging
    assert line.startswith("Dask: 2 workers at tcp://127.0.0.1:") and "dashboard http://127.0.0.1:" in line


def test_jobs_with_a_remote_scheduler_is_refused(fleet: list[Path]) -> None:
    done = run_cli("analyze", fleet[0], "--dask", "tcp://127.0.0.1:8786", "-j", "2")
    assert done.returncode == 2 and "the cluster's workers do the work" in done.stderr


def test_an_unreachable_scheduler_is_one_line(fleet: list[Path], monkeypatch: pytest.MonkeyPatch) -> None:
    import socket

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setattr(cluster_module, "CONNECT_S", 1)
    result = run_cli("analyze", fleet[0], "--dask", f"tcp://127.0.0.1:{port}")
    assert result.returncode == 2
    assert f"cannot reach the Dask scheduler at tcp://127.0.0.1:{port}" in result.stderr


def test_the_progress_bar_is_fed_by_the_cluster(dask_cluster: DaskCluster, fleet: list[Path],
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Each task finished on the cluster moves the bar by its recording's size."""
    monkeypatch.setattr(ByteProgress, "THRESHOLD", 0)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)  # a terminal: the bar shows
    found = find_recordings([str(fleet[0].parent)])
    parts = [p for r in found for p in r.parts]
    with ByteProgress(parts, enabled=True) as progress:
        analysis, unreadable = analyze_cli._analyse_all(found, "dev-sum", Limits(), None, progress,
                                                        dask_cluster.address)
        done = progress.bar.tasks[0].completed
    assert unreadable == [] and len(analysis.files) == len(fleet)
    assert done == sum(p.stat().st_size for p in parts)
