"""The messages of a recording, as JSON: built from TCP reads and from what the
session model made of them.

One function says what a framer item is in JSON (``item_json``): the /frames
messages and the lines of ``whiztap cat --format jsonl`` both describe items
with it.  The encoders a recorder calls once per TCP read, per frame or per
violation (``encode_read``, ``FrameEncoder``, ``encode_plots``,
``encode_violation``) build their bytes directly, for speed; each has a
dict-building twin that says the same plainly (``read_message``,
``plot_messages`` and ``violation_message`` here; those of the /frames and
/log messages, used by nothing else, are in the tests), and tests check that
the two agree byte for byte.  A violation is two messages, its /violations
message and the ``foxglove.Log`` made from it, built together, so the two
always agree.
"""

from __future__ import annotations

import base64
from typing import Any

import orjson

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
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.text import escape
from whiztap.analyzer.traffic import Intervention
from whiztap.analyzer.recording.format import (
    MASK_BYTE,
    REDACTED,
    SEND_TOPICS,
    SENSOR_TOPICS,
    SERVO_TOPICS,
    SWITCH_TOPICS,
    TOPIC_CAMERA,
    TOPIC_SENDS,
    TOPIC_SENSORS,
    TOPIC_SERVOS,
    TOPIC_SWITCHES,
    channel_topic,
)

# orjson: compact UTF-8 JSON, about 15 times the standard library's speed on
# these messages (benchmarks/bench_writer.py), and far more on a camera
# image's long base64 string.  Dict keys stay in insertion order.
_dumps = orjson.dumps


def encode(message: dict) -> bytes:
    """A message dict as the bytes of an MCAP message (compact UTF-8 JSON)."""
    return _dumps(message)


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def read_message(conn: int, direction: str, t_ns: int, offset: int, data: bytes,
                 redacted: list[tuple[int, int]] | None = None) -> dict:
    """A /tcp/reads message.  Key order is part of the format: the scan's fast
    reader matches it (and falls back to a JSON parser when it does not)."""
    message: dict[str, Any] = {"conn": conn, "dir": direction, "t_ns": t_ns, "offset": offset, "size": len(data)}
    if redacted:
        message["redacted"] = [list(s) for s in redacted]
    message["data"] = _b64(data)
    return message


def encode_read(conn: int, direction: str, t_ns: int, offset: int, data: bytes,
                redacted: list[tuple[int, int]] | None = None) -> bytes:
    """``encode(read_message(...))``, built directly: one of these per TCP read."""
    if redacted:
        return encode(read_message(conn, direction, t_ns, offset, data, redacted))
    return b'{"conn":%d,"dir":"%s","t_ns":%d,"offset":%d,"size":%d,"data":"%s"}' % (
        conn, direction.encode(), t_ns, offset, len(data), base64.b64encode(data))


def item_json(obs: Observation, redact: bool = False) -> dict[str, Any]:
    """What a framer item is, in JSON: the one description that /frames messages
    and ``whiztap cat --format jsonl`` lines share.  Its kind, why it is
    unframed, its size and bytes (``raw``, base64), their text, meaning, message
    title and decoded fields (with ``latency_ns`` when it answers a request),
    the rules it breaks, and whether it is redacted.  With ``redact`` a
    password's bytes become '*' and its text ``<redacted>``; its length stays,
    so offsets and replays still line up."""
    item = obs.item
    raw = item.raw
    hidden = redact and item.kind is ItemKind.PASSWORD
    if hidden:
        raw = MASK_BYTE * len(raw)
    return {
        "kind": item.kind.value, "reason": item.reason.value if item.reason is not None else None,
        "size": len(raw), "raw": _b64(raw), "text": REDACTED if hidden else escape(raw), "meaning": meaning(obs),
        "message": obs.message.title if obs.message is not None else None, "fields": fields(obs),
        "violations": [v.rule_id for v in obs.violations], "redacted": hidden,
    }


def cat_line(conn: int, obs: Observation) -> dict[str, Any]:
    """A line of ``whiztap cat --format jsonl`` (docs/recording-format.md): when
    and where, then ``item_json`` with the bytes as ``raw_b64``."""
    item = obs.item
    line: dict[str, Any] = {"t_ns": item.t_end_ns, "t_start_ns": item.t_start_ns, "conn": conn,
                            "dir": obs.direction.value}
    for key, value in item_json(obs).items():
        line["raw_b64" if key == "raw" else key] = value
    return line


def frame_static(obs: Observation, redact: bool) -> dict:
    """The part of a /frames message fixed by the item's bytes and meaning:
    ``item_json`` less the latency, a top-level field of the frame."""
    static = item_json(obs, redact)
    static["fields"].pop("latency_ns", None)
    return static


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
DIR_TEXT = {d: d.value for d in Direction}  # Enum.value is a slow property
_CACHED_RAW_MAX = 256  # longer items (images, unframed runs) are rare: not worth keeping
_CACHE_LIMIT = 4096  # distinct frames kept; answers with varying values mostly miss anyway


class FrameEncoder:
    """A /frames message (docs/recording-format.md) as JSON bytes, built fast: one of these per frame.

    Real sessions repeat a few hundred distinct frames, so the JSON of the part
    that depends only on the bytes and their meaning (``frame_static``) is
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
            static = _dumps(frame_static(obs, redact))[1:]
        else:
            key = (raw, kind, reason, message.__class__, None if answers is None else answers[3].__class__,
                   violations)
            cached = self._cache.get(key)
            if cached is None:
                if len(self._cache) >= _CACHE_LIMIT:
                    self._cache.clear()
                cached = self._cache[key] = _dumps(frame_static(obs, redact))[1:]
            static = cached
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
        "level": int(rule.severity), "section": violation.section, "summary": rule.summary,
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


LOG_LEVELS = {"info": 2, "warning": 3, "error": 4}  # whiztap's severities as foxglove.Log levels


def _quote(text: str) -> str:
    """A string as ``encode`` writes it (in quotes)."""
    return _dumps(text).decode()


def _rule_json(violation: Violation) -> tuple[str, int]:
    """The rule's fixed fields of a /violations message, as JSON, and its log level."""
    rule = violation.rule
    severity = str(rule.severity)
    return (f'"rule_id":{_quote(rule.id)},"severity":"{severity}","level":{int(rule.severity)},'
            f'"section":{_quote(violation.section)},"summary":{_quote(rule.summary)}', LOG_LEVELS[severity])


_VIOLATION_CACHE: dict[tuple, tuple[bytes, bytes]] = {}  # what decides a violation's messages -> their templates


def encode_violation(conn: int, violation: Violation, about: Observation | None, t_ns: int, late: bool,
                     redact: bool, count: int = 1) -> tuple[bytes, bytes]:
    """A violation's two messages as JSON bytes, built directly: its /violations
    message (``encode(violation_message(...))``) and the ``foxglove.Log`` twin
    made from it for Foxglove's Log panel (docs/recording-format.md, ``/log``),
    whose plain twin is in the tests.  The rule id is the log's ``name`` (the
    panel lists names to filter by), ``file`` and ``line`` say where in the
    traffic (``conn-1 c2s``, the frame's index), and ``message`` says it all in
    one line: rule, detail, connection, direction, frame and its escaped text.

    A client that breaks a rule usually breaks it the same way again and again
    (the pipelined benchmark: one request in ten), so the two messages are
    kept as templates, keyed by everything but the connection, the time and
    the frame's index, which fill them in (as ``FrameEncoder`` does for
    frames).  Passwords are never kept."""
    direction = None if about is None else about.direction
    raw = None if about is None else about.item.raw[:200]
    keep = about is None or about.item.kind is not ItemKind.PASSWORD  # a password is never kept
    key = (violation, raw, direction, late, count)
    templates = _VIOLATION_CACHE.get(key) if keep else None
    if templates is None:
        frame = None if about is None else (about.direction, REDACTED if redact and not keep else escape(raw or b""))
        templates = _violation_templates(violation, frame, late, count)
        if keep:
            if len(_VIOLATION_CACHE) >= _CACHE_LIMIT:
                _VIOLATION_CACHE.clear()
            _VIOLATION_CACHE[key] = templates
    sec, nsec = divmod(t_ns, 1_000_000_000)
    if about is None:
        return templates[0] % (conn, t_ns), templates[1] % (sec, nsec, conn, conn)
    line = about.index
    return templates[0] % (conn, t_ns, line), templates[1] % (sec, nsec, conn, line, conn, line)


def _violation_templates(violation: Violation, frame: tuple[Direction, str] | None, late: bool,
                         count: int) -> tuple[bytes, bytes]:
    """The two messages of ``encode_violation`` with ``%d`` where the
    connection, the time (seconds and nanoseconds in the log) and the frame's
    index go; every other ``%`` doubled.  ``frame``: the direction and text of
    the frame it is about (None: about the connection)."""
    def lit(value: str) -> str:
        return value.replace("%", "%%")

    rule_id = violation.rule_id
    fixed = _rule_json(violation)
    detail = lit(_quote(violation.detail)[1:-1])
    if frame is None:
        about_json = where = ""
        file = "conn-%d"
    else:
        d = DIR_TEXT[frame[0]]
        quoted = lit(_quote(frame[1])[1:-1])
        about_json = f',"dir":"{d}","frame_index":%d,"frame_text":"{quoted}"'
        where = f" {d}, frame %d: {quoted}"
        file = f"conn-%d {d}"
    if late:
        where += ", found later"
    counted = f',"count":{count}' if count > 1 else ""
    flag = "true" if late else "false"
    rule = lit(rule_id)
    return (f'{{"conn":%d,"t_ns":%d,{lit(fixed[0])},"detail":"{detail}","late":{flag}{about_json}{counted}}}'
            .encode(),
            f'{{"timestamp":{{"sec":%d,"nsec":%d}},"level":{fixed[1]},'
            f'"message":"{rule}: {detail} (conn %d{where})","name":"{rule}","file":"{file}",'
            f'"line":{"%d" if frame is not None else 0}}}'.encode())


def plot_messages(conn: int, obs: Observation) -> list[tuple[str, dict]]:
    """The plottable values an observation gives: (topic, message) pairs, the
    topic that of the message's channel (``/sensors/12``, ``format.channel_topic``)."""
    message = obs.message
    if message is None:
        return []
    if isinstance(message, ChannelResponse) and obs.answers is not None:
        channel = message.channel
        if response_meaning(obs) == "servo":
            return [(channel_topic(TOPIC_SERVOS, channel), {
                "conn": conn, "channel": channel, "data": message.data, "position": message.data / 4,
                "latency_ns": obs.latency_ns})]
        return [(channel_topic(TOPIC_SENSORS, channel), {"conn": conn, "channel": channel, "value": message.data,
                                                         "latency_ns": obs.latency_ns})]
    if isinstance(message, NormalSend):
        return [(channel_topic(TOPIC_SENDS, message.channel),
                 {"conn": conn, "channel": message.channel, "value": message.value})]
    if isinstance(message, (ActivateSwitch, DeactivateSwitch)):
        state = 1 if isinstance(message, ActivateSwitch) else 0
        return [(channel_topic(TOPIC_SWITCHES, message.channel),
                 {"conn": conn, "channel": message.channel, "state": state})]
    if isinstance(message, CameraImage):
        t = obs.item.t_end_ns
        return [(TOPIC_CAMERA, {"timestamp": {"sec": t // 1_000_000_000, "nsec": t % 1_000_000_000},
                                "frame_id": f"conn-{conn}", "data": _b64(message.data),
                                "format": message.format})]
    return []


_SENSOR = b'{"conn":%d,"channel":%d,"value":%d,"latency_ns":%s}'
_SERVO = b'{"conn":%d,"channel":%d,"data":%d,"position":%s,"latency_ns":%s}'
_SEND = b'{"conn":%d,"channel":%d,"value":%d}'
_SWITCH = b'{"conn":%d,"channel":%d,"state":%d}'


def encode_plots(conn: int, obs: Observation) -> list[tuple[str, bytes]]:
    """``plot_messages`` encoded.  The answers to sensor and servo requests,
    which come by the thousand, and the commands that set a channel are built
    directly, their topic found by indexing a tuple (``format.PER_CHANNEL``:
    channels 0-23, then BASE/other at 24, where any channel past the spec's goes)."""
    message = obs.message
    match message:
        case ChannelResponse():
            answers = obs.answers
            if answers is None:
                return []
            channel = message.channel
            latency = b"null" if obs.latency_ns is None else b"%d" % obs.latency_ns
            if type(answers.message) is ServoPositionRequest:
                topics = SERVO_TOPICS
                data = _SERVO % (conn, channel, message.data, repr(message.data / 4).encode(), latency)
            else:
                topics = SENSOR_TOPICS
                data = _SENSOR % (conn, channel, message.data, latency)
        case NormalSend():
            channel = message.channel
            topics = SEND_TOPICS
            data = _SEND % (conn, channel, message.value)
        case ActivateSwitch() | DeactivateSwitch():
            channel = message.channel
            topics = SWITCH_TOPICS
            data = _SWITCH % (conn, channel, 1 if type(message) is ActivateSwitch else 0)
        case CameraImage():
            return [(topic, encode(m)) for topic, m in plot_messages(conn, obs)]
        case _:
            return []
    try:
        return [(topics[channel], data)]
    except IndexError:  # a channel past 24 (no cost on the way that does not raise)
        return [(topics[-1], data)]


def intervention_message(event: Intervention, redact: bool) -> dict[str, Any]:
    """An /interventions message: the frame before and after as escaped text
    (a password's as ``<redacted>`` unless secrets are kept; sizes stay), the
    cause as one line and as its fields, the frame's index and the held id."""
    hidden = redact and (event.secret or event.kind == ItemKind.PASSWORD.value)
    cause = event.cause
    message: dict[str, Any] = {
        "conn": event.conn, "t_ns": event.t_ns, "dir": event.direction.value, "action": event.action.value,
        "cause": str(cause), "source": cause.source.value, "name": cause.name, "spec": cause.text,
        "kind": event.kind,
        "before": REDACTED if hidden and event.before else escape(event.before),
        "after": REDACTED if hidden and event.after else escape(event.after),
        "before_size": len(event.before), "after_size": len(event.after), "detail": event.detail}
    if event.index >= 0:
        message["index"] = event.index
    if event.offset >= 0:
        message["offset"] = event.offset
    if event.delivered >= 0:
        message["delivered"] = event.delivered
    if event.held:
        message["held"] = event.held
    if hidden:
        message["redacted"] = True
    return message
