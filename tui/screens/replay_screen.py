"""The replay screen (``r``): replay the open recording against a server.

Choose a target, a password (recordings keep it redacted), pace, rate and how
answers are compared; start, pause, step one write at a time, stop.  Each
answer the server gives appears beside the recorded one, differences marked;
the selected row's side-by-side diff shows below.  With "save as" the replayed
session is written as a recording too.  The replay runs in a worker thread on
its own event loop (``ReplayRunner``); the list reads its results on a timer.

Faults: none (the default), those the recording was made under (as
``whiztap replay --faults-from-recording``: read by the runner, in its
thread), or SPECs typed in as ``whiztap record --fault`` takes them, several
separated by ``;`` outside quotes (the field is one line; a quoted ``;``, as
in ``replace:'a;b'``, belongs to its SPEC).  A typed SPEC that does not read
is said on the field itself before anything starts.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

from rich.style import Style
from rich.text import Text
from textual import on, work
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.screen import Screen
from textual.widgets import Button, Footer, Header, Input, Label, Select, Static
from whiztap.analyzer.protocol.text import escape, printable
from whiztap.tui.widgets.virtual_list import VirtualList

if TYPE_CHECKING:
    from whiztap.analyzer.mitm.spec import FaultSpec
    from whiztap.sniffer.replay.options import ReplayOptions
    from whiztap.tui.data.replay_runner import ReplayRunner

TICK_S = 0.1
DEFAULT_TARGET = "127.0.0.1:5000"  # where `whiztap sim` listens by default
FAULT_CHOICES = (("none", "none"), ("from the recording", "recording"), ("typed", "typed"))
MARKS = {"match": "✔", "mismatch": "✘", "missing": "?", "extra": "+", "ignored": "·", "unanswered": " "}
STATUS_STYLES = {"match": "green", "mismatch": "bold red", "missing": "yellow", "extra": "magenta",
                 "ignored": "dim", "unanswered": "dim"}


def _cut(text: str, width: int) -> str:
    return f"{text:<{width}}" if len(text) <= width else text[:width - 1] + "…"


class ComparisonList(VirtualList):
    """Recorded and replayed answers side by side, one row per judged answer."""

    def __init__(self, *, id: str | None = None) -> None:
        super().__init__(id=id)
        self.runner: ReplayRunner | None = None
        self.counts_new = False

    def row_count(self) -> int:
        return len(self.runner.comparisons) if self.runner is not None else 0

    def row_key(self, row: int) -> tuple[int, int]:
        return id(self.runner), row

    def row_cells(self, row: int) -> list[tuple[str, Style]]:
        assert self.runner is not None  # there are rows: a runner made them
        c = self.runner.comparisons[row]
        status = str(c.status)
        style = Style.parse(STATUS_STYLES.get(status, ""))
        recorded = escape(c.recorded) if c.recorded is not None else "(none recorded)"
        replayed = escape(c.replayed) if c.replayed is not None else "(no answer)"
        return [
            (f"{MARKS.get(status, ' ')} {status:<9}", style),
            (f"c{c.conn:<3} {c.recorded_s:9.3f} s  ", Style(dim=True)),
            (_cut(c.request_text, 30) + "  ", Style()),
            (_cut(recorded, 24), Style(bold=True)),
            (" │ ", Style(dim=True)),
            (replayed, style if not c.match else Style(bold=True)),
        ]


class ReplayScreen(Screen):
    BINDINGS = [
        Binding("f5", "start", "Start"),
        Binding("f6", "pause", "Pause/resume"),
        Binding("f7", "step", "Step"),
        Binding("f8", "stop", "Stop"),
        Binding("escape", "back", "Back"),
    ]
    DEFAULT_CSS = """
    ReplayScreen .form { height: 3; }
    ReplayScreen .form > Label { padding: 1 1 0 1; width: auto; }
    ReplayScreen .form > Input { width: 1fr; }
    ReplayScreen .form > Select { width: 18; }
    ReplayScreen #rate { width: 8; }
    ReplayScreen #faults { width: 26; }
    ReplayScreen .buttons { height: 3; }
    ReplayScreen .buttons > Button { margin-right: 1; }
    ReplayScreen #replay-status { height: 2; padding: 0 1; }
    ReplayScreen #comparisons { height: 1fr; }
    ReplayScreen #diff { height: 8; border: round $primary 50%; padding: 0 1; }
    """

    def __init__(self, path: str) -> None:
        super().__init__()
        self.path = path
        self.runner: ReplayRunner | None = None
        self._shown_finished: ReplayRunner | None = None  # the finished runner whose end is on screen
        self.comparisons = ComparisonList(id="comparisons")
        # the form's fields and the lines the timer updates, made here: never a query of a subtree
        self.target = Input(DEFAULT_TARGET, id="target")
        self.password = Input(os.environ.get("WHIZTAP_PASSWORD", ""), password=True, id="password",
                              placeholder="winsock password")
        self.output = Input("", id="output", placeholder="replay.mcap (optional)")
        self.pace = Select([(p, p) for p in ("recorded", "lockstep", "max")], value="recorded",
                           allow_blank=False, id="pace")
        self.rate = Input("1", id="rate")
        self.compare = Select([(m, m) for m in ("structure", "exact", "none")], value="structure",
                              allow_blank=False, id="compare")
        self.faults = Select(FAULT_CHOICES, value="none", allow_blank=False, id="faults")
        self.fault_specs = Input("", id="fault-specs", disabled=True,
                                 placeholder="as record --fault: drop dir:s2c every:2; delay:200ms")
        self.pause_button = Button("Pause (F6)", id="pause", disabled=True)
        self.stop_button = Button("Stop (F8)", id="stop", disabled=True)
        self.status_line = Static(Text(f"Replay {printable(path)}: choose a target and start."), id="replay-status")
        self.diff = Static("", id="diff")

    def compose(self) -> ComposeResult:
        yield Header(show_clock=False)
        with Horizontal(classes="form"):
            yield Label("Target")
            yield self.target
            yield Label("Password")
            yield self.password
            yield Label("Save as")
            yield self.output
        with Horizontal(classes="form"):
            yield Label("Pace")
            yield self.pace
            yield Label("Rate")
            yield self.rate
            yield Label("Compare")
            yield self.compare
        with Horizontal(classes="form"):
            yield Label("Faults")
            yield self.faults
            yield Label("SPECs (; between)")
            yield self.fault_specs
        with Horizontal(classes="buttons"):
            yield Button("Start (F5)", id="start", variant="primary")
            yield self.pause_button
            yield Button("Step (F7)", id="step")
            yield self.stop_button
        yield self.status_line
        with Vertical():
            yield self.comparisons
            yield self.diff
        yield Footer()

    def on_mount(self) -> None:
        self.sub_title = f"replay {self.path}"
        self.comparisons.border_title = "Answers: recorded │ replayed"
        self.set_interval(TICK_S, self._tick)

    # -- options -------------------------------------------------------------------------------

    def _options(self, output: str | None) -> ReplayOptions:
        """The form as ReplayOptions; raises ValueError with a line for the user."""
        from whiztap.analyzer.analysis.compare import CompareError, CompareRules
        from whiztap.sniffer.nettext import parse_address
        from whiztap.sniffer.replay.options import Pace, ReplayOptions

        target = parse_address(self.target.value.strip(), None, "target")  # AddressError is a ValueError
        try:
            rate = float(self.rate.value)
        except ValueError:
            raise ValueError("rate: a number such as 1 (as recorded) or 2 (twice as fast)") from None
        if rate <= 0:
            raise ValueError("rate must be above 0")
        try:
            rules = CompareRules.parse(str(self.compare.value))
        except CompareError as e:
            raise ValueError(str(e)) from None
        if output is not None:
            self._check_output(output)
        password = self.password.value
        faults = self._typed_faults() if self.faults.value == "typed" else ()
        return ReplayOptions(target=target, password=password.encode() if password else None,
                             pace=Pace(str(self.pace.value)), rate=rate, rules=rules,
                             output=output, faults=faults)

    def _typed_faults(self) -> tuple[FaultSpec, ...]:
        """The typed SPECs, parsed; FaultSpecError (a ValueError) for the first that does not read."""
        from whiztap.analyzer.mitm.spec import FaultSpecError, parse_fault

        specs = split_specs(self.fault_specs.value)
        if not specs:
            raise FaultSpecError("type a SPEC, such as drop dir:s2c kind:response every:2, or choose no faults")
        return tuple(parse_fault(spec) for spec in specs)

    def _check_output(self, output: str) -> None:
        """The output rule (whiztap.analyzer.recording.output_rule): never the recording being
        replayed, and never an existing file (there is no --force here)."""
        from whiztap.analyzer.recording.output_rule import OutputRefused, check_output
        from whiztap.tui.data.replay_runner import recording_parts

        try:
            check_output(output, recording_parts(self.path), recording=True)
        except OutputRefused as e:
            if e.existing is not None:
                raise ValueError(f"save as: {e.existing} exists; choose another name "
                                 "(the TUI never writes over a file)") from None
            raise ValueError(f"save as: {e}") from None

    # -- actions -------------------------------------------------------------------------------

    def _start(self, paused: bool) -> ReplayRunner | None:
        """A replay begun as the form says (None: the form says something wrong)."""
        from whiztap.analyzer.mitm.spec import FaultSpecError
        from whiztap.tui.data.replay_runner import ReplayRunner

        output = self.output.value.strip() or None
        try:
            options = self._options(output)
        except FaultSpecError as e:
            self._fault_error(str(e))
            return None
        except ValueError as e:
            self.notify(str(e), severity="error", timeout=6, markup=False)
            return None
        from_recording = self.faults.value == "recording"
        self.runner = runner = ReplayRunner(self.path, options, start_paused=paused,
                                            faults_from_recording=from_recording)
        self.comparisons.runner = runner
        self.comparisons.tail = True
        self.comparisons.reset()
        self._run(runner)
        return runner

    @work(thread=True, group="replay")
    def _run(self, runner: ReplayRunner) -> None:
        runner.run()

    def action_start(self) -> None:
        if self.runner is not None and not self.runner.done:
            self.notify("a replay is running: stop it first", timeout=3)
            return
        self._start(paused=False)

    def action_pause(self) -> None:
        if self.runner is None or self.runner.done:
            return
        self.runner.control("resume" if self.runner.state == "paused" else "pause")

    def action_step(self) -> None:
        runner = self.runner
        if runner is None or runner.done:
            runner = self._start(paused=True)
            if runner is None:
                return
        runner.control("step")

    def action_stop(self) -> None:
        if self.runner is not None and not self.runner.done:
            self.runner.control("stop")

    def action_back(self) -> None:
        self.action_stop()
        self.dismiss()

    def on_unmount(self) -> None:
        """Leaving (or quitting the app): a replay must not outlive its screen."""
        self.action_stop()

    @on(Button.Pressed)
    def _on_button(self, event: Button.Pressed) -> None:
        getattr(self, f"action_{event.button.id}")()

    @on(Select.Changed, "#faults")
    def _on_faults_chosen(self, event: Select.Changed) -> None:
        specs = self.fault_specs
        specs.disabled = event.value != "typed"
        self._fault_error("")
        if not specs.disabled:
            specs.focus()

    @on(Input.Changed, "#fault-specs")
    def _on_specs_typed(self) -> None:
        self._fault_error("")

    def _fault_error(self, error: str) -> None:
        """Say on the SPEC field what is wrong with it (or nothing)."""
        specs = self.fault_specs
        specs.set_class(bool(error), "-invalid")
        specs.border_subtitle = Text(error) if error else None  # quotes what was typed: never markup
        if error:
            specs.focus()
            self.status_line.update(Text(f"faults: {error}", style="red"))

    @on(VirtualList.Moved, "#comparisons")
    def _on_moved(self, message: VirtualList.Moved) -> None:
        self._show_diff(message.row)

    # -- display -------------------------------------------------------------------------------

    def _tick(self) -> None:
        self.comparisons.sync()
        runner = self.runner
        if runner is None or runner is self._shown_finished:
            return
        if runner.done:  # shown one last time: what is said since (a SPEC's error) stays
            self._shown_finished = runner
        state = runner.state
        running = not runner.done
        self.pause_button.disabled = not running
        self.stop_button.disabled = not running
        self.pause_button.label = "Resume (F6)" if state == "paused" else "Pause (F6)"
        self.status_line.update(self._status_text(runner))
        self.comparisons.border_subtitle = self._faults_text(runner)

    @staticmethod
    def _faults_text(runner: ReplayRunner) -> Text | None:
        """The faults the replay goes through, or why there are none."""
        faults = runner.options.faults
        if faults:
            return Text(f"through faults: {'; '.join(printable(f.text) for f in faults)}")
        return Text(runner.note) if runner.note else None

    @staticmethod
    def _status_text(runner: ReplayRunner) -> Text:
        text = Text()
        text.append(runner.state.upper(), style="bold red" if runner.state == "failed" else "bold")
        if runner.error:
            text.append(f"  {printable(runner.error)}", style="red")
        counts: dict[str, int] = {}
        for c in runner.comparisons:
            counts[str(c.status)] = counts.get(str(c.status), 0) + 1
        text.append(f"  {runner.connections} connection(s), {runner.sent} writes; ")
        text.append(", ".join(f"{n} {status}" for status, n in counts.items()) or "no answer judged yet")
        result = runner.result
        if result is not None:
            text.append(f"\n{result.summary()}", style="dim")
            if result.drift is not None:
                text.append(f"; {result.drift.text()}", style="dim")
            if runner.options.output and not result.error:
                text.append(f"; saved as {runner.options.output}", style="dim")
        return text

    def _show_diff(self, row: int | None) -> None:
        diff = self.diff
        if row is None or self.runner is None:
            diff.update("")
            return
        c = self.runner.comparisons[row]
        if c.diff:
            diff.update(Text("\n".join(map(printable, c.diff.split("\n"))), style="red" if not c.match else ""))
            return
        replayed = escape(c.replayed) if c.replayed is not None else "(no answer)"
        diff.update(Text(f"{c.status}: {c.request_text}\n  recorded {escape(c.recorded or b'')}\n"
                         f"  replayed {replayed}"))


def split_specs(text: str) -> list[str]:
    """SPECs separated by ``;`` outside quotes: a SPEC is words split as a
    shell splits them, so a quoted ``;`` (``replace:'a;b'``) is part of it.
    A quote left open is left for parse_fault to name."""
    specs: list[str] = []
    start, quote, escaped = 0, "", False
    for i, ch in enumerate(text):
        if escaped:
            escaped = False
        elif ch == "\\" and quote != "'":
            escaped = True
        elif quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == ";":
            specs.append(text[start:i])
            start = i + 1
    specs.append(text[start:])
    return [spec.strip() for spec in specs if spec.strip()]


def open_replay(app: App) -> None:
    """The replay screen for the open recording; live traffic has no finished file yet."""
    from whiztap.tui.data.sources import FileSource

    source = getattr(app, "source", None)
    if not isinstance(source, FileSource):
        app.notify("replay works on a finished recording: quit, then 'whiztap tui FILE.mcap' and r",
                   severity="warning", timeout=6)
        return
    app.push_screen(ReplayScreen(source.path))
