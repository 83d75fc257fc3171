"""``record --ring`` holds what it says, whatever the peers do.

Every container the flight recorder keeps beyond a ``RecordingFile``'s own
is in one registry (``RING_BUFFERS``), with how to measure it and its bound;
``test_every_buffer_of_the_ring_is_registered`` fails on one that is not, so
a new buffer joins these tests by construction, as the middle's do in
``test_middle_memory.py``.  The abuse runs through the real ``Recorder``
into the real ``RingFile``, the buffers checked as it goes: a long stream
through a small ring, connections that open and never close, requests never
answered under ``latency>``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

import pytest

from whiztap.analyzer.protocol.examples import CONFIG, VPN_OPEN, C, S
from whiztap.analyzer.traffic import Data, Opened
from whiztap.sniffer.record import trigger
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.ring import ENTRY_COST, OPENING_BYTES, RingFile
from whiztap.sniffer.record.seam import ServerSeek
from whiztap.sniffer.record.trigger import MIN_RING_BYTES, Ring, Triggers
from whiztap.sniffer.record.writer import RecordingFile

MS = 1_000_000
T0 = 1_700_000_000_000_000_000
ASK, ANSWER = b"rr1-3--0--0-ss1", b"cr1-3--10--0-ss1"


def _cost(messages) -> int:
    return sum(len(m[2]) + ENTRY_COST for m in messages)


def _openings(openings) -> int:
    return sum(o.size for o in openings.values())


# For each class of the ring, each attribute that holds something that can grow: how to measure
# it, and its bound for a RingFile ``f`` (the window and the openings share the ring's bytes).
Bound = Callable[[RingFile], int]
RING_BUFFERS: dict[type, dict[str, tuple[Callable[[object], int], Bound]]] = {
    RingFile: {
        "_window": (_cost, lambda f: f.ring.max_bytes - f._opening_bytes),
        "_openings": (_openings, lambda f: f.ring.max_bytes // 4),
        "_start": (len, lambda f: 1),  # the recording's start event
        "incidents": (len, lambda f: len(f.finished) + 1),  # one per file written, and the one being written
        "_ids": (len, lambda f: len(f.channel_ids)),  # channel ids, into the incident being written
    },
    ServerSeek: {
        "seeking": (len, lambda f: len(f._openings)),  # connections whose opening the incident holds
        "held": (len, lambda f: len(f._openings)),  # one read each, at most
        "topics": (len, lambda f: len(f.channel_ids)),  # the ring's own channel map
    },
    Triggers: {
        "pending": (len, lambda f: trigger.PENDING_KEPT),
        "rules": (len, lambda f: len(f.triggers.rules)),  # the --trigger words: fixed at start
    },
}
CONTAINERS = (bytes, bytearray, list, dict, set, tuple, deque)


def buffers_of(f: RingFile) -> list[tuple[object, str, object]]:
    """(owner, attribute, value) of every container the ring keeps beyond a RecordingFile's own."""
    own = set(vars(RecordingFile("x.mcap", {})))
    found = [(f, name, value) for name, value in vars(f).items() if name not in own and isinstance(value, CONTAINERS)]
    for part in (f.triggers, f._seek):
        found += [(part, name, value) for name, value in vars(part).items() if isinstance(value, CONTAINERS)]
    return found


def check(f: RingFile, where: str) -> None:
    for owner, name, value in buffers_of(f):
        size, bound = RING_BUFFERS[type(owner)][name]
        assert size(value) <= bound(f), f"{where}: {type(owner).__name__}.{name} holds {size(value):,}, " \
                                        f"more than {bound(f):,}"
    assert f._held + f._opening_bytes <= f.ring.max_bytes, where
    assert all(o.size <= OPENING_BYTES for o in f._openings.values()), where


def _ring(tmp_path, ring: Ring, triggers: list[str]) -> tuple[Recorder, RingFile]:
    f = RingFile(str(tmp_path / "rec.mcap"), {}, ring, triggers, 100 * MS)
    recorder = Recorder(f)
    recorder.start(T0)
    return recorder, f


def test_every_buffer_of_the_ring_is_registered(tmp_path):
    """A container attribute added to the ring or its triggers fails here
    until RING_BUFFERS says how big it may get (and the tests below bound it)."""
    _, f = _ring(tmp_path, Ring(None, MIN_RING_BYTES), ["latency>5", "fault"])
    present = {f"{type(o).__name__}.{n}" for o, n, _ in buffers_of(f)}
    registered = {f"{cls.__name__}.{n}" for cls, names in RING_BUFFERS.items() for n in names}
    assert present <= registered, f"buffers of the ring not in RING_BUFFERS: {present - registered}"
    assert registered <= present, f"RING_BUFFERS names what the ring no longer has: {registered - present}"


@pytest.mark.slow
def test_a_long_stream_through_a_small_ring_holds_no_more_than_the_ring(tmp_path):
    """20,000 requests and answers (about 5 MB of messages) through a 64 kB
    ring, and 500 connections that open, say their opening and never close:
    every buffer within its bound all along, and nothing written."""
    recorder, f = _ring(tmp_path, Ring(None, MIN_RING_BYTES), ["fault"])
    t = T0
    for conn in range(2, 502):
        recorder.receive(Opened(conn, t, "c", "u"))
        recorder.receive(Data(conn, C, t, VPN_OPEN[0][1]))
        recorder.receive(Data(conn, S, t, CONFIG))
    recorder.receive(Opened(1, t, "c", "u"))
    for i in range(20_000):
        t += MS
        recorder.receive(Data(1, C, t, ASK))
        recorder.receive(Data(1, S, t, ANSWER))
        if i % 500 == 0:
            recorder.tick(t)
            check(f, f"request {i}")
    check(f, "the end")
    assert f._opening_bytes > MIN_RING_BYTES // 8  # the openings did take their share
    assert recorder.stop(t).files == [] and list(tmp_path.iterdir()) == []


def test_requests_never_answered_are_watched_up_to_the_cap(tmp_path, monkeypatch):
    """latency> watches each request until its answer or its deadline; a
    client that asks faster than the deadline passes is watched up to
    PENDING_KEPT requests, never more."""
    monkeypatch.setattr(trigger, "PENDING_KEPT", 300)
    recorder, f = _ring(tmp_path, Ring(None, MIN_RING_BYTES), ["latency>60000"])
    recorder.receive(Opened(1, T0, "c", "u"))
    recorder.receive(Data(1, C, T0, VPN_OPEN[0][1]))
    recorder.receive(Data(1, S, T0, CONFIG))
    for i in range(2_000):
        recorder.receive(Data(1, C, T0 + i * MS, ASK))
        check(f, f"request {i}")
    assert len(f.triggers.pending) == 300


@pytest.mark.slow
@pytest.mark.parametrize("after_ms", [1, 1000])
def test_a_ring_that_keeps_writing_incidents_holds_no_more_than_the_ring(tmp_path, after_ms):
    """An error in every read: incident after incident (or one long one);
    what waits in memory stays within the ring all the same."""
    f = RingFile(str(tmp_path / "rec.mcap"), {}, Ring(None, MIN_RING_BYTES), ["severity:error"], after_ms * MS)
    recorder = Recorder(f)
    recorder.start(T0)
    recorder.receive(Opened(1, T0, "c", "u"))
    for i in range(1, 400):
        recorder.receive(Data(1, C, T0 + i * MS, b"rr1-31--5--0-ss1"))
        if i % 20 == 0:
            recorder.tick(T0 + i * MS)
            check(f, f"read {i}")
    assert recorder.stop(T0 + 3000 * MS).files
