"""What the proxy in the middle did to a frame, as the TUI marks it.

Every intervention the proxy records (``Intervention`` events: a fault, a
script, a hand edit, an injection, a hold) becomes a ``Mark`` on the frame it
changed.  The marks fall into a few kinds a person tells apart at a glance in
the list (a glyph and a colour each) and can filter on (the filter bar's words
``held``, ``injected``, ``edited``, ``dropped``, ``delayed``, ``faulted``).
"""

from __future__ import annotations

from typing import NamedTuple

from whiztap.analyzer.analysis.item_filter import INTERVENTION_WORDS
from whiztap.analyzer.traffic import Intervention


class Mark(NamedTuple):
    action: str
    cause: str
    before: bytes
    after: bytes
    detail: str
    t_ns: int

    @classmethod
    def of(cls, event: Intervention) -> Mark:
        return cls(event.action, event.cause, event.before, event.after, event.detail, event.t_ns)

    @property
    def kind(self) -> str:
        return KIND_OF_ACTION.get(self.action, "faulted")


# action -> the kind of intervention it is (the filter word, the glyph, the colour)
KIND_OF_ACTION = {
    "hold": "held", "release": "held",
    "inject": "injected",
    "edit": "edited",
    "drop": "dropped", "blackhole": "dropped",
    "delay": "delayed",
}
MARK_KINDS = INTERVENTION_WORDS
GLYPHS = {"held": "⏸", "injected": "+", "edited": "✎", "dropped": "✗", "delayed": "⏱", "faulted": "⚡"}


def worst(marks: list[Mark]) -> str:
    """The kind a frame shows in the list when several things were done to it
    (dropped first: the frame never arrived, whatever else happened)."""
    kinds = {m.kind for m in marks}
    for kind in ("dropped", "injected", "edited", "faulted", "delayed", "held"):
        if kind in kinds:
            return kind
    return "faulted"
