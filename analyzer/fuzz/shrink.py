"""Shrinking a failing session: delta debugging over frames, then over bytes.

Sans-IO: ``shrink`` is a generator that yields candidate sessions and is sent
back whether each one still fails the same way (the runner executes it against
the server).  It returns the smallest failing session it found; the runner may
stop sending at any time (its budget) and keep the last one that failed.  The
order of candidates depends only on the session and the answers, so a shrink
is as repeatable as the server.

Zeller's ddmin: try to keep only one of n chunks, then to drop one of n chunks;
on success restart from the smaller input, else double n.  Frames first (whole
frames dropped), then each frame's bytes (a frame's cuts follow its bytes),
then what is not needed of how the frames are sent (cuts, pipelining).
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Sequence
from typing import TypeVar

from whiztap.analyzer.fuzz.grammar import Frame, Session

T = TypeVar("T")
Shrinking = Generator[Session, bool, Session]


def ddmin(items: Sequence[T], build: Callable[[list[T]], Session]) -> Generator[Session, bool, list[T]]:
    """A 1-minimal subsequence of ``items`` for which ``build(subsequence)``
    still fails (it must fail for the whole), found by asking."""
    current = list(items)
    n = 2
    while len(current) >= 2:
        size = -(-len(current) // n)  # ceil
        chunks = [current[i:i + size] for i in range(0, len(current), size)]
        found = None
        for chunk in chunks:
            if len(chunks) > 2 and (yield build(chunk)):
                found, n = chunk, 2
                break
        if found is None:
            for i in range(len(chunks)):
                rest = [x for j, c in enumerate(chunks) if j != i for x in c]
                if (yield build(rest)):
                    found, n = rest, max(n - 1, 2)
                    break
        if found is not None:
            current = found
        elif n >= len(current):
            break
        else:
            n = min(n * 2, len(current))
    return current


def _with_bytes(frame: Frame, kept: list[int]) -> Frame:
    """``frame`` keeping the bytes at the positions ``kept``; each cut moves
    to where its next kept byte now is."""
    data = bytes(frame.data[i] for i in kept)
    cuts = sorted({sum(1 for i in kept if i < c) for c in frame.cuts} - {0, len(data)})
    return frame.replace(data=data, cuts=tuple(cuts))


def shrink(session: Session) -> Shrinking:
    """The smallest session found that still fails (send True when a yielded one does)."""
    frames = yield from ddmin(session, tuple)
    best: Session = tuple(frames)
    for at in range(len(best)):
        frame = best[at]
        if frame.secret or len(frame.data) < 2:
            continue
        before, after = best[:at], best[at + 1:]

        def build(kept: list[int], before: Session = before, after: Session = after, frame: Frame = frame) -> Session:
            return (*before, _with_bytes(frame, kept), *after)

        kept = yield from ddmin(range(len(frame.data)), build)
        best = build(kept)
    for at, frame in enumerate(best):
        if frame.cuts or frame.pipelined:
            plain = (*best[:at], frame.replace(cuts=(), pipelined=False), *best[at + 1:])
            if (yield plain):
                best = plain
    return best
