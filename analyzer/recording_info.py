"""File-level facts about a recording, for ``whiztap info``."""

from __future__ import annotations

import datetime as dt
from collections import Counter
from pathlib import Path
from typing import Any

from analyzer.recording import METADATA_NAME, TOPIC_EVENTS, TOPICS, RecordingError, RecordingScan


def _iso(t_ns: int | None) -> str:
    if t_ns is None:
        return "-"
    return dt.datetime.fromtimestamp(t_ns / 1e9, dt.timezone.utc).isoformat(timespec="milliseconds")


def _indexed(path: Path) -> bool:
    """True when the file ends with a footer and a summary section (it was finished)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        try:
            return make_reader(f).get_summary() is not None
        except (McapError, ValueError, EOFError, OSError):
            return False
        except Exception:  # noqa: BLE001 - the mcap reader raises struct.error etc. on damaged files
            return False


def recording_info(path: Path) -> dict[str, Any]:
    """One pass over the file: counts per topic, time span, connections, metadata."""
    topics: Counter[str] = Counter()
    first = last = None
    connections: set[int] = set()
    with open(path, "rb") as f:
        scan = RecordingScan(f, TOPICS, validate_crcs=True)
        try:
            for t, topic, buf, start, stop in scan.records():
                topics[topic] += 1
                first = t if first is None or t < first else first
                last = t if last is None or t > last else last
                if topic == TOPIC_EVENTS and b'"event":"opened"' in buf[start:stop]:
                    import json

                    connections.add(json.loads(buf[start:stop])["conn"])
        except RecordingError as e:
            raise ValueError(str(e)) from None
    complete = not scan.truncated and _indexed(path)
    state = "complete" if complete else ("truncated: a crash leftover" if scan.truncated
                                         else "not indexed (no summary section)")
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
        "connections": len(connections),
        "topics": {topic: topics.get(topic, 0) for topic in TOPICS},
    }
