"""``probe client``'s cases, sans-IO: what the server whiztap plays does to its replies.

whiztap plays a server that behaves as the simulator does (the runner,
``whiztap.sniffer.probe.client_run``, drives the simulator's robot) with an
adversarial schedule layered on its replies: cut into pieces, held back,
preceded by stray bytes, replaced by a close, by silence or by the largest
camera picture.  A case is a schedule and what the client must do under it.

The catalogue is built from the protocol's tables, not from hand-written
frames: one handshake case per verdict the server may give
(``handshake.VERDICTS``), the field cuts from the frame headers, separator and
trailer (``framing``), the stray bytes from those that start no item (the
framer's openings), the largest picture from the analyzer's image limit.

Every case judges the client's traffic with the analyzer's session (its
error-severity violations fail the case) and wants the client to end by
itself within the run's wait.  Where the spec says what a conforming server
does, the case is "normal" (``must_succeed``): the client has no reason to
fail and exit status 0 is expected.  Where the server misbehaves (silence,
a close, garbage, a refused password) the spec says nothing of what the
client should report, so any exit status passes, but not a crash.
"""

from __future__ import annotations

import fnmatch
import itertools
import random
from collections.abc import Iterable
from dataclasses import dataclass
from enum import StrEnum

from whiztap.analyzer.protocol.framing import DEFAULT_MAX_IMAGE, FRAME_HEADERS, TRAILER
from whiztap.analyzer.protocol.handshake import FAILED_VALIDATION, READYTOGO, VERDICTS
from whiztap.analyzer.protocol.images import JPEG_SOI
from whiztap.analyzer.protocol.observations import may_tell

SEPARATOR = b"--"
GAP_S = 0.002  # between the pieces of a cut reply, so that a client reading at once gets them apart
MAX_GAPPED = 64  # a reply cut in more pieces (an image) goes without gaps: TCP may join them
SLOW_DELAY_S = 0.25  # how long each of the slow server's writes waits
LINGER_S = 1.0  # how long the server keeps reading after Failed Validation, for the client to close
LARGEST_IMAGE = DEFAULT_MAX_IMAGE  # the spec sets no limit; this is the largest the analyzer takes as one item
_COMMENT = 0xFE  # JPEG COM marker: padding a viewer ignores
_MAX_SEGMENT = 0xFFFF - 2  # a segment's payload: its length field counts itself
# Stray bytes that begin no item (no frame header, handshake word, image or line break can start with them).
GARBAGE_ALPHABET = bytes(b for b in range(0x20, 0x7F) if not may_tell(bytes([b])) and b not in b"\r\n\xff\x89")
MAX_GARBAGE = 8


class Need(StrEnum):
    """What the client must do for a schedule to have something to act on;
    a case whose need was not met is skipped with the reason."""

    NOTHING = "nothing"
    ANSWER = "answer"  # send a request the server answers
    IMAGE = "image"  # ask for a camera picture


NEED_REASON = {
    Need.ANSWER: "the client sent no request that has an answer, so the schedule had nothing to act on",
    Need.IMAGE: "the client never sent Fetch Camera Image",
}


class Cut(StrEnum):
    NONE = "none"
    BYTES = "bytes"  # one byte at a time
    FIELDS = "fields"  # at every field boundary


@dataclass(frozen=True, slots=True)
class Schedule:
    """How the played server departs from the simulator.  ``verdict``: the
    handshake's answer to any password (None: the simulator's own check);
    ``idle``: nothing is ever sent; ``close_at_answer``: close instead of
    sending the Nth answer; ``largest_image``: camera pictures padded to
    ``LARGEST_IMAGE`` bytes."""

    cut: Cut = Cut.NONE
    delay_s: float = 0.0
    garbage: bool = False
    verdict: bytes | None = None
    idle: bool = False
    close_at_answer: int | None = None
    largest_image: bool = False


@dataclass(frozen=True, slots=True)
class ClientCase:
    """One case of the catalogue.  ``must_succeed``: the client faces a server
    that keeps the spec and should exit 0; ``winsock_only``: the case is about
    the password handshake, which VPN mode has not."""

    id: str
    title: str
    spec: str
    schedule: Schedule
    must_succeed: bool
    need: Need = Need.NOTHING
    winsock_only: bool = False

    def applies(self, mode: str) -> str:
        """Why the case cannot run in ``mode`` ("" when it can)."""
        return "VPN mode has no password handshake" if self.winsock_only and mode == "vpn" else ""


_VERDICT_CASES = {
    READYTOGO: ("session.baseline", "the simulator as it is: the password accepted, every request answered", True),
    FAILED_VALIDATION: ("handshake.failed-validation",
                        "'Failed Validation' to any password: the client sends nothing more and closes", False),
}


def _verdict_cases() -> list[ClientCase]:
    cases = []
    for verdict in VERDICTS:
        case_id, title, normal = _VERDICT_CASES[verdict]
        cases.append(ClientCase(case_id, title, "Functional Flow",
                                Schedule(verdict=None if normal else verdict), must_succeed=normal,
                                winsock_only=not normal))
    return cases


def catalogue() -> list[ClientCase]:
    """Every case, in the order they run."""
    flow, api = "Functional Flow", "API Definition"
    return [
        *_verdict_cases(),
        ClientCase("split.bytes", "every server write one byte at a time (handshake words, answers, images)",
                   api, Schedule(cut=Cut.BYTES), must_succeed=True),
        ClientCase("split.fields", "answers cut at every field boundary (header, '--' separators, trailer)",
                   api, Schedule(cut=Cut.FIELDS), must_succeed=True, need=Need.ANSWER),
        ClientCase("slow.answers", f"every server write, the handshake verdict too, {SLOW_DELAY_S:g} s late",
                   api, Schedule(delay_s=SLOW_DELAY_S), must_succeed=True),
        ClientCase("camera.largest", f"Fetch Camera Image answered with a {LARGEST_IMAGE >> 20} MiB JPEG "
                   "(the largest the analyzer takes; the spec sets no limit)", "Fetch Camera Image",
                   Schedule(largest_image=True), must_succeed=True, need=Need.IMAGE),
        ClientCase("garbage.before-answer", "stray bytes that form no item before every answer",
                   api, Schedule(garbage=True), must_succeed=False, need=Need.ANSWER),
        ClientCase("close.mid-session", "the server closes the connection instead of sending the first answer",
                   api, Schedule(close_at_answer=1), must_succeed=False, need=Need.ANSWER),
        ClientCase("idle.server", "the server accepts the connection and never sends a byte",
                   flow, Schedule(idle=True), must_succeed=False),
    ]


def select(cases: Iterable[ClientCase], patterns: Iterable[str]) -> list[ClientCase]:
    """The cases whose id matches one of the glob ``patterns`` (all of them for none)."""
    patterns = list(patterns)
    return [c for c in cases if not patterns or any(fnmatch.fnmatchcase(c.id, p) for p in patterns)]


def catalogue_table(cases: Iterable[ClientCase]) -> str:
    """The cases as a Markdown table (what ``probe client --list`` prints and docs/probe.md holds)."""
    rows = ["| id | spec section | a conforming server? | what the played server does |", "|---|---|---|---|"]
    for case in cases:
        normal = "yes: exit 0 expected" if case.must_succeed else "no: any exit status but a crash"
        only = " (winsock only)" if case.winsock_only else ""
        rows.append(f"| `{case.id}` | {case.spec} | {normal} | {case.title}{only} |")
    return "\n".join(rows) + "\n"


# -- what a schedule does to one reply ---------------------------------------------------------------


def field_cuts(data: bytes) -> list[bytes]:
    """``data`` cut at every field boundary of a frame: after its header, on
    both sides of each separator, before its trailer (other bytes whole)."""
    if not data.startswith(FRAME_HEADERS) or not data.endswith(TRAILER):
        return [data]
    end = len(data) - len(TRAILER)
    bounds = {len(FRAME_HEADERS[0]), end}
    at = data.find(SEPARATOR, 0, end)
    while at != -1:
        bounds.update((at, at + len(SEPARATOR)))
        at = data.find(SEPARATOR, at + len(SEPARATOR), end)
    points = [0, *sorted(b for b in bounds if 0 < b < len(data)), len(data)]
    return [data[a:b] for a, b in itertools.pairwise(points) if b > a]


def cut(data: bytes, how: Cut) -> list[bytes]:
    """The pieces ``data`` is written in (none for no bytes)."""
    if not data:
        return []
    if how is Cut.BYTES:
        return [data[i:i + 1] for i in range(len(data))]
    if how is Cut.FIELDS:
        return field_cuts(data)
    return [data]


def garbage(rng: random.Random) -> bytes:
    """1 to ``MAX_GARBAGE`` stray bytes that no item can begin with."""
    return bytes(rng.choice(GARBAGE_ALPHABET) for _ in range(rng.randint(1, MAX_GARBAGE)))


def pad_jpeg(jpeg: bytes, size: int) -> bytes:
    """``jpeg`` grown to exactly ``size`` bytes with comment segments after its
    SOI: still one well-formed picture (a viewer shows the same image), and
    walked segment by segment by a framer."""
    if not jpeg.startswith(JPEG_SOI):
        raise ValueError("not a JPEG")
    missing = size - len(jpeg)
    if missing == 0:
        return jpeg
    count = -(-missing // (_MAX_SEGMENT + 4))  # each segment: marker, length, payload
    room = missing - 4 * count
    if room < 0:
        raise ValueError(f"cannot pad a {len(jpeg)}-byte JPEG to {size} bytes")
    segments = [bytes((0xFF, _COMMENT)) + (n + 2).to_bytes(2, "big") + b" " * n
                for n in (room // count + (i < room % count) for i in range(count))]
    return jpeg[:2] + b"".join(segments) + jpeg[2:]


class Shaper:
    """One connection's schedule applied to the simulator's replies, in order:
    each reply becomes the pieces to write (none when the server is idle), or
    None where the server closes instead.  Seeded, so one seed and one
    sequence of requests give the same stray bytes."""

    def __init__(self, schedule: Schedule, seed: int | str) -> None:
        self.schedule = schedule
        self.rng = random.Random(f"whiztap-probe-client:{seed}")
        self.answers = 0  # answers the simulator gave so far

    def shape(self, data: bytes, answer: bool) -> list[bytes] | None:
        schedule = self.schedule
        if answer:
            self.answers += 1
            if self.answers == schedule.close_at_answer:
                return None
            if schedule.garbage:
                data = garbage(self.rng) + data
        if schedule.idle:
            return []
        return cut(data, schedule.cut)
