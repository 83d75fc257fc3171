"""A line of filter words (the filter bar ``/``, the intercept bar ``i``) that
says on itself why the words were refused.

Words that do not parse change nothing: the filter in force stays, and the
bar keeps the words typed, marked invalid, with the parse error on its lower
border, until they are changed (or ``Esc`` puts back the words in force).
A notice would go away after a few seconds and leave the words looking
applied.
"""

from __future__ import annotations

from rich.text import Text
from textual import on
from textual.widgets import Input


class FilterBar(Input):
    DEFAULT_CSS = """
    FilterBar { display: none; border: round $accent; }
    FilterBar.shown { display: block; }
    FilterBar.-invalid { border: round $error; }
    """

    def refuse(self, error: str) -> None:
        """The words were not applied: say why, on the bar."""
        self.add_class("-invalid")
        self.border_subtitle = Text(error)  # quotes what was typed: never markup

    def accepted(self) -> None:
        self.remove_class("-invalid")
        self.border_subtitle = None

    @on(Input.Changed)
    def _typed(self) -> None:
        """New words: the old error no longer applies to them."""
        self.accepted()
