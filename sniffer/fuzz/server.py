"""The server under test as the fuzzer keeps it: given, or started by ``--run``.

A ``Server`` starts (if it is the fuzzer's to start) and restarts after a
crash.  ``Given`` is a server someone else runs: it cannot be restarted, so a
crash that stops it accepting ends the run.  ``Command`` is ``--run 'CMD'``: the
command line is started in a process group of its own, the fuzzer waits until
the address accepts connections, and a crash kills what is left of the group
and starts it again.  ``InProcess`` does the same for a server started by a
coroutine in this process (the simulator, from Python: tests and benchmarks)::

    from whiztap.sniffer.fuzz.server import InProcess
"""


from __future__ import annotations

import asyncio
import os
import shlex
import signal
import subprocess
from collections.abc import Awaitable, Callable
from typing import Any, Protocol

from whiztap.sniffer.fuzz.execute import FuzzError

START_WAIT = 15.0  # seconds for a started server to accept connections
POLL = 0.05


class Server(Protocol):
    """The server the fuzzer runs against, as far as keeping it up goes."""

    async def start(self) -> None: ...

    async def restart(self) -> bool:
        """Bring the server back after a crash; False when it cannot be."""
        ...

    async def stop(self) -> None: ...


class Given:
    """A server the fuzzer did not start and cannot restart."""

    async def start(self) -> None:
        return None

    async def restart(self) -> bool:
        return False

    async def stop(self) -> None:
        return None


async def accepts(address: tuple[str, int]) -> bool:
    """Whether a connection to ``address`` is accepted now."""
    try:
        _, writer = await asyncio.wait_for(asyncio.open_connection(*address), 1.0)
    except (OSError, TimeoutError):
        return False
    writer.transport.abort()
    return True


class Command:
    """``--run CMD``: the server as a command line, (re)started by the fuzzer."""

    def __init__(self, command: str, address: tuple[str, int]) -> None:
        self.argv = shlex.split(command)
        if not self.argv:
            raise FuzzError("--run needs a command line")
        self.address = address
        self.process: subprocess.Popen[bytes] | None = None
        self.starts = 0

    async def start(self) -> None:
        try:
            self.process = subprocess.Popen(self.argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                            stderr=subprocess.DEVNULL, start_new_session=True)
        except OSError as e:
            raise FuzzError(f"--run: cannot start {self.argv[0]} ({e.strerror or e})") from None
        self.starts += 1
        loop = asyncio.get_running_loop()
        end = loop.time() + START_WAIT
        while not await accepts(self.address):
            if self.process.poll() is not None:
                raise FuzzError(f"--run: the server exited with status {self.process.returncode} "
                                f"before accepting connections on {self.address[0]}:{self.address[1]}")
            if loop.time() > end:
                await self.stop()
                raise FuzzError(f"--run: the server did not accept connections on "
                                f"{self.address[0]}:{self.address[1]} within {START_WAIT:g} s")
            await asyncio.sleep(POLL)

    async def restart(self) -> bool:
        await self.stop()
        await self.start()
        return True

    async def stop(self) -> None:
        process, self.process = self.process, None
        if process is None:
            return
        if process.poll() is None:
            try:
                os.killpg(process.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        for _ in range(100):
            if process.poll() is not None:
                break
            await asyncio.sleep(POLL)
        else:
            try:
                os.killpg(process.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            process.wait()


class InProcess:
    """A server this process runs: ``start`` is a coroutine function that
    starts one (listening on the fuzzer's address) and returns it; what it
    returns is closed with ``await server.close()`` before a restart."""

    def __init__(self, start: Callable[[], Awaitable[Any]]) -> None:
        self._start = start
        self.server: Any = None
        self.starts = 0

    async def start(self) -> None:
        self.server = await self._start()
        self.starts += 1

    async def restart(self) -> bool:
        await self.stop()
        await self.start()
        return True

    async def stop(self) -> None:
        server, self.server = self.server, None
        if server is not None:
            await server.close()
