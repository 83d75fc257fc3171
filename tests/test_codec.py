"""Decoding the spec's examples, encoding them back, and the frame-local rules."""

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.checksum import CHECKSUM_RULES, DEFAULT_CHECKSUM_RULE, get_rule, satisfied_rules
from whiztap.analyzer.protocol.codec import decode, encode, resolve
from whiztap.analyzer.protocol.framing import ItemKind, Unframed
from whiztap.analyzer.protocol.messages import UnitType
from tests.spec_vectors import COMMANDS, RESPONSES, SET_CONFIG_EXAMPLE
from tests.streams import frame_all


def decode_raw(raw: bytes):
    [item] = frame_all([raw])
    return decode(item.kind, item.raw, item.reason)


@pytest.mark.parametrize(("raw", "meanings"), COMMANDS + RESPONSES)
def test_spec_examples_decode_to_their_meanings(raw, meanings):
    decoded = decode_raw(raw)
    assert decoded.candidates == meanings
    assert decoded.message == (meanings[0] if len(meanings) == 1 else None)
    assert decoded.violations == ()


@pytest.mark.parametrize(("raw", "meanings"), COMMANDS + RESPONSES)
def test_spec_examples_encode_to_their_bytes(raw, meanings):
    for meaning in meanings:
        assert encode(meaning) == raw


def test_every_checksum_candidate_validates_the_spec_example():
    example = decode_raw(SET_CONFIG_EXAMPLE).message
    assert example.checksum == 72
    assert sum(SET_CONFIG_EXAMPLE[8:-8]) == 87  # why the plain sum cannot be the rule
    assert satisfied_rules(example.entries, example.checksum) == tuple(CHECKSUM_RULES)
    assert get_rule(DEFAULT_CHECKSUM_RULE).compute(example.entries) == 72


def test_checksum_candidates_disagree_elsewhere():
    entries = (m.SetConfigEntry(100, 0, 2), m.SetConfigEntry(100, 1, 2))
    values = {name: rule.compute(entries) for name, rule in CHECKSUM_RULES.items()}
    assert values == {"dev-sum": 200, "dev-unit-sum": 204, "dev-sum-7bit": 72}
    assert satisfied_rules(entries, 204) == ("dev-unit-sum",)


def test_unknown_checksum_rule_names_the_known_ones():
    with pytest.raises(ValueError, match="dev-sum"):
        get_rule("crc32")


def test_resolve_by_unit_type():
    candidates = decode_raw(b"rr1-3--0--0-ss1").candidates
    assert resolve(candidates, UnitType.SENSOR) == m.SensorRequest(3)
    assert resolve(candidates, UnitType.SWITCH) == m.DeactivateSwitch(3)
    assert resolve(candidates, UnitType.SERVO) == m.NormalSend(3, 0)
    assert resolve(candidates, None) is None
    assert resolve(decode_raw(b"rr1-3--1--0-ss1").candidates, UnitType.SENSOR) is None


def rules_of(raw: bytes) -> list[str]:
    return [v.rule_id for v in decode_raw(raw).violations]


@pytest.mark.parametrize(("raw", "rules"), [
    (b"rr1-30--500--0-ss1", ["PW-RANGE-CHANNEL"]),
    (b"rr1-3--2001--0-ss1", ["PW-RANGE-SEND-VALUE"]),
    (b"rr1-3--2000--0-ss1", []),
    (b"rr1-0--0--268-ss1", ["PW-RANGE-SCRIPT"]),
    (b"rr1-0--0--999-ss1", ["PW-RANGE-SCRIPT"]),
    (b"rr1-0--0--5-ss1", ["PW-UNKNOWN-COMMAND"]),
    (b"rr1-4--0--11-ss1", ["PW-FIXED-FIELD"]),
    (b"rr1-0--7--267-ss1", ["PW-FIXED-FIELD"]),
    (b"rr1-3--5--2-ss1", ["PW-FIXED-FIELD"]),
    (b"rr1-24--3--0-ss1", ["PW-FIXED-FIELD"]),
    (b"rr1-29--1--0-ss1", ["PW-FIXED-FIELD"]),
    (b"cr1-2--100--4-ss1", ["PW-FIXED-FIELD"]),
    (b"rr1-03--60--0-ss1", ["PW-SYNTAX-LEADING-ZERO"]),
    (b"rr1-123--0--2-ss1", ["PW-SYNTAX-WIDTH", "PW-RANGE-CHANNEL"]),
    (b"rr1-0--0--0120-ss1", ["PW-SYNTAX-LEADING-ZERO", "PW-SYNTAX-WIDTH"]),
    (b"rr1-0 --60--0-ss1", ["PW-SYNTAX-SPACE"]),
    (b"rr1-0--6x--0-ss1", ["PW-SYNTAX-FIELDS"]),
    (b"rr1-0--60-ss1", ["PW-SYNTAX-FIELDS"]),
    (b"sr1-\x19" + b"000" * 25 + b"-ss1", ["PW-CFG-COUNT"]),
    (b"sr1-\x02000300-ss1", ["PW-CFG-UNIT"]),
    (b"sr1-\x02000010-ss1", ["PW-CFG-UNUSED"]),
    (b"sr1-\x02000102-ss1", ["PW-CFG-SWITCH-TYPE"]),
    (b"sr1-\x020x0000-ss1", ["PW-CFG-DIGIT"]),
    (b"sr1-25--" + bytes([200, 0, 0, 200]) + b"--0-ss1", ["PW-SETCFG-DEV"]),
    (b"sr1-25--" + bytes([12, 24, 0, 12]) + b"--0-ss1", ["PW-SETCFG-PORT"]),
    (b"sr1-25--" + bytes([12, 0, 3, 12]) + b"--0-ss1", ["PW-SETCFG-UNIT"]),
    (b"sr1-25--" + bytes([7]) + b"--0-ss1", ["PW-SETCFG-EMPTY"]),
    (b"sr1-\x19" + bytes([12, 0, 0, 12]) + b"0-ss1", ["PW-SETCFG-FORM"]),
    (b"sr1-\x19" + bytes([12, 0, 0, 12]) + b"X-ss1", ["PW-SETCFG-FORM", "PW-SETCFG-TRAILER"]),
])
def test_frame_local_rules(raw, rules):
    assert rules_of(raw) == rules


def test_layout_form_set_config_still_decodes_its_entries():
    decoded = decode_raw(b"sr1-\x19" + bytes([12, 0, 0, 12, 1, 0, 24]) + b"0-ss1")
    assert decoded.message == m.SetConfiguration((m.SetConfigEntry(12, 0, 0), m.SetConfigEntry(12, 1, 0)), 24)


@pytest.mark.parametrize(("reason", "rule"), [
    (Unframed.GARBAGE, "PW-FRAME-GARBAGE"),
    (Unframed.TRUNCATED, "PW-FRAME-TRUNCATED"),
    (Unframed.OVERSIZE, "PW-FRAME-OVERSIZE"),
])
def test_unframed_items_map_to_their_rule(reason, rule):
    assert [v.rule_id for v in decode(ItemKind.UNFRAMED, b"xx", reason).violations] == [rule]


# -- round trips ---------------------------------------------------------------------

channel = st.integers(0, 23)
valid_messages = st.one_of(
    st.just(m.FetchConfiguration()),
    st.just(m.FetchCameraImage()),
    st.builds(m.NormalSend, channel, st.integers(2, 2000)),
    st.builds(m.ServoPositionRequest, channel),
    st.builds(m.PlayInternalScript, st.integers(11, 266)),
    st.builds(m.PlayExternalScript, st.integers(270, 275)),
    st.just(m.StopInternalScript()),
    st.just(m.StopExternalScript()),
    st.builds(m.ChannelResponse, channel, st.integers(0, 8000)),
    st.builds(lambda chs: m.ConfigurationSettings(tuple(chs)),
              st.lists(st.builds(m.ChannelConfig, st.integers(0, 2), st.just(0), st.integers(0, 1)), max_size=24)),
    st.builds(lambda es, chk: m.SetConfiguration(tuple(es), chk),
              st.lists(st.builds(m.SetConfigEntry, st.integers(0, 127), channel, st.integers(0, 2)),
                       min_size=1, max_size=24),
              st.integers(0, 255)),
)


@pytest.mark.slow
@settings(max_examples=500, deadline=None)
@given(valid_messages)
def test_encode_then_decode_gives_the_message_back(message):
    raw = encode(message)
    [item] = frame_all([raw])
    assert item.raw == raw
    decoded = decode(item.kind, item.raw)
    assert decoded.message == message
    assert decoded.violations == ()


@settings(max_examples=300, deadline=None)
@given(channel, st.sampled_from([0, 1]))
def test_ambiguous_frames_round_trip_through_every_candidate(ch, value):
    raw = b"rr1-%d--%d--0-ss1" % (ch, value)
    decoded = decode_raw(raw)
    assert decoded.ambiguous and decoded.message is None
    assert all(encode(c) == raw for c in decoded.candidates)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=80))
def test_decode_never_raises(data):
    for item in frame_all([data]):
        decode(item.kind, item.raw, item.reason)
