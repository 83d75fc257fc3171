"""Salvage a recording whose writer died, or whose file was damaged.

A crashed recorder leaves every chunk it flushed (it flushes at least once a
second), followed perhaps by half a chunk and no index: ``NAME.mcap.part``
becomes ``NAME.mcap``.  A damaged file (a bad sector, a bit flip, a copy that
went wrong) may have a bad chunk anywhere.  Recovery reads the file once, from
the start, one record at a time (never more than the readers' limit of it in
memory, whatever the file's size), and copies what checks out (schemas,
channels, messages, metadata, attachments) into a new file through mcap's
Writer, which adds the index:

- a chunk whose contents do not check out (CRC, decompression, the size it
  claims, record lengths) is skipped whole, and reading goes on after it;
- where a record's header makes no sense (junk, a length past the end), it
  looks ahead for the next chunk whose header adds up (or the end of the data
  section) and goes on from there;
- a record that runs past the end of the file, with nothing readable after it,
  is where the writer stopped.

The result says what was skipped and where.  The original is never modified;
the output is written under a private temporary name in its folder and renamed
into place only when complete.
"""

from __future__ import annotations

import io
import os
import struct
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import IO, NamedTuple

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.records import Attachment, Channel, Metadata, Schema
from mcap.writer import Writer

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.text import human_bytes, plural
from whiztap.analyzer.recording.format import PROFILE
from whiztap.analyzer.recording.mcap import (
    CHUNK_HEAD,
    KNOWN_OPS,
    MAGIC,
    MESSAGE_FIELDS,
    OP_ATTACHMENT,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_MESSAGE,
    OP_METADATA,
    OP_SCHEMA,
    READ_COMPRESSIONS,
    RECORD_HEAD,
    U32,
    U64,
    DamagedRecord,
    TooBig,
    open_chunk,
)
from whiztap.analyzer.recording.output_rule import OutputRefused, check_output
from whiztap.analyzer.recording.scan import MAX_CHUNK_ENV, RecordingError, max_chunk_setting

_COPIED = frozenset((OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_ATTACHMENT, OP_METADATA))
_COMPRESSIONS = frozenset(c.encode() for c in READ_COMPRESSIONS)
_CHUNK_FIXED = CHUNK_HEAD.size + 4  # a chunk's fixed fields and its compression's length
_DATA_END = RECORD_HEAD.pack(OP_DATA_END, 4)
_CHUNK_OP = bytes((OP_CHUNK,))
_WINDOW = 1 << 20  # bytes looked through at a time when looking for the next chunk
_PROBE = 9 + _CHUNK_FIXED + 4 + 8  # enough of a record to tell whether it is a chunk


class RecoverError(WhiztapError):
    """Recovery could not run; one line for the user."""


@dataclass(frozen=True)
class Skipped:
    """A stretch of the input that could not be read: a damaged chunk, or junk."""

    offset: int
    length: int
    too_big: bool = False  # a chunk claiming more than the limit: damaged, or a file that needs a higher limit


@dataclass(frozen=True)
class RecoverResult:
    output: str
    messages: int
    skipped: tuple[Skipped, ...] = ()
    cut_at: int | None = None  # where the file ends without its data section's end (the usual crash)
    cut_bytes: int = 0  # bytes after cut_at that could not be read (a record cut short, or junk)
    orphans: int = 0  # messages dropped: their channel was defined in a skipped chunk

    def summary(self) -> str:
        """What recovery did, in one line for the user."""
        text = f"recovered {plural(self.messages, 'message')} into {self.output}"
        if self.skipped:
            where = ", ".join(str(s.offset) for s in self.skipped[:5]) + (", ..." if len(self.skipped) > 5 else "")
            lost = human_bytes(sum(s.length for s in self.skipped))
            n = len(self.skipped)
            text += f"; skipped {n} damaged {'region' if n == 1 else 'regions'} (at byte {where}: {lost})"
            too_big = sum(s.too_big for s in self.skipped)
            if too_big:
                text += f", {too_big} of them larger than {MAX_CHUNK_ENV} allows (raise it for a file you trust)"
        if self.orphans:
            text += f"; dropped {plural(self.orphans, 'message')} whose channel was in a damaged region"
        if self.cut_at is not None:
            text += f"; the file ended mid-write at byte {self.cut_at}"
            if self.cut_bytes:
                text += f" (the {human_bytes(self.cut_bytes)} after it could not be read)"
        return text


def default_output(path: str) -> str:
    if path.endswith(".part"):
        return path[: -len(".part")]
    stem, _ = os.path.splitext(path)
    return stem + ".recovered.mcap"


def recover(path: str, output: str | None = None, *, force: bool = False,
            max_chunk: int | None = None) -> RecoverResult:
    """Copy every readable record of ``path`` into a new, indexed MCAP file,
    taking at most ``max_chunk`` bytes of it at once (None: the user's
    setting, ``scan.max_chunk_setting()``)."""
    if not os.path.isfile(path):
        raise RecoverError(f"{path}: no such file" if not os.path.exists(path) else f"{path}: not a file")
    output = output or default_output(path)
    try:
        check_output(output, [path], force=force)
    except OutputRefused as e:
        raise RecoverError(str(e)) from None
    try:
        limit = max_chunk_setting() if max_chunk is None else max_chunk
        source = open(path, "rb")  # closed below
    except RecordingError as e:
        raise RecoverError(str(e)) from None
    except OSError as e:
        raise RecoverError(f"cannot read {path}: {e.strerror}") from None
    with source:
        if source.read(len(MAGIC)) != MAGIC:
            raise RecoverError(f"{path} is not an MCAP file (bad magic)")
        return _write(output, lambda sink: _copy(_Salvage(source, limit), sink, path))


def _write(output: str,
           copy: Callable[[IO[bytes]], tuple[int, tuple[Skipped, ...], int | None, int, int]]) -> RecoverResult:
    """Run ``copy`` into a private temporary file beside ``output``, then rename
    it into place; never leaves the temporary file behind."""
    folder = os.path.dirname(os.path.abspath(output))
    try:
        fd, partial = tempfile.mkstemp(prefix=f".{os.path.basename(output)}.", suffix=".recovering", dir=folder)
    except OSError as e:
        raise RecoverError(f"cannot write {output}: {e.strerror}") from None
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o644 & ~umask)  # as the recorder creates recordings, not mkstemp's 0600
        with os.fdopen(fd, "wb") as sink:
            result = copy(sink)
        os.replace(partial, output)
    except OSError as e:
        _remove(partial)
        raise RecoverError(f"cannot write {output}: {e.strerror}") from None
    except BaseException:
        _remove(partial)
        raise
    return RecoverResult(output, *result)


def _remove(path: str) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


class _Salvage:
    """The records of an MCAP file that check out, read once from the start
    (after the magic), with what had to be skipped and where reading stopped."""

    def __init__(self, f: IO[bytes], limit: int) -> None:
        self.f = f
        self.limit = limit
        self.size = os.fstat(f.fileno()).st_size
        self.skipped: list[Skipped] = []
        self.cut_at: int | None = None
        self.cut_bytes = 0

    def records(self) -> Iterator[Item]:
        """Each record to copy, those inside good chunks included, in file order."""
        pos = len(MAGIC)
        while True:
            head = self._read(pos, 9)
            if len(head) < 9:
                self.cut_at, self.cut_bytes = pos, len(head)
                return
            op, length = RECORD_HEAD.unpack(head)
            if op in (OP_DATA_END, OP_FOOTER):
                return
            if not self._plausible(pos, op, length):
                found = self._next_chunk(pos + 1)
                if found is None:  # nothing readable follows: this is where the writer stopped
                    self.cut_at, self.cut_bytes = pos, self.size - pos
                    return
                self.skipped.append(Skipped(pos, found - pos))
                pos = found
                continue
            if op == OP_CHUNK or op in _COPIED:
                try:
                    if length > self.limit:
                        raise TooBig(length, self.limit)
                    body = self._read(pos + 9, length)
                    items = _chunk_items(*open_chunk(body, self.limit)) if op == OP_CHUNK else [_item(op, body)]
                except (DamagedRecord, struct.error) as e:
                    self.skipped.append(Skipped(pos, 9 + length, isinstance(e, TooBig)))
                else:
                    yield from items
            pos += 9 + length

    def _read(self, pos: int, n: int) -> bytes:
        """The input's bytes; a failing read (a bad sector) names the input, not the output."""
        try:
            self.f.seek(pos)
            return self.f.read(n)
        except OSError as e:
            raise RecoverError(f"cannot read {self.f.name} at byte {pos}: {e.strerror or e}") from None

    def _plausible(self, pos: int, op: int, length: int) -> bool:
        """Whether a record header at ``pos`` can be taken at its word: a known
        opcode, a length within the file, and for a chunk, a header whose own
        lengths add up."""
        if not (op in KNOWN_OPS or op >= 0x80) or pos + 9 + length > self.size:
            return False
        return op != OP_CHUNK or _chunk_header_adds_up(self._read(pos, _PROBE), length)

    def _next_chunk(self, start: int) -> int | None:
        """The offset of the next chunk whose header adds up, or of the data
        section's end, at or after ``start``; None when there is neither.
        Looks through the file a window at a time: memory stays small."""
        pos = start
        while pos < self.size:
            window = self._read(pos, _WINDOW + _PROBE)  # overlapping: a header across the edge is seen whole
            best = window.find(_DATA_END, 0, _WINDOW + len(_DATA_END))
            i = window.find(_CHUNK_OP, 0, _WINDOW)
            while i >= 0 and (best < 0 or i < best):
                op, length = RECORD_HEAD.unpack_from(window, i) if i + 9 <= len(window) else (0, 0)
                if op == OP_CHUNK and pos + i + 9 + length <= self.size and \
                        _chunk_header_adds_up(window[i:i + _PROBE], length):
                    return pos + i
                i = window.find(_CHUNK_OP, i + 1, _WINDOW)
            if best >= 0:
                return pos + best
            pos += _WINDOW
        return None


def _chunk_header_adds_up(probe: bytes, length: int) -> bool:
    """Whether the start of a record (``probe``) looks like a Chunk of ``length``
    bytes: a compression whiztap reads, and lengths that sum to the record's."""
    if len(probe) < 9 + _CHUNK_FIXED:
        return False
    start, end, _size, _crc = CHUNK_HEAD.unpack_from(probe, 9)
    n = U32.unpack_from(probe, 9 + CHUNK_HEAD.size)[0]
    if n > 4 or len(probe) < 9 + _CHUNK_FIXED + n + 8 or start > end:
        return False
    at = 9 + _CHUNK_FIXED
    if probe[at:at + n] not in _COMPRESSIONS:
        return False
    data = U64.unpack_from(probe, at + n)[0]
    return _CHUNK_FIXED + n + 8 + data == length


class _Message(NamedTuple):
    channel: int
    sequence: int
    log_time: int
    publish_time: int
    data: bytes


Item = _Message | Schema | Channel | Metadata | Attachment


def _message(buffer: bytes, at: int, length: int) -> _Message:
    """The message record whose body is ``buffer[at:at + length]``."""
    channel, sequence, log_time, publish_time = MESSAGE_FIELDS.unpack_from(buffer, at)
    return _Message(channel, sequence, log_time, publish_time, buffer[at + MESSAGE_FIELDS.size:at + length])


def _item(op: int, body: bytes) -> Item:
    """A record to copy, parsed (by mcap's own code but for messages, the bulk);
    DamagedRecord or McapError when its fields do not parse."""
    if op == OP_MESSAGE:
        if len(body) < MESSAGE_FIELDS.size:
            raise DamagedRecord("a message too short for its fields")
        return _message(body, 0, len(body))
    kinds: dict[int, type[Schema | Channel | Metadata | Attachment]] = {
        OP_SCHEMA: Schema, OP_CHANNEL: Channel, OP_METADATA: Metadata, OP_ATTACHMENT: Attachment}
    kind = kinds[op]
    try:
        return kind.read(ReadDataStream(io.BytesIO(body)))
    except (McapError, ValueError, struct.error) as e:  # text that is not UTF-8, a field cut short
        raise DamagedRecord(str(e) or type(e).__name__) from None


def _chunk_items(records: bytes, first: int, end: int) -> Iterator[Item]:
    """The records to copy from a chunk's contents, ``records[first:end]``.
    Every record is checked (and all but messages parsed) before any is given,
    so a chunk is copied whole or not at all, without holding its messages twice."""
    checked: dict[int, Item] = {}
    pos = first
    while pos < end:
        op, length = RECORD_HEAD.unpack_from(records, pos)
        if op == 0 or pos + 9 + length > end:
            raise DamagedRecord(f"a record at {pos - first} in it does not fit")
        if op == OP_MESSAGE:
            if length < MESSAGE_FIELDS.size:
                raise DamagedRecord(f"the message at {pos - first} in it is too short")
        elif op in _COPIED:
            checked[pos] = _item(op, records[pos + 9:pos + 9 + length])
        pos += 9 + length
    return _chunk_walk(records, first, end, checked)


def _chunk_walk(records: bytes, first: int, end: int, checked: dict[int, Item]) -> Iterator[Item]:
    pos = first
    while pos < end:
        op, length = RECORD_HEAD.unpack_from(records, pos)
        if op == OP_MESSAGE:
            yield _message(records, pos + 9, length)
        elif pos in checked:
            yield checked[pos]
        pos += 9 + length


def _copy(salvage: _Salvage, sink: IO[bytes], path: str) -> tuple[int, tuple[Skipped, ...], int | None, int, int]:
    """Write what ``salvage`` reads into an MCAP file on ``sink``; the counts
    for ``RecoverResult``."""
    writer = Writer(sink)
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    messages = orphans = 0
    started = False
    for record in salvage.records():
        if not started:
            writer.start(PROFILE, "whiztap recover")
            started = True
        if type(record) is _Message:
            channel = channels.get(record.channel)
            if channel is None:
                orphans += 1
                continue
            writer.add_message(channel, record.log_time, record.data, record.publish_time, record.sequence)
            messages += 1
        elif isinstance(record, Schema) and record.id not in schemas:
            schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
        elif isinstance(record, Channel) and record.id not in channels:
            channels[record.id] = writer.register_channel(
                record.topic, record.message_encoding, schemas.get(record.schema_id, 0), record.metadata)
        elif isinstance(record, Metadata):
            writer.add_metadata(record.name, record.metadata)
        elif isinstance(record, Attachment):
            writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type, record.data)
    if not started:
        raise RecoverError(f"{path} holds nothing to recover: no schema, channel, message or metadata could be read")
    writer.finish()
    return messages, tuple(salvage.skipped), salvage.cut_at, salvage.cut_bytes, orphans

