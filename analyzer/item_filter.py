"""The one filter over observed items, shared by ``whiztap cat`` and the TUI."""

from __future__ import annotations

from dataclasses import dataclass

from analyzer.session import Observation

NS = 1_000_000_000


def channel_of(observation: Observation) -> int | None:
    """The channel an item is about, whatever it means (None if it has none)."""
    subject = observation.message or (observation.candidates[0] if observation.candidates else None)
    return getattr(subject, "channel", None)


@dataclass(frozen=True)
class ItemFilter:
    conns: frozenset[int] = frozenset()
    direction: str | None = None
    kinds: frozenset[str] = frozenset()
    channels: frozenset[int] = frozenset()
    since_s: float | None = None
    until_s: float | None = None
    violations_only: bool = False
    text: str = ""  # a substring of the item's escaped bytes or meaning (the TUI's free text)

    def accepts(self, conn: int, observation: Observation, start_ns: int, late: bool = False) -> bool:
        item = observation.item
        if self.conns and conn not in self.conns:
            return False
        if self.direction and observation.direction != self.direction:
            return False
        if self.kinds and item.kind not in self.kinds:
            return False
        if self.channels and channel_of(observation) not in self.channels:
            return False
        rel = (item.t_end_ns - start_ns) / NS
        if self.since_s is not None and rel < self.since_s:
            return False
        if self.until_s is not None and rel >= self.until_s:
            return False
        if self.violations_only and not (late or observation.violations):
            return False
        if self.text:
            from analyzer.describe import meaning
            from analyzer.text import escape

            needle = self.text.lower()
            return needle in escape(item.raw).lower() or needle in meaning(observation).lower()
        return True
