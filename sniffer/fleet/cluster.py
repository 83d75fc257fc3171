"""Per-file tasks on a Dask distributed cluster (``whiztap analyze --dask``).

One machine's processes (``analyze -j N``) run out on a fleet's thousands of
recordings a day, and scheduling across machines (placement, a worker lost in
the middle of a file, retries, a dashboard) is a solved problem: Dask's
scheduler does it, and this module only hands it the work, through the Dask
client, which talks to the scheduler over sockets: that is why it lives in the
sniffer (the socket side), not in the analyzer.  The analyzer's ``analyze``
command finds it through the ``whiztap.runners`` entry point ``dask``
(``run``), so no analyzer module imports it.

Each task is one recording, run by a function the caller names (it must be
importable on the workers, which run the same whiztap).  Results come back as
tasks finish, with their input index, for the caller to merge in input order
(``analysis.merge``).  A worker that dies in the middle of a task is Dask's to
handle: the scheduler gives the task to another worker, and only the run that
finished is returned, so nothing is counted twice or lost.  A task whose
workers keep dying (``distributed.scheduler.allowed-failures``, 3 by
default: a recording that exhausts memory) comes back as ``Lost``.

``Lost`` and ``RunnerError`` are the analyzer's (``analysis.merge``): what any
runner may hand back or raise.
"""

from __future__ import annotations

import contextlib
import logging
import os
import warnings
from collections.abc import Callable, Iterator
from typing import Any

from whiztap.analyzer import __version__
from whiztap.analyzer.analysis.merge import Lost, RunnerError
from whiztap.analyzer.protocol.text import plural

LOCAL = "local"  # --dask local: a LocalCluster on this machine
CONNECT_S = 10  # how long to try the scheduler
WORKERS_S = 30  # how long to wait for a first worker to join it
DASHBOARD = "127.0.0.1:8787"  # a local cluster's dashboard (another free port when taken), on this machine only


class ClusterError(RunnerError):
    """The cluster cannot do the work (unreachable, no workers, another
    whiztap on the workers, dask not installed); one line."""


def run(scheduler: str, workers: int | None, task: Callable[[Any], Any], jobs: list[Any],
        announce: Callable[[str], None] | None = None) -> Iterator[tuple[int, Any]]:
    """The ``whiztap.runners`` entry point ``dask``: (index, result) of
    ``task(jobs[index])`` for every job, as tasks on the Dask cluster at
    ``scheduler`` (``local``: a LocalCluster of ``workers`` processes);
    ``announce`` gets the cluster's one line (``describe``) first.  Raises
    ClusterError."""
    with dask_client(scheduler, workers) as client:
        if announce is not None:
            announce(describe(client))
        yield from run_tasks(client, task, jobs)


def whiztap_version() -> str:
    """Run on each worker: the whiztap it would analyse with."""
    return __version__


@contextlib.contextmanager
def dask_client(scheduler: str, workers: int | None = None) -> Iterator[Any]:
    """A ``distributed.Client`` of the scheduler at ``scheduler``
    (``tcp://HOST:PORT``, ...), or of a LocalCluster of ``workers`` processes
    (default: one per core) for ``local``; closed (and the local cluster
    stopped) on the way out.  Raises ClusterError."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ClusterError("--dask needs dask.distributed: pip install 'whiztap[fleet]'") from None
    logging.getLogger("distributed").setLevel(logging.ERROR)  # its warnings would break one-line output
    cluster = None
    try:
        if scheduler == LOCAL:
            with warnings.catch_warnings():  # "port 8787 is already in use": the cluster line names the one taken
                warnings.filterwarnings("ignore", message="Port .* is already in use")
                cluster = LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1,
                                       processes=True, host="127.0.0.1", dashboard_address=DASHBOARD,
                                       silence_logs=logging.ERROR)
        try:
            client = Client(cluster if cluster is not None else scheduler, timeout=CONNECT_S)
        except (OSError, ValueError, TypeError) as e:
            raise ClusterError(f"cannot reach the Dask scheduler at {scheduler}: {_line(e)}") from None
        try:
            _check_workers(client, scheduler)
            yield client
        finally:
            client.close()
    finally:
        if cluster is not None:
            cluster.close()


def _check_workers(client: Any, scheduler: str) -> None:
    """At least one worker, each running this whiztap: another version could
    judge differently, and the report would not be one report."""
    try:
        client.wait_for_workers(1, timeout=WORKERS_S)
    except (TimeoutError, OSError):
        raise ClusterError(f"no worker joined the Dask scheduler at {scheduler} within {WORKERS_S} s") from None
    try:
        versions = client.run(whiztap_version)
    except Exception as e:  # whatever the workers raised unpickling or running it
        raise ClusterError(f"the Dask workers cannot run whiztap ({_line(e)}); install whiztap {__version__} "
                           "with its fleet extra on every worker") from None
    other = sorted({v for v in versions.values() if v != __version__})
    if other:
        raise ClusterError(f"the Dask workers run whiztap {', '.join(other)}, this is {__version__}; "
                           "install the same version everywhere")


def describe(client: Any) -> str:
    """One line about the cluster: its workers, its scheduler, its dashboard."""
    info = client.scheduler_info()
    workers = len(info.get("workers", {}))
    line = f"Dask: {plural(workers, 'worker')} at {client.scheduler.address}"
    link = getattr(client, "dashboard_link", None)
    return f"{line}; dashboard {link}" if link and "status" in link else line


def run_tasks(client: Any, task: Callable[[Any], Any], jobs: list[Any]) -> Iterator[tuple[int, Any]]:
    """(index, result) of ``task(jobs[index])`` for every job, each as its task
    finishes anywhere on the cluster; ``Lost`` for a task Dask gave up on.
    An exception the task raised is raised here.  Tasks are submitted in
    input order, which is the order the scheduler prefers to run them in, so
    results mostly come back in the order they are merged."""
    from distributed import KilledWorker, as_completed

    futures = client.map(task, jobs, pure=False)
    index = {future.key: i for i, future in enumerate(futures)}
    pending = set(futures)
    try:
        for future in as_completed(futures):
            if future.status == "error" and isinstance(future.exception(), KilledWorker):
                result: Any = Lost("every Dask worker that ran it died (out of memory?); "
                                   "distributed.scheduler.allowed-failures sets how many may")
            else:
                result = future.result()  # a task's own exception is raised here
            pending.discard(future)
            future.release()  # its result leaves the worker's memory
            yield index[future.key], result
    finally:
        if pending:  # stopped early (an error, Ctrl-C): the cluster need not go on
            client.cancel(list(pending))


def _line(e: BaseException) -> str:
    """An exception from dask as one line."""
    return " ".join(str(e).split()) or type(e).__name__
