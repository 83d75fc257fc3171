"""The one MCAP layout whiztap knows: magic, opcodes, record heads, a small fast
writer, and the low-level pieces every reader shares (a chunk's records, a
string, a metadata record).  ``scan`` and ``recover`` read with these; the
writer writes with them.

Why not ``mcap.writer.Writer``: it builds a record object per message and writes
it field by field through a BytesIO, about 4 us a message here, which is more
than everything else whiztap does per frame.  This writer packs each Message
record with one precompiled struct into the open chunk, which is several times
faster, and writes the same file layout as the reference writer: chunked and
compressed data with per-chunk message indexes, then a summary (schemas,
channels, statistics, chunk and metadata indexes, summary offsets) and a footer
with its CRC.  Tests read every file it writes with mcap's Python reader and
with the TypeScript @mcap/core reader, CRC checks on.

Unlike the reference writer, schemas and channels are written as soon as they
are registered, outside chunks and before any chunk that holds their
messages, so a file cut short anywhere still says what its channels are.  A
channel may be registered late, on its first message (``on_new_channel``), with
the id the caller chose, so ids can stay the same across the files of a split
recording while each file defines only the channels it uses.  And a channel
can be registered into a chunk group of
its own: its messages then go into chunks that hold only that group, so a
reader that wants only those channels (the analyzer wants the TCP reads, not
the frames decoded from them) decompresses only their chunks.  Chunks of
different groups overlap in time, which MCAP allows; within a channel, file
order is still time order.  A flush closes the open chunks in group order.
Single-threaded, like the reference writer.

Readers trust nothing: the read helpers raise ``DamagedRecord`` (``TooBig`` for
a claim past the reader's limit) saying what is wrong; their callers add where.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable, Iterable
from typing import Protocol

from whiztap.analyzer.errors import WhiztapError

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_MESSAGE_INDEX, OP_CHUNK_INDEX, OP_ATTACHMENT, OP_STATISTICS = 0x07, 0x08, 0x09, 0x0B
OP_METADATA, OP_METADATA_INDEX, OP_SUMMARY_OFFSET, OP_DATA_END = 0x0C, 0x0D, 0x0E, 0x0F
KNOWN_OPS = frozenset(range(OP_HEADER, OP_DATA_END + 1))  # MCAP's opcodes; 0x80 and up are for private records
RECORD_HEAD = struct.Struct("<BQ")  # opcode, length of what follows
RECORD_HEAD_CHANNEL = struct.Struct("<BQH")  # a record head, then a Message's channel id
MESSAGE_FIELDS = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
MESSAGE_FIXED = MESSAGE_FIELDS.size  # a Message's length less its data
MESSAGE_DATA_AT = RECORD_HEAD.size + MESSAGE_FIXED  # where its data starts in the record
LOG_TIME_AT = RECORD_HEAD.size + 6  # where its log time is in the record
_MESSAGE = struct.Struct("<BQHIQQ")  # a Message record's head and fields, packed by the writer at once
CHUNK_HEAD = struct.Struct("<QQQI")  # start and end time, uncompressed size, its CRC; then the compression
FILE_END = struct.Struct("<BQQQI8s")  # the Footer record and the closing magic
U16, U32, U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
MIB = 1 << 20


class DamagedRecord(WhiztapError, ValueError):
    """A record whose lengths or contents do not add up.  The message says
    what, not where: its reader adds the offset."""


class TooBig(DamagedRecord):
    """A record, or a chunk's contents, claiming more than the reader's limit."""

    def __init__(self, size: int, limit: int, what: str = "") -> None:
        super().__init__(f"claims {size} bytes{what}, more than readers take ({_mib(limit)}): the file is "
                         "damaged or a decompression bomb")
        self.size = size


def _mib(n: int) -> str:
    return f"{n} bytes" if n < MIB else f"{n / MIB:g} MiB"


class Stream(Protocol):
    def write(self, data: bytes) -> int: ...
    def tell(self) -> int: ...
    def flush(self) -> None: ...


def _str(s: str) -> bytes:
    b = s.encode()
    return struct.pack("<I", len(b)) + b


def _map(m: dict[str, str]) -> bytes:
    body = b"".join(_str(k) + _str(v) for k, v in m.items())
    return struct.pack("<I", len(body)) + body


def _record(op: int, body: bytes) -> bytes:
    return RECORD_HEAD.pack(op, len(body)) + body


def minimal_end() -> bytes:
    """DataEnd + Footer (no summary) + magic: the smallest valid end of an MCAP
    file, for closing one whose writer can no longer write its summary."""
    return _record(OP_DATA_END, struct.pack("<I", 0)) + _record(OP_FOOTER, struct.pack("<QQI", 0, 0, 0)) + MAGIC


def _compressor(compression: str) -> Callable[[bytes], bytes]:
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdCompressor().compress
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.compress
    if compression == "":
        return bytes
    raise ValueError(f"unknown compression {compression!r}: expected zstd, lz4 or ''")


class _OpenChunk:
    """The messages of one chunk group not yet written, and their index: for each
    channel of the group, a flat list of (log time, offset in chunk) pairs.  The
    lists live as long as the writer and are emptied in place, so a message
    finds its chunk and its index with one look-up (``McapWriter._slots``)."""

    __slots__ = ("records", "index")

    def __init__(self) -> None:
        self.records = bytearray()
        self.index: dict[int, list[int]] = {}  # channel -> [log time, offset, log time, offset, ...]


class McapWriter:
    """Writes one MCAP file to ``stream`` (anything with write, tell and flush)."""

    def __init__(self, stream: Stream, *, chunk_size: int = 1 << 20, compression: str = "zstd") -> None:
        self._stream = stream
        self.chunk_size = chunk_size
        self.compression = compression
        self._compress = _compressor(compression)
        self._schemas: list[bytes] = []  # record bytes, repeated in the summary
        self._channels: list[bytes] = []
        self._counts: dict[int, int] = {}  # messages per channel
        self._chunks: list[_OpenChunk] = [_OpenChunk()]  # the open chunk of each group
        # channel -> (its group's open chunk records, its index list, its group's _OpenChunk)
        self._slots: dict[int, tuple[bytearray, list[int], _OpenChunk]] = {}
        self._chunk_indexes: list[bytes] = []
        self._metadata_indexes: list[bytes] = []
        self.index_size = 0  # bytes of chunk indexes so far: finish() writes them in the summary
        self._start: int | None = None  # message times over the file
        self._end: int | None = None
        self.message_count = 0
        # called with a channel id that a message names and that is not
        # registered yet: it must register it (or raise)
        self.on_new_channel: Callable[[int], None] | None = None

    def start(self, profile: str, library: str) -> None:
        self._stream.write(MAGIC + _record(OP_HEADER, _str(profile) + _str(library)))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema_id = len(self._schemas) + 1
        record = _record(OP_SCHEMA, struct.pack("<H", schema_id) + _str(name) + _str(encoding)
                         + struct.pack("<I", len(data)) + data)
        self._schemas.append(record)
        self._stream.write(record)
        return schema_id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int, group: int = 0,
                         channel_id: int | None = None) -> int:
        """``group``: channels of the same group share chunks; 0 is the default
        group.  ``channel_id``: the id to give it (default: one past the largest so far)."""
        if channel_id is None:
            channel_id = max(self._counts, default=0) + 1
        elif channel_id in self._counts or not 0 < channel_id < 1 << 16:
            raise ValueError(f"channel id {channel_id} is taken or out of range")
        record = _record(OP_CHANNEL, struct.pack("<HH", channel_id, schema_id) + _str(topic)
                         + _str(message_encoding) + _map({}))
        self._channels.append(record)
        self._counts[channel_id] = 0
        while len(self._chunks) <= group:
            self._chunks.append(_OpenChunk())
        open_chunk = self._chunks[group]
        index = open_chunk.index[channel_id] = []
        self._slots[channel_id] = (open_chunk.records, index, open_chunk)
        self._stream.write(record)
        return channel_id

    def add_metadata(self, name: str, values: dict[str, str]) -> None:
        self._finish_chunks()
        offset = self._stream.tell()
        record = _record(OP_METADATA, _str(name) + _map(values))
        self._stream.write(record)
        self._metadata_indexes.append(_record(OP_METADATA_INDEX, struct.pack("<QQ", offset, len(record))
                                              + _str(name)))

    def add_message(self, channel_id: int, log_time: int, data: bytes) -> None:
        """Append a message (publish time = log time) to its group's open chunk."""
        self.add_messages(((channel_id, log_time, data),))

    def add_messages(self, messages: Iterable[tuple[int, int, bytes]]) -> None:
        """``add_message`` for each (channel id, log time, data): the recorder's
        hot path, one call per TCP read rather than per message."""
        slots = self._slots
        pack = _MESSAGE.pack
        limit = self.chunk_size
        for channel_id, log_time, data in messages:
            try:
                chunk, index, open_chunk = slots[channel_id]
            except KeyError:  # no cost on the way that does not raise
                chunk, index, open_chunk = self._new_slot(channel_id)
            index.append(log_time)
            index.append(len(chunk))
            chunk += pack(OP_MESSAGE, MESSAGE_FIXED + len(data), channel_id, 0, log_time, log_time)
            chunk += data
            if len(chunk) >= limit:
                self._finish_chunk(open_chunk)

    def _new_slot(self, channel_id: int) -> tuple[bytearray, list[int], _OpenChunk]:
        """A message names a channel not registered: ``on_new_channel`` registers it now."""
        if self.on_new_channel is None:
            raise KeyError(f"no channel {channel_id}")
        self.on_new_channel(channel_id)
        return self._slots[channel_id]

    @property
    def pending(self) -> int:
        """Bytes in the open chunks (not yet on the stream)."""
        return sum(len(c.records) for c in self._chunks)

    def flush(self) -> None:
        """Close the open chunks and flush the stream: everything so far is on disk."""
        self._finish_chunks()
        self._stream.flush()

    def _finish_chunks(self) -> None:
        for open_chunk in self._chunks:
            self._finish_chunk(open_chunk)

    def _finish_chunk(self, open_chunk: _OpenChunk) -> None:
        indexes_in_use = [(channel_id, index) for channel_id, index in open_chunk.index.items() if index]
        if not indexes_in_use:
            return
        records = bytes(open_chunk.records)
        start = min(min(index[0::2]) for _, index in indexes_in_use)
        end = max(max(index[0::2]) for _, index in indexes_in_use)
        compressed = self._compress(records)
        chunk = _record(OP_CHUNK, CHUNK_HEAD.pack(start, end, len(records), zlib.crc32(records))
                        + _str(self.compression) + struct.pack("<Q", len(compressed)) + compressed)
        stream = self._stream
        chunk_offset = stream.tell()
        stream.write(chunk)
        index_offset = stream.tell()
        offsets = bytearray()
        indexes = bytearray()
        for channel_id, index in indexes_in_use:
            offsets += struct.pack("<HQ", channel_id, index_offset + len(indexes))
            entries = struct.pack(f"<{len(index)}Q", *index)
            indexes += _record(OP_MESSAGE_INDEX, struct.pack("<HI", channel_id, len(entries)) + entries)
            self._counts[channel_id] += len(index) // 2
            self.message_count += len(index) // 2
            index.clear()
        stream.write(bytes(indexes))
        self._chunk_indexes.append(_record(OP_CHUNK_INDEX, struct.pack("<QQQQ", start, end, chunk_offset, len(chunk))
                                           + struct.pack("<I", len(offsets)) + offsets
                                           + struct.pack("<Q", len(indexes)) + _str(self.compression)
                                           + struct.pack("<QQ", len(compressed), len(records))))
        self.index_size += len(self._chunk_indexes[-1])
        self._start = start if self._start is None else min(self._start, start)
        self._end = end if self._end is None else max(self._end, end)
        open_chunk.records.clear()

    def finish(self) -> None:
        """Write the last chunks, the summary and the footer."""
        self._finish_chunks()
        stream = self._stream
        stream.write(_record(OP_DATA_END, struct.pack("<I", 0)))
        summary_start = stream.tell()
        counts = b"".join(struct.pack("<HQ", c, n) for c, n in self._counts.items())
        statistics = _record(OP_STATISTICS, struct.pack(
            "<QHIIIIQQ", self.message_count, len(self._schemas), len(self._channels), 0,
            len(self._metadata_indexes), len(self._chunk_indexes), self._start or 0, self._end or 0)
            + struct.pack("<I", len(counts)) + counts)
        groups = [(OP_SCHEMA, self._schemas), (OP_CHANNEL, self._channels), (OP_STATISTICS, [statistics]),
                  (OP_CHUNK_INDEX, self._chunk_indexes), (OP_METADATA_INDEX, self._metadata_indexes)]
        summary = bytearray()
        offsets = bytearray()
        for op, records in groups:
            if records:
                body = b"".join(records)
                offsets += _record(OP_SUMMARY_OFFSET, struct.pack("<BQQ", op, summary_start + len(summary), len(body)))
                summary += body
        summary_offset_start = summary_start + len(summary)
        footer_head = struct.pack("<BQQQ", OP_FOOTER, 20, summary_start, summary_offset_start)
        crc = zlib.crc32(footer_head, zlib.crc32(offsets, zlib.crc32(summary)))
        stream.write(bytes(summary) + bytes(offsets) + footer_head + struct.pack("<I", crc) + MAGIC)
        stream.flush()


# -- reading: what every reader of records shares ------------------------------------------------


def read_string(buf: bytes, pos: int, end: int) -> tuple[str, int]:
    """The string at ``pos`` (a u32 length, then UTF-8) and where it ends; it
    must end by ``end``."""
    n = U32.unpack_from(buf, pos)[0]
    stop = pos + 4 + n
    if stop > end:
        raise DamagedRecord(f"a string of {n} bytes runs past the end of its record")
    return buf[pos + 4:stop].decode(), stop


def read_metadata_record(buf: bytes, pos: int, end: int) -> tuple[str, dict[str, str]]:
    """A Metadata record's name and string map, from its content at ``pos``."""
    name, pos = read_string(buf, pos, end)
    limit = pos + 4 + U32.unpack_from(buf, pos)[0]
    if limit > end:
        raise DamagedRecord("its map runs past the end of the record")
    pos += 4
    values: dict[str, str] = {}
    while pos < limit:
        key, pos = read_string(buf, pos, limit)
        values[key], pos = read_string(buf, pos, limit)
    return name, values


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


_DECOMPRESSORS: dict[str, Callable[[memoryview, int], bytes]] = {"zstd": _zstd, "lz4": _lz4}
READ_COMPRESSIONS = ("", *_DECOMPRESSORS)  # the chunk compressions whiztap reads


def _decompress(compression: str, data: memoryview, size: int) -> bytes:
    """A compressed chunk's records, which must be exactly ``size`` bytes, as it claims.

    Decompressed as a stream that stops one byte past the claim: memory grows
    with the real output, never past what the chunk claims (which the caller
    has checked against its limit)."""
    if compression not in _DECOMPRESSORS:
        raise DamagedRecord(f"its compression {compression!r} is none whiztap reads (zstd, lz4 or none)")
    try:
        out = _DECOMPRESSORS[compression](data, size + 1)
    except Exception as e:  # each library has its own error types for damaged data
        raise DamagedRecord(f"its {compression} data does not decompress: {e}") from None
    if len(out) > size:
        raise DamagedRecord(f"it holds more than the {size} bytes it claims")
    if len(out) < size:
        raise DamagedRecord(f"it holds {len(out)} bytes, not the {size} it claims")
    return out


def open_chunk(body: bytes, limit: int, validate_crc: bool = True) -> tuple[bytes, int, int]:
    """The records in a Chunk record (``body``: the record without its 9-byte
    head) as ``(buffer, start, end)``: they are ``buffer[start:end]``,
    decompressed within ``limit`` to exactly the size the chunk claims, and CRC
    checked.  Uncompressed records are not copied out of ``body``: a chunk
    costs its size once.  ``DamagedRecord`` (``TooBig``) says what is wrong."""
    try:
        _start, _end, size, crc = CHUNK_HEAD.unpack_from(body, 0)
        compression, pos = read_string(body, CHUNK_HEAD.size, len(body))
        n = U64.unpack_from(body, pos)[0]
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
