"""The connections pane: one table row per connection, and one for all of them.

A DataTable is right here (and wrong for frames): connections are few, and a
row is added once and then updated in place.  Choosing a row (Enter or a
click) narrows the frame list to that connection.  The pane grows with the
connections, up to a third of the screen (then it scrolls): the frame list
keeps the rest.
"""

from __future__ import annotations

from rich.text import Text
from textual.binding import Binding
from textual.message import Message
from textual.widgets import DataTable
from whiztap.analyzer.protocol.text import printable
from whiztap.tui.data.model import ConnectionRow

ALL = "all"
COLUMNS = (("conn", "#"), ("client", "client"), ("upstream", "upstream"), ("mode", "mode"),
           ("handshake", "handshake"), ("frames", "frames"), ("violations", "violations"), ("state", "state"))


class ConnectionsPane(DataTable):
    BINDINGS = [
        Binding("j", "cursor_down", "Down", show=False),
        Binding("k", "cursor_up", "Up", show=False),
        Binding("g", "scroll_top", "First", show=False),
        Binding("G", "scroll_bottom", "Last", show=False),
    ]
    DEFAULT_CSS = """
    ConnectionsPane { height: auto; max-height: 33%; min-height: 5; border: round $primary 50%; }
    ConnectionsPane:focus { border: round $primary; }
    """

    class Chosen(Message):
        """The user chose a connection (None: all of them)."""

        def __init__(self, conn: int | None) -> None:
            super().__init__()
            self.conn = conn

    def __init__(self, *, id: str | None = None) -> None:
        super().__init__(id=id, cursor_type="row", zebra_stripes=True)
        self.border_title = "Connections (Enter: show only this one)"
        self._shown: dict[str, tuple] = {}

    def on_mount(self) -> None:
        for key, label in COLUMNS:
            self.add_column(label, key=key)
        self.add_row(*(Text(c) for c in ("all", "", "", "", "", "", "", "")), key=ALL)

    def show(self, rows: list[ConnectionRow]) -> None:
        """Add new connections and update changed ones; untouched rows stay as they are."""
        total_frames = total_violations = 0
        for row in rows:
            total_frames += row.frames
            total_violations += row.violations
            cells = (str(row.conn), row.client, row.upstream, row.mode, row.handshake,
                     f"{row.frames:,}", self._violations(row.violations), row.state)
            self._put(str(row.conn), cells)
        self._put(ALL, ("all", f"{len(rows)} connection(s)", "", "", "", f"{total_frames:,}",
                        self._violations(total_violations), ""))

    @staticmethod
    def _violations(n: int) -> Text:
        return Text(f"{n:,}", style="bold red" if n else "")

    def _put(self, key: str, values: tuple) -> None:
        """Cells are Text, never markup (an IPv6 peer is written in brackets), and
        addresses come from the recording: control characters are shown escaped."""
        cells = tuple(v if isinstance(v, Text) else Text(printable(v)) for v in values)
        before = self._shown.get(key)
        if before == cells:
            return
        self._shown[key] = cells
        if key not in self.rows:
            self.add_row(*cells, key=key)
            return
        for (column, _), value, old in zip(COLUMNS, cells, before or (None,) * len(cells)):
            if value != old:
                self.update_cell(key, column, value, update_width=True)

    def on_data_table_row_selected(self, event: DataTable.RowSelected) -> None:
        event.stop()
        key = event.row_key.value
        self.post_message(self.Chosen(None if key is None or key == ALL else int(key)))
