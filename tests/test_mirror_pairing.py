"""The writer's side of ``record --mirror``, in-process: the real Recorder and file, the mirror's
bytes drawn by Hypothesis (a mirror is a peer: anything may come from it).

Properties: whatever the mirror sends and however its reads interleave with the
primary's, nothing raises, every difference the pairing reports is on
``/mirror/differences`` and counted, the mirror's stream is recorded whole
and in order, and the client's password, masked for the primary's file, shows
in no mirror topic, difference or status line, even when the mirror does not
ask for it (the pairing reads the client's bytes as the file has them).
Also the memory registry of the mirror's buffers (like test_middle_memory's
``BUFFERS``): a container added to a mirror class fails until it is bounded here.
"""

from __future__ import annotations

import base64
import json
from collections import deque
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from whiztap.analyzer.analysis.diff import DiffResult
from whiztap.analyzer.analysis.mirror import MAX_HANDSHAKE, MAX_WAITING, MirrorPairing, MirrorTally, _Pair, _Side
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.session import Limits
from whiztap.analyzer.recording.format import MIRROR_TOPICS, metadata_record
from whiztap.analyzer.traffic import Closed, Data, HalfClosed, Opened
from whiztap.sniffer.record.mirror import MIRROR_BUFFER, MirrorLeg, MirrorView
from whiztap.sniffer.record.mirror_record import MIRROR_QUEUE_CAP, MirrorRecorder, mirror_recorder
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile

from tests.outputs import SECRET, TRAFFIC_TOPICS, assert_no_leak
from tests.record_support import read_all

C2S, S2C = Direction.C2S, Direction.S2C
T0 = 1_700_000_000_000_000_000
REQUESTS = b"rr1-12--0--0-ss1rr1-13--0--0-ss1"
PRIMARY = [b"sendchkpass", b"readytogo", b"cr1-12--465--0-ss1", b"cr1-13--7--0-ss1"]
PIECES = [b"sendchkpass", b"readytogo", b"Failed Validation", b"cr1-12--999--0-ss1", b"cr1-13--7--0-ss1",
          b"\r\n", b"cr1-", b"rr1-12--0--0-ss1", b"sr1-25--\x02000200-ss1"]


@st.composite
def mirror_streams(draw) -> list[bytes]:
    """What a mirror sends: the protocol's words, fragments of them, and any bytes, cut anywhere."""
    pieces = draw(st.lists(st.one_of(st.sampled_from(PIECES), st.binary(max_size=40)), max_size=8))
    data = b"".join(pieces)
    cuts = sorted(draw(st.sets(st.integers(0, len(data)), max_size=6)))
    return [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)]) if b > a]


def _record(path: Path, first_line: bytes, mirror_reads: list[bytes],
            order: list[bool]) -> tuple[list[dict], dict, MirrorRecorder]:
    """One connection: the client's password and requests, the primary's greeting and answers, the
    mirror's reads interleaved as ``order`` says; the status lines said, the last, and the recorder."""
    said: list[dict] = []
    file = RecordingFile(str(path), metadata_record(source="test", listen="", upstream="", mirror="m:1"))
    recorder = Recorder(file)
    mirror = mirror_recorder(recorder, file, {"mirror": "m:1", "checksum_rule": "dev-sum",
                                              "limits": Limits().as_dict()}, said.append)
    assert isinstance(mirror, MirrorRecorder)
    recorder.start(T0)
    t = T0
    recorder.receive(Opened(1, t, "127.0.0.1:40000", "127.0.0.1:5000"))
    mirror.receive(1, False, t, json.dumps({"event": "connected", "detail": ""}).encode())
    primary = [(S2C, PRIMARY[0]), (C2S, first_line), (S2C, PRIMARY[1]), (C2S, REQUESTS),
               *((S2C, answer) for answer in PRIMARY[2:])]
    reads = deque(mirror_reads)
    for mine in order:
        t += 1_000
        if mine and reads:
            mirror.receive(1, True, t, reads.popleft())
        elif primary:
            direction, data = primary.pop(0)
            recorder.receive(Data(1, direction, t, data))
    for direction, data in primary:
        t += 1_000
        recorder.receive(Data(1, direction, t, data))
    for data in reads:
        t += 1_000
        mirror.receive(1, True, t, data)
    recorder.receive(HalfClosed(1, t + 1, C2S))
    recorder.receive(Closed(1, t + 2, "client"))
    mirror.receive(1, False, t + 3, json.dumps({"event": "closed", "detail": "closed by the mirror"}).encode())
    mirror.finish(t + 4)
    recorder.stop(t + 5)
    return said, said[-1], mirror


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(first_line=st.sampled_from([SECRET + b"\r\n", SECRET + b"\n", SECRET]), mirror_reads=mirror_streams(),
       order=st.lists(st.booleans(), max_size=16))
def test_no_mirror_puts_the_password_anywhere_or_breaks_the_pairing(tmp_path_factory, first_line, mirror_reads,
                                                                    order):
    path = tmp_path_factory.mktemp("mirror") / "m.mcap"
    said, final, _ = _record(path, first_line, mirror_reads, order)
    topics = read_all(str(path))
    assert b"".join(base64.b64decode(m["data"]) for m in topics.get("/mirror/tcp/s2c", [])) == b"".join(mirror_reads)
    differences = topics.get("/mirror/differences", [])
    assert final["final"] and final["total"] == len(differences), (final, differences)
    for topic in MIRROR_TOPICS:
        assert_no_leak(topic, json.dumps(topics.get(topic, [])))
    assert_no_leak("the status lines", json.dumps(said))


def test_the_mirror_topics_are_registered_traffic_topics():
    """The secrets registry (tests/outputs.py) enumerates the mirror's topics with the format's
    others; tests/test_mirror.py::test_the_password_sent_to_both_servers_shows_nowhere reaches them."""
    assert set(MIRROR_TOPICS) <= set(TRAFFIC_TOPICS)


# -- the memory registry of the mirror's buffers ------------------------------------------------------

# class -> attribute -> its bound (bytes or items), as the module constants say
BUFFERS: dict[type, dict[str, int]] = {
    MirrorLeg: {"waiting": MIRROR_BUFFER},  # (and its transport's buffer: MIRROR_BUFFER past which it is dropped)
    MirrorView: {"by_kind": 5, "latest": 5, "events": 4},
    MirrorRecorder: {"offsets": 1 << 16, "cut_off": 1 << 16, "events": 4, "first": 5, "latest": 5},  # per open conn
    MirrorPairing: {"pairs": 1 << 16},  # one per open connection
    MirrorTally: {},
    DiffResult: {"differences": 0, "by_kind": 5},  # counts only
    _Pair: {"seen": MAX_WAITING},
    _Side: {"waiting": MAX_WAITING, "asked": MAX_WAITING, "handshake": MAX_HANDSHAKE},
}
CONTAINERS = (bytes, bytearray, list, deque, dict, set)


def _containers(owner: object) -> list[tuple[str, object]]:
    names = vars(owner) if hasattr(owner, "__dict__") else {n: getattr(owner, n) for n in type(owner).__slots__}
    return [(name, value) for name, value in names.items() if isinstance(value, CONTAINERS)]


def test_every_buffer_of_the_mirror_is_registered_and_bounded(tmp_path):
    """Each container attribute of the mirror's classes is in ``BUFFERS`` (a new one fails
    here until it says how big it gets), within its bound after a lying mirror's run; a
    mirror that never answers does not pile up the primary's requests."""
    mirror_reads = [b"sendchkpass", b"readytogo"] + [b"cr1-12--999--0-ss1"] * 50
    said, _, recorder = _record(tmp_path / "m.mcap", SECRET + b"\r\n", mirror_reads, [True, False] * 40)
    assert said and MIRROR_QUEUE_CAP >= MIRROR_BUFFER
    pairing = MirrorPairing(Limits().session, 5_000_000_000)
    pairing.opened(1)
    pair = pairing.pairs[1]
    owners = [recorder, pairing, pairing.tally, pairing.tally.result, pair, pair.primary, pair.mirror, MirrorView(),
              MirrorLeg(None, 1)]  # its attributes only: no mirror behind it
    for owner in owners:
        for name, value in _containers(owner):
            bound = BUFFERS[type(owner)].get(name)
            assert bound is not None, f"{type(owner).__name__}.{name} is not in BUFFERS"
            assert len(value) <= bound, f"{type(owner).__name__}.{name} holds {len(value)}, past {bound}"
    for _ in range(MAX_WAITING + 100):
        pairing.client(1, b"rr1-12--0--0-ss1", T0)
        pairing.primary(1, b"cr1-12--465--0-ss1", T0)
    for side in (pair.primary, pair.mirror):
        assert len(side.waiting) <= MAX_WAITING and len(side.asked) <= MAX_WAITING + 1
    assert pairing.tally.result.exchanges >= 100


def test_the_mirrors_answers_waiting_behind_a_password_are_bounded(tmp_path, monkeypatch):
    """While the client's first line is undecided everything waits behind it, the mirror's
    answers too; past ``MIRROR_QUEUE_CAP`` its connection is dropped, recorded, and the rest
    of its answers left out (here the cap is 150 bytes, and the mirror sends three 100)."""
    import whiztap.sniffer.record.mirror_record as mirror_record

    monkeypatch.setattr(mirror_record, "MIRROR_QUEUE_CAP", 150)
    path = tmp_path / "m.mcap"
    file = RecordingFile(str(path), metadata_record(source="test", listen="", upstream="", mirror="m:1"))
    recorder = Recorder(file)
    mirror = mirror_recorder(recorder, file, {"mirror": "m:1", "checksum_rule": "dev-sum"}, lambda said: None)
    assert mirror is not None
    recorder.start(T0)
    recorder.receive(Opened(1, T0 + 1, "127.0.0.1:40000", "127.0.0.1:5000"))
    mirror.receive(1, False, T0 + 2, json.dumps({"event": "connected", "detail": ""}).encode())
    recorder.receive(Data(1, C2S, T0 + 3, SECRET))  # undecided: the server has not spoken
    for n in range(3):
        mirror.receive(1, True, T0 + 4 + n, b"x" * 100)
    recorder.receive(Data(1, S2C, T0 + 10, b"sendchkpass"))
    recorder.receive(Closed(1, T0 + 11, "client"))
    mirror.receive(1, False, T0 + 12, json.dumps({"event": "closed", "detail": "closed by the mirror"}).encode())
    mirror.finish(T0 + 13)
    recorder.stop(T0 + 14)
    topics = read_all(str(path))
    assert [len(base64.b64decode(m["data"])) for m in topics["/mirror/tcp/s2c"]] == [100]
    events = topics["/mirror/tcp/events"]
    assert [e["event"] for e in events] == ["connected", "dropped", "closed"], events
    assert "waited to be recorded" in events[1]["detail"] and mirror.waiting == 0 and not mirror.offsets
    assert_no_leak("the mirror's topics", json.dumps(topics))
