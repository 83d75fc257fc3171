"""What ``record --ring`` keeps and what makes it write an incident.

The flight recorder's words, parsed once for the command and the writer:
``--ring 30s`` or ``--ring 64MB`` (``parse_ring``), ``--after 5s``
(``parse_duration``) and each ``--trigger`` (``parse_trigger``): a rule id,
``severity:LEVEL``, ``latency>MS`` or ``fault``.  ``Triggers`` watches the
messages the recorder writes (a violation's rule and severity, a frame's
answer latency, an intervention) and says when one fires, and why.  It
reads the recorder's own messages rather than the traffic, so what fires
is exactly what the file says: the verdict of the one session model.

A ring given as a duration is a window in time and, so that no peer can make
it hold more, also in bytes (``DURATION_RING_BYTES``); a ring given as a size
is that many bytes whatever the time.
"""

from __future__ import annotations

import difflib
import re
from dataclasses import dataclass

from whiztap.analyzer.protocol.messages import FetchCameraImage, FetchConfiguration, SensorRequest, ServoPositionRequest
from whiztap.analyzer.protocol.rules import RULES, Severity
from whiztap.analyzer.protocol.text import parse_size

NS = 1_000_000_000
DURATION_RING_BYTES = 256 << 20  # what a ring given as a duration may hold at most
MIN_RING_BYTES = 64 << 10  # below it, one connection's opening would not fit
DEFAULT_AFTER_S = 5.0
PENDING_KEPT = 100_000  # requests watched for latency> at once; past it the oldest is no longer watched
_DURATION = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*(ms|s|m|h)\s*$")  # lower case: 64M is no duration
_DURATION_UNITS = {"ms": 1e-3, "s": 1.0, "m": 60.0, "h": 3600.0}
_SIZE_WORD = re.compile(r"^\s*\d+(?:\.\d+)?\s*[kmgt]?i?b\s*$", re.IGNORECASE)  # a size says B: 64MB, 512kB, 1GiB
_LATENCY = re.compile(r"^latency\s*>\s*(\d+(?:\.\d+)?)\s*(?:ms)?$", re.IGNORECASE)
_RING_WANTS = "wants a duration (30s, 2m, 500ms) or a size in bytes (64MB, 512kB)"
TRIGGER_WANTS = "wants a rule id (PW-PAIR-UNSOLICITED), severity:LEVEL (info, warning, error), latency>MS or fault"
# Requests that wait for an answer, by the title a /frames message names them with (pairing.answer_spec's).
_REQUESTS = "|".join(m.title for m in (FetchConfiguration, FetchCameraImage, SensorRequest, ServoPositionRequest))
_FRAME = re.compile(rb'\{"conn":(\d+),"dir":"(c2s|s2c)","index":(\d+),"t_start_ns":\d+,"t_end_ns":(\d+),'
                    rb'"offset":\d+,"answers":(null|\d+),"latency_ns":(null|\d+),"kind":"(\w+)"')
_REQUEST = re.compile(rb'"message":"(?:' + _REQUESTS.encode() + rb')"')
_VIOLATION = re.compile(rb'"rule_id":"([A-Z0-9-]+)","severity":"(\w+)"')
_CONN = re.compile(rb'\{"conn":(\d+)[,}]')


@dataclass(frozen=True)
class Ring:
    """The window kept: ``duration_ns`` (None: a size alone) and ``max_bytes``."""

    duration_ns: int | None
    max_bytes: int

    def describe(self) -> str:
        mib = f"{self.max_bytes / (1 << 20):g} MiB"
        return mib if self.duration_ns is None else f"{self.duration_ns / NS:g} s (at most {mib})"


@dataclass(frozen=True)
class RingSettings:
    """``record --ring``: the window, the ``--trigger`` words (canonical), and ``--after`` in seconds."""

    ring: Ring
    triggers: tuple[str, ...]
    after_s: float = DEFAULT_AFTER_S

    def config(self) -> dict:
        """As the writer process's configuration carries it (JSON)."""
        return {"duration_ns": self.ring.duration_ns, "max_bytes": self.ring.max_bytes,
                "triggers": list(self.triggers), "after_ns": round(self.after_s * NS)}


def parse_duration(text: str) -> float:
    """``30s``, ``2m``, ``500ms``, ``1h`` in seconds (a unit is needed: ``m`` is minutes); ValueError otherwise."""
    m = _DURATION.match(text)
    if m is None or float(m.group(1)) <= 0:
        raise ValueError(f"wants a duration such as 30s, 2m or 500ms, got {text!r}")
    return float(m.group(1)) * _DURATION_UNITS[m.group(2)]


def parse_ring(text: str) -> Ring:
    """``--ring``: a duration (at most ``DURATION_RING_BYTES`` too) or a size
    that ends in B; a bare number or ``64M`` is refused, as it could be either."""
    if _SIZE_WORD.match(text):
        size = parse_size(text)
        if size < MIN_RING_BYTES:
            raise ValueError(f"{text!r} is too small a ring: at least 64kB")
        return Ring(None, size)
    try:
        seconds = parse_duration(text)
    except ValueError:
        raise ValueError(f"{_RING_WANTS}, got {text!r}") from None
    return Ring(round(seconds * NS), DURATION_RING_BYTES)


def parse_trigger(text: str) -> str:
    """One ``--trigger`` in its canonical spelling (``PW-PAIR-UNSOLICITED``,
    ``severity:error``, ``latency>250``, ``fault``); ValueError naming what
    is wanted, and the rule meant when a rule id is misspelt."""
    word = text.strip()
    if word.lower() == "fault":
        return "fault"
    if word.lower().startswith("severity:"):
        return f"severity:{Severity.parse(word.partition(':')[2].strip())}"
    m = _LATENCY.match(word)
    if m is not None and float(m.group(1)) > 0:
        return f"latency>{float(m.group(1)):g}"
    if word.upper() in RULES:
        return word.upper()
    close = difflib.get_close_matches(word.upper(), RULES, n=1)
    hint = f" (did you mean {close[0]}?)" if close else "; 'whiztap rules' lists the rule ids"
    raise ValueError(f"{TRIGGER_WANTS}, got {text!r}{hint}")


def conn_of(data: bytes) -> int:
    """The connection a message of the recorder's is about (0: the recording's own)."""
    m = _CONN.match(data)
    return int(m.group(1)) if m else 0


class Triggers:
    """The ``--trigger`` words at work over the recorder's messages: each
    ``violation``, ``frame`` and ``intervention`` call, and ``due`` as time
    passes, returns why an incident begins now, or None."""

    def __init__(self, words: list[str]) -> None:
        self.rules = {w for w in words if w in RULES}
        levels = [Severity.parse(w.partition(":")[2]) for w in words if w.startswith("severity:")]
        self.severity = min(levels) if levels else None
        latencies = [float(w.partition(">")[2]) for w in words if w.startswith("latency>")]
        self.latency_ns = round(min(latencies) * 1e6) if latencies else None
        self.fault = "fault" in words
        # (conn, frame index) -> when the request was sent: requests not answered yet, oldest first
        self.pending: dict[tuple[int, int], int] = {}

    def violation(self, data: bytes) -> str | None:
        m = _VIOLATION.search(data)
        if m is None:
            return None
        rule, severity = m.group(1).decode(), m.group(2).decode()
        if rule in self.rules:
            return f"{rule} on conn #{conn_of(data)}"
        if self.severity is not None and Severity.parse(severity) >= self.severity:
            return f"{rule} ({severity}) on conn #{conn_of(data)}"
        return None

    def intervention(self, data: bytes) -> str | None:
        return f"a fault on conn #{conn_of(data)}" if self.fault else None

    def frame(self, data: bytes) -> str | None:
        """A /frames message: a request to watch, or an answer (too late or not)."""
        limit = self.latency_ns
        m = _FRAME.match(data) if limit is not None else None
        if limit is None or m is None:
            return None
        conn = int(m.group(1))
        if m.group(2) == b"c2s":
            if m.group(7) == b"command" and _REQUEST.search(data):
                self.pending[conn, int(m.group(3))] = int(m.group(4))
                if len(self.pending) > PENDING_KEPT:
                    del self.pending[next(iter(self.pending))]
            return None
        if m.group(5) != b"null":
            self.pending.pop((conn, int(m.group(5))), None)
        if m.group(6) != b"null" and int(m.group(6)) > limit:
            return f"an answer after {int(m.group(6)) / 1e6:.0f} ms on conn #{conn}"
        return None

    def due(self, t_ns: int) -> str | None:
        """A request unanswered for longer than ``latency>`` by ``t_ns``: the
        oldest says why (each is told once, then no longer watched)."""
        limit = self.latency_ns
        pending = self.pending
        why = None
        while limit is not None and pending:
            key = next(iter(pending))
            if pending[key] + limit > t_ns:
                break
            del pending[key]
            why = why or f"no answer within {limit / 1e6:g} ms on conn #{key[0]}"
        return why
