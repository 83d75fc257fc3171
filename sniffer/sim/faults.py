"""Fault injection for the simulator, decided sans-IO from a seeded generator.

The planner decides, per reply, whether it is dropped, how long it waits, what
stray bytes precede it and how it is cut into writes.  Keeping the decisions out
of the socket code makes them reproducible: one seed and one request sequence
give one plan, whatever the scheduler does.
"""

from __future__ import annotations

import random
from dataclasses import dataclass

# Stray bytes that can start no item the framer knows (no 'r', 'c', 's', 'F',
# CR/LF, 0xFF or 0x89), so injected garbage never merges with a real frame.
GARBAGE_ALPHABET = b"#%&*+/<=>?@^_~!$()[]{}|0123456789\x00\x01\x02\x03\x7f"
MAX_GARBAGE = 8
MIN_SPLIT_LIMIT = 16  # largest piece of a split reply, for replies up to 512 bytes


@dataclass(frozen=True, slots=True)
class FaultConfig:
    latency_ms: float = 0.0
    jitter_ms: float = 0.0
    drop_rate: float = 0.0  # probability that an answer is not sent
    split: bool = False  # write every reply in random small pieces
    garbage_rate: float = 0.0  # probability of stray bytes before a reply

    def __post_init__(self) -> None:
        for name in ("drop_rate", "garbage_rate"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name.replace('_', '-')} must be between 0 and 1")
        if self.latency_ms < 0 or self.jitter_ms < 0:
            raise ValueError("latency and jitter must not be negative")

    @property
    def active(self) -> bool:
        return bool(self.latency_ms or self.jitter_ms or self.drop_rate or self.split or self.garbage_rate)


@dataclass(frozen=True, slots=True)
class Plan:
    delay_s: float  # from when the request was read
    pieces: tuple[bytes, ...]  # written one after another; joined, garbage + the reply


class FaultPlanner:
    """Turns each reply into a Plan (or None: dropped).  One per connection."""

    def __init__(self, config: FaultConfig, seed: int | str) -> None:
        self.config = config
        self.rng = random.Random(f"whiztap-faults:{seed}")

    def plan(self, data: bytes, answer: bool) -> Plan | None:
        """Only answers are dropped: handshake text always goes out."""
        config, rng = self.config, self.rng
        if answer and config.drop_rate and rng.random() < config.drop_rate:
            return None
        delay_ms = config.latency_ms
        if config.jitter_ms:
            delay_ms += rng.uniform(-config.jitter_ms, config.jitter_ms)
        if config.garbage_rate and rng.random() < config.garbage_rate:
            data = bytes(rng.choice(GARBAGE_ALPHABET) for _ in range(rng.randint(1, MAX_GARBAGE))) + data
        pieces = self._split(data) if config.split else (data,)
        return Plan(max(0.0, delay_ms) / 1000, pieces)

    def _split(self, data: bytes) -> tuple[bytes, ...]:
        limit = max(MIN_SPLIT_LIMIT, len(data) // 32)  # an image in ~64 pieces, not thousands
        pieces = []
        pos = 0
        while pos < len(data):
            size = self.rng.randint(1, limit)
            pieces.append(data[pos:pos + size])
            pos += size
        return tuple(pieces)
