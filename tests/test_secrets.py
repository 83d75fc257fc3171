"""A recording never shows the password, whatever the client's timing, order or framing.

The redaction rule (docs/recording-format.md, *Passwords*): in a session whose
server begins with ``sendchkpass`` (or never says whether it does), the
client's first line, up to its line break or a frame that completes, is masked
('*', line breaks kept).  These tests drive clients that do everything a real
one may (the password before the server's greeting in one write, one byte per
write, 200 bytes without a line break, then gone before the verdict, refused at
its first wrong byte) through the real recording proxy, and
look for the password, as text and as base64 at every alignment, in everything
a user can see: the file, ``record --analyze``, ``cat``, every report format,
``info``, the TUI (from the file and live) and ``replay -o``.  A VPN client's
eager commands must stay visible.
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import threading
from itertools import accumulate
from pathlib import Path

import pytest
import whiztap.sniffer.record.recorder as recorder_module
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from whiztap.analyzer.analysis.exchanges import load_exchanges
from whiztap.analyzer.protocol.examples import CONFIG
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.format import (
    STREAM_TOPICS,
    TOPIC_READS,
    metadata_record,
)
from whiztap.analyzer.recording.info import set_info
from whiztap.analyzer.recording.redaction import Redactor
from whiztap.analyzer.recording.scan import RecordingScan
from whiztap.analyzer.recording.sets import find_one
from whiztap.sniffer.record.record_run import RecordSettings
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile
from whiztap.sniffer.replay.plan import Selection, dry_run_lines, plan
from whiztap.sniffer.sim.simulator import Simulator
from whiztap.sniffer.sim.tcp_server import TcpServer
from whiztap.tui.data.model import TrafficModel
from whiztap.tui.data.sources import LiveSource, ProxyRig

from tests.outputs import FILE_OUTPUTS, SECRET, assert_no_leak, run, store_text
from tests.cli_support import start_process
from tests.record_support import LOCAL, WAIT, RecordProcess, op_event, play_client, play_steps, read_all, streams
from tests.test_readers_property import TOKENS, stream

C2S, S2C = Direction.C2S, Direction.S2C
COMMAND = b"rr1-24--0--0-ss1"
SENSOR, SENSOR_ANSWER = b"rr1-3--0--0-ss1", b"cr1-3--5--0-ss1"


def assert_file_has_no_leak(path: Path) -> dict[str, list[dict]]:
    by_topic = read_all(str(path))
    assert_no_leak(f"{path.name} (messages)", json.dumps(by_topic))
    for topic, messages in by_topic.items():
        for m in messages:
            for key in ("data", "raw"):
                if isinstance(m.get(key), str):  # base64 bytes (a servo's "data" is its position, a number)
                    assert_no_leak(f"{path.name} {topic} {key}", base64.b64decode(m[key]))
    return by_topic


# -- a server that plays one script per connection ----------------------------------------------


class ScriptServer(TcpServer):
    """Plays the next script on each connection, in accept order: ``("send", bytes)``,
    ``("recv", n)`` (wait for n bytes from the client), ``("close",)``; at the
    end it reads until the client closes."""

    def __init__(self, scripts: list[list[tuple]]) -> None:
        super().__init__(LOCAL, 0)
        self.scripts = list(scripts)
        self.accepted = asyncio.Event()  # the first connection came: 'whiztap record' trying the upstream at start

    async def _serve_connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        script = self.scripts.pop(0)
        self.accepted.set()
        try:
            if await play_steps(reader, writer, script, bytearray()):
                await asyncio.wait_for(reader.read(-1), WAIT)
        except (ConnectionError, OSError, asyncio.IncompleteReadError):
            pass
        finally:
            writer.close()


EAGER = SECRET + b"\r\n" + COMMAND
LONG = SECRET + b"x" * 187  # 200 bytes with no line break: still within a password's length
# (name, server script, client steps); the server waits for the client's first
# bytes before it greets, so they certainly reach the proxy before 'sendchkpass'.
CONNECTIONS = [
    ("eager, one write", [("recv", len(EAGER)), ("send", b"sendchkpass"), ("send", b"readytogo"), ("send", CONFIG)],
     [("send", EAGER), ("recv", 11 + 9 + len(CONFIG))]),
    ("eager, one byte per write", [("recv", len(SECRET) + 2), ("send", b"sendchkpass"), ("send", b"readytogo"),
                                   ("recv", len(COMMAND)), ("send", CONFIG)],
     [("bytewise", SECRET + b"\r\n"), ("recv", 11 + 9), ("send", COMMAND), ("recv", len(CONFIG))]),
    ("200 bytes without a line break", [("recv", len(LONG)), ("send", b"sendchkpass"), ("send", b"Failed Validation"),
                                     ("close",)],
     [("send", LONG), ("recv", 11 + 17)]),
    ("gone before the server spoke", [("recv", len(SECRET) + 2)], [("send", SECRET + b"\r\n")]),
    ("gone before the verdict", [("send", b"sendchkpass"), ("recv", len(SECRET))],
     [("recv", 11), ("send", SECRET)]),
    ("refused at its first byte", [("send", b"sendchkpass"), ("recv", 1), ("send", b"Failed Validation")],
     [("recv", 11), ("send", SECRET[:1]), ("recv", 17), ("bytewise", SECRET[1:]), ("send", b"\r\n" + COMMAND)]),
    ("vpn, eager", [("recv", 2 * len(SENSOR)), ("send", CONFIG + SENSOR_ANSWER)],
     [("send", COMMAND + SENSOR), ("recv", len(CONFIG) + len(SENSOR_ANSWER))]),
]
VPN_CONN = len(CONNECTIONS)


async def record_every_client(path: Path) -> str:
    """Each connection of CONNECTIONS, one after the other, through ``whiztap
    record --analyze``; what it printed."""
    async with ScriptServer([[]] + [server for _, server, _ in CONNECTIONS]) as server:
        rec = await RecordProcess.start(server.port, path, "--analyze")
        await asyncio.wait_for(server.accepted.wait(), WAIT)  # record's try of the upstream: nothing to play
        for n, (_name, _, steps) in enumerate(CONNECTIONS, 1):
            await play_client(rec.port, steps)
            await rec.wait_line(rf"#{n} closed by")
        code, stdout, stderr = await rec.finish()
    assert code == 0, stderr
    return stdout + stderr


@pytest.mark.slow
async def test_an_eager_or_odd_client_never_leaves_its_password_anywhere(tmp_path):
    path = tmp_path / "eager.mcap"
    printed = await record_every_client(path)
    assert_no_leak("record --analyze", printed)

    by_topic = assert_file_has_no_leak(path)
    recorded = streams(str(path))
    for n, (name, _, steps) in enumerate(CONNECTIONS, 1):
        sent = b"".join(step[1] for step in steps if step[0] in ("send", "bytewise"))
        assert len(recorded[(n, "c2s")]) == len(sent), name  # masking keeps every length
    assert recorded[(2, "c2s")].endswith(b"\r\n" + COMMAND)  # sent after the verdict: shown
    assert recorded[(6, "c2s")].endswith(b"\r\n" + COMMAND)
    assert recorded[(VPN_CONN, "c2s")] == COMMAND + SENSOR  # no login in VPN mode: nothing masked
    closed = {e["conn"]: e for e in by_topic["/tcp/events"] if e["event"] == "closed"}
    assert closed[VPN_CONN]["mode"] == "vpn"
    assert closed[1]["handshake"] == "readytogo" and closed[2]["handshake"] == "readytogo"

    env = {"WHIZTAP_PASSWORD": SECRET.decode()}
    for name, read in FILE_OUTPUTS.items():  # every reader of a recording (tests/outputs.py)
        assert_no_leak(name, read(path))
    assert_no_leak("replay --dry-run", run("replay", str(path), "--dry-run", env=env))

    # replay -o records the replayed session: the password it sends (from the
    # environment) is masked there too
    replayed = tmp_path / "replayed.mcap"
    async with Simulator(mode="winsock", password=SECRET) as sim:
        proc = await start_process("replay", path, "--target", f"{LOCAL}:{sim.port}", "--pace", "max", "--timeout",
                                   "0.5", "-o", replayed, "-v", env={**os.environ, **env})
        out, err = await asyncio.wait_for(proc.communicate(), WAIT)
    assert proc.returncode in (0, 1), err
    assert_no_leak("replay -v", out + err)
    replay_topics = assert_file_has_no_leak(replayed)
    verdicts = [e.get("handshake") for e in replay_topics["/tcp/events"] if e["event"] == "closed"]
    assert "readytogo" in verdicts  # the real password was sent, and accepted


async def test_the_live_tui_shows_the_bytes_the_file_has(tmp_path):
    """The TUI's proxy taps traffic before the writer: it must mask the same
    bytes the file masks, from the same rule."""
    path = tmp_path / "live.mcap"
    async with ScriptServer([server for _, server, _ in CONNECTIONS]) as server:
        settings = RecordSettings((LOCAL, 0), (LOCAL, server.port), str(path), quiet=True)
        source = LiveSource(ProxyRig(settings), "live")
        await source.start()
        port = source.recording.proxy.port
        for _name, _, steps in CONNECTIONS:
            await play_client(port, steps)
        await asyncio.sleep(0.2)  # the last close reaches the proxy
        await source.stop()
    model = TrafficModel(str(path), redact_passwords=True)
    source.feed(model, threading.Event())
    assert_no_leak("the live TUI", store_text(model))
    assert_file_has_no_leak(path)
    store = model.store
    shown: dict[tuple[int, bool], bytes] = {}
    for i in range(store.count):
        key = (store.conn[i], bool(store.flags[i] & 0x10))
        shown[key] = shown.get(key, b"") + bytes(store.raws[store.raw_end[i - 1] if i else 0:store.raw_end[i]])
    recorded = streams(str(path))
    for n in range(1, len(CONNECTIONS) + 1):
        assert shown[(n, False)] == recorded[(n, "c2s")], CONNECTIONS[n - 1][0]


# -- the property: random traffic into the Recorder, then every reader -------------------------------

T0 = 1_700_000_000_000_000_000
MS = 1_000_000
SERVER_TOKENS = [t for t in TOKENS if t not in (b"readytogo", b"Failed Validation")]
server_token = st.one_of(st.sampled_from(SERVER_TOKENS), st.binary(min_size=1, max_size=12))


def _cut(draw, data: bytes) -> list[bytes]:
    """``data`` in random pieces (reads)."""
    cuts = sorted(draw(st.lists(st.integers(0, max(len(data), 1)), max_size=6)))
    return [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)]) if b > a]


def _interleave(draw, *queues: list) -> list:
    """The queues' items merged in a random order, each queue keeping its own."""
    queues = [list(q) for q in queues]
    merged = []
    while any(queues):
        live = [q for q in queues if q]
        merged.append(live[draw(st.integers(0, len(live) - 1))].pop(0))
    return merged


@st.composite
def logins(draw, conn: int):
    """One connection's ops: ("data", conn, dir, bytes), ("half", conn, dir),
    ("closed", conn), ("tick", expire); and what kind of server it had."""
    kind = draw(st.sampled_from(["winsock", "winsock", "silent", "partial", "vpn"]))
    lead = draw(st.sampled_from([b"", b"\r\n", b"\n"]))
    filler = b"x" * 20_000 if draw(st.integers(0, 9)) == 0 else b""  # beyond the undecided cap
    if kind == "vpn":
        client_pre = draw(st.sampled_from([b"rr1-24--0--0-ss1", b"rr1-12--0--0-ss1rr1-0--0--2-ss1", b"hello\r\n"]))
        greeting = lead + draw(st.sampled_from([CONFIG, b"cr1-12--100--0-ss1", b"\xff\xd8\xff", b"Welcome"]))
    else:
        # the password is the client's first line: its end a line break, a frame, or none yet
        ender = draw(st.sampled_from([b"\r\n", b"\n", b"\r", COMMAND, b"sr1-25--\x0c\x00\x00\x07--0-ss1", b""]))
        after = draw(stream) + filler if ender else b""
        client_pre = draw(st.sampled_from([b"", b"\r\n", b"\n"])) + SECRET + ender + after
        greeting = {"winsock": lead + b"sendchkpass", "silent": lead, "partial": lead + b"sendch"}[kind]
    middle = b"".join(draw(st.lists(server_token, max_size=3))) if kind == "winsock" else b""
    verdict = draw(st.sampled_from([b"readytogo", b"Failed Validation", b""])) if kind == "winsock" else b""
    server = greeting + middle + verdict
    server_pieces = _cut(draw, server)
    if verdict:  # the piece that completes the verdict comes after every password byte
        last = list(accumulate(len(piece) for piece in server_pieces)).index(len(server))
        early, decisive, late = server_pieces[:last], [server_pieces[last]], []
    else:
        early, decisive, late = server_pieces, [], []
    client_post = draw(stream) if verdict or kind == "vpn" else b""
    if verdict or kind == "vpn":
        late += _cut(draw, draw(stream))  # the server's answers, or more junk
    c2s = [("data", conn, "c2s", p) for p in _cut(draw, client_pre)]
    post = [("data", conn, "c2s", p) for p in _cut(draw, client_post)]
    s2c_early = [("data", conn, "s2c", p) for p in early]
    s2c_late = [("data", conn, "s2c", p) for p in [*decisive, *late]]
    ops = _interleave(draw, c2s, s2c_early) + _interleave(draw, s2c_late, post)
    for d in ("c2s", "s2c"):  # a half-close anywhere after that side's last bytes
        if draw(st.booleans()):
            last_of = max((i for i, op in enumerate(ops) if op[2] == d), default=-1)
            ops.insert(draw(st.integers(last_of + 1, len(ops))), ("half", conn, d, b""))
    for _ in range(draw(st.integers(0, 3))):
        ops.insert(draw(st.integers(0, len(ops))), ("tick", conn, "", draw(st.booleans())))
    ops = [("opened", conn, "", b""), *ops]
    if draw(st.booleans()):
        ops.append(("closed", conn, "", b""))
    return kind, ops


@st.composite
def sessions(draw):
    drawn = [draw(logins(conn)) for conn in range(1, draw(st.integers(1, 3)) + 1)]
    return [kind for kind, _ in drawn], _interleave(draw, *[ops for _, ops in drawn])


class FakeClock:
    """The recorder's monotonic clock, moved on by the test: a tick may let the
    hold limit pass, or not."""

    def __init__(self) -> None:
        self.now = 1000.0

    def monotonic(self) -> float:
        return self.now


def _record_ops(path: Path, ops: list, clock: FakeClock) -> dict[int, bytes]:
    """Through the real Recorder, as the proxy drives it; what each client sent."""
    recorder = Recorder(RecordingFile(str(path), metadata_record(source="test", secrets="redacted")))
    recorder.start(T0)
    t = T0
    sent: dict[int, bytes] = {}
    for op, conn, d, payload in ops:
        t += MS
        if op == "tick":
            clock.now += 60.0 if payload else 0.001
            recorder.tick(t)
            continue
        recorder.receive(op_event(op, conn, d, t, payload))
        if op == "data" and d == "c2s":
            sent[conn] = sent.get(conn, b"") + payload
    recorder.stop(t + MS)
    return sent


def _says_no_login(server: bytes) -> bool:
    """The server's bytes so far show it does not ask for a password: line breaks
    aside, they have begun and are not the beginning of 'sendchkpass'.  A line
    break alone, or 's' of a configuration frame, does not tell yet."""
    head = server.lstrip(b"\r\n")[:len(b"sendchkpass")]
    return bool(head) and not b"sendchkpass".startswith(head)


def _undisturbed_vpn(kinds: list[str], ops: list) -> set[int]:
    """VPN connections whose client bytes no expired hold could have masked:
    no tick let the limit pass while they waited for the server's bytes to say
    that there is no login (docs/recording-format.md, *Passwords*, rules 1, 3, 5)."""
    waiting: set[int] = set()
    spoiled: set[int] = set()
    server: dict[int, bytes] = {}
    decided: set[int] = set()
    for op, conn, d, payload in ops:
        if op == "data" and d == "c2s" and conn not in decided:
            waiting.add(conn)
        elif op == "data" and d == "s2c":
            server[conn] = server.get(conn, b"") + payload
            if _says_no_login(server[conn]):
                decided.add(conn)
                waiting.discard(conn)
        elif op == "tick" and payload:
            spoiled |= waiting
    return {n for n, kind in enumerate(kinds, 1) if kind == "vpn"} - spoiled


def _check_stream_order(path: Path, sent: dict[int, bytes]) -> None:
    """Per connection: opened first; each direction's reads contiguous from 0;
    no read after its side's half-close or the connection's close."""
    ended: set[tuple[int, str]] = set()
    offsets: dict[tuple[int, str], int] = {}
    opened: set[int] = set()
    with open(path, "rb") as f:
        for topic, _t, record in RecordingScan(f, STREAM_TOPICS).messages():
            if topic == TOPIC_READS:
                key = (record["conn"], record["dir"])
                assert record["conn"] in opened, f"a read of #{record['conn']} before it opened"
                assert key not in ended, f"a read of {key} after its side ended"
                assert record["offset"] == offsets.get(key, 0), f"{key} out of stream order"
                offsets[key] = record["offset"] + record["size"]
                continue
            conn, event = record["conn"], record["event"]
            if event == "opened":
                opened.add(conn)
            elif event == "half_closed":
                ended.add((conn, record["dir"]))
            elif event == "closed":
                ended |= {(conn, "c2s"), (conn, "s2c")}
    for conn, data in sent.items():
        assert offsets.get((conn, "c2s"), 0) == len(data)


def _every_reader(path: Path) -> list[tuple[str, str | bytes]]:
    """What each reader shows of the file (every one tests/outputs.py registers,
    and the replay's plan both ways); none may raise."""
    shown: list[tuple[str, str | bytes]] = [(name, read(path)) for name, read in FILE_OUTPUTS.items()]
    recording = find_one([str(path)])
    sessions_ = load_exchanges(recording)
    for segments in (False, True):
        shown.append(("replay plan", "\n".join(dry_run_lines(plan(sessions_, Selection(), segments),
                                                              sessions_.start_ns))))
    set_info(list(recording.parts))
    return shown


# Found by the property; the oracle was wrong both times, not the recorder.
# A VPN client's first bytes, held while the server has sent only a line break
# (which decides nothing), are masked when the hold limit passes (rule 5).
HELD_PAST_A_LINE_BREAK = (["vpn"], [
    ("opened", 1, "", b""), ("data", 1, "c2s", b"r"), ("data", 1, "s2c", b"\r"), ("tick", 1, "", True),
    ("data", 1, "c2s", b"r1-24--0--0-ss1"), ("data", 1, "s2c", b"\n" + CONFIG), ("closed", 1, "", b"")])
# A servo answer puts a number under "data" in /servos/1: not base64.
SERVO_ANSWER = (["vpn"], [
    ("opened", 1, "", b""), ("data", 1, "c2s", b"rr1-24--0--0-ss1rr1-1--0--2-ss1"),
    ("data", 1, "s2c", CONFIG + b"cr1-1--400--0-ss1"), ("closed", 1, "", b"")])


@pytest.mark.slow
@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(drawn=sessions())
@example(drawn=HELD_PAST_A_LINE_BREAK)
@example(drawn=SERVO_ANSWER)
def test_no_sequence_of_events_puts_the_password_in_a_recording(tmp_path_factory, monkeypatch, drawn):
    """Random bytes, reads cut anywhere, the password as the client's first
    line (ended by a line break, a frame, or nothing before the verdict), the
    greeting before or after it, half-closes and closes in any order, holds
    that expire or not: no reader raises, the file is in stream order, the
    password shows nowhere, and a VPN client's bytes stay visible."""
    kinds, ops = drawn
    clock = FakeClock()
    monkeypatch.setattr(recorder_module, "time", clock)
    path = tmp_path_factory.mktemp("secret") / "r.mcap"
    sent = _record_ops(path, ops, clock)
    assert_file_has_no_leak(path)
    _check_stream_order(path, sent)
    for where, text in _every_reader(path):
        assert_no_leak(where, text)
    recorded = streams(str(path))
    for conn in _undisturbed_vpn(kinds, ops):
        assert recorded.get((conn, "c2s"), b"") == sent.get(conn, b""), f"#{conn}: VPN bytes were masked"


# -- the rule does not depend on how the bytes were cut into reads ----------------------------------

GREETINGS = [b"sendchkpass", b"\r\nsendchkpass", b"sendch", b"", b"sr1-\x02000200-ss1", b"cr1-3--5--0-ss1"]
FIRST_LINES = [SECRET + b"\r\n", SECRET + b"\n", SECRET + COMMAND, SECRET + b"rr1-", SECRET, COMMAND, b"\x00" * 300]


@st.composite
def arrivals(draw):
    """A client's and a server's bytes in one arrival order, byte by byte:
    (client bytes, server bytes, for each byte in order whether it is the client's)."""
    lead = draw(st.sampled_from([b"", b"\r\n", b"\n", b"\r"]))
    client = lead + draw(st.one_of(st.sampled_from(FIRST_LINES), stream)) + draw(stream)
    server = draw(st.sampled_from(GREETINGS)) + b"".join(draw(st.lists(st.sampled_from(
        [b"readytogo", b"Failed Validation", b"\r\n", b"cr1-0--7--0-ss1", b"sendchkpass"]), max_size=3)))
    # how many client bytes arrived before each server byte
    before = sorted(draw(st.lists(st.integers(0, len(client)), min_size=len(server), max_size=len(server))))
    order: list[bool] = []
    for n in [*before, len(client)]:
        order += [True] * (n - order.count(True)) + [False]
    return client, server, order[:-1]


def _masked(client: bytes, server: bytes, order: list[bool], cuts: set[int]) -> bytes:
    """What a Redactor lets out of the client's bytes, the arrival order cut into
    reads at each direction change and at ``cuts``."""
    redactor: Redactor[int] = Redactor(hold_s=1e9)
    redactor.opened(1)
    out = bytearray()
    streams_ = {True: client, False: server}
    done = {True: 0, False: 0}
    i = 0
    while i < len(order):
        j = i + 1
        while j < len(order) and order[j] == order[i] and j not in cuts:
            j += 1
        side = order[i]
        data = streams_[side][done[side]:done[side] + j - i]
        done[side] += j - i
        redactor.read(1, C2S if side else S2C, data, 0, 0.0)
        i = j
        out += b"".join(r.data for r in redactor.released() if r.direction is C2S)
    redactor.closed(1)
    redactor.event(1, 0)
    out += b"".join(r.data for r in redactor.released() if r.direction is C2S)
    return bytes(out)


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(drawn=arrivals(), cuts=st.sets(st.integers(0, 200), max_size=30))
def test_what_is_masked_does_not_depend_on_how_reads_were_cut(drawn, cuts):
    """Given the order in which the bytes arrived, any cutting into reads masks
    the same client bytes as one read per byte; lengths and line breaks stay;
    nothing past the client's first line break is masked; a password line is
    masked when the server asked for it (or never said), nothing when it
    began with anything else."""
    client, server, order = drawn
    one_per_byte = _masked(client, server, order, set(range(len(order))))
    assert _masked(client, server, order, cuts) == one_per_byte
    assert len(one_per_byte) == len(client)
    assert all(a == b or (a == ord("*") and b not in b"\r\n") for a, b in zip(one_per_byte, client))
    start = len(client) - len(client.lstrip(b"\r\n"))
    line_end = min((i for i in (client.find(b"\r", start), client.find(b"\n", start)) if i != -1), default=None)
    if line_end is not None:
        assert one_per_byte[line_end:] == client[line_end:]
    said = server.lstrip(b"\r\n")[:len(b"sendchkpass")]
    if said and not b"sendchkpass".startswith(said):
        assert one_per_byte == client  # no login: nothing masked
    elif client[start:].startswith(SECRET) and client[start + len(SECRET):][:1] in (b"\r", b"\n", b"r"):
        assert one_per_byte[start:start + len(SECRET)] == b"*" * len(SECRET)


def _out(redactor: Redactor) -> list[tuple[str, bytes]]:
    return [(r.record, r.data) for r in redactor.released()]


def test_bytes_held_too_long_or_too_many_are_masked_never_shown():
    """The clock and the bounds only mask, and only what may be the password:
    what they let out early is masked, and what comes once the server has
    spoken follows the rule."""
    redactor: Redactor[str] = Redactor(hold_s=2.0, queue_cap=1000)
    redactor.opened(1)
    redactor.read(1, C2S, b"pw\r\n" + COMMAND, "first", now=0.0)
    redactor.tick(1.0)
    assert _out(redactor) == []  # undecided, within the limit: held
    redactor.tick(2.5)
    assert _out(redactor) == [("first", b"**\r\n" + COMMAND)]  # the line only
    redactor.read(1, S2C, CONFIG, "answer", now=3.0)  # VPN: from here on nothing is masked
    redactor.read(1, C2S, SENSOR, "second", now=3.0)
    assert _out(redactor) == [("answer", CONFIG), ("second", SENSOR)]

    redactor.opened(2)  # a first line that waits on a Set Configuration of 21 kB still arriving
    line = b"pw" + b"sr1-25--" + b"\x0c\x00\x00" * 7000
    redactor.read(2, C2S, line, "many", now=4.0)  # beyond the undecided cap
    assert _out(redactor) == [("many", b"*" * len(line))]
    redactor.opened(3)
    redactor.read(3, C2S, b"pw", "held", now=4.0)
    redactor.opened(4)
    redactor.read(4, C2S, COMMAND, "behind", now=4.0)
    redactor.read(4, S2C, b"cr1-24--1--0-ss1" * 70, "flood", now=4.0)  # too much waits behind #3
    assert _out(redactor) == [("held", b"**"), ("behind", COMMAND), ("flood", b"cr1-24--1--0-ss1" * 70)]
