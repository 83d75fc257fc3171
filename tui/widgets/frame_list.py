"""The frame list: every frame of a FrameView, one line each, rendered on demand.

A line: a mark coloured by the worst violation's severity, a glyph for what
the proxy in the middle did to the frame (data/marks.py), the time from the first
frame, the connection, the direction, the item kind, the exact bytes
(escaped, cut to fit) and the decoded meaning.

A line is built from the store only when it comes into view (and then kept in
the strip cache, keyed by frame id: a frame's line never changes, except when
a late violation marks it).  Besides moving, the list jumps to the next or
previous violation in view (n / N) and to a frame's paired request or response (p).

Live, with the proxy in the middle, the frames it holds for a person follow
the view's rows: they are not in the store until delivered, so they are
pseudo-rows drawn from the Controller's held frames (``Controls``, polled each
tick), each with how long it has waited; the border's title counts them.  On
one, ``a`` lets it go, ``x`` drops it, ``e`` edits it; ``A`` lets every one go.
"""

from __future__ import annotations

from typing import Any

from rich.style import Style
from rich.text import Text
from textual.binding import Binding
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.text import escape, printable
from whiztap.tui.data.controls import Controls, HeldKey
from whiztap.tui.data.marks import GLYPHS, MARK_KINDS, worst
from whiztap.tui.data.store import FrameStore
from whiztap.tui.data.view import FrameView
from whiztap.tui.widgets.held import HeldActions
from whiztap.tui.widgets.virtual_list import VirtualList

BYTES_WIDTH = 22
MARKS = {0: " ", 1: "·", 2: "▲", 3: "●"}
SEVERITY_CLASS = {1: "framelist--info", 2: "framelist--warning", 3: "framelist--error"}


def _bytes_text(raw: bytes, size: int) -> str:
    """A frame's bytes escaped, cut to the column's width."""
    text = escape(raw[:BYTES_WIDTH])
    if len(text) > BYTES_WIDTH or size > BYTES_WIDTH:
        text = text[:BYTES_WIDTH - 1] + "…"
    return text


class FrameList(HeldActions, VirtualList):
    """Rows of a FrameView, then the frames held at the proxy; the cursor's
    frame is the one the detail pane shows."""

    BINDINGS = [
        Binding("n", "violation(1)", "Next violation"),
        Binding("N", "violation(-1)", "Prev violation"),
        Binding("p", "pair", "Paired frame"),
        Binding("a", "accept", "Accept held"),
        Binding("x", "drop", "Drop held"),
        Binding("e", "edit", "Edit held"),
        Binding("A", "accept_all", "Accept all held"),
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

    def __init__(self, store: FrameStore, view: FrameView, *, live: bool, controls: Controls | None = None,
                 id: str | None = None) -> None:
        super().__init__(id=id)
        self.store = store
        self.view = view
        self.controls = controls
        self.counts_new = live
        self._late_seen = 0
        self._marks_seen = 0
        # as of the last row count: rows are read against these until the next
        # one, however the view and the held frames changed meanwhile
        self.store_rows = 0  # the view's rows
        self._held: list[Any] = []
        self._title: tuple[str, int] = ("", 0)
        self._held_bindings = (False, False)  # (on a held frame, any held): the footer's keys

    def counted_rows(self) -> int:
        """Held frames are not new frames: "N new" counts the view's rows."""
        return self.store_rows

    def row_count(self) -> int:
        self.store_rows = len(self.view)
        self._held = self.controls.held if self.controls is not None else []
        return self.store_rows + len(self._held)

    def row_key(self, row: int) -> int | HeldKey:
        if row < self.store_rows:
            return self.view[row]
        assert self.controls is not None  # rows after the store's are held frames: there are controls
        return self.controls.key(self._held[row - self.store_rows])

    @property
    def frame(self) -> int | None:
        """The stored frame under the cursor (None on a held frame)."""
        key = self.current
        return key if isinstance(key, int) else None

    @property
    def held_frame(self) -> Any:
        """The held frame (a Controller's ``Held``) under the cursor, or None."""
        at = self.cursor - self.store_rows
        return self._held[at] if 0 <= at < len(self._held) else None

    def set_view(self, view: FrameView) -> None:
        """Show another view, keeping the cursor on the same frame (or the next one)."""
        frame = self.frame
        self.view = view
        self.reset(view.row_of(frame) if frame is not None else 0)

    def take_in(self) -> bool:
        """``sync`` (new rows, held frames' waits); True when a late violation
        or a mark of the middle changed how frames already shown look."""
        marked, middle = len(self.store.late_marked), len(self.store.marked)
        changed = marked != self._late_seen or middle != self._marks_seen
        if changed:
            self._late_seen, self._marks_seen = marked, middle
            self.clear_strips()
        was_held, on = bool(self._held), self.current
        super().sync()
        if self._held or was_held:
            if isinstance(on, HeldKey) and not self.tail:
                self._stay_on(on.id)
            self.refresh()  # the held rows show how long they have waited
            self._announce()  # and so does the detail pane, on the held frame under the cursor
        self.show_held()
        return changed

    def position(self) -> str:
        """The border's count: the view's rows (held frames are counted in the title)."""
        at = self.cursor - self.store_rows
        if 0 <= at < len(self._held):
            return f"held {at + 1} of {len(self._held)} · {self.store_rows:,} frames"
        return f"{min(self.cursor + 1, self.store_rows):,} / {self.store_rows:,}"

    def _stay_on(self, held_id: int) -> None:
        """Keep the cursor on the held frame it was on, as rows come before it."""
        for at, held in enumerate(self._held):
            if held.id == held_id:
                if self.store_rows + at != self.cursor:
                    self._place(self.store_rows + at)
                return

    def show_held(self) -> None:
        """The border's title: the intercept filter in force and how many frames wait;
        the footer: the keys that let them go."""
        intercept = self.controls.intercept if self.controls is not None else ""
        title = (intercept, len(self._held))
        if title != self._title:
            self._title = title
            text = "Frames"
            if intercept:
                text += f" · intercepting {printable(intercept)}"
            if self._held:
                text += f" · {len(self._held)} held"
            self.border_title = Text(text)  # the filter's words: never markup
        state = (self.held_frame is not None, bool(self._held))
        if state != self._held_bindings:
            self._held_bindings = state
            self.refresh_bindings()

    def on_virtual_list_moved(self, message: VirtualList.Moved) -> None:
        """On or off a held frame: the footer shows or hides its keys (the message goes on to the app)."""
        self.show_held()

    # -- jumps ------------------------------------------------------------------------------------

    def _jump(self, frame: int) -> bool:
        row = self.view.row_of(frame)
        if row < min(self.rows, self.store_rows) and self.view[row] == frame:
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
        if row >= self.store_rows:
            return self._held_cells(self._held[row - self.store_rows])
        n = self.view[row]
        store = self.store
        style = self.get_component_rich_style
        severity = store.severity(n)
        c2s = store.direction(n) is Direction.C2S
        text = _bytes_text(store.raw(n), store.size(n))
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

    def _held_cells(self, held: Any) -> list[tuple[str, Style]]:
        """A frame waiting at the proxy: where the time goes, that it is held;
        where the meaning goes, its number and the seconds left before it goes
        on as it is (``--hold-timeout``; the detail pane says it in full)."""
        style = self.get_component_rich_style
        controls = self.controls
        assert controls is not None  # a held frame is shown: there are controls
        state = held.as_dict(controls.now_ns)
        _, left = controls.waits(held)
        c2s = held.direction is Direction.C2S
        waiting = style("framelist--held")
        return [
            ("  ", Style()),
            (f"{GLYPHS['held']} held".rjust(11) + " ", waiting),
            (f"#{held.conn:<3} ", style("framelist--conn")),
            ("→ " if c2s else "← ", style("framelist--c2s" if c2s else "framelist--s2c")),
            (f"{state['kind']:<10} ", style("framelist--kind")),
            (f"{_bytes_text(held.shown, len(held.shown)):<{BYTES_WIDTH}} ", style("framelist--bytes")),
            (f"#{held.id}, {left} s left: ", waiting),
            (state["meaning"], Style()),
        ]
