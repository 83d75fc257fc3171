"""The TUI's handle on the proxy in the middle: the same Controller as ``whiztap ctl``.

Live, the proxy runs on the app's own event loop, so the screen calls the
Controller (``whiztap.sniffer.mitm.controller``) directly: holding, releasing,
editing, dropping, injecting and the faults go through the one control layer
the JSON API and ``whiztap ctl`` use, and the TUI and the API never disagree.

What the screen shows of it lives here, outside any widget: the frames held
now (taken once a tick, as the list takes in new rows) and what was injected
(the inject dialog's history).
"""

from __future__ import annotations

from typing import Any, NamedTuple

HISTORY = 100  # injected frames remembered for the up arrow
NS = 1_000_000_000


class HeldKey(NamedTuple):
    """A held frame's row in the list: its id, and the whole seconds it has
    waited (its line, which shows them, is drawn again as they change)."""

    id: int
    waited_s: int


class Controls:
    """The Controller of a source that has one (the live proxy), or nothing."""

    def __init__(self, source: object) -> None:
        self.source = source
        self.held: list[Any] = []  # the controller's Held frames, oldest first, as of the last poll
        self.now_ns = 0  # the proxy's clock at the last poll: how long each has waited
        self.intercept = ""  # the intercept filter in force
        self.injected: list[str] = []  # frames typed into the inject dialog, oldest first

    @property
    def available(self) -> bool:
        """The source can put the proxy in the middle (the keys i, I, f and the faults tab exist)."""
        return hasattr(self.source, "controller")

    @property
    def controller(self) -> Any:  # a whiztap.sniffer.mitm.controller.Controller, or None
        return getattr(self.source, "controller", None)

    @property
    def checksum_rule(self) -> str:
        """The rule typed frames are judged by: the Controller's."""
        return self.controller.checksum_rule

    def find(self, held_id: int) -> Any:
        """The Held frame ``held_id`` as of the last poll (None: let go since)."""
        return next((h for h in self.held if h.id == held_id), None)

    def key(self, held: Any) -> HeldKey:
        return HeldKey(held.id, (self.now_ns - held.since_ns) // NS)

    def waits(self, held: Any) -> tuple[int, int]:
        """Whole seconds ``held`` has waited, as of the last poll, and those
        left before it goes on as it is (``--hold-timeout``): what its row
        and the detail pane show, drawn again each second."""
        waited = self.now_ns - held.since_ns
        left = self.controller.context.hold_timeout_ns - waited
        return waited // NS, max(0, -(-left // NS))

    def poll(self) -> None:
        """Take in what is held now.  The Held objects themselves, not
        ``held_frames()``: that builds every frame's text and meaning, and with
        thousands held the tick would pay for rows nobody sees; the list asks
        a Held for its ``as_dict`` only when its row is drawn."""
        controller = self.controller
        if controller is None:
            return
        self.held = list(controller.held.frames.values())
        self.now_ns = controller.clock()
        self.intercept = controller.intercept.text

    def remember(self, text: str) -> None:
        """An injected frame's text, for the history (the latest last, no repeats in a row)."""
        if not self.injected or self.injected[-1] != text:
            self.injected.append(text)
            del self.injected[:-HISTORY]
