"""What the proxy in the middle did to a frame, as the TUI marks it.

A frame's marks are the ``Intervention`` events themselves (a fault, a
script, a hand edit, an injection, a hold: the facts the proxy told, with the
frame's offsets and held id), kept with the row they are about
(``middle_view.py`` finds it).  They fall into a few kinds a person tells apart at
a glance in the list (a glyph and a colour each) and can filter on (the
filter bar's words ``held``, ``injected``, ``edited``, ``dropped``,
``delayed``, ``faulted``); the kind is read off the ``Action``.
"""

from __future__ import annotations

from collections.abc import Iterable

from whiztap.analyzer.analysis.item_filter import INTERVENTION_WORDS
from whiztap.analyzer.traffic import Action, Intervention

# action -> the kind of intervention it is (the filter word, the glyph, the colour); any other: "faulted"
KIND_OF_ACTION: dict[Action, str] = {
    Action.HOLD: "held", Action.RELEASE: "held",
    Action.INJECT: "injected",
    Action.EDIT: "edited",
    Action.DROP: "dropped", Action.BLACKHOLE: "dropped", Action.EXPIRE: "dropped",
    Action.DELAY: "delayed",
}
TIMING = frozenset({Action.DELAY, Action.HOLD, Action.RELEASE, Action.EDIT, Action.SLICE, Action.BANDWIDTH})
"""Actions that change when a side gets a frame (so its two latencies differ)."""
MARK_KINDS = INTERVENTION_WORDS
GLYPHS = {"held": "⏸", "injected": "+", "edited": "✎", "dropped": "✗", "delayed": "⏱", "faulted": "⚡"}


def mark_kind(mark: Intervention) -> str:
    """The kind of one mark (its filter word)."""
    return KIND_OF_ACTION.get(mark.action, "faulted")


def worst(marks: Iterable[Intervention]) -> str:
    """The kind a frame shows in the list when several things were done to it
    (dropped first: the frame never arrived, whatever else happened)."""
    kinds = {mark_kind(m) for m in marks}
    for kind in ("dropped", "injected", "edited", "faulted", "delayed", "held"):
        if kind in kinds:
            return kind
    return "faulted"
