"""Where an incident's window joins a connection's opening (``ring.py``).

The window begins wherever the ring's oldest message is: for a connection
opened before it, maybe in the middle of a frame, and with answers on their
way to requests that fell out of it.  A reader of the incident frames the
opening's bytes and then the window's as one stream, so at that seam it
would see garbage and answers to nothing (a pipelined client: a thousand
``PW-PAIR-UNSOLICITED`` that the live recorder, which saw every byte, never
found).  ``trim`` starts each such connection's window where its streams
can be read on: the client's at its first read that begins a frame, the
server's at its first read that begins a frame that answers nothing or a
request from then on.  What is left out was whole reads, never part of one:
the bytes kept are as they were, and their offsets show the jump.  The
recorder's own messages about what is left out (its frames, violations,
plots) go with it; connection events always stay.

The positions come from the recorder's own messages in the window: each
read's stream offset, each frame's offset, index and the request it answers.
"""

from __future__ import annotations

import re
from collections.abc import Iterable

from whiztap.analyzer.recording.format import TOPIC_EVENTS, TOPIC_FRAMES, TOPIC_LOG, TOPIC_READS
from whiztap.sniffer.record.trigger import conn_of

Message = tuple[int, int, bytes]  # channel id, log time, the message's bytes
_READ = re.compile(rb'\{"conn":\d+,"dir":"(c2s|s2c)","t_ns":\d+,"offset":(\d+),"size":(\d+)')
_FRAME = re.compile(rb'\{"conn":\d+,"dir":"(c2s|s2c)","index":(\d+),"t_start_ns":\d+,"t_end_ns":\d+,'
                    rb'"offset":(\d+),"answers":(null|\d+)')
_DIR = re.compile(rb'"dir":"(c2s|s2c)"')
_LOG_DIR = re.compile(rb'"file":"conn-\d+ (c2s|s2c)"')


def stream_ends(opening: Iterable[Message], reads: int) -> dict[bytes, int]:
    """Where each direction's stream stands after an opening's reads."""
    ends = {b"c2s": 0, b"s2c": 0}
    for ch, _, data in opening:
        m = _READ.match(data) if ch == reads else None
        if m is not None:
            ends[m.group(1)] = max(ends[m.group(1)], int(m.group(2)) + int(m.group(3)))
    return ends


def trim(window: list[Message], ends: dict[int, dict[bytes, int]], topics: dict[int, str], keep: int
         ) -> tuple[list[Message], ServerSeek]:
    """The window, each connection of ``ends`` (its streams' ends after its
    opening, which the incident holds) begun where its streams can be read on,
    but never later than position ``keep`` (what made the trigger fire is
    kept, seam or not); and what goes on looking, after the window, for the
    server streams that found no such place in it."""
    ids = {topic: ch for ch, topic in topics.items()}
    reads, frames = ids[TOPIC_READS], ids[TOPIC_FRAMES]
    first_read: dict[tuple[int, bytes], tuple[int, int]] = {}  # (conn, dir) -> (position, offset)
    read_at: dict[tuple[int, bytes], list[tuple[int, int]]] = {}  # (conn, dir) -> [(position, offset)]
    starts: dict[tuple[int, bytes], dict[int, tuple[int, int | None]]] = {}  # offset -> (index, answers)
    for pos, (ch, _, data) in enumerate(window):
        if ch != reads and ch != frames:
            continue
        conn = conn_of(data)
        if conn not in ends:
            continue
        if ch == reads:
            m = _READ.match(data)
            if m is not None:
                key = (conn, m.group(1))
                first_read.setdefault(key, (pos, int(m.group(2))))
                read_at.setdefault(key, []).append((pos, int(m.group(2))))
            continue
        f = _FRAME.match(data)
        if f is not None:
            answers = None if f.group(4) == b"null" else int(f.group(4))
            starts.setdefault((conn, f.group(1)), {})[int(f.group(3))] = (int(f.group(2)), answers)
    cuts = {}
    seeking: dict[int, int] = {}
    for conn, end in ends.items():
        if all(first_read.get((conn, d), (0, end[d]))[1] == end[d] for d in (b"c2s", b"s2c")):
            continue  # the window goes on from the opening: no seam
        found = _cut(read_at.get((conn, b"c2s"), []), read_at.get((conn, b"s2c"), []),
                     starts.get((conn, b"c2s"), {}), starts.get((conn, b"s2c"), {}))
        if found is not None:
            where, first_index = found
            if max(where.values()) > keep:  # it would leave out what fired: begin there, as it is
                where, first_index = {d: min(p, keep) for d, p in where.items()}, None
            cuts[conn] = where
            if first_index is not None:
                seeking[conn] = first_index
    seek = ServerSeek(seeking, topics)
    if not cuts:
        return window, seek
    events = ids[TOPIC_EVENTS]
    return [m for pos, m in enumerate(window)
            if m[0] == events or (cut := cuts.get(conn_of(m[2]))) is None
            or pos >= cut[_direction(m, topics)]], seek


def _cut(c2s: list[tuple[int, int]], s2c: list[tuple[int, int]], c2s_starts: dict[int, tuple[int, int | None]],
         s2c_starts: dict[int, tuple[int, int | None]]) -> tuple[dict[bytes, int], int | None] | None:
    """Where each direction of one connection begins (window positions), or
    None when its client's stream has no read that begins a frame (left as it
    is).  Best, and usual: the first server read that begins with the answer
    to a request a client read begins with; both streams then read on as the
    live recorder read them.  Otherwise the client's first read that begins a
    frame, and the server's first that begins a frame answering nothing or a
    request from then on (none: the server's reads in the window are left out,
    and the index of the client's first request kept says what to look for after it)."""
    asked_at = {c2s_starts[o][0]: p for p, o in c2s if o in c2s_starts}  # request index -> its read's position
    for p, o in s2c:
        answers = s2c_starts[o][1] if o in s2c_starts else None
        if answers is not None and answers in asked_at:
            return {b"c2s": asked_at[answers], b"s2c": p}, None
    clean = next(((pos, c2s_starts[offset][0]) for pos, offset in c2s if offset in c2s_starts), None)
    if clean is None:
        return None
    pos, first_index = clean
    server = next((p for p, o in s2c if o in s2c_starts and (s2c_starts[o][1] or first_index) >= first_index), None)
    if server is not None:
        return {b"c2s": pos, b"s2c": server}, None
    return {b"c2s": pos, b"s2c": s2c[-1][0] + 1 if s2c else 0}, first_index


def _direction(message: Message, topics: dict[int, str]) -> bytes:
    """Whose stream a message is about: the client's or the server's."""
    ch, _, data = message
    topic = topics[ch]
    m = (_LOG_DIR if topic == TOPIC_LOG else _DIR).search(data)
    if m is not None:
        return m.group(1)
    return b"c2s" if topic.startswith("/sends") else b"s2c"  # a plot: a value sent, or one answered


class ServerSeek:
    """After the window, the server streams that found no place to read on in
    it: each of their messages is left out until a read that begins a frame
    answering nothing or a request kept.  A read is held until the recorder's
    first frame after it says where that frame began (its frames come in the
    messages that follow it): at most one read per connection waits."""

    def __init__(self, seeking: dict[int, int], topics: dict[int, str]) -> None:
        self.seeking = seeking  # conn -> the index of its client's first request kept
        self.topics = topics
        ids = {topic: ch for ch, topic in topics.items()}
        self._reads, self._frames, self._events = ids[TOPIC_READS], ids[TOPIC_FRAMES], ids[TOPIC_EVENTS]
        self.held: dict[int, Message] = {}  # conn -> a server read waiting for its first frame

    def messages(self, messages: list[Message]) -> list[Message]:
        """What of ``messages`` the incident takes."""
        if not self.seeking:
            return messages
        out = []
        for m in messages:
            conn = conn_of(m[2])
            first = self.seeking.get(conn)
            if first is None or m[0] == self._events or _direction(m, self.topics) != b"s2c":
                out.append(m)
            elif m[0] == self._reads:
                self.held[conn] = m
            elif m[0] == self._frames and conn in self.held:
                held = self.held.pop(conn)  # its first frame decides: it is the read to begin at, or not
                read, frame = _READ.match(held[2]), _FRAME.match(m[2])
                if read is not None and frame is not None and read.group(2) == frame.group(3) and (
                        frame.group(4) == b"null" or int(frame.group(4)) >= first):
                    out += [held, m]
                    del self.seeking[conn]
        return out
