"""Every frame the TUI has seen, held outside any widget, in compact columns.

A million frames must fit in a few tens of megabytes and show at once, so the
store keeps no object per frame: fixed-width columns in ``array``s, the raw
bytes of all frames in one ``bytearray``, and sparse dicts for what few frames
have (violations, a start time that differs from the end time, an unframed
reason).  What an item means is worked out again only for the frames on screen
(``observation``), from the bytes and the few context facts the session model
found when the frame arrived: which of the codec's candidate meanings it took,
and which frame it answers.

One writer (an ingest worker thread) appends under ``lock``; the screen reads
rows below ``count``, which is published only after a batch is complete.
"""

from __future__ import annotations

import threading
from array import array
from bisect import bisect_left, insort
from collections.abc import Iterable
from typing import Any

from whiztap.analyzer.protocol.codec import decode
from whiztap.analyzer.protocol.describe import fields, meaning
from whiztap.analyzer.protocol.items import Item, ItemKind, Unframed
from whiztap.analyzer.protocol.observations import Direction, Event, LateViolation, Observation
from whiztap.analyzer.protocol.rules import Violation
from whiztap.analyzer.traffic import Intervention

NS = 1_000_000_000
KINDS: tuple[ItemKind, ...] = tuple(ItemKind)
KIND_CODE = {kind: code for code, kind in enumerate(KINDS)}
S2C_BIT = 0x10
SEVERITY_SHIFT = 5  # flags: kind (bits 0-3), direction (bit 4), severity 0-3 (bits 5-6)
NO_MEANING = 255  # choice column: the item has no single meaning
RAW_CAP = 4096  # bytes of one item kept; a camera image keeps its head and its size


class FrameStore:
    """Frames in arrival order; a frame's position here is its id in the TUI."""

    def __init__(self, redact_passwords: bool = False, raw_cap: int = RAW_CAP) -> None:
        self.lock = threading.RLock()
        self.redact_passwords = redact_passwords
        self.raw_cap = raw_cap
        self.count = 0  # frames readable by the screen
        self.start_ns: int | None = None  # time of the first frame: times are shown from here
        self.t_end = array("q")
        self.conn = array("I")
        self.session_index = array("I")  # the Observation's index within its connection
        self.flags = bytearray()
        self.choice = bytearray()  # which codec candidate the session settled on
        self.pair = array("i")  # the request a response answers, or the response a request got
        self.raw_end = array("Q")
        self.raws = bytearray()
        self.t_start: dict[int, int] = {}  # only where it differs from t_end
        self.reasons: dict[int, Unframed] = {}
        self.violations: dict[int, tuple[Violation, ...]] = {}
        self.violating: list[int] = []  # sorted frame ids with a violation
        self.late_marked: list[int] = []  # frames that got a violation after they were stored
        self.capped: dict[int, tuple[int, str, dict[str, Any]]] = {}  # size, meaning, fields
        self.rates: dict[int, list[int]] = {}  # second -> [c2s frames, s2c frames]
        self._by_conn: dict[int, array] = {}  # conn -> frame id by session index
        self._second = -1  # the second the last frame fell in, and its counts
        self._counts = [0, 0]
        self.marks: dict[int, list[Intervention]] = {}  # what the proxy in the middle did to a frame
        # in the middle, where the proxy changed a frame's timing: when its client sent it (c2s) or got it
        # (s2c), the row's own time being the server's
        self.client_t: dict[int, int] = {}
        self.marked: list[int] = []  # frames given a mark after they were stored (lines to redraw)
        self.unseen: dict[int, list[int]] = {}  # conn -> its rows no session saw (add_unseen), in order

    # -- writing (the ingest worker) ------------------------------------------------------

    def add(self, conn: int, events: Iterable[Event]) -> None:
        """Store a connection's session events: observations become frames, late
        violations mark the frame they are about.

        A hot loop, kept in one piece with everything in locals: it runs once
        per frame, at hundreds of thousands of frames a second while a
        recording loads, where a helper call or attribute lookup per frame
        shows in the TUI's load benchmark (benchmarks/bench_tui.py).
        """
        index = self._by_conn.get(conn)
        if index is None:
            index = self._by_conn[conn] = array("i")
        n = first = self.count
        flag, choose = self.flags.append, self.choice.append
        end_at, conn_of, session_at = self.t_end.append, self.conn.append, self.session_index.append
        pair = self.pair
        paired = pair.append
        raws = self.raws
        raw_ends = self.raw_end.append
        indexed = index.append
        kind_code, s2c_dir, password = KIND_CODE, Direction.S2C, ItemKind.PASSWORD
        cap, redact = self.raw_cap, self.redact_passwords
        rates, second, counts = self.rates, self._second, self._counts
        for e in events:
            if isinstance(e, LateViolation):
                self._mark_late(index, e)
                continue
            at, direction, item, message, candidates, violations, answers, _ = e
            kind, raw, t_start, t_end, reason = item
            s2c = direction is s2c_dir
            if violations:
                self.violations[n] = violations
                self.violating.append(n)
                flag(kind_code[kind] | (S2C_BIT if s2c else 0)
                     | max(v.severity for v in violations) << SEVERITY_SHIFT)
            else:
                flag(kind_code[kind] | (S2C_BIT if s2c else 0))
            if message is None:
                choose(NO_MEANING)
            elif message is candidates[0]:
                choose(0)
            else:
                choose(candidates.index(message))
            end_at(t_end)
            conn_of(conn)
            session_at(at)
            if at == len(index):
                indexed(n)
            else:  # not expected from a Session; keep the map right anyway
                index.extend([-1] * (at + 1 - len(index)))
                index[at] = n
            if answers is not None and answers.index < len(index) and index[answers.index] >= 0:
                request = index[answers.index]
                paired(request)
                pair[request] = n
            else:
                paired(-1)
            if len(raw) > cap or (redact and kind is password):
                raw = self._unusual_raw(n, e)
            raws += raw
            raw_ends(len(raws))
            if t_start != t_end:
                self.t_start[n] = t_start
            if reason is not None:
                self.reasons[n] = reason
            this_second = t_end // NS
            if this_second != second:
                second = this_second
                known = rates.get(second)
                if known is None:
                    known = rates[second] = [0, 0]
                counts = known
            counts[s2c] += 1
            n += 1
        self._second, self._counts = second, counts
        if self.start_ns is None and n > first:
            self.start_ns = self.t_start.get(first, self.t_end[first])
        self.count = n

    def add_unseen(self, conn: int, direction: Direction, kind: ItemKind, raw: bytes, t_ns: int,
                   marks: list[Intervention]) -> int:
        """A frame no session saw, with what happened to it (``marks``): one the
        proxy dropped before the server got it, or injected toward the client.
        It pairs with nothing; its row id is returned."""
        n = self.count
        self.flags.append(KIND_CODE[kind] | (S2C_BIT if direction is Direction.S2C else 0))
        self.choice.append(NO_MEANING if len(decode(kind, raw).candidates) != 1 else 0)
        self.t_end.append(t_ns)
        self.conn.append(conn)
        self.session_index.append(0)
        self.pair.append(-1)
        self.raws += raw[:self.raw_cap]
        self.raw_end.append(len(self.raws))
        self.marks[n] = marks
        self.unseen.setdefault(conn, []).append(n)
        if self.start_ns is None:
            self.start_ns = t_ns
        self.count = n + 1
        return n

    def mark(self, n: int, mark: Intervention) -> None:
        """Add what the proxy did to frame ``n`` (its line is drawn again)."""
        self.marks.setdefault(n, []).append(mark)
        self.marked.append(n)

    def last_frames(self, conn: int, direction: Direction, within: int = 256) -> Iterable[int]:
        """The connection's most recent frames in ``direction``, newest first."""
        index = self._by_conn.get(conn)
        if index is None:
            return ()
        return (n for n in reversed(index[-within:]) if n >= 0 and self.direction(n) is direction)

    def _unusual_raw(self, n: int, e: Observation) -> bytes:
        """What is kept of a password (masked) or of a large item (its head)."""
        raw = e.item.raw
        if e.item.kind is ItemKind.PASSWORD and self.redact_passwords:
            raw = b"*" * len(raw)
        if len(raw) > self.raw_cap:
            self.capped[n] = (len(raw), meaning(e), fields(e))
            raw = raw[:self.raw_cap]
        return raw

    def _mark_late(self, index: array, e: LateViolation) -> None:
        about = e.about.index
        if about >= len(index) or index[about] < 0:
            return
        self.add_violation(index[about], e.violation)

    def add_violation(self, n: int, violation: Violation) -> None:
        """A violation found after frame ``n`` was stored (its line is drawn again)."""
        before = self.violations.get(n, ())
        self.violations[n] = before + (violation,)
        if not before:
            insort(self.violating, n)
        severity = max(self.severity(n), violation.severity)
        self.flags[n] = (self.flags[n] & ~(3 << SEVERITY_SHIFT)) | severity << SEVERITY_SHIFT
        self.late_marked.append(n)

    # -- reading (the screen) -------------------------------------------------------------

    def kind(self, n: int) -> ItemKind:
        return KINDS[self.flags[n] & 0x0F]

    def direction(self, n: int) -> Direction:
        return Direction.S2C if self.flags[n] & S2C_BIT else Direction.C2S

    def severity(self, n: int) -> int:
        """0 for a frame without violations, else the worst one's Severity value."""
        return self.flags[n] >> SEVERITY_SHIFT & 3

    def raw(self, n: int) -> bytes:
        return bytes(self.raws[self.raw_end[n - 1] if n else 0:self.raw_end[n]])

    def size(self, n: int) -> int:
        capped = self.capped.get(n)
        return capped[0] if capped else self.raw_end[n] - (self.raw_end[n - 1] if n else 0)

    def conn_rows(self, conn: int) -> int:
        """The rows of connection ``conn``: what the list shows with it chosen,
        and what the connections pane counts (its session's frames, and
        those no session saw)."""
        return len(self._by_conn.get(conn, ())) + len(self.unseen.get(conn, ()))

    def conn_ordinal(self, n: int) -> int:
        """Frame ``n``'s place among its connection's rows, from 1: the last
        row's is what the connections pane counts."""
        conn = self.conn[n]
        unseen = self.unseen.get(conn, [])
        at = bisect_left(unseen, n)
        if at < len(unseen) and unseen[at] == n:  # seen by no session: after the session's frames before it
            return bisect_left(self._by_conn.get(conn, array("i")), n) + at + 1
        return self.session_index[n] + at + 1

    def relative_s(self, n: int) -> float:
        return (self.t_end[n] - (self.start_ns or 0)) / NS

    def observation(self, n: int, with_answer: bool = True) -> Observation:
        """Frame ``n`` as the session observed it (rebuilt; for what is shown)."""
        kind = self.kind(n)
        raw = self.raw(n)
        t_end = self.t_end[n]
        reason = self.reasons.get(n)
        item = Item(kind, raw, self.t_start.get(n, t_end), t_end, reason)
        decoded = decode(kind, raw, reason)
        choice = self.choice[n]
        message = None if choice == NO_MEANING or choice >= len(decoded.candidates) else decoded.candidates[choice]
        answers = latency = None
        paired = self.pair[n]
        if with_answer and paired >= 0 and paired < n:
            answers = self.observation(paired, with_answer=False)
            latency = t_end - self.t_end[paired]
        return Observation(self.session_index[n], self.direction(n), item, message, decoded.candidates,
                           self.violations.get(n, ()), answers, latency)

    def meaning(self, n: int) -> str:
        capped = self.capped.get(n)
        return capped[1] if capped else meaning(self.observation(n))

    def fields(self, n: int) -> dict[str, Any]:
        capped = self.capped.get(n)
        return capped[2] if capped else fields(self.observation(n))

    def next_violation(self, after: int) -> int | None:
        """The first frame id above ``after`` with a violation."""
        with self.lock:
            at = bisect_left(self.violating, after + 1)
            return self.violating[at] if at < len(self.violating) else None

    def violations_from(self, start: int, step: int) -> Iterable[int]:
        """Frame ids with violations from ``start`` on (step 1) or back (step -1)."""
        with self.lock:
            ids = list(self.violating)
        at = bisect_left(ids, start)
        if step > 0:
            return ids[at:]
        if at < len(ids) and ids[at] == start:
            at += 1
        return reversed(ids[:at])

    def rate_series(self, last_seconds: int | None = None) -> tuple[list[int], list[int]]:
        """Frames per second (client to server, server to client), gaps as zeros."""
        with self.lock:
            if not self.rates:
                return [], []
            first, last = min(self.rates), max(self.rates)
            if last_seconds is not None:
                first = max(first, last - last_seconds + 1)
            rows = [self.rates.get(s, (0, 0)) for s in range(first, last + 1)]
        return [r[0] for r in rows], [r[1] for r in rows]

    def nbytes(self) -> int:
        """Memory the columns hold (arrays as allocated; sparse dicts roughly)."""
        columns = (self.t_end, self.conn, self.session_index, self.pair, self.raw_end)
        total = sum(c.buffer_info()[1] * c.itemsize for c in columns)
        total += len(self.flags) + len(self.choice) + len(self.raws)
        total += sum(a.buffer_info()[1] * a.itemsize for a in self._by_conn.values())
        sparse = len(self.t_start) + len(self.reasons) + len(self.violations) + len(self.capped) + len(self.client_t)
        return total + 100 * sparse + 8 * len(self.violating)

