"""Helpers for the recorder tests: loopback servers, a recording in a test's
event loop, and checks that read recordings back with the real MCAP reader."""

from __future__ import annotations

import asyncio
import atexit
import base64
import contextlib
import json
import os
import re
import signal
import socket
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import jsonschema
from mcap.reader import make_reader

from whiztap.analyzer.protocol.framing import Framer, Item, ItemKind, unasked
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.format import SCHEMA_ENCODING, TOPIC_FRAMES, TOPIC_READS
from whiztap.analyzer.recording.scan import RecordingScan
from whiztap.analyzer.traffic import Closed, Data, Gap, HalfClosed, Opened, TrafficEvent
from whiztap.sniffer.record.record_run import Recording, RecordSettings
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.sim.tcp_server import TcpServer

from tests.cli_support import start_process

LOCAL = "127.0.0.1"
WAIT = 20.0  # generous bound for anything a test waits on; never a timing assertion


# -- loopback servers ------------------------------------------------------------------------


class EchoServer(TcpServer):
    """Echoes every byte; answers a FIN with a FIN.  Keeps what each connection sent."""

    def __init__(self) -> None:
        super().__init__(LOCAL, 0)
        self.received: list[bytearray] = []

    async def _serve_connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        got = bytearray()
        self.received.append(got)
        try:
            while data := await reader.read(65536):
                got += data
                writer.write(data)
                await writer.drain()
            writer.write_eof()
            await writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            writer.close()


class ScriptedServer(TcpServer):
    """Reads an 8-byte tag, then sends ``replies[tag]`` in its given pieces,
    half-closes, and reads the client's bytes until the client's FIN."""

    def __init__(self) -> None:
        super().__init__(LOCAL, 0)
        self.replies: dict[bytes, list[bytes]] = {}
        self.received: dict[bytes, bytes] = {}

    async def _serve_connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            tag = await reader.readexactly(8)
            for piece in self.replies[tag]:
                writer.write(piece)
                await writer.drain()
            writer.write_eof()
            self.received[tag] = tag + await reader.read(-1)
        except (ConnectionError, OSError, asyncio.IncompleteReadError):
            pass
        finally:
            writer.close()


def closed_port() -> int:
    """A port nothing listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind((LOCAL, 0))
        return s.getsockname()[1]


# -- a recording in the test's loop --------------------------------------------------------------


@contextlib.asynccontextmanager
async def recording(upstream_port: int, path: str, **options):
    """A recording proxy on a free port in front of ``upstream_port``; finished on exit."""
    settings = RecordSettings((LOCAL, 0), (LOCAL, upstream_port), str(path), **options)
    lines: list[str] = []
    rec = Recording(settings, lines.append)
    rec.lines = lines
    await rec.start()
    try:
        yield rec
    finally:
        if rec.summary is None:
            await rec.stop()


def op_event(op: str, conn: int, d: str, t: int, payload: bytes | int) -> TrafficEvent | None:
    """The traffic event the proxy reports for one step of a drawn session,
    ``(op, conn, direction, payload)`` at ``t``: "opened", "data", "half",
    "gap" (``payload`` bytes missing) or "closed"; None for any other op."""
    if op == "opened":
        return Opened(conn, t, f"127.0.0.1:{40000 + conn}", "127.0.0.1:5000")
    if op == "data":
        return Data(conn, Direction(d), t, payload)
    if op == "half":
        return HalfClosed(conn, t, Direction(d))
    if op == "gap":
        return Gap(conn, t, Direction(d), payload)
    if op == "closed":
        return Closed(conn, t, "client")
    return None


DRAWN_T0 = 1_700_000_000_000_000_000  # when drawn traffic starts, and its step
DRAWN_STEP = 1_000_000


def record_drawn(recorder: Recorder, ops: list) -> list[str]:
    """Drawn traffic (``op_event``'s steps) through a real Recorder, a step
    apart from DRAWN_T0, ticked after each, as the proxy drives it; its files."""
    recorder.start(DRAWN_T0)
    t = DRAWN_T0
    for op, conn, d, payload in ops:
        t += DRAWN_STEP
        event = op_event(op, conn, d, t, payload)
        if event is not None:
            recorder.receive(event)
        recorder.tick(t)
    return recorder.stop(t + DRAWN_STEP).files


# -- the command, as a user runs it --------------------------------------------------------------

_LISTENING = re.compile(rb"recording 127\.0\.0\.1:(\d+) -> ")


_STARTED: list[asyncio.subprocess.Process] = []


@atexit.register
def _stop_leftovers() -> None:
    """A test that failed half-way leaves its recorder running: stop it with
    the test run, as SIGTERM does (the file is finished, the writer exits)."""
    for proc in _STARTED:
        if proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(proc.pid, signal.SIGTERM)


class RecordProcess:
    """A ``whiztap record`` subprocess."""

    def __init__(self, proc: asyncio.subprocess.Process) -> None:
        self.proc = proc
        self.lines: list[str] = []
        self.port = 0
        self.first = ""  # its first line (start)
        _STARTED.append(proc)

    @classmethod
    async def start(cls, upstream: int, output: Path, *args: str, preexec_fn=None,
                    new_session: bool = False) -> RecordProcess:
        proc = await start_process("record", "--listen", "127.0.0.1:0", "--upstream", f"{LOCAL}:{upstream}",
                                   "-o", output, *args, preexec_fn=preexec_fn, start_new_session=new_session)
        rec = cls(proc)
        first = await asyncio.wait_for(proc.stdout.readline(), WAIT)  # printed even with -q
        rec.first = first.decode(errors="replace")  # where it listens, and its Foxglove and control addresses
        m = _LISTENING.match(first)
        assert m, first + await proc.stderr.read()
        rec.port = int(m.group(1))
        return rec

    async def connect(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        """Connect through the proxy (its first line said it listens; tries again for a little while)."""
        for _ in range(int(WAIT * 100)):
            try:
                return await asyncio.open_connection(LOCAL, self.port)
            except ConnectionRefusedError:
                await asyncio.sleep(0.01)
        raise AssertionError("whiztap record never listened")

    async def wait_line(self, pattern: str) -> str:
        while True:
            line = (await asyncio.wait_for(self.proc.stdout.readline(), WAIT)).decode()
            assert line, f"no line matching {pattern!r}; got {self.lines}"
            self.lines.append(line.rstrip("\n"))
            if re.search(pattern, line):
                return line

    async def finish(self, sig: int | None = signal.SIGINT, wait: float = 3 * WAIT) -> tuple[int, str, str]:
        """Signal the recorder (SIGINT: Ctrl-C) and wait up to ``wait`` seconds
        for it to finish its file and exit: status, stdout, stderr.  Wider than
        WAIT: the writer, a process of its own at a lower priority, writes what
        is still queued first, and beside other tests (make test runs several
        at once) it gets little of the CPU; a bound, never a timing assertion."""
        if sig is not None:
            self.proc.send_signal(sig)
        out, err = await asyncio.wait_for(self.proc.communicate(), wait)
        return self.proc.returncode, "\n".join(self.lines) + out.decode(), err.decode()



# -- reading recordings back ------------------------------------------------------------------------


@contextlib.asynccontextmanager
async def running_record(upstream: int, output: Path, *args: str):
    """``whiztap record`` in its own process; killed if the test fails half-way
    (a proxy under test may be too busy, or frozen, to stop)."""
    rec = await RecordProcess.start(upstream, output, *args)
    try:
        yield rec
    finally:
        if rec.proc.returncode is None:
            rec.proc.kill()
            await asyncio.wait_for(rec.proc.wait(), WAIT)


CONTROL_TOKEN = "whiztap-test-token"  # what tests give a TCP control API with --control-token


def post_status(url: str, body: bytes) -> int:
    """POST a JSON ``body`` to the TCP control API at ``url`` (its token CONTROL_TOKEN): the HTTP status it answered."""
    import urllib.error
    import urllib.request

    headers = {"Content-Type": "application/json", "Authorization": f"Bearer {CONTROL_TOKEN}"}
    request = urllib.request.Request(url, data=body, method="POST", headers=headers)
    try:
        with urllib.request.urlopen(request, timeout=WAIT) as reply:  # a local test server
            return reply.status
    except urllib.error.HTTPError as e:
        return e.code


def read_all(path: str) -> dict[str, list[dict]]:
    """Every message by topic, read with mcap's own indexed reader with CRC
    checks on, each checked against its channel's JSON schema."""
    by_topic: dict[str, list[dict]] = defaultdict(list)
    validators: dict[int, jsonschema.Draft202012Validator] = {}
    last_time: dict[str, int] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None, f"{path} has no summary: not finished"
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            assert channel.topic.startswith("/") and "." not in channel.topic
            assert channel.message_encoding == "json" and schema.encoding == SCHEMA_ENCODING
            if channel.id not in validators:
                validators[channel.id] = jsonschema.Draft202012Validator(json.loads(schema.data))
            decoded = json.loads(message.data)
            validators[channel.id].validate(decoded)
            assert message.log_time >= last_time.get(channel.topic, 0), f"log_time went back on {channel.topic}"
            last_time[channel.topic] = message.log_time
            by_topic[channel.topic].append(decoded)
    return by_topic


def on_channels(by_topic: dict[str, list[dict]], base: str) -> list[dict]:
    """The messages of every channel's topic under ``base`` (``/sensors/12``,
    ``/sensors/13``, ...: docs/recording-format.md), channel by channel."""
    return [m for topic in sorted(by_topic) if topic.startswith(base + "/") for m in by_topic[topic]]


class Read(NamedTuple):
    """A /tcp/reads message as the test reads it: with its stream offset."""

    conn: int
    dir: str
    t_ns: int
    offset: int
    data: bytes


def tcp_reads(scan: RecordingScan) -> Iterator[Read]:
    """Every /tcp/reads message the scan gives, as a Read, in file order."""
    for _t, topic, buf, start, stop in scan.records():
        if topic == TOPIC_READS:
            d = scan.decode(topic, buf, start, stop)
            yield Read(d["conn"], d["dir"], d["t_ns"], d["offset"], base64.b64decode(d["data"]))


class Segment(NamedTuple):
    offset: int  # stream offset of data[0]
    data: bytes


def rebuild_streams(path: str, topic: str = TOPIC_READS) -> dict[tuple[int, str], list[Segment]]:
    """Each (connection, direction) byte stream, from /tcp/reads or from /frames
    (docs/recording-format.md, "Rebuilding the streams").

    A stream is a list of contiguous segments: one, unless the recording has a
    gap (a capture that missed packets) or starts mid-stream (a rotated file).
    Redacted password bytes come back as '*'.
    """
    parts: dict[tuple[int, str], list[tuple[int, bytes]]] = {}
    with open(path, "rb") as f:
        scan = RecordingScan(f, (topic,))
        if topic == TOPIC_READS:
            for r in tcp_reads(scan):
                parts.setdefault((r.conn, r.dir), []).append((r.offset, r.data))
        else:
            for _topic, _t, m in scan.messages():
                parts.setdefault((m["conn"], m["dir"]), []).append((m["offset"], base64.b64decode(m["raw"])))
    streams: dict[tuple[int, str], list[Segment]] = {}
    for key, pieces in parts.items():
        joined: list[tuple[int, bytearray]] = []
        for offset, data in pieces:
            if joined and joined[-1][0] + len(joined[-1][1]) == offset:
                joined[-1][1].extend(data)
            elif data:
                joined.append((offset, bytearray(data)))
        streams[key] = [Segment(o, bytes(d)) for o, d in joined]
    return streams


def stream_bytes(segments: list[Segment]) -> bytes:
    """The whole stream, which must have no gap and start at offset 0."""
    if not segments:
        return b""
    where = ", ".join(f"{s.offset}+{len(s.data)}" for s in segments)
    assert len(segments) == 1 and segments[0].offset == 0, f"stream is not contiguous from 0 (segments at {where})"
    return segments[0].data


def streams(path: str, topic: str = TOPIC_READS) -> dict[tuple[int, str], bytes]:
    return {key: stream_bytes(segments) for key, segments in rebuild_streams(path, topic).items()}


def both_ways(path: str) -> dict[tuple[int, str], bytes]:
    """The streams rebuilt from /tcp/reads, checked equal to those from /frames
    (a run of unframed bytes whose raw /frames leaves out has its bytes taken
    from the reads: its offset and size must fit them)."""
    from_reads = streams(path, TOPIC_READS)
    from_frames: dict[tuple[int, str], bytearray] = {}
    with open(path, "rb") as f:
        for _, _, m in RecordingScan(f, (TOPIC_FRAMES,)).messages():
            key = (m["conn"], m["dir"])
            got = from_frames.setdefault(key, bytearray())
            assert m["offset"] == len(got)
            raw = base64.b64decode(m["raw"])
            if m.get("elided"):
                assert not raw
                raw = from_reads[key][m["offset"]:m["offset"] + m["size"]]
            assert len(raw) == m["size"]
            got += raw
    assert from_reads == {key: bytes(got) for key, got in from_frames.items()}
    return from_reads


def frame_items(frames: list[dict], conn: int, direction: str) -> list[tuple[str, bytes]]:
    return [(f["kind"], base64.b64decode(f["raw"])) for f in frames if f["conn"] == conn and f["dir"] == direction]


def check_frames(frames: list[dict], conn: int, direction: str, data: bytes) -> None:
    """One direction's /frames messages are the items of framing its whole
    stream, except that a run of unframed items and line breaks may be one
    message (with ``items``, and without its raw when ``elided``)."""
    items = framed(data, client=direction == "c2s")
    i = 0
    for f in frames:
        if (f["conn"], f["dir"]) != (conn, direction):
            continue
        group = items[i:i + f.get("items", 1)]
        i += len(group)
        raw = b"".join(r for _, r in group)
        if "items" in f:
            assert len(group) == f["items"] and {k for k, _ in group} <= {"unframed", "eol"}
            assert f["size"] == len(raw) and (f["elided"] or base64.b64decode(f["raw"]) == raw)
        else:
            assert group == [(f["kind"], base64.b64decode(f["raw"]))]
    assert i == len(items)


def framed(data: bytes, client: bool = False) -> list[tuple[str, bytes]]:
    """What a framer makes of a whole stream (framing does not depend on
    chunking); a client's first line is cut as the session cuts it, and framed
    as any other bytes (no server here asks for a password)."""
    framer = Framer()
    if client:
        framer.expect_password()
    items: list[Item] = []
    for item in framer.feed(data, 0) + framer.end(1):
        items += unasked(item) if item.kind is ItemKind.PASSWORD else [item]
    return [(i.kind.value, i.raw) for i in items]


def events(by_topic: dict[str, list[dict]], conn: int) -> list[str]:
    return [e["event"] for e in by_topic["/tcp/events"] if e["conn"] == conn]



# -- a scripted two-sided session through the real proxy ---------------------------------------------


async def play_steps(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, steps: list[tuple],
                     got: bytearray, timeout: float | None = WAIT) -> bool:
    """One side of a scripted connection: ``("send", bytes)``, ``("bytewise", bytes)``
    (one write per byte, each its own read at the far end), ``("recv", n)`` (wait
    for n bytes, added to ``got``), ``("sleep", s)``, ``("eof",)`` (half-close).
    Any other step, such as ``("close",)``, ends the play early: False."""
    for step in steps:
        if step[0] == "send":
            writer.write(step[1])
            await writer.drain()
        elif step[0] == "bytewise":
            for i in range(len(step[1])):
                writer.write(step[1][i:i + 1])
                await writer.drain()
                await asyncio.sleep(0.005)
        elif step[0] == "recv":
            got += await asyncio.wait_for(reader.readexactly(step[1]), timeout)
        elif step[0] == "sleep":
            await asyncio.sleep(step[1])
        elif step[0] == "eof":
            writer.write_eof()
        else:
            return False
    return True


class StepServer(TcpServer):
    """Plays ``steps`` (``play_steps``) on each connection: ``("send", bytes)``,
    ``("recv", n)`` (wait for n more bytes from the client), ``("close",)``;
    after the last step it reads until the client closes."""

    def __init__(self, steps: list[tuple]) -> None:
        super().__init__(LOCAL, 0)
        self.steps = steps
        self.received = bytearray()

    async def _serve_connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            if await play_steps(reader, writer, self.steps, self.received, timeout=None):
                self.received += await reader.read(-1)
        except (ConnectionError, OSError, asyncio.IncompleteReadError):
            pass
        finally:
            writer.close()


async def play_client(port: int, steps: list[tuple]) -> bytes:
    """The client side: ``steps`` as ``play_steps`` plays them; closes at the
    end and returns what it received."""
    reader, writer = await asyncio.open_connection(LOCAL, port)
    got = bytearray()
    try:
        await play_steps(reader, writer, steps, got)
    finally:
        writer.close()
        with contextlib.suppress(ConnectionError, OSError):
            await writer.wait_closed()
    return bytes(got)


async def record_dialogue(path: Path, server_steps: list[tuple], client_steps: list[tuple],
                          **options) -> Path:
    """One connection client -> real recording proxy -> scripted server, recorded to ``path``."""
    async with StepServer(server_steps) as server:
        async with recording(server.port, str(path), **options) as rec:
            await play_client(rec.proxy.port, client_steps)
            await asyncio.sleep(0.05)  # the server's close reaches the proxy
        assert rec.summary is not None
    return path
