"""The whiztap recording format: what goes into an MCAP file.

Everything a recorder writes and every reader of recordings agrees on is
defined here: topic names, JSON schemas, the format version and the metadata
record (docs/recording-format.md describes them for people).  The messages are
built in ``encode``, laid out in MCAP by ``mcap`` and read back by ``scan``.

Every channel uses schema encoding ``jsonschema`` and message encoding ``json``
so Foxglove shows all of them; numbers are JSON numbers so it can plot them.
Violations are also ``foxglove.Log`` messages (``/log``) for Foxglove's Log
panel, and the plottable values have a topic per protocol channel
(``/sensors/12``), so a plot needs no message-path filter.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any

from whiztap.analyzer import __version__
from whiztap.analyzer.protocol.codec import MAX_CHANNEL
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.traffic import NAMES, HalfClosed

FORMAT_VERSION = "4"  # 2: /log, and the plot topics per channel (/sensors/12) instead of /sensors;
# 3: /tcp/delivered and /interventions when the proxy stands in the middle;
# 4: an intervention's cause as fields (source, name, spec), its frame's index, offsets and held id
PROFILE = "whiztap"
SPEC_REVISION = "1.8"
METADATA_NAME = "whiztap"
SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"
REDACTED = "<redacted>"
MASK_BYTE = b"*"  # stands in for each byte of a redacted password

TOPIC_READS = "/tcp/reads"
TOPIC_EVENTS = "/tcp/events"
TOPIC_DELIVERED = "/tcp/delivered"
TOPIC_INTERVENTIONS = "/interventions"
TOPIC_FRAMES = "/frames"
TOPIC_VIOLATIONS = "/violations"
TOPIC_LOG = "/log"
TOPIC_CAMERA = "/camera"
TOPIC_MIRROR_S2C = "/mirror/tcp/s2c"  # record --mirror: the mirror server's answers
TOPIC_MIRROR_EVENTS = "/mirror/tcp/events"  # ... its connection's life (connected, failed, dropped, closed)
TOPIC_MIRROR_DIFFERENCES = "/mirror/differences"  # ... where its answers differ from the primary's
# The plot topics' bases: channel N's values are on BASE/N (BASE/other for a
# channel number past the spec's 0-23); version 1 files had them all on BASE.
TOPIC_SENSORS = "/sensors"
TOPIC_SERVOS = "/servos"
TOPIC_SENDS = "/sends"
TOPIC_SWITCHES = "/switches"
OTHER_CHANNEL = "other"

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
        {"conn": _CONN, "event": {"type": "string", "enum": list(NAMES.values())}, "t_ns": _NS,
         "by": {"type": ["string", "null"], "enum": ["client", "server", "recorder", "proxy", None]},
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
    "whiztap.Intervention": _object(
        "whiztap.Intervention", "The proxy changed the traffic on purpose (a fault, a script, a hand edit, "
                                "an injection): what, why, and the frame before and after.",
        {"conn": _CONN, "t_ns": _NS, "dir": _DIR,
         "action": {"type": "string", "description": "drop, dup, delay, corrupt, replace, slice, bandwidth, "
                                                     "blackhole, reset, close, hold, release, edit, inject, "
                                                     "expire (due after its connection closed)"},
         "cause": {"type": "string", "description": "the fault (name: SPEC), script, hand edit or injection"},
         "source": {"type": "string", "enum": ["fault", "script", "hand", "intercept", "injection", "timeout",
                                               "closing", "proxy"], "description": "who or what intervened (format 4)"},
         "name": {"type": "string", "description": "the fault's or script's name; for a hand, what it did"},
         "spec": {"type": "string", "description": "the fault's SPEC; for a hold timeout, how long"},
         "index": {"type": "integer", "description": "the frame's number among its sender's frames in its "
                                                     "direction (absent: no sent frame: an injection, a timer)"},
         "held": {"type": "integer", "description": "the held frame's id (absent: not a held frame)"},
         "offset": {"type": "integer", "description": "where the frame begins in its sender's stream"},
         "delivered": {"type": "integer", "description": "where the frame begins in the stream its receiver got "
                                                         "(/tcp/delivered offsets; absent: not delivered)"},
         "kind": _STR, "before": _STR, "after": _STR,
         "before_size": _INT, "after_size": _INT, "detail": _STR, "redacted": {"type": "boolean"}},
        ("conn", "t_ns", "dir", "action", "cause", "before", "after")),
    "whiztap.MirrorEvent": _object(
        "whiztap.MirrorEvent", "record --mirror: the life of a connection's mirror connection, which gets the "
                               "client's bytes too and whose answers never reach the client.",
        {"conn": _CONN, "t_ns": _NS,
         "event": {"type": "string", "enum": ["connected", "failed", "dropped", "closed"],
                   "description": "failed: never connected; dropped: by the proxy (its buffer was full, or the "
                                  "recording fell behind), so the primary is never held up"},
         "detail": _STR, "c2s_bytes": {"type": "integer", "description": "client bytes the kernel took toward the "
                                                                        "mirror (0 before it ended)"},
         "s2c_bytes": {"type": "integer", "description": "bytes the mirror sent"}},
        ("conn", "t_ns", "event", "detail")),
    "whiztap.MirrorDifference": _object(
        "whiztap.MirrorDifference", "record --mirror: an exchange the primary and the mirror answered differently, "
                                    "paired as 'whiztap diff' pairs two recordings.",
        {"conn": _CONN, "t_ns": _NS,
         "kind": {"type": "string", "enum": ["value", "timing", "missing", "extra", "handshake"],
                  "description": "missing: the primary has it and the mirror not; extra: the other way"},
         "exchange": _STR, "what": _STR, "primary": _STR, "mirror": _STR,
         "at_fault": {"type": "string", "enum": ["primary", "mirror", "both", "neither"],
                      "description": "which server's conversation breaks the spec here (the client's "
                                     "own breaches are in both alike)"},
         "rules": {"type": "array", "items": _STR, "description": "SIDE RULE: the rules broken, and by whom"}},
        ("conn", "t_ns", "kind", "exchange", "what", "primary", "mirror", "at_fault")),
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
    "foxglove.Log": {
        "title": "foxglove.Log", "description": "A log message (Foxglove's schema): a violation, for the Log panel",
        "type": "object",
        "properties": {
            "timestamp": {"type": "object", "properties": {"sec": _INT, "nsec": _INT}},
            "level": {"type": "integer", "description": "0 UNKNOWN, 1 DEBUG, 2 INFO, 3 WARNING, 4 ERROR, 5 FATAL",
                      "oneOf": [{"title": name, "const": n} for n, name in enumerate(
                          ("UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL"))]},
            "message": _STR,
            "name": {"type": "string", "description": "the rule id"},
            "file": {"type": "string", "description": "where in the traffic: conn-N and the direction"},
            "line": {"type": "integer", "description": "the frame's index in the session (0 when none)"}},
        "required": ["timestamp", "level", "message", "name", "file", "line"]},
    "foxglove.CompressedImage": {
        "title": "foxglove.CompressedImage", "description": "A compressed image (Foxglove's schema)",
        "type": "object",
        "properties": {
            "timestamp": {"type": "object", "properties": {"sec": _INT, "nsec": _INT}},
            "frame_id": _STR, "data": _B64, "format": _STR},
        "required": ["timestamp", "frame_id", "data", "format"]},
}

# topic -> schema name of the topics every file has, in registration order
# (channel ids follow it).  What a reader of byte streams needs (the analyzer,
# replay, the TUI): the TCP reads and the connection events, in arrival order.
# The writer keeps them in chunks of their own, so such a reader decompresses
# nothing else.
STREAM_TOPICS = (TOPIC_READS, TOPIC_EVENTS, TOPIC_DELIVERED, TOPIC_INTERVENTIONS)

TOPICS: dict[str, str] = {
    TOPIC_READS: "whiztap.TcpRead",
    TOPIC_EVENTS: "whiztap.ConnectionEvent",
    TOPIC_FRAMES: "whiztap.Frame",
    TOPIC_VIOLATIONS: "whiztap.Violation",
    TOPIC_LOG: "foxglove.Log",
    TOPIC_CAMERA: "foxglove.CompressedImage",
}

# Topics only a recording made with the proxy in the middle has (registered on
# their first message): what each side received, and every change made to it.
MITM_TOPICS: dict[str, str] = {
    TOPIC_DELIVERED: "whiztap.TcpRead",
    TOPIC_INTERVENTIONS: "whiztap.Intervention",
}

# Topics only a recording made with --mirror has (registered on their first message).
MIRROR_TOPICS: dict[str, str] = {
    TOPIC_MIRROR_S2C: "whiztap.TcpRead",
    TOPIC_MIRROR_EVENTS: "whiztap.MirrorEvent",
    TOPIC_MIRROR_DIFFERENCES: "whiztap.MirrorDifference",
}

# The plottable values: base topic -> schema.  A file has a topic per channel
# that occurred (registered on its first message in each file), not the base.
PLOT_TOPICS: dict[str, str] = {
    TOPIC_SENSORS: "whiztap.SensorValue",
    TOPIC_SERVOS: "whiztap.ServoPosition",
    TOPIC_SENDS: "whiztap.NormalSend",
    TOPIC_SWITCHES: "whiztap.Switch",
}


def _per_channel(base: str) -> tuple[str, ...]:
    return (*(f"{base}/{channel}" for channel in range(MAX_CHANNEL + 1)), f"{base}/{OTHER_CHANNEL}")


# Each base's topics indexed by channel number: channels 0-23, then BASE/other
# at 24, where every channel number past the spec's goes (``channel_topic``).
PER_CHANNEL: dict[str, tuple[str, ...]] = {base: _per_channel(base) for base in PLOT_TOPICS}
SENSOR_TOPICS, SERVO_TOPICS = PER_CHANNEL[TOPIC_SENSORS], PER_CHANNEL[TOPIC_SERVOS]  # encode_plots' look-ups
SEND_TOPICS, SWITCH_TOPICS = PER_CHANNEL[TOPIC_SENDS], PER_CHANNEL[TOPIC_SWITCHES]

# Every per-channel topic -> its schema: a bounded set (a hostile client's
# channel numbers all go to BASE/other), so a file never has more channels
# than len(TOPICS) + len(CHANNEL_TOPICS).
CHANNEL_TOPICS: dict[str, str] = {topic: PLOT_TOPICS[base] for base, topics in PER_CHANNEL.items()
                                  for topic in topics}

# Every topic whiztap has written: this version's, and the aggregated plot
# topics of version 1 files (read and checked alike; no reader needs them).
KNOWN_TOPICS: dict[str, str] = {**TOPICS, **MITM_TOPICS, **MIRROR_TOPICS, **CHANNEL_TOPICS, **PLOT_TOPICS}

# The topics a file defines on their first message rather than at its start.
LATE_TOPICS: dict[str, str] = {**MITM_TOPICS, **MIRROR_TOPICS, **CHANNEL_TOPICS}


def channel_topic(base: str, channel: int) -> str:
    """The plot topic of ``channel`` under ``base`` (``/sensors/12``; past the
    spec's channels, ``/sensors/other``)."""
    topics = PER_CHANNEL[base]
    return topics[channel] if channel < MAX_CHANNEL + 1 else topics[-1]


def schema_bytes(name: str) -> bytes:
    """A schema as a channel's schema record holds it (compact JSON)."""
    return json.dumps(SCHEMAS[name], separators=(",", ":")).encode()


def metadata_record(**values: Any) -> dict[str, str]:
    """The one "whiztap" metadata record: MCAP metadata values are strings."""
    record = {"format_version": FORMAT_VERSION, "whiztap_version": __version__, "spec_revision": SPEC_REVISION}
    record.update({k: "" if v is None else str(v) for k, v in values.items()})
    return record


# -- checking what a reader gets -------------------------------------------------------------

_MAX_INT = 10 ** 19  # integers in messages are ids, counts, offsets and times: non-negative, 19 digits at most
_JSON_TYPES: dict[str, type] = {"string": str, "boolean": bool, "array": list, "object": dict, "null": type(None)}


def misfit(message: Any, topic: str) -> str | None:
    """Why a decoded message of ``topic`` does not fit its schema's top-level
    fields (None when it does, or when whiztap defines no such topic): readers
    then use those fields without checking them."""
    name = KNOWN_TOPICS.get(topic)
    if name is None:
        return None
    schema = SCHEMAS[name]
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
    if message.get("event") == NAMES[HalfClosed] and "dir" not in message:
        return "a half_closed event without 'dir'"
    return None


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
