"""The two views of a connection in the middle begin only when it goes out of
step (analyzer/analysis/sides.py): until the first intervention, or the first
delivery that is not the read as it was, the one session judges it for both
sides.  What a report says must be what it said when the views were fed from
each connection's first event (``Sides(lazy=False)``, kept for these tests)."""

from __future__ import annotations

import asyncio
import functools
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.replay_support import until_closed
from tests.record_support import LOCAL
from tests.streams import stream_pieces
from whiztap.analyzer.analysis import analyzer as analyzer_module
from whiztap.analyzer.analysis import sides as sides_module
from whiztap.analyzer.analysis.analyzer import Analyzer
from whiztap.analyzer.analysis.report.content import build
from whiztap.analyzer.analysis.instep import HELD_MAX
from whiztap.analyzer.analysis.sides import Sides
from whiztap.analyzer.analysis.verdict import Judge
from whiztap.analyzer.cli.analyze import analyse_file
from whiztap.analyzer.mitm.spec import parse_fault
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.codec import encode
from whiztap.analyzer.protocol.examples import CONFIG, WINSOCK_OPEN
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.session import Limits, Session
from whiztap.analyzer.traffic import (
    Action,
    Cause,
    Closed,
    Data,
    Delivered,
    Gap,
    HalfClosed,
    Intervention,
    Opened,
    Source,
    TrafficEvent,
)
from whiztap.sniffer.record.record_run import MiddleSettings, Recording, RecordSettings
from whiztap.sniffer.sim.client import Client, ResponseTimeout
from whiztap.sniffer.sim.simulator import Simulator

C2S, S2C = Direction.C2S, Direction.S2C
T0 = 1_700_000_000_000_000_000
MS = 1_000_000
LIMITS = Limits(answer_timeout_ns=200 * MS)
FAULT = Cause(Source.FAULT, "fault-1", "drop dir:s2c")
REQUEST, ANSWER = encode(m.SensorRequest(3)), encode(m.ChannelResponse(3, 500))


def _analyzer(lazy: bool = True, limits: Limits = LIMITS) -> Analyzer:
    """A middle analyzer; ``lazy=False``: with the views fed from every connection's first event."""
    with pytest.MonkeyPatch.context() as patch:
        if not lazy:
            patch.setattr(analyzer_module, "Sides", functools.partial(Sides, lazy=False))
        return Analyzer("f", limits=limits, every_event=False, middle=True)


def _report(events: list[TrafficEvent], lazy: bool = True, limits: Limits = LIMITS) -> dict:
    """The report, and the plots' facts (frames by second, values) beside it."""
    analyzer = _analyzer(lazy, limits)
    for event in events:
        analyzer.receive(event)
    analysis = analyzer.finish()
    plots = {"frames_per_second": {s: dict(n) for s, n in analysis.frames_per_second.items() if +n},
             "values": {key: list(series.points) for key, series in analysis.values.items()}}
    return build(analysis) | {"plots": plots}


@pytest.fixture
def feeds(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """How many times any session is handed bytes, from now on (a one-item list)."""
    count = [0]
    receive = Session.receive

    def counted(self: Session, direction: Direction, data: bytes, t_ns: int) -> list:
        count[0] += 1
        return receive(self, direction, data, t_ns)

    monkeypatch.setattr(Session, "receive", counted)
    return count


def _in_step(conn: int, steps: list[tuple[Direction, bytes]], t: int) -> list[TrafficEvent]:
    """Each read, and its delivery as it was, at once (the proxy in the middle changing nothing)."""
    events: list[TrafficEvent] = []
    for direction, data in steps:
        t += MS
        events += [Data(conn, direction, t, data), Delivered(conn, direction, t, data)]
    return events


def _pairs(n: int) -> list[tuple[Direction, bytes]]:
    """The configuration asked and given, then ``n`` Sensor Requests answered."""
    return [(C2S, b"rr1-24--0--0-ss1"), (S2C, CONFIG)] + [step for _ in range(n) for step in
                                                            ((C2S, REQUEST), (S2C, ANSWER))]


def _reads(events: list[TrafficEvent]) -> int:
    return sum(type(e) is Data for e in events)


# -- a connection in step costs one session -------------------------------------------------------------


LOGIN_AND_PAIRS = WINSOCK_OPEN + _pairs(20)[2:] + [(C2S, b"rr1-3-- 5--0-ss1")]  # and a client's violation


def test_a_connection_never_out_of_step_is_fed_to_one_session_only(feeds):
    events = [Opened(1, T0), *_in_step(1, LOGIN_AND_PAIRS, T0), Closed(1, T0 + 100 * MS, "client")]
    report = _report(events)
    assert feeds[0] == _reads(events)  # the analyzer's own session, each read once: no view was fed
    assert "PW-SYNTAX-SPACE" in report["rule_counts"] and {v["side"] for v in report["violations"]} == {"client"}
    assert report["client_latency"] == report["latency"] and report["latency"]
    assert report == _report(events, lazy=False)


def test_views_begin_at_the_first_intervention_and_are_fed_from_there(feeds):
    t = T0 + 50 * MS
    dropped = [Data(1, C2S, t, REQUEST), Delivered(1, C2S, t, REQUEST), Data(1, S2C, t + MS, ANSWER),
               Intervention(1, t + MS, S2C, Action.DROP, FAULT, ANSWER, b"", "response", index=11)]
    after = _pairs(3)[2:]
    events = [Opened(1, T0), *_in_step(1, _pairs(10), T0), *dropped, *_in_step(1, after, t + 2 * MS),
              Closed(1, t + 20 * MS, "client")]
    report = _report(events)
    # before the drop, one session; the answer it dropped also in the server's view, each read after in both
    assert feeds[0] == _reads(events) + 1 + 2 * len(after)
    [unanswered] = report["violations"]
    assert (unanswered["rule_id"], unanswered["side"]) == ("PW-PAIR-UNANSWERED", "client")
    assert "the client's experience only" in unanswered["detail"]
    assert report == _report(events, lazy=False)


@pytest.mark.parametrize("case", ["later", "other bytes", "joined", "undelivered", "never", "too much"])
def test_a_delivery_out_of_step_begins_the_views_too(feeds, case):
    """Another time, other bytes, one delivery for two reads, a read left
    undelivered while the other side speaks or to the end, too much held:
    each begins the views; a read delivered in pieces at once does not."""
    t = T0 + 50 * MS
    middle = {
        "later": [Data(1, C2S, t, REQUEST), Delivered(1, C2S, t + 1, REQUEST)],
        "other bytes": [Data(1, C2S, t, REQUEST), Delivered(1, C2S, t, REQUEST[:-1] + b"2")],
        "joined": [Data(1, C2S, t, REQUEST[:5]), Data(1, C2S, t, REQUEST[5:]), Delivered(1, C2S, t, REQUEST)],
        "undelivered": [Data(1, C2S, t, REQUEST), Data(1, S2C, t + 1, ANSWER), Delivered(1, C2S, t + 2, REQUEST)],
        "never": [Data(1, C2S, t, REQUEST)],
        "too much": [Data(1, S2C, t, b"\xff\xd8" + b"\x00" * HELD_MAX)],
    }[case]
    pieces = [Data(1, C2S, t - MS, REQUEST), *(Delivered(1, C2S, t - MS, REQUEST[i:i + 4]) for i in range(0, 16, 4)),
              Data(1, S2C, t - MS // 2, ANSWER), Delivered(1, S2C, t - MS // 2, ANSWER)]
    before = [Opened(1, T0), *_in_step(1, _pairs(5), T0), *pieces]
    end = [] if case == "never" else [*_in_step(1, _pairs(2)[2:], t + 10 * MS), Closed(1, t + 20 * MS, "client")]
    _report(before)
    assert feeds[0] == _reads(before)
    feeds[0] = 0
    report = _report(before + middle + end)
    assert feeds[0] > _reads(before + middle + end)
    assert report == _report(before + middle + end, lazy=False)


def test_a_live_verdict_on_a_connection_in_step_and_both_latencies():
    """Judge.verdict() and latencies() while the connection is open: in step,
    the one session's violations and latencies are both sides'."""
    judges = {lazy: Judge(limits=LIMITS, middle=True) for lazy in (True, False)}
    judges[False].analyzer = _analyzer(lazy=False)
    events = [Opened(1, T0), *_in_step(1, LOGIN_AND_PAIRS, T0), Data(1, C2S, T0 + 99 * MS, REQUEST)]
    for judge in judges.values():
        for event in events:
            judge.receive(event)
    verdicts = {lazy: judge.verdict() for lazy, judge in judges.items()}
    assert verdicts[True] == verdicts[False] and "PW-SYNTAX-SPACE" in verdicts[True].by_rule
    counts = {lazy: [{title: s.count for title, s in side.items()} for side in judge.latencies()]
              for lazy, judge in judges.items()}
    server, client = counts[True]
    assert server == client == {"Fetch Configuration Settings": 1, "Sensor Request": 20}
    assert counts[True] == counts[False]
    for judge in judges.values():
        judge.receive(Intervention(1, T0 + 100 * MS, S2C, Action.INJECT, Cause(Source.INJECTION), b"", ANSWER))
        judge.receive(Delivered(1, S2C, T0 + 100 * MS, ANSWER))
    assert judges[True].verdict() == judges[False].verdict()
    assert judges[True].finish() == judges[False].finish()


def test_a_view_begun_as_a_copy_goes_its_own_way():
    """The copy the views begin with shares nothing that changes: answers it
    takes leave the one session's awaited requests where they were."""
    session = LIMITS.session()
    for direction, data in _pairs(3) + [(C2S, REQUEST * 5)]:
        session.receive(direction, data, T0)
    copy = sides_module._copy(session)
    assert len(copy.awaited.pending) == len(session.awaited.pending) == 5
    copy.receive(S2C, ANSWER * 5, T0 + MS)
    assert (len(copy.awaited.pending), len(session.awaited.pending)) == (0, 5)
    assert copy.latencies["Sensor Request"].count == 8 and session.latencies["Sensor Request"].count == 3


# -- drawn traffic: the same report either way ---------------------------------------------------------

_WAYS = ["now"] * 6 + ["pieces", "later", "part", "changed", "dropped", "lost"]
_CALM = ["now"] * 40 + ["pieces"] * 4 + _WAYS[7:]  # mostly in step, for a while at least


@st.composite
def _middle_traffic(draw) -> list[TrafficEvent]:  # one drawing, step by step
    """One or two connections, interleaved: reads both ways (protocol pieces and
    junk), each delivered at once, in pieces, later (or part of it), changed,
    dropped or not at all; injections; half-closes and a gap."""
    per_conn: dict[int, list[tuple]] = {}
    ways = draw(st.sampled_from([_WAYS, _CALM]))
    for conn in range(1, draw(st.integers(1, 2)) + 1):
        ops: list[tuple] = []
        for d in (C2S, S2C):
            data = b"".join(draw(stream_pieces()))
            cuts = sorted(draw(st.lists(st.integers(0, max(len(data), 1)), max_size=5)))
            ops += [("data", d, data[a:b], draw(st.sampled_from(ways)))
                    for a, b in zip([0, *cuts], [*cuts, len(data)]) if b > a]
            if draw(st.booleans()):
                ops.append(("half", d, b"", ""))
        if draw(st.booleans()):
            ops.append(("inject", draw(st.sampled_from([C2S, S2C])), draw(st.sampled_from([REQUEST, ANSWER])), ""))
        if draw(st.integers(0, 3)) == 0:
            ops.append(("gap", draw(st.sampled_from([C2S, S2C])), b"", ""))
        by_dir = {d: [op for op in ops if op[1] is d] for d in (C2S, S2C)}
        per_conn[conn] = [by_dir[d].pop(0) for d in draw(st.permutations([op[1] for op in ops]))]
    events: list[TrafficEvent] = []
    later: list[tuple[int, Direction, bytes]] = []  # delivered after the next step
    t = T0
    for conn in per_conn:
        events.append(Opened(conn, t))
    order = draw(st.permutations([conn for conn, ops in per_conn.items() for _ in ops]))
    for conn in order:
        op, d, data, way = per_conn[conn].pop(0)
        t += draw(st.sampled_from([MS, 300 * MS, 1_000 * MS]))
        if op == "data":
            events.append(Data(conn, d, t, data))
        elif op == "half":
            events.append(HalfClosed(conn, t, d))
        elif op == "gap":
            events.append(Gap(conn, t, d, 3))
        else:
            events += [Intervention(conn, t, d, Action.INJECT, Cause(Source.INJECTION), b"", data),
                       Delivered(conn, d, t, data)]
        events += [Delivered(late, d_late, t, data_late) for late, d_late, data_late in later]
        later = []
        if way == "now":
            events.append(Delivered(conn, d, t, data))
        elif way == "pieces":
            cut = draw(st.integers(0, len(data)))
            events += [Delivered(conn, d, t, data[:cut]), Delivered(conn, d, t, data[cut:])]
        elif way == "later":
            later.append((conn, d, data))
        elif way == "part":  # the rest later
            cut = draw(st.integers(1, max(len(data) - 1, 1)))
            events.append(Delivered(conn, d, t, data[:cut]))
            later.append((conn, d, data[cut:]))
        elif way == "changed":
            after = draw(st.sampled_from([REQUEST, ANSWER, b"junk", data[::-1]]))
            events += [Intervention(conn, t, d, Action.CORRUPT, FAULT, data, after), Delivered(conn, d, t, after)]
        elif way == "dropped":
            events.append(Intervention(conn, t, d, Action.DROP, FAULT, data, b""))
    events += [Delivered(conn, d, t, data) for conn, d, data in later]
    if draw(st.booleans()):  # else the recording was cut short
        events += [Closed(conn, t + MS, "client") for conn in per_conn]
    return events


@pytest.mark.slow
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(events=_middle_traffic())
def test_the_report_is_the_one_the_views_always_fed_give(events):
    limits = Limits(answer_timeout_ns=500 * MS)  # deadlines pass within the drawn traffic
    assert _report(events, limits=limits) == _report(events, lazy=False, limits=limits)


# -- a recording made through the real proxy ------------------------------------------------------------


def _record(path: Path, judges: tuple[Judge, ...]) -> Path:
    """Two clients through the proxy in the middle, in front of the simulator
    (winsock, so each logs in first): the first has clean traffic, a frame
    the server refuses, then an answer dropped and one injected; the second
    a frame of its own that breaks a rule, and nothing the proxy changes."""
    async def run() -> None:
        async with Simulator(port=0, mode="winsock", password="secret", seed=7) as sim:
            middle = MiddleSettings(faults=(parse_fault("drop dir:s2c kind:response ch:12 nth:3"),))
            rec = Recording(RecordSettings((LOCAL, 0), (LOCAL, sim.port), str(path), middle=middle),
                            consumers=judges)
            await rec.start()
            try:
                async with await Client.connect(LOCAL, rec.proxy.port, password="secret", timeout=0.5) as one, \
                        await Client.connect(LOCAL, rec.proxy.port, password="secret", timeout=0.5) as two:
                    for client in (one, two):
                        await client.fetch_configuration()
                    await one.send_raw(b"rr1-99--0--0-ss1")
                    await two.send_raw(b"rr1-13-- 0--0-ss1")
                    for _ in range(4):
                        for client, channel in ((one, 12), (two, 13)):
                            try:
                                await client.sensor(channel)
                            except ResponseTimeout:
                                pass  # the proxy dropped its answer
                    rec.controller.inject(1, "s2c", "cr1-12--5--0-ss1")
                    await asyncio.sleep(0.05)
                    await two.sensor(13)
                await until_closed(sim)  # the simulator has seen its clients go
            finally:
                await rec.stop()
    asyncio.run(run())
    return path


@pytest.mark.slow
def test_a_recording_made_in_the_middle_reads_as_it_did_with_the_views_always_fed(tmp_path, monkeypatch):
    limits = Limits(answer_timeout_ns=200 * MS)
    judges = {lazy: Judge(limits=limits, middle=True) for lazy in (True, False)}
    judges[False].analyzer = _analyzer(lazy=False, limits=limits)
    path = _record(tmp_path / "middle.mcap", tuple(judges.values()))
    out_of_step: list[int] = []
    diverge = Sides._diverge

    def spied(self: Sides, conn: int, c: object) -> list:
        out_of_step.append(conn)
        return diverge(self, conn, c)

    monkeypatch.setattr(sides_module.Sides, "_diverge", spied)
    lazy = build(analyse_file(path, "dev-sum", limits))
    assert out_of_step == [1]  # the second client's connection was never out of step
    monkeypatch.setattr(analyzer_module, "Sides", functools.partial(Sides, lazy=False))
    eager = build(analyse_file(path, "dev-sum", limits))
    assert lazy == eager
    by_conn = {(v["conn"], v["rule_id"], v["side"]) for v in lazy["violations"]}
    assert by_conn == {(1, "PW-RANGE-CHANNEL", "client"), (1, "PW-CHANNEL-UNCONFIGURED", "client"),
                       (1, "PW-PAIR-UNANSWERED", "client"), (2, "PW-SYNTAX-SPACE", "client"),
                       (2, "PW-PAIR-UNANSWERED", "server")}  # the simulator does not answer a frame it cannot read
    assert lazy["latency"] and lazy["client_latency"] and lazy["latency"] != lazy["client_latency"]
    assert [c.get("interventions") for c in lazy["connections"]] == [2, 0]
    live = {lazy: judge.finish() for lazy, judge in judges.items()}
    assert live[True] == live[False] and live[True].by_rule == lazy["rule_counts"]
