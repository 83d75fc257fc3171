"""File-level facts about a recording, for ``whiztap info``."""

from __future__ import annotations

import datetime as dt
from collections import Counter
from pathlib import Path
from typing import Any

from whiztap.analyzer.recording.format import KNOWN_TOPICS, METADATA_NAME, TOPIC_EVENTS, TOPICS
from whiztap.analyzer.recording.scan import RecordingError, RecordingScan, is_finished
from whiztap.analyzer.recording.sets import being_written
from whiztap.analyzer.traffic import NAMES, Opened

_OPENED = b'"event":"%s"' % NAMES[Opened].encode()  # how a connection's opening reads in /tcp/events


def _iso(t_ns: int | None) -> str:
    if t_ns is None:
        return "-"
    return dt.datetime.fromtimestamp(t_ns / 1e9, dt.UTC).isoformat(timespec="milliseconds")


def _topic_counts(counts: Counter[str]) -> dict[str, int]:
    """Messages per topic: every topic each file has (0 when none), then the
    other whiztap topics that occur (plot topics such as /sensors/12, or a
    version 1 file's /sensors), in the format's order."""
    return {topic: counts.get(topic, 0) for topic in KNOWN_TOPICS if topic in TOPICS or counts.get(topic)}


def recording_info(path: Path) -> dict[str, Any]:
    """One pass over the file: counts per topic, time span, connections, metadata."""
    topics: Counter[str] = Counter()
    first = last = None
    connections = 0
    with open(path, "rb") as f:
        scan = RecordingScan(f, KNOWN_TOPICS, validate_crcs=True)
        try:
            for t, topic, buf, start, stop in scan.records():
                topics[topic] += 1
                first = t if first is None or t < first else first
                last = t if last is None or t > last else last
                if topic == TOPIC_EVENTS and _OPENED in buf[start:stop]:
                    connections += 1  # counted, not decoded: info reads no message's contents
        except RecordingError as e:
            raise ValueError(str(e)) from None
    complete = not scan.truncated and is_finished(str(path))
    if complete:
        state = "complete"
    elif being_written(path):
        state = "being written by a running recorder ('whiztap cat --follow' shows it as it grows)"
    elif scan.truncated:
        state = "truncated: a crash leftover"
    else:
        state = "not indexed (no summary section)"
    metadata = scan.metadata.get(METADATA_NAME, {})
    return {
        "path": str(path),
        "size_bytes": path.stat().st_size,
        "complete": complete,
        "state": state,
        "format_version": metadata.get("format_version"),
        "metadata": dict(metadata),
        "start_ns": first,
        "end_ns": last,
        "start": _iso(first),
        "end": _iso(last),
        "duration_s": ((last - first) / 1e9) if first is not None and last is not None else 0.0,
        "connections": connections,
        "topics": _topic_counts(topics),
    }


def set_info(parts: list[Path]) -> dict[str, Any]:
    """``recording_info`` of a recording split into parts, as one: sizes and
    counts added up, the span from the first part's start to the last's end,
    each connection counted once; ``parts`` lists each file's own facts."""
    infos = [recording_info(p) for p in parts]
    if len(infos) == 1:
        return infos[0]
    first = infos[0]
    starts = [i["start_ns"] for i in infos if i["start_ns"] is not None]
    ends = [i["end_ns"] for i in infos if i["end_ns"] is not None]
    start, end = (min(starts), max(ends)) if starts and ends else (None, None)
    metadata = {k: v for k, v in first["metadata"].items() if k != "part"}
    incomplete = [i for i in infos if not i["complete"]]
    return {
        "path": first["path"],
        "parts": [{"path": i["path"], "size_bytes": i["size_bytes"], "state": i["state"]} for i in infos],
        "size_bytes": sum(i["size_bytes"] for i in infos),
        "complete": not incomplete,
        "state": "complete" if not incomplete else f"{incomplete[0]['path']}: {incomplete[0]['state']}",
        "format_version": first["format_version"],
        "metadata": metadata,
        "start_ns": start,
        "end_ns": end,
        "start": _iso(start),
        "end": _iso(end),
        "duration_s": ((end - start) / 1e9) if start is not None and end is not None else 0.0,
        "connections": sum(i["connections"] for i in infos),  # 'opened' is written once, in its own part
        "topics": _topic_counts(sum((Counter(i["topics"]) for i in infos), Counter())),
    }
