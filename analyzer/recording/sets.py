"""A recording as the user names it: one file, or every part of a split one.

``whiztap record --split-size/--split-duration`` writes ``NAME-0001.mcap``,
``NAME-0002.mcap``, ...; each part carries the recording's ``session_id`` and its
``part`` number in its metadata, and starts with a ``continued`` event for each
connection still open.  Every command that reads recordings takes a part set
as one recording: named by its first (or any) part, by a folder holding it, or
by a glob.  Parts are grouped by their session id, never by name alone, so two
recordings in one folder stay two.
"""

from __future__ import annotations

import contextlib
import fcntl
import glob
import os
import re
import threading
from collections.abc import Callable, Generator, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.format import METADATA_NAME, STREAM_TOPICS
from whiztap.analyzer.recording.remote import (
    PartFile,
    RemoteInputError,
    RemotePart,
    is_url,
    open_part,
    remote_parts,
)
from whiztap.analyzer.recording.scan import RecordingError, RecordingScan, read_metadata
from whiztap.analyzer.traffic import Continued, Gap, RecordingStopped, TrafficEvent

_PART_NAME = re.compile(r"^(?P<stem>.+)-(?P<n>\d{4,})(?P<ext>\.mcap)$")
_PART_NUMBER = re.compile(r"[0-9]{1,9}")
_GLOB_CHARS = frozenset("*?[")
POLL_S = 0.1  # a growing file is looked at this often; the recorder flushes every 0.5 s


class RecordingInputError(WhiztapError, ValueError):
    """A named input is not a recording: missing, or a folder with none."""


class PartError(RecordingError):
    """A file of a recording cannot be read; the message starts with its name."""

    def __init__(self, path: Path | RemotePart, why: str) -> None:
        super().__init__(f"{path}: {why}")
        self.path = path
        self.truncated = "truncated" in why


def part_path(path: str, part: int | None) -> str:
    """The final name of part ``part`` of a recording written to ``path``
    (None: an unsplit recording)."""
    if part is None:
        return path
    stem, ext = os.path.splitext(path)
    return f"{stem}-{part:04d}{ext or '.mcap'}"


@dataclass(frozen=True)
class RecordingSet:
    """The files of one recording, in part order (a URL's: ``RemotePart``)."""

    parts: tuple[Path | RemotePart, ...]
    missing: tuple[int, ...] = ()  # part numbers absent between the first and last found

    @property
    def name(self) -> Path | RemotePart:
        return self.parts[0]

    def __str__(self) -> str:
        if len(self.parts) == 1:
            return str(self.parts[0])
        return f"{self.parts[0]} (+{len(self.parts) - 1} parts)"

    def warning(self) -> str | None:
        """One line when parts are missing, for the commands to print."""
        if not self.missing:
            return None
        listed = ", ".join(str(n) for n in self.missing)
        one = len(self.missing) == 1
        return (f"{self.parts[0]}: {'part' if one else 'parts'} {listed} of this split recording "
                f"{'is' if one else 'are'} missing; connections that crossed {'it' if one else 'them'} "
                "are judged as if the missing bytes were a capture gap")


def being_written(path: Path | str) -> bool:
    """Whether a recorder is writing this file now (it holds a lock on it while
    it writes; a file left by a crash holds none)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    finally:
        os.close(fd)
    return False


def _part_number(metadata: dict[str, str]) -> int | None:
    """The part number a split recording's metadata gives this file, else None
    (unsplit, or a value that is no part number)."""
    if not (metadata.get("split_size") or metadata.get("split_duration")):
        return None
    part = metadata.get("part", "")
    return int(part) if _PART_NUMBER.fullmatch(part) else None


def _part_key(path: Path | RemotePart) -> tuple[str, int] | None:
    """(session id, part number) of a part of a split recording, else None."""
    if _PART_NAME.match(path.name) is None:
        return None
    try:
        meta = read_metadata(path)
    except (OSError, RecordingError):
        return None
    part = _part_number(meta)
    if part is None or not meta.get("session_id"):
        return None
    return meta["session_id"], part


def group(paths: Iterable[Path | RemotePart]) -> list[RecordingSet]:
    """Files as recordings: parts of one split recording together, in order."""
    sets: dict[object, dict[int, Path | RemotePart]] = {}
    for path in paths:
        key = _part_key(path)
        if key is None:
            sets.setdefault(path, {0: path})
        else:
            sets.setdefault((path.parent, key[0]), {})[key[1]] = path
    out = []
    for found in sets.values():
        numbers = sorted(found)
        missing = tuple(n for n in range(numbers[0], numbers[-1] + 1) if n not in found and not _taken(found, n))
        out.append(RecordingSet(tuple(found[n] for n in numbers), missing))
    return sorted(out, key=lambda s: str(s.name))


def _taken(found: dict[int, Path | RemotePart], n: int) -> bool:
    """Whether part ``n``'s name holds a file of something else: a number the
    recorder found taken and skipped, not a part that went missing."""
    first = found[min(found)]
    m = _PART_NAME.match(first.name)
    if not isinstance(first, Path) or m is None:
        return False
    name = first.parent / f"{m['stem']}-{n:04d}{m['ext']}"
    return os.path.lexists(name) or os.path.lexists(f"{name}.part")


def numbered_parts(output: str) -> list[str]:
    """The numbered parts of a recording written to ``output`` that are there
    (``NAME-0002.mcap``, and the ``.part`` of one being written or cut short;
    a link counts, even dangling), by name."""
    stem, ext = os.path.splitext(output)
    ext = ext or ".mcap"
    name = re.compile(re.escape(stem) + r"-\d{4,}" + re.escape(ext) + r"(\.part)?")
    pattern = glob.escape(stem) + "-[0-9][0-9][0-9][0-9]*" + glob.escape(ext) + "*"
    return sorted(p for p in glob.glob(pattern) if name.fullmatch(p))


def _siblings(path: Path) -> list[Path]:
    """The other parts a part's name suggests (same stem, any number), of
    the same recording: a file at such a name that is not one of its parts
    (a name the recorder found taken and skipped) is left out."""
    m = _PART_NAME.match(path.name)
    key = _part_key(path) if m is not None else None
    if m is None or key is None:
        return [path]
    session = key[0]
    names = [Path(p) for p in numbered_parts(str(path.parent / m["stem"]) + m["ext"]) if not p.endswith(".part")]
    return [p for p in names if p == path or (_part_key(p) or ("",))[0] == session]


def find_recordings(inputs: Iterable[str], urls: bool = False) -> list[RecordingSet]:
    """What the user named, as recordings: files, folders (every .mcap below),
    globs (expanded here too, for a quoted pattern), each split recording once;
    with ``urls``, also URLs that fsspec reads (``remote``), named the same ways.
    Raises RecordingInputError for a name that matches nothing."""
    files: list[Path | RemotePart] = []
    for name in inputs:
        path = Path(name)
        if urls and is_url(name):
            try:
                files += remote_parts(name)
            except RemoteInputError as e:
                raise RecordingInputError(str(e)) from None
        elif path.is_dir():
            found = sorted(p for p in path.rglob("*") if p.suffix == ".mcap" and p.is_file())
            if not found:
                raise RecordingInputError(f"{name}: no .mcap recordings in this folder")
            files += found
        elif not path.exists() and _GLOB_CHARS & set(name):
            matched = sorted(Path(p) for p in glob.glob(name) if p.endswith(".mcap") and os.path.isfile(p))
            if not matched:
                raise RecordingInputError(f"{name}: no recording matches this pattern")
            files += matched
        elif not path.exists():
            raise RecordingInputError(f"{name}: no such file")
        elif path.is_file() and _part_key(path) is not None:
            files += _siblings(path)
        else:
            files.append(path)
    unique = list(dict.fromkeys(files))
    return group(unique)


def find_one(inputs: Iterable[str]) -> RecordingSet:
    """The one recording a command reads (a split one's parts count as one)."""
    names = list(inputs)
    if not names:
        raise RecordingInputError("no recording given")
    found = find_recordings(names)
    if len(found) != 1:
        raise RecordingInputError(f"{' '.join(names)}: names {len(found)} recordings ({found[0]}, {found[1]}, ...); "
                                  "give one (a split recording's parts count as one)")
    return found[0]


def scan_set(recording: RecordingSet,
             open_file: Callable[[Path | RemotePart], PartFile] = open_part) -> Iterator[TrafficEvent]:
    """The traffic of every part, as one stream of typed events, each read with
    its stream offset and masked flag: a connection continued from the
    previous part is the same connection (its ``Continued`` event is dropped);
    after a missing part, a ``Gap`` for each direction of each connection that
    crossed it comes first (the next read's offset says how much is missing).
    Raises ``PartError`` (a RecordingError naming the file) for a part that
    cannot be read or is truncated."""
    seen: set[int] = set()
    expected = None
    for path in recording.parts:
        meta_part = _part_key(path)
        hole = expected is not None and meta_part is not None and meta_part[1] != expected
        expected = meta_part[1] + 1 if meta_part is not None else None
        try:
            f = open_file(path)
        except OSError as e:
            raise PartError(path, f"cannot read ({e.strerror})") from None
        with f:
            scan = RecordingScan(f, STREAM_TOPICS)
            with _part_errors(path):
                yield from _part_records(scan, seen, hole)
            if scan.truncated:
                raise PartError(path, "the file is truncated (no footer)")
            topics = sorted(set(scan.channels.values()))
            if METADATA_NAME not in scan.metadata and not set(topics) & set(STREAM_TOPICS):
                found = ", ".join(topics[:5]) + (", ..." if len(topics) > 5 else "") if topics else "none"
                raise PartError(path, f"not a whiztap recording: an MCAP file without /tcp/reads "
                                      f"(its topics: {found})")


@contextlib.contextmanager
def _part_errors(path: Path | RemotePart) -> Iterator[None]:
    """What reading a part raises, as a ``PartError`` naming it."""
    try:
        yield
    except RecordingError as e:  # the reader checks every length and every field it yields
        raise PartError(path, str(e)) from None
    except (KeyError, ValueError, TypeError, IndexError) as e:  # a nested field the reader does not check
        raise PartError(path, f"the file is damaged ({str(e) or type(e).__name__})") from None


def _part_records(scan: RecordingScan, seen: set[int], hole: bool) -> Iterator[TrafficEvent]:
    """One part's traffic, less what repeats the previous part."""
    for event in scan.traffic():
        if type(event) is Continued and event.conn in seen:
            if hole:
                for direction in Direction:
                    yield Gap(event.conn, event.t_ns, direction, detail="a part of the recording is missing")
            continue
        if event.conn:
            seen.add(event.conn)
        yield event


# -- a recording still being written ---------------------------------------------------------------


class Stopped(Exception):
    """Following was told to stop."""


class GrowingFile:
    """A recording still being written: ``read(n)`` waits until n bytes are there.

    The recorder writes whole chunks at each flush, so waiting inside a read
    lets ``RecordingScan`` parse a file that is still growing as if it were
    complete; it ends at the DataEnd record the recorder writes when it
    finishes (the open file survives the rename of ``.part`` to ``.mcap``).
    """

    def __init__(self, f: IO[bytes], stop: threading.Event, poll_s: float = POLL_S) -> None:
        self.f, self.stop, self.poll_s = f, stop, poll_s

    def read(self, n: int = -1) -> bytes:
        chunks = []
        need = n
        while need:
            data = self.f.read(need)
            if data:
                chunks.append(data)
                need -= len(data)
            elif self.stop.wait(self.poll_s):
                raise Stopped
        return b"".join(chunks)


def _next_part(path: str, metadata: dict[str, str]) -> str | None:
    """The final name of the part after ``path`` in a split recording, else None."""
    part = _part_number(metadata)
    if part is None:
        return None
    final = path.removesuffix(".part")
    stem, ext = os.path.splitext(final)
    suffix = f"-{part:04d}"
    if not stem.endswith(suffix):
        return None  # renamed by hand: its neighbours cannot be told
    return part_path(stem.removesuffix(suffix) + ext, part + 1)


def _wait_for_part(final: str, stop: threading.Event) -> str | None:
    """The next part's file once the recorder has created it (its ``.part``, or
    the finished file if it is already done); None when told to stop."""
    while True:
        for candidate in (final + ".part", final):
            if os.path.exists(candidate):
                return candidate
        if stop.wait(POLL_S):
            return None


class Follower:
    """The traffic of a recording as a running ``whiztap record`` writes it (its
    ``.part``), and of each part after it, until the recorder stops it, as one
    stream of events (like ``scan_set``'s).  Iterating raises ``Stopped`` once
    ``stop`` is set, and ``PartError`` for a part that cannot be read.

    What a screen says while it follows is here: ``path`` is the part being
    read, ``waiting_for`` the final name of the next one while the recorder
    has not begun it; ``on_part(path)`` is called as each part is opened,
    before its first event (the TUI reads its metadata then).
    """

    def __init__(self, path: str, stop: threading.Event, on_part: Callable[[str], None] | None = None) -> None:
        self.path = path
        self.waiting_for: str | None = None
        self.stop = stop
        self.on_part = on_part

    def __iter__(self) -> Iterator[TrafficEvent]:
        seen: set[int] = set()
        while True:
            stopped, metadata = yield from self._part(seen)
            following = None if stopped else _next_part(self.path, metadata)
            if following is None:
                return
            self.waiting_for = following
            found = _wait_for_part(following, self.stop)
            if found is None:
                raise Stopped
            self.path, self.waiting_for = found, None

    def _part(self, seen: set[int]) -> Generator[TrafficEvent, None, tuple[bool, dict[str, str]]]:
        """One part's events; whether the recording stopped in it, and its metadata."""
        path = Path(self.path)
        if self.on_part is not None:
            self.on_part(self.path)
        stopped = False
        try:
            f = open(path, "rb")
        except OSError as e:
            raise PartError(path, f"cannot read ({e.strerror})") from None
        with f, _part_errors(path):
            scan = RecordingScan(GrowingFile(f, self.stop), STREAM_TOPICS, growing=True)
            for event in _part_records(scan, seen, hole=False):
                if type(event) is RecordingStopped:
                    stopped = True
                yield event
        return stopped, scan.metadata.get(METADATA_NAME, {})
