"""The session model: handshake, channel map, pairing, and every rule firing."""

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.channels import unit_of
from whiztap.analyzer.protocol.codec import encode
from whiztap.analyzer.protocol.examples import CONFIG, SCENARIOS, VPN_OPEN, WINSOCK_OPEN
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.handshake import HandshakeState, Mode
from whiztap.analyzer.protocol.observations import Direction, LateViolation, Observation
from whiztap.analyzer.protocol.rules import RULES
from whiztap.analyzer.protocol.session import Session
from tests.streams import TINY_JPEG, chunked

C, S = Direction.C2S, Direction.S2C


def run(script, session=None, close=True, step_ns=1_000_000):
    session = session or Session()
    events = []
    for t, (direction, data) in enumerate(script, start=1):
        events += session.receive(direction, data, t * step_ns)
    if close:
        events += session.close((len(script) + 1) * step_ns)
    return session, events


def observations(events):
    return [e for e in events if isinstance(e, Observation)]


def fired(events):
    rules = []
    for e in events:
        rules += [e.violation.rule_id] if isinstance(e, LateViolation) else [v.rule_id for v in e.violations]
    return rules


def test_clean_winsock_session():
    session, events = run(WINSOCK_OPEN + [(C, b"rr1-3--0--0-ss1"), (S, b"cr1-3--512--0-ss1")])
    assert fired(events) == []
    assert session.mode is Mode.WINSOCK and session.state is HandshakeState.READY
    assert session.handshake_outcome == "readytogo"
    obs = observations(events)
    assert [o.item.kind for o in obs] == ["handshake", "eol", "password", "eol", "handshake", "eol",
                                          "command", "config", "command", "response"]
    assert obs[2].message == m.Password(b"secret")
    assert obs[8].message == m.SensorRequest(3)
    assert obs[9].answers is obs[8] and obs[9].latency_ns == 1_000_000
    assert {title: (s.count, s.max) for title, s in session.latencies.items()} == {
        "Fetch Configuration Settings": (1, 1_000_000), "Sensor Request": (1, 1_000_000)}


def test_clean_vpn_session():
    session, events = run(VPN_OPEN + [(C, b"rr1-0--0--2-ss1"), (S, b"cr1-0--4000--0-ss1")])
    assert fired(events) == []
    assert session.mode is Mode.VPN
    assert session.channel_map[2] == m.ChannelConfig(1, 0, 1)


def test_password_split_over_writes_is_one_item():
    _, events = run([(S, b"sendchkpass"), (C, b"se"), (C, b"cr"), (C, b"et"), (S, b"readytogo")])
    [password] = [o for o in observations(events) if o.item.kind == "password"]
    assert password.item.raw == b"secret"
    kinds = [o.item.kind for o in observations(events)]
    assert kinds == ["handshake", "password", "handshake"]


def test_channel_map_resolves_ambiguous_frames():
    _, events = run(VPN_OPEN + [(C, b"rr1-0--0--0-ss1rr1-2--0--0-ss1rr1-2--1--0-ss1rr1-3--0--0-ss1")],
                    close=False)
    assert [o.message for o in observations(events)[2:]] == [
        m.NormalSend(0, 0), m.DeactivateSwitch(2), m.ActivateSwitch(2), m.SensorRequest(3)]


def test_ambiguity_without_a_map_is_reported_not_guessed():
    _, events = run([(C, b"rr1-24--0--0-ss1rr1-5--1--0-ss1")], close=False)
    last = observations(events)[-1]
    assert last.message is None
    assert last.candidates == (m.ActivateSwitch(5), m.NormalSend(5, 1))
    assert fired(events) == ["PW-AMBIGUOUS"]


def test_response_to_an_ambiguous_request_pairs_with_it():
    _, events = run([(C, b"rr1-24--0--0-ss1"), (C, b"rr1-5--0--0-ss1"), (S, b"cr1-5--77--0-ss1")])
    response = observations(events)[-1]
    assert response.answers is not None and response.answers.item.raw == b"rr1-5--0--0-ss1"
    assert "PW-PAIR-UNSOLICITED" not in fired(events)


def test_ambiguous_request_left_unanswered_is_not_a_violation():
    _, events = run([(C, b"rr1-24--0--0-ss1"), (C, b"rr1-5--0--0-ss1")])
    assert "PW-PAIR-UNANSWERED" in fired(events)  # the Fetch Configuration
    assert fired(events).count("PW-PAIR-UNANSWERED") == 1


def test_unanswered_after_timeout():
    session = Session(answer_timeout_ns=5_000_000)
    _, events = run(VPN_OPEN + [(C, b"rr1-3--0--0-ss1")] + [(C, b"rr1-0--100--0-ss1")] * 10,
                    session=session, close=False)
    late = [e for e in events if isinstance(e, LateViolation)]
    assert len(late) == 1 and late[0].about.message == m.SensorRequest(3)


def test_camera_image_answers_fetch_camera():
    _, events = run(VPN_OPEN + [(C, b"rr1-29--0--0-ss1"), (S, TINY_JPEG)])
    image = observations(events)[-1]
    assert image.message == m.CameraImage("jpeg", TINY_JPEG)
    assert image.answers.message == m.FetchCameraImage()
    assert fired(events) == []


def test_valid_set_configuration_updates_the_map_and_invalid_does_not():
    good = encode(m.SetConfiguration((m.SetConfigEntry(12, 3, 0),), 12))
    bad = encode(m.SetConfiguration((m.SetConfigEntry(12, 2, 2),), 99))
    session, events = run(VPN_OPEN + [(C, good), (C, bad)])
    assert unit_of(session.channel_map, 3) is m.UnitType.SERVO
    assert unit_of(session.channel_map, 2) is m.UnitType.SWITCH
    assert fired(events) == ["PW-SETCFG-CHECKSUM"]


def test_checksum_rule_is_selectable():
    frame = encode(m.SetConfiguration((m.SetConfigEntry(12, 3, 2),), 14))
    assert fired(run(VPN_OPEN + [(C, frame)])[1]) == ["PW-SETCFG-CHECKSUM"]
    assert fired(run(VPN_OPEN + [(C, frame)], session=Session("dev-unit-sum"))[1]) == []


@settings(max_examples=100, deadline=None)
@given(cuts_c=st.lists(st.integers(0, 400), max_size=15), cuts_s=st.lists(st.integers(0, 400), max_size=15))
def test_session_does_not_depend_on_segmentation(cuts_c, cuts_s):
    client = b"rr1-24--0--0-ss1rr1-3--0--0-ss1rr1-0--0--2-ss1rr1-2--1--0-ss1rr1-29--0--0-ss1"
    server = CONFIG + b"cr1-3--5--0-ss1cr1-0--80--0-ss1" + TINY_JPEG

    def shape(events):
        return [(o.direction, o.item.raw, o.message, o.violations) for o in observations(events)] + [
            e.violation for e in events if isinstance(e, LateViolation)]

    def session_run(c_chunks, s_chunks):
        # client first, then the server's answers, as on the wire
        return run([(C, c) for c in c_chunks] + [(S, s) for s in s_chunks])[1]

    assert shape(session_run(chunked(client, cuts_c), chunked(server, cuts_s))) == shape(
        session_run([client], [server]))


# -- every rule has a scenario that fires it --------------------------------------------

def test_every_rule_has_a_scenario():
    assert set(SCENARIOS) == set(RULES)


@pytest.mark.parametrize("rule_id", list(SCENARIOS))
def test_scenario_fires_its_rule(rule_id):
    _, events = run(SCENARIOS[rule_id])
    assert rule_id in fired(events)
    for e in events:
        for v in ([e.violation] if isinstance(e, LateViolation) else e.violations):
            assert v.detail  # every violation says what was expected and seen


def test_clean_prefixes_fire_nothing():
    assert fired(run(VPN_OPEN)[1]) == []
    assert fired(run(WINSOCK_OPEN)[1]) == []


# -- the fast path is only faster ----------------------------------------------------------


class SlowSession(Session):
    """Every item through the general path: the reference for the fast one."""

    def _observe_all(self, direction, items, t_ns):
        events = []
        for item in items:
            self._observe(direction, item, events)
        return events


def _shape(events):
    out = []
    for e in events:
        if isinstance(e, LateViolation):
            out.append(("late", e.violation, e.about.index, e.t_ns))
        else:
            out.append((e.index, e.direction, e.item, e.message, e.candidates, e.violations,
                        e.answers.index if e.answers else None, e.latency_ns))
    return out


sensor_value = st.one_of(st.integers(0, 1024), st.integers(1025, 1100))
servo_value = st.one_of(st.integers(0, 8000), st.integers(8001, 8100))
exchange = st.one_of(
    st.tuples(st.just(b"rr1-3--0--0-ss1"), sensor_value.map(lambda v: b"cr1-3--%d--0-ss1" % v)),
    st.tuples(st.just(b"rr1-0--0--2-ss1"), servo_value.map(lambda v: b"cr1-0--%d--0-ss1" % v)),
    st.tuples(st.sampled_from([b"rr1-0--700--0-ss1", b"rr1-2--1--0-ss1", b"rr1-2--0--0-ss1", b"rr1-9--1--0-ss1",
                               b"rr1-13--0--0-ss1", b"rr1-0--0--120-ss1", b"rr1-3--5--0-ss1",
                               b"rr1-0--2500--0-ss1"]), st.just(b"")),
    st.tuples(st.just(b""), st.sampled_from([b"cr1-3--7--0-ss1", b"cr1-0--9--0-ss1", b"cr1-13--9--0-ss1"])),
)


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(st.lists(exchange, max_size=60), st.integers(1, 4), st.booleans())
def test_fast_path_matches_the_general_path(exchanges, batch, winsock):
    opening = WINSOCK_OPEN if winsock else VPN_OPEN
    script = list(opening)
    for i in range(0, len(exchanges), batch):
        group = exchanges[i:i + batch]
        script.append((C, b"".join(c for c, _ in group)))
        script.append((S, b"".join(s for _, s in group)))
    script = [(d, data) for d, data in script if data]
    fast_session, fast = run(script, session=Session(answer_timeout_ns=3_500_000))
    slow = run(script, session=SlowSession(answer_timeout_ns=3_500_000))[1]
    assert _shape(fast) == _shape(slow)
    # without clean commands as events: the rest is the same, and so is every total
    quiet_session, quiet = run(script, session=Session(answer_timeout_ns=3_500_000, clean_commands=False))
    full, lean = _shape(fast), _shape(quiet)
    missing = []
    j = 0
    for e, shape in zip(fast, full):
        if j < len(lean) and lean[j] == shape:
            j += 1
        else:
            missing.append(e)
    assert j == len(lean)  # the lean events are the full ones, in order, less some
    assert all(isinstance(e, Observation) and e.direction is C and e.item.kind is ItemKind.COMMAND
               and not e.violations for e in missing)
    a, b = fast_session, quiet_session
    assert (a.counts, a.violation_counts, a.state, a.channel_map) == (b.counts, b.violation_counts, b.state,
                                                                       b.channel_map)
    assert {k: (v.count, v.total, v.histogram()) for k, v in a.latencies.items()} == \
        {k: (v.count, v.total, v.histogram()) for k, v in b.latencies.items()}


def test_bytes_after_a_half_close_are_framed_not_refused():
    """A file written out of order (another writer, an older whiztap) can hold a
    direction's bytes after its half-close: they are still framed and checked."""
    s = Session()
    s.receive(C, b"rr1-24--0-", 1)
    s.end(C, 2)
    events = s.receive(C, b"rr1-24--0--0-ss1", 3)
    assert [e.item.kind for e in events] == [ItemKind.COMMAND]


# -- eager clients and late answers ------------------------------------------------------


def test_a_password_sent_before_sendchkpass_breaks_the_order_and_is_still_the_password():
    """An eager client: its password and first command reach the proxy before the
    server's greeting.  The server reads them in order and lets it in."""
    session, events = run([(C, b"secret\r\nrr1-24--0--0-ss1"), (S, b"sendchkpass\r\n"), (S, b"readytogo\r\n"),
                           (S, b"sr1-\x01200-ss1")])
    obs = observations(events)
    assert [(o.item.kind, o.item.raw) for o in obs][:3] == [
        ("password", b"secret"), ("eol", b"\r\n"), ("command", b"rr1-24--0--0-ss1")]
    assert fired(events) == ["PW-HS-ORDER", "PW-HS-COMMAND-BEFORE-READY"]
    assert session.mode is Mode.WINSOCK and session.handshake_outcome == "readytogo"
    assert obs[-1].answers is obs[2]


def test_a_password_begun_before_sendchkpass_without_a_line_break_breaks_the_order():
    session, events = run([(C, b"sec"), (S, b"sendchkpass"), (C, b"ret"), (S, b"readytogo")])
    [password] = [o for o in observations(events) if o.item.kind == "password"]
    assert password.item.raw == b"secret" and [v.rule_id for v in password.violations] == ["PW-HS-ORDER"]
    assert session.handshake_outcome == "readytogo"


def client_items(events):
    return [(o.item.kind, o.item.raw) for o in observations(events) if o.direction is C]


def test_an_early_password_is_still_asked_for_by_a_server_that_begins_with_a_line_break():
    session, events = run([(C, b"secret\r\n"), (S, b"\r\nsendchkpass"), (S, b"readytogo")])
    assert client_items(events) == [("password", b"secret"), ("eol", b"\r\n")]
    assert fired(events) == ["PW-FRAME-EOL", "PW-HS-ORDER"]  # the server's line break before any item: info
    assert session.handshake_outcome == "readytogo"


def test_an_early_password_with_a_header_that_never_completes_is_one_password():
    _session, events = run([(C, b"secrr1-et\r\nrr1-24--0--0-ss1"), (S, b"sendchkpass"), (S, b"readytogo"),
                           (S, b"sr1-\x01200-ss1")])
    assert client_items(events) == [("password", b"secrr1-et"), ("eol", b"\r\n"), ("command", b"rr1-24--0--0-ss1")]
    assert fired(events) == ["PW-HS-ORDER", "PW-HS-COMMAND-BEFORE-READY"]
    command = next(o for o in observations(events) if o.item.kind == "command")
    assert observations(events)[-1].answers is command


def test_the_rest_of_a_password_judged_at_its_first_byte_is_still_the_password():
    """The server refused at the first byte; the client sends the rest of its
    line anyway: a password (sent after the verdict), not garbage."""
    _, events = run([(S, b"sendchkpass"), (C, b"K"), (S, b"Failed Validation"), (C, b"x9\r\n")])
    assert client_items(events) == [("password", b"K"), ("password", b"x9"), ("eol", b"\r\n")]
    assert fired(events) == ["PW-HS-AFTER-FAILED"]


def test_a_first_line_longer_than_a_password_is_no_password():
    line = b"x" * 300
    session, events = run([(S, b"sendchkpass"), (C, line + b"\r\n"), (S, b"Failed Validation")])
    assert client_items(events) == [("unframed", line), ("eol", b"\r\n")]
    assert session.handshake_outcome == "failed validation"


def test_garbage_before_a_vpn_session_is_still_garbage():
    session, events = run([(C, b"hello\r\n"), (C, b"rr1-24--0--0-ss1"), (S, b"sr1-\x01200-ss1")])
    assert fired(events) == ["PW-FRAME-GARBAGE", "PW-FRAME-EOL"]
    assert session.mode is Mode.VPN


def test_a_late_answer_is_unanswered_once_and_not_unsolicited():
    session = Session(answer_timeout_ns=5_000_000)
    _, events = run(VPN_OPEN + [(C, b"rr1-3--0--0-ss1")] + [(C, b"rr1-0--100--0-ss1")] * 8
                    + [(S, b"cr1-3--10--0-ss1")], session=session)
    assert fired(events) == ["PW-PAIR-UNANSWERED"]
    answer = observations(events)[-1]
    assert answer.answers is not None and answer.answers.message == m.SensorRequest(3)
