"""``I``: inject a typed frame into a connection, toward the server or the client.

The connection is the selected frame's (a held one's too), else the one
chosen in the connections pane, else the only one open.  The frame goes
through ``Controller.inject``, as ``whiztap ctl inject`` does; Ctrl+T turns it
around, and the up and down arrows walk through what was injected before
(kept in ``Controls``, so the history outlives the dialog).
"""

from __future__ import annotations

from textual.binding import Binding
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.text import escape
from whiztap.tui.data.controls import Controls
from whiztap.tui.middle.frame_dialog import WAY, FrameDialog
from whiztap.tui.widgets.frame_list import FrameList


def target_connection(frames: FrameList, chosen: int | None, controls: Controls) -> int | None:
    """The connection ``I`` injects into: the selected frame's, the pane's choice, or the only one open."""
    held = frames.held_frame
    if held is not None:
        return held.conn
    frame = frames.frame
    if frame is not None:
        return frames.store.conn[frame]
    if chosen is not None:
        return chosen
    open_now = list(controls.controller.cores)
    return open_now[0] if len(open_now) == 1 else None


def closed_to_injection(controls: Controls, conn: int) -> str:
    """Why nothing can be injected into ``conn`` now ("" if something can):
    said before the dialog opens, not after a frame was typed into it."""
    entry = controls.controller.cores.get(conn)
    if entry is None:
        return f"conn #{conn} is closed: nothing can be injected into it (select a frame of an open one)"
    if entry[0].closing:
        return f"conn #{conn} is closing: nothing can be injected into it (select a frame of an open one)"
    return ""


class InjectScreen(FrameDialog):
    BINDINGS = [
        Binding("ctrl+t", "turn", "Toward the other side"),
        Binding("up", "history(-1)", "Earlier", show=False),
        Binding("down", "history(1)", "Later", show=False),
    ]

    def __init__(self, controls: Controls, conn: int, direction: Direction = Direction.C2S) -> None:
        super().__init__(controls, "", direction, f"Inject into conn #{conn}")
        self.conn = conn
        self._back = len(controls.injected)  # where the arrows are in the history (its length: a new frame)

    def heading(self) -> str:
        return f"A frame for conn #{self.conn}, {WAY[self.direction]}"

    def keys(self) -> str:
        return "Enter: send · Ctrl+T: toward the other side · ↑/↓: injected before · Esc: close"

    def send(self, text: str, force: bool) -> str:
        data = self.controls.controller.inject(self.conn, self.direction, text, force=force)
        self.controls.remember(text)
        return f"injected {escape(data)} into conn #{self.conn} {self.direction.value}" + (" (forced)" if force else "")

    def action_turn(self) -> None:
        self.direction = Direction.S2C if self.direction is Direction.C2S else Direction.C2S
        self._confirming = None
        self.judge()

    def action_history(self, step: int) -> None:
        """Recall an earlier injection (up) or a later one (down; past the last: an empty line)."""
        history = self.controls.injected
        at = max(0, min(len(history), self._back + step))
        if at == self._back:
            return
        self._back = at
        box = self.typed_input
        box.value = history[at] if at < len(history) else ""
        box.cursor_position = len(box.value)
