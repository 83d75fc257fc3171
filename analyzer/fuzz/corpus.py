"""The sessions the fuzzer mutates: seeds, and those that showed something new.

A server is a black box, so "new" is new behaviour: how the handshake ended,
the kinds of the server's items, the client rules the frames broke
(``Judge.behaviour``).  A session that shows a behaviour not seen before joins
the corpus.  Memory is bounded: at most ``CAPACITY`` sessions (each at most
``grammar.MAX_FRAMES`` frames) and ``BEHAVIOURS_KEPT`` behaviour keys; past the
cap a newcomer takes the place of an entry that was not a seed, drawn by the
seeded random, so the corpus stays a function of the seed and the server.
"""

from __future__ import annotations

import random

from whiztap.analyzer.fuzz.grammar import Session

CAPACITY = 256
BEHAVIOURS_KEPT = 65536


class Corpus:
    def __init__(self, seeds: list[Session], capacity: int = CAPACITY) -> None:
        if not seeds:
            raise ValueError("a corpus needs at least one seed session")
        self.capacity = max(capacity, 1)
        self.entries: list[Session] = list(seeds[:self.capacity])
        self.seeds = len(self.entries)
        self._seen: set[tuple[str, ...]] = set()

    def __len__(self) -> int:
        return len(self.entries)

    def pick(self, rng: random.Random) -> tuple[Session, Session]:
        """A session to mutate and a donor to splice from."""
        return rng.choice(self.entries), rng.choice(self.entries)

    def consider(self, rng: random.Random, session: Session, behaviour: tuple[str, ...]) -> bool:
        """Keep ``session`` if ``behaviour`` is new; whether it was kept."""
        if behaviour in self._seen or len(self._seen) >= BEHAVIOURS_KEPT:
            return False
        self._seen.add(behaviour)
        if len(self.entries) < self.capacity:
            self.entries.append(session)
        elif len(self.entries) > self.seeds:
            self.entries[rng.randrange(self.seeds, len(self.entries))] = session
        else:
            return False
        return True
