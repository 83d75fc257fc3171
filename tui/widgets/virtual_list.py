"""A list of any length that renders only the lines on screen (the Line API).

Modelled on Textualize's toolong: a ScrollView whose ``render_line(y)`` builds
the rows in view from data held elsewhere, keeps the strips it built in an LRU
cache, and never has a widget per row.  The row count is re-read by
``sync()`` (called on the app's tick), so rows may arrive at any rate.

Tail mode: the cursor sits on the newest row and the list follows it.  Moving
up, paging, clicking or scrolling the wheel stops following; the border then
counts the rows that arrived since; End (or G) follows again.

Subclasses say how many rows there are (``row_count``), what identifies a
row's content (``row_key``) and how it looks (``row_cells``).
"""

from __future__ import annotations

from collections.abc import Hashable

from rich.segment import Segment
from rich.style import Style
from textual import events
from textual.binding import Binding
from textual.cache import LRUCache
from textual.geometry import Size
from textual.message import Message
from textual.reactive import reactive
from textual.scroll_view import ScrollView
from textual.strip import Strip

STRIP_CACHE = 512  # lines kept drawn: a few screens, to scroll back and forth without rebuilding


class VirtualList(ScrollView, can_focus=True):
    BINDINGS = [
        Binding("down,j", "move(1)", "Down", show=False),
        Binding("up,k", "move(-1)", "Up", show=False),
        Binding("pagedown", "page(1)", "Page down", show=False),
        Binding("pageup", "page(-1)", "Page up", show=False),
        Binding("home,g", "first", "First", show=False),
        Binding("end,G", "last", "Last/follow"),
    ]
    COMPONENT_CLASSES = {"virtuallist--cursor"}
    DEFAULT_CSS = """
    VirtualList {
        border: round $primary 50%;
        border-subtitle-color: $text-muted;
        &:focus { border: round $primary; }
        & > .virtuallist--cursor { background: $accent 35%; }
    }
    """

    tail: reactive[bool] = reactive(False)
    counts_new = True  # say in the border how many rows came while not following

    class Moved(Message):
        """The cursor is on another row (None: the list is empty)."""

        def __init__(self, virtual_list: VirtualList, row: int | None, key: Hashable | None) -> None:
            super().__init__()
            self.virtual_list = virtual_list
            self.row = row
            self.key = key

        @property
        def control(self) -> VirtualList:
            return self.virtual_list

    def __init__(self, *, id: str | None = None) -> None:
        super().__init__(id=id)
        self.rows = 0  # rows known to the widget (the data may already hold more)
        self.cursor = 0
        self.new_rows = 0  # rows that arrived while not following
        self._counted = 0  # counted_rows() at the last look
        self._strips: LRUCache[tuple[Hashable, bool, int], Strip] = LRUCache(STRIP_CACHE)
        self._announced: Hashable | None = None

    # -- for subclasses -----------------------------------------------------------------------

    def row_count(self) -> int:
        raise NotImplementedError

    def row_key(self, row: int) -> Hashable:
        """What the row shows: rows with equal keys look the same."""
        return row

    def row_cells(self, row: int) -> list[tuple[str, Style]]:
        raise NotImplementedError

    # -- data ------------------------------------------------------------------------------------

    @property
    def current(self) -> Hashable | None:
        """The key of the row under the cursor."""
        return self.row_key(self.cursor) if self.cursor < self.rows else None

    def reset(self, cursor: int = 0) -> None:
        """The data changed entirely (a new filter): forget the rows drawn."""
        self.rows = self.row_count()
        self.new_rows = 0
        self._strips.clear()
        self._resize()
        if self.tail:
            self._follow()
        else:
            self._place(cursor)
        self.refresh()
        self._update_subtitle()

    def clear_strips(self) -> None:
        """Rows may look different now (a late violation marked one)."""
        self._strips.clear()
        self.refresh()

    def sync(self) -> None:
        """Take in rows that arrived since the last look (or went: a subclass's
        rows after the data's own, such as frames held at the proxy)."""
        rows = self.row_count()
        if rows == self.rows and self.counted_rows() == self._counted:
            return
        before, self.rows = self.rows, rows
        counted, self._counted = self._counted, self.counted_rows()
        self._resize()
        if self.tail:
            self._follow()
        else:
            self.new_rows = max(0, self.new_rows + self._counted - counted)
            if before == 0 or self.cursor >= rows:
                self._place(min(self.cursor, rows - 1) if before else 0)
            if min(before, rows) < self.scroll_offset.y + self.size.height:
                self.refresh()
        self._update_subtitle()

    def counted_rows(self) -> int:
        """The rows that count as new when they arrive (a subclass may add
        rows of another kind after them, such as frames held at the proxy)."""
        return self.rows

    def _resize(self) -> None:
        """Set the scrollable height to the row count.

        Assigning ``virtual_size`` asks for a layout of the whole screen, which
        repaints every widget; at ten ticks a second while a million frames
        load that costs more than the loading.  Only this list and its
        scrollbar change, unless the scrollbar appears or goes, so that is all
        that is redrawn.
        """
        size = Size(0, self.rows)
        needs_bar = self.rows > self.scrollable_content_region.height
        if not self.size or needs_bar != self.show_vertical_scrollbar:
            self.virtual_size = size
            return
        self.set_reactive(VirtualList.virtual_size, size)
        if self.show_vertical_scrollbar:
            self.vertical_scrollbar.window_virtual_size = self.rows

    def _follow(self) -> None:
        self._place(max(self.rows - 1, 0))
        self.scroll_to(y=self.max_scroll_y, animate=False)
        self.refresh()

    def _place(self, row: int) -> None:
        """Put the cursor on ``row`` and scroll so that it is in sight."""
        row = max(0, min(row, self.rows - 1))
        if row != self.cursor:
            self.refresh_line(self.cursor)
            self.cursor = row
            self.refresh_line(row)
        height = self.scrollable_content_region.height or self.size.height
        top = self.scroll_offset.y
        if row < top:
            self.scroll_to(y=row, animate=False)
        elif height and row >= top + height:
            self.scroll_to(y=row - height + 1, animate=False)
        self._announce()

    def _announce(self) -> None:
        """Tell the app what the cursor is on when that changed: another row,
        or its row showing something else (the seconds a held frame waited)."""
        key = self.current
        if key != self._announced:
            self._announced = key
            self.post_message(self.Moved(self, self.cursor if self.rows else None, key))

    def watch_tail(self, tail: bool) -> None:
        self.new_rows = 0
        if tail:
            self._follow()
        self._update_subtitle()

    def _update_subtitle(self) -> None:
        if self.tail:
            self.border_subtitle = f"following · {self.counted_rows():,}"
        elif self.new_rows and self.counts_new:
            self.border_subtitle = f"{self.new_rows:,} new (End follows)"
        else:
            self.border_subtitle = self.position()

    def position(self) -> str:
        """Where the cursor is, for the border (a subclass counts its own rows)."""
        return f"{min(self.cursor + 1, self.rows):,} / {self.rows:,}"

    # -- actions ---------------------------------------------------------------------------------

    def move_to(self, row: int) -> None:
        """Put the cursor on a row as the user's choice: stop following."""
        self.tail = False
        self._place(row)
        self._update_subtitle()

    def action_move(self, step: int) -> None:
        if step > 0 and self.tail:
            return
        self.move_to(self.cursor + step)

    def action_page(self, step: int) -> None:
        height = max(self.scrollable_content_region.height, 1)
        self.move_to(self.cursor + step * height)

    def action_first(self) -> None:
        self.move_to(0)

    def action_last(self) -> None:
        if self.tail:
            self._follow()
        else:
            self.tail = True

    def on_click(self, event: events.Click) -> None:
        row = self.scroll_offset.y + event.y - self.gutter.top
        if 0 <= row < self.rows:
            self.move_to(row)

    def on_mouse_scroll_up(self, event: events.MouseScrollUp) -> None:
        self.tail = False

    # -- rendering --------------------------------------------------------------------------------

    def notify_style_update(self) -> None:
        super().notify_style_update()
        self._strips.clear()

    def render_line(self, y: int) -> Strip:
        row = self.scroll_offset.y + y
        width = self.scrollable_content_region.width
        base = self.rich_style
        if row >= self.rows:
            return Strip.blank(width, base)
        at_cursor = row == self.cursor
        key = (self.row_key(row), at_cursor, width)
        strip = self._strips.get(key)
        if strip is None:
            # Built at the width it is shown at: a strip cropped at each paint
            # would keep every crop in its own caches (tens of thousands of
            # small objects for the collector to walk while traffic streams).
            cursor = base + self.get_component_rich_style("virtuallist--cursor") if at_cursor else None
            strip = Strip([Segment(text, (base + style + cursor) if cursor else base + style)
                           for text, style in self.row_cells(row)])
            strip = strip.adjust_cell_length(width, cursor or base)
            self._strips.set(key, strip)
        return strip
