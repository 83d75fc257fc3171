"""The metadata every recording whiztap makes starts with: where it came from
(proxy, capture, replay), when, on which host, whether secrets were kept, the
checksum rule, and a session id that ties a split recording's parts together."""

from __future__ import annotations

import datetime
import socket
import uuid

from whiztap.analyzer.recording.format import metadata_record


def base_metadata(source: str, keep_secrets: bool, checksum_rule: str, start_ns: int, **extra: object) -> dict:
    """The metadata record of a recording from ``source`` started at ``start_ns``;
    ``extra``: what that source adds (listen address, server port, replay target...)."""
    start = datetime.datetime.fromtimestamp(start_ns / 1e9, datetime.timezone.utc)
    return metadata_record(source=source, start_time=start.isoformat(), start_time_ns=start_ns,
                           checksum_rule=checksum_rule, host=socket.gethostname(),
                           secrets="kept" if keep_secrets else "redacted",
                           session_id=uuid.uuid4().hex, **extra)
