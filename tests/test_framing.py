"""The framer's invariants: lossless, chunking-independent, total, bounded."""

import re
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from whiztap.analyzer.protocol.framing import (
    DEFAULT_MAX_ITEM,
    MAX_PASSWORD,
    MIN_MAX_ITEM,
    Framer,
    Item,
    ItemKind,
    Unframed,
)
from tests.spec_vectors import ALL_FRAMES, COMMANDS, HANDSHAKE_SERVER, RESPONSES
from tests.streams import big_jpeg, TINY_JPEG, TINY_PNG, chunked, frame_all, stream_pieces


REPO = Path(__file__).parent.parent
# the framer's state about a password, private to framing.py (images.py is the framer's too)
_PRIVATE = re.compile(r"\._(password_mode|in_password|password_begun|password_left)\b")


def shape(items: list[Item]) -> list[tuple]:
    return [(i.kind, i.raw, i.reason) for i in items]


# -- golden vectors ----------------------------------------------------------------


@pytest.mark.parametrize("raw", [raw for raw, _ in COMMANDS])
def test_each_spec_command_is_one_item(raw):
    kind = ItemKind.SET_CONFIG if raw.startswith(b"sr1-") else ItemKind.COMMAND
    assert shape(frame_all([raw])) == [(kind, raw, None)]


@pytest.mark.parametrize("raw", [raw for raw, _ in RESPONSES])
def test_each_spec_response_is_one_item(raw):
    kind = ItemKind.CONFIG if raw.startswith(b"sr1-") else ItemKind.RESPONSE
    assert shape(frame_all([raw])) == [(kind, raw, None)]


def test_spec_frames_back_to_back_split_at_every_offset():
    stream = b"".join(ALL_FRAMES)
    whole = shape(frame_all([stream]))
    assert [raw for _, raw, _ in whole] == ALL_FRAMES
    for cut in range(1, len(stream)):
        assert shape(frame_all([stream[:cut], stream[cut:]])) == whole


def test_one_byte_at_a_time():
    stream = b"".join(ALL_FRAMES) + b"sendchkpass\r\nreadytogo" + TINY_JPEG + TINY_PNG
    assert shape(frame_all([stream[i:i + 1] for i in range(len(stream))])) == shape(frame_all([stream]))


@pytest.mark.parametrize("word", HANDSHAKE_SERVER)
@pytest.mark.parametrize("eol", [b"", b"\r\n", b"\n", b"\r"])
def test_handshake_words_with_optional_line_break(word, eol):
    items = frame_all([word + eol + b"cr1-0--0--0-ss1"])
    expected = [(ItemKind.HANDSHAKE, word, None)]
    if eol:
        expected.append((ItemKind.EOL, eol, None))
    expected.append((ItemKind.RESPONSE, b"cr1-0--0--0-ss1", None))
    assert shape(items) == expected


def test_password_runs_until_the_verdict_closes_it():
    framer = Framer()
    framer.expect_password()
    assert framer.feed(b"se", 1) == []
    assert framer.feed(b"cret", 2) == []
    [item] = framer.close_password(3)
    assert item == Item(ItemKind.PASSWORD, b"secret", 1, 3)
    assert shape(framer.feed(b"rr1-24--0--0-ss1", 4)) == [(ItemKind.COMMAND, b"rr1-24--0--0-ss1", None)]


def test_password_ends_at_line_break_or_frame_header():
    framer = Framer()
    framer.expect_password()
    items = framer.feed(b"pw\r\nrr1-24--0--0-ss1", 1)
    assert shape(items) == [(ItemKind.PASSWORD, b"pw", None), (ItemKind.EOL, b"\r\n", None),
                            (ItemKind.COMMAND, b"rr1-24--0--0-ss1", None)]
    framer = Framer()
    framer.expect_password()
    assert shape(framer.feed(b"pwrr1-24--0--0-ss1", 1))[0] == (ItemKind.PASSWORD, b"pw", None)


# -- the password: the client's first line (docs/protocol.md, A14) ----------------------------

SET_CONFIG = b"sr1-25--\x0c\x00\x00\x0c\x01\x02\x18--0-ss1"
P, E, C = ItemKind.PASSWORD, ItemKind.EOL, ItemKind.COMMAND


def frame_password(data: bytes, bytewise: bool = False) -> list[tuple]:
    framer = Framer()
    framer.expect_password()
    chunks = [data[i:i + 1] for i in range(len(data))] if bytewise else [data]
    items = [item for t, chunk in enumerate(chunks) for item in framer.feed(chunk, t)]
    return shape(items + framer.end(len(chunks)))


@pytest.mark.parametrize("data, expected", [
    (b"secrr1-et\r\nrr1-24--0--0-ss1",  # a header whose frame never completes is part of the password
     [(P, b"secrr1-et", None), (E, b"\r\n", None), (C, b"rr1-24--0--0-ss1", None)]),
    (b"\r\n\npw\r\n", [(E, b"\r\n", None), (E, b"\n", None), (P, b"pw", None), (E, b"\r\n", None)]),
    (b"\rpw" + SET_CONFIG, [(E, b"\r", None), (P, b"pw", None), (ItemKind.SET_CONFIG, SET_CONFIG, None)]),
    (b"\n" + b"x" * MAX_PASSWORD + b"\r\n", [(E, b"\n", None), (P, b"x" * MAX_PASSWORD, None), (E, b"\r\n", None)]),
    (b"x" * (MAX_PASSWORD + 1) + b"\r\n",  # longer than a password: bytes like any others
     [(ItemKind.UNFRAMED, b"x" * (MAX_PASSWORD + 1), Unframed.GARBAGE), (E, b"\r\n", None)]),
    (b"\npwsr1-\x02000200-ss1",
     [(E, b"\n", None), (P, b"pw", None), (ItemKind.CONFIG, b"sr1-\x02000200-ss1", None)]),
])
def test_the_password_is_the_first_line_up_to_a_line_break_or_a_frame_that_completes(data, expected):
    assert frame_password(data) == expected
    assert frame_password(data, bytewise=True) == expected


def test_a_verdict_before_the_line_ends_leaves_the_rest_of_the_line_a_password():
    """A server may judge at the first wrong byte: what came is handed over at
    once, and the rest of the line is the password's too, not garbage."""
    framer = Framer()
    framer.expect_password()
    assert framer.feed(b"K", 1) == []
    assert framer.close_password(2) == [Item(P, b"K", 1, 2)]
    assert not framer.password_pending  # the proxy in the middle frames what follows
    assert framer.in_password  # ... and the password rule masks the rest of the line
    assert shape(framer.feed(b"x9hunter\r\nrr1-24--0--0-ss1", 3)) == [
        (P, b"x9hunter", None), (E, b"\r\n", None), (C, b"rr1-24--0--0-ss1", None)]
    assert not framer.in_password


def test_what_the_framer_says_of_a_password_it_says_publicly():
    """``password_pending`` (until the server's verdict) and ``in_password``
    (until the line ends) are what the middle's lane and the password rule
    read: nothing outside framing.py reads the framer's private state."""
    framer = Framer()
    assert (framer.password_pending, framer.in_password) == (False, False)
    framer.expect_password()
    assert (framer.password_pending, framer.in_password) == (True, True)
    framer.feed(b"sec", 1)
    assert (framer.password_pending, framer.in_password) == (True, True)
    framer.feed(b"ret\r\n", 2)
    assert (framer.password_pending, framer.in_password) == (False, False)
    framer.expect_password()
    framer.feed(b"rr1-24--0--0-ss1", 3)  # a line that begins with a frame header is no password
    assert (framer.password_pending, framer.in_password) == (False, False)
    readers = [path for root in ("analyzer", "sniffer", "tui") for path in (REPO / root).rglob("*.py")
               if path.name != "framing.py" and _PRIVATE.search(path.read_text())]
    assert readers == []


def test_images_are_recognised_whole():
    items = frame_all([TINY_JPEG + TINY_PNG + b"rr1-24--0--0-ss1"])
    assert shape(items) == [(ItemKind.IMAGE, TINY_JPEG, None), (ItemKind.IMAGE, TINY_PNG, None),
                            (ItemKind.COMMAND, b"rr1-24--0--0-ss1", None)]


def test_jpeg_of_headers_only_ends_at_its_end_marker():
    headers_only = b"\xff\xd8\xff\xe0\x00\x04ab\xff\xd9"
    framer = Framer()
    assert shape(framer.feed(headers_only, 1)) == [(ItemKind.IMAGE, headers_only, None)]


def test_timestamps_of_first_and_last_chunk():
    framer = Framer()
    assert framer.feed(b"rr1-0--", 10) == []
    assert framer.feed(b"60--0", 20) == []
    first, second = framer.feed(b"-ss1rr1-1--1--0-ss1", 30)
    assert (first.t_start_ns, first.t_end_ns) == (10, 30)
    assert (second.t_start_ns, second.t_end_ns) == (30, 30)


# -- adversarial input -----------------------------------------------------------------


@pytest.mark.parametrize("payload_byte", [ord("-"), ord("s"), ord("1"), ord("0"), ord("r")])
def test_set_config_payload_bytes_that_look_like_the_trailer(payload_byte):
    # a Dev# byte and a checksum byte equal to trailer characters
    raw = b"sr1-25--" + bytes([payload_byte, 3, 1, 12, 4, 0]) + bytes([payload_byte]) + b"--0-ss1"
    assert shape(frame_all([raw, b"rr1-24--0--0-ss1"])) == [
        (ItemKind.SET_CONFIG, raw, None), (ItemKind.COMMAND, b"rr1-24--0--0-ss1", None)]


def test_set_config_checksum_dash_then_trailer():
    raw = b"sr1-25--" + bytes([12, 0, 0]) + b"-" + b"--0-ss1"
    assert shape(frame_all([raw])) == [(ItemKind.SET_CONFIG, raw, None)]


def test_config_count_byte_equal_to_dash():
    raw = b"sr1-" + bytes([0x2D]) + b"000" * 0x2D + b"-ss1"
    assert shape(frame_all([raw, b"cr1-1--5--0-ss1"])) == [
        (ItemKind.CONFIG, raw, None), (ItemKind.RESPONSE, b"cr1-1--5--0-ss1", None)]


def test_config_count_byte_equal_to_two_is_not_set_config():
    raw = b"sr1-" + bytes([ord("2")]) + b"200" * ord("2") + b"-ss1"
    assert shape(frame_all([raw])) == [(ItemKind.CONFIG, raw, None)]


def test_layout_form_set_config_is_framed_as_set_config():
    raw = b"sr1-" + bytes([25]) + bytes([12, 0, 0, 12, 1, 0]) + bytes([24]) + b"0-ss1"
    assert shape(frame_all([raw])) == [(ItemKind.SET_CONFIG, raw, None)]


def test_garbage_between_frames_resynchronises():
    items = frame_all([b"rr1-24--0--0-ss1" + b"\x00\xffjunk" + b"rr1-0--0--2-ss1"])
    assert shape(items) == [
        (ItemKind.COMMAND, b"rr1-24--0--0-ss1", None),
        (ItemKind.UNFRAMED, b"\x00\xffjunk", Unframed.GARBAGE),
        (ItemKind.COMMAND, b"rr1-0--0--2-ss1", None),
    ]


def test_frame_cut_short_by_the_next_header():
    items = frame_all([b"rr1-0--6rr1-0--0--2-ss1"])
    assert shape(items) == [(ItemKind.UNFRAMED, b"rr1-0--6", Unframed.TRUNCATED),
                            (ItemKind.COMMAND, b"rr1-0--0--2-ss1", None)]


def test_stream_ending_inside_a_frame():
    assert shape(frame_all([b"rr1-24--0--0-ss1", b"cr1-3--1"])) == [
        (ItemKind.COMMAND, b"rr1-24--0--0-ss1", None), (ItemKind.UNFRAMED, b"cr1-3--1", Unframed.TRUNCATED)]


def test_frames_with_spaces_and_letters_are_still_framed_for_the_decoder():
    assert shape(frame_all([b"rr1-0 --6x--0-ss1"])) == [(ItemKind.COMMAND, b"rr1-0 --6x--0-ss1", None)]


def test_endless_stream_without_trailer_stays_bounded():
    framer = Framer(max_item=MIN_MAX_ITEM)
    emitted = 0
    chunk = b"sr1-25--" + b"\x01\x02\x03" * 300
    for t in range(200):
        for item in framer.feed(chunk if t == 0 else b"\x05\x06\x07" * 100, t):
            assert item.kind is ItemKind.UNFRAMED
            emitted += len(item.raw)
        assert framer.buffered < MIN_MAX_ITEM
    assert emitted > 50_000


def test_endless_garbage_stays_bounded():
    framer = Framer()
    for t in range(100):
        framer.feed(b"\x00" * 10_000, t)
        assert framer.buffered < DEFAULT_MAX_ITEM


def test_max_item_has_a_floor():
    with pytest.raises(ValueError):
        Framer(max_item=MIN_MAX_ITEM - 1)


# -- properties ------------------------------------------------------------------------


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=600), cuts=st.lists(st.integers(0, 600), max_size=20))
def test_lossless_and_chunking_independent_on_any_bytes(data, cuts):
    one = frame_all([data])
    many = frame_all(chunked(data, cuts))
    assert b"".join(i.raw for i in many) == data
    assert shape(many) == shape(one)
    assert all(i.raw for i in many)


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(pieces=stream_pieces(), cuts=st.lists(st.integers(0, 4000), max_size=30))
def test_lossless_and_chunking_independent_on_protocol_like_streams(pieces, cuts):
    data = b"".join(pieces)
    one = frame_all([data])
    many = frame_all(chunked(data, cuts))
    assert b"".join(i.raw for i in many) == data
    assert shape(many) == shape(one)


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(lead=st.sampled_from([b"", b"\r\n", b"\n", b"\r", b"x" * 300]), pieces=stream_pieces(),
       cuts=st.lists(st.integers(0, 4000), max_size=30))
def test_a_password_is_cut_the_same_in_any_reads(lead, pieces, cuts):
    """Told to expect a password, the framer cuts the same items from any
    chunking, loses nothing, and its one password item is the first line (line
    breaks before it aside), never longer than a password may be."""
    data = lead + b"".join(pieces)
    framer = Framer()
    framer.expect_password()
    one = shape(framer.feed(data, 0) + framer.end(1))
    framer = Framer()
    framer.expect_password()
    many = [item for t, chunk in enumerate(chunked(data, cuts)) for item in framer.feed(chunk, t)]
    many = shape(many + framer.end(10**6))
    assert many == one and b"".join(raw for _, raw, _ in one) == data
    kinds = [kind for kind, _, _ in one]
    passwords = [raw for kind, raw, _ in one if kind is P]
    assert len(passwords) <= 1 and all(len(raw) <= MAX_PASSWORD for raw in passwords)
    if passwords:
        assert set(kinds[:kinds.index(P)]) <= {E}  # only line breaks before it
        assert not passwords[0].startswith((b"rr1-", b"cr1-", b"sr1-"))


@pytest.mark.slow
@settings(max_examples=100, deadline=None)
@given(pieces=stream_pieces(), cuts=st.lists(st.integers(0, 4000), max_size=30))
def test_bounded_with_smallest_limit(pieces, cuts):
    framer = Framer(max_item=MIN_MAX_ITEM, max_image=MIN_MAX_ITEM)
    data = b"".join(pieces) * 3
    out = []
    for t, chunk in enumerate(chunked(data, cuts)):
        out += framer.feed(chunk, t)
        assert framer.buffered < MIN_MAX_ITEM
    out += framer.end(10**6)
    assert b"".join(i.raw for i in out) == data
    assert all(len(i.raw) <= MIN_MAX_ITEM for i in out)


@pytest.mark.slow
@settings(max_examples=200, deadline=None)
@given(frames=st.lists(st.sampled_from(ALL_FRAMES), min_size=1, max_size=30),
       cuts=st.lists(st.integers(0, 3000), max_size=30))
def test_valid_frames_are_recovered_exactly(frames, cuts):
    items = frame_all(chunked(b"".join(frames), cuts))
    assert [i.raw for i in items] == frames
    assert all(i.kind is not ItemKind.UNFRAMED for i in items)


# -- camera images larger than the frame limit -------------------------------------------


def test_an_image_of_several_megabytes_is_one_item_in_any_reads():
    """The spec sets no size for a camera picture: it is one item, however it
    arrives, while other items keep the 64 KiB bound (a 5 MB picture fed 1 KiB at a
    time is walked once: each read looks only at what it added)."""
    picture = big_jpeg(5_000_000)
    tail = b"cr1-12--5--0-ss1"
    for chunks in ([picture + tail], chunked(picture + tail, list(range(0, len(picture) + 16, 1024)))):
        items = frame_all(chunks)
        assert [(i.kind, len(i.raw)) for i in items] == [(ItemKind.IMAGE, len(picture)),
                                                        (ItemKind.RESPONSE, len(tail))]


def test_an_image_past_its_limit_is_cut_where_any_chunking_cuts_it():
    picture = big_jpeg(300_000)
    one = frame_all([picture], max_image=100_000)
    many = frame_all(chunked(picture, list(range(0, len(picture), 777))), max_image=100_000)
    assert shape(one) == shape(many)
    assert (one[0].kind, one[0].reason, len(one[0].raw)) == (ItemKind.UNFRAMED, Unframed.OVERSIZE, 100_000)


def test_the_framer_holds_no_more_than_the_image_limit():
    framer = Framer(max_image=100_000)
    for t, chunk in enumerate(chunked(big_jpeg(1_000_000), list(range(0, 1_000_000, 4096)))):
        framer.feed(chunk, t)
        assert framer.buffered < 100_000 + 4096


@pytest.mark.slow
@settings(max_examples=150, deadline=None)
@given(sizes=st.lists(st.integers(0, 6000), min_size=1, max_size=4), pieces=stream_pieces(),
       cuts=st.lists(st.integers(0, 30000), max_size=40), limit=st.sampled_from([MIN_MAX_ITEM, 4000, 10**6]))
def test_images_are_chunking_independent_at_any_limit(sizes, pieces, cuts, limit):
    data = b"".join(big_jpeg(n, seed=n) + p for n, p in zip(sizes, [*pieces, b"", b"", b"", b""]))
    one = frame_all([data], max_item=MIN_MAX_ITEM, max_image=limit)
    many = frame_all(chunked(data, cuts), max_item=MIN_MAX_ITEM, max_image=limit)
    assert b"".join(i.raw for i in many) == data
    assert shape(many) == shape(one)
