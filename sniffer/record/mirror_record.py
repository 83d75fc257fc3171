"""The writer process's side of ``record --mirror``: the mirror's traffic recorded and paired.

The proxy hands the mirror's answers and its connection's events down the
recording pipe (``feed.REC_MIRROR``, from ``mirror.py``).  Here they become
events of the ``Recorder`` (``Recorder.extend``), so they are written in
turn with the primary's traffic: behind a client read the password rule
still holds, never before it.  The same hook shows this module the primary's
traffic as the file has it (the password masked), which, with the mirror's
answers, feeds the pairing (``analyzer/analysis/mirror.py``); each
difference goes to ``/mirror/differences`` and, as a ``mirror`` status line,
to the proxy (the TUI's status line, the closing summary).

The mirror's bytes waiting here behind an undecided password are bounded
(``MIRROR_QUEUE_CAP``): past it the mirror's further answers on that
connection are left out, and that is recorded as the mirror being dropped.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from whiztap.analyzer.analysis.diff import Difference
from whiztap.analyzer.analysis.mirror import MirrorPairing
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.encode import encode, encode_read
from whiztap.analyzer.recording.format import TOPIC_MIRROR_DIFFERENCES, TOPIC_MIRROR_EVENTS, TOPIC_MIRROR_S2C
from whiztap.analyzer.traffic import Closed, Data, Gap, HalfClosed, Opened, TrafficEvent

if TYPE_CHECKING:
    from whiztap.sniffer.record.recorder import Recorder, Work
    from whiztap.sniffer.record.writer import RecordingFile

MIRROR_QUEUE_CAP = 8 << 20  # the mirror's bytes waiting to be written (behind an undecided password)
STATUS_S = 0.2  # the proxy hears of new differences at most this often (a JSON line it parses, off its path)
FIRST = 5  # differences the closing summary shows in full
SIDES = {"A": "primary", "B": "mirror"}


@dataclass(frozen=True, slots=True)
class MirrorRead:
    """Bytes the mirror sent on one connection's mirror connection."""

    conn: int
    t_ns: int
    data: bytes


@dataclass(frozen=True, slots=True)
class MirrorEvent:
    """What became of a mirror connection (``/mirror/tcp/events``'s fields besides conn and time)."""

    conn: int
    t_ns: int
    fields: dict[str, Any]


def at_fault(d: Difference) -> str:
    """Which server's conversation breaks the spec here: "primary", "mirror", "both" or "neither".
    The client's own breaches are in both conversations alike: they tell the servers apart in nothing."""
    who = {SIDES[b.recording] for b in d.breaches if b.side == "server"}
    return "both" if len(who) == 2 else (who.pop() if who else "neither")


def difference_line(d: Difference) -> str:
    """A difference in one line, for the terminal and the TUI."""
    fault = at_fault(d)
    blame = "" if fault == "neither" else f" [{fault} {'break' if fault == 'both' else 'breaks'} the spec]"
    return f"#{d.connection} {d.exchange}: {d.what}: primary {d.a or '-'} | mirror {d.b or '-'}{blame}"


def difference_message(d: Difference, t_ns: int) -> dict[str, Any]:
    """A difference as its ``/mirror/differences`` message."""
    return {"conn": d.connection, "t_ns": t_ns, "kind": d.kind.value, "exchange": d.exchange, "what": d.what,
            "primary": d.a, "mirror": d.b, "at_fault": at_fault(d),
            "rules": [f"{SIDES[b.recording]} {b.side} {b.rule_id}".replace("  ", " ") for b in d.breaches]}


class MirrorRecorder:
    """The mirror's traffic into the recording, in turn, and paired with the primary's."""

    def __init__(self, recorder: Recorder, file: RecordingFile, pairing: MirrorPairing, server: str,
                 say: Callable[[dict], None]) -> None:
        self.file = file
        self.pairing = pairing
        self.server = server
        self.say = say
        self.receive_event: Callable[[Any], None] = recorder.receive  # with the types ``extend`` adds
        self.offsets: dict[int, int] = {}  # the mirror's stream offset per connection
        self.waiting = 0  # the mirror's bytes queued in the recorder, not yet written
        self.cut_off: set[int] = set()  # connections whose mirror answers are left out (the queue was full)
        self.events: Counter[str] = Counter()
        self.first: list[str] = []
        self.latest: list[Difference] = []  # differences not yet told to the proxy (the last FIRST of them)
        self.told_at = 0.0
        recorder.extend({MirrorRead: self._input_read, MirrorEvent: self._input_event}, self._primary)

    def receive(self, conn: int, read: bool, t_ns: int, payload: bytes) -> None:
        """One record of the pipe's ``REC_MIRROR`` kind: an answer (``read``) or an event (JSON)."""
        if not read:
            event = MirrorEvent(conn, t_ns, json.loads(payload))
            if event.fields.get("event") != "connected":  # the proxy's last word on this connection
                self.cut_off.discard(conn)
            self.receive_event(event)
        elif conn not in self.cut_off:
            if self.waiting + len(payload) > MIRROR_QUEUE_CAP:
                self.cut_off.add(conn)
                detail = f"more than {MIRROR_QUEUE_CAP >> 20} MiB of its answers waited to be recorded"
                self.receive_event(MirrorEvent(conn, t_ns, {"event": "dropped", "detail": detail}))
                return
            self.waiting += len(payload)
            self.receive_event(MirrorRead(conn, t_ns, payload))

    def finish(self, t_ns: int) -> None:
        """The recording ends: every comparison still open ends, and the totals are said."""
        self._found(self.pairing.finish(t_ns), t_ns)
        tally = self.pairing.tally
        self.say({"type": "mirror", "final": True, "server": self.server, "total": tally.result.total,
                  "by_kind": tally.result.counts(), "exchanges": tally.result.exchanges,
                  "connections": tally.connections, "not_compared": tally.not_compared,
                  "events": dict(self.events), "first": self.first})

    # -- the recorder's turn ----------------------------------------------------------------------

    def _input_read(self, e: MirrorRead) -> Work:
        def work() -> None:
            self.waiting -= len(e.data)
            offset = self.offsets.get(e.conn, 0)
            self.offsets[e.conn] = offset + len(e.data)
            self.file.write_late(TOPIC_MIRROR_S2C, e.t_ns, encode_read(e.conn, "s2c", e.t_ns, offset, e.data))
            self._found(self.pairing.mirror(e.conn, e.data, e.t_ns), e.t_ns)
        return work

    def _input_event(self, e: MirrorEvent) -> Work:
        def work() -> None:
            event = str(e.fields.get("event"))
            self.events[event] += 1
            self.file.write_late(TOPIC_MIRROR_EVENTS, e.t_ns, encode({"conn": e.conn, "t_ns": e.t_ns, **e.fields}))
            if event == "connected":
                self.pairing.mirror_started(e.conn)
            else:
                self.offsets.pop(e.conn, None)
                sent = e.fields.get("c2s_bytes")  # what the proxy got to send it (the writer's own drop: none)
                self._found(self.pairing.mirror_ended(e.conn, e.t_ns, sent if isinstance(sent, int) else None),
                            e.t_ns)
        return work

    def _primary(self, e: TrafficEvent) -> None:
        """The primary's traffic as the file has it (``Recorder.extend``'s watcher)."""
        if isinstance(e, Data):
            feed = self.pairing.client if e.direction is Direction.C2S else self.pairing.primary
            self._found(feed(e.conn, e.data, e.t_ns), e.t_ns)
        elif isinstance(e, Opened):
            self.pairing.opened(e.conn)
        elif isinstance(e, HalfClosed) and e.direction is Direction.C2S:
            self._found(self.pairing.client_ended(e.conn, e.t_ns), e.t_ns)
        elif isinstance(e, Closed):
            self._found(self.pairing.primary_closed(e.conn, e.t_ns), e.t_ns)
        elif isinstance(e, Gap):  # the primary's streams are cut: its comparison ends here
            self._found(self.pairing.mirror_ended(e.conn, e.t_ns), e.t_ns)

    def _found(self, differences: list[Difference], t_ns: int) -> None:
        if not differences:
            return
        channel = self.file.channel_ids.get(TOPIC_MIRROR_DIFFERENCES)
        if channel is None:
            channel = self.file.channel_id(TOPIC_MIRROR_DIFFERENCES)  # its first message: a late topic
        self.file.write_all([(channel, t_ns, encode(difference_message(d, t_ns))) for d in differences])
        room = FIRST - len(self.first)
        if room > 0:
            self.first += [difference_line(d) for d in differences[:room]]
        self.latest = (self.latest + differences)[-FIRST:]  # in words when told: most never are
        self.tick(time.monotonic())

    def tick(self, now: float) -> None:
        """Tell the proxy what the pairing found since it last heard, at most every ``STATUS_S``
        (called often by the writer's loop, and on each new difference)."""
        if self.latest and now - self.told_at >= STATUS_S:
            self.told_at = now
            result = self.pairing.tally.result
            self.say({"type": "mirror", "total": result.total, "by_kind": result.counts(),
                      "latest": [difference_line(d) for d in self.latest]})
            self.latest = []

def mirror_recorder(recorder: Recorder, file: RecordingFile, config: dict[str, Any],
                    say: Callable[[dict], None]) -> MirrorRecorder | None:
    """The writer's ``MirrorRecorder`` when the recording has a mirror (its configuration's
    ``mirror``: the server's address), judging with the recording's own session settings."""
    if not config.get("mirror"):
        return None
    from functools import partial

    from whiztap.analyzer.protocol.session import Limits

    limits = Limits.from_dict(config.get("limits", {}))
    pairing = MirrorPairing(partial(limits.session, config["checksum_rule"]), limits.answer_timeout_ns)
    return MirrorRecorder(recorder, file, pairing, config["mirror"], say)
