"""The flight recorder (``record --ring``): a bounded window instead of the
whole session, and an incident file around each trigger.

``RingFile`` stands where the recorder's ``RecordingFile`` stands, in the
writer process, and takes the same messages: the recorder's own, already
masked (the password rule ran before them), already judged by the one
session model that saw every byte.  It keeps them in a window bounded in
time and bytes (``trigger.Ring``) instead of writing them.  When a trigger
fires (``trigger.Triggers``: a rule, a severity, a latency, a fault), it
writes ``NAME-incident-N.mcap``, an ordinary recording (a ``RecordingFile``),
with, in order:

- the recording's first message (its start event) and its metadata, which
  says which incident this is and what began it;
- each connection's *opening* that came before the window: its messages from
  its ``opened`` event up to the server's configuration answer (or
  ``OPENING_BYTES`` of them), so the handshake and the channel map that decide
  what every later frame means are in the file;
- the window, each connection opened before it begun where its streams
  can be read on (``seam.py``);
- everything that follows until ``--after`` has passed since the last
  trigger: a trigger within that time extends the same file (overlapping
  incidents merge), and then a ``recording_stopped`` event ends it.

Messages go to one place only: into the window, or into the incident being
written; so after an incident the window fills again from where it ended,
and no message is in two incident files.

Why in the writer process rather than the proxy: the messages there are
already masked, already judged (the triggers read the recorder's own
violations, frames and interventions), and the proxy's hot path stays as it
is; the writer does less than when recording everything (no compression, no
disk), so it keeps up more easily (docs/benchmarks.md, *Flight recorder*).
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable

from whiztap.analyzer.recording.format import (
    TOPIC_EVENTS,
    TOPIC_FRAMES,
    TOPIC_INTERVENTIONS,
    TOPIC_READS,
    TOPIC_VIOLATIONS,
)
from whiztap.analyzer.recording.encode import encode
from whiztap.analyzer.traffic import RecordingStopped, to_json
from whiztap.sniffer.record.seam import ServerSeek, stream_ends, trim
from whiztap.sniffer.record.trigger import Ring, Triggers, conn_of
from whiztap.sniffer.record.writer import RecordingFile, RecordingWriteError, _warn_on_stderr

# What a message kept costs beside its bytes: its tuple, the bytes object and a deque slot take about
# 105; the rest is the allocator's slack, so the resident size stays within the ring (docs/benchmarks.md).
ENTRY_COST = 160
OPENING_BYTES = 64 << 10  # of one connection's opening, at most
Message = tuple[int, int, bytes]  # channel id, log time, the message's bytes


class _Opening:
    """A connection's first messages, up to its configuration answer: what a
    reader of a window later in the connection needs to decode it."""

    __slots__ = ("messages", "size", "done")

    def __init__(self) -> None:
        self.messages: list[tuple[int, Message]] = []  # (sequence number, message)
        self.size = 0
        self.done = False


def incident_path(output: str, n: int | str) -> str:
    """``NAME-incident-N.mcap`` for ``-o NAME.mcap``."""
    stem = output[:-5] if output.endswith(".mcap") else output
    return f"{stem}-incident-{n}.mcap"


class RingFile(RecordingFile):
    """The recorder's file under ``--ring``: the window, the openings, and the
    incident being written.  ``finished`` lists the incident files written;
    ``incidents`` says what began each."""

    def __init__(self, path: str, metadata: dict[str, str], ring: Ring, triggers: list[str], after_ns: int, *,
                 overwrite: bool = True, warn: Callable[[str], None] = _warn_on_stderr) -> None:
        super().__init__(path, metadata, overwrite=overwrite, warn=warn)
        self.ring = ring
        self.after_ns = after_ns
        self.triggers = Triggers(triggers)
        self.incidents: list[dict] = []  # path, the trigger that began it, how many fired while it was written
        ids = self.channel_ids
        self._events, self._frames, self._reads = ids[TOPIC_EVENTS], ids[TOPIC_FRAMES], ids[TOPIC_READS]
        self._violations, self._interventions = ids[TOPIC_VIOLATIONS], self.channel_id(TOPIC_INTERVENTIONS)
        self._window: deque[Message] = deque()  # in write order
        self._held = 0  # the window's cost (bytes + ENTRY_COST each)
        self._seq = 0  # the next message's sequence number
        self._first = 0  # the window's first message's
        self._start: list[tuple[int, Message]] = []  # the recording's start event, with its sequence number
        self._openings: dict[int, _Opening] = {}
        self._opening_bytes = 0
        self._filling = 0  # openings not done
        self._incident: RecordingFile | None = None
        self._seek = ServerSeek({}, self._topics)  # after the window, server streams still looking for where to begin
        self._ids: dict[int, int] = {}  # channel id here -> in the incident
        self._until = 0
        self._number = 0
        self._t = 0  # the latest log time taken in
        self._busy = False  # messages came since the last tick

    # -- what the recorder calls --------------------------------------------------------------

    def open(self, t_ns: int) -> None:
        """Nothing is written until a trigger fires; but a folder that cannot
        take the incidents is said now, not at the first incident, hours on."""
        folder = os.path.dirname(os.path.abspath(self.path))
        if not os.path.isdir(folder):
            raise RecordingWriteError(f"cannot write incidents into {folder}: no such folder")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise RecordingWriteError(f"cannot write incidents into {folder}: permission denied")

    def flush(self) -> None:
        if self._incident is not None:
            self._incident.flush()

    def rotate_if_due(self, t_ns: int) -> None:
        """A ring is never split."""

    def tick(self, t_ns: int) -> None:
        """Time passes: a request unanswered too long fires ``latency>``, an
        incident's ``--after`` ends.  While messages come, time is theirs (a
        writer behind the traffic must not take answers waiting in its pipe
        for answers never sent); once none came since the last tick, the clock's."""
        if self._busy:
            self._busy = False
            t_ns = self._t
        why = self.triggers.due(t_ns)
        if why is not None:
            self._trigger(t_ns, why)
        incident = self._incident
        if incident is not None:
            if t_ns >= self._until:
                self._end(t_ns)
            else:
                incident.tick(t_ns)

    def finish(self) -> list[str]:
        """End the incident being written, if one is (Ctrl-C: a complete file)."""
        if self._incident is not None:
            self._end(self._t)
        return self.finished

    def report(self) -> dict:
        """What the closing summary says of the ring: the window kept, and each incident."""
        return {"window": self.ring.describe(), "incidents": self.incidents}

    def write_all(self, messages: list[Message]) -> None:
        """Hot loop (every message of the recording): the triggers look at
        violations, frames and interventions; the messages go to the incident
        being written, or into the window."""
        if self._incident is not None and messages[0][1] >= self._until:
            self._end(messages[0][1])
        triggers = self.triggers
        why = None
        self._t = messages[-1][1]
        self._busy = True
        for message in messages:
            ch, _, data = message
            found = None
            if ch == self._frames:
                if triggers.latency_ns is not None:
                    found = triggers.frame(data)
            elif ch == self._violations:
                found = triggers.violation(data)
            elif ch == self._interventions:
                found = triggers.intervention(data)
            elif ch == self._events:
                self._event(message)
            if self._filling:
                self._note_opening(message)
            self._seq += 1
            why = why or found  # the first trigger names the incident
        if self._incident is not None:
            self._copy(messages)
        else:
            self._window.extend(messages)
            self._held += sum(len(m[2]) for m in messages) + ENTRY_COST * len(messages)
            self._evict(messages[-1][1])
        if why is not None:
            self._trigger(messages[-1][1], why, len(messages))

    # -- the window and the openings ----------------------------------------------------------

    def _event(self, message: Message) -> None:
        """A connection event: an opening begins; the recording's start is kept."""
        data = message[2]
        if b'"event":"opened"' in data:
            self._openings[conn_of(data)] = _Opening()
            self._filling += 1
        elif b'"event":"recording_started"' in data:
            self._start = [(self._seq, message)]

    def _note_opening(self, message: Message) -> None:
        """Keep a message of a connection still in its opening; the opening is
        done at the server's configuration answer, or when it is full."""
        data = message[2]
        opening = self._openings.get(conn_of(data))
        if opening is None or opening.done:
            return
        cost = len(data) + ENTRY_COST
        if opening.size + cost > OPENING_BYTES or self._opening_bytes + cost > self.ring.max_bytes // 4:
            self._done(opening)
            return
        opening.messages.append((self._seq, message))
        opening.size += cost
        self._opening_bytes += cost
        if message[0] == self._frames and b'"dir":"s2c"' in data and b'"kind":"config"' in data:
            self._done(opening)

    def _done(self, opening: _Opening) -> None:
        if not opening.done:
            opening.done = True
            self._filling -= 1

    def _forget(self, conn: int) -> None:
        """A connection whose last message has left the window needs its opening no more."""
        opening = self._openings.pop(conn, None)
        if opening is not None:
            self._done(opening)
            self._opening_bytes -= opening.size

    def _evict(self, now: int) -> None:
        """Drop the oldest messages past the ring's time or over its bytes
        (the openings' bytes count too)."""
        window = self._window
        limit = self.ring.max_bytes - self._opening_bytes
        cutoff = now - self.ring.duration_ns if self.ring.duration_ns is not None else None
        events = self._events
        while window and (self._held > limit or (cutoff is not None and window[0][1] < cutoff)):
            ch, _, data = window.popleft()
            self._held -= len(data) + ENTRY_COST
            self._first += 1
            if ch == events and b'"event":"closed"' in data:
                self._forget(conn_of(data))

    # -- incidents ----------------------------------------------------------------------------

    def _trigger(self, t_ns: int, why: str, kept: int = 0) -> None:
        """A trigger fired at ``t_ns``: begin an incident, or extend the one
        being written.  ``kept``: the window's last messages, which made it
        fire; they and the read before them (the one they are about) are in
        the incident whatever the seams."""
        if self._incident is not None:
            self.incidents[-1]["triggers"] += 1
        else:
            self._begin(t_ns, why, kept)
        self._until = max(self._until, t_ns + self.after_ns)

    def _begin(self, t_ns: int, why: str, kept: int) -> None:
        self._evict(t_ns)
        self._number += 1
        path = incident_path(self.path, self._number)
        while not self.overwrite and (os.path.lexists(path) or os.path.lexists(path + ".part")):
            self._number += 1  # an earlier run's incident is left alone
            path = incident_path(self.path, self._number)
        metadata = {k: v for k, v in self.metadata.items() if k != "part"}
        metadata.update(incident=str(self._number), incident_trigger=why)
        incident = RecordingFile(path, metadata, overwrite=self.overwrite, warn=self.warn)
        first = self._first  # what the window no longer holds of the start and the openings goes first
        saved = (*self._start, *(entry for opening in self._openings.values() for entry in opening.messages))
        head = [m for seq, m in sorted(saved) if seq < first]
        ends = {conn: stream_ends((m for seq, m in o.messages if seq < first), self._reads)
                for conn, o in self._openings.items() if o.messages and o.messages[0][0] < first}
        incident.open(head[0][1] if head else t_ns)
        self._incident, self._ids = incident, {}
        self.incidents.append({"path": path, "trigger": why, "triggers": 1})
        self._copy(head)
        # each seam where its streams read on, never past what fired
        window, self._seek = trim(list(self._window), ends, self._topics, len(self._window) - kept - 1)
        self._window.clear()
        self._held = 0
        self._first = self._seq
        if window:
            self._copy(window)
        incident.flush()  # on disk at once: a crash now still leaves what led to it

    def _copy(self, messages: list[Message]) -> None:
        """Messages into the incident, under its channel ids."""
        incident = self._incident
        assert incident is not None  # being written
        ids = self._ids
        out = []
        for ch, t, data in self._seek.messages(messages):
            mapped = ids.get(ch)
            if mapped is None:
                topic = self._topics[ch]
                mapped = ids[ch] = incident.channel_ids.get(topic) or incident.channel_id(topic)
            out.append((mapped, t, data))
            if ch == self._events and b'"event":"closed"' in data:
                self._forget(conn_of(data))
        incident.write_all(out)

    def _end(self, t_ns: int) -> None:
        """The incident's ``--after`` has passed (or the recording stops): finish its file."""
        incident = self._incident
        assert incident is not None  # being written
        t = max(self._t, min(t_ns, self._until))
        stopped = RecordingStopped(t, "recorder", f"incident {self._number} ends")
        incident.write(TOPIC_EVENTS, t, encode(to_json(stopped)))
        self._incident = None
        self._first = self._seq
        self.messages += incident.messages
        self.finished.extend(incident.finish())
