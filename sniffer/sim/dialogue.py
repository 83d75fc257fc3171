"""Play a scripted two-sided session over real sockets.

A ``Dialogue`` is both a server (listening on loopback) and a client: for each
step it writes the bytes on one side and reads exactly those bytes on the
other, so every byte has crossed the network (and whatever sits in between,
such as the recording proxy) before the next step starts.  It makes sessions
no real peer would produce on demand: the violations sample, and tests.
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterable

from whiztap.analyzer.protocol.observations import Direction

LOCAL = "127.0.0.1"


class Dialogue:
    """The scripted server; ``play()`` connects a scripted client to ``target``."""

    def __init__(self, timeout: float = 10.0) -> None:
        self.timeout = timeout
        self._accepted: asyncio.Queue[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = asyncio.Queue()
        self._server: asyncio.Server | None = None

    async def __aenter__(self) -> Dialogue:
        self._server = await asyncio.start_server(
            lambda r, w: self._accepted.put_nowait((r, w)), LOCAL, 0)
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self._server is not None
        self._server.close()

    @property
    def port(self) -> int:
        assert self._server is not None
        return self._server.sockets[0].getsockname()[1]

    async def play(self, steps: Iterable[tuple[Direction, bytes]], target: tuple[str, int]) -> None:
        """One connection through ``target`` (which must lead to this server)."""
        client_r, client_w = await asyncio.open_connection(*target)
        server_r, server_w = await asyncio.wait_for(self._accepted.get(), self.timeout)
        try:
            for direction, data in steps:
                source, sink = (client_w, server_r) if direction is Direction.C2S else (server_w, client_r)
                source.write(data)
                await source.drain()
                got = await asyncio.wait_for(sink.readexactly(len(data)), self.timeout)
                if got != data:
                    raise AssertionError(f"{direction} bytes changed on the way: {data!r} became {got!r}")
        finally:
            for writer in (client_w, server_w):
                writer.close()
            for writer in (client_w, server_w):
                try:
                    await writer.wait_closed()
                except (ConnectionError, OSError):
                    pass
