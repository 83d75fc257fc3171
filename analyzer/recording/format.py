"""The whiztap recording format: what goes into an MCAP file, and reading it back.

Everything a recorder writes and every reader of recordings agrees on lives
here: topic names, JSON schemas, the format version, the metadata record, the
functions that turn TCP reads and session observations into JSON messages, and
a fast reader that rebuilds each connection's byte streams.  It does no I/O
except reading files, so the proxy, the pcap importer and the analysis commands
share one definition (docs/recording-format.md describes it for people).

Every channel uses schema encoding ``jsonschema`` and message encoding ``json``
so Foxglove shows all of them; numbers are JSON numbers so it can plot them.
"""

from __future__ import annotations

import base64
import binascii
import json
import os
import re
import struct
import zlib
from collections.abc import Iterable, Iterator
from typing import IO, Any, NamedTuple

from whiztap.analyzer import __version__
from whiztap.analyzer.protocol.describe import fields, meaning, response_meaning
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import (
    ActivateSwitch,
    CameraImage,
    ChannelResponse,
    DeactivateSwitch,
    NormalSend,
    ServoPositionRequest,
)
from whiztap.analyzer.protocol.rules import Violation
from whiztap.analyzer.protocol.session import Direction, Observation
from whiztap.analyzer.protocol.text import escape
from whiztap.analyzer.traffic import NAMES, Data, TrafficError, TrafficEvent, from_json

FORMAT_VERSION = "1"
PROFILE = "whiztap"
SPEC_REVISION = "1.8"
METADATA_NAME = "whiztap"
SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"
REDACTED = "<redacted>"
MASK_BYTE = b"*"  # stands in for each byte of a redacted password

TOPIC_READS = "/tcp/reads"
TOPIC_EVENTS = "/tcp/events"
TOPIC_FRAMES = "/frames"
TOPIC_VIOLATIONS = "/violations"
TOPIC_SENSORS = "/sensors"
TOPIC_SERVOS = "/servos"
TOPIC_SENDS = "/sends"
TOPIC_SWITCHES = "/switches"
TOPIC_CAMERA = "/camera"

# Connection events (the "event" field of /tcp/events).
EV_RECORDING_STARTED = "recording_started"
EV_OPENED = "opened"
EV_UPSTREAM_CONNECTED = "upstream_connected"
EV_UPSTREAM_FAILED = "upstream_failed"
EV_HALF_CLOSED = "half_closed"
EV_CLOSED = "closed"
EV_GAP = "gap"
EV_CONTINUED = "continued"
EV_RECORDING_STOPPED = "recording_stopped"
EVENTS = (EV_RECORDING_STARTED, EV_OPENED, EV_UPSTREAM_CONNECTED, EV_UPSTREAM_FAILED,
          EV_HALF_CLOSED, EV_CLOSED, EV_GAP, EV_CONTINUED, EV_RECORDING_STOPPED)

# -- schemas ---------------------------------------------------------------------------

_INT = {"type": "integer"}
_NS = {"type": "integer", "description": "nanoseconds since the Unix epoch"}
_INT_OR_NULL = {"type": ["integer", "null"]}
_STR = {"type": "string"}
_STR_OR_NULL = {"type": ["string", "null"]}
_B64 = {"type": "string", "contentEncoding": "base64"}
_CONN = {"type": "integer", "description": "connection id, unique within the recording"}
_DIR = {"type": "string", "enum": ["c2s", "s2c"], "description": "c2s: client to server"}
_SPANS = {"type": "array", "items": {"type": "array", "items": _INT, "minItems": 2, "maxItems": 2},
          "description": "[start, length] ranges of data replaced by '*' (a redacted password)"}


def _object(title: str, description: str, properties: dict[str, Any], required: Iterable[str]) -> dict:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title,
            "description": description, "type": "object", "properties": properties,
            "required": list(required)}


SCHEMAS: dict[str, dict] = {
    "whiztap.TcpRead": _object(
        "whiztap.TcpRead", "One read from a TCP socket, exactly as received.",
        {"conn": _CONN, "dir": _DIR, "t_ns": _NS,
         "offset": {"type": "integer", "description": "stream offset of the first byte"},
         "size": _INT, "redacted": _SPANS, "data": _B64},
        ("conn", "dir", "t_ns", "offset", "size", "data")),
    "whiztap.ConnectionEvent": _object(
        "whiztap.ConnectionEvent", "A connection's lifecycle, and the recording's own start and stop.",
        {"conn": _CONN, "event": {"type": "string", "enum": list(EVENTS)}, "t_ns": _NS,
         "by": {"type": ["string", "null"], "enum": ["client", "server", "recorder", None]},
         "detail": _STR, "client": _STR, "upstream": _STR, "dir": _DIR,
         "offset": _INT, "length": _INT, "c2s_bytes": _INT, "s2c_bytes": _INT,
         "c2s_offset": _INT, "s2c_offset": _INT, "mode": _STR, "handshake": _STR},
        ("conn", "event", "t_ns")),
    "whiztap.Frame": _object(
        "whiztap.Frame", "One framer item (frame, handshake text, password, image, line break, "
                         "unframed bytes) with its raw bytes and decoded fields.",
        {"conn": _CONN, "dir": _DIR, "index": {"type": "integer", "description": "position in the session"},
         "kind": {"type": "string", "enum": [k.value for k in ItemKind]}, "reason": _STR_OR_NULL,
         "t_start_ns": _NS, "t_end_ns": _NS, "offset": _INT, "size": _INT, "raw": _B64,
         "text": _STR, "meaning": _STR, "message": _STR_OR_NULL,
         "fields": {"type": "object", "description": "decoded fields; numbers are JSON numbers"},
         "violations": {"type": "array", "items": _STR}, "answers": _INT_OR_NULL,
         "latency_ns": _INT_OR_NULL, "redacted": {"type": "boolean"},
         "items": {"type": "integer", "description": "framer items this message stands for: a run of "
                                                    "unframed bytes and line breaks (1 when absent)"},
         "elided": {"type": "boolean", "description": "raw is left out (a run of over 256 bytes): the "
                                                      "bytes are in /tcp/reads, from offset, size of them"}},
        ("conn", "dir", "index", "kind", "t_start_ns", "t_end_ns", "offset", "size", "raw")),
    "whiztap.Violation": _object(
        "whiztap.Violation", "A rule the live session model found broken.",
        {"conn": _CONN, "t_ns": _NS, "rule_id": _STR,
         "severity": {"type": "string", "enum": ["info", "warning", "error"]},
         "level": {"type": "integer", "description": "1 info, 2 warning, 3 error"},
         "section": _STR, "summary": _STR, "detail": _STR, "dir": _DIR,
         "frame_index": _INT, "frame_text": _STR, "late": {"type": "boolean"},
         "count": {"type": "integer", "description": "times the rule broke in the run of unframed bytes "
                                                    "this message stands for (1 when absent)"}},
        ("conn", "t_ns", "rule_id", "severity", "level", "detail")),
    "whiztap.SensorValue": _object(
        "whiztap.SensorValue", "A Sensor/Servo Response that answers a Sensor Request.",
        {"conn": _CONN, "channel": _INT, "value": _INT, "latency_ns": _INT_OR_NULL},
        ("conn", "channel", "value")),
    "whiztap.ServoPosition": _object(
        "whiztap.ServoPosition", "A Sensor/Servo Response that answers a Servo Position Request.",
        {"conn": _CONN, "channel": _INT, "data": _INT,
         "position": {"type": "number", "description": "data / 4"}, "latency_ns": _INT_OR_NULL},
        ("conn", "channel", "data", "position")),
    "whiztap.NormalSend": _object(
        "whiztap.NormalSend", "A Normal Send to Channel/Port command (a servo set point).",
        {"conn": _CONN, "channel": _INT, "value": _INT}, ("conn", "channel", "value")),
    "whiztap.Switch": _object(
        "whiztap.Switch", "An Activate (1) or De-Activate (0) Switch command.",
        {"conn": _CONN, "channel": _INT, "state": _INT}, ("conn", "channel", "state")),
    "foxglove.CompressedImage": {
        "title": "foxglove.CompressedImage", "description": "A compressed image (Foxglove's schema)",
        "type": "object",
        "properties": {
            "timestamp": {"type": "object", "properties": {"sec": _INT, "nsec": _INT}},
            "frame_id": _STR, "data": _B64, "format": _STR},
        "required": ["timestamp", "frame_id", "data", "format"]},
}

# topic -> schema name, in registration order (channel ids follow it).
# What a reader of byte streams needs (the analyzer, replay, the TUI): the TCP
# reads and the connection events, in arrival order.  The writer keeps them in
# chunks of their own, so such a reader decompresses nothing else.
STREAM_TOPICS = (TOPIC_READS, TOPIC_EVENTS)

TOPICS: dict[str, str] = {
    TOPIC_READS: "whiztap.TcpRead",
    TOPIC_EVENTS: "whiztap.ConnectionEvent",
    TOPIC_FRAMES: "whiztap.Frame",
    TOPIC_VIOLATIONS: "whiztap.Violation",
    TOPIC_SENSORS: "whiztap.SensorValue",
    TOPIC_SERVOS: "whiztap.ServoPosition",
    TOPIC_SENDS: "whiztap.NormalSend",
    TOPIC_SWITCHES: "whiztap.Switch",
    TOPIC_CAMERA: "foxglove.CompressedImage",
}


def schema_bytes(name: str) -> bytes:
    return json.dumps(SCHEMAS[name], separators=(",", ":")).encode()


# -- messages ----------------------------------------------------------------------------

_dumps = json.JSONEncoder(separators=(",", ":")).encode


def encode(message: dict) -> bytes:
    """A message dict as the bytes of an MCAP message (compact UTF-8 JSON)."""
    return _dumps(message).encode()


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def mask(data: bytes, spans: Iterable[tuple[int, int]]) -> bytes:
    """``data`` with each [start, length] span replaced by as many '*' bytes."""
    out = bytearray(data)
    for start, length in spans:
        out[start:start + length] = MASK_BYTE * length
    return bytes(out)


def read_message(conn: int, direction: str, t_ns: int, offset: int, data: bytes,
                 redacted: list[tuple[int, int]] | None = None) -> dict:
    """A /tcp/reads message.  Key order is part of the format: the fast reader
    below matches it (and falls back to a JSON parser when it does not)."""
    message: dict[str, Any] = {"conn": conn, "dir": direction, "t_ns": t_ns, "offset": offset, "size": len(data)}
    if redacted:
        message["redacted"] = [list(s) for s in redacted]
    message["data"] = _b64(data)
    return message


def event_message(conn: int, event: str, t_ns: int, **details: Any) -> dict:
    """A /tcp/events message; ``details`` holds the fields that event has."""
    return {"conn": conn, "event": event, "t_ns": t_ns, **details}


def encode_read(conn: int, direction: str, t_ns: int, offset: int, data: bytes,
                redacted: list[tuple[int, int]] | None = None) -> bytes:
    """``encode(read_message(...))``, built directly: one of these per TCP read."""
    if redacted:
        return encode(read_message(conn, direction, t_ns, offset, data, redacted))
    return b'{"conn":%d,"dir":"%s","t_ns":%d,"offset":%d,"size":%d,"data":"%s"}' % (
        conn, direction.encode(), t_ns, offset, len(data), base64.b64encode(data))


def _frame_static(obs: Observation, redact: bool) -> dict:
    """The part of a /frames message fixed by the item's bytes and meaning."""
    item = obs.item
    raw = item.raw
    hidden = redact and item.kind is ItemKind.PASSWORD
    if hidden:
        raw = MASK_BYTE * len(raw)
    decoded = fields(obs)
    decoded.pop("latency_ns", None)  # a top-level field of the frame
    return {
        "kind": item.kind.value, "reason": item.reason.value if item.reason is not None else None,
        "size": len(raw), "raw": _b64(raw), "text": REDACTED if hidden else escape(raw), "meaning": meaning(obs),
        "message": obs.message.title if obs.message is not None else None, "fields": decoded,
        "violations": [v.rule_id for v in obs.violations], "redacted": hidden,
    }


def frame_message(conn: int, obs: Observation, offset: int, redact: bool) -> dict:
    """A /frames message.  With ``redact`` a password's bytes become '*' and its
    text ``<redacted>``; its length stays, so offsets and replays still line up."""
    item = obs.item
    return {
        "conn": conn, "dir": obs.direction.value, "index": obs.index,
        "t_start_ns": item.t_start_ns, "t_end_ns": item.t_end_ns, "offset": offset,
        "answers": obs.answers.index if obs.answers is not None else None, "latency_ns": obs.latency_ns,
        **_frame_static(obs, redact),
    }


RUN_INLINE_MAX = 256  # a run of unframed bytes up to this long keeps its raw bytes in /frames
RUN_TEXT_MAX = 64  # bytes of a longer run shown in its text


def run_message(conn: int, run: list[Observation], offset: int) -> dict:
    """One /frames message for a run of unframed items and line breaks that one
    read completed (``Recorder`` writes one when the run has more than one
    item or more than ``RUN_INLINE_MAX`` bytes).  Bytes that are not protocol
    then cost a message per read rather than one per line of junk, and a
    long run's bytes are in the file once, in /tcp/reads, not again here in
    base64 and as escaped text (which made junk recordings 4.6 times the traffic)."""
    raw = b"".join(o.item.raw for o in run)
    unframed = [o.item for o in run if o.item.kind is ItemKind.UNFRAMED]
    elided = len(raw) > RUN_INLINE_MAX
    breaks = len(run) - len(unframed)
    first = run[0]
    return {
        "conn": conn, "dir": first.direction.value, "index": first.index, "t_start_ns": first.item.t_start_ns,
        "t_end_ns": run[-1].item.t_end_ns, "offset": offset, "answers": None, "latency_ns": None,
        "kind": (ItemKind.UNFRAMED if unframed else ItemKind.EOL).value,
        "reason": unframed[0].reason.value if unframed and unframed[0].reason is not None else None,
        "size": len(raw), "raw": "" if elided else _b64(raw),
        "text": escape(raw[:RUN_TEXT_MAX]) if elided else escape(raw),
        "meaning": f"{len(unframed)} unframed items and {breaks} line breaks, {len(raw)} bytes"
                   + (" (in /tcp/reads)" if elided else ""),
        "message": None, "fields": {}, "violations": list(dict.fromkeys(v.rule_id for o in run for v in o.violations)),
        "redacted": False, "items": len(run), "elided": elided,
    }


_FRAME_START = b'{"conn":%d,"dir":"%s","index":%d,"t_start_ns":%d,"t_end_ns":%d,"offset":%d,'
_FRAME_HEAD = _FRAME_START + b'"answers":%s,"latency_ns":%s,'
_COMMAND_HEAD = _FRAME_START + b'"answers":null,"latency_ns":null,'
_ANSWER_HEAD = _FRAME_START + b'"answers":%d,"latency_ns":%d,'
_DIR_BYTES = {d: d.value.encode() for d in Direction}  # Enum.value is a slow property
_CACHED_RAW_MAX = 256  # longer items (images, unframed runs) are rare: not worth keeping
_CACHE_LIMIT = 4096  # distinct frames kept; answers with varying values mostly miss anyway


class FrameEncoder:
    """``encode(frame_message(...))``, built fast: one of these per frame.

    Real sessions repeat a few hundred distinct frames, so the JSON of the part
    that depends only on the bytes and their meaning (``_frame_static``) is
    kept, keyed by everything that decides it; each frame then costs one bytes
    format for its connection, position, times and pairing (a template each for
    the two commonest cases: nothing answered, and an answer with its latency).
    Passwords are never kept.
    """

    def __init__(self) -> None:
        self._cache: dict[tuple, bytes] = {}

    def encode(self, conn: int, obs: Observation, offset: int, redact: bool) -> bytes:
        index, direction, item, message, _, violations, answers, latency = obs
        kind, raw, t_start, t_end, reason = item
        if kind is ItemKind.PASSWORD or len(raw) > _CACHED_RAW_MAX:
            static = _dumps(_frame_static(obs, redact))[1:].encode()
        else:
            key = (raw, kind, reason, message.__class__, None if answers is None else answers[3].__class__,
                   violations)
            static = self._cache.get(key)  # type: ignore[assignment]
            if static is None:
                if len(self._cache) >= _CACHE_LIMIT:
                    self._cache.clear()
                static = self._cache[key] = _dumps(_frame_static(obs, redact))[1:].encode()
        if answers is None and latency is None:
            return _COMMAND_HEAD % (conn, _DIR_BYTES[direction], index, t_start, t_end, offset) + static
        if answers is not None and latency is not None:
            return _ANSWER_HEAD % (conn, _DIR_BYTES[direction], index, t_start, t_end, offset, answers[0],
                                   latency) + static
        return _FRAME_HEAD % (conn, _DIR_BYTES[direction], index, t_start, t_end, offset,
                              b"null" if answers is None else b"%d" % answers[0],
                              b"null" if latency is None else b"%d" % latency) + static


def violation_message(conn: int, violation: Violation, about: Observation | None, t_ns: int,
                      late: bool, redact: bool, count: int = 1) -> dict:
    """A /violations message: the rule, its severity and what was seen; with a
    ``count``, for that many breaks of the rule in a run of unframed bytes
    (``about`` is the first)."""
    rule = violation.rule
    message: dict[str, Any] = {
        "conn": conn, "t_ns": t_ns, "rule_id": rule.id, "severity": str(rule.severity),
        "level": int(rule.severity), "section": rule.section, "summary": rule.summary,
        "detail": violation.detail, "late": late,
    }
    if about is not None:
        hidden = redact and about.item.kind is ItemKind.PASSWORD
        message["dir"] = about.direction.value
        message["frame_index"] = about.index
        message["frame_text"] = REDACTED if hidden else escape(about.item.raw[:200])
    if count > 1:
        message["count"] = count
    return message


def plot_messages(conn: int, obs: Observation) -> list[tuple[str, dict]]:
    """The plottable channels an observation feeds: (topic, message) pairs."""
    message = obs.message
    if message is None:
        return []
    if isinstance(message, ChannelResponse) and obs.answers is not None:
        if response_meaning(obs) == "servo":
            return [(TOPIC_SERVOS, {"conn": conn, "channel": message.channel, "data": message.data,
                                    "position": message.data / 4, "latency_ns": obs.latency_ns})]
        return [(TOPIC_SENSORS, {"conn": conn, "channel": message.channel, "value": message.data,
                                 "latency_ns": obs.latency_ns})]
    if isinstance(message, NormalSend):
        return [(TOPIC_SENDS, {"conn": conn, "channel": message.channel, "value": message.value})]
    if isinstance(message, (ActivateSwitch, DeactivateSwitch)):
        state = 1 if isinstance(message, ActivateSwitch) else 0
        return [(TOPIC_SWITCHES, {"conn": conn, "channel": message.channel, "state": state})]
    if isinstance(message, CameraImage):
        t = obs.item.t_end_ns
        return [(TOPIC_CAMERA, {"timestamp": {"sec": t // 1_000_000_000, "nsec": t % 1_000_000_000},
                                "frame_id": f"conn-{conn}", "data": _b64(message.data),
                                "format": message.format})]
    return []


_SENSOR = b'{"conn":%d,"channel":%d,"value":%d,"latency_ns":%s}'
_SERVO = b'{"conn":%d,"channel":%d,"data":%d,"position":%s,"latency_ns":%s}'
_PLOTTED = (NormalSend, ActivateSwitch, DeactivateSwitch, CameraImage)


def encode_plots(conn: int, obs: Observation) -> list[tuple[str, bytes]]:
    """``plot_messages`` encoded; the answers to sensor and servo requests,
    which come by the thousand, are built directly."""
    message = obs.message
    if type(message) is ChannelResponse:
        answers = obs.answers
        if answers is None:
            return []
        latency = b"null" if obs.latency_ns is None else b"%d" % obs.latency_ns
        if type(answers.message) is ServoPositionRequest:
            return [(TOPIC_SERVOS, _SERVO % (conn, message.channel, message.data,
                                             repr(message.data / 4).encode(), latency))]
        return [(TOPIC_SENSORS, _SENSOR % (conn, message.channel, message.data, latency))]
    if isinstance(message, _PLOTTED):
        return [(topic, encode(m)) for topic, m in plot_messages(conn, obs)]
    return []


def metadata_record(**values: Any) -> dict[str, str]:
    """The one "whiztap" metadata record: MCAP metadata values are strings."""
    record = {"format_version": FORMAT_VERSION, "whiztap_version": __version__, "spec_revision": SPEC_REVISION}
    record.update({k: "" if v is None else str(v) for k, v in values.items()})
    return record


# -- reading -------------------------------------------------------------------------------

MAGIC = b"\x89MCAP0\r\n"
_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 0x03, 0x04, 0x05, 0x06
_OP_MESSAGE_INDEX, _OP_METADATA, _OP_DATA_END, _OP_FOOTER = 0x07, 0x0C, 0x0F, 0x02
_OP_READ = frozenset((_OP_CHUNK, _OP_CHANNEL, _OP_MESSAGE, _OP_METADATA))  # what a scan looks inside
_OP_NAMES = {_OP_CHUNK: "chunk", _OP_MESSAGE_INDEX: "message index", _OP_METADATA: "metadata record",
             _OP_CHANNEL: "channel record", _OP_MESSAGE: "message"}
MAX_CHUNK_ENV = "WHIZTAP_MAX_CHUNK"
DEFAULT_MAX_CHUNK = 256 << 20
_MIB = 1 << 20
_RECORD_HEAD = struct.Struct("<BQ")
_RECORD_HEAD_CHANNEL = struct.Struct("<BQH")  # opcode, length, then a Message's channel id
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_CHUNK_HEAD = struct.Struct("<QQQI")
_FILE_END = struct.Struct("<BQQQI8s")  # the Footer record and the closing magic
_MESSAGE_FIXED = 2 + 4 + 8 + 8  # channel id, sequence, log and publish time
_MESSAGE_DATA_AT = 9 + _MESSAGE_FIXED
_MAX_INT = 10 ** 19  # integers in messages are ids, counts, offsets and times: non-negative, 19 digits at most
_DIRECTIONS = {b"c2s": Direction.C2S, b"s2c": Direction.S2C}
_READ_JSON = re.compile(
    rb'\{"conn":(\d{1,19}),"dir":"(c2s|s2c)","t_ns":(\d{1,19}),"offset":(\d{1,19}),"size":\d+,'
    rb'(?:"redacted":\[[\d,\[\]]*\],)?"data":"([A-Za-z0-9+/=]*)"\}')


class RecordingError(Exception):
    """The file is not a recording whiztap can read (message says why, in one line)."""


class DamagedRecord(ValueError):
    """A record whose lengths or contents do not add up.  The message says
    what, not where: ``RecordingScan`` and ``whiztap recover`` add the offset."""


class TooBig(DamagedRecord):
    """A record, or a chunk's contents, claiming more than ``max_chunk()``."""

    def __init__(self, size: int, limit: int, what: str = "") -> None:
        advice = (f"; if you trust it, {MAX_CHUNK_ENV}={-(-size // _MIB)}M lets whiztap read it"
                  if size < 1 << 40 else "")
        super().__init__(f"claims {size} bytes{what}, more than readers take ({_mib(limit)}): the file is "
                         f"damaged or a decompression bomb{advice}")


class Read(NamedTuple):
    conn: int
    dir: str
    t_ns: int
    offset: int
    data: bytes


class Segment(NamedTuple):
    offset: int  # stream offset of data[0]
    data: bytes


def max_chunk() -> int:
    """The most bytes a reader takes for one record or one chunk's contents.

    Whiztap's chunks hold about 1 MiB; one 32 MiB camera image (the framer's
    default --max-image) makes a chunk of about 200 MiB of JSON.  A file that
    claims more is damaged or a decompression bomb, refused before anything is
    allocated.  A file you trust that needs more is read with WHIZTAP_MAX_CHUNK
    set higher (a byte count: 512M, 2G); it is read here, in one place.
    """
    value = os.environ.get(MAX_CHUNK_ENV, "")
    if not value:
        return DEFAULT_MAX_CHUNK
    from whiztap.analyzer.protocol.text import parse_size

    try:
        return parse_size(value)
    except ValueError as e:
        raise RecordingError(f"{MAX_CHUNK_ENV}: {e}") from None


def _mib(n: int) -> str:
    return f"{n} bytes" if n < _MIB else f"{n / _MIB:g} MiB"


def _decompress(compression: str, data: memoryview, size: int) -> bytes:
    """A compressed chunk's records, which must be exactly ``size`` bytes, as it claims.

    Decompressed as a stream that stops one byte past the claim: memory grows
    with the real output, never past what the chunk claims (which the caller
    has checked against ``max_chunk``)."""
    if compression not in _DECOMPRESSORS:
        raise DamagedRecord(f"its compression {compression!r} is none whiztap reads (zstd, lz4 or none)")
    try:
        out = _DECOMPRESSORS[compression](data, size + 1)
    except Exception as e:  # noqa: BLE001 - each library has its own error types for damaged data
        raise DamagedRecord(f"its {compression} data does not decompress: {e}") from None
    if len(out) > size:
        raise DamagedRecord(f"it holds more than the {size} bytes it claims")
    if len(out) < size:
        raise DamagedRecord(f"it holds {len(out)} bytes, not the {size} it claims")
    return out


def _zstd(data: memoryview, most: int) -> bytes:
    import zstandard

    read = zstandard.ZstdDecompressor().stream_reader(data).read
    pieces: list[bytes] = []
    got = 0
    while got < most and (piece := read(most - got)):
        pieces.append(piece)
        got += len(piece)
    return b"".join(pieces)


def _lz4(data: memoryview, most: int) -> bytes:
    import lz4.frame

    decompressor = lz4.frame.LZ4FrameDecompressor()
    pieces = [decompressor.decompress(data, max_length=most)]
    got = len(pieces[0])
    while got < most and pieces[-1] and not decompressor.eof:
        pieces.append(decompressor.decompress(b"", max_length=most - got))
        got += len(pieces[-1])
    return b"".join(pieces)


_DECOMPRESSORS = {"zstd": _zstd, "lz4": _lz4}


def open_chunk(body: bytes, limit: int, validate_crc: bool = True) -> tuple[bytes, int, int]:
    """The records in a Chunk record (``body``: the record without its 9-byte
    head) as ``(buffer, start, end)``: they are ``buffer[start:end]``,
    decompressed within ``limit`` to exactly the size the chunk claims, and CRC
    checked.  Uncompressed records are not copied out of ``body``: a chunk
    costs its size once.  ``DamagedRecord`` (``TooBig``) says what is wrong."""
    try:
        _start, _end, size, crc = _CHUNK_HEAD.unpack_from(body, 0)
        compression, pos = _string(body, _CHUNK_HEAD.size, len(body))
        n = _U64.unpack_from(body, pos)[0]
    except (struct.error, UnicodeDecodeError) as e:
        raise DamagedRecord(f"its header does not add up: {e}") from None
    if pos + 8 + n > len(body):
        raise DamagedRecord(f"it claims {n} bytes of data in a record of {len(body)}")
    if size > limit:
        raise TooBig(size, limit, " uncompressed")
    if compression == "":
        if n != size:
            raise DamagedRecord(f"it holds {n} bytes, not the {size} it claims")
        records, start = body, pos + 8
    else:
        records, start = _decompress(compression, memoryview(body)[pos + 8:pos + 8 + n], size), 0
    if validate_crc and crc and zlib.crc32(memoryview(records)[start:start + size]) != crc:
        raise DamagedRecord("its CRC does not match its contents")
    return records, start, start + size


def _skip(f: IO[bytes], n: int) -> bool:
    """Read past ``n`` bytes of ``f`` a MiB at a time (a stream may not seek);
    False when it ends first."""
    while n > 0:
        got = len(f.read(min(n, _MIB)))
        if not got:
            return False
        n -= got
    return True


def _string(buf: bytes, pos: int, end: int) -> tuple[str, int]:
    n = _U32.unpack_from(buf, pos)[0]
    stop = pos + 4 + n
    if stop > end:
        raise DamagedRecord(f"a string of {n} bytes runs past the end of its record")
    return buf[pos + 4:stop].decode(), stop


def _metadata(buf: bytes, pos: int, end: int) -> tuple[str, dict[str, str]]:
    """A Metadata record's name and string map, from its content at pos."""
    name, pos = _string(buf, pos, end)
    limit = pos + 4 + _U32.unpack_from(buf, pos)[0]
    if limit > end:
        raise DamagedRecord("its map runs past the end of the record")
    pos += 4
    values: dict[str, str] = {}
    while pos < limit:
        key, pos = _string(buf, pos, limit)
        values[key], pos = _string(buf, pos, limit)
    return name, values


def _misfit(message: Any, schema: dict) -> str | None:
    """Why a decoded message does not fit its schema's top-level fields (None
    when it does): readers then use those fields without checking them."""
    if type(message) is not dict:
        return "not a JSON object"
    for key in schema["required"]:
        if key not in message:
            return f"no {key!r}"
    properties = schema["properties"]
    for key, value in message.items():
        spec = properties.get(key)
        if spec is not None and not _fits(value, spec["type"]):
            return f"{key!r} is not {spec['type'] if isinstance(spec['type'], str) else ' or '.join(spec['type'])}"
    if message.get("dir", "c2s") not in ("c2s", "s2c"):
        return "'dir' is neither c2s nor s2c"
    if message.get("event") == EV_HALF_CLOSED and "dir" not in message:
        return "a half_closed event without 'dir'"
    return None


_JSON_TYPES: dict[str, type] = {"string": str, "boolean": bool, "array": list, "object": dict, "null": type(None)}


def _fits(value: Any, kinds: str | list[str]) -> bool:
    for kind in [kinds] if isinstance(kinds, str) else kinds:
        if kind == "integer":
            if type(value) is int and 0 <= value < _MAX_INT:
                return True
        elif kind == "number":
            if type(value) in (int, float):
                return True
        elif type(value) is _JSON_TYPES[kind]:
            return True
    return False


class RecordingScan:
    """One pass over an MCAP file's data section that yields the /tcp/reads
    messages fast, and notes what else a reader of streams needs.

    Why not ``mcap.reader``: decoding every message as an object, then as JSON,
    tops out near 150k messages/s here.  This walks records with ``struct``,
    decompresses chunks itself (checking their CRC), skips other channels by
    id without decoding them, and pulls the fields of each read from its JSON
    with one compiled regex (falling back to ``json.loads`` for a message
    another writer laid out differently).  It reads files in order, so it also
    reads a ``.part`` left by a crash, up to its last complete chunk; then
    ``truncated`` is true.

    It trusts nothing in the file: no record or chunk may claim more than
    ``max_chunk()`` bytes, a chunk must decompress to exactly what it claims
    (and memory grows only with what it really holds), every length must fit
    inside what contains it, and every message a reader gets fits its schema.
    Anything else raises ``RecordingError`` naming the record's offset.
    """

    def __init__(self, stream: IO[bytes], topics: Iterable[str] = (TOPIC_READS,),
                 validate_crcs: bool = True, growing: bool = False) -> None:
        self._stream = stream
        self._wanted = set(topics)
        self.validate_crcs = validate_crcs
        # a file still being written (the TUI's follow mode): yield each chunk
        # as soon as it is read, without reading on to its message indexes,
        # which would wait for the recorder's next flush
        self.growing = growing
        self.channels: dict[int, str] = {}  # channel id -> topic
        self.metadata: dict[str, dict[str, str]] = {}
        self.truncated = False
        self._at = 0  # file offset of the record being read, and its opcode: for messages
        self._op = 0

    # -- records ---------------------------------------------------------------------

    def records(self) -> Iterator[tuple[int, str, bytes, int, int]]:
        """(log_time, topic, data, start, end) of each wanted message, file order;
        ``data[start:end]`` is the message (no copy is made)."""
        limit = max_chunk()
        try:
            yield from self._records(limit)
        except TooBig as e:
            raise RecordingError(f"{self._where()} {e}") from None
        except (ValueError, struct.error) as e:  # DamagedRecord, or a field that does not parse
            raise RecordingError(f"{self._where()} is damaged ({e}); 'whiztap recover' copies what is "
                                 "readable into a new file") from None

    def _where(self) -> str:
        return f"the {_OP_NAMES.get(self._op, 'record')} at byte {self._at}"

    def _records(self, limit: int) -> Iterator[tuple[int, str, bytes, int, int]]:
        f = self._stream
        if f.read(8) != MAGIC:
            raise RecordingError("not an MCAP file (bad magic)")
        at = 8
        head = f.read(9)
        while True:
            self._at, self._op = at, 0
            if len(head) < 9:
                self.truncated = True
                return
            op, length = _RECORD_HEAD.unpack(head)
            self._op = op
            if op in (_OP_DATA_END, _OP_FOOTER):
                return
            if op == 0:
                raise DamagedRecord("opcode 0 starts no MCAP record")
            if length > limit:
                raise TooBig(length, limit)
            if op not in _OP_READ:  # skipped in pieces: a record may be as long as the limit
                if not _skip(f, length):
                    self.truncated = True
                    return
                at += 9 + length
                head = f.read(9)
                continue
            body = f.read(length)
            if len(body) < length:
                self.truncated = True
                return
            at += 9 + length
            if op != _OP_CHUNK:
                yield from self._record(op, head + body, 0, 9 + length)
                head = f.read(9)
                continue
            if self.growing:
                yield from self._chunk(body, None, limit)
                head = f.read(9)
                continue
            # The chunk's message indexes follow it: with them, only the wanted
            # messages are looked at (a recording holds several messages per
            # frame, of which an analysis wants one per TCP read).  Only in
            # whiztap's own files, whose writer defines every channel before the
            # first chunk, so a chunk skipped this way cannot hide a channel.
            chunk_at = self._at
            offsets: list[int] | None = [] if METADATA_NAME in self.metadata else None
            indexed = False
            head = f.read(9)
            while len(head) == 9 and head[0] == _OP_MESSAGE_INDEX:
                self._at, self._op = at, _OP_MESSAGE_INDEX
                size = _RECORD_HEAD.unpack(head)[1]
                if size > limit:
                    raise TooBig(size, limit)
                index = f.read(size)
                if len(index) < size:
                    head = b""  # the file ends inside the index: the chunk itself is whole
                    offsets = None
                    break
                at += 9 + size
                indexed = True
                if offsets is not None:
                    offsets = self._indexed_offsets(index, offsets)
                head = f.read(9)
            self._at, self._op = chunk_at, _OP_CHUNK
            yield from self._chunk(body, offsets if indexed else None, limit)

    def _indexed_offsets(self, index: bytes, offsets: list[int]) -> list[int] | None:
        """Add one MessageIndex record's offsets for wanted channels; None when it
        names a channel not yet defined (then the chunk is walked whole)."""
        channel = _U16.unpack_from(index, 0)[0]
        topic = self.channels.get(channel)
        if topic is None:
            return None
        if topic in self._wanted:
            n = _U32.unpack_from(index, 2)[0]
            if 6 + n > len(index) or n % 16:
                raise DamagedRecord(f"it claims {n} bytes of entries in a record of {len(index)}")
            offsets.extend(struct.unpack_from(f"<{n // 8}Q", index, 6)[1::2])
        return offsets

    def _chunk(self, body: bytes, offsets: list[int] | None,
               limit: int) -> Iterator[tuple[int, str, bytes, int, int]]:
        if offsets is not None and not offsets:
            return  # indexed, and nothing wanted in it: not even decompressed
        records, first, end = open_chunk(body, limit, self.validate_crcs)
        unpack = _RECORD_HEAD_CHANNEL.unpack_from
        log_time = _U64.unpack_from
        wanted = self._wanted_ids()
        if offsets:
            offsets.sort()  # file order is arrival order; the index is in log-time order
            if first + offsets[-1] + 9 > end:  # checked once: the largest is the last
                raise DamagedRecord("a message index points past the end of its chunk")
            for offset in offsets:
                pos = first + offset
                op, length, channel = unpack(records, pos)  # struct.error past the buffer
                if op != _OP_MESSAGE or length < _MESSAGE_FIXED or pos + 9 + length > end:
                    raise DamagedRecord("a message index points at no message in it")
                if channel in wanted:
                    yield log_time(records, pos + 15)[0], wanted[channel], records, pos + _MESSAGE_DATA_AT, \
                        pos + 9 + length
            return
        pos = first
        while pos < end:
            op, length, channel = unpack(records, pos)
            stop = pos + 9 + length
            if stop > end or op == 0:
                raise DamagedRecord(f"the record at {pos - first} in it is "
                                    f"{'opcode 0' if op == 0 else 'longer than the chunk'}")
            if op == _OP_MESSAGE:
                if length < _MESSAGE_FIXED:
                    raise DamagedRecord(f"the message at {pos - first} in it is too short")
                if channel in wanted:
                    yield log_time(records, pos + 15)[0], wanted[channel], records, pos + _MESSAGE_DATA_AT, stop
            else:
                yield from self._record(op, records, pos, stop)
                wanted = self._wanted_ids()
            pos = stop

    def _record(self, op: int, buf: bytes, pos: int, stop: int) -> Iterator[tuple[int, str, bytes, int, int]]:
        if op == _OP_CHANNEL:
            channel = _U16.unpack_from(buf, pos + 9)[0]
            topic, _ = _string(buf, pos + 13, stop)
            self.channels[channel] = topic
        elif op == _OP_MESSAGE:
            if stop - pos < _MESSAGE_DATA_AT:
                raise DamagedRecord("it is too short for a message")
            channel = _U16.unpack_from(buf, pos + 9)[0]
            topic = self.channels.get(channel)
            if topic in self._wanted:
                yield _U64.unpack_from(buf, pos + 15)[0], topic, buf, pos + _MESSAGE_DATA_AT, stop
        elif op == _OP_METADATA:
            name, values = _metadata(buf, pos + 9, stop)
            self.metadata[name] = values

    def _wanted_ids(self) -> dict[int, str]:
        return {cid: topic for cid, topic in self.channels.items() if topic in self._wanted}

    # -- messages ---------------------------------------------------------------------

    def decode(self, topic: str, buf: bytes, start: int, stop: int) -> dict:
        """A wanted message (``records()`` yields where it is) as a dict whose
        fields fit its topic's schema, or RecordingError."""
        try:
            message = json.loads(buf[start:stop])
        except (ValueError, RecursionError) as e:  # not UTF-8, not JSON, nested past Python's stack
            raise self._invalid(topic, f"not JSON: {e}") from None
        problem = _misfit(message, SCHEMAS[TOPICS[topic]]) if topic in TOPICS else None
        if problem is not None:
            raise self._invalid(topic, problem)
        return message

    def _invalid(self, topic: str, why: str) -> RecordingError:
        return RecordingError(f"a {topic} message in {self._where()} is not valid ({why}): the file is damaged "
                              "or not a whiztap recording")

    def reads(self) -> Iterator[Read]:
        """Every /tcp/reads message as a Read (with its stream offset), in file order."""
        for _t, topic, buf, start, stop in self.records():
            if topic == TOPIC_READS:
                d = self.decode(topic, buf, start, stop)
                try:
                    yield Read(d["conn"], d["dir"], d["t_ns"], d["offset"], base64.b64decode(d["data"]))
                except ValueError as e:
                    raise self._invalid(topic, f"its data is not base64: {e}") from None

    def traffic(self) -> Iterator[TrafficEvent]:
        """The recording's traffic as typed events in file (= arrival) order:
        each /tcp/reads message as ``Data``, each /tcp/events message as its
        connection event (``traffic.from_json``).  Other topics are skipped."""
        match = _READ_JSON.match
        b64 = binascii.a2b_base64  # what base64.b64decode calls, without its Python layer
        directions = _DIRECTIONS
        try:
            for _t, topic, buf, start, stop in self.records():
                if topic == TOPIC_READS:
                    m = match(buf, start, stop)
                    if m is not None and m.end() == stop:
                        conn, direction, t_ns, _offset, data = m.groups()
                        yield Data(int(conn), directions[direction], int(t_ns), b64(data))
                    else:
                        d = self.decode(topic, buf, start, stop)
                        yield Data(d["conn"], directions[d["dir"].encode()], d["t_ns"], b64(d["data"]))
                elif topic == TOPIC_EVENTS:
                    try:
                        yield from_json(self.decode(topic, buf, start, stop))
                    except TrafficError as e:
                        raise self._invalid(topic, str(e)) from None
        except ValueError as e:  # binascii.Error: data that is not base64 (or not ASCII)
            if isinstance(e, RecordingError):
                raise
            raise self._invalid(TOPIC_READS, f"its data is not base64: {e}") from None

    def messages(self) -> Iterator[tuple[str, int, dict]]:
        """(topic, log_time, decoded JSON) of each wanted message, file order."""
        for t, topic, buf, start, stop in self.records():
            yield topic, t, self.decode(topic, buf, start, stop)


def rebuild_streams(path: str, topic: str = TOPIC_READS) -> dict[tuple[int, str], list[Segment]]:
    """Each (connection, direction) byte stream, from /tcp/reads or from /frames.

    A stream is a list of contiguous segments: one, unless the recording has a
    gap (a capture that missed packets) or starts mid-stream (a rotated file).
    Redacted password bytes come back as '*'.
    """
    parts: dict[tuple[int, str], list[tuple[int, bytes]]] = {}
    with open(path, "rb") as f:
        recording = RecordingScan(f, (topic,))
        if topic == TOPIC_READS:
            for r in recording.reads():
                parts.setdefault((r.conn, r.dir), []).append((r.offset, r.data))
        elif topic == TOPIC_FRAMES:
            for _topic, _t, m in recording.messages():
                parts.setdefault((m["conn"], m["dir"]), []).append((m["offset"], base64.b64decode(m["raw"])))
        else:
            raise ValueError(f"streams are rebuilt from {TOPIC_READS} or {TOPIC_FRAMES}, not {topic}")
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
    """The whole stream, when it has no gap and starts at offset 0."""
    if not segments:
        return b""
    if len(segments) > 1 or segments[0].offset != 0:
        where = ", ".join(f"{s.offset}+{len(s.data)}" for s in segments)
        raise RecordingError(f"stream is not contiguous from offset 0 (segments at {where})")
    return segments[0].data


def read_metadata(path: str) -> dict[str, str]:
    """The "whiztap" metadata record of a recording ({} if it has none).

    Recorders write it before the first chunk, so this stops at the first
    metadata record instead of reading the whole file.  Raises RecordingError
    for a file that is no MCAP file or whose records do not add up.
    """
    limit = max_chunk()
    with open(path, "rb") as f:
        if f.read(8) != MAGIC:
            raise RecordingError("not an MCAP file (bad magic)")
        at = 8
        while len(head := f.read(9)) == 9:
            op, length = _RECORD_HEAD.unpack(head)
            if op in (_OP_DATA_END, _OP_FOOTER):
                break
            if op == 0:
                raise RecordingError(f"the record at byte {at} is damaged (opcode 0 starts no MCAP record)")
            if length > limit:
                raise RecordingError(f"the record at byte {at} {TooBig(length, limit)}")
            if op == _OP_METADATA:
                body = f.read(length)
                if len(body) < length:
                    break  # cut short: whoever reads on says so
                try:
                    name, values = _metadata(body, 0, length)
                except (ValueError, struct.error) as e:
                    raise RecordingError(f"the metadata record at byte {at} is damaged ({e})") from None
                if name == METADATA_NAME:
                    return values
            else:
                f.seek(length, 1)
            at += 9 + length
    return {}


def is_finished(path: str) -> bool:
    """Whether the file ends as a finished MCAP file does: a footer that points
    at a summary section (the index), then the magic.  Reads the last bytes only."""
    with open(path, "rb") as f:
        size = f.seek(0, os.SEEK_END)
        if size < len(MAGIC) + _FILE_END.size:
            return False
        f.seek(size - _FILE_END.size)
        op, length, summary_start, _summary_offsets, _crc, magic = _FILE_END.unpack(f.read(_FILE_END.size))
    return op == _OP_FOOTER and length == 20 and magic == MAGIC and len(MAGIC) < summary_start < size
