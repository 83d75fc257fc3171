"""The dialog a person types a frame in: the edit of a held frame, or an injection.

The text is read and judged at every keystroke (``data/typed.py``), and what it
means, its fields and the rules it breaks show beside it, so a mistake is seen
before it is sent.  Enter sends through the Controller.  A frame that breaks a
rule is not sent at the first Enter: the dialog says which rules, and a second
Enter on the same text sends it with force, so the spec is broken only on
purpose and never by a slip of the finger.  A refusal from the Controller
(the frame was let go meanwhile, the connection closed) shows in the dialog,
which stays open.
"""

from __future__ import annotations

from rich.text import Text
from textual import on
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.screen import ModalScreen
from textual.widgets import Input, Static
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.text import printable
from whiztap.sniffer.mitm.controller import ControlError
from whiztap.tui.data.controls import Controls
from whiztap.tui.data.typed import TypedFrame, read_typed
from whiztap.tui.widgets.detail import describe_typed

WAY = {Direction.C2S: "→ toward the server (c2s)", Direction.S2C: "← toward the client (s2c)"}


def _rules(typed: TypedFrame) -> str:
    """The ids of the rules a typed frame breaks, each once, in order."""
    return ", ".join(dict.fromkeys(v.rule_id for v in typed.violations))


class FrameDialog(ModalScreen[None]):
    """Subclasses say what the dialog is about (``heading``, ``keys``) and
    what Enter does with the frame (``send``)."""

    BINDINGS = [Binding("escape", "cancel", "Close")]
    DEFAULT_CSS = """
    FrameDialog { align: center middle; }
    FrameDialog > #dialog {
        width: 112; max-width: 100%; height: auto; max-height: 90%;
        border: thick $accent; background: $surface; padding: 0 1;
    }
    FrameDialog #typed-column { width: 1fr; height: auto; }
    FrameDialog #preview { width: 1fr; height: auto; padding: 0 0 0 2; }
    FrameDialog #dialog-heading { margin: 0 0 1 0; }
    FrameDialog #dialog-status { height: auto; margin: 1 0 0 0; }
    FrameDialog #dialog-keys { color: $text-muted; margin: 1 0 0 0; }
    """

    def __init__(self, controls: Controls, text: str, direction: Direction, title: str) -> None:
        super().__init__()
        self.controls = controls
        self.direction = direction
        self.title_text = title
        self._confirming: str | None = None  # the text whose broken rules were shown: Enter again forces it
        # the parts a keystroke updates, made here: never a query of a subtree not composed yet
        self.heading_line = Static("", id="dialog-heading")
        self.typed_input = Input(text, placeholder="rr1-12--0--0-ss1, sensor 12, servo 3 1500 …", id="typed")
        self.status_line = Static("", id="dialog-status")
        self.preview = Static("", id="preview")

    # -- for subclasses --------------------------------------------------------------------------

    def heading(self) -> str:
        raise NotImplementedError

    def keys(self) -> str:
        raise NotImplementedError

    def send(self, text: str, force: bool) -> str:
        """Send the frame; what to tell the user.  Raises ControlError."""
        raise NotImplementedError

    # -- the dialog ------------------------------------------------------------------------------

    def compose(self) -> ComposeResult:
        with Horizontal(id="dialog") as dialog:
            dialog.border_title = Text(self.title_text)
            with Vertical(id="typed-column"):
                yield self.heading_line
                yield self.typed_input
                yield self.status_line
                yield Static(Text(self.keys()), id="dialog-keys")
            yield self.preview

    def on_mount(self) -> None:
        self.typed_input.focus()
        self.judge()

    def judge(self) -> None:
        """Read and judge the text as it stands; show what it is beside it."""
        typed = read_typed(self.typed_input.value, self.direction, self.controls.checksum_rule)
        self.preview.update(describe_typed(typed))
        self.heading_line.update(Text(printable(self.heading())))
        if typed.error:
            self.say(typed.error, "red")
        elif typed.violations:
            self.say(f"breaks {_rules(typed)}: Enter asks before sending it", "yellow")
        else:
            self.say("")

    def say(self, text: str, style: str = "") -> None:
        self.status_line.update(Text(printable(text), style=style))

    @on(Input.Changed, "#typed")
    def _changed(self, event: Input.Changed) -> None:
        self._confirming = None
        self.judge()

    @on(Input.Submitted, "#typed")
    def _submitted(self, event: Input.Submitted) -> None:
        event.stop()
        text = event.value
        typed = read_typed(text, self.direction, self.controls.checksum_rule)
        if typed.error:  # no frame, or an unknown checksum rule (the Controller would raise ValueError)
            self.say(typed.error, "bold red")
            return
        force = bool(typed.violations)
        if force and self._confirming != text:
            self._confirming = text
            self.say(f"This frame breaks {_rules(typed)}. Enter again sends it anyway (force); "
                     f"change it, or Esc to leave it.", "bold yellow")
            return
        try:
            done = self.send(text, force)
        except ControlError as e:
            self.say(str(e), "bold red")
            return
        self.app.notify(done, timeout=4, markup=False)
        self.dismiss()

    def action_cancel(self) -> None:
        self.dismiss()
