"""The metadata every recording whiztap makes starts with: where it came from
(proxy, capture, replay), when, on which host, whether secrets were kept, the
checksum rule, and a session id that ties a split recording's parts together;
then the user's own keys (``whiztap record --meta robot=r7``), which a fleet
report groups by (docs/fleet.md)."""

from __future__ import annotations

import datetime
import re
import socket
import uuid
from collections.abc import Iterable, Mapping

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.recording.format import metadata_record

# Keys whiztap itself writes (docs/recording-format.md): a user's key may not
# take one, or a recording could claim to be made in the middle, or another
# recording's part.
RESERVED_KEYS = frozenset((
    "format_version", "whiztap_version", "spec_revision", "source", "replay_of", "target", "pace", "rate",
    "listen", "upstream", "pcap", "iface", "server_port", "start_time", "start_time_ns", "checksum_rule", "host",
    "secrets", "session_id", "split_size", "split_duration", "part", "middle", "faults", "seed",
    "incident", "incident_trigger", "mirror",
))
_KEY = re.compile(r"^[A-Za-z_][A-Za-z0-9_.-]{0,63}$")
MAX_VALUE = 1024  # characters of one value: a name or a version, not a document


class MetadataError(WhiztapError, ValueError):
    """A --meta that cannot go into a recording; one line."""


def user_metadata(pairs: Iterable[str]) -> dict[str, str]:
    """``KEY=VALUE`` pairs as the recording's own keys.  Raises MetadataError
    for a pair without ``=``, a key that is not a plain name, one of
    whiztap's own keys, a key given twice, or a value over 1024 characters."""
    found: dict[str, str] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise MetadataError(f"--meta {pair!r}: expected KEY=VALUE")
        if not _KEY.match(key):
            raise MetadataError(f"--meta {pair!r}: {key!r} is not a key (a letter or _, then letters, digits, "
                                "_ . -; 64 at most)")
        if key in RESERVED_KEYS:
            raise MetadataError(f"--meta {pair!r}: {key!r} is a key whiztap writes itself; choose another name")
        if key in found:
            raise MetadataError(f"--meta {key!r} is given twice")
        if len(value) > MAX_VALUE:
            raise MetadataError(f"--meta {key!r}: the value is over {MAX_VALUE} characters")
        found[key] = value
    return found


def base_metadata(source: str, keep_secrets: bool, checksum_rule: str, start_ns: int,
                  user: Mapping[str, str] | None = None, **extra: object) -> dict:
    """The metadata record of a recording from ``source`` started at ``start_ns``;
    ``extra``: what that source adds (listen address, server port, replay target...);
    ``user``: the user's own keys (``user_metadata``), after whiztap's."""
    start = datetime.datetime.fromtimestamp(start_ns / 1e9, datetime.UTC)
    record = metadata_record(source=source, start_time=start.isoformat(), start_time_ns=start_ns,
                             checksum_rule=checksum_rule, host=socket.gethostname(),
                             secrets="kept" if keep_secrets else "redacted",
                             session_id=uuid.uuid4().hex, **extra)
    record.update(user or {})
    return record
