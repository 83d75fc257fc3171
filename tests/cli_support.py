"""Running ``whiztap`` from a test: one way in this process, one way as a process.

``run_cli`` runs the command line in this process, through ``root.main``
itself (so a problem still comes out as one line on stderr and an exit
status, as the installed command prints it), with click's ``CliRunner``
isolation for stdin, stdout, stderr and the environment.  It costs
milliseconds where starting the interpreter and importing the command costs
about a second, so it is the way wherever a process of its own is not the
point.

``run_process``, ``run_process_async`` and ``start_process`` run the
installed entry point in a process of its own, for the tests where that is the point: a signal (Ctrl-C,
SIGTERM, SIGKILL), the process's own memory or exit, what the entry point
imports, a recorder running beside the test's own event loop.  Both return or
wrap the same things as ``run_cli``, so a test reads the same either way.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, NamedTuple

from click.testing import CliRunner
from whiztap.analyzer.cli.root import main

WHIZTAP = str(Path(sys.executable).with_name("whiztap"))
_STARTED: list[asyncio.subprocess.Process] = []  # by start_process; killed after each test (conftest)
TIMEOUT = 120  # seconds a command run to its end may take before the test fails


class Ran(NamedTuple):
    """How a command ended: named as ``subprocess.CompletedProcess`` names it."""

    returncode: int
    stdout: str
    stderr: str


@contextlib.contextmanager
def _in(cwd: Path | str | None) -> Iterator[None]:
    """The working directory a command runs in, put back afterwards."""
    if cwd is None:
        yield
        return
    before = os.getcwd()
    os.chdir(cwd)
    try:
        yield
    finally:
        os.chdir(before)


def run_cli(*args: object, stdin: str | bytes | None = None, env: Mapping[str, str | None] | None = None,
            cwd: Path | str | None = None) -> Ran:
    """``whiztap ARGS`` in this process: its exit status, stdout and stderr.

    ``env`` is laid over this process's environment for the run (None removes
    a variable); ``stdin`` is what the command reads (empty when None, as a
    process with stdin from /dev/null).  An unexpected error fails the test
    whatever it expects, with its traceback (WHIZTAP_DEBUG): reaching a user,
    it is a bug."""
    argv = ["whiztap", *map(str, args)]
    runner = CliRunner()
    env = {"WHIZTAP_DEBUG": "1", **(env or {})}  # root.main raises what it did not expect, traceback and all
    with _in(cwd), runner.isolation(input=stdin, env=env) as (out, err, _):
        saved, sys.argv = sys.argv, argv
        code: Any = 0
        try:
            main()
        except SystemExit as e:
            code = e.code
        finally:
            sys.argv = saved
            sys.stdout.flush()
            sys.stderr.flush()
        stdout, stderr = out.getvalue(), err.getvalue()
    if code is None:
        code = 0
    elif not isinstance(code, int):  # sys.exit("message"): printed, status 1, as Python does
        stderr += f"{code}\n".encode()
        code = 1
    ran = Ran(code, stdout.decode(errors="replace"), stderr.decode(errors="replace"))
    assert "whiztap: unexpected error" not in ran.stderr, ran.stderr  # a bug, whatever the test expects
    return ran


def run_process(*args: object, stdin: str | None = None, env: Mapping[str, str] | None = None,
                cwd: Path | str | None = None, timeout: float = TIMEOUT) -> Ran:
    """The installed ``whiztap ARGS`` in a process of its own, run to its end
    (stdin from /dev/null unless given; ``env`` replaces the environment)."""
    done = subprocess.run([WHIZTAP, *map(str, args)], input=stdin, env=env, cwd=cwd, capture_output=True,
                          text=True, timeout=timeout, stdin=subprocess.DEVNULL if stdin is None else None)
    return Ran(done.returncode, done.stdout, done.stderr)


async def run_process_async(*args: object, stdin: bytes | None = None,
                            env: Mapping[str, str] | None = None) -> Ran:
    """``run_process`` for a test whose event loop serves what the command
    talks to (a simulator, a proxy): awaited, so the loop goes on meanwhile."""
    proc = await start_process(*args, env=env,
                               stdin=asyncio.subprocess.PIPE if stdin is not None else asyncio.subprocess.DEVNULL)
    out, err = await asyncio.wait_for(proc.communicate(stdin), TIMEOUT)
    assert proc.returncode is not None
    return Ran(proc.returncode, out.decode(errors="replace"), err.decode(errors="replace"))


async def start_process(*args: object, **kwargs: Any) -> asyncio.subprocess.Process:
    """The installed ``whiztap ARGS`` started in a process of its own, its
    stdout and stderr piped (stdin from /dev/null) unless ``kwargs`` say
    otherwise; the test waits for it, signals it or reads its lines."""
    kwargs.setdefault("stdout", asyncio.subprocess.PIPE)
    kwargs.setdefault("stderr", asyncio.subprocess.PIPE)
    kwargs.setdefault("stdin", asyncio.subprocess.DEVNULL)
    proc = await asyncio.create_subprocess_exec(WHIZTAP, *map(str, args), **kwargs)
    _STARTED.append(proc)
    return proc


def kill_leftovers() -> list[int]:
    """Kill what ``start_process`` started and the test left running (one that
    failed half-way, before it stopped its server): the pids killed.  A
    process already reaped is left alone (``waitpid`` says so), so a pid the
    system gave to another process since is never signalled."""
    killed = []
    while _STARTED:
        proc = _STARTED.pop()
        if proc.returncode is not None:
            continue
        try:
            if os.waitpid(proc.pid, os.WNOHANG) != (0, 0):
                continue  # it had ended: reaped now
            os.kill(proc.pid, 9)
            os.waitpid(proc.pid, 0)
        except ChildProcessError:  # reaped already by the event loop's watcher
            continue
        killed.append(proc.pid)
    return killed
