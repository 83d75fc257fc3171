"""Shadow traffic (``record --mirror HOST:PORT``): each client connection also opened to a mirror server.

The mirror gets the client's bytes as the primary server gets them (the
proxy hands them over right after writing them toward the primary, or, in
the middle, right after delivering them), and its answers go to the
recording only (``/mirror/tcp/s2c``), never to the client.  The writer
process pairs them with the primary's (``mirror_record.py``,
``analyzer/analysis/mirror.py``) and says what differs.

Nothing the mirror does may slow or change the primary's traffic, so the
proxy never waits for it:

- A mirror connection holds at most ``MIRROR_BUFFER`` bytes of the client's
  that the mirror has not taken (while it connects, and in its transport's
  buffer after, beside the kernel's ``MIRROR_SOCKET_BUFFER``); past that it
  is dropped: closed, recorded, said once.
- The mirror's answers go into the recording's batch only while the writer
  keeps up: past ``MIRROR_WRITER_ROOM`` bytes of backlog (well below where
  the writer starts to hold the primary's connections) the mirror connection
  is dropped rather than let the recording hold up a client.
- A mirror that refuses or dies is recorded (``/mirror/tcp/events``) and
  said once per kind of failure; the client's connection is not touched.
- After the client's connection ends the mirror may answer for
  ``MIRROR_GRACE_S`` more; then its connection is closed.
- The mirror is written to and read from at most every ``MIRROR_BATCH_S``
  (5 ms), all that came meanwhile at once: a busy connection costs the proxy
  a wakeup or two per 5 ms for its mirror, not a write and a read per
  request.  So the mirror's answers are up to 10 ms later than it sent them
  as the pairing sees them, well inside what ``diff`` forgives (100 ms).

``MirrorView`` is what the writer found, for the TUI and the closing lines.
"""

from __future__ import annotations

import asyncio
import json
import socket
from collections import Counter, deque
from collections.abc import Callable
from typing import Protocol, cast

from whiztap.analyzer.protocol.text import plural
from whiztap.sniffer.nettext import reason, show_address

MIRROR_BUFFER = 1 << 20  # client bytes a mirror connection may have waiting for the mirror (1 MiB)
MIRROR_WRITER_ROOM = 2 << 20  # the recording's backlog past which a mirror's answers drop it (feed.CAUGHT_UP)
MIRROR_SOCKET_BUFFER = 256 << 10  # the kernel's send buffer toward the mirror, fixed (no autotuning to MBs)
MIRROR_BATCH_S = 0.005  # the mirror is written to and read from at most this often: a wakeup per 5 ms, not per read
MIRROR_GRACE_S = 2.0  # how long the mirror may go on answering after the client's connection ended
LATEST = 5  # differences the live view keeps


class MirrorSink(Protocol):
    """Where the mirror's traffic goes: the writer process (``feed.WriterProcess``)."""

    @property
    def backlog(self) -> int: ...

    def mirror(self, conn: int, t_ns: int, read: bool, payload: bytes) -> None: ...


class MirrorView:
    """What the writer found so far (its ``mirror`` status lines), for the
    TUI's status line and the closing summary: counts and the latest differences."""

    def __init__(self) -> None:
        self.differences = 0
        self.by_kind: dict[str, int] = {}
        self.latest: deque[str] = deque(maxlen=LATEST)
        self.events: Counter[str] = Counter()  # mirror connections by how they ended (and "connected")
        self.final: dict | None = None  # the writer's last word (``MirrorRecorder.finish``)

    def update(self, message: dict) -> None:
        """A ``mirror`` status line from the writer (``mirror_record.py``)."""
        self.differences = int(message.get("total", self.differences))
        self.by_kind = dict(message.get("by_kind", self.by_kind))
        self.latest.extend(str(line) for line in message.get("latest", ()))
        if message.get("final"):
            self.final = {k: v for k, v in message.items() if k not in ("type", "final")}

    def text(self) -> str:
        """One line: how the mirror compares so far."""
        ended = ", ".join(f"{n} {what}" for what, n in sorted(self.events.items()) if what != "connected")
        head = f"mirror: {plural(self.differences, 'difference')}"
        if self.by_kind:
            head += " (" + ", ".join(f"{n:,} {kind}" for kind, n in sorted(self.by_kind.items())) + ")"
        return head + (f"; its connections: {ended}" if ended else "")


class MirrorLeg(asyncio.Protocol):
    """One client connection's mirror connection."""

    def __init__(self, mirror: Mirror, conn: int) -> None:
        self.mirror = mirror
        self.conn = conn
        self.transport: asyncio.Transport | None = None
        self.waiting = bytearray()  # the client's bytes not yet written to the mirror (connecting, or batched)
        self.fed = 0  # client bytes handed over (written or waiting)
        self.sent = 0  # ... of which the kernel took, as far as the end knows (for the comparison's cut)
        self.received = 0  # bytes the mirror sent
        self.ended = False
        self.client_done = False  # the client sent its FIN
        self._connect: asyncio.Task | None = None
        self._grace: asyncio.TimerHandle | None = None
        self._resume: asyncio.TimerHandle | None = None  # reading again, MIRROR_BATCH_S after the last read
        self._write: asyncio.TimerHandle | None = None  # writing what waits, MIRROR_BATCH_S after it began to

    def start(self) -> None:
        self._connect = asyncio.get_running_loop().create_task(self._open())

    async def _open(self) -> None:
        m = self.mirror
        try:
            await asyncio.wait_for(asyncio.get_running_loop().create_connection(lambda: self, m.host, m.port),
                                   m.connect_timeout)
        except asyncio.CancelledError:
            return
        except (TimeoutError, OSError) as e:
            why = "timed out" if isinstance(e, asyncio.TimeoutError) else reason(e)
            self.end("failed", f"cannot connect to the mirror {m.text}: {why}")

    def feed(self, data: bytes) -> None:
        """The client's bytes, as the primary got them: written within ``MIRROR_BATCH_S``, never awaited."""
        if self.ended:
            return
        self.fed += len(data)
        waiting = self.waiting
        waiting += data
        transport = self.transport
        if len(waiting) + (transport.get_write_buffer_size() if transport is not None else 0) > MIRROR_BUFFER:
            self.drop(f"the mirror took too little: more than {MIRROR_BUFFER >> 10} KiB of the client's bytes "
                      "waited for it" if transport is not None else
                      f"the mirror did not connect before {MIRROR_BUFFER >> 10} KiB of the client's bytes came")
        elif transport is not None and self._write is None:
            self._write = asyncio.get_running_loop().call_later(MIRROR_BATCH_S, self._flush)

    def _flush(self) -> None:
        """Write what waits (the drop check is ``feed``'s: what waits here counts as the transport's)."""
        if self._write is not None:
            self._write.cancel()
            self._write = None
        if self.waiting and self.transport is not None and not self.ended:
            self.transport.write(bytes(self.waiting))
            self.waiting.clear()

    def client_eof(self) -> None:
        """The client's FIN, passed on when the primary gets it."""
        if self.client_done:
            return
        self.client_done = True
        if self.transport is not None and not self.ended and self.transport.can_write_eof():
            self._flush()
            self.transport.write_eof()

    def client_closed(self) -> None:
        """The client's connection is over: the mirror has ``MIRROR_GRACE_S`` to finish."""
        if self.ended:
            return
        if self.transport is None:
            self.end("closed", "the client's connection ended before the mirror's was made")
            return
        if not self.client_done:
            self.client_eof()
        self._grace = asyncio.get_running_loop().call_later(
            MIRROR_GRACE_S, self.end, "closed", f"closed by the proxy {MIRROR_GRACE_S:g} s after the client's "
                                                "connection ended")

    # -- the mirror's socket ------------------------------------------------------------------

    def connection_made(self, base: asyncio.BaseTransport) -> None:
        self.transport = transport = cast(asyncio.Transport, base)
        if self.ended:  # ended while connecting (the recording stopped)
            transport.abort()
            return
        sock = transport.get_extra_info("socket")
        if sock is not None:
            try:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, MIRROR_SOCKET_BUFFER)
            except OSError:
                pass
        self.mirror.event(self, "connected", "")
        self._flush()
        if self.client_done and transport.can_write_eof():
            transport.write_eof()

    def data_received(self, data: bytes) -> None:
        if self.ended:
            return
        self.received += len(data)
        mirror = self.mirror
        if mirror.sink.backlog > MIRROR_WRITER_ROOM:
            self.drop("the recording fell behind: the mirror is dropped so that the primary's traffic is not held up")
            return
        mirror.sink.mirror(self.conn, mirror.clock(), True, data)
        if self._resume is None and self.transport is not None:  # what else it says, in one read, later:
            self.transport.pause_reading()  # its answers never reach the client, so a few ms do not matter,
            self._resume = asyncio.get_running_loop().call_later(MIRROR_BATCH_S, self._read_again)  # wakeups do

    def _read_again(self) -> None:
        self._resume = None
        if not self.ended and self.transport is not None:
            self.transport.resume_reading()

    def eof_received(self) -> bool:
        return False  # the mirror is done sending: close

    def connection_lost(self, exc: Exception | None) -> None:
        self.end("closed", f"reset by the mirror ({exc})" if exc is not None else "closed by the mirror")

    # -- ends ---------------------------------------------------------------------------------

    def drop(self, detail: str) -> None:
        self.end("dropped", detail)

    def end(self, event: str, detail: str) -> None:
        """The mirror connection is over, once: recorded, said once per kind, closed."""
        if self.ended:
            return
        self.ended = True
        self.sent = self.fed - len(self.waiting) - (self.transport.get_write_buffer_size() if self.transport else 0)
        self.waiting.clear()
        for pending in (self._connect, self._grace, self._resume, self._write):
            if pending is not None:
                pending.cancel()
        if self.transport is not None:
            self.transport.abort()
        self.mirror.event(self, event, detail)
        self.mirror.legs.pop(self.conn, None)


class Mirror:
    """The mirror server of a recording: a ``MirrorLeg`` per client connection
    (``open``), its traffic handed to ``sink``, its failures to ``say`` once."""

    def __init__(self, host: str, port: int, connect_timeout: float, clock: Callable[[], int], sink: MirrorSink,
                 say: Callable[[str], None]) -> None:
        self.host, self.port = host, port
        self.text = show_address(host, port)
        self.connect_timeout = connect_timeout
        self.clock = clock
        self.sink = sink
        self.say = say
        self.legs: dict[int, MirrorLeg] = {}
        self.view = MirrorView()
        self._said: set[str] = set()

    def open(self, conn: int) -> MirrorLeg:
        leg = self.legs[conn] = MirrorLeg(self, conn)
        leg.start()
        return leg

    def client_closed(self, conn: int) -> None:
        leg = self.legs.get(conn)
        if leg is not None:
            leg.client_closed()

    def event(self, leg: MirrorLeg, event: str, detail: str) -> None:
        self.view.events[event] += 1
        body = {"event": event, "detail": detail, "c2s_bytes": leg.sent, "s2c_bytes": leg.received}
        self.sink.mirror(leg.conn, self.clock(), False, json.dumps(body).encode())
        if event in ("failed", "dropped"):
            self.say_once(event, f"mirror: #{leg.conn} {event}: {detail} (said once; the closing summary counts "
                                 "them all)")
        elif event == "closed" and leg.fed and not leg.client_done:  # while the client was still talking
            self.say_once("died", f"mirror: #{leg.conn} {detail} while the client was still connected "
                                  "(said once; the closing summary counts them all)")

    def say_once(self, kind: str, line: str) -> None:
        """Say ``line`` if nothing of its ``kind`` was said yet in this run."""
        if kind not in self._said:
            self._said.add(kind)
            self.say(line)

    def close(self) -> None:
        """The recording stops: every mirror connection ends now."""
        for leg in list(self.legs.values()):
            leg.end("closed", "recording stopped")


def mirror_lines(final: dict) -> list[str]:
    """The closing summary's lines about the mirror (``MirrorRecorder.finish``'s totals)."""
    total = final.get("total", 0)
    kinds = ", ".join(f"{n:,} {kind}" for kind, n in sorted(final.get("by_kind", {}).items()))
    events = final.get("events", {})
    ended = ", ".join(f"{events[what]:,} {what}" for what in ("failed", "dropped") if events.get(what))
    lines = [f"mirror {final.get('server', '?')}: {plural(final.get('exchanges', 0), 'exchange')} compared over "
             f"{plural(final.get('connections', 0), 'connection')}: "
             + (f"{plural(total, 'difference')} ({kinds})" if total else "no differences")
             + (f"; {final['not_compared']:,} requests not compared (the mirror had ended)"
                if final.get("not_compared") else "")
             + (f"; mirror connections {ended}" if ended else "")]
    first = final.get("first", [])
    lines += [f"  {line}" for line in first]
    if total > len(first):
        lines.append(f"  ... and {total - len(first):,} more on /mirror/differences")
    return lines
