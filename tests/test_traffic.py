"""Traffic events: one shape, their /tcp/events messages, and one session per connection."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from whiztap.analyzer import traffic as t
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.session import Limits

C2S, S2C = Direction.C2S, Direction.S2C
ints = st.integers(min_value=0, max_value=2**63)
text = st.text(max_size=20)
directions = st.sampled_from([C2S, S2C])


def maybe(s):
    return st.none() | s


events = st.one_of(
    st.builds(t.RecordingStarted, ints, text),
    st.builds(t.Opened, ints, ints, text, text),
    st.builds(t.Continued, ints, ints, text, text, ints, ints, text),
    st.builds(t.UpstreamConnected, ints, ints, text),
    st.builds(t.UpstreamFailed, ints, ints, text),
    st.builds(t.HalfClosed, ints, ints, directions),
    st.builds(t.Gap, ints, ints, directions, maybe(ints), maybe(ints), text),
    st.builds(t.Closed, ints, ints, text, text, maybe(ints), maybe(ints), maybe(text), maybe(text)),
    st.builds(t.RecordingStopped, ints, text, text),
)


@given(events)
def test_every_event_survives_its_json_message(event):
    assert t.from_json(t.to_json(event)) == event


def test_the_messages_keep_the_recording_format():
    """Byte compatibility: the names and fields recordings have always carried."""
    assert list(t.NAMES.values()) == ["recording_started", "opened", "upstream_connected", "upstream_failed",
                                      "half_closed", "closed", "gap", "continued", "recording_stopped"]
    assert t.to_json(t.HalfClosed(3, 10, S2C)) == {"conn": 3, "event": "half_closed", "t_ns": 10,
                                                   "by": "server", "dir": "s2c"}
    assert t.to_json(t.Opened(1, 5, "127.0.0.1:4000", "127.0.0.1:5000")) == {
        "conn": 1, "event": "opened", "t_ns": 5, "client": "127.0.0.1:4000", "upstream": "127.0.0.1:5000"}
    assert t.to_json(t.Gap(2, 7, C2S, 12, 100, "why")) == {"conn": 2, "event": "gap", "t_ns": 7, "dir": "c2s",
                                                           "length": 12, "offset": 100, "detail": "why"}


def test_a_newer_writers_extra_fields_are_left_out():
    assert t.from_json({"conn": 1, "event": "opened", "t_ns": 2, "client": "a", "colour": "red"}) == t.Opened(1, 2, "a")


@pytest.mark.parametrize("message", [
    {"conn": 1, "event": "exploded", "t_ns": 2},
    {"conn": 1, "t_ns": 2},
    {"conn": 1, "event": "half_closed", "t_ns": 2},
    {"conn": 1, "event": "half_closed", "t_ns": 2, "dir": "sideways"},
    {"event": "closed", "t_ns": 2},
])
def test_a_message_that_is_no_event_is_a_traffic_error(message):
    with pytest.raises(t.TrafficError):
        t.from_json(message)


def observations(events):
    return [e for e in events if isinstance(e, Observation)]


def test_one_session_per_connection_and_each_ends_once():
    ended = []
    traffic = t.Traffic(Limits().session, lambda conn, session: ended.append(conn))
    assert observations(traffic.receive(t.Data(1, C2S, 1, b"rr1-12--0--0-ss1")))
    assert observations(traffic.receive(t.Data(2, C2S, 2, b"rr1-13--0--0-ss1")))
    assert set(traffic.sessions) == {1, 2}
    traffic.receive(t.Closed(1, 3, "client"))
    assert ended == [1] and set(traffic.sessions) == {2}
    traffic.receive(t.Closed(1, 4, "client"))  # a second close of nothing is nothing
    assert ended == [1]
    assert [conn for conn, _ in traffic.finish()] == [2]
    assert ended == [1, 2] and not traffic.sessions


def test_a_gap_judges_each_side_on_its_own():
    traffic = t.Traffic(Limits().session)
    traffic.receive(t.Data(1, C2S, 1, b"rr1-12--0"))
    first = traffic.sessions[1]
    assert observations(traffic.receive(t.Gap(1, 2, C2S, 5))), "the frame cut by the gap is judged at it"
    assert 1 not in traffic.sessions
    assert observations(traffic.receive(t.Data(1, C2S, 3, b"rr1-12--0--0-ss1")))
    assert traffic.sessions[1] is not first


def test_a_half_close_and_an_unreachable_server_reach_the_session():
    traffic = t.Traffic(Limits().session)
    traffic.receive(t.Data(1, C2S, 1, b"rr1-24--0--0-ss1"))  # Fetch Configuration Settings
    traffic.receive(t.UpstreamFailed(1, 2, "connection refused"))
    assert traffic.receive(t.HalfClosed(1, 3, C2S)) == []
    late = traffic.receive(t.Closed(1, 4, "server"))
    assert [(e.violation.rule_id, e.violation.detail) for e in late] == [
        ("PW-PAIR-UNANSWERED", "Fetch Configuration Settings: the server was never reached (connection refused)")]
