"""One recording on disk: an MCAP writer that never loses what it has flushed.

The file is written as ``NAME.mcap.part`` and renamed to ``NAME.mcap`` only once
``finish()`` has written the index, so a file with the final name is always a
complete MCAP and a ``.part`` is always something ``whiztap recover`` can salvage.
The open chunk is flushed at least every ``FLUSH_INTERVAL_S`` (an MCAP writer
keeps it in memory until then) and synced to the disk, so ``kill -9`` or a power
loss costs at most about the last second.  Optional rotation starts numbered
files by size or duration.

Names: a file is created only where nothing is (``O_EXCL``, which also never
follows a symbolic link), and a finished file is never renamed over an existing
one, unless ``overwrite`` (the user's ``--force``): then what is at the name is
removed first, a link as a link, never what it points at.  A later part whose
name is taken while recording (someone else's file, a link) is not a reason
to stop every client's connection: that number is skipped, with a warning, and
the part takes the next free one (its metadata's part number is its name's).

When a write fails (disk full, file too large, I/O error) the file is cut back
to the end of the last complete flush and closed with a DataEnd and Footer
record, which needs only a few dozen bytes: what was written stays a valid
(unindexed) MCAP that every reader opens, and ``whiztap recover`` re-indexes it.

Channels: the topics every file has (``format.TOPICS``) are defined when a
file begins; a plot topic (``/sensors/12``) gets its id on its first use in the
recording (``channel_id``) and is defined in each file on its first message
there, so a file has only the channels that occurred in it.  A topic's id is
the same in every file of a recording, so messages made before a rotation
still name the right channel after it.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shlex
import signal
import sys
import time
from collections.abc import Callable
from typing import NoReturn

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.recording.format import (
    LATE_TOPICS,
    MESSAGE_ENCODING,
    METADATA_NAME,
    PROFILE,
    SCHEMA_ENCODING,
    STREAM_TOPICS,
    TOPICS,
    schema_bytes,
)
from whiztap.analyzer.recording.sets import part_path
from whiztap.analyzer.recording.mcap import McapWriter, minimal_end

# What ends a recording cleanly (the file finished, exit status 0): Ctrl-C,
# SIGTERM, and SIGHUP from a closed terminal or ssh session.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
FLUSH_INTERVAL_S = 0.5  # < 1 s, so a kill -9 or a power loss loses at most about a second
DEFAULT_CHUNK_SIZE = 1 << 20
MIN_CHUNK_SIZE = 16 << 10
_STREAM_BUFFER = 1 << 20
MAX_SKIPPED = 1000  # taken part names skipped in a row before the recording gives up


# What one message adds to an open chunk besides its data (opcode, length,
# channel, sequence, two times), and to the chunk's message index.
_MESSAGE_COST = 31 + 16


class RecordingWriteError(WhiztapError):
    """Writing the recording failed; the message says what was kept, in one line."""


def _warn_on_stderr(text: str) -> None:
    """Where a ``RecordingFile`` made in-process says what it worked around."""
    print(f"whiztap: {text}", file=sys.stderr, flush=True)


def _create(path: str, overwrite: bool) -> int:
    """A new file at ``path``, opened for writing.  ``O_EXCL`` fails on any
    existing name, a symbolic link included (never followed, even dangling); with
    ``overwrite`` the name is removed first (a link, not what it points at)."""
    if overwrite:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
    return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)


def _publish(part: str, final: str, overwrite: bool) -> None:
    """Rename the finished ``part`` to ``final``.  Without ``overwrite`` an
    existing ``final`` is never replaced: a hard link cannot be made over a name
    (rename would replace it silently); file systems without hard links (FAT)
    check the name first.  A link at ``final`` is replaced, never followed."""
    if overwrite:
        os.replace(part, final)
        return
    try:
        os.link(part, final, follow_symlinks=False)
    except FileExistsError:
        raise
    except OSError:  # no hard links here
        if os.path.lexists(final):
            raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), final) from None
        os.rename(part, final)
        return
    os.unlink(part)


def _sync_folder(path: str) -> None:
    """Make a created or renamed name in ``path``'s folder survive a power loss.
    Best effort: some file systems cannot sync a folder, and the file's own
    bytes are already synced."""
    with contextlib.suppress(OSError):
        fd = os.open(os.path.dirname(path) or ".", os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


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
    that file alone needs (the connections still open).  ``overwrite``: replace
    files at the names it writes (the caller checked, or the user said --force);
    otherwise a later part's name taken while recording is skipped, and
    ``warn`` is told (one line).
    """

    def __init__(self, path: str, metadata: dict[str, str], *, split_size: int | None = None,
                 split_duration_ns: int | None = None, chunk_size: int = DEFAULT_CHUNK_SIZE,
                 compression: str = "zstd", overwrite: bool = True,
                 warn: Callable[[str], None] = _warn_on_stderr) -> None:
        self.path = path
        self.overwrite = overwrite
        self.warn = warn
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
        # topic -> channel id over the whole recording (the same in every part): the
        # topics every file has, then the plot topics in the order they occurred
        self._channels: dict[str, int] = {topic: n for n, topic in enumerate(TOPICS, start=1)}
        self._topics: dict[int, str] = {n: topic for topic, n in self._channels.items()}
        self._schema_ids: dict[str, int] = {}  # schema name -> id in the current part
        self._part_start_ns = 0
        self._part_opening: int | None = 0  # messages when the part began (None: beginning it)
        self._unchecked = 0  # bytes of messages added since the part's size was last checked
        self._summary_base = 0  # what finish() repeats of the part's opening (schemas, channels)
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

    def _finished_size(self) -> int:
        """What the current part would take if finished now, rather more than
        less: the bytes so far, the open chunks before compression, and the
        summary (schemas and channels again, one index per chunk)."""
        writer = self._writer
        if writer is None:
            return 0
        return self.size + writer.pending + writer.index_size + self._summary_base

    def open(self, t_ns: int) -> None:
        """Create the first file; an unwritable path raises RecordingWriteError."""
        self._open_part(t_ns)

    def _create_part(self) -> int:
        """Create the current part's ``.part`` file; its descriptor.  The first
        part's name was checked at start: taken now, the recording cannot
        begin.  A later part's name that is taken (the final name or its
        ``.part``, a link there too: never followed) is skipped for the next
        free number, with one warning for the names skipped."""
        skipped: list[str] = []
        while True:
            final = self.current_path
            target = final + ".part"
            try:
                if not self.overwrite and os.path.lexists(final):  # checked now, not after a part's worth of traffic
                    raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), final)
                fd = _create(target, self.overwrite)
            except FileExistsError as e:
                if not self.part or self.part == 1 or len(skipped) >= MAX_SKIPPED:
                    self._cannot_create(e, target)
                skipped.append(e.filename or target)
                self.part += 1
                continue
            except OSError as e:
                self._cannot_create(e, target)
            if skipped:
                self.warn(_skipped_text(skipped, final))
            return fd

    def _cannot_create(self, error: OSError, target: str) -> NoReturn:
        kept = f"; recording stopped, what was written before is in {self.finished[-1]}" if self.finished else ""
        raise RecordingWriteError(f"cannot write {error.filename or target}: {error.strerror}{kept}") from None

    def _open_part(self, t_ns: int) -> None:
        fd = self._create_part()
        target = self.current_path + ".part"
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
            self._schema_ids = {}
            for topic in TOPICS:
                self._define(topic)
            writer.on_new_channel = self._define_late
            self._stream.flush()  # synced with the first flush of traffic
        except OSError as e:
            os.close(fd)
            os.unlink(target)
            raise RecordingWriteError(f"cannot write {target}: {e.strerror or e}") from None
        _sync_folder(target)  # the name, so that what the flushes sync can be found after a power loss
        self._good = self._summary_base = self._stream.written
        self._last_flush = time.monotonic()

    def _define(self, topic: str) -> None:
        """Define ``topic``'s schema (once per part) and channel in the current part."""
        writer = self._writer
        assert writer is not None  # a part is open
        schema = TOPICS.get(topic) or LATE_TOPICS[topic]
        schema_id = self._schema_ids.get(schema)
        if schema_id is None:
            schema_id = self._schema_ids[schema] = writer.register_schema(
                schema, SCHEMA_ENCODING, schema_bytes(schema))
        # the stream topics' chunks first at every flush: a crash then loses
        # decoded frames before the reads they were decoded from
        writer.register_channel(topic, MESSAGE_ENCODING, schema_id,
                                group=0 if topic in STREAM_TOPICS else 1, channel_id=self._channels[topic])

    def _define_late(self, channel_id: int) -> None:
        """A message on a channel this part has not defined yet (a plot topic's
        first in this part): define it before the chunk that will hold it."""
        before = self.size
        self._define(self._topics[channel_id])
        self._summary_base += self.size - before  # finish() repeats it

    @property
    def channel_ids(self) -> dict[str, int]:
        """Topic -> channel id, the same in every part; it grows as plot topics
        occur (``channel_id``).  The recorder looks ids up here, once per message."""
        return self._channels

    def channel_id(self, topic: str) -> int:
        """The id of a plot topic (``/sensors/12``) not in ``channel_ids`` yet,
        which it joins; each part defines it on its first message there.  A
        topic the format does not know raises KeyError."""
        if topic not in LATE_TOPICS:
            raise KeyError(f"{topic} is no late topic of the recording format")
        channel_id = self._channels.get(topic)
        if channel_id is None:
            channel_id = self._channels[topic] = len(self._channels) + 1
            self._topics[channel_id] = topic
        return channel_id

    def write_late(self, topic: str, t_ns: int, data: bytes) -> None:
        """``write`` to a topic defined on its first message (``LATE_TOPICS``)."""
        channel_id = self._channels.get(topic)
        self.write_all([(channel_id if channel_id is not None else self.channel_id(topic), t_ns, data)])

    def write(self, topic: str, t_ns: int, data: bytes) -> None:
        """Add one message (its JSON bytes) at ``t_ns``."""
        self.write_all([(self._channels[topic], t_ns, data)])

    def write_all(self, messages: list[tuple[int, int, bytes]]) -> None:
        """Add (channel id, t_ns, JSON bytes) messages, ids from ``channel_ids``:
        what one TCP read produced, in one call."""
        if self.split_size is None or self.closing:
            self._add(messages)
        else:
            self._add_splitting(messages, self.split_size)

    def _add(self, messages: list[tuple[int, int, bytes]]) -> None:
        writer = self._writer
        assert writer is not None  # a part is open
        try:
            writer.add_messages(messages)
        except OSError as e:
            self._fail(e)
        self.messages += len(messages)
        self._dirty = True

    def _add_splitting(self, messages: list[tuple[int, int, bytes]], split_size: int) -> None:
        """Add messages to a part that ends at a split size.  The recorder ends
        a full part before each read and connection event (``rotate_if_due``);
        here, after each chunk's worth of messages, a full part ends even in the
        middle of one read's messages (a read of thousands of small frames), so
        a part passes --split-size by at most a chunk and a message."""
        start = 0
        for i, (_, t_ns, data) in enumerate(messages):
            if self._unchecked >= self.chunk_size:
                if i > start:
                    self._add(messages[start:i])
                    start = i
                self._unchecked = 0
                if self._finished_size() >= split_size and self._holds_traffic():
                    self._rotate(t_ns)
            self._unchecked += len(data) + _MESSAGE_COST
        if start < len(messages):
            self._add(messages[start:])

    def flush(self) -> None:
        """Write out the open chunks and sync them to the disk: what was
        recorded so far survives a crash of the process or of the machine."""
        if not self._dirty:
            return
        writer, stream = self._writer, self._stream
        assert writer is not None and stream is not None  # a part is open
        try:
            writer.flush()
            stream.flush()
            os.fdatasync(stream.fd)
        except OSError as e:
            self._fail(e)
        self._good = stream.written
        self._dirty = False
        self._last_flush = time.monotonic()

    def tick(self, t_ns: int) -> None:
        """Flush if one is due; note when a split limit is reached."""
        if self._dirty and time.monotonic() - self._last_flush >= FLUSH_INTERVAL_S:
            self.flush()
        if self.part is None:
            return
        if (self.split_size is not None and self._finished_size() >= self.split_size) or (
                self.split_duration_ns is not None and t_ns - self._part_start_ns >= self.split_duration_ns):
            # The next part begins with the next message, not now: an idle recorder
            # (or one about to stop) never leaves a part without traffic.
            self._rotate_due = True

    def rotate_if_due(self, t_ns: int) -> None:
        """Begin the next part if a split limit was reached.  The recorder calls
        this before it takes in more traffic, never in the middle of a read's
        messages, so an idle recorder (or one about to stop) leaves no part
        without traffic, and parts stay near --split-size however fast data comes."""
        if self.closing or not self._holds_traffic():
            return
        if self._rotate_due or (self.split_size is not None and self._finished_size() >= self.split_size):
            self._rotate(t_ns)

    def _rotate(self, t_ns: int) -> None:
        self._rotate_due = False
        self._finish_part(rotating=True)
        assert self.part is not None  # only a split recording rotates
        self.part += 1
        self._open_part(t_ns)
        self._part_opening = None  # what a reader of this part alone needs first is not traffic
        if self.on_new_part is not None:
            self.on_new_part(self.part)
        self._part_opening = self.messages

    def _holds_traffic(self) -> bool:
        """Whether the part holds more than its opening: only then may it end,
        so that no part is written without traffic."""
        return self._part_opening is not None and self.messages > self._part_opening

    def finish(self) -> list[str]:
        """Write the index, close, rename the .part; returns every file written."""
        if self._writer is not None:
            self._finish_part()
        return self.finished

    def _finish_part(self, rotating: bool = False) -> None:
        writer, stream = self._writer, self._stream
        assert writer is not None and stream is not None  # a part is open
        try:
            writer.finish()
            stream.flush()
            os.fdatasync(stream.fd)  # all of it on disk before the final name
        except OSError as e:
            self._fail(e)
        self._close_and_rename(rotating)

    def _close_and_rename(self, rotating: bool = False) -> None:
        """Close the part and give it its final name.  A name taken while the
        part was written stops nothing when more parts follow (``rotating``):
        the part keeps its ``.part`` name, complete, and the recording goes on."""
        assert self._stream is not None  # a part is open
        os.close(self._stream.fd)
        final = self.current_path
        self._writer = None
        self._stream = None
        try:
            _publish(final + ".part", final, self.overwrite)
        except FileExistsError:
            if not rotating:
                raise RecordingWriteError(f"cannot name the finished recording {final}: File exists; "
                                          f"it is kept, complete, as {final}.part") from None
            self.warn(f"warning: {final} was taken while this part was written, not by this recording: "
                      f"the part is kept, complete, as {final}.part; the recording goes on")
            self.finished.append(final + ".part")
            return
        except OSError as e:
            raise RecordingWriteError(f"cannot name the finished recording {final}: {e.strerror}; "
                                      f"it is kept, complete, as {final}.part") from None
        _sync_folder(final)
        self.finished.append(final)

    def _fail(self, error: OSError) -> NoReturn:
        """Keep what reached the disk readable, then report the failure."""
        what = error.strerror or str(error)
        part = self.current_path + ".part"
        stream = self._stream
        assert stream is not None  # what failed was writing the open part
        self._writer = None
        try:
            os.ftruncate(stream.fd, self._good)
            os.pwrite(stream.fd, minimal_end(), self._good)
            os.fdatasync(stream.fd)
            self._close_and_rename()
        except OSError:
            try:
                os.close(stream.fd)
            except OSError:
                pass
            raise RecordingWriteError(
                f"cannot write {part}: {what}; recording stopped; "
                f"to save what was written: whiztap recover {shlex.quote(part)}") from None
        raise RecordingWriteError(
            f"cannot write {part}: {what}; recording stopped, "
            f"what was written before is in {self.finished[-1]}") from None


def _skipped_text(skipped: list[str], final: str) -> str:
    """The warning for part names skipped because they were taken."""
    shown = [f"{name} (a link, never followed)" if os.path.islink(name) else name for name in skipped[:3]]
    names = ", ".join(shown) + (f" and {len(skipped) - 3} more" if len(skipped) > 3 else "")
    verb = "is" if len(skipped) == 1 else "are"
    return f"warning: {names} {verb} taken, not by this recording: left alone; the recording goes on in {final}"
