"""Reading a recording back, fast, trusting nothing in the file.

``RecordingScan`` walks an MCAP file's records once, in file order, and gives
the messages of the topics asked for; ``traffic()`` turns the TCP reads and
connection events into typed traffic events, and in a recording made with the
proxy in the middle what each side received and each change the proxy made.  ``read_metadata`` reads only as
far as the "whiztap" metadata record, ``is_finished`` only the file's last
bytes.  Every failure is a ``RecordingError`` whose message is one line for the
user, naming the record's offset.

How much of a file a reader takes at once is limited (``max_chunk``): the
callers pass it in; ``max_chunk_setting()`` is the user's setting, read from
the environment in this one place.
"""

from __future__ import annotations

import binascii
import io
import json
import os
import re
import struct
from collections.abc import Iterable, Iterator
from pathlib import Path

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.text import parse_size, unescape
from whiztap.analyzer.recording.format import (
    MASK_BYTE,
    METADATA_NAME,
    REDACTED,
    TOPIC_DELIVERED,
    TOPIC_EVENTS,
    TOPIC_INTERVENTIONS,
    TOPIC_READS,
    misfit,
)
from whiztap.analyzer.recording.mcap import (
    FILE_END,
    LOG_TIME_AT,
    MAGIC,
    MESSAGE_DATA_AT,
    MESSAGE_FIXED,
    MIB,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_METADATA,
    RECORD_HEAD,
    RECORD_HEAD_CHANNEL,
    U16,
    U32,
    U64,
    DamagedRecord,
    TooBig,
    open_chunk,
    read_metadata_record,
    read_string,
)
from whiztap.analyzer.recording.remote import Readable, RemotePart, open_part
from whiztap.analyzer.traffic import (
    Action,
    Cause,
    Data,
    Delivered,
    Intervention,
    Source,
    TrafficError,
    TrafficEvent,
    from_json,
)

MAX_CHUNK_ENV = "WHIZTAP_MAX_CHUNK"
DEFAULT_MAX_CHUNK = 256 << 20
_OP_READ = frozenset((OP_CHUNK, OP_CHANNEL, OP_MESSAGE, OP_METADATA))  # what a scan looks inside
_OP_METADATA_ONLY = frozenset((OP_METADATA,))  # what it looks inside when no topic is wanted
_OP_NAMES = {OP_CHUNK: "chunk", OP_MESSAGE_INDEX: "message index", OP_METADATA: "metadata record",
             OP_CHANNEL: "channel record", OP_MESSAGE: "message"}
_DIRECTIONS = {b"c2s": Direction.C2S, b"s2c": Direction.S2C}
_HELD_IN_CAUSE = re.compile(r" \(held #(\d+)\)$")  # format 3 wrote a held id only in the cause
_READ_JSON = re.compile(
    rb'\{"conn":(\d{1,19}),"dir":"(c2s|s2c)","t_ns":(\d{1,19}),"offset":(\d{1,19}),"size":\d+,'
    rb'(?:"redacted":(\[[\d,\[\]]*\]),)?"data":"([A-Za-z0-9+/=]*)"\}')

Record = tuple[int, str, bytes, int, int]  # log time, topic, buffer, start, end: the message is buffer[start:end]


class RecordingError(WhiztapError):
    """The file is not a recording whiztap can read (message says why, in one line)."""


def max_chunk_setting() -> int:
    """The most bytes a reader takes for one record or one chunk's contents, as
    the user set it (``WHIZTAP_MAX_CHUNK``, a byte count: 512M, 2G).

    Whiztap's chunks hold about 1 MiB; one 32 MiB camera image (the framer's
    default --max-image) makes a chunk of about 200 MiB of JSON.  A file that
    claims more is damaged or a decompression bomb, refused before anything is
    allocated.  A file you trust that needs more is read with the setting
    raised.  This is the one place whiztap reads it.
    """
    value = os.environ.get(MAX_CHUNK_ENV, "")
    if not value:
        return DEFAULT_MAX_CHUNK
    try:
        return parse_size(value)
    except ValueError as e:
        raise RecordingError(f"{MAX_CHUNK_ENV}: {e}") from None


def _too_big(where: str, e: TooBig) -> RecordingError:
    advice = f"; if you trust it, {MAX_CHUNK_ENV}={-(-e.size // MIB)}M lets whiztap read it" if e.size < 1 << 40 else ""
    return RecordingError(f"{where} {e}{advice}")


def _skip(f: Readable, n: int) -> bool:
    """Go past ``n`` bytes of ``f``: a file seeks, any other stream (a growing
    file, one that counts what is read) reads a MiB at a time.  False when it
    ends first (for a file that seeks, the next read finds out)."""
    if type(f) is io.BufferedReader:
        f.seek(n, 1)
        return True
    while n > 0:
        got = len(f.read(min(n, MIB)))
        if not got:
            return False
        n -= got
    return True


class RecordingScan:
    """One pass over an MCAP file's data section that yields the wanted topics'
    messages fast, and notes what else a reader of streams needs (channels,
    metadata, whether the file was cut short).

    Why not ``mcap.reader``: decoding every message as an object, then as JSON,
    tops out near 150k messages/s here.  This walks records with ``struct``,
    decompresses chunks itself (checking their CRC), skips other channels by
    id without decoding them, and pulls the fields of each read from its JSON
    with one compiled regex (falling back to ``json.loads`` for a message
    another writer laid out differently).  It reads files in order, so it also
    reads a ``.part`` left by a crash, up to its last complete chunk; then
    ``truncated`` is true.

    It trusts nothing in the file: no record or chunk may claim more than
    ``max_chunk`` bytes (None: ``max_chunk_setting()``), a chunk must decompress
    to exactly what it claims (and memory grows only with what it really
    holds), every length must fit inside what contains it, and every message a
    reader gets fits its schema.  Anything else raises ``RecordingError``
    naming the record's offset.
    """

    def __init__(self, stream: Readable, topics: Iterable[str] = (TOPIC_READS,),
                 validate_crcs: bool = True, growing: bool = False, *, max_chunk: int | None = None) -> None:
        self._stream = stream
        self._wanted = set(topics)
        self._look_inside = _OP_READ if self._wanted else _OP_METADATA_ONLY
        self._max_chunk = max_chunk
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

    def records(self, until_metadata: str | None = None) -> Iterator[Record]:
        """(log_time, topic, data, start, end) of each wanted message, file order;
        ``data[start:end]`` is the message (no copy is made).  With
        ``until_metadata``, the walk ends after the metadata record of that name."""
        limit = max_chunk_setting() if self._max_chunk is None else self._max_chunk
        try:
            yield from self._records(limit, until_metadata)
        except TooBig as e:
            raise _too_big(self._where(), e) from None
        except (ValueError, struct.error) as e:  # DamagedRecord, or a field that does not parse
            raise RecordingError(f"{self._where()} is damaged ({e}); 'whiztap recover' copies what is "
                                 "readable into a new file") from None

    def _where(self) -> str:
        return f"the {_OP_NAMES.get(self._op, 'record')} at byte {self._at}"

    def _records(self, limit: int, until_metadata: str | None) -> Iterator[Record]:
        """The walk over the data section's records (one step per record; a
        chunk's messages come from ``_chunk``)."""
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
            op, length = RECORD_HEAD.unpack(head)
            self._op = op
            if op in (OP_DATA_END, OP_FOOTER):
                return
            if op == 0:
                raise DamagedRecord("opcode 0 starts no MCAP record")
            if length > limit:
                raise TooBig(length, limit)
            if op not in self._look_inside:
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
            if op != OP_CHUNK:
                yield from self._record(op, head + body, 0, 9 + length)
                if until_metadata is not None and until_metadata in self.metadata:
                    return
                head = f.read(9)
            elif self.growing:
                yield from self._chunk(body, None, limit)
                head = f.read(9)  # after the chunk's messages: this read waits for the recorder
            else:
                offsets, head, at = self._message_indexes(at, limit)
                yield from self._chunk(body, offsets, limit)

    def _message_indexes(self, at: int, limit: int) -> tuple[list[int] | None, bytes, int]:
        """Read the message indexes that follow a chunk (``at`` is where they
        start): the offsets of the wanted messages in it (None: walk the chunk
        whole), the head of the record after them, and where it starts.

        With the indexes, only the wanted messages are looked at (a recording
        holds several messages per frame, of which an analysis wants one per
        TCP read).  Only in whiztap's own files, whose writer defines every
        channel outside chunks, before the first chunk that holds its
        messages (a plot topic's on its first message), so a chunk skipped
        this way cannot hide a channel."""
        f = self._stream
        chunk_at = self._at
        offsets: list[int] | None = [] if METADATA_NAME in self.metadata else None
        indexed = False
        head = f.read(9)
        while len(head) == 9 and head[0] == OP_MESSAGE_INDEX:
            self._at, self._op = at, OP_MESSAGE_INDEX
            size = RECORD_HEAD.unpack(head)[1]
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
        self._at, self._op = chunk_at, OP_CHUNK
        return (offsets if indexed else None), head, at

    def _indexed_offsets(self, index: bytes, offsets: list[int]) -> list[int] | None:
        """Add one MessageIndex record's offsets for wanted channels; None when it
        names a channel not yet defined (then the chunk is walked whole)."""
        channel = U16.unpack_from(index, 0)[0]
        topic = self.channels.get(channel)
        if topic is None:
            return None
        if topic in self._wanted:
            n = U32.unpack_from(index, 2)[0]
            if 6 + n > len(index) or n % 16:
                raise DamagedRecord(f"it claims {n} bytes of entries in a record of {len(index)}")
            offsets.extend(struct.unpack_from(f"<{n // 8}Q", index, 6)[1::2])
        return offsets

    def _chunk(self, body: bytes, offsets: list[int] | None, limit: int) -> Iterator[Record]:
        """The wanted messages of a chunk: those its index points at, or all of
        them when it has no index that can be used."""
        if offsets is not None and not offsets:
            return  # indexed, and nothing wanted in it: not even decompressed
        records, first, end = open_chunk(body, limit, self.validate_crcs)
        unpack = RECORD_HEAD_CHANNEL.unpack_from
        log_time = U64.unpack_from
        wanted = self._wanted_ids()
        if offsets:
            offsets.sort()  # file order is arrival order; the index is in log-time order
            if first + offsets[-1] + 9 > end:  # checked once: the largest is the last
                raise DamagedRecord("a message index points past the end of its chunk")
            for offset in offsets:
                pos = first + offset
                op, length, channel = unpack(records, pos)  # struct.error past the buffer
                if op != OP_MESSAGE or length < MESSAGE_FIXED or pos + 9 + length > end:
                    raise DamagedRecord("a message index points at no message in it")
                if channel in wanted:
                    yield log_time(records, pos + LOG_TIME_AT)[0], wanted[channel], records, \
                        pos + MESSAGE_DATA_AT, pos + 9 + length
            return
        pos = first
        while pos < end:
            op, length, channel = unpack(records, pos)
            stop = pos + 9 + length
            if stop > end or op == 0:
                raise DamagedRecord(f"the record at {pos - first} in it is "
                                    f"{'opcode 0' if op == 0 else 'longer than the chunk'}")
            if op == OP_MESSAGE:
                if length < MESSAGE_FIXED:
                    raise DamagedRecord(f"the message at {pos - first} in it is too short")
                if channel in wanted:
                    yield log_time(records, pos + LOG_TIME_AT)[0], wanted[channel], records, pos + MESSAGE_DATA_AT, \
                        stop
            else:
                yield from self._record(op, records, pos, stop)
                wanted = self._wanted_ids()
            pos = stop

    def _record(self, op: int, buf: bytes, pos: int, stop: int) -> Iterator[Record]:
        if op == OP_CHANNEL:
            channel = U16.unpack_from(buf, pos + 9)[0]
            topic, _ = read_string(buf, pos + 13, stop)
            self.channels[channel] = topic
        elif op == OP_MESSAGE:
            if stop - pos < MESSAGE_DATA_AT:
                raise DamagedRecord("it is too short for a message")
            channel = U16.unpack_from(buf, pos + 9)[0]
            topic = self.channels.get(channel, "")  # no topic is "": a channel not defined is not wanted
            if topic in self._wanted:
                yield U64.unpack_from(buf, pos + LOG_TIME_AT)[0], topic, buf, pos + MESSAGE_DATA_AT, stop
        elif op == OP_METADATA:
            name, values = read_metadata_record(buf, pos + 9, stop)
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
        problem = misfit(message, topic)
        if problem is not None:
            raise self._invalid(topic, problem)
        return message

    def _invalid(self, topic: str, why: str) -> RecordingError:
        return RecordingError(f"a {topic} message in {self._where()} is not valid ({why}): the file is damaged "
                              "or not a whiztap recording")

    def traffic(self) -> Iterator[TrafficEvent]:
        """The recording's traffic as typed events in file (= arrival) order:
        each /tcp/reads message as ``Data``, each /tcp/events message as its
        connection event (``traffic.from_json``), each /tcp/delivered message
        as ``Delivered`` and each /interventions message as ``Intervention``
        (when the scan was asked for those topics).  Other topics are skipped."""
        match = _READ_JSON.match
        b64 = binascii.a2b_base64  # what base64.b64decode calls, without its Python layer
        directions = _DIRECTIONS
        topic = TOPIC_READS
        try:
            for _t, topic, buf, start, stop in self.records():
                if topic == TOPIC_READS:
                    m = match(buf, start, stop)
                    if m is not None and m.end() == stop:
                        conn, direction, t_ns, offset, spans, data = m.groups()
                        yield Data(int(conn), directions[direction], int(t_ns), b64(data), int(offset),
                                   spans is not None and spans != b"[]")
                    else:
                        d = self.decode(topic, buf, start, stop)
                        yield Data(d["conn"], directions[d["dir"].encode()], d["t_ns"], b64(d["data"]), d["offset"],
                                   bool(d.get("redacted")))
                elif topic == TOPIC_EVENTS:
                    try:
                        yield from_json(self.decode(topic, buf, start, stop))
                    except TrafficError as e:
                        raise self._invalid(topic, str(e)) from None
                elif topic == TOPIC_DELIVERED:
                    yield self._delivered(buf, start, stop)
                elif topic == TOPIC_INTERVENTIONS:
                    yield self._intervention(self.decode(topic, buf, start, stop))
        except ValueError as e:  # binascii.Error: data that is not base64 (or not ASCII)
            if isinstance(e, RecordingError):
                raise
            raise self._invalid(topic, f"its data is not base64: {e}") from None

    def _delivered(self, buf: bytes, start: int, stop: int) -> Delivered:
        """A /tcp/delivered message (a read's layout): what one side received;
        ``secret`` when it holds a masked password."""
        m = _READ_JSON.match(buf, start, stop)
        if m is not None and m.end() == stop:
            conn, direction, t_ns, _offset, spans, data = m.groups()
            return Delivered(int(conn), _DIRECTIONS[direction], int(t_ns), binascii.a2b_base64(data),
                             spans is not None and spans != b"[]")
        d = self.decode(TOPIC_DELIVERED, buf, start, stop)
        return Delivered(d["conn"], _DIRECTIONS[d["dir"].encode()], d["t_ns"], binascii.a2b_base64(d["data"]),
                         bool(d.get("redacted")))

    def _intervention(self, d: dict) -> Intervention:
        """An /interventions message: the frame before and after as bytes again,
        the cause and held id from their fields (format 3 wrote them only in
        the cause's text, which is read for them then)."""
        redacted = d.get("redacted") is True
        try:
            action = Action(d["action"])
            if "source" in d:
                cause = Cause(Source(d["source"]), d.get("name", ""), d.get("spec", ""))
                held = d.get("held", 0)
            else:
                cause = Cause.parse(d["cause"])
                held = int(m.group(1)) if (m := _HELD_IN_CAUSE.search(d["cause"])) else 0
        except (ValueError, KeyError, TypeError) as e:
            raise self._invalid(TOPIC_INTERVENTIONS, f"not an intervention whiztap knows ({e})") from None
        kind = d.get("kind", "")
        return Intervention(d["conn"], d["t_ns"], _DIRECTIONS[d["dir"].encode()], action, cause,
                            self._frame_bytes(d, "before", redacted), self._frame_bytes(d, "after", redacted),
                            kind, d.get("detail", ""), d.get("index", -1), held,
                            redacted or kind == "password", d.get("offset", -1), d.get("delivered", -1))

    def _frame_bytes(self, d: dict, key: str, redacted: bool) -> bytes:
        """A frame an /interventions message holds as escaped text; a password
        the recorder left out (``<redacted>``) as mask bytes of its size, which
        may be no larger than a record may be."""
        text = d[key]
        if redacted and text == REDACTED:
            size = d.get(f"{key}_size")
            limit = max_chunk_setting() if self._max_chunk is None else self._max_chunk
            if size is None or size > limit:
                raise self._invalid(TOPIC_INTERVENTIONS, f"a redacted {key!r} without a size up to {limit}")
            return MASK_BYTE * size
        try:
            return unescape(text)
        except ValueError as e:  # a lone surrogate cannot be encoded
            raise self._invalid(TOPIC_INTERVENTIONS, f"{key!r} is not escaped text ({e})") from None

    def messages(self) -> Iterator[tuple[str, int, dict]]:
        """(topic, log_time, decoded JSON) of each wanted message, file order."""
        for t, topic, buf, start, stop in self.records():
            yield topic, t, self.decode(topic, buf, start, stop)


def made_in_the_middle(path: str | Path | RemotePart) -> bool:
    """Whether a recording's metadata says the proxy stood in the middle
    (docs/faults.md).  A file that cannot tell is read as one that was not:
    whatever reads it next says what is wrong with it, in its own words."""
    try:
        return read_metadata(path).get("middle") == "yes"
    except (OSError, RecordingError):
        return False


def read_metadata(path: str | Path | RemotePart, max_chunk: int | None = None) -> dict[str, str]:
    """The "whiztap" metadata record of a recording ({} if it has none); ``path``
    may be a URL's ``RemotePart``.

    Recorders write it before the first chunk, so this walks only as far as
    that record, looking inside nothing else.  Raises RecordingError for a file
    that is no MCAP file or whose records do not add up.
    """
    with open_part(path, head=True) as f:
        scan = RecordingScan(f, (), max_chunk=max_chunk)
        for _ in scan.records(until_metadata=METADATA_NAME):
            pass  # no topic is wanted: nothing comes; the walk notes the metadata
    return scan.metadata.get(METADATA_NAME, {})


def is_finished(path: str) -> bool:
    """Whether the file ends as a finished MCAP file does: a footer that points
    at a summary section (the index), then the magic.  Reads the last bytes only."""
    with open(path, "rb") as f:
        size = f.seek(0, os.SEEK_END)
        if size < len(MAGIC) + FILE_END.size:
            return False
        f.seek(size - FILE_END.size)
        op, length, summary_start, _summary_offsets, _crc, magic = FILE_END.unpack(f.read(FILE_END.size))
    return op == OP_FOOTER and length == 20 and magic == MAGIC and len(MAGIC) < summary_start < size
