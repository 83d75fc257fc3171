"""What the frame list's keys do to a frame the proxy holds.

``a`` lets the frame under the cursor go as it is, ``x`` drops it, ``e`` asks
for the editor on it (``EditHeld``: the app opens it, as it opens every
dialog, so the frame list needs none of the middle's screens), ``A`` lets
every held frame go: through the Controller, as ``whiztap ctl release``,
``drop`` and ``release-all`` do, so the recording says the same whichever was
used.  The keys show in the footer only where they act (on a held frame;
``A`` while any is held).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from textual.message import Message
from whiztap.sniffer.mitm.controller import ControlError
from whiztap.tui.data.controls import Controls

# Checked as the widget it is mixed into; at run time a plain class, so that Textual's
# class machinery (bindings, component classes) sees only the frame list's own bases.
if TYPE_CHECKING:
    from textual.widget import Widget as _MixedInto
else:
    _MixedInto = object

_ON_HELD = frozenset({"accept", "drop", "edit"})


class EditHeld(Message):
    """``e`` on a held frame: open the editor on ``held`` (a Controller's ``Held``)."""

    def __init__(self, held: Any) -> None:
        super().__init__()
        self.held = held


class HeldActions(_MixedInto):
    """The held frames' keys, mixed into the frame list (which has
    ``controls``, ``held_frame`` and ``take_in``)."""

    controls: Controls | None
    held_frame: Any
    take_in: Callable[[], bool]

    def check_action(self, action: str, parameters: tuple[object, ...]) -> bool | None:
        if action in _ON_HELD:
            return self.held_frame is not None
        if action == "accept_all":
            return bool(self.controls is not None and self.controls.held)
        return super().check_action(action, parameters)

    def _let_go(self, how: Callable[[Any, int], object], done: str) -> None:
        held = self.held_frame
        if held is None or self.controls is None:
            return
        try:
            how(self.controls.controller, held.id)
        except ControlError as e:
            self.notify(str(e), severity="error", timeout=5, markup=False)
            return
        self.notify(f"held #{held.id} {done}", timeout=2, markup=False)
        self._taken_in(self.controls)

    def _taken_in(self, controls: Controls) -> None:
        """Show the change now, not at the next tick."""
        controls.poll()
        self.take_in()

    def action_accept(self) -> None:
        self._let_go(lambda controller, held_id: controller.release(held_id), "let go as it was")

    def action_drop(self) -> None:
        self._let_go(lambda controller, held_id: controller.drop(held_id), "dropped")

    def action_accept_all(self) -> None:
        if self.controls is None or self.controls.controller is None:
            return
        released = self.controls.controller.release_all()
        self.notify(f"{released} held frame(s) let go", timeout=2)
        self._taken_in(self.controls)

    def action_edit(self) -> None:
        held = self.held_frame
        if held is not None and self.controls is not None:
            self.post_message(EditHeld(held))
