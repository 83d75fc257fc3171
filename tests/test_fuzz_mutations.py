"""The fuzzer's sans-IO parts: generation, mutation, shrinking and the judge (no sockets)."""

from __future__ import annotations

import random

from hypothesis import given, settings
from hypothesis import strategies as st

from whiztap.analyzer.fuzz.corpus import Corpus
from whiztap.analyzer.fuzz.grammar import MAX_FRAME_BYTES, MAX_FRAMES, Frame, Knowledge, generate, normalise
from whiztap.analyzer.fuzz.judge import Judge
from whiztap.analyzer.fuzz.mutate import MUTATIONS, digit_count, mutate
from whiztap.analyzer.fuzz.shrink import shrink
from whiztap.analyzer.protocol.codec import decode
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.handshake import Mode
from whiztap.analyzer.protocol.messages import ChannelConfig
from whiztap.sniffer.sim.channels import DEFAULT_CHANNELS, parse_channels

CHANNELS = parse_channels(DEFAULT_CHANNELS)
WINSOCK = Knowledge.of(Mode.WINSOCK, CHANNELS)
PASSWORD = b"s3cret-pw"


def _run_shrink(session, fails):
    """Drive ``shrink`` with a pure predicate; the result and how many were asked."""
    steps = shrink(session)
    asked = 0
    try:
        candidate = next(steps)
        while True:
            asked += 1
            candidate = steps.send(fails(candidate))
    except StopIteration as done:
        return done.value, asked


def test_generated_sessions_are_well_formed_and_start_with_the_handshake():
    rng = random.Random(0)
    for _ in range(50):
        session = generate(rng, WINSOCK)
        assert session[0].secret == "password"
        for frame in session[1:]:
            decoded = decode(ItemKind.COMMAND, frame.data)
            assert decoded.candidates and not decoded.violations, frame.data


@given(st.integers(0, 2**32), st.binary(min_size=1, max_size=20))
@settings(max_examples=200, deadline=None)
def test_mutated_sessions_stay_within_the_caps_and_show_the_password_only_first(seed, password):
    rng = random.Random(seed)
    session = generate(rng, WINSOCK)
    for _ in range(8):
        session, names = mutate(rng, session, WINSOCK, generate(rng, WINSOCK))
        assert set(names) <= set(MUTATIONS)
        assert len(session) <= MAX_FRAMES
        assert all(len(f.data) <= MAX_FRAME_BYTES for f in session)
        assert all(f.secret not in ("password", "short") for f in session[1:])
        for frame in session:
            assert b"".join(frame.pieces(password)) == frame.wire(password)


@given(st.integers(0, 2**32))
@settings(max_examples=50, deadline=None)
def test_mutation_is_a_function_of_the_seed(seed):
    def run():
        rng = random.Random(seed)
        session = generate(rng, WINSOCK)
        return [mutate(rng, session, WINSOCK, session) for _ in range(5)]
    assert run() == run()


def test_digit_counts_reach_three_digits_where_one_is_written():
    rng = random.Random(0)
    seen = {digit_count(rng, (Frame(b"rr1-12--0--0-ss1"),), WINSOCK, ())[0].data for _ in range(200)}
    assert b"rr1-12--000--0-ss1" in seen


def test_normalise_turns_a_later_password_into_a_stand_in():
    session = normalise((Frame(b"rr1-24--0--0-ss1"), Frame(secret="password"), Frame(secret="short")))
    assert [f.secret for f in session] == ["", "stand-in", "stand-in"]
    assert PASSWORD not in b"".join(f.wire(PASSWORD) for f in session)


@given(st.lists(st.binary(min_size=1, max_size=12), min_size=1, max_size=12), st.integers(0, 255))
@settings(max_examples=150, deadline=None)
def test_shrinking_keeps_the_failure_and_leaves_nothing_removable(chunks, marker):
    """The failure here: some frame holds the marker byte.  The result still
    fails, is one frame of one byte when the whole did, and the whole never
    grows."""
    session = tuple(Frame(c) for c in chunks)

    def fails(s):
        return any(marker in f.data for f in s)

    if not fails(session):
        session += (Frame(bytes([1, marker, 2])),)
    smallest, asked = _run_shrink(session, fails)
    assert fails(smallest)
    assert smallest == (Frame(bytes([marker])),)
    assert asked < 40 * (len(session) + sum(len(f.data) for f in session))


def test_shrinking_keeps_a_cut_where_the_failure_needs_it():
    session = (Frame(secret="password"), Frame(b"rr1-12--0--0-ss1", cuts=(3,)), Frame(b"rr1-24--0--0-ss1"))

    def fails(s):
        return any(f.cuts for f in s)  # a server that dies on any frame that comes in pieces

    smallest, _ = _run_shrink(session, fails)
    assert len(smallest) == 1 and smallest[0].cuts and len(smallest[0].data) == 2


@given(st.lists(st.binary(max_size=64), max_size=12), st.lists(st.binary(max_size=64), max_size=12))
@settings(max_examples=200, deadline=None)
def test_the_judge_takes_any_bytes_from_either_side(client, server):
    judge = Judge(Mode.WINSOCK, PASSWORD, CHANNELS)
    for t, (c, s) in enumerate(zip(client, server)):
        judge.client(c, t * 1000)
        judge.server(s, t * 1000 + 1)
        assert judge.due() >= 0
    judge.close(10**9)
    breach = judge.breach()
    assert breach is None or breach.kind == "violation"


def test_the_judge_owes_a_clean_request_its_answer_and_not_a_malformed_one():
    judge = Judge(Mode.VPN, b"", (ChannelConfig(2),) * 24)
    judge.client(b"rr1-12--0--0-ss1", 1)
    assert judge.due() == 1
    judge.client(b"rr1-12--0--0-ss2", 2)  # no frame: never owed
    judge.server(b"cr1-12--100--0-ss1", 3)
    assert judge.due() == 0 and judge.breach() is None
    judge.client(b"rr1-13--0--0-ss1", 4)
    judge.server(b"cr1-13--2000--0-ss1", 5)
    assert judge.breach().rule == "PW-RANGE-SENSOR"


def test_the_corpus_keeps_new_behaviour_within_its_capacity():
    rng = random.Random(0)
    corpus = Corpus([(Frame(b"a"),)], capacity=3)
    assert corpus.consider(rng, (Frame(b"b"),), ("x",))
    assert not corpus.consider(rng, (Frame(b"c"),), ("x",))
    for n in range(10):
        corpus.consider(rng, (Frame(b"%d" % n),), (str(n),))
    assert len(corpus) == 3 and corpus.entries[0] == (Frame(b"a"),)


def test_the_docs_list_every_mutation_as_the_code_has_it():
    from pathlib import Path

    rows = [f"| `{name}` | {weight} | {' '.join((fn.__doc__ or '').split())} |"
            for name, (fn, weight) in MUTATIONS.items()]
    doc = (Path(__file__).parent.parent / "docs" / "fuzz.md").read_text()
    assert "\n".join(rows) in doc
