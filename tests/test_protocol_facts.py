"""Protocol facts live in analyzer/protocol, once: the login words, who speaks
first, and how a frame on its own is judged, whoever asks (the proxy in the
middle, the Controller, the TUI, ``whiztap decode``, the capture)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from whiztap.analyzer.protocol.frame_text import check_frame
from whiztap.analyzer.protocol.handshake import HANDSHAKE_WORDS
from whiztap.analyzer.protocol.observations import OPENINGS, Direction, may_tell, sender_of
from tests.core_support import FakeClockMiddle
from tests.spec_vectors import COMMANDS, HANDSHAKE_SERVER, RESPONSES, SET_CONFIG_EXAMPLE

C, S = Direction.C2S, Direction.S2C
REPO = Path(__file__).parent.parent
WORDS = (b"sendchkpass", b"readytogo", b"Failed Validation")  # as the spec spells them, not as whiztap does
WORDS_TEXT = {word.decode() for word in WORDS}


# -- the login words ------------------------------------------------------------------------------


def test_the_login_words_are_the_specs():
    assert HANDSHAKE_WORDS == WORDS == tuple(HANDSHAKE_SERVER)


@pytest.mark.slow
def test_the_login_words_are_spelled_only_in_handshake_py():
    """No library module but analyzer/protocol/handshake.py spells a login
    word in bytes, or as a string that is just the word: the others import
    it (prose in docstrings and messages may name it)."""
    spelled = []
    for root in ("analyzer", "sniffer", "tui"):
        for path in sorted((REPO / root).rglob("*.py")):
            if path == REPO / "analyzer" / "protocol" / "handshake.py":
                continue
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if not isinstance(node, ast.Constant):
                    continue
                value = node.value
                if (isinstance(value, bytes) and any(w in value for w in WORDS)) or value in WORDS_TEXT:
                    spelled.append(f"{path.relative_to(REPO)}:{node.lineno}: {value!r}")
    assert spelled == []


# -- who speaks first -----------------------------------------------------------------------------


def test_a_conversations_first_bytes_tell_which_side_sent_them():
    firsts = (b"rr1-24--0--0-ss1", b"sr1-25--\x0c", b"cr1-3--1--0-ss1", b"sr1-\x01000-ss1", b"sendchkpass",
              b"Failed Validation", b"sr1-2", b"send", b"GET / HTTP/1.1")
    assert [sender_of(first) for first in firsts] == [C, C, S, S, S, S, None, None, None]
    assert [may_tell(first) for first in firsts[-3:]] == [True, True, False]  # too few bytes yet, or not Progwhiz


def test_every_frame_of_the_spec_is_told_by_its_first_bytes_as_the_side_it_may_come_from():
    """``sender_of`` and PW-DIRECTION read the same table: the side a frame's
    opening names is the one it may come from."""
    frames = [(raw, C) for raw, _ in COMMANDS] + [(raw, S) for raw, _ in RESPONSES] + [
        (word, S) for word in WORDS]
    for raw, sender in frames:
        assert sender_of(raw) is sender, raw
        assert not [v for v in check_frame(raw, sender) if v.rule_id == "PW-DIRECTION"]
        other = C if sender is S else S
        assert [v.rule_id for v in check_frame(raw, other)].count("PW-DIRECTION") == 1, raw


openings = st.sampled_from([opening for opening, _ in OPENINGS])
first_bytes = st.one_of(
    st.binary(max_size=20),
    st.tuples(openings, st.integers(0, 20), st.binary(max_size=6)).map(lambda t: t[0][:t[1]] + t[2]),
)


@pytest.mark.slow
@settings(max_examples=400, deadline=None)
@given(first_bytes, st.binary(max_size=20))
def test_more_bytes_never_change_what_the_first_ones_told(first, more):
    """Whatever a peer sends: once its first bytes tell a side, more of them
    tell the same; once they cannot tell, no more of them will; and bytes
    that tell nothing yet begin an opening (the capture holds them)."""
    told = sender_of(first)
    if told is not None:
        assert sender_of(first + more) is told
    elif may_tell(first):
        assert any(opening.startswith(first) for opening, _ in OPENINGS)
    else:
        assert sender_of(first + more) is None and not may_tell(first + more)


# -- a frame judged alone, by the middle too --------------------------------------------------------

ALONE = [(raw, C) for raw, _ in COMMANDS[:3]] + [(raw, S) for raw, _ in RESPONSES[:4]] + [
    (b"rr1-12--0--0-ss1", S),  # a command from the server: PW-DIRECTION
    (b"cr1-3--5--0-ss1", C),  # an answer from the client
    (SET_CONFIG_EXAMPLE, C),  # its checksum fits dev-sum only
    (SET_CONFIG_EXAMPLE[:-8] + b"\x00--0-ss1", C),  # a checksum no rule computes
    (b"rr1-31--5--0-ss1", C),  # a channel out of range
    (b"readytogo", S),
    (b"Failed Validation", C),  # a login word from the client
]


@settings(max_examples=60, deadline=None)
@given(st.sampled_from(ALONE), st.sampled_from(["dev-sum", "dev-unit-sum", "dev-sum-7bit"]))
def test_the_middle_judges_each_frame_as_check_frame_does(frame, rule):
    """The proxy in the middle judges the frames it holds as the Controller
    judges one typed to inject (``check_frame``), under the run's checksum
    rule: the direction and the checksum too, not the codec's rules alone."""
    raw, direction = frame
    mid = FakeClockMiddle(intercept=f"dir:{direction}", checksum_rule=rule)
    mid.send(direction, raw)
    [held] = mid.controller.held.frames.values()
    assert held.observation.item.raw == raw
    assert list(held.observation.violations) == check_frame(raw, direction, rule)
