"""The frame list: every frame of a FrameView, one line each, rendered on demand.

A line: a mark coloured by the worst violation's severity, a glyph for what
the proxy in the middle did to the frame (marks.py), the time from the first
frame, the connection, the direction, the item kind, the exact bytes
(escaped, cut to fit) and the decoded meaning.

A line is built from the store only when it comes into view (and then kept in
the strip cache, keyed by frame id: a frame's line never changes, except when
a late violation marks it).  Besides moving, the list jumps to the next or
previous violation in view (n / N) and to a frame's paired request or response (p).
"""

from __future__ import annotations

from rich.style import Style
from textual.binding import Binding

from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.text import escape
from whiztap.tui.marks import GLYPHS, MARK_KINDS, worst
from whiztap.tui.store import FrameStore
from whiztap.tui.view import FrameView
from whiztap.tui.virtual_list import VirtualList

BYTES_WIDTH = 22
MARKS = {0: " ", 1: "·", 2: "▲", 3: "●"}
SEVERITY_CLASS = {1: "framelist--info", 2: "framelist--warning", 3: "framelist--error"}


class FrameList(VirtualList):
    """Rows of a FrameView; the cursor's frame is the one the detail pane shows."""

    BINDINGS = [
        Binding("n", "violation(1)", "Next violation"),
        Binding("N", "violation(-1)", "Prev violation"),
        Binding("p", "pair", "Paired frame"),
    ]
    COMPONENT_CLASSES = {
        "framelist--time", "framelist--conn", "framelist--c2s", "framelist--s2c", "framelist--kind",
        "framelist--bytes", "framelist--error", "framelist--warning", "framelist--info",
        *(f"framelist--{kind}" for kind in MARK_KINDS),
    }
    DEFAULT_CSS = """
    FrameList {
        & > .framelist--time { color: $text-muted; }
        & > .framelist--conn { color: $secondary; }
        & > .framelist--c2s { color: $success; }
        & > .framelist--s2c { color: $warning; }
        & > .framelist--kind { color: $text-muted; }
        & > .framelist--bytes { color: $text; text-style: bold; }
        & > .framelist--error { color: $error; text-style: bold; }
        & > .framelist--warning { color: $warning; text-style: bold; }
        & > .framelist--info { color: $primary; }
        & > .framelist--held { color: $accent; text-style: bold; }
        & > .framelist--injected { color: $success; text-style: bold; }
        & > .framelist--edited { color: $secondary; text-style: bold; }
        & > .framelist--dropped { color: $error; text-style: bold; }
        & > .framelist--delayed { color: $warning; }
        & > .framelist--faulted { color: $warning; text-style: bold; }
    }
    """

    def __init__(self, store: FrameStore, view: FrameView, *, live: bool, id: str | None = None) -> None:  # noqa: A002
        super().__init__(id=id)
        self.store = store
        self.view = view
        self.counts_new = live
        self._late_seen = 0
        self._marks_seen = 0

    def row_count(self) -> int:
        return len(self.view)

    def row_key(self, row: int) -> int:
        return self.view[row]

    @property
    def frame(self) -> int | None:
        """The frame under the cursor."""
        return self.current  # type: ignore[return-value]

    def set_view(self, view: FrameView) -> None:
        """Show another view, keeping the cursor on the same frame (or the next one)."""
        frame = self.frame
        self.view = view
        self.reset(view.row_of(frame) if frame is not None else 0)

    def sync(self) -> bool:
        """Take in new rows; True when a late violation changed how frames look."""
        marked, middle = len(self.store.late_marked), len(self.store.marked)
        changed = marked != self._late_seen or middle != self._marks_seen
        if changed:
            self._late_seen, self._marks_seen = marked, middle
            self.clear_strips()
        super().sync()
        return changed

    # -- jumps ------------------------------------------------------------------------------------

    def _jump(self, frame: int) -> bool:
        row = self.view.row_of(frame)
        if row < self.rows and self.view[row] == frame:
            self.move_to(row)
            return True
        return False

    def action_violation(self, step: int) -> None:
        """Move to the next (1) or previous (-1) frame in view that breaks a rule."""
        frame = self.frame
        start = (frame + 1 if step > 0 else frame) if frame is not None else 0
        for candidate in self.store.violations_from(start, step):
            if candidate != frame and self._jump(candidate):
                return
        self.app.bell()
        self.notify("no further violation" if step > 0 else "no earlier violation", timeout=2)

    def action_pair(self) -> None:
        """Jump to the request this response answers, or the response this request got."""
        frame = self.frame
        paired = self.store.pair[frame] if frame is not None else -1
        if paired < 0:
            self.notify("this frame has no paired request or response", timeout=2)
        elif not self._jump(paired):
            self.notify("the paired frame is hidden by the filter", timeout=2)

    # -- rendering --------------------------------------------------------------------------------

    def row_cells(self, row: int) -> list[tuple[str, Style]]:
        n = self.view[row]
        store = self.store
        style = self.get_component_rich_style
        severity = store.severity(n)
        c2s = store.direction(n) is Direction.C2S
        text = escape(store.raw(n)[:BYTES_WIDTH])
        if len(text) > BYTES_WIDTH or store.size(n) > BYTES_WIDTH:
            text = text[:BYTES_WIDTH - 1] + "…"
        mark = style(SEVERITY_CLASS[severity]) if severity else Style()
        marks = store.marks.get(n)
        if marks:  # what the proxy in the middle did to it: a glyph and a colour per kind
            kind = worst(marks)
            head = [(MARKS[severity], mark), (GLYPHS[kind], style(f"framelist--{kind}"))]
        else:
            head = [(MARKS[severity] + " ", mark)]
        return [
            *head,
            (f"{store.relative_s(n):11.6f} ", style("framelist--time")),
            (f"#{store.conn[n]:<3} ", style("framelist--conn")),
            ("→ " if c2s else "← ", style("framelist--c2s" if c2s else "framelist--s2c")),
            (f"{store.kind(n):<10} ", style("framelist--kind")),
            (f"{text:<{BYTES_WIDTH}} ", style("framelist--bytes")),
            (store.meaning(n), mark if severity >= 2 else Style()),
        ]
