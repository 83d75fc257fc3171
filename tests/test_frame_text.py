"""Frames written as text (analyzer/protocol/frame_text.py): the console's words
make the spec's example frames, escaped text round-trips, and check_frame finds
what is wrong with one frame on its own."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.spec_vectors import SET_CONFIG_EXAMPLE
from tests.streams import TINY_JPEG, TINY_PNG
from whiztap.analyzer.protocol.examples import CONFIG, SCENARIOS
from whiztap.analyzer.protocol.frame_text import (
    CONSOLE_WORDS,
    FrameTextError,
    check_frame,
    frame_from_text,
    message_from_words,
)
from whiztap.analyzer.protocol.messages import PlayExternalScript, PlayInternalScript, SetConfiguration
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.text import escape

C, S = Direction.C2S, Direction.S2C

# Console words and the frame they make; every rr1 frame here is an example of the spec's.
WORDS = [
    ("config", b"rr1-24--0--0-ss1"),
    ("camera", b"rr1-29--0--0-ss1"),
    ("send 0 60", b"rr1-0--60--0-ss1"),
    ("send 2 72", b"rr1-2--72--0-ss1"),
    ("servo 14 9", b"rr1-14--9--0-ss1"),
    ("switch 0 on", b"rr1-0--1--0-ss1"),
    ("switch 14 close", b"rr1-14--1--0-ss1"),
    ("switch 2 off", b"rr1-2--0--0-ss1"),
    ("switch 14 0", b"rr1-14--0--0-ss1"),
    ("script 11", b"rr1-0--0--11-ss1"),
    ("script 120", b"rr1-0--0--120-ss1"),
    ("script stop internal", b"rr1-0--0--267-ss1"),
    ("script 272", b"rr1-0--0--272-ss1"),
    ("script stop external", b"rr1-0--0--269-ss1"),
    ("sensor 3", b"rr1-3--0--0-ss1"),
    ("servo 3", b"rr1-3--0--2-ss1"),
    ("servo 2", b"rr1-2--0--2-ss1"),
    ("setconfig servo:0-5", SET_CONFIG_EXAMPLE),
    ("setconfig servo:0-5 72", SET_CONFIG_EXAMPLE),
    # not in the spec
    ("sensor 12", b"rr1-12--0--0-ss1"),
    ("servo 3 1500", b"rr1-3--1500--0-ss1"),
    ("send 5 100", b"rr1-5--100--0-ss1"),
    ("switch 4 on", b"rr1-4--1--0-ss1"),
    ("script 20", b"rr1-0--0--20-ss1"),
    ("  SENSOR   12 ", b"rr1-12--0--0-ss1"),
    ("setconfig servo:0-1,sensor:2 9", b"sr1-25--\x0c\x00\x00\x0c\x01\x00\x0c\x02\x02\x09--0-ss1"),
]


@pytest.mark.parametrize("text, frame", WORDS, ids=[t for t, _ in WORDS])
def test_console_words_make_the_exact_frame(text, frame):
    assert frame_from_text(text) == frame


def test_setconfig_makes_one_entry_per_channel_with_the_default_checksum():
    data = frame_from_text("setconfig servo:0-5,sensor:6-23")
    assert data.startswith(b"sr1-25--") and data.endswith(b"--0-ss1")
    triples = data[8:-8]
    assert len(triples) == 24 * 3
    assert [triples[i + 2] for i in range(0, len(triples), 3)] == [0] * 6 + [2] * 18
    assert data[-8] == (12 * 24) % 256
    assert check_frame(data, C) == []


def test_scripts_are_internal_or_external_by_number():
    assert message_from_words(["script", "120"]) == PlayInternalScript(120)
    assert message_from_words(["script", "272"]) == PlayExternalScript(272)
    assert isinstance(message_from_words(["setconfig", "servo:0"]), SetConfiguration)
    assert set(CONSOLE_WORDS) == {"config", "camera", "sensor", "servo", "send", "switch", "script", "setconfig"}


ESCAPED = [
    ("rr1-12--0--0-ss1", b"rr1-12--0--0-ss1"),
    ("cr1-12--999--0-ss1\\r\\n", b"cr1-12--999--0-ss1\r\n"),
    ("rr1-0-- 5--0-ss1", b"rr1-0-- 5--0-ss1"),
    ("sr1-\\x01000-ss1", b"sr1-\x01000-ss1"),
    ('"sensor 12"', b"sensor 12"),
    ("'  '", b"  "),
    ("sendchkpass\\r\\n", b"sendchkpass\r\n"),
    ("\\x00\\xff", b"\x00\xff"),
]


@pytest.mark.parametrize("text, frame", ESCAPED, ids=[t for t, _ in ESCAPED])
def test_escaped_text(text, frame):
    assert frame_from_text(text) == frame


@pytest.mark.parametrize("data", [b"rr1-12--0--0-ss1", SET_CONFIG_EXAMPLE, CONFIG, bytes(range(256)),
                                  *(step for steps in SCENARIOS.values() for _, step in steps)])
def test_escaped_text_round_trips(data):
    text = escape(data)
    if text.startswith(("rr1-", "sr1-", "cr1-")) or "\\" in text:
        assert frame_from_text(text) == data
    assert frame_from_text(f"'{text}'") == data


@pytest.mark.parametrize("text, words", [
    ("", ["no frame"]),
    ("   ", ["no frame"]),
    ("bogus 1", ["'bogus'"]),
    ("sensor", ["wrong arguments", "sensor CH"]),
    ("sensor 1 2", ["wrong arguments"]),
    ("sensor x", ["whole number", "'x'"]),
    ("sensor -1", ["must not be negative"]),
    ("servo 1 2 3", ["wrong arguments"]),
    ("send 1", ["wrong arguments"]),
    ("switch 7 maybe", ["on or off", "'maybe'"]),
    ("script", ["wrong arguments"]),
    ("script stop", ["usage"]),
    ("script stop all", ["usage"]),
    ("config now", ["wrong arguments"]),
    ("camera -o x", ["wrong arguments"]),
    ("setconfig motor:0", ["bad channel group"]),
    ("setconfig servo:0-99999999999", ["at most 24 channels"]),
    ("setconfig servo:0 300", ["one byte"]),
    ("'rr1-0--0--0-ss1", ["closing quote"]),
    ('""', ["empty"]),
    ("rr1-\ud800", ["surrogate"]),
])
def test_bad_text_says_why(text, words):
    with pytest.raises(FrameTextError) as caught:
        frame_from_text(text)
    for word in words:
        assert word in str(caught.value)


# -- check_frame -----------------------------------------------------------------------------


def _rules(data: bytes, direction: Direction, checksum_rule: str = "dev-sum") -> list[str]:
    return [v.rule_id for v in check_frame(data, direction, checksum_rule)]


@pytest.mark.parametrize("data, direction", [
    *((frame, C) for text, frame in WORDS if not text.endswith(" 9")),  # the last has a wrong checksum
    (b"cr1-12--999--0-ss1", S), (CONFIG, S), (b"sendchkpass", S), (b"readytogo", S), (TINY_JPEG, S), (TINY_PNG, S),
])
def test_a_valid_frame_has_no_violation(data, direction):
    assert check_frame(data, direction) == []


def test_range_violations():
    assert _rules(frame_from_text("sensor 99"), C) == ["PW-RANGE-CHANNEL"]
    assert _rules(frame_from_text("send 3 2500"), C) == ["PW-RANGE-SEND-VALUE"]
    assert _rules(frame_from_text("script 300"), C) == ["PW-RANGE-SCRIPT"]
    assert "PW-SYNTAX-WIDTH" in _rules(frame_from_text("servo 3 99999"), C)


def test_direction_violations():
    assert _rules(b"rr1-12--0--0-ss1", S) == ["PW-DIRECTION"]
    assert _rules(SET_CONFIG_EXAMPLE, S) == ["PW-DIRECTION"]
    assert _rules(b"cr1-12--5--0-ss1", C) == ["PW-DIRECTION"]
    assert _rules(CONFIG, "c2s") == ["PW-DIRECTION"]
    assert _rules(b"sendchkpass", C) == ["PW-DIRECTION"]
    message = check_frame(b"rr1-12--0--0-ss1", S)[0].detail
    assert message == "a command came from the server"  # the session's wording


def test_checksum_violations_follow_the_rule():
    wrong = frame_from_text("setconfig servo:0-5 73")
    assert _rules(wrong, C) == ["PW-SETCFG-CHECKSUM"]
    assert "expected 72 (dev-sum), got 73" in check_frame(wrong, C)[0].detail
    assert _rules(SET_CONFIG_EXAMPLE, C, "dev-unit-sum") == []  # unit types 0: the same sum
    mixed = frame_from_text("setconfig servo:0,sensor:1")  # dev-sum 24
    assert _rules(mixed, C, "dev-unit-sum") == ["PW-SETCFG-CHECKSUM"]
    with pytest.raises(ValueError, match="unknown checksum rule"):
        check_frame(mixed, C, "no-such-rule")


@pytest.mark.parametrize("data, rules", [
    (b"", ["PW-FRAME-GARBAGE"]),
    (b"junk", ["PW-FRAME-GARBAGE"]),
    (b"rr1-0--5", ["PW-FRAME-TRUNCATED", "PW-FRAME-GARBAGE"]),
    (b"rr1-1--0--0-ss1rr1-2--0--0-ss1", ["PW-FRAME-GARBAGE"]),
    (b"rr1-1--0--0-ss1\r\n", ["PW-FRAME-GARBAGE"]),
    (b"\x00\x01junk rr1-0--5--0-ss1", ["PW-FRAME-GARBAGE"]),
])
def test_not_exactly_one_frame(data, rules):
    assert _rules(data, C) == rules


def test_the_codec_rules_are_reported():
    assert _rules(b"rr1-0--05--0-ss1", C) == ["PW-SYNTAX-LEADING-ZERO"]
    assert _rules(b"rr1-0--0--7-ss1", C) == ["PW-UNKNOWN-COMMAND"]
    assert _rules(b"sr1-\x01500-ss1", S) == ["PW-CFG-UNIT"]


# -- any text ----------------------------------------------------------------------------------

_PIECES = st.sampled_from([*CONSOLE_WORDS, "stop", "internal", "on", "off", "servo:0-5", "sensor:6-23", "1", "23",
                           "-1", "99999", "rr1-", "cr1-", "'", '"', "\\", "\\x4", "\\r", " ", "\ud800", "é", ":"])


@pytest.mark.slow
@settings(max_examples=500, deadline=None)
@given(st.one_of(st.text(), st.lists(_PIECES, max_size=8).map(" ".join), st.lists(_PIECES, max_size=8).map("".join)))
def test_any_text_is_bytes_or_a_frame_text_error(text):
    try:
        data = frame_from_text(text)
    except FrameTextError:
        return
    assert isinstance(data, bytes) and data
    for direction in Direction:
        assert isinstance(check_frame(data, direction), list)
