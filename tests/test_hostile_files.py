"""Files made to hurt, given to every command that reads a recording.

Truncated files, decompression bombs, chunks that lie about their size, another
tool's MCAP files, junk after the magic, damaged chunks, bad metadata and
malformed messages: each command says one line on stderr and exits 2 (3 is
analyze's gate on a file with nothing to judge), never a traceback or
"unexpected error", in bounded memory and time.  ``recover`` salvages what is
readable instead and says what it skipped.

This extends tests/test_bad_input.py (missing, empty, binary, folder, text,
junk-after-magic and foreign files, and the commands that read other inputs).
The matrix runs in process (``whiztap.analyzer.cli.root.main``, the real entry point, fast);
the bombs run as subprocesses, whose peak memory the kernel reports.
"""

from __future__ import annotations

import functools
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from itertools import pairwise
from pathlib import Path

import lz4.frame
import pytest
import zstandard
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.format import METADATA_NAME, metadata_record
from whiztap.analyzer.recording.mcap import MAGIC
from whiztap.analyzer.traffic import Closed, Data, Opened
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile

from tests.cli_support import WHIZTAP, run_cli

T0 = 1_700_000_000_000_000_000
READS, EVENTS = 1, 2  # channel ids in a whiztap recording (the order of whiztap.analyzer.recording.format.TOPICS)
MIB = 1 << 20
MEMORY_BOUND = 400 * MIB  # peak RSS allowed to a command reading a hostile file
TIME_BOUND_S = 60

# -- MCAP records, built by hand -------------------------------------------------------------------


def record(op: int, body: bytes) -> bytes:
    return struct.pack("<BQ", op, len(body)) + body


def string(s: str | bytes) -> bytes:
    b = s.encode() if isinstance(s, str) else s
    return struct.pack("<I", len(b)) + b


def message(channel: int, data: bytes, t: int = T0) -> bytes:
    return record(0x05, struct.pack("<HIQQ", channel, 0, t, t) + data)


def message_index(channel: int, offsets: list[int]) -> bytes:
    entries = b"".join(struct.pack("<QQ", T0, o) for o in offsets)
    return record(0x07, struct.pack("<HI", channel, len(entries)) + entries)


def chunk(records: bytes, compression: str = "zstd", *, claimed: int | None = None, crc: int | None = None,
          data: bytes | None = None) -> bytes:
    """A Chunk record holding ``records``; ``claimed``, ``crc`` and ``data``
    (the compressed bytes) say something else when given."""
    if data is None:
        data = {"zstd": zstandard.ZstdCompressor().compress, "lz4": lz4.frame.compress, "": bytes}[compression](
            records)
    head = struct.pack("<QQQI", T0, T0, len(records) if claimed is None else claimed,
                       zlib.crc32(records) if crc is None else crc)
    return record(0x06, head + string(compression) + struct.pack("<Q", len(data)) + data)


END = record(0x0F, struct.pack("<I", 0)) + record(0x02, struct.pack("<QQI", 0, 0, 0)) + MAGIC


def metadata(values: dict[bytes, bytes], name: bytes = METADATA_NAME.encode()) -> bytes:
    body = b"".join(string(k) + string(v) for k, v in values.items())
    return record(0x0C, string(name) + struct.pack("<I", len(body)) + body)


def zeros(compressor, size: int) -> bytes:
    """``size`` zero bytes, compressed a MiB at a time."""
    out = [compressor.begin()] if hasattr(compressor, "begin") else []
    out += [compressor.compress(bytes(MIB)) for _ in range(size // MIB)]
    return b"".join(out) + compressor.flush()


# -- a real recording, and its layout -------------------------------------------------------------------


def write_recording(path: Path, exchanges: int = 60, chunk_size: int = 2048, compression: str = "zstd") -> Path:
    """A winsock session through the real recorder, in small chunks (so damage
    can fall between good ones)."""
    file = RecordingFile(str(path), metadata_record(source="test", listen="", upstream=""), chunk_size=chunk_size,
                         compression=compression)
    rec = Recorder(file)
    rec.start(T0)
    rec.receive(Opened(1, T0 + 1, "127.0.0.1:5555", "127.0.0.1:5000"))
    t = T0 + 10
    for direction, data in [(Direction.S2C, b"sendchkpass"), (Direction.C2S, b"secret"),
                            (Direction.S2C, b"readytogo")]:
        rec.receive(Data(1, direction, t, data))
        t += 1000
    for i in range(exchanges):
        rec.receive(Data(1, Direction.C2S, t, b"rr1-%d--0--0-ss1" % (i % 4)))
        rec.receive(Data(1, Direction.S2C, t + 500, b"cr1-%d--%d--0-ss1" % (i % 4, 1000 + i)))
        t += 1_000_000
    rec.receive(Closed(1, t, "client", "closed"))
    rec.stop(t + 1)
    return path


@functools.cache
def base(compression: str = "zstd") -> bytes:
    with tempfile.TemporaryDirectory() as tmp:
        return write_recording(Path(tmp) / "base.mcap", compression=compression).read_bytes()


def layout(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, record length) of each record up to the footer."""
    out, pos = [], 8
    while pos + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, pos)
        out.append((pos, op, 9 + length))
        pos += 9 + length
        if op == 0x02:
            break
    return out


def offsets_of(op: int, data: bytes | None = None) -> list[int]:
    return [pos for pos, o, _ in layout(data or base()) if o == op]


def prefix() -> bytes:
    """Magic, header, metadata, schemas and channels of the base recording."""
    return base()[:offsets_of(0x06)[0]]


def data_end() -> int:
    return offsets_of(0x0F)[0]


def with_reads(*payloads: bytes, channel: int = READS, meta: bytes | None = None) -> bytes:
    """A whiztap recording whose one chunk holds these messages on ``channel``."""
    records, offsets = b"", []
    for p in payloads:
        offsets.append(len(records))
        records += message(channel, p)
    start = prefix()
    if meta is not None:
        at = offsets_of(0x0C)[0]
        length = next(n for pos, o, n in layout(base()) if pos == at)
        start = start[:at] + meta + start[at + length:]
    return start + chunk(records) + message_index(channel, offsets) + END


def damaged(at: int, edit: Callable[[bytearray, int], None]) -> bytes:
    """The base recording with one edit to the chunk at ``at``; edit(buf, body) gets the body offset."""
    buf = bytearray(base())
    edit(buf, at + 9)
    return bytes(buf)


def read_chunks(data: bytes | None = None) -> list[int]:
    """Offsets of the chunks holding /tcp/reads (the ones every reader decompresses)."""
    records = layout(data or base())
    return [pos for (pos, op, _), (index, op2, _) in pairwise(records)
            if op == 0x06 and op2 == 0x07 and struct.unpack_from("<H", data or base(), index + 9)[0] == READS]


def middle_chunk() -> int:
    chunks = read_chunks()
    return chunks[len(chunks) // 2]


def flip_crc(buf: bytearray, body: int) -> None:
    buf[body + 24] ^= 0xFF  # the uncompressed CRC


def corrupt_data(buf: bytearray, body: int) -> None:
    n = struct.unpack_from("<I", buf, body + 28)[0]
    data = body + 32 + n + 8
    size = struct.unpack_from("<Q", buf, body + 32 + n)[0]
    for i in range(data + 4, data + size - 4, 7):  # past the zstd magic, before the checksum
        buf[i] ^= 0x5A


def read_json(**fields: object) -> bytes:
    d = {"conn": 1, "dir": "c2s", "t_ns": T0, "offset": 0, "size": 4, "data": "cnIxLQ=="}
    d.update(fields)
    return json.dumps({k: v for k, v in d.items() if v is not ...}).encode()


def foreign(path: Path, topics: dict[str, bytes] | None = None) -> Path:
    """An MCAP file another tool wrote with the mcap library."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start("other", "another tool")
        for topic, data in (topics or {}).items():
            channel = w.register_channel(topic, "json", w.register_schema("Foo", "jsonschema", b"{}"))
            w.add_message(channel, log_time=T0, data=data, publish_time=T0)
        w.finish()
    return path


def _truncations() -> dict[str, Callable[[], bytes]]:
    def cut(where: Callable[[], int]) -> Callable[[], bytes]:
        return lambda: base()[:where()]

    def first_chunk():
        return offsets_of(0x06)[0]

    return {
        "cut-after-magic": cut(lambda: 8),
        "cut-in-header": cut(lambda: 13),
        "cut-in-metadata": cut(lambda: offsets_of(0x0C)[0] + 30),
        "cut-in-first-chunk": cut(lambda: first_chunk() + 40),
        "cut-before-an-index": cut(lambda: offsets_of(0x07)[0]),
        "cut-in-an-index": cut(lambda: offsets_of(0x07)[0] + 12),
        "cut-in-a-middle-chunk": cut(lambda: middle_chunk() + 50),
        "cut-before-data-end": cut(data_end),
    }


# kind -> the file's bytes, given a folder for the ones the mcap library writes
KINDS: dict[str, Callable[[Path], bytes]] = {
    **{name: (lambda build: lambda tmp: build())(make) for name, make in _truncations().items()},
    "cut-in-summary": lambda tmp: base()[:data_end() + 40],
    "junk-after-header": lambda tmp: prefix() + bytes(range(256)) * 20,
    "huge-record-length": lambda tmp: prefix() + struct.pack("<BQ", 0x06, 1 << 63) + bytes(64),
    "chunk-claims-exabytes": lambda tmp: prefix() + chunk(b"", "", claimed=1 << 62, crc=0, data=b"x" * 10)
    + message_index(READS, [0]) + END,
    "chunk-shorter-than-claimed": lambda tmp: prefix() + chunk(message(READS, read_json()), claimed=10 * MIB)
    + message_index(READS, [0]) + END,
    "uncompressed-size-mismatch": lambda tmp: prefix() + chunk(b"", "", claimed=100, crc=0, data=b"\x05" * 40)
    + message_index(READS, [0]) + END,
    "unknown-compression": lambda tmp: prefix() + chunk(b"", "brotli", claimed=4, crc=0, data=b"abcd")
    + message_index(READS, [0]) + END,
    "index-claims-huge-count": lambda tmp: prefix() + chunk(message(READS, read_json()))
    + record(0x07, struct.pack("<HI", READS, 0xFFFFFFF0)) + END,
    "index-points-outside": lambda tmp: prefix() + chunk(message(READS, read_json()))
    + message_index(READS, [1 << 40]) + END,
    "record-overruns-chunk": lambda tmp: prefix() + chunk(record(0x05, struct.pack("<HIQQ", READS, 0, T0, T0))[:1]
                                                          + struct.pack("<Q", 1 << 40) + bytes(30)) + END,
    "zeros-in-a-chunk": lambda tmp: prefix() + chunk(bytes(MIB)) + END,  # op 0, length 0: forever
    "bad-crc": lambda tmp: damaged(middle_chunk(), flip_crc),
    "corrupt-zstd": lambda tmp: damaged(middle_chunk(), corrupt_data),
    "empty-recording": lambda tmp: prefix() + END,
    "foreign-topics": lambda tmp: foreign(tmp / "f.mcap", {"/foo": b"{}", "/camera/raw": b"{}"}).read_bytes(),
    "foreign-no-channels": lambda tmp: foreign(tmp / "f.mcap").read_bytes(),
    "foreign-tcp-reads": lambda tmp: foreign(tmp / "f.mcap", {"/tcp/reads": b'{"hello": "world"}'}).read_bytes(),
    "metadata-not-utf8": lambda tmp: with_reads(read_json(), meta=metadata({b"format_version": b"\xff\xfe"})),
    "metadata-map-overruns": lambda tmp: with_reads(read_json(), meta=record(
        0x0C, string(METADATA_NAME) + struct.pack("<I", 1 << 30) + string("k"))),
    "metadata-string-overruns": lambda tmp: with_reads(read_json(), meta=record(
        0x0C, string(METADATA_NAME) + struct.pack("<I", 12) + struct.pack("<I", 1 << 31) + b"abcdefgh")),
    "metadata-wrong-values-0001": lambda tmp: with_reads(read_json(), meta=metadata(
        {b"format_version": b"99", b"part": "²".encode(), b"split_size": b"x", b"session_id": b"s",
         b"checksum_rule": b"no-such-rule", b"secrets": b"maybe", b"start_time_ns": b"soon"})),
    "metadata-missing-keys": lambda tmp: with_reads(read_json(), meta=metadata({})),
    "read-missing-fields": lambda tmp: with_reads(b'{"conn":1}'),
    "read-wrong-types": lambda tmp: with_reads(read_json(conn="1", data=5)),
    "read-bad-direction": lambda tmp: with_reads(read_json(dir="up")),
    "read-bool-conn": lambda tmp: with_reads(read_json(conn=True)),
    "read-negative-offset": lambda tmp: with_reads(read_json(offset=-5)),
    "read-huge-number": lambda tmp: with_reads(read_json(t_ns=10 ** 40)),
    "read-bad-base64": lambda tmp: with_reads(read_json(data="!!not base64!!")),
    "read-not-utf8": lambda tmp: with_reads(b'{"conn":1,"dir":"c2s","t_ns":1,"offset":0,"size":1,"data":"\xff"}'),
    "read-not-json": lambda tmp: with_reads(b"\x00\x01 not json"),
    "read-an-array": lambda tmp: with_reads(b"[1, 2, 3]"),
    "read-many-digits": lambda tmp: with_reads(b'{"conn":%s,"dir":"c2s","t_ns":1,"offset":0,"size":0,"data":""}'
                                               % (b"9" * 5000)),
    "event-missing-fields": lambda tmp: with_reads(b'{"event":"opened"}', channel=EVENTS),
    "event-wrong-types": lambda tmp: with_reads(b'{"conn":1,"event":"half_closed","t_ns":"late","dir":"c2s"}',
                                                channel=EVENTS),
    "event-bad-direction": lambda tmp: with_reads(b'{"conn":1,"event":"half_closed","t_ns":1,"dir":"up"}',
                                                  channel=EVENTS),
    "event-not-an-object": lambda tmp: with_reads(b'"opened"', channel=EVENTS),
}

# What a command does with a file that is not an error: a verdict, a report
# of the file, a copy, or (replay, against a closed port) failing to connect.
TRUNCATED = {"info": 0, "recover": 0}  # info says how it was cut; recover is for this
READABLE = {"analyze": (0, 1), "cat": 0, "info": 0, "recover": 0}
SALVAGED = {"recover": 0}  # damage: every reader refuses, recover skips it and copies the rest
MESSAGES = {"info": 0, "recover": 0}  # a bad message: info and recover never decode one
EXPECTED: dict[str, dict[str, int | tuple[int, ...]]] = {
    "cut-after-magic": {"info": 0}, "cut-in-header": {"info": 0}, "cut-in-metadata": {"info": 0},  # nothing to save
    "cut-in-first-chunk": TRUNCATED, "cut-before-an-index": TRUNCATED, "cut-in-an-index": TRUNCATED,
    "cut-in-a-middle-chunk": TRUNCATED, "cut-before-data-end": TRUNCATED,
    "cut-in-summary": READABLE,  # every chunk is there: only the index is lost
    "empty-recording": {**READABLE, "analyze": 3},
    "foreign-topics": {"info": 0, "recover": 0}, "foreign-no-channels": {"info": 0},
    "foreign-tcp-reads": {"info": 0, "recover": 0},
    "metadata-wrong-values-0001": READABLE, "metadata-missing-keys": READABLE,
}
for _kind in ("junk-after-header", "huge-record-length", "chunk-claims-exabytes", "chunk-shorter-than-claimed",
              "uncompressed-size-mismatch", "unknown-compression", "index-claims-huge-count", "index-points-outside",
              "record-overruns-chunk", "zeros-in-a-chunk", "bad-crc", "corrupt-zstd",
              "metadata-not-utf8", "metadata-map-overruns", "metadata-string-overruns"):
    EXPECTED[_kind] = SALVAGED
EXPECTED.update({kind: MESSAGES for kind in KINDS if kind.startswith(("read-", "event-"))})

# What recover says it lost: a damaged region skipped, or the end of the file
# unreadable; nothing for the rest (a bad index or a bad message is no loss:
# the copy gets a new index, and messages are copied as they are).
CUT, SKIPPED = "; the file ended mid-write at byte ", "; skipped 1 damaged region (at byte "
RECOVER_SAYS = {
    **dict.fromkeys(_truncations(), CUT), "junk-after-header": CUT, "huge-record-length": CUT,
    **dict.fromkeys(("chunk-claims-exabytes", "chunk-shorter-than-claimed", "uncompressed-size-mismatch",
                     "unknown-compression", "record-overruns-chunk", "zeros-in-a-chunk", "bad-crc", "corrupt-zstd",
                     "metadata-not-utf8", "metadata-map-overruns", "metadata-string-overruns"), SKIPPED),
}

# How each command is given its input (as in tests/test_bad_input.py).  Replay
# targets a closed port and stub listens on a port in use: each reads the whole
# recording first, then fails to connect or to listen, so neither ever waits.
COMMANDS: dict[str, Callable[[str, Path, int], list[str]]] = {
    "analyze": lambda f, out, port: ["analyze", f],
    "cat": lambda f, out, port: ["cat", f],
    "info": lambda f, out, port: ["info", f],
    "recover": lambda f, out, port: ["recover", f, "-o", str(out / "r.mcap")],
    "replay": lambda f, out, port: ["replay", f, "--target", "127.0.0.1:1", "--password", "x"],
    "stub": lambda f, out, port: ["stub", f, "--listen", f"127.0.0.1:{port}", "--once"],
    "tui": lambda f, out, port: ["tui", f],
}


@pytest.fixture(scope="module")
def busy_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, str]:
    folder = tmp_path_factory.mktemp("hostile")
    out = {}
    for kind, build in KINDS.items():
        path = folder / f"{kind}.mcap"
        data = build(folder)
        path.write_bytes(data)
        out[kind] = str(path)
    return out


def whiztap_in_process(args: list[str], capsys) -> tuple[int, str, str]:
    """``whiztap ARGS`` through its real entry point, in this process."""
    from whiztap.analyzer.cli.root import main

    argv = sys.argv
    sys.argv = ["whiztap", *args]
    try:
        main()
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    finally:
        sys.argv = argv
    out, err = capsys.readouterr()
    return code, out, err


def check_outcome(kind: str, command: str, code: int, out: str, err: str) -> None:
    assert "unexpected error" not in err and "Traceback" not in err, err
    expected = EXPECTED[kind].get(command, 2)
    if code == 2 or expected == 2:
        assert code == expected, (code, out[-300:], err)
        assert err.startswith("whiztap: ") and err.count("\n") == 1, err
        return
    assert code in (expected if isinstance(expected, tuple) else (expected,)), (code, out[-300:], err)
    if command == "recover":
        assert out.startswith("recovered ") and out.count("\n") == 1 and err == "", (out, err)
        says = RECOVER_SAYS.get(kind)
        assert (says in out) if says else ("skipped" not in out and "mid-write" not in out), out


@pytest.mark.parametrize("command", sorted(COMMANDS))
@pytest.mark.parametrize("kind", sorted(KINDS))
def test_every_command_says_one_line(files, busy_port, tmp_path, capsys, kind, command):
    code, out, err = whiztap_in_process(COMMANDS[command](files[kind], tmp_path, busy_port), capsys)
    check_outcome(kind, command, code, out, err)
    if command == "recover" and code == 0:
        assert_indexed_mcap(tmp_path / "r.mcap", int(out.split()[1]))


def assert_indexed_mcap(path: Path, messages: int) -> None:
    """A valid MCAP file with its index, read by mcap's own reader, CRCs checked."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert reader.get_summary() is not None
        assert sum(1 for _ in reader.iter_messages(log_time_order=False)) == messages


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_the_tui_loads_every_file_and_says_what_went_wrong(files, kind):
    """The TUI's loading code (a worker thread, no terminal needed): never an
    exception, and one line for the frame list's footer when the file is bad."""
    from whiztap.analyzer.recording.sets import find_one
    from whiztap.tui.data.model import TrafficModel
    from whiztap.tui.data.sources import FileSource

    source = FileSource(find_one([files[kind]]))
    source.feed(TrafficModel(), threading.Event())
    if EXPECTED[kind].get("analyze", 2) == 2:
        assert source.note and "\n" not in source.note, source.note
    else:
        assert source.note == ""


# -- decompression bombs, run as subprocesses whose peak memory the kernel reports ---------------


def bombs() -> dict[str, Callable[[], bytes]]:
    gib = 1 << 30

    def claiming(claim: int, data: bytes, compression: str = "zstd", index: bool = True) -> bytes:
        return prefix() + chunk(b"", compression, claimed=claim, crc=0, data=data) + (
            message_index(READS, [0]) if index else b"") + END

    return {
        # 33 kB claiming 1 GiB, and holding it: zeros, which a walk takes for endless empty records
        "zstd-bomb": lambda: claiming(gib, zeros(zstandard.ZstdCompressor().compressobj(size=gib), gib)),
        "zstd-bomb-unindexed": lambda: claiming(gib, zeros(zstandard.ZstdCompressor().compressobj(), gib),
                                                index=False),
        "lz4-bomb": lambda: claiming(gib, zeros(lz4.frame.LZ4FrameCompressor(), 64 * MIB), "lz4"),
        # claiming a little, holding a lot: decompression must stop at the claim
        "zstd-holds-more-than-it-claims": lambda: claiming(MIB, zeros(zstandard.ZstdCompressor().compressobj(), gib)),
        "lz4-holds-more-than-it-claims": lambda: claiming(MIB, zeros(lz4.frame.LZ4FrameCompressor(), 256 * MIB),
                                                          "lz4"),
        # just under the limit, and honest about it: read, then refused at its first record
        "zeros-up-to-the-limit": lambda: claiming(255 * MIB, zeros(zstandard.ZstdCompressor().compressobj(),
                                                                    255 * MIB), index=False),
    }


# Runs the command as its child and writes the child's peak RSS (KiB) to the file
# named first.  Why a middle process: Linux keeps a process's peak RSS across
# exec, counting the memory of the process it was forked (or vforked) from, so a
# command started straight from pytest "peaks" at pytest's own size (180 MB
# late in a full run).  Forked from this small process, it starts from ~10 MB.
_MEASURE = """
import os, signal, sys
pid = os.fork()
if pid == 0:
    os.execvp(sys.argv[2], sys.argv[2:])
_, status, usage = os.wait4(pid, 0)
with open(sys.argv[1], "w") as f:
    f.write(str(usage.ru_maxrss))
code = os.waitstatus_to_exitcode(status)
if code < 0:
    signal.signal(-code, signal.SIG_DFL)
    os.kill(os.getpid(), -code)
sys.exit(code)
"""


def run_measured(argv: list[str], env: dict[str, str] | None = None) -> tuple[int, str, str, int, float]:
    """Run a command to its end (killed after TIME_BOUND_S): exit status,
    stdout, stderr, peak RSS in bytes (from the kernel, through wait4 in a
    small middle process) and seconds taken."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err, \
            tempfile.NamedTemporaryFile("r") as peak:
        start = time.monotonic()
        proc = subprocess.Popen([sys.executable, "-c", _MEASURE, peak.name, *argv], stdin=subprocess.DEVNULL,
                                stdout=out, stderr=err, start_new_session=True, env=env)
        timer = threading.Timer(TIME_BOUND_S, os.killpg, (proc.pid, signal.SIGKILL))
        timer.start()
        try:
            proc.wait()
        finally:
            timer.cancel()
        took = time.monotonic() - start
        out.seek(0)
        err.seek(0)
        return (proc.returncode, out.read().decode(), err.read().decode(), int(peak.read() or 0) * 1024, took)


@pytest.fixture(scope="module")
def bomb_files(tmp_path_factory) -> dict[str, str]:
    folder = tmp_path_factory.mktemp("bombs")
    out = {}
    for kind, build in bombs().items():
        path = folder / f"{kind}.mcap"
        path.write_bytes(build())
        out[kind] = str(path)
    return out


EXPECTED.update(dict.fromkeys(bombs(), SALVAGED))
RECOVER_SAYS.update(dict.fromkeys(bombs(), SKIPPED))


@pytest.mark.slow
@pytest.mark.parametrize("kind", sorted(bombs()))
def test_bombs_are_refused_in_bounded_memory_and_time(bomb_files, busy_port, tmp_path, kind):
    def run(command: str) -> tuple[int, str, str, int, float]:
        (tmp_path / command).mkdir()
        return run_measured([WHIZTAP, *COMMANDS[command](bomb_files[kind], tmp_path / command, busy_port)])

    with ThreadPoolExecutor(3) as pool:
        results = dict(zip(COMMANDS, pool.map(run, COMMANDS)))
    for command, (code, out, err, peak, took) in results.items():
        assert peak < MEMORY_BOUND and code != -signal.SIGKILL, (command, peak >> 20, took)  # killed: it hung
        check_outcome(kind, command, code, out.replace(str(tmp_path / command), str(tmp_path)), err)
    assert "WHIZTAP_MAX_CHUNK" in results["analyze"][2] or "holds more than" in results["analyze"][2] or \
        "opcode 0" in results["analyze"][2], results["analyze"][2]


@pytest.mark.slow
def test_the_limit_is_settable_and_named_when_it_refuses(tmp_path):
    path = tmp_path / "big-chunk.mcap"
    path.write_bytes(with_reads(*[read_json(data="QUJD" * 4096)] * 300))  # a chunk of about 5 MB
    code, _, err = run_cli("analyze", path, env={"WHIZTAP_MAX_CHUNK": "1M"})
    chunk = offsets_of(0x06, path.read_bytes())[0]
    assert code == 2 and err.count("\n") == 1 and f"{path}: the chunk at byte {chunk} claims" in err \
        and "WHIZTAP_MAX_CHUNK=5M lets whiztap read it" in err, err
    assert run_cli("analyze", path, env={"WHIZTAP_MAX_CHUNK": "5M"}).returncode in (0, 1)
    code, _, err = run_cli("cat", path, env={"WHIZTAP_MAX_CHUNK": "lots"})
    assert code == 2 and err.count("\n") == 1 and "WHIZTAP_MAX_CHUNK: 'lots' is not a size" in err, err


# -- any damage at all ------------------------------------------------------------------------------------


@pytest.mark.slow
@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_any_damage_is_read_or_refused_in_one_line_and_recover_copies_what_checks_out(tmp_path, data):
    """Random bytes written over a recording (compressed, or not and without
    CRCs, so the damage reaches the records and the JSON), cut anywhere: every
    reader either reads it or raises RecordingError with one line, the analysis
    of what it reads never fails, and recover writes a valid file or says why not."""
    from whiztap.analyzer.analysis.analyzer import Analyzer
    from whiztap.analyzer.recording.format import STREAM_TOPICS, TOPICS
    from whiztap.analyzer.recording.recover import RecoverError, recover
    from whiztap.analyzer.recording.scan import (
        RecordingError,
        RecordingScan,
        read_metadata,
    )

    plain = data.draw(st.booleans(), label="uncompressed, no CRCs")
    raw = bytearray(base("" if plain else "zstd"))
    for at, junk in data.draw(st.lists(st.tuples(st.integers(8, len(raw) - 1), st.binary(min_size=1, max_size=12)),
                                       min_size=1, max_size=4), label="edits"):
        raw[at:at + len(junk)] = junk
    if plain:
        for pos, op, _ in layout(bytes(raw)):
            if op == 0x06 and pos + 9 + 28 <= len(raw):
                struct.pack_into("<I", raw, pos + 9 + 24, 0)  # no CRC: the reader looks inside
    raw = raw[:data.draw(st.integers(8, len(raw)), label="cut at")]
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(raw))
    for topics in (STREAM_TOPICS, tuple(TOPICS)):
        analyzer = Analyzer(str(path))
        try:
            read_metadata(str(path))
            with open(path, "rb") as f:
                for event in RecordingScan(f, topics).traffic():
                    analyzer.receive(event)
        except RecordingError as e:
            assert "\n" not in str(e) and str(e)
        analyzer.finish()
    try:
        result = recover(str(path), str(tmp_path / "out.mcap"), force=True)
    except RecoverError as e:
        assert "\n" not in str(e)
    else:
        assert_indexed_mcap(Path(result.output), result.messages)
        assert "\n" not in result.summary()


def test_a_message_index_pointing_past_any_buffer_is_one_line(tmp_path):
    """Found by the property test above: an index entry with an offset of 2**63
    ended in OverflowError (not struct.error), an 'unexpected error'."""
    from whiztap.analyzer.recording.format import STREAM_TOPICS
    from whiztap.analyzer.recording.scan import RecordingError, RecordingScan

    raw = bytearray(base())
    indexes = [(pos, length) for pos, op, length in layout(bytes(raw)) if op == 0x07]
    assert indexes
    for pos, length in indexes:  # every entry's offset: (log_time u64, offset u64) after channel u16, size u32
        for entry in range(pos + 9 + 6, pos + length, 16):
            struct.pack_into("<Q", raw, entry + 8, 1 << 63)
    path = tmp_path / "far.mcap"
    path.write_bytes(bytes(raw))
    with open(path, "rb") as f, pytest.raises(RecordingError, match="points past the end"):
        for _ in RecordingScan(f, STREAM_TOPICS).traffic():
            pass
