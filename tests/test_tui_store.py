"""The TUI's data, without a screen: the compact frame store, the model and the filter index."""

import threading
from pathlib import Path

import pytest

from whiztap.analyzer.analysis.analyzer import Analyzer
from whiztap.analyzer.protocol.describe import fields, meaning
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.analysis.item_filter import ItemFilter
from whiztap.analyzer.recording.format import TOPIC_EVENTS, TOPIC_READS
from whiztap.analyzer.recording.scan import RecordingScan
from whiztap.analyzer.protocol.observations import Direction, LateViolation, Observation
from whiztap.tui.data.model import TrafficModel
from whiztap.tui.data.sources import FileSource
from whiztap.tui.data.store import FrameStore
from whiztap.analyzer.analysis.item_filter import FilterSyntaxError, parse_filter
from whiztap.tui.data.view import FrameView, with_connection

SAMPLES = Path(__file__).parent.parent / "samples"
ALL_SAMPLES = sorted(SAMPLES.glob("*.mcap"))


def analysed(path):
    """Every (conn, event) of a recording, as ``whiztap cat`` sees them."""
    analyzer = Analyzer(str(path))
    out = []
    with open(path, "rb") as f:
        for event in RecordingScan(f, (TOPIC_READS, TOPIC_EVENTS)).traffic():
            out += [(event.conn, e) for e in analyzer.receive(event)]
    for conn, events in analyzer.close_all():
        out += [(conn, e) for e in events]
    return out


def loaded(path, raw_cap: int | None = None) -> TrafficModel:
    model = TrafficModel(str(path))
    if raw_cap is not None:
        model.store.raw_cap = raw_cap
    FileSource(str(path)).feed(model, threading.Event())
    return model


@pytest.mark.parametrize("path", ALL_SAMPLES, ids=lambda p: p.name)
def test_every_frame_comes_back_as_the_session_observed_it(path):
    """The store keeps no objects, only bytes and a few facts; what it rebuilds
    for the screen must be what the session model said when the frame arrived."""
    events = analysed(path)
    observations = [(c, e) for c, e in events if isinstance(e, Observation)]
    late = {}
    for c, e in events:
        if isinstance(e, LateViolation):
            late.setdefault((c, e.about.index), []).append(e.violation)
    store = loaded(path).store
    assert store.count == len(observations)
    for n, (conn, obs) in enumerate(observations):
        got = store.observation(n)
        assert store.conn[n] == conn
        assert got.item._replace(raw=b"") == obs.item._replace(raw=b"")
        assert got.item.raw == obs.item.raw[:store.raw_cap] and store.size(n) == len(obs.item.raw)
        assert got.direction is obs.direction and got.index == obs.index
        if len(obs.item.raw) <= store.raw_cap:
            assert got.message == obs.message and got.candidates == obs.candidates
        assert got.violations == obs.violations + tuple(late.get((conn, obs.index), ()))
        assert store.meaning(n) == meaning(obs) and store.fields(n) == fields(obs)
        assert got.latency_ns == obs.latency_ns
        assert (got.answers is None) == (obs.answers is None)
        if obs.answers is not None:
            assert got.answers.item == obs.answers.item


def test_violations_are_indexed_in_order_with_their_severity():
    store = loaded(SAMPLES / "violations.mcap").store
    with_violations = [n for n in range(store.count) if store.observation(n).violations]
    assert store.violating == with_violations
    for n in with_violations:
        assert store.severity(n) == max(v.severity for v in store.observation(n).violations)
    assert store.next_violation(-1) == with_violations[0]
    assert list(store.violations_from(with_violations[3], -1)) == with_violations[3::-1]
    assert list(store.violations_from(with_violations[3], 1)) == with_violations[3:]


def test_requests_and_responses_point_at_each_other():
    store = loaded(SAMPLES / "clean-winsock.mcap").store
    pairs = [(n, store.pair[n]) for n in range(store.count) if store.pair[n] >= 0]
    assert pairs
    for n, other in pairs:
        assert store.pair[other] == n
        request, response = sorted((n, other))
        assert store.direction(request) is Direction.C2S and store.direction(response) is Direction.S2C
        assert store.observation(response).latency_ns == store.t_end[response] - store.t_end[request]


def test_a_camera_image_keeps_its_head_its_size_and_its_meaning():
    store = loaded(SAMPLES / "clean-winsock.mcap", raw_cap=1024).store
    [image] = [n for n in range(store.count) if store.kind(n) is ItemKind.IMAGE]
    assert store.size(image) > store.raw_cap == len(store.raw(image))
    assert store.meaning(image).startswith("Camera image (jpeg, ")
    assert store.fields(image)["data"] == store.size(image)


def test_live_passwords_are_masked_in_the_store():
    store = FrameStore(redact_passwords=True)
    from whiztap.analyzer.protocol.session import Session

    session = Session()
    events = session.receive(Direction.S2C, b"sendchkpass", 1)
    events += session.receive(Direction.C2S, b"secret", 2)
    events += session.receive(Direction.S2C, b"readytogo", 3)
    store.add(1, events)
    passwords = [n for n in range(store.count) if store.kind(n) is ItemKind.PASSWORD]
    assert passwords and all(store.raw(n) == b"******" for n in passwords)
    assert b"secret" not in store.raws


def test_memory_per_frame_is_small():
    model = loaded(SAMPLES / "vpn.mcap")
    store = model.store
    assert store.nbytes() / store.count < 100


def test_connections_summarise_each_session():
    rows = loaded(SAMPLES / "failed-password.mcap").connections()
    assert [(r.conn, r.mode, r.handshake) for r in rows] == [(1, "winsock", "failed validation")]
    assert rows[0].state.startswith("closed by")
    model = loaded(SAMPLES / "vpn.mcap")
    assert set(model.latencies()) == {"Fetch Configuration Settings", "Sensor Request", "Servo Position Request"}
    assert {key[0] for key in model.channel_values()} == {"sensor", "servo"}


# -- the filter --------------------------------------------------------------------------------


def test_filter_words_become_the_cat_filter():
    f = parse_filter("conn:1,3 dir:s2c kind:response,config ch:12 since:0.5 until:2 violations Servo")
    assert f == ItemFilter(conns=frozenset({1, 3}), direction="s2c",
                           kinds=frozenset({ItemKind.RESPONSE, ItemKind.CONFIG}), channels=frozenset({12}),
                           since_s=0.5, until_s=2.0, violations_only=True, text="Servo")
    assert parse_filter("") == ItemFilter()
    assert parse_filter("!").violations_only
    assert with_connection(parse_filter("kind:command"), 4).conns == frozenset({4})


@pytest.mark.parametrize("text, says", [
    ("dir:up", "c2s or s2c"), ("kind:frame", "'frame' is not one of"), ("conn:x", "numbers"),
    ("since:soon", "seconds"), ('"open', "quotation"),
])
def test_bad_filter_words_say_what_is_wrong(text, says):
    with pytest.raises(FilterSyntaxError, match=says):
        parse_filter(text)


@pytest.mark.parametrize("text", ["kind:response", "conn:3", "violations", "dir:c2s ch:0", "Fetch",
                                  "since:0.01 until:0.05"])
def test_a_filtered_view_holds_exactly_what_cat_would_print(text):
    path = SAMPLES / "violations.mcap"
    model = loaded(path)
    store = model.store
    item_filter = parse_filter(text)
    view = FrameView(store, item_filter)
    view.judge()
    assert view.complete
    expected = [n for n in range(store.count)
                if item_filter.accepts(store.conn[n], store.observation(n), store.start_ns)]
    assert list(view.rows) == expected and expected
    assert view.row_of(expected[-1]) == len(expected) - 1


def test_a_late_violation_lets_a_judged_frame_into_a_violations_view():
    from whiztap.analyzer.protocol.session import Session

    session = Session()
    store = FrameStore()
    store.add(1, session.receive(Direction.C2S, b"rr1-24--0--0-ss1", 1_000))
    view = FrameView(store, parse_filter("violations"))
    view.judge()
    assert len(view) == 0
    store.add(1, session.close(2_000))  # never answered
    view.judge()
    assert list(view.rows) == [0]


def test_the_detail_of_a_camera_image_shows_its_size_not_sensor_ranges():
    from rich.console import Console

    from whiztap.analyzer.protocol.session import Session
    from tests.streams import TINY_JPEG
    from whiztap.tui.widgets.detail import describe_frame

    session = Session()
    store = FrameStore()
    store.add(1, session.receive(Direction.C2S, b"rr1-24--0--0-ss1rr1-29--0--0-ss1", 1))
    store.add(1, session.receive(Direction.S2C, b"sr1-\x01200-ss1" + TINY_JPEG, 2))
    console = Console(width=200, record=True, file=open("/dev/null", "w"))
    console.print(describe_frame(store, store.count - 1))
    text = console.export_text()
    assert "Camera Image" in text and f"{len(TINY_JPEG)} bytes" in text
    assert "sensor" not in text.lower() and "servo" not in text.lower()
