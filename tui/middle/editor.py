"""``e`` on a held frame: edit it, then let it go as typed.

The frame opens as escaped text (console words work too); Enter releases it
through ``Controller.release(id, edit=...)``, exactly as ``whiztap ctl release
ID --edit`` does, so the recording has an ``edit`` intervention with the frame
before and after.  Esc leaves it held as it was.
"""

from __future__ import annotations

from typing import Any

from whiztap.analyzer.protocol.text import escape
from whiztap.tui.data.controls import Controls
from whiztap.tui.middle.frame_dialog import WAY, FrameDialog


class EditorScreen(FrameDialog):
    def __init__(self, controls: Controls, held: Any) -> None:
        """``held``: the Controller's Held frame (sniffer/mitm/intercept.py)."""
        super().__init__(controls, escape(held.shown), held.direction, f"Edit held #{held.id}")
        self.held = held

    def heading(self) -> str:
        return (f"Held #{self.held.id} on conn #{self.held.conn}, {WAY[self.direction]}, "
                f"held by {self.held.cause}")

    def keys(self) -> str:
        return "Enter: let it go as typed · Esc: leave it held as it was"

    def send(self, text: str, force: bool) -> str:
        self.controls.controller.release(self.held.id, edit=text, force=force)
        return f"held #{self.held.id} let go as edited" + (" (forced)" if force else "")
