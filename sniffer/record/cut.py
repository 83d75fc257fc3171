"""Cutting a recording into a smaller recording (``whiztap cut``).

What is kept is decided per connection: a connection stays, whole, when it is
one asked for (``--conn``) and at least one of its items passes the filter
words and the time window.  Whole, because a connection's bytes are one TCP
stream: its handshake, password and configuration exchange decide what every
later frame means (an ``rr1-N--0--0-ss1`` is ambiguous until the channel map is
known), and a stream with a hole in it is a different stream to the session
model.  So ``analyze`` of the cut gives the kept connections exactly the
verdicts they had in the original, and the cut is a recording every reader
opens: it is written by ``RecordingFile``, the recorder's own writer, with the
original's metadata.

Messages without a connection (the recording's own start and stop) are kept;
a ``continued`` event that repeats a connection already in the cut (the
original was split into parts) is left out, as a reader of the parts together
leaves it out.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from whiztap.analyzer.recording.format import LATE_TOPICS, METADATA_NAME, TOPIC_EVENTS, TOPIC_LOG, TOPICS

if TYPE_CHECKING:
    from whiztap.analyzer.analysis.item_filter import ItemFilter
    from whiztap.analyzer.protocol.session import Limits
    from whiztap.analyzer.recording.remote import PartFile, RemotePart
    from whiztap.analyzer.traffic import TrafficEvent

NS = 1_000_000_000
ALL_TOPICS = (*TOPICS, *LATE_TOPICS)
_LOG_FILE = re.compile(r"conn-(\d{1,19})")  # a /log line names its connection in its "file" field
_FIRST_CONN = re.compile(rb'\{"conn":(\d{1,19})[,}]')  # how whiztap's writer begins a message: no JSON parse


@dataclass(frozen=True)
class Bound:
    """One end of the time window: ns after the first traffic, or an absolute
    time (ns since the epoch) from an ISO timestamp."""

    offset_ns: int = 0
    epoch_ns: int | None = None

    def at(self, start_ns: int) -> int:
        """The bound in ns since the epoch, for a recording whose traffic begins at ``start_ns``."""
        return self.epoch_ns if self.epoch_ns is not None else start_ns + self.offset_ns


_WANTS = "wants seconds after the recording's first traffic (2.5, 2.5s, 250ms) or an ISO timestamp " \
         "(2026-11-28T05:12:00)"
_UNITS = (("ms", 1e-3), ("us", 1e-6), ("s", 1.0), ("m", 60.0), ("h", 3600.0))
_LONGEST_S = 100 * 365 * 86400  # a century: past it a time is a typing slip, not a recording's length


def parse_bound(text: str) -> Bound:
    """``2.5``, ``2.5s``, ``250ms``, ``1m`` (after the first traffic) or an ISO
    timestamp (``2026-11-28T05:12:00``, local time unless it has a zone);
    ValueError with what is wanted otherwise."""
    from datetime import datetime

    value = text.strip()
    for suffix, scale in (*_UNITS, ("", 1.0)):
        number = value[: len(value) - len(suffix)]
        if value.endswith(suffix) and _is_number(number):
            seconds = float(number) * scale
            if not -_LONGEST_S <= seconds <= _LONGEST_S:
                raise ValueError(f"{_WANTS}; {text!r} is more than a century")
            return Bound(offset_ns=round(seconds * NS))
    try:
        return Bound(epoch_ns=round(datetime.fromisoformat(value).timestamp() * NS))
    except (ValueError, OverflowError, OSError):  # not ISO, or a date the clock cannot count
        raise ValueError(f"{_WANTS}, got {text!r}") from None


def _is_number(text: str) -> bool:
    """A finite decimal number (not ``nan``, ``inf``, nor empty)."""
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def chosen_connections(events: Iterable[TrafficEvent], item_filter: ItemFilter, start: Bound | None,
                       end: Bound | None, name: str, checksum_rule: str, limits: Limits) -> set[int]:
    """The connections with at least one item that passes ``item_filter`` and
    lies in [start, end) (by the item's last byte, as ``cat`` times items),
    judged by the one session model the reports use; with no words and no
    window, every connection (of ``--conn``) there is."""
    from dataclasses import replace

    from whiztap.analyzer.analysis.analyzer import Analyzer
    from whiztap.analyzer.protocol.observations import LateViolation
    from whiztap.analyzer.traffic import Data

    # the window is checked here, in ns (the caller made the filter's since:/until: part of it)
    words = replace(item_filter, since_s=None, until_s=None)
    # nothing but connections asked for: a connection without a single item (opened, then closed) is kept too
    every = start is None and end is None and words == type(words)(conns=words.conns)
    analyzer = Analyzer(name, checksum_rule, limits)
    kept: set[int] = set()
    first: int | None = None
    window = (0, 0)

    def look(conn: int, found: list) -> None:
        if conn in kept:
            return
        for e in found:
            about, late = (e.about, True) if isinstance(e, LateViolation) else (e, False)
            t = about.item.t_end_ns
            if ((start is None or t >= window[0]) and (end is None or t < window[1])
                    and words.accepts(conn, about, first or 0, late=late)):
                kept.add(conn)
                return

    for event in events:
        if every and event.conn and (not words.conns or event.conn in words.conns):
            kept.add(event.conn)
        if first is None and type(event) is Data:
            first = event.t_ns
            window = (start.at(first) if start else 0, end.at(first) if end else 0)
        look(event.conn, analyzer.receive(event))
    for conn, found in analyzer.close_all():
        look(conn, found)
    return kept


def copy_connections(parts: Iterable[Path | RemotePart], output: str, kept: set[int], *, force: bool,
                     open_file: Callable[[Path | RemotePart], PartFile]) -> int:
    """Write ``output``: every message of the ``kept`` connections and the
    recording's own, in the original's order and times, under the first
    part's metadata.  Returns the messages written."""
    from whiztap.sniffer.record.writer import RecordingFile

    out: RecordingFile | None = None
    try:
        for topic, t_ns, data, metadata in _kept_messages(parts, kept, open_file):
            if out is None:
                out = RecordingFile(output, _metadata(metadata), overwrite=force)
                out.open(t_ns)
            if topic in TOPICS:
                out.write(topic, t_ns, data)
            else:
                out.write_late(topic, t_ns, data)
        if out is None:
            raise ValueError("the recording holds no message to copy")
        out.finish()
    except BaseException:
        _abandon(out)
        raise
    return out.messages


def _metadata(original: dict[str, str]) -> dict[str, str]:
    """The cut's metadata: the original's (robot, firmware, when, the format,
    its session id), less what made it a part of a split recording: the cut
    is one file, which no reader may take for a sibling of the original's parts."""
    single = {"split_size": "", "split_duration": ""}
    return {k: single.get(k, v) for k, v in original.items() if k != "part"}


def _abandon(out: object) -> None:
    """A cut that failed leaves no ``.part`` behind: it is no crash to recover from."""
    import contextlib
    import os

    from whiztap.sniffer.record.writer import RecordingFile

    if not isinstance(out, RecordingFile) or out._stream is None:
        return
    with contextlib.suppress(OSError):
        os.close(out._stream.fd)
    with contextlib.suppress(OSError):
        os.unlink(out.current_path + ".part")


def _kept_messages(parts: Iterable[Path | RemotePart], kept: set[int],
                   open_file: Callable[[Path | RemotePart], PartFile]
                   ) -> Iterator[tuple[str, int, bytes, dict[str, str]]]:
    """(topic, log time, message bytes, the part's whiztap metadata) of each message kept."""
    from whiztap.analyzer.recording.scan import RecordingScan

    seen: set[int] = set()
    for path in parts:
        with open_file(path) as f:
            scan = RecordingScan(f, ALL_TOPICS)
            for t_ns, topic, buf, start, stop in scan.records():
                data = bytes(buf[start:stop])
                conn = _conn_of(topic, data)
                if conn and conn not in kept:
                    continue
                if topic == TOPIC_EVENTS and conn:
                    if json.loads(data).get("event") == "continued" and conn in seen:
                        continue
                    seen.add(conn)
                yield topic, t_ns, data, scan.metadata.get(METADATA_NAME, {})


def _conn_of(topic: str, data: bytes) -> int:
    """The connection a message is about (0: the recording's own)."""
    if topic == TOPIC_LOG:
        # not in its text, which quotes what peers sent ("(conn 1" in a frame)
        named = _LOG_FILE.match(str(json.loads(data).get("file", "")))
        return int(named.group(1)) if named else 0
    found = _FIRST_CONN.match(data)
    if found:
        return int(found.group(1))
    conn = json.loads(data).get("conn", 0)  # another writer's layout
    return conn if isinstance(conn, int) else 0
