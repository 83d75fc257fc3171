"""A small, fast MCAP writer for recordings.

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
are registered, before any chunk, so a file cut short anywhere still says
what its channels are.  And a channel can be registered into a chunk group of
its own: its messages then go into chunks that hold only that group, so a
reader that wants only those channels (the analyzer wants the TCP reads, not
the frames decoded from them) decompresses only their chunks.  Chunks of
different groups overlap in time, which MCAP allows; within a channel, file
order is still time order.  A flush closes the open chunks in group order.
Single-threaded, like the reference writer.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterable
from typing import Protocol

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_MESSAGE_INDEX, OP_CHUNK_INDEX, OP_STATISTICS, OP_METADATA, OP_METADATA_INDEX = 0x07, 0x08, 0x0B, 0x0C, 0x0D
OP_SUMMARY_OFFSET, OP_DATA_END = 0x0E, 0x0F
_MESSAGE = struct.Struct("<BQHIQQ")  # opcode, length, channel, sequence, log time, publish time
_MESSAGE_FIXED = _MESSAGE.size - 9


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
    return struct.pack("<BQ", op, len(body)) + body


def minimal_end() -> bytes:
    """DataEnd + Footer (no summary) + magic: the smallest valid end of an MCAP
    file, for closing one whose writer can no longer write its summary."""
    return _record(OP_DATA_END, struct.pack("<I", 0)) + _record(OP_FOOTER, struct.pack("<QQI", 0, 0, 0)) + MAGIC


def _compressor(compression: str):  # noqa: ANN202 - bytes -> bytes
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
        self._start = self._end = None  # message times over the file
        self.message_count = 0

    def start(self, profile: str, library: str) -> None:
        self._stream.write(MAGIC + _record(OP_HEADER, _str(profile) + _str(library)))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema_id = len(self._schemas) + 1
        record = _record(OP_SCHEMA, struct.pack("<H", schema_id) + _str(name) + _str(encoding)
                         + struct.pack("<I", len(data)) + data)
        self._schemas.append(record)
        self._stream.write(record)
        return schema_id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int, group: int = 0) -> int:
        """``group``: channels of the same group share chunks; 0 is the default group."""
        channel_id = len(self._channels) + 1
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
            chunk, index, open_chunk = slots[channel_id]
            index.append(log_time)
            index.append(len(chunk))
            chunk += pack(OP_MESSAGE, _MESSAGE_FIXED + len(data), channel_id, 0, log_time, log_time)
            chunk += data
            if len(chunk) >= limit:
                self._finish_chunk(open_chunk)

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
        chunk = _record(OP_CHUNK, struct.pack("<QQQI", start, end, len(records), zlib.crc32(records))
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
