"""The mutation vocabulary: changes to a session that know the grammar.

Each mutation takes a seeded ``random.Random``, a session, what the fuzzer
knows of the server and a donor session (for splicing), and returns a new
session; ``mutate`` applies one to four of them, drawn by weight, and names
them.  The text-frame ones work on the fields the codec reads (``rr1-D1--D2--D3-ss1``):
values at and past the ranges the codec checks, digit counts around the
Layout's widths, separators, headers and trailers; the rest work on the
session: truncation, splitting a frame across writes, pipelining, reordering,
duplicating and dropping frames, garbage, and the handshake's steps skipped,
repeated or spoiled.  docs/fuzz.md lists them.
"""

from __future__ import annotations

import random
from collections.abc import Callable

from whiztap.analyzer.fuzz.grammar import MAX_FRAME_BYTES, Frame, Knowledge, Session, normalise, request
from whiztap.analyzer.protocol.codec import (
    EXTERNAL_SCRIPTS,
    FIELD_WIDTHS,
    INTERNAL_SCRIPTS,
    MAX_CHANNEL,
    MAX_SEND_VALUE,
    MAX_SENSOR_DATA,
    MAX_SERVO_DATA,
    STOP_EXTERNAL,
    STOP_INTERNAL,
)
from whiztap.analyzer.protocol.framing import COMMAND_HEADER, CONFIG_HEADER, RESPONSE_HEADER, TRAILER

SEPARATOR = b"--"
# Values worth trying in each field of a text frame: each range's ends and one past.
BOUNDARIES: tuple[tuple[int, ...], ...] = (
    (0, MAX_CHANNEL, MAX_CHANNEL + 1, 24, 29, 99),
    (0, 1, MAX_SEND_VALUE, MAX_SEND_VALUE + 1, MAX_SENSOR_DATA + 1, MAX_SERVO_DATA + 1, 9999),
    (0, 1, 2, 3, INTERNAL_SCRIPTS.start, INTERNAL_SCRIPTS.stop - 1, STOP_INTERNAL, STOP_INTERNAL + 1,
     STOP_EXTERNAL, EXTERNAL_SCRIPTS.start, EXTERNAL_SCRIPTS.stop - 1, EXTERNAL_SCRIPTS.stop, 999),
)
HEADERS = (RESPONSE_HEADER, CONFIG_HEADER, b"rr2-", b"RR1-", COMMAND_HEADER[:-1], b"", COMMAND_HEADER * 2)
TRAILERS = (b"-ss2", TRAILER[1:], b"", TRAILER * 2, TRAILER[:-1], b"\r\n", TRAILER + b"\r\n")
SEPARATORS = (b"-", b"---", b"", b"-_", b"- -")
EVERY_BYTE_UP_TO = 24  # longest frame split into single bytes (each write costs a pause)

Mutation = Callable[[random.Random, Session, Knowledge, Session], Session]


def _text_fields(data: bytes) -> list[bytes] | None:
    """The three fields of a well-shaped text frame, or None."""
    if len(data) < 8 or data[3:4] != b"-" or not data.endswith(TRAILER):
        return None
    fields = data[4:-len(TRAILER)].split(SEPARATOR)
    return fields if len(fields) == 3 else None


def _pick(rng: random.Random, session: Session, fits: Callable[[Frame], bool]) -> int | None:
    places = [i for i, f in enumerate(session) if fits(f)]
    return rng.choice(places) if places else None


def _put(session: Session, i: int, frame: Frame) -> Session:
    return session[:i] + (frame,) + session[i + 1:]


def _rewrite(frame: Frame, at: int, digits: bytes) -> Frame:
    fields = _text_fields(frame.data)
    assert fields is not None
    fields[at] = digits
    return Frame(frame.data[:4] + SEPARATOR.join(fields) + TRAILER, pipelined=frame.pipelined)


def _numeric(frame: Frame) -> bool:
    fields = _text_fields(frame.data)
    return fields is not None and all(d.isdigit() for d in fields)


def _on_field(rng: random.Random, session: Session, change: Callable[[random.Random, int, bytes], bytes]) -> Session:
    """``change`` one field of a text frame (its position and digits in, new
    digits out); half the time the same field of every such frame, as a
    client that writes that field wrongly would."""
    i = _pick(rng, session, _numeric)
    if i is None:
        return session
    at = rng.randrange(3)
    fields = _text_fields(session[i].data)
    assert fields is not None
    if rng.random() < 0.5:
        return _put(session, i, _rewrite(session[i], at, change(rng, at, fields[at])))
    state = rng.getstate()  # each frame's field changed by the same draw
    out = []
    for frame in session:
        if _numeric(frame):
            rng.setstate(state)
            digits = _text_fields(frame.data)[at]  # type: ignore[index]  # a numeric frame has its fields
            frame = _rewrite(frame, at, change(rng, at, digits))
        out.append(frame)
    return tuple(out)


def field_value(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """A field set to a boundary of its range, or one past it."""
    return _on_field(rng, session, lambda r, at, _: b"%d" % r.choice(BOUNDARIES[at]))


def digit_count(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """A field written with another number of digits: zero-padded by one or
    two, cut to one, or one past the Layout's width (so 3 digits where 1-2
    or 4 are expected)."""
    def change(r: random.Random, at: int, digits: bytes) -> bytes:
        width = r.choice((1, len(digits) + 1, len(digits) + 2, FIELD_WIDTHS[at] + 1))
        return digits.rjust(width, b"0") if width >= len(digits) else digits[-width:]
    return _on_field(rng, session, change)


def _replace_part(rng: random.Random, session: Session, old: bytes, choices: tuple[bytes, ...],
                  where: str) -> Session:
    i = _pick(rng, session, lambda f: old in f.data)
    if i is None:
        return session
    data = session[i].data
    at = {"first": data.find(old), "last": data.rfind(old), "any": -1}[where]
    if at < 0:
        spots = [j for j in range(len(data)) if data.startswith(old, j)]
        at = rng.choice(spots)
    new = data[:at] + rng.choice(choices) + data[at + len(old):]
    return _put(session, i, Frame(new, pipelined=session[i].pipelined))


def separator(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """One '--' between fields changed or dropped."""
    return _replace_part(rng, session, SEPARATOR, SEPARATORS, "any")


def header(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """The 'rr1-' header changed, dropped or doubled."""
    return _replace_part(rng, session, COMMAND_HEADER, HEADERS, "first")


def trailer(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """The '-ss1' trailer changed, dropped, doubled or followed by a line break."""
    return _replace_part(rng, session, TRAILER, TRAILERS, "last")


def truncate(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """A frame cut short (what follows it then arrives glued to its head)."""
    i = _pick(rng, session, lambda f: len(f.data) > 1)
    if i is None:
        return session
    data = session[i].data
    return _put(session, i, Frame(data[:rng.randrange(1, len(data))], pipelined=session[i].pipelined))


def garbage(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """Bytes that form no frame inserted, or one byte of a frame replaced."""
    i = _pick(rng, session, lambda f: bool(f.data))
    if i is not None and rng.random() < 0.5:
        data = bytearray(session[i].data)
        data[rng.randrange(len(data))] = rng.randrange(256)
        return _put(session, i, Frame(bytes(data), pipelined=session[i].pipelined))
    junk = Frame(bytes(rng.randrange(256) for _ in range(rng.randint(1, 8))))
    at = rng.randint(0, len(session))
    return session[:at] + (junk,) + session[at:]


def split(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """A frame sent in pieces, so that it reaches the server across reads: cut
    at a field boundary, anywhere, or one byte at a time."""
    i = _pick(rng, session, lambda f: len(f.data) > 1)
    if i is None:
        return session
    frame = session[i]
    size = len(frame.data)
    how = rng.randrange(3)
    if how == 0 and size <= EVERY_BYTE_UP_TO:
        cuts = tuple(range(1, size))
    elif how == 1 and b"-" in frame.data[1:]:
        cuts = (rng.choice([j for j in range(1, size) if frame.data[j] == 0x2D]),)
    else:
        cuts = (rng.randrange(1, size),)
    return _put(session, i, frame.replace(cuts=cuts))


def pipeline(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """A run of frames sent back to back, without waiting for answers."""
    if len(session) < 2:
        return session
    start = rng.randrange(1, len(session))
    end = rng.randint(start + 1, len(session))
    return session[:start] + tuple(f.replace(pipelined=True) for f in session[start:end]) + session[end:]


def reorder(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """Two frames swapped (the handshake's included)."""
    if len(session) < 2:
        return session
    a, b = sorted(rng.sample(range(len(session)), 2))
    out = list(session)
    out[a], out[b] = out[b], out[a]
    return tuple(out)


def duplicate(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """A frame sent twice (a repeated password becomes a stand-in)."""
    if not session:
        return session
    i = rng.randrange(len(session))
    return session[:i + 1] + session[i:]


def drop(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """A frame left out (the password's too: the handshake skipped)."""
    if len(session) < 2:
        return session
    i = rng.randrange(len(session))
    return session[:i] + session[i + 1:]


def handshake(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """The password spoiled (a stand-in, one byte short, a bare line break),
    or a password step added where none was."""
    i = _pick(rng, session, lambda f: bool(f.secret))
    if i is None:
        return (Frame(secret="password"),) + session
    return _put(session, i, session[i].replace(secret=rng.choice(("stand-in", "short", "empty-line"))))


def insert(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """A well-formed request added anywhere."""
    at = rng.randint(0, len(session))
    return session[:at] + (request(rng, k),) + session[at:]


def splice(rng: random.Random, session: Session, k: Knowledge, donor: Session) -> Session:
    """Frames of another session of the corpus inserted."""
    if not donor:
        return session
    a = rng.randrange(len(donor))
    b = rng.randint(a + 1, len(donor))
    at = rng.randint(0, len(session))
    return session[:at] + donor[a:b] + session[at:]


# Every mutation by name, with its weight: the grammar's own most often.
MUTATIONS: dict[str, tuple[Mutation, int]] = {
    "field-value": (field_value, 4), "digit-count": (digit_count, 4), "separator": (separator, 2),
    "header": (header, 2), "trailer": (trailer, 2), "truncate": (truncate, 2), "garbage": (garbage, 1),
    "split": (split, 3), "pipeline": (pipeline, 2), "reorder": (reorder, 1), "duplicate": (duplicate, 1),
    "drop": (drop, 1), "handshake": (handshake, 1), "insert": (insert, 2), "splice": (splice, 1),
}
_NAMES = tuple(MUTATIONS)
_WEIGHTS = tuple(weight for _, weight in MUTATIONS.values())


def mutate(rng: random.Random, session: Session, knowledge: Knowledge,
           donor: Session = ()) -> tuple[Session, tuple[str, ...]]:
    """One to four mutations in a row; the session as it may be sent, and their names."""
    names = tuple(rng.choices(_NAMES, _WEIGHTS, k=rng.randint(1, 4)))
    for name in names:
        session = MUTATIONS[name][0](rng, session, knowledge, donor)
    return normalise(tuple(f if len(f.data) <= MAX_FRAME_BYTES else f.replace(data=f.data[:MAX_FRAME_BYTES])
                           for f in session)), names
