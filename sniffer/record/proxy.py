"""A transparent TCP proxy that tells its consumers everything it forwards.

Each client connection gets its own upstream connection.  Every chunk read from
one side is written to the other side's transport at once, inside the same
``data_received`` call, before anything else happens: no byte is held back,
reordered or changed, and nothing waits for a frame to complete.  Only then is
the chunk handed on as a traffic event (``Data``) to the consumer: a fan-out
(``whiztap.sniffer.record.consumers``) to the recorder's pipe, which copies it
into a batch, and to any other consumer (the TUI's tap), each isolated.
``asyncio.Protocol`` rather than streams: streams add a task switch and a
buffer copy per read, which halves round trips (see docs/benchmarks.md).

Flow control is end to end, and derived, not remembered: a side is read
exactly while there is somewhere to send its bytes (the upstream is connected
and the client's early bytes are passed on), the other side's transport buffer
is at most its high-water mark, the side has not sent its FIN, and the
recorder does not hold the connection (``RecordingProxy.hold``: the writer is
behind and this connection has more than its share of the backlog).
``_Leg.sync`` makes the transport match that rule and is called whenever one
of those facts changes; it is asserted again on every read and just after
``connection_made`` (uvloop starts reading only after ``connection_made``
returns, so a pause made there would be lost).  A side that should not be
read stops after at most one read, and TCP pushes back on its sender: the
proxy never buffers more than a transport's high-water mark and one read per
direction, however slowly a client reads.

Half-close passes through (a FIN from one side becomes ``write_eof()`` on the
other); a reset or close on one side closes the other once its buffered bytes
are sent.  A connection that fails in any way is recorded and closed; it never
affects another.  A client whose upstream cannot be reached is reset (RST,
never a FIN): the nearest a proxy comes to the refusal the server would have
given it, and never mistaken for a server that answered and closed.
"""

from __future__ import annotations

import asyncio
import itertools
import socket
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, cast

from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.traffic import Closed, Data, HalfClosed, Opened, UpstreamConnected, UpstreamFailed
from whiztap.sniffer.nettext import arm_reset, reason, show_address
from whiztap.sniffer.record.consumers import Consumer

if TYPE_CHECKING:
    from whiztap.sniffer.mitm.controller import Controller
    from whiztap.sniffer.mitm.shell import MiddleShell
    from whiztap.sniffer.record.mirror import MirrorLeg

C2S, S2C = Direction.C2S, Direction.S2C
TRANSPORT_HIGH_WATER = 256 << 10
CLOSE_GRACE_S = 2.0


class Clock:
    """Wall-clock nanoseconds that never go backwards: the wall time at start
    plus a monotonic counter, so an NTP step cannot reorder a recording."""

    def __init__(self) -> None:
        self._base = time.time_ns() - time.perf_counter_ns()

    def __call__(self) -> int:
        return self._base + time.perf_counter_ns()


def address(sockname: tuple | None) -> str:
    """A socket's (host, port, ...) as host:port; "?" when there is none."""
    return show_address(sockname[0], sockname[1]) if sockname else "?"


class _Leg(asyncio.Protocol):
    """One socket of a connection; ``direction`` is that of the bytes it reads."""

    peer: _Leg  # the other side, paired by the ``Connection`` that makes both

    def __init__(self, conn: Connection, direction: Direction) -> None:
        self.conn = conn
        self.direction = direction
        self.transport: asyncio.Transport | None = None
        self.target: asyncio.Transport | None = None  # where its bytes go, once they may
        self.eof = False  # this side sent FIN
        self.received = 0  # bytes read from this side
        self.early: list[bytes] = []  # read before the upstream was connected
        self.lost = False

    def may_read(self) -> bool:
        """The rule for reading this side (see the module docstring)."""
        target = self.target
        middle = self.conn.middle
        return (target is not None and target.get_write_buffer_size() <= TRANSPORT_HIGH_WATER
                and not self.conn.held and not self.eof and (middle is None or middle.may_read(self.direction)))

    def sync(self) -> None:
        """Read, or not, as the rule says now (both calls are no-ops when already so)."""
        if self.transport is not None and not self.lost:
            if self.may_read():
                self.transport.resume_reading()
            else:
                self.transport.pause_reading()

    def connection_made(self, base: asyncio.BaseTransport) -> None:
        self.transport = transport = cast(asyncio.Transport, base)  # a TCP connection's
        sock = transport.get_extra_info("socket")
        if sock is not None:
            try:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError:
                pass
        transport.set_write_buffer_limits(high=TRANSPORT_HIGH_WATER)
        if self.direction is S2C:  # the client is connected before its upstream
            self.target = self.peer.transport
            if self.conn.middle is not None:
                self.conn.middle.ready(S2C)
        else:
            self.conn.client_made(transport)
        asyncio.get_running_loop().call_soon(self.sync)  # once reading has started

    def data_received(self, data: bytes) -> None:
        conn = self.conn
        proxy = conn.proxy
        t = proxy.clock()
        if conn.middle is not None:  # in the middle: its core decides what is written, and when (and tells the read)
            self.received += len(data)
            conn.middle.received(self.direction, data, t)
            if not self.lost and not self.may_read():
                self._pause()
            return
        target = self.target
        if target is not None:
            target.write(data)
        else:
            self.early.append(data)  # the upstream is not connected yet
        self.received += len(data)
        proxy.receive(Data(conn.id, self.direction, t, data))
        if conn.mirror is not None and self.direction is C2S:  # --mirror: the same bytes, never awaited
            conn.mirror.feed(data)
        if not self.may_read():  # whatever pause was missed, this read is the last
            self._pause()

    def _pause(self) -> None:
        if self.transport is not None:  # always, once a read has come
            self.transport.pause_reading()

    def eof_received(self) -> bool:
        self.eof = True
        self.conn.half_closed(self)
        return True  # keep the other direction open

    def pause_writing(self) -> None:
        self.peer.sync()

    def resume_writing(self) -> None:
        self.peer.sync()
        middle = self.conn.middle
        if middle is not None:  # what the middle queued toward this side may go on
            middle.drained(S2C if self.direction is C2S else C2S)

    def connection_lost(self, exc: Exception | None) -> None:
        self.lost = True
        self.conn.leg_lost(self, exc)


class Connection:
    """A client connection and its upstream connection."""

    def __init__(self, proxy: RecordingProxy, conn_id: int) -> None:
        self.proxy = proxy
        self.id = conn_id
        self.client = _Leg(self, C2S)
        self.upstream = _Leg(self, S2C)
        self.client.peer, self.upstream.peer = self.upstream, self.client
        self.client_addr = "?"
        self.held = False  # by the recorder: see RecordingProxy.hold
        self.middle: MiddleShell | None = None  # when the proxy stands in the middle (sniffer/mitm)
        self.mirror: MirrorLeg | None = None  # record --mirror: the client's bytes also go there (mirror.py)
        self.closed_by: str | None = None
        self.detail = ""
        self.upstream_failed = False  # the upstream could not be reached: the client was reset
        self.opened_ns = 0
        self._connect: asyncio.Task | None = None
        self._done = asyncio.get_running_loop().create_future()

    # -- setup --------------------------------------------------------------------------

    def client_made(self, transport: asyncio.Transport) -> None:
        proxy = self.proxy
        self.client_addr = address(transport.get_extra_info("peername"))
        self.opened_ns = proxy.clock()
        proxy.receive(Opened(self.id, self.opened_ns, self.client_addr, proxy.upstream_text))
        if proxy.controller is not None:
            from whiztap.sniffer.mitm.shell import MiddleShell

            self.middle = MiddleShell(proxy.controller, self, proxy.clock, TRANSPORT_HIGH_WATER)
        if proxy.on_opened is not None:
            proxy.on_opened(self)
        self._connect = asyncio.get_running_loop().create_task(self._open_upstream())

    async def _open_upstream(self) -> None:
        proxy = self.proxy
        loop = asyncio.get_running_loop()
        try:
            upstream, _ = await asyncio.wait_for(
                loop.create_connection(lambda: self.upstream, proxy.upstream_host, proxy.upstream_port),
                proxy.connect_timeout)
        except asyncio.CancelledError:
            return
        except (TimeoutError, OSError) as e:
            why = "timed out" if isinstance(e, asyncio.TimeoutError) else reason(e)
            detail = f"cannot connect to {proxy.upstream_text}: {why}"
            proxy.receive(UpstreamFailed(self.id, proxy.clock(), detail))
            self.detail = detail
            self.closed_by = "server"
            self.upstream_failed = True
            self._reset_client()
            return
        if self.client.lost:
            upstream.close()
            return
        local = address(upstream.get_extra_info("sockname"))
        proxy.receive(UpstreamConnected(self.id, proxy.clock(), f"from {local}"))
        if self.middle is not None:
            self.client.target = upstream
            self.middle.ready(C2S)  # what the client sent meanwhile, and its FIN
            self.client.sync()
            return
        for data in self.client.early:
            upstream.write(data)
        self.client.early.clear()
        if self.client.eof:  # the client's FIN came while connecting: pass it on now
            upstream.write_eof()
        self.client.target = upstream
        self.client.sync()

    def _reset_client(self) -> None:
        """End the client's connection with an RST, whatever it sent or not."""
        transport = self.client.transport
        if transport is None:  # never: a connection starts with its client's
            return
        arm_reset(transport)
        transport.abort()

    # -- teardown -------------------------------------------------------------------------

    def half_closed(self, leg: _Leg) -> None:
        """A FIN from one side (the client's is only read once upstream is connected)."""
        self.proxy.receive(HalfClosed(self.id, self.proxy.clock(), leg.direction))
        if self.closed_by is None:
            self.closed_by, self.detail = leg.direction.sender, "closed"
        if self.middle is not None:  # the FIN follows what the middle still holds
            self.middle.sender_ended(leg.direction)
            return
        self.pass_eof(leg)

    def pass_eof(self, leg: _Leg) -> None:
        """Pass ``leg``'s FIN on to the other side (both done sending: close)."""
        peer = leg.peer
        if leg is self.client and self.mirror is not None:  # as the primary gets it, or will once connected
            self.mirror.client_eof()
        if peer.lost or peer.transport is None:
            return  # gone, or still connecting (which passes the FIN on)
        middle = self.middle
        if peer.eof and (middle is None or middle.eof_passed(peer.direction)):
            self.close_both()  # both sides are done sending
        elif peer.transport.can_write_eof():
            peer.transport.write_eof()

    def leg_lost(self, leg: _Leg, exc: Exception | None) -> None:
        if self.closed_by is None:
            self.closed_by = "client" if leg is self.client else "server"
            self.detail = f"reset ({exc})" if exc is not None else "closed"
        if self._connect is not None and not self._connect.done():
            self._connect.cancel()
        if self.middle is not None:
            self.middle.lost(leg.direction)
        peer = leg.peer
        if peer.transport is not None and not peer.lost:
            peer.transport.close()  # after sending what it holds
        elif not self._done.done():
            self.proxy.receive(Closed(self.id, self.proxy.clock(), self.closed_by, self.detail))
            self._done.set_result(None)
            self.proxy.forget(self)

    def close_both(self, by: str | None = None, detail: str = "") -> None:
        if by is not None and self.closed_by is None:
            self.closed_by, self.detail = by, detail
        if self._connect is not None and not self._connect.done():
            self._connect.cancel()
        for leg in (self.client, self.upstream):
            if leg.transport is not None and not leg.lost:
                leg.transport.close()

    def abort(self) -> None:
        for leg in (self.client, self.upstream):
            if leg.transport is not None and not leg.lost:
                leg.transport.abort()

    async def wait_closed(self) -> None:
        await asyncio.shield(self._done)


async def try_upstream(host: str, port: int, timeout: float) -> str | None:
    """Connect to the upstream once and close at once: None when it accepts,
    else why not ('Connection refused', 'timed out').  ``whiztap record``
    asks at start, so that a wrong --upstream is said before any client
    finds out."""
    try:
        _, writer = await asyncio.wait_for(asyncio.open_connection(host, port), timeout)
    except TimeoutError:
        return f"no answer within {timeout:g} s"
    except OSError as e:
        return reason(e)
    writer.close()
    return None


class RecordingProxy:
    """Listens, and proxies each client to the upstream address, handing what
    happens to ``consumer`` as traffic events (one ``Data`` per read).

    Two hooks, for the person running it: ``on_opened(connection)`` when a
    client connects, ``on_closed(connection)`` when both of its sides are done.
    With a ``controller`` (sniffer/mitm) the proxy stands in the middle: each
    connection's bytes go through its lanes (faults, scripts, interception)
    and what each side received is told as ``Delivered`` events.
    """

    def __init__(self, listen_host: str, listen_port: int, upstream_host: str, upstream_port: int,
                 consumer: Consumer, *, connect_timeout: float = 5.0,
                 on_opened: Callable[[Connection], None] | None = None,
                 on_closed: Callable[[Connection], None] | None = None,
                 controller: Controller | None = None) -> None:
        self.listen_host, self.listen_port = listen_host, listen_port
        self.upstream_host, self.upstream_port = upstream_host, upstream_port
        self.upstream_text = address((upstream_host, upstream_port))
        self.receive = consumer.receive
        self.connect_timeout = connect_timeout
        self.on_opened = on_opened
        self.on_closed = on_closed
        self.clock = Clock()
        self.controller = controller
        if controller is not None:
            controller.attach(self.clock, self.receive)
        self.connections: dict[int, Connection] = {}
        self._ids = itertools.count(1)
        self._server: asyncio.Server | None = None

    @property
    def port(self) -> int:
        """The port it listens on, once started (0 before)."""
        return self._server.sockets[0].getsockname()[1] if self._server is not None else 0

    @property
    def listen_text(self) -> str:
        return address(self._server.sockets[0].getsockname()) if self._server is not None else "?"

    async def start(self, serving: bool = True) -> None:
        """Bind (OSError if the address is taken); accept now or at ``serve()``."""
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(self._accept, self.listen_host, self.listen_port,
                                                reuse_address=True, backlog=512, start_serving=serving)

    async def serve(self) -> None:
        if self._server is not None:  # started
            await self._server.start_serving()

    def _accept(self) -> _Leg:
        conn = Connection(self, next(self._ids))
        self.connections[conn.id] = conn
        return conn.client

    def forget(self, conn: Connection) -> None:
        self.connections.pop(conn.id, None)
        if self.controller is not None:
            self.controller.closed(conn.id)
        if self.on_closed is not None:
            self.on_closed(conn)

    def hold(self, conn_id: int, held: bool) -> None:
        """The recorder's verdict on one connection: stop reading both of its
        sides (its bytes are the writer's backlog), or read them again."""
        conn = self.connections.get(conn_id)
        if conn is not None:
            conn.held = held
            conn.client.sync()
            conn.upstream.sync()

    async def close(self, detail: str = "recording stopped") -> None:
        """Stop accepting, close every connection (sending what is buffered), wait."""
        if self._server is not None:
            self._server.close()
        conns = list(self.connections.values())
        for conn in conns:
            conn.close_both("recorder", detail)
        if conns:
            _, pending = await asyncio.wait([asyncio.ensure_future(c.wait_closed()) for c in conns],
                                            timeout=CLOSE_GRACE_S)
            if pending:
                for conn in list(self.connections.values()):
                    conn.abort()
                await asyncio.wait(pending, timeout=CLOSE_GRACE_S)
        if self._server is not None:
            await self._server.wait_closed()
