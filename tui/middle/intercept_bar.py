"""``i``: the intercept filter, typed like the filter bar, in the filter bar's words.

From Enter on, every frame the words choose waits at the proxy for a person
(``Controller.set_intercept``, as ``whiztap ctl intercept`` sets it); an empty
line holds nothing more (frames held already stay held).  A filter that does
not parse is refused on the bar (``FilterBar``) and the one in force stays.
"""

from __future__ import annotations

from rich.text import Text
from textual import on
from textual.binding import Binding
from textual.widgets import Input
from whiztap.analyzer.analysis.item_filter import FILTER_HELP
from whiztap.sniffer.mitm.controller import ControlError
from whiztap.tui.data.controls import Controls
from whiztap.tui.widgets.filter_bar import FilterBar


class InterceptBar(FilterBar):
    BINDINGS = [Binding("escape", "close", "Leave", show=False)]
    DEFAULT_CSS = """
    InterceptBar { border: round $warning; }
    """

    def __init__(self, controls: Controls, *, id: str | None = None) -> None:
        super().__init__(placeholder=FILTER_HELP, id=id)
        self.controls = controls
        self.border_title = Text("Intercept: hold the frames these words choose (Enter sets; empty holds nothing)")

    def open(self) -> None:
        """Show the filter in force, ready to be changed."""
        controller = self.controls.controller
        if controller is None:
            self.notify("the proxy is not running yet", severity="warning", timeout=3)
            return
        self.value = controller.intercept.text
        self.add_class("shown")
        self.focus()

    @on(Input.Submitted)
    def _set(self, event: Input.Submitted) -> None:
        event.stop()
        text = event.value.strip()
        try:
            self.controls.controller.set_intercept(text)
        except ControlError as e:
            self.refuse(str(e))
            return
        if text:
            self.notify(f"intercepting {text}: a lets a held frame go, x drops it, e edits it", timeout=4,
                        markup=False)
        else:
            self.notify("intercept off: nothing more is held", timeout=3)
        self.controls.poll()
        self.action_close()

    def action_close(self) -> None:
        self.remove_class("shown")
        self.app.action_leave()  # type: ignore[attr-defined]  # WhiztapApp's: a pane may not import the app
