"""What every whiztap server shares: listening, its connections' tasks, shutdown.

The simulator and the stub differ only in how they serve one connection
(``_serve_connection``); closing must cancel every connection still being
served, which asyncio's server does not do by itself.
"""

from __future__ import annotations

import asyncio
import socket
from typing import Self

READ_SIZE = 65536
BACKLOG = 1024  # many clients connect at once in tests; asyncio's default is 100


class TcpServer:
    """An asyncio TCP server on ``host:port`` (port 0 picks a free one)."""

    def __init__(self, host: str, port: int) -> None:
        self.host = host
        self.requested_port = port
        self._server: asyncio.Server | None = None
        self._addresses: list[tuple[str, int]] = []  # kept once listening stops (a crash)
        self._handlers: set[asyncio.Task] = set()

    @property
    def addresses(self) -> list[tuple[str, int]]:
        """Every (address, port) listened on: a host name may resolve to several."""
        if self._server is None:
            raise RuntimeError(f"the {type(self).__name__.lower()} is not listening")
        return self._addresses

    @property
    def port(self) -> int:
        return self.addresses[0][1]

    async def start(self) -> None:
        """Listen (OSError if the address cannot be bound)."""
        self._server = await asyncio.start_server(
            self._accept, self.host, self.requested_port, backlog=BACKLOG, limit=READ_SIZE)
        self._addresses = [sock.getsockname()[:2] for sock in self._server.sockets]

    def stop_listening(self) -> None:
        """Close the listening socket at once; connections are left as they are."""
        if self._server is not None:
            self._server.close()

    async def close(self) -> None:
        """Stop listening and end every connection."""
        if self._server is None:
            return
        self._server.close()
        for task in list(self._handlers):
            task.cancel()
        await asyncio.gather(*self._handlers, return_exceptions=True)
        await self._server.wait_closed()
        self._server = None

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._handlers.add(task)
        sock = writer.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            await self._serve_connection(reader, writer)
        finally:
            self._handlers.discard(task)

    async def _serve_connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        raise NotImplementedError
