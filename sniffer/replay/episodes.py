"""New episodes: the exchanges a stub fetched from the real server, appended to its recording.

``whiztap stub --upstream`` and the pytest plugin's ``new_episodes`` answer
from the recording when it can, and otherwise forward the request to the real
server (``upstream.UpstreamLink``).  What crosses each such upstream
connection is recorded here, by the recorder's own ``Recorder`` (passwords
masked as ``whiztap record`` masks them), into a recording of its own in a
temporary folder, while the stub runs.

Only when the run ends well is anything appended, and then atomically: a
complete new recording is written beside the old one (every message of the
old, in order, then every message of the new, by ``cut``'s copier under the
old recording's metadata) and renamed over it.  A run whose upstream failed,
that recorded nothing new, or that dies or is interrupted before the rename,
leaves the old recording byte for byte as it was.  Writing beside rather than
in place costs a copy of the old recording per run that adds something; it
buys a file that is always either the old recording or the new one.

Each appended connection is a real connection with its own handshake, and
says whose episodes it holds in its ``client`` field (``EPISODES_OF``): a
stub serving recorded connection N later answers from N's exchanges first,
then from those of the connections appended for N, in the order they came.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import tempfile
from pathlib import Path

from whiztap.analyzer.recording.format import TOPIC_EVENTS
from whiztap.analyzer.traffic import TrafficEvent
from whiztap.sniffer.nettext import show_address
from whiztap.sniffer.record.metadata import base_metadata
from whiztap.sniffer.record.proxy import Clock
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile, RecordingWriteError

EPISODES_OF = "whiztap stub, new episodes of connection {}"
_EPISODES_OF = re.compile(r"whiztap stub, new episodes of connection (\d{1,19})")


def episodes_of(client: str) -> int | None:
    """The recorded connection an appended connection holds new episodes of
    (None: it is a connection of its own)."""
    found = _EPISODES_OF.fullmatch(client)
    return int(found.group(1)) if found else None


class Episodes:
    """The new exchanges of one stub run, and their append to ``path``.

    ``open()`` before serving, ``tell(event)`` for each traffic event of an
    upstream connection (``new_conn()`` numbers them after every connection
    of the old recording), ``fail(why)`` when the upstream let the run down,
    ``finish()`` at the end."""

    def __init__(self, path: Path, upstream: tuple[str, int], checksum_rule: str, timeout_s: float) -> None:
        self.path = path
        self.upstream = upstream
        self.upstream_text = show_address(*upstream)
        self.checksum_rule = checksum_rule
        self.timeout_s = timeout_s  # for the upstream's connect, handshake and each answer
        self.failure: str | None = None
        self.connections = 0  # upstream connections opened so far
        self.exchanges = 0  # requests forwarded and answered
        self.clock = Clock()
        self._recorder: Recorder | None = None
        self._folder: Path | None = None
        self._old: set[int] = set()
        self._next = 1

    def open(self) -> None:
        """Note the old recording's connections and begin recording the new
        ones; OSError or RecordingWriteError (one line) when it cannot."""
        self._old = _connections(self.path)
        self._next = max(self._old, default=0) + 1
        self._folder = Path(tempfile.mkdtemp(prefix="whiztap-episodes-"))
        start = self.clock()
        metadata = base_metadata("stub", False, self.checksum_rule, start, None, upstream=self.upstream_text)
        recorder = Recorder(RecordingFile(str(self._folder / "new.mcap"), metadata), checksum_rule=self.checksum_rule)
        try:
            recorder.start(start, detail=f"new episodes from {self.upstream_text}, through whiztap stub")
        except BaseException:
            self._clean()
            raise
        self._recorder = recorder

    def new_conn(self) -> int:
        """A connection number for a new upstream connection."""
        conn = self._next
        self._next += 1
        self.connections += 1
        return conn

    def tell(self, event: TrafficEvent) -> None:
        """A traffic event of an upstream connection, into the new recording."""
        recorder = self._recorder
        if recorder is None:
            return
        try:  # never ticked: its flushes sync to the disk, a wait the forwarding path need not
            recorder.receive(event)  # take for a file a crash discards anyway (chunks go out when full)
        except RecordingWriteError as e:
            self.fail(f"cannot record the new episodes ({e})")

    def fail(self, why: str) -> None:
        """The run cannot append (the first reason is the one told)."""
        if self.failure is None:
            self.failure = why

    def finish(self) -> bool:
        """Append what was recorded, atomically; whether the recording changed.
        Nothing changes after a failure or when nothing new was recorded.
        RecordingError, RecordingWriteError or OSError when the merge fails,
        which leaves the old recording as it was."""
        from whiztap.sniffer.record.cut import copy_connections

        recorder, self._recorder = self._recorder, None
        try:
            if recorder is None:
                return False
            files = recorder.stop(self.clock(), "stub finished").files
            if self.failure is not None or self.connections == 0:
                return False
            kept = self._old | set(range(max(self._old, default=0) + 1, self._next))
            beside = self.path.with_name(f".{self.path.name}.{os.getpid()}.appending.mcap")
            try:
                copy_connections([self.path, *map(Path, files)], str(beside), kept, force=True,
                                 open_file=lambda p: open(str(p), "rb"))
                os.replace(beside, self.path)
            finally:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(beside)
            return True
        finally:
            self._clean()

    def _clean(self) -> None:
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)
            self._folder = None


def _connections(path: Path) -> set[int]:
    """Every connection number the recording uses (those without traffic too)."""
    from whiztap.analyzer.recording.scan import RecordingScan

    found: set[int] = set()
    with open(path, "rb") as f:
        for _t, _topic, buf, start, stop in RecordingScan(f, (TOPIC_EVENTS,)).records():
            conn = json.loads(bytes(buf[start:stop])).get("conn", 0)
            if isinstance(conn, int) and conn > 0:
                found.add(conn)
    return found
