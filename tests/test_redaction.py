"""The password rule on its own (analyzer/recording/redaction.py): only the
client's first line can be masked, and only when the server asks for a
password (or never says whether it does).

``LoginMask`` and ``Redactor`` are fed bytes as the proxy would see them; the
property at the end checks the rule against a plain statement of it, for any
arrival order and any cutting into reads."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from whiztap.analyzer.protocol.framing import MAX_PASSWORD, Framer, ItemKind
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.redaction import LoginMask, Phase, Redactor

from tests.streams import chunked

C2S, S2C = Direction.C2S, Direction.S2C
SECRET = b"Kx9hunter2Tq4"
FETCH = b"rr1-24--0--0-ss1"
CONFIG = b"sr1-\x18" + b"200" * 24 + b"-ss1"
SEND = b"rr1-5--600--0-ss1"  # a Normal Send: no answer


# protocol-like bytes: frames, handshake words, line breaks, fragments, anything
stream = st.lists(st.one_of(st.sampled_from([
    FETCH, b"rr1-3--0--2-ss1", b"cr1-12--100--0-ss1", b"sr1-\x02000200-ss1", b"sr1-25--\x0c\x00\x00\x07--0-ss1",
    b"sendchkpass", b"readytogo", b"Failed Validation", b"rr1-", b"cr1-", b"-ss1", b"\r\n", b"\n", b"\r", b" ",
]), st.binary(min_size=1, max_size=12)), max_size=12).map(b"".join)


def shown(mask: LoginMask, data: bytes) -> bytes:
    return mask.apply(0, data)[0]


def out(redactor: Redactor) -> list[tuple[str, bytes]]:
    return [(r.record, r.data) for r in redactor.released()]


# -- one connection -----------------------------------------------------------------------------


def test_a_client_that_begins_with_a_frame_is_shown_at_once():
    """A VPN client pipelining 2,000 requests before its server's first byte:
    nothing waits and nothing is masked."""
    mask = LoginMask()
    sent = FETCH + b"rr1-12--0--0-ss1" * 1999
    mask.client(sent)
    assert mask.phase is Phase.OPEN and mask.undecided == 0 and mask.decided >= len(sent)
    assert shown(mask, sent) == sent


def test_after_sendchkpass_only_the_password_line_is_masked():
    """The password and a command sent before 'readytogo': the command is the
    client's to answer for, and is shown at once, before any verdict."""
    data = SECRET + b"\r\n" + FETCH
    mask = LoginMask()
    mask.server(b"sendchkpass")
    mask.client(data)
    assert mask.phase is Phase.OPEN
    assert shown(mask, data) == b"*" * len(SECRET) + b"\r\n" + FETCH


def test_a_password_ends_at_the_header_of_a_frame_that_completes_not_at_one_that_never_does():
    for data, masked in [(SECRET + FETCH, len(SECRET)), (b"secrr1-et\r\n" + FETCH, 9)]:
        mask = LoginMask()
        mask.client(data)
        mask.server(b"\r\nsendchkpass")
        assert shown(mask, data) == b"*" * masked + data[masked:]


def test_a_first_line_longer_than_a_password_is_shown():
    data = b"x" * (MAX_PASSWORD + 1) + b"\r\n" + FETCH
    mask = LoginMask()
    mask.server(b"sendchkpass")
    mask.client(data)
    assert mask.phase is Phase.OPEN and shown(mask, data) == data


def test_binary_before_the_server_speaks_is_shown_once_it_does():
    """64 KiB of binary in one read before an echo server's first byte: the
    first line waits for the server (it may be a password); no bound masks it."""
    data = bytes(random.Random(7).randrange(256) for _ in range(64 * 1024)).replace(b"s", b"t")
    mask = LoginMask()
    mask.client(data)
    assert mask.undecided <= MAX_PASSWORD + 4
    mask.server(data[:100])
    assert mask.phase is Phase.OPEN and shown(mask, data) == data


def test_what_the_clock_masked_stays_masked_and_the_rest_follows_the_rule():
    """Held too long, the bytes of the first line so far are masked; the rest
    of the line is masked once the server asks, and what follows it is shown."""
    mask = LoginMask()
    mask.client(b"sec")
    mask.force()
    assert mask.masked_end == 3 and mask.decided == 3
    rest = b"ret\r\n" + FETCH
    mask.client(rest)
    assert mask.decided == 3  # the rest of the line: undecided, and what follows waits behind it
    mask.server(b"sendchkpass")
    assert mask.phase is Phase.OPEN
    assert shown(mask, b"sec" + rest) == b"******\r\n" + FETCH


def test_a_verdict_before_the_line_ends_masks_what_came_of_it_at_once():
    """A server that refuses at the first wrong byte has judged that much as
    the password: masked then, as the session hands it over then; the rest of
    the line follows the rule (masked, or shown if the line is too long to be
    a password)."""
    for rest, masked in [(b"x9hunter2Tq4\r\n" + FETCH, len(SECRET)), (b"x" * MAX_PASSWORD + b"\r\n", 1)]:
        mask = LoginMask()
        mask.server(b"sendchkpass")
        mask.client(b"K")
        assert mask.decided == 0
        mask.server(b"Failed Valid")
        mask.server(b"ation")
        assert mask.masked_end == mask.decided == 1
        mask.client(rest)
        assert mask.phase is Phase.OPEN
        assert shown(mask, b"K" + rest) == b"*" * masked + (b"K" + rest)[masked:]


def test_a_verdict_between_the_bytes_of_a_first_frame_header_masks_nothing():
    mask = LoginMask()
    mask.server(b"sendchkpass")
    mask.client(b"rr")
    mask.server(b"readytogo")
    mask.client(b"1-24--0--0-ss1")
    assert mask.phase is Phase.OPEN and shown(mask, b"rr1-24--0--0-ss1") == b"rr1-24--0--0-ss1"


# -- every connection, in arrival order -----------------------------------------------------------


def test_a_one_way_blast_to_a_server_that_never_speaks_is_never_held():
    redactor: Redactor[int] = Redactor(hold_s=2.0)
    redactor.opened(1)
    blast = [SEND * 1000 for _ in range(50)]
    for n, data in enumerate(blast):
        redactor.read(1, C2S, data, n, now=0.0)
        assert out(redactor) == [(n, data)]  # out at once, as sent
        assert redactor.passing(1)  # and the next read may skip the queue


def test_a_server_that_never_speaks_masks_the_first_line_only():
    redactor: Redactor[str] = Redactor(hold_s=2.0)
    redactor.opened(1)
    redactor.read(1, C2S, b"pw\r\n" + SEND * 500, "first", now=0.0)
    redactor.read(1, C2S, SEND * 500, "second", now=0.5)
    assert out(redactor) == []
    redactor.tick(2.5)
    assert out(redactor) == [("first", b"**\r\n" + SEND * 500), ("second", SEND * 500)]


def test_a_silent_server_that_ends_leaves_the_password_masked_and_what_follows_shown():
    redactor: Redactor[str] = Redactor(hold_s=1e9)
    redactor.opened(1)
    redactor.read(1, C2S, SECRET + b"\r\n" + FETCH, "sent", now=0.0)
    redactor.ended(1, S2C)
    assert out(redactor) == [("sent", b"*" * len(SECRET) + b"\r\n" + FETCH)]


def test_a_client_that_ends_its_line_by_leaving_is_decided_then():
    """The client's FIN ends its first line: a server that asked has it masked
    at once, with no clock."""
    redactor: Redactor[str] = Redactor(hold_s=1e9)
    redactor.opened(1)
    redactor.read(1, S2C, b"sendchkpass", "asked", now=0.0)
    redactor.read(1, C2S, SECRET + b"rr1-", "sent", now=0.0)
    assert out(redactor) == [("asked", b"sendchkpass")]
    redactor.ended(1, C2S)
    assert out(redactor) == [("sent", b"*" * (len(SECRET) + 4))]


# -- the property: the rule, stated plainly, for any order and any reads -----------------------------

HEADERS = (b"rr1-", b"cr1-", b"sr1-")


def _completes(rest: bytes) -> bool:
    """Whether a frame begins ``rest`` and completes (framed as any other bytes)."""
    framer = Framer()
    first = (framer.feed(rest, 0) + framer.end(1))[0]
    return first.kind in (ItemKind.COMMAND, ItemKind.RESPONSE, ItemKind.CONFIG, ItemKind.SET_CONFIG)


def expected(client: bytes, server: bytes) -> bytes:
    """The client's bytes as the rule shows them once the connection is over."""
    said = server.lstrip(b"\r\n")[:11]
    if said and not b"sendchkpass".startswith(said):
        return client  # the server began with anything else: no password asked
    start = len(client) - len(client.lstrip(b"\r\n"))
    if client[start:start + 4] in HEADERS:
        return client  # a client that begins with a frame
    end = start
    while end < len(client) and client[end] not in b"\r\n":
        if client[end:end + 4] in HEADERS and _completes(client[end:]):
            break
        end += 1
    if end - start > MAX_PASSWORD:
        return client
    return client[:start] + bytes(b if b in b"\r\n" else ord("*") for b in client[start:end]) + client[end:]


first_lines = st.sampled_from([SECRET + b"\r\n", SECRET + FETCH, SECRET, b"secrr1-et\n", FETCH, b"x" * 300,
                               b"sr1-25--\x0c\x00", b"pw" + CONFIG])
servers = st.sampled_from([b"sendchkpass", b"\r\nsendchkpass", b"sendch", b"", b"\n", CONFIG, b"cr1-3--5--0-ss1",
                           b"se\r\n"])


@st.composite
def connections(draw):
    """A client's and a server's bytes, and the order their bytes arrived in."""
    lead = draw(st.sampled_from([b"", b"\r\n", b"\n", b"\r"]))
    client = lead + draw(st.one_of(first_lines, stream)) + draw(stream)
    server = draw(servers) + draw(st.sampled_from([b"", b"readytogo", b"Failed Validation", CONFIG]))
    order = draw(st.permutations([True] * len(client) + [False] * len(server)))
    return client, server, order


def _through_redactor(client: bytes, server: bytes, order: list[bool], cuts: set[int]) -> bytes:
    """The client's bytes as a Redactor lets them out, the arrival order cut
    into reads at each change of side and at ``cuts``; the connection closes."""
    redactor: Redactor[int] = Redactor(hold_s=1e9)
    redactor.opened(1)
    done = {True: 0, False: 0}
    streams = {True: client, False: server}
    got = bytearray()
    i = 0
    while i < len(order):
        j = i + 1
        while j < len(order) and order[j] == order[i] and j not in cuts:
            j += 1
        side = order[i]
        redactor.read(1, C2S if side else S2C, streams[side][done[side]:done[side] + j - i], 0, 0.0)
        done[side] += j - i
        i = j
        got += b"".join(r.data for r in redactor.released() if r.direction is C2S)
    redactor.closed(1)
    redactor.event(1, 0)
    got += b"".join(r.data for r in redactor.released() if r.direction is C2S)
    return bytes(got)


def _masked_at(shown_bytes: bytes, client: bytes) -> set[int]:
    return {i for i, (a, b) in enumerate(zip(shown_bytes, client)) if a != b}


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(drawn=connections(), cuts=st.sets(st.integers(0, 300), max_size=40))
def test_the_rule_holds_for_any_arrival_order_and_any_reads(drawn, cuts):
    """Without a clock, what is masked is the rule's answer for the two
    streams, whatever the order their bytes came in and however they were cut
    into reads, one byte per read included.  (A verdict before the first line
    has ended may mask more of it: never anything past its first line break.)"""
    client, server, order = drawn
    want = expected(client, server)
    got = _through_redactor(client, server, order, set(range(len(order))))
    assert _through_redactor(client, server, order, cuts) == got
    assert len(got) == len(client) and all(a == b or a == ord("*") for a, b in zip(got, client))
    if b"readytogo" not in server and b"Failed Validation" not in server:
        assert got == want
    else:
        start = len(client) - len(client.lstrip(b"\r\n"))
        line_end = min([i for i in (client.find(b"\r", start), client.find(b"\n", start)) if i != -1] or [len(client)])
        assert _masked_at(want, client) <= _masked_at(got, client) <= set(range(start, line_end))


@pytest.mark.slow
@settings(max_examples=200, deadline=None)
@given(drawn=connections(), cuts=st.lists(st.integers(0, 300), max_size=40))
def test_a_mask_fed_in_any_reads_decides_at_the_same_bytes(drawn, cuts):
    """``LoginMask`` alone, the client's bytes in any reads after the server's:
    the same masked bytes, and never more undecided than a first line holds."""
    client, server, _ = drawn
    results = []
    for pieces in (chunked(client, cuts), [client[i:i + 1] for i in range(len(client))]):
        mask = LoginMask()
        mask.server(server)
        for piece in pieces:
            mask.client(piece)
            assert mask.undecided <= MAX_PASSWORD + 64 or b"sr1-" in client  # the line, and a text frame it waits on
        mask.end()
        results.append((mask.masked_end, shown(mask, client)))
    assert results[0] == results[1]
    assert results[0][1] == expected(client, server)
