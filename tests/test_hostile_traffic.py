"""Bounded work on hostile traffic: requests never answered, answers that match
nothing, SYN floods, and junk bytes cost memory and time in proportion to what
is kept, never to how long the abuse goes on."""

from __future__ import annotations

import asyncio
import json
import random
import struct
import subprocess
import sys
from collections import Counter, deque

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from whiztap.analyzer.protocol import pairing
from whiztap.analyzer.protocol.examples import CONFIG, VPN_OPEN
from whiztap.analyzer.protocol.observations import Direction, LateViolation, Observation
from whiztap.analyzer.protocol.pairing import PENDING_KEPT
from whiztap.analyzer.protocol.session import Session
from whiztap.analyzer.recording.format import TOPIC_EVENTS
from whiztap.analyzer.recording.scan import RecordingScan
from whiztap.analyzer.traffic import Closed, Data, Opened
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.tcpreasm import (
    ACK,
    DLT_EN10MB,
    EVICTED,
    FIN,
    MAX_OPEN,
    SYN,
    Reassembler,
    parse_frame,
)
from whiztap.sniffer.record.writer import RecordingFile
from whiztap.sniffer.sim.tcp_server import TcpServer

from tests.cli_support import WHIZTAP, run_cli
from tests.record_support import (
    LOCAL,
    WAIT,
    RecordProcess,
    both_ways,
    read_all,
    streams,
)
from tests.streams import TINY_JPEG
from tests.test_session import SlowSession, _shape

C, S = Direction.C2S, Direction.S2C


def verdicts(events: list) -> tuple[int, int]:
    """(PW-PAIR-UNANSWERED, PW-PAIR-UNSOLICITED) among the events."""
    unanswered = unsolicited = 0
    for e in events:
        if isinstance(e, LateViolation):
            unanswered += e.violation.rule_id == "PW-PAIR-UNANSWERED"
        else:
            unsolicited += sum(v.rule_id == "PW-PAIR-UNSOLICITED" for v in e.violations)
    return unanswered, unsolicited


# -- requests never answered: memory ------------------------------------------------------

_FEED = """
import json, sys
from whiztap.analyzer.protocol.examples import VPN_OPEN
from whiztap.analyzer.protocol.observations import Direction, LateViolation
from whiztap.analyzer.protocol.session import Session

def peak_kib():
    # this process's own peak (VmHWM): ru_maxrss would count pytest's memory,
    # which Linux carries across the fork and exec that started us
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))

def feed(n, step_ns):
    s = Session(clean_commands=False)
    late = 0
    t = 1
    for d, data in VPN_OPEN:
        s.receive(d, data, t)
        t += 1
    block = 1000
    for _ in range(n // block):
        late += sum(isinstance(e, LateViolation) for e in s.receive(Direction.C2S, b"rr1-3--0--0-ss1" * block, t))
        t += step_ns * block
    late += sum(isinstance(e, LateViolation) for e in s.close(t))
    return late, s.violation_counts["PW-PAIR-UNANSWERED"]

inside = feed(1_200_000, 1)  # all within one answer deadline (5 s)
across = feed(500_000, 100_000)  # 50 s of requests: each deadline passes
print(json.dumps({"inside": inside, "across": across,
                  "maxrss_mb": peak_kib() / 1024}))
"""


@pytest.mark.slow
def test_unanswered_requests_cost_bounded_memory_and_are_each_reported_once():
    """1.2M requests nobody answers within one deadline, and 500k across many:
    every one is reported unanswered exactly once, and the session keeps at most
    PENDING_KEPT of them (it kept them all: 312 MB for 500k, 841 MB for 2.1M;
    kept whole, 1.2M would take about 750 MB, the cap holds it near 160 MB)."""
    out = subprocess.run([sys.executable, "-c", _FEED], capture_output=True, text=True, timeout=300, check=True)
    result = json.loads(out.stdout)
    assert result["inside"] == [1_200_000, 1_200_000]
    assert result["across"] == [500_000, 500_000]
    assert result["maxrss_mb"] < 300


# -- answers that match nothing: work -------------------------------------------------------


class CountingDeque(deque):
    """Counts the entries the pairing books look at: a measure of their work
    that does not depend on the machine."""

    looked = 0

    def __getitem__(self, i):
        CountingDeque.looked += 1
        return super().__getitem__(i)

    def popleft(self):
        CountingDeque.looked += 1
        return super().popleft()

    def __iter__(self):
        for entry in super().__iter__():
            CountingDeque.looked += 1
            yield entry


def _mismatched(n: int, interleaved: bool) -> tuple[tuple[int, int], int]:
    """n Sensor Requests on channel 3 answered on channel 4: (verdicts, work)."""
    CountingDeque.looked = 0
    s = Session(clean_commands=False)
    events = []
    t = 1
    for d, data in VPN_OPEN:
        events += s.receive(d, data, t)
        t += 1
    if interleaved:
        steps = [(C, b"rr1-3--0--0-ss1"), (S, b"cr1-4--7--0-ss1")] * n
    else:
        steps = [(C, b"rr1-3--0--0-ss1")] * n + [(S, b"cr1-4--7--0-ss1")] * n
    for d, data in steps:
        events += s.receive(d, data, t)
        t += 1
    events += s.close(t)
    return verdicts(events), CountingDeque.looked


@pytest.mark.slow
def test_answers_that_match_nothing_cost_linear_work(monkeypatch):
    """Every answer used to scan every waiting request (20,000 such pairs: 15 s)."""
    monkeypatch.setattr(pairing, "deque", CountingDeque)
    n = 20_000
    for interleaved in (False, True):
        found, work = _mismatched(n, interleaved)
        assert found == (n, n)  # each request unanswered, each answer unsolicited
        assert work < 20 * n


def test_pairing_stays_linear_when_a_client_pipelines_before_the_channel_map(monkeypatch):
    """Thousands of ambiguous requests outstanding: each answer must not rescan
    them all (it did, and a 200k-frame pipeline took the recorder hours)."""
    monkeypatch.setattr(pairing, "deque", CountingDeque)
    CountingDeque.looked = 0
    n = 3000
    s = Session()
    requests = b"rr1-24--0--0-ss1" + b"".join(b"rr1-%d--0--0-ss1" % (12 + i % 12) for i in range(n))
    answers = b"sr1-\x18" + b"200" * 24 + b"-ss1" + b"".join(b"cr1-%d--5--0-ss1" % (12 + i % 12) for i in range(n))
    s.receive(C, requests, 1)
    events = s.receive(S, answers, 2)
    assert sum(1 for e in events if getattr(e, "answers", None) is not None) == n + 1
    assert CountingDeque.looked < 20 * n


def test_requests_past_the_cap_are_reported_unanswered_and_still_pair_late():
    s = Session()
    s.awaited.pending_kept = 3
    events = []
    for t, (d, data) in enumerate(VPN_OPEN + [(C, b"rr1-3--0--0-ss1")] * 4 + [(S, b"cr1-3--1--0-ss1")] * 5,
                                  start=1):
        events += s.receive(d, data, t)
    events += s.close(100)
    [dropped] = [e for e in events if isinstance(e, LateViolation)]
    assert dropped.violation.detail == ("Sensor Request: not answered while 3 later requests were waiting "
                                        "(whiztap awaits at most 3 at once)")
    answers = [e for e in events if isinstance(e, Observation) and e.direction is S][1:]
    # the four awaited or given-up requests are answered; the fifth answer is unsolicited
    assert [a.answers is not None for a in answers] == [True] * 4 + [False]
    assert dropped.about in [a.answers for a in answers]
    assert PENDING_KEPT == 250_000  # the documented cap


def test_an_answer_takes_a_request_that_certainly_asked_and_a_late_one_the_oldest():
    """Before the channel map, rr1-1--0--0 may be a Sensor Request; a Servo
    Position Request certainly asked, so it is answered first.  Once both are
    given up, a late answer takes the oldest, certain or not."""
    ambiguous, servo = b"rr1-1--0--0-ss1", b"rr1-1--0--2-ss1"
    s = Session(answer_timeout_ns=1000)
    events = s.receive(C, ambiguous + servo, 1) + s.receive(S, b"cr1-1--40--0-ss1cr1-1--41--0-ss1", 2)
    assert [e.answers.item.raw for e in events if e.direction is S] == [servo, ambiguous]
    s = Session(answer_timeout_ns=1000)
    events = s.receive(C, ambiguous + servo, 1) + s.receive(S, b"cr1-1--40--0-ss1cr1-1--41--0-ss1", 5000)
    assert [e.answers.item.raw for e in events if isinstance(e, Observation) and e.direction is S] == [
        ambiguous, servo]


# -- the indexed books give the verdicts of a plain scan --------------------------------------


class ListBook:
    """The reference: waiting requests in a list, scanned for each answer."""

    def __init__(self) -> None:
        self.order: list = []

    @property
    def live(self) -> int:
        return len(self.order)

    def __iter__(self):
        return iter(list(self.order))

    def add(self, pending) -> None:
        self.order.append(pending)

    def pop_oldest(self):
        return self.order.pop(0)

    def take(self, kind, channel, certain_first):
        maybe = None
        for pending in self.order:
            if pending.answer_kind is kind and (channel is None or pending.channel == channel):
                if pending.certain or not certain_first:
                    self.order.remove(pending)
                    return pending
                maybe = maybe or pending
        if maybe is not None:
            self.order.remove(maybe)
        return maybe

    def clear(self) -> None:
        self.order.clear()


class ReferenceSession(SlowSession):
    """Every item through the general path, with list-scanning books."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.awaited.pending = ListBook()
        self.awaited.expired = ListBook()


# Without a channel map, rr1-N--0--0 may be a Sensor Request (not certain); with
# one, channel 5 is still unknown.  Servo Position Requests are always certain.
REQUESTS = [b"rr1-3--0--0-ss1", b"rr1-2--0--0-ss1", b"rr1-1--0--2-ss1", b"rr1-0--0--2-ss1",
            b"rr1-24--0--0-ss1", b"rr1-29--0--0-ss1", b"rr1-5--0--0-ss1", b"rr1-1--0--0-ss1"]
ANSWERS = [b"cr1-3--7--0-ss1", b"cr1-2--0--0-ss1", b"cr1-1--40--0-ss1", b"cr1-0--9000--0-ss1",
           b"cr1-5--1--0-ss1", b"cr1-x--1--0-ss1", CONFIG, TINY_JPEG]
# gaps: none, short, and past any deadline, so that requests often expire
step = st.tuples(st.booleans(), st.integers(0, len(REQUESTS) - 1), st.sampled_from([0, 400_000, 1_500_000, 9_000_000]))


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(st.lists(step, min_size=8, max_size=60), st.booleans(), st.integers(1, 6), st.integers(1, 6),
       st.integers(1_000_000, 8_000_000), st.sampled_from([0, 2, pairing.REBUILD_SLACK]))
def test_indexed_pairing_gives_the_verdicts_of_a_plain_scan(steps, configured, kept, expired_kept, timeout, slack):
    """Random requests and answers (certain and ambiguous ones, undecodable
    answers that fit any channel, configurations, images) at random times, with
    small caps so that deadlines, the cap, late answers and the books' rebuilds
    all come into play."""
    script = list(VPN_OPEN) if configured else []
    for is_request, i, _ in steps:
        script.append((C, REQUESTS[i]) if is_request else (S, ANSWERS[i]))
    times = [1_000_000 * (k + 1) for k in range(len(script) - len(steps))]
    for _, _, gap in steps:
        times.append((times[-1] if times else 0) + gap)

    def run(session):
        session.awaited.pending_kept, session.awaited.expired_kept = kept, expired_kept
        events = []
        for (d, data), t in zip(script, times):
            events += session.receive(d, data, t)
        events += session.close((times[-1] if times else 0) + 1)
        return session, _shape(events)

    default_slack, pairing.REBUILD_SLACK = pairing.REBUILD_SLACK, slack
    try:
        fast, fast_events = run(Session(answer_timeout_ns=timeout))
    finally:
        pairing.REBUILD_SLACK = default_slack
    reference, reference_events = run(ReferenceSession(answer_timeout_ns=timeout))
    assert fast_events == reference_events
    assert fast.violation_counts == reference.violation_counts
    assert {k: (v.count, v.total) for k, v in fast.latencies.items()} == \
        {k: (v.count, v.total) for k, v in reference.latencies.items()}


# -- SYN floods ------------------------------------------------------------------------------

PSH = 0x08
SERVER = ("10.0.0.9", 5000)
REAL = ("10.0.0.2", 40000)
REAL_C2S, REAL_S2C = b"rr1-24--0--0-ss1", b"sr1-\x01200-ss1"


def _frame(src: tuple[str, int], dst: tuple[str, int], seq: int, ack: int, flags: int, payload: bytes = b"") -> bytes:
    """An Ethernet/IPv4/TCP frame, by hand: Scapy takes a minute for 100k of them."""
    tcp = struct.pack("!HHIIBBHHH", src[1], dst[1], seq & 0xFFFFFFFF, ack, 5 << 4, flags, 65535, 0, 0)
    ip = struct.pack("!BBHHHBBH4s4s", 0x45, 0, 20 + len(tcp) + len(payload), 0, 0, 64, 6, 0,
                     bytes(map(int, src[0].split("."))), bytes(map(int, dst[0].split("."))))
    return b"\x00" * 12 + b"\x08\x00" + ip + tcp + payload


def _flood(syns: int, syn_acks: bool = False) -> list[bytes]:
    """``syns`` SYNs from distinct clients to SERVER, never completed (each
    answered by a SYN-ACK if asked), and one real connection in the middle:
    handshake, a request and its answer, then (after the flood) FINs."""
    ic, is_ = 1000, 9000
    frames = []
    for i in range(syns):
        if i == syns // 2:
            frames += [_frame(REAL, SERVER, ic, 0, SYN), _frame(SERVER, REAL, is_, ic + 1, SYN | ACK),
                       _frame(REAL, SERVER, ic + 1, is_ + 1, ACK),
                       _frame(REAL, SERVER, ic + 1, is_ + 1, PSH | ACK, REAL_C2S),
                       _frame(SERVER, REAL, is_ + 1, ic + 17, PSH | ACK, REAL_S2C)]
        client = (f"10.{1 + i // 60_000}.{i // 250 % 240}.{1 + i % 250}", 1024 + i % 60_000)
        frames.append(_frame(client, SERVER, i * 7919, 0, SYN))
        if syn_acks:
            frames.append(_frame(SERVER, client, i, i * 7919 + 1, SYN | ACK))
    c_end, s_end = ic + 1 + len(REAL_C2S), is_ + 1 + len(REAL_S2C)
    frames += [_frame(REAL, SERVER, c_end, s_end, FIN | ACK), _frame(SERVER, REAL, s_end, c_end + 1, FIN | ACK),
               _frame(REAL, SERVER, c_end + 1, s_end + 1, ACK)]
    return frames


def _write_pcap(path, frames: list[bytes]) -> None:
    with open(path, "wb") as f:
        f.write(struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, DLT_EN10MB))
        for i, frame in enumerate(frames):
            f.write(struct.pack("<IIII", 1_700_000_000 + i // 1_000_000, i % 1_000_000, len(frame), len(frame)))
            f.write(frame)


class CountingRecorder(Recorder):
    """A real recorder that also counts the connections it is told are open."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.open_now = self.most_open = 0

    def receive(self, event) -> None:
        super().receive(event)
        if type(event) is Opened:
            self.open_now += 1
            self.most_open = max(self.most_open, self.open_now)
        elif type(event) is Closed:
            self.open_now -= 1


def _reassemble(path, frames: list[bytes], max_open: int) -> CountingRecorder:
    recorder = CountingRecorder(RecordingFile(str(path), {"source": "pcap"}), keep_secrets=True)
    recorder.start(1)
    reassembler = Reassembler(SERVER[1], recorder, max_open)
    t = 1
    for t, frame in enumerate(frames, start=2):
        reassembler.segment(parse_frame(DLT_EN10MB, frame, t))
    reassembler.finish(t)
    recorder.stop(t)
    return recorder


def _events(path) -> list[dict]:
    with open(path, "rb") as f:
        return [m for _, _, m in RecordingScan(f, (TOPIC_EVENTS,)).messages()]


def _closes(events: list[dict]) -> Counter:
    return Counter(e["detail"] for e in events if e["event"] == "closed")


def test_a_syn_flood_keeps_at_most_max_open_connections_each_closed_on_record(tmp_path):
    """Half-open connections are evicted first, each recorded as closed with a
    reason; their SYN-ACKs do not bring them back; the real connection, which
    carried bytes, is recorded whole."""
    syns, cap = 3000, 100
    recorder = _reassemble(tmp_path / "flood.mcap", _flood(syns, syn_acks=True), cap)
    assert recorder.most_open == cap
    events = _events(tmp_path / "flood.mcap")
    opened = [e for e in events if e["event"] == "opened"]
    assert len(opened) == syns + 1
    assert _closes(events) == {EVICTED: syns + 1 - cap, "the capture ended": cap - 1, "closed": 1}
    [real] = [e["conn"] for e in opened if e["client"] == "{}:{}".format(*REAL)]
    recorded = streams(str(tmp_path / "flood.mcap"))
    assert (recorded[(real, "c2s")], recorded[(real, "s2c")]) == (REAL_C2S, REAL_S2C)


def test_an_evicted_connection_that_sends_again_is_followed_again(tmp_path):
    a, b, c = ("10.0.0.3", 41000), ("10.0.0.4", 41000), ("10.0.0.5", 41000)
    frames = [_frame(a, SERVER, 0, 0, PSH | ACK, b"rr1-24"), _frame(b, SERVER, 0, 0, PSH | ACK, b"rr1-24--0--0-ss1"),
              _frame(c, SERVER, 0, 0, SYN),  # a, idle longest, makes room
              _frame(a, SERVER, 6, 0, PSH | ACK, b"--0--0-ss1"),  # and is back: c, half-open, makes room
              _frame(a, SERVER, 16, 0, ACK)]
    _reassemble(tmp_path / "evict.mcap", frames, max_open=2)
    events = _events(tmp_path / "evict.mcap")
    assert [(e["event"], e["conn"], e.get("detail")) for e in events if e["event"] in ("opened", "closed")] == [
        ("opened", 1, None), ("opened", 2, None), ("closed", 1, EVICTED), ("opened", 3, None),
        ("closed", 3, EVICTED), ("opened", 4, None), ("closed", 2, "the capture ended"),
        ("closed", 4, "the capture ended")]
    recorded = streams(str(tmp_path / "evict.mcap"))
    assert (recorded[(1, "c2s")], recorded[(4, "c2s")]) == (b"rr1-24", b"--0--0-ss1")


_CAPTURE = """
import resource, subprocess, sys
done = subprocess.run(sys.argv[1:], capture_output=True, text=True)
print(done.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss // 1024, repr(done.stderr))
"""


@pytest.mark.slow
def test_capture_of_a_syn_flood_stays_within_bounded_memory(tmp_path):
    """100k half-open connections: ``whiztap capture --pcap`` grew by about
    7 KB each (878 MB for 120k) and kept them all; it now follows at most MAX_OPEN."""
    syns = 100_000
    pcap, out = tmp_path / "flood.pcap", tmp_path / "flood.mcap"
    _write_pcap(pcap, _flood(syns))
    command = [WHIZTAP, "capture", "--pcap", str(pcap), "--port", str(SERVER[1]), "-o", str(out), "-q",
               "--keep-secrets"]
    done = subprocess.run([sys.executable, "-c", _CAPTURE, *command], capture_output=True, text=True,
                          timeout=300, check=True)
    status, maxrss_mb, stderr = done.stdout.split(" ", 2)
    assert (status, stderr.strip()) == ("0", "''")
    assert int(maxrss_mb) < 250
    events = _events(out)
    assert _closes(events) == {EVICTED: syns + 1 - MAX_OPEN, "the capture ended": MAX_OPEN - 1, "closed": 1}
    [real] = [e["conn"] for e in events if e["event"] == "opened" and e["client"] == "{}:{}".format(*REAL)]
    recorded = streams(str(out))
    assert (recorded[(real, "c2s")], recorded[(real, "s2c")]) == (REAL_C2S, REAL_S2C)


# -- junk --------------------------------------------------------------------------------------


class ConfigThenSink(TcpServer):
    """Answers the client's first frame with a configuration (the session is
    VPN: no password to hold back), then takes whatever comes."""

    def __init__(self) -> None:
        super().__init__(LOCAL, 0)

    async def _serve_connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            await reader.readexactly(16)
            writer.write(CONFIG)
            while await reader.read(65536):
                pass
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            writer.close()


@pytest.mark.slow
async def test_a_recording_of_junk_is_about_the_size_of_the_junk(tmp_path):
    """1 MiB of random bytes from a client through ``whiztap record``: the file
    was 4.7 times the traffic (a /frames and a /violations message, with the
    bytes in base64 and as escaped text, for every few dozen bytes).  Now the
    junk is in the file once, in /tcp/reads (whose base64 zstd takes back to
    about 1.0), with a /frames message per read, so the bound is 1.3."""
    out = tmp_path / "junk.mcap"
    junk = random.Random(14).randbytes(1 << 20)
    async with ConfigThenSink() as server:
        rec = await RecordProcess.start(server.port, out)
        reader, writer = await rec.connect()
        writer.write(b"rr1-24--0--0-ss1")
        await asyncio.wait_for(reader.readexactly(len(CONFIG)), WAIT)
        for i in range(0, len(junk), 8192):
            writer.write(junk[i:i + 8192])
            await writer.drain()
        writer.write_eof()
        await asyncio.wait_for(reader.read(), WAIT)
        writer.close()
        code, _, stderr = await rec.finish()
    assert (code, stderr) == (0, "")
    traffic = 16 + len(CONFIG) + len(junk)
    assert out.stat().st_size <= 1.3 * traffic
    assert both_ways(str(out))[(1, "c2s")] == b"rr1-24--0--0-ss1" + junk
    by_topic = read_all(str(out))
    reads, frames = by_topic["/tcp/reads"], by_topic["/frames"]
    assert len(frames) <= len(reads) + 2  # the request, the configuration, and a message per read
    # every break of a rule is counted, as analyze counts them
    recorded = Counter()
    for v in by_topic["/violations"]:
        recorded[v["rule_id"]] += v.get("count", 1)
    analyzed = run_cli("analyze", out, "--format", "json")
    assert recorded == json.loads(analyzed.stdout)["rule_counts"]


@pytest.mark.slow
def test_a_flood_of_line_breaks_is_a_message_per_read(tmp_path):
    """Each line break is an item; 100 in a read were 100 /frames and 100
    /violations messages."""
    path = tmp_path / "breaks.mcap"
    recorder = Recorder(RecordingFile(str(path), {"source": "test"}))
    recorder.start(1)
    recorder.receive(Opened(1, 2, "client", "server"))
    recorder.receive(Data(1, C, 3, b"rr1-24--0--0-ss1"))
    recorder.receive(Data(1, S, 4, CONFIG))
    for t in range(5, 505):
        recorder.receive(Data(1, C, t, b"\n" * 100))
    recorder.receive(Closed(1, 505, "client"))
    summary = recorder.stop(506)
    by_topic = read_all(str(path))
    c2s = [f for f in by_topic["/frames"] if f["dir"] == "c2s"]
    assert len(c2s) == 1 + 500
    assert [(f["kind"], f["items"], f["size"], f["elided"]) for f in c2s[1:]] == [("eol", 100, 100, False)] * 500
    # a /violations message per read, each line break counted
    assert [(v["rule_id"], v["count"]) for v in by_topic["/violations"]] == [("PW-FRAME-EOL", 100)] * 500
    assert summary.violations["info"] == 500 * 100
    assert both_ways(str(path))[(1, "c2s")] == b"rr1-24--0--0-ss1" + b"\n" * 50_000


@pytest.mark.slow
def test_a_client_pipelining_200k_requests_ahead_of_their_answers_breaks_no_rule():
    """A cap of 10,000 waiting requests gave up 190,000 requests of the pipelined
    benchmark (200k Sensor Requests sent before the first answer arrived):
    90,000 reported unanswered and 88,976 answers unsolicited, on traffic that
    breaks no rule.  The cap must sit above what a real client pipelines."""
    s = Session(clean_commands=False)
    t = 1
    for d, data in VPN_OPEN:
        s.receive(d, data, t)
        t += 1
    n = 200_000
    events = list(s.receive(Direction.C2S, b"rr1-3--0--0-ss1" * n, t))
    events += s.receive(Direction.S2C, b"cr1-3--7--0-ss1" * n, t + 1_000_000)
    events += s.close(t + 2_000_000)
    assert sum(len(getattr(e, "violations", ())) for e in events if isinstance(e, Observation)) == 0
    assert not [e for e in events if isinstance(e, LateViolation)]
