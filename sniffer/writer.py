"""One recording on disk: an MCAP writer that never loses what it has flushed.

The file is written as ``NAME.mcap.part`` and renamed to ``NAME.mcap`` only once
``finish()`` has written the index, so a file with the final name is always a
complete MCAP and a ``.part`` is always something ``whiztap recover`` can salvage.
The open chunk is flushed to disk at least every ``FLUSH_INTERVAL_S`` (an MCAP
writer keeps it in memory until then), so ``kill -9`` loses at most about a
second.  Optional rotation starts numbered files by size or duration.

When a write fails (disk full, file too large, I/O error) the file is cut back
to the end of the last complete flush and closed with a DataEnd and Footer
record, which needs only a few dozen bytes: what was written stays a valid
(unindexed) MCAP that every reader opens, and ``whiztap recover`` re-indexes it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import time
from collections.abc import Callable

from analyzer.recording import (
    MESSAGE_ENCODING,
    METADATA_NAME,
    PROFILE,
    SCHEMA_ENCODING,
    STREAM_TOPICS,
    TOPICS,
    schema_bytes,
)
from analyzer.recording_set import part_path
from sniffer.mcapwriter import McapWriter, minimal_end

FLUSH_INTERVAL_S = 0.5  # < 1 s, so a kill -9 loses at most about a second
DEFAULT_CHUNK_SIZE = 1 << 20
MIN_CHUNK_SIZE = 16 << 10
_STREAM_BUFFER = 1 << 20


class RecordingWriteError(Exception):
    """Writing the recording failed; the message says what was kept, in one line."""


class _FileStream:
    """The file object the MCAP writer writes to: a plain buffer over a file
    descriptor, so that after a failed write we know exactly how many bytes
    reached the file and no buffered object retries the write behind our back."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.written = 0
        self._buf = bytearray()

    def write(self, data: bytes) -> int:
        self._buf += data
        if len(self._buf) >= _STREAM_BUFFER:
            self.flush()
        return len(data)

    def tell(self) -> int:
        return self.written + len(self._buf)

    def flush(self) -> None:
        view = memoryview(self._buf)
        done = 0
        try:
            while done < len(view):
                done += os.write(self.fd, view[done:])
        finally:
            view.release()
            del self._buf[:done]
            self.written += done


class RecordingFile:
    """The MCAP file(s) of one recording, written from a single thread.

    ``write()`` adds a message; ``tick()`` flushes when due; ``rotate_if_due()``
    begins the next part once a split limit is reached; ``finish()`` closes the last file.  ``on_new_part``
    is called after each rotation so the recorder can write what a reader of
    that file alone needs (the connections still open).
    """

    def __init__(self, path: str, metadata: dict[str, str], *, split_size: int | None = None,
                 split_duration_ns: int | None = None, chunk_size: int = DEFAULT_CHUNK_SIZE,
                 compression: str = "zstd") -> None:
        self.path = path
        self.metadata = metadata
        self.split_size = split_size
        self.split_duration_ns = split_duration_ns
        split = split_size is not None or split_duration_ns is not None
        if split_size is not None:
            chunk_size = max(MIN_CHUNK_SIZE, min(chunk_size, split_size // 8))
        self.chunk_size = chunk_size
        self.compression = compression
        self.on_new_part: Callable[[int], None] | None = None
        self.part: int | None = 1 if split else None
        self.finished: list[str] = []  # final names of completed files
        self.messages = 0  # over all parts
        self._writer: McapWriter | None = None
        self._stream: _FileStream | None = None
        self._channels: dict[str, int] = {}
        self._part_start_ns = 0
        self._last_flush = 0.0
        self._good = 0  # file offset just after the last complete flush
        self._dirty = False
        self._rotate_due = False  # a split limit was reached: the next message opens a new part
        self.closing = False  # the recording is stopping: what is left goes into this part

    @property
    def current_path(self) -> str:
        return part_path(self.path, self.part)

    @property
    def size(self) -> int:
        """Bytes of the current file so far (written or buffered)."""
        return self._stream.tell() if self._stream is not None else 0

    def open(self, t_ns: int) -> None:
        """Create the first file; an unwritable path raises RecordingWriteError."""
        self._open_part(t_ns)

    def _open_part(self, t_ns: int) -> None:
        target = self.current_path + ".part"
        try:
            fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        except OSError as e:
            raise RecordingWriteError(f"cannot write {target}: {e.strerror}") from None
        with contextlib.suppress(OSError):  # tells readers the file is being written (being_written)
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        self._stream = _FileStream(fd)
        self._good = 0
        writer = McapWriter(self._stream, chunk_size=self.chunk_size, compression=self.compression)
        self._writer = writer
        self._part_start_ns = t_ns
        metadata = dict(self.metadata, part=str(self.part or 1))
        try:
            writer.start(PROFILE, f"whiztap {self.metadata.get('whiztap_version', '')}".strip())
            writer.add_metadata(METADATA_NAME, metadata)
            schema_ids: dict[str, int] = {}
            for topic, schema in TOPICS.items():
                if schema not in schema_ids:
                    schema_ids[schema] = writer.register_schema(schema, SCHEMA_ENCODING, schema_bytes(schema))
                # the stream topics' chunks first at every flush: a crash then loses
                # decoded frames before the reads they were decoded from
                self._channels[topic] = writer.register_channel(topic, MESSAGE_ENCODING, schema_ids[schema],
                                                                group=0 if topic in STREAM_TOPICS else 1)
            self._stream.flush()
        except OSError as e:
            os.close(fd)
            os.unlink(target)
            raise RecordingWriteError(f"cannot write {target}: {e.strerror or e}") from None
        self._good = self._stream.written
        self._last_flush = time.monotonic()

    @property
    def channel_ids(self) -> dict[str, int]:
        """Topic -> channel id in the file being written (the same in every part)."""
        return self._channels

    def write(self, topic: str, t_ns: int, data: bytes) -> None:
        """Add one message (its JSON bytes) at ``t_ns``."""
        self.write_all([(self._channels[topic], t_ns, data)])

    def write_all(self, messages: list[tuple[int, int, bytes]]) -> None:
        """Add (channel id, t_ns, JSON bytes) messages, ids from ``channel_ids``:
        what one TCP read produced, in one call."""
        try:
            self._writer.add_messages(messages)  # type: ignore[union-attr]
        except OSError as e:
            self._fail(e)
        self.messages += len(messages)
        self._dirty = True

    def flush(self) -> None:
        if not self._dirty:
            return
        try:
            self._writer.flush()  # type: ignore[union-attr]
            self._stream.flush()  # type: ignore[union-attr]
        except OSError as e:
            self._fail(e)
        self._good = self._stream.written  # type: ignore[union-attr]
        self._dirty = False
        self._last_flush = time.monotonic()

    def tick(self, t_ns: int) -> None:
        """Flush if one is due; note when a split limit is reached."""
        if self._dirty and time.monotonic() - self._last_flush >= FLUSH_INTERVAL_S:
            self.flush()
        if self.part is None:
            return
        if (self.split_size is not None and self.size >= self.split_size) or (
                self.split_duration_ns is not None and t_ns - self._part_start_ns >= self.split_duration_ns):
            # The next part begins with the next message, not now: an idle recorder
            # (or one about to stop) never leaves a part without traffic.
            self._rotate_due = True

    def rotate_if_due(self, t_ns: int) -> None:
        """Begin the next part if a split limit was reached.  The recorder calls
        this before it takes in more traffic, never in the middle of a read's
        messages, so an idle recorder (or one about to stop) leaves no part
        without traffic, and parts stay near --split-size however fast data comes."""
        if self.closing:
            return
        if self._rotate_due or (self.split_size is not None and self.size >= self.split_size):
            self._rotate(t_ns)

    def _rotate(self, t_ns: int) -> None:
        self._rotate_due = False
        self._finish_part()
        self.part += 1  # type: ignore[operator]
        self._open_part(t_ns)
        if self.on_new_part is not None:
            self.on_new_part(self.part)  # type: ignore[arg-type]

    def finish(self) -> list[str]:
        """Write the index, close, rename the .part; returns every file written."""
        if self._writer is not None:
            self._finish_part()
        return self.finished

    def _finish_part(self) -> None:
        try:
            self._writer.finish()  # type: ignore[union-attr]
            self._stream.flush()  # type: ignore[union-attr]
        except OSError as e:
            self._fail(e)
        self._close_and_rename()

    def _close_and_rename(self) -> None:
        os.close(self._stream.fd)  # type: ignore[union-attr]
        os.replace(self.current_path + ".part", self.current_path)
        self.finished.append(self.current_path)
        self._writer = None
        self._stream = None
        self._channels = {}

    def _fail(self, error: OSError) -> None:
        """Keep what reached the disk readable, then report the failure."""
        what = error.strerror or str(error)
        part = self.current_path + ".part"
        stream = self._stream
        self._writer = None
        try:
            os.ftruncate(stream.fd, self._good)  # type: ignore[union-attr]
            os.pwrite(stream.fd, minimal_end(), self._good)  # type: ignore[union-attr]
            self._close_and_rename()
        except OSError:
            try:
                os.close(stream.fd)  # type: ignore[union-attr]
            except OSError:
                pass
            raise RecordingWriteError(
                f"cannot write {part}: {what}; recording stopped, "
                f"run 'whiztap recover {part}' to save what was written") from None
        raise RecordingWriteError(
            f"cannot write {part}: {what}; recording stopped, "
            f"what was written before is in {self.finished[-1]}") from None
