"""``f``: the faults in force, how many frames each has hit, and new ones.

The pane shows the Controller's faults (``Fault.as_dict()``: the list ``whiztap
ctl fault list`` prints), refreshed once a second.  ``a`` opens a line for a
SPEC (docs/faults.md): the last word completes from the grammar's actions,
filter words and options (Right or Tab takes the suggestion), and the parse
error shows under the line as you type; Enter adds the fault at once
(``Controller.add_fault``).  ``d`` removes the selected fault, ``space``
switches it off and on, Esc leaves the line, then the pane.
"""

from __future__ import annotations

from rich.text import Text
from textual import on
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Vertical
from textual.suggester import Suggester
from textual.widgets import DataTable, Input, Static
from whiztap.analyzer.mitm.spec import ACTIONS, ACTIONS_WITH_ARGUMENT, OPTIONS, FaultSpecError, parse_fault
from whiztap.analyzer.protocol.items import ItemKind
from whiztap.analyzer.protocol.text import printable
from whiztap.sniffer.mitm.controller import ControlError
from whiztap.tui.data.controls import Controls

REFRESH_S = 1.0  # hits change with the traffic: the table looks again this often
FIRST_WORDS = tuple(f"{a}:" if a in ACTIONS_WITH_ARGUMENT else a for a in ACTIONS)
LATER_WORDS = ("dir:c2s", "dir:s2c", *(f"kind:{k.value}" for k in ItemKind), "ch:", "conn:", "violations",
               *(f"{o}:" for o in OPTIONS))
COLUMNS = ("id", "on", "hits", "spec", "name")  # the spec before the name: the pane is narrow


def complete_spec(value: str) -> str | None:
    """The SPEC with its last word completed: an action first, then filter words and options."""
    head, _, last = value.rpartition(" ")
    if not last:
        return None
    words = LATER_WORDS if head.strip() else FIRST_WORDS
    found = next((w for w in words if w.startswith(last) and w != last), None)
    return value + found[len(last):] if found else None


class SpecSuggester(Suggester):
    """Textual's Input asks this for a completion at each keystroke."""

    def __init__(self) -> None:
        super().__init__(case_sensitive=True)

    async def get_suggestion(self, value: str) -> str | None:
        return complete_spec(value)


class SpecInput(Input):
    """The SPEC line; Tab takes the suggestion, as Right does at the end."""

    BINDINGS = [Binding("tab", "complete", "Complete", show=False)]
    DEFAULT_CSS = """
    SpecInput { display: none; }
    SpecInput.shown { display: block; }
    """

    def action_complete(self) -> None:
        if self.cursor_at_end and self._suggestion:
            self.action_cursor_right()  # Input's own way of taking a suggestion
        else:
            self.screen.focus_next()


class FaultsPane(Vertical):
    BINDINGS = [
        Binding("a", "add", "Add fault"),
        Binding("d", "remove", "Remove fault"),
        Binding("space", "toggle_fault", "On/off"),
        Binding("escape", "leave", "Leave", show=False),
    ]
    DEFAULT_CSS = """
    FaultsPane { padding: 0 1; }
    FaultsPane > #fault-table { height: auto; max-height: 16; }
    FaultsPane > #fault-error { color: $error; height: auto; }
    FaultsPane > #fault-keys { color: $text-muted; margin: 1 0 0 0; }
    """

    def __init__(self, controls: Controls, *, id: str | None = None) -> None:
        super().__init__(id=id)
        self.controls = controls
        self.table: DataTable = DataTable(id="fault-table", cursor_type="row", zebra_stripes=True)
        self.spec = SpecInput(placeholder="ACTION [FILTER WORDS] [OPTIONS]: drop dir:s2c kind:response every:2",
                              suggester=SpecSuggester(), id="fault-spec")
        self.error = Static("", id="fault-error")
        self.ids: list[int] = []  # the table's rows: fault ids, in order
        self._shown: tuple = ()

    def compose(self) -> ComposeResult:
        yield self.table
        yield self.spec
        yield self.error
        yield Static("a add · d remove · space off/on · Esc back to the frames\n"
                     "hits: frames each fault acted on", id="fault-keys")

    def on_mount(self) -> None:
        for column in COLUMNS:
            self.table.add_column(column, key=column)
        self.show()
        self.set_interval(REFRESH_S, self.show)

    def show(self) -> None:
        """The faults in force, if they changed (hits included); the cursor stays on its row."""
        controller = self.controls.controller
        faults = tuple(tuple(f.as_dict().values()) for f in controller.faults) if controller is not None else ()
        if faults == self._shown:
            return
        self._shown = faults
        table, cursor = self.table, self.table.cursor_row
        table.clear()
        self.ids = []
        for fault in controller.faults if controller is not None else ():
            self.ids.append(fault.id)
            table.add_row(str(fault.id), "on" if fault.enabled else "off", f"{fault.hits:,}",
                          Text(printable(fault.spec.text)), Text(printable(fault.name)), key=str(fault.id))
        if self.ids:
            table.move_cursor(row=min(cursor, len(self.ids) - 1))

    def focus_table(self) -> None:
        self.table.focus()

    # -- keys ------------------------------------------------------------------------------------

    def _selected(self) -> int | None:
        row = self.table.cursor_row
        return self.ids[row] if 0 <= row < len(self.ids) else None

    def action_add(self) -> None:
        self.spec.value = ""
        self.spec.add_class("shown")
        self.spec.focus()

    def action_remove(self) -> None:
        fault_id = self._selected()
        if fault_id is None:
            return
        try:
            fault = self.controls.controller.remove_fault(fault_id)
        except ControlError as e:  # removed meanwhile (through the control API)
            self.notify(str(e), severity="error", timeout=4, markup=False)
        else:
            self.notify(f"fault {fault.name} removed", timeout=2, markup=False)
        self.show()

    def action_toggle_fault(self) -> None:  # not action_toggle: every DOM node has one, of an attribute
        fault_id = self._selected()
        if fault_id is None:
            return
        controller = self.controls.controller
        try:
            fault = controller.enable_fault(fault_id, not controller.fault(fault_id).enabled)
        except ControlError as e:
            self.notify(str(e), severity="error", timeout=4, markup=False)
        else:
            self.notify(f"fault {fault.name} {'on' if fault.enabled else 'off'}", timeout=2, markup=False)
        self.show()

    def action_leave(self) -> None:
        if self.spec.has_focus:
            self._close_spec()
        else:
            self.app.action_leave()  # type: ignore[attr-defined]  # WhiztapApp's: a pane may not import the app

    def _close_spec(self) -> None:
        self.spec.remove_class("shown")
        self.error.update("")
        self.table.focus()

    # -- the SPEC line -----------------------------------------------------------------------------

    @on(Input.Changed, "#fault-spec")
    def _check(self, event: Input.Changed) -> None:
        """The parse error in place, as the SPEC is typed (nothing while it parses, or is empty)."""
        error = ""
        if event.value.strip():
            try:
                parse_fault(event.value)
            except FaultSpecError as e:
                error = str(e)
        self.error.update(Text(printable(error)))

    @on(Input.Submitted, "#fault-spec")
    def _add(self, event: Input.Submitted) -> None:
        event.stop()
        try:
            fault = self.controls.controller.add_fault(event.value.strip())
        except (FaultSpecError, ControlError) as e:
            self.error.update(Text(printable(str(e))))
            return
        self.notify(f"fault {fault.name} added: {fault.spec.text}", timeout=3, markup=False)
        self.show()
        self._close_spec()
        self.table.move_cursor(row=len(self.ids) - 1)
